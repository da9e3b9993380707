"""MikkTSpace tangent frames in numpy: the frames normal-map bakers (Blender, Substance,
xNormal, glTF exporters) use, so that a baked map decodes the way it was baked.

This follows Morten Mikkelsen's reference implementation (``mikktspace.c``,
``genTangSpaceDefault``: no angular threshold) step by step:

1. weld corners whose position, normal and texture coordinates are equal;
2. per triangle, the unit direction of ∂p/∂u (``vOs``, eq. 18 of Mikkelsen's
   thesis) and the orientation: whether the UV map preserves the triangle's
   winding (the sign of its signed UV area);
3. group the corners around each vertex: two triangles that share an edge
   through the vertex (with consistent winding) and the same orientation are in
   one group, so mirrored UV islands and UV seams get their own frames;
4. per group, the sum of the triangles' ∂p/∂u projected onto the vertex normal,
   weighted by the triangles' corner angles, normalised; the sign (glTF's
   ``TANGENT.w``) is +1 for orientation-preserving groups, −1 otherwise, and
   the bitangent is B = sign·(N×T).

Triangles of zero UV area ("group with any") take the orientation of their
first well-formed neighbour and contribute nothing to the sums; corners of
triangles with two identical welded vertices copy the frame of another corner
of that vertex (Mikkelsen's ``DegenEpilogue``). Both are simplifications of the
reference's order-dependent handling, which only matters on such degenerate
triangles. The test suite compares the result with the reference C code
(``pymikktspace``) on a multi-chart mesh.

The UV convention matters: MikkTSpace's bitangent follows +v of the UVs it is
given, and normal maps store +Y (green) towards the image's top. glTF's v grows
downwards in the image, so glTF tangents are those of (u, 1 − v);
:func:`mikktspace` takes ``flip_v`` for that.
"""

from __future__ import annotations

import numpy as np

__all__ = ["mikktspace", "split_vertices"]

_FLT_MIN = np.finfo(np.float32).tiny


def _normalize(v, eps=_FLT_MIN):
    """v / |v| along the last axis; vectors of length ≤ eps stay as they are (MikkTSpace's VNotZero)."""
    length = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(length > eps, v / np.where(length > eps, length, 1.0), v)


def _weld(positions, normals, uvs, faces):
    """Welded vertex index per corner, (F, 3): equal position, normal and uv → one index."""
    corners = np.concatenate([positions[faces], normals[faces], uvs[faces]], axis=-1)
    corners = corners.reshape(-1, 8).astype(np.float32) + np.float32(0.0)   # −0.0 → +0.0, as C's ==
    _, inverse = np.unique(corners, axis=0, return_inverse=True)
    return inverse.reshape(-1, 3)


def _neighbours(welded):
    """Triangle across each edge, (F, 3) (−1 for none): edge i runs from corner i to i+1.

    Like ``BuildNeighborsFast``: edges are paired with an edge of opposite
    direction (consistent winding), greedily in the order (min, max, triangle).
    """
    n_tri = welded.shape[0]
    a = welded.ravel()
    b = welded[:, [1, 2, 0]].ravel()
    tri = np.repeat(np.arange(n_tri), 3)
    lo, hi = np.minimum(a, b), np.maximum(a, b)
    order = np.lexsort((tri, hi, lo))
    neighbours = np.full(3 * n_tri, -1, dtype=np.int64)
    lo_s, hi_s = lo[order], hi[order]
    run_start = np.flatnonzero(np.r_[True, (lo_s[1:] != lo_s[:-1]) | (hi_s[1:] != hi_s[:-1])])
    run_len = np.diff(np.r_[run_start, len(order)])
    # The common case: a manifold edge, two triangles with opposite directions.
    pairs = run_start[run_len == 2]
    e0, e1 = order[pairs], order[pairs + 1]
    ok = (a[e0] == b[e1]) & (b[e0] == a[e1]) & (a[e0] != b[e0])
    neighbours[e0[ok]] = tri[e1[ok]]
    neighbours[e1[ok]] = tri[e0[ok]]
    # Non-manifold edges: pair each unpaired edge with the next unpaired opposite one.
    for start, length in zip(run_start[run_len > 2], run_len[run_len > 2]):
        edges = order[start:start + length]
        for i, ei in enumerate(edges):
            if neighbours[ei] >= 0 or a[ei] == b[ei]:
                continue
            for ej in edges[i + 1:]:
                if neighbours[ej] < 0 and a[ej] == b[ei] and b[ej] == a[ei]:
                    neighbours[ei], neighbours[ej] = tri[ej], tri[ei]
                    break
    return neighbours.reshape(n_tri, 3)


def _components(n, links):
    """Connected components of ``n`` nodes joined by ``links`` (k, 2): a root label per node."""
    parent = np.arange(n)
    if len(links) == 0:
        return parent
    u, v = links[:, 0], links[:, 1]
    while True:
        pu, pv = parent[u], parent[v]
        if np.array_equal(pu, pv):
            return parent
        np.minimum.at(parent, np.maximum(pu, pv), np.minimum(pu, pv))
        while True:                                   # pointer jumping
            grand = parent[parent]
            if np.array_equal(grand, parent):
                break
            parent = grand


def _triangle_frames(p, t, welded):
    """Per triangle (InitTriInfo): unit ∂p/∂u times the orientation sign, the orientation
    (UV area > 0), whether the frame is usable, and whether the triangle is degenerate."""
    d1, d2 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    t21, t31 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    area = t21[:, 0] * t31[:, 1] - t21[:, 1] * t31[:, 0]
    v_os = t31[:, 1:2] * d1 - t21[:, 1:2] * d2
    v_ot = -t31[:, 0:1] * d1 + t21[:, 0:1] * d2
    orient = area > 0
    good_area = np.abs(area) > _FLT_MIN
    len_os, len_ot = np.linalg.norm(v_os, axis=-1), np.linalg.norm(v_ot, axis=-1)
    sign = np.where(orient, 1.0, -1.0)
    v_os = np.where((good_area & (len_os > _FLT_MIN))[:, None],
                    v_os * (sign / np.where(len_os > 0, len_os, 1.0))[:, None], 0.0)
    with np.errstate(divide="ignore", invalid="ignore"):
        mag_s, mag_t = len_os / np.abs(area), len_ot / np.abs(area)
    good = good_area & (mag_s > _FLT_MIN) & (mag_t > _FLT_MIN)
    degenerate = ((welded[:, 0] == welded[:, 1]) | (welded[:, 1] == welded[:, 2])
                  | (welded[:, 0] == welded[:, 2]))
    return v_os, orient, good & ~degenerate, degenerate


def _adopt_orientations(orient, good, degenerate, neighbours):
    """Zero-UV-area triangles take the orientation of a well-formed neighbour (in place)."""
    settled = good.copy()
    for _ in range(8):
        pending = np.flatnonzero(~settled & ~degenerate)
        if len(pending) == 0:
            break
        nb = neighbours[pending]
        has = (nb >= 0) & settled[np.maximum(nb, 0)]
        first = np.where(has.any(axis=1), nb[np.arange(len(pending)), np.argmax(has, axis=1)], -1)
        adopt = pending[first >= 0]
        orient[adopt] = orient[first[first >= 0]]
        settled[adopt] = True


def _corner_groups(welded, neighbours, orient):
    """A group label per corner (Build4RuleGroups): the corners around a vertex joined across
    shared edges of triangles of the same orientation."""
    n_tri = len(welded)
    f_idx = np.repeat(np.arange(n_tri), 3)
    i_idx = np.tile(np.arange(3), n_tri)
    g = neighbours.ravel()
    has = g >= 0
    f, i, g = f_idx[has], i_idx[has], g[has]
    same = orient[f] == orient[g]
    f, i, g = f[same], i[same], g[same]
    links = []
    for k in (i, (i + 1) % 3):                         # the edge's two end vertices
        vert = welded[f, k]
        j = np.argmax(welded[g] == vert[:, None], axis=1)
        links.append(np.stack([3 * f + k, 3 * g + j], axis=-1))
    return _components(3 * n_tri, np.concatenate(links))


def _group_tangents(p, n, v_os, good, labels):
    """Per corner (EvalTspace): the sum over its group of ∂p/∂u projected onto each corner's
    vertex normal, weighted by the corner angle; normalised."""
    def project(v):
        return _normalize(v - np.sum(n * v, axis=-1, keepdims=True) * n)

    os_c = project(np.broadcast_to(v_os[:, None, :], n.shape))
    e1 = project(p[:, [2, 0, 1]] - p)                 # to the previous corner
    e2 = project(p[:, [1, 2, 0]] - p)                 # to the next corner
    angle = np.arccos(np.clip(np.sum(e1 * e2, axis=-1), -1.0, 1.0))
    contrib = np.where(good[:, None, None], angle[..., None] * os_c, 0.0).reshape(-1, 3)
    sums = np.zeros((3 * len(p), 3))
    np.add.at(sums, labels, contrib)
    return _normalize(sums[labels])


def _copy_to_degenerate(result, welded, degenerate):
    """Degenerate triangles copy the frame of another corner of the same vertex
    (DegenEpilogue), in place."""
    donor_corner = np.full(welded.max() + 1, -1)
    ok = np.repeat(~degenerate, 3)
    donor_corner[welded.ravel()[ok][::-1]] = np.flatnonzero(ok)[::-1]
    bad = np.flatnonzero(~ok)
    donor = donor_corner[welded.ravel()[bad]]
    result[bad[donor >= 0]] = result[donor[donor >= 0]]


def mikktspace(positions, normals, uvs, faces, flip_v: bool = False):
    """MikkTSpace tangents per triangle corner: an (F, 3, 4) array of (T, sign).

    ``positions``, ``normals`` (unit) and ``uvs`` are per-vertex arrays (V, 3),
    (V, 3), (V, 2); ``faces`` (F, 3) indexes them. ``flip_v`` uses (u, 1 − v),
    for glTF's top-left UV origin. T is a unit vector orthogonal to the
    corner's normal (zero where it is undefined: a vertex whose triangles all
    have zero UV area); the bitangent is sign·(N×T).
    """
    positions = np.asarray(positions, dtype=np.float32)
    normals = np.asarray(normals, dtype=np.float32)
    uvs = np.asarray(uvs, dtype=np.float32)
    faces = np.asarray(faces, dtype=np.int64).reshape(-1, 3)
    if flip_v:
        uvs = np.stack([uvs[:, 0], np.float32(1.0) - uvs[:, 1]], axis=-1)
    n_tri = len(faces)
    welded = _weld(positions, normals, uvs, faces)
    p = positions[faces].astype(np.float64)
    n = normals[faces].astype(np.float64)
    t = uvs[faces].astype(np.float64)

    v_os, orient, good, degenerate = _triangle_frames(p, t, welded)
    neighbours = _neighbours(welded)
    neighbours[degenerate] = -1
    neighbours[np.isin(neighbours, np.flatnonzero(degenerate))] = -1
    _adopt_orientations(orient, good, degenerate, neighbours)
    labels = _corner_groups(welded, neighbours, orient)
    tangent = _group_tangents(p, n, v_os, good, labels)
    result = np.concatenate([tangent, np.repeat(np.where(orient, 1.0, -1.0), 3)[:, None]], axis=-1)
    if degenerate.any():
        _copy_to_degenerate(result, welded, degenerate)
    return result.reshape(n_tri, 3, 4)


def split_vertices(**corner_attributes):
    """Index a triangle mesh whose attributes are given per corner, (F, 3, k) each.

    Corners with equal values of all attributes share a vertex. Returns
    ``(faces, {name: per-vertex array})``.
    """
    names = list(corner_attributes)
    n_tri = len(corner_attributes[names[0]])
    flat = [np.asarray(corner_attributes[k], dtype=np.float32).reshape(n_tri * 3, -1) for k in names]
    widths = [a.shape[1] for a in flat]
    rows = np.concatenate(flat, axis=1) + np.float32(0.0)
    unique, first, inverse = np.unique(rows, axis=0, return_index=True, return_inverse=True)
    order = np.argsort(first)                          # keep the corners' order of first use
    rank = np.empty_like(order)
    rank[order] = np.arange(len(order))
    vertices = unique[order]
    out, col = {}, 0
    for name, w in zip(names, widths):
        out[name] = vertices[:, col:col + w]
        col += w
    return rank[inverse.ravel()].reshape(-1, 3).astype(np.uint32), out
