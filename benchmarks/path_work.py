#!/usr/bin/env python
r"""Issue 18 diagnosis: how much work the path tracer does per sample, per method.

    python benchmarks/path_work.py [--scenes demo model] [--nested native] [--size 192x144]
        [--methods builtin faithful separable_same] [--spp 16] [--kernels] [--out F.json]

Renders run.py's scenes with every shape's BSDF, and the nested BSDF inside each, wrapped in a
counter (``bench_total``: forwards every call, adds the call's active lanes to one total), and
prints per camera sample: the path vertices where the path tracer samples a BSDF (the shape's
``sample`` calls = path length in BSDF bounces), the calls to the top-level BSDF (``eval_pdf``,
``sample``, ...), and the calls that reach the nested BSDF. The counter makes every call an
indirect Python call, so the counted renders are not timed. ``--kernels``: also a warm render of
the uncounted scene with Dr.Jit's kernel history on: per kernel its size, operation count and
execution time (ms).
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import probes  # noqa: E402  (benchmarks/probes.py)
import run as R  # noqa: E402  (benchmarks/run.py)

OPS = probes.OPS


def counted(scene, nested, method, W, H, spp, assets):
    return probes.count_calls(R.scene_dict(scene, assets, method, nested, W, H, spp), spp, W * H * spp)


def kernels(scene, nested, method, W, H, spp, assets):
    mi, dr = R.mi, R.dr
    sc = R.load_scene(scene, assets, method, nested, W, H, spp)
    R.timed_render(sc, spp, 0)
    dr.kernel_history_clear() if hasattr(dr, "kernel_history_clear") else dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    t, _ = R.timed_render(sc, spp, 1)
    hist = dr.kernel_history()
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    out = []
    for k in hist:
        if k.get("type") != dr.KernelType.JIT:
            continue
        out.append({"size": k.get("size"), "ops": k.get("operation_count"),
                    "ms": k.get("execution_time"), "cache_hit": k.get("cache_hit")})
    return {"render_s": t, "kernels": out}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["demo", "model"])
    ap.add_argument("--nested", nargs="+", default=[R.NATIVE])
    ap.add_argument("--size", default="192x144")
    ap.add_argument("--methods", nargs="+", default=["builtin", "faithful", "separable_same"])
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--kernels", action="store_true")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    R.import_mitsuba()
    W, H = (int(x) for x in args.size.split("x"))
    rows = []
    with R.temporary_assets(args.scenes, "mfnormal_work_") as assets:
        for s in args.scenes:
            for n in args.nested:
                for m in args.methods:
                    row = {"scene": s, "nested": n, "method": m, "size": args.size,
                           "per_sample": counted(s, n, m, W, H, args.spp, assets)}
                    if args.kernels:
                        row.update(kernels(s, n, m, W, H, args.spp, assets))
                    R.log(f"{s:6s} {n:10s} {m:16s} " + "  ".join(
                        f"{lab}: " + " ".join(f"{op} {v:.3f}" for op, v in c.items() if v)
                        for lab, c in row["per_sample"].items()))
                    if args.kernels:
                        R.log("   kernels (size, ops, ms): " + ", ".join(
                            f"({k['size']}, {k['ops']}, {k['ms']:.1f})" for k in row["kernels"]))
                    rows.append(row)
                    if args.out:
                        args.out.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
