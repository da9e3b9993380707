r"""Cost of the pixel's footprint in ``mfnormal_path``: time per sample with ``footprint`` on
against off.

    nice .venv/bin/python -m benchmarks.footprint [--width 192] [--height 144] [--spp 16] [--reps 7] [--out DIR]

The bundled demo scene (``run.py``'s scene (a), its own materials), with Mitsuba's
``normalmap`` (``builtin``) and with the default model (``faithful``), under ``mfnormal_path``
with ``footprint`` true and false, in two settings: ``shipped``, the scene as it is, where no
BSDF reads the footprint, so that Dr.Jit drops the cone's work as dead code (the kernels are
the same: their operation counts are reported); ``read``, every BSDF wrapped in
``bench_footprint_reader`` (probes.py), which reads the footprint without changing the image,
in both configurations: the cost of the cone when a BSDF uses it. Warm renders, interleaved in pairs (which of the two runs
first alternates, so that the drift of a shared machine cancels); the ratio on/off per pair
and its median over ``reps`` pairs. The clock is the process's CPU time with the kernels run
on the calling thread (``--threads 0``, the default, as ``normal_sources.py``: on a shared
machine the work, not the waiting; exact on this thread); ``--threads N`` times the wall clock
with N worker threads. The two images of a pair (same seed) must be equal up to
the order in which the scene's Gaussian pixel filter accumulates its splats across threads
(one scene rendered twice differs by that too; relative 1e-5): the demo's BSDFs do not read the
footprint (``filter="none"``; tests/test_footprint.py checks bit for bit, with a box filter). Writes
``footprint.json`` into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import time
from pathlib import Path

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np

from benchmarks import run

from benchmarks import probes

METHODS = ("builtin", "faithful")
SETTINGS = ("shipped", "read")


def scene(assets: dict, method: str, footprint: bool, args, setting="shipped"):
    """The demo scene for ``method`` under ``mfnormal_path`` with ``footprint`` (``setting``
    ``read``: its BSDFs read the footprint)."""
    d = run.with_integrator(run.scene_dict("demo", assets, method, run.NATIVE, args.width, args.height,
                                           args.spp), "mfnormal_path")
    if setting == "read":
        d = probes.wrap_readers(d)
    key = next(k for k, v in d.items() if isinstance(v, dict) and v.get("type") == "mfnormal_path")
    d[key] = {**d[key], "footprint": footprint}
    return mi.load_dict(d)


def timed(scene, spp: int, seed: int, threads: int):
    """(seconds, image) of one render: CPU time with the kernels on this thread (``threads``
    0), else the wall clock."""
    if threads:
        return run.timed_render(scene, spp, seed)
    dr.sync_thread()
    t0 = time.process_time()
    img = mi.render(scene, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    return time.process_time() - t0, img


def operations(scene, spp: int) -> int:
    """Operations in the JIT kernels of one warm render (Dr.Jit's kernel history)."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history_clear()
        dr.eval(mi.render(scene, spp=spp, seed=0))
        dr.sync_thread()
        hist = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    return int(sum(k.get("operation_count", 0) for k in hist if k.get("type") == dr.KernelType.JIT))


def measure(assets: dict, method: str, setting: str, args) -> dict:
    """The interleaved pairs of one method and setting: seconds per render off and on, the
    ratios on/off (``args.threads`` Dr.Jit threads during the renders), the kernels' operations."""
    scenes = {on: scene(assets, method, on, args, setting) for on in (False, True)}
    pool = dr.thread_count()
    if args.variant.startswith("llvm"):            # loading needs the pool: set only around the renders
        dr.set_thread_count(args.threads)
    try:
        out = pairs(scenes, method, args)
    finally:
        dr.set_thread_count(pool)
    return {**out, "setting": setting, "ops_off": operations(scenes[False], args.spp),
            "ops_on": operations(scenes[True], args.spp)}


def pairs(scenes: dict, method: str, args) -> dict:
    """Warm renders of ``scenes`` (footprint off and on), interleaved."""
    for on in (False, True):                       # compile both before timing
        timed(scenes[on], args.spp, 0, args.threads)
    times = {False: [], True: []}
    for r in range(args.reps):
        images = {}
        for on in ((False, True) if r % 2 == 0 else (True, False)):
            t, img = timed(scenes[on], args.spp, 100 + r, args.threads)
            times[on].append(t)
            images[on] = np.array(img)
        if not np.allclose(images[False], images[True], rtol=1e-5, atol=1e-6):
            raise RuntimeError(f"{method}: the images with the footprint on and off differ (seed {100 + r})")
    ratios = [b / a for a, b in zip(times[False], times[True])]
    return {"method": method, "off_s": times[False], "on_s": times[True], "ratios": ratios,
            "median_ratio": statistics.median(ratios)}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--width", type=int, default=192)
    ap.add_argument("--height", type=int, default=144)
    ap.add_argument("--spp", type=int, default=16)
    ap.add_argument("--reps", type=int, default=7, help="interleaved pairs per method (default 7)")
    ap.add_argument("--threads", type=int, default=0,
                    help="Dr.Jit worker threads (0, the default: kernels on this thread, CPU clock)")
    ap.add_argument("--variant", default="llvm_ad_rgb")
    ap.add_argument("--out", type=Path, default=run.HERE.parent / "out" / "benchmarks")
    args = ap.parse_args(argv)
    run.import_mitsuba(args.variant)
    if not args.variant.startswith("llvm"):
        args.threads = max(args.threads, 1)          # CUDA: the wall clock
    load = os.getloadavg()[0]
    with run.temporary_assets(["demo"]) as assets:
        results = [measure(assets, method, setting, args) for setting in SETTINGS for method in METHODS]
    for r in results:
        print(f"{r['setting']:8s} {r['method']:10s} on/off median {r['median_ratio']:.3f} "
              f"(pairs {', '.join(f'{x:.3f}' for x in r['ratios'])}; off median "
              f"{statistics.median(r['off_s']):.2f} s; operations {r['ops_off']} → {r['ops_on']})")
    args.out.mkdir(parents=True, exist_ok=True)
    record = {"size": [args.width, args.height], "spp": args.spp, "reps": args.reps, "threads": args.threads,
              "clock": "wall" if args.threads else "process CPU", "variant": args.variant,
              "load_before": load, "results": results}
    (args.out / "footprint.json").write_text(json.dumps(record, indent=1))


if __name__ == "__main__":
    main()
