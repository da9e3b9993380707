"""The split harness's arithmetic (validation/real_assets_split.py): from two independent halves of
an image and of the truth, relMSE splits into the bias² a converged render keeps and the noise of
the render at its spp. Checked on synthetic images whose bias and noise are known (no renders):
a uniform truth of 0.5 (its mean luminance is the metered exposure's target, so the exposure is
1), truth halves with noise of standard deviation 0.02·√2 each, method halves 0.5·(1 + β) with
noise 0.1·√2 each; 64² pixels × 3 channels. Tolerances: 4 standard errors of each estimate
(bias² from its reported SE; noise from the χ² spread of a mean of 12,288 squares, ≈ 1.3 %)."""

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import numpy as np
import pytest

from validation.real_assets_split import EPS, RELIEF_BLUR, relief_part, split_metrics

N = 64
W = 1.0 / (0.25 + EPS)          # the weight 1/(T² + ε) at T = 0.5


def halves(rng, mean, sd):
    """Two independent halves whose mean image has noise of standard deviation ``sd``."""
    return tuple(mean + rng.normal(0.0, sd * np.sqrt(2.0), (N, N, 3)) for _ in range(2))


@pytest.mark.parametrize("beta", [0.0, 0.05, 0.2])
def test_bias_and_noise_come_apart(beta):
    rng = np.random.default_rng(12)
    truth = halves(rng, 0.5, 0.02)
    method = halves(rng, 0.5 * (1.0 + beta), 0.1)
    mask = np.ones((N, N), bool)
    m = split_metrics(method, truth, mask)
    bias2, noise = W * (0.5 * beta) ** 2, W * 0.1 ** 2
    assert abs(m["bias2"] - bias2) < 4 * m["bias2_se"] + 1e-12, (m, bias2)
    assert abs(m["noise"] / noise - 1.0) < 4 * np.sqrt(2.0 / (N * N * 3)), (m, noise)
    assert abs(m["truth_noise"] / (W * 0.02 ** 2) - 1.0) < 4 * np.sqrt(2.0 / (N * N * 3))
    assert m["rel_mse"] == pytest.approx(m["bias2"] + m["noise"] + m["truth_noise"], rel=1e-9)
    # the noise is the larger part here: relMSE alone would read it as distance to the truth
    assert m["rel_mse"] > bias2 + 0.5 * noise


def test_the_floor_of_the_truth_again_is_its_standard_error():
    """The truth rendered again (no bias) gives a bias² within a few standard errors of 0."""
    rng = np.random.default_rng(3)
    truth = halves(rng, 0.5, 0.02)
    again = halves(rng, 0.5, 0.1)
    m = split_metrics(again, truth, np.ones((N, N), bool))
    assert abs(m["bias2"]) < 4 * m["bias2_se"] and m["bias2_se"] < 0.02 * m["noise"]


def _shaded_disk(rng, relief_scale, slope, sd, n=128):
    """Two halves of a disk (the rest black) shaded by a smooth ramp of ``slope`` across it, with a
    relief of fine bumps (amplitude 0.1, period 6 px) times ``relief_scale`` on top, and noise of
    standard deviation ``sd`` in the mean image; (halves, mask)."""
    y, x = np.mgrid[0:n, 0:n] + 0.5
    mask = (x - n / 2) ** 2 + (y - n / 2) ** 2 < (0.45 * n) ** 2
    shading = 0.5 + slope * (x / n - 0.5)
    relief = 0.1 * np.sin(2 * np.pi * x / 6.0) * np.sin(2 * np.pi * y / 6.0)
    image = np.where(mask, shading + relief_scale * relief, 0.0)[..., None].repeat(3, -1)
    return tuple(image + np.where(mask[..., None], rng.normal(0.0, sd * np.sqrt(2.0), image.shape), 0.0)
                 for _ in range(2)), mask


@pytest.mark.parametrize("scale", [0.7, 1.0])
def test_relief_contrast_is_the_reliefs_scale_whatever_the_noise_and_the_shading(scale):
    """A method whose bumps are ``scale`` times the truth's, under a shading ramp three times as
    steep and with noise of 0.64 times the truth's relief variance in its mean image, has relief
    contrast ``scale``: the object's shading is not relief (the blur takes it out, the silhouette
    included), and noise is not relief (the halves' covariance). The plain standard deviation of
    the images would read 2.1 for ``scale`` 0.7, and their detail's without the halves 1.1.
    Tolerance 0.04: four standard errors of the contrast (1 % from the covariance of the disk's
    ~10⁴ noisy pixels)."""
    rng = np.random.default_rng(5)
    truth, mask = _shaded_disk(rng, 1.0, 0.2, 0.005)
    method, _ = _shaded_disk(rng, scale, 0.6, 0.04)
    m = split_metrics(method, truth, mask)
    assert abs(m["relief"] - scale) < 0.04, m
    # the premises: without the blur or without the halves the contrast would be far off
    plain = float(np.std(0.5 * (method[0] + method[1])[mask, 0]) / np.std(0.5 * (truth[0] + truth[1])[mask, 0]))
    detail = relief_part(0.5 * (method[0] + method[1])[..., 0], mask, RELIEF_BLUR * mask.shape[1])
    alone = float(np.std(detail) / np.sqrt(m["truth_relief_var"]))
    assert abs(plain - scale) > 0.3 and abs(alone - scale) > 0.2, (plain, alone)
