"""Baking a tangent-space normal map from a high-poly mesh onto a low-poly mesh with UVs.

For each texel of the map, :func:`bake`

1. finds the low-poly triangle whose UV triangle covers the texel's centre (a numpy
   rasteriser of the UV triangles; texel (row i, column j) has its centre at
   uv = ((j + ½)/W, (i + ½)/H), row 0 at the top, as Mitsuba's ``bitmap`` reads it);
2. interpolates there the low-poly's position p, its vertex normal N (normalised, as
   Mitsuba's ``si.sh_frame.n``) and the tangent frame the map will be decoded in:
   ``mikktspace`` (default), the per-corner MikkTSpace tangents of
   :func:`mfnormal.normals.mikktspace.mikktspace` interpolated and made orthogonal to N,
   B = sign·(N×T), as ``normalmap_microfacet`` decodes with ``tangents="vertex_tangent"``
   (:func:`tangent_mesh` adds those attributes to a mesh); or ``mitsuba``, the base shading
   frame ``si.sh_frame`` (S = ∂p/∂u made orthogonal to N, T = N×S) that Mitsuba's
   ``normalmap`` and ``normalmap_microfacet``'s default ``tangents="mitsuba"`` use;
3. finds the high-poly surface nearest to p on the segment p ± cage·N with Mitsuba's ray
   tracer (a scene holding only the high-poly mesh; a ray from p each way along N);
4. writes the high-poly's normal there (its shading normal, or ``high_normals="geometric"``)
   in the texel's frame, (x, y, z) = (⟨n, T⟩, ⟨n, B⟩, ⟨n, N⟩), and the height there: the signed
   distance from p along N to that surface (positive outside, where N points; world units).

The map is the UV square [0, 1]²: triangles whose UVs lie outside it (another UDIM tile, a
repeat) are not baked (a warning says how many lie wholly outside), and UVs that cover no texel
centre at all (a tile other than [0, 1]², islands smaller than a texel) are an error. Texels no
triangle covers, and those whose rays miss, hold the flat normal (0, 0, 1) and height 0; the
covered texels' normals and heights are then spread ``padding`` texels outwards (each new texel
the mean of its covered neighbours), so that bilinear lookups along UV seams read no
background. The heights are the map of displacement a renderer would apply along the low-poly's
interpolated normal to get the high-poly back (:func:`write_heights`: a one-channel float EXR).
:func:`encode_map` turns normals into 8- or 16-bit RGB = (n + 1)/2, and :func:`write_map`
writes the PNG atomically. Meshes are read as Mitsuba reads them (PLY, OBJ), so the map fits
the UVs Mitsuba renders with.

The inputs are checked before any work: the files (:mod:`mfnormal.io.mesh_files`: face indices,
finite numbers, before Mitsuba reads them), then the meshes (triangles, indices, finite
positions, normals and UVs, a low-poly with area). Meshes whose size (the low-poly's
bounding-box diagonal) lies outside WORKING_SIZE are traced scaled by a power of two into it
(exact in floating point; single-precision ray tracing loses normals of tiny triangles), and
their heights scaled back. A cage longer than the scene (the diagonal of both meshes' bounding
box) finds nothing a cage of that length does not, and is shortened to it, so that the rays'
start stays close to the surface. Texels are traced TEXELS_PER_PASS at a time and padded in
bands of rows, so that memory stays below BYTES_PER_TEXEL per texel (mostly the arrays returned);
a bake larger than the memory available is refused before it allocates.
"""

from __future__ import annotations

import math
import numbers
import os
import warnings
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Callable, Sequence, Union

import numpy as np

if TYPE_CHECKING:
    import mitsuba as mi

#: A file path as the functions take it.
PathLike = Union[str, os.PathLike]
#: A mesh's arrays: positions (V, 3), normals (V, 3) or None, uvs (V, 2) or None, faces (F, 3).
MeshArrays = tuple  # (np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray)

from mfnormal.normals.mikktspace import mikktspace, split_vertices

__all__ = ["BakeError", "Baked", "MESH_SUFFIXES", "TANGENT_FRAMES", "SIZE_RANGE", "load_mesh",
           "mesh_arrays", "unwrap", "bake", "encode_map", "write_map", "write_heights", "write_baked",
           "tangent_mesh", "check_low_poly", "check_high_poly", "memory_needed"]

MESH_SUFFIXES = {".ply": "ply", ".obj": "obj"}
TANGENT_FRAMES = ("mikktspace", "mitsuba")
HIGH_NORMALS = ("shading", "geometric")
SIZE_RANGE = (8, 8192)
#: The default cage distance as a fraction of the low-poly's bounding-box diagonal.
CAGE_FRACTION = 0.05
#: The rays along ±N start this fraction of the cage behind the low-poly's surface point.
RAY_START = 1e-3


@dataclass(frozen=True)
class Batches:
    """How many texels a bake handles at once: ``trace`` texels whose frames and rays are
    computed in one pass (memory: ~600 bytes each), ``band`` texels of rows padded and encoded
    together, ``chunk`` texel candidates the rasteriser tests at a time (~200 bytes each). The
    map is the same for any batches; they trade memory for per-step overhead."""
    trace: int = 1 << 19
    band: int = 1 << 20
    chunk: int = 1 << 20


#: The bake's batches.
BATCHES = Batches()
#: Texels traced per pass (``BATCHES.trace``).
TEXELS_PER_PASS = BATCHES.trace
#: Memory a bake takes per texel of the map, with a margin: the normals and heights (float64),
#: the covering triangle (int32), the covered and hit masks, the encoded map and its file
#: (measured: ~37 at 8192², docs/cli.md).
BYTES_PER_TEXEL = 56
#: Transient memory of a bake on top of that: one pass of texels, one chunk of candidates.
BAKE_OVERHEAD_BYTES = 1 << 29
#: The low-poly sizes (bounding-box diagonal) traced as they are; others are scaled by a power
#: of two into this range (single-precision normals of tiny triangles underflow).
WORKING_SIZE = (2.0 ** -7, 2.0 ** 17)


class BakeError(ValueError):
    """An input the baker cannot use (one line, naming the fix)."""


@dataclass
class Baked:
    """A baked map: ``normals`` (H, W, 3) unit tangent-space normals, ``covered`` (H, W) the
    texels a low-poly triangle covers, ``hit`` (H, W) those whose rays found the high-poly,
    ``heights`` (H, W) the high-poly's signed distance along the low-poly's normal (world units);
    ``cage_spans_scene``: the cage was at least as long as the scene is wide, so that a longer
    one would find nothing more."""
    normals: np.ndarray
    covered: np.ndarray
    hit: np.ndarray
    heights: np.ndarray
    cage_spans_scene: bool = False

    @property
    def missed(self) -> int:
        """Covered texels whose rays found no high-poly surface within the cage."""
        return int(np.count_nonzero(self.covered & ~self.hit))


# -- Meshes ---------------------------------------------------------------------------------------

def load_mesh(path: PathLike, what: str = "mesh") -> mi.Mesh:
    """The Mitsuba mesh of the PLY or OBJ file ``path``; :class:`BakeError` if it cannot be."""
    import mitsuba as mi

    path = Path(path)
    if not path.is_file():
        raise BakeError(f"{what} file not found: {path}")
    kind = MESH_SUFFIXES.get(path.suffix.lower())
    if kind is None:
        raise BakeError(f"{what} {path}: expected a .ply or .obj mesh")
    from mfnormal.io.mesh_files import check_mesh_file
    check_mesh_file(path, f"{what} {path}", BakeError)
    try:
        return mi.load_dict({"type": kind, "filename": str(path)})
    except Exception as exc:  # Mitsuba's loaders raise RuntimeError with a multi-line message
        from mfnormal.io.messages import one_line
        raise BakeError(f"cannot load {what} {path}: {one_line(exc)}") from None


def mesh_arrays(mesh: mi.Mesh) -> MeshArrays:
    """(positions (V, 3), normals (V, 3) or None, uvs (V, 2) or None, faces (F, 3)) of a Mitsuba
    mesh, as numpy arrays."""
    import mitsuba as mi

    params = mi.traverse(mesh)
    positions = np.array(params["vertex_positions"], np.float64).reshape(-1, 3)
    faces = np.array(params["faces"], np.int64).reshape(-1, 3)
    normals = (np.array(params["vertex_normals"], np.float64).reshape(-1, 3)
               if mesh.has_vertex_normals() else None)
    uvs = (np.array(params["vertex_texcoords"], np.float64).reshape(-1, 2)
           if mesh.has_vertex_texcoords() else None)
    return positions, normals, uvs, faces


def unwrap(positions: np.ndarray, normals: np.ndarray, faces: np.ndarray, size: int | None = None,
           padding: int = 4) -> MeshArrays:
    """xatlas UVs for a mesh without them: (positions, normals, uvs, faces) with vertices split
    along the UV seams; ``size`` (the map's texels across) with ``padding`` texels between the
    charts. Needs the optional ``xatlas`` package (``pip install 'mfnormal[assets]'``)."""
    try:
        import xatlas
    except ImportError:
        raise BakeError("unwrapping needs the xatlas package: pip install 'mfnormal[assets]' "
                        "(or give a low-poly mesh with UVs)") from None
    atlas = xatlas.Atlas()
    atlas.add_mesh(np.asarray(positions, np.float32), np.asarray(faces, np.uint32))
    pack = xatlas.PackOptions()
    pack.padding = int(padding)
    if size is not None:
        pack.resolution = int(size)
    atlas.generate(pack_options=pack)
    vmapping, new_faces, uvs = atlas[0]
    return (positions[vmapping], normals[vmapping], uvs.astype(np.float64),
            new_faces.astype(np.int64))


def tangent_mesh(name: str, positions: np.ndarray, normals: np.ndarray, uvs: np.ndarray, faces: np.ndarray,
                 bsdf: mi.BSDF | None = None) -> mi.Mesh:
    """A Mitsuba mesh with MikkTSpace vertex tangents (attributes ``vertex_tangent`` and
    ``vertex_tangent_sign``), vertices split where corners' tangents differ: the mesh on which
    ``normalmap_microfacet`` with ``tangents="vertex_tangent"`` decodes a ``mikktspace`` bake
    in the frame it was baked in. ``bsdf``: a loaded BSDF or None."""
    import mitsuba as mi
    from mfnormal.io.gltf import mitsuba_mesh

    faces = np.asarray(faces, np.int64)
    corner_t = mikktspace(positions, normals, uvs, faces, flip_v=True)
    split, v = split_vertices(p=np.asarray(positions)[faces], n=np.asarray(normals)[faces],
                              uv=np.asarray(uvs)[faces], t=corner_t)
    return mitsuba_mesh(name, bsdf if bsdf is not None else mi.load_dict({"type": "diffuse"}),
                        v["p"], v["n"], v["uv"], v["t"], split)


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


def _uv_problem(uvs, faces, size: int) -> str:
    """Why the UV triangles cover no texel centre of a ``size``² map."""
    lo, hi = uvs[faces].reshape(-1, 2).min(axis=0), uvs[faces].reshape(-1, 2).max(axis=0)
    span = f"u {lo[0]:.6g} to {hi[0]:.6g}, v {lo[1]:.6g} to {hi[1]:.6g}"
    if (hi <= 0).any() or (lo >= 1).any():
        return (f"the low-poly mesh's UVs ({span}) lie outside the map, which covers UV 0 to 1 (a "
                "UDIM tile other than the first?); move them into 0 to 1 (bake one tile at a time)")
    return (f"the low-poly mesh's UV triangles ({span}) cover no texel centre of a {size}x{size} "
            "map (each is smaller than a texel, or has no area in UV); raise the map size "
            "(size, --size) or scale the UVs up")


# -- Frames at the texels --------------------------------------------------------------------------

def _unit(v):
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
    n = _unit(_interpolate(normals, faces, tri, bary))
    if frame == "mikktspace":
        if corner is None:
            corner = mikktspace(positions, normals, uvs, faces, flip_v=True)
        t4 = _interpolate(corner, faces, tri, bary)
        sign = np.where(t4[:, 3] < 0, -1.0, 1.0)[:, None]
        tangent = t4[:, :3]
    else:
        geo = _unit(np.cross(*(positions[faces][:, k] - positions[faces][:, 0] for k in (1, 2))))
        tangent = _mitsuba_tangent(positions, uvs, faces, geo)[tri]
        sign = 1.0
    tangent = _unit(tangent - np.sum(tangent * n, axis=1, keepdims=True) * n)
    return p, tangent, sign * np.cross(n, tangent), n


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
    return _unit(normal), distance, hit


# -- Padding and encoding ------------------------------------------------------------------------

def _bands(height: int, width: int, band: int = BATCHES.band):
    """Row ranges (first, last) of about ``band`` texels each."""
    rows = max(1, band // max(width, 1))
    return [(r, min(r + rows, height)) for r in range(0, height, rows)]


def dilate(normals, known, padding: int, unit: bool = True):
    """``normals`` (H, W, C) with the texels outside ``known`` within ``padding`` texels (8-
    neighbourhood rings) set to the mean of their known neighbours (normalised where ``unit``),
    ring by ring."""
    out = normals.copy()
    _dilate_into(out, known, padding, unit)
    return out


def _dilate_into(normals, known, padding: int, unit: bool = True, band: int = BATCHES.band) -> None:
    """:func:`dilate` in place, in bands of rows: a texel after ``padding`` rings depends only on
    the texels within ``padding`` rows of it, so each band is padded in a slab that holds
    ``padding`` more rows on each side, and only the band is written back (the slab's rows
    above, already padded, are not ``known`` and so are not read)."""
    h = known.shape[0]
    for first, last in _bands(*known.shape, band):
        top, bottom = max(first - padding, 0), min(last + padding, h)
        slab = _dilate_slab(normals[top:bottom], known[top:bottom], padding, unit)
        normals[first:last] = slab[first - top:last - top]


def _dilate_slab(normals, known, padding: int, unit: bool):
    normals, known = normals.copy(), known.copy()
    for _ in range(padding):
        total = np.zeros_like(normals)
        count = np.zeros(known.shape)
        padded_n = np.pad(normals * known[..., None], ((1, 1), (1, 1), (0, 0)))
        padded_k = np.pad(known, 1).astype(np.float64)
        h, w = known.shape
        for dy in (-1, 0, 1):
            for dx in (-1, 0, 1):
                total += padded_n[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
                count += padded_k[1 + dy:1 + dy + h, 1 + dx:1 + dx + w]
        ring = ~known & (count > 0)
        if not ring.any():
            break
        normals[ring] = _unit(total[ring]) if unit else total[ring] / count[ring][:, None]
        known |= ring
    return normals


def _check_finite(values, what: str) -> None:
    bad = ~np.isfinite(values)
    if bad.any():
        raise BakeError(f"the {what} hold NaN or infinity ({int(bad.sum())} values); nothing was "
                        "written: give finite values")


def _check_bits(bits) -> int:
    if isinstance(bits, bool) or bits not in (8, 16):
        raise BakeError(f"bits {bits!r}: expected 8 or 16 bits per channel")
    return int(bits)


def encode_map(normals: np.ndarray, bits: int = 8) -> np.ndarray:
    """Unit normals (H, W, 3) as RGB = (n + 1)/2 rounded to ``bits`` (8 or 16) per channel;
    :class:`BakeError` for other ``bits`` or normals that are not finite."""
    top = (1 << _check_bits(bits)) - 1
    normals = np.asarray(normals)
    _check_finite(normals, "normals")
    rgb = np.empty(normals.shape, np.uint8 if bits == 8 else np.uint16)
    bands = _bands(*normals.shape[:2]) if normals.ndim == 3 else [(0, len(normals))]
    for first, last in bands:
        rgb[first:last] = np.round((np.clip(normals[first:last], -1.0, 1.0) + 1.0) * 0.5 * top)
    return rgb


def _map_bytes(normals, bits: int) -> bytes:
    import mitsuba as mi
    from mfnormal.io.images import encode

    bitmap = mi.Bitmap(np.ascontiguousarray(encode_map(normals, bits)), mi.Bitmap.PixelFormat.RGB)
    return encode(bitmap, mi.Bitmap.FileFormat.PNG)


def _heights_bytes(heights) -> bytes:
    import mitsuba as mi
    from mfnormal.io.images import encode

    with np.errstate(over="ignore"):
        heights = np.ascontiguousarray(heights, np.float32)
    _check_finite(heights, "heights (in single precision)")
    bitmap = mi.Bitmap(heights[..., None], mi.Bitmap.PixelFormat.Y)
    return encode(bitmap, mi.Bitmap.FileFormat.OpenEXR)


def write_map(path: PathLike, normals: np.ndarray, bits: int = 8) -> Path:
    """Write the normal map PNG (8- or 16-bit) atomically; returns the path. :class:`BakeError`
    (nothing written) for other ``bits`` or normals that are not finite."""
    return write_baked(path, normals, bits)[0]


def write_heights(path: PathLike, heights: np.ndarray) -> Path:
    """Write the heights (H, W, world units) as a one-channel 32-bit float OpenEXR, atomically
    (what Mitsuba's ``bitmap`` reads with ``raw=True``); returns the path. :class:`BakeError`
    (nothing written) for heights that are not finite in single precision."""
    from mfnormal.files import atomic_write, write_bytes

    data = _heights_bytes(heights)
    return atomic_write(path, lambda p: write_bytes(p, data))


def write_baked(path: PathLike, normals: np.ndarray, bits: int = 8, heights_path: PathLike | None = None,
                heights: np.ndarray | None = None,
                more: Sequence[tuple[PathLike, Callable[[Path], None]]] = ()) -> list:
    """The normal map PNG at ``path`` and, with ``heights_path``, the ``heights`` EXR there (and
    ``more`` (path, write(tmp_path)) items), written as one (all or none:
    :func:`mfnormal.files.atomic_write_all`); returns the paths."""
    from mfnormal.files import atomic_write_all, write_bytes

    map_data = _map_bytes(normals, bits)
    items = [(path, lambda p: write_bytes(p, map_data))]
    if heights_path is not None:
        heights_data = _heights_bytes(heights)
        items.append((heights_path, lambda p: write_bytes(p, heights_data)))
    return atomic_write_all(items + list(more))


# -- The baker ---------------------------------------------------------------------------------

def _as_mesh(mesh, what: str, argument: str, kind):
    """A Mitsuba shape of type ``kind``, or the mesh loaded from a path; :class:`BakeError`
    naming ``argument`` for anything else."""
    if isinstance(mesh, (str, os.PathLike)):
        return load_mesh(mesh, what)
    if not isinstance(mesh, kind):
        raise BakeError(f"{argument}: expected the {what} as a Mitsuba {kind.__name__} or the path "
                        f"of a .ply or .obj file, got {type(mesh).__name__}")
    return mesh


def _check_mesh_arrays(positions, normals, uvs, faces, what: str) -> None:
    """:class:`BakeError` for a mesh without triangles, a face index past its vertices, or
    positions, normals or UVs that are not finite."""
    if len(faces) == 0:
        raise BakeError(f"the {what} has no triangles; give a mesh with faces")
    if faces.min() < 0 or faces.max() >= len(positions):
        raise BakeError(f"the {what} has a face index of {faces.max()}, but {len(positions)} "
                        "vertices; its faces must index its vertices")
    for values, name in ((positions, "positions"), (normals, "vertex normals"), (uvs, "UVs")):
        if values is not None and not np.isfinite(values).all():
            raise BakeError(f"the {what}'s {name} hold NaN or infinity; give finite values")


def check_low_poly(low: mi.Mesh, what: str = "low-poly mesh") -> MeshArrays:
    """(positions, normals, uvs, faces) of the low-poly; :class:`BakeError` without UVs or
    normals, for the problems of :func:`_check_mesh_arrays`, or without area."""
    positions, normals, uvs, faces = mesh_arrays(low)
    if uvs is None:
        raise BakeError(f"the {what} has no UVs (texture coordinates); unwrap it first "
                        "(mfnormal bake --unwrap OUT.ply, with xatlas)")
    if normals is None:
        raise BakeError(f"the {what} has no vertex normals (it is flat-shaded); give it smooth "
                        "vertex normals")
    _check_mesh_arrays(positions, normals, uvs, faces, what)
    corners = positions[faces]
    if not np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]),
                          axis=1).any():
        raise BakeError(f"the {what} has no area (every triangle's corners coincide or lie on a "
                        "line); give a mesh with surface to bake onto")
    return positions, normals, uvs, faces


def check_high_poly(high: mi.Shape, what: str = "high-poly mesh") -> None:
    """:class:`BakeError` for a high-poly mesh with the problems of :func:`_check_mesh_arrays`
    (other shapes, e.g. Mitsuba's analytic sphere, are taken as they are)."""
    import mitsuba as mi

    if isinstance(high, mi.Mesh):
        positions, normals, _, faces = mesh_arrays(high)
        _check_mesh_arrays(positions, normals, None, faces, what)


def default_cage(positions) -> float:
    """CAGE_FRACTION of the bounding-box diagonal of ``positions``."""
    return CAGE_FRACTION * _diagonal(positions)


def _diagonal(positions) -> float:
    return float(np.linalg.norm(positions.max(axis=0) - positions.min(axis=0)))


def _working_scale(size: float) -> float:
    """1, or the power of two that brings a low-poly of ``size`` into WORKING_SIZE."""
    if WORKING_SIZE[0] <= size <= WORKING_SIZE[1]:
        return 1.0
    return 2.0 ** -round(math.log2(size))


def _scaled_mesh(mesh, scale: float):
    """A copy of the Mitsuba mesh ``mesh`` scaled by ``scale`` (a power of two: exact), its
    vertex normals as :func:`_scaled_arrays` gives them."""
    import mitsuba as mi

    if scale == 1.0:
        return mesh
    if not isinstance(mesh, mi.Mesh):
        raise BakeError(f"the low-poly mesh is about {1 / scale:g} units across, too far from 1 to "
                        f"trace a {mesh.class_name()} shape beside it; give the high-poly as a "
                        "mesh, or scale both")
    positions, normals, _, faces = mesh_arrays(mesh)
    return _mesh(*_scaled_arrays(positions, normals, faces, scale), faces)


def _mesh(positions, normals, faces):
    """A Mitsuba mesh of these arrays (without vertex normals where ``normals`` is None: the
    triangles' own normals shade it)."""
    import mitsuba as mi

    mesh = mi.Mesh("mesh", len(positions), len(faces), has_vertex_normals=normals is not None)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ravel(positions).astype(np.float32))
    if normals is not None:
        params["vertex_normals"] = mi.Float(np.ravel(normals).astype(np.float32))
    params["faces"] = mi.UInt32(np.ravel(faces).astype(np.uint32))
    params.update()
    return mesh


def _scaled_arrays(positions, normals, faces, scale: float):
    """(positions·scale, vertex normals): the normals as they are, or recomputed by Mitsuba at
    the working scale where its loader could not compute them at the mesh's own (single-
    precision cross products of tiny triangles underflow, and it gives the vertex (1, 0, 0))."""
    positions = positions * scale
    if normals is not None and _fallback_normals(positions, normals, faces):
        mesh = _mesh(positions, np.zeros_like(positions), faces)
        mesh.recompute_vertex_normals()
        normals = mesh_arrays(mesh)[1]
    return positions, normals


def _fallback_normals(positions, normals, faces) -> bool:
    """Whether a vertex normal is Mitsuba's fallback (1, 0, 0) where the triangles around the
    vertex (in double precision) face elsewhere."""
    corners = positions[faces]
    face_normals = _unit(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]))
    around = np.zeros_like(positions)
    for k in range(3):
        np.add.at(around, faces[:, k], face_normals)
    fallback = np.all(normals == [1.0, 0.0, 0.0], axis=1)
    return bool(np.any(fallback & (_unit(around)[:, 0] < 0.9)))


def _check_variant() -> None:
    import mitsuba as mi

    variant = mi.variant()
    if variant is None or not variant.startswith(("llvm_", "cuda_")):
        raise BakeError(f"the baker traces rays in bulk and needs a JIT variant (llvm_ad_rgb, "
                        f"cuda_ad_rgb), not {variant}: call mitsuba.set_variant('llvm_ad_rgb') "
                        "(mfnormal bake --variant llvm_ad_rgb)")


def _check_number(value, name: str, integer: bool, low: float = 0) -> None:
    kinds = numbers.Integral if integer else numbers.Real
    if isinstance(value, bool) or not isinstance(value, kinds):
        raise BakeError(f"{name} {value!r}: expected {'an integer' if integer else 'a number'}")
    if not low <= value < math.inf:
        raise BakeError(f"{name} {value}: expected {'an integer' if integer else 'a number'} "
                        f"of at least {low}")


def memory_needed(size: int) -> int:
    """About the bytes a ``size``² bake takes at its peak (BYTES_PER_TEXEL per texel and the
    passes' transient memory)."""
    return BYTES_PER_TEXEL * size * size + BAKE_OVERHEAD_BYTES


def _available_memory() -> int | None:
    """The memory this process may still take: the system's available memory (Linux), None
    where unknown."""
    try:
        with open("/proc/meminfo") as f:
            for line in f:
                if line.startswith("MemAvailable:"):
                    return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


def _check_memory(size: int, limit: int | None = None) -> None:
    """A :class:`BakeError` where a ``size``² bake needs more than ``limit`` bytes (default: the
    memory the system has available)."""
    needed, available = memory_needed(size), _available_memory() if limit is None else limit
    if available is not None and needed > available:
        raise BakeError(f"a {size}x{size} bake needs about {needed / 2 ** 30:.1f} GiB of memory, "
                        f"more than the {available / 2 ** 30:.1f} GiB available; lower the map size "
                        "(size, --size)")


def bake(high: mi.Shape | PathLike, low: mi.Mesh | PathLike, size: int = 1024, cage: float | None = None, frame: str = "mikktspace",
         padding: int = 4, high_normals: str = "shading",
         progress: Callable[[int, int], None] | None = None, batches: Batches = BATCHES,
         memory_limit: int | None = None) -> Baked:
    """Bake the tangent-space normal map of ``high`` onto ``low`` (Mitsuba meshes or paths of PLY
    or OBJ files; the low-poly needs UVs and vertex normals), and its heights over ``low``: a
    ``size``² :class:`Baked`.

    ``cage``: how far from the low-poly surface rays look for the high-poly (default:
    CAGE_FRACTION of the low-poly's bounding-box diagonal); ``frame``: ``mikktspace`` or
    ``mitsuba`` (see the module's docstring); ``padding``: texels to dilate the islands by;
    ``high_normals``: the high-poly's ``shading`` (interpolated) or ``geometric`` normal;
    ``progress(done, total)``: called after each pass of ``batches.trace`` texels traced;
    ``batches``: how many texels each step handles (:class:`Batches`); ``memory_limit``: the
    bytes the bake may take (default: what the system has available), checked before it starts.
    A JIT variant (``llvm_*``, ``cuda_*``) must be set. Every input is checked first
    (:class:`BakeError`, one line); a warning says when most texels' normals face away from
    the low-poly's (one of the meshes' normals is flipped)."""
    import mitsuba as mi

    high_mesh, (positions, normals, uvs, faces) = _checked_inputs(high, low, size, cage, frame, padding,
                                                                   high_normals, memory_limit)
    # Trace at a working scale (a power of two: exact); the heights are scaled back.
    scale = _working_scale(_diagonal(positions))
    high_mesh = _scaled_mesh(high_mesh, scale)
    if scale != 1.0:
        positions, normals = _scaled_arrays(positions, normals, faces, scale)
    cage = default_cage(positions) if cage is None else float(cage) * scale
    bbox = high_mesh.bbox()
    scene_size = _diagonal(np.concatenate([positions, [list(bbox.min), list(bbox.max)]]))
    spans_scene = cage >= scene_size
    cage = min(cage, scene_size)

    owner = texel_owners(uvs, faces, size, batches.chunk)
    covered = owner >= 0
    if not covered.any():
        raise BakeError(_uv_problem(uvs, faces, size))
    outside = _outside_map(uvs, faces)
    if outside:
        warnings.warn(f"{outside} of the low-poly mesh's {len(faces)} triangles have UVs wholly "
                      "outside the map's 0 to 1 square (another UDIM tile, or a repeat) and are "
                      "not baked", stacklevel=2)
    scene = mi.load_dict({"type": "scene", "high": high_mesh})
    normals_out, heights, hits = _trace_passes(scene, (positions, normals, uvs, faces), owner, size, frame,
                                               cage, high_normals == "geometric", progress, batches.trace)
    heights /= scale
    covered, hits = covered.reshape(size, size), hits.reshape(size, size)
    normals_out = normals_out.reshape(size, size, 3)
    heights = heights.reshape(size, size, 1)
    _dilate_into(normals_out, covered, padding, band=batches.band)
    _dilate_into(heights, covered, padding, unit=False, band=batches.band)
    return Baked(normals_out, covered, hits, heights[..., 0], spans_scene)


def _checked_inputs(high, low, size, cage, frame, padding, high_normals, memory_limit):
    """:func:`bake`'s inputs checked before any work (one-line :class:`BakeError`s): the
    high-poly mesh and the low-poly's arrays."""
    import mitsuba as mi

    if frame not in TANGENT_FRAMES:
        raise BakeError(f"frame must be one of {', '.join(TANGENT_FRAMES)}, got '{frame}'")
    if high_normals not in HIGH_NORMALS:
        raise BakeError(f"high_normals must be one of {', '.join(HIGH_NORMALS)}, got '{high_normals}'")
    _check_number(size, "size", integer=True)
    if not SIZE_RANGE[0] <= size <= SIZE_RANGE[1]:
        raise BakeError(f"size {size} is out of range ({SIZE_RANGE[0]} to {SIZE_RANGE[1]})")
    _check_number(padding, "padding", integer=True)
    if cage is not None:
        _check_number(cage, "cage", integer=False)
        if not cage > 0:
            raise BakeError(f"cage {cage}: expected a distance above 0")
    _check_variant()
    high_mesh = _as_mesh(high, "high-poly mesh", "high", mi.Shape)
    low_mesh = _as_mesh(low, "low-poly mesh", "low", mi.Mesh)
    check_high_poly(high_mesh)
    arrays = check_low_poly(low_mesh)
    _check_memory(size, memory_limit)
    return high_mesh, arrays


def _trace_passes(scene, low_arrays, owner, size, frame, cage, geometric, progress, per_pass):
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


def _outside_map(uvs, faces) -> int:
    """How many triangles have UVs wholly outside the map's [0, 1]² square."""
    t = uvs[faces]
    return int(np.count_nonzero((t.max(axis=1) <= 0).any(axis=1) | (t.min(axis=1) >= 1).any(axis=1)))
