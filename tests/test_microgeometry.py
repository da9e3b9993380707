"""The random-walk models of ``normalmap_microfacet`` against Mitsuba ray tracing real microgeometry.

The reference (``validation/reference/microgeometry.py``) builds the sawtooth microsurface of
docs/model.md §2.2 as two triangle meshes (p facets and t walls, each with its own
Mitsuba BSDF), shoots a parallel beam from ω_i at it with ``scene.ray_intersect``
and scatters with the facets' own ``bsdf.sample`` until the rays escape. It shares
no code with the plugin's model.

The plugin is sampled with a constant normal map ω_p and the same ω_i, in a shading
frame rotated by PHI_P about ω_g (to exercise its facet frames); exit directions
are binned, weighted by throughput, into 8×8 cells of (cosθ, φ) in both cases.

Statistics: per cell, z = (model − reference) / sqrt(var_model + var_reference),
with both variances estimated from the samples. A case passes if (a) every |z| is
below the Šidák-corrected two-sided bound for a family-wise error of ALPHA over the
informative cells, and (b) Σz² is below the (1 − ALPHA) χ² quantile with one degree
of freedom per informative cell. ALPHA = 1e-3 per case and criterion: over the 26
cases a correct model fails somewhere with probability ≤ 5% for a random seed;
every seed is fixed, so the outcome is deterministic. At N = 5e5 the L1 noise floor
of an 8×8 histogram is ≈ 0.011 (measured: 0.007–0.015 for the non-separable model).
"""

import functools

import numpy as np
import pytest
from scipy import stats

from validation.reference import microgeometry as mg  # noqa: E402  (imports mfnormal first: libLLVM)
import mitsuba as mi
from tiers import FULL

N = 500_000          # rays traced and plugin samples per case
ALPHA = 1e-3         # family-wise false-alarm rate per case
PHI_P = 0.9          # azimuth (radians) of ω_p in the plugin's shading frame

GLOSSY = {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3, "material": "none"}
NESTED = {"lambert": mg.WHITE_DIFFUSE, "ggx0.3": GLOSSY}

# (nested, tangent facet, θ_p, θ_i, φ_i); φ_i = 0 toward the tilt of ω_p, 180 away (t side).
LAMBERT_CASES = [("lambert", tf, tp, ti, phi) for tf in ("specular", "same") for tp in (30, 60)
                 for ti in (20, 70) for phi in (0, 180)]
# Oblique incidence (along-groove component), one per tangent facet.
OBLIQUE_CASES = [("lambert", tf, 60, 70, 90) for tf in ("specular", "same")]
GLOSSY_CASES = [("ggx0.3", "specular", tp, ti, phi) for tp in (30, 60) for ti in (20, 70)
                for phi in (0, 180)]
ALL_CASES = LAMBERT_CASES + OBLIQUE_CASES + GLOSSY_CASES
# The default run compares the Lambertian cases at θ_p = 60° (every θ_i, side and tangent facet);
# those at θ_p = 30° run with MFNORMAL_SLOW=1: the same model code at a milder tilt, whose
# (θ_p, θ_i, side, tangent facet) tests/test_nonseparable_vs_sawtooth.py also compares, against
# the sawtooth tracer, in the default run.
SLOW_CASES = [c for c in LAMBERT_CASES if c[2] == 30]
RUN_CASES = ALL_CASES if FULL else [c for c in ALL_CASES if c not in SLOW_CASES]


def case_params(cases):
    return [pytest.param(c, id=case_id(c), marks=(pytest.mark.slow,) if c in SLOW_CASES else ()) for c in cases]


def case_id(case):
    nested, tf, tp, ti, phi = case
    return f"{nested}-{tf}-p{tp}-i{ti}-az{phi}"


@functools.lru_cache(maxsize=None)
def result(case):
    """Ray-traced and plugin histograms of one case (computed once per test process)."""
    nested, tf, tp, ti, phi = case
    return mg.compare_histograms(tp, ti, phi, NESTED[nested], tf, n=N, seed=ALL_CASES.index(case),
                                 phi_p=PHI_P)


def lambda_p_ref(w, wp):
    """λ_p(ω) = ⟨ω,ω_p⟩₊ / (⟨ω,ω_p⟩₊ + sinθ_p⟨ω,ω_t⟩₊) (docs/model.md §2.1), float64."""
    sin_p = np.hypot(wp[0], wp[1])
    wt = -np.array([wp[0], wp[1], 0.0]) / sin_p
    a_p = max(0.0, float(w @ wp))
    a_t = sin_p * max(0.0, float(w @ wt))
    return a_p / (a_p + a_t)


def agreement(model, reference):
    """(max |z|, Šidák bound, Σz², χ² bound, informative cells) of two histograms."""
    z = mg.z_scores(model, reference)
    informative = (model[1] + reference[1]) > 0
    k = int(informative.sum())
    per_cell = 1.0 - (1.0 - ALPHA) ** (1.0 / k)
    z_max_allowed = stats.norm.isf(per_cell / 2.0)
    chi2 = float(np.sum(z[informative] ** 2))
    return float(np.abs(z).max()), z_max_allowed, chi2, stats.chi2.isf(ALPHA, k), k


# -- The mesh and its geometry -------------------------------------------------------------


@pytest.mark.parametrize("theta_p", [30, 60])
def test_mesh_facets_face_out_with_the_model_normals(theta_p):
    geo = mg.SawtoothScene(theta_p, mg.WHITE_DIFFUSE, mg.MIRROR)
    wp = np.array([np.sin(np.radians(theta_p)), 0.0, np.cos(np.radians(theta_p))])
    for mesh, normal in ((geo.p_mesh, wp), (geo.t_mesh, np.array([-1.0, 0.0, 0.0]))):
        idx = mi.UInt32(np.arange(mesh.face_count(), dtype=np.uint32))
        n = np.array(mesh.face_normal(idx), np.float64).reshape(3, -1).T
        assert np.abs(n - normal).max() < 1e-5
    # Walls are vertical and face back toward the p facet that descends to their foot
    assert geo.wt @ geo.wp < 0 and abs(geo.wt[2]) == 0
    # Crest height 1, mean plane z ∈ [0, 1], and 400 periods by 2·10⁴ crest heights
    for mesh in (geo.p_mesh, geo.t_mesh):
        box = mesh.bbox()
        assert box.min.z == 0.0 and box.max.z == 1.0
        assert box.max.x - box.min.x >= 398 * geo.W and box.max.y - box.min.y >= 2e4
    # A_p ω_p + A_t ω_t = ω_g per unit area: facet areas are 1/cosθ_p and tanθ_p
    box = geo.p_mesh.bbox()
    footprint = (box.max.x - box.min.x) * (box.max.y - box.min.y)
    a_p = float(geo.p_mesh.surface_area()[0]) / footprint
    a_t = float(geo.t_mesh.surface_area()[0]) / footprint
    assert np.allclose(a_p * wp + a_t * geo.wt, [0, 0, 1], atol=1e-4)


@pytest.mark.parametrize("theta_p", [30, 60])
def test_first_hit_fractions_match_lambda_p(theta_p):
    """Mitsuba's first hits agree with λ_p (docs/model.md §2.1) within 5 binomial σ."""
    geo = mg.SawtoothScene(theta_p, mg.WHITE_DIFFUSE, mg.MIRROR)
    n = 100_000
    for i, (theta, phi) in enumerate([(t, a) for t in (10, 40, 70, 85) for a in (0, 60, 120, 180)]):
        w = mg.sph(theta, phi)
        tr = mg.trace(geo, w, n, seed=100 + i, max_bounces=1)
        lam = lambda_p_ref(w, geo.wp)
        frac = tr.first_is_p.mean()
        # 5σ, plus a few rays grazing an edge (leaked) when λ_p ∈ {0, 1}
        tol = 5.0 * np.sqrt(lam * (1.0 - lam) / n) + 5.0 / n
        assert abs(frac - lam) <= tol, (theta, phi, frac, lam)


# -- The non-separable model equals ray tracing -------------------------------------------


@pytest.mark.parametrize("case", case_params(ALL_CASES))
def test_nonseparable_model_matches_raytraced_microgeometry(case):
    res = result(case)
    tr = res["trace"]
    # The reference lost (almost) no rays through corners or to the bounce cap
    assert tr.leaked + tr.capped <= 1e-4 * N, (tr.leaked, tr.capped)
    if case[0] == "lambert":
        # White facets: the microsurface conserves energy exactly
        assert abs(res["reference"][0].sum() - 1.0) <= 1e-4
    z_max, z_bound, chi2, chi2_bound, k = agreement(res["nonseparable"], res["reference"])
    assert z_max < z_bound, f"{case_id(case)}: max |z| {z_max:.2f} ≥ {z_bound:.2f}"
    assert chi2 < chi2_bound, f"{case_id(case)}: χ² {chi2:.1f} ≥ {chi2_bound:.1f} ({k} cells)"


# -- The separable model is an approximation ----------------------------------------------


@pytest.mark.parametrize("case", case_params([c for c in LAMBERT_CASES + OBLIQUE_CASES if c[3] == 70]))
def test_separable_model_is_farther_from_raytracing_at_grazing_incidence(case):
    """At θ_i = 70° forgetting the height correlation is far beyond Monte Carlo noise.

    docs/model.md §7 quotes L1 = 0.25–0.54 (8 bins) for the separable model here.
    """
    res = result(case)
    l1_sep, l1_ns = res["l1"]["separable"], res["l1"]["nonseparable"]
    assert l1_sep > max(3.0 * l1_ns, 0.05), (l1_sep, l1_ns)
    _, _, chi2, chi2_bound, _ = agreement(res["separable"], res["reference"])
    assert chi2 > chi2_bound


def test_report_distances_to_raytracing(capsys):
    """Print the L1 distances of both models to the ray-traced reference (run with -s), for the
    cases of this run (:data:`RUN_CASES`)."""
    lines = [f"{'case':<34} {'L1 nonsep':>9} {'L1 sep':>7} {'χ²/k nonsep':>11} {'χ²/k sep':>9}"]
    for case in RUN_CASES:
        res = result(case)
        _, _, chi_ns, _, k = agreement(res["nonseparable"], res["reference"])
        _, _, chi_s, _, k_s = agreement(res["separable"], res["reference"])
        lines.append(f"{case_id(case):<34} {res['l1']['nonseparable']:9.4f} {res['l1']['separable']:7.4f} "
                     f"{chi_ns / k:11.2f} {chi_s / k_s:9.1f}")
        assert res["l1"]["nonseparable"] < res["l1"]["separable"]
    with capsys.disabled():
        print("\n" + "\n".join(lines))
