"""Reading and validating a glTF 2.0 file before the loader allocates anything from it.

:func:`read_model` is the only way :mod:`mfnormal.io.gltf` reads a file. It parses
the ``.gltf`` JSON or the ``.glb`` container itself, checks the whole document
against what the loader will do with it, and reads the buffers and images —
each at most what the file declares and what :class:`~mfnormal.io.inputs.Limits`
allows. The loader may then index anything without further checks. Every
violation is a :class:`GLTFError` whose message is one line naming the element,
``nodes[3].children: cycle through node 0``.

What is checked:

- the container: GLB magic, version 2, chunk lengths within the file, JSON
  first; JSON that parses (no NaN/Infinity), an object, ``asset.version`` 2.x;
- types: every property the loader reads has its JSON type and range
  (integers are integers, numbers are finite, enumerations are known values);
- indices: every reference (``bufferView``, ``buffer``, ``mesh``, ``camera``,
  ``material``, ``texture``, ``source``, ``sampler``, ``children``, scene
  ``nodes``, ``KHR_lights_punctual`` ``light``, ``skin``, attributes) is in range;
- the node graph: no cycle, no node with two parents, scene roots are roots;
- data bounds: a bufferView lies inside its buffer; ``byteStride`` is 4–252, a
  multiple of 4 and at least the accessor's element size; an accessor's
  ``byteOffset + stride·(count − 1) + element`` lies inside its bufferView;
  sparse indices and values lie inside theirs (and the index values inside the
  accessor, checked when read); an accessor without a bufferView (zeros) counts
  against the byte budget; mesh attributes have the types the loader reads and
  the same count as ``POSITION``;
- URIs: ``data:`` (base64) or a relative path that resolves (symbolic links
  followed) inside the model's folder, to a regular file, of at least the
  declared ``byteLength`` (and only that much is read); nothing else is opened;
- sizes: the file, buffers and image files together at most ``data_bytes``;
  each image's width × height (from its PNG/JPEG header, before decoding) at
  most ``image_pixels``, all of them at most ``texture_pixels``; the vertices
  of the default scene after instancing at most ``vertices``;
- cameras (``yfov`` in (0, π), ``znear`` > 0, ``zfar`` > ``znear``,
  ``aspectRatio`` > 0, ``xmag``/``ymag`` non-zero), lights (known type, colour
  and intensity ≥ 0, ``range`` > 0, 0 ≤ inner < outer ≤ π/2 cone angles),
  material factors in [0, 1], node matrices, translations, rotations (non-zero
  quaternions; normalised) and scales finite.
"""

from __future__ import annotations

import base64
import binascii
import json
import math
import os
import re
import struct
from dataclasses import dataclass, field
from pathlib import Path, PureWindowsPath
from urllib.parse import unquote

from mfnormal.io.image_headers import image_header
from mfnormal.io.inputs import DEFAULT_LIMITS, Limits, not_regular

__all__ = ["GLTFError", "Model", "ImageData", "read_model", "image_header", "COMPONENT_SIZE",
           "TYPE_WIDTH"]

COMPONENT_SIZE = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
TYPE_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_FLOAT, _UBYTE, _USHORT, _UINT = 5126, 5121, 5123, 5125
_MODES = range(7)
_WRAPS = {33071, 33648, 10497}
_MAG = {9728, 9729}
_MIN = {9728, 9729, 9984, 9985, 9986, 9987}
_LIGHT_TYPES = ("directional", "point", "spot")
_ALPHA_MODES = ("OPAQUE", "MASK", "BLEND")
_TOP_ARRAYS = ("accessors", "animations", "buffers", "bufferViews", "cameras", "images", "materials",
               "meshes", "nodes", "samplers", "scenes", "skins", "textures")
# Attributes the loader reads: allowed (componentType, normalized) and types.
_ATTRIBUTE_TYPES = {
    "POSITION": ({"VEC3"}, {(_FLOAT, False)}),
    "NORMAL": ({"VEC3"}, {(_FLOAT, False)}),
    "TANGENT": ({"VEC4"}, {(_FLOAT, False)}),
    "TEXCOORD_0": ({"VEC2"}, {(_FLOAT, False), (_UBYTE, True), (_USHORT, True)}),
}
_GLB_MAGIC, _GLB_JSON, _GLB_BIN = b"glTF", 0x4E4F534A, 0x004E4942


class GLTFError(ValueError):
    """A glTF file the loader refuses: one line naming the element and the problem."""


def _fail(where: str, problem: str):
    raise GLTFError(f"{where}: {problem}" if where else problem)


def _at(where: str, key: str) -> str:
    return f"{where}.{key}" if where else key


@dataclass
class ImageData:
    """An image's encoded bytes and header: ``fmt`` is 'png', 'jpeg' or None (not decodable)."""
    data: bytes
    fmt: str | None
    width: int = 0
    height: int = 0


@dataclass
class Model:
    """A validated glTF file: its JSON text and document, buffers (each exactly its
    ``byteLength``), images and the index of every node's parent (None for roots)."""
    path: Path
    text: str
    doc: dict
    buffers: list = field(default_factory=list)
    images: list = field(default_factory=list)
    parents: list = field(default_factory=list)
    scene_roots: list = field(default_factory=list)


# -- Reading files ---------------------------------------------------------------------------------

class _Budget:
    def __init__(self, limits: Limits):
        self.limits = limits
        self.left = limits.data_bytes

    def take(self, n: int, where: str, what: str):
        if n > self.left:
            _fail(where, f"{what} ({n} bytes) would take the data read for this model past "
                         f"{self.limits.data_bytes} bytes ({self.limits.hint('data_bytes')})")
        self.left -= n


def _read_regular(path: Path, where: str, shown: str, budget: _Budget, length: int | None = None) -> bytes:
    """The bytes of the regular file ``path``: the first ``length`` (at least that many must
    exist), or all of it. The file is opened without blocking and checked with fstat,
    so a FIFO, device or folder is refused without being read."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        _fail(where, f"cannot open '{shown}' ({exc.strerror or type(exc).__name__})")
    try:
        st = os.fstat(fd)
        kind = not_regular(st.st_mode)
        if kind:
            _fail(where, f"'{shown}' is {kind}, not a regular file")
        if length is None:
            length = st.st_size
        elif st.st_size < length:
            _fail(where, f"'{shown}' has {st.st_size} bytes, less than the byteLength {length}")
        budget.take(length, where, f"'{shown}'")
        chunks, left = [], length
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 24))
            if not chunk:
                _fail(where, f"'{shown}' ended after {length - left} of {length} bytes")
            chunks.append(chunk)
            left -= len(chunk)
        return b"".join(chunks)
    finally:
        os.close(fd)


def _short(text: str, n: int = 80) -> str:
    return text if len(text) <= n else text[:n - 3] + "..."


def _uri_path(uri: str, folder: Path, where: str) -> Path:
    """The file a relative URI names, which must lie inside ``folder`` (links resolved)."""
    shown = _short(uri)
    scheme = re.match(r"^([A-Za-z][A-Za-z0-9+.-]*):", uri)
    if scheme:
        _fail(where, f"'{shown}': {scheme.group(1)}: URIs are not read; a glTF file may only refer "
                     "to files in its own folder (relative paths) and to data: URIs")
    rel = unquote(uri)
    if not rel or "\x00" in rel:
        _fail(where, f"'{shown}' is not a file name")
    if rel.startswith(("/", "\\")) or os.path.isabs(rel) or PureWindowsPath(rel).drive:
        _fail(where, f"'{shown}' is an absolute path; a glTF file may only refer to files in its own folder")
    base = os.path.realpath(folder)
    target = os.path.realpath(os.path.join(base, rel))
    if os.path.commonpath([base, target]) != base:
        _fail(where, f"'{shown}' is outside the model's folder; a glTF file may only refer to files "
                     "in its own folder")
    return Path(target)


def _data_uri(uri: str, where: str, budget: _Budget) -> bytes:
    header, sep, payload = uri.partition(",")
    if not sep or not header.endswith(";base64"):
        _fail(where, "a data: URI must be base64 (data:<type>;base64,<data>)")
    payload = re.sub(r"\s+", "", payload)
    budget.take(len(payload) * 3 // 4, where, "the data: URI")
    try:
        return base64.b64decode(payload, validate=True)
    except (binascii.Error, ValueError):
        _fail(where, "the data: URI is not valid base64")


def _uri_bytes(uri, folder: Path, where: str, budget: _Budget, length: int | None = None) -> bytes:
    if not isinstance(uri, str):
        _fail(where, f"expected a string, got {_show(uri)}")
    if uri.startswith("data:"):
        data = _data_uri(uri, where, budget)
        if length is not None:
            if len(data) < length:
                _fail(where, f"the data: URI holds {len(data)} bytes, less than the byteLength {length}")
            data = data[:length]
        return data
    return _read_regular(_uri_path(uri, folder, where), where, _short(uri), budget, length)


def _read_container(path: Path, budget: _Budget) -> tuple[str, bytes | None]:
    """(JSON text, GLB binary chunk or None) of a .gltf or .glb file."""
    data = _read_regular(path, "", path.name, budget)
    if data[:4] != _GLB_MAGIC:
        if path.suffix.lower() == ".glb":
            raise GLTFError("not a valid glTF 2.0 file (a .glb file starts with 'glTF')")
        try:
            return data.decode("utf-8-sig"), None
        except UnicodeDecodeError as exc:
            raise GLTFError(f"not a valid glTF 2.0 file (the JSON is not UTF-8: {exc.reason} at byte "
                            f"{exc.start})") from None

    def bad(problem):
        raise GLTFError(f"not a valid glTF 2.0 file (GLB: {problem})")

    if len(data) < 20:
        bad(f"{len(data)} bytes, too short for a header and a chunk")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2:
        bad(f"version {version}; only version 2 is supported")
    if length > len(data) or length < 20:
        bad(f"the header says {length} bytes, the file has {len(data)}")
    chunks, offset = [], 12
    while offset + 8 <= length:
        size, kind = struct.unpack_from("<II", data, offset)
        if offset + 8 + size > length:
            bad(f"chunk {len(chunks)} of {size} bytes runs past the end of the file")
        chunks.append((kind, data[offset + 8:offset + 8 + size]))
        offset += 8 + size
        offset += -offset % 4 if offset < length else 0
    if not chunks or chunks[0][0] != _GLB_JSON:
        bad("the first chunk is not JSON")
    binary = chunks[1][1] if len(chunks) > 1 and chunks[1][0] == _GLB_BIN else None
    try:
        return chunks[0][1].decode("utf-8-sig"), binary
    except UnicodeDecodeError as exc:
        bad(f"the JSON chunk is not UTF-8 ({exc.reason} at byte {exc.start})")


def _reject_constant(name):
    raise ValueError(f"{name} is not valid JSON")


def _parse_json(text: str) -> dict:
    try:
        doc = json.loads(text, parse_constant=_reject_constant)
    except RecursionError:
        raise GLTFError("not a valid glTF 2.0 file (JSON nested too deeply)") from None
    except ValueError as exc:
        raise GLTFError(f"not a valid glTF 2.0 file (JSON: {' '.join(str(exc).split())})") from None
    if not isinstance(doc, dict):
        raise GLTFError("not a valid glTF 2.0 file (the JSON is not an object)")
    return doc


# -- The document ---------------------------------------------------------------------------------

def _show(value) -> str:
    text = json.dumps(value) if isinstance(value, (dict, list, str, int, float, bool, type(None))) else repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def _is_int(v) -> bool:
    return isinstance(v, int) and not isinstance(v, bool)


def _is_num(v) -> bool:
    return (isinstance(v, (int, float)) and not isinstance(v, bool)) and math.isfinite(v)


def _value(o: dict, key: str, where: str, required: bool):
    """``o[key]``, or None where it is absent (an error where it is ``required``)."""
    v = o.get(key)
    if v is None and required:
        _fail(where, f"'{key}' is required")
    return v


class _Checker:
    def __init__(self, doc: dict, limits: Limits):
        self.doc, self.limits = doc, limits
        self.arrays = {}
        for name in _TOP_ARRAYS:
            value = doc.get(name, [])
            if not isinstance(value, list):
                _fail(name, f"expected an array, got {_show(value)}")
            for i, item in enumerate(value):
                if not isinstance(item, dict):
                    _fail(f"{name}[{i}]", f"expected an object, got {_show(item)}")
            self.arrays[name] = value
        self.lights = []

    # Typed getters: None when absent (or ``default``), else the checked value.
    def obj(self, o, key, where, required=False):
        v = _value(o, key, where, required)
        if v is None:
            return None
        if not isinstance(v, dict):
            _fail(_at(where, key), f"expected an object, got {_show(v)}")
        return v

    def integer(self, o, key, where, lo=0, hi=None, default=None, required=False):
        v = _value(o, key, where, required)
        if v is None:
            return default
        if not _is_int(v):
            _fail(_at(where, key), f"expected an integer, got {_show(v)}")
        if v < lo or (hi is not None and v > hi):
            rng = f"at least {lo}" if hi is None else f"from {lo} to {hi}"
            _fail(_at(where, key), f"{v} is out of range (it must be {rng})")
        return v

    def index(self, o, key, where, target, required=False):
        v = _value(o, key, where, required)
        if v is None:
            return None
        return self.ref(v, _at(where, key), target)

    def ref(self, v, where, target):
        n = len(self.arrays[target]) if isinstance(target, str) else len(target[1])
        name = target if isinstance(target, str) else target[0]
        if not _is_int(v):
            _fail(where, f"expected an index into {name}, got {_show(v)}")
        if not 0 <= v < n:
            _fail(where, f"{v} is not an index into {name} ({n} entr{'y' if n == 1 else 'ies'})")
        return v

    def number(self, o, key, where, lo=None, hi=None, lo_open=False, hi_open=False, default=None,
               required=False):
        v = _value(o, key, where, required)
        if v is None:
            return default
        if not _is_num(v):
            _fail(_at(where, key), f"expected a finite number, got {_show(v)}")
        low_bad = lo is not None and (v <= lo if lo_open else v < lo)
        high_bad = hi is not None and (v >= hi if hi_open else v > hi)
        if low_bad or high_bad:
            left = "(" if lo_open else "["
            right = ")" if hi_open else "]"
            rng = (f"in {left}{lo:g}, {hi:g}{right}" if lo is not None and hi is not None
                   else f"{'>' if lo_open else '>='} {lo:g}" if lo is not None
                   else f"{'<' if hi_open else '<='} {hi:g}")
            _fail(_at(where, key), f"{v:g} is out of range (it must be {rng})")
        return v

    def numbers(self, o, key, where, n, lo=None, hi=None):
        v = o.get(key)
        if v is None:
            return None
        if not isinstance(v, list) or len(v) != n or not all(_is_num(x) for x in v):
            _fail(_at(where, key), f"expected {n} finite numbers, got {_show(v)}")
        if (lo is not None and min(v) < lo) or (hi is not None and max(v) > hi):
            _fail(_at(where, key), f"{_show(v)} has a value outside [{lo:g}, {hi if hi is not None else math.inf:g}]")
        return v

    def string(self, o, key, where, choices=None, default=None):
        v = o.get(key)
        if v is None:
            return default
        if not isinstance(v, str):
            _fail(_at(where, key), f"expected a string, got {_show(v)}")
        if choices is not None and v not in choices:
            _fail(_at(where, key), f"'{v}' is not one of {', '.join(choices)}")
        return v

    def boolean(self, o, key, where):
        v = o.get(key)
        if v is not None and not isinstance(v, bool):
            _fail(_at(where, key), f"expected true or false, got {_show(v)}")
        return v

    def extension(self, o, where, name):
        ext = self.obj(o, "extensions", where)
        return self.obj(ext, name, _at(where, "extensions")) if ext is not None else None

    # -- Sections
    def asset(self):
        asset = self.obj(self.doc, "asset", "", required=True)
        version = self.string(asset, "version", "asset")
        if version is None or not re.fullmatch(r"2\.\d+", version):
            _fail("asset.version", f"{_show(version)} is not a glTF 2.x version")
        minimum = self.string(asset, "minVersion", "asset")
        if minimum is not None and not re.fullmatch(r"2\.0", minimum):
            _fail("asset.minVersion", f"'{minimum}' is newer than the glTF 2.0 this loader reads")
        for key in ("extensionsUsed", "extensionsRequired"):
            v = self.doc.get(key, [])
            if not isinstance(v, list) or not all(isinstance(x, str) for x in v):
                _fail(key, f"expected an array of strings, got {_show(v)}")

    def buffers_and_views(self):
        for i, b in enumerate(self.arrays["buffers"]):
            self.integer(b, "byteLength", f"buffers[{i}]", lo=1, required=True)
            self.string(b, "uri", f"buffers[{i}]")
        for i, v in enumerate(self.arrays["bufferViews"]):
            where = f"bufferViews[{i}]"
            b = self.index(v, "buffer", where, "buffers", required=True)
            offset = self.integer(v, "byteOffset", where, default=0)
            length = self.integer(v, "byteLength", where, lo=1, required=True)
            self.integer(v, "byteStride", where, lo=4, hi=252)
            stride = v.get("byteStride")
            if stride is not None and stride % 4:
                _fail(f"{where}.byteStride", f"{stride} is not a multiple of 4")
            size = self.arrays["buffers"][b]["byteLength"]
            if offset + length > size:
                _fail(where, f"byteOffset {offset} + byteLength {length} = {offset + length} runs past "
                             f"the end of buffers[{b}] ({size} bytes)")

    @staticmethod
    def element_size(component: int, kind: str) -> int:
        size, width = COMPONENT_SIZE[component], TYPE_WIDTH[kind]
        if kind.startswith("MAT"):
            rows = {"MAT2": 2, "MAT3": 3, "MAT4": 4}[kind]
            column = -(-rows * size // 4) * 4       # columns start on 4-byte boundaries
            return rows * column
        return width * size

    def _span(self, view_index, offset, stride, elem, count, where):
        view = self.arrays["bufferViews"][view_index]
        end = offset + stride * (count - 1) + elem
        if end > view["byteLength"]:
            _fail(where, f"{count} element(s) of {elem} bytes, {stride} bytes apart, from byteOffset "
                         f"{offset} need {end} bytes; bufferViews[{view_index}] has {view['byteLength']}")

    def accessors(self, budget: _Budget):
        for i, a in enumerate(self.arrays["accessors"]):
            where = f"accessors[{i}]"
            view = self.index(a, "bufferView", where, "bufferViews")
            offset = self.integer(a, "byteOffset", where, default=0)
            component = a.get("componentType")
            if not _is_int(component) or component not in COMPONENT_SIZE:
                _fail(f"{where}.componentType", f"{_show(component)} is not a glTF component type "
                                                f"({', '.join(map(str, COMPONENT_SIZE))})")
            kind = self.string(a, "type", where, choices=tuple(TYPE_WIDTH))
            if kind is None:
                _fail(where, "'type' is required")
            count = self.integer(a, "count", where, lo=1, required=True)
            for key in ("min", "max"):
                bound = a.get(key)
                if bound is not None and (not isinstance(bound, list) or not all(_is_num(x) for x in bound)):
                    _fail(_at(where, key), f"expected an array of finite numbers, got {_show(bound)}")
            if self.boolean(a, "normalized", where) and component in (_FLOAT, _UINT):
                _fail(f"{where}.normalized", "only 8- and 16-bit integer accessors can be normalized")
            elem = self.element_size(component, kind)
            if view is not None:
                stride = self.arrays["bufferViews"][view].get("byteStride") or elem
                if stride < elem:
                    _fail(where, f"bufferViews[{view}].byteStride {stride} is smaller than the "
                                 f"{elem}-byte element")
                self._span(view, offset, stride, elem, count, where)
            else:
                budget.take(count * elem, where, f"{count} zero-filled element(s) (no bufferView)")
            sparse = self.obj(a, "sparse", where)
            if sparse is not None:
                sw = f"{where}.sparse"
                n = self.integer(sparse, "count", sw, lo=1, hi=count, required=True)
                idx = self.obj(sparse, "indices", sw, required=True)
                iv = self.index(idx, "bufferView", f"{sw}.indices", "bufferViews", required=True)
                ioff = self.integer(idx, "byteOffset", f"{sw}.indices", default=0)
                ic = idx.get("componentType")
                if not _is_int(ic) or ic not in (_UBYTE, _USHORT, _UINT):
                    _fail(f"{sw}.indices.componentType", f"{_show(ic)} is not 5121, 5123 or 5125")
                self._span(iv, ioff, COMPONENT_SIZE[ic], COMPONENT_SIZE[ic], n, f"{sw}.indices")
                val = self.obj(sparse, "values", sw, required=True)
                vv = self.index(val, "bufferView", f"{sw}.values", "bufferViews", required=True)
                voff = self.integer(val, "byteOffset", f"{sw}.values", default=0)
                self._span(vv, voff, elem, elem, n, f"{sw}.values")

    def samplers_textures_images(self):
        for i, s in enumerate(self.arrays["samplers"]):
            where = f"samplers[{i}]"
            for key, allowed in (("magFilter", _MAG), ("minFilter", _MIN), ("wrapS", _WRAPS), ("wrapT", _WRAPS)):
                v = s.get(key)
                if v is not None and (not _is_int(v) or v not in allowed):
                    _fail(_at(where, key), f"{_show(v)} is not one of {', '.join(map(str, sorted(allowed)))}")
        for i, t in enumerate(self.arrays["textures"]):
            self.index(t, "source", f"textures[{i}]", "images")
            self.index(t, "sampler", f"textures[{i}]", "samplers")
        for i, img in enumerate(self.arrays["images"]):
            where = f"images[{i}]"
            has_uri = self.string(img, "uri", where) is not None
            has_view = self.index(img, "bufferView", where, "bufferViews") is not None
            if has_uri == has_view:
                _fail(where, "needs exactly one of 'uri' and 'bufferView'")
            self.string(img, "mimeType", where)

    def texture_info(self, o, key, where):
        info = self.obj(o, key, where)
        if info is not None:
            w = _at(where, key)
            self.index(info, "index", w, "textures", required=True)
            self.integer(info, "texCoord", w, default=0)
        return info

    def materials(self):
        for i, m in enumerate(self.arrays["materials"]):
            where = f"materials[{i}]"
            pbr = self.obj(m, "pbrMetallicRoughness", where)
            if pbr is not None:
                pw = f"{where}.pbrMetallicRoughness"
                self.numbers(pbr, "baseColorFactor", pw, 4, 0.0, 1.0)
                self.number(pbr, "metallicFactor", pw, 0.0, 1.0)
                self.number(pbr, "roughnessFactor", pw, 0.0, 1.0)
                self.texture_info(pbr, "baseColorTexture", pw)
                self.texture_info(pbr, "metallicRoughnessTexture", pw)
            normal = self.texture_info(m, "normalTexture", where)
            if normal is not None:
                self.number(normal, "scale", f"{where}.normalTexture")
            occlusion = self.texture_info(m, "occlusionTexture", where)
            if occlusion is not None:
                self.number(occlusion, "strength", f"{where}.occlusionTexture", 0.0, 1.0)
            self.texture_info(m, "emissiveTexture", where)
            self.numbers(m, "emissiveFactor", where, 3, 0.0, None)
            self.string(m, "alphaMode", where, choices=_ALPHA_MODES)
            self.number(m, "alphaCutoff", where, 0.0)
            self.boolean(m, "doubleSided", where)

    def meshes(self):
        accessors = self.arrays["accessors"]
        for i, mesh in enumerate(self.arrays["meshes"]):
            where = f"meshes[{i}]"
            prims = mesh.get("primitives")
            if not isinstance(prims, list) or not prims:
                _fail(f"{where}.primitives", f"expected a non-empty array, got {_show(prims)}")
            self.string(mesh, "name", where)
            for k, p in enumerate(prims):
                pw = f"{where}.primitives[{k}]"
                if not isinstance(p, dict):
                    _fail(pw, f"expected an object, got {_show(p)}")
                attrs = self.obj(p, "attributes", pw, required=True)
                for name, v in attrs.items():
                    self.ref(v, f"{pw}.attributes.{name}", "accessors")
                count = accessors[attrs["POSITION"]]["count"] if "POSITION" in attrs else None
                for name, (kinds, comps) in _ATTRIBUTE_TYPES.items():
                    if name not in attrs:
                        continue
                    a = accessors[attrs[name]]
                    if a["type"] not in kinds or (a["componentType"], bool(a.get("normalized"))) not in comps:
                        _fail(f"{pw}.attributes.{name}", f"accessors[{attrs[name]}] is a {a['type']} of "
                                                         f"componentType {a['componentType']}"
                                                         f"{' (normalized)' if a.get('normalized') else ''}, "
                                                         f"not what {name} must be")
                    if count is not None and a["count"] != count:
                        _fail(f"{pw}.attributes.{name}", f"accessors[{attrs[name]}] has {a['count']} "
                                                         f"elements, POSITION has {count}")
                idx = self.index(p, "indices", pw, "accessors")
                if idx is not None:
                    a = accessors[idx]
                    if a["type"] != "SCALAR" or a["componentType"] not in (_UBYTE, _USHORT, _UINT) \
                            or a.get("normalized"):
                        _fail(f"{pw}.indices", f"accessors[{idx}] is not a SCALAR of unsigned integers "
                                               "(5121, 5123 or 5125)")
                self.index(p, "material", pw, "materials")
                self.integer(p, "mode", pw, lo=0, hi=6)
                targets = p.get("targets", [])
                if not isinstance(targets, list) or not all(isinstance(t, dict) for t in targets):
                    _fail(f"{pw}.targets", f"expected an array of objects, got {_show(targets)}")
                for t, target in enumerate(targets):
                    for name, v in target.items():
                        self.ref(v, f"{pw}.targets[{t}].{name}", "accessors")

    def cameras(self):
        for i, cam in enumerate(self.arrays["cameras"]):
            where = f"cameras[{i}]"
            kind = self.string(cam, "type", where, choices=("perspective", "orthographic"))
            if kind is None:
                _fail(where, "'type' is required")
            p = self.obj(cam, kind, where, required=True)
            pw = f"{where}.{kind}"
            if kind == "perspective":
                self.number(p, "yfov", pw, 0.0, math.pi, lo_open=True, hi_open=True, required=True)
                znear = self.number(p, "znear", pw, 0.0, lo_open=True, required=True)
                self.number(p, "zfar", pw, znear, lo_open=True)
                self.number(p, "aspectRatio", pw, 0.0, lo_open=True)
            else:
                for key in ("xmag", "ymag"):
                    if self.number(p, key, pw, required=True) == 0:
                        _fail(f"{pw}.{key}", "must not be zero")
                znear = self.number(p, "znear", pw, 0.0, required=True)
                self.number(p, "zfar", pw, znear, lo_open=True, required=True)

    def punctual_lights(self):
        ext = self.extension(self.doc, "", "KHR_lights_punctual")
        if ext is None:
            return
        where = "extensions.KHR_lights_punctual"
        lights = ext.get("lights", [])
        if not isinstance(lights, list):
            _fail(f"{where}.lights", f"expected an array, got {_show(lights)}")
        for i, light in enumerate(lights):
            lw = f"{where}.lights[{i}]"
            if not isinstance(light, dict):
                _fail(lw, f"expected an object, got {_show(light)}")
            kind = self.string(light, "type", lw, choices=_LIGHT_TYPES)
            if kind is None:
                _fail(lw, "'type' is required")
            self.numbers(light, "color", lw, 3, 0.0, None)
            self.number(light, "intensity", lw, 0.0)
            self.number(light, "range", lw, 0.0, lo_open=True)
            spot = self.obj(light, "spot", lw, required=kind == "spot")
            if kind == "spot":
                sw = f"{lw}.spot"
                inner = self.number(spot, "innerConeAngle", sw, 0.0, default=0.0)
                outer = self.number(spot, "outerConeAngle", sw, 0.0, math.pi / 2, lo_open=True,
                                    default=math.pi / 4)
                if inner >= outer:
                    _fail(sw, f"innerConeAngle {inner:g} must be smaller than outerConeAngle {outer:g}")
        self.lights = lights

    def nodes(self):
        nodes = self.arrays["nodes"]
        parents = [None] * len(nodes)
        for i, node in enumerate(nodes):
            where = f"nodes[{i}]"
            children = node.get("children", [])
            if not isinstance(children, list):
                _fail(f"{where}.children", f"expected an array, got {_show(children)}")
            for c in children:
                self.ref(c, f"{where}.children", "nodes")
                if parents[c] == i:
                    _fail(f"{where}.children", f"node {c} is listed twice")
                if parents[c] is not None:
                    _fail(f"{where}.children", f"node {c} is already a child of node {parents[c]} "
                                               "(a node has at most one parent)")
                parents[c] = i
            for key in ("mesh", "camera", "skin"):
                self.index(node, key, where, {"mesh": "meshes", "camera": "cameras", "skin": "skins"}[key])
            self.numbers(node, "matrix", where, 16)
            self.numbers(node, "translation", where, 3)
            self.numbers(node, "scale", where, 3)
            rotation = self.numbers(node, "rotation", where, 4)
            if rotation is not None and not sum(x * x for x in rotation) > 1e-12:
                _fail(f"{where}.rotation", f"{_show(rotation)} is not a unit quaternion")
            light = self.extension(node, where, "KHR_lights_punctual")
            if light is not None:
                self.index(light, "light", f"{where}.extensions.KHR_lights_punctual",
                           ("extensions.KHR_lights_punctual.lights", self.lights), required=True)
        # Cycles: with one parent per node, a node is on a cycle iff its parent chain returns to it.
        state = [0] * len(nodes)             # 0 unseen, 1 on the current chain, 2 done
        for start in range(len(nodes)):
            chain, i = [], start
            while i is not None and state[i] == 0:
                state[i] = 1
                chain.append(i)
                i = parents[i]
            if i is not None and state[i] == 1:
                _fail(f"nodes[{parents[i]}].children", f"cycle through node {i}")
            for j in chain:
                state[j] = 2
        return parents

    def scenes(self, parents):
        for i, scene in enumerate(self.arrays["scenes"]):
            where = f"scenes[{i}]"
            roots = scene.get("nodes", [])
            if not isinstance(roots, list):
                _fail(f"{where}.nodes", f"expected an array, got {_show(roots)}")
            seen = set()
            for r in roots:
                self.ref(r, f"{where}.nodes", "nodes")
                if r in seen:
                    _fail(f"{where}.nodes", f"node {r} is listed twice")
                if parents[r] is not None:
                    _fail(f"{where}.nodes", f"node {r} is a child of node {parents[r]}, not a root")
                seen.add(r)
        default = self.index(self.doc, "scene", "", "scenes")
        if self.arrays["scenes"]:
            return list(self.arrays["scenes"][default or 0].get("nodes", []))
        return [i for i, p in enumerate(parents) if p is None]

    def instanced_vertices(self, roots):
        """Vertices the default scene's meshes take after instancing, against the limit."""
        nodes, meshes, accessors = self.arrays["nodes"], self.arrays["meshes"], self.arrays["accessors"]
        total, stack = 0, list(roots)
        while stack:
            i = stack.pop()
            node = nodes[i]
            stack.extend(node.get("children", []))
            if node.get("mesh") is None:
                continue
            for k, p in enumerate(meshes[node["mesh"]]["primitives"]):
                attrs = p["attributes"]
                if "POSITION" not in attrs:
                    continue
                n = accessors[attrs["POSITION"]]["count"]
                if p.get("indices") is not None:
                    n = max(n, accessors[p["indices"]]["count"])
                total += n
                if total > self.limits.vertices:
                    _fail(f"nodes[{i}]", f"its mesh {node['mesh']} takes the scene past "
                                         f"{self.limits.vertices} vertices after instancing "
                                         f"({self.limits.hint('vertices')})")


_CLASSES = {"accessors": "Accessor", "animations": "Animation", "buffers": "Buffer", "bufferViews": "BufferView",
            "cameras": "Camera", "images": "Image", "materials": "Material", "meshes": "Mesh", "nodes": "Node",
            "samplers": "Sampler", "scenes": "Scene", "skins": "Skin", "textures": "Texture"}


def decode_error(doc: dict, exc: Exception) -> GLTFError:
    """A :class:`GLTFError` naming the element that pygltflib failed to decode (it is strict
    about the types of properties this module does not check, e.g. in animations)."""
    import warnings

    import pygltflib

    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        for name, cls in [("asset", "Asset")] + list(_CLASSES.items()):
            items = [(name, doc.get(name))] if name == "asset" else \
                [(f"{name}[{i}]", item) for i, item in enumerate(doc.get(name) or [])]
            for where, item in items:
                try:
                    getattr(pygltflib, cls).from_dict(item, infer_missing=True)
                except Exception as inner:  # noqa: BLE001
                    return GLTFError(f"{where}: cannot be read ({type(inner).__name__}: "
                                     f"{' '.join(str(inner).split())})")
    return GLTFError(f"not a valid glTF 2.0 file ({type(exc).__name__}: {' '.join(str(exc).split())})")


def _required_extensions(doc):
    unsupported = {"KHR_draco_mesh_compression", "EXT_meshopt_compression",
                   "KHR_mesh_quantization"} & set(doc.get("extensionsRequired") or [])
    if unsupported:
        raise GLTFError(f"needs {', '.join(sorted(unsupported))}, which is not supported")


def read_model(path, limits: Limits = DEFAULT_LIMITS) -> Model:
    """Read and validate the glTF 2.0 file ``path``: see the module docstring. Raises
    :class:`GLTFError` (one line) for anything the loader cannot use safely."""
    path = Path(path)
    budget = _Budget(limits)
    text, binary = _read_container(path, budget)
    doc = _parse_json(text)
    check = _Checker(doc, limits)
    check.asset()
    _required_extensions(doc)
    check.buffers_and_views()
    check.accessors(budget)
    check.samplers_textures_images()
    check.materials()
    check.meshes()
    check.cameras()
    check.punctual_lights()
    parents = check.nodes()
    roots = check.scenes(parents)
    check.instanced_vertices(roots)

    model = Model(path, text, doc, parents=parents, scene_roots=roots)
    folder = path.parent
    for i, b in enumerate(check.arrays["buffers"]):
        where = f"buffers[{i}]"
        length = b["byteLength"]
        if b.get("uri") is not None:
            model.buffers.append(_uri_bytes(b["uri"], folder, f"{where}.uri", budget, length))
        elif i == 0 and binary is not None:
            if len(binary) < length:
                _fail(where, f"byteLength {length} is more than the GLB's binary chunk ({len(binary)} bytes)")
            model.buffers.append(binary[:length])
        else:
            _fail(where, "has no uri, and only buffers[0] of a .glb file may use the binary chunk")
    pixels = 0
    for i, img in enumerate(check.arrays["images"]):
        where = f"images[{i}]"
        if img.get("uri") is not None:
            data = _uri_bytes(img["uri"], folder, f"{where}.uri", budget)
        else:
            view = check.arrays["bufferViews"][img["bufferView"]]
            start = view.get("byteOffset", 0)
            data = model.buffers[view["buffer"]][start:start + view["byteLength"]]
        header = image_header(data)
        if header is None:
            model.images.append(ImageData(data, None))
            continue
        fmt, w, h = header
        if w * h > limits.image_pixels:
            _fail(where, f"the {fmt.upper()} is {w}x{h} pixels, more than an image may have "
                         f"({limits.hint('image_pixels')})")
        pixels += w * h
        if pixels > limits.texture_pixels:
            _fail(where, f"the images take the model past {limits.texture_pixels} pixels "
                         f"({limits.hint('texture_pixels')})")
        model.images.append(ImageData(data, fmt, w, h))
    return model
