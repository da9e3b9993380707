"""Hostile inputs of the baker (``mfnormal bake`` and :func:`mfnormal.io.bake.bake`), and of
``render`` for the mesh files a scene names.

Command line (the worker of tests/cli_worker.py, a child process: a crash, an abort or a hang
fails the test instead of taking pytest down): every case ends in exactly one ``mfnormal:
error:`` line with exit 2 and nothing written, or in exit 0 with finite outputs; the input files
are byte-identical afterwards. Python API: the cases that could crash run in a child Python
(:func:`api_results`); each raises a one-line ``ValueError`` (or ``TypeError``) naming the
argument or the problem. The fuzzer at the end draws broken meshes (:mod:`bake_fuzzing`).
"""

from __future__ import annotations

import hashlib
import json
import os
import subprocess
import sys
import tracemalloc
from pathlib import Path

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import mitsuba as mi
import numpy as np
import pytest
from hypothesis import strategies as st

from bake_fuzzing import bumpy, hostile_mesh, sphere, write_drawn, write_ply
from cli_checks import assert_error_line
from fuzzing import Stats, fuzz_test, input_count, render_or_one_line_error
from helpers import xml_scene
from mfnormal.io import bake as B
from mfnormal.io.bake_inputs import available_memory
from mfnormal.io.meshes import mitsuba_mesh

ROOT = Path(__file__).resolve().parents[1]
SIZE = "32"
QUAD = (np.array([[0, 0, 0], [1, 0, 0], [1, 1, 0], [0, 1, 0]], float), np.tile([0, 0, 1.0], (4, 1)),
        np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float), np.array([[0, 1, 2], [0, 2, 3]]))


def scaled(mesh, factor):
    p, n, uv, f = mesh
    return p * factor, n, uv, f


@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    """The inputs: a bumpy sphere (high), a 12 × 6 UV sphere (low), and the hostile variants."""
    d = tmp_path_factory.mktemp("bake_hostile")
    low, high = sphere(), bumpy()
    p, n, uv, f = low
    write_ply(d / "high.ply", *high)
    write_ply(d / "low.ply", *low)
    write_ply(d / "udim.ply", p, n, uv + 20.0, f)
    write_ply(d / "tiny_uv.ply", p, n, uv * 1e-4 + 0.3, f)
    nan_uv = uv.copy()
    nan_uv[5, 0] = np.nan
    write_ply(d / "nan_uv.ply", p, n, nan_uv, f)
    write_ply(d / "index_2e9.ply", *QUAD[:1], None, QUAD[2], [[0, 1, 2], [0, 2, 2_000_000_000]])
    write_ply(d / "index_past.ply", p, n, uv, np.where(f == f.max(), len(p), f))
    write_ply(d / "no_faces.ply", *QUAD[:3], [])
    write_ply(d / "zero_area.ply", p * 0.0, n, uv, f)
    write_ply(d / "flipped.ply", p, -n, uv, f)
    write_ply(d / "quad.ply", *QUAD)
    write_ply(d / "high_above.ply", QUAD[0] + [0, 0, 0.01], *QUAD[1:])
    for name, factor in (("", 1.0), ("_tiny", 1e-9), ("_huge", 1e9)):
        write_ply(d / f"high{name}.ply", *scaled(high, factor))
        write_ply(d / f"low{name}.ply", *scaled(low, factor))
        p, _, uv, f = scaled(low, factor)         # without normals: Mitsuba's loader computes them
        write_ply(d / f"low{name}_computed.ply", p, None, uv, f)
        p, _, uv, f = scaled(high, factor)
        write_ply(d / f"high{name}_computed.ply", p, None, uv, f)
    (d / "empty.ply").write_bytes(b"")
    (d / "folder.ply").mkdir()
    os.link(d / "low.ply", d / "low_link.ply")
    (d / "scene.xml").write_text(xml_scene('<shape type="ply"><string name="filename" value="$mesh"/></shape>',
                                           {"mesh": "quad.ply"}, spp="1", width="8", height="8"))
    return d


def digests(folder: Path) -> dict:
    return {p.name: hashlib.sha256(p.read_bytes()).hexdigest() for p in folder.iterdir() if p.is_file()}


def run(worker, meshes, *args):
    """``mfnormal ARGS`` in the inputs' folder: the worker's result, after checking that no input
    changed and that an error left no file."""
    before = digests(meshes)
    result = worker.run(list(args), cwd=meshes)
    assert not result.timed_out and result.died is None and result.exception is None, result.describe()
    after = digests(meshes)
    assert {k: after[k] for k in before} == before, "an input file changed"
    if result.rc != 0:
        assert set(after) == set(before), f"an error left {set(after) - set(before)}"
    return result


def bake_error(worker, meshes, high, low, *flags, needles=()):
    """A bake of ``high`` onto ``low`` that ends in one error line holding ``needles``."""
    result = run(worker, meshes, "bake", high, low, "-o", "out.png", "--size", SIZE, *flags)
    return assert_error_line(result, *needles)


def read(path) -> np.ndarray:
    return np.array(mi.Bitmap(str(path)), np.float64)


def bake_ok(worker, meshes, tmp_path, high, low, *flags, heights: bool = False):
    """A bake that succeeds: (map, heights or None, the warning lines); outputs finite, written
    beside each other in ``tmp_path`` (not among the inputs)."""
    out = tmp_path / "out.png"
    extra = ["--heights", str(tmp_path / "out.exr")] if heights else []
    result = run(worker, meshes, "bake", high, low, "-o", str(out), "--size", SIZE, *flags, *extra)
    assert result.rc == 0, result.describe()
    warnings = [ln for ln in result.stderr.splitlines() if ln.strip()]
    assert all(ln.startswith("mfnormal: warning: ") for ln in warnings), result.stderr
    normal_map = read(out)
    h = read(tmp_path / "out.exr") if heights else None
    assert np.isfinite(normal_map).all() and (h is None or np.isfinite(h).all())
    return normal_map, h, warnings


# -- 1. UVs that cover no texel centre -------------------------------------------------------------

@pytest.mark.parametrize("low, flags, needles", [
    ("udim.ply", [], ("u 20 to 21", "outside the map", "0 to 1")),
    ("tiny_uv.ply", [], ("cover no texel centre", "32x32", "--size")),
    ("tiny_uv.ply", ["--size", "64"], ("cover no texel centre", "64x64", "--size")),
    ("nan_uv.ply", [], ("nan_uv.ply", "texture coordinate", "finite")),
])
def test_uvs_that_cover_no_texel_are_one_error_line(worker, meshes, low, flags, needles):
    """A UDIM tile, an island smaller than a texel and a NaN UV aborted Dr.Jit (SIGABRT)."""
    bake_error(worker, meshes, "high.ply", low, *flags, needles=needles)


# -- 2. Outputs that name an input -------------------------------------------------------------------

@pytest.mark.parametrize("flags, needles", [
    (["--unwrap", "high.ply"], ("--unwrap high.ply", "high-poly mesh", "overwrite")),
    (["--unwrap", "low.ply"], ("--unwrap low.ply", "low-poly mesh")),
    (["--unwrap", "./sub/../low.ply"], ("low-poly mesh",)),
    (["--unwrap", "low_link.ply"], ("low-poly mesh",)),          # a hard link to the low-poly
    (["--heights", "high.exr", "-o", "high.exr/../out.png"], ()),
])
def test_an_output_that_is_an_input_is_refused_and_the_input_kept(worker, meshes, flags, needles):
    """--unwrap naming an input overwrote it (exit 0). The last case is no overwrite: it fails on
    its own problem (-o under a file name), not as one."""
    result = run(worker, meshes, "bake", "high.ply", "low.ply", "-o", "out.png", "--size", SIZE, *flags)
    line = assert_error_line(result, *needles)
    if not needles:
        assert "overwrite" not in line


def test_distinct_outputs_beside_the_inputs_are_written(worker, meshes, tmp_path):
    """The overwrite check refuses only what it should: outputs in the inputs' folder, named
    differently, are written (and the inputs kept)."""
    try:
        result = run(worker, meshes, "bake", "high.ply", "low.ply", "-o", "out.png", "--heights",
                     "low.exr", "--size", SIZE)
        assert result.rc == 0, result.describe()
    finally:
        for name in ("out.png", "low.exr"):
            (meshes / name).unlink(missing_ok=True)


def test_an_output_link_to_an_input_is_refused(worker, meshes):
    link = meshes / "link.png"
    link.symlink_to(meshes / "low.ply")
    try:
        bake_error(worker, meshes, "high.ply", "low.ply", "-o", "link.png", needles=("-o link.png", "low-poly"))
        assert link.is_symlink()
    finally:
        link.unlink()


# -- 3. Face indices past the vertices --------------------------------------------------------------

@pytest.mark.parametrize("high, low, name", [("index_2e9.ply", "low.ply", "high-poly mesh index_2e9.ply"),
                                             ("high.ply", "index_2e9.ply", "low-poly mesh index_2e9.ply"),
                                             ("high.ply", "index_past.ply", "low-poly mesh index_past.ply")])
def test_a_face_index_past_the_vertices_is_refused_before_mitsuba_reads_it(worker, meshes, high, low, name):
    bake_error(worker, meshes, high, low, needles=(name, "names vertex", "vertices"))


def test_render_refuses_a_scene_whose_ply_has_a_face_index_past_its_vertices(worker, meshes, tmp_path):
    out = tmp_path / "render"
    result = run(worker, meshes, "render", "scene.xml", "-D", "mesh=index_2e9.ply", "-o", str(out))
    assert_error_line(result, "scene.xml", "index_2e9.ply", "2000000000")
    assert not list(tmp_path.iterdir())
    result = run(worker, meshes, "render", "scene.xml", "-o", str(out))      # control: quad.ply
    assert result.rc == 0, result.describe()
    assert np.isfinite(read(out.with_suffix(".exr"))).all()


# -- 4, 12 (API), 9 (API). The Python API, in a child Python -----------------------------------------

API_CASES = {
    "high_none": ("B.bake(None, LOW, 32)", ("high", "NoneType")),
    "low_none": ("B.bake(HIGH, None, 32)", ("low", "NoneType")),
    "low_number": ("B.bake(HIGH, 5, 32)", ("low", "int")),
    "size_text": ("B.bake(HIGH, LOW, 'abc')", ("size", "integer")),
    "size_float": ("B.bake(HIGH, LOW, 32.5)", ("size", "integer")),
    "cage_text": ("B.bake(HIGH, LOW, 32, cage='abc')", ("cage", "number")),
    "padding_negative": ("B.bake(HIGH, LOW, 32, padding=-1)", ("padding -1",)),
    "low_index_past": ("B.bake(HIGH, mesh(P, N, UV, np.where(F == F.max(), len(P), F)), 32)",
                       ("low-poly mesh", "face index", "vertices")),
    "high_index_past": ("B.bake(mesh(P, N, UV, np.where(F == F.max(), 10**6, F)), LOW, 32)",
                        ("high-poly mesh", "face index")),
    "low_nan_uv": ("B.bake(HIGH, mesh(P, N, np.where(UV > 0.5, np.nan, UV), F), 32)", ("UVs", "NaN")),
    "low_udim": ("B.bake(HIGH, mesh(P, N, UV + 20, F), 32)", ("outside the map",)),
    "high_analytic_tiny": ("B.bake(mi.load_dict({'type': 'sphere'}), mesh(P * 1e-9, N, UV, F), 32)",
                           ("high-poly as a mesh",)),
    "scalar_variant": ("mi.set_variant('scalar_rgb'); B.bake(HIGH, LOW, 32)", ("JIT variant", "scalar_rgb")),
    "cage_infinite": ("B.bake(HIGH, LOW, 32, cage=float('inf'))", ("cage inf", "finite number")),
    "progress_number": ("B.bake(HIGH, LOW, 32, progress=5)", ("progress 5", "function")),
    "batches_number": ("B.bake(HIGH, LOW, 32, batches=5)", ("batches 5", "Batches")),
    "batches_zero": ("B.bake(HIGH, LOW, 32, batches=B.Batches(trace=0))", ("batches.trace 0", "at least 1")),
    "memory_limit_text": ("B.bake(HIGH, LOW, 32, memory_limit='abc')", ("memory_limit 'abc'", "integer")),
}

API_SCRIPT = """
import json, sys
import mfnormal, mitsuba as mi, numpy as np
mi.set_variant('llvm_ad_rgb')
from mfnormal.io import bake as B
from mfnormal.io.meshes import mitsuba_mesh
sys.path.insert(0, {tests!r})
from bake_fuzzing import sphere
P, N, UV, F = sphere()
def mesh(p, n, uv, f):
    return mitsuba_mesh('m', mi.load_dict({{'type': 'diffuse'}}), p, n, uv, None, f)
HIGH, LOW = {high!r}, {low!r}
out = {{}}
for name, call in {cases!r}.items():
    mi.set_variant('llvm_ad_rgb')
    try:
        eval(compile(call, name, 'exec'))
        out[name] = ['returned', '']
    except Exception as exc:
        out[name] = [type(exc).__name__, str(exc)]
print(json.dumps(out))
"""


@pytest.fixture(scope="module")
def api_results(meshes):
    """Each of API_CASES run in one child Python (a crash fails every case instead of pytest):
    {case: [exception type, message]}."""
    script = API_SCRIPT.format(tests=str(ROOT / "tests"), high=str(meshes / "high.ply"),
                               low=str(meshes / "low.ply"), cases={k: v[0] for k, v in API_CASES.items()})
    env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT / "src"), str(ROOT / "tests")]))
    proc = subprocess.run([sys.executable, "-c", script], capture_output=True, text=True, timeout=300, env=env)
    assert proc.returncode == 0, f"the child Python died (status {proc.returncode}): {proc.stderr[-2000:]}"
    return json.loads(proc.stdout.strip().splitlines()[-1])


@pytest.mark.parametrize("case", API_CASES)
def test_python_api_refuses_bad_arguments_in_one_line_naming_them(api_results, case):
    kind, message = api_results[case]
    assert kind in ("BakeError", "TypeError", "ValueError"), (kind, message)
    assert "\n" not in message
    for needle in API_CASES[case][1]:
        assert needle in message, (needle, message)


# -- 6. Memory -------------------------------------------------------------------------------------

def test_the_bakes_memory_is_bounded_per_texel():
    """With small passes, bands and chunks (2^14 texels), a 1024² bake of the two-triangle quad
    (each triangle's box the whole map) takes at its numpy peak under 52 bytes per texel
    (measured 44: the normals and heights kept, 32; the covering triangles, 4; two masks; one
    pass), where baking all texels at once took 347 (with the default constants: 240 at 1024²,
    falling towards 40 with the size, as the passes are bounded). The map and heights are the
    same in 4 passes as in one."""
    quad = mitsuba_mesh("quad", mi.load_dict({"type": "diffuse"}), *QUAD[:3], None, QUAD[3])
    high = mitsuba_mesh("high", mi.load_dict({"type": "diffuse"}), QUAD[0] * [1, 1, 0] + [0, 0, 0.01]
                        + 0.02 * np.sin(QUAD[0][:, :1] * 3), *QUAD[1:3], None, QUAD[3])
    whole = B.bake(high, quad, 256)
    small = B.Batches(trace=1 << 14, band=1 << 14, chunk=1 << 14)
    passes = B.bake(high, quad, 256, batches=small)
    assert np.array_equal(passes.normals, whole.normals) and np.array_equal(passes.heights, whole.heights)
    assert whole.hit.mean() > 0.9
    tracemalloc.start()
    try:
        B.bake(high, quad, 1024, batches=small)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak / 1024 ** 2 < 52, peak / 1024 ** 2


def test_a_bake_larger_than_the_memory_left_is_refused_before_it_allocates():
    """With 1 GiB to take (``memory_limit``; by default what the system has available, which
    this machine reports), an 8192² bake is refused before it allocates the map."""
    assert available_memory() > 0
    quad = mitsuba_mesh("quad", mi.load_dict({"type": "diffuse"}), *QUAD[:3], None, QUAD[3])
    tracemalloc.start()
    try:
        with pytest.raises(B.BakeError, match="8192x8192 bake needs about 4.*GiB.*--size"):
            B.bake(quad, quad, 8192, memory_limit=1 << 30)
        peak = tracemalloc.get_traced_memory()[1]
    finally:
        tracemalloc.stop()
    assert peak < 1 << 24
    assert B.memory_needed(8192) < 8 << 30        # the documented maximum fits an 8 GiB machine


def _kernel_files(root: Path, cgroup: str, files: dict) -> tuple:
    """A /proc and a /sys/fs/cgroup under ``root``: MemAvailable 20 GiB, this process in
    ``cgroup`` (the lines of /proc/self/cgroup), and ``files`` {path under the cgroup root: text}."""
    proc, cgroups = root / "proc", root / "cgroup"
    (proc / "self").mkdir(parents=True)
    (proc / "meminfo").write_text(f"MemTotal: {32 << 20} kB\nMemAvailable: {20 << 20} kB\n")
    (proc / "self" / "cgroup").write_text(cgroup)
    for name, text in files.items():
        (cgroups / name).parent.mkdir(parents=True, exist_ok=True)
        (cgroups / name).write_text(text)
    return proc, cgroups


GIB = 1 << 30


@pytest.mark.parametrize("cgroup, files, room", [
    ("0::/\n", {}, 20 * GIB),                                         # no group: MemAvailable
    ("0::/job/step\n", {"job/step/memory.max": "max\n", "job/step/memory.current": f"{GIB}\n",
                         "job/memory.max": f"{3 * GIB}\n", "job/memory.current": f"{GIB}\n",
                         "job/memory.stat": f"anon 1\ninactive_file {GIB // 2}\n"}, 2.5 * GIB),
    ("4:memory:/docker/abc\n1:cpu:/\n", {"memory/docker/abc/memory.limit_in_bytes": f"{2 * GIB}\n",
                                           "memory/docker/abc/memory.usage_in_bytes": f"{GIB}\n",
                                           "memory/memory.limit_in_bytes": "9223372036854771712\n",
                                           "memory/memory.usage_in_bytes": f"{5 * GIB}\n"}, 1 * GIB),
], ids=["no_group", "v2_cap_above", "v1_container"])
def test_the_memory_left_is_capped_by_the_control_group(tmp_path, cgroup, files, room):
    """In a container or a batch job the kernel kills a process over its control group's cap
    without a message (exit 137), so the room a bake may take is the least of MemAvailable and,
    for the process's group and each above it, cap less usage (less its inactive file cache):
    cgroup v2 (a cap on a parent, "max" on the group) and v1 (the root's 2^63 is no cap). A
    8192² bake is refused before it allocates in a 3 GiB group."""
    proc, cgroups = _kernel_files(tmp_path, cgroup, files)
    assert available_memory(proc, cgroups) == room
    quad = mitsuba_mesh("quad", mi.load_dict({"type": "diffuse"}), *QUAD[:3], None, QUAD[3])
    if room < 4 * GIB:
        with pytest.raises(B.BakeError, match=f"more than the {room / GIB:.1f} GiB available"):
            B.bake(quad, quad, 8192, memory_limit=available_memory(proc, cgroups))


# -- 9. Meshes at 1e-9 and 1e9 -----------------------------------------------------------------------

@pytest.mark.parametrize("scale_name, factor", [("_tiny", 1e-9), ("_huge", 1e9)])
@pytest.mark.parametrize("normals", ["", "_computed"])
@pytest.mark.parametrize("high_normals", ["shading", "geometric"])
def test_meshes_at_any_scale_bake_the_map_of_the_unit_meshes(worker, meshes, tmp_path, scale_name, factor,
                                                             normals, high_normals):
    """The spheres scaled by 1e-9 (every texel was (1, 0, 0) where Mitsuba's loader computed the
    normals; geometric normals NaN, written as black) and by 1e9 bake the map of the unit spheres
    within one 8-bit step, and the heights times the scale; with their normals in the file, or
    computed by Mitsuba's loader (at 1e-9 it gives every vertex (1, 0, 0))."""
    ref, ref_h, _ = bake_ok(worker, meshes, tmp_path / "ref", f"high{normals}.ply", f"low{normals}.ply",
                            "--high-normals", high_normals, heights=True)
    got, h, _ = bake_ok(worker, meshes, tmp_path / "scaled", f"high{scale_name}{normals}.ply",
                        f"low{scale_name}{normals}.ply", "--high-normals", high_normals, heights=True)
    assert np.abs(got - ref).max() <= 1.0
    assert np.abs(h / factor - ref_h).max() < 1e-5 * np.abs(ref_h).max()
    assert np.abs(ref_h).max() > 0.03


# -- 10. Huge cages ----------------------------------------------------------------------------------

@pytest.mark.parametrize("cage", ["1e12", "1e20", "1e300"])
def test_heights_with_a_huge_cage_equal_those_with_the_default_cage(worker, meshes, tmp_path, cage):
    """--cage 1e12 gave heights ±64 (the rays' start 1e9 away, in single precision) against a
    true ±0.1; now within float32 round-off of the default cage's."""
    _, ref_h, _ = bake_ok(worker, meshes, tmp_path / "ref", "high.ply", "low.ply", heights=True)
    _, h, _ = bake_ok(worker, meshes, tmp_path / "cage", "high.ply", "low.ply", "--cage", cage, heights=True)
    assert np.abs(h - ref_h).max() < 1e-6


def test_a_cage_spanning_the_scene_does_not_say_raise_the_cage(worker, meshes, tmp_path):
    """A unit quad baked onto the sphere: most rays miss it. With the default cage the warning
    says to raise the cage; with --cage 1e20 (it said "raise --cage" too) it says that the cage
    spans the scene."""
    _, _, small = bake_ok(worker, meshes, tmp_path / "a", "high_above.ply", "low.ply")
    _, _, huge = bake_ok(worker, meshes, tmp_path / "b", "high_above.ply", "low.ply", "--cage", "1e20")
    assert len(small) == 1 and "raise --cage" in small[0]
    assert len(huge) == 1 and "raise --cage" not in huge[0] and "spans the whole scene" in huge[0]


# -- 12, 13. Empty, faceless and flat inputs; the variant; folders -----------------------------------

@pytest.mark.parametrize("high, low, flags, needles", [
    ("no_faces.ply", "low.ply", [], ("high-poly mesh no_faces.ply", "no faces")),
    ("high.ply", "no_faces.ply", [], ("low-poly mesh no_faces.ply", "no faces")),
    ("high.ply", "low.ply", ["--variant", "scalar_rgb"], ("--variant scalar_rgb", "JIT variant", "llvm_ad_rgb")),
    ("high.ply", "zero_area.ply", [], ("low-poly mesh has no area",)),
    ("empty.ply", "low.ply", [], ("high-poly mesh empty.ply is empty",)),
    ("high.ply", "empty.ply", [], ("low-poly mesh empty.ply is empty",)),
    ("high.ply", "low.ply", ["--unwrap", "folder.ply"], ("--unwrap folder.ply names a folder",)),
])
def test_faceless_empty_and_flat_inputs_are_one_error_line_naming_them(worker, meshes, high, low, flags, needles):
    line = bake_error(worker, meshes, high, low, *flags, needles=needles)
    assert "unexpected" not in line and ".mfnormal" not in line and "tmp" not in line


# -- 14. Flipped normals and the writers -----------------------------------------------------------

def test_flipped_low_poly_normals_bake_with_one_warning(worker, meshes, tmp_path):
    _, _, warnings = bake_ok(worker, meshes, tmp_path, "high.ply", "flipped.ply")
    assert len(warnings) == 1 and "face away" in warnings[0] and "flip" in warnings[0]
    _, _, none = bake_ok(worker, meshes, tmp_path, "high.ply", "low.ply")
    assert none == []


@pytest.mark.parametrize("bad", [np.nan, np.inf])
def test_writers_refuse_non_finite_values_and_write_nothing(tmp_path, bad):
    normals = np.zeros((8, 8, 3))
    normals[..., 2] = 1.0
    normals[3, 4, 0] = bad
    with pytest.raises(B.BakeError, match="normals hold NaN or infinity"):
        B.write_map(tmp_path / "m.png", normals)
    heights = np.zeros((8, 8))
    heights[1, 1] = bad
    with pytest.raises(B.BakeError, match="heights .*NaN or infinity"):
        B.write_heights(tmp_path / "h.exr", heights)
    with pytest.raises(B.BakeError, match="heights"):
        B.write_heights(tmp_path / "h.exr", np.full((8, 8), 1e39))     # infinite in float32
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("normals, heights", [(np.zeros((8, 8)), np.zeros((8, 8, 2))),
                                             (np.zeros((8, 8, 4)), np.zeros(8)),
                                             (np.full((8, 8, 3), "a"), np.full((8, 8), "a"))])
def test_writers_refuse_arrays_of_another_shape_and_write_nothing(tmp_path, normals, heights):
    """A map of another shape was Mitsuba's "Bitmap::rebuild_struct(): channel count (1) does not
    match pixel format (rgb)!"."""
    with pytest.raises(B.BakeError, match=r"^normals of shape .*expected an \(H, W, 3\) array"):
        B.write_map(tmp_path / "m.png", normals)
    with pytest.raises(B.BakeError, match=r"^heights of shape .*expected an \(H, W\) array"):
        B.write_heights(tmp_path / "h.exr", heights)
    assert not list(tmp_path.iterdir())


@pytest.mark.parametrize("bits", [7, 0, 32, True, "8"])
def test_write_map_accepts_only_8_or_16_bits(tmp_path, bits):
    normals = np.zeros((8, 8, 3))
    normals[..., 2] = 1.0
    with pytest.raises(B.BakeError, match=r"^bits .*: expected 8 or 16 bits per channel$"):
        B.write_map(tmp_path / "m.png", normals, bits=bits)
    assert not list(tmp_path.iterdir())


# -- The fuzzer -------------------------------------------------------------------------------------

STATS = Stats("bake fuzz")
report_throughput = STATS.report_fixture()
FLAGS = [[], ["--heights", "out/h.exr"], ["--high-normals", "geometric"], ["--tangents", "mitsuba"],
         ["--cage", "1e30"], ["--cage", "1e-30"], ["--padding", "0"], ["--bits", "16"]]


def fuzz_one(worker, data):
    """One drawn input: a broken high- or low-poly (or both) and flags; the CLI's contract
    (:func:`fuzzing.render_or_one_line_error`), inputs unchanged, outputs finite."""
    intact = {"binary": True, "normals": True, "obj": False}
    with STATS.sandbox("mfnormal-bake-fuzz.") as root:
        files, damages = {}, {}
        for role, base in (("high", bumpy(8, 16)), ("low", sphere())):
            drawn = data.draw(hostile_mesh(base)) if data.draw(st.booleans()) else (base, "none", intact)
            files[role], damages[role] = write_drawn(root / role, *drawn).name, drawn[1]
        flags = data.draw(st.sampled_from(FLAGS))
        before = digests(root)
        result = worker.run(["bake", files["high"], files["low"], "-o", "out/m.png", "--size", "24", *flags],
                            cwd=root, timeout=120)
        STATS.log(result, f"\t{files} {damages} {flags}")

        def written():
            assert np.isfinite(read(root / "out/m.png")).all()
            if "--heights" in flags:
                assert np.isfinite(read(root / "out/h.exr")).all()

        def nothing():
            assert not (root / "out").exists() or not list((root / "out").iterdir())

        STATS.count(render_or_one_line_error(result, 120, written, nothing))
        assert digests(root) == before


@fuzz_test(input_count(12, 400))
def test_bake_fuzz_quick(worker, data):
    fuzz_one(worker, data)


@pytest.mark.slow
@fuzz_test(input_count(300, 3000))
def test_bake_fuzz_long(worker, data):
    fuzz_one(worker, data)
