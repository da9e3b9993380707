"""Fuzzing the command line: random arguments and ``-D`` values for render, demo and compare.

Each Hypothesis example builds an argument list for ``mfnormal render`` (an XML
scene with ``$spp``, ``$width``, ``$height``, ``$mb`` (max_bounces),
``$model``, ``$nm``, ``$strength`` parameters, the same with a uv transform
``<scale x="$su" y="$sv"/>`` (NaN, ±inf and 1e300 among the values) or with the map given as a
file name (``<string name="$kind" value="$nm"/>``, a normal or a height map), a glTF model, or a
missing or odd scene name), ``mfnormal demo`` or ``mfnormal compare --quick``: flags
(``--spp``, ``--seed``, ``--variant``, ``-o``, ``--limit``, ``--model``,
``--width``, ``--methods``) with boundary integers (0, −1, 2^31, 2^32, 2^63),
junk (``''``, ``1.5``, ``nan``, ``0x10``) and hostile names (a folder, a path
under a file, a read-only place, ``..``, ``/dev/zero``), and ``-D key=value``
pairs with known and unknown keys and values of every kind (numbers, NaN,
±inf, 2^32, XML metacharacters, ``$`` references, paths), and scenes that name a FIFO,
a link to one, a device or a folder as a texture, a ``<string name="normalmap">`` or an
``<include>``, or are a FIFO (:func:`special_file_args`). It runs in the worker
process (``tests/cli_worker.py``) and must end with either exit 0 and the
outputs written, or exactly one ``mfnormal: error:`` line (after at most some
``mfnormal: warning:`` lines), exit 2 and nothing written — never a traceback,
a signal, a timeout or the memory cap.

The fuzzer does not ask for long renders: sample counts above 16 are drawn
only where they are invalid (≥ 2^31), and ``--limit render_pixels=4096`` is
always passed last (a larger film is a one-line error). ``QUICK_INPUTS`` inputs in
the default run, ``CI_INPUTS`` with ``MFNORMAL_SLOW=1``, derandomised;
``MFNORMAL_FUZZ_LONG=1`` runs ``LONG_INPUTS`` random ones
(``MFNORMAL_FUZZ_INPUTS=N`` sets the count); ``pytest -s`` prints the
throughput; ``MFNORMAL_FUZZ_LOG=FILE`` appends each input's exit code, last
stderr line and arguments to FILE.
"""

from __future__ import annotations

from pathlib import Path

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

from hypothesis import strategies as st

from fuzzing import Stats, fuzz_test, input_count, render_or_one_line_error
from gltf_models import base_document, glb_bytes, write_gltf
from helpers import write_maps, xml_plugin, xml_scene

QUICK_INPUTS, CI_INPUTS, LONG_INPUTS = 100, 400, 10_000
INPUTS = input_count(CI_INPUTS, LONG_INPUTS, QUICK_INPUTS)
TIMEOUT = 120.0
FORCED = ["--limit", "render_pixels=4096"]

SCENE = xml_scene('<shape type="rectangle"><transform name="to_world"><rotate x="1" angle="-90"/></transform>'
                  + xml_plugin(extra='<integer name="max_bounces" value="$mb"/>'
                                     '<float name="strength" value="$strength"/>') + "</shape>",
                  {"spp": "1", "width": "24", "height": "16", "mb": "64", "model": "separable",
                   "nm": "normalmap.png", "strength": "1"}, spp="$spp", width="$width", height="$height")

# The map with a uv transform ($su, $sv: NaN and ±inf among the drawn values), and the map given
# as a file name, a normal or a height map (<string name="$kind" value="$nm"/>).
UV_SCENE = SCENE.replace('<boolean name="raw" value="true"/></texture>',
                         '<boolean name="raw" value="true"/><transform name="to_uv"><scale x="$su" y="$sv"/>'
                         '</transform></texture>').replace(
    '<default name="nm"', '<default name="su" value="1"/>\n    <default name="sv" value="1"/>\n    <default name="nm"')
STRING_SCENE = SCENE.replace('<texture type="bitmap" name="normalmap"><string name="filename" value="$nm"/>'
                             '<boolean name="raw" value="true"/></texture>', '<string name="$kind" value="$nm"/>').replace(
    '<default name="nm"', '<default name="kind" value="normalmap"/>\n    <default name="nm"')

BIG_INTS = ["2147483648", "4294967295", "4294967296", "9223372036854775808", "-2147483649", "1" + "0" * 40]
SMALL_INTS = ["-5", "-1", "0", "1", "2", "3", "8", "16"]
JUNK = ["", " ", "1.5", "nan", "inf", "-inf", "0x10", "1e3", "abc", "--", "-", "１", "1_000"]
VALUES = (SMALL_INTS + BIG_INTS + JUNK
          + ["0.5", "1e30", "-1e30", "1e-45", "analytic", "separable", "nonseparable", "fancy", "classic",
             "normalmap.png", "gray.png", "missing.png", "../secret.png", "/dev/zero", "/etc/passwd", "sub",
             "<", "&", '"', "'", "]]>", "$spp", "${spp}", "$", "true", "false", "mikktspace", "mitsuba",
             "auto", "a b", "\x7f", "é"])
XML_KEYS = ["spp", "width", "height", "mb", "model", "nm", "strength", "bogus", "max_depth", "Spp", "sp p", "",
            "1x", "_", "$spp", "su", "sv", "kind"]
GLTF_KEYS = ["width", "height", "spp", "max_depth", "model", "tangents", "normal_maps", "lights", "bogus", "nm"]
OUTPUTS = ["out/render", "out/", "out", "outdir", "good.xml/x", "/sys/mfnormal_fuzz/x", "out/a.png", "out/a.exr",
           "", ".", "..", "out/é", "out/a b", "out/.hidden", "outdir/", "nested/deeper/render", "o" * 300,
           "out/" + "o" * 250]
VARIANTS = ["llvm_ad_rgb"] * 6 + ["llvm_ad_mono", "llvm_ad_spectral", "llvm_ad_spectral_polarized",
                                  "scalar_rgb", "cuda_ad_rgb", "bogus", ""]
LIMIT_NAMES = ["render_pixels", "image_pixels", "texture_pixels", "data_bytes", "vertices", "bogus", ""]


# Valid values per -D key (so that many inputs get as far as a render).
VALID = {"spp": ["1", "2", "4"], "width": ["8", "24", "40", "64"], "height": ["8", "16", "30", "64"],
         "mb": ["1", "3", "64", "1000000", "2147483647"], "model": ["analytic", "separable", "nonseparable"],
         "nm": ["normalmap.png"], "strength": ["0", "0.5", "1", "3", "1e30", "1e6"],
         "max_depth": ["-1", "1", "2", "5"], "su": ["1", "2", "-3", "0", "inf", "-inf", "nan", "1e30", "1e300"],
         "sv": ["1", "0.5", "inf", "nan"], "kind": ["normalmap", "heightmap", "normalmap", "bogus"], "tangents": ["auto", "mikktspace", "mitsuba"],
         "normal_maps": ["true", "false", "0", "yes"], "lights": ["true", "false", "off"]}


def spp_values():
    """Small valid counts or invalid ones; never a long render."""
    return st.one_of(st.sampled_from(["1", "2", "4"]), st.sampled_from(SMALL_INTS + BIG_INTS + JUNK))


@st.composite
def defines(draw, keys):
    out = []
    for _ in range(draw(st.integers(0, 4))):
        key = draw(st.sampled_from(keys))
        if key in VALID and draw(st.integers(0, 9)) < 7:
            value = draw(st.sampled_from(VALID[key]))
        else:
            value = draw(st.sampled_from(VALUES))
        if key in ("spp",) and value.lstrip("-").isdigit() and 16 < int(value) < (1 << 31):
            value = "4"
        form = draw(st.sampled_from(["{k}={v}"] * 16 + ["{k}", "={v}", "{k}=={v}", " {k} ={v}"]))
        out += ["-D", form.format(k=key, v=value)]
    return out


@st.composite
def common_flags(draw):
    args = []
    if draw(st.booleans()):
        args += ["--seed", draw(st.one_of(st.sampled_from(["0", "7", "5000", "4294967295"]),
                                          st.sampled_from(SMALL_INTS + BIG_INTS + JUNK)))]
    if draw(st.integers(0, 5)) == 0:
        name = draw(st.sampled_from(LIMIT_NAMES))
        args += ["--limit", f"{name}={draw(st.sampled_from(SMALL_INTS + BIG_INTS + JUNK + ['2**40', '1e9']))}"]
    return args


@st.composite
def render_args(draw):
    scene = draw(st.sampled_from(["scene.xml"] * 10 + ["model/model.gltf"] * 6 + ["model.glb", "nothere.xml",
                                                                                   "sub", "", "gray.xml",
                                                                                   "s" * 300 + ".xml"]
                                 + ["uv.xml"] * 3 + ["string.xml"] * 3))
    args = ["render", scene]
    if draw(st.booleans()):
        args += ["--spp", draw(spp_values())]
    if draw(st.integers(0, 3)) == 0:
        args += ["--variant", draw(st.sampled_from(VARIANTS))]
    args += draw(common_flags())
    if "model" in scene:
        args += ["-D", "width=18", "-D", "height=12"]     # (a later -D overrides these)
    hostile = {"uv.xml": "su", "string.xml": "kind"}.get(scene)
    if hostile:                                        # its hostile value, most of the time
        args += ["-D", f"{hostile}={draw(st.sampled_from(VALID[hostile]))}"] if draw(st.integers(0, 3)) else []
    args += draw(defines(GLTF_KEYS if "model" in scene else XML_KEYS))
    if draw(st.integers(0, 2)):
        args += ["-o", draw(st.one_of(st.just("out/render"), st.sampled_from(OUTPUTS)))]
    return args


@st.composite
def demo_args(draw):
    args = ["demo"]
    if draw(st.booleans()):
        args += ["--model", draw(st.sampled_from(["analytic", "classic", "fancy", "", "nonseparable", "a b"]))]
    if draw(st.booleans()):
        args += ["--spp", draw(spp_values())]
    for item in draw(common_flags()):
        if item.startswith("--seed"):
            break
        args.append(item)
    args += ["-o", draw(st.sampled_from(OUTPUTS))] if draw(st.booleans()) else []
    return args


@st.composite
def compare_args(draw):
    args = ["compare", draw(st.sampled_from(["scene.xml"] * 4 + ["nothere.xml", "gray.xml", "model/model.gltf"])),
            "--quick", "--methods", draw(st.sampled_from(["flat,analytic", "flat", "analytic,fancy", "", ","]))]
    if draw(st.booleans()):
        args += ["--spp", draw(spp_values())]
    if draw(st.integers(0, 2)) == 0:
        args += ["--width", draw(st.sampled_from(["8", "7", "0", "-3", "64", "abc"] + BIG_INTS[:2]))]
    args += draw(common_flags())
    args += draw(defines(XML_KEYS))
    args += ["-o", draw(st.sampled_from(OUTPUTS + ["cmp"]))] if draw(st.booleans()) else []
    return args


@st.composite
def special_file_args(draw):
    """``render`` or ``compare`` of a scene that names a FIFO, a link to one or a device
    (:func:`add_special_files`), or is a FIFO: a one-line error, never a read that blocks."""
    how = draw(st.sampled_from(["texture", "string_map", "include", "scene"]))
    name = draw(st.sampled_from(["pipe.png", "link.png", "/dev/zero", "outdir"]))
    scene = {"texture": "scene.xml", "string_map": "string_map.xml", "include": "include.xml",
             "scene": draw(st.sampled_from(["pipe.xml", "link.xml"]))}[how]
    command = draw(st.sampled_from(["render", "render", "compare"]))
    args = [command, scene] + (["--quick", "--methods", "flat,analytic"] if command == "compare" else [])
    return args + (["-D", f"nm={name}"] if how in ("texture", "string_map") else [])


def add_special_files(root: Path) -> None:
    """FIFOs (a map and a scene), links to them, and scenes that name them: an ``<include>``
    of the FIFO scene, the plugin's map as a ``<string name="normalmap">``. Nothing ever
    writes into the FIFOs: a command that opens one blocks until the worker's timeout."""
    import os

    os.mkfifo(root / "pipe.png")
    os.mkfifo(root / "pipe.xml")
    (root / "link.png").symlink_to("pipe.png")
    (root / "link.xml").symlink_to("pipe.xml")
    (root / "include.xml").write_text(SCENE.replace("</scene>", '<include filename="pipe.xml"/></scene>'))
    texture = SCENE[SCENE.index('<texture type="bitmap" name="normalmap">'):SCENE.index("</texture>") + 10]
    (root / "string_map.xml").write_text(SCENE.replace(texture, '<string name="normalmap" value="$nm"/>'))


def make_sandbox(root: Path) -> Path:
    write_maps(root)
    (root / "scene.xml").write_text(SCENE)
    (root / "gray.xml").write_text(SCENE.replace('value="normalmap.png"', 'value="gray.png"'))
    (root / "good.xml").write_text(SCENE)
    (root / "uv.xml").write_text(UV_SCENE)
    (root / "string.xml").write_text(STRING_SCENE)
    (root / "outdir").mkdir()
    (root / "sub").mkdir()
    doc, blobs = base_document()
    write_gltf(root / "model", doc, blobs)
    (root / "model.glb").write_bytes(glb_bytes(doc, blobs))
    add_special_files(root)
    return root


def snapshot(root: Path) -> set:
    return {str(p.relative_to(root)) for p in root.rglob("*")}


def check_outcome(result, root: Path, before: set):
    written = snapshot(root) - before

    def rendered():
        assert any(w.endswith((".exr", ".html")) for w in written), (written, result.stdout)

    def nothing_written():
        assert not written, f"written despite the error: {sorted(written)}"

    return render_or_one_line_error(result, TIMEOUT, rendered, nothing_written)


STATS = Stats("CLI fuzzer", digits=2)
report_throughput = STATS.report_fixture()


@fuzz_test(INPUTS)
def test_random_command_lines_render_or_fail_in_one_line(worker, data):
    with STATS.sandbox("mfnormal-clifuzz.") as root:
        make_sandbox(root)
        kind = data.draw(st.sampled_from(["render"] * 7 + ["demo", "compare"] + ["special"] * 3),
                         label="command")
        args = data.draw({"render": render_args(), "demo": demo_args(), "compare": compare_args(),
                          "special": special_file_args()}[kind], label="args")
        before = snapshot(root)
        result = worker.run(args + FORCED, cwd=root, timeout=TIMEOUT)
        STATS.log(result, f"\t{args}")
        STATS.count(check_outcome(result, root, before))
