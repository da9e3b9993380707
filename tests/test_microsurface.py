"""Tests of ``mfnormal.surface.microsurface`` against an independent brute-force sawtooth tracer.

The reference is ``validation/reference/sawtooth.py`` (numpy only, no mfnormal code, no closed-form
λ or G1): it intersects rays with the line segments of the periodic sawtooth of
docs/model.md §2.2. Statistical tolerances are binomial: an estimate from N independent
rays has standard deviation σ = sqrt(p(1−p)/N); we allow 5σ plus a tiny absolute
term for the float32 model inputs. Every seed is fixed.
"""

import numpy as np
import pytest

import mfnormal  # noqa: F401  (picks a working libLLVM before mitsuba loads)
import mitsuba as mi
from variant import VARIANT  # noqa: E402  (MFNORMAL_VARIANT, tests/variant.py)

mi.set_variant(VARIANT)
mfnormal.register()

from mfnormal.surface import microsurface as ms  # noqa: E402

from helpers import np3, vec3  # noqa: E402
from validation.reference import sawtooth as sw  # noqa: E402

N_RAYS = 40_000
# Directions within this of a facet's plane see that facet edge-on (see below).
EDGE_ON = 1e-4
# Float32 model inputs move a visibility threshold by ~1e-7; allow 1e-5.
H_TOL = 1e-5


# ---------------------------------------------------------------- helpers
def sph(theta_deg, phi_deg):
    """A unit vector at polar angle θ and azimuth φ, both in degrees (the tracer's convention)."""
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def model(w, wp):
    """(λ_p, G1_p, G1_t) of the model for rows of w and wp, as float64 numpy."""
    w, wp = vec3(w), vec3(wp)
    wt, sin_p = ms.tangent_facet(wp)
    out = (ms.lambda_p(w, wp, wt, sin_p), ms.G1_p(w, wp, wt, sin_p), ms.G1_t(w, wp, wt, sin_p))
    return [np.array(x, dtype=np.float64) for x in out]


def direction_grid(wp, rng):
    """Directions ω around a perturbed normal: θ ∈ {0,20,45,70,85}° toward, away from
    and across the tilt, plus 3 random ones above the horizon."""
    phi_p = np.degrees(np.arctan2(wp[1], wp[0]))
    ws = [sph(0, 0)]
    for theta in (20, 45, 70, 85):
        for dphi in (0, 180, 90):  # toward, away from, across the tilt
            ws.append(sph(theta, phi_p + dphi))
    for _ in range(3):
        z = rng.uniform(0.05, 1.0)
        ws.append(sph(np.degrees(np.arccos(z)), rng.uniform(0, 360)))
    return np.array(ws)


def binomial_tol(p, n):
    return 5.0 * np.sqrt(p * (1.0 - p) / n) + 1e-4


# ------------------------------------------- 1. λ_p and G1 vs brute force
@pytest.mark.parametrize("theta_p", [10, 30, 45, 60, 80])
def test_lambda_and_G1_match_brute_force_sawtooth(theta_p):
    """λ_p, G1_p, G1_t of the model agree with ray tracing the sawtooth.

    Three checks per configuration:
    - λ_p vs the fraction of N parallel rays hitting p first (5σ binomial);
    - G1_m vs the visible fraction of N height-uniform points on m (5σ binomial);
    - exact: a point of m at height h is visible iff h > 1 − G1_m (the visible part
      is the top interval, docs/model.md §2.2), and first hits on m land in that interval.
      This is noise-free; only points within H_TOL of the threshold are ignored.

    Edge-on facets are skipped deliberately: if |⟨ω,ω_m⟩| < EDGE_ON, facet m is seen
    edge-on (ω across the tilt for t; ω in the p plane, e.g. θ_p = θ = 45° away from
    the tilt, for p). Its projected area is 0, so G1_m is 0/0: the model says 0
    (χ⁺), while a ray grazing along the facet may or may not escape, depending on
    rounding. λ_p is continuous there and is always checked.
    """
    rng = np.random.default_rng(1000 + theta_p)
    checked = 0
    for phi_p in (0.0, 130.0, 250.0):
        wp = sph(theta_p, phi_p)
        st = sw.Sawtooth(wp)
        ws = direction_grid(wp, rng)
        lam_m, g1p_m, g1t_m = model(ws, np.tile(wp, (len(ws), 1)))
        for w, lam, g1p, g1t in zip(ws, lam_m, g1p_m, g1t_m):
            where = f"theta_p={theta_p} phi_p={phi_p} w={np.round(w, 4)}"
            # λ_p: fraction of first hits on p.
            m, h = st.first_hit(w, N_RAYS, rng)
            lam_bf = np.mean(m == sw.P)
            assert abs(lam_bf - lam) <= binomial_tol(lam, N_RAYS), (where, lam_bf, lam)
            for facet, g1 in ((sw.P, g1p), (sw.T, g1t)):
                if abs(w @ st.n3[facet]) < EDGE_ON:
                    continue
                vis, hv = st.visible(facet, w, N_RAYS, rng)
                g1_bf = np.mean(vis)
                assert abs(g1_bf - g1) <= binomial_tol(g1, N_RAYS), (where, facet, g1_bf, g1)
                # Visible iff in the top interval [1 − G1, 1].
                clear = np.abs(hv - (1.0 - g1)) > H_TOL
                assert np.array_equal(vis[clear], hv[clear] > 1.0 - g1), (where, facet)
                # First hits on this facet come from its visible band.
                assert np.all(h[m == facet] >= 1.0 - g1 - H_TOL), (where, facet)
                checked += 1
    # Only the edge-on cases are skipped: t from θ = 0 and across the tilt (5 per φ_p),
    # p at θ = 45° away from the tilt when θ_p = 45°.
    assert checked == 3 * (2 * 16 - 5 - (theta_p == 45))


# ---------------------------------------------- 2. closed-form table (docs/model.md §2.1)
def test_closed_form_table_cases():
    """The three rows of the docs/model.md §2.1 table, written out independently."""
    rng = np.random.default_rng(7)
    rows = {1: [], 2: [], 3: []}
    while min(len(r) for r in rows.values()) < 20:
        wp = sph(rng.uniform(3, 85), rng.uniform(0, 360))
        w = sph(np.degrees(np.arccos(rng.uniform(0.02, 1))), rng.uniform(0, 360))
        cos_p, sin_p = wp[2], np.hypot(wp[0], wp[1])
        wt = np.array([-wp[0], -wp[1], 0.0]) / sin_p
        wg_w, wp_w, wt_w = w[2], w @ wp, w @ wt
        if min(abs(wp_w), abs(wt_w)) < 1e-3:
            continue  # keep clear of the row boundaries
        if wt_w <= 0:
            rows[1].append((w, wp, 1.0, cos_p * wg_w / wp_w, 0.0))
        elif wp_w >= 0:
            rows[2].append((w, wp, wp_w / (cos_p * wg_w), 1.0, 1.0))
        else:
            rows[3].append((w, wp, 0.0, 0.0, cos_p / sin_p * wg_w / wt_w))
    for case, r in rows.items():
        w, wp, lam, g1p, g1t = (np.array(c) for c in zip(*r[:20]))
        got = model(w, wp)
        for name, g, want in zip(("lambda_p", "G1_p", "G1_t"), got, (lam, g1p, g1t)):
            np.testing.assert_allclose(g, want, rtol=2e-5, atol=1e-6, err_msg=f"row {case} {name}")


def test_tangent_facet_is_the_sawtooth_wall():
    """ω_t is the horizontal unit normal of the sawtooth wall, sinθ_p its area factor."""
    rng = np.random.default_rng(11)
    wps = np.array([sph(rng.uniform(1, 85), rng.uniform(0, 360)) for _ in range(50)])
    wt, sin_p = ms.tangent_facet(vec3(wps))
    wt, sin_p = np3(wt), np.array(sin_p, dtype=np.float64)
    for wp, t, s in zip(wps, wt, sin_p):
        st = sw.Sawtooth(wp)
        np.testing.assert_allclose(t, st.n3[sw.T], atol=1e-6)
        # Wall height 1 over a period cotθ_p: A_t = tanθ_p = sinθ_p / cosθ_p.
        np.testing.assert_allclose(s / wp[2], 1.0 / st.W, rtol=1e-5)


# ------------------------------------- 2b. the height map, in depths below the crest
@pytest.mark.parametrize("theta_p", [20, 60, 85])
def test_crest_map_matches_ray_traced_sawtooth(theta_p):
    """microsurface.crest_map (τ, κ) against rays traced through the sawtooth: a ray
    leaving facet m at depth D = 1 − h in direction d leaves iff D < τ, else it lands on
    the other facet at depth κ(D − τ). Depths include 1e-9 … 1e-3 under the crest and
    directions grazing to 1e-6, where heights h = 1 − D would be rounded in float32
    (the walk's reason to store depths). The tracer gets the same float32-rounded
    inputs in float64. Tolerance: float32 error propagation with ~16 ulps of slack.
    The across-groove component x = −⟨d, ω_t⟩ is a float32 dot product of unit
    vectors, off by up to ~1e-7 absolute, so τ carries a relative error
    δ = 1e-6/|x| + 1e-6; the escape decision is compared where |D − τ| > δ·|τ|, and a
    landed depth κ(D − τ) to κ·(δ·|τ| + 1e-6·D) + 1e-6·D'."""
    rng = np.random.default_rng(theta_p)
    wp32 = np.float32(sph(theta_p, rng.uniform(0, 360)))
    st = sw.Sawtooth(wp32.astype(np.float64))
    n = 20_000
    m = rng.integers(0, 2, n)
    depth = np.where(rng.random(n) < 0.5, rng.random(n), 10.0 ** rng.uniform(-9, -3, n))
    # Travel directions above the starting facet's plane, a share of them grazing.
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    d[:, 2] = np.where(rng.random(n) < 0.3, np.sign(d[:, 2]) * 10.0 ** rng.uniform(-6, -2, n), d[:, 2])
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    normal = np.where((m == sw.P)[:, None], st.n3[sw.P], st.n3[sw.T])
    d = np.where((np.sum(d * normal, 1) < 0)[:, None], d - 2 * np.sum(d * normal, 1)[:, None] * normal, d)
    d, depth = d.astype(np.float32).astype(np.float64), depth.astype(np.float32).astype(np.float64)

    wt, sin_p = ms.tangent_facet(vec3(wp32))
    tau, k = ms.crest_map(mi.Bool(m == sw.P), vec3(d), wt, ms.cot_p(vec3(wp32), sin_p))
    tau, k = np.array(tau, np.float64), np.array(k, np.float64)
    assert np.all(~np.isnan(tau)) and np.all(~np.isnan(k))

    X, _, Z = st.to_cross(d)
    ox, oz = np.where(m == sw.P, (1.0 - depth) * st.W, 0.0), 1.0 - depth   # Sawtooth.point, per ray
    hit, facet, _, _, h = st.intersect(ox, oz, X, Z, own=m)
    assert np.all(facet[hit] != m[hit]), "a ray hit its own facet"
    dtau = (1e-6 / np.maximum(np.abs(X), 1e-30) + 1e-6) * np.abs(np.where(np.isfinite(tau), tau, 0.0))
    clear = np.abs(depth - tau) > dtau
    assert np.array_equal((depth < tau)[clear], ~hit[clear]), np.flatnonzero(((depth < tau) == hit) & clear)[:5]
    stays = hit & clear
    landed = k[stays] * (depth[stays] - tau[stays])
    want = 1.0 - h[stays]
    tol = k[stays] * (dtau[stays] + 1e-6 * depth[stays]) + 1e-6 * want
    bad = np.abs(landed - want) > tol
    assert not np.any(bad), (landed[bad][:5], want[bad][:5], k[stays][bad][:5])
    # Both outcomes, and the near-crest band, were exercised.
    assert stays.sum() > n // 10 and (~hit).sum() > n // 10
    assert np.sum(stays & (depth < 1e-6)) > 50 and np.sum(~hit & (depth < 1e-6)) > 50


def test_crest_map_is_finite_for_a_flat_normal_and_a_ray_along_the_grooves():
    """A flat normal (cotθ_p = 1e30) and d across the grooves of 1.8e-24: r = cot·d_z/|d_x|
    overflowed to ∞ and τ = ∞/∞ = NaN, which zeroed the MIS pdf (found by the fuzzer)."""
    wp = vec3([0.0, 0.0, 1.0])
    wt, sin_p = ms.tangent_facet(wp)
    for on_p in (True, False):
        for x in (1.8e-24, -1.8e-24, 0.0):
            tau, k = ms.crest_map(mi.Bool(on_p), vec3([x, -0.37, 0.93]), wt, ms.cot_p(wp, sin_p))
            assert not np.isnan(np.array(tau)).any() and not np.isnan(np.array(k)).any(), (on_p, x, tau, k)
            assert ms.escape_fraction(mi.Float(0.0), mi.Float(1.0), tau)[0] == 1.0


# ---------------------------------------------- 3. flip_t and facet_frame
def test_flip_t_keeps_height_and_is_an_involution():
    rng = np.random.default_rng(12)
    w = rng.normal(size=(200, 3))
    w /= np.linalg.norm(w, axis=1, keepdims=True)
    wp = np.array([sph(rng.uniform(1, 85), rng.uniform(0, 360)) for _ in range(200)])
    wt, _ = ms.tangent_facet(vec3(wp))
    f = ms.flip_t(vec3(w), wt)
    ff = np3(ms.flip_t(f, wt))
    f, wt = np3(f), np3(wt)
    np.testing.assert_allclose(f[:, 2], w[:, 2], atol=1e-6)
    np.testing.assert_allclose(ff, w, atol=1e-6)
    dot = lambda a, b: np.einsum("ij,ij->i", a, b)  # noqa: E731
    np.testing.assert_allclose(dot(f, wt), -dot(w, wt), atol=1e-6)
    np.testing.assert_allclose(np.linalg.norm(f, axis=1), 1.0, atol=1e-6)


def _frames(wm):
    fr = ms.facet_frame(vec3(wm))
    return np3(fr.s), np3(fr.t), np3(fr.n)


def test_facet_frame_is_orthonormal_and_right_handed():
    rng = np.random.default_rng(13)
    wm = rng.normal(size=(500, 3))
    wm /= np.linalg.norm(wm, axis=1, keepdims=True)
    wm = wm[wm[:, 2] > -0.9]
    s, t, n = _frames(wm)
    np.testing.assert_allclose(n, wm, atol=1e-6)
    for a, b in ((s, s), (t, t)):
        np.testing.assert_allclose(np.einsum("ij,ij->i", a, b), 1.0, atol=1e-5)
    for a, b in ((s, t), (s, n), (t, n)):
        np.testing.assert_allclose(np.einsum("ij,ij->i", a, b), 0.0, atol=1e-5)
    np.testing.assert_allclose(np.cross(s, t), n, atol=1e-5)


def test_facet_frame_is_identity_at_the_geometric_normal():
    s, t, n = _frames([[0.0, 0.0, 1.0]])
    np.testing.assert_allclose(np.concatenate([s, t, n]), np.eye(3), atol=1e-7)
    # ... and tends to it as ω_m → ω_g.
    s, t, _ = _frames([[1e-4, -2e-4, 1.0]])
    np.testing.assert_allclose(np.concatenate([s, t]), np.eye(3)[:2], atol=1e-3)


def test_facet_frame_is_continuous():
    """A step δ in ω_m moves s and t by O(δ) (Lipschitz bound 1/(1+z) ≤ 10 here)."""
    rng = np.random.default_rng(14)
    wm = rng.normal(size=(500, 3))
    wm /= np.linalg.norm(wm, axis=1, keepdims=True)
    wm = wm[wm[:, 2] > -0.5]
    step = rng.normal(size=wm.shape) * 1e-3
    wm2 = wm + step
    wm2 /= np.linalg.norm(wm2, axis=1, keepdims=True)
    d = np.linalg.norm(wm2 - wm, axis=1)
    s1, t1, _ = _frames(wm)
    s2, t2, _ = _frames(wm2)
    assert np.all(np.linalg.norm(s2 - s1, axis=1) <= 10 * d + 1e-5)
    assert np.all(np.linalg.norm(t2 - t1, axis=1) <= 10 * d + 1e-5)


# ------------------------------------------------ 4. the tracer itself
@pytest.mark.parametrize("theta_p", [0.5, 10, 45, 80, 89])
def test_sawtooth_geometry_has_normals_wp_wt_and_a_horizontal_mean_plane(theta_p):
    # The constructor asserts facet normals ω_p, ω_t and Σ length·normal = W·ω_g.
    st = sw.Sawtooth(sph(theta_p, 77))
    assert st.n3[sw.T][2] == 0
    np.testing.assert_allclose(st.W, 1 / np.tan(np.radians(theta_p)), rtol=1e-12)


def test_tracer_normal_incidence_hits_p_uniformly_in_height():
    """From straight above the wall is edge-on: every ray hits p, heights ~ U(0,1)."""
    from scipy import stats

    rng = np.random.default_rng(21)
    st = sw.Sawtooth(sph(40, 10))
    m, h = st.first_hit(np.array([0.0, 0.0, 1.0]), N_RAYS, rng)
    assert np.all(m == sw.P)
    assert stats.kstest(h, "uniform").pvalue > 1e-3


def test_tracer_flat_limit_hits_p():
    """As θ_p → 0 the wall vanishes: λ_p → 1 and p is fully visible (θ ≤ 70°)."""
    rng = np.random.default_rng(22)
    st = sw.Sawtooth(sph(0.5, 200))
    for w in direction_grid(st.wp, rng):
        if w[2] < np.cos(np.radians(70.5)):
            continue
        m, _ = st.first_hit(w, 4000, rng)
        assert np.mean(m == sw.P) > 0.97
        vis, _ = st.visible(sw.P, w, 4000, rng)
        assert np.mean(vis) > 0.97


@pytest.mark.parametrize("theta_p", [30, 60])
def test_tracer_flux_balance(theta_p):
    """The two tracer estimators agree: the beam per unit area hitting m first equals
    m's visible projected area, λ_m(ω)⟨ω,ω_g⟩ = G1_m(ω) A_m ⟨ω,ω_m⟩ with A_m = facet
    length per period width (geometry, not the model). 5σ of the combined noise."""
    rng = np.random.default_rng(23 + theta_p)
    st = sw.Sawtooth(sph(theta_p, 40))
    area = {f: np.linalg.norm(b - a) / st.W for f, (a, b) in st.seg.items()}
    for w in direction_grid(st.wp, rng)[1:]:
        m, _ = st.first_hit(w, N_RAYS, rng)
        for f in (sw.P, sw.T):
            cos_m = w @ st.n3[f]
            if cos_m < EDGE_ON:
                continue
            lam = np.mean(m == f)
            g1 = np.mean(st.visible(f, w, N_RAYS, rng)[0])
            lhs, rhs = lam * w[2], g1 * area[f] * cos_m
            sigma = np.hypot(w[2] * np.sqrt(lam * (1 - lam) / N_RAYS),
                             area[f] * cos_m * np.sqrt(g1 * (1 - g1) / N_RAYS))
            assert abs(lhs - rhs) <= 5 * sigma + 1e-4, (theta_p, w, f, lhs, rhs)


@pytest.mark.parametrize("facets", [("lambert", "lambert"), ("lambert", "mirror"),
                                    ("mirror", "lambert")])
def test_trace_paths_conserve_energy(facets):
    """Albedo-1 facets: every path leaves, upward, as a unit vector."""
    rng = np.random.default_rng(31)
    for theta_p, theta_i in ((30, 20), (60, 70), (80, 85)):
        wi = sph(theta_i, 15)
        wo, bounces = sw.trace_paths(wi, sph(theta_p, 200), 5000, rng, *facets)
        assert np.all(bounces >= 1) and np.all(bounces <= 1000)
        assert np.all(np.isfinite(wo))
        np.testing.assert_allclose(np.linalg.norm(wo, axis=1), 1.0, atol=1e-9)
        assert np.all(wo[:, 2] > 0)


def test_trace_paths_mirrors_preserve_the_groove_component():
    """Mirror facets have normals in the cross-section plane, so the travel direction's
    along-groove component is unchanged; paths still all leave upward."""
    rng = np.random.default_rng(32)
    for theta_p, theta_i, phi_i in ((30, 40, 0), (60, 70, 100), (80, 20, 250)):
        wp, wi = sph(theta_p, 30), sph(theta_i, phi_i)
        st = sw.Sawtooth(wp)
        wo, bounces = sw.trace_paths(wi, wp, 2000, rng, "mirror", "mirror")
        assert np.all(bounces <= 1000) and np.all(wo[:, 2] > 0)
        np.testing.assert_allclose(wo @ st.ey, -(wi @ st.ey), atol=1e-9)


def test_trace_paths_flat_limit_is_cosine_weighted():
    """θ_p → 0: a Lambertian microsurface is a Lambertian plane, so cos²θ_o and the
    azimuth are uniform (KS tests at p > 1e-3; the 0.1° tilt is far below the noise)."""
    from scipy import stats

    rng = np.random.default_rng(33)
    wo, _ = sw.trace_paths(sph(60, 0), sph(0.1, 45), 20_000, rng, "lambert", "lambert")
    assert stats.kstest(wo[:, 2] ** 2, "uniform").pvalue > 1e-3
    phi = np.arctan2(wo[:, 1], wo[:, 0])
    assert stats.kstest(phi, "uniform", args=(-np.pi, 2 * np.pi)).pvalue > 1e-3


# Direction bins (θ range, azimuth range relative to ω_t), in degrees.
_BINS = [(10, 40, -45, 45), (40, 75, 135, 225), (30, 70, 60, 120)]


def _in_bin(w, b, phi_t):
    theta = np.degrees(np.arccos(np.clip(w[:, 2], -1, 1)))
    phi = (np.degrees(np.arctan2(w[:, 1], w[:, 0])) - phi_t - b[2]) % 360
    return (theta >= b[0]) & (theta < b[1]) & (phi < b[3] - b[2])


def _sample_bin(b, n, rng, phi_t):
    """Cosine-weighted directions restricted to bin b (sin²θ and φ uniform)."""
    s2 = rng.uniform(np.sin(np.radians(b[0])) ** 2, np.sin(np.radians(b[1])) ** 2, n)
    phi = np.radians(phi_t + rng.uniform(b[2], b[3], n))
    return np.stack([np.sqrt(s2) * np.cos(phi), np.sqrt(s2) * np.sin(phi), np.sqrt(1 - s2)], -1)


def _projected_solid_angle(b):
    s2_lo, s2_hi = np.sin(np.radians(b[0])) ** 2, np.sin(np.radians(b[1])) ** 2
    return np.radians(b[3] - b[2]) * (s2_hi - s2_lo) / 2


@pytest.mark.parametrize("facets", [("lambert", "lambert"), ("lambert", "mirror")])
def test_exact_sawtooth_is_reciprocal(facets):
    """Reciprocity of the real microsurface (all orders): the flux exchanged between
    direction bins A and B, T(A,B) = Π_A · P(exit ∈ B | ω_i ~ cos in A), is symmetric.
    5σ of the two binomial estimates (a uniform instead of cosine Lambertian lobe
    gives ~50σ)."""
    rng = np.random.default_rng(34)
    wp, n = sph(45, 30), 40_000
    phi_t = 30 + 180
    T = np.zeros((3, 3))
    S = np.zeros((3, 3))
    for i, a in enumerate(_BINS):
        wo, _ = sw.trace_paths(_sample_bin(a, n, rng, phi_t), wp, n, rng, *facets)
        for j, b in enumerate(_BINS):
            p = np.mean(_in_bin(wo, b, phi_t))
            T[i, j] = _projected_solid_angle(a) * p
            S[i, j] = _projected_solid_angle(a) * np.sqrt(p * (1 - p) / n)
    for i in range(3):
        for j in range(i):
            assert abs(T[i, j] - T[j, i]) <= 5 * np.hypot(S[i, j], S[j, i]), (i, j, T)
