"""Writing renders: NaN/Inf accounting, tonemapping and atomic EXR/PNG output."""

from __future__ import annotations

import os
import tempfile
from pathlib import Path

import numpy as np


def sanitize(rgb: np.ndarray) -> tuple[np.ndarray, int]:
    """Replace NaN/Inf (and negative) pixels by 0; return the image and how many pixels were bad."""
    rgb = np.asarray(rgb, dtype=np.float32)
    bad = ~np.isfinite(rgb).all(axis=-1)
    out = np.where(np.isfinite(rgb), np.maximum(rgb, 0.0), 0.0).astype(np.float32)
    return out, int(bad.sum())


def tonemap(rgb: np.ndarray, exposure: float = 0.0) -> np.ndarray:
    """Linear RGB → 8-bit sRGB (exposure in stops, clipped)."""
    x = np.clip(np.asarray(rgb, np.float32) * (2.0 ** exposure), 0.0, 1.0)
    srgb = np.where(x <= 0.0031308, 12.92 * x, 1.055 * np.power(x, 1 / 2.4) - 0.055)
    return np.round(srgb * 255.0).astype(np.uint8)


def atomic_write(path, write) -> Path:
    """Call ``write(tmp_path)`` then rename onto ``path``: no half-written file on error."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    umask = os.umask(0)
    os.umask(umask)
    try:
        write(tmp)
        os.chmod(tmp, 0o666 & ~umask)   # mkstemp makes it private; give it the usual mode
        os.replace(tmp, path)
    except BaseException:
        if os.path.exists(tmp):
            os.unlink(tmp)
        raise
    return path


def output_paths(output) -> tuple[Path, Path]:
    """(EXR, PNG) paths for an output name given with or without extension."""
    output = Path(output)
    stem = output.with_suffix("") if output.suffix.lower() in (".png", ".exr", ".jpg") else output
    return stem.with_suffix(".exr"), stem.with_suffix(".png")


def save_render(rgb: np.ndarray, output, exposure: float = 0.0) -> tuple[Path, Path]:
    """Write a linear EXR and a tonemapped PNG next to each other, atomically."""
    import mitsuba as mi

    exr, png = output_paths(output)
    linear = np.ascontiguousarray(rgb, dtype=np.float32)
    atomic_write(exr, lambda p: mi.Bitmap(linear, mi.Bitmap.PixelFormat.RGB).write(p))
    atomic_write(png, lambda p: mi.Bitmap(tonemap(linear, exposure), mi.Bitmap.PixelFormat.RGB)
                 .write(p, mi.Bitmap.FileFormat.PNG))
    return exr, png
