"""The normal source of a plugin, from its parameters: the map, the frame it is decoded in, and
the macro normal (the package docstring)."""

from __future__ import annotations

import mitsuba as mi

from mfnormal.normals.height_map import HeightMap
from mfnormal.normals.macro import MACRO_NORMALS, macro_normal
from mfnormal.normals.normal_map import CONVENTIONS, NormalMap
from mfnormal.normals.strength import Strength, fail
from mfnormal.normals.tangents import VertexTangents

MITSUBA_TANGENTS = "mitsuba"


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
    if normalmap is None and isinstance(props.get("normalmap", None), str):
        normalmap = mi.load_dict({"type": "bitmap", "filename": props["normalmap"], "raw": True})
    if heightmap is None and isinstance(props.get("heightmap", None), str):
        heightmap = mi.load_dict({"type": "bitmap", "filename": props["heightmap"], "raw": True})
    if nested is None:
        fail("needs a nested BSDF (e.g. <bsdf type=\"diffuse\"/> inside it)")
    return nested, normalmap, heightmap


def from_properties(props):
    """(nested BSDF, source, macro normal, strength) of a ``normalmap_microfacet``'s properties,
    each checked (ValueError with a one-line message naming the fix)."""
    if mi.is_polarized:
        fail(f"does not support polarized variants ({mi.variant()}); use an rgb, mono or spectral "
             "one (e.g. llvm_ad_rgb)")
    nested, normalmap, heightmap = _textures(props)
    macro = props.get("macro_normal", "shading")
    if macro not in MACRO_NORMALS:
        fail(f"unknown macro_normal '{macro}'; use 'shading' or 'geometric'")
    if normalmap is not None and heightmap is not None:
        fail("takes a 'normalmap' or a 'heightmap', not both")
    if normalmap is None and heightmap is None and macro != "geometric":
        fail("needs a texture named 'normalmap' (a raw bitmap: <texture name=\"normalmap\" "
             "type=\"bitmap\"> with <boolean name=\"raw\" value=\"true\"/>) or 'heightmap' "
             "(or macro_normal=\"geometric\" for a smooth-shaded mesh without a map)")
    height_scale = float(props.get("height_scale", 1.0))
    convention = props.get("normalmap_convention", "opengl")
    if convention not in CONVENTIONS:
        fail(f"unknown normalmap_convention '{convention}'; use 'opengl' or 'directx'")
    if convention != "opengl" and normalmap is None:
        fail("normalmap_convention applies to normal maps only (a height map has no channel order)")
    strength, tangents = Strength(props.get("strength", 1.0)), _tangents(props)
    if heightmap is not None:
        source = HeightMap(heightmap, height_scale, strength, tangents)
    elif normalmap is not None:
        source = NormalMap(normalmap, strength, convention == "directx", tangents)
    else:
        source = Flat()
    return nested, source, macro_normal(macro), strength


def _tangents(props):
    """The vertex tangent frame named by ``tangents``, or None for Mitsuba's shading frame."""
    tangents = props.get("tangents", MITSUBA_TANGENTS)
    if tangents != MITSUBA_TANGENTS and not tangents.startswith("vertex_"):
        fail(f"tangents must be '{MITSUBA_TANGENTS}' or a vertex attribute name such as "
             f"'vertex_tangent', got '{tangents}'")
    return None if tangents == MITSUBA_TANGENTS else VertexTangents(tangents)
