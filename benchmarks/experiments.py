r"""Measurements behind the optimisation suggestions of RESULTS.md, on the plugin as it is.

    python -m benchmarks.experiments [--queries 20] [--out benchmarks]

Each experiment measures the BSDF on the queries of ``run.py``'s metric 4 or on its
scenes, through the plugin's own parameters and the nested BSDFs of ``probes.py``
(nothing in the package is patched):

- ``ops``: Dr.Jit operations in the BSDF's sample / eval kernels, as is and with
  the nested BSDF replaced by the closed-form stub;
- ``cap``: ``max_bounces`` 1024 (default) / 16 / 8 / 4: throughput and the
  energy the cap loses (mean sample weight against the uncapped walk's);
- ``evalnoise``: the relative standard deviation of one stochastic ``eval``
  of the walks (their NEE estimate) at directions they sample themselves;
- ``mispdf``: the walks' MIS pdf against the histogram density of the
  directions their ``sample`` returns;
- ``control``: scene (c)'s relMSE with its wave normal map against constant
  normal maps (which separates estimator noise from sub-pixel image detail).

Writes ``experiments.json`` and ``experiments.md`` (whose *Retired experiments*
section, the numbers of what-if variants of the model code that were measured once
and whose code is gone, is kept as it is).
"""

from __future__ import annotations

import argparse
import json
import os
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
_cache = tempfile.mkdtemp(prefix="mfnormal_exp_drjit_")
os.environ["DRJIT_CACHE_DIR"] = _cache          # cold kernel cache for the compile timings

import numpy as np  # noqa: E402

from benchmarks import run as bench  # noqa: E402

mfnormal, mi, dr = bench.import_mitsuba()


def log(msg):
    print(msg, flush=True)


# -- Measurements --------------------------------------------------------------

class Bench:
    def __init__(self, n, reps):
        self.n, self.reps = n, reps
        self.texture = bench.random_normalmap_texture()
        self.ctx = mi.BSDFContext()
        self.si, self.wo, self.s1, self.s2 = bench.make_queries(n)

    def bsdf(self, method, nested, probe=None, **params):
        return bench.make_bsdf(method, nested, self.texture, probe, **params)

    def qps(self, bsdf):
        ws, _ = bench.time_queries(lambda: bsdf.sample(self.ctx, self.si, self.s1, self.s2), self.reps)
        we, _ = bench.time_queries(lambda: bsdf.eval(self.ctx, self.si, self.wo), self.reps)
        return {"sample_mqps": self.n / ws / 1e6, "eval_mqps": self.n / we / 1e6}

    def sample_weights(self, bsdf):
        bs, w = bsdf.sample(self.ctx, self.si, self.s1, self.s2)
        dr.eval(bs, w)
        return np.array(w, dtype=np.float64), np.array(bs.wo, dtype=np.float64)


def kernel_ops(fn) -> int:
    """Dr.Jit operations in the largest kernel that ``fn()`` launches."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    dr.eval(fn())
    dr.sync_thread()
    ops = max((h.get("operation_count") or 0 for h in dr.kernel_history()), default=0)
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    return ops


def exp_ops(b: Bench) -> list:
    """Operations in the BSDF's sample / eval kernels, with the nested BSDF and with the stub."""
    def ops(bsdf):
        return (kernel_ops(lambda: bsdf.sample(b.ctx, b.si, b.s1, b.s2)),
                kernel_ops(lambda: bsdf.eval(b.ctx, b.si, b.wo)))

    rows = []
    for nested in ("diffuse", "ggx_0.3"):
        for method in bench.METHOD_KEYS:
            so, eo = ops(b.bsdf(method, nested))
            # (The built-in keeps its nested BSDF: the stub times the microfacet models' own logic.)
            so_stub, eo_stub = ops(b.bsdf(method, nested, probe=None if method == "builtin" else "stub"))
            rows.append({"nested": nested, "method": method, "sample_ops": so, "eval_ops": eo,
                         "sample_ops_stub": so_stub, "eval_ops_stub": eo_stub})
            log(f"  ops   {nested:8s} {method:22s} sample {so} (stub {so_stub}), eval {eo} (stub {eo_stub})")
    return rows


def exp_cap(b: Bench) -> list:
    rows = []
    for nested in ("diffuse", "ggx_0.3"):
        for method in ("separable_same", "nonseparable_specular"):
            ref = None
            for cap in (1024, 16, 8, 4):
                bsdf = b.bsdf(method, nested, max_bounces=cap)
                q = b.qps(bsdf)
                w, _ = b.sample_weights(bsdf)
                albedo = float(w.mean())
                ref = albedo if ref is None else ref
                row = {"nested": nested, "method": method, "max_bounces": cap, **q, "albedo": albedo,
                       "energy_lost": 1.0 - albedo / ref}
                rows.append(row)
                log(f"  cap   {nested:8s} {method:22s} {cap:5d}: sample {q['sample_mqps']:.2f} eval "
                    f"{q['eval_mqps']:.2f} Mq/s, energy lost {100 * row['energy_lost']:.3f} %")
    return rows


def _constant_normal(theta_deg, phi_deg=0.0):
    t, f = np.radians(theta_deg), np.radians(phi_deg)
    n = np.array([[[np.sin(t) * np.cos(f), np.sin(t) * np.sin(f), np.cos(t)]]], dtype=np.float32)
    return mi.load_dict({"type": "bitmap", "bitmap": mi.Bitmap(n * 0.5 + 0.5), "raw": True,
                         "filter_type": "nearest"})


def _si(n, wi, p=None):
    """Shading points with the flat base frame, direction wi (n x 3 numpy), random p if given."""
    F = mi.Float
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    zero, one = dr.zeros(F, n), dr.ones(F, n)
    si.t = one
    si.n = mi.Normal3f(zero, zero, one)
    si.sh_frame = mi.Frame3f(mi.Vector3f(one, zero, zero), mi.Vector3f(zero, one, zero), mi.Vector3f(zero, zero, one))
    si.dp_du, si.dp_dv = mi.Vector3f(one, zero, zero), mi.Vector3f(zero, one, zero)
    si.uv = mi.Point2f(F(np.full(n, 0.5, np.float32)), F(np.full(n, 0.5, np.float32)))
    si.wi = mi.Vector3f(*(F(np.ascontiguousarray(wi[:, i], np.float32)) for i in range(3)))
    if p is not None:
        si.p = mi.Point3f(*(F(np.ascontiguousarray(p[:, i], np.float32)) for i in range(3)))
    return si


def _dir(theta_deg, phi_deg):
    t, f = np.radians(theta_deg), np.radians(phi_deg)
    return np.array([np.sin(t) * np.cos(f), np.sin(t) * np.sin(f), np.cos(t)])


def _vec(a):
    """A Dr.Jit 3-vector from an (n, 3) numpy array."""
    return mi.Vector3f(*(mi.Float(np.ascontiguousarray(a[:, i], np.float32)) for i in range(3)))


def _sampled_directions(bsdf, wi, n, rng):
    """The directions of ``bsdf.sample`` from ω_i = ``wi`` (n samples) that have a pdf > 0."""
    u = [mi.Float(rng.uniform(0, 1, n).astype(np.float32)) for _ in range(3)]
    bs, _ = bsdf.sample(mi.BSDFContext(), _si(n, np.tile(wi, (n, 1))), u[0], mi.Point2f(u[1], u[2]))
    return np.array(bs.wo, dtype=np.float64).T[np.array(bs.pdf) > 0]


CONFIGS = ((50.0, 30.0, 180.0), (50.0, 70.0, 180.0), (70.0, 60.0, 0.0))   # (θ_p, θ_i, φ_i)


def exp_eval_noise(b: Bench, m: int = 1024, k: int = 64) -> list:
    """Relative std of one stochastic eval (walk NEE) at directions the method samples itself."""
    rng = np.random.default_rng(5)
    ctx = mi.BSDFContext()
    rows = []
    for nested in ("ggx_0.05", "ggx_0.3", "diffuse"):
        for method in bench.METHOD_KEYS[1:]:
            rel = []
            for theta_p, theta_i, phi_i in CONFIGS:
                tex = _constant_normal(theta_p)
                bsdf = bench.make_bsdf(method, nested, tex)
                wo = _sampled_directions(bsdf, _dir(theta_i, phi_i), k, rng)
                if len(wo) == 0:
                    continue
                q = len(wo) * m
                wo_r = np.repeat(wo, m, axis=0)
                si = _si(q, np.tile(_dir(theta_i, phi_i), (q, 1)), rng.uniform(0, 1, (q, 3)))
                f = np.array(bsdf.eval(ctx, si, _vec(wo_r)), dtype=np.float64)
                f = f.mean(axis=0).reshape(len(wo), m)
                mu, sd = f.mean(axis=1), f.std(axis=1)
                rel += list(sd[mu > 0] / mu[mu > 0])
            rel = np.array(rel)
            row = {"nested": nested, "method": method, "rel_std_median": float(np.median(rel)),
                   "rel_std_p90": float(np.percentile(rel, 90))}
            rows.append(row)
            log(f"  evalnoise {nested:8s} {method:22s} rel. std of one eval: median {row['rel_std_median']:.2f}, "
                f"p90 {row['rel_std_p90']:.2f}")
    return rows


def exp_mis_pdf(b: Bench, n: int = 1 << 21, bins=(32, 64)) -> list:
    """The MIS pdf against the histogram density of the directions ``sample`` returns."""
    rng = np.random.default_rng(9)
    ctx = mi.BSDFContext()
    rows = []
    nu, nphi = bins
    d_omega = (1.0 / nu) * (2 * np.pi / nphi)
    for nested in ("ggx_0.05", "ggx_0.3"):
        for method in bench.METHOD_KEYS[2:]:
            ratios = []
            for theta_p, theta_i, phi_i in CONFIGS:
                bsdf = bench.make_bsdf(method, nested, _constant_normal(theta_p))
                wo = _sampled_directions(bsdf, _dir(theta_i, phi_i), n, rng)
                iu = np.clip((wo[:, 2] * nu).astype(int), 0, nu - 1)
                ip = np.clip((np.mod(np.arctan2(wo[:, 1], wo[:, 0]), 2 * np.pi) / (2 * np.pi) * nphi).astype(int), 0, nphi - 1)
                hist = np.bincount(iu * nphi + ip, minlength=nu * nphi) / (n * d_omega)
                # The MIS pdf averaged over each bin (16 jittered points), like the histogram.
                jit = 16
                uu = (np.repeat(np.arange(nu * nphi) // nphi, jit) + rng.uniform(0, 1, nu * nphi * jit)) / nu
                pp = (np.repeat(np.arange(nu * nphi) % nphi, jit) + rng.uniform(0, 1, nu * nphi * jit)) / nphi * 2 * np.pi
                rr = np.sqrt(np.maximum(1 - uu * uu, 0))
                dirs = np.stack([rr * np.cos(pp), rr * np.sin(pp), uu], -1)
                m = len(dirs)
                pdf = np.array(bsdf.pdf(ctx, _si(m, np.tile(_dir(theta_i, phi_i), (m, 1))), _vec(dirs)),
                               dtype=np.float64)
                pdf = pdf.reshape(-1, jit).mean(axis=1)
                mass = hist * d_omega
                order = np.argsort(-hist)
                top = order[: np.searchsorted(np.cumsum(mass[order]), 0.9 * mass.sum()) + 1]
                r = pdf[top] / np.maximum(hist[top], 1e-30)
                ratios.append((r, mass[top]))
            r = np.concatenate([x[0] for x in ratios])
            wts = np.concatenate([x[1] for x in ratios])
            o = np.argsort(r)
            cw = np.cumsum(wts[o]) / wts.sum()
            q = lambda p: float(r[o][np.searchsorted(cw, p)])  # noqa: E731
            row = {"nested": nested, "method": method, "ratio_p10": q(0.1), "ratio_median": q(0.5),
                   "ratio_p90": q(0.9)}
            rows.append(row)
            log(f"  mispdf {nested:8s} {method:22s} mis_pdf / sampling density over 90 % of the mass: "
                f"p10 {row['ratio_p10']:.2f}, median {row['ratio_median']:.2f}, p90 {row['ratio_p90']:.2f}")
    return rows


def exp_control(b: Bench, assets, root: Path) -> list:
    """relMSE of scene (c) with its wave normal map against constant normal maps: noise of
    the estimator (constant map) versus sub-pixel detail of the image (wave map)."""
    from mfnormal.report.metrics import rel_se
    W, H, spp, ref_passes = 192, 144, 16, 8
    rows = []
    for label, normal in (("waves", None), ("constant 40° away", (40, 90)), ("constant 40° toward", (40, -90)),
                          ("constant 40° across", (40, 0))):
        a = dict(assets)
        if normal:
            path = bench.write_constant_normalmap(root / f"control_{normal[1]}.png", *normal)
            a["plane"] = dict(assets["plane"], normalmap=str(path))
        for nested in ("ggx_0.05", "roughplastic"):
            for method in ("builtin", "analytic", "nonseparable_specular", "nonseparable_same"):
                scene = bench.load_scene("plane", a, method, nested, W, H, spp)
                ref = sum(bench.to_numpy(bench.timed_render(scene, 32, 10_000 + i)[1]) for i in range(ref_passes))
                ref /= ref_passes
                x = bench.to_numpy(bench.timed_render(scene, spp, 20_000)[1])
                e = rel_se(x, ref).mean(axis=-1).ravel()
                top = np.sort(e)[::-1][: max(1, len(e) // 1000)].sum() / max(e.sum(), 1e-30)
                rows.append({"map": label, "nested": nested, "method": method, "relmse": float(e.mean()),
                             "ref_mean": float(ref.mean()), "top_0.1%_share": float(top)})
                log(f"  control {label:20s} {nested:12s} {method:22s} relMSE {e.mean():.4f} mean {ref.mean():.3f} "
                    f"top-0.1 % share {top:.2f}")
    for r in rows:
        base = next(x for x in rows if x["map"] == r["map"] and x["nested"] == r["nested"] and x["method"] == "builtin")
        r["relmse_ratio"] = r["relmse"] / base["relmse"]
    return rows


RETIRED = "## Retired experiments"


def retired_section(path: Path) -> str:
    """The *Retired experiments* section of an existing experiments.md (kept as it is)."""
    text = path.read_text() if path.is_file() else ""
    return text[text.index(RETIRED):] if RETIRED in text else ""


def markdown(res, retired="") -> str:
    L = ["# Optimisation experiments", "",
         f"Machine: {res['machine']['cpu']}, {res['machine']['cores']} cores, load "
         f"{res['machine']['loadavg_start'][0]:.1f}; {res['queries']} queries; `{res['command']}`", ""]
    if res.get("remeasured"):
        L += ["Re-measured later (the other sections are from the run above):", ""]
        L += [f"- {name}: {stamp}" for name, stamp in res["remeasured"].items()]
        L += [""]
    if res.get("ops"):
        L += _section("ops: Dr.Jit operations in the BSDF kernels (compile cost scales with these)",
                      " ".join(["`stub`: the nested BSDF replaced by a closed-form Lambertian (probes.py).",
                                *filter(None, [res.get("section_notes", {}).get("ops")])]),
                      ["nested", "method", "sample ops (stub)", "eval ops (stub)"],
                      [(r["nested"], r["method"], f"{r['sample_ops']} ({r['sample_ops_stub']})",
                        f"{r['eval_ops']} ({r['eval_ops_stub']})") for r in res["ops"]])
    L += _section("cap: max_bounces", None,
                  ["nested", "method", "max_bounces", "sample Mq/s", "eval Mq/s", "energy lost"],
                  [(r["nested"], r["method"], r["max_bounces"], f"{r['sample_mqps']:.2f}", f"{r['eval_mqps']:.2f}",
                    f"{100 * r['energy_lost']:.3f} %") for r in res["cap"]])
    if res.get("control"):
        L += _section("control: scene (c) with its wave map vs constant normal maps (16 spp, equal spp)", None,
                      ["map", "nested", "method", "relMSE", "ratio to built-in", "reference mean",
                       "error share of top 0.1 % pixels"],
                      [(r["map"], r["nested"], r["method"], f"{r['relmse']:.4f}", f"{r['relmse_ratio']:.2f}",
                        f"{r['ref_mean']:.3f}", f"{r['top_0.1%_share']:.2f}") for r in res["control"]])
    if res.get("evalnoise"):
        L += _section("evalnoise: relative std of one `eval` (the walks' NEE estimate)",
                      "At directions each method samples itself; θ_p / θ_i / φ_i = "
                      + ", ".join(f"{a:.0f}°/{c:.0f}°/{d:.0f}°" for a, c, d in CONFIGS) + ".",
                      ["nested", "method", "median", "p90"],
                      [(r["nested"], r["method"], f"{r['rel_std_median']:.2f}", f"{r['rel_std_p90']:.2f}")
                       for r in res["evalnoise"]])
    if res.get("mispdf"):
        L += _section("mispdf: MIS pdf / actual density of `sample`'s directions",
                      "Histogram of 2^21 samples per configuration; quantiles weighted by sample mass over the "
                      "bins holding 90 % of it. < 1: the MIS pdf underestimates the sampler's density there "
                      "(BSDF samples get too little MIS weight, light samples too much). The plugin's pdf "
                      "includes the variance-aware boost (mis_boost_max, default 64): ratios above 1 where the "
                      "longer walks are likely and eval is noisy are intended; the density part alone is "
                      "checked in tests/test_walk.py (mis_boost_max = 1).",
                      ["nested", "method", "p10", "median", "p90"],
                      [(r["nested"], r["method"], f"{r['ratio_p10']:.2f}", f"{r['ratio_median']:.2f}",
                        f"{r['ratio_p90']:.2f}") for r in res["mispdf"]])
    return "\n".join(L).rstrip("\n") + "\n" + ("\n" + retired if retired else "")


def _section(title, intro, header, rows):
    """Markdown lines of a section: its title, an intro paragraph (if any) and a table."""
    lines = [f"## {title}", ""] + ([intro, ""] if intro else [])
    lines += ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    return lines + ["| " + " | ".join(map(str, row)) + " |" for row in rows] + [""]



def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--queries", type=int, default=20, help="log2 of the number of queries (default 20)")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--only", default="ops,cap,evalnoise,mispdf,control")
    ap.add_argument("--out", default=str(HERE.parent / "out" / "benchmarks"))
    ap.add_argument("--merge", action="store_true",
                    help="re-measure only the --only sections and keep the others from --out's experiments.json")
    args = ap.parse_args(argv)
    b = Bench(1 << args.queries, args.reps)
    command = " ".join(["python", "-m", "benchmarks.experiments", *(argv or sys.argv[1:])])
    res = {"command": command, "machine": bench.machine_info(), "queries": b.n}
    only = args.only.split(",")
    old = Path(args.out) / "experiments.json"
    if args.merge and old.is_file():
        res = json.loads(old.read_text())
        stamp = f"commit {bench.git_state().get('commit', '?')}, {time.strftime('%Y-%m-%d', time.gmtime())}, `{command}`"
        res.setdefault("remeasured", {}).update({name: stamp for name in only})
    root = Path(tempfile.mkdtemp(prefix="mfnormal_exp_assets_"))
    assets = bench.prepare_assets(root, ("demo", "plane"))
    for name, fn in (("ops", exp_ops), ("cap", exp_cap), ("evalnoise", exp_eval_noise), ("mispdf", exp_mis_pdf),
                     ("control", lambda b: exp_control(b, assets, root))):
        if name in only:
            res[name] = fn(b)
            res.get("section_notes", {}).pop(name, None)     # a stored table's caveat goes with it
        elif not args.merge:
            res[name] = []
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "experiments.json").write_text(json.dumps(res, indent=1, default=float))
    text = markdown(res, retired_section(out / "experiments.md"))
    (out / "experiments.md").write_text(text)
    log(text)


if __name__ == "__main__":
    main()
