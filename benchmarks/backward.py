r"""Reverse-mode cost of every method against Mitsuba's built-in ``normalmap``.

    nice .venv/bin/python -m benchmarks.backward [--methods builtin,faithful,...] [--res 64]
        [--spp 16] [--texels 16] [--reps 3] [--steps 5] [--variant llvm_ad_rgb] [--out benchmarks]

The scene is the inverse-rendering one (:mod:`validation.inverse`: a plane under a 16² map
(``--texels``), roughplastic α 0.2, one directional sun, ``prb`` max_depth 2). Per method, in a
fresh subprocess (so that peak memory and the kernels traced are its own):

- the primal render (no derivatives), then a differentiable render of the same image plus
  ``dr.backward`` of its mean square error to a target with respect to the map's texels, the
  texels the same each time. Reported: the medians over ``--reps`` warm runs (the first run of
  each, which compiles, is left out) of the primal time and of the render + backward time, their
  ratio, and the peak resident memory of the primal phase and the extra peak of the backward
  phase (max RSS after minus before);
- an optimiser's whole step, as an inverse rendering runs it: Adam (rate 0.01) on the texels,
  each step ``params.update(opt)`` (the new texels into the scene: what the plugin rebuilds for
  them), the differentiable render, its loss's ``dr.backward`` and ``opt.step()``. The texels
  change every step. Reported: the medians over ``--steps`` warm steps (after two steps that
  compile) of the update, the render, the backward (with ``opt.step()``) and the whole step, each
  phase waited for (``dr.sync_thread``) before the next starts, the whole step's mean (which
  counts the few updates that build the map's tables again), and the step's ratios to the
  built-in's, measured in the same run.

The walks' loops are reversed with Dr.Jit's sum-style reverse mode (``max_iterations=-1``):
nothing is stored per iteration; their backward pass replays the walk (docs/model.md §9).

Writes ``backward.json`` and ``backward.md`` (``--map flat``: ``backward_flat.*``) into ``--out``.
"""

from __future__ import annotations

import argparse
import json
import os
import resource
import statistics
import subprocess
import sys
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
ROOT = HERE.parent
METHODS = ("builtin", "faithful", "analytic", "separable_specular", "separable_same",
           "nonseparable_specular", "nonseparable_same")


def rss_mb() -> float:
    return resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / 1024.0


def _setup(method, res, spp, start, texels):
    """(scene, its traversed parameters, the map's key, the target) of ``method``."""
    import mitsuba as mi
    from validation import inverse as I

    setup = I.Setup(res=res, spp=spp, texels=texels, suns=((40.0, 0.0),))
    target = I.same_method_targets(setup, method)[0]
    texels = I.flat_map(setup) if start == "flat" else I.H.encode_normals(I.true_normals(setup))
    scene = I._plane_scenes(setup, method, texels)[0]
    params = mi.traverse(scene)
    return scene, params, next(k for k in params.keys() if k.endswith("normalmap.data")), target


def steps(scene, params, key, target, spp, count, warm=2):
    """``count`` warm optimiser steps (after ``warm`` that compile): the medians of (update,
    render, backward with the optimiser's step, the whole step) and the mean of the whole step
    (with the updates that rebuild what the map's statistics need, which the median may not
    show), in seconds."""
    import drjit as dr
    import mitsuba as mi

    opt = mi.ad.Adam(lr=0.01)
    opt[key] = params[key]

    def step(seed):
        t = [time.perf_counter()]
        params.update(opt)
        dr.sync_thread()
        t.append(time.perf_counter())
        img = mi.render(scene, params, spp=spp, seed=seed)
        loss = dr.mean(dr.square(img - target), axis=None)
        dr.eval(loss)
        dr.sync_thread()
        t.append(time.perf_counter())
        dr.backward(loss)
        opt.step()
        dr.eval(opt[key])
        dr.sync_thread()
        t.append(time.perf_counter())
        return t[1] - t[0], t[2] - t[1], t[3] - t[2], t[3] - t[0]

    runs = [step(k) for k in range(warm + count)][warm:]
    return [statistics.median(r[n] for r in runs) for n in range(4)] + [statistics.mean(r[3] for r in runs)]


def worker(method, res, spp, reps, start="true", variant="llvm_ad_rgb", texels=16, count=5):
    import mfnormal  # noqa: F401  (before mitsuba)
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    mi.set_variant(variant)
    mfnormal.register()
    scene, params, key, target = _setup(method, res, spp, start, texels)

    def primal(seed):
        t = time.perf_counter()
        img = mi.render(scene, params, spp=spp, seed=seed)
        dr.eval(img)
        np.array(img)
        return time.perf_counter() - t

    def backward(seed):
        data = mi.TensorXf(params[key])
        dr.enable_grad(data)
        params[key] = data
        params.update()
        t = time.perf_counter()
        img = mi.render(scene, params, spp=spp, seed=seed)
        loss = dr.mean(dr.square(img - target), axis=None)
        dr.backward(loss)
        g = np.array(dr.grad(data))
        dt = time.perf_counter() - t
        params[key] = dr.detach(data)
        params.update()
        return dt, float(np.abs(g).max())

    primal(0)
    rss_before = rss_mb()
    t_primal = [primal(1 + k) for k in range(reps)]
    rss_primal = rss_mb()
    backward(0)
    runs = [backward(1 + k) for k in range(reps)]
    rss_backward = rss_mb()
    update_s, render_s, backward_s, step_s, step_mean_s = steps(scene, params, key, target, spp, count)
    return {"method": method, "primal_s": statistics.median(t_primal),
            "backward_s": statistics.median(r[0] for r in runs), "grad_max": runs[-1][1],
            "rss_primal_mb": rss_primal, "rss_before_mb": rss_before,
            "backward_extra_mb": rss_backward - rss_primal, "step_update_s": update_s,
            "step_render_s": render_s, "step_backward_s": backward_s, "step_s": step_s,
            "step_mean_s": step_mean_s}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--methods", type=lambda s: s.split(","), default=list(METHODS))
    p.add_argument("--res", type=int, default=64)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--texels", type=int, default=16, help="the map's resolution per axis (default 16)")
    p.add_argument("--steps", type=int, default=5, help="warm optimiser steps timed (default 5)")
    p.add_argument("--out", type=Path, default=ROOT / "out" / "benchmarks")
    p.add_argument("--map", choices=["true", "flat"], default="true",
                   help="the map differentiated at: the true one, or a flat one (the optimisation's start, "
                        "where every texel takes the flat normal's derivatives: 4 more evaluations)")
    p.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (default llvm_ad_rgb)")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print("JSON " + json.dumps(worker(args.worker, args.res, args.spp, args.reps, args.map, args.variant,
                                          args.texels, args.steps)))
        return 0
    rows, load = [], os.getloadavg()[0]
    for m in args.methods:
        proc = subprocess.run([sys.executable, "-m", "benchmarks.backward", "--worker", m, "--res", str(args.res), "--spp",
                               str(args.spp), "--reps", str(args.reps), "--map", args.map, "--variant", args.variant,
                               "--texels", str(args.texels), "--steps", str(args.steps)],
                              cwd=ROOT, capture_output=True, text=True)
        line = [x for x in proc.stdout.splitlines() if x.startswith("JSON ")]
        if proc.returncode != 0 or not line:
            rows.append({"method": m, "error": (proc.stderr or proc.stdout)[-500:]})
            print(f"{m}: FAILED {rows[-1]['error']}", flush=True)
            continue
        rows.append(json.loads(line[0][5:]))
        r = rows[-1]
        print(f"{m}: primal {r['primal_s']:.3f} s, render+backward {r['backward_s']:.3f} s, "
              f"peak RSS {r['rss_primal_mb']:.0f} MB, backward +{r['backward_extra_mb']:.0f} MB; step "
              f"{r['step_s']:.3f} s, mean {r['step_mean_s']:.3f} s (update {r['step_update_s']:.3f}, render {r['step_render_s']:.3f}, "
              f"backward {r['step_backward_s']:.3f})", flush=True)
    write(args, rows, load)
    return 0


def write(args, rows, load=None):
    args.out.mkdir(parents=True, exist_ok=True)
    name = "backward" if args.map == "true" else "backward_flat"
    (args.out / f"{name}.json").write_text(json.dumps({"command": " ".join(["python -m benchmarks.backward", *sys.argv[1:]]), "res": args.res,
                                                       "spp": args.spp, "texels": args.texels, "map": args.map,
                                                       "load_before": load, "rows": rows}, indent=1))
    base = next((r for r in rows if r["method"] == "builtin" and "error" not in r), None)
    busy = f" Load average before the run: {load:.2f}." if load is not None else ""
    lines = ["# Reverse-mode cost per method", "",
             f"`python -m benchmarks.backward --res {args.res} --spp {args.spp} --texels {args.texels} --map {args.map}`: "
             f"the inverse-rendering plane ({args.texels}² map, {'the true map' if args.map == 'true' else 'a flat map'}, "
             f"roughplastic α 0.2, one sun, `prb` max_depth 2), {args.variant}.{busy} Times: medians of "
             "warm runs; render+backward = a differentiable render and `dr.backward` of its MSE w.r.t. the "
             "texels. Memory: peak RSS of the primal phase, and the extra peak of the backward phase.", "",
             "| method | primal s | render+backward s | ×primal | ×built-in's backward | peak RSS MB | backward extra MB |",
             "|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            lines.append(f"| {r['method']} | failed | | | | | |")
            continue
        rel = f"{r['backward_s'] / base['backward_s']:.1f}" if base else "–"
        lines.append(f"| {r['method']} | {r['primal_s']:.3f} | {r['backward_s']:.3f} | "
                     f"{r['backward_s'] / r['primal_s']:.1f} | {rel} | {r['rss_primal_mb']:.0f} | "
                     f"{r['backward_extra_mb']:.0f} |")
    lines += step_table(rows, base, args.steps)
    (args.out / f"{name}.md").write_text("\n".join(lines) + "\n")


def step_table(rows, base, count) -> list:
    """The optimiser step's lines: each phase's median, the whole step's mean, and their ratios to
    the built-in's."""
    lines = ["", f"An optimiser's whole step (Adam on the texels, new texels every step; medians of {count} warm "
             "steps, and the whole step's mean): `params.update(opt)`, the differentiable render, its "
             "`dr.backward` with `opt.step()`.", "",
             "| method | update s | render s | backward s | step s | step s, mean | ×built-in's step | "
             "×built-in's, means | render+backward ×built-in's |",
             "|---|---|---|---|---|---|---|---|---|"]
    for r in rows:
        if "error" in r:
            continue
        rel = f"{r['step_s'] / base['step_s']:.1f}" if base else "–"
        mean = r["step_mean_s"]
        rel_mean = f"{mean / base['step_mean_s']:.1f}" if base else "–"
        rb = r["step_render_s"] + r["step_backward_s"]
        rel_rb = f"{rb / (base['step_render_s'] + base['step_backward_s']):.1f}" if base else "–"
        lines.append(f"| {r['method']} | {r['step_update_s']:.3f} | {r['step_render_s']:.3f} | "
                     f"{r['step_backward_s']:.3f} | {r['step_s']:.3f} | {mean:.3f} | {rel} | "
                     f"{rel_mean} | {rel_rb} |")
    return lines


if __name__ == "__main__":
    sys.exit(main())
