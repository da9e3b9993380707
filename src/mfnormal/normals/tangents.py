"""Vertex tangent frames (``tangents="vertex_tangent"``): the baker's per-vertex frame.

A normal map baked in MikkTSpace (glTF's convention) is decoded in the frame T, B = sign·(N×T),
N, with T the interpolated 3-float mesh attribute ``NAME`` and sign the 1-float attribute
``NAME_sign`` (glTF's ``TANGENT.w``). :func:`~mfnormal.surface.shading.from_tangent_frame`
turns ω_p from it into the base shading frame; :func:`mfnormal.normals.mikktspace.mikktspace`
computes the attributes for a mesh (``mfnormal.io.gltf.load_gltf`` adds them).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi


class VertexTangents:
    """The vertex tangent attribute ``name`` (and ``name + "_sign"``) of the shape at a hit."""

    def __init__(self, name: str):
        self.name = name

    def lookup(self, si, active):
        """(T, sign) of the vertex tangent frame at ``si`` (world space), (None, None) where a scalar
        variant's shape has no such attribute (JIT variants: T = 0 there, which from_tangent_frame and
        tangent_rotation treat as missing)."""
        name, shape = self.name, si.shape
        if not dr.is_jit_v(mi.Float) and (shape is None or not shape.is_mesh()
                                          or not shape.has_attribute(name)):
            return None, None
        tangent = mi.Vector3f(shape.eval_attribute_3(name, si, active))
        sign = shape.eval_attribute_1(name + "_sign", si, active) if (
            dr.is_jit_v(mi.Float) or shape.has_attribute(name + "_sign")) else 1.0
        return tangent, sign
