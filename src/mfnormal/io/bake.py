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

Texels no triangle covers, and those whose rays miss, hold the flat normal (0, 0, 1) and height
0; the covered texels' normals and heights are then spread ``padding`` texels outwards (each new
texel the mean of its covered neighbours), so that bilinear lookups along UV seams read no
background. The heights are the map of displacement a renderer would apply along the low-poly's
interpolated normal to get the high-poly back (:func:`write_heights`: a one-channel float EXR).
:func:`encode_map` turns normals into 8- or 16-bit RGB = (n + 1)/2, and :func:`write_map`
writes the PNG atomically. Meshes are read as Mitsuba reads them (PLY, OBJ), so the map fits
the UVs Mitsuba renders with.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import numpy as np

from mfnormal.normals.mikktspace import mikktspace, split_vertices

__all__ = ["BakeError", "Baked", "MESH_SUFFIXES", "TANGENT_FRAMES", "SIZE_RANGE", "load_mesh",
           "mesh_arrays", "unwrap", "bake", "encode_map", "write_map", "write_heights", "write_baked",
           "tangent_mesh"]

MESH_SUFFIXES = {".ply": "ply", ".obj": "obj"}
TANGENT_FRAMES = ("mikktspace", "mitsuba")
HIGH_NORMALS = ("shading", "geometric")
SIZE_RANGE = (8, 8192)
#: The default cage distance as a fraction of the low-poly's bounding-box diagonal.
CAGE_FRACTION = 0.05
#: The rays along ±N start this fraction of the cage behind the low-poly's surface point.
RAY_START = 1e-3
#: Texel candidates tested per rasteriser chunk (memory: ~100 bytes each).
CHUNK = 1 << 22


class BakeError(ValueError):
    """An input the baker cannot use (one line, naming the fix)."""


@dataclass
class Baked:
    """A baked map: ``normals`` (H, W, 3) unit tangent-space normals, ``covered`` (H, W) the
    texels a low-poly triangle covers, ``hit`` (H, W) those whose rays found the high-poly,
    ``heights`` (H, W) the high-poly's signed distance along the low-poly's normal (world units)."""
    normals: np.ndarray
    covered: np.ndarray
    hit: np.ndarray
    heights: np.ndarray

    @property
    def missed(self) -> int:
        """Covered texels whose rays found no high-poly surface within the cage."""
        return int(np.count_nonzero(self.covered & ~self.hit))


# -- Meshes ---------------------------------------------------------------------------------------

def load_mesh(path, what: str = "mesh"):
    """The Mitsuba mesh of the PLY or OBJ file ``path``; :class:`BakeError` if it cannot be."""
    import mitsuba as mi

    path = Path(path)
    if not path.is_file():
        raise BakeError(f"{what} file not found: {path}")
    kind = MESH_SUFFIXES.get(path.suffix.lower())
    if kind is None:
        raise BakeError(f"{what} {path}: expected a .ply or .obj mesh")
    try:
        return mi.load_dict({"type": kind, "filename": str(path)})
    except Exception as exc:  # Mitsuba's loaders raise RuntimeError with a multi-line message
        from mfnormal.io.messages import one_line
        raise BakeError(f"cannot load {what} {path}: {one_line(exc)}") from None


def mesh_arrays(mesh):
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


def unwrap(positions, normals, faces, size: int | None = None, padding: int = 4):
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


def tangent_mesh(name, positions, normals, uvs, faces, bsdf=None):
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

def _candidates(x, y, size, first, last):
    """Texel candidates of triangles first..last−1: (triangle, column, row) of each texel
    centre inside the triangle's UV bounding box."""
    lo_x = np.clip(np.ceil(x[first:last].min(axis=1)), 0, size - 1).astype(np.int64)
    hi_x = np.clip(np.floor(x[first:last].max(axis=1)), -1, size - 1).astype(np.int64)
    lo_y = np.clip(np.ceil(y[first:last].min(axis=1)), 0, size - 1).astype(np.int64)
    hi_y = np.clip(np.floor(y[first:last].max(axis=1)), -1, size - 1).astype(np.int64)
    nx, ny = np.maximum(hi_x - lo_x + 1, 0), np.maximum(hi_y - lo_y + 1, 0)
    count = nx * ny
    tri = np.repeat(np.arange(first, last), count)
    k = np.arange(count.sum()) - np.repeat(np.cumsum(count) - count, count)
    local = tri - first
    return tri, lo_x[local] + k % np.maximum(nx[local], 1), lo_y[local] + k // np.maximum(nx[local], 1)


def _chunks(x, y, size):
    """Triangle ranges whose bounding boxes hold at most about CHUNK texel candidates each."""
    w = np.clip(np.floor(x.max(axis=1)) - np.ceil(x.min(axis=1)) + 1, 0, size)
    h = np.clip(np.floor(y.max(axis=1)) - np.ceil(y.min(axis=1)) + 1, 0, size)
    total = np.cumsum(w * h)
    bounds, first = [], 0
    while first < len(x):
        last = int(np.searchsorted(total, (total[first - 1] if first else 0) + CHUNK, "right"))
        last = max(last, first + 1)
        bounds.append((first, min(last, len(x))))
        first = last
    return bounds


def rasterise(uvs, faces, size: int):
    """The texels whose centres a UV triangle covers: (texel index row·size + column (K,),
    triangle (K,), barycentrics (K, 3)), one triangle per texel (the first that covers it)."""
    x = uvs[faces][..., 0] * size - 0.5          # texel-centre coordinates, (F, 3)
    y = uvs[faces][..., 1] * size - 0.5
    found = []
    for first, last in _chunks(x, y, size):
        tri, col, row = _candidates(x, y, size, first, last)
        x0, y0 = x[tri, 0], y[tri, 0]
        e1x, e1y, e2x, e2y = x[tri, 1] - x0, y[tri, 1] - y0, x[tri, 2] - x0, y[tri, 2] - y0
        det = e1x * e2y - e2x * e1y
        px, py = col - x0, row - y0
        with np.errstate(divide="ignore", invalid="ignore"):
            b1 = (px * e2y - e2x * py) / det
            b2 = (e1x * py - px * e1y) / det
        b0 = 1.0 - b1 - b2
        eps = -1e-9
        inside = (det != 0) & (b0 >= eps) & (b1 >= eps) & (b2 >= eps)
        found.append((row[inside] * size + col[inside], tri[inside],
                      np.stack([b0, b1, b2], axis=1)[inside]))
    texel = np.concatenate([f[0] for f in found])
    tri = np.concatenate([f[1] for f in found])
    bary = np.concatenate([f[2] for f in found]) if found else np.zeros((0, 3))
    texel, first = np.unique(texel, return_index=True)
    return texel, tri[first], bary[first]


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


def texel_frames(low, tri, bary, frame: str):
    """(p, T, B, N) at the texels: the low-poly's position and the frame the map is decoded in
    (see the module's docstring). ``low`` = (positions, normals, uvs, faces)."""
    positions, normals, uvs, faces = low
    p = _interpolate(positions, faces, tri, bary)
    n = _unit(_interpolate(normals, faces, tri, bary))
    if frame == "mikktspace":
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


def high_surface_at(high_mesh, p, n, cage: float, geometric: bool = False):
    """The high-poly's unit normal at the surface point nearest to ``p`` on the segment
    p ± cage·``n``, (K, 3), that point's signed distance from p along ``n``, (K,), and whether
    there is one, (K,).

    Two rays leave p, one along +n and one along −n, each from RAY_START·cage behind p (so that
    a surface through p itself is met, not skipped) up to cage beyond it; each meets the first
    surface on its side, and the one nearer to p wins."""
    import mitsuba as mi

    scene = mi.load_dict({"type": "scene", "high": high_mesh})
    eps = RAY_START * cage
    t_up, n_up, hit_up = _trace(scene, p - eps * n, n, cage + eps, geometric)
    t_down, n_down, hit_down = _trace(scene, p + eps * n, -n, cage + eps, geometric)
    use_up = hit_up & (~hit_down | (np.abs(t_up - eps) <= np.abs(t_down - eps)))
    normal = np.where(use_up[:, None], n_up, n_down)
    hit = hit_up | hit_down
    distance = np.where(hit, np.where(use_up, t_up - eps, eps - t_down), 0.0)
    return _unit(normal), distance, hit


# -- Padding and encoding ------------------------------------------------------------------------

def dilate(normals, known, padding: int, unit: bool = True):
    """``normals`` (H, W, C) with the texels outside ``known`` within ``padding`` texels (8-
    neighbourhood rings) set to the mean of their known neighbours (normalised where ``unit``),
    ring by ring."""
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


def encode_map(normals, bits: int = 8):
    """Unit normals (H, W, 3) as RGB = (n + 1)/2 rounded to ``bits`` (8 or 16) per channel."""
    top = (1 << bits) - 1
    rgb = np.round((np.clip(normals, -1.0, 1.0) + 1.0) * 0.5 * top)
    return rgb.astype(np.uint8 if bits == 8 else np.uint16)


def _map_bytes(normals, bits: int) -> bytes:
    import mitsuba as mi
    from mfnormal.io.images import encode

    bitmap = mi.Bitmap(np.ascontiguousarray(encode_map(normals, bits)), mi.Bitmap.PixelFormat.RGB)
    return encode(bitmap, mi.Bitmap.FileFormat.PNG)


def _heights_bytes(heights) -> bytes:
    import mitsuba as mi
    from mfnormal.io.images import encode

    bitmap = mi.Bitmap(np.ascontiguousarray(heights, np.float32)[..., None], mi.Bitmap.PixelFormat.Y)
    return encode(bitmap, mi.Bitmap.FileFormat.OpenEXR)


def write_map(path, normals, bits: int = 8):
    """Write the normal map PNG (8- or 16-bit) atomically; returns the path."""
    return write_baked(path, normals, bits)[0]


def write_heights(path, heights):
    """Write the heights (H, W, world units) as a one-channel 32-bit float OpenEXR, atomically
    (what Mitsuba's ``bitmap`` reads with ``raw=True``); returns the path."""
    from mfnormal.io.images import atomic_write, write_bytes

    data = _heights_bytes(heights)
    return atomic_write(path, lambda p: write_bytes(p, data))


def write_baked(path, normals, bits: int = 8, heights_path=None, heights=None) -> list:
    """The normal map PNG at ``path`` and, with ``heights_path``, the ``heights`` EXR there, written
    as one (both or neither: :func:`mfnormal.io.images.atomic_write_all`); returns the paths."""
    from mfnormal.io.images import atomic_write_all, write_bytes

    map_data = _map_bytes(normals, bits)
    items = [(path, lambda p: write_bytes(p, map_data))]
    if heights_path is not None:
        heights_data = _heights_bytes(heights)
        items.append((heights_path, lambda p: write_bytes(p, heights_data)))
    return atomic_write_all(items)


# -- The baker ---------------------------------------------------------------------------------

def _as_mesh(mesh, what):
    return load_mesh(mesh, what) if isinstance(mesh, (str, Path)) else mesh


def check_low_poly(low, what: str = "low-poly mesh"):
    """(positions, normals, uvs, faces) of the low-poly; :class:`BakeError` without UVs or normals."""
    positions, normals, uvs, faces = mesh_arrays(low)
    if uvs is None:
        raise BakeError(f"the {what} has no UVs (texture coordinates); unwrap it first "
                        "(mfnormal bake --unwrap OUT.ply, with xatlas)")
    if normals is None:
        raise BakeError(f"the {what} has no vertex normals (it is flat-shaded); give it smooth "
                        "vertex normals")
    if len(faces) == 0:
        raise BakeError(f"the {what} has no triangles")
    return positions, normals, uvs, faces


def default_cage(positions) -> float:
    """CAGE_FRACTION of the bounding-box diagonal of ``positions``."""
    return CAGE_FRACTION * float(np.linalg.norm(positions.max(axis=0) - positions.min(axis=0)))


def bake(high, low, size: int = 1024, cage: float | None = None, frame: str = "mikktspace",
         padding: int = 4, high_normals: str = "shading") -> Baked:
    """Bake the tangent-space normal map of ``high`` onto ``low`` (Mitsuba meshes or paths of PLY
    or OBJ files; the low-poly needs UVs and vertex normals), and its heights over ``low``: a
    ``size``² :class:`Baked`.

    ``cage``: how far from the low-poly surface rays look for the high-poly (default:
    CAGE_FRACTION of the low-poly's bounding-box diagonal); ``frame``: ``mikktspace`` or
    ``mitsuba`` (see the module's docstring); ``padding``: texels to dilate the islands by;
    ``high_normals``: the high-poly's ``shading`` (interpolated) or ``geometric`` normal.
    A JIT variant (``llvm_*``, ``cuda_*``) must be set."""
    if frame not in TANGENT_FRAMES:
        raise BakeError(f"frame must be one of {', '.join(TANGENT_FRAMES)}, got '{frame}'")
    if high_normals not in HIGH_NORMALS:
        raise BakeError(f"high_normals must be one of {', '.join(HIGH_NORMALS)}, got '{high_normals}'")
    if not SIZE_RANGE[0] <= size <= SIZE_RANGE[1]:
        raise BakeError(f"size {size} is out of range ({SIZE_RANGE[0]} to {SIZE_RANGE[1]})")
    high_mesh, low_mesh = _as_mesh(high, "high-poly mesh"), _as_mesh(low, "low-poly mesh")
    arrays = check_low_poly(low_mesh)
    cage = default_cage(arrays[0]) if cage is None else float(cage)
    if not (0 < cage < float("inf")):
        raise BakeError(f"cage {cage}: expected a distance above 0")
    texel, tri, bary = rasterise(arrays[2], arrays[3], size)
    p, tangent, bitangent, n = texel_frames(arrays, tri, bary, frame)
    normal, distance, hit = high_surface_at(high_mesh, p, n, cage, high_normals == "geometric")
    local = np.stack([np.sum(normal * v, axis=1) for v in (tangent, bitangent, n)], axis=1)
    normals = np.zeros((size * size, 3))
    normals[:, 2] = 1.0
    normals[texel[hit]] = local[hit]
    heights = np.zeros((size * size, 1))
    heights[texel[hit], 0] = distance[hit]
    covered, hits = np.zeros(size * size, bool), np.zeros(size * size, bool)
    covered[texel], hits[texel[hit]] = True, True
    covered, hits = covered.reshape(size, size), hits.reshape(size, size)
    normals = dilate(normals.reshape(size, size, 3), covered, padding)
    heights = dilate(heights.reshape(size, size, 1), covered, padding, unit=False)
    return Baked(normals, covered, hits, heights[..., 0])
