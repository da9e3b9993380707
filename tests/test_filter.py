"""Tests of ``filter="lean"``: the default model reading the pixel's footprint from the map's
slope-moment pyramid (src/mfnormal/normals/normal_map.py ``NormalMap.footprint``) and the nested
rough conductor widened by it (src/mfnormal/plugins/widened.py).

References are independent of the code under test: the footprint's facet from numpy over the
texels, the widened lobe from Mitsuba's ``roughconductor`` at α' with albedos integrated here,
the sampler against the pdf (χ²), derivatives against central differences of re-built maps.
Every seed is fixed.
"""

import math
import warnings

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from helpers import WHITE, encode, np1, np3, random_hemisphere, sph, vec3

from mfnormal.normals.normal_map import FILTER_TAIL
from mfnormal.normals.pyramid import CLASS_BOUNDS
from mfnormal.plugins import widened

GOLD = {"type": "roughconductor", "material": "Au", "alpha": 0.1}
WHITE_BECKMANN = {"type": "roughconductor", "distribution": "beckmann", "alpha": 0.15,
                  "specular_reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}
WHITE_GGX = dict(WHITE_BECKMANN, distribution="ggx", alpha=0.08)
BLOCK, SIZE = 8, 64         # a random 8 × 8 block of texels, tiled over a 64 × 64 map
RADIANCE, IMPORTANCE = mi.TransportMode.Radiance, mi.TransportMode.Importance


def block_texels(seed=0, steep_share=0.3, mild_max=0.12):
    """A random BLOCK² block of unit normals (RGB, OpenGL): mild slopes (|s| ≤ ``mild_max``) and, for
    ``steep_share`` of them, steep ones (|s| 0.4-1.5), tiled to SIZE²: every level of the pyramid
    above the block holds the block's moments, wherever it is read."""
    rng = np.random.default_rng(seed)
    n = BLOCK * BLOCK
    slope = np.where(rng.random(n) < steep_share, rng.uniform(0.4, 1.5, n), rng.uniform(0.0, mild_max, n))
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.stack([slope * np.cos(phi), slope * np.sin(phi)], -1)
    normal = np.concatenate([-s, np.ones((n, 1))], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    block = encode(normal).reshape(BLOCK, BLOCK, 3)
    return np.tile(block, (SIZE // BLOCK, SIZE // BLOCK, 1)).astype(np.float32)


def texture(texels):
    return {"type": "bitmap", "bitmap": mi.Bitmap(texels), "raw": True, "filter_type": "nearest"}


def plugin(texels, nested, filter="lean", **params):
    return mi.load_dict({"type": "normalmap_microfacet", "normalmap": texture(texels), "bsdf": nested,
                         "filter": filter, **params})


def queries(wi, texel_xy, width_texels):
    """Interactions at the centres of texels ``texel_xy`` (k×2), seen from ``wi`` (k×3), each with a
    square footprint ``width_texels`` wide."""
    k = len(wi)
    si = dr.zeros(mi.SurfaceInteraction3f, k)
    si.wi = vec3(np.asarray(wi, np.float64))
    si.uv = mi.Point2f(*(((np.asarray(texel_xy, np.float64)[:, i] + 0.5) / SIZE).astype(np.float32) for i in (0, 1)))
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    si.n = mi.Normal3f(0, 0, 1)
    d = np.full(k, width_texels / SIZE, np.float32)
    si.duv_dx = mi.Vector2f(d, np.zeros(k, np.float32))
    si.duv_dy = mi.Vector2f(np.zeros(k, np.float32), d)
    return si


def decoded_slopes(texels):
    """The slopes of the texels as the plugin decodes them (2·rgb − 1, normalised)."""
    n = texels.reshape(-1, 3).astype(np.float64) * 2.0 - 1.0
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return -n[:, :2] / n[:, 2:3]


# -- The footprint's facet -------------------------------------------------------------------------


def test_the_footprints_facet_is_the_mean_slope_and_spread_of_its_texels_of_the_same_class():
    """At a footprint of BLOCK texels (the pyramid's level 3 exactly), a flat or mild texel reads
    its block's texels of its class (numpy over the block: mean slope, var(s_x) + var(s_y)) where
    their Gaussian keeps within the class's bound, and the texel itself elsewhere; a steep texel,
    and any texel under a footprint of one texel or none, reads itself (1e-5)."""
    kept_blocks = []
    for seed, steep_share, mild_max in ((0, 0.3, 0.12), (1, 0.0, 0.12), (2, 0.6, 0.12), (3, 0.1, 0.28)):
        texels = block_texels(seed, steep_share, mild_max)
        bsdf = plugin(texels, WHITE)
        s = decoded_slopes(texels[:BLOCK, :BLOCK])
        s2 = np.sum(s * s, 1)
        cls = np.where(s2 < CLASS_BOUNDS[0] ** 2, 0, np.where(s2 < CLASS_BOUNDS[1] ** 2, 1, 2))
        own = np.concatenate([-s, np.ones((len(s), 1))], 1)
        own /= np.linalg.norm(own, axis=-1, keepdims=True)
        facet, spread, kept = own.copy(), np.zeros(len(s)), np.zeros(len(s), bool)
        for c, bound in enumerate(CLASS_BOUNDS):
            mine = cls == c
            if not mine.any():
                continue
            mean, var = s[mine].mean(0), s[mine].var(0).sum()
            ok = var * FILTER_TAIL <= (bound - np.linalg.norm(mean)) ** 2
            kept[mine] = ok
            if ok:
                facet[mine] = np.append(-mean, 1.0) / np.linalg.norm(np.append(-mean, 1.0))
                spread[mine] = var
        kept_blocks.append(bool(kept[cls == 1].all()))
        assert np.any(cls == 0) and np.any(cls == 1)
        xy = np.stack(np.meshgrid(np.arange(BLOCK), np.arange(BLOCK)), -1).reshape(-1, 2) + BLOCK * 2
        for width, filtered in ((BLOCK, True), (1.0, False), (0.0, False)):
            w, v = bsdf.source.footprint(queries(np.tile([0.0, 0.0, 1.0], (len(xy), 1)), xy, width))
            np.testing.assert_allclose(np3(w), facet if filtered else own, atol=1e-5,
                                       err_msg=f"seed {seed}, width {width}")
            np.testing.assert_allclose(np1(v), spread if filtered else 0.0, atol=1e-5)
    assert kept_blocks == [True, True, True, False]     # (a mild spread too wide for the bound is not filtered)
    # The classes' pyramid: 10 channels over a third of the texels, 1.11× a 3-channel map's floats.
    assert bsdf.source.pyramid(classes=True).memory_ratio() == pytest.approx(10 * 1365 / (3 * SIZE * SIZE))


def test_without_a_footprint_the_filter_changes_nothing():
    """eval, pdf and sample with ``filter="lean"`` equal ``filter="none"``'s bit for bit where the
    footprint is at most a texel wide (none, or half a texel), for a widened conductor and a
    diffuse nested BSDF."""
    texels = block_texels(3)
    rng = np.random.default_rng(5)
    k = 4096
    wi, wo = random_hemisphere(rng, k, 0.05), random_hemisphere(rng, k, 0.05)
    xy = rng.integers(0, SIZE, (k, 2))
    s1, s2 = mi.Float(rng.random(k)), mi.Point2f(rng.random(k), rng.random(k))
    ctx = mi.BSDFContext()
    for nested in (GOLD, WHITE):
        a, b = plugin(texels, nested, "none"), plugin(texels, nested, "lean")
        for width in (0.0, 0.5):
            si = queries(wi, xy, width)
            for x, y in zip(a.eval_pdf(ctx, si, vec3(wo)), b.eval_pdf(ctx, si, vec3(wo))):
                np.testing.assert_array_equal(np.array(x), np.array(y))
            (bs_a, w_a), (bs_b, w_b) = a.sample(ctx, si, s1, s2), b.sample(ctx, si, s1, s2)
            np.testing.assert_array_equal(np3(bs_a.wo), np3(bs_b.wo))
            np.testing.assert_array_equal(np3(w_a), np3(w_b))


# -- The widened nested lobe -----------------------------------------------------------------------


@pytest.mark.parametrize("nested,made", [
    (GOLD, True), (WHITE_BECKMANN, True), (WHITE_GGX, True),
    ({"type": "roughconductor", "alpha_u": 0.1, "alpha_v": 0.2}, False),
    ({"type": "roughdielectric", "alpha": 0.1}, False), ({"type": "roughplastic"}, False), (WHITE, False),
    ({"type": "roughconductor", "alpha": {"type": "bitmap", "bitmap": mi.Bitmap(np.full((2, 2, 1), 0.2, np.float32))}},
     False)])
def test_a_twin_is_made_for_a_rough_conductor_with_one_uniform_alpha(nested, made):
    assert (widened.twin(mi.load_dict(nested)) is not None) == made


def white_albedo(distribution, alpha, mu, n=1 << 18, seed=0):
    """∫ f·cos dω_o of a white Mitsuba ``roughconductor`` at cosine ``mu``: the mean of its sample
    weights over n independent uniform samples drawn here."""
    bsdf = mi.load_dict({"type": "roughconductor", "distribution": distribution, "alpha": alpha,
                         "specular_reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}})
    rng = np.random.default_rng(seed)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(math.sqrt(1 - mu * mu), 0.0, mu)
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    _, w = bsdf.sample(mi.BSDFContext(), si, mi.Float(rng.random(n)), mi.Point2f(rng.random(n), rng.random(n)))
    return float(np3(w)[:, 0].mean())


@pytest.mark.parametrize("nested", [WHITE_BECKMANN, WHITE_GGX])
def test_the_twin_is_the_conductor_at_the_widened_alpha_with_the_albedo_kept(nested):
    """At a query carrying the spread v, the twin's value is Mitsuba's roughconductor at
    α' = √(α² + v) times E(μ_i, α)/E(μ_i, α'), E the white albedo integrated here (2^18 samples,
    standard error < 0.1 %): 1.5 % (the twin's table is bilinear in μ and α), and its pdf is that
    conductor's (1e-5); so its white albedo at μ_i is the nested BSDF's own (sampled: 1.5 %)."""
    twin = widened.twin(mi.load_dict(nested))
    alpha, dist = nested["alpha"], nested["distribution"]
    rng = np.random.default_rng(2)
    k = 2048
    for mu, v in ((0.9, 0.01), (0.5, 0.04), (0.2, 0.09)):
        wide = math.sqrt(alpha * alpha + v)
        ref = mi.load_dict(dict(nested, alpha=wide))
        gain = white_albedo(dist, alpha, mu) / white_albedo(dist, wide, mu)
        si = dr.zeros(mi.SurfaceInteraction3f, k)
        si.wi = mi.Vector3f(math.sqrt(1 - mu * mu), 0.0, mu)
        si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
        si.duv_dx = mi.Vector2f(v, 0.0)
        wo = vec3(random_hemisphere(rng, k, 0.05))
        got, pdf = twin.eval_pdf(mi.BSDFContext(), si, wo)
        want, want_pdf = ref.eval_pdf(mi.BSDFContext(), si, wo)
        np.testing.assert_allclose(np1(pdf), np1(want_pdf), rtol=1e-5, atol=1e-6)
        keep = np3(want)[:, 0] > 1e-3 * np3(want)[:, 0].max()
        np.testing.assert_allclose(np3(got)[keep, 0] / np3(want)[keep, 0], gain, rtol=0.015)
        n = 1 << 18
        si_n = dr.zeros(mi.SurfaceInteraction3f, n)
        si_n.wi = mi.Vector3f(math.sqrt(1 - mu * mu), 0.0, mu)
        si_n.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
        si_n.duv_dx = mi.Vector2f(v, 0.0)
        _, w = twin.sample(mi.BSDFContext(), si_n, mi.Float(rng.random(n)), mi.Point2f(rng.random(n), rng.random(n)))
        assert float(np3(w)[:, 0].mean()) == pytest.approx(white_albedo(dist, alpha, mu, seed=9), rel=0.015)


# -- The model with a footprint --------------------------------------------------------------------


def test_white_furnace_with_a_footprint():
    """White Lambertian facets, footprints of 8 texels over a map of mild and steep texels (the
    mild ones on the footprint's facet, the steep ones as they are): every sample weight's mean
    1 ± 1 % from 48 random (texel, ω_i) pairs, 2^13 samples each; and a white Beckmann conductor
    keeps its unfiltered albedo: the filtered mean over the same pairs within 1 % of the
    unfiltered model's at the same texels (its facets' spread kept out of the albedo)."""
    texels = block_texels(4, steep_share=0.2)
    rng = np.random.default_rng(6)
    pairs, per = 48, 1 << 13
    xy = np.repeat(rng.integers(0, SIZE, (pairs, 2)), per, axis=0)
    wi = np.repeat(random_hemisphere(rng, pairs, z_min=0.05), per, axis=0)
    si = queries(wi, xy, BLOCK)
    s1 = mi.Float(rng.random(pairs * per))
    s2 = mi.Point2f(rng.random(pairs * per), rng.random(pairs * per))
    _, w = plugin(texels, WHITE).sample(mi.BSDFContext(), si, s1, s2)
    means = np3(w)[:, 0].reshape(pairs, per).mean(1)
    assert np.all(np.abs(means - 1.0) < 0.01), means
    filtered = plugin(texels, WHITE_BECKMANN).sample(mi.BSDFContext(), si, s1, s2)[1]
    plain = plugin(texels, WHITE_BECKMANN, "none").sample(mi.BSDFContext(), si, s1, s2)[1]
    assert np3(filtered)[:, 0].mean() == pytest.approx(np3(plain)[:, 0].mean(), rel=0.01)


@pytest.mark.parametrize("nested", ["gold", "white"])
def test_sampler_matches_pdf_chi2_with_a_footprint(nested):
    """Pearson χ² (Mitsuba's ChiSquareTest) of sample() against pdf() with ``filter="lean"`` at a
    footprint of 8 texels, on a filtered mild texel, on a steep one and at three θ_i: overall
    significance 1 % (Šidák over the 6 tests)."""
    from mitsuba.chi2 import ChiSquareTest, SphericalDomain
    texels = block_texels(0)
    s = decoded_slopes(texels[:BLOCK, :BLOCK])
    mild = np.flatnonzero(np.sum(s * s, 1) < 0.04)[0]
    steep = np.flatnonzero(np.sum(s * s, 1) > 0.5)[0]
    bsdf = plugin(texels, GOLD if nested == "gold" else WHITE)
    failures = []
    for seed, (texel, theta) in enumerate((t, th) for t in (mild, steep) for th in (0.0, 50.0, 80.0)):
        xy = np.array([[texel % BLOCK, texel // BLOCK]])
        wi = sph(theta, 0.3)[None]

        def at(n):
            si = queries(np.repeat(wi, n, 0), np.repeat(xy, n, 0), BLOCK)
            return si

        def sample_func(sample):
            n = dr.width(sample)
            bs, w = bsdf.sample(mi.BSDFContext(), at(n), sample[0], mi.Point2f(sample[1], sample[2]))
            ok = (w[0] > 0) | (w[1] > 0) | (w[2] > 0)
            return dr.select(ok, bs.wo, mi.Vector3f(0, 0, 1)), dr.select(ok, 1.0, 0.0)

        def pdf_func(wo):
            return bsdf.pdf(mi.BSDFContext(), at(dr.width(wo)), wo)
        test = ChiSquareTest(domain=SphericalDomain(), sample_func=sample_func, pdf_func=pdf_func,
                             sample_dim=3, sample_count=400_000, res=128, ires=32, seed=seed)
        if not test.run(0.01, 6, quiet=True):
            failures.append(f"texel {texel} θ_i={theta}: {test.messages}")
    assert not failures, "\n".join(failures)


def test_light_tracing_sees_the_adjoint_with_a_footprint():
    """eval in Importance mode equals eval in Radiance mode with the roles swapped, times
    ⟨b,ω_g⟩/⟨a,ω_g⟩, at filtered queries (the footprint does not depend on the directions)."""
    texels = block_texels(7)
    rng = np.random.default_rng(8)
    k = 8192
    a, b = random_hemisphere(rng, k, 0.02), random_hemisphere(rng, k, 0.02)
    xy = rng.integers(0, SIZE, (k, 2))
    bsdf = plugin(texels, GOLD)
    imp = np3(bsdf.eval(mi.BSDFContext(IMPORTANCE), queries(a, xy, BLOCK), vec3(b)))
    rad = np3(bsdf.eval(mi.BSDFContext(RADIANCE), queries(b, xy, BLOCK), vec3(a)))
    np.testing.assert_allclose(imp, rad * (b[:, 2] / a[:, 2])[:, None], rtol=1e-5, atol=1e-7)


def test_texel_derivatives_through_the_pyramid_match_central_differences():
    """∂eval/∂texel at filtered queries (footprint 8 texels, a conductor and a diffuse nested BSDF),
    forward mode through the mild pyramid, against central differences of maps rebuilt with the
    texel moved by ±3e-3 (its value in every tile; at 1e-3 float32 rounding of the diffuse
    values reaches 2e-5 of their differences): 2 % or 1e-4 of the largest, but for at most
    8 of the 256 queries (kinks, below), which are within 1 % of the largest."""
    texels = block_texels(0, steep_share=0.0)
    rng = np.random.default_rng(10)
    k = 256
    xy = rng.integers(0, SIZE, (k, 2))
    wi, wo = random_hemisphere(rng, k, 0.3), random_hemisphere(rng, k, 0.3)
    for nested in (GOLD, WHITE):
        bsdf = plugin(texels, nested)
        params = mi.traverse(bsdf)
        data = mi.TensorXf(texels)
        dr.enable_grad(data)
        params["normalmap.data"] = data
        params.update()
        s = decoded_slopes(texels[:BLOCK, :BLOCK])
        y, x = divmod(int(np.flatnonzero(np.hypot(s[:, 0], s[:, 1]) > 0.05)[0]), BLOCK)     # a mild texel
        step = np.zeros_like(texels)
        step[y::BLOCK, x::BLOCK, 0] = 1.0      # its red channel, in every tile
        value = bsdf.eval(mi.BSDFContext(), queries(wi, xy, BLOCK), vec3(wo))
        dr.set_grad(data, mi.TensorXf(step))
        dr.forward_to(value)
        ad = np3(dr.grad(value))[:, 1]
        h = 3e-3
        fd = []
        for sign in (1, -1):
            plain = plugin(texels + sign * h * step, nested)
            fd.append(np3(plain.eval(mi.BSDFContext(), queries(wi, xy, BLOCK), vec3(wo)))[:, 1])
        fd = (fd[0] - fd[1]) / (2 * h)
        scale = np.abs(fd).max()
        assert scale > 0 and np.count_nonzero(np.abs(fd) > 1e-2 * scale) > k // 10    # (derivatives to check)
        off = np.abs(ad - fd) > 0.02 * np.abs(fd) + 1e-4 * scale + 1e-6
        # (A central difference that straddles a kink, e.g. of the albedo table, bilinear in μ and
        # α', reads the mean of the slopes on either side: 1-5 queries in 256 here, within 1 % of
        # the scale. Derivatives lost through the pyramid would miss most of the queries.)
        assert np.count_nonzero(off) <= 8, (nested, scale, np.flatnonzero(off), ad[off], fd[off])
        assert np.all(np.abs(ad - fd) <= 0.02 * np.abs(fd) + 1e-2 * scale)


# -- Parameters ------------------------------------------------------------------------------------


def test_filter_refuses_other_models_and_maps_and_warns_for_other_nested_bsdfs():
    texels = block_texels(0)
    with pytest.raises((ValueError, RuntimeError), match="filter='lean' needs model=\"faithful\""):
        plugin(texels, WHITE, model="analytic")
    with pytest.raises((ValueError, RuntimeError), match="needs a 'normalmap'"):
        mi.load_dict({"type": "normalmap_microfacet", "heightmap": texture(texels[..., :1].copy()),
                      "bsdf": WHITE, "filter": "lean"})
    with pytest.raises((ValueError, RuntimeError), match="unknown filter 'box'"):
        plugin(texels, WHITE, filter="box")
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        bsdf = plugin(texels, {"type": "roughplastic"})
    assert any("RoughPlastic is shaded per texel" in str(w.message) for w in caught)
    assert bsdf.twin is None and not bsdf.source.filtered


def test_updates_rebuild_the_mild_pyramid_and_the_twin_follows_the_nested_alpha():
    """After ``mi.traverse`` updates of the map and of the nested BSDF's alpha, filtered queries
    equal those of a plugin loaded with the new values (1e-6)."""
    a, b = block_texels(0), block_texels(1)
    rng = np.random.default_rng(11)
    k = 1024
    xy = rng.integers(0, SIZE, (k, 2))
    wi, wo = random_hemisphere(rng, k, 0.1), random_hemisphere(rng, k, 0.1)
    bsdf = plugin(a, GOLD)
    params = mi.traverse(bsdf)
    params["normalmap.data"] = mi.TensorXf(b)
    params["nested_bsdf.alpha.value"] = 0.2
    params.update()
    fresh = plugin(b, dict(GOLD, alpha=0.2))
    si = queries(wi, xy, BLOCK)
    np.testing.assert_allclose(np3(bsdf.eval(mi.BSDFContext(), si, vec3(wo))),
                               np3(fresh.eval(mi.BSDFContext(), si, vec3(wo))), rtol=1e-6, atol=1e-6)


# -- Renders ---------------------------------------------------------------------------------------


SLOPE_RMS = 0.06     # the far plane's map: slopes of this rms per axis, mild (below CLASS_BOUNDS[1])


def noise_texture(size, rms, tiles):
    """A raw bitmap texture of a smooth Gaussian noise height field's normals (``size``², periodic,
    fixed seed), slopes of ``rms`` per axis, tiled ``tiles`` times."""
    rng = np.random.default_rng(0)
    h = rng.standard_normal((size, size))
    f = np.fft.fftfreq(size)
    h = np.real(np.fft.ifft2(np.fft.fft2(h) * np.exp(-0.5 * np.add.outer(f * f, f * f) * (6 * np.pi) ** 2)))
    gx, gy = (np.roll(h, -1, 1) - np.roll(h, 1, 1)) / 2, (np.roll(h, -1, 0) - np.roll(h, 1, 0)) / 2
    scale = rms / np.sqrt((gx ** 2 + gy ** 2).mean() / 2)
    normal = np.stack([-gx * scale, gy * scale, np.ones_like(gx)], -1)
    normal /= np.linalg.norm(normal, axis=-1, keepdims=True)
    return {"type": "bitmap", "bitmap": mi.Bitmap(encode(normal.reshape(-1, 3)).reshape(size, size, 3).astype(np.float32)),
            "raw": True, "to_uv": mi.ScalarTransform4f().scale([tiles, tiles, 1])}


def far_scene(filter, integrator, texture, res, max_depth, alpha):
    """A gold plane (α ``alpha``) with ``texture`` under a sun whose highlight the camera sees,
    seen from afar, ``res``² px, box filter, independent sampler."""
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": max_depth},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at([0, -4, 3], [0, 0, 0], [0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "plane": {"type": "rectangle", "bsdf": {"type": "normalmap_microfacet", "normalmap": texture, "filter": filter,
                                                "bsdf": {"type": "roughconductor", "material": "Au", "alpha": alpha}}},
        "sun": {"type": "directional", "direction": [0.0, -0.75, -0.6], "irradiance": 3.0}})


def far_plane(filter, spp, seed):
    """The far gold plane (α 0.1) with a 256² noise map (SLOPE_RMS) tiled 8 times (about 40 texels
    per pixel), ``mfnormal_path`` with its footprint, 48² px, rendered."""
    scene = far_scene(filter, "mfnormal_path", noise_texture(256, SLOPE_RMS, 8), 48, 3, 0.1)
    return np.array(mi.render(scene, spp=spp, seed=seed))


def test_a_far_view_converges_with_less_noise_and_to_the_unfiltered_image():
    """The far gold plane at 16 spp: the filtered image's noise (the variance of two independent
    renders' difference, per pixel) is at most a quarter of the unfiltered one's, and its mean
    within 3 % of the unfiltered one's at 1024 spp; at 1024 spp (where the footprint, a pixel over
    √spp, is about a texel) the two means within 0.5 %. Measured: noise 0.047×, means 0.994 and
    0.999 (maps of rms slope 0.04 and 0.08: noise 0.076× and 0.054×, means 0.998 and 0.983)."""
    noise, means = {}, {}
    for filter in ("none", "lean"):
        a, b = far_plane(filter, 16, 1), far_plane(filter, 16, 2)
        noise[filter] = np.mean((a - b) ** 2) / 2
        means[filter] = (a.mean() + b.mean()) / 2
    assert noise["lean"] <= 0.25 * noise["none"], noise
    converged = {f: far_plane(f, 1024, 3).mean() for f in ("none", "lean")}
    assert means["lean"] == pytest.approx(converged["none"], rel=0.03)
    assert converged["lean"] == pytest.approx(converged["none"], rel=0.005)


def far_prb_scene(filter):
    """The far gold plane (α 0.15) under its sun (direct light only: ``max_depth`` 2), a 64² map
    of rms slope 0.06 tiled 16 times, ``mfnormal_prb`` (which gives the BSDF its footprint), 24² px."""
    return far_scene(filter, "mfnormal_prb", noise_texture(64, 0.06, 16), 24, 2, 0.15)


def test_a_filtered_render_differentiates_strength_as_central_differences_do():
    """d(mean pixel)/d``strength`` of the far plane under ``mfnormal_prb`` with ``filter="lean"``
    (reverse mode, through the pyramid) against central differences of renders with the same seed,
    at steps 1e-2 and 2e-2: within 3 %. (Smaller steps see the steps a texel makes as it crosses a
    class's bound or the Gaussian's, where the footprint's facet jumps: at 5e-3 the difference
    moves by 6 %.) Measured: AD −0.787, differences −0.793 and −0.799; unfiltered, AD −0.780
    against −0.793."""
    key = "plane.bsdf.strength"
    scene = far_prb_scene("lean")
    params = mi.traverse(scene)
    dr.enable_grad(params[key])
    params.update()
    dr.backward(dr.mean(mi.render(scene, params, spp=8, seed=3), axis=None))
    ad = float(np.array(dr.grad(params[key])).ravel()[0])
    for h in (1e-2, 2e-2):
        means = []
        for sign in (1, -1):
            moved = far_prb_scene("lean")
            p = mi.traverse(moved)
            p[key] = 1.0 + sign * h
            p.update()
            means.append(float(np.mean(np.array(mi.render(moved, spp=8, seed=3)))))
        fd = (means[0] - means[1]) / (2 * h)
        assert ad == pytest.approx(fd, rel=0.03), (ad, fd, h)
