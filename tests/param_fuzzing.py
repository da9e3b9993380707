"""Wrong and valid values for every typed parameter of every plugin the project registers, and the
ways to give them: ``mi.load_dict``, an XML scene, and ``mi.traverse`` updates
(``tests/test_typed_params.py``).

Each parameter (``PARAMS`` of :mod:`mfnormal.plugins.normalmap_microfacet`, ``mfnormal_path`` and
``mfnormal_prb``) is a :mod:`mfnormal.models.properties` spec; which values are wrong is decided here,
by the spec's kind and range, not by asking the spec: a boolean takes only ``True``/``False``, an
integer no float, bool, string or value outside [lo, hi], a number no bool, string, NaN, ±inf or
value below lo, a choice no other string. The contract of every wrong value: the plugin is not
made, and the error's last line is one ``ValueError: PLUGIN: ...`` line that names the parameter.
"""

from __future__ import annotations

import math
from xml.sax.saxutils import quoteattr

import mitsuba as mi
import numpy as np

from mfnormal.models import properties as P
from mfnormal.plugins import mfnormal_path, mfnormal_prb, normalmap_microfacet

PLUGINS = {"normalmap_microfacet": normalmap_microfacet.PARAMS, "mfnormal_path": mfnormal_path.PARAMS,
           "mfnormal_prb": mfnormal_prb.PARAMS}
#: What every parameter receives whatever its kind: another type, or a string that reads as a value.
JUNK = ["abc", "", "1", "nan", "true", "false", "no", [1.0, 2.0, 3.0]]


def params(plugin: str) -> dict:
    return {p.name: p for p in PLUGINS[plugin]}


def wrong_values(param) -> list:
    """Values ``param`` must refuse, by its kind and range."""
    if isinstance(param, P.Boolean):
        return JUNK + [0, 1, 0.0, 1.0, math.nan]
    if isinstance(param, P.Integer):
        return JUNK + [param.lo - 1, param.hi + 1, 2 ** 40, -2 ** 40, 1.5, float(param.lo), math.nan, math.inf,
                       True, False]
    if isinstance(param, P.Number):
        below = [param.lo - 1.0, param.lo - 1e-3] if math.isfinite(param.lo) else []
        return JUNK + ["1.5"] + below + [math.nan, math.inf, -math.inf, True, False]
    if isinstance(param, P.Choice):
        return JUNK + [c.upper() for c in param.choices] + [param.choices[0] + " ", 0, 1.5, True]
    assert isinstance(param, P.Text), param
    if param.name == "tangents":
        return ["tangent", "", "Mitsuba", "vertex", 5, 1.5, True, [1.0, 2.0, 3.0]]
    return ["", 5, 1.5, True, False, math.nan, [1.0, 2.0, 3.0]]         # a map's file name


def wrong_updates(param) -> list:
    """The numbers among ``param``'s wrong values that an ``mi.traverse`` update must refuse too (a
    whole float is an integer there: the exposed array is a float one)."""
    numbers = [v for v in wrong_values(param) if isinstance(v, (int, float)) and not isinstance(v, bool)]
    if isinstance(param, P.Integer):
        numbers = [v for v in numbers if not (float(v).is_integer() and param.lo <= v <= param.hi)]
    return numbers


def valid_values(param) -> list:
    """Values ``param`` must take (a map's file name: none here, it needs a file)."""
    if isinstance(param, P.Boolean):
        return [True, False]
    if isinstance(param, P.Integer):
        return [param.lo, param.lo + 1, param.hi, 8]
    if isinstance(param, P.Number):
        lo = param.lo if math.isfinite(param.lo) else -3.5
        return [lo, int(lo) + 2, lo + 0.25, 1e6]
    if isinstance(param, P.Choice):
        return list(param.choices)
    return ["mitsuba", "vertex_tangent"] if param.name == "tangents" else []


# -- The plugins, given as a dict and as XML ------------------------------------------------------

MAP = np.full((4, 4, 3), 0.5, np.float32)
MAP[1, 2] = (0.7, 0.4, 0.9)
NESTED = {"type": "diffuse"}


def base_model(values: dict) -> str:
    """The model a BSDF with ``values`` is loaded with unless they give one: ``separable`` (its
    walk parameters are in effect), ``faithful`` for a ``filter`` (which needs it)."""
    return "faithful" if values.get("filter", "none") != "none" else "separable"


def plugin_dict(plugin: str, values: dict) -> dict:
    """``plugin`` with ``values``: the BSDF around a diffuse BSDF with a 4×4 normal map (model
    :func:`base_model` unless given), an integrator alone."""
    if plugin == "normalmap_microfacet":
        base = {"model": base_model(values), "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(MAP), "raw": True},
                "bsdf": NESTED}
        return {"type": plugin, **base, **values}
    return {"type": plugin, **values}


def xml_property(name: str, value) -> str:
    """The XML element that gives ``name`` the Python ``value`` (its tag by its type)."""
    if isinstance(value, bool):
        return f'<boolean name="{name}" value="{str(value).lower()}"/>'
    if isinstance(value, int):
        return f'<integer name="{name}" value="{value}"/>'
    if isinstance(value, float):
        return f'<float name="{name}" value="{value!r}"/>'
    if isinstance(value, str):
        return f'<string name="{name}" value={quoteattr(value)}/>'
    x, y, z = value
    return f'<vector name="{name}" x="{x}" y="{y}" z="{z}"/>'


def plugin_xml(plugin: str, values: dict, map_file) -> str:
    """A scene holding ``plugin`` with ``values`` (the BSDF's normal map: the file ``map_file``)."""
    props = "".join(xml_property(k, v) for k, v in values.items())
    if plugin == "normalmap_microfacet":
        model = "" if "model" in values else f'<string name="model" value="{base_model(values)}"/>'
        texture = ("" if "normalmap" in values else
                   f'<texture type="bitmap" name="normalmap"><string name="filename" value="{map_file}"/>'
                   '<boolean name="raw" value="true"/></texture>')
        body = f'<bsdf type="{plugin}">{model}{props}{texture}<bsdf type="diffuse"/></bsdf>'
    else:
        body = f'<integrator type="{plugin}">{props}</integrator>'
    return f'<scene version="3.0.0">{body}</scene>'


def write_map(folder):
    path = folder / "normalmap.exr"
    mi.Bitmap(MAP).write(str(path))
    return path


def refusal(load) -> str | None:
    """The last line of the error that ``load()`` raises (None: it loaded)."""
    try:
        load()
    except Exception as e:               # Mitsuba wraps the plugin's ValueError in a RuntimeError
        text = str(e).strip()
        return text.splitlines()[-1] if text else type(e).__name__
    return None


def assert_names(line: str | None, plugin: str, names) -> str:
    """``line`` is the plugin's one-line ValueError about one of ``names``: the parameter, and
    what it expects or that the value is unknown. Returns the name."""
    assert line is not None, f"{plugin} took a wrong value of {sorted(names)}"
    prefix = f"ValueError: {plugin}: "
    assert line.startswith(prefix), line
    rest = line[len(prefix):]
    named = [n for n in names if rest.startswith((f"{n} must be ", f"unknown {n} '"))]
    assert named, f"{line!r} names none of {sorted(names)}"
    assert "got " in rest or rest.startswith("unknown "), line
    return named[0]
