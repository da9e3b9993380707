"""glTF 2.0 scenes (``.gltf``, ``.glb``) as Mitsuba scenes, normal maps decoded in the baker's frame.

:func:`load_gltf` reads a file with ``pygltflib`` and returns a Mitsuba scene
dict: one triangle mesh per primitive and node (in world space), its material as
a ``principled`` BSDF (base colour, metallic, roughness, with their textures and
factors) wrapped in ``normalmap_microfacet`` where the material has a
``normalTexture`` (its ``scale`` is the plugin's ``strength``), the file's first
camera or one that frames the model, and its ``KHR_lights_punctual`` lights or
a generated sky with a sun.

Tangent frames: normal maps are baked in MikkTSpace. Each normal-mapped mesh
carries the per-vertex tangent T (attribute ``vertex_tangent``) and the
handedness sign (``vertex_tangent_sign``, glTF's ``TANGENT.w``): the file's
``TANGENT`` where it has one, else MikkTSpace tangents computed here
(:mod:`mfnormal.normals.mikktspace`; vertices are split where they differ), and the
plugin decodes the map in T, B = sign·(N×T), N (its ``tangents`` parameter).

Texture conventions: base colour is sRGB, normals and metallic-roughness are
linear (roughness in G, metallic in B). glTF's UV origin is the image's top
left, which is also where Mitsuba's ``bitmap`` puts v = 0, so UVs pass through
unchanged; MikkTSpace tangents are computed for (u, 1 − v), whose +v is the
image's up, the normal map's +Y.

Hostile files: :func:`mfnormal.io.gltf_validate.read_model` reads and validates the
whole file first (the node graph, every index, buffer bounds, URIs confined to
the model's folder, sizes against :class:`mfnormal.io.inputs.Limits`); what it
refuses is a :class:`GLTFError`, one line naming the element. A degenerate
transform (a zero scale) skips that mesh, light or camera with a warning.

Not supported (ignored, with a warning): texture coordinate sets other than
``TEXCOORD_0``, ``KHR_texture_transform``, emission, occlusion, alpha
blending and masking, skins, morph targets, animation, compressed geometry
(Draco, meshopt: an error) and the ``KHR_materials_*`` extensions.
"""

from __future__ import annotations

import math
import warnings
from pathlib import Path

import numpy as np

from mfnormal.scenes import sky
from mfnormal.io.gltf_validate import GLTFError, decode_error, read_model
from mfnormal.io.messages import one_line
from mfnormal.normals.mikktspace import mikktspace, split_vertices
from mfnormal.io.inputs import DEFAULT_LIMITS, Limits

__all__ = ["load_gltf", "GLTF_SUFFIXES", "TANGENT_MODES", "MACRO_NORMALS", "GLTFError", "is_smooth_shaded",
           "mitsuba_mesh"]

GLTF_SUFFIXES = (".gltf", ".glb")
TANGENT_MODES = ("auto", "mikktspace", "mitsuba")
TANGENT_ATTR = "vertex_tangent"
#: ``load_gltf(macro_normal=...)``: ``shading`` (the interpolated normal is the macro surface, as
#: without the option) or ``geometric`` (every smooth-shaded mesh gets the true triangle as the
#: macro surface: ``normalmap_microfacet`` with ``macro_normal="geometric"``, map or not).
MACRO_NORMALS = ("shading", "geometric")
#: A mesh is smooth-shaded where some vertex normal is more than this many degrees off its
#: triangle's normal (glTF writers store flat shading as split vertices with face normals).
SMOOTH_MIN_DEG = 0.5

_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
              5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_WRAP = {33071: "clamp", 33648: "mirror", 10497: "repeat"}
_NEAREST = {9728, 9984, 9986}
_TRIANGLES, _STRIP, _FAN = 4, 5, 6


def _warn(msg):
    warnings.warn(f"glTF: {msg}", RuntimeWarning, stacklevel=3)


class _File:
    """A parsed glTF file: its JSON (pygltflib), buffers and decoded images, read through
    :func:`mfnormal.io.gltf_validate.read_model` (which validates everything first)."""

    def __init__(self, path: Path, limits: Limits = DEFAULT_LIMITS):
        import pygltflib

        self.path = path
        self.model = read_model(path, limits)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                self.gltf = pygltflib.GLTF2.gltf_from_json(self.model.text)
        except Exception as exc:  # noqa: BLE001  (pygltflib raises anything on a broken file)
            raise decode_error(self.model.doc, exc) from None
        self.buffers = self.model.buffers
        self._images = {}

    def accessor(self, index: int) -> np.ndarray:
        """Accessor ``index`` as an (count, width) array; normalized integers become floats."""
        acc = self.gltf.accessors[index]
        dtype = np.dtype(_COMPONENT[acc.componentType])
        width = _WIDTH[acc.type]
        if acc.bufferView is None:
            data = np.zeros((acc.count, width), dtype)
        else:
            view = self.gltf.bufferViews[acc.bufferView]
            data = self._view(acc.bufferView, acc.byteOffset or 0, dtype, width, acc.count,
                              view.byteStride)
        if acc.sparse is not None:
            s = acc.sparse
            idx = self._view(s.indices.bufferView, s.indices.byteOffset or 0,
                             np.dtype(_COMPONENT[s.indices.componentType]), 1, s.count)[:, 0]
            if idx.max() >= acc.count:
                raise GLTFError(f"accessors[{index}].sparse.indices: index {int(idx.max())} is out of "
                                f"range (the accessor has {acc.count} elements)")
            val = self._view(s.values.bufferView, s.values.byteOffset or 0, dtype, width, s.count)
            data = data.copy()
            data[idx.astype(np.int64)] = val
        if acc.normalized and dtype.kind in "iu":
            data = np.maximum(data / np.float32(np.iinfo(dtype).max), -1.0).astype(np.float32)
        return data

    def _view(self, view_index, offset, dtype, width, count, stride=None) -> np.ndarray:
        """``count`` elements of ``width`` × ``dtype`` from bufferView ``view_index`` at
        ``offset``, ``stride`` bytes apart (None: tightly packed). The validation made
        sure they lie inside the view; this checks it again before any strided read."""
        view = self.gltf.bufferViews[view_index]
        buf = self.buffers[view.buffer]
        elem = dtype.itemsize * width
        stride = stride or elem
        if count == 0:
            return np.zeros((0, width), dtype)
        start = (view.byteOffset or 0) + offset
        end = start + stride * (count - 1) + elem
        if not (stride >= elem > 0 and offset >= 0 and end - (view.byteOffset or 0) <= view.byteLength
                and end <= len(buf)):
            raise GLTFError(f"bufferViews[{view_index}]: a read of {count} x {elem} bytes at {offset} "
                            "is out of bounds")
        raw = np.frombuffer(buf, np.uint8, end - start, start)
        rows = np.lib.stride_tricks.as_strided(raw, (count, elem), (stride, 1), writeable=False)
        return np.ascontiguousarray(rows).view(dtype).reshape(count, width)

    def image(self, index: int) -> np.ndarray | None:
        """Image ``index`` as raw values in [0, 1], (h, w, channels) float32; None if undecodable."""
        if index in self._images:
            return self._images[index]
        import mitsuba as mi

        img = self.gltf.images[index]
        info = self.model.images[index]
        name = "a data: URI" if (img.uri or "").startswith("data:") else (img.uri or img.mimeType)
        arr = None
        if info.fmt is None:
            _warn(f"image {index} ({name}) is not a PNG or JPEG file; texture ignored")
        else:
            try:
                stream = mi.MemoryStream(len(info.data))
                stream.write(info.data)
                stream.seek(0)
                fmt = mi.Bitmap.FileFormat.PNG if info.fmt == "png" else mi.Bitmap.FileFormat.JPEG
                arr = np.array(mi.Bitmap(stream, fmt))
            except Exception as exc:  # noqa: BLE001  (an unreadable texture is skipped, not fatal)
                _warn(f"cannot decode image {index} ({name}): {one_line(exc)}; texture ignored")
                arr = None
        if arr is not None:
            if arr.ndim == 2:
                arr = arr[:, :, None]
            if arr.dtype.kind in "iu":
                arr = arr.astype(np.float32) / np.float32(np.iinfo(arr.dtype).max)
            arr = arr.astype(np.float32)
            if arr.shape[0] * arr.shape[1] != info.width * info.height:
                _warn(f"image {index} decoded to {arr.shape[1]}x{arr.shape[0]} pixels, not the "
                      f"{info.width}x{info.height} of its header; texture ignored")
                arr = None
        self._images[index] = arr
        return arr


# Scene graph

def _node_matrix(node) -> np.ndarray:
    if node.matrix is not None:
        return np.array(node.matrix, dtype=np.float64).reshape(4, 4).T    # column-major
    t = np.array(node.translation or [0, 0, 0], dtype=np.float64)
    q = np.array(node.rotation or [0, 0, 0, 1], dtype=np.float64)
    x, y, z, w = q / np.linalg.norm(q)          # validated non-zero; exporters round unit ones
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    s = np.array(node.scale or [1, 1, 1], dtype=np.float64)
    m = np.eye(4)
    m[:3, :3] = r * s[None, :]
    m[:3, 3] = t
    return m


def _walk_nodes(gltf, roots):
    """(index, node, world matrix) for every node of the default scene (``roots`` and their
    descendants: a tree, validated), parents first."""
    stack = [(i, np.eye(4)) for i in reversed(roots)]
    while stack:
        i, parent = stack.pop()
        node = gltf.nodes[i]
        with np.errstate(over="ignore", invalid="ignore"):
            world = parent @ _node_matrix(node)
        yield i, node, world
        stack.extend((c, world) for c in reversed(node.children or []))


# Materials

def _srgb_to_linear(c):
    return np.where(c <= 0.04045, c / 12.92, ((c + 0.055) / 1.055) ** 2.4).astype(np.float32)


def _channels(arr, n):
    """The first ``n`` colour channels (grey repeated), alpha dropped."""
    colour = arr[:, :, :1].repeat(3, axis=2) if arr.shape[2] in (1, 2) else arr[:, :, :3]
    return np.ascontiguousarray(colour[:, :, :n])


class _Materials:
    """glTF materials → Mitsuba BSDF dicts, textures decoded once."""

    def __init__(self, f: _File, model: str, tangents: str, normal_maps: bool, macro_normal: str = "shading"):
        self.f, self.model, self.tangents, self.normal_maps = f, model, tangents, normal_maps
        self.macro_normal = macro_normal
        self._warned = set()

    def _warn_once(self, key, msg):
        if key not in self._warned:
            self._warned.add(key)
            _warn(msg)

    def _texture(self, info, what):
        """(raw image array, sampler settings) of a textureInfo, or (None, None)."""
        if info is None:
            return None, None
        if (info.texCoord or 0) != 0:
            self._warn_once(("texcoord", what), f"{what} uses TEXCOORD_{info.texCoord}; "
                                                "only TEXCOORD_0 is supported, using it")
        if info.extensions and "KHR_texture_transform" in info.extensions:
            self._warn_once(("transform", what), f"KHR_texture_transform on {what} is ignored")
        tex = self.f.gltf.textures[info.index]
        if tex.source is None:
            self._warn_once(("source", info.index), f"texture {info.index} has no PNG/JPEG source "
                                                    "(a texture extension?); ignored")
            return None, None
        arr = self.f.image(tex.source)
        if arr is None:
            return None, None
        sampler = self.f.gltf.samplers[tex.sampler] if tex.sampler is not None else None
        settings = {"wrap_mode": _WRAP.get(getattr(sampler, "wrapS", None), "repeat"),
                    "filter_type": "nearest" if getattr(sampler, "magFilter", None) in _NEAREST
                    else "bilinear"}
        return arr, settings

    @staticmethod
    def _bitmap(data, settings):
        import mitsuba as mi

        return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(data, dtype=np.float32)),
                "raw": True, **settings}

    def normal_texture(self, mat):
        """(bitmap dict, strength) of the material's normal map, or (None, None)."""
        if mat is None or mat.normalTexture is None or not self.normal_maps:
            return None, None
        arr, settings = self._texture(mat.normalTexture, "normalTexture")
        if arr is None:
            return None, None
        if arr.shape[2] < 3:
            self._warn_once(("nchan", id(mat)), "a normalTexture with fewer than 3 channels is ignored")
            return None, None
        scale = 1.0 if mat.normalTexture.scale is None else float(mat.normalTexture.scale)
        rgb = arr[:, :, :3]
        if scale < 0:
            # A negative scale flips the map's x and y: 2(1 − c) − 1 = −(2c − 1).
            rgb = rgb.copy()
            rgb[:, :, :2] = 1.0 - rgb[:, :, :2]
            scale = -scale
        return self._bitmap(rgb, settings), scale

    def principled(self, mat) -> dict:
        pbr = mat.pbrMetallicRoughness if mat is not None else None
        base = list((pbr.baseColorFactor if pbr and pbr.baseColorFactor else [1, 1, 1, 1])[:3])
        metallic = 1.0 if pbr is None or pbr.metallicFactor is None else float(pbr.metallicFactor)
        roughness = 1.0 if pbr is None or pbr.roughnessFactor is None else float(pbr.roughnessFactor)
        bsdf = {"type": "principled", "base_color": {"type": "rgb", "value": base},
                "metallic": metallic, "roughness": roughness}
        if pbr is not None:
            arr, settings = self._texture(pbr.baseColorTexture, "baseColorTexture")
            if arr is not None:
                colour = _srgb_to_linear(_channels(arr, 3)) * np.float32(base)
                bsdf["base_color"] = self._bitmap(colour, settings)
            arr, settings = self._texture(pbr.metallicRoughnessTexture, "metallicRoughnessTexture")
            if arr is not None:
                if arr.shape[2] < 3:
                    arr = _channels(arr, 3)
                bsdf["roughness"] = self._bitmap(arr[:, :, 1:2] * np.float32(roughness), settings)
                bsdf["metallic"] = self._bitmap(arr[:, :, 2:3] * np.float32(metallic), settings)
        if mat is not None:
            if mat.emissiveTexture is not None or any(mat.emissiveFactor or []):
                self._warn_once("emissive", "emission is ignored")
            if mat.alphaMode not in (None, "OPAQUE"):
                self._warn_once("alpha", f"alphaMode {mat.alphaMode} is rendered opaque")
            if mat.extensions:
                for ext in mat.extensions:
                    self._warn_once(ext, f"material extension {ext} is ignored")
        return bsdf

    def bsdf(self, index, has_uv: bool, has_tangents: bool, smooth: bool = False):
        """The Mitsuba BSDF dict of material ``index`` (None: the default material) on a mesh
        (``smooth``: smooth-shaded, which ``macro_normal="geometric"`` wraps even without a map)."""
        mat = self.f.gltf.materials[index] if index is not None else None
        bsdf = self.principled(mat)
        normalmap, strength = self.normal_texture(mat) if has_uv else (None, None)
        geometric = smooth and self.macro_normal == "geometric"
        if normalmap is not None:
            bsdf = {"type": "normalmap_microfacet", "normalmap": normalmap, "bsdf": bsdf,
                    "strength": strength, "model": self.model,
                    "tangents": TANGENT_ATTR if has_tangents else "mitsuba"}
            if geometric:
                bsdf["macro_normal"] = "geometric"
        elif geometric:
            bsdf = {"type": "normalmap_microfacet", "macro_normal": "geometric", "bsdf": bsdf, "model": self.model}
        if mat is not None and mat.doubleSided:
            bsdf = {"type": "twosided", "bsdf": bsdf}
        return bsdf

    def wants_tangents(self, index) -> bool:
        mat = self.f.gltf.materials[index] if index is not None else None
        return (self.tangents != "mitsuba" and self.normal_maps and mat is not None
                and mat.normalTexture is not None)


# Meshes

def _triangles(indices, mode):
    if mode != _TRIANGLES and len(indices) < 3:
        return np.zeros((0, 3), np.int64)
    if mode == _TRIANGLES:
        return indices[: len(indices) // 3 * 3].reshape(-1, 3)
    k = np.arange(max(len(indices) - 2, 0))
    if mode == _STRIP:
        even = (k % 2) == 0
        tri = np.stack([indices[k], np.where(even, indices[k + 1], indices[k + 2]),
                        np.where(even, indices[k + 2], indices[k + 1])], axis=-1)
        return tri
    return np.stack([np.full_like(k, indices[0]), indices[k + 1], indices[k + 2]], axis=-1)


def _finite_attribute(f: _File, index: int, where: str, name: str) -> np.ndarray:
    """A float attribute's values, which must be finite."""
    data = f.accessor(index).astype(np.float32)
    if not np.all(np.isfinite(data)):
        bad = int(np.argmax(~np.isfinite(data).all(axis=1)))
        raise GLTFError(f"{where}.attributes.{name}: accessors[{index}] element {bad} is not finite")
    return data


def _primitive_arrays(f: _File, prim, want_tangents: bool, tangents_mode: str, where: str = "a primitive"):
    """Object-space (positions, normals, uvs | None, tangents4 | None, faces) of a primitive."""
    attrs = prim.attributes
    positions = _finite_attribute(f, attrs.POSITION, where, "POSITION")
    count = len(positions)
    indices = (f.accessor(prim.indices)[:, 0].astype(np.int64) if prim.indices is not None
               else np.arange(count))
    faces = _triangles(indices, prim.mode if prim.mode is not None else _TRIANGLES)
    if len(faces) and faces.max() >= count:
        raise GLTFError(f"{where}.indices: index {int(faces.max())} is out of range "
                        f"(POSITION has {count} vertices)")
    uvs = (_finite_attribute(f, attrs.TEXCOORD_0, where, "TEXCOORD_0")[:, :2]
           if attrs.TEXCOORD_0 is not None else None)
    tangents = (_finite_attribute(f, attrs.TANGENT, where, "TANGENT")
                if attrs.TANGENT is not None and tangents_mode == "auto" else None)
    if attrs.NORMAL is not None:
        normals = _finite_attribute(f, attrs.NORMAL, where, "NORMAL")
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = np.where(length > 0, normals / np.where(length > 0, length, 1), normals)
    else:
        # glTF: without normals, flat shading: one normal per triangle, vertices split.
        p = positions[faces]
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
        positions = p.reshape(-1, 3)
        normals = np.repeat(n, 3, axis=0).astype(np.float32)
        uvs = uvs[faces].reshape(-1, 2) if uvs is not None else None
        tangents = tangents[faces].reshape(-1, 4) if tangents is not None else None
        faces = np.arange(len(positions)).reshape(-1, 3)
    if want_tangents and uvs is not None and tangents is None:
        # MikkTSpace per corner; split the vertices where corners differ.
        corner_t = mikktspace(positions, normals, uvs, faces, flip_v=True)
        faces, v = split_vertices(p=positions[faces], n=normals[faces], uv=uvs[faces], t=corner_t)
        positions, normals, uvs, tangents = v["p"], v["n"], v["uv"], v["t"]
    if not want_tangents:
        tangents = None
    return positions, normals, uvs, tangents, faces.astype(np.uint32)


def is_smooth_shaded(positions, normals, faces, min_deg: float = SMOOTH_MIN_DEG) -> bool:
    """Whether some vertex normal of the mesh is more than ``min_deg`` off its triangle's normal
    (degenerate triangles are left out)."""
    p = np.asarray(positions, np.float64)[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    length = np.linalg.norm(n, axis=1)
    ok = length > 1e-12 * np.maximum(np.abs(p).max(axis=(1, 2)) ** 2, 1e-30)
    if not ok.any():
        return False
    n = n[ok] / length[ok, None]
    vn = np.asarray(normals, np.float64)[faces[ok]]
    cos = np.einsum("fd,fkd->fk", n, vn) / np.maximum(np.linalg.norm(vn, axis=2), 1e-30)
    return bool(np.any(np.abs(cos) < np.cos(np.radians(min_deg))))


def mitsuba_mesh(name, bsdf, positions, normals, uvs, tangents, faces):
    """A Mitsuba mesh of these vertex arrays with ``bsdf`` (loaded); ``uvs`` and ``tangents``
    (V, 4: T and its sign, as attributes ``vertex_tangent`` and ``vertex_tangent_sign``) may be None."""
    import mitsuba as mi

    props = mi.Properties()
    props["bsdf"] = bsdf
    mesh = mi.Mesh(name, len(positions), len(faces), props, has_vertex_normals=True,
                   has_vertex_texcoords=uvs is not None)
    params = mi.traverse(mesh)
    # The buffers' own types: mi.Float in JIT variants, Dr.Jit's scalar arrays otherwise.
    floats, ints = type(params["vertex_positions"]), type(params["faces"])
    params["vertex_positions"] = floats(positions.astype(np.float32).ravel())
    params["vertex_normals"] = floats(normals.astype(np.float32).ravel())
    if uvs is not None:
        params["vertex_texcoords"] = floats(uvs.astype(np.float32).ravel())
    params["faces"] = ints(faces.astype(np.uint32).ravel())
    params.update()
    if tangents is not None:
        mesh.add_attribute(TANGENT_ATTR, 3, np.ascontiguousarray(tangents[:, :3], np.float32).ravel())
        mesh.add_attribute(TANGENT_ATTR + "_sign", 1,
                           np.where(tangents[:, 3] < 0, -1.0, 1.0).astype(np.float32))
    return mesh


def _cofactor(lin):
    """The cofactor matrix det(L)·L^−T (columns: the cross products of L's columns), which
    maps normals like the inverse transpose and exists for singular L too."""
    a, b, c = lin[:, 0], lin[:, 1], lin[:, 2]
    return np.stack([np.cross(b, c), np.cross(c, a), np.cross(a, b)], axis=1)


def _to_world(m, positions, normals, tangents, faces, where="a node"):
    """World-space arrays under the node matrix ``m`` (winding flipped for mirroring matrices),
    or None where ``m`` flattens the mesh to a line or a point (a zero scale)."""
    lin = m[:3, :3]
    if not np.all(np.isfinite(m)):
        raise GLTFError(f"{where}: its world transform is not finite (its matrix or scale, times "
                        "its parents', overflows)")
    with np.errstate(over="ignore", invalid="ignore"):
        world = positions @ lin.T + m[:3, 3]
        det = np.linalg.det(lin)
        cof = _cofactor(lin) * (np.sign(det) if det != 0 else 1.0)
    if not (np.all(np.isfinite(world)) and np.all(np.abs(world) <= np.finfo(np.float32).max)):
        raise GLTFError(f"{where}: its world transform takes the vertices past the float range")
    if not np.any(np.abs(cof) > 1e-300):
        _warn(f"{where}: its transform has a zero scale, so its mesh has no area; not rendered")
        return None
    positions = world
    if not (np.isfinite(det) and np.all(np.isfinite(cof))):
        cof = _cofactor(lin / np.max(np.abs(lin)))    # normals need only its direction
        det = np.linalg.det(lin / np.max(np.abs(lin)))
    normals = normals @ cof.T                     # ∝ the inverse transpose, applied to rows
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = normals / np.maximum(length, 1e-300)
    if det == 0:
        # A flat scale (rank 2) maps normals in the plane to 0: they get the plane's normal.
        plane = cof[:, np.argmax(np.linalg.norm(cof, axis=0))]
        normals = np.where(length > 0, normals, plane / np.linalg.norm(plane))
    if tangents is not None:
        t = tangents[:, :3] @ lin.T
        t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-30)
        tangents = np.concatenate([t, tangents[:, 3:4] * np.sign(det)], axis=1)
    if det < 0:
        faces = faces[:, [0, 2, 1]]
    return positions, normals, tangents, faces


# Camera and lights

def _look_at(origin, target, up):
    import mitsuba as mi

    return mi.ScalarTransform4f().look_at(origin=[float(x) for x in origin],
                                          target=[float(x) for x in target], up=[float(x) for x in up])


def _axis(world, v):
    """The unit world-space direction of the node-space vector ``v``, or None if degenerate."""
    d = world[:3, :3] @ np.asarray(v, dtype=np.float64)
    n = float(np.linalg.norm(d))
    return d / n if np.isfinite(n) and n > 1e-12 * max(1.0, float(np.abs(world[:3, :3]).max())) else None


def _gltf_camera(cam, world):
    """A Mitsuba sensor (without sampler and film) from a glTF camera at ``world``, or None
    where the node's transform is degenerate (a zero scale, an overflow)."""
    import mitsuba as mi

    # glTF cameras look down −Z with +X right; Mitsuba's look down +Z with +X left.
    flip = np.diag([-1.0, 1.0, -1.0, 1.0])
    if not np.all(np.isfinite(world)) or any(_axis(world, e) is None for e in np.eye(3)):
        return None
    rot = world.copy()
    rot[:3, :3] /= np.linalg.norm(rot[:3, :3], axis=0, keepdims=True)   # drop scale
    if abs(np.linalg.det(rot[:3, :3])) < 1e-6:
        return None
    to_world = mi.ScalarTransform4f((rot @ flip).tolist())
    if cam.type == "orthographic":
        o = cam.orthographic
        return {"type": "orthographic",
                "to_world": to_world @ mi.ScalarTransform4f().scale([o.xmag, o.ymag, 1.0])}
    p = cam.perspective
    near = float(p.znear)
    return {"type": "perspective", "fov_axis": "y",
            "fov": min(max(math.degrees(p.yfov), 1e-4), 179.9),    # validated in (0°, 180°)
            "near_clip": near, "far_clip": max(1e4, 1e3 * near), "to_world": to_world}


def _framing_camera(lo, hi, aspect, fov=35.0, elevation=20.0, azimuth=20.0, margin=1.1):
    """A perspective sensor that frames the box [lo, hi] from the front (+Z), a little above:
    the box's corners fill the smaller image side (with ``margin``)."""
    center = 0.5 * (lo + hi)
    radius = max(0.5 * float(np.linalg.norm(hi - lo)), 1e-6)
    el, az = math.radians(elevation), math.radians(azimuth)
    back = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    right = np.cross([0.0, 1.0, 0.0], back)
    right /= np.linalg.norm(right)
    up = np.cross(back, right)
    corners = np.array([[x, y, z] for x in (lo[0], hi[0]) for y in (lo[1], hi[1])
                        for z in (lo[2], hi[2])]) - center
    tan_half_y = math.tan(math.radians(0.5 * fov)) / min(1.0, aspect)   # fov spans the smaller side
    tan_y = tan_half_y / margin
    tan_x = tan_y * aspect
    # Distance along ``back`` at which every corner projects inside the image.
    depth = corners @ back
    distance = float(np.max(np.maximum(np.abs(corners @ right) / tan_x,
                                       np.abs(corners @ up) / tan_y) + depth))
    distance = max(distance, 1e-3 * radius)
    return {"type": "perspective", "fov_axis": "y", "fov": 2 * math.degrees(math.atan(tan_half_y)),
            "near_clip": max(distance - 2 * radius, distance * 1e-3),
            "far_clip": distance + 4 * radius,
            "to_world": _look_at(center + distance * back, center, [0, 1, 0])}


def _punctual_lights(gltf, nodes):
    """Mitsuba emitters for the KHR_lights_punctual lights of the scene's nodes (validated:
    known types, indices in range, colours and intensities >= 0, cone angles in order)."""
    ext = (gltf.extensions or {}).get("KHR_lights_punctual", {})
    lights = ext.get("lights", [])
    emitters = {}
    for i, node, world in nodes:
        ref = (node.extensions or {}).get("KHR_lights_punctual")
        if ref is None:
            continue
        light = lights[ref["light"]]
        colour = np.array(light.get("color", [1, 1, 1]), dtype=np.float64) * light.get("intensity", 1.0)
        rgb = {"type": "rgb", "value": colour.tolist()}
        position = world[:3, 3]
        direction, up = _axis(world, [0.0, 0.0, -1.0]), _axis(world, [0.0, 1.0, 0.0])
        kind = light.get("type")
        if not np.all(np.isfinite(position)) or (kind != "point" and (direction is None or up is None)):
            _warn(f"nodes[{i}]: the transform of its light is degenerate (a zero scale or an "
                  "overflow); the light is skipped")
            continue
        name = f"light_{len(emitters)}"
        if kind == "directional":
            emitters[name] = {"type": "directional", "direction": direction.tolist(), "irradiance": rgb}
        elif kind == "point":
            emitters[name] = {"type": "point", "position": position.tolist(), "intensity": rgb}
        elif kind == "spot":
            spot = light.get("spot", {})
            emitters[name] = {"type": "spot", "intensity": rgb,
                              "cutoff_angle": math.degrees(spot.get("outerConeAngle", math.pi / 4)),
                              "beam_width": math.degrees(spot.get("innerConeAngle", 0.0)),
                              "to_world": _look_at(position, position + direction, up)}
    return emitters


# The scene

def _meshes(f: _File, materials: _Materials, nodes, tangents: str, macro_normal: str):
    """({shape id: Mitsuba mesh}, lo, hi): every triangle primitive of the scene's nodes in
    world space, and their bounding box; one BSDF per (material, uv, tangents, smooth-shaded under
    ``macro_normal="geometric"``) shared by its meshes."""
    import mitsuba as mi

    gltf, shapes, bsdfs = f.gltf, {}, {}
    lo, hi = np.full(3, np.inf), np.full(3, -np.inf)
    for i, node, world in nodes:
        if node.skin is not None:
            materials._warn_once("skin", "skins are ignored (meshes are rendered in bind pose)")
        if node.mesh is None:
            continue
        mesh = gltf.meshes[node.mesh]
        for k, prim in enumerate(mesh.primitives):
            if prim.mode not in (None, _TRIANGLES, _STRIP, _FAN):
                materials._warn_once(("mode", prim.mode), f"primitive mode {prim.mode} (points/lines) "
                                                          "is skipped")
                continue
            if prim.attributes.POSITION is None:
                continue
            if prim.targets:
                materials._warn_once("morph", "morph targets are ignored")
            want = materials.wants_tangents(prim.material)
            where = f"meshes[{node.mesh}].primitives[{k}]"
            positions, normals, uvs, tan, faces = _primitive_arrays(f, prim, want, tangents, where)
            if len(faces) == 0:
                continue
            placed = _to_world(world, positions, normals, tan, faces, f"nodes[{i}]")
            if placed is None:
                continue
            positions, normals, tan, faces = placed
            smooth = macro_normal == "geometric" and is_smooth_shaded(positions, normals, faces)
            key = (prim.material, uvs is not None, tan is not None, smooth)
            if key not in bsdfs:
                bsdfs[key] = mi.load_dict(materials.bsdf(prim.material, uvs is not None, tan is not None, smooth))
            name = f"{mesh.name or f'mesh{node.mesh}'}/{k}"
            shapes[f"mesh_{len(shapes)}"] = mitsuba_mesh(name, bsdfs[key], positions, normals, uvs,
                                                          tan, faces)
            lo = np.minimum(lo, positions.min(axis=0))
            hi = np.maximum(hi, positions.max(axis=0))
    if not np.all(np.isfinite(lo)):
        raise GLTFError("the default scene has no triangle meshes")
    with np.errstate(over="ignore", invalid="ignore"):
        if not np.all(np.isfinite(hi - lo)) or not np.isfinite(np.linalg.norm(hi - lo)):
            raise GLTFError("the model's extent overflows the float range")
    return shapes, lo, hi


def _sensor(gltf, nodes, lo, hi, width: int, height: int, spp: int, limits: Limits) -> dict:
    """The file's first camera (its aspect ratio sets the width), else one that frames the
    box [lo, hi]; with sampler and film."""
    sensor = None
    for i, node, world in nodes:
        if node.camera is not None:
            cam = gltf.cameras[node.camera]
            sensor = _gltf_camera(cam, world)
            if sensor is None:
                _warn(f"nodes[{i}]: the transform of its camera is degenerate (a zero scale or an "
                      "overflow); using a camera that frames the model")
                break
            aspect = cam.perspective.aspectRatio if cam.type == "perspective" else None
            if aspect:
                width = max(1, int(round(height * aspect)))
                _check_render_size(width, height, limits, f"cameras[{node.camera}].perspective.aspectRatio "
                                                          f"{aspect:g} at height {height}")
            break
    if sensor is None:
        sensor = _framing_camera(lo, hi, width / height)
    sensor["sampler"] = {"type": "independent", "sample_count": int(spp)}
    sensor["film"] = {"type": "hdrfilm", "width": int(width), "height": int(height),
                      "pixel_format": "rgb", "rfilter": {"type": "gaussian"}}
    return sensor


def _emitters(gltf, nodes, lights: bool) -> dict:
    """The file's punctual lights (unless ``lights`` is False), else a generated sky with a sun."""
    import mitsuba as mi

    emitters = _punctual_lights(gltf, nodes) if lights else {}
    if not emitters:
        sun = sky.DiskSun(elevation_deg=40.0, azimuth_deg=-35.0, irradiance=3.0, radius_deg=3.0)
        bitmap = mi.Bitmap(sky.envmap(256, gradient=sky.GLTF, sun=sun))
        emitters = {"sky": {"type": "envmap", "bitmap": bitmap}}
    return emitters


def load_gltf(path, *, width: int = 640, height: int = 480, spp: int = 64, max_depth: int = 8,
              model: str = "faithful", tangents: str = "auto", normal_maps: bool = True,
              lights: bool = True, macro_normal: str = "shading", limits: Limits = DEFAULT_LIMITS) -> dict:
    """A Mitsuba scene dict of the glTF 2.0 file ``path`` (``.gltf`` or ``.glb``).

    Needs an active Mitsuba variant (the meshes are built in it). Options:
    ``width``, ``height``, ``spp``, ``max_depth`` (path tracer); ``model``: the
    ``normalmap_microfacet`` model; ``tangents``: ``auto`` (the file's
    ``TANGENT``, else MikkTSpace), ``mikktspace`` (always computed) or
    ``mitsuba`` (Mitsuba's per-triangle frame, for comparison);
    ``normal_maps=False`` drops the normal maps; ``lights=False`` ignores the
    file's lights for the generated sky; ``macro_normal``: ``shading`` (default) or
    ``geometric``: every smooth-shaded mesh (:func:`is_smooth_shaded`) gets the true triangle
    as its microsurface's macro normal, its interpolated normal (and normal map, if any) as the
    facet: ``normalmap_microfacet`` with ``macro_normal="geometric"``, wrapping also the
    materials without a normal map (the shadow-terminator fix; flat-shaded meshes are left
    as they are); ``limits``: the caps on what the file
    may make the loader allocate (:class:`mfnormal.io.inputs.Limits`).

    The file is validated first (:mod:`mfnormal.io.gltf_validate`); anything the
    loader cannot use safely raises :class:`GLTFError`, one line naming the
    element. Files are read only from the model's own folder.
    """
    import mfnormal

    if tangents not in TANGENT_MODES:
        raise ValueError(f"tangents must be one of {', '.join(TANGENT_MODES)}, got '{tangents}'")
    if macro_normal not in MACRO_NORMALS:
        raise ValueError(f"macro_normal must be one of {', '.join(MACRO_NORMALS)}, got '{macro_normal}'")
    for name, value, lo in (("width", width, 1), ("height", height, 1), ("spp", spp, 1),
                            ("max_depth", max_depth, -1)):
        if isinstance(value, bool) or not isinstance(value, int) or not lo <= value < 1 << 31:
            raise GLTFError(f"{name} must be an integer from {lo} to {(1 << 31) - 1}, got {value!r}")
    _check_render_size(width, height, limits, "the film (width, height)")
    mfnormal.register()
    path = Path(path)
    if not path.is_file():
        raise FileNotFoundError(f"glTF file not found: {path}")
    f = _File(path, limits)
    nodes = list(_walk_nodes(f.gltf, f.model.scene_roots))
    shapes, lo, hi = _meshes(f, _Materials(f, model, tangents, normal_maps, macro_normal), nodes, tangents,
                             macro_normal)
    return {"type": "scene", "integrator": {"type": "path", "max_depth": int(max_depth)}, **shapes,
            "sensor": _sensor(f.gltf, nodes, lo, hi, width, height, spp, limits),
            **_emitters(f.gltf, nodes, lights)}


def _check_render_size(width, height, limits, source):
    if width * height > limits.render_pixels:
        raise GLTFError(f"{source}: a {width}x{height} image has {width * height} pixels, more than a "
                        f"render may have ({limits.hint('render_pixels')})")
