"""Validation of a glTF document's data: buffers, bufferViews, accessors and the meshes that read them.

What the loader reads from a buffer lies inside it: a bufferView lies inside its buffer;
``byteStride`` is 4–252, a multiple of 4 and at least the accessor's element size; an
accessor's ``byteOffset + stride·(count − 1) + element`` lies inside its bufferView; sparse
indices and values lie inside theirs; an accessor without a bufferView (zeros) counts against
the byte budget. Mesh attributes have the types the loader reads and the same count as
``POSITION``; indices are unsigned integer scalars; every reference is in range.
"""

from __future__ import annotations

from mfnormal.io.gltf_container import Budget
from mfnormal.io.gltf_json import Document, at, fail, is_int, is_num, show

COMPONENT_SIZE = {5120: 1, 5121: 1, 5122: 2, 5123: 2, 5125: 4, 5126: 4}
TYPE_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}
_FLOAT, _UBYTE, _USHORT, _UINT = 5126, 5121, 5123, 5125
# Attributes the loader reads: allowed (componentType, normalized) and types.
_ATTRIBUTE_TYPES = {
    "POSITION": ({"VEC3"}, {(_FLOAT, False)}),
    "NORMAL": ({"VEC3"}, {(_FLOAT, False)}),
    "TANGENT": ({"VEC4"}, {(_FLOAT, False)}),
    "TEXCOORD_0": ({"VEC2"}, {(_FLOAT, False), (_UBYTE, True), (_USHORT, True)}),
}


def check_buffers_and_views(gltf: Document) -> None:
    """Buffers' ``byteLength`` and ``uri``; each bufferView inside its buffer, its stride 4–252 and a
    multiple of 4."""
    for i, b in enumerate(gltf.arrays["buffers"]):
        gltf.integer(b, "byteLength", f"buffers[{i}]", lo=1, required=True)
        gltf.string(b, "uri", f"buffers[{i}]")
    for i, v in enumerate(gltf.arrays["bufferViews"]):
        where = f"bufferViews[{i}]"
        b = gltf.index(v, "buffer", where, "buffers", required=True)
        offset = gltf.integer(v, "byteOffset", where, default=0)
        length = gltf.integer(v, "byteLength", where, lo=1, required=True)
        gltf.integer(v, "byteStride", where, lo=4, hi=252)
        stride = v.get("byteStride")
        if stride is not None and stride % 4:
            fail(f"{where}.byteStride", f"{stride} is not a multiple of 4")
        size = gltf.arrays["buffers"][b]["byteLength"]
        if offset + length > size:
            fail(where, f"byteOffset {offset} + byteLength {length} = {offset + length} runs past "
                        f"the end of buffers[{b}] ({size} bytes)")


def element_size(component: int, kind: str) -> int:
    """The bytes of one accessor element (matrix columns start on 4-byte boundaries)."""
    size, width = COMPONENT_SIZE[component], TYPE_WIDTH[kind]
    if kind.startswith("MAT"):
        rows = {"MAT2": 2, "MAT3": 3, "MAT4": 4}[kind]
        column = -(-rows * size // 4) * 4       # columns start on 4-byte boundaries
        return rows * column
    return width * size


def _span(gltf: Document, view_index, offset, stride, elem, count, where) -> None:
    """``count`` elements of ``elem`` bytes, ``stride`` apart from ``offset``, lie inside the bufferView."""
    view = gltf.arrays["bufferViews"][view_index]
    end = offset + stride * (count - 1) + elem
    if end > view["byteLength"]:
        fail(where, f"{count} element(s) of {elem} bytes, {stride} bytes apart, from byteOffset "
                    f"{offset} need {end} bytes; bufferViews[{view_index}] has {view['byteLength']}")


def check_accessors(gltf: Document, budget: Budget) -> None:
    """Accessors' types, counts and bounds, their elements (and sparse indices and values) inside
    their bufferViews; zero-filled ones taken from the ``budget``."""
    for i, a in enumerate(gltf.arrays["accessors"]):
        where = f"accessors[{i}]"
        view = gltf.index(a, "bufferView", where, "bufferViews")
        offset = gltf.integer(a, "byteOffset", where, default=0)
        component = a.get("componentType")
        if not is_int(component) or component not in COMPONENT_SIZE:
            fail(f"{where}.componentType", f"{show(component)} is not a glTF component type "
                                           f"({', '.join(map(str, COMPONENT_SIZE))})")
        kind = gltf.string(a, "type", where, choices=tuple(TYPE_WIDTH))
        if kind is None:
            fail(where, "'type' is required")
        count = gltf.integer(a, "count", where, lo=1, required=True)
        for key in ("min", "max"):
            bound = a.get(key)
            if bound is not None and (not isinstance(bound, list) or not all(is_num(x) for x in bound)):
                fail(at(where, key), f"expected an array of finite numbers, got {show(bound)}")
        if gltf.boolean(a, "normalized", where) and component in (_FLOAT, _UINT):
            fail(f"{where}.normalized", "only 8- and 16-bit integer accessors can be normalized")
        elem = element_size(component, kind)
        if view is not None:
            stride = gltf.arrays["bufferViews"][view].get("byteStride") or elem
            if stride < elem:
                fail(where, f"bufferViews[{view}].byteStride {stride} is smaller than the "
                            f"{elem}-byte element")
            _span(gltf, view, offset, stride, elem, count, where)
        else:
            budget.take(count * elem, where, f"{count} zero-filled element(s) (no bufferView)")
        sparse = gltf.obj(a, "sparse", where)
        if sparse is not None:
            sw = f"{where}.sparse"
            n = gltf.integer(sparse, "count", sw, lo=1, hi=count, required=True)
            idx = gltf.obj(sparse, "indices", sw, required=True)
            iv = gltf.index(idx, "bufferView", f"{sw}.indices", "bufferViews", required=True)
            ioff = gltf.integer(idx, "byteOffset", f"{sw}.indices", default=0)
            ic = idx.get("componentType")
            if not is_int(ic) or ic not in (_UBYTE, _USHORT, _UINT):
                fail(f"{sw}.indices.componentType", f"{show(ic)} is not 5121, 5123 or 5125")
            _span(gltf, iv, ioff, COMPONENT_SIZE[ic], COMPONENT_SIZE[ic], n, f"{sw}.indices")
            val = gltf.obj(sparse, "values", sw, required=True)
            vv = gltf.index(val, "bufferView", f"{sw}.values", "bufferViews", required=True)
            voff = gltf.integer(val, "byteOffset", f"{sw}.values", default=0)
            _span(gltf, vv, voff, elem, elem, n, f"{sw}.values")


def check_meshes(gltf: Document) -> None:
    """Meshes' primitives: attributes of the types the loader reads and of ``POSITION``'s count,
    unsigned integer indices, references in range."""
    accessors = gltf.arrays["accessors"]
    for i, mesh in enumerate(gltf.arrays["meshes"]):
        where = f"meshes[{i}]"
        prims = mesh.get("primitives")
        if not isinstance(prims, list) or not prims:
            fail(f"{where}.primitives", f"expected a non-empty array, got {show(prims)}")
        gltf.string(mesh, "name", where)
        for k, p in enumerate(prims):
            pw = f"{where}.primitives[{k}]"
            if not isinstance(p, dict):
                fail(pw, f"expected an object, got {show(p)}")
            attrs = gltf.obj(p, "attributes", pw, required=True)
            for name, v in attrs.items():
                gltf.ref(v, f"{pw}.attributes.{name}", "accessors")
            count = accessors[attrs["POSITION"]]["count"] if "POSITION" in attrs else None
            for name, (kinds, comps) in _ATTRIBUTE_TYPES.items():
                if name not in attrs:
                    continue
                a = accessors[attrs[name]]
                if a["type"] not in kinds or (a["componentType"], bool(a.get("normalized"))) not in comps:
                    fail(f"{pw}.attributes.{name}", f"accessors[{attrs[name]}] is a {a['type']} of "
                                                    f"componentType {a['componentType']}"
                                                    f"{' (normalized)' if a.get('normalized') else ''}, "
                                                    f"not what {name} must be")
                if count is not None and a["count"] != count:
                    fail(f"{pw}.attributes.{name}", f"accessors[{attrs[name]}] has {a['count']} "
                                                    f"elements, POSITION has {count}")
            idx = gltf.index(p, "indices", pw, "accessors")
            if idx is not None:
                a = accessors[idx]
                if a["type"] != "SCALAR" or a["componentType"] not in (_UBYTE, _USHORT, _UINT) \
                        or a.get("normalized"):
                    fail(f"{pw}.indices", f"accessors[{idx}] is not a SCALAR of unsigned integers "
                                          "(5121, 5123 or 5125)")
            gltf.index(p, "material", pw, "materials")
            gltf.integer(p, "mode", pw, lo=0, hi=6)
            targets = p.get("targets", [])
            if not isinstance(targets, list) or not all(isinstance(t, dict) for t in targets):
                fail(f"{pw}.targets", f"expected an array of objects, got {show(targets)}")
            for t, target in enumerate(targets):
                for name, v in target.items():
                    gltf.ref(v, f"{pw}.targets[{t}].{name}", "accessors")
