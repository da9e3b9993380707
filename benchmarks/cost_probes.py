#!/usr/bin/env python
r"""Issue 18 diagnosis: what parts of faithful and of the walks cost at production size (probes).

    python benchmarks/cost_probes.py [--scene demo] [--nested native] [--size 640x360] [--reps 3]
        [--probes NAME ...] [--vertices 192x144]

Each probe changes the model (wrong images: timing only) and is timed against Mitsuba's
``normalmap`` in interleaved warm pairs, like run.py's metric 1 (medians of the per-pair ratios):

- ``faithful``: as it is; ``faithful/no_sample_reeval``: its ``sample`` returns the nested
  sample's weight instead of re-evaluating the model (eval_pdf) at the sampled direction;
  ``faithful/no_fill``: the diffuse fill's ρ (two nested evals per texel) a constant;
  ``faithful/pdf_only_reeval``: ``sample`` re-evaluates only the pdf; ``faithful/no_lambda``: Λ = 0
  (no masking: its gated terms are then skipped too); ``faithful/const_blocked``: B a constant;
  ``faithful/floor``: classic normal mapping's work (one nested sample or eval_pdf on the facet)
  with the sample folded above the macro plane as the model folds its bounces: the model's path
  lengths at about the built-in's BSDF cost;
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
    import drjit as dr
    from mfnormal.models import faithful, walk
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

    def pdf_reeval(self, sp, tx, sample1, sample2, active):
        # the re-evaluation's pdf only (its values not computed): what a sampler whose weight
        # needs no eval at the sampled direction would cost
        dw = self._draw(sp, tx, sample1, sample2, active)
        _, pdf = self.eval_pdf(sp, tx, dw.bs.wo, dw.active, want_value=False, gated=self._gates(sp, tx))
        dw.bs.pdf = dr.select(dw.delta, dw.bs.pdf, pdf)
        return faithful._finish(dw.bs, dw.w, dw.active)

    def no_lambda(w, sigma1, sigma2):
        return 0.0 * w.z

    def const_blocked(self, cos_p, phi, g):
        return 0.3 * g

    def floor_sample(self, sp, tx, sample1, sample2, active):
        # classic normal mapping's work (one nested sample on the facet), folded above the
        # macro plane as the model's bounce folds it: the model's path lengths, not its values
        bs, w = sp.sample(sp.frame_p, tx.wi, sample1, sample2, active & (tx.wi.z > 0))
        bs.wo = mi.Vector3f(bs.wo.x, bs.wo.y, dr.abs(bs.wo.z))
        return faithful._finish(bs, w, active & (tx.wi.z > 0))

    def floor_eval_pdf(self, sp, tx, wo, active, want_value=True, want_pdf=True, gated=None):
        ok = active & (tx.wi.z > 0) & (wo.z > 0)
        return faithful._nested(sp, mi.BSDFContext(faithful.RADIANCE), sp.frame_p, tx.wi, wo, ok,
                                want_value, want_pdf)

    @contextlib.contextmanager
    def floor():
        with attr(faithful.Model, "sample", floor_sample), attr(faithful.Model, "eval_pdf", floor_eval_pdf):
            yield

    none = contextlib.nullcontext
    return {
        "faithful": ("faithful", none, none),
        "faithful/no_sample_reeval": ("faithful", none, lambda: attr(faithful.Model, "sample", no_reeval)),
        "faithful/no_fill": ("faithful", none, lambda: attr(faithful.Model, "_fill_rho", const_fill)),
        "faithful/pdf_only_reeval": ("faithful", none, lambda: attr(faithful.Model, "sample", pdf_reeval)),
        "faithful/no_lambda": ("faithful", none, lambda: attr(faithful, "smith_lambda", no_lambda)),
        "faithful/floor": ("faithful", none, floor),
        "faithful/const_blocked": ("faithful", none, lambda: attr(faithful.Model, "blocked", const_blocked)),
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
    ap.add_argument("--vertices", metavar="WxH",
                    help="also count, at this size, the path vertices per camera sample (probes.py's "
                         "counters: BSDF samples on every shape), the built-in's and each probe's")
    args = ap.parse_args(argv)
    R.import_mitsuba()
    if args.vertices:
        import probes        # benchmarks/probes.py (registered by import_mitsuba)
        VW, VH = (int(x) for x in args.vertices.split("x"))

        def vertices(method):
            d = R.scene_dict(args.scene, assets, method, args.nested, VW, VH, args.spp)
            return probes.path_vertices(probes.count_calls(d, args.spp, VW * VH * args.spp))
    W, H = (int(x) for x in args.size.split("x"))
    with R.temporary_assets([args.scene], "mfnormal_probes_") as assets:
        base = R.load_scene(args.scene, assets, "builtin", args.nested, W, H, args.spp)
        R.timed_render(base, args.spp, 0)
        v_base = vertices("builtin") if args.vertices else None
        for name, (method, at_load, at_render) in patches().items():
            if args.probes and name not in args.probes:
                continue
            with at_load():
                scene = R.load_scene(args.scene, assets, method, args.nested, W, H, args.spp)
            with at_render():
                R.timed_render(scene, args.spp, 0)
                R.timed_render(base, args.spp, 0)     # (the first built-in render after a load is slow)
                tb, tm, ratios = R.interleaved_pairs(base, scene, args.spp, args.reps)
                v = vertices(method) if args.vertices else None
            extra = "" if v is None else (f"  vertices/sample {v:.4f} vs {v_base:.4f} ({v / v_base:.3f}x; "
                                          f"time per vertex {R.median(ratios) * v_base / v:.3f}x)")
            R.log(f"{args.scene} {args.nested} {W}x{H} {name:30s} ratio {R.median(ratios):.3f} "
                  f"{[round(x, 3) for x in ratios]}  ({R.median(tm):.3f} s vs {R.median(tb):.3f} s){extra}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
