"""glTF meshes in world space: the node graph, the primitives' arrays and their transforms.

:func:`walk_nodes` visits the default scene's nodes with their world matrices, parents first.
:func:`primitive_arrays` reads a primitive's positions, normals (without them: flat shading,
vertices split), UVs, tangents and triangles (from lists, strips or fans); where a normal map
needs tangents the file does not have, MikkTSpace tangents are computed for (u, 1 − v) and the
vertices split where they differ. :func:`to_world` places them under a node's matrix (normals
by the cofactor matrix, the winding flipped for mirroring matrices); a degenerate transform (a
zero scale) skips the mesh with a warning.
"""

from __future__ import annotations

import numpy as np

from mfnormal.io.gltf_arrays import GLTFFile, warn
from mfnormal.io.gltf_validate import GLTFError
from mfnormal.normals.mikktspace import mikktspace, split_vertices

#: A mesh is smooth-shaded where some vertex normal is more than this many degrees off its
#: triangle's normal (glTF writers store flat shading as split vertices with face normals).
SMOOTH_MIN_DEG = 0.5
#: glTF's primitive modes that hold triangles: lists, strips and fans (the others: points, lines).
TRIANGLES, STRIP, FAN = 4, 5, 6


# Scene graph

def _node_matrix(node) -> np.ndarray:
    if node.matrix is not None:
        return np.array(node.matrix, dtype=np.float64).reshape(4, 4).T    # column-major
    t = np.array(node.translation or [0, 0, 0], dtype=np.float64)
    q = np.array(node.rotation or [0, 0, 0, 1], dtype=np.float64)
    x, y, z, w = q / np.linalg.norm(q)          # validated non-zero; exporters round unit ones
    r = np.array([[1 - 2 * (y * y + z * z), 2 * (x * y - z * w), 2 * (x * z + y * w)],
                  [2 * (x * y + z * w), 1 - 2 * (x * x + z * z), 2 * (y * z - x * w)],
                  [2 * (x * z - y * w), 2 * (y * z + x * w), 1 - 2 * (x * x + y * y)]])
    s = np.array(node.scale or [1, 1, 1], dtype=np.float64)
    m = np.eye(4)
    m[:3, :3] = r * s[None, :]
    m[:3, 3] = t
    return m


def walk_nodes(gltf, roots):
    """(index, node, world matrix) for every node of the default scene (``roots`` and their
    descendants: a tree, validated), parents first."""
    stack = [(i, np.eye(4)) for i in reversed(roots)]
    while stack:
        i, parent = stack.pop()
        node = gltf.nodes[i]
        with np.errstate(over="ignore", invalid="ignore"):
            world = parent @ _node_matrix(node)
        yield i, node, world
        stack.extend((c, world) for c in reversed(node.children or []))


# Meshes

def _triangles(indices, mode):
    if mode != TRIANGLES and len(indices) < 3:
        return np.zeros((0, 3), np.int64)
    if mode == TRIANGLES:
        return indices[: len(indices) // 3 * 3].reshape(-1, 3)
    k = np.arange(max(len(indices) - 2, 0))
    if mode == STRIP:
        even = (k % 2) == 0
        tri = np.stack([indices[k], np.where(even, indices[k + 1], indices[k + 2]),
                        np.where(even, indices[k + 2], indices[k + 1])], axis=-1)
        return tri
    return np.stack([np.full_like(k, indices[0]), indices[k + 1], indices[k + 2]], axis=-1)


def _finite_attribute(f: GLTFFile, index: int, where: str, name: str) -> np.ndarray:
    """A float attribute's values, which must be finite."""
    data = f.accessor(index).astype(np.float32)
    if not np.all(np.isfinite(data)):
        bad = int(np.argmax(~np.isfinite(data).all(axis=1)))
        raise GLTFError(f"{where}.attributes.{name}: accessors[{index}] element {bad} is not finite")
    return data


def primitive_arrays(f: GLTFFile, prim, want_tangents: bool, tangents_mode: str, where: str = "a primitive"):
    """Object-space (positions, normals, uvs | None, tangents4 | None, faces) of a primitive."""
    attrs = prim.attributes
    positions = _finite_attribute(f, attrs.POSITION, where, "POSITION")
    count = len(positions)
    indices = (f.accessor(prim.indices)[:, 0].astype(np.int64) if prim.indices is not None
               else np.arange(count))
    faces = _triangles(indices, prim.mode if prim.mode is not None else TRIANGLES)
    if len(faces) and faces.max() >= count:
        raise GLTFError(f"{where}.indices: index {int(faces.max())} is out of range "
                        f"(POSITION has {count} vertices)")
    uvs = (_finite_attribute(f, attrs.TEXCOORD_0, where, "TEXCOORD_0")[:, :2]
           if attrs.TEXCOORD_0 is not None else None)
    tangents = (_finite_attribute(f, attrs.TANGENT, where, "TANGENT")
                if attrs.TANGENT is not None and tangents_mode == "auto" else None)
    if attrs.NORMAL is not None:
        normals = _finite_attribute(f, attrs.NORMAL, where, "NORMAL")
        length = np.linalg.norm(normals, axis=1, keepdims=True)
        normals = np.where(length > 0, normals / np.where(length > 0, length, 1), normals)
    else:
        # glTF: without normals, flat shading: one normal per triangle, vertices split.
        p = positions[faces]
        n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
        n /= np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-30)
        positions = p.reshape(-1, 3)
        normals = np.repeat(n, 3, axis=0).astype(np.float32)
        uvs = uvs[faces].reshape(-1, 2) if uvs is not None else None
        tangents = tangents[faces].reshape(-1, 4) if tangents is not None else None
        faces = np.arange(len(positions)).reshape(-1, 3)
    if want_tangents and uvs is not None and tangents is None:
        # MikkTSpace per corner; split the vertices where corners differ.
        corner_t = mikktspace(positions, normals, uvs, faces, flip_v=True)
        faces, v = split_vertices(p=positions[faces], n=normals[faces], uv=uvs[faces], t=corner_t)
        positions, normals, uvs, tangents = v["p"], v["n"], v["uv"], v["t"]
    if not want_tangents:
        tangents = None
    return positions, normals, uvs, tangents, faces.astype(np.uint32)


def is_smooth_shaded(positions, normals, faces, min_deg: float = SMOOTH_MIN_DEG) -> bool:
    """Whether some vertex normal of the mesh is more than ``min_deg`` off its triangle's normal
    (degenerate triangles are left out)."""
    p = np.asarray(positions, np.float64)[faces]
    n = np.cross(p[:, 1] - p[:, 0], p[:, 2] - p[:, 0])
    length = np.linalg.norm(n, axis=1)
    ok = length > 1e-12 * np.maximum(np.abs(p).max(axis=(1, 2)) ** 2, 1e-30)
    if not ok.any():
        return False
    n = n[ok] / length[ok, None]
    vn = np.asarray(normals, np.float64)[faces[ok]]
    cos = np.einsum("fd,fkd->fk", n, vn) / np.maximum(np.linalg.norm(vn, axis=2), 1e-30)
    return bool(np.any(np.abs(cos) < np.cos(np.radians(min_deg))))


def _cofactor(lin):
    """The cofactor matrix det(L)·L^−T (columns: the cross products of L's columns), which
    maps normals like the inverse transpose and exists for singular L too."""
    a, b, c = lin[:, 0], lin[:, 1], lin[:, 2]
    return np.stack([np.cross(b, c), np.cross(c, a), np.cross(a, b)], axis=1)


def to_world(m, positions, normals, tangents, faces, where="a node"):
    """World-space arrays under the node matrix ``m`` (winding flipped for mirroring matrices),
    or None where ``m`` flattens the mesh to a line or a point (a zero scale)."""
    lin = m[:3, :3]
    if not np.all(np.isfinite(m)):
        raise GLTFError(f"{where}: its world transform is not finite (its matrix or scale, times "
                        "its parents', overflows)")
    with np.errstate(over="ignore", invalid="ignore"):
        world = positions @ lin.T + m[:3, 3]
        det = np.linalg.det(lin)
        cof = _cofactor(lin) * (np.sign(det) if det != 0 else 1.0)
    if not (np.all(np.isfinite(world)) and np.all(np.abs(world) <= np.finfo(np.float32).max)):
        raise GLTFError(f"{where}: its world transform takes the vertices past the float range")
    if not np.any(np.abs(cof) > 1e-300):
        warn(f"{where}: its transform has a zero scale, so its mesh has no area; not rendered")
        return None
    positions = world
    if not (np.isfinite(det) and np.all(np.isfinite(cof))):
        cof = _cofactor(lin / np.max(np.abs(lin)))    # normals need only its direction
        det = np.linalg.det(lin / np.max(np.abs(lin)))
    normals = normals @ cof.T                     # ∝ the inverse transpose, applied to rows
    length = np.linalg.norm(normals, axis=1, keepdims=True)
    normals = normals / np.maximum(length, 1e-300)
    if det == 0:
        # A flat scale (rank 2) maps normals in the plane to 0: they get the plane's normal.
        plane = cof[:, np.argmax(np.linalg.norm(cof, axis=0))]
        normals = np.where(length > 0, normals, plane / np.linalg.norm(plane))
    if tangents is not None:
        t = tangents[:, :3] @ lin.T
        t /= np.maximum(np.linalg.norm(t, axis=1, keepdims=True), 1e-30)
        tangents = np.concatenate([t, tangents[:, 3:4] * np.sign(det)], axis=1)
    if det < 0:
        faces = faces[:, [0, 2, 1]]
    return positions, normals, tangents, faces
