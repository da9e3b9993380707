"""The map's texels on the low-poly: which UV triangle covers each texel's centre, and the frame there.

:func:`rasterise` is a numpy rasteriser of the UV triangles: texel (row i, column j) has its
centre at uv = ((j + ½)/W, (i + ½)/H), row 0 at the top, as Mitsuba's ``bitmap`` reads it, and
belongs to the first triangle (lowest index) that covers that centre. The candidates (texel
centres in the triangles' bounding boxes) are tested ``Batches.chunk`` at a time.
:func:`texel_frames` interpolates there the low-poly's position p, its vertex normal N and the
tangent frame the map is decoded in (``mikktspace`` or ``mitsuba``: :mod:`mfnormal.io.bake`).
"""

from __future__ import annotations

import numpy as np

from mfnormal.io.bake_inputs import BATCHES
from mfnormal.normals.mikktspace import mikktspace


# -- Rasterising the UV triangles ----------------------------------------------------------------

def _texel_coordinates(uvs, faces, size):
    """The UV triangles in texel-centre coordinates: (x, y), each (F, 3)."""
    return uvs[faces][..., 0] * size - 0.5, uvs[faces][..., 1] * size - 0.5


def _pieces(x, y, size, chunk: int = BATCHES.chunk):
    """The texel-centre bounding boxes of the triangles, clipped to the map and cut into pieces of
    at most about ``chunk`` centres (a large triangle into bands of rows): (triangle, first column,
    last column, first row, last row) per piece, in triangle order; empty boxes left out."""
    lo_x = np.clip(np.ceil(x.min(axis=1)), 0, size - 1).astype(np.int64)
    hi_x = np.clip(np.floor(x.max(axis=1)), -1, size - 1).astype(np.int64)
    lo_y = np.clip(np.ceil(y.min(axis=1)), 0, size - 1).astype(np.int64)
    hi_y = np.clip(np.floor(y.max(axis=1)), -1, size - 1).astype(np.int64)
    nx, ny = np.maximum(hi_x - lo_x + 1, 0), np.maximum(hi_y - lo_y + 1, 0)
    rows = np.maximum(chunk // np.maximum(nx, 1), 1)
    count = np.where(nx > 0, -(-ny // rows), 0)
    tri = np.repeat(np.arange(len(x)), count)
    k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    first_row = lo_y[tri] + k * rows[tri]
    return tri, lo_x[tri], hi_x[tri], first_row, np.minimum(first_row + rows[tri] - 1, hi_y[tri])


def _candidates(piece, first, last):
    """Texel candidates of pieces first..last−1: (triangle, column, row) of each texel centre in
    each piece's box."""
    tri, lo_x, hi_x, lo_y, hi_y = (a[first:last] for a in piece)
    nx, ny = hi_x - lo_x + 1, hi_y - lo_y + 1
    count = nx * ny
    k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    local = np.repeat(np.arange(last - first), count)
    return tri[local], lo_x[local] + k % nx[local], lo_y[local] + k // nx[local]


def _chunks(piece, chunk: int = BATCHES.chunk):
    """Piece ranges holding about ``chunk`` texel candidates each."""
    tri, lo_x, hi_x, lo_y, hi_y = piece
    total = np.cumsum((hi_x - lo_x + 1) * (hi_y - lo_y + 1))
    bounds, first = [], 0
    while first < len(tri):
        last = int(np.searchsorted(total, (total[first - 1] if first else 0) + chunk, "right"))
        last = max(last, first + 1)
        bounds.append((first, min(last, len(tri))))
        first = last
    return bounds


def _barycentrics(x, y, tri, col, row):
    """(b0, b1, b2, det) of texel centres (col, row) in the triangles ``tri``."""
    x0, y0 = x[tri, 0], y[tri, 0]
    e1x, e1y, e2x, e2y = x[tri, 1] - x0, y[tri, 1] - y0, x[tri, 2] - x0, y[tri, 2] - y0
    det = e1x * e2y - e2x * e1y
    px, py = col - x0, row - y0
    with np.errstate(divide="ignore", invalid="ignore"):
        b1 = (px * e2y - e2x * py) / det
        b2 = (e1x * py - px * e1y) / det
    return 1.0 - b1 - b2, b1, b2, det


def texel_owners(uvs, faces, size: int, chunk: int = BATCHES.chunk):
    """The first triangle (lowest index) whose UV triangle covers each texel's centre, −1 where
    none does: (size·size,) int64, texel index row·size + column; ``chunk`` candidates at a time."""
    x, y = _texel_coordinates(uvs, faces, size)
    owner = np.full(size * size, -1, np.int32 if len(faces) < 1 << 31 else np.int64)
    piece = _pieces(x, y, size, chunk)
    for first, last in _chunks(piece, chunk):
        tri, col, row = _candidates(piece, first, last)
        b0, b1, b2, det = _barycentrics(x, y, tri, col, row)
        eps = -1e-9
        inside = (det != 0) & (b0 >= eps) & (b1 >= eps) & (b2 >= eps)
        texel, at = np.unique(row[inside] * size + col[inside], return_index=True)
        free = owner[texel] < 0
        owner[texel[free]] = tri[inside][at[free]]
    return owner


def owned_barycentrics(uvs, faces, size: int, texel, tri):
    """Barycentrics (K, 3) of the centres of ``texel`` in their triangles ``tri``."""
    x, y = _texel_coordinates(uvs, faces, size)
    row, col = np.divmod(texel, size)
    return np.stack(_barycentrics(x, y, tri, col, row)[:3], axis=1)


def rasterise(uvs, faces, size: int):
    """The texels whose centres a UV triangle covers: (texel index row·size + column (K,),
    triangle (K,), barycentrics (K, 3)), one triangle per texel (the first that covers it)."""
    owner = texel_owners(uvs, faces, size)
    texel = np.flatnonzero(owner >= 0)
    return texel, owner[texel], owned_barycentrics(uvs, faces, size, texel, owner[texel])


def uv_problem(uvs, faces, size: int) -> str:
    """Why the UV triangles cover no texel centre of a ``size``² map."""
    lo, hi = uvs[faces].reshape(-1, 2).min(axis=0), uvs[faces].reshape(-1, 2).max(axis=0)
    span = f"u {lo[0]:.6g} to {hi[0]:.6g}, v {lo[1]:.6g} to {hi[1]:.6g}"
    if (hi <= 0).any() or (lo >= 1).any():
        return (f"the low-poly mesh's UVs ({span}) lie outside the map, which covers UV 0 to 1 (a "
                "UDIM tile other than the first?); move them into 0 to 1 (bake one tile at a time)")
    return (f"the low-poly mesh's UV triangles ({span}) cover no texel centre of a {size}x{size} "
            "map (each is smaller than a texel, or has no area in UV); raise the map size "
            "(size, --size) or scale the UVs up")


def outside_map(uvs, faces) -> int:
    """How many triangles have UVs wholly outside the map's [0, 1]² square."""
    t = uvs[faces]
    return int(np.count_nonzero((t.max(axis=1) <= 0).any(axis=1) | (t.min(axis=1) >= 1).any(axis=1)))


# -- Frames at the texels --------------------------------------------------------------------------

def unit_vectors(v):
    """``v`` with its last axis scaled to unit length (zero vectors stay zero)."""
    length = np.linalg.norm(v, axis=-1, keepdims=True)
    return v / np.where(length > 0, length, 1.0)


def _interpolate(values, faces, tri, bary):
    """Per-vertex (V, k) or per-corner (F, 3, k) ``values`` at the barycentrics."""
    corner = values[faces[tri]] if values.ndim == 2 else values[tri]
    return np.einsum("kc,kcd->kd", bary, corner)


def _mitsuba_tangent(positions, uvs, faces, n):
    """Mitsuba's ∂p/∂u per triangle (``Mesh::compute_surface_interaction``), (F, 3); where the UV
    triangle is degenerate, a tangent from ``coordinate_system`` of the triangle's normal."""
    p = positions[faces]
    dp0, dp1 = p[:, 1] - p[:, 0], p[:, 2] - p[:, 0]
    t = uvs[faces]
    duv0, duv1 = t[:, 1] - t[:, 0], t[:, 2] - t[:, 0]
    det = duv0[:, 0] * duv1[:, 1] - duv0[:, 1] * duv1[:, 0]
    ok = det != 0
    dp_du = (duv1[:, 1:2] * dp0 - duv0[:, 1:2] * dp1) / np.where(ok, det, 1.0)[:, None]
    # Duff et al.'s coordinate_system, as Mitsuba builds a frame from a normal alone.
    s = np.where(n[:, 2] >= 0, 1.0, -1.0)
    a = -1.0 / (s + n[:, 2])
    b = n[:, 0] * n[:, 1] * a
    fallback = np.stack([1.0 + s * n[:, 0] ** 2 * a, s * b, -s * n[:, 0]], axis=1)
    return np.where(ok[:, None], dp_du, fallback)


def texel_frames(low, tri, bary, frame: str, corner=None):
    """(p, T, B, N) at the texels: the low-poly's position and the frame the map is decoded in
    (see the module's docstring). ``low`` = (positions, normals, uvs, faces); ``corner``: the
    low-poly's MikkTSpace corner tangents when already computed."""
    positions, normals, uvs, faces = low
    p = _interpolate(positions, faces, tri, bary)
    n = unit_vectors(_interpolate(normals, faces, tri, bary))
    if frame == "mikktspace":
        if corner is None:
            corner = mikktspace(positions, normals, uvs, faces, flip_v=True)
        t4 = _interpolate(corner, faces, tri, bary)
        sign = np.where(t4[:, 3] < 0, -1.0, 1.0)[:, None]
        tangent = t4[:, :3]
    else:
        geo = unit_vectors(np.cross(*(positions[faces][:, k] - positions[faces][:, 0] for k in (1, 2))))
        tangent = _mitsuba_tangent(positions, uvs, faces, geo)[tri]
        sign = 1.0
    tangent = unit_vectors(tangent - np.sum(tangent * n, axis=1, keepdims=True) * n)
    return p, tangent, sign * np.cross(n, tangent), n
