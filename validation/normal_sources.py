"""Every source of shading normals against true geometry.

    nice .venv/bin/python -m validation.normal_sources [--quick] [--out validation/results]
        [--spp 512] [--res 128] [--levels 1,2,3] [--grid validation/results/heightmap/true_geometry.json]

1. **Shadow terminator**: a smooth-shaded low-poly icosphere (80, 320, 1280 triangles) against
   Mitsuba's analytic ``sphere`` under a grazing sun (:mod:`validation.terminator`), diffuse and
   glossy: luminance error in the terminator band (true normal within 25° of the sun's horizon)
   and on the disc, and the share of near-black pixels, for plain interpolated normals,
   Mitsuba's ``normalmap`` with a flat map (its shadowing term), a Chiang-style term, ours
   (``normalmap_microfacet``, no map, ``macro_normal="geometric"``; every model), face normals,
   and the bound a BSDF can reach under the integrator's shadow rays (the "oracle").
2. **BSDF properties on a tilted triangle** (shading normal 5°/10°/20° off the triangle's):
   reciprocity f(a,b) = f(b,a) of eval/⟨ω_o, n_g⟩ and the white furnace (white Lambertian
   facets: energy reflected above the triangle, and the energy sent *below* it, "leak").
3. **Bump maps**: the summary of ``validation/true_geometry.py`` run on ``heightmap`` methods
   (``--grid``: its json), heightfields as dense displaced meshes against the plane with the
   same heights as a ``heightmap``: ours vs Mitsuba's ``bumpmap``, per view.
4. **Height map vs normal map of the same heights**: ω_p and the BSDF (faithful) at three
   resolutions: the difference shrinks as the derivative's discretisation error does.

Writes ``normal_sources.md``, ``normal_sources.json`` and ``normal_sources.png`` (the terminator
renders: a row per tessellation × material) to ``--out``; ``--quick`` writes
``normal_sources_quick.*`` (one tessellation, low spp: a smoke run, numbers meaningless).
"""

from __future__ import annotations

import argparse
import json
import math
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

import mfnormal  # noqa: E402  (first: selects a working libLLVM)

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

mi.set_variant("llvm_ad_rgb")
mfnormal.register()

from validation import heightfield as H  # noqa: E402
from validation import terminator as T  # noqa: E402
from mfnormal.files import atomic_write  # noqa: E402
from mfnormal.io.images import tonemap  # noqa: E402

TERMINATOR_METHODS = ("plain", "normalmap_flat", "chiang", "geometric", "geometric_analytic",
                      "geometric_separable", "geometric_nonseparable", "flat")
LABELS = {"plain": "interpolated normals", "normalmap_flat": "Mitsuba normalmap (flat map)",
          "chiang": "Chiang-style term", "geometric": "ours (faithful, default)",
          "geometric_analytic": "ours (analytic)", "geometric_separable": "ours (separable)",
          "geometric_nonseparable": "ours (nonseparable)", "flat": "face normals",
          "oracle": "bound (oracle)"}
T.METHODS.setdefault("geometric_separable", T._ours("separable"))


def log(msg):
    print(msg, flush=True)


# -- 1. Terminator ---------------------------------------------------------------------------------

def terminator(levels, materials, res, spp, sun_deg=70.0):
    out, images = {}, {}
    for level in levels:
        for material in materials:
            case = T.Case(level, material, sun_deg)
            log(f"terminator {case.name}")
            r = T.render_case(case, TERMINATOR_METHODS, res=res, spp=spp, log=log, with_oracle=True)
            out[case.name] = {"triangles": case.triangles, "material": material, "sun_deg": sun_deg,
                              "band_pixels": r["band_pixels"], "metrics": r["metrics"], "floor": r["floor"]}
            images[case.name] = r["images"]
    return out, images


# -- 2. BSDF properties on a tilted triangle --------------------------------------------------------

WHITE = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}
BSDF_METHODS = {
    "plain": lambda: WHITE,
    "normalmap_flat": lambda: T.METHODS["normalmap_flat"](WHITE),
    "chiang": lambda: T.METHODS["chiang"](WHITE),
    **{f"geometric_{m}": (lambda m=m: {"type": "normalmap_microfacet", "macro_normal": "geometric",
                                       "model": m, "bsdf": WHITE})
       for m in ("faithful", "analytic", "separable", "nonseparable")},
}


def _si(n, ng):
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    si.n = mi.Normal3f(*(float(x) for x in ng))
    si.dp_du, si.dp_dv = mi.Vector3f(1, 0, 0), mi.Vector3f(0, -1, 0)
    k = np.arange(n)
    si.p = mi.Point3f((k % 4096).astype(np.float32), (k // 4096).astype(np.float32), np.zeros(n, np.float32))
    return si


def _vec(a):
    a = np.asarray(a, np.float32)
    return mi.Vector3f(a[:, 0], a[:, 1], a[:, 2])


def _about(ng, d):
    """Local directions d (z up) turned into the frame of ng."""
    a = np.array([0.0, 1.0, 0.0])
    s = np.cross(a, ng)
    s /= np.linalg.norm(s)
    t = np.cross(ng, s)
    return d[:, :1] * s + d[:, 1:2] * t + d[:, 2:3] * ng


def bsdf_properties(tilts=(5.0, 10.0, 20.0), pairs=1 << 16, furnace_n=1 << 20, seed=0):
    """Reciprocity and white furnace of every method on a triangle whose normal n_g is ``tilt``
    off the shading normal (+z), toward +x."""
    import validation.terminator  # noqa: F401  (registers chiang_terminator)
    T.register()
    rng = np.random.default_rng(seed)
    out = {}
    for tilt in tilts:
        t = math.radians(tilt)
        ng = np.array([math.sin(t), 0.0, math.cos(t)])
        res = {}
        # Pairs uniform over the triangle's hemisphere.
        a = rng.normal(size=(pairs, 3))
        b = rng.normal(size=(pairs, 3))
        a /= np.linalg.norm(a, axis=1, keepdims=True)
        b /= np.linalg.norm(b, axis=1, keepdims=True)
        a *= np.sign(a @ ng)[:, None]
        b *= np.sign(b @ ng)[:, None]
        wo = rng.normal(size=(furnace_n, 3))
        wo /= np.linalg.norm(wo, axis=1, keepdims=True)
        for key, spec in BSDF_METHODS.items():
            bsdf = mi.load_dict(spec())
            ctx = mi.BSDFContext()
            si = _si(pairs, ng)
            si.wi = _vec(a)
            f_ab = np.array(bsdf.eval(ctx, si, _vec(b)))[0] / (b @ ng)
            si.wi = _vec(b)
            f_ba = np.array(bsdf.eval(ctx, si, _vec(a)))[0] / (a @ ng)
            big = np.maximum(f_ab, f_ba)
            live = big > 1e-6
            asym = np.abs(f_ab - f_ba)[live] / big[live]
            one_sided = float(np.mean((np.minimum(f_ab, f_ba)[live] <= 1e-7 * big[live])))
            stochastic = key in ("geometric_separable", "geometric_nonseparable")
            # Furnace: ω_i at θ_i about n_g, toward and away from the tilt; uniform ω_o on the sphere.
            albedo, leak = [], []
            for theta in (0.0, 45.0, 75.0, 85.0):
                for phi in (0.0, math.pi / 2, math.pi):
                    d = np.array([[math.sin(math.radians(theta)) * math.cos(phi),
                                   math.sin(math.radians(theta)) * math.sin(phi), math.cos(math.radians(theta))]])
                    wi = _about(ng, d)[0]
                    si = _si(furnace_n, ng)
                    si.wi = _vec(np.tile(wi, (furnace_n, 1)))
                    e = np.array(bsdf.eval(ctx, si, _vec(wo)))[0] * 4 * math.pi
                    up = (wo @ ng) > 0
                    albedo.append(float(np.mean(np.where(up, e, 0.0))))
                    leak.append(float(np.mean(np.where(up, 0.0, e))))
            res[key] = {"reciprocity_median": float(np.median(asym)) if asym.size else 0.0,
                        "reciprocity_p99": float(np.quantile(asym, 0.99)) if asym.size else 0.0,
                        "one_sided": one_sided, "stochastic_eval": stochastic,
                        "albedo_min": min(albedo), "albedo_max": max(albedo), "leak_max": max(leak)}
            r = res[key]
            log(f"  tilt {tilt:4.1f} {key:24s} asym median {r['reciprocity_median']:.2e} p99 "
                f"{r['reciprocity_p99']:.2e} one-sided {r['one_sided']:.3f} | albedo {r['albedo_min']:.3f}–"
                f"{r['albedo_max']:.3f} leak {r['leak_max']:.3f}")
        out[f"{tilt:g}"] = res
    return out


# -- 3. Bump maps: the true-geometry grid's summary ---------------------------------------------------

def bump_summary(path: Path):
    if not path.is_file():
        return None
    d = json.loads(path.read_text())
    out = {}
    for view in ("frontal", "grazing"):
        cells = [c for c in d["cells"] if c["cell"].split("/")[4] == view and not c.get("errors")]
        methods = sorted({m for c in cells for m in c["metrics"]})
        row = {}
        for m in methods:
            v = [c["metrics"][m]["rel_mse"] for c in cells if m in c["metrics"]]
            row[m] = {"geomean_rel_mse": float(math.exp(np.mean(np.log(np.maximum(v, 1e-30))))),
                      "cells": len(v)}
        if "heightmap" in methods and "bumpmap" in methods:
            hm = np.array([c["metrics"]["heightmap"]["rel_mse"] for c in cells])
            bm = np.array([c["metrics"]["bumpmap"]["rel_mse"] for c in cells])
            row["heightmap_vs_bumpmap"] = {"wins": int(np.sum(hm <= bm)), "cells": len(cells),
                                           "median_ratio": float(np.median(hm / bm))}
            nb_h = [c["metrics"]["heightmap"]["near_black"] for c in cells]
            nb_b = [c["metrics"]["bumpmap"]["near_black"] for c in cells]
            row["near_black_mean"] = {"heightmap": float(np.mean(nb_h)), "bumpmap": float(np.mean(nb_b)),
                                      "truth": float(np.mean([c["truth_stats"]["near_black"] for c in cells]))}
        out[view] = row
    out["settings"] = d.get("settings")
    return out


# -- 4. Height map vs normal map --------------------------------------------------------------------

def height_vs_normal(resolutions=(24, 48, 96), n=1 << 17, seed=22):
    rng = np.random.default_rng(seed)
    hf = H.make_heightfield("bumps", "mild", periods=2)
    uv = rng.random((n, 2))
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    si.n = mi.Normal3f(0, 0, 1)
    si.dp_du, si.dp_dv = mi.Vector3f(1, 0, 0), mi.Vector3f(0, -1, 0)
    si.uv = mi.Point2f(uv[:, 0].astype(np.float32), uv[:, 1].astype(np.float32))
    si.wi = mi.Vector3f(math.sin(math.radians(20)), 0, math.cos(math.radians(20)))
    d = rng.normal(size=(n, 3))
    d[:, 2] = np.abs(d[:, 2]) + 0.05
    wo = _vec(d / np.linalg.norm(d, axis=1, keepdims=True))
    exact = hf.normal(uv[:, 0], 1.0 - uv[:, 1])
    nested = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.2, 0.5, 0.9]}}

    def angle(x, y):
        return float(np.degrees(np.arccos(np.clip(np.sum(x * y, 1), -1, 1))).mean())
    out = {}
    for res in resolutions:
        hb = mi.load_dict({"type": "normalmap_microfacet", "bsdf": nested,
                           "heightmap": H.bitmap_texture(H.height_map(hf, res))})
        nb = mi.load_dict({"type": "normalmap_microfacet", "bsdf": nested,
                           "normalmap": H.bitmap_texture(H.normal_map(hf, res, "central"))})
        wh = np.array(hb.shading_point(mi.BSDFContext(), si).wp).T
        wn = np.array(nb.shading_point(mi.BSDFContext(), si).wp).T
        vh, vn = np.array(hb.eval(mi.BSDFContext(), si, wo)), np.array(nb.eval(mi.BSDFContext(), si, wo))
        out[str(res)] = {"angle_height_vs_normal_deg": angle(wh, wn), "angle_height_vs_exact_deg": angle(wh, exact),
                         "angle_normal_vs_exact_deg": angle(wn, exact),
                         "eval_rel_diff": float(np.abs(vh - vn).mean() / vn.mean()),
                         "slopes_height": list(hb.model.core.slopes[:2]), "slopes_normal": list(nb.model.core.slopes[:2])}
        r = out[str(res)]
        log(f"  {res:4d}² texels: height vs normal map {r['angle_height_vs_normal_deg']:.3f}°, vs exact "
            f"{r['angle_height_vs_exact_deg']:.3f}° / {r['angle_normal_vs_exact_deg']:.3f}°, eval rel diff "
            f"{r['eval_rel_diff']:.4f}")
    return out


# -- Output -----------------------------------------------------------------------------------------

def figure(images, path: Path, thumb: int = 128):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt
    cols = ["truth", "plain", "normalmap_flat", "chiang", "geometric", "geometric_analytic", "flat"]
    rows = list(images)
    fig, axes = plt.subplots(len(rows), len(cols), figsize=(1.6 * len(cols), 1.7 * len(rows)), squeeze=False)
    for i, name in enumerate(rows):
        truth = images[name]["truth"][..., :3]
        k = 0.35 / max(float(np.mean(truth[truth.sum(-1) > 0])), 1e-6)
        for j, c in enumerate(cols):
            ax = axes[i][j]
            ax.imshow(tonemap(images[name][c][..., :3] * k).astype(np.float32) / 255.0)
            ax.set_xticks([])
            ax.set_yticks([])
            if i == 0:
                ax.set_title({"truth": "true sphere", **LABELS}[c].replace(" (", "\n("), fontsize=7)
            if j == 0:
                ax.set_ylabel(name.replace("/sun70", ""), fontsize=7)
    fig.tight_layout()
    atomic_write(path, lambda p: fig.savefig(p, dpi=100, format="png"))
    plt.close(fig)


def markdown(res) -> str:
    L = ["# Every source of shading normals against true geometry", "",
         f"Generated by `{res['command']}` in {res['minutes']:.1f} min (llvm_ad_rgb).", ""]
    term = res["terminator"]
    L += ["## 1. Shadow terminator: low-poly smooth sphere vs the analytic sphere", "",
          f"Orthographic view, sun {next(iter(term.values()))['sun_deg']:g}° from the view axis, dim sky; "
          f"{res['settings']['spp']} spp per method, truth at 4×. Error: mean |ΔY| / mean Y_true over the band's "
          "4×4-pixel blocks (bias with 1/16 of the noise; *noise floor*: an independent truth render at the "
          "methods' spp); *black*: share of band pixels below 10 % of the truth's. Lower is better.", ""]
    methods = list(next(iter(term.values()))["metrics"])
    L.append("| case | " + " | ".join(LABELS.get(m, m) for m in methods) + " | noise floor |")
    L.append("|---" * (len(methods) + 2) + "|")
    for name, c in term.items():
        cells = [f"{c['metrics'][m]['band']['mae_block']:.4f}" + (
            f" ({100 * c['metrics'][m]['band']['black']:.2f} % black)" if c['metrics'][m]['band']['black'] > 0 else "")
            for m in methods]
        L.append(f"| {name.replace('/sun70', '')} | " + " | ".join(cells) + f" | {c['floor']['band']['mae_block']:.4f} |")
    L += ["", "Whole disc (block error):", ""]
    L.append("| case | " + " | ".join(LABELS.get(m, m) for m in methods) + " |")
    L.append("|---" * (len(methods) + 1) + "|")
    for name, c in term.items():
        L.append(f"| {name.replace('/sun70', '')} | " + " | ".join(
            f"{c['metrics'][m]['disc']['mae_block']:.4f}" for m in methods) + " |")
    ok = all(c["metrics"]["geometric"]["band"]["mae_block"] < c["metrics"]["plain"]["band"]["mae_block"]
             and c["metrics"]["geometric"]["band"]["black"] == 0 for c in term.values())
    L += ["", f"**Acceptance** (ours, default model, closer than interpolated normals in the band at every "
          f"tessellation, no black pixels): **{'met' if ok else 'NOT met'}**.", ""]
    props = res["bsdf_properties"]
    L += ["## 2. Reciprocity and white furnace on a tilted triangle", "",
          "White Lambertian material; n_g tilted from the shading normal. *asym*: |f(a,b) − f(b,a)| / max over "
          "pairs above the triangle (f = eval/⟨ω_o, n_g⟩; median and 99th percentile; the walks' eval is "
          "stochastic, so theirs is noise); *one-sided*: pairs where one direction is zero and the other is not; "
          "*albedo*: energy reflected above the triangle over 12 ω_i (θ_i up to 85°); *leak*: energy sent "
          "below the triangle's plane (into the mesh).", ""]
    L.append("| tilt | method | asym median | asym p99 | one-sided | albedo min–max | leak max |")
    L.append("|---|---|---|---|---|---|---|")
    for tilt, rows in props.items():
        for m, r in rows.items():
            L.append(f"| {tilt}° | {m} | {r['reciprocity_median']:.1e} | {r['reciprocity_p99']:.1e} | "
                     f"{r['one_sided']:.3f} | {r['albedo_min']:.3f}–{r['albedo_max']:.3f} | {r['leak_max']:.3f} |")
    bump = res.get("bump")
    L += ["", "## 3. Bump maps: displaced heightfield vs plane with `heightmap`", ""]
    if bump is None:
        L.append("(not run: no true-geometry grid json)")
    else:
        L += ["`validation/true_geometry.py` grid (its settings below): geometric mean of relMSE against the "
              "dense displaced mesh per view; *heightmap* = ours (default model) on the height map, "
              "*bumpmap* = Mitsuba's `bumpmap` on the same texture and scale; `classic_fixed` = Mitsuba's "
              "`normalmap` on the baked normal map, `default` = ours on the normal map.", ""]
        for view in ("frontal", "grazing"):
            row = bump[view]
            ms = [m for m in row if isinstance(row[m], dict) and "geomean_rel_mse" in row[m]]
            if not ms:
                L += [f"**{view}**: no cells", ""]
                continue
            L.append(f"**{view}** ({row[ms[0]]['cells']} cells): " + ", ".join(
                f"{m} {row[m]['geomean_rel_mse']:.4g}" for m in sorted(ms, key=lambda m: row[m]['geomean_rel_mse'])))
            if "heightmap_vs_bumpmap" in row:
                hv = row["heightmap_vs_bumpmap"]
                L.append(f"  - heightmap ≤ bumpmap in {hv['wins']}/{hv['cells']} cells, median relMSE ratio "
                         f"{hv['median_ratio']:.3f}; near-black pixels: heightmap {row['near_black_mean']['heightmap']:.4f}, "
                         f"bumpmap {row['near_black_mean']['bumpmap']:.4f}, truth {row['near_black_mean']['truth']:.4f}")
            L.append("")
        ok = all("heightmap" in bump[v] and bump[v]["heightmap"]["geomean_rel_mse"] <= bump[v]["bumpmap"]["geomean_rel_mse"]
                 for v in ("frontal", "grazing"))
        L += [f"**Acceptance** (heightmap at least as close as bumpmap in both views, geometric mean): "
              f"**{'met' if ok else 'NOT met'}**.", ""]
    hv = res["height_vs_normal"]
    L += ["## 4. Height map vs the normal map of the same heights", "",
          "Bumps heightfield (mild), the plane's parametrisation; height map: Mitsuba's bilinear gradient "
          "(first order); normal map: central differences (second order). Mean angle between the two ω_p, and "
          "each against the analytic normal; mean relative difference of eval (faithful, diffuse, θ_i 20°).", "",
          "| texels | height vs normal map | height map vs exact | normal map vs exact | eval rel. diff |",
          "|---|---|---|---|---|"]
    for r, x in hv.items():
        L.append(f"| {r}² | {x['angle_height_vs_normal_deg']:.3f}° | {x['angle_height_vs_exact_deg']:.3f}° | "
                 f"{x['angle_normal_vs_exact_deg']:.3f}° | {x['eval_rel_diff']:.4f} |")
    L.append("")
    return "\n".join(L)


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--out", type=Path, default=ROOT / "out" / "validation")
    p.add_argument("--quick", action="store_true")
    p.add_argument("--spp", type=int, default=None)
    p.add_argument("--res", type=int, default=128)
    p.add_argument("--levels", type=lambda s: [int(x) for x in s.split(",")], default=None)
    p.add_argument("--grid", type=Path, default=ROOT / "validation" / "results" / "heightmap" / "true_geometry.json")
    p.add_argument("--report-only", action="store_true",
                   help="rewrite the markdown from the json (re-reading --grid), rendering nothing")
    args = p.parse_args(argv)
    if args.report_only:
        stem = "normal_sources_quick" if args.quick else "normal_sources"
        res = json.loads((args.out / f"{stem}.json").read_text())
        res["bump"] = bump_summary(args.grid)
        atomic_write(args.out / f"{stem}.json", lambda q: Path(q).write_text(json.dumps(res, indent=1, default=float)))
        atomic_write(args.out / f"{stem}.md", lambda q: Path(q).write_text(markdown(res)))
        log(f"rewrote {args.out / stem}.{{md,json}}")
        return 0
    t0 = time.time()
    spp = args.spp or (16 if args.quick else 512)
    levels = args.levels or ([1] if args.quick else [1, 2, 3])
    res = {"command": "validation/normal_sources.py " + " ".join(sys.argv[1:] if argv is None else argv),
           "settings": {"spp": spp, "res": args.res, "levels": levels}}
    res["terminator"], images = terminator(levels, ("diffuse", "glossy"), args.res, spp)
    log("BSDF properties")
    res["bsdf_properties"] = bsdf_properties(furnace_n=(1 << 16) if args.quick else (1 << 20))
    res["bump"] = bump_summary(args.grid)
    log("height map vs normal map")
    res["height_vs_normal"] = height_vs_normal()
    res["minutes"] = (time.time() - t0) / 60
    stem = "normal_sources_quick" if args.quick else "normal_sources"
    args.out.mkdir(parents=True, exist_ok=True)
    atomic_write(args.out / f"{stem}.md", lambda q: Path(q).write_text(markdown(res)))
    atomic_write(args.out / f"{stem}.json", lambda q: Path(q).write_text(json.dumps(res, indent=1, default=float)))
    figure(images, args.out / f"{stem}.png")
    log(f"wrote {args.out / stem}.{{md,json,png}} in {res['minutes']:.1f} min")
    return 0


if __name__ == "__main__":
    sys.exit(main())
