"""Transmission in the default ``faithful`` model (docs/faithful.md §7): a nested BSDF that
refracts (``dielectric``, ``roughdielectric``, ``thindielectric``, ``principled`` with
``spec_trans``), seen from above the macro surface and from below it (inside the water or glass).

Radiance-mode sample weights of transmitted light carry Mitsuba's radiance scaling 1/η² across
the interface (η = ``bs.eta``, the relative index the sample crossed); the energy tests multiply
it back (weight·η²) to get the share of the light's flux, which is what a lossless interface
keeps. Every seed is fixed.
"""

import math

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from helpers import encode, make_bsdf, make_si, normalmap, np1, np3, sph, vec3

RADIANCE, IMPORTANCE = mi.TransportMode.Radiance, mi.TransportMode.Importance
ROUGH = {
    "glass_0.1": {"type": "roughdielectric", "distribution": "ggx", "alpha": 0.1},
    "glass_0.3": {"type": "roughdielectric", "distribution": "beckmann", "alpha": 0.3},
    "water_0.2": {"type": "roughdielectric", "distribution": "ggx", "alpha": 0.2, "int_ior": 1.33},
}
TRANSMITTING = dict(ROUGH, principled={"type": "principled", "spec_trans": 0.7, "roughness": 0.3,
                                       "base_color": {"type": "rgb", "value": [0.9, 0.8, 0.7]}})


def texel_pair(tilt, phi=0.0):
    """A 2-texel map: the texel tilted by ``tilt`` toward φ and its mirror image (slopes with zero mean)."""
    n = sph(tilt, phi)
    return encode(np.stack([n, [-n[0], -n[1], n[2]]]))


def both_sides(theta, phi=0.0):
    """ω_i at θ from the macro normal, above and below the macro surface."""
    up = sph(theta, phi)
    return [up, up * [1.0, 1.0, -1.0]]


def flux(bsdf, si, seed, n):
    """(mean, standard error) of the sample weights' red channel with transmitted light's radiance
    scaling removed (weight·η² where the sample crossed the macro surface): the flux albedo."""
    rng = np.random.default_rng(seed)
    s1 = mi.Float(rng.random(n).astype(np.float32))
    s2 = mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32))
    bs, w = bsdf.sample(mi.BSDFContext(), si, s1, s2)
    w, eta = np3(w)[:, 0], np1(bs.eta)
    wi_z, wo_z = np3(si.wi)[:, 2], np3(bs.wo)[:, 2]
    y = np.where(wi_z * wo_z < 0, w * eta * eta, w)
    assert np.all(np.isfinite(y)) and np.all(y >= 0)
    return float(y.mean()), float(y.std() / math.sqrt(n))


# -- Energy ------------------------------------------------------------------------------------------


@pytest.mark.parametrize("texels", [2, 1], ids=["pair", "constant"])
@pytest.mark.parametrize("nested", [{"type": "dielectric"}, {"type": "dielectric", "int_ior": 1.33},
                                    {"type": "thindielectric"}], ids=["glass", "water", "thin"])
def test_smooth_lossless_dielectric_keeps_all_the_light_from_both_sides(nested, texels):
    """R + T = 1 ± 1 % (flux) for tilts 0–85° and θ_i 0–89°, toward and away from the tilt, from
    above and from below (total internal reflection included): the light the neighbours block
    is returned (reflected light bounced above the macro surface, transmitted light below it),
    none is lost; on the texel pair (slopes that average to zero) and on the tilted texel alone
    (a constant map: all of its relief is walls, which turn the hidden texel's light around).
    2^14 samples per query; delta lobes, so the weights take few values and the standard error is
    ≤ 0.4 %: 1 % is the acceptance bound, 4σ never reaches it."""
    failures = []
    for k, tilt in enumerate((0.0, 30.0, 60.0, 85.0)):
        bsdf = make_bsdf(nested, texel_pair(tilt)[:texels])
        for theta in (0.0, 45.0, 80.0, 89.0):
            for phi in (0.0, math.pi):
                for wi in both_sides(theta, phi):
                    n = 1 << 14
                    mean, se = flux(bsdf, make_si(np.tile(wi, (n, 1)), texels, np.zeros(n, np.int64)), k, n)
                    if abs(mean - 1.0) > 0.01:
                        failures.append(f"tilt {tilt} θ_i {theta} φ {phi:.2f} wi_z {wi[2]:+.2f}: {mean:.4f} ± {se:.4f}")
    assert not failures, "\n".join(failures)


def nested_flux_max(nested, below, n=1 << 16):
    """max over θ_i ∈ {0, 20, …, 89}° of the nested BSDF's own flux albedo on the flat frame,
    from above or from ``below``."""
    bsdf = mi.load_dict(nested)
    best = 0.0
    for theta in (0.0, 20.0, 40.0, 60.0, 80.0, 89.0):
        wi = both_sides(theta)[1 if below else 0]
        best = max(best, flux(bsdf, make_si(np.tile(wi, (n, 1)), 1), 7, n)[0])
    return best


@pytest.mark.parametrize("nested", list(TRANSMITTING))
def test_rough_dielectric_never_exceeds_the_nested_albedo(nested):
    """The flux albedo (reflection + transmission) stays ≤ the nested BSDF's own largest flux
    albedo on the flat frame (from the same side) + 4 standard errors + 0.3 % (float32 and
    Mitsuba's own sample weights, which differ from its eval/pdf by ~1e-4), over tilts to 85°
    and θ_i to 89°, both azimuths, both sides. (The bound is the largest over θ_i, not the flat
    frame's value at the same θ_i: the facet sees the light at another angle, and a rough
    dielectric loses some of it by itself, by angle: Beckmann α 0.3 glass seen from inside at
    θ_i = 60° keeps 0.882 flat but 0.9996 on a texel tilted 50° away, where the facet sees it at
    10°; measured, 2^15 samples.) The principled's blocked reflected light goes to the fill (it
    ignores type_mask), its transmitted light below the surface."""
    spec = TRANSMITTING[nested]
    failures = []
    for below in (False, True):
        bound = nested_flux_max(spec, below)
        for k, tilt in enumerate((20.0, 50.0, 75.0, 85.0)):
            bsdf = make_bsdf(spec, texel_pair(tilt))
            for theta in (0.0, 60.0, 85.0, 89.0):
                for phi in (0.0, 2.0, math.pi):
                    wi = both_sides(theta, phi)[1 if below else 0]
                    n = 1 << 14
                    mean, se = flux(bsdf, make_si(np.tile(wi, (n, 1)), 2, np.zeros(n, np.int64)), k, n)
                    if mean > bound + 4 * se + 0.003:
                        failures.append(f"below={below} tilt {tilt} θ_i {theta} φ {phi}: {mean:.4f} ± {se:.4f} "
                                        f"> {bound:.4f}")
    assert not failures, "\n".join(failures)


def test_transmitted_light_is_not_dropped():
    """A smooth glass texel seen frontally sends ~95 % of the light through (flux), none of it
    above the macro surface; before, transmission was dropped (mean weight 0.04)."""
    n = 1 << 14
    bsdf = make_bsdf({"type": "dielectric"}, texel_pair(20.0))
    si = make_si(np.tile(sph(10.0), (n, 1)), 2, np.zeros(n, np.int64))
    rng = np.random.default_rng(3)
    bs, w = bsdf.sample(mi.BSDFContext(), si, mi.Float(rng.random(n).astype(np.float32)),
                        mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32)))
    down = np3(bs.wo)[:, 2] < 0
    assert 0.9 < down.mean() < 1.0 and np.all(np3(w)[down, 0] > 0)


def _split_flux(bsdf, wi, seed, n=1 << 15, eta=None):
    """The flux sent above and below the macro surface from ω_i on texel 0 (weight·η² across it),
    each as (mean, standard error). ``eta``: the nested BSDF's η, which every sample that crosses
    the macro surface must report (``bs.eta``: the relative index its radiance scaling is for)."""
    si = make_si(np.tile(wi, (n, 1)), 2, np.zeros(n, np.int64))
    rng = np.random.default_rng(seed)
    bs, w = bsdf.sample(mi.BSDFContext(), si, mi.Float(rng.random(n).astype(np.float32)),
                        mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32)))
    w, eta_s, up = np3(w)[:, 0], np1(bs.eta), np3(bs.wo)[:, 2] > 0
    crossed = (up != (wi[2] > 0)) & (w > 0)
    if eta is not None:
        np.testing.assert_allclose(eta_s[crossed], eta if wi[2] > 0 else 1.0 / eta, rtol=1e-6)
    y = np.where(crossed, w * eta_s * eta_s, w)
    return [(float(x.mean()), float(x.std() / math.sqrt(n))) for x in (y * up, y * ~up)]


def test_reflection_the_neighbours_block_sinks_below_a_texel_seen_from_above():
    """Seen from above at 40°, a smooth water texel tilted 45° away from the camera reflects the
    view 85° off its normal (Fresnel 0.59) toward a direction below the macro plane, into the
    neighbours, which let it through: it sinks below the surface with the refracted light. So the
    only light sent back above is the hidden share's, (1 − V)·F(40°) ≤ F(40°) = 0.024 (bound: F
    + 4 standard errors; measured 0.020). Bounced back up instead, as a reflecting nested BSDF's
    blocked light is, 0.151 of the flux went up. The sunk light crosses the interface: like the
    refracted light, its samples report η = 1.33 and carry the radiance scaling 1/η² (else a path
    would gain η² on its way out)."""
    bsdf = make_bsdf({"type": "dielectric", "int_ior": 1.33}, texel_pair(45.0, math.pi))
    wi = sph(40.0)
    (up, se_up), (down, _) = _split_flux(bsdf, wi, seed=42, eta=1.33 / 1.000277)   # over Mitsuba's air
    f_flat = float(mi.fresnel(mi.Float(math.cos(math.radians(40.0))), 1.33)[0][0])
    assert up <= f_flat + 4 * se_up, (up, f_flat)
    assert abs(up + down - 1.0) < 0.01, up + down


# -- Contracts ---------------------------------------------------------------------------------------


def random_sphere(rng, n, z_min=0.01):
    """Uniform directions with |z| ≥ z_min, both hemispheres."""
    z = rng.uniform(z_min, 1.0, n) * rng.choice([-1.0, 1.0], n)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    r = np.sqrt(1.0 - z * z)
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


@pytest.mark.parametrize("mode", [RADIANCE, IMPORTANCE], ids=["radiance", "importance"])
@pytest.mark.parametrize("nested", list(TRANSMITTING))
def test_sample_eval_pdf_are_consistent_on_both_sides(nested, mode):
    """From either side, in both transport modes (light tracing: the adjoint and its sampler):
    weight = eval/pdf and bs.pdf = pdf(ω_o) for the sampled directions (tolerance 1e-4
    relative: float32, different nested code paths); eval_pdf = (eval, pdf) bit for bit;
    pdf > 0 wherever eval > 0; eval is deterministic; both sides are sampled."""
    rng = np.random.default_rng(21)
    n = 40_000
    wi = random_sphere(rng, n)
    texels = encode(sph(rng.uniform(0, 85, n), rng.uniform(0, 2 * np.pi, n)))
    bsdf = make_bsdf(TRANSMITTING[nested], texels)
    si, ctx = make_si(wi, n), mi.BSDFContext(mode)
    s1 = mi.Float(rng.random(n).astype(np.float32))
    s2 = mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32))
    bs, w = bsdf.sample(ctx, si, s1, s2)
    ok = np1(bs.pdf) > 0
    v, p = bsdf.eval_pdf(ctx, si, bs.wo)
    v, p, w = np3(v), np1(p), np3(w)
    through = (np3(bs.wo)[:, 2] * wi[:, 2] < 0) & ok
    assert ok.mean() > 0.8 and 0.2 < through.mean() and (ok & ~through).mean() > 0.02
    np.testing.assert_allclose(w[ok], v[ok] / p[ok, None], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(np1(bs.pdf)[ok], p[ok], rtol=1e-4, atol=1e-7)
    wo = vec3(random_sphere(rng, n, 0.0))
    v, p = bsdf.eval_pdf(ctx, si, wo)
    np.testing.assert_array_equal(np3(v), np3(bsdf.eval(ctx, si, wo)))
    np.testing.assert_array_equal(np3(v), np3(bsdf.eval(ctx, si, wo)))
    np.testing.assert_array_equal(np1(p), np1(bsdf.pdf(ctx, si, wo)))
    assert not np.any((np3(v).max(1) > 0) & (np1(p) <= 0))
    assert np.all(np.isfinite(np3(v))) and np.all(np3(v) >= 0)


def sampler_adapter(spec, wi, mode):
    """Mitsuba's chi2.BSDFAdapter, except that a sample counts where its pdf > 0: the χ² test
    then compares ``pdf`` with the density of everything ``sample`` draws, the contract. (The
    adjoint sampler's defensive branches draw some directions where eval* is 0, e.g. on the
    hidden texel's neighbours where V(b) = 1: weight 0, pdf > 0; BSDFAdapter drops them.)"""
    plugin, ctx = mi.load_dict(spec), mi.BSDFContext(mode)

    def interaction(n):
        si = dr.zeros(mi.SurfaceInteraction3f, n)
        si.wi, si.uv = wi, mi.Point2f(0.5, 0.5)
        return si

    def sample_func(sample):
        bs, _ = plugin.sample(ctx, interaction(dr.width(sample)), sample[0], mi.Vector2f(sample[1], sample[2]))
        live = bs.pdf > 0
        return dr.select(live, bs.wo, mi.Vector3f(0, 0, 1)), dr.select(live, 1.0, 0.0)

    return sample_func, lambda wo: plugin.pdf(ctx, interaction(dr.width(wo)), wo)


@pytest.mark.parametrize("nested,tilts,mode", [
    ("glass_0.3", (80.0,), RADIANCE),
    ("glass_0.3", (80.0,), IMPORTANCE),
    pytest.param("glass_0.3", (0.0, 40.0), RADIANCE, marks=pytest.mark.slow),
    pytest.param("glass_0.3", (0.0, 40.0), IMPORTANCE, marks=pytest.mark.slow),
    pytest.param("water_0.2", (0.0, 40.0, 80.0), RADIANCE, marks=pytest.mark.slow),
    pytest.param("water_0.2", (0.0, 40.0, 80.0), IMPORTANCE, marks=pytest.mark.slow)],
    ids=["glass-80-radiance", "glass-80-importance", "glass-radiance", "glass-importance", "water-radiance",
         "water-importance"])
def test_sampler_matches_pdf_chi2_over_both_hemispheres(nested, tilts, mode):
    """Pearson χ² (Mitsuba's ChiSquareTest, the whole sphere) of sample() against pdf(), from
    above and from below, θ_i 0/60/85° toward and away from the tilt, in both transport modes
    (light tracing: the adjoint's sampler): overall significance 1 % (Šidák over the tests of
    the case), as the reflection's χ² test (256 rows). The default run takes the steep tilt,
    where most refracted directions land on the wrong side and are folded (2 preimages);
    MFNORMAL_SLOW=1 the others."""
    from mitsuba.chi2 import ChiSquareTest, SphericalDomain
    cases = [(t, th, ph, side) for t in tilts for th in (0.0, 60.0, 85.0)
             for ph in ((0.0,) if th == 0.0 or t == 0.0 else (0.0, math.pi)) for side in (1.0, -1.0)]
    failures = []
    for seed, (tilt, theta_i, phi, side) in enumerate(cases):
        t = math.radians(theta_i)
        wi = mi.Vector3f(math.sin(t) * math.cos(phi), math.sin(t) * math.sin(phi), side * math.cos(t))
        spec = {"type": "normalmap_microfacet", "normalmap": normalmap(texel_pair(tilt)[:1]),
                "bsdf": ROUGH[nested]}
        sample_func, pdf_func = sampler_adapter(spec, wi, mode)
        test = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                             sample_dim=3, sample_count=500_000, res=256, ires=32, seed=1000 + seed)
        if not test.run(0.01, len(cases), quiet=True):
            failures.append(f"{nested} tilt={tilt} θ_i={theta_i} φ={phi:.2f} side={side}: {test.messages}")
    assert not failures, "\n".join(failures)


def test_camera_below_sees_the_mirrored_heightfield():
    """Seen from below, the surface is the heightfield −h: in the mirror frame F(x, y, z) =
    (x, y, −z) the camera is above and the texel normal is (−p_x, −p_y, p_z). With a nested
    BSDF that is the same from both sides (half a ``twosided`` rough conductor, half a smooth
    dielectric, which makes the plugin refract but adds nothing to eval), eval from below at
    (F(ω_i), F(ω_o)) on the texel ω_p equals half the eval of the rough conductor alone from
    above at (ω_i, ω_o) on the texel (−p_x, −p_y, p_z), over random queries with tilts to 85°
    (relative 1e-4: float32; the frames differ by a reflection, under which the isotropic lobe is
    invariant). (The conductor alone: seen from above, a transmitting nested BSDF's blocked
    reflection sinks below the surface,
    :func:`test_reflection_the_neighbours_block_sinks_below_a_texel_seen_from_above`.) Fails if the
    masking, the bounce or the hidden share were those of the unmirrored geometry."""
    conductor = {"type": "twosided", "bsdf": {"type": "roughconductor", "alpha": 0.2}}
    nested = {"type": "blendbsdf", "weight": 0.5, "bsdf_1": {"type": "dielectric"}, "bsdf_0": conductor}
    rng = np.random.default_rng(23)
    n = 20_000
    wp = sph(rng.uniform(0, 85, n), rng.uniform(0, 2 * np.pi, n))
    wi, wo = random_sphere(rng, n, 0.02), random_sphere(rng, n, 0.0)
    wi[:, 2], wo[:, 2] = np.abs(wi[:, 2]), np.abs(wo[:, 2])
    flip = np.array([1.0, 1.0, -1.0])
    below = np3(make_bsdf(nested, encode(wp)).eval(mi.BSDFContext(), make_si(wi * flip, n), vec3(wo * flip)))
    above = 0.5 * np3(make_bsdf(conductor, encode(wp * [-1.0, -1.0, 1.0])).eval(mi.BSDFContext(), make_si(wi, n),
                                                                              vec3(wo)))
    assert np.count_nonzero(above[:, 0] > 0) > n // 2
    np.testing.assert_allclose(below, above, rtol=1e-4, atol=1e-6)


@pytest.mark.parametrize("nested", list(ROUGH))
def test_light_tracing_eval_is_the_adjoint_on_both_sides(nested):
    """eval in Importance mode (si.wi = the light side a, wo = the camera side b, either side)
    equals eval in Radiance mode with the roles swapped, times |⟨b,ω_g⟩|/|⟨a,ω_g⟩| (Veach's
    adjoint: it carries the η² radiance scaling across the interface; relative 1e-5)."""
    rng = np.random.default_rng(24)
    n = 20_000
    a, b = random_sphere(rng, n), random_sphere(rng, n)
    texels = encode(sph(rng.uniform(0, 85, n), rng.uniform(0, 2 * np.pi, n)))
    bsdf = make_bsdf(ROUGH[nested], texels)
    imp = np3(bsdf.eval(mi.BSDFContext(IMPORTANCE), make_si(a, n), vec3(b)))
    rad = np3(bsdf.eval(mi.BSDFContext(RADIANCE), make_si(b, n), vec3(a)))
    assert np.count_nonzero((a[:, 2] * b[:, 2] < 0) & (rad[:, 0] > 0)) > n // 40     # transmission is compared
    np.testing.assert_allclose(imp, rad * np.abs(b[:, 2] / a[:, 2])[:, None], rtol=1e-5, atol=1e-7)


def test_transmission_derivatives_match_finite_differences():
    """d/d strength, d/d texel, d/dα and d/dη of eval (and d/d strength, d/d texel of pdf) for
    light the facet transmits (ω_o on the far side from ω_i, both sides, 2^16 queries on four
    tilted texels of a GGX α 0.3 glass):
    forward = reverse = FD (tests/gradients.py: within 4 paired standard errors + 3 %; the FD
    averaged over nine steps about h = 1e-3), and each derivative resolved (|FD| > 4 SE) except
    the pdf's by a texel (measured: FD −0.0026 ± 0.0010 paired, AD −0.0009; 2^16 queries do not
    resolve it, the agreement is still checked)."""
    import gradients as G
    from helpers import make_si as si_of

    texels = encode(np.array([sph(30, 0.3), sph(50, 0.8), sph(15, -0.4), sph(40, 2.5)]).reshape(-1, 3))
    b = make_bsdf({"type": "roughdielectric", "distribution": "ggx", "alpha": 0.3}, texels)
    rng = np.random.default_rng(25)
    n = 1 << 16
    wi = random_sphere(rng, n, 0.05)
    wo = random_sphere(rng, n, 0.05)
    wo[:, 2] = -np.sign(wi[:, 2]) * np.abs(wo[:, 2])
    si, u = si_of(wi, 4, p_index=np.arange(n)), rng.random((n, 3)).astype(np.float32)
    keys = [k for k in mi.traverse(b).keys()]
    failures = []
    for what, key in [("eval", "strength"), ("eval", ("texel", 1, 1)), ("eval", "nested_bsdf.alpha.value"),
                      ("eval", "nested_bsdf.eta"), ("pdf", "strength"), ("pdf", ("texel", 1, 1))]:
        if isinstance(key, str) and key not in keys:
            failures.append(f"{key} not traversed: {keys}")
            continue
        c = G.check(b, key, si, vec3(wo), u, 1e-3, what, steps=G.STEPS)
        print(f"transmission {what} {key}: {c}")
        resolved = abs(c.fd) > 4 * c.se or (what, key) == ("pdf", ("texel", 1, 1))
        if not (c.agrees() and resolved):
            failures.append(f"{what} {key}: {c}")
    assert not failures, "\n".join(failures)


def test_eval_is_deterministic_and_smooth_on_both_sides():
    """As the reflection's test (test_faithful.py), with ω_i and ω_o on the whole sphere and
    every transmitting nested BSDF here: the same query gives the same value, and jittering ω_i
    by 1e-4 rad changes eval by < 1e-2 relative for 99.9 % of 20 000 queries (tilts to 85°) and
    by < 3e-2 for all, continuously (measured: 99.9th percentile 0.002–0.003, largest 0.021)."""
    from helpers import assert_deterministic_and_smooth
    rng = np.random.default_rng(13)
    n = 20_000
    wi, wo = random_sphere(rng, n, 0.05), random_sphere(rng, n, 0.05)
    texels = encode(sph(rng.uniform(0, 85, n), rng.uniform(0, 2 * np.pi, n)))
    for name, nested in TRANSMITTING.items():
        assert_deterministic_and_smooth(make_bsdf(nested, texels), wi, wo, rng, name)


@pytest.mark.parametrize("nested", ["glass_0.3", "principled"])
def test_packet_skipping_gives_the_same_values_on_both_sides(nested):
    """Model.eval_pdf with its terms skipped per SIMD packet (gated=True) equals the straight-line
    one bit for bit with a transmitting nested BSDF, on packets of 16 lanes that share a texel
    and ω_i (either side) with random ω_o on the whole sphere."""
    rng = np.random.default_rng(26)
    groups, width = 2048, 16
    texels = encode(sph(rng.uniform(0, 40, groups), rng.uniform(0, 2 * np.pi, groups)))
    wi = np.repeat(random_sphere(rng, groups, 0.02), width, axis=0)
    wo = vec3(random_sphere(rng, groups * width, 0.0))
    bsdf = make_bsdf(TRANSMITTING[nested], texels)
    si = make_si(wi, groups, texel_index=np.repeat(np.arange(groups), width))
    sp = bsdf.shading_point(mi.BSDFContext(), si)
    tx = bsdf.model.core.texel(sp, sp.wi)
    straight = bsdf.model.core.eval_pdf(sp, tx, wo, mi.Bool(True), gated=False)
    gated = bsdf.model.core.eval_pdf(sp, tx, wo, mi.Bool(True), gated=True)
    for x, y in zip(straight, gated):
        np.testing.assert_array_equal(np.array(x), np.array(y))
    assert np.count_nonzero(np1(straight[1])) > groups * width // 4


def test_no_nan_for_bad_texels_and_directions_on_both_sides():
    """NaN/Inf/zero texels, normals below the horizon and directions on, near and below the
    horizon give finite, non-negative values and samples with a transmitting nested BSDF
    (smooth, rough, principled; with ``macro_normal="geometric"`` too), in both transport modes."""
    bad = np.array([[np.nan, 0.5, 1.0], [np.inf, 0.5, 0.5], [0.5, 0.5, 0.5], [0.5, 0.5, 0.0],
                    [1.0, 0.5, 0.5], [0.0, 0.0, 0.0], [0.9, 0.5, 0.55]], np.float32)
    rng = np.random.default_rng(27)
    n = 6000
    wi = np.concatenate([random_sphere(rng, n - 5, 0.0), [[1, 0, 0], [0, 0, -1], [0.6, 0, 1e-7], [0.6, 0, -1e-7],
                                                         [0, 0, 0]]])
    for nested in [{"type": "dielectric"}, ROUGH["glass_0.1"], TRANSMITTING["principled"]]:
        for extra in ({}, {"macro_normal": "geometric"}):
            bsdf = make_bsdf(nested, bad, **extra)
            si = make_si(wi, len(bad))
            for mode in (RADIANCE, IMPORTANCE):
                ctx = mi.BSDFContext(mode)
                v, p = bsdf.eval_pdf(ctx, si, vec3(random_sphere(rng, n, 0.0)))
                s1 = mi.Float(rng.random(n).astype(np.float32))
                s2 = mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32))
                bs, w = bsdf.sample(ctx, si, s1, s2)
                for arr in (np3(v), np1(p), np3(w), np1(bs.pdf), np3(bs.wo)):
                    assert np.all(np.isfinite(arr)), (nested["type"], extra, mode)
                assert np.all(np3(v) >= 0) and np.all(np3(w) >= 0) and np.all(np1(p) >= 0)


# -- Path tracing = light tracing --------------------------------------------------------------------


def tilted_bumps(tilt):
    """The bumps map (tilts to ~65°) with every slope moved by that of a ``tilt`` toward +x: its slopes
    average to tan(tilt), so part of its relief is walls (docs/faithful.md §7); RGB in [0, 1]."""
    from helpers import bumps_normalmap
    if tilt == 0.0:
        return bumps_normalmap(64, 3)
    n = bumps_normalmap(64, 3).astype(np.float64) * 2.0 - 1.0
    sx, sy = -n[..., 0] / n[..., 2] - math.tan(math.radians(tilt)), -n[..., 1] / n[..., 2]
    n = np.stack([-sx, -sy, np.ones_like(sx)], -1)
    return encode(n / np.linalg.norm(n, axis=-1, keepdims=True)).astype(np.float32)


def refraction_scene(integrator, nested, camera_below, tilt=0.0):
    """A normal-mapped glass plane (bumps, tilts to ~65°, at z = 0; with ``tilt``, :func:`tilted_bumps`)
    with an area light on one side and a grey floor on the other, which the camera, between the
    plane and the floor, sees lit through the plane (light tracing reaches the camera through a
    delta lobe only that way)."""
    s = -1.0 if camera_below else 1.0           # the camera's and the floor's side
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": 4},
        "sensor": {"type": "perspective", "fov": 60,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, -0.9, 0.25 * s], target=[0, 0.3, 0.6 * s],
                                                              up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 24, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "glass": {"type": "rectangle",
                  "bsdf": {"type": "normalmap_microfacet", "bsdf": nested,
                           "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(tilted_bumps(tilt)),
                                         "raw": True}}},
        "floor": {"type": "rectangle", "to_world": mi.ScalarTransform4f().translate([0, 0, 0.6 * s]).scale(3.0),
                  "bsdf": {"type": "twosided", "bsdf": {"type": "diffuse"}}},
        "light": {"type": "rectangle",
                  "to_world": mi.ScalarTransform4f().translate([0.2, 0.3, -1.0 * s]).rotate(
                      [1, 0, 0], 180.0 if camera_below else 0.0).scale(0.8),
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 6.0}}}})


@pytest.mark.parametrize("tilt", [0.0, 60.0], ids=["bumps", "tilted_bumps"])
@pytest.mark.parametrize("camera_below", [True, False], ids=["camera_below", "camera_above"])
@pytest.mark.parametrize("nested", [{"type": "roughdielectric", "alpha": 0.2}, {"type": "dielectric"}],
                         ids=["rough", "smooth"])
def test_path_tracing_equals_light_tracing_through_a_refracting_surface(nested, camera_below, tilt):
    """Light tracing (Mitsuba's ptracer: the adjoint and its sampler) gives path tracing's image
    through a normal-mapped glass plane, seen from either side, the light on the other: the
    radiance scaling across the interface and the delta lobes' path weights included; on the
    bumps tilted 60° (:func:`tilted_bumps`: about half of their relief is walls) the walls' share of
    the hidden texel's light, mirrored, too. 8 renders × 128 spp of each; on 4×4-pixel blocks,
    Welch's t test of the difference: no block
    below the Šidák-corrected 1 % family-wise level; and the image means agree within 2 %
    (the smooth glass's caustics on the floor are noisy in path tracing)."""
    from helpers import light_tracing_agrees
    n = 8
    imgs = {k: np.array([np.array(mi.render(refraction_scene(k, nested, camera_below, tilt), spp=128, seed=s))
                         for s in range(n)]) for k in ("path", "ptracer")}
    p_values, z, ratio = light_tracing_agrees(imgs)
    print(f"\n{nested['type']} camera_below={camera_below} tilt={tilt}: mean path {imgs['path'].mean():.4f}, "
          f"ptracer/path {ratio:.4f}, min p {p_values.min():.3g}, max |z| {z.max():.2f}")
    assert len(p_values) > 20
    assert p_values.min() > 1.0 - 0.99 ** (1.0 / len(p_values)), (p_values.min(), z.max())
    assert abs(ratio - 1.0) < 0.02, ratio


@pytest.mark.parametrize("tilt", [20.0, 50.0])
def test_a_normal_mapped_smooth_glass_sphere_is_white_in_the_furnace(tilt):
    """A smooth glass sphere (ior 1.5) with the map baked from a bumpy sphere (validation.furnace_glass,
    max tilt 20° and 50°), in a constant environment 1, ``path`` at depth 64: invisible, as the true
    bumpy sphere is (every pixel 1). Mean 1 ± 1 %, at most 1 % of the pixels off by more than 5 %
    (24² px, 64 spp: one path lost in a pixel moves it by 1.6 %; measured 0.9985 and 0.2 % at 20°
    (a few paths still inside at depth 64; 1.0000 at depth 256), 1.0000 and 0 % at 50°). Classic
    normal mapping renders 0.91 and 0.52 here (validation/results/furnace_glass.md)."""
    from validation import furnace_glass as F
    from validation import heightfield as H
    res, mask = 24, F.sphere_mask(24)
    bsdf = H.method_from_spec("faithful").bsdf(F.GLASS["smooth_glass"], F.sphere_map(tilt))
    img, nonfinite, negative = F.render_sphere(bsdf, res, 64, seed=1)
    m = F.furnace_metrics(img, 1.0, mask)
    assert abs(m["mean"] - 1.0) < 0.01 and m["off_5"] <= 0.01, m
    assert nonfinite == negative == 0


@pytest.mark.parametrize("neighbourhood", [0.0, 8.0])
@pytest.mark.parametrize("tilt", [5.0, 30.0, 60.0])
def test_a_smooth_glass_sphere_under_a_constant_tilt_is_white_in_the_furnace(tilt, neighbourhood):
    """The sphere of the test above with a map tilted the same way everywhere (every texel ``tilt``
    toward dp/du: validation.furnace_glass.constant_map), map-wide and local statistics: white
    (mean 1 ± 1 %, at most 3 % of the pixels off by more than 5 %; 24² px, 64 spp, depth 64).
    Such a map's slopes average to the tilt: it is a sawtooth, whose walls hide its facets and turn
    light around (docs/faithful.md §7). Taken as a tilted plane (local statistics before the walls:
    k = 0) each hit inside reflects about the same tilted normal and the light circles at total
    internal reflection: the sphere rendered 0.92, 0.44 and 0.48 at 5°, 30° and 60° (with
    ``neighbourhood`` 0, whose hidden texel's neighbours did not turn it around: 1.000, 0.78, 0.72)."""
    from validation import furnace_glass as F
    from validation import heightfield as H
    res, mask = 24, F.sphere_mask(24)
    spec = "faithful" if neighbourhood == 8.0 else f"plugin:faithful,neighbourhood={neighbourhood:g}"
    bsdf = H.method_from_spec(spec).bsdf(F.GLASS["smooth_glass"], F.constant_map(tilt))
    img, nonfinite, negative = F.render_sphere(bsdf, res, 64, seed=2)
    m = F.furnace_metrics(img, 1.0, mask)
    print(f"\ntilt {tilt} neighbourhood {neighbourhood}: {m}")
    assert abs(m["mean"] - 1.0) < 0.01 and m["off_5"] <= 0.03, m
    assert nonfinite == negative == 0
