"""A validated glTF file's data as numpy arrays: its accessors and its images.

:class:`GLTFFile` reads a file through :func:`mfnormal.io.gltf_validate.read_model`, which
validates everything first, and parses its JSON with ``pygltflib``. An accessor is read as a
(count, width) array from its bufferView (strided, sparse, or zeros without a view;
normalized integers become floats), an image is decoded by Mitsuba from its PNG or JPEG bytes
into raw values in [0, 1]; an image that cannot be decoded is skipped with a warning.
"""

from __future__ import annotations

import warnings
from pathlib import Path

import numpy as np

from mfnormal.io.gltf_validate import GLTFError, decode_error, read_model
from mfnormal.io.inputs import DEFAULT_LIMITS, Limits
from mfnormal.io.messages import one_line

_COMPONENT = {5120: np.int8, 5121: np.uint8, 5122: np.int16, 5123: np.uint16, 5125: np.uint32,
              5126: np.float32}
_WIDTH = {"SCALAR": 1, "VEC2": 2, "VEC3": 3, "VEC4": 4, "MAT2": 4, "MAT3": 9, "MAT4": 16}


def warn(msg):
    warnings.warn(f"glTF: {msg}", RuntimeWarning, stacklevel=3)


class GLTFFile:
    """A parsed glTF file: its JSON (pygltflib), buffers and decoded images, read through
    :func:`mfnormal.io.gltf_validate.read_model` (which validates everything first)."""

    def __init__(self, path: Path, limits: Limits = DEFAULT_LIMITS):
        import pygltflib

        self.path = path
        self.model = read_model(path, limits)
        try:
            with warnings.catch_warnings():
                warnings.simplefilter("ignore")
                self.gltf = pygltflib.GLTF2.gltf_from_json(self.model.text)
        except Exception as exc:  # noqa: BLE001  (pygltflib raises anything on a broken file)
            raise decode_error(self.model.doc, exc) from None
        self.buffers = self.model.buffers
        self._images = {}

    def accessor(self, index: int) -> np.ndarray:
        """Accessor ``index`` as an (count, width) array; normalized integers become floats."""
        acc = self.gltf.accessors[index]
        dtype = np.dtype(_COMPONENT[acc.componentType])
        width = _WIDTH[acc.type]
        if acc.bufferView is None:
            data = np.zeros((acc.count, width), dtype)
        else:
            view = self.gltf.bufferViews[acc.bufferView]
            data = self._view(acc.bufferView, acc.byteOffset or 0, dtype, width, acc.count,
                              view.byteStride)
        if acc.sparse is not None:
            s = acc.sparse
            idx = self._view(s.indices.bufferView, s.indices.byteOffset or 0,
                             np.dtype(_COMPONENT[s.indices.componentType]), 1, s.count)[:, 0]
            if idx.max() >= acc.count:
                raise GLTFError(f"accessors[{index}].sparse.indices: index {int(idx.max())} is out of "
                                f"range (the accessor has {acc.count} elements)")
            val = self._view(s.values.bufferView, s.values.byteOffset or 0, dtype, width, s.count)
            data = data.copy()
            data[idx.astype(np.int64)] = val
        if acc.normalized and dtype.kind in "iu":
            data = np.maximum(data / np.float32(np.iinfo(dtype).max), -1.0).astype(np.float32)
        return data

    def _view(self, view_index, offset, dtype, width, count, stride=None) -> np.ndarray:
        """``count`` elements of ``width`` × ``dtype`` from bufferView ``view_index`` at
        ``offset``, ``stride`` bytes apart (None: tightly packed). The validation made
        sure they lie inside the view; this checks it again before any strided read."""
        view = self.gltf.bufferViews[view_index]
        buf = self.buffers[view.buffer]
        elem = dtype.itemsize * width
        stride = stride or elem
        if count == 0:
            return np.zeros((0, width), dtype)
        start = (view.byteOffset or 0) + offset
        end = start + stride * (count - 1) + elem
        if not (stride >= elem > 0 and offset >= 0 and end - (view.byteOffset or 0) <= view.byteLength
                and end <= len(buf)):
            raise GLTFError(f"bufferViews[{view_index}]: a read of {count} x {elem} bytes at {offset} "
                            "is out of bounds")
        raw = np.frombuffer(buf, np.uint8, end - start, start)
        rows = np.lib.stride_tricks.as_strided(raw, (count, elem), (stride, 1), writeable=False)
        return np.ascontiguousarray(rows).view(dtype).reshape(count, width)

    def image(self, index: int) -> np.ndarray | None:
        """Image ``index`` as raw values in [0, 1], (h, w, channels) float32; None if undecodable."""
        if index in self._images:
            return self._images[index]
        import mitsuba as mi

        img = self.gltf.images[index]
        info = self.model.images[index]
        name = "a data: URI" if (img.uri or "").startswith("data:") else (img.uri or img.mimeType)
        arr = None
        if info.fmt is None:
            warn(f"image {index} ({name}) is not a PNG or JPEG file; texture ignored")
        else:
            try:
                stream = mi.MemoryStream(len(info.data))
                stream.write(info.data)
                stream.seek(0)
                fmt = mi.Bitmap.FileFormat.PNG if info.fmt == "png" else mi.Bitmap.FileFormat.JPEG
                arr = np.array(mi.Bitmap(stream, fmt))
            except Exception as exc:  # noqa: BLE001  (an unreadable texture is skipped, not fatal)
                warn(f"cannot decode image {index} ({name}): {one_line(exc)}; texture ignored")
                arr = None
        if arr is not None:
            if arr.ndim == 2:
                arr = arr[:, :, None]
            if arr.dtype.kind in "iu":
                arr = arr.astype(np.float32) / np.float32(np.iinfo(arr.dtype).max)
            arr = arr.astype(np.float32)
            if arr.shape[0] * arr.shape[1] != info.width * info.height:
                warn(f"image {index} decoded to {arr.shape[1]}x{arr.shape[0]} pixels, not the "
                     f"{info.width}x{info.height} of its header; texture ignored")
                arr = None
        self._images[index] = arr
        return arr
