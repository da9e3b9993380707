"""Ray origins on the smooth surface of smooth-shaded meshes (the shadow terminator fix of
Hanika, "Hacking the shadow terminator", Ray Tracing Gems II, 2021), shared by the integrators.

On a triangle whose vertex normals differ from its face normal, a ray toward a direction below
the triangle's plane but above the interpolated normal's horizon starts on the flat triangle and
is blocked by the mesh itself: the lit region ends in the stair-stepped line of the triangle
edges. The rays start instead from the smooth surface the vertex normals describe: the hit point
projected onto each vertex's tangent plane (only ever outward, along that vertex's normal), the
three projections interpolated with the hit's barycentrics. The displacement is detached: it
moves where rays start, not what is differentiated.

The tangent planes describe a surface near the triangle only where the vertex normals are near
its face normal. A triangle with a vertex normal more than 60° off it (``COS_SMOOTH_MIN``), or
with vertex normals on both sides of it (odd normals: random, swapped, nearly in the plane), keeps
the flat triangle: its projections would move the origin across the triangle, or below its plane. So
a shifted origin is always above the plane, on the side of the vertex normals.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: The largest angle between a vertex normal and the face normal of a triangle that is shifted:
#: 60°, a smooth-shaded triangular prism's (the coarsest ordinary smooth mesh; a cube's is 54.7°).
COS_SMOOTH_MIN = 0.5


def applies(scene) -> bool:
    """Whether ``scene`` has a shape the offset can move (a mesh with vertex normals): elsewhere
    every shift is 0 and the integrators skip its per-vertex lookup."""
    return any(shape.is_mesh() and shape.has_vertex_normals() for shape in scene.shapes())


def smooth_shift(si, prim_uv, active=True):
    """The detached displacement from ``si.p`` to the smooth surface point (0 where ``si`` is not
    on a mesh with vertex normals, where the point is not on the outer side of the interpolated
    normal, and where it is closer than the spawn offset: flat triangles stay bit for bit)."""
    si, prim_uv = dr.detach(si), dr.detach(prim_uv)
    active = mi.Bool(active) & si.is_valid() & si.shape.is_mesh()
    mesh = mi.MeshPtr(dr.select(active, si.shape, dr.zeros(mi.ShapePtr)))
    shift = dr.dispatch(mesh, _tangent_plane_shift, si.prim_index, prim_uv, si.p)
    height = dr.dot(shift, si.sh_frame.n)
    active &= dr.isfinite(height) & (height > (1.0 + dr.max(dr.abs(si.p))) * mi.math.RayEpsilon)
    return mi.Vector3f(dr.select(active, shift, 0.0))


def _tangent_plane_shift(mesh, prim_index, prim_uv, p):
    """On one shape of the scene: p projected onto each vertex's tangent plane (outward only),
    the projections interpolated with the barycentrics, minus p (0 on a mesh without vertex
    normals, on other shapes, and on a triangle with odd vertex normals: module docstring)."""
    shift = mi.Vector3f(0.0)
    if not (mesh.is_mesh() and mesh.has_vertex_normals()):     # the registry holds every shape
        return shift
    face = mesh.face_indices(prim_index)
    weights = (1.0 - prim_uv.x - prim_uv.y, prim_uv.x, prim_uv.y)
    v = [mesh.vertex_position(index) for index in (face.x, face.y, face.z)]
    n = [mi.Vector3f(dr.normalize(mesh.vertex_normal(index))) for index in (face.x, face.y, face.z)]
    for k in range(3):
        shift -= weights[k] * dr.minimum(dr.dot(p - v[k], n[k]), 0.0) * n[k]
    return dr.select(_smooth(v, n), shift, 0.0)


def _smooth(v, n):
    """Whether the triangle's vertex normals ``n`` are all within 60° of its face
    normal, on one side of it (False for a degenerate triangle)."""
    face_n = dr.normalize(dr.cross(v[1] - v[0], v[2] - v[0]))
    cos = [dr.dot(face_n, nk) for nk in n]
    above = (cos[0] >= COS_SMOOTH_MIN) & (cos[1] >= COS_SMOOTH_MIN) & (cos[2] >= COS_SMOOTH_MIN)
    below = (cos[0] <= -COS_SMOOTH_MIN) & (cos[1] <= -COS_SMOOTH_MIN) & (cos[2] <= -COS_SMOOTH_MIN)
    return above | below


def moved(si, shift):
    """A copy of ``si`` at ``si.p + shift``."""
    out = mi.SurfaceInteraction3f(si)
    out.p = si.p + shift
    return out


def outward(si, shift, d):
    """``shift`` for a ray leaving toward world direction ``d`` on the side of the interpolated
    normal (where the smooth surface is), 0 for one leaving to the other side."""
    return mi.Vector3f(dr.select(dr.dot(d, si.sh_frame.n) > 0.0, shift, 0.0))


def sample_emitter(scene, si, shift, sample, active):
    """``scene.sample_emitter_direction`` from ``si.p + shift`` with its shadow ray: the emitter
    sample and its weight, 0 where the shadow ray, started on the side the light is on, is
    blocked."""
    ds, weight = scene.sample_emitter_direction(moved(si, shift), sample, False, active)
    origin = moved(si, outward(si, shift, ds.d))
    blocked = scene.ray_test(origin.spawn_ray_to(ds.p), active)
    return ds, dr.select(blocked, 0.0, weight)
