#!/usr/bin/env python
r"""Where a cell's per-sample noise comes from: the BSDF-sample and NEE halves of the one-sample
MIS estimator that Mitsuba's ``path``/``direct`` integrators use (balance heuristic), on one
bounce from the camera of benchmarks/run.py's ``plane`` scene, or its ``control`` (``--scene``),
without its sun disc by default.

    python benchmarks/noise_anatomy.py [--nested roughplastic] [--methods builtin,faithful,analytic]
                                       [--passes 64] [--full-sky] [--scene plane|control]

Per pixel and pass: one camera ray (random position in the pixel), one emitter sample (NEE) and
one BSDF sample. A = the BSDF sample's MIS-weighted radiance, B = the NEE's; A1 = the BSDF sample
unweighted (BSDF sampling alone), B1 = the NEE unweighted (emitter sampling alone). Printed: the
mean over the plane's pixels of Var/(ref² + 0.01) (the benchmark's relMSE per sample, luminance,
ref = the pixel's mean over the passes), Var(A + B) split into Var(A) + Var(B) + 2 Cov, the share
of the integral that NEE carries, and the BSDF samples by lobe type (their share of the samples,
of the pixel's value, and of E[A²]), and MIS and BSDF sampling alone on each half of the image
(on control, ω_i hits p first on the left, the tangent facet first on the right).

Measured (issue 18, plane / roughplastic, sunless, 64 passes; docs/faithful.md): the built-in's
MIS costs 12 % over its BSDF sampling alone (0.166 against 0.148), the faithful model's 37 %
(0.226 against 0.165); faithful's BSDF sampling alone is 1.11× the built-in's (1.19× before its
fill share followed the fill's albedo), its emitter sampling alone 2.8×: its glossy samples carry
0.54 of the value against the built-in's 0.40 (the texels the camera does not see show their
neighbours' grazing reflection of the sky). The analytic model: BSDF sampling alone 1.38×, NEE
alone 0.98×, MIS 1.23×.

Issue 25 (analytic, roughplastic, sunless, 256 passes): MIS 1.242× → 1.219× on plane and
1.524× → 1.482× on control with the exit split by energy (docs/model.md §3.2). On control the
excess splits by the side of the view. Where ω_i hits p first (left half) BSDF sampling alone is
2.0× the built-in's; at pixel (30, 100) (2¹⁷ samples) the variance an exact sampler of f would
have, Var_f(L)/E_f(L)², is 2.5× the built-in's (0.099 against 0.039: the masked part of each
lobe leaves mirrored, toward other sky), and the weights vary little more than the built-in's
(E[w²]/E[w]² 1.18 against 1.12). Where ω_i hits the tangent facet first (right half) it is
1.15×; the weight is the nested weight times G1(d, p), the dropped third bounce, which a sampler
of the nested BSDF cannot see (E[w²]/E[w]² 1.28 against 1.12 at pixel (160, 100)).
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import run as R  # noqa: E402


def lum(s) -> np.ndarray:
    return np.array(s[0]) * 0.2126 + np.array(s[1]) * 0.7152 + np.array(s[2]) * 0.0722


def one_pass(scene, seed: int, width: int, height: int) -> dict:
    """A, B, A1, B1 (luminance per pixel) and the BSDF samples' types, for one pass."""
    mi, dr = R.mi, R.dr
    n = width * height
    idx = dr.arange(mi.UInt32, n)
    sampler = mi.load_dict({"type": "independent"})
    sampler.seed(seed, n)
    pos = mi.Point2f(mi.Float(idx % width), mi.Float(idx // width)) + sampler.next_2d()
    ray, _ = scene.sensors()[0].sample_ray(0.0, 0.5, pos / mi.ScalarVector2f(width, height), mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    valid = si.is_valid()
    bsdf, ctx = si.bsdf(ray), mi.BSDFContext()
    ds, em_w = scene.sample_emitter_direction(si, sampler.next_2d(), True, valid)
    f, p_b = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), valid)
    b1 = f * em_w
    bs, w = bsdf.sample(ctx, si, sampler.next_1d(), sampler.next_2d(), valid)
    si2 = scene.ray_intersect(si.spawn_ray(si.to_world(bs.wo)), valid)
    escaped = valid & ~si2.is_valid()
    radiance = dr.select(escaped, scene.environment().eval(si2, escaped), 0.0)
    p_l = scene.pdf_emitter_direction(si, mi.DirectionSample3f(scene, si2, si), escaped)
    a1 = w * radiance
    out = {"A": a1 * bs.pdf / (bs.pdf + p_l), "B": b1 * ds.pdf / (ds.pdf + p_b), "A1": a1, "B1": b1}
    dr.eval(*out.values())
    out = {k: np.nan_to_num(lum(v)) for k, v in out.items()}
    out["type"], out["valid"] = np.array(bs.sampled_type), np.array(valid)
    return out


def anatomy(method: str, nested: str, assets: dict, passes: int, sunless: bool, width=192, height=144,
            scene_name: str = "plane"):
    d = R.scene_dict(scene_name, assets, method, nested, width, height, 1)
    if sunless:
        d = R.with_envmap(d, assets["sunless_envmap"])
    scene = R.mi.load_dict(d)
    runs = [one_pass(scene, 1000 + p, width, height) for p in range(passes)]
    x = {k: np.array([r[k] for r in runs]) for k in ("A", "B", "A1", "B1", "type")}
    ref = x["A"].mean(0) + x["B"].mean(0)
    den, mask = ref ** 2 + 0.01, runs[0]["valid"] & (ref > 0)

    def rel(v):
        return float((v / den)[mask].mean())
    cov = ((x["A"] - x["A"].mean(0)) * (x["B"] - x["B"].mean(0))).mean(0)
    print(f"{method:9s} ref {ref[mask].mean():.4f} | MIS A+B {rel((x['A'] + x['B']).var(0)):.4f} = "
          f"A {rel(x['A'].var(0)):.4f} + B {rel(x['B'].var(0)):.4f} + 2cov {2 * rel(cov):.4f} | BSDF alone "
          f"{rel(x['A1'].var(0)):.4f}, NEE alone {rel(x['B1'].var(0)):.4f} | NEE's share of the integral "
          f"{float((x['B'].mean(0) / np.maximum(ref, 1e-9))[mask].mean()):.3f}", flush=True)
    # Left and right half of the image: on control, ω_i hits p first on the left, the tangent facet on the right.
    left = (np.arange(width * height) % width) < width // 2
    halves = [f"{side}: MIS {float(((x['A'] + x['B']).var(0) / den)[mask & m].mean()):.4f}, BSDF alone "
              f"{float((x['A1'].var(0) / den)[mask & m].mean()):.4f}" for side, m in (("left", left), ("right", ~left))]
    print("   by half of the image, " + "; ".join(halves))
    for flag, name in ((R.mi.BSDFFlags.DiffuseReflection, "diffuse"), (R.mi.BSDFFlags.GlossyReflection, "glossy")):
        sel = (x["type"] & int(flag)) != 0
        print(f"   {name:7s} BSDF samples: {sel[:, mask].mean():.3f} of them, "
              f"{float((np.where(sel, x['A'], 0).mean(0) / np.maximum(ref, 1e-9))[mask].mean()):.3f} of the value "
              f"(MIS-weighted), E[A²] {rel(np.where(sel, x['A'] ** 2, 0).mean(0)):.4f}, "
              f"E[A1²] {rel(np.where(sel, x['A1'] ** 2, 0).mean(0)):.4f}")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--nested", default="roughplastic", choices=sorted(R.NESTED))
    ap.add_argument("--methods", default="builtin,faithful,analytic")
    ap.add_argument("--passes", type=int, default=64)
    ap.add_argument("--full-sky", action="store_true", help="keep the sun disc")
    ap.add_argument("--scene", default="plane", choices=("plane", "control"),
                    help="run.py's plane (a bump map) or control (a constant 40° map)")
    args = ap.parse_args(argv)
    R.import_mitsuba()
    with R.temporary_assets([args.scene], "mfnormal_anatomy_") as assets:
        for m in args.methods.split(","):
            anatomy(m, args.nested, assets, args.passes, not args.full_sky, scene_name=args.scene)
    return 0


if __name__ == "__main__":
    sys.exit(main())
