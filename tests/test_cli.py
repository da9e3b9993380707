"""Bad input to ``mfnormal render`` and ``mfnormal compare``: one line on stderr, non-zero exit.

Each case runs the command line in a child process, as a user would (a subprocess
of its own, or for the parametrised cases the module's command-line worker,
tests/cli_worker.py, which imports Mitsuba once), on a tiny scene written into a
temporary directory: a normal-mapped rectangle (or a PLY quad) under a constant sky. The good scene renders (so a failure below is the bad
input's, not the fixture's); each bad variant must fail with a single line that
names the problem, and without a traceback.

The hardening tests (second half of the file) check that everything
the command line can know before rendering is checked then — sample counts
from any source, seeds, 32-bit parameters, the output name and folder, film
size, variant, ``demo`` and ``compare`` arguments — with nothing written; that
one-channel and AOV films are written whole; that negative pixels are counted;
that the innermost cause of a Dr.Jit or ``<include>`` error is reported; that
``compare`` accepts ``-D width``/``height`` and resolves each scene's files in
its own folder; and that the EXR/PNG pair is written as a pair (a full disk, or
SIGTERM/SIGINT while writing, leave the previous pair and no temporary file).
"""

import os
import shutil
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from cli_checks import assert_error_line, assert_one_line_error  # noqa: E402
from gltf_models import base_document, write_gltf  # noqa: E402
from helpers import write_maps, xml_plugin, xml_scene  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]

SCENE = xml_scene('<shape type="SHAPE">SHAPE_PROPS' + xml_plugin(extra="EXTRA") + "</shape>",
                  {"nm": "normalmap.png", "model": "analytic"})

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
    write_maps(d)
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


def test_version_names_the_package_mitsuba_and_drjit(tmp_path):
    import drjit as dr
    proc = run_cli("--version", cwd=tmp_path)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.strip() == (f"mfnormal {mfnormal.__version__} (Mitsuba {mi.__version__}, "
                                   f"Dr.Jit {dr.__version__})")
    project = (ROOT / "pyproject.toml").read_text(encoding="utf-8")
    assert f'\nversion = "{mfnormal.__version__}"\n' in project


def test_every_command_has_a_description():
    """``mfnormal COMMAND --help`` says what the command does, not only its usage."""
    from mfnormal.cli.commands import build_parser
    for name, parser in build_parser().commands.items():
        assert parser.description and len(parser.description) > 40, name


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


@pytest.mark.skipif(bool(dr.has_backend(dr.JitBackend.CUDA)), reason="this machine has a CUDA GPU")
def test_a_cuda_variant_without_a_gpu_is_one_line_naming_the_llvm_variant(worker, scenes, tmp_path):
    """``--variant cuda_ad_rgb`` on a machine without a GPU: one line that says there is none and
    names the variant to use (it was Dr.Jit's 'jit_init_thread_state(): the CUDA backend hasn't been
    initialized ...'), nothing written."""
    proc = worker.completed(["render", "good.xml", "--variant", "cuda_ad_rgb", "-o", tmp_path / "out"], cwd=scenes)
    assert_one_line_error(proc, "cuda_ad_rgb", "no CUDA GPU", "llvm_ad_rgb")
    assert not (tmp_path / "out.exr").exists()


@pytest.mark.parametrize("case,args,scene,needles", CASES, ids=[c[0] for c in CASES])
def test_render_rejects_bad_input(worker, scenes, tmp_path, case, args, scene, needles):
    proc = worker.completed(["render", scene, *args, "-o", tmp_path / "out"], cwd=scenes)
    assert_one_line_error(proc, *needles)
    assert not (tmp_path / "out.exr").exists()


@pytest.mark.parametrize("case,args,scene,needles", CASES, ids=[c[0] for c in CASES])
def test_compare_rejects_bad_input(worker, scenes, tmp_path, case, args, scene, needles):
    proc = worker.completed(["compare", scene, *args, "--quick", "-o", tmp_path / "report"], cwd=scenes)
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


# -- Hardening: everything is checked before the render; outputs are pairs -------------------------
#
# These run in a worker process (tests/cli_worker.py: one Mitsuba import for all of them,
# a time and memory bound, a crash is a failure) unless they need a process of their own.

SPP_SCENE = SCENE.replace('<default name="model" value="analytic"/>',
                          '<default name="model" value="analytic"/><default name="spp" value="1"/>'
                          '<default name="mb" value="64"/><default name="width" value="24"/>'
                          '<default name="height" value="16"/>') \
                 .replace('<integer name="sample_count" value="1"/>', '<integer name="sample_count" value="$spp"/>') \
                 .replace('<integer name="width" value="24"/><integer name="height" value="16"/>',
                          '<integer name="width" value="$width"/><integer name="height" value="$height"/>')


def film_scene(film_props="", integrator='<integrator type="path"><integer name="max_depth" value="3"/></integrator>'):
    return (SCENE.replace('<film type="hdrfilm">', f'<film type="hdrfilm">{film_props}')
            .replace('<integrator type="path"><integer name="max_depth" value="3"/></integrator>', integrator))


@pytest.fixture(scope="module")
def hard(tmp_path_factory):
    """Scenes for the hardening tests: $spp/$width/$height/$mb parameters, film formats,
    XML <include> chains, a checkerboard normal map, negative radiance, a glTF model."""
    d = tmp_path_factory.mktemp("hard")
    write_maps(d)
    write_scene(d / "good.xml")
    write_scene(d / "params.xml", text=SPP_SCENE.replace("SHAPE_PROPS", RECTANGLE).replace("SHAPE", "rectangle")
                .replace("EXTRA", '<integer name="max_bounces" value="$mb"/><string name="tangent_facet" '
                                  'value="specular"/>').replace('value="$model"', 'value="separable"')
                .replace('<default name="model" value="analytic"/>', ""))
    write_scene(d / "mono_film.xml", text=film_scene('<string name="pixel_format" value="luminance"/>')
                .replace("SHAPE_PROPS", RECTANGLE).replace("SHAPE", "rectangle").replace("EXTRA", ""))
    write_scene(d / "aov.xml", text=film_scene(integrator='<integrator type="aov"><string name="aovs" '
                                                          'value="dd.y:depth,nn:sh_normal"/><integrator '
                                                          'type="path"/></integrator>')
                .replace("SHAPE_PROPS", RECTANGLE).replace("SHAPE", "rectangle").replace("EXTRA", ""))
    write_scene(d / "checker.xml", text=SCENE.replace("SHAPE_PROPS", RECTANGLE).replace("SHAPE", "rectangle")
                .replace("EXTRA", "").replace('<default name="nm" value="normalmap.png"/>', "")
                .replace('<texture type="bitmap" name="normalmap"><string name="filename" value="$nm"/>'
                         '<boolean name="raw" value="true"/></texture>',
                         '<texture type="checkerboard" name="normalmap"/>'))
    (d / "negative.xml").write_text(SCENE.replace('<emitter type="constant"/>',
                                                  '<emitter type="constant"><rgb name="radiance" value="-1, 0.5, 0.5"/>'
                                                  '</emitter>').replace("SHAPE_PROPS", RECTANGLE)
                                    .replace("SHAPE", "rectangle").replace("EXTRA", ""))
    (d / "inc_outer.xml").write_text('<scene version="3.0.0"><include filename="inc_mid.xml"/></scene>')
    (d / "inc_mid.xml").write_text('<scene version="3.0.0"><include filename="inc_bad.xml"/></scene>')
    (d / "inc_bad.xml").write_text('<scene version="3.0.0"><shape type="sphere"></scne>')
    (d / "inc_self.xml").write_text('<scene version="3.0.0"><include filename="inc_self.xml"/></scene>')
    doc, blobs = base_document()
    write_gltf(d / "model", doc, blobs)
    (d / "huge.png").write_bytes(png_header(16000, 16000))
    return d


def png_header(width, height):
    """The signature and IHDR chunk of an 8-bit RGB PNG of width × height, and no pixels."""
    import struct
    import zlib

    ihdr = b"IHDR" + struct.pack(">IIBBBBB", width, height, 8, 2, 0, 0, 0)
    return b"\x89PNG\r\n\x1a\n" + struct.pack(">I", 13) + ihdr + struct.pack(">I", zlib.crc32(ihdr))


def assert_rendered(result, out):
    assert result.exception is None and result.died is None and not result.timed_out, result.describe()
    assert result.rc == 0, result.describe()
    assert Path(f"{out}.exr").is_file() and Path(f"{out}.png").is_file()


# (case, arguments, needles); the scene is in the `hard` folder; nothing may be written.
REJECTED = [
    ("xml_spp_0", ["render", "params.xml", "-D", "spp=0"], ["params.xml", "sample count is 0", "at least 1"]),
    ("gltf_spp_0", ["render", "model/model.gltf", "-D", "spp=0"], ["-D spp=0", "out of range"]),
    ("spp_flag_0", ["render", "good.xml", "--spp", "0"], ["--spp", "at least 1"]),
    ("spp_flag_2_32", ["render", "good.xml", "--spp", "4294967296"], ["--spp", "too large"]),
    ("seed_negative", ["render", "good.xml", "--seed", "-1"], ["--seed", "0 to 4294967295"]),
    ("seed_2_32", ["render", "good.xml", "--seed", "4294967296"], ["--seed", "0 to 4294967295"]),
    ("max_bounces_2_32", ["render", "params.xml", "-D", "mb=4294967296"],
     ["-D mb=4294967296", 'name="max_bounces"', "32-bit"]),
    ("film_width_2_40", ["render", "params.xml", "-D", "width=1099511627776"], ["-D width=1099511627776", "32-bit"]),
    ("film_24000000_pixels_wide", ["render", "params.xml", "-D", "width=24000000"],
     ["24000000x16", "render_pixels"]),
    ("gltf_width_2_32", ["render", "model/model.gltf", "-D", "width=4294967296"], ["-D width=4294967296"]),
    ("limit_unknown", ["render", "good.xml", "--limit", "pixels=3"], ["--limit", "render_pixels"]),
    ("limit_not_a_number", ["render", "good.xml", "--limit", "render_pixels=lots"], ["--limit render_pixels=lots"]),
    ("define_without_name", ["render", "good.xml", "-D", "=3"], ["-D =3", "not a parameter name"]),
    ("argparse_bad_int", ["render", "good.xml", "--spp", "many"], ["--spp", "invalid int value"]),
    ("argparse_no_scene", ["render"], ["scene"]),
    ("include_innermost", ["render", "inc_outer.xml"], ["inc_bad.xml", "Start-end tags mismatch", "inc_mid.xml"]),
    ("include_recursion", ["render", "inc_self.xml"], ["maximum include recursion depth"]),
    ("checkerboard_normal_map", ["render", "checker.xml"], ["Checkerboard", "RGB", "bitmap"]),
    ("polarized_variant", ["render", "good.xml", "--variant", "llvm_ad_spectral_polarized"], ["polarized"]),
    ("demo_unknown_model", ["demo", "--model", "foo"], ["--model foo", "analytic"]),
    ("demo_spp_0", ["demo", "--spp", "0"], ["spp"]),
    ("demo_huge_output_folder_name", ["demo", "-o", "out_dir/"], ["names a folder"]),
    ("compare_seed_negative", ["compare", "good.xml", "--quick", "--seed", "-3"], ["--seed"]),
    ("compare_spp_2_32", ["compare", "good.xml", "--quick", "--spp", "4294967296"], ["--spp", "too large"]),
    ("compare_output_is_a_file", ["compare", "good.xml", "--quick", "-o", "good.xml"], ["good.xml", "is a file"]),
    ("xml_texture_declares_16000_squared", ["render", "good.xml", "-D", "nm=huge.png"],
     ["good.xml", "huge.png", "16000x16000", "image_pixels"]),
    ("xml_texture_over_image_limit", ["render", "good.xml", "--limit", "image_pixels=63"],
     ["normalmap.png", "8x8", "--limit image_pixels"]),
    ("xml_textures_over_texture_limit", ["render", "good.xml", "--limit", "texture_pixels=63"],
     ["normalmap.png", "--limit texture_pixels"]),
    ("compare_xml_texture_declares_16000_squared", ["compare", "good.xml", "--quick", "-D", "nm=huge.png"],
     ["huge.png", "16000x16000", "image_pixels"]),
    ("output_name_too_long", ["render", "good.xml", "-o", "x" * 300], ["too long"]),
    ("scene_name_too_long", ["render", "y" * 300 + ".xml"], ["too long"]),
]


@pytest.mark.parametrize("case,args,needles", REJECTED, ids=[c[0] for c in REJECTED])
def test_bad_input_is_one_line_before_anything_is_written(worker, hard, tmp_path, case, args, needles):
    before = sorted(p.name for p in hard.iterdir())
    out = tmp_path / "out" / "render"
    extra = [] if "-o" in args or args == ["render"] else ["-o", out]
    result = worker.run(args + extra, cwd=hard)
    assert_error_line(result, *needles)
    assert not (tmp_path / "out").exists(), list((tmp_path / "out").rglob("*"))
    assert sorted(p.name for p in hard.iterdir()) == before
    assert "rendered" not in result.stdout


def test_seeds_up_to_2_32_render(worker, hard, tmp_path):
    for seed in ("5000", "4294967295"):
        out = tmp_path / f"seed{seed}"
        assert_rendered(worker.run(["render", "good.xml", "--seed", seed, "-o", out], cwd=hard), out)


def test_output_must_be_a_writable_file_name(worker, hard, tmp_path):
    """-o naming a folder, a path under a file, a read-only folder: one line, before the render."""
    (tmp_path / "folder").mkdir()
    (tmp_path / "afile").write_text("x")
    ro = tmp_path / "readonly"
    ro.mkdir()
    ro.chmod(0o555)
    # root writes into a 0555 folder: then use one no process can create files in.
    readonly = ro / "render" if os.geteuid() != 0 else Path("/sys/mfnormal_test/render")
    for output, needle in [(tmp_path / "folder", "names a folder"), (f"{tmp_path}/new/", "names a folder"),
                           (tmp_path / "afile" / "render", "is a file, not a folder"),
                           (readonly, "cannot write in")]:
        result = worker.run(["render", "good.xml", "-o", output], cwd=hard)
        assert_error_line(result, needle)
        assert "rendered" not in result.stdout
    assert not list((tmp_path / "folder").iterdir()) and not (tmp_path / "new").exists()
    ro.chmod(0o755)


def test_one_channel_and_aov_films_are_written(worker, hard, tmp_path):
    """A mono variant and a luminance film give a one-channel EXR (Y) and a grey PNG; the aov
    integrator's channels are all in the EXR, under their names."""
    for name, args, channels in [("mono", ["good.xml", "--variant", "llvm_ad_mono"], ["Y"]),
                                 ("luminance", ["mono_film.xml"], ["Y"]),
                                 ("aov", ["aov.xml"], ["R", "G", "B", "dd.y.T", "nn.X", "nn.Y", "nn.Z"])]:
        out = tmp_path / name
        result = worker.run(["render", *args, "-o", out], cwd=hard)
        assert_rendered(result, out)
        exr = mi.Bitmap(f"{out}.exr")
        assert [exr.struct_()[i].name for i in range(exr.channel_count())] == channels
        png = mi.Bitmap(f"{out}.png")
        assert png.channel_count() == (1 if channels == ["Y"] else 3)
        values = np.array(exr, dtype=np.float64)
        assert np.all(np.isfinite(values)) and values[..., 0].mean() > 0.01
    depth = np.array(mi.Bitmap(f"{tmp_path / 'aov'}.exr"))[..., 3]
    hit = depth > 0
    assert hit.mean() > 0.05 and 3.0 < np.median(depth[hit]) < 6.0   # the camera is 4.5 from the quad's centre


def test_negative_pixels_are_counted_and_reported(worker, hard, tmp_path):
    """A sky with negative red radiance: the negative pixels are counted in a one-line warning
    and written as 0 (not clamped silently)."""
    out = tmp_path / "neg"
    result = worker.run(["render", "negative.xml", "-o", out], cwd=hard)
    assert_rendered(result, out)
    warning = [ln for ln in result.stderr.splitlines() if "negative" in ln]
    assert len(warning) == 1 and warning[0].startswith("mfnormal: warning: 384 pixel(s)"), result.stderr
    img = np.array(mi.Bitmap(f"{out}.exr"))
    assert img.min() >= 0.0 and img[..., 1].mean() > 0.1


def test_warnings_are_one_line_each(worker, hard, tmp_path):
    doc, blobs = base_document()
    doc["materials"][0]["normalTexture"]["extensions"] = {"KHR_texture_transform": {"scale": [2, 2]}}
    doc["materials"][0]["emissiveFactor"] = [0.1, 0, 0]
    model = write_gltf(tmp_path / "warned", doc, blobs)
    out = tmp_path / "warned_out"
    result = worker.run(["render", model, "-o", out, "-D", "height=12", "-D", "spp=1"], cwd=hard)
    assert_rendered(result, out)
    lines = result.stderr.strip().splitlines()
    assert len(lines) == 2 and all(ln.startswith("mfnormal: warning: glTF: ") for ln in lines), result.stderr


INNERMOST = """
import sys
import mfnormal
import mitsuba as mi
import numpy as np
from mfnormal.io.messages import one_line
mi.set_variant("llvm_ad_rgb")
mfnormal.register()
scene = mi.load_dict({
    "type": "scene", "integrator": {"type": "path", "max_depth": 3},
    "sensor": {"type": "perspective", "to_world": mi.ScalarTransform4f().look_at([0, 0, 3], [0, 0, 0], [0, 1, 0]),
               "film": {"type": "hdrfilm", "width": 4, "height": 4}},
    "sky": {"type": "constant"},
    "quad": {"type": "rectangle", "bsdf": {
        "type": "normalmap_microfacet", "model": "separable",
        "normalmap": {"type": "checkerboard"},
        "bsdf": {"type": "diffuse"}}}})
try:
    mi.render(scene, spp=1)
except Exception as exc:
    print("outer:", " ".join(str(exc).split()))
    print("one_line:", one_line(exc))
"""


def test_the_innermost_cause_of_a_drjit_error_is_reported():
    """Dr.Jit wraps an error in a kernel ('drjit.custom(...) ... (see above)'); one_line
    reports the innermost cause. Here: a checkerboard normal map given to the plugin directly,
    not through the CLI's scene checks (Texture::eval_3 is not implemented for it; in a process
    of its own: a failed kernel trace leaves Dr.Jit unusable for the next ones)."""
    proc = subprocess.run([sys.executable, "-c", INNERMOST], env=dict(os.environ, PYTHONPATH=str(ROOT / "src")),
                          capture_output=True, text=True, timeout=300)
    lines = dict(ln.split(": ", 1) for ln in proc.stdout.splitlines() if ln.startswith(("outer:", "one_line:")))
    assert "see above" in lines["outer"], proc.stdout + proc.stderr
    assert "see above" not in lines["one_line"] and "eval_3(): not implemented" in lines["one_line"], lines


def test_compare_accepts_width_and_height_defines(worker, hard, tmp_path):
    """compare scales the film itself: -D width/height still set the scene's $width/$height
    (not rejected as unused parameters)."""
    out = tmp_path / "cmp"
    result = worker.run(["compare", "params.xml", "--quick", "--methods", "flat,analytic", "-D", "width=40",
                         "-D", "height=30", "-o", out], cwd=hard)
    assert result.rc == 0, result.describe()
    img = mi.Bitmap(str(out / "params" / "flat.exr"))
    assert tuple(img.size()) == (40, 30)


def test_compare_resolves_each_scenes_files_in_its_own_folder(worker, hard, tmp_path):
    """Scene B names a normal map that exists only in scene A's folder: after A, B must fail
    (Mitsuba's file resolver must not keep A's folder)."""
    for name in ("a", "b"):
        (tmp_path / name).mkdir()
        write_scene(tmp_path / name / "scene.xml")
    shutil.copy(hard / "normalmap.png", tmp_path / "a" / "normalmap.png")
    out = tmp_path / "cmp"
    result = worker.run(["compare", tmp_path / "a" / "scene.xml", tmp_path / "b" / "scene.xml", "--quick",
                         "--methods", "flat,analytic", "-o", out], cwd=tmp_path)
    assert_error_line(result, "normalmap.png")
    assert not (out / "report.html").exists()


# -- Writing: a pair or nothing -------------------------------------------------------------------

DRIVER = """
import os, sys, tempfile, time
import mitsuba as mi
from mfnormal.cli import commands as cli
from mfnormal.io import images
real_mkstemp, real_write = tempfile.mkstemp, mi.Bitmap.write
def mkstemp(*args, **kwargs):
    fd, path = real_mkstemp(*args, **kwargs)
    if kwargs.get("suffix") == ".png" and MODE == "disk_full":
        # The PNG's temporary file is /dev/full: writing it fails with ENOSPC, as on a full disk.
        os.close(fd)
        os.unlink(path)
        os.symlink("/dev/full", path)
        fd = os.open(os.devnull, os.O_RDONLY)
    return fd, path
def slow():
    # The PNG is written slowly: the test signals the process meanwhile.
    open(os.environ["MARKER"], "w").close()
    time.sleep(60)
def write(self, path, *args, **kwargs):       # Mitsuba writing the file itself
    if str(path).endswith(".png") and MODE == "slow":
        slow()
    return real_write(self, path, *args, **kwargs)
real_fsync = os.fsync
def fsync(fd):                                # Python writing the file (mfnormal.files.write_bytes)
    if os.readlink(f"/proc/self/fd/{fd}").endswith(".png") and MODE == "slow":
        slow()
    return real_fsync(fd)
tempfile.mkstemp = mkstemp
mi.Bitmap.write = write
os.fsync = fsync
sys.exit(cli.main(sys.argv[1:]))
"""
DISK_FULL, SLOW = "'disk_full'", "'slow'"


def driver(mode, args, cwd, env=None, wait=True):
    code = textwrap.dedent(DRIVER).replace("MODE", mode)
    full_env = dict(os.environ, PYTHONPATH=str(ROOT / "src"), **(env or {}))
    # SIGINT at its default in the child: a test run started in the background (a shell's `&`)
    # inherits it ignored, and the signal test would then wait out the driver's 60 s sleep.
    proc = subprocess.Popen([sys.executable, "-c", code, *map(str, args)], cwd=cwd, env=full_env,
                            stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True,
                            preexec_fn=lambda: signal.signal(signal.SIGINT, signal.SIG_DFL))
    if wait:
        out, err = proc.communicate(timeout=300)
        return subprocess.CompletedProcess(proc.args, proc.returncode, out, err)
    return proc


def previous_pair(hard, tmp_path):
    """Render good.xml to tmp_path/pair.{exr,png}: the previous run's files."""
    proc = run_cli("render", "good.xml", "-o", str(tmp_path / "pair"), cwd=hard)
    assert proc.returncode == 0, proc.stderr
    return {p: p.read_bytes() for p in (tmp_path / "pair.exr", tmp_path / "pair.png")}


def assert_previous_pair_intact(tmp_path, before):
    assert sorted(p.name for p in tmp_path.iterdir()) == ["pair.exr", "pair.png"], list(tmp_path.iterdir())
    for p, data in before.items():
        assert p.read_bytes() == data, f"{p.name} was replaced"


def test_disk_full_leaves_the_previous_pair_and_no_temporary_file(hard, tmp_path):
    """The PNG cannot be written (ENOSPC): one line, exit 2; the previous EXR/PNG pair stays
    as it was (the old code had already replaced the EXR) and no temporary file is left."""
    before = previous_pair(hard, tmp_path)
    proc = driver(DISK_FULL, ["render", "good.xml", "--seed", "7", "-o", tmp_path / "pair"], hard)
    assert_one_line_error(proc, "cannot write")
    assert_previous_pair_intact(tmp_path, before)


@pytest.mark.parametrize("sig", [signal.SIGTERM, signal.SIGINT], ids=["SIGTERM", "SIGINT"])
def test_a_signal_while_writing_leaves_the_previous_pair(hard, tmp_path, sig):
    """SIGTERM or SIGINT while the PNG is being written: the process exits (143 / 130) after
    removing its temporary files; the previous pair is untouched (the old code left a new
    EXR next to the old PNG, and after SIGTERM a hidden 0-byte temporary file)."""
    before = previous_pair(hard, tmp_path)
    marker = tmp_path.parent / f"{tmp_path.name}.marker"
    proc = driver(SLOW, ["render", "good.xml", "--seed", "7", "-o", tmp_path / "pair"], hard,
                  env={"MARKER": str(marker)}, wait=False)
    deadline = time.monotonic() + 240
    while not marker.exists():
        assert proc.poll() is None and time.monotonic() < deadline, proc.communicate()
        time.sleep(0.05)
    proc.send_signal(sig)
    out, err = proc.communicate(timeout=60)
    assert proc.returncode == (143 if sig == signal.SIGTERM else 130), (proc.returncode, err)
    assert err.strip().splitlines()[-1] in ("mfnormal: terminated", "mfnormal: interrupted"), err
    assert_previous_pair_intact(tmp_path, before)


def test_passes_bound_the_paths_per_pass_and_keep_the_seeds():
    """A render's passes: their sample counts sum to the total; none traces more than
    MAX_PASS_LANES paths unless one sample per pixel already does; the default stays 8
    passes (fewer below 8 spp); pass seeds are 32-bit, equal to seed·1000003 + i where that
    fits (the images of small seeds did not change), and distinct for distinct seeds."""
    from mfnormal.render.passes import MAX_PASS_LANES, pass_count, pass_seed, pass_spp

    for total, pixels in [(1, 384), (5, 384), (64, 1920 * 1080), (1000, 1920 * 1080), (1 << 31, 16),
                          (3, 1 << 25), (17, 1 << 24)]:
        n = pass_count(total, pixels)
        counts = [pass_spp(total, n, i) for i in range(min(n, 10))]
        assert sum(pass_spp(total, n, i) for i in range(n)) == total if n < 1e6 else True
        assert n * max(counts) >= total and min(counts) >= 1
        assert max(counts) * pixels <= MAX_PASS_LANES or max(counts) == 1
        if total * pixels <= MAX_PASS_LANES:
            assert n == min(total, 8)
    assert [pass_seed(3, i) for i in range(3)] == [3000009, 3000010, 3000011]
    seeds = {pass_seed(s, 0) for s in range(0, (1 << 32) - 1, 104729)}
    assert len(seeds) == len(range(0, (1 << 32) - 1, 104729)) and max(seeds) < 1 << 32


def test_image_headers_give_the_size_without_decoding(tmp_path):
    """image_headers.image_header reads a PNG's IHDR and a JPEG's frame header (after APPn
    segments such as EXIF) as Mitsuba writes them, and refuses anything else."""
    from mfnormal.io.image_headers import image_header

    img = (np.random.default_rng(3).random((37, 53, 3)) * 255).astype(np.uint8)
    for fmt, name in [(mi.Bitmap.FileFormat.PNG, "png"), (mi.Bitmap.FileFormat.JPEG, "jpeg")]:
        path = tmp_path / f"x.{name}"
        mi.Bitmap(img).write(str(path), fmt)
        assert image_header(path.read_bytes()) == (name, 53, 37)
    jpeg = (tmp_path / "x.jpeg").read_bytes()
    exif = b"\xff\xe1" + (2 + 5000).to_bytes(2, "big") + b"E" * 5000      # a 5 kB APP1 segment
    assert image_header(jpeg[:2] + exif + jpeg[2:]) == ("jpeg", 53, 37)
    for junk in [b"", b"\x89PNG\r\n\x1a\n", jpeg[:40], b"GIF89a" + b"\0" * 20, (tmp_path / "x.png").read_bytes()[:20]]:
        assert image_header(junk) is None


def _bmp(rgb):
    """An uncompressed 24-bit BMP (bottom-up rows padded to 4 bytes)."""
    import struct

    h, w, _ = rgb.shape
    row = (3 * w + 3) // 4 * 4
    data = b"".join(rgb[y, :, ::-1].tobytes().ljust(row, b"\0") for y in range(h - 1, -1, -1))
    info = struct.pack("<IiiHHIIiiII", 40, w, h, 1, 24, 0, len(data), 2835, 2835, 0, 0)
    return b"BM" + struct.pack("<IHHI", 14 + len(info) + len(data), 0, 0, 14 + len(info)) + info + data


def _tga(rgb):
    """An uncompressed true-colour TGA (image type 2, bottom-up, BGR) with the TGA 2.0 footer,
    by which Mitsuba recognises the format."""
    import struct

    h, w, _ = rgb.shape
    return (struct.pack("<BBBHHBHHHHBB", 0, 0, 2, 0, 0, 0, 0, 0, w, h, 24, 0) + rgb[::-1, :, ::-1].tobytes()
            + struct.pack("<II", 0, 0) + b"TRUEVISION-XFILE.\0")


def test_file_image_size_reads_every_format_mitsuba_reads(tmp_path):
    """image_headers.file_image_size gives the width and height of each format Mitsuba's
    Bitmap reads (written by Mitsuba itself, BMP and TGA by hand; each decoded by Mitsuba to
    the same size), from the header alone, and None
    for a broken or unknown file; the XML scene check relies on it."""
    from mfnormal.io.image_headers import file_image_size

    F = mi.Bitmap.FileFormat
    u8 = (np.random.default_rng(3).random((37, 53, 3)) * 255).astype(np.uint8)
    f32 = np.random.default_rng(4).random((37, 53, 3)).astype(np.float32)
    cases = [(F.PNG, "png", u8, "png"), (F.JPEG, "jpg", u8, "jpeg"), (F.OpenEXR, "exr", f32, "exr"),
             (F.RGBE, "hdr", f32, "hdr"), (F.PFM, "pfm", f32, "pfm"), (F.PPM, "ppm", u8, "ppm"),
             ("bmp", "bmp", u8, "bmp"), ("tga", "tga", u8, "tga")]
    for fmt, ext, pixels, name in cases:
        path = tmp_path / f"x.{ext}"
        if isinstance(fmt, str):            # Mitsuba reads BMP and TGA but does not write them
            path.write_bytes(_bmp(u8) if fmt == "bmp" else _tga(u8))
        else:
            mi.Bitmap(pixels).write(str(path), fmt)
        assert file_image_size(path) == (name, 53, 37), ext
        decoded = mi.Bitmap(str(path))                          # what Mitsuba decodes
        assert tuple(decoded.size()) == (53, 37)
        if ext in ("bmp", "tga"):
            assert np.array_equal(np.array(decoded), u8), ext
    exr = (tmp_path / "x.exr").read_bytes()
    (tmp_path / "cut.exr").write_bytes(exr[:12])
    (tmp_path / "x.gif").write_bytes(b"GIF89a" + b"\0" * 20)
    for broken in ["cut.exr", "x.gif"]:
        assert file_image_size(tmp_path / broken) is None, broken
