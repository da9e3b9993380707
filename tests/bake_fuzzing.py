"""Mesh files for the baker's hostile tests (``test_bake_hostile.py``): valid and hostile PLY and
OBJ files written byte by byte (Mitsuba's own ``write_ply`` cannot write a broken file), and a
Hypothesis strategy that draws bake inputs.

- :func:`write_ply` / :func:`write_obj`: a mesh as ASCII or binary PLY, or OBJ, whatever its
  numbers (NaN, ±inf, 1e39) and indices (negative, past the vertices, 2·10⁹);
- :func:`sphere`: a UV sphere's (positions, normals, uvs, faces), and :func:`bumpy`, the same
  with its radius varied by ±5 %;
- :func:`hostile_mesh`: a strategy drawing a mesh and how it is broken (:data:`DAMAGE`).
"""

from __future__ import annotations

import struct
from pathlib import Path

import numpy as np
from hypothesis import strategies as st

from helpers import uv_sphere


def sphere(n_theta: int = 6, n_phi: int = 12):
    """A unit UV sphere (u = φ/2π, v = θ/π), its poles' zero-area triangles left out."""
    return uv_sphere(n_theta, n_phi)


def bumpy(n_theta: int = 20, n_phi: int = 40):
    """:func:`sphere` with its radius varied by ±5 % (its normals those of the unit sphere)."""
    pos, normals, uv, faces = sphere(n_theta, n_phi)
    scale = 1.0 + 0.05 * np.sin(8 * np.pi * uv[:, :1]) * np.sin(4 * np.pi * uv[:, 1:])
    return pos * scale, normals, uv, faces


def write_ply(path, positions, normals=None, uvs=None, faces=(), binary: bool = True,
              corners: int = 3) -> Path:
    """A PLY file of these arrays as they are (any value, any index); ``corners``: the list
    length each face declares (its first indices repeated past 3)."""
    positions = np.asarray(positions, np.float64).reshape(-1, 3)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    columns = [(positions, ["x", "y", "z"]), (normals, ["nx", "ny", "nz"]), (uvs, ["u", "v"])]
    columns = [(np.asarray(a, np.float64).reshape(len(positions), len(n)), n) for a, n in columns if a is not None]
    names = [n for _, ns in columns for n in ns]
    vertices = np.concatenate([a for a, _ in columns], axis=1)
    header = (["ply", f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
               f"element vertex {len(positions)}"] + [f"property float {n}" for n in names]
              + [f"element face {len(faces)}", "property list uchar int vertex_indices", "end_header"])
    out = ("\n".join(header) + "\n").encode()
    rows = [np.resize(f, corners) for f in faces]
    if binary:
        with np.errstate(over="ignore"):
            out += vertices.astype("<f4").tobytes()
        for f in rows:
            out += struct.pack("<B", corners) + np.asarray(f).astype("<i4").tobytes()
    else:
        out += "".join(" ".join(repr(float(v)) for v in row) + "\n" for row in vertices).encode()
        out += "".join(f"{corners} " + " ".join(str(int(i)) for i in f) + "\n" for f in rows).encode()
    Path(path).write_bytes(out)
    return Path(path)


def write_obj(path, positions, normals=None, uvs=None, faces=()) -> Path:
    """An OBJ file of these arrays as they are (1-based indices: ``faces`` + 1)."""
    lines = [f"v {' '.join(repr(float(c)) for c in p)}" for p in np.reshape(positions, (-1, 3))]
    lines += [f"vn {' '.join(repr(float(c)) for c in n)}" for n in np.reshape(normals, (-1, 3))] if normals is not None else []
    lines += [f"vt {' '.join(repr(float(c)) for c in t)}" for t in np.reshape(uvs, (-1, 2))] if uvs is not None else []
    corner = "{0}/{0}/{0}" if normals is not None and uvs is not None else "{0}"
    lines += ["f " + " ".join(corner.format(int(i) + 1) for i in f) for f in np.reshape(faces, (-1, 3))]
    Path(path).write_text("\n".join(lines) + "\n")
    return Path(path)


# -- Drawing hostile bake inputs -------------------------------------------------------------------

#: How a drawn mesh is broken (or not: "none").
DAMAGE = ("none", "nan_position", "inf_position", "huge_position", "nan_uv", "nan_normal", "index_past",
          "index_huge", "index_negative", "no_faces", "no_vertices", "empty_file", "truncated",
          "quads", "scale_tiny", "scale_huge", "uv_tile", "uv_point", "flat_uvs", "flip_normals",
          "zero_area", "garbage")
BAD_NUMBERS = (float("nan"), float("inf"), -float("inf"), 1e39, -1e39)


@st.composite
def hostile_mesh(draw, base):
    """(arrays, damage, writer options) of a mesh drawn from ``base`` (positions, normals, uvs,
    faces) and broken one way of :data:`DAMAGE`."""
    p, n, uv, f = (np.array(a, copy=True) for a in base)
    damage = draw(st.sampled_from(DAMAGE))
    k = draw(st.integers(0, len(p) - 1))
    if damage in ("nan_position", "inf_position", "huge_position"):
        p[k, draw(st.integers(0, 2))] = {"nan_position": np.nan, "inf_position": np.inf,
                                          "huge_position": draw(st.sampled_from((1e39, -1e39, 3e38)))}[damage]
    elif damage == "nan_uv":
        uv[k, draw(st.integers(0, 1))] = draw(st.sampled_from(BAD_NUMBERS))
    elif damage == "nan_normal":
        n[k, draw(st.integers(0, 2))] = draw(st.sampled_from(BAD_NUMBERS))
    elif damage in ("index_past", "index_huge", "index_negative"):
        f[draw(st.integers(0, len(f) - 1)), draw(st.integers(0, 2))] = {
            "index_past": len(p), "index_huge": 2_000_000_000, "index_negative": -1}[damage]
    elif damage == "no_faces":
        f = f[:0]
    elif damage == "no_vertices":
        p, n, uv = p[:0], n[:0], uv[:0]
    elif damage == "scale_tiny":
        p = p * draw(st.sampled_from((1e-9, 1e-12, 1e-20)))
    elif damage == "scale_huge":
        p = p * draw(st.sampled_from((1e9, 1e15)))
    elif damage == "uv_tile":
        uv = uv + draw(st.sampled_from((1.0, 20.0, -3.0, 1e6)))
    elif damage == "uv_point":
        uv = uv * draw(st.sampled_from((1e-4, 1e-7, 0.0))) + 0.3
    elif damage == "flat_uvs":
        uv[:, 1] = 0.5
    elif damage == "flip_normals":
        n = -n
    elif damage == "zero_area":
        p = p * 0.0 + draw(st.sampled_from((0.0, 1.0)))
    options = {"binary": draw(st.booleans()), "normals": draw(st.integers(0, 4)) > 0,
               "obj": draw(st.integers(0, 5)) == 0}
    if damage == "quads":
        options["corners"] = 4
    return (p, n, uv, f), damage, options


def write_drawn(path: Path, mesh, damage: str, options: dict) -> Path:
    """Write a drawn mesh (see :func:`hostile_mesh`) as OBJ or PLY at ``path`` (its suffix set)."""
    p, n, uv, f = mesh
    normals = n if options["normals"] else None
    if damage == "empty_file":
        path = path.with_suffix(".ply")
        path.write_bytes(b"")
        return path
    if damage == "garbage":
        path = path.with_suffix(".ply")
        path.write_bytes(b"ply\nformat binary_little_endian 1.0\nelement vertex 3\nproperty float x\n"
                         b"element face 99999999999\nproperty list uchar int vertex_indices\nend_header\n"
                         + bytes(range(256)))
        return path
    if options["obj"]:
        return write_obj(path.with_suffix(".obj"), p, normals, uv, f)
    path = write_ply(path.with_suffix(".ply"), p, normals, uv, f, options["binary"], options.get("corners", 3))
    if damage == "truncated":
        data = path.read_bytes()
        path.write_bytes(data[:len(data) - 7])
    return path
