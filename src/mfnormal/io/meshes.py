"""Mitsuba meshes from numpy arrays, and numpy arrays from Mitsuba meshes.

:func:`mitsuba_mesh` builds the triangle meshes of the glTF loader, the baker (its low-poly with
tangents, the high-poly at a working scale) and the tests from vertex arrays: positions, faces
and, each optional, vertex normals, UVs and per-vertex tangents with their handedness sign (the
attributes ``normalmap_microfacet`` decodes a MikkTSpace map with, ``tangents="vertex_tangent"``).
:func:`mesh_arrays` reads those arrays back from any Mitsuba mesh.
"""

from __future__ import annotations

from typing import TYPE_CHECKING

import numpy as np

if TYPE_CHECKING:
    import mitsuba as mi

#: The mesh attribute that holds the per-vertex tangent T; ``TANGENT_ATTR + "_sign"`` holds its
#: handedness (glTF's ``TANGENT.w``).
TANGENT_ATTR = "vertex_tangent"
#: A mesh's arrays: positions (V, 3), normals (V, 3) or None, uvs (V, 2) or None, faces (F, 3).
MeshArrays = tuple  # (np.ndarray, np.ndarray | None, np.ndarray | None, np.ndarray)


def mitsuba_mesh(name: str, bsdf: mi.BSDF | None, positions: np.ndarray, normals: np.ndarray | None,
                 uvs: np.ndarray | None, tangents: np.ndarray | None, faces: np.ndarray) -> mi.Mesh:
    """A Mitsuba mesh of these vertex arrays with ``bsdf`` (loaded; None: Mitsuba's default).
    ``normals`` may be None (no vertex normals: the triangles' own normals shade it), and so may
    ``uvs`` and ``tangents`` (V, 4: T and its sign, as attributes ``vertex_tangent`` and
    ``vertex_tangent_sign``)."""
    import mitsuba as mi

    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = bsdf
    mesh = mi.Mesh(name, len(positions), len(faces), props, has_vertex_normals=normals is not None,
                   has_vertex_texcoords=uvs is not None)
    params = mi.traverse(mesh)
    # The buffers' own types: mi.Float in JIT variants, Dr.Jit's scalar arrays otherwise.
    floats, ints = type(params["vertex_positions"]), type(params["faces"])
    params["vertex_positions"] = floats(positions.astype(np.float32).ravel())
    if normals is not None:
        params["vertex_normals"] = floats(normals.astype(np.float32).ravel())
    if uvs is not None:
        params["vertex_texcoords"] = floats(uvs.astype(np.float32).ravel())
    params["faces"] = ints(faces.astype(np.uint32).ravel())
    params.update()
    if tangents is not None:
        mesh.add_attribute(TANGENT_ATTR, 3, np.ascontiguousarray(tangents[:, :3], np.float32).ravel())
        mesh.add_attribute(TANGENT_ATTR + "_sign", 1,
                           np.where(tangents[:, 3] < 0, -1.0, 1.0).astype(np.float32))
    return mesh


def mesh_arrays(mesh: mi.Mesh) -> MeshArrays:
    """(positions (V, 3), normals (V, 3) or None, uvs (V, 2) or None, faces (F, 3)) of a Mitsuba
    mesh, as numpy arrays."""
    import mitsuba as mi

    params = mi.traverse(mesh)
    positions = np.array(params["vertex_positions"], np.float64).reshape(-1, 3)
    faces = np.array(params["faces"], np.int64).reshape(-1, 3)
    normals = (np.array(params["vertex_normals"], np.float64).reshape(-1, 3)
               if mesh.has_vertex_normals() else None)
    uvs = (np.array(params["vertex_texcoords"], np.float64).reshape(-1, 2)
           if mesh.has_vertex_texcoords() else None)
    return positions, normals, uvs, faces
