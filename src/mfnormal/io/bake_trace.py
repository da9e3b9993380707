"""Tracing the high-poly from the low-poly's texels: the nearest surface along ±N within the cage.

:func:`high_surface_at` finds, for points p with normals N, the high-poly surface nearest to p on
the segment p ± cage·N with Mitsuba's ray tracer (a scene holding only the high-poly mesh; a
ray from p each way along N), and gives its normal (shading, or geometric) and its signed
distance along N. :func:`trace_passes` does it for the covered texels of a map,
``Batches.trace`` texels at a time, and writes the normals in each texel's tangent frame.
Meshes whose size (the low-poly's bounding-box diagonal) lies outside WORKING_SIZE are traced
scaled by a power of two into it (:func:`working_scale`, :func:`scaled_mesh`: exact in floating
point; single-precision ray tracing loses normals of tiny triangles).
"""

from __future__ import annotations

import math
import warnings

import numpy as np

from mfnormal.io.bake_inputs import BakeError
from mfnormal.io.bake_texels import owned_barycentrics, texel_frames, unit_vectors
from mfnormal.io.meshes import mesh_arrays, mitsuba_mesh
from mfnormal.normals.mikktspace import mikktspace

#: The default cage distance as a fraction of the low-poly's bounding-box diagonal.
CAGE_FRACTION = 0.05
#: The rays along ±N start this fraction of the cage behind the low-poly's surface point.
RAY_START = 1e-3
#: The low-poly sizes (bounding-box diagonal) traced as they are; others are scaled by a power
#: of two into this range (single-precision normals of tiny triangles underflow).
WORKING_SIZE = (2.0 ** -7, 2.0 ** 17)


# -- The working scale -----------------------------------------------------------------------------

def default_cage(positions) -> float:
    """CAGE_FRACTION of the bounding-box diagonal of ``positions``."""
    return CAGE_FRACTION * diagonal(positions)


def diagonal(positions) -> float:
    """The length of the bounding-box diagonal of ``positions`` (N, 3)."""
    return float(np.linalg.norm(positions.max(axis=0) - positions.min(axis=0)))


def working_scale(size: float) -> float:
    """1, or the power of two that brings a low-poly of ``size`` into WORKING_SIZE."""
    if WORKING_SIZE[0] <= size <= WORKING_SIZE[1]:
        return 1.0
    return 2.0 ** -round(math.log2(size))


def scaled_mesh(mesh, scale: float):
    """A copy of the Mitsuba mesh ``mesh`` scaled by ``scale`` (a power of two: exact), its
    vertex normals as :func:`scaled_arrays` gives them."""
    import mitsuba as mi

    if scale == 1.0:
        return mesh
    if not isinstance(mesh, mi.Mesh):
        raise BakeError(f"the low-poly mesh is about {1 / scale:g} units across, too far from 1 to "
                        f"trace a {mesh.class_name()} shape beside it; give the high-poly as a "
                        "mesh, or scale both")
    positions, normals, _, faces = mesh_arrays(mesh)
    return mitsuba_mesh("mesh", None, *scaled_arrays(positions, normals, faces, scale), None, None, faces)


def scaled_arrays(positions, normals, faces, scale: float):
    """(positions·scale, vertex normals): the normals as they are, or recomputed by Mitsuba at
    the working scale where its loader could not compute them at the mesh's own (single-
    precision cross products of tiny triangles underflow, and it gives the vertex (1, 0, 0))."""
    positions = positions * scale
    if normals is not None and _fallback_normals(positions, normals, faces):
        mesh = mitsuba_mesh("mesh", None, positions, np.zeros_like(positions), None, None, faces)
        mesh.recompute_vertex_normals()
        normals = mesh_arrays(mesh)[1]
    return positions, normals


def _fallback_normals(positions, normals, faces) -> bool:
    """Whether a vertex normal is Mitsuba's fallback (1, 0, 0) where the triangles around the
    vertex (in double precision) face elsewhere."""
    corners = positions[faces]
    face_normals = unit_vectors(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]))
    around = np.zeros_like(positions)
    for k in range(3):
        np.add.at(around, faces[:, k], face_normals)
    fallback = np.all(normals == [1.0, 0.0, 0.0], axis=1)
    return bool(np.any(fallback & (unit_vectors(around)[:, 0] < 0.9)))


# -- Tracing the high-poly ---------------------------------------------------------------------

def _trace(scene, origins, directions, maxt: float, geometric: bool):
    """(t, normal, hit) of rays into ``scene``: numpy in, numpy out."""
    import drjit as dr
    import mitsuba as mi

    ray = mi.Ray3f(mi.Point3f(*(mi.Float(np.ascontiguousarray(c, np.float32)) for c in origins.T)),
                   mi.Vector3f(*(mi.Float(np.ascontiguousarray(c, np.float32)) for c in directions.T)))
    ray.maxt = mi.Float(maxt)
    si = scene.ray_intersect(ray)
    normal = si.n if geometric else si.sh_frame.n
    dr.eval(si.t, normal)
    hit = np.array(si.is_valid(), bool)
    return np.array(si.t, np.float64), np.array(normal, np.float64).reshape(3, -1).T, hit


def high_surface_at(high, p, n, cage: float, geometric: bool = False):
    """The high-poly's unit normal at the surface point nearest to ``p`` on the segment
    p ± cage·``n``, (K, 3), that point's signed distance from p along ``n``, (K,), and whether
    there is one, (K,); ``high`` is the high-poly mesh, or a scene that holds only it (built once
    for many calls).

    Two rays leave p, one along +n and one along −n, each from RAY_START·cage behind p (so that
    a surface through p itself is met, not skipped) up to cage beyond it; each meets the first
    surface on its side, and the one nearer to p wins. A hit whose normal or distance is not
    finite (a degenerate triangle) counts as none."""
    import mitsuba as mi

    scene = high if isinstance(high, mi.Scene) else mi.load_dict({"type": "scene", "high": high})
    eps = RAY_START * cage
    t_up, n_up, hit_up = _trace(scene, p - eps * n, n, cage + eps, geometric)
    t_down, n_down, hit_down = _trace(scene, p + eps * n, -n, cage + eps, geometric)
    hit_up &= np.isfinite(n_up).all(axis=1) & np.isfinite(t_up)
    hit_down &= np.isfinite(n_down).all(axis=1) & np.isfinite(t_down)
    use_up = hit_up & (~hit_down | (np.abs(t_up - eps) <= np.abs(t_down - eps)))
    normal = np.where(use_up[:, None], n_up, n_down)
    hit = hit_up | hit_down
    distance = np.where(hit, np.where(use_up, t_up - eps, eps - t_down), 0.0)
    return unit_vectors(normal), distance, hit


def trace_passes(scene, low_arrays, owner, size, frame, cage, geometric, progress, per_pass):
    """The covered texels' tangent-space normals (size², 3), heights along the low-poly's normal
    (size², 1; at the working scale) and hits (size²,), traced ``per_pass`` texels at a time; a
    warning where most face away from the low-poly's normal."""
    positions, normals, uvs, faces = low_arrays
    corner = mikktspace(positions, normals, uvs, faces, flip_v=True) if frame == "mikktspace" else None
    covered = owner >= 0
    normals_out = np.zeros((size * size, 3))
    normals_out[:, 2] = 1.0
    heights = np.zeros((size * size, 1))
    hits = np.zeros(size * size, bool)
    facing_away = 0
    for first in range(0, size * size, per_pass):
        texel = first + np.flatnonzero(covered[first:first + per_pass])
        tri = owner[texel].astype(np.int64)
        bary = owned_barycentrics(uvs, faces, size, texel, tri)
        p, tangent, bitangent, n = texel_frames(low_arrays, tri, bary, frame, corner)
        normal, distance, hit = high_surface_at(scene, p, n, cage, geometric)
        local = np.stack([np.sum(normal * v, axis=1) for v in (tangent, bitangent, n)], axis=1)
        normals_out[texel[hit]] = local[hit]
        heights[texel[hit], 0] = distance[hit]
        hits[texel[hit]] = True
        facing_away += int(np.count_nonzero(local[hit, 2] < 0))
        if progress is not None:
            progress(min(first + per_pass, size * size), size * size)
    hit_count = int(hits.sum())
    if facing_away > hit_count / 2:
        warnings.warn(f"{facing_away} of {hit_count} baked texels face away from the low-poly's "
                      "normal (z < 0): the low-poly's and the high-poly's normals point opposite "
                      "ways; flip the normals of one of them", stacklevel=3)
    return normals_out, heights, hits
