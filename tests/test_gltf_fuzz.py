"""Structure-aware fuzzing of the glTF loader through ``mfnormal render``.

Each Hypothesis example takes the valid model of ``tests/gltf_models.py`` (a
normal-mapped quad with a strided interleaved buffer, a sparse accessor,
textures, a node tree, a camera and punctual lights) and applies 1–4 mutations
chosen by the document's structure:

- replace a value found anywhere in the JSON tree by one of its kind — an
  index, count, stride or offset by a boundary integer (−1, 0, element sizes,
  252/253, 2^31, 2^32, 2^40, ...), a number (matrix elements, factors, camera
  and light parameters) by a special float (±0, denormal, 1e38, ±inf, NaN), a
  list (children, scene nodes, matrices, colours) by a shortened, lengthened or
  altered one, a string (URIs, types, MIME types) by a hostile one (``..``,
  absolute paths, ``/dev/zero``, ``file:``/``http:`` URIs, percent-encoding, a
  symbolic link out of the folder, a FIFO, a folder, the model itself, ``data:``
  URIs) — or by a value of another JSON type;
- delete a key or a list element, or add a known glTF key (``matrix``,
  ``byteStride``, ``sparse``, ``children``, ``camera``, ``extensions``, ...);
- mutate a file: truncate it, rewrite a PNG's IHDR to 2^16 × 2^16 or more, put
  a JPEG header declaring a huge frame, flip a byte of the buffer;
- write the model as a ``.glb`` (and corrupt a chunk length).

Then ``mfnormal render`` runs in a worker process (``tests/cli_worker.py``:
address space capped at 6 GiB, ``TIMEOUT`` per input) with small ``--limit``\\ s,
and must end with either a render (exit 0, a finite EXR and a PNG) or exactly
one ``mfnormal: error:`` line (exit 2, after at most some ``mfnormal: warning:``
lines, nothing written) — never a traceback, a signal, a timeout, the memory
cap, or a file opened outside the model's folder (the worker records every
open; a ``secret.png`` sits next to the folder, and links to it and to
``/dev/zero`` inside it).

The default run takes ``QUICK_INPUTS`` inputs, ``MFNORMAL_SLOW=1`` ``CI_INPUTS``, both
derandomised (the same inputs every run). ``MFNORMAL_FUZZ_LONG=1`` runs
``LONG_INPUTS`` random inputs (``MFNORMAL_FUZZ_INPUTS=N`` sets the count), and
prints the Hypothesis seed of a failure. The test prints the throughput
(``pytest -s``); ``MFNORMAL_FUZZ_LOG=FILE`` appends each input's exit code and
last stderr line to FILE.
"""

from __future__ import annotations

import base64
import copy
import json
import os
import struct
from pathlib import Path

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import mitsuba as mi
import numpy as np
from hypothesis import strategies as st

from fuzzing import Stats, fuzz_test, input_count, render_or_one_line_error
from gltf_models import base_document, glb_bytes
from mfnormal.io.images import png_bytes

QUICK_INPUTS, CI_INPUTS, LONG_INPUTS = 200, 800, 10_000
INPUTS = input_count(CI_INPUTS, LONG_INPUTS, QUICK_INPUTS)
TIMEOUT = 60.0
# Small caps: a mutation that asks for more is refused quickly (and the caps are exercised).
LIMITS = ["--limit", "render_pixels=20000", "--limit", "image_pixels=1048576", "--limit", "texture_pixels=4194304",
          "--limit", "vertices=100000", "--limit", "data_bytes=16000000"]
ARGS = ["-D", "height=12", "-D", "spp=1", "-D", "max_depth=2"]

SPECIAL_INTS = [-(1 << 63), -(1 << 31), -4, -1, 0, 1, 2, 3, 4, 5, 6, 7, 8, 11, 12, 13, 16, 24, 48, 252, 253, 255, 256,
                4095, 4096, 5120, 5121, 5123, 5125, 5126, 9728, 10497, 65535, 65536, (1 << 31) - 1, 1 << 31,
                (1 << 32) - 1, 1 << 32, 1 << 40, 1 << 63, 10 ** 30]
SPECIAL_FLOATS = [0.0, -0.0, 5e-324, 1e-38, 1e-7, 0.5, 1.0, -1.0, 1.0000001, 1.5707964, 3.1415927, 3.2, 1e6, 1e30,
                  3.4e38, 1e308, float("inf"), float("-inf"), float("nan")]
TYPE_NAMES = ["SCALAR", "VEC2", "VEC3", "VEC4", "MAT2", "MAT4", "perspective", "orthographic", "directional",
              "point", "spot", "area", "OPAQUE", "BLEND", "image/png", "image/jpeg", "image/webp", "", "2.0", "1.0",
              "3.0", "2.1"]
KNOWN_KEYS = ["matrix", "byteStride", "byteOffset", "byteLength", "sparse", "children", "camera", "mesh", "skin",
              "extensions", "uri", "bufferView", "buffer", "scale", "rotation", "translation", "normalized", "count",
              "texCoord", "light", "targets", "mode", "indices", "material", "sampler", "source", "normalTexture",
              "orthographic", "perspective", "aspectRatio", "KHR_lights_punctual", "KHR_texture_transform", "scene",
              "nodes", "TANGENT", "NORMAL", "TEXCOORD_0", "POSITION", "spot", "intensity", "extensionsRequired"]


def sandbox_uris(folder: Path):
    secret = (folder.parent / "secret.png").resolve()
    nm = (folder / "nm.png").read_bytes()
    return ["nm.png", "base.png", "quad.bin", "./nm.png", "sub/../nm.png", "../secret.png", str(secret),
            "/dev/zero", "/etc/passwd", secret.as_uri(), "%2e%2e/secret.png", "..%2fsecret.png", "out_link.png",
            "zero_link", "sub", "pipe", "model.gltf", "", "nm.png%00.bin", "C:\\secret.png",
            "\\\\server\\share\\secret.png", "http://127.0.0.1:9/secret.png",
            "data:application/octet-stream;base64,AAAA", "data:image/png;base64," + base64.b64encode(nm).decode(),
            "data:,abc", "data:image/png;base64,!!!", "n" * 300 + ".png", "sub/" * 600 + "nm.png"]


# -- Mutations ----------------------------------------------------------------------------------------

def json_paths(doc, prefix=()):
    """Every (path, value) below ``doc`` (the root excluded)."""
    out = []
    items = doc.items() if isinstance(doc, dict) else enumerate(doc) if isinstance(doc, list) else []
    for k, v in items:
        out.append((prefix + (k,), v))
        out.extend(json_paths(v, prefix + (k,)))
    return out


def get(doc, path):
    for k in path:
        doc = doc[k]
    return doc


@st.composite
def value_like(draw, old, key, uris):
    """A hostile value, usually of ``old``'s kind."""
    other = st.one_of(st.none(), st.booleans(), st.sampled_from(SPECIAL_INTS), st.sampled_from(SPECIAL_FLOATS),
                      st.sampled_from(TYPE_NAMES + uris), st.just([]), st.just({}),
                      st.lists(st.sampled_from(SPECIAL_INTS[:20]), max_size=5))
    if draw(st.integers(0, 9)) == 0:
        return draw(other)
    if key == "uri" or (isinstance(old, str) and draw(st.booleans())):
        return draw(st.sampled_from(uris))
    if isinstance(old, str):
        return draw(st.sampled_from(TYPE_NAMES))
    if isinstance(old, bool):
        return not old
    if isinstance(old, int):
        return draw(st.one_of(st.sampled_from(SPECIAL_INTS), st.integers(-3, 3).map(lambda d: old + d),
                              st.integers(-(1 << 64), 1 << 64)))
    if isinstance(old, float):
        return draw(st.one_of(st.sampled_from(SPECIAL_FLOATS), st.floats(allow_nan=True, allow_infinity=True),
                              st.floats(-2.0, 2.0).map(lambda f: old * f)))
    if isinstance(old, list):
        if not old:
            return draw(st.lists(st.sampled_from(SPECIAL_INTS[:24]), max_size=4))
        choice = draw(st.integers(0, 4))
        new = list(old)
        if choice == 0:
            return new[:draw(st.integers(0, len(new) - 1))]
        if choice == 1:
            return new + [draw(st.sampled_from(new))] * draw(st.integers(1, 3))
        if choice == 2:
            i = draw(st.integers(0, len(new) - 1))
            new[i] = draw(value_like(new[i], key, uris))
            return new
        if choice == 3:
            return draw(st.lists(st.sampled_from(SPECIAL_FLOATS if isinstance(old[0], float) else SPECIAL_INTS[:24]),
                                 min_size=len(old), max_size=len(old)))
        return list(reversed(new))
    return draw(other)


def png_with_size(data: bytes, w: int, h: int) -> bytes:
    import zlib
    ihdr = bytearray(data[16:29])
    struct.pack_into(">II", ihdr, 0, w, h)
    return data[:16] + bytes(ihdr) + struct.pack(">I", zlib.crc32(b"IHDR" + bytes(ihdr))) + data[33:]


def jpeg_header(w, h) -> bytes:
    return (b"\xff\xd8\xff\xe0" + struct.pack(">H", 16) + b"JFIF\0\x01\x01\0\0\x01\0\x01\0\0"
            + b"\xff\xc0" + struct.pack(">HBHHB", 17, 8, h, w, 3) + b"\x01\x11\0\x02\x11\0\x03\x11\0\xff\xd9")


@st.composite
def file_mutation(draw):
    name = draw(st.sampled_from(["quad.bin", "nm.png", "base.png"]))
    kind = draw(st.sampled_from(["truncate", "huge_png", "jpeg", "flip", "empty"]))
    if kind == "truncate":
        return (name, kind, draw(st.integers(0, 64)))
    if kind == "huge_png":
        return (name, kind, draw(st.sampled_from([(1 << 16, 1 << 16), (16000, 16000), (1 << 31, 1), (0, 5)])))
    if kind == "jpeg":
        return (name, kind, draw(st.sampled_from([(20000, 20000), (65535, 65535), (8, 8), (0, 0)])))
    if kind == "flip":
        return (name, kind, (draw(st.integers(0, 1 << 16)), draw(st.integers(1, 255))))
    return (name, kind, None)


def apply_file_mutation(blobs, mutation):
    name, kind, arg = mutation
    data = blobs[name]
    if kind == "truncate":
        data = data[:arg]
    elif kind == "huge_png":
        data = png_with_size(base_document()[1]["nm.png"], *arg)
    elif kind == "jpeg":
        data = jpeg_header(*arg)
    elif kind == "flip":
        pos, xor = arg
        if data:
            b = bytearray(data)
            b[pos % len(b)] ^= xor
            data = bytes(b)
    else:
        data = b""
    blobs[name] = data


@st.composite
def mutated_model(draw, uris):
    """(document, blobs, container, glb corruption)."""
    doc, blobs = base_document()
    doc = copy.deepcopy(doc)
    blobs = dict(blobs)
    for _ in range(draw(st.integers(1, 4))):
        kind = draw(st.sampled_from(["replace"] * 5 + ["delete", "insert", "file"]))
        paths = json_paths(doc)
        # Mostly below the top level (Hypothesis favours the first entries of a list).
        deep = [p for p in paths if len(p[0]) > 1]
        if deep and draw(st.integers(0, 9)) > 0:
            paths = deep
        if kind == "file":
            apply_file_mutation(blobs, draw(file_mutation()))
            continue
        if not paths:
            continue
        path, old = draw(st.sampled_from(paths))
        parent = get(doc, path[:-1])
        key = path[-1]
        if kind == "replace":
            parent[key] = draw(value_like(old, key if isinstance(key, str) else path[-2], uris))
        elif kind == "delete":
            del parent[key]
        else:
            target = old if isinstance(old, dict) else parent if isinstance(parent, dict) else None
            if target is not None:
                new_key = draw(st.sampled_from(KNOWN_KEYS))
                sample = {"matrix": [1.0] * 16, "children": [0], "rotation": [0.0, 0.0, 0.0, 1.0]}.get(new_key, 1)
                target[new_key] = draw(value_like(sample, new_key, uris))
    container = draw(st.sampled_from(["gltf"] * 4 + ["glb"]))
    corrupt = draw(st.sampled_from([None] * 3 + ["json_length", "bin_length", "total_length", "version"])) \
        if container == "glb" else None
    return doc, blobs, container, corrupt


def write_model(folder: Path, doc, blobs, container, corrupt) -> Path:
    for name, data in blobs.items():
        (folder / name).write_bytes(data)
    if container == "gltf":
        path = folder / "model.gltf"
        path.write_text(json.dumps(doc))           # NaN and Infinity included, as json writes them
        return path
    try:
        data = bytearray(glb_bytes(doc, blobs))
    except (KeyError, TypeError, AttributeError, ValueError):
        data = bytearray(b"glTF" + struct.pack("<II", 2, 20) + struct.pack("<II", 0, 0x4E4F534A))
    if corrupt == "json_length":
        struct.pack_into("<I", data, 12, (1 << 32) - 1)
    elif corrupt == "bin_length" and len(data) > 24:
        text = struct.unpack_from("<I", data, 12)[0]
        if 20 + text + 8 <= len(data):
            struct.pack_into("<I", data, 20 + text, (1 << 31))
    elif corrupt == "total_length":
        struct.pack_into("<I", data, 8, len(data) * 1000)
    elif corrupt == "version":
        struct.pack_into("<I", data, 4, 1)
    path = folder / "model.glb"
    path.write_bytes(bytes(data))
    return path


def make_sandbox(root: Path) -> Path:
    """root/secret.png and root/model/ with the base files, a folder, a FIFO and links out."""
    secret = np.zeros((8, 8, 3), np.uint8)
    secret[..., 0] = 255
    (root / "secret.png").write_bytes(png_bytes(secret))
    folder = root / "model"
    folder.mkdir()
    _, blobs = base_document()
    for name, data in blobs.items():
        (folder / name).write_bytes(data)
    (folder / "sub").mkdir()
    os.mkfifo(folder / "pipe")
    (folder / "out_link.png").symlink_to(root / "secret.png")
    (folder / "zero_link").symlink_to("/dev/zero")
    return folder


# -- The check -----------------------------------------------------------------------------------------

def outside_reads(opened, folder: Path, root: Path) -> list:
    base, sandbox = os.path.realpath(folder), os.path.realpath(root)
    bad = []
    for p in opened:
        real = os.path.realpath(p)
        in_sandbox = os.path.commonpath([sandbox, real]) == sandbox
        in_folder = os.path.commonpath([base, real]) == base
        in_out = os.path.commonpath([os.path.join(sandbox, "out"), real]) == os.path.join(sandbox, "out")
        if (in_sandbox and not in_folder and not in_out) or (real.startswith("/dev/") and real != "/dev/null") \
                or real.startswith("/etc/"):
            bad.append(p)
    return bad


def check_outcome(result, out: Path, folder: Path, root: Path):
    """Render or one-line error; never anything else. Returns 'render' or 'error'."""
    bad = outside_reads(result.opened, folder, root)
    assert not bad, f"opened outside the model's folder: {bad}"

    def rendered():
        img = np.array(mi.Bitmap(f"{out}.exr"), dtype=np.float64)
        assert np.all(np.isfinite(img)) and img.min() >= 0.0
        assert Path(f"{out}.png").is_file()

    def nothing_written():
        assert not out.parent.exists() or not list(out.parent.iterdir()), list(out.parent.iterdir())

    return render_or_one_line_error(result, TIMEOUT, rendered, nothing_written)


STATS = Stats("glTF fuzzer")
report_throughput = STATS.report_fixture()


@fuzz_test(INPUTS)
def test_mutated_gltf_renders_or_fails_in_one_line(worker, data):
    with STATS.sandbox("mfnormal-fuzz.") as root:
        folder = make_sandbox(root)
        doc, blobs, container, corrupt = data.draw(mutated_model(sandbox_uris(folder)), label="model")
        path = write_model(folder, doc, blobs, container, corrupt)
        out = root / "out" / "render"
        result = worker.run(["render", path, "-o", out, *ARGS, *LIMITS], cwd=folder, timeout=TIMEOUT)
        STATS.log(result)
        STATS.count(check_outcome(result, out, folder, root))
