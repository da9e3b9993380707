"""Inverse rendering against the true geometry, per optimisation seed.

    nice .venv/bin/python -m validation.inverse_seeds builtin:0 faithful:0 builtin:1000 ... [--out FILE.json]

Each argument METHOD:SEED is one run of ``validation/inverse_rendering.py``'s true-geometry case
(res 32², 8 spp, 3 suns, Adam lr 0.02, 80 iterations; the targets are rendered once, with their
own fixed seed) with ``Setup.seed`` = SEED: the seeds of the optimisation's renders. Prints and
writes per run the texel-centre error (final and minimum), the surface error
(inverse.surface_error), the loss (first, final and largest) and the recovered map. The
run-to-run spread of an optimisation is what a difference between methods has to exceed.
``--detached-slopes``: the default model's map-wide slopes σ without their derivative
(``Setup.slope_derivatives``), the diagnostic of validation/results/inverse_rendering.md.
``--iterations N --lr-final R``: N iterations with the rate falling geometrically from 0.02 to R
(``Setup.lr_final``), the annealed runs of that file's section 4 (N = 400, 800, 1600; R = 0.001).
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import mfnormal  # noqa: E402,F401  (before mitsuba: selects a working libLLVM)
import mitsuba as mi  # noqa: E402


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("runs", nargs="+", help="METHOD:SEED")
    p.add_argument("--iterations", type=int, default=80)
    p.add_argument("--out", type=Path, default=None)
    p.add_argument("--detached-slopes", action="store_true",
                   help="drop the derivative of the default model's map-wide slopes (Setup.slope_derivatives)")
    p.add_argument("--lr-final", type=float, default=None,
                   help="the rate falls geometrically from 0.02 to this over the iterations (Setup.lr_final)")
    args = p.parse_args(argv)

    mi.set_variant("llvm_ad_rgb")
    mfnormal.register()
    from validation import inverse as I

    targets = I.true_geometry_targets(I.Setup(res=32, spp=8, lr=0.02))
    rows = []
    for run in args.runs:
        method, seed = run.split(":")
        setup = I.Setup(res=32, spp=8, lr=0.02, seed=int(seed), slope_derivatives=not args.detached_slopes,
                        lr_final=args.lr_final)
        r = I.optimise(setup, method, targets, iterations=args.iterations, log=print)
        row = dict(method=method, seed=int(seed), slope_derivatives=setup.slope_derivatives, lr_final=setup.lr_final,
                   iterations=args.iterations, centre_final=r.error[-1], centre_min=min(r.error),
                   surface=I.surface_error(setup, r.texels), loss_start=r.loss[0], loss_final=r.loss[-1],
                   loss_max=max(r.loss), seconds=r.seconds, loss=r.loss, error=r.error, texels=r.texels.tolist())
        print(f"RESULT {method} seed {seed}: centre {row['centre_final']:.3f}° (min {row['centre_min']:.3f}°) "
              f"surface {row['surface']:.4f}° loss {row['loss_start']:.4g} → {row['loss_final']:.4g} "
              f"(max {row['loss_max']:.4g}) {r.seconds:.0f} s", flush=True)
        rows.append(row)
        if args.out is not None:
            args.out.write_text(json.dumps(rows))


if __name__ == "__main__":
    main()
