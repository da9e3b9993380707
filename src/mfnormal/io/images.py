"""Writing renders: NaN/Inf and negative-pixel accounting, tonemapping, atomic EXR/PNG pairs, PNG bytes.

A render is an (H, W, C) float array whose channels are named as the film names
them (:func:`film_channel_names`): ``Y`` (mono variants, a ``luminance`` film),
``Y A``, ``R G B``, ``R G B A``, or those followed by AOVs (the ``aov``
integrator: ``dd.y``, ``nn.X`` ...). The EXR keeps every channel under its
name; the PNG is the tonemapped colour (grey for ``Y`` films).

:func:`save_render` writes the two files as a pair: both go to temporary files in
the output folder first, and only when both are complete are they renamed
(with SIGINT and SIGTERM held back between the two renames), so a failure (a
full disk, a signal) leaves the previous pair, never a new EXR next to an old
PNG, and no temporary file.
"""

from __future__ import annotations

import struct
import zlib
from pathlib import Path

import numpy as np

from mfnormal.files import atomic_write_all, write_bytes

_STANDARD = {("Y",): "Y", ("Y", "A"): "YA", ("R", "G", "B"): "RGB", ("R", "G", "B", "A"): "RGBA"}


def default_channel_names(n: int) -> list[str]:
    """Channel names of an n-channel image without a film to ask."""
    return {1: ["Y"], 2: ["Y", "A"], 3: ["R", "G", "B"], 4: ["R", "G", "B", "A"]}.get(
        n, ["R", "G", "B"] + [f"C{i}" for i in range(3, n)])


def film_channel_names(film, n: int) -> list[str]:
    """The names of the ``n`` channels that ``mi.render`` returned for ``film`` (after a
    render): its base channels (``Y``, ``Y A``, ``R G B`` or ``R G B A``) and AOVs."""
    try:
        bitmap = film.bitmap(raw=False)
        names = [bitmap.struct_()[i].name for i in range(bitmap.channel_count())]
        base = int(film.base_channels_count())
    except Exception:  # noqa: BLE001  (a film without a developed bitmap)
        return default_channel_names(n)
    if len(names) == n:
        return names
    # mi.render leaves out the channels a nested integrator records for itself
    # (the aov integrator's '<id>.R' ...): keep the base channels and the last AOVs.
    if base <= n <= len(names) and len(names) - (n - base) >= base:
        return names[:base] + names[len(names) - (n - base):]
    return default_channel_names(n)


def colour_channels(names) -> list[int]:
    """Indices of the colour channels (R, G, B or Y) among the base channels."""
    names = list(names)
    if names[:3] == ["R", "G", "B"]:
        return [0, 1, 2]
    if names[:1] == ["Y"]:
        return [0]
    return [0]


def sanitize_counts(img: np.ndarray, names=None) -> tuple[np.ndarray, int, int]:
    """(image, pixels with a NaN/Inf value, pixels with a negative colour value).

    NaN/Inf in any channel and negative colour values are written as 0; alpha and
    AOV channels keep their negative values (a normal or position AOV has them)."""
    img = np.array(img, dtype=np.float32, copy=True)
    if img.ndim == 2:
        img = img[..., None]
    names = names or default_channel_names(img.shape[-1])
    finite = np.isfinite(img)
    nonfinite = int((~finite.all(axis=-1)).sum())
    img[~finite] = 0.0
    colour = img[..., colour_channels(names)]
    negative_px = (colour < 0).any(axis=-1)
    negative = int(negative_px.sum())
    if negative:
        idx = colour_channels(names)
        img[..., idx] = np.maximum(img[..., idx], 0.0)
    return img, nonfinite, negative


def tonemap(rgb: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Linear RGB → 8-bit sRGB (exposure in stops, clipped)."""
    x = np.clip(np.asarray(rgb, np.float32) * (2.0 ** exposure), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


def output_paths(output) -> tuple[Path, Path]:
    """(EXR, PNG) paths for an output name given with or without extension."""
    output = Path(output)
    stem = output.with_suffix("") if output.suffix.lower() in (".png", ".exr", ".jpg") else output
    return stem.with_suffix(".exr"), stem.with_suffix(".png")


def save_render(img: np.ndarray, output, exposure: float = 0.0, names=None) -> tuple[Path, Path]:
    """Write a linear EXR (every channel, named ``names``) and a tonemapped PNG (the colour)
    next to each other, as a pair (see :func:`mfnormal.files.atomic_write_all`)."""
    import mitsuba as mi

    exr, png = output_paths(output)
    linear = np.ascontiguousarray(img, dtype=np.float32)
    if linear.ndim == 2:
        linear = linear[..., None]
    names = list(names or default_channel_names(linear.shape[-1]))
    if len(names) != linear.shape[-1]:
        raise ValueError(f"{len(names)} channel names for {linear.shape[-1]} channels")
    fmt = _STANDARD.get(tuple(names))
    if fmt is not None:
        exr_bitmap = mi.Bitmap(linear, getattr(mi.Bitmap.PixelFormat, fmt))
    else:
        exr_bitmap = mi.Bitmap(linear, mi.Bitmap.PixelFormat.MultiChannel, names)
    idx = colour_channels(names)
    colour = np.ascontiguousarray(tonemap(linear[..., idx], exposure))
    png_bitmap = mi.Bitmap(colour, mi.Bitmap.PixelFormat.RGB if len(idx) == 3 else mi.Bitmap.PixelFormat.Y)
    exr_data = encode(exr_bitmap, mi.Bitmap.FileFormat.OpenEXR)
    png_data = encode(png_bitmap, mi.Bitmap.FileFormat.PNG)
    atomic_write_all([(exr, lambda p: write_bytes(p, exr_data)), (png, lambda p: write_bytes(p, png_data))])
    return exr, png


def encode(bitmap, file_format) -> bytes:
    """``bitmap`` encoded as ``file_format``, in memory."""
    import mitsuba as mi

    stream = mi.MemoryStream()
    bitmap.write(stream, file_format)
    return stream.raw_buffer()


def png_bytes(rgb8: np.ndarray) -> bytes:
    """8-bit RGB (H x W x 3) or grey (H x W) as PNG file bytes."""
    a = np.ascontiguousarray(rgb8, dtype=np.uint8)
    h, w = a.shape[:2]
    color = 2 if a.ndim == 3 else 0
    rows = np.concatenate([np.zeros((h, 1), np.uint8), a.reshape(h, -1)], axis=1)

    def chunk(tag: bytes, data: bytes) -> bytes:
        return struct.pack(">I", len(data)) + tag + data + struct.pack(">I", zlib.crc32(tag + data))

    return (b"\x89PNG\r\n\x1a\n" + chunk(b"IHDR", struct.pack(">IIBBBBB", w, h, 8, color, 0, 0, 0))
            + chunk(b"IDAT", zlib.compress(rows.tobytes(), 6)) + chunk(b"IEND", b""))
