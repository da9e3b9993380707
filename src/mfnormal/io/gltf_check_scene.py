"""Validation of a glTF document's scene: textures and materials, cameras, lights, the node graph, its size.

Samplers use known filters and wraps, a texture's references are in range, an image has
exactly one of a URI and a bufferView; material factors lie in [0, 1]; cameras have ``yfov``
in (0, π), ``znear`` > 0, ``zfar`` > ``znear``, ``aspectRatio`` > 0 and non-zero
``xmag``/``ymag``; ``KHR_lights_punctual`` lights have a known type, colour and intensity ≥ 0,
``range`` > 0 and 0 ≤ inner < outer ≤ π/2 cone angles. The node graph has no cycle and no node
with two parents, its matrices, translations, rotations (non-zero quaternions) and scales are
finite, scene roots are roots, and the default scene's vertices after instancing stay within
``Limits.vertices``.
"""

from __future__ import annotations

import math

from mfnormal.io.gltf_json import Document, at, fail, is_int, show

_WRAPS = {33071, 33648, 10497}
_MAG = {9728, 9729}
_MIN = {9728, 9729, 9984, 9985, 9986, 9987}
_LIGHT_TYPES = ("directional", "point", "spot")
_ALPHA_MODES = ("OPAQUE", "MASK", "BLEND")


def check_samplers_textures_images(gltf: Document) -> None:
    """Samplers' filters and wraps, textures' references, images with one of a URI and a bufferView."""
    for i, s in enumerate(gltf.arrays["samplers"]):
        where = f"samplers[{i}]"
        for key, allowed in (("magFilter", _MAG), ("minFilter", _MIN), ("wrapS", _WRAPS), ("wrapT", _WRAPS)):
            v = s.get(key)
            if v is not None and (not is_int(v) or v not in allowed):
                fail(at(where, key), f"{show(v)} is not one of {', '.join(map(str, sorted(allowed)))}")
    for i, t in enumerate(gltf.arrays["textures"]):
        gltf.index(t, "source", f"textures[{i}]", "images")
        gltf.index(t, "sampler", f"textures[{i}]", "samplers")
    for i, img in enumerate(gltf.arrays["images"]):
        where = f"images[{i}]"
        has_uri = gltf.string(img, "uri", where) is not None
        has_view = gltf.index(img, "bufferView", where, "bufferViews") is not None
        if has_uri == has_view:
            fail(where, "needs exactly one of 'uri' and 'bufferView'")
        gltf.string(img, "mimeType", where)


def _texture_info(gltf: Document, o, key, where):
    """The textureInfo ``o[key]`` (None where absent), its texture index in range."""
    info = gltf.obj(o, key, where)
    if info is not None:
        w = at(where, key)
        gltf.index(info, "index", w, "textures", required=True)
        gltf.integer(info, "texCoord", w, default=0)
    return info


def check_materials(gltf: Document) -> None:
    """Materials' factors in range, their textures, alpha mode and sidedness."""
    for i, m in enumerate(gltf.arrays["materials"]):
        where = f"materials[{i}]"
        pbr = gltf.obj(m, "pbrMetallicRoughness", where)
        if pbr is not None:
            pw = f"{where}.pbrMetallicRoughness"
            gltf.numbers(pbr, "baseColorFactor", pw, 4, 0.0, 1.0)
            gltf.number(pbr, "metallicFactor", pw, 0.0, 1.0)
            gltf.number(pbr, "roughnessFactor", pw, 0.0, 1.0)
            _texture_info(gltf, pbr, "baseColorTexture", pw)
            _texture_info(gltf, pbr, "metallicRoughnessTexture", pw)
        normal = _texture_info(gltf, m, "normalTexture", where)
        if normal is not None:
            gltf.number(normal, "scale", f"{where}.normalTexture")
        occlusion = _texture_info(gltf, m, "occlusionTexture", where)
        if occlusion is not None:
            gltf.number(occlusion, "strength", f"{where}.occlusionTexture", 0.0, 1.0)
        _texture_info(gltf, m, "emissiveTexture", where)
        gltf.numbers(m, "emissiveFactor", where, 3, 0.0, None)
        gltf.string(m, "alphaMode", where, choices=_ALPHA_MODES)
        gltf.number(m, "alphaCutoff", where, 0.0)
        gltf.boolean(m, "doubleSided", where)


def check_cameras(gltf: Document) -> None:
    """Perspective and orthographic cameras' projections (see the module docstring)."""
    for i, cam in enumerate(gltf.arrays["cameras"]):
        where = f"cameras[{i}]"
        kind = gltf.string(cam, "type", where, choices=("perspective", "orthographic"))
        if kind is None:
            fail(where, "'type' is required")
        p = gltf.obj(cam, kind, where, required=True)
        pw = f"{where}.{kind}"
        if kind == "perspective":
            gltf.number(p, "yfov", pw, 0.0, math.pi, lo_open=True, hi_open=True, required=True)
            znear = gltf.number(p, "znear", pw, 0.0, lo_open=True, required=True)
            gltf.number(p, "zfar", pw, znear, lo_open=True)
            gltf.number(p, "aspectRatio", pw, 0.0, lo_open=True)
        else:
            for key in ("xmag", "ymag"):
                if gltf.number(p, key, pw, required=True) == 0:
                    fail(f"{pw}.{key}", "must not be zero")
            znear = gltf.number(p, "znear", pw, 0.0, required=True)
            gltf.number(p, "zfar", pw, znear, lo_open=True, required=True)


def check_punctual_lights(gltf: Document) -> None:
    """The ``KHR_lights_punctual`` lights, kept as ``gltf.lights`` for the nodes that refer to them."""
    ext = gltf.extension(gltf.doc, "", "KHR_lights_punctual")
    if ext is None:
        return
    where = "extensions.KHR_lights_punctual"
    lights = ext.get("lights", [])
    if not isinstance(lights, list):
        fail(f"{where}.lights", f"expected an array, got {show(lights)}")
    for i, light in enumerate(lights):
        lw = f"{where}.lights[{i}]"
        if not isinstance(light, dict):
            fail(lw, f"expected an object, got {show(light)}")
        kind = gltf.string(light, "type", lw, choices=_LIGHT_TYPES)
        if kind is None:
            fail(lw, "'type' is required")
        gltf.numbers(light, "color", lw, 3, 0.0, None)
        gltf.number(light, "intensity", lw, 0.0)
        gltf.number(light, "range", lw, 0.0, lo_open=True)
        spot = gltf.obj(light, "spot", lw, required=kind == "spot")
        if kind == "spot":
            sw = f"{lw}.spot"
            inner = gltf.number(spot, "innerConeAngle", sw, 0.0, default=0.0)
            outer = gltf.number(spot, "outerConeAngle", sw, 0.0, math.pi / 2, lo_open=True,
                                default=math.pi / 4)
            if inner >= outer:
                fail(sw, f"innerConeAngle {inner:g} must be smaller than outerConeAngle {outer:g}")
    gltf.lights = lights


def check_nodes(gltf: Document) -> list:
    """Nodes' references and transforms, and the node graph a forest: each node's parent (None
    for roots)."""
    nodes = gltf.arrays["nodes"]
    parents = [None] * len(nodes)
    for i, node in enumerate(nodes):
        where = f"nodes[{i}]"
        children = node.get("children", [])
        if not isinstance(children, list):
            fail(f"{where}.children", f"expected an array, got {show(children)}")
        for c in children:
            gltf.ref(c, f"{where}.children", "nodes")
            if parents[c] == i:
                fail(f"{where}.children", f"node {c} is listed twice")
            if parents[c] is not None:
                fail(f"{where}.children", f"node {c} is already a child of node {parents[c]} "
                                          "(a node has at most one parent)")
            parents[c] = i
        for key in ("mesh", "camera", "skin"):
            gltf.index(node, key, where, {"mesh": "meshes", "camera": "cameras", "skin": "skins"}[key])
        gltf.numbers(node, "matrix", where, 16)
        gltf.numbers(node, "translation", where, 3)
        gltf.numbers(node, "scale", where, 3)
        rotation = gltf.numbers(node, "rotation", where, 4)
        if rotation is not None and not sum(x * x for x in rotation) > 1e-12:
            fail(f"{where}.rotation", f"{show(rotation)} is not a unit quaternion")
        light = gltf.extension(node, where, "KHR_lights_punctual")
        if light is not None:
            gltf.index(light, "light", f"{where}.extensions.KHR_lights_punctual",
                       ("extensions.KHR_lights_punctual.lights", gltf.lights), required=True)
    # Cycles: with one parent per node, a node is on a cycle iff its parent chain returns to it.
    state = [0] * len(nodes)             # 0 unseen, 1 on the current chain, 2 done
    for start in range(len(nodes)):
        chain, i = [], start
        while i is not None and state[i] == 0:
            state[i] = 1
            chain.append(i)
            i = parents[i]
        if i is not None and state[i] == 1:
            fail(f"nodes[{parents[i]}].children", f"cycle through node {i}")
        for j in chain:
            state[j] = 2
    return parents


def check_scenes(gltf: Document, parents) -> list:
    """Scenes' root lists; the default scene's roots (without scenes: every root node)."""
    for i, scene in enumerate(gltf.arrays["scenes"]):
        where = f"scenes[{i}]"
        roots = scene.get("nodes", [])
        if not isinstance(roots, list):
            fail(f"{where}.nodes", f"expected an array, got {show(roots)}")
        seen = set()
        for r in roots:
            gltf.ref(r, f"{where}.nodes", "nodes")
            if r in seen:
                fail(f"{where}.nodes", f"node {r} is listed twice")
            if parents[r] is not None:
                fail(f"{where}.nodes", f"node {r} is a child of node {parents[r]}, not a root")
            seen.add(r)
    default = gltf.index(gltf.doc, "scene", "", "scenes")
    if gltf.arrays["scenes"]:
        return list(gltf.arrays["scenes"][default or 0].get("nodes", []))
    return [i for i, p in enumerate(parents) if p is None]


def check_instanced_vertices(gltf: Document, roots) -> None:
    """Vertices the default scene's meshes take after instancing, against the limit."""
    nodes, meshes, accessors = gltf.arrays["nodes"], gltf.arrays["meshes"], gltf.arrays["accessors"]
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
            if total > gltf.limits.vertices:
                fail(f"nodes[{i}]", f"its mesh {node['mesh']} takes the scene past "
                                    f"{gltf.limits.vertices} vertices after instancing "
                                    f"({gltf.limits.hint('vertices')})")
