"""Inverse rendering of a normal map from a flat start, every method, both targets.

    nice .venv/bin/python -m validation.inverse_rendering [--methods builtin,faithful,...]
        [--targets same,true] [--iterations 80] [--walk-iterations 40] [--res 32] [--spp 8]
        [--out validation/results]

A plane under a 16² map (roughplastic, GGX α 0.2) is optimised with Adam from a flat map
against 3 renders, each lit by one directional sun (validation.inverse). Targets: ``same``,
the plane rendered by the same method with the true map; ``true``, the true geometry (the
heightfield as a dense displaced mesh of the bare material, path traced). Reports per
method and target: the first step (max |Δ texel|), the mean texel angle to the true
normals at the start and the end (and its minimum over the run), the surface error of the
final map (inverse.surface_error: over the whole surface, the map bilinearly interpolated as
rendered), the loss, the time; the JSON also holds each recovered map.
The random walks are run for fewer iterations (``--walk-iterations``; ~10× the cost per
iteration); their row says how many. Writes ``inverse_rendering.md`` and ``.json``.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

import mfnormal  # noqa: E402,F401  (before mitsuba: selects a working libLLVM)
import mitsuba as mi  # noqa: E402

WALKS = ("separable_specular", "separable_same", "nonseparable_specular", "nonseparable_same")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--methods", type=lambda s: s.split(","), default=None)
    p.add_argument("--targets", type=lambda s: s.split(","), default=["same", "true"])
    p.add_argument("--iterations", type=int, default=80)
    p.add_argument("--walk-iterations", type=int, default=40)
    p.add_argument("--res", type=int, default=32)
    p.add_argument("--spp", type=int, default=8)
    p.add_argument("--lr", type=float, default=0.02)
    p.add_argument("--out", type=Path, default=ROOT / "out" / "validation")
    args = p.parse_args(argv)

    mi.set_variant("llvm_ad_rgb")
    mfnormal.register()
    from validation import inverse as I

    methods = args.methods or list(I.METHODS)
    setup = I.Setup(res=args.res, spp=args.spp, lr=args.lr)
    rows = []
    for target in args.targets:
        true_targets = I.true_geometry_targets(setup) if target == "true" else None
        for m in methods:
            targets = true_targets if target == "true" else I.same_method_targets(setup, m)
            iters = args.walk_iterations if m in WALKS else args.iterations
            r = I.optimise(setup, m, targets, iterations=iters, log=print)
            row = {"target": target, "method": m, "iterations": iters, "first_step": r.first_step,
                   "error_start": r.error[0], "error_final": r.error[-1], "error_min": min(r.error),
                   "loss_start": r.loss[0], "loss_final": r.loss[-1], "seconds": r.seconds,
                   "error_curve": r.error, "surface_start": I.surface_error(setup, I.flat_map(setup)),
                   "surface_final": I.surface_error(setup, r.texels), "texels": r.texels.tolist()}
            print(f"RESULT {target} {m}: {iters} it, first step {r.first_step:.3g}, error "
                  f"{r.error[0]:.2f}° → {r.error[-1]:.2f}° (min {min(r.error):.2f}°), surface error "
                  f"{row['surface_final']:.2f}°, {r.seconds:.0f} s", flush=True)
            rows.append(row)
            write(args.out, rows, args)


def write(out, rows, args):
    out.mkdir(parents=True, exist_ok=True)
    (out / "inverse_rendering.json").write_text(json.dumps(rows, indent=1))
    lines = ["# Inverse rendering of a 16² normal map from a flat start", "",
             f"`validation/inverse_rendering.py`: res {args.res}², {args.spp} spp per render, 3 suns, Adam "
             f"lr {args.lr}, roughplastic α 0.2. Error: mean angle between the recovered texels and the true "
             "surface normals at the texel centres; surface error: mean angle between the map as the plane "
             "shades with it (bilinear) and the true normal, over 16² points per texel (inverse.surface_error). "
             "`same`: target rendered by the method itself with the "
             "true map; `true`: target rendered from the true geometry (displaced mesh).", "",
             "| target | method | iterations | first step | error start | error final | error min "
             "| surface error start | surface error final | seconds |",
             "|---|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        lines.append(f"| {r['target']} | {r['method']} | {r['iterations']} | {r['first_step']:.3g} | "
                     f"{r['error_start']:.2f}° | {r['error_final']:.2f}° | {r['error_min']:.2f}° | "
                     f"{r['surface_start']:.2f}° | {r['surface_final']:.2f}° | {r['seconds']:.0f} |")
    (out / "inverse_rendering.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
