"""Bad input to ``mfnormal render`` and ``mfnormal compare``: one line on stderr, non-zero exit.

Each case runs the command line in a subprocess, as a user would, on a tiny scene
written into a temporary directory: a normal-mapped rectangle (or a PLY quad)
under a constant sky. The good scene renders (so a failure below is the bad
input's, not the fixture's); each bad variant must fail with a single line that
names the problem, and without a traceback.
"""

import os
import subprocess
import sys
from pathlib import Path

import numpy as np
import pytest

from mfnormal.report import png_bytes
from cli_checks import assert_one_line_error  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

SCENE = """<scene version="3.0.0">
    <default name="nm" value="normalmap.png"/>
    <default name="model" value="analytic"/>
    <integrator type="path"><integer name="max_depth" value="3"/></integrator>
    <sensor type="perspective">
        <transform name="to_world"><lookat origin="0, 2, 4" target="0, 0, 0" up="0, 1, 0"/></transform>
        <sampler type="independent"><integer name="sample_count" value="1"/></sampler>
        <film type="hdrfilm"><integer name="width" value="24"/><integer name="height" value="16"/></film>
    </sensor>
    <emitter type="constant"/>
    <shape type="SHAPE">
        SHAPE_PROPS
        <bsdf type="normalmap_microfacet">
            <string name="model" value="$model"/>
            EXTRA
            <texture type="bitmap" name="normalmap">
                <string name="filename" value="$nm"/>
                <boolean name="raw" value="true"/>
            </texture>
            <bsdf type="diffuse"/>
        </bsdf>
    </shape>
</scene>
"""

RECTANGLE = '<transform name="to_world"><rotate x="1" angle="-90"/></transform>'

PLY_NO_UV = """ply
format ascii 1.0
element vertex 4
property float x
property float y
property float z
property float nx
property float ny
property float nz
element face 2
property list uchar int vertex_indices
end_header
-1 0 -1 0 1 0
1 0 -1 0 1 0
1 0 1 0 1 0
-1 0 1 0 1 0
3 0 2 1
3 0 3 2
"""


def write_scene(path, shape="rectangle", shape_props=RECTANGLE, extra="", text=None):
    text = text or SCENE.replace("SHAPE_PROPS", shape_props).replace("SHAPE", shape).replace("EXTRA", extra)
    path.write_text(text)
    return path


@pytest.fixture(scope="module")
def scenes(tmp_path_factory):
    """A directory with the good scene and one bad variant per failure."""
    d = tmp_path_factory.mktemp("cli")
    bumps = np.zeros((8, 8, 3), np.uint8)
    bumps[...] = (128, 128, 255)
    bumps[2:6, 2:6] = (200, 128, 220)
    (d / "normalmap.png").write_bytes(png_bytes(bumps))
    (d / "gray.png").write_bytes(png_bytes(np.full((8, 8), 128, np.uint8)))
    (d / "quad.ply").write_text(PLY_NO_UV)
    write_scene(d / "good.xml")
    write_scene(d / "bad_xml.xml", text=SCENE.replace("</scene>", "</scne>"))
    write_scene(d / "unknown_param.xml", extra='<float name="bogus_param" value="1"/>')
    write_scene(d / "no_uv.xml", shape="ply", shape_props='<string name="filename" value="quad.ply"/>')
    write_scene(d / "no_plugin.xml", text=SCENE.replace('type="normalmap_microfacet"', 'type="twosided"')
                .replace('<string name="model" value="$model"/>', "")
                .replace('<default name="model" value="analytic"/>', ""))
    return d


def run_cli(*args, cwd):
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    return subprocess.run([sys.executable, "-m", "mfnormal", *args], cwd=cwd, env=env,
                          capture_output=True, text=True, timeout=300)


def test_good_scene_renders(scenes, tmp_path):
    proc = run_cli("render", "good.xml", "-o", str(tmp_path / "good"), cwd=scenes)
    assert proc.returncode == 0, proc.stderr
    assert (tmp_path / "good.exr").is_file() and (tmp_path / "good.png").is_file()


# (case, arguments after the scene name, scene, what the line must name)
CASES = [
    ("missing_scene", [], "nothere.xml", ["not found", "nothere.xml"]),
    ("xml_error", [], "bad_xml.xml", ["bad_xml.xml"]),
    ("unknown_parameter", [], "unknown_param.xml", ["unreferenced", "bogus_param"]),
    ("unknown_model", ["-D", "model=fancy"], "good.xml", ["unknown model 'fancy'"]),
    ("missing_normal_map", ["-D", "nm=missing.png"], "good.xml", ["missing.png"]),
    ("one_channel_normal_map", ["-D", "nm=gray.png"], "good.xml", ["gray.png", "1 channel", "3"]),
    ("mesh_without_uvs", [], "no_uv.xml", ["quad.ply", "texture coordinates"]),
    ("variant_not_installed", ["--variant", "nonexistent_rgb"], "good.xml", ["nonexistent_rgb", "not available"]),
]
# compare sets the model itself, so a scene's $model is a parameter it leaves unused.
COMPARE_NEEDLES = {"unknown_model": ["unused", "model=fancy"]}


@pytest.mark.parametrize("case,args,scene,needles", CASES, ids=[c[0] for c in CASES])
def test_render_rejects_bad_input(scenes, tmp_path, case, args, scene, needles):
    proc = run_cli("render", scene, *args, "-o", str(tmp_path / "out"), cwd=scenes)
    assert_one_line_error(proc, *needles)
    assert not (tmp_path / "out.exr").exists()


@pytest.mark.parametrize("case,args,scene,needles", CASES, ids=[c[0] for c in CASES])
def test_compare_rejects_bad_input(scenes, tmp_path, case, args, scene, needles):
    proc = run_cli("compare", scene, *args, "--quick", "-o", str(tmp_path / "report"), cwd=scenes)
    assert_one_line_error(proc, *COMPARE_NEEDLES.get(case, needles))
    assert not (tmp_path / "report" / "report.html").exists()


def test_compare_rejects_a_scene_without_the_plugin(scenes, tmp_path):
    proc = run_cli("compare", "no_plugin.xml", "--quick", "-o", str(tmp_path), cwd=scenes)
    assert_one_line_error(proc, "no_plugin.xml", "normalmap_microfacet")


def test_compare_rejects_unknown_methods_and_missing_validation_dir(scenes, tmp_path):
    proc = run_cli("compare", "good.xml", "--methods", "flat,fancy", cwd=scenes)
    assert_one_line_error(proc, "fancy")
    proc = run_cli("compare", "good.xml", "--validation", "no_such_dir", cwd=scenes)
    assert_one_line_error(proc, "no_such_dir")
