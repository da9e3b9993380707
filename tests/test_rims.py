"""An object's rim on a coarse mesh: the camera sees a triangle whose interpolated (shading) normal
faces away from it. The default model sees the microsurface on the triangle there
(``normals/macro.py``, ``turned_normal``) instead of returning nothing; the paper's models are
unchanged (nothing there), and light tracing is unchanged: Mitsuba's ``ptracer`` drops the paths
whose camera side lies below the shading plane and above the triangle, whatever the BSDF returns.

The shading point: the shading frame is the identity, the triangle's normal 20° from it (toward +y);
the camera at ω_i = (0, 1, −0.2)/|·|, 11° below the shading plane and 9° above the triangle's."""

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import encode, make_bsdf, make_si, np1, np3, sph

TRIANGLE = np.array([0.0, np.sin(np.radians(20.0)), np.cos(np.radians(20.0))])
CAMERA = np.array([0.0, 1.0, -0.2]) / np.hypot(1.0, 0.2)
DIFFUSE = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.6}}
PLASTIC = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.3}
#: texels: flat, and 15° toward the camera's side, away from it, and across
TEXELS = encode(np.array([sph(0.0), sph(15.0, 0.5 * np.pi), sph(15.0, -0.5 * np.pi), sph(15.0, 0.0)]))


def rim_queries(n=256, seed=3):
    """(si, wo): ``n`` queries at the rim, on the texels in turn, lit from random directions above
    the triangle."""
    rng = np.random.default_rng(seed)
    si = make_si(np.broadcast_to(CAMERA, (n, 3)), len(TEXELS))
    si.n = mi.Normal3f(*(float(x) for x in TRIANGLE))
    wo = rng.normal(size=(n, 3))
    wo /= np.linalg.norm(wo, axis=1, keepdims=True)
    wo *= np.sign(wo @ TRIANGLE)[:, None]
    return si, mi.Vector3f(*(wo[:, k].astype(np.float32) for k in range(3)))


@pytest.mark.parametrize("nested", [DIFFUSE, PLASTIC], ids=["diffuse", "roughplastic"])
def test_the_default_sees_the_triangle_where_the_shading_normal_faces_away(nested):
    """Every texel shows light at the rim (it was black: the camera is below the shading plane),
    as much as the same microsurface on the triangle (``macro_normal="geometric"``) shows; its
    sample is consistent with its eval and pdf there."""
    si, wo = rim_queries()
    ctx = mi.BSDFContext()
    default = make_bsdf(nested, TEXELS)
    value = np3(default.eval(ctx, si, wo))
    on_triangle = np3(make_bsdf(nested, TEXELS, macro_normal="geometric").eval(ctx, si, wo))
    per_texel = value.mean(axis=1).reshape(-1, len(TEXELS)).mean(axis=0)
    assert np.all(per_texel > 0.01), per_texel
    np.testing.assert_allclose(value, on_triangle, rtol=1e-5, atol=1e-7)
    n = dr.width(si)
    bs, weight = default.sample(ctx, si, mi.Float(np.linspace(0.01, 0.99, n).astype(np.float32)),
                                mi.Point2f(np.random.default_rng(4).random((2, n)).astype(np.float32)))
    ok = np1(bs.pdf) > 0
    assert ok.mean() > 0.5
    f, p = default.eval_pdf(ctx, si, bs.wo)
    np.testing.assert_allclose(np1(p)[ok], np1(bs.pdf)[ok], rtol=1e-4)
    np.testing.assert_allclose(np3(weight)[ok], (np3(f) / np1(p)[:, None])[ok], rtol=1e-3, atol=1e-6)


@pytest.mark.parametrize("model", ["analytic", "nonseparable"])
def test_the_papers_models_are_unchanged_at_the_rim(model):
    si, wo = rim_queries(64)
    value = np3(make_bsdf(DIFFUSE, TEXELS, model=model).eval(mi.BSDFContext(), si, wo))
    assert np.all(value == 0.0)


def test_light_tracing_at_the_rim_is_unchanged():
    """In light tracing (the camera side is ω_o) the default returns nothing for a camera below the
    shading plane, as before: ``ptracer`` drops those paths itself."""
    si, wo = rim_queries(64)
    # light from above the shading plane at si.wi, the camera below it at wo
    light = make_si(np.broadcast_to(sph(40.0, 1.0), (64, 3)), len(TEXELS))
    light.n = si.n
    camera = mi.Vector3f(*(np.broadcast_to(CAMERA, (64, 3))[:, k].astype(np.float32) for k in range(3)))
    ctx = mi.BSDFContext(mi.TransportMode.Importance)
    assert np.all(np3(make_bsdf(DIFFUSE, TEXELS).eval(ctx, light, camera)) == 0.0)


def test_a_coarse_sphere_has_no_black_pixel_at_its_rim():
    """A 10 × 20 UV sphere whose vertex normals lean 0.25 toward +x (a coarse low-poly's normals
    disagree with its triangles), a flat map, diffuse, under a constant sky, seen from −x: all round
    its rim the normals lean away from the camera, and face away from it while the triangles face it.
    The default shows every pixel of the sphere lit (at least 20 % of the median); the paper's
    ``analytic``, which sees nothing below the shading plane, leaves 2.1 % of them black (the check
    that the rim is in the frame; so did the default without ``turned_normal``)."""
    from helpers import mesh, uv_sphere

    res = 64
    pos, normals, uv, faces = uv_sphere(10, 20, lean=0.25)
    flat = {"type": "bitmap", "bitmap": mi.Bitmap(np.full((4, 4, 3), [0.5, 0.5, 1.0], np.float32)), "raw": True}

    def scene(model):
        bsdf = {"type": "normalmap_microfacet", "model": model, "normalmap": flat, "bsdf": DIFFUSE}
        return mi.load_dict({
            "type": "scene", "integrator": {"type": "path", "max_depth": 2},
            "sensor": {"type": "perspective", "fov": 30.0,
                       "to_world": mi.ScalarTransform4f().look_at(origin=[-4.5, 0, 0], target=[0, 0, 0],
                                                                  up=[0, 0, 1]),
                       "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"}},
                       "sampler": {"type": "independent", "sample_count": 16}},
            "sky": {"type": "constant"}, "sphere": mesh("sphere", pos, normals, uv, faces, bsdf)})

    s = scene("faithful")
    ys, xs = np.mgrid[0:res, 0:res]
    # pixels whose whole footprint is on the sphere: all four corners' rays hit it
    hit = np.ones((res, res), bool)
    for dx, dy in ((0.05, 0.05), (0.95, 0.05), (0.05, 0.95), (0.95, 0.95)):
        p = mi.Point2f(((xs.ravel() + dx) / res).astype(np.float32), ((ys.ravel() + dy) / res).astype(np.float32))
        ray, _ = s.sensors()[0].sample_ray(0.0, 0.5, p, mi.Point2f(0.5, 0.5))
        hit &= np.array(s.ray_intersect(ray).is_valid()).reshape(res, res)
    lum = {m: np.asarray(mi.render(scene(m), seed=1)) @ np.array([0.2126, 0.7152, 0.0722])
           for m in ("faithful", "analytic")}
    dark = {m: float(np.mean(v[hit] < 0.2 * np.median(v[hit]))) for m, v in lum.items()}
    assert dark["faithful"] == 0.0, dark
    assert dark["analytic"] > 0.01, dark       # the rim is in the frame: without the turn it is black
