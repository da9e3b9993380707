"""The true-geometry harness (``validation.heightfield``): its conventions, generators and scenes.

The harness compares a coarse plane carrying a baked normal map with the dense mesh
the map was baked from; if the map's frame or orientation were off, every number it
produces would be wrong. The central test renders both with Mitsuba's own
``normalmap`` in a case where classic normal mapping is exact (mild map, frontal
orthographic view, directional light above every facet's horizon, direct light only)
and checks that they agree pixelwise — and that the same map with its green channel
flipped, u and v swapped, or its rows reversed does not.
"""

import math

import numpy as np
import pytest

import mfnormal  # noqa: F401  (picks a working libLLVM before mitsuba loads)
import drjit as dr
import mitsuba as mi
from variant import VARIANT  # noqa: E402  (MFNORMAL_VARIANT, tests/variant.py)

mi.set_variant(VARIANT)
mfnormal.register()

from validation import heightfield as H  # noqa: E402


def wrong_maps(nm):
    """The baked map under the three convention errors a harness could make."""
    return {
        "green flipped (DirectX)": np.stack([nm[..., 0], 1.0 - nm[..., 1], nm[..., 2]], axis=-1),
        "u and v swapped": np.transpose(nm, (1, 0, 2))[..., [1, 0, 2]],
        "rows reversed (v origin at the bottom)": nm[::-1],
    }


# ---------------------------------------------------------------------------
# Generators
# ---------------------------------------------------------------------------

@pytest.mark.parametrize("kind", H.KINDS)
@pytest.mark.parametrize("steepness", ["mild", "steep"])
def test_generators_hit_their_max_tilt_target(kind, steepness):
    hf = H.make_heightfield(kind, steepness, periods=3)
    target = H.STEEPNESS[steepness]
    # On a finer grid than the one the amplitude was fitted on: the max is the surface's, not the grid's.
    st = H.tilt_stats(hf, n=1024)
    assert abs(st["max"] - target) < 0.3, st
    assert st["median"] < st["p99"] <= st["max"] + 1e-9
    assert abs(st["mean_height"] - hf.mean_height) < 1e-3 * st["peak_to_peak"]


@pytest.mark.parametrize("kind", H.KINDS)
def test_generators_hit_a_median_tilt_target_and_are_periodic(kind):
    gen = {"bumps": H.bumps, "eggcrate": H.egg_crate, "noise": H.noise}[kind]
    hf = gen(periods=4, median_tilt=9.0)
    assert abs(H.tilt_stats(hf, n=1024)["median"] - 9.0) < 0.3
    rng = np.random.default_rng(3)
    x, y = rng.random(500), rng.random(500)
    for dx, dy in ((hf.period, 0.0), (0.0, hf.period), (1.0, -2.0)):
        for a, b in zip(hf.eval(x, y), hf.eval(x + dx, y + dy)):
            np.testing.assert_allclose(a, b, atol=1e-9 * max(1.0, np.abs(a).max()))
    # Same seed, same field; the presets' mild maps are mild.
    assert gen(periods=4, median_tilt=9.0) == hf
    mild = H.tilt_stats(H.make_heightfield(kind, "mild"))
    assert 5.0 < mild["median"] < 22.0 and mild["max"] < 28.5


def test_gradient_is_the_derivative_of_the_height():
    for kind in H.KINDS:
        hf = H.make_heightfield(kind, "steep", periods=2)
        rng = np.random.default_rng(5)
        x, y = rng.random(200), rng.random(200)
        e = 1e-6
        _, hx, hy = hf.eval(x, y)
        np.testing.assert_allclose(hx, (hf.height(x + e, y) - hf.height(x - e, y)) / (2 * e), atol=1e-5)
        np.testing.assert_allclose(hy, (hf.height(x, y + e) - hf.height(x, y - e)) / (2 * e), atol=1e-5)


def test_egg_crate_normals_and_central_difference_bake():
    """The baked map's normals are the analytic ones; a central-difference bake is within its
    O(Δ²) error bound and converges at second order."""
    hf = H.egg_crate(periods=2, max_tilt=60.0)
    A, k = hf.amplitude, 2 * np.pi * hf.periods
    assert abs(math.degrees(math.atan(A * k)) - 60.0) < 0.01        # max tilt atan(2π p A)
    res = 64
    x, y = H.texel_centres(res)
    exact = np.stack([-A * k * np.cos(k * x) * np.sin(k * y), -A * k * np.sin(k * x) * np.cos(k * y),
                      np.ones_like(x)], axis=-1)
    exact /= np.linalg.norm(exact, axis=-1, keepdims=True)
    np.testing.assert_allclose(H.texel_normals(hf, res), exact, atol=1e-12)
    np.testing.assert_allclose(H.normal_map(hf, res), exact * 0.5 + 0.5, atol=1e-6)

    def angle_err(r):
        a = H.texel_normals(hf, r, gradient="central")
        b = H.texel_normals(hf, r)
        return np.degrees(np.arccos(np.clip((a * b).sum(-1), -1, 1))).max()

    # Central differences of sin(kx): k cos(kx) · sin(kΔ)/(kΔ), a relative gradient error
    # 1 − sin(kΔ)/(kΔ); the tilt error is at most that times |∇h| (d atan(g)/dg ≤ 1).
    for r in (32, 64, 128):
        d = 1.0 / r
        bound = math.degrees(A * k * (1 - math.sin(k * d) / (k * d)))
        assert angle_err(r) <= bound * 1.01 + 1e-9, (r, angle_err(r), bound)
    assert 3.6 < angle_err(64) / angle_err(128) < 4.4        # second order


# ---------------------------------------------------------------------------
# Conventions, without rendering: Mitsuba's own texture lookup and shading frame
# ---------------------------------------------------------------------------

def _map_normals_at(img, world_xy, extent=(-2.0, 3.0, -2.0, 3.0)):
    """World-space normals decoded from ``img`` the way ``normalmap`` does it, at world points
    on :func:`plane_mesh` (Mitsuba's ray intersection, UVs, bitmap lookup and sh_frame)."""
    scene = mi.load_dict({"type": "scene", "plane": H.plane_mesh(extent, 0.0, {"type": "diffuse"})})
    n = len(world_xy)
    ray = mi.Ray3f(mi.Point3f(world_xy[:, 0], world_xy[:, 1], np.full(n, 1.0)), mi.Vector3f(0, 0, -1))
    si = scene.ray_intersect(ray)
    tex = mi.load_dict(H.bitmap_texture(img))
    rgb = tex.eval(si)
    local = dr.normalize(mi.Vector3f(2 * rgb[0] - 1, 2 * rgb[1] - 1, 2 * rgb[2] - 1))
    world = si.sh_frame.to_world(local)
    return np.array(world).T, si


def test_plane_frame_and_uv_layout():
    """u = x, v = 1 − y; Mitsuba's dp/du = +x, dp/dv = −y, sh_frame (s, t, n) = (+x, +y, +z)."""
    pts = np.array([[0.2, 0.3], [0.7, 0.9], [1.3, -0.2]])
    _, si = _map_normals_at(np.zeros((4, 4, 3), np.float32) + 0.5, pts)
    np.testing.assert_allclose(np.array(si.uv).T, np.stack([pts[:, 0], 1 - pts[:, 1]], 1), atol=1e-6)
    for vec, want in ((si.dp_du, [1, 0, 0]), (si.dp_dv, [0, -1, 0]), (si.sh_frame.s, [1, 0, 0]),
                      (si.sh_frame.t, [0, 1, 0]), (si.sh_frame.n, [0, 0, 1])):
        np.testing.assert_allclose(np.array(vec).T, np.tile(want, (3, 1)), atol=1e-6)
    # The image's first row is v = 0, i.e. the plane's top edge y = 1.
    img = np.zeros((4, 4, 3), np.float32)
    img[0, :, 0] = 1.0
    tex = mi.load_dict(H.bitmap_texture(img, "nearest"))
    scene = mi.load_dict({"type": "scene", "plane": H.plane_mesh(bsdf={"type": "diffuse"})})
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f([0.5, 0.5], [0.9, 0.1], [1, 1]), mi.Vector3f(0, 0, -1)))
    np.testing.assert_allclose(np.array(tex.eval(si)[0]), [1.0, 0.0])


def test_baked_map_decodes_to_the_surface_normal_in_mitsubas_frame():
    """At texel centres (where bilinear lookup returns the texel exactly), the map decoded in the
    plane's shading frame is the heightfield's world normal — also outside [0, 1]² (repeat) —
    and under each wrong convention it is not."""
    hf = H.make_heightfield("noise", "steep", periods=2)
    res = 32
    rng = np.random.default_rng(0)
    c, r = rng.integers(0, res, 300), rng.integers(0, res, 300)
    tile = rng.integers(-1, 2, (300, 2))
    xy = np.stack([(c + 0.5) / res, 1.0 - (r + 0.5) / res], 1) + tile
    want = hf.normal(xy[:, 0], xy[:, 1])
    nm = H.normal_map(hf, res)
    got, _ = _map_normals_at(nm, xy)
    assert np.abs(got - want).max() < 1e-5
    for name, bad in wrong_maps(nm).items():
        got, _ = _map_normals_at(np.ascontiguousarray(bad), xy)
        assert np.degrees(np.arccos(np.clip((got * want).sum(1), -1, 1))).mean() > 10.0, name
    # The height map has the same layout: heights relative to the plane at the mean height.
    hm = H.height_map(hf, res)
    scene = mi.load_dict({"type": "scene", "plane": H.plane_mesh((-2, 2, -2, 2), 0.0, {"type": "diffuse"})})
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f(xy[:, 0], xy[:, 1], np.ones(300)), mi.Vector3f(0, 0, -1)))
    got_h = np.array(mi.load_dict(H.bitmap_texture(hm)).eval_1(si))
    np.testing.assert_allclose(got_h, hf.height(xy[:, 0], xy[:, 1]) - hf.mean_height, atol=1e-6)


@pytest.mark.parametrize("view", ["oblique40", "grazing", "inside40"])
def test_first_hit_is_the_first_crossing_of_the_camera_ray(view):
    """The point :func:`first_hit` returns lies on the camera ray through the plane point and on
    the surface (to 1e-9 of the heights' range), and the ray is on the camera's side of the
    surface all the way from the heights' slab to it: no earlier crossing (checked at 20 000 points
    per ray, finer than the march). Fails if the march kept the last crossing, or none."""
    hf = H.make_heightfield("eggcrate", 50.0, periods=2)
    d = H._direction(H.VIEWS[view].theta, H.CAMERA_AZIMUTH)
    rng = np.random.default_rng(5)
    x, y = rng.uniform(0, 1, 200), rng.uniform(0, 1, 200)
    z0 = hf.mean_height
    t = H.first_hit(hf, x, y, z0, d)
    lo, hi = hf.height_range
    residual = (z0 + t * d[2]) - hf.height(x + t * d[0], y + t * d[1])
    assert np.abs(residual).max() < 1e-9 * (hi - lo)
    t_near = max((lo - z0) / d[2], (hi - z0) / d[2])
    side = np.sign(d[2])
    s = t[:, None] + (t_near - t)[:, None] * np.linspace(1e-4, 1.0, 20_000)[None, :]
    gap = side * ((z0 + s * d[2]) - hf.height(x[:, None] + s * d[0], y[:, None] + s * d[1]))
    assert (gap > 0).all()
    # Some rays meet the steep egg crate more than a tenth of a period sideways from where they
    # cross the plane (at 40°: up to 0.16 of it): the shift the registration undoes.
    assert np.abs(t * np.hypot(d[0], d[1])).max() > 0.1 * hf.period


def test_the_registered_map_shows_each_camera_ray_the_normal_where_it_meets_the_surface():
    """Read by Mitsuba on the plane (its uv, bilinear lookup and frame), the map registered for a
    camera 40° from the normal gives, at each plane point, the true surface's normal where the
    camera ray through that point meets it: within the bilinear interpolation's error of the map
    (median under 1°), while the baked map there is off by tens of degrees (median over 10°).
    Seen from the front it is the baked map itself."""
    hf = H.make_heightfield("eggcrate", 50.0, periods=2)
    res = 48
    nm = H.normal_map(hf, res)
    np.testing.assert_array_equal(H.registered_map(hf, nm, np.array([0.0, 0.0, 1.0]), upsample=1), nm)
    d = H._direction(40.0, H.CAMERA_AZIMUTH)
    reg = H.registered_map(hf, nm, d)
    rng = np.random.default_rng(6)
    xy = rng.uniform(0, 1, (400, 2))
    t = H.first_hit(hf, xy[:, 0], xy[:, 1], hf.mean_height, d)
    want = hf.normal(xy[:, 0] + t * d[0], xy[:, 1] + t * d[1])

    def angle(img):
        got, _ = _map_normals_at(img, xy)
        return np.degrees(np.arccos(np.clip((got * want).sum(1), -1, 1)))
    assert np.median(angle(reg)) < 1.0
    assert np.median(angle(nm)) > 10.0


def test_true_mesh_samples_the_heightfield():
    hf = H.make_heightfield("bumps", "steep", periods=2)
    pos, nrm, uv, faces = H.displaced_arrays(hf, (-0.3, 0.4, 0.1, 0.9), 16)
    np.testing.assert_allclose(pos[:, 2], hf.height(pos[:, 0], pos[:, 1]), atol=1e-6)
    np.testing.assert_allclose(nrm, hf.normal(pos[:, 0], pos[:, 1]), atol=1e-6)
    np.testing.assert_allclose(uv, np.stack([pos[:, 0], 1 - pos[:, 1]], 1), atol=1e-6)
    assert pos[:, 0].min() <= -0.3 and pos[:, 0].max() >= 0.4 and pos[:, 1].min() <= 0.1
    # Counter-clockwise seen from +z: geometric normals point up, like the vertex normals.
    p = pos.astype(np.float64)
    ng = np.cross(p[faces[:, 1]] - p[faces[:, 0]], p[faces[:, 2]] - p[faces[:, 0]])
    assert (ng[:, 2] > 0).all()


@pytest.mark.parametrize("view", ["frontal", "grazing"])
@pytest.mark.parametrize("magnification", ["magnified", "minified"])
def test_surface_fills_the_frame(view, magnification):
    """Every primary ray hits the surface — the truth and the plane, steep map, grazing sun
    (the largest margins) — so metrics need no masks and silhouettes never differ; and the plane
    sits at the mean height of the true surface."""
    hf = H.make_heightfield("eggcrate", "steep", periods=H.MAGNIFICATIONS[magnification].periods)
    vpp = H.MAGNIFICATIONS[magnification].verts_per_period
    res = 48
    for surface in ("true", "plane"):
        d = H.scene_dict(hf, surface, {"type": "diffuse"}, "grazing_sun", view, res, 1, 8, vpp)
        scene = mi.load_dict(d)
        sensor = scene.sensors()[0]
        # Each pixel's four corners (~2 % inside). Offsets off the mesh's rational lattice: Embree
        # is not watertight, so a ray exactly on a shared edge can miss both triangles (a
        # measure-zero event in a render, but not for rays on a grid commensurate with the mesh).
        idx = np.arange(res * res * 4)
        sub = idx % 4
        px = (idx // 4) % res + 0.0193 + 0.9614 * (sub % 2)
        py = (idx // 4) // res + 0.0241 + 0.9562 * (sub // 2)
        ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(px / res, py / res), mi.Point2f(0.5))
        si = scene.ray_intersect(ray)
        assert np.array(si.is_valid()).all(), (surface, view, magnification)
        # Image orientation: columns run along +x; the top rows are at +y (frontal: the map's
        # layout; grazing: the far side, camera on −y).
        p = np.array(si.p).T.reshape(res, res, 4, 3)[..., 0, :]
        assert p[0, 0, 0] < p[0, -1, 0] and p[0, 0, 1] > p[-1, 0, 1]
        if view == "frontal":
            np.testing.assert_allclose(p[:, :, 0].mean(0), (np.arange(res) + 0.0193) / res, atol=1e-5)
        if surface == "plane":
            np.testing.assert_allclose(np.array(si.p.z), hf.mean_height, atol=1e-6)
    assert abs(hf.mean_height) < 1e-9                              # sin·sin has mean 0
    assert abs(H.make_heightfield("bumps", "steep").mean_height) > 0   # bumps do not: the plane follows


# ---------------------------------------------------------------------------
# The convention test that matters: renders against the true mesh
# ---------------------------------------------------------------------------

def _render(hf, surface, bsdf, spp=64, res=64, seed=1):
    d = H.scene_dict(hf, surface, bsdf, "test_sun", "frontal", res, spp, max_depth=2,
                     verts_per_period=64)
    return H.render(d, spp, seed)


@pytest.mark.parametrize("kind", ["noise", "bumps"])
def test_classic_normal_map_on_the_plane_matches_the_true_mesh(kind):
    """Mild map (max tilt 28°), magnified (48 texels over 64 px), frontal orthographic view,
    diffuse, a directional sun 45° up at azimuth 30° (so x and y gradients both show; no facet
    faces away from it and no slope can cast a shadow: 28° < 45°), no sky, direct light only
    (max_depth 2: the true mesh's interreflections, ~2 % here, are the one thing classic normal
    mapping leaves out). Here classic normal mapping is exact up to interpolation: each pixel
    shows ρ/π·E·(n·l) with n the mesh's interpolated vertex normal (64 per period) or the map's
    bilinear texel normal (24 per period) at the same (x, y) — a frontal orthographic view has no
    parallax. Measured relMSE ~4e-5 (the normal interpolation; the noise is ~1e-8); tolerance 2e-4.
    Each wrong convention is ≥ 3.5e-3 (measured), asserted ≥ 20× the right one's error."""
    hf = H.make_heightfield(kind, "mild", periods=2)
    nested = H.MATERIALS["diffuse"]
    truth = _render(hf, "true", nested)
    nm = H.normal_map(hf, 48)

    def classic(img):
        bsdf = H.METHODS["classic"].bsdf(nested, H.bitmap_texture(np.ascontiguousarray(img)))
        return H.rel_mse(_render(hf, "plane", bsdf, seed=2), truth)

    right = classic(nm)
    assert right < 2e-4, right
    nomap = H.rel_mse(_render(hf, "plane", nested, seed=2), truth)
    assert nomap > 50 * right
    for name, bad in wrong_maps(nm).items():
        err = classic(bad)
        assert err > 20 * right and err > 2e-3, (name, err, right)


def test_bumpmap_on_the_baked_height_map_matches_the_true_mesh():
    """The height map's convention (the ``heightmap`` normal source's): Mitsuba's ``bumpmap`` (scale 1, heights in
    world units over u = x, v = 1 − y) reproduces the true mesh like the normal map does
    (measured 9e-5: bilinear heights have piecewise-constant gradients, so a little worse);
    inverted heights do not."""
    hf = H.make_heightfield("bumps", "mild", periods=2)
    nested = H.MATERIALS["diffuse"]
    truth = _render(hf, "true", nested)
    maps = {"heightmap": H.bitmap_texture(H.height_map(hf, 48))}
    right = H.rel_mse(_render(hf, "plane", H.METHODS["bumpmap"].bsdf(nested, None, maps), seed=2), truth)
    assert right < 5e-4, right
    inverted = {"type": "bumpmap", "bsdf": nested, "scale": -1.0, "texture": maps["heightmap"]}
    assert H.rel_mse(_render(hf, "plane", inverted, seed=2), truth) > 50 * right


# ---------------------------------------------------------------------------
# Methods as data, metrics, one cell end to end
# ---------------------------------------------------------------------------

def test_method_specs():
    m = H.method_from_spec("plugin:nonseparable:same,max_bounces=64,mis_boost_max=1.5")
    d = m.bsdf({"type": "diffuse"}, {"type": "bitmap"})
    assert d["type"] == "normalmap_microfacet" and d["model"] == "nonseparable"
    assert d["tangent_facet"] == "same" and d["max_bounces"] == 64 and d["mis_boost_max"] == 1.5
    assert "model" not in H.method_from_spec("plugin:").bsdf({}, {})      # the plugin's default
    assert H.method_from_spec("classic_fixed").bsdf({}, {})["use_shadowing_function"] is True
    assert H.method_from_spec("nomap").bsdf({"type": "diffuse"}, {}) == {"type": "diffuse"}
    with pytest.raises(ValueError):
        H.method_from_spec("nosuchmethod")


def test_metrics_definitions():
    rng = np.random.default_rng(0)
    truth = rng.uniform(0.2, 1.0, (8, 8, 3))
    m = H.metrics(truth, truth)
    assert m["rel_mse"] == 0 and m["ln_err"] == 0 and m["near_black"] == 0
    img = truth * 1.1
    y, yt = H.luminance(img), H.luminance(truth)
    k = 0.5 / yt.mean()
    f = 0.01 * np.median(yt)
    m = H.metrics(img, truth)
    assert m["rel_mse"] == pytest.approx(np.mean((img * k - truth * k) ** 2 / ((truth * k) ** 2 + 1e-2)))
    assert m["rel_mse_raw"] == pytest.approx(np.mean((img - truth) ** 2 / (truth ** 2 + 1e-2)))
    assert m["ln_err"] == pytest.approx(np.mean(np.abs(np.log((y + f) / (yt + f)))))
    assert m["contrast"] == pytest.approx(y.std() / y.mean())
    dark = img.copy()
    dark[:2] = 0.0
    assert H.metrics(dark, truth)["near_black"] == pytest.approx(0.25)
    assert H.block_mean(truth, 4).shape == (2, 2, 3)
    np.testing.assert_allclose(H.block_mean(truth, 4)[0, 0], truth[:4, :4].reshape(-1, 3).mean(0))


def test_render_cell_end_to_end_reports_a_missing_model():
    cell = H.Cell("eggcrate", "mild", "diffuse", "sky_sun", "grazing", "minified")
    methods = [H.METHODS["classic"], H.METHODS["analytic"], H.method_from_spec("plugin:no_such_model")]
    out = H.render_cell(cell, methods, res=16, spp=4, ref_factor=2)
    assert set(out["metrics"]) == {"classic", "analytic"}
    assert "no_such_model" in out["errors"]["no_such_model"]
    assert out["truth"].shape == (16, 16, 3) and np.isfinite(out["truth"]).all()
    assert out["block"] == 4 and out["ref_spp"] == 8
    for m in list(out["metrics"].values()) + [out["floor"]]:
        assert np.isfinite(m["rel_mse"]) and m["rel_mse"] >= 0
    # Fixed seeds: the same cell renders the same numbers.
    again = H.render_cell(cell, methods[:1], res=16, spp=4, ref_factor=2)
    assert again["metrics"]["classic"]["rel_mse"] == out["metrics"]["classic"]["rel_mse"]


def test_truth_scene_reuse_swaps_the_material_exactly():
    """render_cell keeps the last truth scene and swaps its mesh's BSDF for the next material:
    the same pixels as a freshly loaded scene."""
    for mat in ("diffuse", "gold", "plastic"):
        cell = H.Cell("bumps", "steep", mat, "sky_sun", "frontal", "magnified")
        reused = H.render(H._truth_scene(cell, 16, 4, 8), 4, 1)
        fresh = H.render(cell.truth_scene(16, 4, 8), 4, 1)
        np.testing.assert_array_equal(reused, fresh)
