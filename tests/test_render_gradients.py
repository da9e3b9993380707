"""Render-level derivatives: Mitsuba's ``prb`` and ``prb_projective`` against finite differences.

In the style of Mitsuba's own ``test_ad_integrators.py``: a parameter θ moves the scene
(here ``strength``, or one channel of one texel of the normal map, θ added to it), the AD
integrator's forward-mode image ∂I/∂θ is compared pixel by pixel with the central finite
difference of two ``path`` renders at θ ± h (same seed and sample count: common random
numbers), and its reverse-mode gradient of the mean image with the FD image's mean.

The scene: a plane under a 4×4 normal map (nearest filtering), seen from above by a
perspective camera, lit by one directional sun at 40° elevation (direct light only,
max_depth 2: the image is the BSDF's eval, so the FD is exact up to float rounding for the
deterministic models and shares the walks' hashed random numbers). h = 1e-3 for the
deterministic models (float32 rounding ~1e-4 relative; truncation O(h²)), 0.02 for the walk
(its decisions flip between θ ± h; the FD's noise ∝ 1/h, see tests/test_gradients.py).

Tolerances: stated per case at ``CASES``.
"""

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import os

import drjit as dr
import mitsuba as mi
from variant import VARIANT  # noqa: E402  (MFNORMAL_VARIANT, tests/variant.py)
import numpy as np
import pytest

mi.set_variant(VARIANT)
mfnormal.register()

from helpers import encode, sph  # noqa: E402

RES, SPP, SPP_WALK = 24, 16, 64
TEXELS = encode(np.array([sph(30 + 10 * (k % 3), 0.7 * k) for k in range(16)]).reshape(4, 4, 3))
NESTED = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.2,
          "diffuse_reflectance": {"type": "rgb", "value": [0.6, 0.6, 0.6]}}

# (model, tangent facet, step h, tolerance of the forward image's mean relative error,
#  tolerance of a mean's relative error). Measured: faithful / analytic agree to ~2e-4 in
#  reverse mode; the walk (64 spp) to 3 % with a paired SE of 5 %.
CASES = [("faithful", None, 1e-3, 0.05, 0.01),
         ("analytic", None, 1e-3, 0.05, 0.01),
         ("nonseparable", "same", 0.02, 0.5, 0.03)]
SLOW = os.environ.get("MFNORMAL_SLOW") == "1"
# CI runs these (~40 s on 2 cores); MFNORMAL_SLOW=1 every combination.
FAST = {("faithful", "texel", "prb"), ("analytic", "strength", "prb_projective"),
        ("nonseparable", "texel", "prb")}
# prb's forward mode loses the derivative of the faithful model's map-wide rms slope σ (a
# value that parameters_changed derives from the map: the render's forward pass does not
# see its tangent; reverse mode does). Measured: the forward image's mean 3 % low.
FORWARD_XFAIL = {"faithful"}


def cases(mode):
    out = []
    for model, facet, h, tf, tb in CASES:
        for what in ("texel", "strength"):
            for integrator in ("prb", "prb_projective"):
                marks = []
                if not SLOW and (model, what, integrator) not in FAST:
                    marks.append(pytest.mark.skip(reason="MFNORMAL_SLOW=1"))
                if mode == "forward" and model in FORWARD_XFAIL:
                    marks.append(pytest.mark.xfail(strict=True, reason="forward mode: σ's derivative lost"))
                out.append(pytest.param(model, facet, h, tf, tb, what, integrator, marks=marks,
                                        id=f"{model}-{what}-{integrator}"))
    return out


def scene(model, facet):
    bsdf = {"type": "normalmap_microfacet", "model": model, "bsdf": NESTED,
            "normalmap": {"type": "bitmap", "data": mi.TensorXf(TEXELS), "raw": True,
                          "filter_type": "nearest"}}
    if facet is not None:
        bsdf["tangent_facet"] = facet
    el = np.radians(40.0)
    return mi.load_dict({
        "type": "scene",
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0.3, 0.2, 3.0], target=[0, 0, 0],
                                                              up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": RES, "height": RES, "rfilter": {"type": "box"},
                            "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": SPP}},
        "plane": {"type": "rectangle", "bsdf": bsdf,
                  "to_world": mi.ScalarTransform4f().scale([1.5, 1.5, 1.0])},
        "sun": {"type": "directional", "direction": [-np.cos(el), -0.3, -np.sin(el)],
                "irradiance": {"type": "rgb", "value": 3.0}},
    })


def key_of(params, what):
    return next(k for k in params.keys() if k.endswith("normalmap.data" if what == "texel" else "." + what))


def update(params, what, base, theta):
    """θ added to texel (1, 2)'s x channel, or strength = 1 + θ."""
    key = key_of(params, what)
    if what == "texel":
        mask = np.zeros_like(TEXELS)
        mask[1, 2, 0] = 1.0
        params[key] = mi.TensorXf(base) + theta * mi.TensorXf(mask)
    else:
        params[key] = mi.Float(1.0) + theta
    params.update()


def fd_image(sc, params, what, base, h, spp):
    path = mi.load_dict({"type": "path", "max_depth": 2})
    out = []
    for t in (h, -h):
        update(params, what, base, mi.Float(t))
        out.append(np.array(mi.render(sc, params, integrator=path, seed=0, spp=spp), np.float64))
    update(params, what, base, mi.Float(0.0))
    return (out[0] - out[1]) / (2 * h)


def prepare(model, facet, what, h, integrator, spp):
    sc = scene(model, facet)
    params = mi.traverse(sc)
    base = np.array(params[key_of(params, "texel")])
    ref = fd_image(sc, params, what, base, h, spp)
    assert abs(ref.mean()) > 1e-4 and np.abs(ref).max() > 1e-3, "the scene must see the parameter"
    theta = mi.Float(0.0)
    dr.enable_grad(theta)
    update(params, what, base, theta)
    img = mi.render(sc, params, integrator=mi.load_dict({"type": integrator, "max_depth": 2}), seed=0, spp=spp)
    return theta, img, ref


def forward_image(model, facet, what, h, integrator, spp):
    theta, img, ref = prepare(model, facet, what, h, integrator, spp)
    dr.forward(theta)
    return np.array(dr.grad(img), np.float64), ref


def paired_se(fwd, ref):
    """Standard error of the mean of the per-pixel differences AD − FD (pixels are independent
    estimates: independent sampler; a walk's noise, 0 up to rounding for the others)."""
    d = (fwd - ref).ravel()
    return float(d.std() / np.sqrt(d.size))


@pytest.mark.parametrize("model, facet, h, tol_img, tol_mean, what, integrator", cases("forward"))
def test_render_forward_gradient_matches_finite_differences(model, facet, h, tol_img, tol_mean, what,
                                                            integrator):
    """The forward-mode image against the FD image: the mean over pixels of
    |AD − FD| / max(|FD|, 10 % of max |FD|) (Mitsuba's test style) below tol_img, and the
    images' means within 4 paired standard errors + tol_mean relative."""
    spp = SPP_WALK if facet is not None else SPP
    fwd, ref = forward_image(model, facet, what, h, integrator, spp)
    err = float((np.abs(fwd - ref) / np.maximum(np.abs(ref), 0.1 * np.abs(ref).max())).mean())
    se = paired_se(fwd, ref)
    print(f"{model} {what} {integrator} forward: mean {fwd.mean():+.5g}, FD {ref.mean():+.5g} ± {se:.2g} "
          f"(rel. error {abs(fwd.mean() - ref.mean()) / abs(ref.mean()):.3g}), per-pixel error {err:.3g}")
    assert err < tol_img, err
    assert abs(fwd.mean() - ref.mean()) < 4 * se + tol_mean * abs(ref.mean()), (fwd.mean(), ref.mean(), se)


@pytest.mark.parametrize("model, facet, h, tol_img, tol_mean, what, integrator", cases("reverse"))
def test_render_reverse_gradient_matches_finite_differences(model, facet, h, tol_img, tol_mean, what,
                                                            integrator):
    """Reverse mode: d(mean image)/dθ against the FD image's mean, within tol_mean relative plus,
    for the walk, 4 paired standard errors (those of its forward image against the FD's)."""
    spp = SPP_WALK if facet is not None else SPP
    se = 0.0
    if facet is not None:
        se = paired_se(*forward_image(model, facet, what, h, integrator, spp))
    theta, img, ref = prepare(model, facet, what, h, integrator, spp)
    dr.backward(dr.mean(img, axis=None))
    bwd = float(np.array(dr.grad(theta)).ravel()[0])
    err = abs(bwd - ref.mean()) / abs(ref.mean())
    print(f"{model} {what} {integrator} reverse: {bwd:+.5g}, FD {ref.mean():+.5g} ± {se:.2g} (rel. error {err:.3g})")
    assert abs(bwd - ref.mean()) < 4 * se + tol_mean * abs(ref.mean()), (bwd, ref.mean(), se)
