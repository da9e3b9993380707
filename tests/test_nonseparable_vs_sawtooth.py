"""The non-separable walk against brute-force ray tracing of the sawtooth (docs/model.md §2.2, §4).

The reference is ``validation/reference/sawtooth.py``: numpy ray tracing of the periodic sawtooth
microsurface, sharing no code with ``mfnormal``. docs/model.md §2.2 states that the
non-separable model *equals* that ray tracing, while the separable model forgets
the height correlation between bounces (§4.1, §7). Both claims are tested here for
white Lambertian p facets with a mirror (``tangent_facet='specular'``) or white
Lambertian (``'same'``) tangent facet, θ_p ∈ {30°, 60°}, θ_i ∈ {20°, 70°}, ω_i
toward or away from the tilt (16 cases, ``sawtooth_compare.CASES``).

Histograms have 6×8 cells in (cos²θ_o, φ_o − φ_p) (``sawtooth_compare.cell_index``);
a cell's value estimates ∫_cell f·cosθ_o dω_o. Every seed is fixed, so every test
is deterministic.

Tolerances. Each statistical test (per case: the two-sample χ², the Šidák-corrected
most extreme cell z-score of the sample histogram, the same for the eval integrals)
must have p > ALPHA = 1e-4. Over the 16 cases × 3 tests plus the reciprocity tests
the family-wise false-alarm rate is below 1 % for a correct model; a real bug gives
p ≈ 0 (the separable model, a genuinely different model, gets p < 1e-50 in every
case). Both histograms' noise enters every statistic.

The numbers these tests print (``pytest -s``), and the power of the tests against
mutations of the walk, are in validation/results/measured_in_tests.md.
"""

import functools

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from variant import VARIANT  # noqa: E402  (MFNORMAL_VARIANT, tests/variant.py)
mi.set_variant(VARIANT)
mfnormal.register()

from helpers import floats, vec3  # noqa: E402
from validation.reference import sawtooth_compare as C  # noqa: E402

N_PATHS = 400_000       # paths per side (tracer and model) per case
EVAL_PER_CELL = 8192    # eval() queries per histogram cell per case
ALPHA = 1e-4            # per-test significance level (see the module docstring)
CASE_IDS = [c.id for c in C.CASES]


# -- Cached histograms (each case's tracer run serves every test) -----------------------


@functools.lru_cache(maxsize=None)
def tracer_hist(k):
    return C.histogram(*C.tracer_paths(C.CASES[k], N_PATHS, seed=1000 + k))


MODEL_SEED = {"nonseparable": 2000, "separable": 3000}


@functools.lru_cache(maxsize=None)
def model_hist(k, model):
    return C.histogram(*C.model_paths(C.CASES[k], model, N_PATHS, seed=MODEL_SEED[model] + k))


# -- (a) sample(): exit-direction histograms ---------------------------------------------


@pytest.mark.parametrize("k", range(len(C.CASES)), ids=CASE_IDS)
def test_nonseparable_sample_matches_sawtooth_ray_tracing(k):
    """The walk's exit histogram (throughput-weighted) equals the tracer's within MC noise."""
    ht, hn = tracer_hist(k), model_hist(k, "nonseparable")
    chi2, dof, p_chi2 = C.two_sample_chi2(hn, ht)
    z = C.cell_z(hn[0], hn[1], ht[0], ht[1])
    p_cell = C.sidak_p(z)
    print(f"\n{C.CASES[k].id}: chi2 = {chi2:.1f}/{dof} (p = {p_chi2:.3g}), "
          f"max|z| = {np.abs(z).max():.2f} (Sidak p = {p_cell:.3g}), L1 = {C.l1(hn[0], ht[0]):.4f}, "
          f"mass {hn[0].sum():.4f} vs {ht[0].sum():.4f}")
    assert p_chi2 > ALPHA, (chi2, dof)
    assert p_cell > ALPHA, z.reshape(C.N_U, C.N_PHI).round(2)
    # White facets conserve energy in both (nothing lost to the bounce cap).
    assert abs(hn[0].sum() - 1.0) < 1e-4 and abs(ht[0].sum() - 1.0) < 1e-4


# -- (b) eval(): cell integrals ----------------------------------------------------------


@pytest.mark.parametrize("k", range(len(C.CASES)), ids=CASE_IDS)
def test_nonseparable_eval_integrates_to_sawtooth_cell_fractions(k):
    """∫_cell eval dω_o (stratified cosine-weighted ω_o, one si.p per query) = cell mass."""
    ht = tracer_hist(k)
    integral, var = C.eval_cells(C.CASES[k], "nonseparable", EVAL_PER_CELL, seed=4000 + k)
    z = C.cell_z(integral, var, ht[0], ht[1])
    p_cell = C.sidak_p(z)
    # The total is the albedo, 1 for white facets; its standard error is √Σvar.
    z_total = (integral.sum() - 1.0) / np.sqrt(var.sum())
    print(f"\n{C.CASES[k].id}: max|z| = {np.abs(z).max():.2f} (Sidak p = {p_cell:.3g}), "
          f"sum = {integral.sum():.4f} (z = {z_total:.2f}), L1 = {C.l1(integral, ht[0]):.4f}")
    assert p_cell > ALPHA, z.reshape(C.N_U, C.N_PHI).round(2)
    assert abs(z_total) < 4.0


# -- (c) the separable model is not the sawtooth ----------------------------------------


def test_separable_model_is_distinguishable_from_sawtooth_ray_tracing():
    """Forgetting height correlation (docs/model.md §7) shows: p ≈ 0 at grazing incidence.

    The same data put the non-separable model within noise (L1 at the noise floor),
    and the separable error is largest at grazing incidence for both tangent facets.
    """
    rows = []
    for k, case in enumerate(C.CASES):
        ht, hs, hn = tracer_hist(k), model_hist(k, "separable"), model_hist(k, "nonseparable")
        rows.append((case, C.l1(hs[0], ht[0]), C.two_sample_chi2(hs, ht)[2],
                     C.l1(hn[0], ht[0]), C.two_sample_chi2(hn, ht)[2]))
    print("\ncase                          L1 sep   p sep      L1 nonsep  p nonsep")
    for case, l1_s, p_s, l1_n, p_n in rows:
        print(f"{case.id:28s}  {l1_s:.3f}   {p_s:9.3g}   {l1_n:.4f}     {p_n:.3g}")
    for case, l1_s, p_s, l1_n, p_n in rows:
        if case.grazing:
            assert p_s < 1e-20 and l1_s > 5.0 * l1_n, (case.id, l1_s, p_s, l1_n)
        assert p_n > ALPHA, (case.id, p_n)
    for tf in ("specular", "same"):
        worst = max((r for r in rows if r[0].tangent_facet == tf), key=lambda r: r[1])
        assert worst[0].grazing, (tf, worst[0].id, worst[1])


# -- (d) reciprocity ---------------------------------------------------------------------

RECIPROCITY_WP = C.sph(45.0, C.PHI_P_DEG)
# (θ_i, φ_i) ↔ (θ_o, φ_o) in degrees: both toward the tilt, across it, both away, grazing.
RECIPROCITY_PAIRS = [((20.0, 55.0), (70.0, 235.0)), ((50.0, 10.0), (80.0, 130.0)),
                     ((75.0, 220.0), (65.0, 250.0)), ((35.0, 300.0), (85.0, 40.0))]
RECIPROCITY_N = 200_000 # NEE estimates (distinct si.p) per direction of each pair


@pytest.mark.parametrize("model,tangent_facet", [(m, t) for m in ("separable", "nonseparable")
                                                  for t in ("specular", "same")])
def test_walk_models_are_reciprocal(model, tangent_facet):
    """f(ω_i, ω_o) = f(ω_o, ω_i): mean eval/cosθ_o over distinct si.p, z-test per pair (Šidák)."""
    bsdf = C.make_bsdf(model, tangent_facet, RECIPROCITY_WP)
    dirs = [(C.sph(*a), C.sph(*b)) for a, b in RECIPROCITY_PAIRS]
    queries = [q for a, b in dirs for q in ((a, b), (b, a))]
    wi = np.repeat([q[0] for q in queries], RECIPROCITY_N, axis=0)
    wo = np.repeat([q[1] for q in queries], RECIPROCITY_N, axis=0).astype(np.float32)
    n = len(wi)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = vec3(wi)
    si.p = mi.Point3f(floats(np.arange(n)), 0.0, 0.0)
    wo_v = vec3(wo)
    f_cos = np.array(bsdf.eval(mi.BSDFContext(), si, wo_v))[0]
    f = (f_cos / wo[:, 2]).reshape(len(queries), RECIPROCITY_N)
    mean, se = f.mean(axis=1), f.std(axis=1, ddof=1) / np.sqrt(RECIPROCITY_N)
    z = (mean[0::2] - mean[1::2]) / np.hypot(se[0::2], se[1::2])
    print(f"\n{model}/{tangent_facet}: f(i,o) = {mean[0::2].round(4)}, f(o,i) = {mean[1::2].round(4)}, "
          f"rel. se {(se / mean).max():.4f}, z = {z.round(2)}")
    assert np.all(mean > 0.01)
    assert C.sidak_p(z) > ALPHA, z
