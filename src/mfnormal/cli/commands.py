"""The ``mfnormal`` command line: render scenes that use the plugin, and the bundled demo.

    mfnormal render SCENE.xml|MODEL.gltf|MODEL.glb [-o OUT] [--spp N] [--variant V] [-D key=value ...]
                    [--chunks N] [--cluster local:N|ADDRESS [--shared-files] [--cluster-timeout S]
                     [--cluster-tls-ca FILE --cluster-tls-cert FILE --cluster-tls-key FILE]]
    mfnormal demo [-o OUT] [--spp N] [--resolution WxH] [--model M] [--seed N] ...
                                           (also mfnormal-demo)
    mfnormal compare SCENE [SCENE ...] [-o DIR] [--spp N] [--ref-spp N] [--quick] [--cluster ...]
    (each also takes --limit NAME=N: the caps of mfnormal.io.inputs.Limits)
    mfnormal bake HIGH.ply|obj LOW.ply|obj -o MAP.png [--size N] [--cage D] [--tangents F] ...
                                           (mfnormal.cli.bake)

Every error is one line on stderr and exit code 2, reported before the render
starts wherever it can be known then (:mod:`mfnormal.io.inputs`); outputs are
written as a pair (a linear EXR and a tonemapped PNG), atomically. The scene a command names is
loaded by :mod:`mfnormal.cli.loading`; it renders through :mod:`mfnormal.render`, here or on a cluster.
"""

from __future__ import annotations

import argparse
import math
import os
import shlex
import sys
import time
import warnings
from pathlib import Path
from types import ModuleType
from typing import Callable, Sequence

import numpy as np

from mfnormal.cli.loading import gltf_options, load_scene, parse_defines
from mfnormal.io.messages import one_line
from mfnormal.methods import METHOD_BY_KEY, METHODS
from mfnormal.render.passes import render_scene, use_variant
from mfnormal.io.inputs import (CLIError, LIMIT_HELP, Limits, Terminated, check_int32, check_output,
                                check_regular_file, check_render_size, check_scene_before_render, check_seed,
                                check_spp, check_xml_scene, parse_limits, raise_on_sigterm)

__all__ = ["CLIError", "main", "demo_main", "build_parser", "setup_variant", "run_command"]

DEFAULT_VARIANT = "llvm_ad_rgb"
DEMO_OUTPUT = os.path.join("out", "demo.png")


def setup_variant(variant: str) -> ModuleType:
    """Import Mitsuba in ``variant`` with the plugin registered, or raise CLIError."""
    import mitsuba as mi

    return use_variant(variant, CLIError,
                       f"variant '{variant}' is not available in this Mitsuba build; "
                       f"choose one of: {', '.join(v for v in mi.variants() if 'rgb' in v)}",
                       f"cannot use variant '{variant}'")


class Progress:
    """A one-line progress bar with ETA on a terminal; silent when piped.
    ``update(done, total)`` after each of ``total`` passes (or other ``unit``)."""

    def __init__(self, stream=sys.stderr, unit: str = "passes"):
        self.stream = stream
        self.unit = unit
        self.enabled = stream.isatty()
        self.start = time.time()

    def update(self, done: int, total: int):
        if not self.enabled:
            return
        elapsed = time.time() - self.start
        eta = elapsed / done * (total - done) if done else 0.0
        bar = "#" * int(30 * done / total)
        self.stream.write(f"\r[{bar:<30}] {done}/{total} {self.unit}, {elapsed:5.1f}s, ETA {eta:5.1f}s")
        if done == total:
            self.stream.write("\n")
        self.stream.flush()


def write_render(mi, scene, img, output, exposure: float = 0.0):
    """Sanitise (NaN/Inf and negative colour → 0, warned about) and write the EXR/PNG pair."""
    from mfnormal.io.images import film_channel_names, sanitize_counts, save_render

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


def _check_cluster_args(args):
    """The ``--cluster`` target (None without it), its options checked; :class:`CLIError`."""
    if getattr(args, "chunks", None) is not None:
        check_int32(args.chunks, "--chunks", lo=1)
    timeout = getattr(args, "cluster_timeout", 60.0)
    if not (0 < timeout < float("inf")):
        raise CLIError(f"--cluster-timeout {timeout}: expected a number of seconds above 0")
    tls = tuple(getattr(args, f"cluster_tls_{n}", None) for n in ("ca", "cert", "key"))
    if args.cluster is None:
        if getattr(args, "shared_files", False):
            raise CLIError("--shared-files goes with --cluster")
        if any(tls):
            raise CLIError("--cluster-tls-ca, --cluster-tls-cert and --cluster-tls-key go with --cluster")
        return None
    from mfnormal.render.cluster import parse_cluster
    return parse_cluster(args.cluster, tls)


def _render_on_cluster(args, target, scene, spp: int, params: dict, limits: Limits):
    """``mfnormal render --cluster``: the chunks of :func:`mfnormal.render.passes.schedule`
    rendered on the workers, merged in order; returns (image, what it ran on)."""
    from mfnormal.render.bundle import scene_spec
    from mfnormal.render.cluster import Cluster
    from mfnormal.io.gltf import GLTF_SUFFIXES
    from mfnormal.render.passes import film_image, schedule

    gltf = Path(args.scene).suffix.lower() in GLTF_SUFFIXES
    spec, files = scene_spec(args.scene, params, gltf_options(params) if gltf else None,
                             args.shared_files, limits)
    pixels = int(np.prod([int(v) for v in scene.sensors()[0].film().crop_size()]))
    with Cluster(target, args.variant, args.cluster_timeout) as cluster:
        workers = cluster.workers()
        passes = schedule(spp, pixels, args.chunks or max(8, 4 * workers), args.seed)
        where = (f"{len(passes)} chunks on {workers} worker(s) of {target.text}, "
                 f"{cluster.variants(cluster.info)}")
        img = cluster.render(spec, files, passes, Progress(unit="chunks").update)
    return film_image(img), where


def cmd_render(args) -> int:
    import mfnormal

    limits = parse_limits(args.limit)
    check_seed(args.seed)
    if args.spp is not None:
        check_spp(args.spp, "--spp")
    target = _check_cluster_args(args)
    output = args.output or str(Path("out") / Path(args.scene).stem)
    check_output(output)
    params = parse_defines(args.define)
    mi = setup_variant(args.variant)
    started = time.time()
    scene = load_scene(mi, args.scene, params, limits)
    spp = check_scene_before_render(mi, scene, args.spp, limits, Path(args.scene).name)
    where = "on this machine"
    try:
        if target is None:
            img = render_scene(scene, spp, passes=args.chunks, seed=args.seed, progress=Progress().update,
                               killable=True)
        else:
            img, where = _render_on_cluster(args, target, scene, spp, params, limits)
    except CLIError:
        raise
    except Exception as exc:
        raise CLIError(f"render failed: {one_line(exc)}") from None
    img, exr, png = write_render(mi, scene, img, output)
    print(f"variant {args.variant}, libLLVM {mfnormal.LLVM_PATH}")
    print(f"rendered {img.shape[1]}x{img.shape[0]} at {spp} spp ({where}) in {time.time() - started:.1f}s")
    print(f"wrote {exr}\nwrote {png}")
    return 0


def _check_demo(args, limits: Limits) -> None:
    """Every argument of ``mfnormal demo``, before anything is written."""
    from mfnormal.scenes.assets import TILES_NAME
    from mfnormal.cli.demo import CLASSIC
    from mfnormal.plugins.normalmap_microfacet import MODELS

    if args.model not in MODELS + (CLASSIC,):
        raise CLIError(f"--model {args.model}: unknown model; choose one of {', '.join(MODELS + (CLASSIC,))}")
    check_spp(args.spp, "--spp")
    check_seed(args.seed)
    check_int32(args.max_depth, "--max-depth", lo=-1)
    if not (0.0 <= args.strength < float("inf")):
        raise CLIError(f"--strength {args.strength}: the strength must be a finite number >= 0")
    if not math.isfinite(args.exposure) or abs(args.exposure) > 100:
        raise CLIError(f"--exposure {args.exposure}: expected a number of stops from -100 to 100")
    w, h = args.resolution
    check_render_size(w, h, limits, "the demo image")
    check_output(args.output)
    if args.assets_dir is not None:
        check_output(Path(args.assets_dir) / TILES_NAME, "--assets-dir")


def cmd_demo(args) -> int:
    """Render the bundled demo scene (:mod:`mfnormal.cli.demo`); write the EXR/PNG pair."""
    import mfnormal
    from mfnormal.cli import demo
    from mfnormal.scenes.assets import DEMO_XML
    from mfnormal.io.images import output_paths
    from mfnormal.render.passes import MAX_PASS_LANES, average_passes

    _check_demo(args, parse_limits(args.limit))
    exr_path, _ = output_paths(args.output)
    assets_dir = Path(args.assets_dir) if args.assets_dir else exr_path.parent / "demo_assets"
    mi = setup_variant(DEFAULT_VARIANT)
    (w, h), spp = args.resolution, args.spp
    print(f"variant : {mi.variant()}")
    print(f"LLVM    : {mfnormal.LLVM_PATH}")
    print(f"scene   : {DEMO_XML}  (model={args.model}, {w}x{h}, {spp} spp, "
          f"max_depth={args.max_depth})")
    sys.stdout.flush()

    t0 = time.perf_counter()
    try:
        scene = demo.load_scene(model=args.model, spp=spp, resolution=args.resolution,
                                assets_dir=assets_dir, strength=args.strength, max_depth=args.max_depth)
    except Exception as exc:
        raise CLIError(f"cannot load the demo scene: {one_line(exc)}") from None
    t1 = time.perf_counter()
    try:
        if spp * w * h <= MAX_PASS_LANES:   # one pass with the demo's own seed
            rgb = average_passes(scene, [(spp, args.seed)], killable=True).astype(np.float32)[..., :3]
        else:
            rgb = render_scene(scene, spp, seed=args.seed, progress=Progress().update, killable=True)
    except Exception as exc:
        raise CLIError(f"render failed: {one_line(exc)}") from None
    t2 = time.perf_counter()
    _, exr_path, png_path = write_render(mi, scene, rgb, args.output, exposure=args.exposure)
    print(f"load    : {t1 - t0:.1f} s (texture generation and scene loading)")
    print(f"render  : {t2 - t1:.1f} s (JIT compilation and rendering)")
    print(f"wrote   : {exr_path}")
    print(f"wrote   : {png_path}")
    return 0


def _width(text: str) -> int:
    v = int(text)
    if v < 8:
        raise argparse.ArgumentTypeError(f"expected a width of at least 8 pixels, got {text!r}")
    return v


def _compare_settings(args, compare):
    """The comparison's settings: --quick's or the defaults, with --seed, --spp, --ref-spp, --width."""
    import dataclasses

    settings = compare.QUICK if args.quick else compare.Settings()
    changes = {"seed": args.seed}
    if args.spp:
        changes["spp"] = args.spp
    if args.ref_spp or args.spp:
        changes["ref_spp"] = args.ref_spp or 4 * changes.get("spp", settings.spp)
    if args.width:
        changes["width"] = args.width
    return dataclasses.replace(settings, **changes)


def _compare_methods(names):
    """The methods --methods names (comma-separated keys of the catalogue), or all of them."""
    if not names:
        return METHODS
    keys = [k.strip() for k in names.split(",") if k.strip()]
    unknown = [k for k in keys if k not in METHOD_BY_KEY]
    if unknown or not keys:
        raise CLIError(f"unknown method(s) {', '.join(unknown) or repr(names)}; choose from "
                       f"{', '.join(METHOD_BY_KEY)}")
    return tuple(METHOD_BY_KEY[k] for k in keys)


def cmd_compare(args) -> int:
    """Render SCENE(s) with every normal-mapping method; write DIR/report.html."""
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
    target = _check_cluster_args(args)
    params = parse_defines(args.define)
    setup_variant(args.variant)
    from mfnormal.report import compare
    from mfnormal.scenes.assets import BUNDLED
    from mfnormal.io.scene_xml import SceneError

    settings, methods = _compare_settings(args, compare), _compare_methods(args.methods)
    if args.validation and not Path(args.validation).is_dir():
        raise CLIError(f"validation directory not found: {args.validation}")
    for scene in args.scenes:
        if scene not in BUNDLED:
            check_regular_file(scene, f"the scene {scene}",
                               f"scene file not found: {scene} (bundled scenes: {', '.join(BUNDLED)})")
            check_xml_scene(scene, params, limits)
    command = "mfnormal " + " ".join(shlex.quote(a) for a in getattr(args, "argv", []))
    try:
        if target is None:
            report = compare.compare(args.scenes, out, settings, methods, validation=args.validation,
                                     params=params, command=command, limits=limits)
        else:
            from mfnormal.render.cluster import Cluster
            with Cluster(target, args.variant, args.cluster_timeout) as cluster:
                report = compare.compare(args.scenes, out, settings, methods, validation=args.validation,
                                         params=params, command=command, limits=limits,
                                         cluster=cluster)
    except CLIError:
        raise
    except SceneError as exc:
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


def _add_seed(p):
    p.add_argument("--seed", type=int, default=0, help="sampler seed, 0 to 4294967295 (default 0)")


def _add_scene_options(p):
    """--variant, --seed, -D and --limit (render and compare)."""
    p.add_argument("--variant", default=DEFAULT_VARIANT, help=f"Mitsuba variant (default {DEFAULT_VARIANT})")
    _add_seed(p)
    p.add_argument("-D", "--define", action="append", metavar="KEY=VALUE", help="scene parameter ($KEY)")
    _add_limit(p)
    from mfnormal.render.cluster import CLUSTER_HELP
    p.add_argument("--cluster", metavar="local:N|ADDRESS", help=CLUSTER_HELP)
    p.add_argument("--cluster-timeout", type=float, default=60.0, metavar="S",
                   help="seconds to wait for the scheduler, for a first worker, and with no "
                        "worker left (default 60)")
    for name, what in (("ca", "the certificate authority (PEM) that signed the scheduler's and "
                               "workers' certificates"),
                       ("cert", "this client's certificate (PEM)"),
                       ("key", "this client's private key (PEM), unless the certificate file holds it")):
        p.add_argument(f"--cluster-tls-{name}", metavar="FILE",
                       help=f"with --cluster tls://HOST:PORT (or local:N, then over TLS too): {what}; "
                            "default: Dask's distributed.comm.tls configuration")


def _positive_int(text: str) -> int:
    try:
        v = int(text)
    except ValueError:
        v = 0
    if v <= 0:
        raise argparse.ArgumentTypeError(f"expected a positive integer, got {text!r}")
    return v


def _resolution(text: str) -> tuple:
    try:
        w, h = (int(v) for v in text.lower().split("x"))
        if w <= 0 or h <= 0:
            raise ValueError
    except ValueError:
        raise argparse.ArgumentTypeError(f"expected WIDTHxHEIGHT, e.g. 512x384, got {text!r}")
    return w, h


def _add_render(sub):
    r = sub.add_parser("render", help="render a Mitsuba 3 scene (XML) that may use normalmap_microfacet, "
                                      "or a glTF 2.0 model (.gltf, .glb)",
                       description="Render SCENE, a Mitsuba 3 XML scene whose BSDFs may be "
                                   "normalmap_microfacet (and whose integrators may be mfnormal_path or "
                                   "mfnormal_prb), or a glTF 2.0 model with its normal maps wrapped in "
                                   "normalmap_microfacet. Writes a linear EXR (every channel of the film) "
                                   "and a tonemapped PNG side by side, atomically. The scene is checked "
                                   "before rendering: every error is one line and exit code 2.")
    r.add_argument("scene", help="scene file (.xml), or a glTF 2.0 file (.gltf, .glb: -D sets width, "
                                 "height, spp, max_depth, model, tangents, normal_maps, lights, macro_normal)")
    r.add_argument("-o", "--output", help="output path without extension (writes .exr and .png)")
    r.add_argument("--spp", type=int, help="samples per pixel (default: the scene's)")
    r.add_argument("--chunks", type=int, help="split the samples into N passes with seeds derived "
                                              "from --seed (default 8; with --cluster, 4 per worker, "
                                              "at least 8): the same N gives the same image here "
                                              "and on a cluster")
    r.add_argument("--shared-files", action="store_true",
                   help="with --cluster: the workers read the scene and its files from the same "
                        "path (a shared file system) instead of receiving them")
    _add_scene_options(r)
    r.set_defaults(func=cmd_render)
    return r


def _add_demo(sub):
    from mfnormal.cli import demo

    d = sub.add_parser("demo", help="render the bundled demo scene",
                       description="Render the mfnormal demo scene (scenes/demo.xml): a normal-mapped "
                                   "sphere and ground plane under a procedural sky. Writes a linear EXR "
                                   "and a tonemapped sRGB PNG.")
    d.add_argument("-o", "--output", default=DEMO_OUTPUT,
                   help=f"output image; the .exr and .png are written side by side (default: {DEMO_OUTPUT})")
    d.add_argument("--spp", type=_positive_int, default=demo.DEFAULT_SPP,
                   help=f"samples per pixel (default: {demo.DEFAULT_SPP})")
    d.add_argument("--resolution", type=_resolution, default=demo.DEFAULT_RESOLUTION, metavar="WxH",
                   help="image size (default: %dx%d)" % demo.DEFAULT_RESOLUTION)
    d.add_argument("--model", default="faithful",
                   help="normalmap_microfacet model (default: faithful), or "
                        f"'{demo.CLASSIC}' for Mitsuba's built-in normal mapping")
    d.add_argument("--strength", type=float, default=1.0, help="normal map strength (default: 1.0)")
    d.add_argument("--max-depth", type=int, default=demo.DEFAULT_MAX_DEPTH,
                   help=f"path integrator max_depth (default: {demo.DEFAULT_MAX_DEPTH})")
    d.add_argument("--exposure", type=float, default=0.0, help="exposure of the PNG in stops (default: 0)")
    _add_seed(d)
    d.add_argument("--assets-dir", default=None,
                   help="where to generate the textures (default: <output dir>/demo_assets)")
    _add_limit(d)
    d.set_defaults(func=cmd_demo)
    return d


def _add_compare(sub):
    from mfnormal.scenes.assets import BUNDLED

    names = ", ".join(m.key for m in METHODS)
    c = sub.add_parser("compare", help="render a scene with every normal-mapping method; write an HTML report",
                       description=f"Render SCENE once per normal-mapping method ({names}: the nested BSDF "
                                   "alone, Mitsuba's normalmap without and with its fixes, and "
                                   "normalmap_microfacet's models, the default faithful first) and write a "
                                   "self-contained DIR/report.html. SCENE is an XML file whose normal-mapped "
                                   "materials are normalmap_microfacet BSDFs, or a bundled scene: "
                                   + "; ".join(f"'{b.name}', {b.title}" for b in BUNDLED.values()) + ".")
    c.add_argument("scenes", nargs="+", metavar="SCENE",
                   help="scene file (.xml) or a bundled scene: " + ", ".join(BUNDLED))
    c.add_argument("-o", "--output", default=os.path.join("out", "compare"),
                   help="output directory (default out/compare)")
    c.add_argument("--spp", type=int, help="samples per pixel (default 32; --quick: 2)")
    c.add_argument("--ref-spp", type=int, help="samples per pixel of the references (default 4x spp)")
    c.add_argument("--width", type=_width,
                   help="scale the film down to this width, keeping its aspect (default 320; --quick: 64)")
    c.add_argument("--methods", help="comma-separated subset of the methods (default: all)")
    c.add_argument("--validation", metavar="DIR",
                   help="add the PNG figures in DIR to the report (e.g. validation/results of a "
                        "checkout, written by validation/run.py)")
    c.add_argument("--quick", action="store_true", help="tiny images and sample counts (for tests)")
    _add_scene_options(c)
    c.set_defaults(func=cmd_compare)
    return c


def version_line() -> str:
    """``mfnormal VERSION (Mitsuba X, Dr.Jit Y)``: what ``mfnormal --version`` prints."""
    import drjit as dr
    import mitsuba as mi

    import mfnormal
    return f"mfnormal {mfnormal.__version__} (Mitsuba {mi.__version__}, Dr.Jit {dr.__version__})"


def build_parser() -> argparse.ArgumentParser:
    """The ``mfnormal`` parser; ``parser.commands`` holds each subcommand's own parser."""
    parser = _Parser(prog="mfnormal", description=__doc__.split("\n\n")[0])
    parser.add_argument("--version", action="version", version=version_line())
    sub = parser.add_subparsers(dest="command", required=True)
    from mfnormal.cli.bake import add_bake

    parser.commands = {"render": _add_render(sub), "demo": _add_demo(sub), "compare": _add_compare(sub),
                       "bake": add_bake(sub)}
    return parser


def _one_line_warning(message, category, filename, lineno, file=None, line=None):
    text = " ".join(str(message).split())
    print(f"mfnormal: warning: {text}", file=file or sys.stderr)


def run_command(prog: str, command: Callable[[], int]) -> int:
    """Run ``command()`` with the command line's error path: a :class:`CLIError` (or a
    missing libLLVM, or a path the system refuses) is one line ``PROG: error: ...`` and
    exit 2; Ctrl-C exits 130 and
    SIGTERM 143 (temporary files removed; during a render pass both end the process at once,
    :func:`mfnormal.render.passes.signals_end_the_process`); warnings are one line each; anything else
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


def main(argv: Sequence[str] | None = None, prog: str = "mfnormal", command: str | None = None) -> int:
    """``mfnormal`` with ``argv`` (default: the process's); ``command`` runs one subcommand as
    a program of its own, named ``prog`` (``mfnormal-demo`` is ``mfnormal demo``)."""
    argv = list(sys.argv[1:] if argv is None else argv)

    def run():
        parser = build_parser()
        if command is not None:
            parser = parser.commands[command]
            parser.prog = prog
        args = parser.parse_args(argv)
        args.argv = argv if command is None else [command, *argv]
        return args.func(args)

    return run_command(prog, run)


def demo_main(argv: Sequence[str] | None = None) -> int:
    """``mfnormal-demo``: ``mfnormal demo`` under that name."""
    return main(argv, prog="mfnormal-demo", command="demo")


if __name__ == "__main__":
    sys.exit(main())
