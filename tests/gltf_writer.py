"""Write small glTF 2.0 binaries (.glb) with pygltflib, for the tests of ``mfnormal.io.gltf``."""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pygltflib as g

from mfnormal.io.images import png_bytes  # noqa: F401  (re-exported for the tests)


@dataclass
class Primitive:
    positions: np.ndarray               # (V, 3)
    normals: np.ndarray | None          # (V, 3)
    uvs: np.ndarray | None              # (V, 2), glTF convention (v = 0 at the image's top)
    indices: np.ndarray                 # (F, 3)
    tangents: np.ndarray | None = None  # (V, 4)
    material: int | None = None


@dataclass
class Material:
    base_color: tuple = (0.5, 0.5, 0.5, 1.0)
    metallic: float = 0.0
    roughness: float = 1.0
    normal_png: bytes | None = None
    normal_scale: float = 1.0
    base_color_png: bytes | None = None
    metallic_roughness_png: bytes | None = None


def write_glb(path, primitives: list[Primitive], materials: list[Material],
              matrix: np.ndarray | None = None) -> Path:
    """One node (optionally transformed by the 4×4 ``matrix``) with one mesh of ``primitives``."""
    blob = bytearray()
    gltf = g.GLTF2(asset=g.Asset(version="2.0"), scene=0)

    def add_view(data: bytes, target=None) -> int:
        while len(blob) % 4:
            blob.append(0)
        gltf.bufferViews.append(g.BufferView(buffer=0, byteOffset=len(blob), byteLength=len(data),
                                             target=target))
        blob.extend(data)
        return len(gltf.bufferViews) - 1

    def add_accessor(arr, kind, component=g.FLOAT, target=g.ARRAY_BUFFER) -> int:
        arr = np.ascontiguousarray(arr)
        view = add_view(arr.tobytes(), target)
        acc = g.Accessor(bufferView=view, componentType=component, count=len(arr), type=kind)
        if kind == "VEC3" and component == g.FLOAT:
            acc.min, acc.max = arr.min(axis=0).tolist(), arr.max(axis=0).tolist()
        gltf.accessors.append(acc)
        return len(gltf.accessors) - 1

    def add_texture(png: bytes) -> int:
        view = add_view(png)
        gltf.images.append(g.Image(bufferView=view, mimeType="image/png"))
        gltf.textures.append(g.Texture(source=len(gltf.images) - 1, sampler=0))
        return len(gltf.textures) - 1

    gltf.samplers.append(g.Sampler(magFilter=g.LINEAR, minFilter=g.LINEAR_MIPMAP_LINEAR,
                                   wrapS=g.REPEAT, wrapT=g.REPEAT))
    for m in materials:
        pbr = g.PbrMetallicRoughness(baseColorFactor=list(m.base_color), metallicFactor=m.metallic,
                                     roughnessFactor=m.roughness)
        if m.base_color_png is not None:
            pbr.baseColorTexture = g.TextureInfo(index=add_texture(m.base_color_png))
        if m.metallic_roughness_png is not None:
            pbr.metallicRoughnessTexture = g.TextureInfo(index=add_texture(m.metallic_roughness_png))
        mat = g.Material(pbrMetallicRoughness=pbr, doubleSided=False)
        if m.normal_png is not None:
            mat.normalTexture = g.NormalMaterialTexture(index=add_texture(m.normal_png),
                                                        scale=m.normal_scale)
        gltf.materials.append(mat)

    prims = []
    for p in primitives:
        attrs = g.Attributes(POSITION=add_accessor(p.positions.astype(np.float32), "VEC3"))
        if p.normals is not None:
            attrs.NORMAL = add_accessor(p.normals.astype(np.float32), "VEC3")
        if p.uvs is not None:
            attrs.TEXCOORD_0 = add_accessor(p.uvs.astype(np.float32), "VEC2")
        if p.tangents is not None:
            attrs.TANGENT = add_accessor(p.tangents.astype(np.float32), "VEC4")
        idx = add_accessor(p.indices.astype(np.uint32).ravel()[:, None], "SCALAR",
                           g.UNSIGNED_INT, g.ELEMENT_ARRAY_BUFFER)
        prims.append(g.Primitive(attributes=attrs, indices=idx, material=p.material))
    gltf.meshes.append(g.Mesh(primitives=prims, name="mesh"))
    node = g.Node(mesh=0)
    if matrix is not None:
        node.matrix = np.asarray(matrix, dtype=np.float64).T.ravel().tolist()   # column-major
    gltf.nodes.append(node)
    gltf.scenes.append(g.Scene(nodes=[0]))
    gltf.buffers.append(g.Buffer(byteLength=len(blob)))
    gltf.set_binary_blob(bytes(blob))
    path = Path(path)
    gltf.save_binary(str(path))
    return path

