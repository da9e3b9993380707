"""Derivatives of every model: forward and reverse AD against central finite differences.

The loss is a BSDF query averaged over 2^18 queries (random ω_i, ω_o, four texels of a
1×4 map, distinct positions; eval and pdf weighted by c(ω_o) = 1 + ω_x + ½ω_y and a sample's
weight by c of its direction, so that the loss sees where the lobes lie and not just how
much energy leaves). Its derivative with respect to ``strength``, the nested GGX α and
single texel channels is taken by forward AD (every query's own derivative, hence a mean and
a standard error), by reverse AD (the mean's gradient), and by central finite differences
with common random numbers (the walks hash their random numbers from the query, never from
θ). They must agree within 4 paired standard errors of AD − FD plus 3 % of FD
(``gradients.Check.agrees``); the paired standard error is that of the per-query
differences, so a deterministic model is held to a few float ulps and a walk to its noise.

Steps, and why: the deterministic models (faithful, analytic) h = 1e-3 (float32 leaves
FD ~1e-4 of relative rounding, the truncation error is O(h²)); the walks h = 0.02 at tilted
texels and for α (a walk's FD noise comes from decisions that flip between θ ± h, its
variance ∝ 1/(h·N), and smaller steps drown in it; halving h moves the FD by less than its
noise). At a flat texel and at strength = 0 every model uses h = 1e-3: there the walks'
eval bends sharply within tilts of ~0.04 (measured: FD at h = 0.02 is 11 % below the limit
that h = 1e-3 reaches), while few decisions flip, so the noise stays small. Strength = 0 is
the boundary of its domain (strength ≥ 0): its FD is one-sided, second order.

The facets are Lambertian (the walks' noise is lowest there, so their checks are sharpest;
its pdf, cosθ/π, vanishes at a facet's horizon, so every pdf is continuous in ω_p), and a GGX
roughconductor for α (Mitsuba's roughplastic precomputes its albedo from α outside AD, so its
own α derivative is off: AD −0.031, FD −0.065 measured). With GGX facets the pdfs jump where
a facet's horizon crosses ω_o (the nested pdf does not vanish there): AD gives their
derivative without that boundary term.
"""

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

mi.set_variant("llvm_ad_rgb")
mfnormal.register()

import gradients as G  # noqa: E402
from helpers import encode, make_bsdf, sph  # noqa: E402

MODELS = [("faithful", None), ("analytic", None), ("separable", "specular"), ("separable", "same"),
          ("nonseparable", "specular"), ("nonseparable", "same")]
IDS = ["faithful", "analytic", "separable-specular", "separable-same", "nonseparable-specular", "nonseparable-same"]
DIFFUSE = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.3, 0.6, 0.9]}}
GGX = {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3}
N = 1 << 18
# Four texels: tilts 30°, 50°, 15° at three azimuths, and one exactly flat.
TILTED = encode(np.array([sph(30, 0.3), sph(50, 0.8), sph(15, -0.4), sph(0)]).reshape(-1, 3))
FLAT = encode(np.array([sph(0)] * 4).reshape(-1, 3))


def walk(model):
    return model not in ("faithful", "analytic")


def checks(model, facet, texels, keys, what="eval", one_sided=(), nested=DIFFUSE, **params):
    b = make_bsdf(nested, texels, model=model, tangent_facet=facet, **params)
    si, wo, u = G.queries(N, 4)
    out = {}
    for key, h in keys:
        c = G.check(b, key, si, wo, u, h, what, one_sided=key in one_sided)
        print(f"{model}-{facet} {what} {key}: {c}")
        out[key] = c
    return out


@pytest.mark.parametrize("model, facet", MODELS, ids=IDS)
def test_eval_derivatives_match_finite_differences(model, facet):
    """d/d strength and d/d texel (tilted texels, and a flat one in a tilted map), d/dα (GGX
    facets): forward = reverse = FD."""
    h = 0.02 if walk(model) else 1e-3
    out = checks(model, facet, TILTED, [("strength", h), (("texel", 0, 0), h), (("texel", 1, 1), h),
                                        (("texel", 3, 0), 1e-3)])
    out.update(checks(model, facet, TILTED, [("nested_bsdf.alpha.value", h)], nested=GGX))
    for key, c in out.items():
        assert c.agrees(), f"{key}: {c}"
        assert abs(c.fd) > 4 * c.se, f"{key}: the check must see a derivative ({c})"


@pytest.mark.parametrize("model, facet", MODELS, ids=IDS)
def test_eval_derivatives_at_a_flat_map(model, facet):
    """At an exactly flat map (the usual start of an optimisation) every texel channel has
    its central derivative (FD of 1e-3), not the 0 that detaching the flat normal gives;
    strength has no effect there (0 both ways)."""
    keys = [(("texel", 0, 0), 1e-3), (("texel", 1, 1), 1e-3), ("strength", 1e-3)]
    out = checks(model, facet, FLAT, keys)
    for key, c in out.items():
        assert c.agrees(), f"{key}: {c}"
    assert out["strength"].ad == 0.0 and out["strength"].fd == 0.0
    for key in (("texel", 0, 0), ("texel", 1, 1)):
        assert abs(out[key].ad) > 0.01, f"{key}: a flat map must have a texel derivative ({out[key]})"


@pytest.mark.parametrize("model, facet", MODELS, ids=IDS)
def test_eval_derivatives_at_strength_zero(model, facet):
    """At strength = 0 (a flat surface from any map) strength has its one-sided derivative,
    and the texels none (both exactly 0)."""
    keys = [("strength", 1e-3), (("texel", 0, 0), 1e-3)]
    out = checks(model, facet, TILTED, keys, one_sided=("strength",), strength=0.0)
    assert out["strength"].agrees(), out["strength"]
    assert abs(out["strength"].ad) > 0.02, out["strength"]
    assert out[("texel", 0, 0)].ad == 0.0 and out[("texel", 0, 0)].rev == 0.0 and out[("texel", 0, 0)].fd == 0.0


@pytest.mark.parametrize("model, facet", MODELS, ids=IDS)
def test_pdf_and_sample_derivatives_match_finite_differences(model, facet):
    """pdf (a deterministic function) and a sample's weight × c(its direction) (the sampled
    direction detached where it has a density, Mitsuba's detached sampling; the walks'
    throughput carries p/detach(p) for every decision): d/d strength and d/d texel.

    For the sample, FD with common sample numbers sees branch changes (samples that jump
    between lobes as θ moves), which makes it noisy; the paired SE measures that."""
    h = 0.02 if walk(model) else 1e-3
    keys = [("strength", h), (("texel", 0, 0), h)]
    for what in ("pdf", "sample"):
        hs = keys if what == "pdf" or walk(model) else [(k, 0.01) for k, _ in keys]
        for key, c in checks(model, facet, TILTED, hs, what).items():
            assert c.agrees(), f"{what} {key}: {c}"
