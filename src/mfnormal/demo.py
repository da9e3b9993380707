"""Bundled demo: render a normal-mapped sphere and ground plane.

    python -m mfnormal.demo [-o out/demo.png] [--spp N] [--model analytic]
    mfnormal-demo ...                                  (same, console script)

All assets are generated procedurally (:func:`generate_assets`): a strong
tangent-space normal map of pillowed tiles with a hemispherical rivet in each
(OpenGL convention, 8-bit PNG) and a small HDR sky with a sun (EXR).

The scene itself is described once, in ``scenes/demo.xml`` (see
:data:`SCENE_XML`). :func:`main` renders that file with ``mi.load_file``;
:func:`demo_scene` converts the same file into a Python scene dict (for tests
and programmatic use, e.g. to swap the nested BSDF).

``model='classic'`` in :func:`demo_scene` / ``--model classic`` replaces the
plugin by Mitsuba's built-in ``normalmap`` BSDF, for comparison.
"""

from __future__ import annotations

import argparse
import copy
import os
import sys
import time
from pathlib import Path

import numpy as np

import mfnormal  # before mitsuba: selects a working libLLVM for Dr.Jit
import mitsuba as mi

from .images import atomic_write, output_paths
from .methods import PLUGIN
from .scene_xml import dicts_of_type, xml_to_dict

__all__ = ["SCENE_XML", "generate_assets", "make_normalmap", "make_envmap", "demo_scene",
           "load_scene", "render_scene", "render", "main"]

#: The demo scene (single source of truth).
SCENE_XML = Path(__file__).resolve().parent / "scenes" / "demo.xml"

NORMALMAP_NAME = "normalmap.png"
ENVMAP_NAME = "envmap.exr"

VARIANT = "llvm_ad_rgb"
DEFAULT_OUTPUT = os.path.join("out", "demo.png")
DEFAULT_SPP = 64
DEFAULT_RESOLUTION = (512, 384)
DEFAULT_MAX_DEPTH = 8

# Value of the 'model' parameter that selects Mitsuba's built-in normal mapping.
CLASSIC = "classic"


# ---------------------------------------------------------------------------
# Procedural assets
# ---------------------------------------------------------------------------

def make_normalmap(size: int = 512, tiles: int = 4, gap: float = 0.035,
                   bevel: float = 0.2, rivet: float = 0.2) -> np.ndarray:
    """Unit tangent-space normals (``size`` x ``size`` x 3, float32).

    A running-bond pattern of ``tiles`` x ``tiles`` square tiles separated by
    flat grooves; each tile has a quarter-circle bevel (its normals tilt all the
    way to the horizon at the tile border) and a hemispherical rivet in its
    centre. The pattern is periodic, so the map tiles seamlessly. All lengths
    are in units of one tile.

    OpenGL convention: +x points right and +y *up* in the image (row 0 is the
    top row), so a bump looks green at its top and red at its right side.
    """
    c = (np.arange(size, dtype=np.float64) + 0.5) * (tiles / size)
    x, y = np.meshgrid(c, c)                     # y grows downwards (rows)
    row = np.floor(y)
    xs = x + 0.5 * (row % 2)                     # offset every other row
    px = xs - np.floor(xs) - 0.5                 # position within the tile,
    py = y - row - 0.5                           # in [-0.5, 0.5)
    half = 0.5 - gap / 2

    # Bevel: distance to the inner (flat-topped) rectangle, rounded corners.
    mx = np.maximum(np.abs(px) - (half - bevel), 0.0)
    my = np.maximum(np.abs(py) - (half - bevel), 0.0)
    d = np.hypot(mx, my)
    s = np.clip(d / bevel, 0.0, 1.0)             # sin of the tilt
    inv_d = np.where(d > 0, 1.0 / np.maximum(d, 1e-12), 0.0)
    nx = s * mx * inv_d * np.sign(px)
    ny = -s * my * inv_d * np.sign(py)           # image y is down, normal y up
    nz = np.sqrt(np.maximum(1.0 - s * s, 0.0))

    in_groove = (np.abs(px) > half) | (np.abs(py) > half)
    nx[in_groove], ny[in_groove], nz[in_groove] = 0.0, 0.0, 1.0

    # Hemispherical rivet.
    r2 = px * px + py * py
    on_rivet = r2 < rivet * rivet
    nx = np.where(on_rivet, px / rivet, nx)
    ny = np.where(on_rivet, -py / rivet, ny)
    nz = np.where(on_rivet, np.sqrt(np.maximum(rivet * rivet - r2, 0.0)) / rivet, nz)

    n = np.stack([nx, ny, nz], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n.astype(np.float32)


def encode_normalmap(n: np.ndarray) -> np.ndarray:
    """8-bit encoding rgb = n * 0.5 + 0.5."""
    return np.clip(np.round((n * 0.5 + 0.5) * 255.0), 0, 255).astype(np.uint8)


def envmap_directions(width: int, height: int) -> np.ndarray:
    """World direction of every pixel centre of a lat-long map, as Mitsuba's
    ``envmap`` (with identity ``to_world``) maps it: y is up, row 0 is the
    zenith, u = atan2(x, -z) / (2 pi)."""
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    phi, theta = np.meshgrid(2.0 * np.pi * u, np.pi * v)
    return np.stack([np.sin(theta) * np.sin(phi), np.cos(theta),
                     -np.sin(theta) * np.cos(phi)], axis=-1)


def make_envmap(width: int = 256, height: int = 128,
                sun_direction=(-0.75, 0.34, -0.56), sun_radiance: float = 700.0,
                sun_size_deg: float = 4.0, sky_scale: float = 0.7) -> np.ndarray:
    """Linear RGB radiance (``height`` x ``width`` x 3, float32): a blue sky
    gradient, a darker ground below the horizon and a bright sun blob.

    The default sun stands about 20 degrees high behind the scene, to the left
    of the demo camera (which looks down -z)."""
    d = envmap_directions(width, height)
    up = d[..., 1:2]
    zenith = np.array([0.22, 0.38, 0.8])
    horizon = np.array([1.0, 0.95, 0.88])
    ground = np.array([0.22, 0.19, 0.16])
    t = np.clip(up, 0.0, 1.0) ** 0.45
    sky = horizon * (1.0 - t) + zenith * t
    # smooth the horizon over ~3 degrees
    w = np.clip(up / 0.05 + 0.5, 0.0, 1.0)
    rgb = sky_scale * (sky * w + ground * (1.0 - w))

    s = np.asarray(sun_direction, dtype=np.float64)
    s /= np.linalg.norm(s)
    cos_a = np.clip(d @ s, -1.0, 1.0)[..., None]
    ang = np.arccos(cos_a)
    sigma = np.radians(sun_size_deg)
    sun_rgb = np.array([1.0, 0.93, 0.82])
    rgb = rgb + sun_rgb * (sun_radiance * np.exp(-0.5 * (ang / sigma) ** 2)
                           + 2.0 * np.exp(-ang / 0.25))   # blob + soft glow
    return rgb.astype(np.float32)


def generate_assets(assets_dir) -> dict:
    """Write the procedural textures into ``assets_dir``; returns their paths
    as ``{'normalmap': Path, 'envmap': Path}``. Deterministic and fast (well
    under a second), so the files are simply rewritten every time."""
    assets_dir = Path(assets_dir)
    paths = {"normalmap": assets_dir / NORMALMAP_NAME, "envmap": assets_dir / ENVMAP_NAME}
    normals = mi.Bitmap(encode_normalmap(make_normalmap()))
    sky = mi.Bitmap(make_envmap(), mi.Bitmap.PixelFormat.RGB)
    atomic_write(paths["normalmap"], lambda p: normals.write(str(p), mi.Bitmap.FileFormat.PNG))
    atomic_write(paths["envmap"], lambda p: sky.write(str(p), mi.Bitmap.FileFormat.OpenEXR))
    return paths


def default_assets_dir() -> Path:
    """Per-user cache directory for the generated textures."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return Path(base) / "mfnormal" / "demo_assets"


# ---------------------------------------------------------------------------
# Scene: XML file -> parameters / dict
# ---------------------------------------------------------------------------

def scene_parameters(model: str = "faithful", spp: int = DEFAULT_SPP,
                     resolution=DEFAULT_RESOLUTION, assets: dict | None = None,
                     strength: float = 1.0, max_depth: int = DEFAULT_MAX_DEPTH) -> dict:
    """The ``$name`` substitutions of :data:`SCENE_XML`, as strings."""
    width, height = resolution
    params = {"spp": str(int(spp)), "width": str(int(width)), "height": str(int(height)),
              "max_depth": str(int(max_depth)), "model": str(model),
              "strength": repr(float(strength))}
    if assets is not None:
        params["normalmap"] = str(Path(assets["normalmap"]).resolve())
        params["envmap"] = str(Path(assets["envmap"]).resolve())
    return params


def demo_scene(model: str = "faithful", bsdf: dict | None = None, spp: int = DEFAULT_SPP,
               resolution=DEFAULT_RESOLUTION, assets_dir=None, strength: float = 1.0,
               max_depth: int = DEFAULT_MAX_DEPTH) -> dict:
    """The demo scene (:data:`SCENE_XML`) as a Mitsuba scene dict.

    Args:
        model: ``normalmap_microfacet``'s ``model`` parameter; ``'classic'``
            uses Mitsuba's built-in ``normalmap`` BSDF instead.
        bsdf: optional nested BSDF dict replacing the materials of both the
            sphere and the ground.
        spp, resolution, max_depth: samples per pixel, (width, height), path length.
        assets_dir: where the generated textures are written
            (default: :func:`default_assets_dir`).
        strength: normal map strength (ignored by ``'classic'``).

    The active variant must be set before calling this (``mi.load_dict`` of
    the result needs ``mfnormal.register()`` as well).
    """
    assets = generate_assets(default_assets_dir() if assets_dir is None else assets_dir)
    classic = model == CLASSIC
    params = scene_parameters(model="analytic" if classic else model, spp=spp,
                              resolution=resolution, assets=assets, strength=strength,
                              max_depth=max_depth)
    scene = xml_to_dict(SCENE_XML, **params)
    for nm in list(dicts_of_type(scene, PLUGIN)):
        if bsdf is not None:
            nm["bsdf"] = copy.deepcopy(bsdf)
        if classic:
            nm["type"] = "normalmap"
            for key in ("model", "strength", "normalmap_convention"):
                nm.pop(key, None)
    return scene


# ---------------------------------------------------------------------------
# Rendering and output
# ---------------------------------------------------------------------------

def load_scene(model: str = "faithful", spp: int = DEFAULT_SPP, resolution=DEFAULT_RESOLUTION,
               assets_dir=None, strength: float = 1.0,
               max_depth: int = DEFAULT_MAX_DEPTH) -> "mi.Scene":
    """Generate the textures and load the demo scene in the active variant.

    Loads :data:`SCENE_XML` with ``mi.load_file``; ``model='classic'`` goes
    through :func:`demo_scene` instead (the XML names the plugin).
    """
    if model == CLASSIC:
        return mi.load_dict(demo_scene(model=model, spp=spp, resolution=resolution,
                                       assets_dir=assets_dir, strength=strength,
                                       max_depth=max_depth))
    assets = generate_assets(default_assets_dir() if assets_dir is None else assets_dir)
    params = scene_parameters(model=model, spp=spp, resolution=resolution,
                              assets=assets, strength=strength, max_depth=max_depth)
    return mi.load_file(str(SCENE_XML), **params)


def render_scene(scene: "mi.Scene", seed: int = 0) -> np.ndarray:
    """Render ``scene``; returns linear RGB (H x W x 3, float32, evaluated)."""
    return np.array(mi.render(scene, seed=seed), dtype=np.float32)[..., :3]


def render(seed: int = 0, **kwargs) -> np.ndarray:
    """:func:`load_scene` (``kwargs``) + :func:`render_scene`: linear RGB (H x W x 3)."""
    return render_scene(load_scene(**kwargs), seed=seed)


def _resolution(text: str) -> tuple:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w <= 0 or h <= 0:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 512x384, got {text!r}")
    return w, h


def _positive_int(text: str) -> int:
    v = int(text)
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def build_parser(parser_class=argparse.ArgumentParser) -> argparse.ArgumentParser:
    from .validate import LIMIT_HELP

    parser = parser_class(
        prog="mfnormal-demo",
        description="Render the mfnormal demo scene (scenes/demo.xml): a normal-mapped "
                    "sphere and ground plane under a procedural sky. Writes a linear EXR "
                    "and a tonemapped sRGB PNG.")
    parser.add_argument("-o", "--output", default=DEFAULT_OUTPUT,
                        help="output image; the .exr and .png are written side by side "
                             f"(default: {DEFAULT_OUTPUT})")
    parser.add_argument("--spp", type=_positive_int, default=DEFAULT_SPP,
                        help=f"samples per pixel (default: {DEFAULT_SPP})")
    parser.add_argument("--resolution", type=_resolution, default=DEFAULT_RESOLUTION,
                        metavar="WxH", help="image size (default: %dx%d)" % DEFAULT_RESOLUTION)
    parser.add_argument("--model", default="faithful",
                        help="normalmap_microfacet model (default: faithful), or "
                             f"'{CLASSIC}' for Mitsuba's built-in normal mapping")
    parser.add_argument("--strength", type=float, default=1.0,
                        help="normal map strength (default: 1.0)")
    parser.add_argument("--max-depth", type=int, default=DEFAULT_MAX_DEPTH,
                        help=f"path integrator max_depth (default: {DEFAULT_MAX_DEPTH})")
    parser.add_argument("--exposure", type=float, default=0.0,
                        help="exposure of the PNG in stops (default: 0)")
    parser.add_argument("--seed", type=int, default=0, help="sampler seed, 0 to 4294967295 (default: 0)")
    parser.add_argument("--assets-dir", default=None,
                        help="where to generate the textures (default: <output dir>/demo_assets)")
    parser.add_argument("--limit", action="append", metavar="NAME=N", help=LIMIT_HELP)
    return parser


def check_args(args) -> None:
    """Every argument of :func:`run`, before anything is written; raises CLIError."""
    from .plugin import MODELS
    from .validate import (CLIError, check_int32, check_output, check_render_size, check_seed,
                           check_spp, parse_limits)

    if args.model not in MODELS + (CLASSIC,):
        raise CLIError(f"--model {args.model}: unknown model; choose one of {', '.join(MODELS + (CLASSIC,))}")
    check_spp(args.spp, "--spp")
    check_seed(args.seed)
    check_int32(args.max_depth, "--max-depth", lo=-1)
    if not (0.0 <= args.strength < float("inf")):
        raise CLIError(f"--strength {args.strength}: the strength must be a finite number >= 0")
    if not np.isfinite(args.exposure) or abs(args.exposure) > 100:
        raise CLIError(f"--exposure {args.exposure}: expected a number of stops from -100 to 100")
    w, h = args.resolution
    check_render_size(w, h, parse_limits(args.limit), "the demo image")
    check_output(args.output)
    if args.assets_dir is not None:
        check_output(Path(args.assets_dir) / NORMALMAP_NAME, "--assets-dir")


def run(args) -> int:
    """Render the demo with parsed ``args`` (:func:`build_parser`); raises CLIError (one
    line) on bad arguments, before anything is written, and on a failed load or render."""
    from .cli import Progress, write_render
    from .messages import one_line
    from .rendering import MAX_PASS_LANES, render_scene as render_in_passes
    from .validate import CLIError

    check_args(args)
    exr_path, png_path = output_paths(args.output)
    assets_dir = Path(args.assets_dir) if args.assets_dir else exr_path.parent / "demo_assets"

    mi.set_variant(VARIANT)
    mfnormal.register()
    print(f"variant : {mi.variant()}")
    print(f"LLVM    : {mfnormal.LLVM_PATH}")
    print(f"scene   : {SCENE_XML}  (model={args.model}, {args.resolution[0]}x"
          f"{args.resolution[1]}, {args.spp} spp, max_depth={args.max_depth})")
    sys.stdout.flush()

    t0 = time.perf_counter()
    try:
        scene = load_scene(model=args.model, spp=args.spp, resolution=args.resolution,
                           assets_dir=assets_dir, strength=args.strength, max_depth=args.max_depth)
    except Exception as exc:
        raise CLIError(f"cannot load the demo scene: {one_line(exc)}") from None
    t1 = time.perf_counter()
    try:
        if args.spp * args.resolution[0] * args.resolution[1] <= MAX_PASS_LANES:
            rgb = render_scene(scene, seed=args.seed)
        else:   # in passes of bounded size
            rgb = render_in_passes(scene, args.spp, seed=args.seed, progress=Progress().update)
    except Exception as exc:
        raise CLIError(f"render failed: {one_line(exc)}") from None
    t2 = time.perf_counter()
    _, exr_path, png_path = write_render(mi, scene, rgb, args.output, exposure=args.exposure)
    print(f"load    : {t1 - t0:.1f} s (texture generation and scene loading)")
    print(f"render  : {t2 - t1:.1f} s (JIT compilation and rendering)")
    print(f"wrote   : {exr_path}")
    print(f"wrote   : {png_path}")
    return 0


def main(argv=None) -> int:
    """``mfnormal-demo``: :func:`run` with the command line's one-line error path."""
    from .cli import _Parser, run_command

    return run_command("mfnormal-demo", lambda: run(build_parser(_Parser).parse_args(argv)))


if __name__ == "__main__":
    sys.exit(main())
