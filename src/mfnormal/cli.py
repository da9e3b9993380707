"""The ``mfnormal`` command line: render scenes that use the plugin, and the bundled demo.

    mfnormal render SCENE.xml|MODEL.gltf|MODEL.glb [-o OUT] [--spp N] [--variant V] [-D key=value ...]
    mfnormal demo [-o OUT] [--spp N] [--model M]
    mfnormal compare SCENE [SCENE ...] [-o DIR] [--spp N] [--ref-spp N] [--quick]

Every error is one line on stderr and a non-zero exit code; outputs are written
atomically (a linear EXR and a tonemapped PNG).
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
from pathlib import Path

from .messages import one_line

DEFAULT_VARIANT = "llvm_ad_rgb"
# The validation figures committed with the source tree (absent in an installed wheel).
VALIDATION_RESULTS = Path(__file__).resolve().parents[2] / "validation" / "results"


class CLIError(Exception):
    """An error to report as one line, without a traceback."""


def setup_variant(variant: str):
    """Import Mitsuba in ``variant`` with the plugin registered, or raise CLIError."""
    import mfnormal
    import mitsuba as mi

    if variant not in mi.variants():
        raise CLIError(f"variant '{variant}' is not available in this Mitsuba build; "
                       f"choose one of: {', '.join(v for v in mi.variants() if 'rgb' in v)}")
    try:
        mi.set_variant(variant)
    except Exception as exc:  # e.g. cuda_* without a GPU
        raise CLIError(f"cannot use variant '{variant}': {one_line(exc)}") from None
    mfnormal.register()
    return mi


def parse_defines(defines: list[str]) -> dict[str, str]:
    params = {}
    for item in defines or []:
        if "=" not in item:
            raise CLIError(f"-D expects key=value, got '{item}'")
        key, value = item.split("=", 1)
        params[key.strip()] = value
    return params


def _flag(text: str) -> bool:
    if text.strip().lower() in ("1", "true", "yes", "on"):
        return True
    if text.strip().lower() in ("0", "false", "no", "off"):
        return False
    raise ValueError(f"expected true or false, got '{text}'")


# -D options of a glTF file: load_gltf's keyword arguments, parsed from text.
GLTF_OPTIONS = {"width": int, "height": int, "spp": int, "max_depth": int, "model": str,
                "tangents": str, "normal_maps": _flag, "lights": _flag}


def _gltf_scene(mi, path: Path, params: dict[str, str]):
    """The scene dict of a glTF file, with -D key=value as load_gltf options."""
    from .gltf import load_gltf

    options = {}
    for key, value in params.items():
        if key not in GLTF_OPTIONS:
            raise CLIError(f"unknown -D option '{key}' for a glTF scene; use one of "
                           f"{', '.join(GLTF_OPTIONS)}")
        try:
            options[key] = GLTF_OPTIONS[key](value)
        except ValueError:
            raise CLIError(f"-D {key}={value}: not a valid {key}") from None
    return mi.load_dict(load_gltf(path, **options))


def load_scene(mi, path, params: dict[str, str]):
    """A Mitsuba XML scene (``-D`` sets its ``$key`` defaults) or a glTF 2.0 file (``.gltf``, ``.glb``)."""
    from .gltf import GLTF_SUFFIXES

    path = Path(path)
    if not path.is_file():
        raise CLIError(f"scene file not found: {path}")
    try:
        if path.suffix.lower() in GLTF_SUFFIXES:
            scene = _gltf_scene(mi, path, params)
        else:
            scene = mi.load_file(str(path), **params)
    except CLIError:
        raise
    except Exception as exc:
        raise CLIError(f"cannot load {path}: {one_line(exc)}") from None
    from .scene_checks import check_scene
    try:
        check_scene(scene)
    except ValueError as exc:
        raise CLIError(f"{path}: {exc}") from None
    return scene


class Progress:
    """A one-line progress bar with ETA on a terminal; silent when piped."""

    def __init__(self, total: int, stream=sys.stderr):
        self.total, self.stream = total, stream
        self.enabled = stream.isatty()
        self.start = time.time()

    def update(self, done: int):
        if not self.enabled:
            return
        elapsed = time.time() - self.start
        eta = elapsed / done * (self.total - done) if done else 0.0
        bar = "#" * int(30 * done / self.total)
        self.stream.write(f"\r[{bar:<30}] {done}/{self.total} passes, {elapsed:5.1f}s, ETA {eta:5.1f}s")
        if done == self.total:
            self.stream.write("\n")
        self.stream.flush()


def render_scene(mi, scene, spp: int | None = None, passes: int | None = None, seed: int = 0, progress=True):
    """Render in passes (for the progress bar) and average them; returns linear RGB (numpy)."""
    import numpy as np

    sensor = scene.sensors()[0]
    total = int(spp or sensor.sampler().sample_count())
    passes = max(1, min(total, passes or (8 if total >= 8 else total)))
    counts = [total // passes + (1 if i < total % passes else 0) for i in range(passes)]
    bar = Progress(passes) if progress else None
    acc = None
    for i, n in enumerate(counts):
        img = np.array(mi.render(scene, spp=n, seed=seed * 1000003 + i), dtype=np.float64)
        acc = img * n if acc is None else acc + img * n
        if bar:
            bar.update(i + 1)
    rgb = (acc / total).astype(np.float32)
    return rgb[..., :3] if rgb.ndim == 3 else rgb


def _finish(mi, rgb, output, started, spp, variant):
    import mfnormal

    from .images import sanitize, save_render

    rgb, bad = sanitize(rgb)
    if bad:
        print(f"warning: {bad} pixel(s) were NaN/Inf and were written as 0", file=sys.stderr)
    exr, png = save_render(rgb, output)
    print(f"variant {variant}, libLLVM {mfnormal.LLVM_PATH}")
    print(f"rendered {rgb.shape[1]}x{rgb.shape[0]} at {spp} spp in {time.time() - started:.1f}s")
    print(f"wrote {exr}\nwrote {png}")
    return 0


def cmd_render(args) -> int:
    mi = setup_variant(args.variant)
    params = parse_defines(args.define)
    started = time.time()
    scene = load_scene(mi, args.scene, params)
    spp = args.spp or scene.sensors()[0].sampler().sample_count()
    try:
        rgb = render_scene(mi, scene, spp, seed=args.seed)
    except Exception as exc:
        raise CLIError(f"render failed: {one_line(exc)}") from None
    output = args.output or Path("out") / Path(args.scene).stem
    return _finish(mi, rgb, output, started, spp, args.variant)


def cmd_demo(args) -> int:
    from . import demo

    argv = ["-o", str(args.output)] if args.output else []
    if args.spp:
        argv += ["--spp", str(args.spp)]
    if args.model:
        argv += ["--model", args.model]
    return demo.main(argv)


def _width(text: str) -> int:
    v = int(text)
    if v < 8:
        raise argparse.ArgumentTypeError(f"expected a width of at least 8 pixels, got {text!r}")
    return v


def cmd_compare(args) -> int:
    """Render SCENE(s) with every normal-mapping method; write DIR/report.html."""
    import dataclasses

    setup_variant(args.variant)
    from . import compare

    settings = compare.QUICK if args.quick else compare.Settings()
    changes = {"seed": args.seed}
    if args.spp:
        changes["spp"] = args.spp
    if args.ref_spp or args.spp:
        changes["ref_spp"] = args.ref_spp or 4 * changes.get("spp", settings.spp)
    if args.width:
        changes["width"] = args.width
    settings = dataclasses.replace(settings, **changes)
    methods = compare.METHODS
    if args.methods:
        keys = [k.strip() for k in args.methods.split(",") if k.strip()]
        unknown = [k for k in keys if k not in compare.METHOD_BY_KEY]
        if unknown:
            raise CLIError(f"unknown method(s) {', '.join(unknown)}; choose from "
                           f"{', '.join(compare.METHOD_BY_KEY)}")
        methods = tuple(compare.METHOD_BY_KEY[k] for k in keys)
    if args.validation is None and not args.quick and VALIDATION_RESULTS.is_dir():
        args.validation = str(VALIDATION_RESULTS)   # figures of validation/run.py in a checkout
    if args.validation and not Path(args.validation).is_dir():
        raise CLIError(f"validation directory not found: {args.validation}")
    for scene in args.scenes:
        if scene not in compare.BUNDLED and not Path(scene).is_file():
            raise CLIError(f"scene file not found: {scene} (bundled scenes: {', '.join(compare.BUNDLED)})")
    out = Path(args.output)
    command = "mfnormal " + " ".join(shlex.quote(a) for a in getattr(args, "argv", []))
    try:
        report = compare.compare(args.scenes, out, settings, methods, validation=args.validation,
                                 params=parse_defines(args.define), command=command)
    except compare.SceneError as exc:
        raise CLIError(str(exc)) from None
    except Exception as exc:  # e.g. a render that fails deep inside Dr.Jit
        raise CLIError(f"compare failed: {one_line(exc)}") from None
    print(f"wrote {report}")
    return 0


def build_parser() -> argparse.ArgumentParser:
    parser = argparse.ArgumentParser(prog="mfnormal", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="render a Mitsuba 3 scene (XML) that may use normalmap_microfacet, "
                                      "or a glTF 2.0 model (.gltf, .glb)")
    r.add_argument("scene", help="scene file (.xml), or a glTF 2.0 file (.gltf, .glb: -D sets width, "
                                 "height, spp, max_depth, model, tangents, normal_maps, lights)")
    r.add_argument("-o", "--output", help="output path without extension (writes .exr and .png)")
    r.add_argument("--spp", type=int, help="samples per pixel (default: the scene's)")
    r.add_argument("--variant", default=DEFAULT_VARIANT, help=f"Mitsuba variant (default {DEFAULT_VARIANT})")
    r.add_argument("--seed", type=int, default=0)
    r.add_argument("-D", "--define", action="append", metavar="KEY=VALUE", help="scene parameter ($KEY)")
    r.set_defaults(func=cmd_render)

    d = sub.add_parser("demo", help="render the bundled demo scene")
    d.add_argument("-o", "--output", help="output path (default out/demo.png)")
    d.add_argument("--spp", type=int)
    d.add_argument("--model")
    d.set_defaults(func=cmd_demo)

    c = sub.add_parser("compare", help="render a scene with every normal-mapping method; write an HTML report",
                       description="Render SCENE once per normal-mapping method (flat, Mitsuba's normalmap "
                                   "without and with its fixes, normalmap_microfacet's analytic, separable "
                                   "and non-separable models with both tangent facets) and write a "
                                   "self-contained DIR/report.html. SCENE is an XML file whose normal-mapped "
                                   "materials are normalmap_microfacet BSDFs, or a bundled scene: "
                                   "'demo' (a) or 'model' (b).")
    c.add_argument("scenes", nargs="+", metavar="SCENE", help="scene file (.xml), 'demo' or 'model'")
    c.add_argument("-o", "--output", default=os.path.join("out", "compare"),
                   help="output directory (default out/compare)")
    c.add_argument("--spp", type=int, help="samples per pixel (default 32; --quick: 2)")
    c.add_argument("--ref-spp", type=int, help="samples per pixel of the references (default 4x spp)")
    c.add_argument("--width", type=_width,
                   help="scale the film down to this width, keeping its aspect (default 320; --quick: 64)")
    c.add_argument("--methods", help="comma-separated subset of the methods (default: all)")
    c.add_argument("--validation", metavar="DIR",
                   help="add the PNG figures in DIR to the report (default: validation/results "
                        "of this checkout, written by validation/run.py, when it exists)")
    c.add_argument("--quick", action="store_true", help="tiny images and sample counts (for tests)")
    c.add_argument("--variant", default=DEFAULT_VARIANT, help=f"Mitsuba variant (default {DEFAULT_VARIANT})")
    c.add_argument("--seed", type=int, default=0)
    c.add_argument("-D", "--define", action="append", metavar="KEY=VALUE", help="scene parameter ($KEY)")
    c.set_defaults(func=cmd_compare)
    return parser


def main(argv=None) -> int:
    parser = build_parser()
    args = parser.parse_args(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    if getattr(args, "spp", None) is not None and args.spp < 1:
        parser.error("--spp must be >= 1")
    if getattr(args, "ref_spp", None) is not None and args.ref_spp < 1:
        parser.error("--ref-spp must be >= 1")
    try:
        return args.func(args)
    except CLIError as exc:
        print(f"mfnormal: error: {exc}", file=sys.stderr)
        return 2
    except ImportError as exc:  # e.g. no usable libLLVM
        print(f"mfnormal: error: {exc}", file=sys.stderr)
        return 2
    except KeyboardInterrupt:
        print("mfnormal: interrupted", file=sys.stderr)
        return 130


if __name__ == "__main__":
    sys.exit(main())
