#!/usr/bin/env python
r"""Inlined against indirect nested-BSDF calls in the random walks (issue 18 item 2).

    python benchmarks/nested_calls.py compile|time METHODS NESTED [--reps N]

Runs the demo scene of ``benchmarks/run.py`` (its ``full`` profile: 192×144, 16 spp) with
``walk.INDIRECT_NESTED_CALLS`` off (``inline``) and on (``indirect``), each against Mitsuba's
``normalmap`` (``builtin``), with run.py's own measurements:

- ``compile``: run.py's metric 2 (a fresh process and an empty kernel cache per render; first
  render minus warm render, the kernel history's largest kernel and LLVM backend time),
  repeated ``--reps`` times as builtin, inline, indirect, builtin, ...; medians of the per-rep
  ratios to the built-in;
- ``time``: run.py's metric 1 (warm renders at equal spp), interleaved builtin, inline,
  builtin, indirect, ...; medians of the per-pair ratios.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import run as R  # noqa: E402  (benchmarks/run.py)

VARIANTS = {"inline": False, "indirect": True}


def worker(args: dict) -> dict:
    """In a fresh process with an empty DRJIT_CACHE_DIR: run.py's compile worker."""
    rss0 = R.memory_mb()["VmHWM"]
    R.import_mitsuba()
    from mfnormal.models import walk
    walk.INDIRECT_NESTED_CALLS = args.pop("indirect", False)
    return R._worker(args, rss0)


def run_worker(args: dict) -> dict:
    cache = tempfile.mkdtemp(prefix="mfnormal_nested_calls_")
    try:
        proc = subprocess.run([sys.executable, __file__, "--worker", json.dumps(args)],
                              env=dict(os.environ, DRJIT_CACHE_DIR=cache), capture_output=True, text=True,
                              timeout=900)
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    raise RuntimeError(f"worker exited {proc.returncode}: {proc.stderr.strip().splitlines()[-3:]}")


def compile_ab(methods, nested, assets, reps):
    prof = R.FULL
    job = dict(scene="demo", nested=nested, assets=assets, width=prof.width, height=prof.height,
               spp=prof.spp, warm_reps=prof.compile_warm_reps)
    for m in methods:
        rows = {v: [] for v in VARIANTS}
        for r in range(reps):
            b = run_worker(dict(job, method="builtin"))
            for v, on in VARIANTS.items():
                x = run_worker(dict(job, method=m, indirect=on))
                rows[v].append((x["compile_s"] / b["compile_s"], x["backend_s"] / b["backend_s"],
                                x["max_kernel_ops"], b["max_kernel_ops"]))
                R.log(f"  {m} {nested} {v} rep {r}: compile {x['compile_s']:.3f} s / builtin "
                      f"{b['compile_s']:.3f} s, ops {x['max_kernel_ops']} / {b['max_kernel_ops']}")
        for v in VARIANTS:
            t = rows[v]
            R.log(f"COMPILE {m} {nested} {v}: ratio {statistics.median(a[0] for a in t):.2f} "
                  f"[{min(a[0] for a in t):.2f}, {max(a[0] for a in t):.2f}], backend ratio "
                  f"{statistics.median(a[1] for a in t):.2f}, ops {t[0][2]} (builtin {t[0][3]})")


def time_ab(methods, nested, assets, reps):
    from mfnormal.models import walk
    prof = R.FULL
    builtin = R.load_scene("demo", assets, "builtin", nested, prof.width, prof.height, prof.spp)
    R.timed_render(builtin, prof.spp, 0)
    for m in methods:
        scene = R.load_scene("demo", assets, m, nested, prof.width, prof.height, prof.spp)
        ratios = {v: [] for v in VARIANTS}
        for on in VARIANTS.values():                # compile both
            walk.INDIRECT_NESTED_CALLS = on
            R.timed_render(scene, prof.spp, 0)
        for r in range(reps):
            for v, on in VARIANTS.items():
                walk.INDIRECT_NESTED_CALLS = False
                tb = R.timed_render(builtin, prof.spp, 100 + r)[0]
                walk.INDIRECT_NESTED_CALLS = on      # read while the render traces its kernel
                tm = R.timed_render(scene, prof.spp, 100 + r)[0]
                ratios[v].append(tm / tb)
        walk.INDIRECT_NESTED_CALLS = False
        for v, t in ratios.items():
            R.log(f"TIME {m} {nested} {v}: ratio {statistics.median(t):.3f} [{min(t):.2f}, {max(t):.2f}]")


def main():
    if len(sys.argv) > 2 and sys.argv[1] == "--worker":
        print("RESULT " + json.dumps(worker(json.loads(sys.argv[2]))), flush=True)
        return
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[1])
    ap.add_argument("mode", choices=("compile", "time"))
    ap.add_argument("methods", help="comma-separated walk methods, e.g. separable_same,nonseparable_same")
    ap.add_argument("nested", help=f"one of {','.join(R.NESTED)}")
    ap.add_argument("--reps", type=int, default=5)
    args = ap.parse_args()
    R.import_mitsuba()
    with R.temporary_assets(["demo"], "mfnormal_nested_calls_assets_") as assets:
        (compile_ab if args.mode == "compile" else time_ab)(args.methods.split(","), args.nested, assets, args.reps)


if __name__ == "__main__":
    main()
