"""Dr.Jit arrays from numpy values, every one the same kernel input (the references' and the tests')."""

from __future__ import annotations

import mitsuba as mi
import numpy as np

__all__ = ["aligned", "floats", "uints", "vec3"]


def aligned(a, dtype=np.float32):
    """``a`` as a contiguous numpy array of ``dtype`` that starts on a 64-byte boundary.

    Dr.Jit reads a numpy array where it lies, and its LLVM backend compiles the loads from it
    as aligned or unaligned depending on where the array starts: the same computation on
    arrays that start elsewhere is another kernel, compiled again and missing the kernel
    cache (every input a coin flip with numpy's 16-byte-aligned allocations). Inputs built
    here always give the same kernel."""
    a = np.asarray(a, dtype)
    buf = np.empty(a.nbytes + 64, np.uint8)
    start = (-buf.ctypes.data) % 64
    out = buf[start:start + a.nbytes].view(dtype).reshape(a.shape)
    out[...] = a
    return out


def floats(a):
    """mi.Float from values (as float32, :func:`aligned`)."""
    return mi.Float(aligned(np.ravel(a)))


def uints(a):
    """mi.UInt32 from values (:func:`aligned`)."""
    return mi.UInt32(aligned(np.ravel(a), np.uint32))


def vec3(a):
    """mi.Vector3f from (n, 3) or (3,) values (as float32, :func:`aligned`)."""
    a = np.asarray(a, np.float32).reshape(-1, 3)
    return mi.Vector3f(*(aligned(a[:, i]) for i in range(3)))
