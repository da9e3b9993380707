#!/usr/bin/env python
r"""Issue 18 diagnosis: what parts of faithful and of the walks cost at production size (probes).

    python benchmarks/cost_probes.py [--scene demo] [--nested native] [--size 640x360] [--reps 3]

Each probe changes the model (wrong images: timing only) and is timed against Mitsuba's
``normalmap`` in interleaved warm pairs, like run.py's metric 1 (medians of the per-pair ratios):

- ``faithful``: as it is; ``faithful/no_sample_reeval``: its ``sample`` returns the nested
  sample's weight instead of re-evaluating the model (eval_pdf) at the sampled direction;
  ``faithful/no_fill``: the diffuse fill's ρ (two nested evals per texel) a constant;
- ``separable_same`` as it is; with ``max_bounces`` 1 (one nested sample per walk) and 2;
  with ``rr_depth`` 1 (roulette from the first bounce) and 2.
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import run as R  # noqa: E402  (benchmarks/run.py)


def patches():
    """{probe name: (method, context manager factory)}"""
    import contextlib
    from mfnormal import faithful, walk
    mi = R.mi

    @contextlib.contextmanager
    def attr(obj, name, value):
        old = getattr(obj, name)
        setattr(obj, name, value)
        try:
            yield
        finally:
            setattr(obj, name, old)

    def no_reeval(self, sp, tx, sample1, sample2, active):
        dw = self._draw(sp, tx, sample1, sample2, active)
        return faithful._finish(dw.bs, dw.w, dw.active)

    def const_fill(self, sp, tx):
        if tx.fill_rho is None:
            tx.fill_rho = mi.Spectrum(0.3)
        return tx.fill_rho

    none = contextlib.nullcontext
    return {
        "faithful": ("faithful", none, none),
        "faithful/no_sample_reeval": ("faithful", none, lambda: attr(faithful.Model, "sample", no_reeval)),
        "faithful/no_fill": ("faithful", none, lambda: attr(faithful.Model, "_fill_rho", const_fill)),
        "separable_same": ("separable_same", none, none),
        "separable_same/max_bounces=1": ("separable_same", lambda: attr(walk, "MAX_BOUNCES", 1), none),
        "separable_same/max_bounces=2": ("separable_same", lambda: attr(walk, "MAX_BOUNCES", 2), none),
        "separable_same/rr_depth=1": ("separable_same", lambda: attr(walk, "RR_DEPTH", 1), none),
        "separable_same/rr_depth=2": ("separable_same", lambda: attr(walk, "RR_DEPTH", 2), none),
    }


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="demo")
    ap.add_argument("--nested", default=R.NATIVE)
    ap.add_argument("--size", default="640x360")
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--probes", nargs="+")
    args = ap.parse_args(argv)
    R.import_mitsuba()
    W, H = (int(x) for x in args.size.split("x"))
    with R.temporary_assets([args.scene], "mfnormal_probes_") as assets:
        base = R.load_scene(args.scene, assets, "builtin", args.nested, W, H, args.spp)
        R.timed_render(base, args.spp, 0)
        for name, (method, at_load, at_render) in patches().items():
            if args.probes and name not in args.probes:
                continue
            with at_load():
                scene = R.load_scene(args.scene, assets, method, args.nested, W, H, args.spp)
            with at_render():
                R.timed_render(scene, args.spp, 0)
                R.timed_render(base, args.spp, 0)     # (the first built-in render after a load is slow)
                tb, tm, ratios = R.interleaved_pairs(base, scene, args.spp, args.reps)
            R.log(f"{args.scene} {args.nested} {W}x{H} {name:30s} ratio {R.median(ratios):.3f} "
                  f"{[round(x, 3) for x in ratios]}  ({R.median(tm):.3f} s vs {R.median(tb):.3f} s)")
    return 0


if __name__ == "__main__":
    sys.exit(main())
