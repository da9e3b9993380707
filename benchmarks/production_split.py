#!/usr/bin/env python
r"""Issue 18 diagnosis: size (fixed costs) or materials behind the production profile's ratios?

    python benchmarks/production_split.py [--scenes demo model] [--nested native ggx_0.05]
        [--sizes 192x144 1280x720] [--methods faithful separable_same] [--reps 3] [--out F.json]

Renders run.py's scenes (its ``load_scene`` / ``timed_render``: the same scene dicts, 16 spp)
for every scene × nested BSDF × size cell, with each method interleaved against Mitsuba's
``normalmap`` (builtin, method, builtin, method, ...: warm renders at equal spp); prints the
median of the per-pair ratios and the built-in's time per sample (µs per pixel sample).
``native`` is the scenes' own materials (run.py's production profile), the others replace
every normal-mapped material (run.py's small profile); ``--probe stub`` replaces them by
probes.py's closed-form Lambertian stub in the built-in and the methods alike.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import run as R  # noqa: E402  (benchmarks/run.py)


def cell(scene, nested, size, methods, reps, spp, assets, probe=None):
    W, H = size
    names = ("builtin",) + tuple(methods)
    scenes = {m: R.load_scene(scene, assets, m, nested, W, H, spp, probe=probe) for m in names}
    for m in names:                                    # JIT-compile (warm-up)
        R.timed_render(scenes[m], spp, 0)
    rows = []
    for m in methods:
        tb, tm, ratios = R.interleaved_pairs(scenes["builtin"], scenes[m], spp, reps)
        row = {"scene": scene, "nested": nested, "probe": probe, "size": f"{W}x{H}", "method": m,
               "builtin_s": R.median(tb), "method_s": R.median(tm), "ratio": R.median(ratios),
               "ratios": ratios, "builtin_us_per_sample": 1e6 * R.median(tb) / (W * H * spp)}
        R.log(f"{scene:6s} {nested + ('/' + probe if probe else ''):12s} {W}x{H:<4d} {m:16s} {row['method_s']:7.3f} s vs "
              f"{row['builtin_s']:7.3f} s ratio {row['ratio']:.3f} {[round(x, 3) for x in ratios]}"
              f"  builtin {row['builtin_us_per_sample']:.3f} µs/sample")
        rows.append(row)
    return rows


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", nargs="+", default=["demo", "model"])
    ap.add_argument("--nested", nargs="+", default=[R.NATIVE, "ggx_0.05"])
    ap.add_argument("--sizes", nargs="+", default=["192x144", "1280x720"])
    ap.add_argument("--methods", nargs="+", default=["faithful", "separable_same"])
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--probe", choices=["stub", "counting"],
                    help="run.py's probes: the nested BSDF (not native) replaced by the closed-form stub")
    ap.add_argument("--out", type=Path)
    args = ap.parse_args(argv)
    R.import_mitsuba()
    rows = []
    with R.temporary_assets(args.scenes, "mfnormal_split_") as assets:
        for s in args.scenes:
            for n in args.nested:
                for size in args.sizes:
                    W, H = (int(x) for x in size.split("x"))
                    rows += cell(s, n, (W, H), args.methods, args.reps, args.spp, assets, args.probe)
                    if args.out:
                        args.out.write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
