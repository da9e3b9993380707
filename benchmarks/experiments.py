#!/usr/bin/env python
r"""What-if variants of the model code, behind the optimisation suggestions of RESULTS.md.

    python benchmarks/experiments.py [--queries 20] [--out benchmarks]

Each experiment swaps one piece of ``mfnormal.analytic`` / ``mfnormal.walk`` for a
variant *in this process only* (monkeypatching; the package's files are not
touched) and measures the BSDF on the queries of ``run.py``'s metric 4:

- ``ops``: Dr.Jit operations in the BSDF's sample / eval kernels, as is, with
  the nested calls stubbed out, and with the murmur3 random numbers below;
- ``rng``: the walks' TEA random numbers (6 rounds per number, 4 per hashed
  float) replaced by a murmur3-style integer mix, with the nested BSDF real and
  stubbed out (the model's own logic alone);
- ``cap``: ``max_bounces`` 1024 (default) / 16 / 8 / 4: throughput and the
  energy the cap loses (mean sample weight against the uncapped walk's);
- ``loop3``: ``analytic.eval_pdf`` with its three nested calls folded into one
  call site inside a 3-iteration symbolic loop: kernel size and LLVM compile
  time of a render's megakernel (cold cache), and the throughput;
- ``reuse``: ``analytic.sample`` reusing the nested sample's own (f, pdf) for
  the sampled path's term: 2 nested eval_pdf instead of 3, and the largest
  relative difference of the weights against the original;
- ``evalnoise``: the relative standard deviation of one stochastic ``eval``
  of the walks (their NEE estimate) at directions they sample themselves;
- ``mispdf``: the walks' MIS pdf against the histogram density of the
  directions their ``sample`` returns;
- ``control``: scene (c)'s relMSE with its wave normal map against constant
  normal maps (which separates estimator noise from sub-pixel image detail).

Writes ``experiments.json`` and prints a Markdown summary (``experiments.md``).
"""

from __future__ import annotations

import argparse
import contextlib
import json
import os
import sys
import tempfile
import time
from pathlib import Path

HERE = Path(__file__).resolve().parent
_cache = tempfile.mkdtemp(prefix="mfnormal_exp_drjit_")
os.environ["DRJIT_CACHE_DIR"] = _cache          # cold kernel cache for the compile timings
sys.path.insert(0, str(HERE))

import numpy as np  # noqa: E402

import run as bench  # noqa: E402

mfnormal, mi, dr = bench.import_mitsuba()
from mfnormal import analytic, rng, walk  # noqa: E402
from mfnormal.microsurface import negate  # noqa: E402
from mfnormal.rng import ONE_MINUS_EPS  # noqa: E402


def log(msg):
    print(msg, flush=True)


@contextlib.contextmanager
def patched(module, **attrs):
    old = {k: getattr(module, k) for k in attrs}
    for k, v in attrs.items():
        setattr(module, k, v)
    try:
        yield
    finally:
        for k, v in old.items():
            setattr(module, k, v)


# -- Variants ------------------------------------------------------------------

def _mix(h):
    """murmur3's 32-bit finaliser."""
    h = h ^ (h >> 16)
    h = h * 0x85EBCA6B
    h = h ^ (h >> 13)
    h = h * 0xC2B2AE35
    return h ^ (h >> 16)


def cheap_uniform(seed, counter):
    h = _mix(mi.UInt32(seed) ^ (mi.UInt32(counter) * 0x9E3779B9 + 0x7F4A7C15))
    return dr.minimum(mi.Float(h >> 8) * (1.0 / 16777216.0), ONE_MINUS_EPS)


def cheap_hash_floats(salt, *values):
    h = mi.UInt32(salt)
    for v in values:
        h = _mix(h ^ (dr.reinterpret_array(mi.UInt32, mi.Float32(v)) + 0x9E3779B9 + (h << 6) + (h >> 2)))
    return h


def _coefficients(sp, wi, wo):
    lp = sp.lambda_p(wi)
    wo_m, wi_m = sp.flip_t(wo), sp.flip_t(wi)
    g_o_p, g_o_t = sp.G1_p(wo), sp.G1_t(wo)
    c1 = lp * g_o_p
    c2 = dr.select(g_o_t > 0, lp * sp.one_minus_G1_p(wo_m), 0.0)
    c3 = dr.select(g_o_p > 0, sp.lambda_t(wi), 0.0)
    return wo_m, wi_m, (c1, c2, c3), (c1, c2 * g_o_t, c3 * g_o_p)


def _term_args(k, wi, wo, wi_m, wo_m, cp, cv):
    """(wi, wo, pdf coefficient, value coefficient) of term k ∈ {0, 1, 2}."""
    pick = lambda a: dr.select(k == 0, a[0], dr.select(k == 1, a[1], a[2]))  # noqa: E731
    return dr.select(k == 2, wi_m, wi), dr.select(k == 1, wo_m, wo), pick(cp), pick(cv)


def _finish(value, pdf, active, want_value, want_pdf):
    if want_value:
        value = dr.select(active & dr.all(dr.isfinite(value)), dr.maximum(value, 0.0), 0.0)
    if want_pdf:
        pdf = dr.select(active & dr.isfinite(pdf), dr.maximum(pdf, 0.0), 0.0)
    return value, pdf


def eval_pdf_loop3(sp, wo, active, want_value=True, want_pdf=True):
    """analytic.eval_pdf with one nested call site, run 3 times by a symbolic loop."""
    wi = sp.wi
    active = active & (wi.z > 0) & (wo.z > 0)
    wo_m, wi_m, cp, cv = _coefficients(sp, wi, wo)
    n = dr.width(wi)

    def body(k, value, pdf):
        a_wi, a_wo, c_p, c_v = _term_args(k, wi, wo, wi_m, wo_m, cp, cv)
        a = active & (c_p > 0)
        if want_value and want_pdf:
            f, p = sp.eval_pdf(sp.frame_p, a_wi, a_wo, a)
        elif want_value:
            f, p = sp.eval(sp.frame_p, a_wi, a_wo, a), mi.Float(0.0)
        else:
            f, p = mi.Spectrum(0.0), sp.pdf(sp.frame_p, a_wi, a_wo, a)
        return k + 1, value + f * c_v, pdf + p * c_p

    _, value, pdf = dr.while_loop((dr.zeros(mi.UInt32, n), dr.zeros(mi.Spectrum, n), dr.zeros(mi.Float, n)),
                                  lambda k, v, p: k < 3, body, label="analytic_terms")
    return _finish(value, pdf, active, want_value, want_pdf)


def sample_reuse(sp, sample1, sample2, active):
    """analytic.sample, with the sampled term's nested (f, pdf) taken from the sample."""
    wi = sp.wi
    active = active & (wi.z > 0)
    lp = sp.lambda_p(wi)
    on_p = sample1 < lp
    s1 = dr.select(on_p, sample1 / dr.maximum(lp, 1e-30), (sample1 - lp) / dr.maximum(1.0 - lp, 1e-30))
    s1 = dr.clip(s1, 0.0, ONE_MINUS_EPS)
    bs, w = sp.sample(sp.frame_p, dr.select(on_p, wi, sp.flip_t(wi)), s1, sample2, active)
    g_p = sp.G1_p(bs.wo)
    to_t = on_p & (rng.uniform(rng.hash_floats(0x6d666e31, sample1, sample2.x, sample2.y), 0) >= g_p)
    wo = dr.select(to_t, sp.flip_t(bs.wo), bs.wo)
    path = dr.select(to_t, sp.G1_t(wo), g_p)
    prob = dr.select(on_p, lp * dr.select(to_t, 1.0 - g_p, g_p), 1.0 - lp)
    active &= (bs.pdf > 0) & (path > 0) & (wo.z > 0) & dr.all(dr.isfinite(wo))
    delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    smooth = active & negate(delta)

    # The sampled term k_s and the two others, A < B.
    wo_m, wi_m, cp, cv = _coefficients(sp, wi, wo)
    k_s = dr.select(on_p, dr.select(to_t, mi.UInt32(1), mi.UInt32(0)), mi.UInt32(2))
    k_a = dr.select(k_s == 0, mi.UInt32(1), mi.UInt32(0))
    k_b = dr.select(k_s == 2, mi.UInt32(1), mi.UInt32(2))
    value, pdf = mi.Spectrum(0.0), mi.Float(0.0)
    for k in (k_a, k_b):
        a_wi, a_wo, c_p, c_v = _term_args(k, wi, wo, wi_m, wo_m, cp, cv)
        f, p = sp.eval_pdf(sp.frame_p, a_wi, a_wo, smooth & (c_p > 0))
        value += f * c_v
        pdf += p * c_p
    _, _, c_p, c_v = _term_args(k_s, wi, wo, wi_m, wo_m, cp, cv)
    own = smooth & (c_p > 0)
    value += dr.select(own, w * bs.pdf, 0.0) * c_v
    pdf += dr.select(own, bs.pdf, 0.0) * c_p
    value, pdf = _finish(value, pdf, smooth, True, True)

    weight = dr.select(delta, w * path, value / dr.select(pdf > 0, pdf, 1.0))
    bs.pdf = dr.select(delta, bs.pdf * prob, pdf)
    active &= (bs.pdf > 0) & dr.all(dr.isfinite(weight))
    bs.wo = dr.select(active, wo, mi.Vector3f(0.0, 0.0, 1.0))
    bs.pdf = dr.select(active, bs.pdf, 0.0)
    return bs, dr.select(active, dr.maximum(weight, 0.0), 0.0)


# -- Measurements --------------------------------------------------------------

class Bench:
    def __init__(self, n, reps):
        self.n, self.reps = n, reps
        self.texture = bench.random_normalmap_texture()
        self.ctx = mi.BSDFContext()
        self.si, self.wo, self.s1, self.s2 = bench.make_queries(n)

    def bsdf(self, method, nested, **extra):
        b = bench.make_bsdf(method, nested, self.texture)
        if extra:
            d = {"type": "normalmap_microfacet", "normalmap": self.texture,
                 "bsdf": dict(bench.NESTED[nested]), "model": bench.METHOD_BY_KEY[method][1], **extra}
            if bench.METHOD_BY_KEY[method][2]:
                d["tangent_facet"] = bench.METHOD_BY_KEY[method][2]
            b = mi.load_dict(d)
        return b

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
    """Operations in the BSDF's sample / eval kernels, with and without the nested calls."""
    rows = []
    for nested in ("diffuse", "ggx_0.3"):
        for method in bench.METHOD_KEYS:
            bsdf = b.bsdf(method, nested)

            def ops():
                return (kernel_ops(lambda: bsdf.sample(b.ctx, b.si, b.s1, b.s2)),
                        kernel_ops(lambda: bsdf.eval(b.ctx, b.si, b.wo)))
            so, eo = ops()
            with bench.stubbed_nested():
                so_stub, eo_stub = ops()
            with patched(walk, uniform=cheap_uniform, hash_floats=cheap_hash_floats), \
                    patched(rng, uniform=cheap_uniform, hash_floats=cheap_hash_floats):
                so_mix, eo_mix = ops()
            rows.append({"nested": nested, "method": method, "sample_ops": so, "eval_ops": eo,
                         "sample_ops_stub": so_stub, "eval_ops_stub": eo_stub,
                         "sample_ops_mix": so_mix, "eval_ops_mix": eo_mix})
            log(f"  ops   {nested:8s} {method:22s} sample {so} (stub {so_stub}, mix {so_mix}), "
                f"eval {eo} (stub {eo_stub}, mix {eo_mix})")
    return rows


def exp_rng(b: Bench) -> list:
    rows = []
    for nested in ("ggx_0.3", "diffuse"):
        for method in ("separable_same", "nonseparable_specular"):
            bsdf = b.bsdf(method, nested)
            for stub in (False, True):
                def ops():
                    return {"sample_ops": kernel_ops(lambda: bsdf.sample(b.ctx, b.si, b.s1, b.s2)),
                            "eval_ops": kernel_ops(lambda: bsdf.eval(b.ctx, b.si, b.wo))}
                with bench.stubbed_nested() if stub else contextlib.nullcontext():
                    base = {**b.qps(bsdf), **ops()}
                    with patched(walk, uniform=cheap_uniform, hash_floats=cheap_hash_floats):
                        cheap = {**b.qps(bsdf), **ops()}
                row = {"nested": nested, "method": method, "nested_stubbed": stub, "tea": base, "mix": cheap,
                       "sample_speedup": cheap["sample_mqps"] / base["sample_mqps"],
                       "eval_speedup": cheap["eval_mqps"] / base["eval_mqps"]}
                rows.append(row)
                log(f"  rng   {nested:8s} {method:22s} stub={stub!s:5s} sample ×{row['sample_speedup']:.2f} "
                    f"eval ×{row['eval_speedup']:.2f}; eval kernel ops {base['eval_ops']} → {cheap['eval_ops']}, "
                    f"sample {base['sample_ops']} → {cheap['sample_ops']}")
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


def _render_kernel(scene, spp=4):
    """(LLVM backend s, ops) of the largest kernel of a first render, and the warm time."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    bench.timed_render(scene, spp, 0)
    hist = [h for h in dr.kernel_history() if h.get("operation_count")]
    big = max(hist, key=lambda h: h["operation_count"])
    warm = bench.median([bench.timed_render(scene, spp, i + 1)[0] for i in range(3)])
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    return {"backend_s": (big.get("backend_time") or 0.0) / 1e3, "ops": big["operation_count"],
            "cache_hit": bool(big.get("cache_hit")), "warm_s": warm}


def exp_loop3(b: Bench, assets) -> list:
    rows = []
    for nested in ("ggx_0.3", "roughplastic"):
        bsdf = b.bsdf("analytic", nested)
        for variant in ("original", "loop3"):
            patch = patched(analytic, eval_pdf=eval_pdf_loop3) if variant == "loop3" else contextlib.nullcontext()
            with patch:
                scene = bench.load_scene("demo", assets, "analytic", nested, 96, 72, 4)
                k = _render_kernel(scene)
                q = b.qps(bsdf)
                q["bsdf_eval_ops"] = kernel_ops(lambda: bsdf.eval(b.ctx, b.si, b.wo))
                q["bsdf_sample_ops"] = kernel_ops(lambda: bsdf.sample(b.ctx, b.si, b.s1, b.s2))
            row = {"nested": nested, "variant": variant, **k, **q}
            rows.append(row)
            log(f"  loop3 {nested:12s} {variant:8s} megakernel {k['ops']} ops, LLVM {k['backend_s']:.2f} s "
                f"(cache hit {k['cache_hit']}), warm render {k['warm_s']:.3f} s, sample {q['sample_mqps']:.2f} "
                f"eval {q['eval_mqps']:.2f} Mq/s")
    return rows


def exp_reuse(b: Bench) -> list:
    rows = []
    for nested in ("ggx_0.05", "ggx_0.3", "roughplastic", "diffuse"):
        bsdf = b.bsdf("analytic", nested)
        w0, d0 = b.sample_weights(bsdf)
        q0 = b.qps(bsdf)
        with patched(analytic, sample=sample_reuse):
            w1, d1 = b.sample_weights(bsdf)
            q1 = b.qps(bsdf)
            with bench.instrumented(b.n) as (counts, sites, loops):
                out = bsdf.sample(b.ctx, b.si, b.s1, b.s2)
                dr.eval(out, sites)
                simd = float(np.array(sites).max())
        same_dir = np.abs(d0 - d1).max()
        rel = np.abs(w1 - w0) / np.maximum(np.abs(w0), 1e-3)
        row = {"nested": nested, "original": q0, "reuse": q1,
               "sample_speedup": q1["sample_mqps"] / q0["sample_mqps"], "nested_call_sites": simd,
               "max_dir_diff": float(same_dir), "weight_rel_diff_p99": float(np.percentile(rel, 99)),
               "weight_rel_diff_max": float(rel.max()), "mean_weight": [float(w0.mean()), float(w1.mean())]}
        rows.append(row)
        log(f"  reuse {nested:12s} sample ×{row['sample_speedup']:.2f} ({simd:.0f} nested call sites), weights: "
            f"p99 rel diff {row['weight_rel_diff_p99']:.2e}, mean {w0.mean():.5f} → {w1.mean():.5f}")
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
                wi = np.tile(_dir(theta_i, phi_i), (k, 1))
                bs, w = bsdf.sample(ctx, _si(k, wi), mi.Float(rng.uniform(0, 1, k).astype(np.float32)),
                                    mi.Point2f(*(mi.Float(rng.uniform(0, 1, k).astype(np.float32)) for _ in range(2))))
                wo = np.array(bs.wo, dtype=np.float64).T[np.array(bs.pdf) > 0]
                if len(wo) == 0:
                    continue
                q = len(wo) * m
                wo_r = np.repeat(wo, m, axis=0)
                si = _si(q, np.tile(_dir(theta_i, phi_i), (q, 1)), rng.uniform(0, 1, (q, 3)))
                f = np.array(bsdf.eval(ctx, si, mi.Vector3f(*(mi.Float(np.ascontiguousarray(wo_r[:, i], np.float32))
                                                             for i in range(3)))), dtype=np.float64)
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
                wi = np.tile(_dir(theta_i, phi_i), (n, 1))
                bs, w = bsdf.sample(ctx, _si(n, wi), mi.Float(rng.uniform(0, 1, n).astype(np.float32)),
                                    mi.Point2f(*(mi.Float(rng.uniform(0, 1, n).astype(np.float32)) for _ in range(2))))
                wo = np.array(bs.wo, dtype=np.float64).T
                ok = np.array(bs.pdf) > 0
                wo = wo[ok]
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
                pdf = np.array(bsdf.pdf(ctx, _si(m, np.tile(_dir(theta_i, phi_i), (m, 1))),
                                        mi.Vector3f(*(mi.Float(np.ascontiguousarray(dirs[:, i], np.float32))
                                                      for i in range(3)))), dtype=np.float64)
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
    from mfnormal import demo
    W, H, spp, ref_passes = 192, 144, 16, 8
    rows = []
    for label, normal in (("waves", None), ("constant 40° away", (40, 90)), ("constant 40° toward", (40, -90)),
                          ("constant 40° across", (40, 0))):
        a = dict(assets)
        if normal:
            t, f = np.radians(normal[0]), np.radians(normal[1])
            n = np.array([np.sin(t) * np.cos(f), np.sin(t) * np.sin(f), np.cos(t)], np.float32)
            path = root / f"control_{normal[1]}.png"
            mi.Bitmap(demo.encode_normalmap(np.tile(n, (4, 4, 1)))).write(str(path))
            a["plane"] = dict(assets["plane"], normalmap=str(path))
        for nested in ("ggx_0.05", "roughplastic"):
            for method in ("builtin", "analytic", "nonseparable_specular", "nonseparable_same"):
                scene = bench.load_scene("plane", a, method, nested, W, H, spp)
                ref = sum(bench.to_numpy(bench.timed_render(scene, 32, 10_000 + i)[1]) for i in range(ref_passes))
                ref /= ref_passes
                x = bench.to_numpy(bench.timed_render(scene, spp, 20_000)[1])
                e = ((x - ref) ** 2 / (ref ** 2 + bench.REL_MSE_EPS)).mean(axis=-1).ravel()
                top = np.sort(e)[::-1][: max(1, len(e) // 1000)].sum() / max(e.sum(), 1e-30)
                rows.append({"map": label, "nested": nested, "method": method, "relmse": float(e.mean()),
                             "ref_mean": float(ref.mean()), "top_0.1%_share": float(top)})
                log(f"  control {label:20s} {nested:12s} {method:22s} relMSE {e.mean():.4f} mean {ref.mean():.3f} "
                    f"top-0.1 % share {top:.2f}")
    for r in rows:
        base = next(x for x in rows if x["map"] == r["map"] and x["nested"] == r["nested"] and x["method"] == "builtin")
        r["relmse_ratio"] = r["relmse"] / base["relmse"]
    return rows


def markdown(res) -> str:
    L = ["# Optimisation experiments (what-if variants, monkeypatched)", "",
         f"Machine: {res['machine']['cpu']}, {res['machine']['cores']} cores, load "
         f"{res['machine']['loadavg_start'][0]:.1f}; {res['queries']} queries; `{res['command']}`", ""]
    if res.get("remeasured"):
        L += ["Re-measured later (the other sections are from the run above):", ""]
        L += [f"- {name}: {stamp}" for name, stamp in res["remeasured"].items()]
        L += [""]
    if res.get("ops"):
        L += ["## ops: Dr.Jit operations in the BSDF kernels (compile cost scales with these)", "",
              "`stub`: nested calls replaced by a closed-form Lambertian; `mix`: TEA random numbers "
              "replaced by a murmur3 mix.", "",
              "| nested | method | sample ops (stub, mix) | eval ops (stub, mix) |", "|---|---|---|---|"]
        L += [f"| {r['nested']} | {r['method']} | {r['sample_ops']} ({r['sample_ops_stub']}, {r['sample_ops_mix']}) | "
              f"{r['eval_ops']} ({r['eval_ops_stub']}, {r['eval_ops_mix']}) |" for r in res["ops"]]
        L += [""]
    L += ["## rng: TEA → murmur3 mix in the walk", "",
          "| nested | method | nested stubbed | sample speed-up | eval speed-up | sample kernel ops | eval kernel ops |",
          "|---|---|---|---|---|---|---|"]
    L += [f"| {r['nested']} | {r['method']} | {r['nested_stubbed']} | {r['sample_speedup']:.2f}× | "
          f"{r['eval_speedup']:.2f}× | {r['tea']['sample_ops']} → {r['mix']['sample_ops']} | "
          f"{r['tea']['eval_ops']} → {r['mix']['eval_ops']} |" for r in res["rng"]]
    L += ["", "## cap: max_bounces", "",
          "| nested | method | max_bounces | sample Mq/s | eval Mq/s | energy lost |", "|---|---|---|---|---|---|"]
    L += [f"| {r['nested']} | {r['method']} | {r['max_bounces']} | {r['sample_mqps']:.2f} | {r['eval_mqps']:.2f} | "
          f"{100 * r['energy_lost']:.3f} % |" for r in res["cap"]]
    L += ["", "## loop3: analytic.eval_pdf's 3 nested calls as one call site in a 3-iteration loop", "",
          "| nested | variant | demo megakernel ops | LLVM compile s | warm render s | BSDF sample / eval kernel ops | "
          "sample Mq/s | eval Mq/s |",
          "|---|---|---|---|---|---|---|---|"]
    L += [f"| {r['nested']} | {r['variant']} | {r['ops']} | {r['backend_s']:.2f} | {r['warm_s']:.3f} | "
          f"{r['bsdf_sample_ops']} / {r['bsdf_eval_ops']} | "
          f"{r['sample_mqps']:.2f} | {r['eval_mqps']:.2f} |" for r in res["loop3"]]
    L += ["", "## reuse: analytic.sample takes the sampled term's (f, pdf) from the nested sample", "",
          "| nested | sample speed-up | nested call sites | weight rel. diff p99 / max | mean weight orig → reuse |",
          "|---|---|---|---|---|"]
    L += [f"| {r['nested']} | {r['sample_speedup']:.2f}× | {r['nested_call_sites']:.0f} (orig 4) | "
          f"{r['weight_rel_diff_p99']:.1e} / {r['weight_rel_diff_max']:.1e} | "
          f"{r['mean_weight'][0]:.5f} → {r['mean_weight'][1]:.5f} |" for r in res["reuse"]]
    if res.get("control"):
        L += ["", "## control: scene (c) with its wave map vs constant normal maps (16 spp, equal spp)", "",
              "| map | nested | method | relMSE | ratio to built-in | reference mean | error share of top 0.1 % pixels |",
              "|---|---|---|---|---|---|---|"]
        L += [f"| {r['map']} | {r['nested']} | {r['method']} | {r['relmse']:.4f} | {r['relmse_ratio']:.2f} | "
              f"{r['ref_mean']:.3f} | {r['top_0.1%_share']:.2f} |" for r in res["control"]]
    if res.get("evalnoise"):
        L += ["", "## evalnoise: relative std of one `eval` (the walks' NEE estimate)", "",
              "At directions each method samples itself; θ_p / θ_i / φ_i = " +
              ", ".join(f"{a:.0f}°/{c:.0f}°/{d:.0f}°" for a, c, d in CONFIGS) + ".", "",
              "| nested | method | median | p90 |", "|---|---|---|---|"]
        L += [f"| {r['nested']} | {r['method']} | {r['rel_std_median']:.2f} | {r['rel_std_p90']:.2f} |"
              for r in res["evalnoise"]]
    if res.get("mispdf"):
        L += ["", "## mispdf: MIS pdf / actual density of `sample`'s directions", "",
              "Histogram of 2^21 samples per configuration; quantiles weighted by sample mass over the "
              "bins holding 90 % of it. < 1: the MIS pdf underestimates the sampler's density there "
              "(BSDF samples get too little MIS weight, light samples too much). The plugin's pdf "
              "includes the variance-aware boost (mis_boost_max, default 64): ratios above 1 where the "
              "longer walks are likely and eval is noisy are intended; the density part alone is "
              "checked in tests/test_walk.py (mis_boost_max = 1).", "",
              "| nested | method | p10 | median | p90 |", "|---|---|---|---|---|"]
        L += [f"| {r['nested']} | {r['method']} | {r['ratio_p10']:.2f} | {r['ratio_median']:.2f} | "
              f"{r['ratio_p90']:.2f} |" for r in res["mispdf"]]
    return "\n".join(L) + "\n"


def main(argv=None):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--queries", type=int, default=20, help="log2 of the number of queries (default 20)")
    ap.add_argument("--reps", type=int, default=5)
    ap.add_argument("--only", default="ops,rng,cap,loop3,reuse,evalnoise,mispdf,control")
    ap.add_argument("--out", default=str(HERE))
    ap.add_argument("--merge", action="store_true",
                    help="re-measure only the --only sections and keep the others from --out's experiments.json")
    args = ap.parse_args(argv)
    b = Bench(1 << args.queries, args.reps)
    command = " ".join(["python", "benchmarks/experiments.py", *(argv or sys.argv[1:])])
    res = {"command": command, "machine": bench.machine_info(), "queries": b.n}
    only = args.only.split(",")
    old = Path(args.out) / "experiments.json"
    if args.merge and old.is_file():
        res = json.loads(old.read_text())
        stamp = f"commit {bench.git_state().get('commit', '?')}, {time.strftime('%Y-%m-%d', time.gmtime())}, `{command}`"
        res.setdefault("remeasured", {}).update({name: stamp for name in only})
    root = Path(tempfile.mkdtemp(prefix="mfnormal_exp_assets_"))
    assets = bench.prepare_assets(root, ("demo", "plane"))
    for name, fn in (("ops", exp_ops), ("rng", exp_rng), ("cap", exp_cap), ("loop3", lambda b: exp_loop3(b, assets)),
                     ("reuse", exp_reuse), ("evalnoise", exp_eval_noise), ("mispdf", exp_mis_pdf),
                     ("control", lambda b: exp_control(b, assets, root))):
        if name in only:
            res[name] = fn(b)
        elif not args.merge:
            res[name] = []
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    (out / "experiments.json").write_text(json.dumps(res, indent=1, default=float))
    (out / "experiments.md").write_text(markdown(res))
    log(markdown(res))


if __name__ == "__main__":
    main()
