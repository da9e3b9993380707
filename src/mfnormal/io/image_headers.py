"""Image sizes read from file headers, without decoding the pixels.

The glTF loader and the XML scene check (:func:`mfnormal.io.inputs.check_xml_scene`)
compare these sizes with :class:`mfnormal.io.inputs.Limits` before anything is
decoded, so that an image that declares 100000² pixels fails in one line instead
of exhausting memory inside Mitsuba.

- :func:`image_header`: PNG (IHDR) and JPEG (the frame header, after any APPn
  segments), from bytes; the formats glTF allows;
- :func:`file_image_size`: those two and the other formats Mitsuba's ``Bitmap``
  reads: OpenEXR (the first part's ``dataWindow``), Radiance RGBE (``.hdr``), PFM,
  BMP, TGA and PPM/PGM; from the first bytes of a file.
"""

from __future__ import annotations

import re
import struct
from pathlib import Path

__all__ = ["image_header", "file_image_size", "HEADER_BYTES"]

HEADER_BYTES = 1 << 20   # read at most this much of a file (an EXR's header holds its attributes)

_SOF = {0xC0, 0xC1, 0xC2, 0xC3, 0xC5, 0xC6, 0xC7, 0xC9, 0xCA, 0xCB, 0xCD, 0xCE, 0xCF}


def _sized(fmt: str, w: int, h: int):
    return (fmt, w, h) if w > 0 and h > 0 else None


def _jpeg(data: bytes):
    i = 2
    while i + 4 <= len(data):
        if data[i] != 0xFF:
            return None
        marker = data[i + 1]
        if marker == 0xFF:              # fill byte
            i += 1
            continue
        if marker == 0x01 or 0xD0 <= marker <= 0xD8:
            i += 2
            continue
        if marker in (0xD9, 0xDA):      # end of image or start of scan before a frame header
            return None
        seg = struct.unpack_from(">H", data, i + 2)[0]
        if marker in _SOF:
            if i + 9 > len(data) or seg < 7:
                return None
            h, w = struct.unpack_from(">HH", data, i + 5)
            return _sized("jpeg", w, h)
        if seg < 2:
            return None
        i += 2 + seg
    return None


def image_header(data: bytes) -> tuple[str, int, int] | None:
    """('png' | 'jpeg', width, height) from a PNG's IHDR or a JPEG's SOF marker, without
    decoding; None if the bytes are neither (or the header is broken)."""
    if data[:8] == b"\x89PNG\r\n\x1a\n":
        if len(data) < 24 or data[12:16] != b"IHDR":
            return None
        return _sized("png", *struct.unpack_from(">II", data, 16))
    if data[:2] == b"\xff\xd8":
        return _jpeg(data)
    return None


def _exr(data: bytes):
    """The first header's ``dataWindow`` (a box2i: xMin, yMin, xMax, yMax) of an OpenEXR file."""
    i = 8                                   # magic and version
    while i < len(data) and data[i] != 0:
        name_end = data.find(b"\0", i)
        type_end = data.find(b"\0", name_end + 1) if name_end >= 0 else -1
        if type_end < 0 or type_end + 5 > len(data):
            return None
        name, kind = data[i:name_end], data[name_end + 1:type_end]
        size = struct.unpack_from("<i", data, type_end + 1)[0]
        start = type_end + 5
        if size < 0:
            return None
        if name == b"dataWindow" and kind == b"box2i" and size == 16 and start + 16 <= len(data):
            x0, y0, x1, y1 = struct.unpack_from("<iiii", data, start)
            return _sized("exr", x1 - x0 + 1, y1 - y0 + 1)
        i = start + size
    return None


_RGBE_SIZE = re.compile(rb"\n\s*([-+])Y\s+(\d+)\s+([-+])X\s+(\d+)\s*\n")
_NUMBERS = re.compile(rb"(?:\s|#[^\n]*\n)*(\d+)(?:\s|#[^\n]*\n)+(\d+)")


def file_image_size(path) -> tuple[str, int, int] | None:
    """(format, width, height) of the image file ``path`` from its header, or None when the
    format is not one listed in the module's docstring or the header is broken."""
    with open(path, "rb") as f:
        data = f.read(HEADER_BYTES)
    head = image_header(data)
    if head is not None:
        return head
    if data[:4] == b"\x76\x2f\x31\x01":
        return _exr(data)
    if data[:2] == b"#?":
        m = _RGBE_SIZE.search(data[:65536])
        return _sized("hdr", int(m.group(4)), int(m.group(2))) if m else None
    if data[:2] in (b"PF", b"Pf", b"P2", b"P3", b"P5", b"P6"):
        m = _NUMBERS.match(data, 2)
        return _sized("pfm" if data[1:2] in b"Ff" else "ppm", int(m.group(1)), int(m.group(2))) if m else None
    if data[:2] == b"BM" and len(data) >= 26:
        w, h = struct.unpack_from("<ii", data, 18)
        return _sized("bmp", w, abs(h))
    if Path(path).suffix.lower() == ".tga" and len(data) >= 18:
        return _sized("tga", *struct.unpack_from("<HH", data, 12))
    return None
