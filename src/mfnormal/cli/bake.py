"""``mfnormal bake HIGH LOW -o MAP.png [--heights HEIGHTS.exr]``: a tangent-space normal map of a
high-poly mesh baked onto a low-poly mesh's UVs, and the high-poly's heights over the low-poly
(:mod:`mfnormal.io.bake`).

Every argument, both files and the output paths are checked before the meshes are loaded (no
output may be an input, or another output: inputs are never written to); the mesh files before
Mitsuba reads them, the meshes (and the low-poly's UVs) before the bake; the files are written
atomically.
"""

from __future__ import annotations

import argparse
import math
import os
import sys
import time
from pathlib import Path
from typing import Callable, TextIO

from mfnormal.io.bake import (BakeError, HIGH_NORMALS, MESH_SUFFIXES, SIZE_RANGE, TANGENT_FRAMES,
                              TEXELS_PER_PASS, bake, load_mesh, memory_needed, mesh_arrays, tangent_mesh,
                              unwrap, write_baked)
from mfnormal.io.inputs import CLIError, check_output

__all__ = ["add_bake", "cmd_bake", "progress_lines"]

DEFAULT_SIZE = 1024
PADDING_MAX = 64
#: What each output is, by its suffix (for the message when a name lacks it).
OUTPUT_KINDS = {".png": "the map is a PNG", ".exr": "the heights are a float OpenEXR",
                ".ply": "the mesh is written as PLY"}
#: Covered texels whose rays may miss the high-poly before the command warns.
MISSED_WARN = 0.01
#: Bakes of at least this many passes (of TEXELS_PER_PASS texels) report their progress.
PROGRESS_PASSES = 4


def _check_mesh_file(path: str, what: str) -> None:
    p = Path(path)
    if not p.is_file():
        raise CLIError(f"{what} file not found: {path}")
    if p.suffix.lower() not in MESH_SUFFIXES:
        raise CLIError(f"{what} {path}: expected a .ply or .obj mesh")


def _check_output_file(path: str, flag: str, suffix: str) -> None:
    """``path`` ends in ``suffix``, is not a folder, and its folder is writable."""
    if Path(path).suffix.lower() != suffix:
        raise CLIError(f"{flag} {path}: {OUTPUT_KINDS[suffix]}; give a name ending in {suffix}")
    if Path(path).is_dir():
        raise CLIError(f"{flag} {path} names a folder; give a file name ending in {suffix}")
    check_output(Path(path).with_suffix(""), flag)


def _same_file(a: str, b: str) -> bool:
    """Whether the paths ``a`` and ``b`` name one file (links and ``..`` resolved)."""
    try:
        if os.path.exists(a) and os.path.exists(b):
            return os.path.samefile(a, b)
        return Path(a).resolve() == Path(b).resolve()
    except (OSError, RuntimeError):
        return False


def _check_no_overwrite(args) -> None:
    """No output names an input mesh or another output."""
    inputs = (("high-poly mesh", args.high), ("low-poly mesh", args.low))
    outputs = [(flag, path) for flag, path in (("-o", args.output), ("--heights", args.heights),
                                               ("--unwrap", args.unwrap),
                                               ("--tangent-mesh", args.tangent_mesh)) if path is not None]
    for k, (flag, path) in enumerate(outputs):
        for what, source in inputs:
            if _same_file(path, source):
                raise CLIError(f"{flag} {path} is the {what} {source}; the bake would overwrite "
                               "its input: give another output name")
        for other, other_path in outputs[:k]:
            if _same_file(path, other_path):
                raise CLIError(f"{flag} {path} is also {other} {other_path}; give each output "
                               "its own name")


def _check_bake(args) -> Path:
    """Every argument of ``mfnormal bake`` before anything is loaded; the map's path."""
    if not SIZE_RANGE[0] <= args.size <= SIZE_RANGE[1]:
        raise CLIError(f"--size {args.size}: expected a map size from {SIZE_RANGE[0]} to "
                       f"{SIZE_RANGE[1]} texels")
    if args.cage is not None and not (0 < args.cage < math.inf):
        raise CLIError(f"--cage {args.cage}: expected a finite distance above 0")
    if not 0 <= args.padding <= PADDING_MAX:
        raise CLIError(f"--padding {args.padding}: expected 0 to {PADDING_MAX} texels")
    _check_output_file(args.output, "-o", ".png")
    if args.heights is not None:
        _check_output_file(args.heights, "--heights", ".exr")
    if args.unwrap is not None:
        _check_output_file(args.unwrap, "--unwrap", ".ply")
    if args.tangent_mesh is not None:
        if args.tangents != "mikktspace":
            raise CLIError(f"--tangent-mesh {args.tangent_mesh}: the mesh carries MikkTSpace tangents, "
                           f"which a --tangents {args.tangents} map does not use; drop --tangent-mesh "
                           "or bake with --tangents mikktspace")
        _check_output_file(args.tangent_mesh, "--tangent-mesh", ".ply")
    _check_mesh_file(args.high, "high-poly mesh")
    _check_mesh_file(args.low, "low-poly mesh")
    _check_no_overwrite(args)
    if not args.variant.startswith(("llvm_", "cuda_")):
        raise CLIError(f"--variant {args.variant}: the baker traces rays in bulk and needs a JIT "
                       "variant; choose llvm_ad_rgb (or cuda_ad_rgb)")
    return Path(args.output)


def _unwrapped(low_mesh, size: int, padding: int):
    """The low-poly with xatlas UVs."""
    import mitsuba as mi
    from mfnormal.io.meshes import mitsuba_mesh

    positions, normals, _, faces = mesh_arrays(low_mesh)
    if normals is None:
        raise CLIError("the low-poly mesh has no vertex normals (it is flat-shaded); give it smooth "
                       "vertex normals")
    p, n, uv, f = unwrap(positions, normals, faces, size, padding)
    return mitsuba_mesh("low", mi.load_dict({"type": "diffuse"}), p, n, uv, None, f)


def progress_lines(size: int, started: float, stream: TextIO = sys.stderr,
                   per_pass: int = TEXELS_PER_PASS) -> Callable[[int, int], None] | None:
    """The bake's progress callback: on a bake of PROGRESS_PASSES passes (of ``per_pass``
    texels) or more, a line on ``stream`` as each quarter of the texels is traced (at most three
    lines); None otherwise."""
    if size * size < PROGRESS_PASSES * per_pass:
        return None
    reported = [0]

    def report(done: int, total: int) -> None:
        quarter = 4 * done // total
        if reported[0] < quarter < 4:
            reported[0] = quarter
            print(f"mfnormal: bake: {25 * quarter} % of {total} texels traced "
                  f"({time.time() - started:.0f} s)", file=stream, flush=True)
    return report


def cmd_bake(args: argparse.Namespace) -> int:
    """Bake HIGH's normals onto LOW's UVs; write the PNG."""
    from mfnormal.render.passes import use_variant
    import mitsuba as mi

    output = _check_bake(args)
    use_variant(args.variant, CLIError, f"variant '{args.variant}' is not available in this "
                f"Mitsuba build; choose one of: {', '.join(v for v in mi.variants() if 'ad_rgb' in v)}",
                f"cannot use variant '{args.variant}'")
    started = time.time()
    try:
        high, low = load_mesh(args.high, "high-poly mesh"), load_mesh(args.low, "low-poly mesh")
        low = _unwrapped(low, args.size, args.padding) if args.unwrap else low
        baked = bake(high, low, args.size, args.cage, args.tangents, args.padding, args.high_normals,
                     progress_lines(args.size, started))
    except BakeError as exc:
        raise CLIError(str(exc)) from None
    except MemoryError:
        raise CLIError(f"--size {args.size}: not enough memory for the bake (about "
                       f"{memory_needed(args.size) / 2 ** 30:.1f} GiB); lower --size") from None
    covered = int(baked.covered.sum())
    if baked.missed > MISSED_WARN * max(covered, 1):
        fix = ("the cage spans the whole scene: the high-poly is not there along the low-poly's "
               "normals" if baked.cage_spans_scene else "raise --cage")
        print(f"mfnormal: warning: {baked.missed} of {covered} texels found no high-poly surface "
              f"within the cage and are flat; {fix}", file=sys.stderr, flush=True)
    meshes = [(args.unwrap, lambda p: low.write_ply(str(p)))] if args.unwrap else []
    if args.tangent_mesh:
        with_tangents = tangent_mesh("low", *mesh_arrays(low))     # checked by bake()
        meshes.append((args.tangent_mesh, lambda p: with_tangents.write_ply(str(p))))
    write_baked(output, baked.normals, args.bits, args.heights, baked.heights, meshes)
    print(f"baked {args.size}x{args.size} ({args.tangents} frame, {covered} texels covered) "
          f"in {time.time() - started:.1f}s")
    for path in (args.unwrap, args.tangent_mesh):
        if path:
            print(f"wrote {path}")
    print(f"wrote {output}")
    if args.heights:
        print(f"wrote {args.heights}")
    return 0


def add_bake(sub: argparse._SubParsersAction) -> argparse.ArgumentParser:
    b = sub.add_parser("bake", help="bake a tangent-space normal map of a high-poly mesh onto a "
                                    "low-poly mesh's UVs",
                       description="Bake the normals of HIGH onto the UVs of LOW (PLY or OBJ, as "
                                   "Mitsuba loads them): for each texel, the high-poly's normal "
                                   "nearest along the low-poly's interpolated normal, in the "
                                   "low-poly's tangent frame, as an RGB PNG.")
    b.add_argument("high", help="the high-poly mesh (.ply, .obj)")
    b.add_argument("low", help="the low-poly mesh with UVs and vertex normals (.ply, .obj)")
    b.add_argument("-o", "--output", required=True, help="the normal map to write (.png)")
    b.add_argument("--size", type=int, default=DEFAULT_SIZE,
                   help=f"map width and height in texels (default {DEFAULT_SIZE})")
    b.add_argument("--cage", type=float, help="how far from the low-poly surface to look for the "
                                              "high-poly (default: 5%% of the low-poly's "
                                              "bounding-box diagonal)")
    b.add_argument("--padding", type=int, default=4,
                   help="texels to extend each UV island by (default 4)")
    b.add_argument("--tangents", choices=TANGENT_FRAMES, default="mikktspace",
                   help="the frame of the map: mikktspace (default; decode with "
                        "tangents=vertex_tangent) or mitsuba (Mitsuba's si.sh_frame, as Mitsuba's "
                        "normalmap and tangents=mitsuba decode)")
    b.add_argument("--bits", type=int, choices=(8, 16), default=8, help="bits per channel (default 8)")
    b.add_argument("--heights", metavar="HEIGHTS.exr",
                   help="also write the high-poly's heights over the low-poly: per texel the signed "
                        "distance along the low-poly's interpolated normal (world units, positive "
                        "outside), a one-channel float OpenEXR")
    b.add_argument("--high-normals", choices=HIGH_NORMALS, default="shading",
                   help="the high-poly's interpolated (shading, default) or triangle (geometric) normal")
    b.add_argument("--unwrap", metavar="MESH.ply",
                   help="unwrap the low-poly with xatlas (pip install 'mfnormal[assets]'), write it "
                        "to MESH.ply and bake onto it")
    b.add_argument("--tangent-mesh", metavar="MESH.ply",
                   help="also write the low-poly with its MikkTSpace tangents (vertex attributes "
                        "vertex_tangent, vertex_tangent_sign) as PLY: the mesh an XML scene renders "
                        "the map on with tangents=\"vertex_tangent\" (--tangents mikktspace)")
    b.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (default llvm_ad_rgb)")
    b.set_defaults(func=cmd_bake)
    return b
