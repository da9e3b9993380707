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

The baker's steps: :mod:`~mfnormal.io.bake_inputs` (the checks, the batches),
:mod:`~mfnormal.io.bake_texels` (rasterising the UV triangles, the frames at the texels),
:mod:`~mfnormal.io.bake_trace` (the working scale, tracing the high-poly) and
:mod:`~mfnormal.io.bake_write` (padding, encoding, writing); the meshes are built by
:mod:`mfnormal.io.meshes`. This module runs them, and its names are theirs too.
"""

from __future__ import annotations

import warnings
from dataclasses import dataclass
from typing import TYPE_CHECKING, Callable

import numpy as np

# The steps' public names are this module's too (``from mfnormal.io import bake``: ``bake.rasterise``).
from mfnormal.io.bake_inputs import (BAKE_OVERHEAD_BYTES, BATCHES, BYTES_PER_TEXEL, HIGH_NORMALS,  # noqa: F401
                                     MESH_SUFFIXES, SIZE_RANGE, TANGENT_FRAMES, TEXELS_PER_PASS, BakeError, Batches,
                                     PathLike, check_high_poly, check_low_poly, check_options, checked_inputs,
                                     load_mesh, memory_needed)
from mfnormal.io.bake_texels import outside_map, rasterise, texel_frames, texel_owners, uv_problem  # noqa: F401
from mfnormal.io.bake_trace import (CAGE_FRACTION, RAY_START, WORKING_SIZE, default_cage, diagonal,  # noqa: F401
                                    high_surface_at, scaled_arrays, scaled_mesh, trace_passes, working_scale)
from mfnormal.io.bake_write import dilate, dilate_into, encode_map, write_baked, write_heights, write_map  # noqa: F401
from mfnormal.io.meshes import MeshArrays, mesh_arrays, mitsuba_mesh
from mfnormal.normals.mikktspace import mikktspace, split_vertices

if TYPE_CHECKING:
    import mitsuba as mi

__all__ = ["BakeError", "Baked", "MESH_SUFFIXES", "TANGENT_FRAMES", "SIZE_RANGE", "load_mesh",
           "mesh_arrays", "unwrap", "bake", "encode_map", "write_map", "write_heights", "write_baked",
           "tangent_mesh", "check_low_poly", "check_high_poly", "memory_needed"]


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

    faces = np.asarray(faces, np.int64)
    corner_t = mikktspace(positions, normals, uvs, faces, flip_v=True)
    split, v = split_vertices(p=np.asarray(positions)[faces], n=np.asarray(normals)[faces],
                              uv=np.asarray(uvs)[faces], t=corner_t)
    return mitsuba_mesh(name, bsdf if bsdf is not None else mi.load_dict({"type": "diffuse"}),
                        v["p"], v["n"], v["uv"], v["t"], split)


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
    bytes the bake may take (default: what the system, or the process's control group, has
    available), checked before it starts.
    A JIT variant (``llvm_*``, ``cuda_*``) must be set. Every input is checked first
    (:class:`BakeError`, one line); a warning says when most texels' normals face away from
    the low-poly's (one of the meshes' normals is flipped)."""
    import mitsuba as mi

    check_options(progress, batches)
    high_mesh, (positions, normals, uvs, faces) = checked_inputs(high, low, size, cage, frame, padding,
                                                                  high_normals, memory_limit)
    # Trace at a working scale (a power of two: exact); the heights are scaled back.
    scale = working_scale(diagonal(positions))
    high_mesh = scaled_mesh(high_mesh, scale)
    if scale != 1.0:
        positions, normals = scaled_arrays(positions, normals, faces, scale)
    cage = default_cage(positions) if cage is None else float(cage) * scale
    bbox = high_mesh.bbox()
    scene_size = diagonal(np.concatenate([positions, [list(bbox.min), list(bbox.max)]]))
    spans_scene = cage >= scene_size
    cage = min(cage, scene_size)

    owner = texel_owners(uvs, faces, size, batches.chunk)
    covered = owner >= 0
    if not covered.any():
        raise BakeError(uv_problem(uvs, faces, size))
    outside = outside_map(uvs, faces)
    if outside:
        warnings.warn(f"{outside} of the low-poly mesh's {len(faces)} triangles have UVs wholly "
                      "outside the map's 0 to 1 square (another UDIM tile, or a repeat) and are "
                      "not baked", stacklevel=2)
    scene = mi.load_dict({"type": "scene", "high": high_mesh})
    normals_out, heights, hits = trace_passes(scene, (positions, normals, uvs, faces), owner, size, frame,
                                              cage, high_normals == "geometric", progress, batches.trace)
    heights /= scale
    covered, hits = covered.reshape(size, size), hits.reshape(size, size)
    normals_out = normals_out.reshape(size, size, 3)
    heights = heights.reshape(size, size, 1)
    dilate_into(normals_out, covered, padding, band=batches.band)
    dilate_into(heights, covered, padding, unit=False, band=batches.band)
    return Baked(normals_out, covered, hits, heights[..., 0], spans_scene)
