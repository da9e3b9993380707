"""Mitsuba scenes as XML text, XML trees and Python dicts: ``$`` parameters, conversion, rewriting.

- ``$name`` parameters: :func:`substitute` (what ``mi.load_file(path, name=value)``
  does to the text) and :func:`references` (whether a text uses one);
- :func:`xml_to_dict`: a (simple) XML scene file as the scene dict ``mi.load_dict``
  takes, parameters substituted;
- scene dicts: :func:`dicts_of_type` and :func:`rewrite_dict` (a copy with every
  plugin of one type rewritten, e.g. every ``normalmap_microfacet``'s nested BSDF);
- XML trees: :func:`read_scene` and :func:`rewrite`, the scene with every
  ``normalmap_microfacet`` BSDF rewritten for one :class:`mfnormal.methods.Method`
  (what ``mfnormal compare`` renders), and :func:`set_film_width`.
"""

from __future__ import annotations

import copy
import os
import re
import xml.etree.ElementTree as ET
from pathlib import Path

from mfnormal.methods import PLUGIN, Method

__all__ = ["SceneError", "PARAMETER", "substitute", "references", "read_scene", "xml_to_dict",
           "dicts_of_type", "rewrite_dict", "rewrite", "film_size_parameters", "set_film_width"]

#: A ``$name`` parameter reference in a scene's text.
PARAMETER = re.compile(r"\$(\w+)")


class SceneError(Exception):
    """A problem with the user's scene (reported as one line by the CLI)."""


def substitute(text: str, values: dict) -> str:
    """``text`` with every ``$name`` replaced by ``values[name]``; unknown names stay as they are."""
    return PARAMETER.sub(lambda m: str(values.get(m.group(1), m.group(0))), text)


def references(text: str, name: str) -> bool:
    """Whether ``text`` refers to the parameter ``$name``."""
    return re.search(rf"\${name}\b", text) is not None


def defaults(root: ET.Element) -> dict:
    """The values of a scene's ``<default>`` parameters."""
    return {d.get("name"): d.get("value") for d in root.iter("default")}


def read_scene(path) -> ET.Element:
    """The root ``<scene>`` element of an XML file; :class:`SceneError` if it is not one."""
    path = Path(path)
    try:
        root = ET.parse(path).getroot()
    except ET.ParseError as exc:
        raise SceneError(f"cannot parse {path.name}: {exc}") from None
    if root.tag != "scene":
        raise SceneError(f"{path.name}: the root element is <{root.tag}>, not <scene>")
    return root


# ---------------------------------------------------------------------------
# XML -> dict
# ---------------------------------------------------------------------------

_OBJECT_TAGS = {"scene", "integrator", "sensor", "film", "sampler", "rfilter", "emitter",
                "shape", "bsdf", "texture", "medium", "phase", "volume"}


def _floats(text: str) -> list:
    return [float(v) for v in text.replace(",", " ").split()]


def _xyz(a: dict, default: float) -> list:
    if "value" in a:
        v = _floats(a["value"])
        return v * 3 if len(v) == 1 else v
    return [float(a.get(k, default)) for k in ("x", "y", "z")]


def _transform(el: ET.Element, values: dict, where: str):
    import mitsuba as mi

    T = mi.ScalarTransform4d()
    for op in el:
        if not isinstance(op.tag, str):
            continue
        a = {k: substitute(v, values) for k, v in op.attrib.items()}
        if op.tag == "lookat":
            M = mi.ScalarTransform4d().look_at(origin=_floats(a["origin"]),
                                                target=_floats(a["target"]),
                                                up=_floats(a.get("up", "0 1 0")))
        elif op.tag == "rotate":
            M = mi.ScalarTransform4d().rotate(_xyz(a, 0.0), float(a["angle"]))
        elif op.tag == "scale":
            M = mi.ScalarTransform4d().scale(_xyz(a, 1.0))
        elif op.tag == "translate":
            M = mi.ScalarTransform4d().translate(_xyz(a, 0.0))
        else:
            raise ValueError(f"{where}: unsupported transform operation <{op.tag}>")
        T = M @ T          # XML order: later operations are applied last
    return T


def _property(tag: str, a: dict, child: ET.Element, values: dict, where: str):
    if tag == "integer":
        return int(a["value"])
    if tag == "float":
        return float(a["value"])
    if tag == "boolean":
        return a["value"].strip().lower() == "true"
    if tag == "string":
        return a["value"]
    if tag == "rgb":
        return {"type": "rgb", "value": _floats(a["value"])}
    if tag == "transform":
        return _transform(child, values, where)
    raise ValueError(f"{where}: unsupported element <{tag}>")


def _element_to_dict(el: ET.Element, values: dict, where: str) -> dict:
    if el.tag == "scene":
        out = {"type": "scene"}
    else:
        out = {"type": substitute(el.attrib["type"], values)} if "type" in el.attrib else {}
    counter = 0
    for child in el:
        if not isinstance(child.tag, str) or child.tag == "default":
            continue
        a = {k: substitute(v, values) for k, v in child.attrib.items()}
        if child.tag in _OBJECT_TAGS:
            key = a.get("name") or a.get("id")
            if key is None:
                key, counter = f"{child.tag}_{counter}", counter + 1
            out[key] = _element_to_dict(child, values, where)
        else:
            out[a["name"]] = _property(child.tag, a, child, values, where)
    return out


def _resolve_files(d: dict, folder: Path):
    for k, v in d.items():
        if isinstance(v, dict):
            _resolve_files(v, folder)
        elif k == "filename" and not os.path.isabs(v):
            d[k] = str(folder / v)


def xml_to_dict(path, **params) -> dict:
    """Convert a (simple) Mitsuba XML scene into a scene dict, substituting
    ``$name`` parameters like ``mi.load_file(path, **params)`` does.

    Supports objects, integer/float/boolean/string/rgb properties and transforms
    made of lookat/rotate/scale/translate (what the bundled scenes use). Relative
    file names are resolved against the XML file's directory.
    """
    path = Path(path).resolve()
    root = ET.parse(path).getroot()
    values = defaults(root)
    unknown = set(params) - set(values)
    if unknown:
        raise ValueError(f"{path.name}: unknown parameter(s) {sorted(unknown)}")
    values.update({k: str(v) for k, v in params.items()})
    scene = _element_to_dict(root, values, path.name)
    _resolve_files(scene, path.parent)
    return scene


# ---------------------------------------------------------------------------
# Scene dicts
# ---------------------------------------------------------------------------

def dicts_of_type(d: dict, plugin_type: str):
    """Every dict of ``type`` ``plugin_type`` nested in ``d`` (not looking inside those)."""
    for v in d.values():
        if isinstance(v, dict):
            if v.get("type") == plugin_type:
                yield v
            else:
                yield from dicts_of_type(v, plugin_type)


def _copy_dicts(d):
    """Copy the nested dicts of a scene dict, sharing the leaves (transforms, bitmaps, ...)."""
    return {k: _copy_dicts(v) if isinstance(v, dict) else v for k, v in d.items()}


def rewrite_dict(scene: dict, plugin_type: str, rewrite, what: str) -> dict:
    """A copy of ``scene`` with ``rewrite(d)`` applied to every nested dict of ``plugin_type``
    (in place, on the copy); ``RuntimeError`` if there is none."""
    scene = _copy_dicts(scene)
    found = list(dicts_of_type(scene, plugin_type))
    if not found:
        raise RuntimeError(f"scene has no {what} to swap")
    for d in found:
        rewrite(d)
    return scene


# ---------------------------------------------------------------------------
# XML trees: a scene rewritten for one normal-mapping method
# ---------------------------------------------------------------------------

def _remove_props(el, names):
    for child in list(el):
        if child.tag != "bsdf" and child.get("name") in names:
            el.remove(child)


def _set_prop(el, tag, name, value):
    _remove_props(el, {name})
    el.insert(0, ET.Element(tag, name=name, value=value))


def _as_plugin(el: ET.Element, method: Method) -> ET.Element:
    """The plugin with the method's model (and tangent facet, for the walks)."""
    params = method.plugin_params()
    for name, value in params.items():
        _set_prop(el, "string", name, value)
    if "tangent_facet" not in params:
        _remove_props(el, {"tangent_facet"})
    return el


def _as_flat(el: ET.Element) -> ET.Element:
    """The plugin's nested BSDF in its place (its id and name carried over)."""
    nested = [c for c in el if c.tag == "bsdf" or (c.tag == "ref" and c.get("name") != "normalmap")]
    if len(nested) != 1:
        raise SceneError(f"a {PLUGIN} BSDF needs exactly one nested BSDF, found {len(nested)}")
    flat = copy.deepcopy(nested[0])
    if el.get("id"):
        if flat.tag == "ref":
            raise SceneError(f"cannot replace {PLUGIN} '{el.get('id')}' by its nested "
                             "<ref> BSDF: give the nested BSDF inline")
        flat.set("id", el.get("id"))
    flat.attrib.pop("name", None)
    if el.get("name"):
        flat.set("name", el.get("name"))
    return flat


def _as_classic(el: ET.Element, fixes: bool, values: dict, notes: set) -> ET.Element:
    """Mitsuba's normalmap: the same texture and nested BSDF, none of the plugin's options."""
    props = {c.get("name"): substitute(c.get("value", ""), values) for c in el if c.tag != "bsdf"}
    try:
        strength = float(props.get("strength", 1.0))
    except ValueError:                         # an unresolved $parameter: the plugin will say
        strength = 1.0
    if strength != 1.0:
        notes.add(f"Mitsuba's normalmap has no strength parameter: it uses the map as is "
                  f"(the scene's strength is {props['strength']}).")
    if props.get("normalmap_convention", "opengl") != "opengl":
        notes.add("Mitsuba's normalmap assumes the OpenGL convention; the scene's map is DirectX.")
    el.set("type", "normalmap")
    for child in list(el):
        if child.tag == "string" and child.get("name") == "normalmap":
            tex = ET.Element("texture", type="bitmap", name="normalmap")
            ET.SubElement(tex, "string", name="filename", value=child.get("value"))
            ET.SubElement(tex, "boolean", name="raw", value="true")
            el.remove(child)
            el.insert(0, tex)
    _remove_props(el, {"model", "tangent_facet", "max_bounces", "strength", "normalmap_convention"})
    flag = "true" if fixes else "false"
    _set_prop(el, "boolean", "use_shadowing_function", flag)
    _set_prop(el, "boolean", "flip_invalid_normals", flag)
    return el


def _convert(el: ET.Element, method: Method, values: dict, notes: set) -> ET.Element:
    """One ``normalmap_microfacet`` element rewritten for ``method``."""
    el = copy.deepcopy(el)
    if method.kind == "microfacet":
        return _as_plugin(el, method)
    if method.kind == "flat":
        return _as_flat(el)
    return _as_classic(el, method.fixes, values, notes)


def rewrite(root: ET.Element, method: Method, values: dict | None = None,
            notes: set | None = None) -> ET.Element:
    """A copy of the scene with every ``normalmap_microfacet`` BSDF rewritten for ``method``
    (``values``: the ``$`` parameters, to read the plugin's strength and convention;
    ``notes`` collects what a method cannot reproduce, e.g. a strength for Mitsuba's normalmap)."""
    root = copy.deepcopy(root)
    values = values or {}
    notes = set() if notes is None else notes
    targets = [(parent, i) for parent in root.iter() for i, child in enumerate(parent)
               if child.tag == "bsdf" and child.get("type") == PLUGIN]
    for parent, i in targets:
        parent[i] = _convert(parent[i], method, values, notes)
    return root


def film_size_parameters(root: ET.Element) -> set:
    """The ``$`` parameters that the films' width and height refer to."""
    return {name for film in root.iter("film") for c in film
            if c.tag == "integer" and c.get("name") in ("width", "height")
            for name in PARAMETER.findall(c.get("value", ""))}


def set_film_width(root: ET.Element, values: dict, width: int | None) -> tuple:
    """Scale the film down to ``width`` pixels (keeping its aspect ratio), in place;
    returns (w, h)."""
    sizes = []
    for film in root.iter("film"):
        def get(name, default):
            for c in film:
                if c.tag == "integer" and c.get("name") == name:
                    return int(float(substitute(c.get("value"), values)))
            return default
        w, h = get("width", 768), get("height", 576)
        if width is not None and w > width:
            w, h = width, max(1, int(round(h * width / w)))
        for name, v in (("width", w), ("height", h)):
            _remove_props(film, {name})
            film.insert(0, ET.Element("integer", name=name, value=str(v)))
        sizes.append((w, h))
    return sizes[0] if sizes else (768, 576)
