"""End-to-end renders with the ``normalmap_microfacet`` plugin in llvm_ad_rgb.

Small scenes at low resolution and sample counts: they check that whole images
come out finite and lit (not that they are converged), plus the bundled demo
(``mfnormal.cli.demo``): its command line (``mfnormal demo``, ``mfnormal-demo``), its XML scene and
the dict built from it.
"""

import numpy as np
import pytest

import mfnormal  # noqa: F401  (picks a working libLLVM before mitsuba loads)
import mitsuba as mi
from variant import VARIANT  # noqa: E402  (MFNORMAL_VARIANT, tests/variant.py)

mi.set_variant(VARIANT)
mfnormal.register()

from helpers import bumps_normalmap, light_tracing_agrees, small_scene  # noqa: E402
from mfnormal.scenes import assets  # noqa: E402
from mfnormal.cli import commands as cli, demo
from mfnormal.methods import PLUGIN  # noqa: E402
from mfnormal.io.scene_xml import dicts_of_type  # noqa: E402


def test_plugin_scene_renders_finite_and_lit():
    img = np.array(mi.render(mi.load_dict(small_scene(bumps_normalmap())), seed=1))
    assert img.shape == (36, 48, 3)
    assert np.all(np.isfinite(img))
    assert img.min() >= 0.0
    assert img.mean() > 0.1
    lum = img.mean(axis=-1)
    assert np.mean(lum > 0) > 0.99      # sky, sphere and ground: every pixel gets light
    # the bumps are visible: the normal-mapped ground is not a flat shade
    ground = lum[-8:]
    assert ground.std() > 0.01 * ground.mean()


def test_demo_scene_dict_matches_xml(tmp_path):
    """demo_scene() (dict built from scenes/demo.xml) renders the same image as
    mi.load_file() of the XML with the same parameters."""
    kw = dict(spp=2, resolution=(24, 18))
    scene_dict = demo.demo_scene(assets_dir=tmp_path, **kw)
    assert len(list(dicts_of_type(scene_dict, PLUGIN))) == 2
    params = demo.scene_parameters(assets={"normalmap": tmp_path / assets.TILES_NAME,
                                           "envmap": tmp_path / assets.ENVMAP_NAME}, **kw)
    from_dict = np.array(mi.render(mi.load_dict(scene_dict), seed=3))
    from_xml = np.array(mi.render(mi.load_file(str(assets.DEMO_XML), **params), seed=3))
    assert from_dict.shape == (18, 24, 3)
    assert np.all(np.isfinite(from_dict)) and from_dict.mean() > 0.05
    np.testing.assert_allclose(from_dict, from_xml, rtol=1e-5, atol=1e-6)


def test_demo_scene_options(tmp_path):
    nested = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.25}}
    scene = demo.demo_scene(bsdf=nested, strength=0.5, assets_dir=tmp_path)
    mats = list(dicts_of_type(scene, PLUGIN))
    assert len(mats) == 2
    assert all(m["bsdf"] == nested and m["strength"] == 0.5 for m in mats)
    assert mats[0]["bsdf"] is not mats[1]["bsdf"]
    classic = demo.demo_scene(model="classic", assets_dir=tmp_path)
    shapes = [classic["sphere"], classic["ground"]]
    types = [v["type"] for s in shapes for v in s.values() if isinstance(v, dict)]
    assert types.count("normalmap") == 2 and "normalmap_microfacet" not in types


def test_demo_assets(tmp_path):
    paths = assets.generate_demo_assets(tmp_path)
    nm = np.array(mi.Bitmap(str(paths["normalmap"])))
    assert nm.shape == (512, 512, 3) and nm.dtype == np.uint8
    n = nm.astype(np.float64) / 255.0 * 2.0 - 1.0
    assert np.allclose(np.linalg.norm(n, axis=-1), 1.0, atol=0.02)   # unit normals
    assert n[..., 2].min() < 0.2                                    # strong: near-horizon tilts
    env = np.array(mi.Bitmap(str(paths["envmap"])))
    assert env.shape == (128, 256, 3) and np.all(np.isfinite(env)) and env.min() > 0
    assert env.max() > 100 * np.median(env)                         # a sun


def test_demo_main_writes_exr_and_png(tmp_path, capsys):
    out = tmp_path / "sub" / "demo.png"
    rc = cli.demo_main(["-o", str(out), "--spp", "2", "--resolution", "40x30"])
    assert rc == 0
    exr, png = tmp_path / "sub" / "demo.exr", tmp_path / "sub" / "demo.png"
    assert exr.is_file() and png.is_file()
    lin = np.array(mi.Bitmap(str(exr)))
    srgb = np.array(mi.Bitmap(str(png)))
    assert lin.shape[:2] == (30, 40) and srgb.shape[:2] == (30, 40)
    assert srgb.dtype == np.uint8
    assert np.all(np.isfinite(lin)) and lin.mean() > 0.05
    assert srgb.mean() > 20
    assert not [p.name for p in (tmp_path / "sub").iterdir() if p.name.startswith(".")]
    printed = capsys.readouterr().out
    assert "llvm_ad_rgb" in printed and str(mfnormal.LLVM_PATH) in printed
    assert str(png) in printed and str(exr) in printed


WALKS = [("separable", "specular"), ("separable", "same"),
         ("nonseparable", "specular"), ("nonseparable", "same")]


def furnace_scene(model, tangent_facet, spp, size):
    """A white normal-mapped sphere inside a uniform white environment."""
    bsdf = {"type": "normalmap_microfacet", "model": model,
            "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(bumps_normalmap(cells=3, radius=0.45)),
                          "raw": True},
            "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": 1.0}}}
    if model not in ("analytic", "faithful"):
        bsdf["tangent_facet"] = tangent_facet
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 4},
        "sensor": {"type": "perspective", "fov": 30,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 4.5], target=[0, 0, 0], up=[0, 1, 0]),
                   "sampler": {"type": "independent", "sample_count": spp},
                   "film": {"type": "hdrfilm", "width": size, "height": size, "rfilter": {"type": "box"}}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 1.0}},
        "sphere": {"type": "sphere", "bsdf": bsdf},
    }


def sphere_pixels(size):
    """Pixels whose whole footprint lies on the sphere (radius 1 at distance 4.5, fov 30°)."""
    c = (np.arange(size) + 0.5) / size * 2 - 1
    x, y = np.meshgrid(c, c)
    tan_half = np.tan(np.radians(15))
    r_img = np.sin(np.arcsin(1 / 4.5)) / np.cos(np.arcsin(1 / 4.5)) / tan_half
    return np.hypot(x, y) < 0.85 * r_img


@pytest.mark.parametrize("model, tangent_facet", [("faithful", None)] + WALKS)
def test_energy_conserving_models_keep_a_white_sphere_white_in_a_furnace(model, tangent_facet):
    """Energy conservation through Mitsuba's path integrator, MIS included.

    Every pixel on a white, energy-conserving sphere in a uniform environment of
    radiance 1 has expected value 1, whatever the (approximate) MIS pdf, as long
    as BSDF sampling, eval and MIS are consistent. The mean over ~200 sphere
    pixels × 64 spp has a standard error below 0.3 %; we allow 1.5 %.
    """
    size = 24
    img = np.array(mi.render(mi.load_dict(furnace_scene(model, tangent_facet, 64, size)), seed=3))
    assert np.all(np.isfinite(img))
    on_sphere = img[sphere_pixels(size)].mean(axis=-1)
    assert on_sphere.size > 150
    assert abs(on_sphere.mean() - 1.0) < 0.015, on_sphere.mean()


def test_analytic_model_darkens_but_never_blackens_a_white_sphere():
    """The analytic model drops ≥ 3-bounce paths: below 1, but no black pixels."""
    size = 24
    img = np.array(mi.render(mi.load_dict(furnace_scene("analytic", "specular", 16, size)), seed=3))
    on_sphere = img[sphere_pixels(size)].mean(axis=-1)
    assert 0.5 < on_sphere.mean() < 0.99
    assert on_sphere.min() > 0.05


@pytest.mark.parametrize("model, tangent_facet", [("faithful", None), ("analytic", "specular")] + WALKS)
def test_every_model_renders_in_scalar_rgb(model, tangent_facet):
    """The plugin also runs in a scalar variant (as a slow reference)."""
    mi.set_variant("scalar_rgb")
    mfnormal.register()
    try:
        img = np.array(mi.render(mi.load_dict(furnace_scene(model, tangent_facet, 2, 6)), seed=1))
    finally:
        mi.set_variant(VARIANT)
        mfnormal.register()
    assert np.all(np.isfinite(img)) and img.min() >= 0
    assert img.mean() > 0.3


def light_tracing_scene(integrator, model, nested):
    """A normal-mapped plane (bumps, tilts to ~65°) under a small spherical light, seen at 35°."""
    return mi.load_dict({
        "type": "scene", "integrator": {"type": integrator, "max_depth": 3},
        "sensor": {"type": "perspective", "fov": 40,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, -2.2, 1.6], target=[0, 0, 0], up=[0, 0, 1]),
                   "film": {"type": "hdrfilm", "width": 32, "height": 24, "rfilter": {"type": "box"}},
                   "sampler": {"type": "independent"}},
        "plane": {"type": "rectangle",
                  "bsdf": {"type": "normalmap_microfacet", "model": model, "bsdf": nested,
                           "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(bumps_normalmap(64, 3)),
                                         "raw": True}}},
        "light": {"type": "sphere", "center": [1.2, -0.4, 0.9], "radius": 0.25,
                  "emitter": {"type": "area", "radiance": {"type": "rgb", "value": 8.0}}}})


@pytest.mark.parametrize("nested", [
    {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.7, 0.6, 0.5]}},
    {"type": "roughconductor", "alpha": 0.3}], ids=["diffuse", "ggx0.3"])
def test_path_tracing_equals_light_tracing_for_the_default_model(nested):
    """The faithful model is not reciprocal; light tracing (Mitsuba's ptracer, which asks
    for the adjoint BSDF) must still give path tracing's image. 8 renders × 128 spp of each;
    on 4×4-pixel blocks, Welch's t test of the difference (variances from the render-to-render
    spread, Welch-Satterthwaite degrees of freedom): no block below the Šidák-corrected 1 %
    family-wise level; and the image means agree within 1 %. (With 4 renders the t statistic
    has 3-6 degrees of freedom and a fixed 4.5σ bound fails by chance: seen at 4.65 on a block
    that 12 renders put at 0.8σ.)"""
    n = 8
    imgs = {k: np.array([np.array(mi.render(light_tracing_scene(k, "faithful", nested), spp=128, seed=s))
                         for s in range(n)]) for k in ("path", "ptracer")}
    p_values, z, ratio = light_tracing_agrees(imgs)
    assert len(p_values) > 20
    assert p_values.min() > 1.0 - 0.99 ** (1.0 / len(p_values)), (p_values.min(), z.max())
    assert abs(ratio - 1.0) < 0.01, ratio


def test_albedo_aov_is_the_nested_bsdfs_albedo_through_the_map():
    """The ``aov`` integrator's ``albedo`` (what denoisers read) of a normal-mapped textured
    diffuse is the diffuse's own albedo at each hit: the plugin forwards
    ``eval_diffuse_reflectance`` to the nested BSDF (Mitsuba's default would be the plugin's
    ``eval`` toward its normal times π, which the bumps darken)."""
    reflectance = {"type": "checkerboard", "color0": {"type": "rgb", "value": [0.8, 0.2, 0.1]},
                   "color1": {"type": "rgb", "value": [0.1, 0.3, 0.9]}}

    def albedo(bsdf):
        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": "aov", "aovs": "albedo:albedo"},
            "sensor": {"type": "perspective",
                       "to_world": mi.ScalarTransform4f().look_at([0, -2, 2], [0, 0, 0], [0, 0, 1]),
                       "film": {"type": "hdrfilm", "width": 24, "height": 24, "pixel_format": "rgb"},
                       "sampler": {"type": "independent", "sample_count": 1}},
            "plane": {"type": "rectangle", "bsdf": bsdf}})
        return np.array(mi.render(scene, seed=0))

    nested = {"type": "diffuse", "reflectance": reflectance}
    mapped = {"type": "normalmap_microfacet", "bsdf": nested, "normalmap": {
        "type": "bitmap", "bitmap": mi.Bitmap(bumps_normalmap(32, cells=2, radius=0.45)), "raw": True}}
    own, through_map = albedo(nested), albedo(mapped)
    assert own.max() > 0.5 and own.min() >= 0.0     # the plane fills the view, the checks show
    np.testing.assert_allclose(through_map, own, rtol=1e-6, atol=1e-7)
