"""The glTF document: its JSON parsed strictly, and typed getters that fail with one line naming the element.

Every violation the validation finds is a :class:`GLTFError` whose message is one line naming
the element, ``nodes[3].children: cycle through node 0`` (``fail``). :func:`parse_json` refuses
NaN and Infinity and anything but an object; a :class:`Document` checks that the top-level
arrays are arrays of objects and reads properties with their JSON type and range (integers are
integers, numbers finite, enumerations known values, indices in range). :func:`decode_error`
names the element ``pygltflib`` could not decode.
"""

from __future__ import annotations

import json
import math

from mfnormal.io.inputs import Limits

_TOP_ARRAYS = ("accessors", "animations", "buffers", "bufferViews", "cameras", "images", "materials",
               "meshes", "nodes", "samplers", "scenes", "skins", "textures")


class GLTFError(ValueError):
    """A glTF file the loader refuses: one line naming the element and the problem."""


def fail(where: str, problem: str):
    """Raise the :class:`GLTFError` ``where: problem``."""
    raise GLTFError(f"{where}: {problem}" if where else problem)


def at(where: str, key: str) -> str:
    """The name of property ``key`` of the element ``where``."""
    return f"{where}.{key}" if where else key


def show(value) -> str:
    """``value`` as JSON, cut to 40 characters, for a message."""
    text = json.dumps(value) if isinstance(value, (dict, list, str, int, float, bool, type(None))) else repr(value)
    return text if len(text) <= 40 else text[:37] + "..."


def is_int(v) -> bool:
    """Whether ``v`` is a JSON integer (not a boolean)."""
    return isinstance(v, int) and not isinstance(v, bool)


def is_num(v) -> bool:
    """Whether ``v`` is a finite JSON number (not a boolean)."""
    return (isinstance(v, (int, float)) and not isinstance(v, bool)) and math.isfinite(v)


def _value(o: dict, key: str, where: str, required: bool):
    """``o[key]``, or None where it is absent (an error where it is ``required``)."""
    v = o.get(key)
    if v is None and required:
        fail(where, f"'{key}' is required")
    return v


def _reject_constant(name):
    raise ValueError(f"{name} is not valid JSON")


def parse_json(text: str) -> dict:
    """The JSON object ``text`` holds; a :class:`GLTFError` for NaN, Infinity, deep nesting or a
    value that is not an object."""
    try:
        doc = json.loads(text, parse_constant=_reject_constant)
    except RecursionError:
        raise GLTFError("not a valid glTF 2.0 file (JSON nested too deeply)") from None
    except ValueError as exc:
        raise GLTFError(f"not a valid glTF 2.0 file (JSON: {' '.join(str(exc).split())})") from None
    if not isinstance(doc, dict):
        raise GLTFError("not a valid glTF 2.0 file (the JSON is not an object)")
    return doc


class Document:
    """The glTF JSON document and its top-level arrays (each an array of objects), with typed
    getters that read a property and fail with one line naming it: None when absent (or
    ``default``), else the checked value. ``lights``: the ``KHR_lights_punctual`` lights, once
    checked."""

    def __init__(self, doc: dict, limits: Limits):
        self.doc, self.limits = doc, limits
        self.arrays = {}
        for name in _TOP_ARRAYS:
            value = doc.get(name, [])
            if not isinstance(value, list):
                fail(name, f"expected an array, got {show(value)}")
            for i, item in enumerate(value):
                if not isinstance(item, dict):
                    fail(f"{name}[{i}]", f"expected an object, got {show(item)}")
            self.arrays[name] = value
        self.lights = []

    def obj(self, o, key, where, required=False):
        v = _value(o, key, where, required)
        if v is None:
            return None
        if not isinstance(v, dict):
            fail(at(where, key), f"expected an object, got {show(v)}")
        return v

    def integer(self, o, key, where, lo=0, hi=None, default=None, required=False):
        v = _value(o, key, where, required)
        if v is None:
            return default
        if not is_int(v):
            fail(at(where, key), f"expected an integer, got {show(v)}")
        if v < lo or (hi is not None and v > hi):
            rng = f"at least {lo}" if hi is None else f"from {lo} to {hi}"
            fail(at(where, key), f"{v} is out of range (it must be {rng})")
        return v

    def index(self, o, key, where, target, required=False):
        v = _value(o, key, where, required)
        if v is None:
            return None
        return self.ref(v, at(where, key), target)

    def ref(self, v, where, target):
        n = len(self.arrays[target]) if isinstance(target, str) else len(target[1])
        name = target if isinstance(target, str) else target[0]
        if not is_int(v):
            fail(where, f"expected an index into {name}, got {show(v)}")
        if not 0 <= v < n:
            fail(where, f"{v} is not an index into {name} ({n} entr{'y' if n == 1 else 'ies'})")
        return v

    def number(self, o, key, where, lo=None, hi=None, lo_open=False, hi_open=False, default=None,
               required=False):
        v = _value(o, key, where, required)
        if v is None:
            return default
        if not is_num(v):
            fail(at(where, key), f"expected a finite number, got {show(v)}")
        low_bad = lo is not None and (v <= lo if lo_open else v < lo)
        high_bad = hi is not None and (v >= hi if hi_open else v > hi)
        if low_bad or high_bad:
            left = "(" if lo_open else "["
            right = ")" if hi_open else "]"
            rng = (f"in {left}{lo:g}, {hi:g}{right}" if lo is not None and hi is not None
                   else f"{'>' if lo_open else '>='} {lo:g}" if lo is not None
                   else f"{'<' if hi_open else '<='} {hi:g}")
            fail(at(where, key), f"{v:g} is out of range (it must be {rng})")
        return v

    def numbers(self, o, key, where, n, lo=None, hi=None):
        v = o.get(key)
        if v is None:
            return None
        if not isinstance(v, list) or len(v) != n or not all(is_num(x) for x in v):
            fail(at(where, key), f"expected {n} finite numbers, got {show(v)}")
        if (lo is not None and min(v) < lo) or (hi is not None and max(v) > hi):
            fail(at(where, key), f"{show(v)} has a value outside [{lo:g}, {hi if hi is not None else math.inf:g}]")
        return v

    def string(self, o, key, where, choices=None, default=None):
        v = o.get(key)
        if v is None:
            return default
        if not isinstance(v, str):
            fail(at(where, key), f"expected a string, got {show(v)}")
        if choices is not None and v not in choices:
            fail(at(where, key), f"'{v}' is not one of {', '.join(choices)}")
        return v

    def boolean(self, o, key, where):
        v = o.get(key)
        if v is not None and not isinstance(v, bool):
            fail(at(where, key), f"expected true or false, got {show(v)}")
        return v

    def extension(self, o, where, name):
        ext = self.obj(o, "extensions", where)
        return self.obj(ext, name, at(where, "extensions")) if ext is not None else None


_CLASSES = {"accessors": "Accessor", "animations": "Animation", "buffers": "Buffer", "bufferViews": "BufferView",
            "cameras": "Camera", "images": "Image", "materials": "Material", "meshes": "Mesh", "nodes": "Node",
            "samplers": "Sampler", "scenes": "Scene", "skins": "Skin", "textures": "Texture"}


def decode_error(doc: dict, exc: Exception) -> GLTFError:
    """A :class:`GLTFError` naming the element that pygltflib failed to decode (it is strict
    about the types of properties the validation does not check, e.g. in animations)."""
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
