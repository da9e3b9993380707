"""Padding a baked map's islands, and writing the map and its heights.

:func:`dilate` spreads the covered texels' values ``padding`` texels outwards (each new texel the
mean of its covered neighbours), so that bilinear lookups along UV seams read no background; a
bake pads in bands of ``Batches.band`` texels. :func:`encode_map` turns unit normals into 8- or
16-bit RGB = (n + 1)/2, :func:`write_map` writes the PNG and :func:`write_heights` the heights
as a one-channel float EXR, each atomically; :func:`write_baked` writes them all or none.
"""

from __future__ import annotations

from pathlib import Path
from typing import Callable, Sequence

import numpy as np

from mfnormal.io.bake_inputs import BATCHES, BakeError, PathLike
from mfnormal.io.bake_texels import unit_vectors


# -- Padding -------------------------------------------------------------------------------------

def _bands(height: int, width: int, band: int = BATCHES.band):
    """Row ranges (first, last) of about ``band`` texels each."""
    rows = max(1, band // max(width, 1))
    return [(r, min(r + rows, height)) for r in range(0, height, rows)]


def dilate(normals, known, padding: int, unit: bool = True):
    """``normals`` (H, W, C) with the texels outside ``known`` within ``padding`` texels (8-
    neighbourhood rings) set to the mean of their known neighbours (normalised where ``unit``),
    ring by ring."""
    out = normals.copy()
    dilate_into(out, known, padding, unit)
    return out


def dilate_into(normals, known, padding: int, unit: bool = True, band: int = BATCHES.band) -> None:
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
        normals[ring] = unit_vectors(total[ring]) if unit else total[ring] / count[ring][:, None]
        known |= ring
    return normals


# -- Encoding and writing ----------------------------------------------------------------------

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
    if normals.ndim != 3 or normals.shape[-1] != 3 or not np.issubdtype(normals.dtype, np.number):
        raise BakeError(f"normals of shape {normals.shape} ({normals.dtype}): expected an (H, W, 3) "
                        "array of numbers, one unit normal per texel")
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

    heights = np.asarray(heights)
    if heights.ndim == 3 and heights.shape[-1] == 1:          # as Mitsuba's Bitmap reads the EXR
        heights = heights[..., 0]
    if heights.ndim != 2 or not np.issubdtype(heights.dtype, np.number):
        raise BakeError(f"heights of shape {heights.shape}: expected an (H, W) array of numbers, one "
                        "height per texel")
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
