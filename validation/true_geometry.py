"""Normal-mapping methods against the true geometry the map was baked from.

    nice .venv/bin/python -m validation.true_geometry [--quick] [--out validation/results]
        [--heightfields bumps,eggcrate,noise] [--steepness mild,steep]
        [--materials diffuse,plastic,aluminium,gold] [--lightings sky_sun,grazing_sun]
        [--views frontal,grazing] [--magnifications magnified,minified]
        [--methods nomap,classic,...,plugin:MODEL[:FACET][,k=v]] [--extra-methods FILE.py:NAME]
        [--res 96] [--spp 64] [--ref-factor 4] [--method-noise] [--no-scenes] [--no-grid]

For every cell of the grid (heightfield × steepness × material × lighting × view ×
magnification) it renders the heightfield as a dense displaced mesh (the truth) and
a two-triangle plane at its mean height carrying the normal map baked from the same
heights, wrapped by each method (:mod:`validation.heightfield`), and measures each
method against the truth. Then two stand-alone scenes:

- **diffuse relief**: diffuse plane, bumps of max tilt 48°, a 45° sun (no sky),
  frontal: the image contrast (std/mean of luminance) of each method vs the truth;
- **egg-crate grazing**: egg crate of max tilt 70°, view 78° from the normal, glossy
  metal (GGX α 0.0225), sun + sky: the near-black pixel fraction of each method.

Writes ``true_geometry.md`` (summary, the two scenes, a table per cell),
``true_geometry.json`` (every number) and ``true_geometry.png`` (contact sheet: a row
per cell, truth then the methods, one exposure per row) to ``--out``; ``--quick``
writes ``true_geometry_quick.*`` instead (a small grid at low resolution, ~2 min).

Candidate models: ``--methods plugin:mymodel`` adds ``normalmap_microfacet`` with
``model="mymodel"`` (any parameters after commas), and ``--extra-methods FILE.py:NAME``
imports a list of :class:`validation.heightfield.Method` (each a callable
``wrap(nested_dict, normalmap_texture) -> bsdf dict``) from a Python file. A method
that fails to load is reported per cell and left out of the summary.

Everything is seeded, per cell (:func:`validation.heightfield.cell_seed`, from the cell's name and
``--seed``): the same command gives the same numbers, and a subset run (e.g. one cell by its
flags) gives exactly that cell's numbers of the full run.
"""

from __future__ import annotations

import argparse
import importlib.util
import itertools
import json
import math
import re
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

import mfnormal  # noqa: E402  (first: selects a working libLLVM)

import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

mi.set_variant("llvm_ad_rgb")
mfnormal.register()

from validation import heightfield as H  # noqa: E402
from mfnormal.files import atomic_write  # noqa: E402
from mfnormal.io.images import tonemap  # noqa: E402

FULL = dict(heightfields=list(H.KINDS), steepness=["mild", "steep"],
            materials=["diffuse", "plastic", "aluminium", "gold"],
            lightings=["sky_sun", "grazing_sun"], views=["frontal", "grazing"],
            magnifications=["magnified", "minified"], res=96, spp=64, ref_factor=4)
QUICK = dict(heightfields=["bumps", "eggcrate"], steepness=["mild", "steep"],
             materials=["diffuse", "aluminium"], lightings=["sky_sun", "grazing_sun"],
             views=["frontal", "grazing"], magnifications=["magnified"], res=48, spp=16,
             ref_factor=4)

RELIEF = H.Cell("bumps", 48.0, "diffuse", "sun45", "frontal", "magnified")
EGGCRATE = H.Cell("eggcrate", 70.0, "glossy_metal", "sky_sun", "grazing78", "magnified")

THUMB = 48          # contact-sheet thumbnail size (pixels)
#: The contact sheet of a large grid: per heightfield × steepness, all materials under one
#: lighting / view / magnification (rotating, the steep maps at grazing), plus the two scenes.
SHEET_SETTINGS = {("bumps", "mild"): ("sky_sun", "frontal", "magnified"),
                  ("bumps", "steep"): ("grazing_sun", "grazing", "magnified"),
                  ("eggcrate", "mild"): ("grazing_sun", "frontal", "magnified"),
                  ("eggcrate", "steep"): ("sky_sun", "grazing", "magnified"),
                  ("noise", "mild"): ("sky_sun", "grazing", "minified"),
                  ("noise", "steep"): ("grazing_sun", "frontal", "minified")}
SHEET_MAX_ROWS = 40
ROW_EXPOSURE = 0.35  # contact sheet: the truth's mean luminance maps to this (linear)


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=ROOT / "out" / "validation")
    p.add_argument("--quick", action="store_true", help="small grid at low resolution (~2 min)")
    for name in ("heightfields", "steepness", "materials", "lightings", "views", "magnifications"):
        p.add_argument(f"--{name}", type=lambda s: s.split(","), default=None,
                       help=f"comma-separated subset (default: {','.join(FULL[name])})")
    p.add_argument("--methods", type=H.split_methods, default=list(H.DEFAULT_METHODS),
                   help="method keys or plugin:MODEL[:FACET][,k=v] specs")
    p.add_argument("--extra-methods", action="append", default=[],
                   help="FILE.py:NAME, a list of heightfield.Method objects to add")
    p.add_argument("--res", type=int, default=None)
    p.add_argument("--spp", type=int, default=None, help="per method render (×4 for glossy materials)")
    p.add_argument("--ref-factor", type=int, default=None, help="truth reference spp = this × spp")
    p.add_argument("--method-noise", action="store_true", help="also measure each method's own noise")
    p.add_argument("--no-scenes", action="store_true", help="skip the two stand-alone scenes")
    p.add_argument("--no-grid", action="store_true", help="only the two stand-alone scenes")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--registered", action="store_true",
                   help="every method on the normal map registered for the camera (each camera ray reads "
                        "the texel where it meets the true surface: a perfect parallax lookup); writes "
                        "true_geometry_registered.*")
    p.add_argument("--sheet", choices=["auto", "all"], default="auto",
                   help=f"contact sheet rows: every cell (all; auto when ≤ {SHEET_MAX_ROWS} cells) or the "
                        "SHEET_SETTINGS selection")
    return p.parse_args(argv)


def load_extra(spec: str):
    path, _, name = spec.rpartition(":")
    mod_spec = importlib.util.spec_from_file_location("extra_methods", path)
    mod = importlib.util.module_from_spec(mod_spec)
    mod_spec.loader.exec_module(mod)
    return list(getattr(mod, name))


def geomean(values):
    v = [x for x in values if x is not None and np.isfinite(x) and x > 0]
    return float(math.exp(np.mean(np.log(v)))) if v else float("nan")


def is_grazing(cell: str) -> bool:
    _, _, _, lighting, view, _ = cell.split("/")
    return view.startswith("grazing") or lighting.startswith("grazing")


def groups(cells):
    """Cell subsets for the summary: name → predicate on the cell name."""
    parts = [c.split("/") for c in cells]
    g = {"all cells": lambda c: True,
         "mild cells": lambda c: c.split("/")[1] == "mild",
         "steep cells": lambda c: c.split("/")[1] == "steep",
         "steep grazing cells (grazing view or sun)": lambda c: c.split("/")[1] == "steep" and is_grazing(c),
         "steep, grazing view and grazing sun": lambda c: c.split("/")[1] == "steep"
         and c.split("/")[3].startswith("grazing") and c.split("/")[4].startswith("grazing"),
         "magnified cells": lambda c: c.endswith("/magnified"),
         "minified cells": lambda c: c.endswith("/minified"),
         "mild magnified cells": lambda c: c.split("/")[1] == "mild" and c.endswith("/magnified"),
         "mild minified cells": lambda c: c.split("/")[1] == "mild" and c.endswith("/minified"),
         "the 12-cell design (plastic, aluminium, gold × 2 lightings × 2 views), mild, magnified":
             lambda c: c.split("/")[1] == "mild" and c.endswith("/magnified")
             and c.split("/")[2] in ("plastic", "aluminium", "gold")}
    for mat in dict.fromkeys(p[2] for p in parts):
        g[f"material {mat}"] = lambda c, mat=mat: c.split("/")[2] == mat
    for hf in dict.fromkeys(p[0] for p in parts):
        g[f"heightfield {hf}"] = lambda c, hf=hf: c.split("/")[0] == hf
    return g


def summarise(results, method_keys):
    """Per group: geometric-mean relMSE and mean |ln| per method, floors, wins against classic."""
    cells = [r["cell"] for r in results]
    out = {}
    for gname, pred in groups(cells).items():
        rs = [r for r in results if pred(r["cell"])]
        if not rs:
            continue
        row = {"cells": len(rs),
               "floor_rel_mse": geomean([r["floor"]["rel_mse"] for r in rs]),
               "floor_ln_err": float(np.mean([r["floor"]["ln_err"] for r in rs])),
               "methods": {}}
        for k in method_keys:
            have = [r for r in rs if k in r["metrics"]]
            if not have:
                continue
            rel = [r["metrics"][k]["rel_mse"] for r in have]
            classic = [min(r["metrics"][c]["rel_mse"] for c in ("classic", "classic_fixed")
                           if c in r["metrics"]) if any(c in r["metrics"] for c in ("classic", "classic_fixed"))
                       else None for r in have]
            wins = sum(1 for a, b in zip(rel, classic) if b is not None and a <= b)
            near_floor = sum(1 for r in have if r["metrics"][k]["rel_mse"] < 2 * r["floor"]["rel_mse"])
            row["methods"][k] = {
                "cells": len(have), "rel_mse": geomean(rel),
                "ln_err": float(np.mean([r["metrics"][k]["ln_err"] for r in have])),
                "near_black": float(np.mean([r["metrics"][k]["near_black_px"] for r in have])),
                # Magnified cells only: a minified frame's block means are near uniform (frontal),
                # their contrast is mostly noise.
                "contrast_ratio": geomean([r["metrics"][k]["contrast"] / max(r["floor"]["contrast"], 1e-9)
                                           for r in have if r["block"] == 1]),
                "energy_ratio": geomean([r["metrics"][k]["mean"] / max(r["truth_stats"]["mean"], 1e-12)
                                         for r in have]),
                "le_best_classic": wins, "within_2x_floor": near_floor}
        out[gname] = row
    return out


def strip_images(r):
    out = {k: v for k, v in r.items() if k not in ("images", "truth", "index")}
    # The reference's own share of every score, if noise falls as 1/spp: floor / (ref_factor + 1).
    out["ref_noise"] = r["floor"]["rel_mse"] * r["spp"] / (r["spp"] + r["ref_spp"])
    return out


# ---------------------------------------------------------------------------
# Contact sheet
# ---------------------------------------------------------------------------

def thumb(img, size):
    H_, W_ = img.shape[:2]
    f = max(1, H_ // size)
    t = img[:H_ - H_ % f, :W_ - W_ % f].reshape(H_ // f, f, W_ // f, f, 3).mean(axis=(1, 3))
    if t.shape[0] != size:         # upsample small renders (quick mode) by repetition
        r = max(1, size // t.shape[0])
        t = np.repeat(np.repeat(t, r, 0), r, 1)
    return t


def contact_sheet(results, method_keys, labels, path, size=THUMB, title=""):
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    cols = ["truth"] + list(method_keys)
    label_w, head_h, pad = 290, 34, 2
    W = label_w + len(cols) * (size + pad)
    Hh = head_h + len(results) * (size + pad)
    canvas = np.ones((Hh, W, 3), np.float32)
    for i, r in enumerate(results):
        k = ROW_EXPOSURE / max(float(H.luminance(r["truth"]).mean()), 1e-12)
        y0 = head_h + i * (size + pad)
        for j, key in enumerate(cols):
            img = r["truth"] if key == "truth" else r["images"].get(key)
            x0 = label_w + j * (size + pad)
            if img is None:
                canvas[y0:y0 + size, x0:x0 + size] = 0.5
                continue
            t = tonemap(thumb(img, size) * k).astype(np.float32) / 255.0
            canvas[y0:y0 + size, x0:x0 + size] = t[:size, :size]
    dpi = 100
    fig = plt.figure(figsize=(W / dpi, Hh / dpi), dpi=dpi)
    fig.figimage(canvas, 0, 0, origin="upper")
    for j, key in enumerate(cols):
        x = label_w + j * (size + pad) + size / 2
        fig.text(x / W, 1 - (head_h - 2) / Hh, key.replace("_", "\n"), ha="center", va="bottom",
                 fontsize=5.5)
    for i, r in enumerate(results):
        y = head_h + i * (size + pad) + size / 2
        name = r.get("label") or r["cell"].replace("/", " / ")
        fig.text(4 / W, 1 - y / Hh, f"{r.get('index', i + 1)}. {name}", ha="left", va="center", fontsize=5.5)
    if title:
        fig.text(4 / W, 1 - 4 / Hh, title, ha="left", va="top", fontsize=7, weight="bold")
    atomic_write(path, lambda p: fig.savefig(p, dpi=dpi, format="png"))
    plt.close(fig)


# ---------------------------------------------------------------------------
# Markdown
# ---------------------------------------------------------------------------

def fmt(x, digits=4):
    if x is None or not np.isfinite(x):
        return "–"
    if x == 0:
        return "0"
    if abs(x) < 1e-3 or abs(x) >= 1e4:
        return f"{x:.2e}"
    return f"{x:.{digits}g}"


def method_table(L, header, first, keys, metrics, row, errors=None):
    """Append a Markdown table to ``L``: ``header`` (its ``\\|`` are literal bars), its separator,
    the row ``first``, then per method key the ``errors`` row or ``row(k, metrics[k])`` (methods
    without metrics are left out), and a blank line."""
    columns = len(re.split(r"(?<!\\)\|", header.strip())) - 2
    L += [header, "|" + "---|" * columns, first]
    for k in keys:
        if errors and k in errors:
            L.append(errors[k])
        elif metrics.get(k) is not None:
            L.append(row(k, metrics[k]))
    L.append("")


def markdown(report, labels, settings, quick):
    L = []
    L.append("# Normal-mapping methods against true geometry" + (" (quick run)" if quick else ""))
    L.append("")
    L.append(f"Generated by `{settings['command']}` in {settings['elapsed_s'] / 60:.1f} min "
             f"({settings['cells']} cells; Mitsuba {mi.__version__}, `llvm_ad_rgb`).")
    L.append("")
    L.append("**Setup** (`validation.heightfield`): each heightfield is rendered as a dense displaced mesh "
             "with analytic vertex normals (the truth) and as a two-triangle plane at its mean height with "
             "the normal map baked from the same heights (analytic gradient, OpenGL convention in Mitsuba's "
             "frame), wrapped by each method. Orthographic camera, the surface fills the frame "
             f"(no masks). `path`, max_depth 8, multi-jittered sampling, {settings['res']}² px. "
             f"Methods at {settings['spp']} spp (×4 for gold and other GGX α ≤ 0.05), truth reference at "
             f"{settings['ref_factor']}× that; the **noise floor** is the truth rendered again at the methods' "
             "spp with another seed and scored like a method: what an exact, unbiased method with the "
             "truth's variance would get (it contains the reference's noise, as every score does; the "
             "reference's own share of each score is ≈ floor / (ref_factor + 1)). In glossy cells under the "
             "grazing sun the truth has rare fireflies (sunlight reflected from one glossy facet onto "
             "another, found by a BSDF sample and then next-event estimation): there the floor itself "
             "fluctuates and a deterministic method can score below it.")
    L.append("")
    if settings.get("registered"):
        L.append("**Registered** (`--registered`): every method renders the plane with the normal map "
                 "registered for the camera (`validation.heightfield.registered_map`): at each point of the "
                 "plane, the texel where the camera ray through it meets the true surface, as a perfect "
                 "parallax (relief) lookup would give the camera rays; the light's rays read the same map, "
                 "and every ray still leaves from the plane.")
        L.append("")
    L.append("Magnified: 2 periods across the image, 24 texels per period (a texel ≈ 2×2 px frontal), "
             "64 mesh vertices per period. Minified: 24 periods across, 16 texels and 32 vertices per "
             "period (4×4 texels per pixel frontal; the truth at 48 vertices per period differs by 2.3 % "
             "in energy and relMSE 7e-4 in the worst case measured, steep bumps at grazing view and sun); "
             "minified metrics are taken on 4×4-pixel block means "
             "(one period per block frontal: the aggregate the pixel-scale moiré and glints average to; "
             "near-black is counted per pixel everywhere). Views: frontal, grazing = 75° from the normal "
             "(camera on −y). Lightings: `sky_sun` = smooth sky (no disc) + directional sun 45° up, "
             "azimuth 30° (behind-right of the surface); `grazing_sun` = sun 10° up (80° from the normal) "
             "from +x (the image's right) + the sky at 0.1. Steepness: max tilt 28° (mild) / 65° (steep).")
    L.append("")
    L.append("**Metrics**: relMSE = mean((x − ref)²/(ref² + 1e-2)) over pixels and channels "
             "(`mfnormal.report.metrics.rel_mse`), after a metered exposure (both images scaled so the truth's "
             "mean luminance is 0.5; `rel_mse_raw` in the JSON is without it); |ln| = mean "
             "|ln((Y + f)/(Y_true + f))|, f = 1 % of the truth's median luminance; contrast = std/mean of "
             "luminance (the truth's is taken at the methods' spp, same noise); near-black = fraction of "
             "pixels with luminance < 5 % of the truth's median; energy = mean luminance / truth's.")
    L.append("")
    method_keys = [k for k in settings["methods"]]
    if report.get("summary"):
        L.append("## Summary")
        L.append("")
        L.append("Geometric mean of relMSE over the cells of each group (the floor row: the truth at the "
                 "methods' spp). `≤classic`: cells where the method's relMSE ≤ min(classic, classic_fixed). "
                 "`~floor`: cells where the method's relMSE < 2× the floor (indistinguishable from noise). "
                 "Contrast / truth: geometric mean over the group's magnified cells only (minified block means "
                 "are nearly uniform, their contrast is mostly noise); energy / truth: mean luminance ratio.")
        L.append("")
        for gname, row in report["summary"].items():
            L.append(f"### {gname} ({row['cells']} cells)")
            L.append("")
            def summary_row(k, m):
                return (f"| {labels.get(k, k)} | {fmt(m['rel_mse'])} | {fmt(m['ln_err'], 3)} | "
                        f"{fmt(m['contrast_ratio'], 3)} | {fmt(m['energy_ratio'], 3)} | "
                        f"{m['near_black'] * 100:.2f} % | {m['le_best_classic']}/{m['cells']} | "
                        f"{m['within_2x_floor']}/{m['cells']} |")
            method_table(L, "| method | relMSE (geo-mean) | mean \\|ln\\| | contrast / truth | energy / truth "
                            "| near-black | ≤classic | ~floor |",
                         f"| *noise floor (truth @ spp)* | {fmt(row['floor_rel_mse'])} | "
                         f"{fmt(row['floor_ln_err'], 3)} | 1 | 1 | | | |",
                         method_keys, row["methods"], summary_row)
    for sname in ("relief", "eggcrate"):
        s = report.get(sname)
        if not s:
            continue
        title = {"relief": "Diffuse relief: bumps (max tilt 48°), diffuse 0.8, 45° sun, no sky, frontal",
                 "eggcrate": "Egg crate at grazing view: max tilt 70°, view 78° from the normal, "
                             "GGX α 0.0225 aluminium, sky + sun"}[sname]
        L.append(f"## {title}")
        L.append("")
        L.append(f"`{s['cell']}`, {s['spp']} spp (truth {s['ref_spp']}); truth contrast {fmt(s['floor']['contrast'], 3)}"
                 f" (reference {fmt(s['truth_stats']['contrast'], 3)}), truth near-black "
                 f"{s['floor']['near_black_px'] * 100:.2f} %.")
        L.append("")
        def scene_row(k, m, s=s):
            return (f"| {labels.get(k, k)} | {fmt(m['contrast'], 3)} | "
                    f"{fmt(m['contrast'] / max(s['floor']['contrast'], 1e-9), 3)} | "
                    f"{m['near_black_px'] * 100:.2f} % | {fmt(m['rel_mse'])} | {fmt(m['ln_err'], 3)} | "
                    f"{fmt(m['mean'] / s['truth_stats']['mean'], 3)} |")
        method_table(L, "| method | contrast | contrast / truth | near-black | relMSE | \\|ln\\| | energy |",
                     f"| *truth @ spp* | {fmt(s['floor']['contrast'], 3)} | 1 | "
                     f"{s['floor']['near_black_px'] * 100:.2f} % | {fmt(s['floor']['rel_mse'])} | "
                     f"{fmt(s['floor']['ln_err'], 3)} | 1 |", method_keys, s["metrics"], scene_row)
    if report.get("cells"):
        L.append("## Cells")
        L.append("")
        L.append("Per cell: heightfield / steepness / material / lighting / view / magnification; the tilt "
                 "statistics of the heightfield; spp of the methods (truth reference); time per render.")
        L.append("")
        for i, r in enumerate(report["cells"]):
            t = r["tilts"]
            L.append(f"### {i + 1}. {r['cell']}")
            L.append("")
            L.append(f"tilt median {t['median']:.1f}°, p99 {t['p99']:.1f}°, max {t['max']:.1f}°; "
                     f"{r['spp']} spp (truth {r['ref_spp']}), metric block {r['block']}; truth contrast "
                     f"{fmt(r['floor']['contrast'], 3)}, near-black {r['floor']['near_black_px'] * 100:.2f} %; "
                     f"the reference's own noise in every score ≈ {fmt(r['ref_noise'])}.")
            L.append("")
            noise = bool(r.get("self_noise"))

            def cell_row(k, m, r=r, noise=noise):
                return (f"| {labels.get(k, k)} | {fmt(m['rel_mse'])} | {fmt(m['ln_err'], 3)} | "
                        f"{fmt(m['contrast'], 3)} | {m['near_black_px'] * 100:.2f} % | "
                        f"{fmt(m['mean'] / r['truth_stats']['mean'], 3)} | {r['times'].get(k, 0):.1f}"
                        + (f" | {fmt(r['self_noise'].get(k))} |" if noise else " |"))
            errors = {k: f"| {labels.get(k, k)} | error: {e} | | | | | |" + (" |" if noise else "")
                      for k, e in r["errors"].items()}
            method_table(L, "| method | relMSE | \\|ln\\| | contrast | near-black | energy | time (s)"
                            + (" | own noise |" if noise else " |"),
                         f"| *noise floor* | {fmt(r['floor']['rel_mse'])} | {fmt(r['floor']['ln_err'], 3)} | "
                         f"{fmt(r['floor']['contrast'], 3)} | {r['floor']['near_black_px'] * 100:.2f} % | "
                         f"{fmt(r['floor']['mean'] / r['truth_stats']['mean'], 3)} | "
                         f"{r['times'].get('truth', 0):.1f}" + (" | |" if noise else " |"),
                         method_keys, r["metrics"], cell_row, errors)
    return "\n".join(L) + "\n"


# ---------------------------------------------------------------------------

def main(argv=None):
    args = parse_args(argv)
    base = QUICK if args.quick else FULL
    opts = {k: getattr(args, k) if getattr(args, k, None) is not None else base[k] for k in base}
    methods = [H.method_from_spec(s) for s in args.methods]
    for spec in args.extra_methods:
        methods += load_extra(spec)
    keys = [m.key for m in methods]
    if len(set(keys)) != len(keys):
        sys.exit(f"duplicate method keys: {keys}")
    labels = {"truth": "truth", **{m.key: m.label for m in methods}}
    stem = ("true_geometry_quick" if args.quick else "true_geometry") + ("_registered" if args.registered else "")
    args.out.mkdir(parents=True, exist_ok=True)

    # Material innermost: consecutive cells share the truth scene (its BVH is built once).
    cells = [H.Cell(hf, st, mat, li, vi, mag) for hf, st, li, vi, mag, mat in itertools.product(
        opts["heightfields"], opts["steepness"], opts["lightings"], opts["views"],
        opts["magnifications"], opts["materials"])]
    if args.no_grid:
        cells = []
    res, spp, rf = opts["res"], opts["spp"], opts["ref_factor"]
    t_start = time.time()
    results = []
    for i, cell in enumerate(cells):
        t0 = time.time()
        r = H.render_cell(cell, methods, res=res, spp=spp, ref_factor=rf,
                          seed=H.cell_seed(cell, args.seed), method_noise=args.method_noise,
                          registered=args.registered)
        results.append(r)
        best = min(r["metrics"].items(), key=lambda kv: kv[1]["rel_mse"])[0] if r["metrics"] else "-"
        print(f"[{i + 1}/{len(cells)}] {cell.name}: {time.time() - t0:.1f} s, floor "
              f"{r['floor']['rel_mse']:.3g}, best {best}; elapsed {(time.time() - t_start) / 60:.1f} min",
              flush=True)

    report = {"cells": [strip_images(r) for r in results]}
    if results:
        report["summary"] = summarise(results, keys)
    scenes = {}
    if not args.no_scenes:
        for name, cell in (("relief", RELIEF), ("eggcrate", EGGCRATE)):
            t0 = time.time()
            r = H.render_cell(cell, methods, res=res, spp=spp, ref_factor=rf,
                              seed=H.cell_seed(cell, args.seed), method_noise=args.method_noise,
                              registered=args.registered)
            scenes[name] = r
            report[name] = strip_images(r)
            print(f"[scene {name}] {time.time() - t0:.1f} s", flush=True)

    elapsed = time.time() - t_start
    cmd = "nice .venv/bin/python -m validation.true_geometry" + (" " + " ".join(sys.argv[1:]) if sys.argv[1:] else "")
    settings = {"command": cmd, "elapsed_s": elapsed, "cells": len(cells), "res": res, "spp": spp,
                "ref_factor": rf, "methods": keys, "seed": args.seed, "registered": args.registered,
                "method_about": {m.key: m.about for m in methods},
                "thresholds": {"rel_mse_eps": H.REL_MSE_EPS, "exposure_mean": H.EXPOSURE_MEAN,
                               "ln_floor": H.LN_FLOOR, "black_fraction": H.BLACK_FRACTION}}
    report["settings"] = settings
    md = markdown(report, labels, settings, args.quick)
    atomic_write(args.out / f"{stem}.md", lambda p: Path(p).write_text(md))
    atomic_write(args.out / f"{stem}.json",
                 lambda p: Path(p).write_text(json.dumps(report, indent=1, default=float)))
    for i, r in enumerate(results):
        r["index"] = i + 1
    rows = results
    if args.sheet == "auto" and len(results) > SHEET_MAX_ROWS:
        rows = [r for r in results if SHEET_SETTINGS.get(tuple(r["cell"].split("/")[:2]))
                == tuple(r["cell"].split("/")[3:])] or results[:SHEET_MAX_ROWS]
    for name in ("relief", "eggcrate"):
        if name in scenes:
            scenes[name]["index"] = name
    sheet = rows + [scenes[n] for n in ("relief", "eggcrate") if n in scenes]
    if sheet:
        contact_sheet(sheet, keys, labels, args.out / f"{stem}.png",
                      title="truth, then each method; one exposure per row")
    print(f"wrote {args.out / stem}.{{md,json,png}} in {elapsed / 60:.1f} min")


if __name__ == "__main__":
    main()
