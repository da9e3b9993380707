"""The baker's inputs, checked before any work: the meshes, the numbers, the variant, the memory.

Every check raises a :class:`BakeError`, one line naming the input and the fix. The files are
checked before Mitsuba reads them (:mod:`mfnormal.io.mesh_files`: face indices, finite numbers),
then the meshes (triangles, indices, finite positions, normals and UVs, a low-poly with UVs,
vertex normals and area), the map size, padding and cage, the variant (a JIT one: the baker
traces rays in bulk) and the memory a bake of that size takes (BYTES_PER_TEXEL per texel and
BAKE_OVERHEAD_BYTES) against what the system, or the process's control group, has available.
:class:`Batches` says how many texels a bake handles at once.
"""

from __future__ import annotations

import math
import numbers
import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Union

import numpy as np

from mfnormal.io.meshes import MeshArrays, mesh_arrays

if TYPE_CHECKING:
    import mitsuba as mi

#: A file path as the functions take it.
PathLike = Union[str, os.PathLike]

MESH_SUFFIXES = {".ply": "ply", ".obj": "obj"}
TANGENT_FRAMES = ("mikktspace", "mitsuba")
HIGH_NORMALS = ("shading", "geometric")
SIZE_RANGE = (8, 8192)


@dataclass(frozen=True)
class Batches:
    """How many texels a bake handles at once: ``trace`` texels whose frames and rays are
    computed in one pass (memory: ~600 bytes each), ``band`` texels of rows padded and encoded
    together, ``chunk`` texel candidates the rasteriser tests at a time (~200 bytes each). The
    map is the same for any batches; they trade memory for per-step overhead."""
    trace: int = 1 << 19
    band: int = 1 << 20
    chunk: int = 1 << 20


#: The bake's batches.
BATCHES = Batches()
#: Texels traced per pass (``BATCHES.trace``).
TEXELS_PER_PASS = BATCHES.trace
#: Memory a bake takes per texel of the map, with a margin: the normals and heights (float64),
#: the covering triangle (int32), the covered and hit masks, the encoded map and its file
#: (measured: ~37 at 8192², docs/cli.md).
BYTES_PER_TEXEL = 56
#: Transient memory of a bake on top of that: one pass of texels, one chunk of candidates.
BAKE_OVERHEAD_BYTES = 1 << 29


class BakeError(ValueError):
    """An input the baker cannot use (one line, naming the fix)."""


def load_mesh(path: PathLike, what: str = "mesh") -> mi.Mesh:
    """The Mitsuba mesh of the PLY or OBJ file ``path``; :class:`BakeError` if it cannot be."""
    import mitsuba as mi

    path = Path(path)
    if not path.is_file():
        raise BakeError(f"{what} file not found: {path}")
    kind = MESH_SUFFIXES.get(path.suffix.lower())
    if kind is None:
        raise BakeError(f"{what} {path}: expected a .ply or .obj mesh")
    from mfnormal.io.mesh_files import check_mesh_file
    check_mesh_file(path, f"{what} {path}", BakeError)
    try:
        return mi.load_dict({"type": kind, "filename": str(path)})
    except Exception as exc:  # Mitsuba's loaders raise RuntimeError with a multi-line message
        from mfnormal.io.messages import one_line
        raise BakeError(f"cannot load {what} {path}: {one_line(exc)}") from None


def checked_inputs(high, low, size, cage, frame, padding, high_normals, memory_limit):
    """:func:`bake`'s inputs checked before any work (one-line :class:`BakeError`s): the
    high-poly mesh and the low-poly's arrays."""
    import mitsuba as mi

    if frame not in TANGENT_FRAMES:
        raise BakeError(f"frame must be one of {', '.join(TANGENT_FRAMES)}, got '{frame}'")
    if high_normals not in HIGH_NORMALS:
        raise BakeError(f"high_normals must be one of {', '.join(HIGH_NORMALS)}, got '{high_normals}'")
    _check_number(size, "size", integer=True)
    if not SIZE_RANGE[0] <= size <= SIZE_RANGE[1]:
        raise BakeError(f"size {size} is out of range ({SIZE_RANGE[0]} to {SIZE_RANGE[1]})")
    _check_number(padding, "padding", integer=True)
    if cage is not None:
        _check_number(cage, "cage", integer=False)
        if not cage > 0:
            raise BakeError(f"cage {cage}: expected a distance above 0")
    if memory_limit is not None:
        _check_number(memory_limit, "memory_limit", integer=True)
    _check_variant()
    high_mesh = _as_mesh(high, "high-poly mesh", "high", mi.Shape)
    low_mesh = _as_mesh(low, "low-poly mesh", "low", mi.Mesh)
    check_high_poly(high_mesh)
    arrays = check_low_poly(low_mesh)
    _check_memory(size, memory_limit)
    return high_mesh, arrays


def check_options(progress, batches) -> None:
    """:func:`bake`'s ``progress`` (a function or None) and ``batches`` (a :class:`Batches` of
    positive integers); :class:`BakeError` naming the argument."""
    if progress is not None and not callable(progress):
        raise BakeError(f"progress {progress!r}: expected a function progress(done, total), or None")
    if not isinstance(batches, Batches):
        raise BakeError(f"batches {batches!r}: expected a bake.Batches(trace=..., band=..., chunk=...)")
    for name in ("trace", "band", "chunk"):
        _check_number(getattr(batches, name), f"batches.{name}", integer=True, low=1)


def _as_mesh(mesh, what: str, argument: str, kind):
    """A Mitsuba shape of type ``kind``, or the mesh loaded from a path; :class:`BakeError`
    naming ``argument`` for anything else."""
    if isinstance(mesh, (str, os.PathLike)):
        return load_mesh(mesh, what)
    if not isinstance(mesh, kind):
        raise BakeError(f"{argument}: expected the {what} as a Mitsuba {kind.__name__} or the path "
                        f"of a .ply or .obj file, got {type(mesh).__name__}")
    return mesh


def _check_mesh_arrays(positions, normals, uvs, faces, what: str) -> None:
    """:class:`BakeError` for a mesh without triangles, a face index past its vertices, or
    positions, normals or UVs that are not finite."""
    if len(faces) == 0:
        raise BakeError(f"the {what} has no triangles; give a mesh with faces")
    if faces.min() < 0 or faces.max() >= len(positions):
        raise BakeError(f"the {what} has a face index of {faces.max()}, but {len(positions)} "
                        "vertices; its faces must index its vertices")
    for values, name in ((positions, "positions"), (normals, "vertex normals"), (uvs, "UVs")):
        if values is not None and not np.isfinite(values).all():
            raise BakeError(f"the {what}'s {name} hold NaN or infinity; give finite values")


def check_low_poly(low: mi.Mesh, what: str = "low-poly mesh") -> MeshArrays:
    """(positions, normals, uvs, faces) of the low-poly; :class:`BakeError` without UVs or
    normals, for the problems of :func:`_check_mesh_arrays`, or without area."""
    positions, normals, uvs, faces = mesh_arrays(low)
    if uvs is None:
        raise BakeError(f"the {what} has no UVs (texture coordinates); unwrap it first "
                        "(mfnormal bake --unwrap OUT.ply, with xatlas)")
    if normals is None:
        raise BakeError(f"the {what} has no vertex normals (it is flat-shaded); give it smooth "
                        "vertex normals")
    _check_mesh_arrays(positions, normals, uvs, faces, what)
    corners = positions[faces]
    if not np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]),
                          axis=1).any():
        raise BakeError(f"the {what} has no area (every triangle's corners coincide or lie on a "
                        "line); give a mesh with surface to bake onto")
    return positions, normals, uvs, faces


def check_high_poly(high: mi.Shape, what: str = "high-poly mesh") -> None:
    """:class:`BakeError` for a high-poly mesh with the problems of :func:`_check_mesh_arrays`
    (other shapes, e.g. Mitsuba's analytic sphere, are taken as they are)."""
    import mitsuba as mi

    if isinstance(high, mi.Mesh):
        positions, normals, _, faces = mesh_arrays(high)
        _check_mesh_arrays(positions, normals, None, faces, what)


def _check_variant() -> None:
    import mitsuba as mi

    variant = mi.variant()
    if variant is None or not variant.startswith(("llvm_", "cuda_")):
        raise BakeError(f"the baker traces rays in bulk and needs a JIT variant (llvm_ad_rgb, "
                        f"cuda_ad_rgb), not {variant}: call mitsuba.set_variant('llvm_ad_rgb') "
                        "(mfnormal bake --variant llvm_ad_rgb)")


def _check_number(value, name: str, integer: bool, low: float = 0) -> None:
    kinds = numbers.Integral if integer else numbers.Real
    if isinstance(value, bool) or not isinstance(value, kinds):
        raise BakeError(f"{name} {value!r}: expected {'an integer' if integer else 'a number'}")
    if not low <= value < math.inf:
        raise BakeError(f"{name} {value}: expected {'an integer' if integer else 'a finite number'} "
                        f"of at least {low}")


def memory_needed(size: int) -> int:
    """About the bytes a ``size``² bake takes at its peak (BYTES_PER_TEXEL per texel and the
    passes' transient memory)."""
    return BYTES_PER_TEXEL * size * size + BAKE_OVERHEAD_BYTES


def available_memory(proc: PathLike = "/proc", cgroups: PathLike = "/sys/fs/cgroup") -> int | None:
    """The memory this process may still take (Linux): the system's available memory, or less
    where its control group (v1 or v2, here or in a group above it) caps it, as in a container
    or a batch job (over the cap the kernel kills the process, with no message); None where
    unknown. ``proc``, ``cgroups``: where the kernel's files are."""
    rooms = [_meminfo_available(Path(proc) / "meminfo"), *_cgroup_rooms(Path(proc), Path(cgroups))]
    known = [room for room in rooms if room is not None]
    return min(known) if known else None


def _read_number(path: Path) -> int | None:
    """The integer in the file ``path``; None if it is absent, unreadable or not one ("max")."""
    try:
        return int(path.read_text().split()[0])
    except (OSError, ValueError, IndexError):
        return None


def _meminfo_available(meminfo: Path) -> int | None:
    try:
        for line in meminfo.read_text().splitlines():
            if line.startswith("MemAvailable:"):
                return int(line.split()[1]) * 1024
    except (OSError, ValueError, IndexError):
        pass
    return None


#: A cgroup v1 memory limit at or above this is no limit (the kernel writes 2^63 rounded to pages).
UNLIMITED = 1 << 62


def _cgroup_rooms(proc: Path, cgroups: Path) -> list:
    """Limit minus usage of this process's memory control group and each group above it
    (``proc``/self/cgroup: ``0::PATH`` on v2, ``N:memory:PATH`` on v1)."""
    try:
        lines = (proc / "self" / "cgroup").read_text().splitlines()
    except OSError:
        return []
    rooms = []
    for line in lines:
        _, controllers, path = (line.split(":", 2) + ["", ""])[:3]
        v1 = "memory" in controllers.split(",")
        if not (v1 or controllers == ""):
            continue
        root = cgroups / "memory" if v1 else cgroups
        folder = root / path.strip("/")
        for group in [folder, *folder.parents]:
            cap = _read_number(group / ("memory.limit_in_bytes" if v1 else "memory.max"))
            used = _cgroup_used(group, v1)
            if cap is not None and used is not None and cap < UNLIMITED:
                rooms.append(max(cap - used, 0))
            if group == root:
                break
    return rooms


def _cgroup_used(group: Path, v1: bool) -> int | None:
    """The memory a control group holds that the kernel cannot drop: its usage less its inactive
    file cache (``memory.stat``), as ``docker stats`` counts it."""
    used = _read_number(group / ("memory.usage_in_bytes" if v1 else "memory.current"))
    if used is None:
        return None
    key = "total_inactive_file" if v1 else "inactive_file"
    try:
        stat = dict(line.split()[:2] for line in (group / "memory.stat").read_text().splitlines()
                    if len(line.split()) >= 2)
        return max(used - int(stat.get(key, 0)), 0)
    except (OSError, ValueError):
        return used


def _check_memory(size: int, limit: int | None = None) -> None:
    """A :class:`BakeError` where a ``size``² bake needs more than ``limit`` bytes (default: the
    memory the system has available)."""
    needed, available = memory_needed(size), available_memory() if limit is None else limit
    if available is not None and needed > available:
        raise BakeError(f"a {size}x{size} bake needs about {needed / 2 ** 30:.1f} GiB of memory, "
                        f"more than the {available / 2 ** 30:.1f} GiB available; lower the map size "
                        "(size, --size)")
