"""Image metrics the tools share: luminance, the relative squared error, near-black pixels.

The project's relMSE is ``mean((x − ref)² / (ref² + REL_MSE_EPS))`` over pixels and
channels (:func:`rel_mse`), the same in ``mfnormal compare``, the benchmarks and the
true-geometry harness (:func:`validation.heightfield.metrics`, which adds its own).
"""

from __future__ import annotations

import numpy as np

__all__ = ["REL_MSE_EPS", "luminance", "rel_se", "rel_mse", "near_black_fraction"]

#: relMSE = mean((x − ref)² / (ref² + REL_MSE_EPS))
REL_MSE_EPS = 1e-2


def luminance(rgb: np.ndarray) -> np.ndarray:
    """Rec. 709 luminance of linear RGB (..., 3)."""
    return rgb[..., 0] * 0.2126 + rgb[..., 1] * 0.7152 + rgb[..., 2] * 0.0722


def rel_se(x: np.ndarray, ref: np.ndarray) -> np.ndarray:
    """The relative squared error ``(x − ref)² / (ref² + REL_MSE_EPS)`` per pixel and channel."""
    return (x - ref) ** 2 / (ref ** 2 + REL_MSE_EPS)


def rel_mse(x: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    """mean((x − ref)² / (ref² + 1e-2)) over pixels (in ``mask``) and channels; NaN for
    no pixels."""
    err = rel_se(x, ref)
    if mask is not None:
        err = err[mask]
    return float(err.mean()) if err.size else float("nan")


def near_black_fraction(rgb: np.ndarray, mask: np.ndarray, threshold) -> float:
    """Fraction of ``mask`` pixels whose luminance is below ``threshold`` (a number,
    or an image of per-pixel thresholds)."""
    if not mask.any():
        return float("nan")
    below = luminance(rgb) < threshold
    return float(below[mask].mean())
