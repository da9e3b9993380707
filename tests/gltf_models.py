"""A small, complete glTF 2.0 model as a JSON document, for the hostile-input tests and the fuzzer.

:func:`base_document` returns (document, blobs): a textured, normal-mapped quad
that uses most of what the loader reads — an interleaved bufferView with a
``byteStride`` (positions and normals), a sparse accessor, 16-bit indices, two
PNG textures (a normal map and a base colour) with a sampler, a node tree with
TRS transforms, a perspective camera with an ``aspectRatio``, and
``KHR_lights_punctual`` directional and spot lights — and blobs, the files it
refers to (``quad.bin``, ``nm.png``, ``base.png``). :func:`write_gltf` writes a
``.gltf`` with those files next to it; :func:`write_glb` packs the same model
into one ``.glb`` (the buffer in the binary chunk, the images in bufferViews).
The model renders: the tests mutate copies of it.
"""

from __future__ import annotations

import copy
import json
import struct
from pathlib import Path

import numpy as np

from mfnormal.io.images import png_bytes


def _normal_map(size=8):
    n = np.zeros((size, size, 3), np.float64)
    n[...] = (0.0, 0.0, 1.0)
    n[2:6, 2:6] = (0.5, 0.2, 0.84)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return np.round((n * 0.5 + 0.5) * 255).astype(np.uint8)


def _base_colour(size=8):
    img = np.zeros((size, size, 3), np.uint8)
    img[...] = (200, 180, 150)
    img[::2, ::2] = (90, 120, 200)
    return img


def base_document():
    """(glTF document as a dict, {file name: bytes})."""
    positions = np.array([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]], np.float32)
    normals = np.tile(np.float32([0, 0, 1]), (4, 1))
    uvs = np.array([[0, 1], [1, 1], [1, 0], [0, 0]], np.float32)
    indices = np.array([0, 1, 2, 0, 2, 3], np.uint16)
    interleaved = np.concatenate([positions, normals], axis=1)          # 24-byte stride
    parts, views = [], []

    def add(data: bytes, stride=None):
        offset = sum(len(p) for p in parts)
        parts.append(data + b"\0" * (-len(data) % 4))
        view = {"buffer": 0, "byteOffset": offset, "byteLength": len(data)}
        if stride:
            view["byteStride"] = stride
        views.append(view)
        return len(views) - 1

    v_inter = add(interleaved.tobytes(), stride=24)
    v_uv = add(uvs.tobytes())
    v_idx = add(indices.tobytes())
    v_sparse_idx = add(np.array([2], np.uint8).tobytes())
    v_sparse_val = add(positions[2].tobytes())          # the same value: the sparse read is exercised
    blob = b"".join(parts)
    accessors = [
        {"bufferView": v_inter, "byteOffset": 0, "componentType": 5126, "count": 4, "type": "VEC3",
         "min": [-1, -1, 0], "max": [1, 1, 0],
         "sparse": {"count": 1, "indices": {"bufferView": v_sparse_idx, "componentType": 5121},
                    "values": {"bufferView": v_sparse_val}}},
        {"bufferView": v_inter, "byteOffset": 12, "componentType": 5126, "count": 4, "type": "VEC3"},
        {"bufferView": v_uv, "componentType": 5126, "count": 4, "type": "VEC2"},
        {"bufferView": v_idx, "componentType": 5123, "count": 6, "type": "SCALAR"},
    ]
    doc = {
        "asset": {"version": "2.0", "generator": "mfnormal tests"},
        "extensionsUsed": ["KHR_lights_punctual"],
        "scene": 0,
        "scenes": [{"nodes": [0]}],
        "nodes": [
            {"name": "root", "children": [1, 2, 3, 4]},
            {"name": "quad", "mesh": 0, "translation": [0, 0, 0], "rotation": [0, 0, 0, 1], "scale": [1, 1, 1]},
            {"name": "camera", "camera": 0, "translation": [0, 0, 3.2]},
            {"name": "sun", "rotation": [-0.3826834, 0, 0, 0.9238795],
             "extensions": {"KHR_lights_punctual": {"light": 0}}},
            {"name": "spot", "translation": [0, 0, 2],
             "extensions": {"KHR_lights_punctual": {"light": 1}}},
        ],
        "meshes": [{"name": "quad", "primitives": [
            {"attributes": {"POSITION": 0, "NORMAL": 1, "TEXCOORD_0": 2}, "indices": 3, "material": 0,
             "mode": 4}]}],
        "materials": [{"name": "bumpy",
                       "pbrMetallicRoughness": {"baseColorTexture": {"index": 1}, "baseColorFactor": [1, 1, 1, 1],
                                                "metallicFactor": 0.0, "roughnessFactor": 0.6},
                       "normalTexture": {"index": 0, "scale": 1.0}}],
        "textures": [{"source": 0, "sampler": 0}, {"source": 1, "sampler": 0}],
        "images": [{"uri": "nm.png"}, {"uri": "base.png"}],
        "samplers": [{"magFilter": 9729, "minFilter": 9987, "wrapS": 10497, "wrapT": 10497}],
        "accessors": accessors,
        "bufferViews": views,
        "buffers": [{"uri": "quad.bin", "byteLength": len(blob)}],
        "cameras": [{"type": "perspective", "perspective": {"yfov": 0.8, "znear": 0.05, "zfar": 100,
                                                             "aspectRatio": 1.5}}],
        "extensions": {"KHR_lights_punctual": {"lights": [
            {"type": "directional", "color": [1, 1, 1], "intensity": 3.0},
            {"type": "spot", "color": [1, 0.9, 0.8], "intensity": 8.0,
             "spot": {"innerConeAngle": 0.3, "outerConeAngle": 0.7}}]}},
    }
    blobs = {"quad.bin": blob, "nm.png": png_bytes(_normal_map()), "base.png": png_bytes(_base_colour())}
    return doc, blobs


def write_gltf(folder, doc, blobs, name="model.gltf") -> Path:
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    for file, data in blobs.items():
        (folder / file).write_bytes(data)
    path = folder / name
    path.write_text(json.dumps(doc))
    return path


def glb_bytes(doc, blobs) -> bytes:
    """The model as one GLB: quad.bin and the images in the binary chunk."""
    doc = copy.deepcopy(doc)
    binary = bytearray(blobs["quad.bin"])
    for img in doc["images"]:
        uri = img.pop("uri")
        data = blobs[uri]
        while len(binary) % 4:
            binary.append(0)
        doc["bufferViews"].append({"buffer": 0, "byteOffset": len(binary), "byteLength": len(data)})
        binary.extend(data)
        img["bufferView"] = len(doc["bufferViews"]) - 1
        img["mimeType"] = "image/png"
    while len(binary) % 4:
        binary.append(0)
    doc["buffers"] = [{"byteLength": len(binary)}]
    text = json.dumps(doc).encode()
    text += b" " * (-len(text) % 4)
    body = struct.pack("<II", len(text), 0x4E4F534A) + text + struct.pack("<II", len(binary), 0x004E4942) + binary
    return b"glTF" + struct.pack("<II", 2, 12 + len(body)) + body


def write_glb(folder, doc, blobs, name="model.glb") -> Path:
    folder = Path(folder)
    folder.mkdir(parents=True, exist_ok=True)
    path = folder / name
    path.write_bytes(glb_bytes(doc, blobs))
    return path
