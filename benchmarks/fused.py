#!/usr/bin/env python
"""The fused BSDF call (issue #18): every method under Mitsuba's ``path`` and under ``mfnormal_path``.

    PYTHONPATH=src python benchmarks/fused.py [--scene demo] [--sizes 192x144 1280x720]
        [--nested native ggx_0.05] [--spp 16] [--reps 3] [--methods ...] [--no-compile]
        [--out benchmarks/fused.json]

``path`` calls ``eval_pdf_sample`` per vertex, which for a Python BSDF runs ``eval_pdf`` and
then ``sample`` (two walks for the random-walk models); ``mfnormal_path`` (mfnormal.plugins.mfnormal_path)
calls the plugin's own ``eval_pdf_sample`` (one walk). Per scene size and nested BSDF:

- render time at equal spp: each configuration (method × integrator; the built-in also under
  ``mfnormal_path``, the fairness check: it should be ≈ 1) against the built-in under ``path``,
  interleaved (base, config) pairs, the configurations taken round-robin in each repetition so
  that a change of machine load reaches all of them alike; the median of the per-pair ratios;
- first-render compile time (run.py's metric 2: a subprocess with an empty kernel cache per
  configuration; first − warm render, or without warm renders the kernel history's codegen +
  backend time) and the largest kernel's operation count, as ratios to the built-in's under
  ``path``.

Uses run.py's helpers (``load_scene``, ``timed_render``, ``run_worker``), the same scenes and
MAX_DEPTH. Writes ``--out`` (JSON) and its tables beside it (``.md``; ``--report-only JSON``
rewrites them from a JSON file).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parent))
import run as R  # noqa: E402

METHODS = R.METHOD_KEYS
INTEGRATORS = R.INTEGRATORS


def configs(methods):
    """(method, integrator) pairs measured; the built-in under path is the base of every ratio."""
    return [(m, i) for m in methods for i in INTEGRATORS if (m, i) != ("builtin", "path")]


def render_ratios(scene, nested, assets, size, spp, reps, methods) -> dict:
    """{(method, integrator): (median ratio, [ratios], median seconds)} and the base's seconds."""
    W, H = size
    base = R.load_scene(scene, assets, "builtin", nested, W, H, spp)
    scenes = {c: R.load_scene(scene, assets, c[0], nested, W, H, spp, integrator=c[1]) for c in configs(methods)}
    R.timed_render(base, spp, 0)
    for c, sc in scenes.items():                 # warm-up: compiles each kernel once
        t = R.timed_render(sc, spp, 0)[0]
        R.log(f"  warm-up {c[0]:22s} {c[1]:14s} {t:.2f} s")
    ratios = {c: [] for c in scenes}
    seconds = {c: [] for c in scenes}
    t_base = []
    for r in range(reps):
        for c, sc in scenes.items():
            tb = R.timed_render(base, spp, 100 + r)[0]
            tm = R.timed_render(sc, spp, 100 + r)[0]
            t_base.append(tb)
            seconds[c].append(tm)
            ratios[c].append(tm / tb)
    out = {f"{m}|{i}": {"ratio": statistics.median(ratios[(m, i)]), "ratios": ratios[(m, i)],
                        "seconds": statistics.median(seconds[(m, i)])} for (m, i) in scenes}
    out["builtin|path"] = {"ratio": 1.0, "ratios": [], "seconds": statistics.median(t_base)}
    return out


def compile_rows(scene, nested, assets, size, spp, methods, variant) -> dict:
    """run.py's metric 2 per (method, integrator): compile seconds and the largest kernel's ops."""
    W, H = size
    warm = 2 if W * H <= 192 * 144 else 0
    job = {"scene": scene, "nested": nested, "assets": assets, "width": W, "height": H, "spp": spp,
           "warm_reps": warm, "variant": variant}
    out = {}
    for m, i in [("builtin", "path")] + configs(methods):
        r = R.run_worker(dict(job, method=m, integrator=i))
        out[f"{m}|{i}"] = r
        R.log(f"  compile {m:22s} {i:14s} " + (r["error"] if "error" in r else
              f"{r['compile_s']:.2f} s ({r['compile_from']}), ops {r['max_kernel_ops']}"))
    b = out["builtin|path"]
    for r in out.values():
        if "error" not in r and "error" not in b:
            r["compile_ratio"] = r["compile_s"] / max(b["compile_s"], 1e-3)
            r["ops_ratio"] = r["max_kernel_ops"] / max(b["max_kernel_ops"], 1)
    return out


def table(cell: dict, methods) -> list:
    lines = ["| method | time path | time mfnormal_path | mf/path | mf/(builtin mf) | compile path | compile mf "
             "| ops path | ops mf |", "|---|---|---|---|---|---|---|---|---|"]
    base_mf = cell["render"]["builtin|mfnormal_path"]["ratio"]
    comp = cell.get("compile", {})

    def c(m, i, key, spec=".2f"):
        v = comp.get(f"{m}|{i}", {}).get(key)
        return "–" if v is None else format(v, spec)
    for m in methods:
        tp, tm = cell["render"][f"{m}|path"]["ratio"], cell["render"][f"{m}|mfnormal_path"]["ratio"]
        lines.append(f"| {m} | {tp:.3f} | {tm:.3f} | {tm / tp:.3f} | {tm / base_mf:.3f} | {c(m, 'path', 'compile_ratio')} | "
                     f"{c(m, 'mfnormal_path', 'compile_ratio')} | {c(m, 'path', 'max_kernel_ops', 'd')} | "
                     f"{c(m, 'mfnormal_path', 'max_kernel_ops', 'd')} |")
    return lines


def write_markdown(results: dict, path: Path, methods=METHODS):
    """The tables of every cell: each configuration's time and compile as ratios to the built-in
    under ``path``, and the largest kernel's operations."""
    m = results["machine"]
    lines = ["# The fused BSDF call: every method under `path` and under `mfnormal_path`", "",
             f"`benchmarks/fused.py`, scene `{results['scene']}`, {results['spp']} spp, {results['reps']} "
             f"interleaved repetitions (medians of per-pair ratios to the built-in under `path`), commit "
             f"`{results['git']['commit']}`, {m['variant']}, {m['cores']} cores ({m['cpu']}). "
             "Compile: run.py's metric 2 (192×144: first − warm render; 1280×720: the kernel history's "
             "codegen + backend time). `mf/path`: the method's time under `mfnormal_path` over its time under "
             "`path`; `mf/(builtin mf)`: its time under `mfnormal_path` over the built-in's under "
             "`mfnormal_path` (the integrators' own difference taken out).", ""]
    for cell in results["cells"]:
        w, h = cell["size"]
        lines += [f"## {w}×{h}, nested {cell['nested']}", ""] + table(cell, methods) + [""]
    path.write_text("\n".join(lines))


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--scene", default="demo", choices=R.SCENES)
    ap.add_argument("--sizes", nargs="+", default=["192x144", "1280x720"])
    ap.add_argument("--nested", nargs="+", default=[R.NATIVE, "ggx_0.05"])
    ap.add_argument("--methods", nargs="+", default=list(METHODS), choices=METHODS)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--reps", type=int, default=3)
    ap.add_argument("--no-compile", action="store_true")
    ap.add_argument("--variant", default=R.VARIANT)
    ap.add_argument("--out", type=Path, default=R.HERE / "fused.json")
    ap.add_argument("--report-only", type=Path, help="write the markdown of this JSON file and exit")
    args = ap.parse_args(argv)
    if args.report_only:
        write_markdown(json.loads(args.report_only.read_text()), args.out.with_suffix(".md"))
        return 0
    if "builtin" not in args.methods:
        args.methods.insert(0, "builtin")
    R.import_mitsuba(args.variant)
    sizes = [tuple(int(x) for x in s.split("x")) for s in args.sizes]
    results = {"scene": args.scene, "spp": args.spp, "reps": args.reps, "machine": R.machine_info(),
               "git": R.git_state(), "cells": []}
    t0 = time.time()
    with R.temporary_assets((args.scene,)) as assets:
        for size in sizes:
            for nested in args.nested:
                R.log(f"[{args.scene} {size[0]}x{size[1]} {nested}]")
                cell = {"size": list(size), "nested": nested,
                        "render": render_ratios(args.scene, nested, assets, size, args.spp, args.reps, args.methods)}
                if not args.no_compile:
                    cell["compile"] = compile_rows(args.scene, nested, assets, size, args.spp, args.methods,
                                                   args.variant)
                results["cells"].append(cell)
                R.log("\n".join(table(cell, args.methods)))
                args.out.write_text(json.dumps(results, indent=1, default=str))
                write_markdown(results, args.out.with_suffix(".md"), args.methods)
    R.log(f"done in {time.time() - t0:.0f} s: {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
