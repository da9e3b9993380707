"""Reading a glTF file's bytes: the ``.gltf`` or ``.glb`` container, its buffers and images, within a budget.

:func:`read_container` parses the ``.glb`` container itself (magic, version 2, chunk lengths
within the file, JSON first). A URI is ``data:`` (base64) or a relative path that resolves
(symbolic links followed) inside the model's folder, to a regular file, of at least the
declared ``byteLength``, and only that much is read (:func:`uri_bytes`); nothing else is
opened. A :class:`Budget` keeps the file, buffers and image files together at most
``Limits.data_bytes``. :func:`read_buffers` and :func:`read_images` read a checked document's
data; an image's size comes from its PNG or JPEG header, before anything decodes it.
"""

from __future__ import annotations

import base64
import binascii
import os
import re
import struct
from dataclasses import dataclass
from pathlib import Path, PureWindowsPath
from urllib.parse import unquote

from mfnormal.io.gltf_json import GLTFError, fail, show
from mfnormal.io.image_headers import image_header
from mfnormal.io.inputs import Limits, not_regular

_GLB_MAGIC, _GLB_JSON, _GLB_BIN = b"glTF", 0x4E4F534A, 0x004E4942


@dataclass
class ImageData:
    """An image's encoded bytes and header: ``fmt`` is 'png', 'jpeg' or None (not decodable)."""
    data: bytes
    fmt: str | None
    width: int = 0
    height: int = 0


class Budget:
    """The bytes a model may still read: ``Limits.data_bytes`` for the file, its buffers and its
    images together."""

    def __init__(self, limits: Limits):
        self.limits = limits
        self.left = limits.data_bytes

    def take(self, n: int, where: str, what: str):
        """Take ``n`` bytes for ``what``; a :class:`GLTFError` at ``where`` past the budget."""
        if n > self.left:
            fail(where, f"{what} ({n} bytes) would take the data read for this model past "
                        f"{self.limits.data_bytes} bytes ({self.limits.hint('data_bytes')})")
        self.left -= n


def _read_regular(path: Path, where: str, shown: str, budget: Budget, length: int | None = None) -> bytes:
    """The bytes of the regular file ``path``: the first ``length`` (at least that many must
    exist), or all of it. The file is opened without blocking and checked with fstat,
    so a FIFO, device or folder is refused without being read."""
    flags = os.O_RDONLY | getattr(os, "O_NONBLOCK", 0) | getattr(os, "O_CLOEXEC", 0) | getattr(os, "O_BINARY", 0)
    try:
        fd = os.open(path, flags)
    except OSError as exc:
        fail(where, f"cannot open '{shown}' ({exc.strerror or type(exc).__name__})")
    try:
        st = os.fstat(fd)
        kind = not_regular(st.st_mode)
        if kind:
            fail(where, f"'{shown}' is {kind}, not a regular file")
        if length is None:
            length = st.st_size
        elif st.st_size < length:
            fail(where, f"'{shown}' has {st.st_size} bytes, less than the byteLength {length}")
        budget.take(length, where, f"'{shown}'")
        chunks, left = [], length
        while left > 0:
            chunk = os.read(fd, min(left, 1 << 24))
            if not chunk:
                fail(where, f"'{shown}' ended after {length - left} of {length} bytes")
            chunks.append(chunk)
            left -= len(chunk)
        return b"".join(chunks)
    finally:
        os.close(fd)


def _short(text: str, n: int = 80) -> str:
    """``text`` cut to ``n`` characters, for a message."""
    return text if len(text) <= n else text[:n - 3] + "..."


def _uri_path(uri: str, folder: Path, where: str) -> Path:
    """The file a relative URI names, which must lie inside ``folder`` (links resolved)."""
    shown = _short(uri)
    scheme = re.match(r"^([A-Za-z][A-Za-z0-9+.-]*):", uri)
    if scheme:
        fail(where, f"'{shown}': {scheme.group(1)}: URIs are not read; a glTF file may only refer "
                    "to files in its own folder (relative paths) and to data: URIs")
    rel = unquote(uri)
    if not rel or "\x00" in rel:
        fail(where, f"'{shown}' is not a file name")
    if rel.startswith(("/", "\\")) or os.path.isabs(rel) or PureWindowsPath(rel).drive:
        fail(where, f"'{shown}' is an absolute path; a glTF file may only refer to files in its own folder")
    base = os.path.realpath(folder)
    target = os.path.realpath(os.path.join(base, rel))
    if os.path.commonpath([base, target]) != base:
        fail(where, f"'{shown}' is outside the model's folder; a glTF file may only refer to files "
                    "in its own folder")
    return Path(target)


def _data_uri(uri: str, where: str, budget: Budget) -> bytes:
    """The bytes of a base64 ``data:`` URI."""
    header, sep, payload = uri.partition(",")
    if not sep or not header.endswith(";base64"):
        fail(where, "a data: URI must be base64 (data:<type>;base64,<data>)")
    payload = re.sub(r"\s+", "", payload)
    budget.take(len(payload) * 3 // 4, where, "the data: URI")
    try:
        return base64.b64decode(payload, validate=True)
    except (binascii.Error, ValueError):
        fail(where, "the data: URI is not valid base64")


def uri_bytes(uri, folder: Path, where: str, budget: Budget, length: int | None = None) -> bytes:
    """The bytes ``uri`` names (a ``data:`` URI or a file in ``folder``): the first ``length``, or all."""
    if not isinstance(uri, str):
        fail(where, f"expected a string, got {show(uri)}")
    if uri.startswith("data:"):
        data = _data_uri(uri, where, budget)
        if length is not None:
            if len(data) < length:
                fail(where, f"the data: URI holds {len(data)} bytes, less than the byteLength {length}")
            data = data[:length]
        return data
    return _read_regular(_uri_path(uri, folder, where), where, _short(uri), budget, length)


def read_container(path: Path, budget: Budget) -> tuple[str, bytes | None]:
    """(JSON text, GLB binary chunk or None) of a .gltf or .glb file."""
    data = _read_regular(path, "", path.name, budget)
    if data[:4] != _GLB_MAGIC:
        if path.suffix.lower() == ".glb":
            raise GLTFError("not a valid glTF 2.0 file (a .glb file starts with 'glTF')")
        try:
            return data.decode("utf-8-sig"), None
        except UnicodeDecodeError as exc:
            raise GLTFError(f"not a valid glTF 2.0 file (the JSON is not UTF-8: {exc.reason} at byte "
                            f"{exc.start})") from None

    def bad(problem):
        raise GLTFError(f"not a valid glTF 2.0 file (GLB: {problem})")

    if len(data) < 20:
        bad(f"{len(data)} bytes, too short for a header and a chunk")
    version, length = struct.unpack_from("<II", data, 4)
    if version != 2:
        bad(f"version {version}; only version 2 is supported")
    if length > len(data) or length < 20:
        bad(f"the header says {length} bytes, the file has {len(data)}")
    chunks, offset = [], 12
    while offset + 8 <= length:
        size, kind = struct.unpack_from("<II", data, offset)
        if offset + 8 + size > length:
            bad(f"chunk {len(chunks)} of {size} bytes runs past the end of the file")
        chunks.append((kind, data[offset + 8:offset + 8 + size]))
        offset += 8 + size
        offset += -offset % 4 if offset < length else 0
    if not chunks or chunks[0][0] != _GLB_JSON:
        bad("the first chunk is not JSON")
    binary = chunks[1][1] if len(chunks) > 1 and chunks[1][0] == _GLB_BIN else None
    try:
        return chunks[0][1].decode("utf-8-sig"), binary
    except UnicodeDecodeError as exc:
        bad(f"the JSON chunk is not UTF-8 ({exc.reason} at byte {exc.start})")


def read_buffers(buffers: list, binary: bytes | None, folder: Path, budget: Budget) -> list:
    """The bytes of the checked ``buffers``, each exactly its ``byteLength``: from its URI, or
    for buffers[0] of a .glb file without one, from the ``binary`` chunk."""
    out = []
    for i, b in enumerate(buffers):
        where = f"buffers[{i}]"
        length = b["byteLength"]
        if b.get("uri") is not None:
            out.append(uri_bytes(b["uri"], folder, f"{where}.uri", budget, length))
        elif i == 0 and binary is not None:
            if len(binary) < length:
                fail(where, f"byteLength {length} is more than the GLB's binary chunk ({len(binary)} bytes)")
            out.append(binary[:length])
        else:
            fail(where, "has no uri, and only buffers[0] of a .glb file may use the binary chunk")
    return out


def read_images(images: list, views: list, buffers: list, folder: Path, budget: Budget, limits: Limits) -> list:
    """The :class:`ImageData` of the checked ``images``, from their URIs or bufferViews: each at
    most ``limits.image_pixels`` by its header, all at most ``limits.texture_pixels``."""
    out, pixels = [], 0
    for i, img in enumerate(images):
        where = f"images[{i}]"
        if img.get("uri") is not None:
            data = uri_bytes(img["uri"], folder, f"{where}.uri", budget)
        else:
            view = views[img["bufferView"]]
            start = view.get("byteOffset", 0)
            data = buffers[view["buffer"]][start:start + view["byteLength"]]
        header = image_header(data)
        if header is None:
            out.append(ImageData(data, None))
            continue
        fmt, w, h = header
        if w * h > limits.image_pixels:
            fail(where, f"the {fmt.upper()} is {w}x{h} pixels, more than an image may have "
                        f"({limits.hint('image_pixels')})")
        pixels += w * h
        if pixels > limits.texture_pixels:
            fail(where, f"the images take the model past {limits.texture_pixels} pixels "
                        f"({limits.hint('texture_pixels')})")
        out.append(ImageData(data, fmt, w, h))
    return out
