"""Checks of a PLY or OBJ mesh file made before Mitsuba loads it.

Mitsuba's PLY loader trusts the file: it allocates what the header declares and keeps
face indices as they are, so a face index past the vertices crashes the process when the
mesh is traced (a segmentation fault, not an error). :func:`check_mesh_file` reads the file
itself first, cheaply (numpy over the records: a header and the element data), and raises
one line naming the file and the problem:

- an empty file, a PLY without faces;
- a PLY whose data is shorter than its header declares, or does not parse as numbers;
- a PLY face that is not a triangle, or whose vertex index is not one of its vertices;
- a PLY vertex position, normal or texture coordinate that is NaN or infinite;
- an OBJ without faces, with ``vt`` or ``vn`` lines that some face corners do not name (Mitsuba
  leaves those corners' values uninitialised), or a ``v``, ``vn`` or ``vt`` line with NaN or
  infinity (Mitsuba's OBJ loader checks the face indices itself).

What the checker cannot parse (a header Mitsuba refuses too) is left to Mitsuba's own error.
"""

from __future__ import annotations

import re
from pathlib import Path

import numpy as np

__all__ = ["check_mesh_file"]

#: PLY property types (Mitsuba's names, with its extensions) as numpy types.
PLY_TYPES = {"char": "i1", "uchar": "u1", "short": "i2", "ushort": "u2", "int": "i4", "uint": "u4",
             "float": "f4", "double": "f8", "uint8": "u1", "uint16": "u2", "uint32": "u4",
             "int8": "i1", "int16": "i2", "int32": "i4", "long": "i8", "ulong": "u8",
             "half": "f2", "float16": "f2", "float32": "f4", "float64": "f8"}
#: The vertex properties that must be finite, and what they are.
PLY_FINITE = {**dict.fromkeys(("x", "y", "z"), "position"), **dict.fromkeys(("nx", "ny", "nz"), "normal"),
              **dict.fromkeys(("u", "v", "texture_u", "texture_v", "s", "t"), "texture coordinate")}
PLY_FORMATS = {"ascii": None, "binary_little_endian": "<", "binary_big_endian": ">"}
#: The most bytes a PLY header may take (comments included) for the checker to read it.
HEADER_MAX = 1 << 24


class _Unparsed(Exception):
    """A file the checker does not understand (left to Mitsuba's own error)."""


def check_mesh_file(path, name: str | None = None, error: type = ValueError) -> None:
    """Raise ``error`` (one line: ``name``, by default the path, then the problem and the fix)
    for a PLY or OBJ file that Mitsuba would crash on or load as garbage (see the module
    docstring)."""
    path = Path(path)
    name = name or str(path)
    try:
        size = path.stat().st_size
    except OSError:
        return                      # missing: the caller's or the loader's error
    if size == 0:
        raise error(f"{name} is empty (0 bytes); give a mesh file with vertices and triangles")
    try:
        if path.suffix.lower() == ".ply":
            problem = _ply_problem(path, size)
        elif path.suffix.lower() == ".obj":
            problem = _obj_problem(path)
        else:
            return
    except _Unparsed:
        return
    if problem:
        raise error(f"{name}: {problem}")


# -- PLY ---------------------------------------------------------------------------------------

def _ply_header(path: Path):
    """(byte order: '<', '>' or None for ASCII; elements [(name, count, [(property, numpy
    type, list count type or None)])]; header length in bytes) of a PLY file."""
    lines, length = [], 0
    with open(path, "rb") as f:
        while not lines or lines[-1].split()[:1] != ["end_header"]:
            line = f.readline(HEADER_MAX)
            length += len(line)
            if not line or length > HEADER_MAX:
                raise _Unparsed()
            lines.append(line.decode("ascii", "replace"))
    if lines[0].split() != ["ply"]:
        raise _Unparsed()
    fmt, elements = "", []
    for line in lines[1:-1]:
        tokens = line.split()
        if not tokens or tokens[0] == "comment":
            continue
        if tokens[0] == "format" and len(tokens) == 3 and tokens[1] in PLY_FORMATS:
            fmt = PLY_FORMATS[tokens[1]]
        elif tokens[0] == "element" and len(tokens) == 3 and tokens[2].isdigit():
            elements.append((tokens[1], int(tokens[2]), []))
        elif tokens[0] == "property" and elements and len(tokens) == 3 and tokens[1] in PLY_TYPES:
            elements[-1][2].append((tokens[2], PLY_TYPES[tokens[1]], None))
        elif (tokens[0] == "property" and elements and len(tokens) == 5 and tokens[1] == "list"
              and tokens[2] in PLY_TYPES and tokens[3] in PLY_TYPES):
            elements[-1][2].append((tokens[4], PLY_TYPES[tokens[3]], PLY_TYPES[tokens[2]]))
        else:
            raise _Unparsed()
    if fmt == "":
        raise _Unparsed()
    return fmt, elements, length


def _fields(props, order: str):
    """The numpy fields of one record: a list property is its count and three indices (the
    triangles Mitsuba reads)."""
    fields = []
    for name, kind, count_kind in props:
        if count_kind is None:
            fields.append((name, order + kind))
        else:
            fields += [(name + ".count", order + count_kind)] + [(f"{name}.i{k}", order + kind) for k in range(3)]
    return fields


def _ply_records(path: Path, size: int) -> list:
    """[(element name, count, {field: values})] of a PLY file."""
    fmt, elements, start = _ply_header(path)
    declared = ", ".join(f"{count} {name}s" for name, count, _ in elements)
    if fmt is None:
        with open(path, "rb") as f:
            f.seek(start)
            text = f.read().decode("ascii", "replace")
        try:
            values = np.fromstring(text, sep=" ") if text.strip() else np.zeros(0)
        except ValueError:
            raise _Unparsed() from None
        needed = sum(count * len(_fields(props, "")) for _, count, props in elements)
        if len(values) < needed:
            raise ValueError(f"the file holds {len(values)} numbers after its header, fewer than the "
                             f"{needed} that its {declared} take; the file is truncated or not a "
                             "triangle mesh")
        records, at = [], 0
        for name, count, props in elements:
            names = [n for n, _ in _fields(props, "")]
            block = values[at:at + count * len(names)].reshape(count, len(names))
            records.append((name, count, {n: block[:, k] for k, n in enumerate(names)}))
            at += count * len(names)
        return records
    records, at = [], start
    for name, count, props in elements:
        dtype = np.dtype(_fields(props, fmt))
        if at + count * dtype.itemsize > size:
            raise ValueError(f"the file has {size} bytes, fewer than its header's {declared} take "
                             f"({at + count * dtype.itemsize}); the file is truncated")
        block = np.fromfile(path, dtype, count, offset=at) if count else np.zeros(0, dtype)
        records.append((name, count, {n: block[n] for n in dtype.names or ()}))
        at += count * dtype.itemsize
    return records


def _ply_problem(path: Path, size: int) -> str | None:
    try:
        records = _ply_records(path, size)
    except ValueError as exc:
        return str(exc)
    vertices = next((r for r in records if r[0] == "vertex"), None)
    faces = next((r for r in records if r[0] == "face"), None)
    count = vertices[1] if vertices else 0
    if vertices:
        for name in PLY_FINITE:
            values = vertices[2].get(name)
            finite = _finite32(values) if values is not None else None
            if finite is not None and not finite.all():
                bad = int(np.argmin(finite))
                return (f"vertex {bad}'s {PLY_FINITE[name]} '{name}' is {values[bad]} (not finite "
                        "in single precision, as Mitsuba reads it); every position, normal and "
                        "texture coordinate must be a finite number")
    if not faces or faces[1] == 0:
        return "the file has no faces (element face); give a mesh with triangles"
    if faces:
        fields = faces[2]
        counts = next((fields[k] for k in fields if k.endswith(".count")), None)
        if counts is not None and (counts != 3).any():
            bad = int(np.argmax(counts != 3))
            return (f"face {bad} has {counts[bad]:g} corners; Mitsuba's PLY loader reads triangles "
                    "only: triangulate the mesh")
        for key in (k for k in fields if re.search(r"\.i[012]$", k)):
            index = fields[key].astype(np.float64)
            wrong = (index < 0) | (index >= count) | (index != np.floor(index))
            if wrong.any():
                bad = int(np.argmax(wrong))
                return (f"face {bad} names vertex {index[bad]:.0f}, but the file has {count} "
                        f"vertices (0 to {count - 1}); the file is corrupt")
    return None


# -- OBJ ------------------------------------------------------------------------------------------

_OBJ_NUMBERS = re.compile(rb"^[ \t]*(v|vn|vt)[ \t]+([^\r\n#]*)", re.M)


_OBJ_FACES = re.compile(rb"^[ \t]*f[ \t]+([^\r\n#]*)", re.M)


def _obj_problem(path: Path) -> str | None:
    data = path.read_bytes()
    corners = b" ".join(_OBJ_FACES.findall(data)).split()
    if not corners:
        return "the file has no faces ('f' lines); give a mesh with triangles"
    problem = _obj_corner_problem(data, corners)
    if problem:
        return problem
    numbers = b" ".join(m.group(2) for m in _OBJ_NUMBERS.finditer(data))
    try:
        values = np.fromstring(numbers.decode("ascii", "replace"), sep=" ") if numbers.strip() else []
    except ValueError:
        return None                      # Mitsuba's own parser reports it
    if _finite32(values).all():
        return None
    for match in _OBJ_NUMBERS.finditer(data):
        text = match.group(2).decode("ascii", "replace").strip()
        if not _finite32(np.fromstring(text, sep=" ") if text else []).all():
            line = data.count(b"\n", 0, match.start()) + 1
            return (f"line {line} ('{match.group(1).decode()} {text}') holds NaN or infinity (in "
                    "single precision, as Mitsuba reads it); every position, normal and texture "
                    "coordinate must be finite")
    return None


def _obj_corner_problem(data: bytes, corners: list) -> str | None:
    """A file with ``vt`` (``vn``) lines whose face corners do not all name one: Mitsuba leaves
    those corners' texture coordinates (normals) uninitialised memory."""
    parts = [c.split(b"/") for c in corners]
    for kind, slot, what in ((b"vt", 1, "texture coordinate"), (b"vn", 2, "normal")):
        if re.search(rb"^[ \t]*" + kind + rb"[ \t]", data, re.M) is None:
            continue
        missing = sum(1 for p in parts if len(p) <= slot or not p[slot])
        if missing:
            return (f"{missing} of its {len(parts)} face corners name no {what} although the file "
                    f"has '{kind.decode()}' lines (Mitsuba would read memory it never wrote); give "
                    f"every corner one (f v/vt/vn) or remove the '{kind.decode()}' lines")
    return None


def _finite32(values) -> np.ndarray:
    """Whether each value is finite in single precision, as Mitsuba stores it."""
    with np.errstate(over="ignore", invalid="ignore"):
        return np.isfinite(np.asarray(values, np.float64).astype(np.float32))
