"""``mfnormal bake HIGH LOW -o MAP.png [--heights HEIGHTS.exr]``: a tangent-space normal map of a
high-poly mesh baked onto a low-poly mesh's UVs, and the high-poly's heights over the low-poly
(:mod:`mfnormal.io.bake`).

Every argument, both files and the output folders are checked before the meshes are loaded;
the meshes (and the low-poly's UVs) before the bake; the files are written atomically.
"""

from __future__ import annotations

import math
import time
from pathlib import Path

from mfnormal.io.bake import (BakeError, HIGH_NORMALS, MESH_SUFFIXES, SIZE_RANGE, TANGENT_FRAMES,
                              bake, check_low_poly, load_mesh, mesh_arrays, unwrap, write_baked)
from mfnormal.io.inputs import CLIError, check_output

__all__ = ["add_bake", "cmd_bake"]

DEFAULT_SIZE = 1024
PADDING_MAX = 64
#: Covered texels whose rays may miss the high-poly before the command warns.
MISSED_WARN = 0.01


def _check_mesh_file(path: str, what: str) -> None:
    p = Path(path)
    if not p.is_file():
        raise CLIError(f"{what} file not found: {path}")
    if p.suffix.lower() not in MESH_SUFFIXES:
        raise CLIError(f"{what} {path}: expected a .ply or .obj mesh")


def _check_bake(args) -> Path:
    """Every argument of ``mfnormal bake`` before anything is loaded; the map's path."""
    if not SIZE_RANGE[0] <= args.size <= SIZE_RANGE[1]:
        raise CLIError(f"--size {args.size}: expected a map size from {SIZE_RANGE[0]} to "
                       f"{SIZE_RANGE[1]} texels")
    if args.cage is not None and not (0 < args.cage < math.inf):
        raise CLIError(f"--cage {args.cage}: expected a distance above 0")
    if not 0 <= args.padding <= PADDING_MAX:
        raise CLIError(f"--padding {args.padding}: expected 0 to {PADDING_MAX} texels")
    output = Path(args.output)
    if output.suffix.lower() != ".png":
        raise CLIError(f"-o {args.output}: the map is a PNG; give a name ending in .png")
    check_output(output.with_suffix(""))
    if args.heights is not None:
        if Path(args.heights).suffix.lower() != ".exr":
            raise CLIError(f"--heights {args.heights}: the heights are a float OpenEXR; give a name "
                           "ending in .exr")
        check_output(Path(args.heights).with_suffix(""), "--heights")
    if args.unwrap is not None:
        if Path(args.unwrap).suffix.lower() != ".ply":
            raise CLIError(f"--unwrap {args.unwrap}: the unwrapped mesh is written as PLY; give a "
                           "name ending in .ply")
        check_output(Path(args.unwrap).with_suffix(""), "--unwrap")
    _check_mesh_file(args.high, "high-poly mesh")
    _check_mesh_file(args.low, "low-poly mesh")
    return output


def _unwrapped(low_mesh, path: str, size: int, padding: int):
    """The low-poly with xatlas UVs, also written to ``path`` (PLY, atomically)."""
    import mitsuba as mi
    from mfnormal.io.gltf import mitsuba_mesh
    from mfnormal.io.images import atomic_write

    positions, normals, _, faces = mesh_arrays(low_mesh)
    if normals is None:
        raise CLIError("the low-poly mesh has no vertex normals (it is flat-shaded); give it smooth "
                       "vertex normals")
    p, n, uv, f = unwrap(positions, normals, faces, size, padding)
    mesh = mitsuba_mesh("low", mi.load_dict({"type": "diffuse"}), p, n, uv, None, f)
    atomic_write(path, lambda p: mesh.write_ply(str(p)))
    return mesh


def cmd_bake(args) -> int:
    """Bake HIGH's normals onto LOW's UVs; write the PNG."""
    from mfnormal.cli.rendering import use_variant
    import mitsuba as mi

    output = _check_bake(args)
    use_variant(args.variant, CLIError, f"variant '{args.variant}' is not available in this "
                f"Mitsuba build; choose one of: {', '.join(v for v in mi.variants() if 'ad_rgb' in v)}",
                f"cannot use variant '{args.variant}'")
    started = time.time()
    try:
        high, low = load_mesh(args.high, "high-poly mesh"), load_mesh(args.low, "low-poly mesh")
        low = _unwrapped(low, args.unwrap, args.size, args.padding) if args.unwrap else low
        check_low_poly(low)
        baked = bake(high, low, args.size, args.cage, args.tangents, args.padding, args.high_normals)
    except BakeError as exc:
        raise CLIError(str(exc)) from None
    covered = int(baked.covered.sum())
    if baked.missed > MISSED_WARN * max(covered, 1):
        print(f"mfnormal: warning: {baked.missed} of {covered} texels found no high-poly surface "
              "within the cage and are flat; raise --cage", flush=True)
    write_baked(output, baked.normals, args.bits, args.heights, baked.heights)
    print(f"baked {args.size}x{args.size} ({args.tangents} frame, {covered} texels covered) "
          f"in {time.time() - started:.1f}s")
    if args.unwrap:
        print(f"wrote {args.unwrap}")
    print(f"wrote {output}")
    if args.heights:
        print(f"wrote {args.heights}")
    return 0


def add_bake(sub):
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
    b.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (default llvm_ad_rgb)")
    b.set_defaults(func=cmd_bake)
    return b
