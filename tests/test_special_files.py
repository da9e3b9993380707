"""Files that are not regular files: ``mfnormal render`` and ``compare`` refuse them before
anything opens them.

Opening a FIFO for reading blocks until a writer comes (Mitsuba's loader thread then
ignores SIGTERM and Ctrl-C), reading a device may never end, and a folder fails deep in
a loader. Every file an XML scene names — the scene itself, an ``<include>``, a
texture's ``filename``, the plugin's ``normalmap`` and ``heightmap`` strings — is checked
with ``os.stat`` (links followed) and refused in one line, exit 2, nothing written. The
commands run in the module's command-line worker (tests/cli_worker.py) with a time
bound: a check that lets Mitsuba open the FIFO fails the test by timing out instead of
hanging the suite. Nothing ever writes into the FIFOs.
"""

from __future__ import annotations

import os
from pathlib import Path

import pytest
from cli_checks import assert_one_line_error
from helpers import write_maps, xml_plugin, xml_scene

pytestmark = pytest.mark.skipif(not hasattr(os, "mkfifo"), reason="no FIFOs on this system")

#: Seconds a refused case may take (the worker imports Mitsuba on its first request).
TIMEOUT = 90
SHAPE = '<shape type="sphere">{}</shape>'
STRING_MAP = ('<bsdf type="normalmap_microfacet"><string name="{}" value="{}"/>'
              '<bsdf type="diffuse"/></bsdf>')


def _scene(folder: Path, shapes: str, name: str = "scene.xml", **defaults) -> Path:
    path = folder / name
    path.write_text(xml_scene(shapes, {"nm": "normalmap.png", "model": "faithful", **defaults}, spp="1",
                              width="8", height="6"))
    return path


@pytest.fixture
def files(tmp_path):
    """A folder with maps, a FIFO, a link to it, a folder, and scenes that name each."""
    write_maps(tmp_path)
    os.mkfifo(tmp_path / "pipe.png")
    os.mkfifo(tmp_path / "pipe.xml")
    (tmp_path / "link.png").symlink_to("pipe.png")
    (tmp_path / "folder.png").mkdir()
    return tmp_path


def _run(worker, folder: Path, *args):
    proc = worker.completed(list(args), folder, timeout=TIMEOUT)
    assert proc.returncode == 2, proc.stdout + proc.stderr
    assert not any(p.name.startswith("out") for p in folder.iterdir())
    return proc


CASES = {
    # name: (the scene's shapes and -D values, words the error must hold)
    "texture_fifo": (SHAPE.format(xml_plugin()), ["-D", "nm=pipe.png"],
                     ["'pipe.png'", "is a FIFO (named pipe), not a regular file"]),
    "texture_link_to_fifo": (SHAPE.format(xml_plugin()), ["-D", "nm=link.png"],
                             ["'link.png'", "is a FIFO"]),
    "texture_device": (SHAPE.format(xml_plugin()), ["-D", "nm=/dev/zero"],
                       ["'/dev/zero'", "is a character device"]),
    "texture_folder": (SHAPE.format(xml_plugin()), ["-D", "nm=folder.png"],
                       ["'folder.png'", "is a folder"]),
    "normalmap_string_fifo": (SHAPE.format(STRING_MAP.format("normalmap", "pipe.png")), [],
                              ['<string name="normalmap"> \'pipe.png\'', "is a FIFO"]),
    "heightmap_string_link": (SHAPE.format(STRING_MAP.format("heightmap", "link.png")), [],
                              ['<string name="heightmap"> \'link.png\'', "is a FIFO"]),
    "include_fifo": ('<include filename="pipe.xml"/>', [],
                     ["<include filename> 'pipe.xml'", "is a FIFO"]),
}


@pytest.mark.parametrize("case", CASES)
def test_render_refuses_a_named_file_that_is_not_regular(worker, files, case):
    shapes, defines, needles = CASES[case]
    scene = _scene(files, shapes)
    proc = _run(worker, files, "render", scene, "-o", files / "out", *defines)
    assert_one_line_error(proc, "scene.xml: ", *needles)


def test_an_include_inside_an_include_is_checked_too(worker, files):
    _scene(files, '<include filename="pipe.xml"/>', name="inner.xml")
    scene = _scene(files, '<include filename="inner.xml"/>')
    proc = _run(worker, files, "render", scene, "-o", files / "out")
    assert_one_line_error(proc, "inner.xml: <include filename> 'pipe.xml'", "is a FIFO")


@pytest.mark.parametrize("case", ["normalmap_string_fifo", "include_fifo", "texture_link_to_fifo"])
def test_compare_refuses_a_named_file_that_is_not_regular(worker, files, case):
    shapes, defines, needles = CASES[case]
    if "normalmap_microfacet" not in shapes:      # compare needs the plugin in the scene
        shapes = SHAPE.format(xml_plugin()) + shapes
    proc = _run(worker, files, "compare", _scene(files, shapes), "-o", files / "out", "--quick", *defines)
    assert_one_line_error(proc, "scene.xml: ", *needles)


@pytest.mark.parametrize("command", ["render", "compare"])
def test_a_scene_that_is_a_fifo_is_refused(worker, files, command):
    proc = _run(worker, files, command, files / "pipe.xml", "-o", files / "out")
    assert_one_line_error(proc, "pipe.xml is a FIFO (named pipe), not a regular file")


def test_a_missing_scene_is_still_not_found(worker, files):
    proc = _run(worker, files, "render", files / "absent.xml", "-o", files / "out")
    assert_one_line_error(proc, "scene file not found")
