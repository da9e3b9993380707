"""The normal source of a plugin, from its parameters: the map, the frame it is decoded in, and
the macro normal (the package docstring). Every source offers :class:`NormalSource`."""

from __future__ import annotations

from typing import Protocol, runtime_checkable

import mitsuba as mi

from mfnormal.models.properties import Choice, Number, Text
from mfnormal.normals.height_map import HeightMap
from mfnormal.normals.macro import MACRO_NORMALS, macro_normal
from mfnormal.normals.normal_map import CONVENTIONS, NormalMap
from mfnormal.normals.strength import Strength, fail
from mfnormal.normals.tangents import VertexTangents

MITSUBA_TANGENTS = "mitsuba"

# The normal source's parameters (mfnormal.models.properties; ``strength``: normals/strength.py).
PLUGIN = "normalmap_microfacet"
MACRO_NORMAL = Choice(PLUGIN, "macro_normal", "shading", MACRO_NORMALS)
CONVENTION = Choice(PLUGIN, "normalmap_convention", "opengl", CONVENTIONS)
HEIGHT_SCALE = Number(PLUGIN, "height_scale", 1.0, "a finite number")
TANGENTS = Text(PLUGIN, "tangents", MITSUBA_TANGENTS,
                f"'{MITSUBA_TANGENTS}' or a vertex attribute name such as 'vertex_tangent'",
                lambda name: name == MITSUBA_TANGENTS or name.startswith("vertex_"))
#: ``filter``: what a lookup reads where the pixel's footprint covers many texels (``none``: the texel
#: at the footprint's centre; ``lean``: the footprint's mean facet and slope spread, normals/normal_map.py).
FILTERS = ("none", "lean")
FILTER = Choice(PLUGIN, "filter", "none", FILTERS)
#: A map given by name instead of as a texture: its file (loaded raw).
MAP_FILES = {name: Text(PLUGIN, name, None, "a texture (a raw bitmap) or a file name", lambda f: f != "")
             for name in ("normalmap", "heightmap")}


@runtime_checkable
class NormalSource(Protocol):
    """What every source of ω_p offers the plugin and the models: :class:`~mfnormal.normals.normal_map.NormalMap`,
    :class:`~mfnormal.normals.height_map.HeightMap` and :class:`Flat`. None knows the plugin."""

    texture: mi.Texture | None                  # the map (a plugin parameter), None without one
    tangents: VertexTangents | None             # the vertex tangent frame it is decoded in, None: si.sh_frame

    def facet_normal(self, si, active, nudge=None) -> tuple:
        """(ω_p in si.sh_frame, the map frame's tangent_rotation or None, whether ω_p carries
        derivatives); ``nudge``: a nudged ω_p, for a flat normal's derivatives."""

    def flat_texels(self) -> bool:
        """Whether the map may decode to the flat normal somewhere (docs/model.md §9)."""

    def slopes(self, attached=False) -> tuple:
        """((σ1, σ2, φ_e), the same as Dr.Jit values that carry derivatives or None): the map's
        principal rms slopes, for the faithful model."""

    def walls(self, attached=False) -> tuple:
        """((ψ_w, w_x, w_y), the same as Dr.Jit values that carry derivatives or None): the share of
        the map's relief that is walls and their mean slope in its tangent frame (neighbourhood.walls),
        for the faithful model."""

    def local(self, width: float, attached=False) -> tuple | None:
        """The faithful model's local statistics of a window ``width`` texels wide, or None: the
        map's slopes hold for every texel (docs/faithful.md §5)."""

    def parameters_changed(self, keys) -> None:
        """The plugin's parameters ``keys`` changed (``mi.traverse``)."""

    def describe(self) -> str:
        """The source's lines of the plugin's ``to_string``."""


class Flat:
    """No map: ω_p is the shading normal itself (``macro_normal="geometric"`` without a map)."""

    texture = None
    tangents = None

    def facet_normal(self, si, active, nudge=None):
        return mi.Vector3f(0.0, 0.0, 1.0), None, False

    def flat_texels(self) -> bool:
        return False

    def slopes(self, attached=False):
        return (0.0, 0.0, 0.0), None

    def walls(self, attached=False):
        return (0.0, 0.0, 0.0), None

    def local(self, width: float, attached=False):
        return None

    def parameters_changed(self, keys):
        pass

    def describe(self) -> str:
        return "  normalmap=None,\n"


def _textures(props):
    """(nested BSDF, normal map, height map) among the plugin's objects and strings."""
    nested = normalmap = heightmap = None
    for name, obj in props.objects():
        if isinstance(obj, mi.BSDF) and name in ("normalmap", "heightmap"):
            fail(f"'{name}' is a BSDF ({obj.class_name()}); it must be a texture: a raw bitmap "
                 f"(<texture name=\"{name}\" type=\"bitmap\"> with <boolean name=\"raw\" "
                 "value=\"true\"/>) or a file name")
        if isinstance(obj, mi.BSDF):
            if nested is not None:
                fail("expects exactly one nested BSDF, got several")
            nested = obj
        elif isinstance(obj, mi.Texture) and name == "normalmap":
            normalmap = obj
        elif isinstance(obj, mi.Texture) and name == "heightmap":
            heightmap = obj
    if normalmap is None:
        normalmap = _map_file(props, "normalmap")
    if heightmap is None:
        heightmap = _map_file(props, "heightmap")
    if nested is None:
        fail("needs a nested BSDF (e.g. <bsdf type=\"diffuse\"/> inside it)")
    return nested, normalmap, heightmap


def _map_file(props, name):
    """The raw bitmap of the file that the string parameter ``name`` names, or None."""
    filename = MAP_FILES[name].read(props)
    return None if filename is None else mi.load_dict({"type": "bitmap", "filename": filename, "raw": True})


def from_properties(props) -> tuple:
    """(nested BSDF, :class:`NormalSource`, macro normal, strength) of a ``normalmap_microfacet``'s
    properties, each checked (ValueError with a one-line message naming the fix)."""
    if mi.is_polarized:
        fail(f"does not support polarized variants ({mi.variant()}); use an rgb, mono or spectral "
             "one (e.g. llvm_ad_rgb)")
    nested, normalmap, heightmap = _textures(props)
    macro = MACRO_NORMAL.read(props)
    if normalmap is not None and heightmap is not None:
        fail("takes a 'normalmap' or a 'heightmap', not both")
    if normalmap is None and heightmap is None and macro != "geometric":
        fail("needs a texture named 'normalmap' (a raw bitmap: <texture name=\"normalmap\" "
             "type=\"bitmap\"> with <boolean name=\"raw\" value=\"true\"/>) or 'heightmap' "
             "(or macro_normal=\"geometric\" for a smooth-shaded mesh without a map)")
    height_scale = HEIGHT_SCALE.read(props)
    convention = CONVENTION.read(props)
    if convention != "opengl" and normalmap is None:
        fail("normalmap_convention applies to normal maps only (a height map has no channel order)")
    strength, tangents = Strength(props), TANGENTS.read(props)
    if heightmap is not None:
        source = HeightMap(heightmap, height_scale, strength, _frame(tangents))
    elif normalmap is not None:
        source = NormalMap(normalmap, strength, convention == "directx", _frame(tangents))
    else:
        source = Flat()
    return nested, source, macro_normal(macro), strength


def _frame(tangents: str):
    """The vertex tangent frame named by ``tangents``, or None for Mitsuba's shading frame."""
    return None if tangents == MITSUBA_TANGENTS else VertexTangents(tangents)
