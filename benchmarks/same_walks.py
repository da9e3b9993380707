#!/usr/bin/env python
r"""The same-material walks against the built-in where both render the same content (issue 18).

    python benchmarks/same_walks.py [--scenes plane,demo,model] [--nested ggx_0.05,ggx_0.3]
                                    [--out benchmarks/same_walks.md]

Per scene and nested BSDF, under the benchmark's sky without its sun disc (``run.py``'s
``sunless`` control) and at ``run.py``'s full profile size (192×144, 16 spp): the render
time ratio at equal spp (median of interleaved built-in/method pairs), the equal-time
relMSE ratio (each method at the spp it reaches in the built-in's time, against its own
256-spp reference, ``run.equal_time_noise``), and the first render's compile time and
largest kernel (a subprocess with an empty kernel cache, ``run.run_worker``) against the
built-in's. A subset of ``run.py``'s metrics for the two ``same`` walks, small enough to
rerun while changing them; ``run.py`` stays the benchmark of record.
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))

import run as bench  # noqa: E402

METHODS = ("separable_same", "nonseparable_same")


def cell(scene, nested, assets, prof, reps, compile_runs):
    """The rows of one scene and nested BSDF: builtin first."""
    W, H, spp = prof.width, prof.height, prof.spp
    scenes = {m: bench.load_scene(scene, assets, m, nested, W, H, spp, sunless=True)
              for m in ("builtin",) + METHODS}
    for s in scenes.values():
        bench.timed_render(s, spp, 0)
    rows = []
    for m in METHODS:
        ratios = bench.interleaved_pairs(scenes["builtin"], scenes[m], spp, reps)[2]
        rows.append({"scene": scene, "nested": nested, "method": m, "time_ratio": bench.median(ratios)})
    base = bench.equal_time_noise(scenes["builtin"], spp, prof)
    for row in rows:
        row["spp"] = max(1, int(round(spp / row["time_ratio"])))
        n = bench.equal_time_noise(scenes[row["method"]], row["spp"], prof)
        row.update(relmse_ratio=n["relmse"] / base["relmse"], ref_mean_ratio=n["ref_mean"] / base["ref_mean"],
                   top=n["top"])
    if compile_runs:
        args = {"scene": scene, "assets": assets, "nested": nested, "width": W, "height": H, "spp": spp,
                "warm_reps": prof.compile_warm_reps}
        b = bench.run_worker(dict(args, method="builtin"))
        for row in rows:
            c = bench.run_worker(dict(args, method=row["method"]))
            row.update(compile_s=c.get("compile_s"), compile_builtin_s=b.get("compile_s"),
                       ops=c.get("max_kernel_ops"), ops_builtin=b.get("max_kernel_ops"),
                       compile_ratio=c["compile_s"] / b["compile_s"] if "compile_s" in c and b.get("compile_s")
                       else None)
    for row in rows:
        bench.log(f"  {scene:6s} {nested:9s} {row['method']:18s} time {row['time_ratio']:.2f}  relMSE "
                  f"{row['relmse_ratio']:.2f} (mean {row['ref_mean_ratio']:.3f}, top-0.1 % {row['top']:.2f})"
                  + (f"  compile {row['compile_ratio']:.2f} ({row['ops']} vs {row['ops_builtin']} ops)"
                     if row.get("compile_ratio") else ""))
    return rows


def markdown(rows, argv) -> str:
    lines = ["# The `same` walks under the sky without its sun disc (issue 18)", "",
             f"`python benchmarks/same_walks.py {' '.join(argv)}`; ratios are method / built-in, "
             "192×144, 16 spp, llvm_ad_rgb. Targets: time ≤ 1.5 (separable) / 1.6 (non-separable), "
             "equal-time relMSE ≤ 6 (rough conductors), compile ≤ 2.", "",
             "| scene | nested | method | time | relMSE (equal time) | reference mean | top-0.1 % share "
             "| compile (built-in s) | ops (built-in) |", "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        comp = (f"{r['compile_ratio']:.2f} ({r['compile_builtin_s']:.2f})" if r.get("compile_ratio") else "–")
        ops = f"{r['ops']} ({r['ops_builtin']})" if r.get("ops") else "–"
        lines.append(f"| {r['scene']} | {r['nested']} | {r['method']} | {r['time_ratio']:.2f} | "
                     f"{r['relmse_ratio']:.2f} | {r['ref_mean_ratio']:.3f} | {r['top']:.2f} | {comp} | {ops} |")
    return "\n".join(lines) + "\n"


def main(argv=None) -> int:
    argv = sys.argv[1:] if argv is None else argv
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scenes", default="plane,demo,model")
    ap.add_argument("--nested", default="ggx_0.05,ggx_0.3")
    ap.add_argument("--reps", type=int, default=5, help="interleaved timing pairs per method")
    ap.add_argument("--noise-seeds", type=int, default=4)
    ap.add_argument("--no-compile", action="store_true", help="skip the cold-cache subprocesses")
    ap.add_argument("--out", type=Path, default=None, help="markdown (and .json beside it)")
    args = ap.parse_args(argv)
    bench.import_mitsuba()
    scenes = tuple(args.scenes.split(","))
    prof = bench.Profile("same_walks", scenes, tuple(args.nested.split(",")), METHODS,
                         width=192, height=144, spp=16, reps=args.reps, ref_spp=256, ref_pass=32,
                         noise_seeds=args.noise_seeds, queries=0, tput_reps=0, stub_reps=0, compile_warm_reps=2)
    rows = []
    with bench.temporary_assets(scenes, "mfnormal_same_walks_") as assets:
        for scene in scenes:
            for nested in prof.nested:
                rows += cell(scene, nested, assets, prof, args.reps, not args.no_compile)
    if args.out:
        args.out.write_text(markdown(rows, argv))
        args.out.with_suffix(".json").write_text(json.dumps(rows, indent=1))
    return 0


if __name__ == "__main__":
    sys.exit(main())
