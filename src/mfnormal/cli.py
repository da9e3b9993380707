"""The ``mfnormal`` command line: render scenes that use the plugin, and the bundled demo.

    mfnormal render SCENE.xml|MODEL.gltf|MODEL.glb [-o OUT] [--spp N] [--variant V] [-D key=value ...]
    mfnormal demo [-o OUT] [--spp N] [--model M]
    mfnormal compare SCENE [SCENE ...] [-o DIR] [--spp N] [--ref-spp N] [--quick]
    (each also takes --limit NAME=N: the caps of mfnormal.validate.Limits)

Every error is one line on stderr and exit code 2, reported before the render
starts wherever it can be known then (:mod:`mfnormal.validate`); outputs are
written as a pair (a linear EXR and a tonemapped PNG), atomically.
"""

from __future__ import annotations

import argparse
import os
import shlex
import sys
import time
import warnings
from pathlib import Path

from .messages import one_line
from .validate import (CLIError, DEFAULT_LIMITS, LIMIT_HELP, Limits, Terminated, check_int32,
                       check_output, check_scene_before_render, check_seed, check_spp,
                       check_xml_integers, parse_limits, pass_count, pass_seed, pass_spp,
                       raise_on_sigterm)

__all__ = ["CLIError", "main", "build_parser", "load_scene", "render_scene", "setup_variant",
           "parse_defines", "run_command"]

DEFAULT_VARIANT = "llvm_ad_rgb"
# The validation figures committed with the source tree (absent in an installed wheel).
VALIDATION_RESULTS = Path(__file__).resolve().parents[2] / "validation" / "results"


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
        key = key.strip()
        if not key.isidentifier():
            raise CLIError(f"-D {item}: '{key}' is not a parameter name (letters, digits and _)")
        params[key] = value
    return params


def _flag(text: str) -> bool:
    if text.strip().lower() in ("1", "true", "yes", "on"):
        return True
    if text.strip().lower() in ("0", "false", "no", "off"):
        return False
    raise ValueError(f"expected true or false, got '{text}'")


# -- D options of a glTF file: load_gltf's keyword arguments, parsed from text, with their ranges.
GLTF_OPTIONS = {"width": int, "height": int, "spp": int, "max_depth": int, "model": str,
                "tangents": str, "normal_maps": _flag, "lights": _flag, "macro_normal": str}
_GLTF_RANGES = {"width": (1, None), "height": (1, None), "spp": (1, None), "max_depth": (-1, None)}


def gltf_options(params: dict[str, str]) -> dict:
    """``-D`` values as :func:`mfnormal.gltf.load_gltf` keyword arguments, checked."""
    options = {}
    for key, value in params.items():
        if key not in GLTF_OPTIONS:
            raise CLIError(f"unknown -D option '{key}' for a glTF scene; use one of "
                           f"{', '.join(GLTF_OPTIONS)}")
        try:
            options[key] = GLTF_OPTIONS[key](value.strip() if GLTF_OPTIONS[key] is int else value)
        except ValueError:
            raise CLIError(f"-D {key}={value}: not a valid {key}") from None
        if key in _GLTF_RANGES:
            lo, _ = _GLTF_RANGES[key]
            check_int32(options[key], f"-D {key}={value}", lo=lo)
    return options


def _gltf_scene(mi, path: Path, params: dict[str, str], limits: Limits):
    """The scene dict of a glTF file, with -D key=value as load_gltf options."""
    from .gltf import load_gltf

    options = gltf_options(params)
    return mi.load_dict(load_gltf(path, limits=limits, **options))


def load_scene(mi, path, params: dict[str, str], limits: Limits = DEFAULT_LIMITS):
    """A Mitsuba XML scene (``-D`` sets its ``$key`` defaults) or a glTF 2.0 file (``.gltf``, ``.glb``)."""
    from .gltf import GLTF_SUFFIXES, GLTFError

    path = Path(path)
    if not path.is_file():
        raise CLIError(f"scene file not found: {path}")
    gltf = path.suffix.lower() in GLTF_SUFFIXES
    if not gltf:
        check_xml_integers(path, params)
    try:
        if gltf:
            scene = _gltf_scene(mi, path, params, limits)
        else:
            scene = mi.load_file(str(path), **params)
    except CLIError:
        raise
    except GLTFError as exc:
        raise CLIError(f"{path.name}: {exc}") from None
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
    """Render in passes (for the progress bar, and to bound each pass's size) and average
    them; returns the film's channels (H × W × C, float32: RGB, Y, or with AOVs)."""
    import numpy as np

    sensor = scene.sensors()[0]
    total = int(spp or sensor.sampler().sample_count())
    pixels = int(np.prod([int(v) for v in sensor.film().crop_size()]))
    n_passes = pass_count(total, pixels, passes)
    bar = Progress(n_passes) if progress else None
    acc = None
    for i in range(n_passes):
        n = pass_spp(total, n_passes, i)
        img = np.array(mi.render(scene, spp=n, seed=pass_seed(seed, i)), dtype=np.float64)
        acc = img * n if acc is None else acc + img * n
        if bar:
            bar.update(i + 1)
    out = (acc / total).astype(np.float32)
    return out if out.ndim == 3 else out[..., None]


def write_render(mi, scene, img, output, exposure: float = 0.0):
    """Sanitise (NaN/Inf and negative colour → 0, warned about) and write the EXR/PNG pair."""
    from .images import film_channel_names, sanitize_counts, save_render

    names = film_channel_names(scene.sensors()[0].film(), img.shape[-1])
    img, nonfinite, negative = sanitize_counts(img, names)
    if nonfinite:
        print(f"mfnormal: warning: {nonfinite} pixel(s) were NaN/Inf and were written as 0", file=sys.stderr)
    if negative:
        print(f"mfnormal: warning: {negative} pixel(s) had negative values and were written as 0",
              file=sys.stderr)
    try:
        exr, png = save_render(img, output, exposure, names=names)
    except (OSError, RuntimeError) as exc:
        raise CLIError(f"cannot write {output}: {one_line(exc)}") from None
    return img, exr, png


def cmd_render(args) -> int:
    import mfnormal

    limits = parse_limits(args.limit)
    check_seed(args.seed)
    if args.spp is not None:
        check_spp(args.spp, "--spp")
    output = args.output or str(Path("out") / Path(args.scene).stem)
    check_output(output)
    params = parse_defines(args.define)
    mi = setup_variant(args.variant)
    started = time.time()
    scene = load_scene(mi, args.scene, params, limits)
    spp = check_scene_before_render(mi, scene, args.spp, limits, Path(args.scene).name)
    try:
        img = render_scene(mi, scene, spp, seed=args.seed)
    except Exception as exc:
        raise CLIError(f"render failed: {one_line(exc)}") from None
    img, exr, png = write_render(mi, scene, img, output)
    print(f"variant {args.variant}, libLLVM {mfnormal.LLVM_PATH}")
    print(f"rendered {img.shape[1]}x{img.shape[0]} at {spp} spp in {time.time() - started:.1f}s")
    print(f"wrote {exr}\nwrote {png}")
    return 0


def cmd_demo(args) -> int:
    from . import demo

    argv = ["-o", str(args.output)] if args.output else []
    if args.spp is not None:
        argv += ["--spp", str(args.spp)]
    if args.model:
        argv += ["--model", args.model]
    for item in args.limit or []:
        argv += ["--limit", item]
    return demo.run(demo.build_parser(parser_class=_Parser).parse_args(argv))


def _width(text: str) -> int:
    v = int(text)
    if v < 8:
        raise argparse.ArgumentTypeError(f"expected a width of at least 8 pixels, got {text!r}")
    return v


def cmd_compare(args) -> int:
    """Render SCENE(s) with every normal-mapping method; write DIR/report.html."""
    import dataclasses

    limits = parse_limits(args.limit)
    check_seed(args.seed)
    for flag, value in (("--spp", args.spp), ("--ref-spp", args.ref_spp)):
        if value is not None:
            check_spp(value, flag)
    if args.width is not None:
        check_int32(args.width, "--width")
    out = Path(args.output)
    if out.exists() and not out.is_dir():
        raise CLIError(f"-o {args.output} is a file; compare writes a folder (report.html and the renders)")
    check_output(out / "report")
    params = parse_defines(args.define)
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
        if unknown or not keys:
            raise CLIError(f"unknown method(s) {', '.join(unknown) or repr(args.methods)}; choose from "
                           f"{', '.join(compare.METHOD_BY_KEY)}")
        methods = tuple(compare.METHOD_BY_KEY[k] for k in keys)
    if args.validation is None and not args.quick and VALIDATION_RESULTS.is_dir():
        args.validation = str(VALIDATION_RESULTS)   # figures of validation/run.py in a checkout
    if args.validation and not Path(args.validation).is_dir():
        raise CLIError(f"validation directory not found: {args.validation}")
    for scene in args.scenes:
        if scene not in compare.BUNDLED and not Path(scene).is_file():
            raise CLIError(f"scene file not found: {scene} (bundled scenes: {', '.join(compare.BUNDLED)})")
        if scene not in compare.BUNDLED:
            check_xml_integers(scene, params)
    command = "mfnormal " + " ".join(shlex.quote(a) for a in getattr(args, "argv", []))
    try:
        report = compare.compare(args.scenes, out, settings, methods, validation=args.validation,
                                 params=params, command=command, limits=limits)
    except CLIError:
        raise
    except compare.SceneError as exc:
        raise CLIError(str(exc)) from None
    except Exception as exc:  # e.g. a render that fails deep inside Dr.Jit
        raise CLIError(f"compare failed: {one_line(exc)}") from None
    print(f"wrote {report}")
    return 0


class _Parser(argparse.ArgumentParser):
    """argparse, with its errors as one line (:class:`CLIError`) instead of usage + exit."""

    def error(self, message):
        raise CLIError(f"{message} (see {self.prog} --help)")


def _add_limit(p):
    p.add_argument("--limit", action="append", metavar="NAME=N", help=LIMIT_HELP)


def build_parser() -> argparse.ArgumentParser:
    parser = _Parser(prog="mfnormal", description=__doc__.split("\n\n")[0])
    sub = parser.add_subparsers(dest="command", required=True)

    r = sub.add_parser("render", help="render a Mitsuba 3 scene (XML) that may use normalmap_microfacet, "
                                      "or a glTF 2.0 model (.gltf, .glb)")
    r.add_argument("scene", help="scene file (.xml), or a glTF 2.0 file (.gltf, .glb: -D sets width, "
                                 "height, spp, max_depth, model, tangents, normal_maps, lights, macro_normal)")
    r.add_argument("-o", "--output", help="output path without extension (writes .exr and .png)")
    r.add_argument("--spp", type=int, help="samples per pixel (default: the scene's)")
    r.add_argument("--variant", default=DEFAULT_VARIANT, help=f"Mitsuba variant (default {DEFAULT_VARIANT})")
    r.add_argument("--seed", type=int, default=0, help="sampler seed, 0 to 4294967295 (default 0)")
    r.add_argument("-D", "--define", action="append", metavar="KEY=VALUE", help="scene parameter ($KEY)")
    _add_limit(r)
    r.set_defaults(func=cmd_render)

    d = sub.add_parser("demo", help="render the bundled demo scene")
    d.add_argument("-o", "--output", help="output path (default out/demo.png)")
    d.add_argument("--spp", type=int)
    d.add_argument("--model")
    _add_limit(d)
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
    c.add_argument("--seed", type=int, default=0, help="sampler seed, 0 to 4294967295 (default 0)")
    c.add_argument("-D", "--define", action="append", metavar="KEY=VALUE", help="scene parameter ($KEY)")
    _add_limit(c)
    c.set_defaults(func=cmd_compare)
    return parser


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    text = " ".join(str(message).split())
    print(f"mfnormal: warning: {text}", file=file or sys.stderr)


def run_command(prog: str, command) -> int:
    """Run ``command()`` with the command line's error path: a :class:`CLIError` (or a
    missing libLLVM, or a path the system refuses) is one line ``PROG: error: ...`` and
    exit 2; Ctrl-C exits 130 and
    SIGTERM 143 (temporary files removed); warnings are one line each; anything else
    is one line and exit 1 (``MFNORMAL_DEBUG=1`` re-raises it with its traceback)."""
    raise_on_sigterm()
    with warnings.catch_warnings():
        warnings.showwarning = _one_line_warning
        try:
            return command()
        except (CLIError, ImportError) as exc:  # ImportError: e.g. no usable libLLVM
            print(f"{prog}: error: {' '.join(str(exc).split())}", file=sys.stderr)
            return 2
        except KeyboardInterrupt:
            print(f"{prog}: interrupted", file=sys.stderr)
            return 130
        except Terminated:
            print(f"{prog}: terminated", file=sys.stderr)
            return 143
        except OSError as exc:    # a path the system refuses (too long, a loop of links, ...)
            name = f"{exc.filename}: " if exc.filename else ""
            print(f"{prog}: error: {name}{exc.strerror or one_line(exc)}", file=sys.stderr)
            return 2
        except Exception as exc:  # noqa: BLE001  (a bug: still one line, unless debugging)
            if os.environ.get("MFNORMAL_DEBUG"):
                raise
            print(f"{prog}: error: unexpected {type(exc).__name__}: {one_line(exc)} "
                  "(MFNORMAL_DEBUG=1 shows the traceback)", file=sys.stderr)
            return 1


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)

    def command():
        args = build_parser().parse_args(argv)
        args.argv = argv
        return args.func(args)

    return run_command("mfnormal", command)


if __name__ == "__main__":
    sys.exit(main())
