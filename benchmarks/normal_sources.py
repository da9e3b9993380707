r"""Cost per query of the other normal sources against the normal-map path.

    nice .venv/bin/python -m benchmarks.normal_sources [--queries 20] [--reps 9] [--out benchmarks]

For every model (faithful, analytic, separable, nonseparable) and nested BSDF (diffuse,
roughplastic), times ``eval``, ``eval_pdf`` and ``sample`` of ``normalmap_microfacet`` on
2^queries random queries (random ω_i, ω_o, uv, a triangle normal up to 30° off the shading
normal, skewed dp/du, dp/dv) with, besides the reference ``normalmap`` (a 256² bilinear map):

- ``heightmap``: a 256² bilinear height map instead (Mitsuba's ``eval_1_grad``);
- ``geometric``: the normal map with ``macro_normal="geometric"``;
- ``geometric_heightmap``: both;
- ``geometric_nomap``: no map, ``macro_normal="geometric"`` (the terminator fix).

Warm kernels only (one untimed call first), process CPU time (tracing included) with the
kernels run on the calling thread (``--threads 0``, the default: Dr.Jit's pool is
``dr.set_thread_count(0)``). With worker threads (``--threads N``) the process clock only
adds the other threads' time at the scheduler tick (the readings of one 2^19-query
call, 8-50 ms, came in steps of about 4 ms), which at this size is ±10-50 % per reading; on the
calling thread the clock is exact. The configurations are interleaved
(reference, config, config, reference, ...: which one runs first alternates; in a fixed
order, of two variants differing by 5 operations the later one measured 0-9 % faster) and
each ratio is the median over ``reps`` pairs, so the drift of a shared machine cancels;
beside it the operation count of the JIT kernels (deterministic). Writes ``normal_sources.json`` and
``normal_sources.md`` into ``--out``. Target: ``heightmap`` and ``geometric``
within 10 % of the normal-map path (ratio ≤ 1.10).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import mfnormal  # first: selects a working libLLVM

import drjit as dr
import mitsuba as mi
import numpy as np

HERE = Path(__file__).resolve().parent
MODELS = ("faithful", "analytic", "separable", "nonseparable")
NESTED = {"diffuse": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}},
          "roughplastic": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.2,
                           "diffuse_reflectance": {"type": "rgb", "value": [0.3, 0.5, 0.2]}}}
CONFIGS = ("heightmap", "geometric", "geometric_heightmap", "geometric_nomap")
TEX = 256


def textures(seed=3):
    rng = np.random.default_rng(seed)
    h = rng.normal(0, 1, (TEX, TEX))
    for _ in range(3):
        h = (h + np.roll(h, 1, 0) + np.roll(h, 1, 1) + np.roll(h, (1, 1), (0, 1))) / 4
    h = (h / h.std() * 0.01).astype(np.float32)
    gy, gx = np.gradient(h.astype(np.float64), 1.0 / TEX)
    n = np.stack([-gx, gy, np.ones_like(gx)], -1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    def tex(a):
        return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(a, np.float32)), "raw": True,
                "filter_type": "bilinear", "wrap_mode": "repeat"}
    return tex(n * 0.5 + 0.5), tex(h[..., None])


def plugin(model, nested, config, normalmap, heightmap):
    d = {"type": "normalmap_microfacet", "model": model, "bsdf": NESTED[nested]}
    if config in ("heightmap", "geometric_heightmap"):
        d["heightmap"] = heightmap
    elif config != "geometric_nomap":
        d["normalmap"] = normalmap
    if config.startswith("geometric"):
        d["macro_normal"] = "geometric"
    return mi.load_dict(d)


def queries(n, seed=11):
    rng = np.random.default_rng(seed)

    def f(a):
        return mi.Float(np.ascontiguousarray(a, np.float32))

    def hemi(k):
        d = rng.normal(size=(k, 3))
        d[:, 2] = np.abs(d[:, 2]) + 1e-3
        return d / np.linalg.norm(d, axis=1, keepdims=True)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    t = np.radians(rng.uniform(0, 30, n))
    p = rng.uniform(0, 2 * np.pi, n)
    si.n = mi.Normal3f(f(np.sin(t) * np.cos(p)), f(np.sin(t) * np.sin(p)), f(np.cos(t)))
    si.dp_du = mi.Vector3f(f(1.0 + 0.1 * rng.normal(size=n)), f(0.2 * rng.normal(size=n)), 0.0)
    si.dp_dv = mi.Vector3f(f(0.2 * rng.normal(size=n)), f(-1.0 + 0.1 * rng.normal(size=n)), 0.0)
    si.uv = mi.Point2f(f(rng.random(n)), f(rng.random(n)))
    k = np.arange(n)
    si.p = mi.Point3f(f(k % 4096), f(k // 4096), 0.0)
    si.wi = mi.Vector3f(*(f(c) for c in hemi(n).T))
    wo = mi.Vector3f(*(f(c) for c in hemi(n).T))
    u = rng.random((n, 3))
    return si, wo, f(u[:, 0]), mi.Point2f(f(u[:, 1]), f(u[:, 2]))


def timed(fn):
    """CPU seconds of the process for one call, tracing included: on a machine shared with other
    jobs this counts the work, not the waiting (exact with the kernels on this thread, --threads 0)."""
    dr.sync_thread()
    t = time.process_time()
    out = fn()
    dr.eval(out)
    dr.sync_thread()
    return time.process_time() - t


def op_count(fn) -> int:
    """Operations in the JIT kernels one call launches (Dr.Jit's kernel history): a deterministic
    cost measure beside the timings."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history()                          # clear
        timed(fn)
        hist = dr.kernel_history()
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)
    return int(sum(k.get("operation_count", 0) for k in hist if k.get("type") == dr.KernelType.JIT))


def calls(bsdf, q):
    si, wo, s1, s2 = q
    ctx = mi.BSDFContext()
    return {"eval": lambda: bsdf.eval(ctx, si, wo),
            "eval_pdf": lambda: bsdf.eval_pdf(ctx, si, wo),
            "sample": lambda: bsdf.sample(ctx, si, s1, s2)}


def interleaved(ref, other, reps: int) -> tuple:
    """CPU times of ``reps`` pairs of calls of ``ref`` and ``other`` (warm: one untimed call of
    each first), the first of each pair alternating: (ref's times, other's times)."""
    timed(ref)
    timed(other)
    t_ref, t_other = [], []
    for rep in range(reps):
        if rep % 2:
            t_other.append(timed(other))
            t_ref.append(timed(ref))
        else:
            t_ref.append(timed(ref))
            t_other.append(timed(other))
    return t_ref, t_other


def measure(model, nested, config, what, ref, other, n: int, reps: int) -> dict:
    """One row: ``what`` (eval, eval_pdf or sample) with ``config`` against the normal map, timed
    on the ``n`` queries of ``ref``/``other`` and counted on their small twins (the ``_ops`` keys)."""
    t_ref, t_other = interleaved(ref[what], other[what], reps)
    ratios = [b / a for a, b in zip(t_ref, t_other)]
    ops = (op_count(ref[what + "_ops"]), op_count(other[what + "_ops"]))
    return {"model": model, "nested": nested, "config": config, "call": what,
            "ref_ops": ops[0], "ops": ops[1], "ops_ratio": ops[1] / max(ops[0], 1),
            "ratio_q1": float(np.quantile(ratios, 0.25)), "ratio_q3": float(np.quantile(ratios, 0.75)),
            "ref_ns_per_query": 1e9 * statistics.median(t_ref) / n,
            "ns_per_query": 1e9 * statistics.median(t_other) / n,
            "ratio": statistics.median(ratios)}


def summarize(rows: list, models) -> dict:
    """Per model and option: the max and geometric mean of the time and operation ratios."""
    summary = {}
    for model in models:
        for config in CONFIGS:
            r = [x["ratio"] for x in rows if x["model"] == model and x["config"] == config]
            o = [x["ops_ratio"] for x in rows if x["model"] == model and x["config"] == config]
            summary[f"{model}/{config}"] = {"max": max(r), "geomean": float(np.exp(np.mean(np.log(r)))),
                                            "ops_max": max(o), "ops_geomean": float(np.exp(np.mean(np.log(o))))}
    return summary


def markdown(out: dict) -> str:
    """normal_sources.md from the results ``out``."""
    md = ["# Cost per query of the other normal sources", "",
          f"`{out['command']}`: {out['queries']} queries, median of {out['reps']} interleaved pairs; ratio = "
          "time with the option / time of the same model on the normal map (eval, eval_pdf, sample; "
          "diffuse and roughplastic). Acceptance: ≤ 1.10. CPU time of the process with "
          + ("the kernels on the calling thread (exact clock)" if out["threads"] == 0 else
             f"{out['threads']} worker threads (clock of the other threads quantised to the scheduler tick)")
          + ".", "",
          "*ops*: operations in the JIT kernels of one call (Dr.Jit's kernel history), the same ratio "
          "without timing noise.", "",
          "| model | config | time ratio geomean | time ratio max | ops ratio geomean | ops ratio max |",
          "|---|---|---|---|---|---|"]
    for k, v in out["summary"].items():
        m, c = k.split("/")
        md.append(f"| {m} | {c} | {v['geomean']:.3f} | {v['max']:.3f} | {v['ops_geomean']:.3f} | {v['ops_max']:.3f} |")
    md += ["", "| model | nested | config | call | ns/query | normal map ns/query | ratio (IQR) | ops | normal map ops |",
           "|---|---|---|---|---|---|---|---|---|"]
    for x in out["rows"]:
        md.append(f"| {x['model']} | {x['nested']} | {x['config']} | {x['call']} | {x['ns_per_query']:.0f} | "
                  f"{x['ref_ns_per_query']:.0f} | {x['ratio']:.3f} ({x['ratio_q1']:.2f}–{x['ratio_q3']:.2f}) | "
                  f"{x['ops']} | {x['ref_ops']} |")
    return "\n".join(md) + "\n"


def bsdf_calls(model, nested, config, normalmap, heightmap, q, q_ops) -> dict:
    """The plugin's eval, eval_pdf and sample on the timed queries ``q``, and as ``NAME_ops`` on
    the small set ``q_ops`` whose kernels are counted."""
    bsdf = plugin(model, nested, config, normalmap, heightmap)
    return {**calls(bsdf, q), **{f"{k}_ops": v for k, v in calls(bsdf, q_ops).items()}}


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--queries", type=int, default=20, help="log2 of the query count (default 20)")
    ap.add_argument("--reps", type=int, default=9)
    ap.add_argument("--models", default=",".join(MODELS))
    ap.add_argument("--out", type=Path, default=HERE.parent / "out" / "benchmarks")
    ap.add_argument("--threads", type=int, default=0,
                    help="Dr.Jit worker threads (0, the default: kernels on this thread, exact CPU clock)")
    args = ap.parse_args(argv)
    mi.set_variant("llvm_ad_rgb")
    dr.set_thread_count(args.threads)
    mfnormal.register()
    normalmap, heightmap = textures()
    q = queries(1 << args.queries)
    q_ops = queries(1 << 10, seed=12)
    rows = []
    for model in args.models.split(","):
        for nested in NESTED:
            ref = bsdf_calls(model, nested, "normalmap", normalmap, heightmap, q, q_ops)
            for config in CONFIGS:
                other = bsdf_calls(model, nested, config, normalmap, heightmap, q, q_ops)
                for what in ("eval", "eval_pdf", "sample"):
                    rows.append(measure(model, nested, config, what, ref, other, 1 << args.queries, args.reps))
                    r = rows[-1]
                    print(f"{model:12s} {nested:12s} {config:20s} {what:8s} ratio {r['ratio']:.3f} ops "
                          f"{r['ops']}/{r['ref_ops']} ({r['ns_per_query']:.0f} vs {r['ref_ns_per_query']:.0f} "
                          "ns/query)", flush=True)
    out = {"queries": 1 << args.queries, "reps": args.reps, "threads": args.threads, "rows": rows,
           "command": "benchmarks/normal_sources.py " + " ".join(sys.argv[1:] if argv is None else argv)}
    out["summary"] = summarize(rows, args.models.split(","))
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "normal_sources.json").write_text(json.dumps(out, indent=1))
    (args.out / "normal_sources.md").write_text(markdown(out))
    print(f"wrote {args.out / 'normal_sources'}.{{json,md}}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
