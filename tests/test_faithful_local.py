"""The default model's local statistics (``neighbourhood``, docs/faithful.md §5): the neighbourhood
of a texel is measured around it (the slopes' variance and mean under a Gaussian window), not over
the whole map.

References are independent of the model code: a direct (non-separable) weighted sum over the
window for the field, Mitsuba's ``normalmap`` for a smooth region, Monte Carlo furnaces drawn
here, finite differences for derivatives. Every seed is fixed.
"""

import math

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from helpers import WHITE, bumps_normalmap, encode, make_bsdf, make_si, np1, np3, random_hemisphere, sph, vec3

import gradients as G
from mfnormal.models import neighbourhood

GLOSSY = {"type": "roughconductor", "distribution": "ggx", "alpha": 0.15}


def texture(rgb):
    """A raw bilinear bitmap of an H×W×3 map."""
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(rgb, np.float32)), "raw": True,
            "filter_type": "bilinear"}


def bsdf_on(rgb, nested, **params):
    return mi.load_dict({"type": "normalmap_microfacet", "normalmap": texture(rgb), "bsdf": nested, **params})


def half_smooth_map(size=64, tilt=25.0, balanced=False):
    """Left half (u < ½): one constant tilt; right half: steep bumps. RGB in [0, 1], H×W×3.
    ``balanced``: the left half's lower rows tilt the other way, so that the map's slopes average to
    zero (as a real map's smooth regions, the low-poly's shape differences, do over the map); else
    the map's mean slope is half the tilt's, and part of its relief is walls (docs/faithful.md §7)."""
    rgb = bumps_normalmap(size, 8, 0.45)
    rgb[:, : size // 2] = encode(sph(tilt, 0.5)[None])[0]
    if balanced:
        rgb[size // 2:, : size // 2] = encode(sph(tilt, 0.5 + math.pi)[None])[0]
    return rgb


def test_local_field_is_the_windowed_variance_and_mean():
    """The field (separable blur, wrapping) against a direct 2-D weighted sum over the window at a
    few texels: k² = (E|s|² − |E s|²)/(σ1² + σ2²) and E s, to 1e-9."""
    rng = np.random.default_rng(3)
    res = 32
    sx, sy = rng.normal(0, 0.3, res * res), rng.normal(0, 0.2, res * res)
    taps = neighbourhood.window_taps(6.0, res)
    total = float(np.mean(sx * sx + sy * sy))
    k, mx, my = neighbourhood.local_field(sx, sy, res, taps, total)
    off, w = taps
    fx, fy = sx.reshape(res, res), sy.reshape(res, res)
    for i, j in ((0, 0), (5, 17), (31, 9)):
        acc = np.zeros(3)
        for a, wa in zip(off, w):
            for b, wb in zip(off, w):
                x, y = fx[(i + a) % res, (j + b) % res], fy[(i + a) % res, (j + b) % res]
                acc += wa * wb * np.array([x * x + y * y, x, y])
        var = acc[0] - acc[1] ** 2 - acc[2] ** 2
        n = i * res + j
        assert abs(mx[n] - acc[1]) < 1e-9 and abs(my[n] - acc[2]) < 1e-9
        assert abs(k[n] - math.sqrt(var / total)) < 1e-9


def test_a_smooth_region_has_no_neighbourhood_and_its_own_macro_surface():
    """On a constant-tilt region of a map whose slopes average to zero, k = 0 and the mean normal is
    the tilt itself; on the bumpy half
    k is of the order of the map's (the map-wide σ is about the bumps: k > 1)."""
    b = bsdf_on(half_smooth_map(balanced=True), GLOSSY, neighbourhood=4.0)
    n = 6
    si = make_si(np.tile(sph(0.0), (2 * n, 1)), 1)
    v = np.linspace(0.15, 0.35, n)
    si.uv = mi.Point2f(np.r_[np.full(n, 0.25), np.full(n, 0.75)], np.r_[v, v])
    core = b.model.core
    k, wm = core.local_stats(b.shading_point(mi.BSDFContext(), si))
    k, wm = np1(k), np3(wm)
    assert np.all(k[:n] < 1e-3), k[:n]
    assert np.all(k[n:] > 1.0), k[n:]
    want = sph(25.0, 0.5)
    np.testing.assert_allclose(wm[:n], np.tile(want, (n, 1)), atol=2e-3)


def test_a_map_tilted_the_same_way_everywhere_is_all_walls():
    """A constant map's slopes average to its tilt: it is a sawtooth's facets, without the walls
    between them (docs/faithful.md §7). Its walls' mean slope is the tilt's (ψ = 1); its
    neighbourhoods are as rough as the map's about ω_g (k = 1, ω_m = ω_g), not a tilted plane; all
    of their relief, and of the neighbours that hide a texel, is walls, whose plane is upright
    across the tilt. A map whose slopes average to zero (the balanced half-smooth map) has none:
    its tilted region is the plane it was (the tests above)."""
    tilt, phi = 30.0, 0.5
    b = bsdf_on(np.tile(encode(sph(tilt, phi)), (8, 8, 1)), GLOSSY)
    core = b.model.core
    mu = -math.tan(math.radians(tilt)) * np.array([math.cos(phi), math.sin(phi)])
    assert core.wall[0] == 1.0
    np.testing.assert_allclose(core.wall[1:], mu, rtol=1e-5)
    rng = np.random.default_rng(4)
    n = 256
    si = make_si(random_hemisphere(rng, n, 0.05), 1)
    si.uv = mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32))
    sp = b.shading_point(mi.BSDFContext(), si)
    k, wm = core.local_stats(sp)
    np.testing.assert_allclose(np1(k), 1.0, rtol=1e-4)
    np.testing.assert_allclose(np3(wm), np.tile([0.0, 0.0, 1.0], (n, 1)), atol=1e-5)
    tx = core.texel(sp, sp.wi)
    np.testing.assert_allclose(np1(tx.wall_share), 1.0, rtol=1e-5)
    np.testing.assert_allclose(np1(tx.local_walls), 1.0, rtol=1e-4)
    np.testing.assert_allclose(np.abs(np3(tx.wall_n) @ [math.cos(phi), math.sin(phi), 0.0]), 1.0, rtol=1e-5)
    balanced = bsdf_on(half_smooth_map(balanced=True), GLOSSY)
    zero, sp = balanced.model.core, balanced.shading_point(mi.BSDFContext(), si)
    assert zero.wall == (0.0, 0.0, 0.0) and np.all(np1(zero.texel(sp, sp.wi).wall_share) == 0.0)


def test_a_smooth_tilted_region_shades_as_classic_normal_mapping():
    """Where the map is a constant tilt (a smooth region of a real map: the low-poly's shape
    difference), the texel is a plane, not a facet among neighbours: with local statistics the
    model is Mitsuba's ``normalmap`` (fixes off) there, to 1e-4 relative, at every query whose
    directions see the facet and whose mirror images (the bounce's preimages) leave it. With the
    map-wide statistics of the bumps next to it, the same queries differ (masking, the hidden
    texel): by more than 5 % on a tenth of them."""
    rgb = half_smooth_map(balanced=True)
    classic = mi.load_dict({"type": "normalmap", "normalmap": texture(rgb), "bsdf": GLOSSY,
                            "flip_invalid_normals": False, "use_shadowing_function": False})
    rng = np.random.default_rng(5)
    n = 20000
    wi, wo = random_hemisphere(rng, n, 0.05), random_hemisphere(rng, n, 0.05)
    wp = sph(25.0, 0.5)
    mirror = 2 * (wi @ wp)[:, None] * wp - wi
    keep = (wi @ wp > 0.05) & (wo @ wp > 0.05) & (mirror[:, 2] > 0.05) & ((wo * [1, 1, -1]) @ wp < 0)
    wi, wo = wi[keep], wo[keep]
    si = make_si(wi, 1)
    si.uv = mi.Point2f(rng.uniform(0.16, 0.34, len(wi)), rng.uniform(0.16, 0.34, len(wi)))
    ctx = mi.BSDFContext()
    ref = np3(classic.eval(ctx, si, vec3(wo)))
    local = np3(bsdf_on(rgb, GLOSSY, neighbourhood=4.0).eval(ctx, si, vec3(wo)))
    wide = np3(bsdf_on(rgb, GLOSSY, neighbourhood=0.0).eval(ctx, si, vec3(wo)))
    assert len(wi) > 2000
    np.testing.assert_allclose(local, ref, rtol=1e-4, atol=1e-6)
    assert np.mean(np.abs(wide - ref) > 0.05 * ref + 1e-6) > 0.1


def test_a_texel_in_a_smooth_neighbourhood_keeps_its_footprint_at_grazing_views():
    """In a smooth neighbourhood (mild slopes, k ≈ 0.04 of the map's, steep bumps beside it) a texel
    is the surface there, not a facet among neighbours: seen at 75–88° from ω_g it is hidden only by
    what masks it, V ≥ 0.95·G1 wherever it faces the camera (measured: 1st percentile of V/G1 0.985;
    R is taken on a plane between the texel's own and its neighbourhood's mean plane, the texel's
    own as k → 0: OWN_PLANE_K). Taken on the mean plane, a small deviation from it foreshortens the
    texel at grazing views: 27 % of the same queries had V < 0.9·G1 (1st percentile 0.58), and the
    low-poly's own lobe showed through at real assets' limbs (docs/faithful.md §1.1)."""
    size = 128
    rgb = bumps_normalmap(size, 8, 0.45)
    x, y = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size)
    waves = ((0.03, 8, 3, 0.3), (0.02, -5, 11, 1.1), (0.025, 13, -7, 2.0))
    sx = sum(a * np.sin(2 * np.pi * (fx * x + fy * y) + ph) for a, fx, fy, ph in waves)
    sy = sum(a * np.cos(2 * np.pi * (fy * x + fx * y) + ph) for a, fx, fy, ph in waves)
    n = np.stack([-sx, -sy, np.ones_like(sx)], -1)
    rgb[:, : size // 2] = encode(n / np.linalg.norm(n, axis=-1, keepdims=True))[:, : size // 2]
    bsdf = bsdf_on(rgb, GLOSSY)
    rng = np.random.default_rng(7)
    count = 20000
    wi = sph(rng.uniform(75.0, 88.0, count), rng.uniform(0.0, 2 * np.pi, count))
    si = make_si(wi, 1)
    si.uv = mi.Point2f(rng.uniform(0.1, 0.4, count), rng.uniform(0.0, 1.0, count))
    sp = bsdf.shading_point(mi.BSDFContext(), si)
    tx = bsdf.model.core.texel(sp, sp.wi)
    k, vis, g1 = np1(tx.k), np1(tx.vis), np1(dr.rcp(1.0 + tx.lam_i))
    facing = np1(dr.dot(tx.wi, tx.wp)) > 0.5 * wi[:, 2]
    assert np.max(k) < 0.1 and np.mean(facing) > 0.9, (np.max(k), np.mean(facing))
    assert np.min(vis[facing] / g1[facing]) >= 0.95, np.percentile(vis[facing] / g1[facing], [0, 1])


def test_a_mild_neighbourhood_is_measured_in_the_finer_window():
    """A mild map's slopes that vary across the window (a long wave, 16 texels per period, max tilt
    8°, rms slope 0.1) hold the surface's shape, which masks nothing at the texel's scale: the
    texel's k is moved to the finer window's (neighbourhood.FINE_WINDOW; at most the window's), well
    below the window's (measured: mean 0.55 against 0.96). A steep map's neighbourhood (the bumps map,
    where the window's rms slope k·σ ≥ MILD_SLOPE) keeps the window's k."""
    from mfnormal.models.faithful import MILD_SLOPE
    size = 64
    x, _ = np.meshgrid((np.arange(size) + 0.5) / size, (np.arange(size) + 0.5) / size)
    sx = math.tan(math.radians(8.0)) * np.sin(2 * np.pi * 4 * x)
    n = np.stack([-sx, np.zeros_like(sx), np.ones_like(sx)], -1)
    wave = encode(n / np.linalg.norm(n, axis=-1, keepdims=True))
    rng = np.random.default_rng(11)
    count = 4096
    for rgb, mild in ((wave, True), (bumps_normalmap(size, 4, 0.45), False)):
        b = bsdf_on(rgb, GLOSSY)
        si = make_si(random_hemisphere(rng, count, z_min=0.1), 1)
        si.uv = mi.Point2f(rng.random(count).astype(np.float32), rng.random(count).astype(np.float32))
        sp = b.shading_point(mi.BSDFContext(), si)
        core = b.model.core
        k = np1(core.texel(sp, sp.wi).k)
        fields, res, uv_of = core.local
        uv = uv_of(sp.si)
        window, fine = (np1(dr.minimum(f, core.k_max)) for f in neighbourhood.field_lookup(
            [fields[0], fields[3]], res, uv.x, uv.y))
        rms = window * np1(dr.sqrt(0.5 * (core.sigma1 ** 2 + core.sigma2 ** 2)))
        assert np.all(k <= window + 1e-6) and np.all(k >= np.minimum(fine, window) - 1e-6)
        if mild:
            assert np.all(rms < MILD_SLOPE) and np.mean(k) < 0.7 * np.mean(window), (np.mean(k), np.mean(window))
        else:
            steep = rms >= MILD_SLOPE
            assert np.mean(steep) > 0.5 and np.allclose(k[steep], window[steep], rtol=1e-5, atol=1e-6)


def test_the_finer_window_is_measured_on_maps_larger_than_the_grid():
    """The statistics are computed on a grid of at most LOCAL_RES² samples of the map. On a map
    4096 texels wide that grid has a cell per 4 texels: the 8-texel window spans 2 cells, and 3/8 of
    it would be under one, where the grid sees no variation. The finer window is kept at
    neighbourhood.FINE_MIN_CELLS cells (never wider than the window), so its k is measured on the
    grid: on a random map at least 0.7 of the window's at the median texel (measured: 0.92), where a
    window of 0.75 cells gives 0.37."""
    from mfnormal.normals.normal_map import LOCAL_RES
    rng = np.random.default_rng(31)
    width = 4096
    assert width >= 4 * LOCAL_RES
    rgb = encode(sph(rng.uniform(0, 30, 4 * width), rng.uniform(0, 2 * np.pi, 4 * width))).reshape(4, width, 3)
    fields, res, _ = bsdf_on(rgb, GLOSSY).model.core.local
    assert res == LOCAL_RES
    k, k_fine = np.array(fields[0]), np.array(fields[3])
    assert np.median(k_fine / np.maximum(k, 1e-9)) > 0.7, np.median(k_fine / np.maximum(k, 1e-9))


@pytest.mark.parametrize("width", [2.0, 8.0])
def test_white_furnace_with_local_statistics(width):
    """White Lambertian facets on a map whose neighbourhood varies from none to several times the
    map's (k between the table's nodes): 64 random (texel, ω_i) pairs, 2^13 samples each, every
    mean sample weight within 1 ± (1 % + 4 standard errors), as the map-wide test."""
    rgb = half_smooth_map(32)
    rng = np.random.default_rng(8)
    pairs, per = 64, 1 << 13
    uv = np.repeat(rng.random((pairs, 2)), per, axis=0)
    wi = np.repeat(random_hemisphere(rng, pairs, z_min=0.02), per, axis=0)
    b = bsdf_on(rgb, WHITE, neighbourhood=width)
    si = make_si(wi, 1)
    si.uv = mi.Point2f(uv[:, 0], uv[:, 1])
    s1 = mi.Float(rng.random(len(wi)).astype(np.float32))
    s2 = mi.Point2f(rng.random(len(wi)).astype(np.float32), rng.random(len(wi)).astype(np.float32))
    _, w = b.sample(mi.BSDFContext(), si, s1, s2)
    w = np3(w)[:, 0].reshape(pairs, per)
    mean, se = w.mean(1), w.std(1) / math.sqrt(per)
    assert np.all(np.abs(mean - 1.0) < 0.01 + 4 * se), (mean.min(), mean.max())


@pytest.mark.parametrize("strength, most, least", [(0.12, 0.0, 0.3), (1.0, 0.9, 1.0)])
def test_only_a_steep_neighbourhood_sends_blocked_light_back(strength, most, least):
    """The retro-reflected share of the blocked glossy light (Texel.retro_share) at grazing ω_i,
    where the facet's mirror direction is mostly under the macro plane: a cavity with steep walls
    sends it back (the bumps map: some queries ≥ 0.9), a mild neighbourhood does not (the same map
    at strength 0.12, rms slope about a tenth: every query ≤ 0.3), so that at an object's limb
    the mirror image of a mild texel's lobe skims on instead of coming back toward the camera."""
    b = bsdf_on(bumps_normalmap(64, 4, 0.45), GLOSSY, neighbourhood=8.0, strength=strength)
    rng = np.random.default_rng(9)
    n = 4096
    z = rng.uniform(0.03, 0.2, n)
    phi = rng.uniform(0.0, 2.0 * math.pi, n)
    wi = np.stack([np.sqrt(1 - z * z) * np.cos(phi), np.sqrt(1 - z * z) * np.sin(phi), z], -1)
    si = make_si(wi, 1)
    si.uv = mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32))
    sp = b.shading_point(mi.BSDFContext(), si)
    share = np1(b.model.core.texel(sp, sp.wi).retro_share())
    assert np.all(np.isfinite(share)) and np.all(share >= 0.0)
    assert share.max() >= most and share.max() <= least, (share.min(), share.max())


def test_sample_eval_pdf_are_consistent_with_local_statistics():
    """weight = eval/pdf, bs.pdf = pdf(ω_o) on the half-smooth map (1e-4 relative, float32)."""
    rgb = half_smooth_map(32)
    rng = np.random.default_rng(9)
    n = 40000
    b = bsdf_on(rgb, {"type": "roughplastic", "alpha": 0.2}, neighbourhood=4.0)
    si = make_si(random_hemisphere(rng, n, 0.01), 1)
    si.uv = mi.Point2f(rng.random(n), rng.random(n))
    s1 = mi.Float(rng.random(n).astype(np.float32))
    s2 = mi.Point2f(rng.random(n).astype(np.float32), rng.random(n).astype(np.float32))
    bs, w = b.sample(mi.BSDFContext(), si, s1, s2)
    ok = np1(bs.pdf) > 0
    v, p = b.eval_pdf(mi.BSDFContext(), si, bs.wo)
    np.testing.assert_allclose(np3(w)[ok], np3(v)[ok] / np1(p)[ok, None], rtol=1e-4, atol=1e-6)
    np.testing.assert_allclose(np1(bs.pdf)[ok], np1(p)[ok], rtol=1e-4, atol=1e-7)


def _field_after(b, data):
    params = mi.traverse(b)
    params["normalmap.data"] = data
    params.update()
    return b.model.core.local[0]


@pytest.mark.parametrize("strength", [1.0, 0.0])
def test_local_field_carries_the_texels_derivatives(strength):
    """k, the mean slope and the finer window's k on an 8 × 8 map with a window of 3 texels: forward-mode derivatives
    with respect to one texel channel against central differences of the field (h = 1e-3), at every
    grid cell, to 2 % + 2e-3 (float32 texels: the FD's rounding is ~1e-4 of the field). At strength 0
    k is the map's at strength 1 (its limit), and it keeps that map's derivatives."""
    rng = np.random.default_rng(21)
    rgb = encode(sph(rng.uniform(0, 50, 64), rng.uniform(0, 2 * np.pi, 64))).reshape(8, 8, 3)
    b = bsdf_on(rgb, WHITE, neighbourhood=3.0, strength=strength)
    base = np.array(mi.traverse(b)["normalmap.data"])
    h = 1e-3
    for texel, channel in (((2, 3), 0), ((5, 5), 1)):
        def at(delta):
            data = base.copy()
            data[texel[0], texel[1], channel] += delta
            return [np.array(f, np.float64) for f in _field_after(b, mi.TensorXf(data))]
        fd = [(p - m) / (2 * h) for p, m in zip(at(h), at(-h))]
        # k, the mean slope along the channel's axis (red: x, green: y), and k in the finer window.
        for n in ((0, 1 + channel, 3) if strength else (0, 3)):
            b = bsdf_on(rgb, WHITE, neighbourhood=3.0, strength=strength)
            params = mi.traverse(b)
            data = params["normalmap.data"]
            dr.enable_grad(data)
            params.update()
            field = b.model.core.local[0][n]
            seed = np.zeros(base.shape, np.float32)
            seed[texel[0], texel[1], channel] = 1.0
            dr.set_grad(data, mi.TensorXf(seed))
            dr.forward_to(field)
            ad = np.array(dr.grad(field), np.float64)
            assert np.abs(fd[n]).max() > 0.02, (n, "the texel must move the field")
            np.testing.assert_allclose(ad, fd[n], rtol=0.02, atol=2e-3, err_msg=f"field {n}, texel {texel}")


def test_local_statistics_carry_the_texels_derivatives():
    """d eval / d texel on a 4-texel map whose every texel is in every other's window (neighbourhood
    2 texels): a texel moves its neighbours' k and mean normal, and forward = reverse = FD (the
    harness of tests/test_gradients.py: 4 paired SE + 3 %; the FD is noisier than the map-wide
    model's, a texel moves the kinks of every texel's V)."""
    texels = encode(np.array([sph(30, 0.3), sph(50, 0.8), sph(15, -0.4), sph(40, 2.5)]).reshape(-1, 3))
    b = make_bsdf({"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.3, 0.6, 0.9]}}, texels,
                  neighbourhood=2.0)
    si, wo, u = G.queries(1 << 17, 4)
    for key in (("texel", 1, 1), ("texel", 2, 0)):
        c = G.check(b, key, si, wo, u, 1e-3, steps=G.STEPS)
        assert c.agrees(), f"{key}: {c}"
        assert abs(c.fd) > 4 * c.se, f"{key}: the check must see a derivative ({c})"


def test_neighbourhood_must_be_a_number_of_texels():
    for bad in (-1.0, float("inf"), float("nan")):
        with pytest.raises(Exception, match="neighbourhood must be a finite number of texels"):
            bsdf_on(half_smooth_map(8), WHITE, neighbourhood=bad)


def ramped_bumps():
    """Bumps whose slopes grow 3.3× from u = 0 to u = 1: k from 0.34 to 1.7 over the map."""
    n = 2.0 * bumps_normalmap(64, 8, 0.45) - 1.0
    n[..., :2] *= np.linspace(0.3, 1.0, 64)[None, :, None]
    return 0.5 * n / np.linalg.norm(n, axis=-1, keepdims=True) + 0.5


@pytest.mark.parametrize("bumps", ["even", "ramped"])
def test_only_the_scales_a_lookup_reads_are_computed(bumps):
    """The table B is computed only at the neighbourhood scales the map's k spans
    (neighbourhood.needed_scales; the others hold a copy that no lookup reads): eval, pdf and the
    texels' derivatives (forward mode, along a random direction of the texels) are bit for bit
    those with the tables computed at every scale, at 2^15 random queries over the whole map, on
    even bumps (scales 2–7 of 0–8) and on bumps whose slopes grow across the map (1–8); with
    fewer scales than the map needs they are not (checked: the span's two ends alone)."""
    from mfnormal.models.neighbourhood import blocked_table, kernel_array, local_scales, needed_scales
    rng = np.random.default_rng(31)
    rgb = bumps_normalmap(64, 8, 0.45) if bumps == "even" else ramped_bumps()
    n = 1 << 15
    wi, wo = random_hemisphere(rng, n, 0.02), random_hemisphere(rng, n, 0.02)
    si = make_si(wi)
    si.uv = mi.Point2f(*(rng.random((2, n)).astype(np.float32)))
    b = bsdf_on(rgb, {"type": "roughplastic", "alpha": 0.15})     # (B weights the diffuse fill)
    params = mi.traverse(b)
    dr.enable_grad(params["normalmap.data"])
    params.update()
    core = b.model.core
    fields = core.local[0]
    span = needed_scales([np.array(fields[0]), np.array(fields[3])], local_scales())
    assert span is not None and 2 < len(span) < len(local_scales())
    seed = mi.TensorXf(rng.normal(size=rgb.shape).astype(np.float32))

    def values(needed):
        """eval, pdf and their forward derivatives with the tables of the scales ``needed``."""
        table, t1, t2 = blocked_table(*core.slopes[:2], core.cos_min, True, local_scales(), needed)
        core.table = kernel_array(mi.Float, table.ravel())
        core.d_tables = (kernel_array(mi.Float, t1.ravel()), kernel_array(mi.Float, t2.ravel()))
        dr.make_opaque(core.table, *core.d_tables)
        v, p = b.eval_pdf(mi.BSDFContext(), si, vec3(wo))
        dr.set_grad(params["normalmap.data"], seed)
        # (The edges from the texels to the map's statistics are kept for the next call.)
        dv, dp = dr.forward_to(v[0] + v[1] + v[2], p, flags=dr.ADFlag.ClearInterior | dr.ADFlag.ClearInput)
        return np3(v), np1(p), np1(dv), np1(dp)
    part, full = values(span), values(None)
    for a, c in zip(part, full):
        assert np.array_equal(a, c)
    ends = values((span[0], span[-1]))
    assert not all(np.array_equal(a, c) for a, c in zip(ends, full))


@pytest.mark.parametrize("sigma", [(0.05, 0.03), (0.2, 0.19), (0.3, 0.02), (0.6, 0.6), (1.5, 0.8), (8.0, 7.0)])
def test_a_followed_table_is_within_2e_5_of_the_one_built_there(sigma):
    """tables._BuiltTable.follow: the table B with derivatives built at (σ1, σ2), followed to first
    order to each corner of the square TABLE_FOLLOW around it (the farthest a table is followed),
    every neighbourhood scale, is within 2e-5 of the table built at that corner (measured: 1e-6 at
    σ 0.05, 1.7e-5 at the steepest; the quadrature's own error is 7e-5), and closer than a tenth
    of the distance of the table it follows from."""
    from mfnormal.models.faithful.tables import TABLE_FOLLOW, _BuiltTable
    from mfnormal.models.neighbourhood import blocked_table, local_scales
    s1, s2 = sigma
    scales = local_scales()
    built = _BuiltTable(0.02, scales, None, s1, s2, blocked_table(s1, s2, 0.02, True, scales), None)
    for a, b in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
        t1, t2 = s1 * (1 + a * TABLE_FOLLOW), s2 * (1 + b * TABLE_FOLLOW)
        there = blocked_table(t1, t2, 0.02, False, scales)
        error = np.abs(built.follow(t1, t2) - there).max()
        assert error < 2e-5
        assert error < 0.1 * np.abs(built.tables[0] - there).max()


def test_an_optimisers_small_update_follows_the_table_and_a_large_one_builds_it():
    """With the texels carrying derivatives, an update whose σ1, σ2 move by 0.5 % (``strength``
    1 → 1.005: every slope scales with it, the neighbourhoods' k do not) builds no table
    (blocked_table's cache sees no new call) and its table is within 2e-5 of the one built at the new
    σ, the old one not; one that moves σ by 5 % builds it there, bit for bit; and a primal update
    (no derivatives) always builds it exactly."""
    from mfnormal.models.neighbourhood import blocked_table, local_scales
    b = bsdf_on(bumps_normalmap(64, 8, 0.45), {"type": "roughplastic", "alpha": 0.15})
    params = mi.traverse(b)
    dr.enable_grad(params["normalmap.data"])
    params.update()
    core = b.model.core

    def exact(derivatives=True):
        """The table blocked_table builds at the map's σ now (its value, flat)."""
        fields = core.local[0]
        needed = neighbourhood.needed_scales([np.array(fields[0]), np.array(fields[3])], local_scales())
        table = blocked_table(*core.slopes[:2], core.cos_min, derivatives, local_scales(), needed)
        return (table[0] if derivatives else table).ravel()
    start = np.array(core.table)
    assert np.array_equal(start, exact())
    calls = blocked_table.cache_info().misses + blocked_table.cache_info().hits
    params["strength"] = 1.005
    params.update()
    assert blocked_table.cache_info().misses + blocked_table.cache_info().hits == calls
    followed, there = np.array(core.table), exact()
    assert np.abs(followed - there).max() < 2e-5 < np.abs(start - there).max()
    params["strength"] = 1.05
    params.update()
    assert np.array_equal(np.array(core.table), exact())
    dr.disable_grad(params["normalmap.data"])
    params["strength"] = 1.055
    params.update()
    assert core.d_tables is None
    assert np.array_equal(np.array(core.table), exact(derivatives=False))
