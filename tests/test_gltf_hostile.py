"""Hostile glTF files: every class of the loader's security and termination problems.

Each case mutates a copy of a small valid model (``tests/gltf_models.py``: a
normal-mapped quad with an interleaved, strided buffer, a sparse accessor, a
camera and lights) and renders it with ``mfnormal render`` in a worker process
under a time and memory bound (``tests/cli_worker.py``: 6 GiB address space,
120 s). A case either renders (exit 0, an EXR/PNG pair) or fails with exactly one
line ``mfnormal: error: ...`` that names the element (the needles), exit 2, and
writes nothing. In every case no file outside the model's folder is opened: a
``secret.png`` sits next to the folder, and the worker records every file the
command opens.

Classes: reference cycles and nodes with two parents (a
walk that never ends), negative or too-small ``byteStride``, negative
``byteOffset``, counts past the view, views past the buffer, sparse indices out
of range, URIs outside the folder (``..``, absolute, percent-encoded, ``file:``,
a symbolic link), non-regular files (``/dev/zero``, a folder, a FIFO), files
shorter than ``byteLength``, decompression bombs (a 16000² PNG, a 20000² JPEG
header), a camera ``aspectRatio`` of 1e6 and ``-D width=24000000``, indices out
of range (materials, accessors, textures, index data), a camera without its
projection, lights with index −1, a negative intensity or a negative cone angle,
a legal ``scale: [0, 0, 0]`` node (renders), broken JSON and GLB containers,
and the vertex limit after instancing.
"""

from __future__ import annotations

import copy
import json
import os
import struct
import zlib
from pathlib import Path

import numpy as np
import pytest

from gltf_models import base_document, glb_bytes, write_gltf
from mfnormal.io.images import png_bytes

SMALL = ["-D", "height=12", "-D", "spp=1", "-D", "max_depth=2"]

#: (id, mutation, expected: "renders" or the needles of the one-line error), one per mutation below.
CASES = []


def case(name: str, expected):
    """Register the decorated mutation ``f(doc, blobs, folder)`` as the hostile case ``name``."""
    def register(mutation):
        CASES.append((name, mutation, expected))
        return mutation
    return register


@pytest.fixture(scope="module")
def huge_png(tmp_path_factory) -> bytes:
    """A real 16000×16000 8-bit grey PNG (all zeros, ~250 KB): decoding it takes 256 MB and more."""
    w = h = 16000
    comp = zlib.compressobj(9)
    row = b"\0" * (w + 1)
    idat = b"".join(comp.compress(row) for _ in range(h)) + comp.flush()

    def chunk(tag, data):
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, 0, 0, 0, 0))
            + chunk(b"IDAT", idat) + chunk(b"IEND", b""))


def jpeg_header(w, h) -> bytes:
    """A JPEG start: SOI, an APP0 segment and a baseline SOF0 frame header declaring w × h."""
    app0 = b"\xff\xe0" + struct.pack(">H", 16) + b"JFIF\0\x01\x01\0\0\x01\0\x01\0\0"
    sof = b"\xff\xc0" + struct.pack(">HBHHB", 17, 8, h, w, 3) + b"\x01\x11\0\x02\x11\0\x03\x11\0"
    return b"\xff\xd8" + app0 + sof + b"\xff\xd9"


# -- Mutations: (doc, blobs, folder) -> optional extra CLI arguments -------------------------------

@case("cycle", ["nodes[1].children", "cycle through node 0"])
def cycle(doc, blobs, folder):
    doc["nodes"][1]["children"] = [0]


@case("self_cycle", ["nodes[0].children", "cycle through node 0"])
def self_cycle(doc, blobs, folder):
    doc["scenes"] = [{"nodes": [0]}]
    doc["nodes"] = [{"mesh": 0, "children": [0]}]


@case("two_parents_40_levels", ["nodes[2].children", "node 3 is already a child of node 1"])
def diamond_tower(doc, blobs, folder):
    """40 levels of two nodes, each listing both nodes of the next level: 2^40 paths."""
    nodes = [{"children": [1, 2]}]
    for level in range(40):
        a = 1 + 2 * level
        nxt = [a + 2, a + 3] if level < 39 else []
        nodes += [{"mesh": 0, "children": nxt}, {"children": nxt}]
    doc["nodes"] = nodes
    doc["scenes"] = [{"nodes": [0]}]


@case("child_listed_twice", ["nodes[0].children", "node 1 is listed twice"])
def child_listed_twice(doc, blobs, folder):
    doc["nodes"][0]["children"] = [1, 1, 2, 3, 4]


@case("scene_root_is_a_child", ["scenes[0].nodes", "node 1", "not a root"])
def root_listed_as_child(doc, blobs, folder):
    doc["scenes"][0]["nodes"] = [0, 1]


@case("negative_byteStride", ["bufferViews[0].byteStride", "-12"])
def negative_stride(doc, blobs, folder):
    doc["bufferViews"][0]["byteStride"] = -12


@case("byteStride_below_element", ["accessors[0]", "byteStride 8", "12-byte element"])
def small_stride(doc, blobs, folder):
    doc["bufferViews"][0]["byteStride"] = 8


@case("negative_byteOffset", ["accessors[2].byteOffset", "-8"])
def negative_offset(doc, blobs, folder):
    doc["accessors"][2]["byteOffset"] = -8


@case("count_past_bufferView", ["accessors[2]", "bufferViews[1]"])
def count_past_view(doc, blobs, folder):
    doc["accessors"][2]["count"] = 100000


@case("bufferView_past_buffer", ["bufferViews[1]", "buffers[0]"])
def view_past_buffer(doc, blobs, folder):
    doc["bufferViews"][1]["byteLength"] = 1 << 20


@case("sparse_index_out_of_range", ["accessors[0].sparse.indices", "200"])
def sparse_index_out_of_range(doc, blobs, folder):
    view = doc["bufferViews"][3]
    blob = bytearray(blobs["quad.bin"])
    blob[view["byteOffset"]] = 200           # the sparse index: the accessor has 4 elements
    blobs["quad.bin"] = bytes(blob)


@case("sparse_count_past_accessor", ["accessors[0].sparse.count", "50"])
def sparse_count_past_accessor(doc, blobs, folder):
    doc["accessors"][0]["sparse"]["count"] = 50


@case("zero_filled_accessor_bomb", ["accessors[0]", "data_bytes"])
def zero_filled_bomb(doc, blobs, folder):
    """An accessor without bufferView is zeros: a count of 2^40 asks for 12 TB."""
    acc = doc["accessors"][0]
    acc.pop("bufferView")
    acc.pop("sparse")
    acc["count"] = 1 << 40


# URIs that lead out of the model's folder: (case, element, its uri for the model's folder, needles).
OUTSIDE_URIS = [
    ("uri_dotdot", "images", lambda folder: "../secret.png", ["images[0].uri", "outside the model's folder"]),
    ("uri_subfolder_dotdot", "images", lambda folder: "textures/../../secret.png",
     ["images[0].uri", "outside the model's folder"]),
    ("uri_absolute", "images", lambda folder: str((folder.parent / "secret.png").resolve()),
     ["images[0].uri", "absolute path"]),
    ("uri_percent_encoded", "images", lambda folder: "%2e%2e/secret.png",
     ["images[0].uri", "outside the model's folder"]),
    ("uri_file_scheme", "images", lambda folder: (folder.parent / "secret.png").resolve().as_uri(),
     ["images[0].uri", "file: URIs are not read"]),
    ("uri_dev_zero", "buffers", lambda folder: "/dev/zero", ["buffers[0].uri", "absolute path"]),
]


def set_uri(element: str, uri):
    def mutate(doc, blobs, folder):
        doc[element][0]["uri"] = uri(folder)
    return mutate


for name, element, uri, needles in OUTSIDE_URIS:
    case(name, needles)(set_uri(element, uri))


@case("uri_symlink_out_of_folder", ["images[0].uri", "outside the model's folder"])
def symlink_out_of_folder(doc, blobs, folder):
    (folder / "link.png").symlink_to(folder.parent / "secret.png")
    doc["images"][0]["uri"] = "link.png"


@case("uri_symlink_to_dev_zero", ["buffers[0].uri", "outside the model's folder"])
def dev_zero_symlink(doc, blobs, folder):
    (folder / "zero.bin").symlink_to("/dev/zero")
    doc["buffers"][0]["uri"] = "zero.bin"


@case("uri_folder", ["buffers[0].uri", "not a regular file"])
def folder_as_buffer(doc, blobs, folder):
    (folder / "sub").mkdir()
    doc["buffers"][0]["uri"] = "sub"


@case("uri_fifo", ["images[0].uri", "not a regular file"])
def fifo_as_image(doc, blobs, folder):
    os.mkfifo(folder / "pipe.png")
    doc["images"][0]["uri"] = "pipe.png"


@case("buffer_shorter_than_byteLength", ["buffers[0].uri", "less than the byteLength"])
def buffer_shorter_than_declared(doc, blobs, folder):
    doc["buffers"][0]["byteLength"] += 4096
    doc["bufferViews"][1]["byteLength"] += 4096


def png_bomb(huge):
    def mutate(doc, blobs, folder):
        blobs["nm.png"] = huge
    return mutate


# The PNG bomb's mutation needs the huge_png fixture: prepare() builds it.
CASES.append(("png_16000x16000", "png_bomb", ["images[0]", "16000x16000", "image_pixels"]))


@case("jpeg_20000x20000", ["images[0]", "20000x20000", "image_pixels"])
def jpeg_bomb(doc, blobs, folder):
    blobs["nm.jpg"] = jpeg_header(20000, 20000)
    doc["images"][0]["uri"] = "nm.jpg"


@case("camera_aspectRatio_1e6", ["cameras[0].perspective.aspectRatio", "render_pixels"])
def huge_aspect_ratio(doc, blobs, folder):
    doc["cameras"][0]["perspective"]["aspectRatio"] = 1e6


@case("width_24000000", ["24000000", "render_pixels"])
def huge_width(doc, blobs, folder):
    return ["-D", "width=24000000"]


@case("material_index_out_of_range", ["meshes[0].primitives[0].material", "5"])
def material_out_of_range(doc, blobs, folder):
    doc["meshes"][0]["primitives"][0]["material"] = 5


@case("accessor_index_out_of_range", ["attributes.POSITION", "99"])
def accessor_out_of_range(doc, blobs, folder):
    doc["meshes"][0]["primitives"][0]["attributes"]["POSITION"] = 99


@case("texture_source_out_of_range", ["textures[1].source", "7"])
def texture_source_out_of_range(doc, blobs, folder):
    doc["textures"][1]["source"] = 7


@case("index_data_out_of_range", ["meshes[0].primitives[0].indices", "5124"])
def index_data_out_of_range(doc, blobs, folder):
    view = doc["bufferViews"][2]
    blob = bytearray(blobs["quad.bin"])
    struct.pack_into("<H", blob, view["byteOffset"] + 4, 5124)
    blobs["quad.bin"] = bytes(blob)


@case("camera_without_perspective", ["cameras[0]", "'perspective' is required"])
def camera_without_projection(doc, blobs, folder):
    doc["cameras"][0].pop("perspective")


@case("light_index_minus_one", ["nodes[3].extensions.KHR_lights_punctual.light", "-1"])
def light_index_minus_one(doc, blobs, folder):
    doc["nodes"][3]["extensions"]["KHR_lights_punctual"]["light"] = -1


@case("light_negative_intensity", ["lights[0].intensity", "-3"])
def negative_intensity(doc, blobs, folder):
    doc["extensions"]["KHR_lights_punctual"]["lights"][0]["intensity"] = -3.0


@case("light_negative_cone_angle", ["lights[1].spot.innerConeAngle", "-0.5"])
def negative_cone_angle(doc, blobs, folder):
    doc["extensions"]["KHR_lights_punctual"]["lights"][1]["spot"]["innerConeAngle"] = -0.5


@case("scale_zero_node_renders", "renders")
def zero_scale_node(doc, blobs, folder):
    """A second instance of the mesh, scaled to nothing (legal: e.g. a hidden object)."""
    doc["nodes"].append({"mesh": 0, "scale": [0, 0, 0]})
    doc["nodes"][0]["children"].append(len(doc["nodes"]) - 1)


@case("scale_flat_node_renders", "renders")
def flat_scale_node(doc, blobs, folder):
    doc["nodes"][1]["scale"] = [1, 0, 1]      # the quad seen edge-on: flattened, still legal
    doc["nodes"].append({"mesh": 0, "translation": [0, 0, -1]})
    doc["nodes"][0]["children"].append(len(doc["nodes"]) - 1)


@case("zero_quaternion", ["nodes[1].rotation", "unit quaternion"])
def zero_quaternion(doc, blobs, folder):
    doc["nodes"][1]["rotation"] = [0, 0, 0, 0]


@case("json_nan", ["not a valid glTF 2.0 file", "NaN"])
def nan_matrix(doc, blobs, folder):
    (folder / "model.gltf").write_text(json.dumps(doc).replace('"scale": [1, 1, 1]', '"scale": [NaN, 1, 1]'))
    return "raw"


@case("node_matrix_1e300", ["nodes[1]", "float range"])
def huge_matrix(doc, blobs, folder):
    """A finite matrix whose products overflow: one line, without numpy's overflow warnings."""
    for key in ("translation", "rotation", "scale"):
        doc["nodes"][1].pop(key)
    doc["nodes"][1]["matrix"] = [1e300, 0, 0, 0, 0, 1e300, 0, 0, 0, 0, 1e300, 0, 0, 0, 0, 1]


@case("json_not_an_object", ["not a valid glTF 2.0 file", "not an object"])
def json_not_an_object(doc, blobs, folder):
    (folder / "model.gltf").write_text("[1, 2, 3]")
    return "raw"


@case("asset_version_1", ["asset.version", "1.0"])
def wrong_version(doc, blobs, folder):
    doc["asset"]["version"] = "1.0"


@case("data_uri_not_base64", ["images[1].uri", "base64"])
def data_uri_not_base64(doc, blobs, folder):
    doc["images"][1]["uri"] = "data:image/png,%89PNG"


@case("vertex_limit_after_instancing", ["vertices", "after instancing"])
def many_instances(doc, blobs, folder):
    """1000 nodes instancing the 4-vertex quad, under a vertex limit of 100."""
    for k in range(1000):
        doc["nodes"].append({"mesh": 0, "translation": [0, 0, -0.001 * k]})
        doc["nodes"][0]["children"].append(len(doc["nodes"]) - 1)
    return ["--limit", "vertices=100"]


@case("glb_chunk_past_end", ["not a valid glTF 2.0 file", "GLB", "past the end"])
def glb_chunk_past_end(doc, blobs, folder):
    data = bytearray(glb_bytes(doc, blobs))
    struct.pack_into("<I", data, 12, len(data) * 4)         # the JSON chunk's length
    (folder / "model.glb").write_bytes(bytes(data))
    return "glb"


@case("glb_buffer_past_binary_chunk", ["buffers[0]", "binary chunk"])
def glb_buffer_past_binary_chunk(doc, blobs, folder):
    """buffers[0].byteLength is larger than the binary chunk (cut to 16 bytes)."""
    data = glb_bytes(doc, blobs)
    text_len = struct.unpack_from("<I", data, 12)[0]
    head = data[:20 + text_len]
    binary = data[20 + text_len + 8:][:16]
    body = head[12:] + struct.pack("<II", len(binary), 0x004E4942) + binary
    (folder / "model.glb").write_bytes(b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body)
    return "glb"




def prepare(tmp_path, mutation, huge_png):
    """The model folder ``tmp_path/model`` (and ``tmp_path/secret.png``): (file, extra args)."""
    folder = tmp_path / "model"
    folder.mkdir()
    secret = np.zeros((8, 8, 3), np.uint8)
    secret[..., 0] = 255
    (tmp_path / "secret.png").write_bytes(png_bytes(secret))
    doc, blobs = base_document()
    doc, blobs = copy.deepcopy(doc), dict(blobs)
    if mutation == "png_bomb":
        mutation = png_bomb(huge_png)
    extra = mutation(doc, blobs, folder)
    if extra == "raw":
        for name, data in blobs.items():
            (folder / name).write_bytes(data)
        return folder / "model.gltf", []
    if extra == "glb":
        return folder / "model.glb", []
    return write_gltf(folder, doc, blobs), list(extra or [])


def outside_reads(result, folder: Path, sandbox: Path) -> list:
    """Files the command opened in ``sandbox`` but outside ``folder``, and device files."""
    bad = []
    base = os.path.realpath(folder)
    for p in result.opened:
        real = os.path.realpath(p)
        inside_sandbox = os.path.commonpath([os.path.realpath(sandbox), real]) == os.path.realpath(sandbox)
        inside_folder = os.path.commonpath([base, real]) == base
        if (inside_sandbox and not inside_folder and not real.startswith(os.path.realpath(sandbox / "out"))) \
                or real.startswith("/dev/") and real != "/dev/null":
            bad.append(p)
    return bad


def check_result(result, expected, out: Path):
    lines = [ln for ln in result.stderr.strip().splitlines() if ln.strip()]
    if expected == "renders":
        assert result.rc == 0, result.describe()
        assert out.with_suffix(".exr").is_file() and out.with_suffix(".png").is_file()
        return
    assert result.rc == 2, result.describe()
    assert len(lines) == 1 and lines[0].startswith("mfnormal: error: "), result.stderr
    for needle in expected:
        assert needle in lines[0], f"{needle!r} not in {lines[0]!r}"
    assert not list(out.parent.iterdir()), f"files written: {list(out.parent.iterdir())}"


@pytest.mark.parametrize("case,mutation,expected", CASES, ids=[c[0] for c in CASES])
def test_hostile_gltf_renders_or_fails_in_one_line(worker, tmp_path, huge_png, case, mutation, expected):
    path, extra = prepare(tmp_path, mutation, huge_png)
    (tmp_path / "out").mkdir()
    out = tmp_path / "out" / "render"
    result = worker.run(["render", path, "-o", out, *SMALL, *extra], cwd=path.parent)
    assert not result.timed_out and result.died is None and result.exception is None, result.describe()
    check_result(result, expected, out)
    assert not outside_reads(result, path.parent, tmp_path), outside_reads(result, path.parent, tmp_path)


def test_the_base_model_renders_as_gltf_and_glb(worker, tmp_path):
    """The unmutated model renders in both containers, and the same (so a case above that
    fails does so because of its mutation)."""
    doc, blobs = base_document()
    gltf = write_gltf(tmp_path / "a", doc, blobs)
    (tmp_path / "b").mkdir()
    glb = tmp_path / "b" / "model.glb"
    glb.write_bytes(glb_bytes(doc, blobs))
    images = []
    for path in (gltf, glb):
        out = tmp_path / f"out_{path.suffix[1:]}"
        result = worker.run(["render", path, "-o", out, "-D", "height=24", "-D", "spp=4"], cwd=path.parent)
        assert result.rc == 0, result.describe()
        import mitsuba as mi
        images.append(np.array(mi.Bitmap(str(out) + ".exr")))
    assert images[0].shape == (24, 36, 3)          # the camera's aspectRatio 1.5
    assert images[0].mean() > 0.01
    # The same up to the film's float sums in thread order (see test_hostile.THREAD_RTOL).
    assert np.allclose(images[0], images[1], rtol=1e-5, atol=1e-7)


def test_zero_scale_instance_is_skipped_with_a_warning(worker, tmp_path):
    """scale [0, 0, 0] on a second instance: the render equals the model without it, and the
    warning names the node (the old loader failed with 'Singular matrix')."""
    doc, blobs = base_document()
    plain = write_gltf(tmp_path / "plain", doc, blobs)
    zero_scale_node(doc, blobs, None)
    hidden = write_gltf(tmp_path / "hidden", doc, blobs)
    import mitsuba as mi
    images = []
    for path in (plain, hidden):
        out = path.parent / "render"
        result = worker.run(["render", path, "-o", out, "-D", "height=24", "-D", "spp=2"], cwd=path.parent)
        assert result.rc == 0, result.describe()
        images.append(np.array(mi.Bitmap(str(out) + ".exr")))
    assert "nodes[5]" in result.stderr and "zero scale" in result.stderr, result.stderr
    assert np.allclose(images[0], images[1], rtol=1e-5, atol=1e-7)
