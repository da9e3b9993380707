"""Hostile map inputs: non-finite uv transforms, one-channel maps, maps given as file names, and
the plugin's other load-time refusals, replayed through the command line and the Python API.

Command line (the worker of tests/cli_worker.py, a child process: a crash or a hang fails the
test instead of taking pytest down): every case ends in exactly one ``mfnormal: error:`` line
with exit 2 and nothing written, or renders finite, non-negative pixels at most 1e6; SIGTERM and
Ctrl-C end a render within seconds and leave no file. Python API: the plugin's constructor (and
``mi.traverse`` updates) raise a ``ValueError`` whose message is one line naming the problem and
the fix.
"""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
import warnings
from pathlib import Path

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from cli_checks import assert_one_line_error  # noqa: E402
from helpers import write_maps, xml_scene  # noqa: E402

from variant import VARIANT  # noqa: E402
mi.set_variant(VARIANT)
mfnormal.register()

ROOT = Path(__file__).resolve().parents[1]
NON_FINITE = ("inf", "-inf", "nan")
RECTANGLE = '<shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/></transform>BSDF</shape>'
UV = '<transform name="to_uv"><scale x="$su" y="$sv"/></transform>'


def texture(name, extra=""):
    return (f'<texture type="bitmap" name="{name}"><string name="filename" value="$nm"/>'
            f'<boolean name="raw" value="true"/>{extra}</texture>')


def plugin(inner, wrap="PLUGIN"):
    return wrap.replace("PLUGIN", '<bsdf type="normalmap_microfacet"><string name="model" value="$model"/>'
                        '<string name="tangent_facet" value="$tf"/>' + inner + '<bsdf type="diffuse"/></bsdf>')


def scene(bsdf, **defaults):
    values = {"nm": "normalmap.png", "model": "faithful", "tf": "specular", "su": "1", "sv": "1", **defaults}
    return xml_scene(RECTANGLE.replace("BSDF", bsdf), values, spp="4", width="16", height="16")


TWOSIDED = '<bsdf type="twosided">PLUGIN</bsdf>'
SCENES = {
    "uv_normalmap.xml": scene(plugin(texture("normalmap", UV))),
    "uv_heightmap.xml": scene(plugin(texture("heightmap", UV)), nm="gray.png"),
    "uv_twosided.xml": scene(plugin(texture("normalmap", UV), TWOSIDED)),
    "uv_mitsuba.xml": scene('<bsdf type="normalmap">' + texture("normalmap", UV) + '<bsdf type="diffuse"/></bsdf>'),
    "map.xml": scene(plugin(texture("normalmap"))),
    "map_twosided.xml": scene(plugin(texture("normalmap"), TWOSIDED)),
    "mitsuba_twosided.xml": scene('<bsdf type="twosided"><bsdf type="normalmap">' + texture("normalmap")
                                  + '<bsdf type="diffuse"/></bsdf></bsdf>'),
    "string_map.xml": scene(plugin('<string name="$kind" value="$nm"/>'), kind="normalmap"),
    # Two shapes whose plugins nest a transmitting principled.
    "principled.xml": xml_scene("".join(
        RECTANGLE.replace("BSDF", plugin(texture("normalmap")).replace(
            '<bsdf type="diffuse"/>', f'<bsdf type="principled"><float name="spec_trans" value="{t}"/></bsdf>'))
        for t in (0.5, 0.8)), {"nm": "normalmap.png", "model": "faithful", "tf": "specular"}, spp="4",
        width="16", height="16"),
    "no_integrator.xml": scene(plugin(texture("normalmap"))).replace(
        '<integrator type="path"><integer name="max_depth" value="3"/></integrator>', ""),
}
# The models and tangent facets of the issue's rows: the walks hung, analytic and same gave garbage.
MODELS = [("faithful", "specular"), ("analytic", "specular"), ("separable", "specular"),
          ("nonseparable", "specular"), ("nonseparable", "same")]


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    d = tmp_path_factory.mktemp("hostile_inputs")
    write_maps(d)
    for name, text in SCENES.items():
        (d / name).write_text(text)
    return d


def render(worker, scenes, tmp_path, scene_name, *args):
    defines = [x for a in args if "=" in a and not a.startswith("-") for x in ("-D", a)]
    flags = [a for a in args if "=" not in a or a.startswith("-")]
    return worker.completed(["render", scene_name, *defines, *flags, "-o", tmp_path / "out"], cwd=scenes,
                            timeout=120)


def assert_refused(proc, tmp_path, *needles):
    assert_one_line_error(proc, *needles)
    assert proc.returncode == 2
    assert not list(tmp_path.iterdir()), "written despite the error"


@pytest.mark.parametrize("model,tf", MODELS)
@pytest.mark.parametrize("value", NON_FINITE)
def test_non_finite_uv_transform_of_a_normal_map_is_refused(worker, scenes, tmp_path, model, tf, value):
    proc = render(worker, scenes, tmp_path, "uv_normalmap.xml", f"su={value}", f"model={model}", f"tf={tf}")
    assert_refused(proc, tmp_path, "to_uv", "NaN or infinity", "finite")


@pytest.mark.parametrize("scene_name,args", [("uv_heightmap.xml", ["su=inf"]), ("uv_heightmap.xml", ["sv=-inf"]),
                                             ("uv_heightmap.xml", ["su=nan"]),
                                             ("uv_twosided.xml", ["su=nan", "model=separable"]),
                                             ("uv_mitsuba.xml", ["su=inf"])])
def test_non_finite_uv_transform_is_refused_for_height_maps_nested_and_mitsubas_normalmap(
        worker, scenes, tmp_path, scene_name, args):
    """A height map's gradient lookup crashed the process; nested in twosided and in Mitsuba's own
    normalmap the scene check refuses the transform before the render."""
    assert_refused(render(worker, scenes, tmp_path, scene_name, *args), tmp_path, "to_uv", "NaN or infinity")


@pytest.mark.parametrize("scene_name", ["map.xml", "map_twosided.xml", "mitsuba_twosided.xml"])
@pytest.mark.parametrize("model", ["faithful", "separable"])
def test_one_channel_normal_map_is_refused_with_its_channel_count(worker, scenes, tmp_path, scene_name, model):
    model_args = [] if scene_name.startswith("mitsuba") else [f"model={model}"]   # (no $model there)
    proc = render(worker, scenes, tmp_path, scene_name, "nm=gray.png", *model_args)
    assert_refused(proc, tmp_path, "gray.png", "has 1 channel", "needs 3 (RGB)")


@pytest.mark.parametrize("kind,image", [("normalmap", "normalmap.png"), ("heightmap", "gray.png")])
def test_string_form_maps_obey_the_image_limits(worker, scenes, tmp_path, kind, image):
    """``<string name="normalmap" value="..."/>`` (and ``heightmap``) is checked like a texture's
    ``filename``: the 8×8 map is over ``image_pixels=10`` and ``texture_pixels=10``, and renders
    with the default limits."""
    args = [f"kind={kind}", f"nm={image}"]
    for limit in ("image_pixels", "texture_pixels"):
        proc = render(worker, scenes, tmp_path, "string_map.xml", *args, f"--limit={limit}=10")
        assert_refused(proc, tmp_path, image, f"--limit {limit}=N")
    proc = render(worker, scenes, tmp_path, "string_map.xml", *args)
    assert proc.returncode == 0, proc.stderr
    img = np.array(mi.Bitmap(str(tmp_path / "out.exr")), dtype=np.float64)
    assert np.all(np.isfinite(img)) and img.min() >= 0 and img.max() <= 1e6 and img.mean() > 0.01


def test_transmitting_nested_bsdf_renders_without_a_warning(worker, scenes, tmp_path):
    """Two plugins nesting a ``principled`` that transmits: rendered by the default model, which
    refracts, with nothing on stderr (before: a warning that its transmission was dropped)."""
    proc = render(worker, scenes, tmp_path, "principled.xml")
    assert proc.returncode == 0, proc.stderr
    assert proc.stderr.strip() == "", proc.stderr


def test_scene_without_integrator_is_refused_before_the_render(worker, scenes, tmp_path):
    proc = render(worker, scenes, tmp_path, "no_integrator.xml")
    assert_refused(proc, tmp_path, "no integrator", "<integrator type=\"path\"/>")


# -- The Python API -------------------------------------------------------------------------------


def bitmap(texels, **extra):
    return {"type": "bitmap", "raw": True, "bitmap": mi.Bitmap(np.asarray(texels, np.float32)), **extra}


RGB_MAP = np.full((4, 4, 3), (0.6, 0.45, 0.9), np.float32)


def load_error(spec) -> str:
    """The innermost message of the error ``mi.load_dict(spec)`` raises."""
    with pytest.raises(Exception) as info:
        mi.load_dict(spec)
    return str(info.value).strip().splitlines()[-1]


@pytest.mark.parametrize("kind", ["normalmap", "heightmap"])
@pytest.mark.parametrize("scale", [[float("inf"), 1, 1], [1, float("nan"), 1], [-float("inf"), 2, 1]])
def test_plugin_refuses_a_non_finite_to_uv_at_load(kind, scale):
    texels = RGB_MAP if kind == "normalmap" else RGB_MAP[..., :1]
    spec = {"type": "normalmap_microfacet", kind: bitmap(texels, to_uv=mi.ScalarTransform4f().scale(scale)),
            "bsdf": {"type": "diffuse"}}
    for wrapped in (spec, {"type": "twosided", "b": spec}):
        msg = load_error(wrapped)
        assert msg.startswith("ValueError: normalmap_microfacet:") and "to_uv" in msg and "finite" in msg, msg


def test_traverse_update_to_a_non_finite_to_uv_is_refused_and_undone():
    plugin = mi.load_dict({"type": "normalmap_microfacet", "model": "analytic", "bsdf": {"type": "diffuse"},
                           "normalmap": bitmap(RGB_MAP, to_uv=mi.ScalarTransform4f().scale([2, 2, 1]))})
    params = mi.traverse(plugin)
    before = np.array(params["normalmap.to_uv"].matrix)
    params["normalmap.to_uv"] = mi.ScalarTransform3f().scale([float("inf"), 1])
    with pytest.raises(ValueError, match="to_uv holds NaN or infinity"):
        params.update()
    assert np.array_equal(np.array(mi.traverse(plugin)["normalmap.to_uv"].matrix), before)


def test_non_finite_uv_gives_finite_values_and_ends():
    """A NaN or infinite surface uv (a mesh's texture coordinates) is looked up as uv = 0: before,
    the bitmap read outside its data and the walks' loops never ended. Every model, eval and
    sample, finite and non-negative; with NaN in ω_i or in the shading frame on some lanes too
    (the walks' loops end by their bounce cap whatever the numbers)."""
    n = 64
    k = dr.arange(mi.UInt32, n)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.uv = mi.Point2f(dr.select(k % 2 == 0, dr.nan, dr.inf), 0.25)
    si.wi = dr.select(k % 8 == 1, mi.Vector3f(dr.nan, 0.2, 1.0), dr.normalize(mi.Vector3f(0.3, 0.2, 1.0)))
    si.sh_frame = mi.Frame3f(dr.select(k % 8 == 3, mi.Vector3f(dr.nan, 0, 1), mi.Vector3f(0, 0, 1)))
    si.dp_du, si.dp_dv = mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0)
    ctx = mi.BSDFContext()
    for model, tf in MODELS:
        for kind, texels in (("normalmap", RGB_MAP), ("heightmap", RGB_MAP[..., :1])):
            plugin = mi.load_dict({"type": "normalmap_microfacet", "model": model, "tangent_facet": tf,
                                   kind: bitmap(texels), "bsdf": {"type": "diffuse"}})
            value = plugin.eval(ctx, si, dr.normalize(mi.Vector3f(-0.3, 0.1, 1.0)))
            bs, weight = plugin.sample(ctx, si, mi.Float(0.3), mi.Point2f(0.4, 0.6))
            for x in (value, weight, bs.wo):
                a = np.array(x)
                assert np.all(np.isfinite(a)), (model, tf, kind)
            assert np.array(value).min() >= 0 and np.array(weight).min() >= 0


@pytest.mark.parametrize("model", ["faithful", "analytic", "separable"])
def test_one_channel_normal_map_is_one_clear_error_for_every_model(model):
    msg = load_error({"type": "normalmap_microfacet", "model": model, "normalmap": bitmap(RGB_MAP[..., :1]),
                      "bsdf": {"type": "diffuse"}})
    assert msg.startswith("ValueError: normalmap_microfacet:") and "has 1 channel" in msg and "needs 3" in msg, msg


def test_normalmap_given_a_bsdf_says_it_must_be_a_texture():
    msg = load_error({"type": "normalmap_microfacet", "normalmap": {"type": "diffuse"}, "bsdf": {"type": "diffuse"}})
    assert "'normalmap' is a BSDF" in msg and "must be a texture" in msg, msg


@pytest.mark.parametrize("key,value,model", [("strength", mi.Float([1.0, 2.0]), "analytic"),
                                             ("max_bounces", mi.Int32([1, 2]), "separable"),
                                             ("mis_boost_max", mi.Float([2.0, 3.0]), "nonseparable")])
def test_traverse_refuses_a_wide_array_and_keeps_the_value(key, value, model):
    plugin = mi.load_dict({"type": "normalmap_microfacet", "model": model, "normalmap": bitmap(RGB_MAP),
                           "bsdf": {"type": "diffuse"}})
    params = mi.traverse(plugin)
    before = np.array(params[key]).tolist()
    params[key] = value
    with pytest.raises(ValueError, match=f"{key} must be one number"):
        params.update()
    assert np.array(mi.traverse(plugin)[key]).tolist() == before


def test_transmitting_nested_bsdf_loads_without_a_warning():
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        plugin = mi.load_dict({"type": "normalmap_microfacet", "normalmap": bitmap(RGB_MAP),
                               "bsdf": {"type": "principled", "spec_trans": 0.5}})
    assert not [w for w in caught if "normalmap_microfacet" in str(w.message)], [str(w.message) for w in caught]
    assert mi.has_flag(plugin.flags(), mi.BSDFFlags.Transmission)


def test_polarized_variant_is_refused_at_load():
    """In a process of its own (the variant is global)."""
    if "llvm_ad_mono_polarized" not in mi.variants():
        pytest.skip("no llvm_ad_mono_polarized in this Mitsuba build")
    code = ("import mfnormal, mitsuba as mi\nmi.set_variant('llvm_ad_mono_polarized'); mfnormal.register()\n"
            "try:\n    mi.load_dict({'type': 'normalmap_microfacet', 'normalmap': 'x.png', 'bsdf': {'type': 'diffuse'}})\n"
            "except Exception as e:\n    print(str(e).strip().splitlines()[-1])\n")
    out = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, timeout=120)
    assert "does not support polarized variants" in out.stdout, out.stdout + out.stderr


# -- SIGTERM and Ctrl-C during a render -----------------------------------------------------------------


def test_signals_end_the_process_during_a_pass_and_are_restored_after():
    """In a child: inside ``signals_end_the_process`` SIGTERM ends the process at once (a native
    call that Python's handlers could not interrupt: here a blocking read); after the block the
    handlers before it are back. Outside the main thread it changes nothing."""
    code = ("import signal, sys, os, threading\nfrom mfnormal.render.passes import signals_end_the_process\n"
            "mine = lambda *a: None\nsignal.signal(signal.SIGTERM, mine)\n"
            "with signals_end_the_process(False):\n    assert signal.getsignal(signal.SIGTERM) is mine\n"
            "def other():\n    with signals_end_the_process():\n        assert signal.getsignal(signal.SIGTERM) is mine\n"
            "t = threading.Thread(target=other); t.start(); t.join()\n"
            "with signals_end_the_process():\n    assert signal.getsignal(signal.SIGTERM) == signal.SIG_DFL\n"
            "assert signal.getsignal(signal.SIGTERM) is mine\n"
            "with signals_end_the_process():\n    print('ready', flush=True)\n    os.read(0, 1)\n"
            "print('survived', flush=True)\n")
    proc = subprocess.Popen([sys.executable, "-c", code], stdin=subprocess.PIPE, stdout=subprocess.PIPE,
                            stderr=subprocess.PIPE, text=True)
    assert proc.stdout.readline().strip() == "ready", proc.stderr.read()
    proc.send_signal(signal.SIGTERM)
    out, err = proc.communicate(timeout=10)
    assert proc.returncode == -signal.SIGTERM, (proc.returncode, out, err)
    assert "survived" not in out


@pytest.mark.slow
@pytest.mark.parametrize("sig", ["SIGTERM", "SIGINT"])
def test_a_long_render_ends_within_seconds_of_a_signal_and_leaves_no_file(scenes, tmp_path, sig):
    """``mfnormal render`` of a render that takes many minutes (512², 4096 spp: passes of 2^24
    paths, the non-separable walk, 16 bounces inside a closed, glowing sphere), signalled after
    15 s (loading or rendering: either way): it ends within 5 s, by the signal or with exit
    130/143, and writes nothing. Measured on 2 shared cores: 0.1 s during a pass; before, the
    signal waited for the end of the pass (10.6 s for a 2^24-lane pass of an open scene)."""
    box = ('<shape type="sphere"><float name="radius" value="20"/><emitter type="area"><rgb name="radiance" '
           'value="0.2"/></emitter><bsdf type="twosided"><bsdf type="diffuse"/></bsdf></shape>')
    big = SCENES["map.xml"].replace('name="width" value="16"', 'name="width" value="512"').replace(
        'name="height" value="16"', 'name="height" value="512"').replace(
        '<integer name="max_depth" value="3"/>', '<integer name="max_depth" value="16"/>').replace(
        "</scene>", box + "</scene>")
    (scenes / "big.xml").write_text(big)
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    proc = subprocess.Popen([sys.executable, "-m", "mfnormal", "render", "big.xml", "-D", "model=nonseparable",
                             "--spp", "4096", "-o", str(tmp_path / "out")], cwd=scenes, env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True)
    time.sleep(15)
    assert proc.poll() is None, proc.communicate()
    start = time.monotonic()
    proc.send_signal(getattr(signal, sig))
    out, err = proc.communicate(timeout=60)
    assert time.monotonic() - start < 5.0
    assert proc.returncode in (-getattr(signal, sig), 130, 143), (proc.returncode, err)
    assert "Traceback" not in err and not list(tmp_path.iterdir())
