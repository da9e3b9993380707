"""A normal map read as sRGB colour (Mitsuba's ``bitmap`` without ``raw``): its vectors are bent
by the sRGB curve (a flat texel (0.5, 0.5, 1) decodes 39° tilted), so the plugin refuses it in one
line naming the file and ``raw``, through the Python API and the command line; a float OpenEXR
map, which Mitsuba reads as linear whatever ``raw`` says, is taken as it is. From Python, a float
Bitmap of a numpy array is linear and taken; an 8-bit one is marked sRGB and refused without raw."""

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import math

import mitsuba as mi
import numpy as np
import pytest
from cli_checks import assert_error_line
from helpers import write_maps, xml_scene


def plugin(filename, **texture):
    return {"type": "normalmap_microfacet", "bsdf": {"type": "diffuse"},
            "normalmap": {"type": "bitmap", "filename": str(filename), **texture}}


def test_an_srgb_read_map_is_refused_in_one_line(tmp_path):
    write_maps(tmp_path)
    with pytest.raises(Exception) as info:
        mi.load_dict(plugin(tmp_path / "normalmap.png"))
    line = str(info.value).strip().splitlines()[-1]
    assert "normalmap.png" in line and "raw=True" in line and "sRGB" in line, line
    mi.load_dict(plugin(tmp_path / "normalmap.png", raw=True))       # the same map, raw: accepted


def test_the_tilt_the_message_names_is_what_srgb_decoding_does(tmp_path):
    """Mitsuba's bitmap without raw, at a flat texel (128, 128, 255), decoded as a normal: 39°."""
    write_maps(tmp_path)
    texture = mi.load_dict({"type": "bitmap", "filename": str(tmp_path / "normalmap.png"), "filter_type": "nearest"})
    si = mi.SurfaceInteraction3f()
    si.uv = mi.Point2f(0.05, 0.05)                   # a corner texel: flat
    n = 2.0 * np.array(texture.eval(si)).ravel() - 1.0
    assert math.degrees(math.acos(n[2] / np.linalg.norm(n))) == pytest.approx(39, abs=0.5)


def test_a_float_exr_map_is_linear_without_raw(tmp_path):
    texels = np.zeros((4, 4, 3), np.float32)
    texels[...] = (0.5, 0.5, 1.0)
    mi.Bitmap(texels).write(str(tmp_path / "flat.exr"))
    mi.load_dict(plugin(tmp_path / "flat.exr"))


def test_the_command_line_refuses_an_srgb_read_map_in_one_line(worker, tmp_path):
    write_maps(tmp_path)
    shape = ('<shape type="rectangle"><bsdf type="normalmap_microfacet"><texture type="bitmap" name="normalmap">'
             '<string name="filename" value="normalmap.png"/></texture><bsdf type="diffuse"/></bsdf></shape>')
    (tmp_path / "scene.xml").write_text(xml_scene(shape, {}))
    result = worker.run(["render", "scene.xml", "-o", "out.exr"], cwd=tmp_path)
    assert_error_line(result, "normalmap.png", "raw")
    assert not (tmp_path / "out.exr").exists()


def bitmap_plugin(texels, **texture):
    return {"type": "normalmap_microfacet", "bsdf": {"type": "diffuse"},
            "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(texels), **texture}}


def test_a_linear_float_bitmap_from_python_is_taken_without_raw():
    """A float Bitmap built from numpy is linear: Mitsuba's bitmap looks its texels up as they are
    with raw false too (a flat texel stays flat), so it is taken (it was refused as sRGB, its name
    empty)."""
    texels = np.zeros((4, 4, 3), np.float32)
    texels[...] = (0.5, 0.5, 1.0)
    texels[1, 2] = (0.8, 0.3, 0.9)
    texture = mi.load_dict({"type": "bitmap", "bitmap": mi.Bitmap(texels), "filter_type": "nearest"})
    si = mi.SurfaceInteraction3f()
    si.uv = mi.Point2f(0.125, 0.125)
    assert np.allclose(np.array(texture.eval(si)).ravel(), (0.5, 0.5, 1.0))
    mi.load_dict(bitmap_plugin(texels))


def test_an_8_bit_bitmap_from_python_is_srgb_and_refused_without_raw():
    """An 8-bit Bitmap built from numpy is marked sRGB: without raw its lookups are decoded (128
    reads 0.216), so it is refused in one line naming raw; with raw=True it is taken."""
    texels = np.full((4, 4, 3), 128, np.uint8)
    texels[..., 2] = 255
    with pytest.raises(Exception) as info:
        mi.load_dict(bitmap_plugin(texels))
    line = str(info.value).strip().splitlines()[-1]
    assert "Bitmap marked sRGB" in line and "raw=True" in line, line
    mi.load_dict(bitmap_plugin(texels, raw=True))
