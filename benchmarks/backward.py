r"""Reverse-mode cost of every method against Mitsuba's built-in ``normalmap``.

    nice .venv/bin/python -m benchmarks.backward [--methods builtin,faithful,...] [--res 64]
        [--spp 16] [--reps 3] [--variant llvm_ad_rgb] [--out benchmarks]

The scene is the inverse-rendering one (:mod:`validation.inverse`: a plane under a 16² map,
roughplastic α 0.2, one directional sun, ``prb`` max_depth 2). Per method, in a fresh
subprocess (so that peak memory is its own): the primal render (no derivatives), then a
differentiable render of the same image plus ``dr.backward`` of its mean square error to
a target with respect to the map's texels. Reported: the medians over ``--reps`` warm runs
(the first run of each, which compiles, is left out) of the primal time and of the
render + backward time, their ratio, and the peak resident memory of the primal phase and
the extra peak of the backward phase (max RSS after minus before). The walks' loops are
reversed with Dr.Jit's sum-style reverse mode (``max_iterations=-1``): nothing is stored
per iteration; their backward pass replays the walk (docs/model.md §9).

Writes ``backward.json`` and ``backward.md`` (``--map flat``: ``backward_flat.*``) into ``--out``.
"""

from __future__ import annotations

import argparse
import json
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


def worker(method, res, spp, reps, start="true", variant="llvm_ad_rgb"):
    import mfnormal  # noqa: F401  (before mitsuba)
    import drjit as dr
    import mitsuba as mi
    import numpy as np

    mi.set_variant(variant)
    mfnormal.register()
    from validation import inverse as I

    setup = I.Setup(res=res, spp=spp, suns=((40.0, 0.0),))
    target = I.same_method_targets(setup, method)[0]
    texels = I.flat_map(setup) if start == "flat" else I.H.encode_normals(I.true_normals(setup))
    scene = I._plane_scenes(setup, method, texels)[0]
    params = mi.traverse(scene)
    key = next(k for k in params.keys() if k.endswith("normalmap.data"))

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
    return {"method": method, "primal_s": statistics.median(t_primal),
            "backward_s": statistics.median(r[0] for r in runs), "grad_max": runs[-1][1],
            "rss_primal_mb": rss_primal, "rss_before_mb": rss_before,
            "backward_extra_mb": rss_backward - rss_primal}


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--methods", type=lambda s: s.split(","), default=list(METHODS))
    p.add_argument("--res", type=int, default=64)
    p.add_argument("--spp", type=int, default=16)
    p.add_argument("--reps", type=int, default=3)
    p.add_argument("--out", type=Path, default=ROOT / "out" / "benchmarks")
    p.add_argument("--map", choices=["true", "flat"], default="true",
                   help="the map differentiated at: the true one, or a flat one (the optimisation's start, "
                        "where every texel takes the flat normal's derivatives: 4 more evaluations)")
    p.add_argument("--variant", default="llvm_ad_rgb", help="Mitsuba variant (default llvm_ad_rgb)")
    p.add_argument("--worker", help=argparse.SUPPRESS)
    args = p.parse_args(argv)
    if args.worker:
        print("JSON " + json.dumps(worker(args.worker, args.res, args.spp, args.reps, args.map, args.variant)))
        return 0
    rows = []
    for m in args.methods:
        proc = subprocess.run([sys.executable, "-m", "benchmarks.backward", "--worker", m, "--res", str(args.res),
                               "--spp", str(args.spp), "--reps", str(args.reps), "--map", args.map,
                               "--variant", args.variant], cwd=ROOT, capture_output=True, text=True)
        line = [x for x in proc.stdout.splitlines() if x.startswith("JSON ")]
        if proc.returncode != 0 or not line:
            rows.append({"method": m, "error": (proc.stderr or proc.stdout)[-500:]})
            print(f"{m}: FAILED {rows[-1]['error']}", flush=True)
            continue
        rows.append(json.loads(line[0][5:]))
        r = rows[-1]
        print(f"{m}: primal {r['primal_s']:.3f} s, render+backward {r['backward_s']:.3f} s, "
              f"peak RSS {r['rss_primal_mb']:.0f} MB, backward +{r['backward_extra_mb']:.0f} MB", flush=True)
    write(args, rows)
    return 0


def write(args, rows):
    args.out.mkdir(parents=True, exist_ok=True)
    name = "backward" if args.map == "true" else "backward_flat"
    (args.out / f"{name}.json").write_text(json.dumps({"command": " ".join(["python -m benchmarks.backward", *sys.argv[1:]]), "res": args.res,
                                                       "spp": args.spp, "map": args.map, "rows": rows}, indent=1))
    base = next((r for r in rows if r["method"] == "builtin" and "error" not in r), None)
    lines = ["# Reverse-mode cost per method", "",
             f"`python -m benchmarks.backward --res {args.res} --spp {args.spp} --map {args.map}`: the inverse-rendering "
             f"plane (16² map, {'the true map' if args.map == 'true' else 'a flat map'}, roughplastic α 0.2, one "
             f"sun, `prb` max_depth 2), {args.variant}. Times: medians of "
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
    (args.out / f"{name}.md").write_text("\n".join(lines) + "\n")


if __name__ == "__main__":
    sys.exit(main())
