"""The real-asset harness with each image rendered as two independent halves: bias² and noise
apart, per cell, at equal spp and at equal time, with a noise floor for the bias itself.

    nice .venv/bin/python -m validation.real_assets_split [--quick] [--out out/validation/real_assets_split]
        [--assets bunny,dragon,rock] [--materials aluminium,plastic,diffuse]
        [--lightings sky_sun,grazing_sun] [--views frontal,limb,far]
        [--methods classic,classic_fixed,faithful] [--res 96] [--spp 64] [--truth-spp 1024]
        [--integrator path|mfnormal_path] [--frame mikktspace|mitsuba]

The assets, their low-polys, maps, cameras, lightings and materials are those of
:mod:`validation.real_assets`; the views add ``far``: the whole object in a quarter of the frame
(the frontal view's window twice as wide), where each pixel covers many texels (the report gives
how many, from the map's covered texels per unit of the low-poly's area).

Every image X — the truth T at ``--truth-spp``, each method at ``--spp``, and the truth again at
``--spp`` — is the mean of two renders of half the samples with independent seeds, X₁ and X₂.
Per pixel and channel, with w = 1/(T² + 10⁻²) after the metered exposure of
:func:`validation.real_assets.object_metrics` (the truth's mean luminance over the object → 0.5):

- relMSE = mean w·(X − T)², what the method shows at the cell's spp;
- noise = mean w·(X₁ − X₂)²/4, its variance at that spp (X₁ − X₂ has twice the variance of X
  around its mean, over 2);
- bias² = relMSE − noise − the truth's own noise (mean w·(T₁ − T₂)²/4): the distance to the truth
  a converged render would keep.

The **relief contrast** of an image is how much of the truth's relief it draws: the standard
deviation of its luminance's detail over the object (the image less its Gaussian blur of
:data:`RELIEF_BLUR` of the frame's width, taken over the object alone, and counted away from the
silhouette by twice that), over the truth's. The object's own shading, which changes over its whole
size, is not relief; nor is noise: the detail's variance is the covariance of the two halves'
details, whose noise is independent, so the contrast is that of a converged render at any spp. A
method keeps the relief of a cell where its contrast is within :data:`RELIEF_TOLERANCE` of 1; the
truth rendered again at the methods' spp shows what the instrument resolves.

The **noise floor** of a cell is what the instrument can resolve in a bias²: the truth rendered
again at the methods' spp has bias² 0, and its estimate's magnitude plus two standard errors (over
the object's pixels) is the floor. A cell is **resolved** when its floor is at most 1/10 of the
better classic setting's relMSE at equal spp (Mitsuba's ``normalmap`` with its fixes off or on,
the better of the two per cell). A method is ≤ classic in a cell when its relMSE (equal spp) is at
most the better classic's plus twice the floor.

**Equal time.** Each method's seconds per render at the cell's spp, warm and interleaved with the
others over :data:`validation.real_assets.TIME_ROUNDS` rounds (the median), give the spp it gets
in the time of the faster classic setting, n = spp·t_classic/t_method; its relMSE there is
bias² + noise·spp/n (noise falls as 1/spp). No second render is needed, and the comparison is the
one users make: the same time for each.

Writes ``real_assets_split.md`` and ``.json`` to ``--out`` (default ``out/validation/real_assets_split``,
outside the tracked tree).
"""

from __future__ import annotations

import gc
import itertools
import json
import math
import sys
import time
from pathlib import Path

import numpy as np
from scipy import ndimage

from validation import real_assets as RA

import mitsuba as mi  # noqa: E402  (after real_assets: it imports mfnormal first)

from mfnormal.io import bake as B  # noqa: E402
from mfnormal.files import atomic_write  # noqa: E402
from mfnormal.report.metrics import luminance  # noqa: E402
from validation import heightfield as H  # noqa: E402
from validation import true_geometry as TG  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]
OUT = ROOT / "out" / "validation" / "real_assets_split"
FULL = dict(assets=["bunny", "dragon", "rock"], materials=["aluminium", "plastic", "diffuse"],
            lightings=["sky_sun", "grazing_sun"], views=["frontal", "limb", "far"], res=96, spp=64,
            truth_spp=1024, faces=1000, map_size=1024)
QUICK = dict(assets=["bunny_small"], materials=["aluminium"], lightings=["sky_sun"],
             views=["limb", "far"], res=32, spp=8, truth_spp=64, faces=300, map_size=256)
METHODS = ("classic", "classic_fixed", "faithful")
CLASSIC = ("classic", "classic_fixed")
VIEWS = ("frontal", "limb", "far")
#: The far view's window: the frontal one's times this (the object in 1/FAR² of the frame).
FAR = 2.0
#: The relMSE regulariser after the metered exposure (as :func:`mfnormal.report.metrics.rel_mse`).
EPS = 1e-2
#: A cell is resolved where its floor is at most this share of the better classic's relMSE.
RESOLVED = 0.1
#: The relief contrast's blur, as a share of the frame's width: the Gaussian's standard deviation
#: (3 px at 96²) that parts the relief a map draws from the object's own shading (relief_part).
RELIEF_BLUR = 1.0 / 32.0
#: A method keeps the truth's relief in a cell where its relief contrast is within this of 1.
RELIEF_TOLERANCE = 0.1
#: Seeds of the second halves: this far from the first halves' (render passes take seed, seed + 1, ...).
HALF_SEED = 500_000


def camera(positions, view: str):
    """(target, half width): :func:`validation.real_assets.camera`'s, and ``far`` = the frontal
    window FAR times as wide."""
    if view == "far":
        target, half = RA.camera(positions, "frontal")
        return target, FAR * half
    return RA.camera(positions, view)


def render_halves(scene, spp: int, seed: int):
    """Two renders of ``spp``/2 samples (at least 1) with independent seeds."""
    n = max(1, spp // 2)
    return H.render(scene, n, seed), H.render(scene, n, seed + HALF_SEED)


def relief_part(lum, mask, sigma_px: float):
    """The relief in a luminance image ``lum``: its pixels in ``mask`` minus a Gaussian blur of
    standard deviation ``sigma_px`` pixels over the mask alone (normalised convolution, so that the
    background and the silhouette add nothing): the detail a normal map draws, without the
    object's own shading, which falls off over its whole size."""
    m = mask.astype(np.float64)
    smooth = ndimage.gaussian_filter(lum * m, sigma_px, mode="constant")
    weight = ndimage.gaussian_filter(m, sigma_px, mode="constant")
    return (lum - smooth / np.maximum(weight, 1e-12))[mask]


def relief_variance(lum_halves, mask, sigma_px: float) -> float:
    """The variance of the relief (:func:`relief_part`) over the mask less a rim of 2·``sigma_px``
    (where the blur of a shading that changes across the silhouette would leave some of it), without
    the noise: the covariance of the two halves' reliefs, whose noise is independent (a converged
    render's variance, whatever the spp)."""
    inner = ndimage.binary_erosion(mask, iterations=max(1, math.ceil(2.0 * sigma_px)))
    inner = inner if inner.any() else mask
    h1, h2 = (relief_part(lum, mask, sigma_px)[inner[mask]] for lum in lum_halves)
    return float(np.mean(h1 * h2) - np.mean(h1) * np.mean(h2))


def split_metrics(halves, truth_halves, mask) -> dict:
    """relMSE, noise, bias² and bias²'s standard error (over the pixels of ``mask``) of the image
    whose two halves are ``halves`` against the truth's (module docstring), its energy and its
    relief contrast (the relief's standard deviation over the truth's, both without noise:
    :func:`relief_variance`; NaN where the truth shows none)."""
    t1, t2 = truth_halves
    t = 0.5 * (t1 + t2)
    k = H.EXPOSURE_MEAN / max(float(luminance(t)[mask].mean()), 1e-12)
    x1, x2 = halves[0] * k, halves[1] * k
    t, t1, t2 = t * k, t1 * k, t2 * k
    x = 0.5 * (x1 + x2)
    w = 1.0 / (t * t + EPS)
    err = (w * (x - t) ** 2)[mask].mean(axis=-1)
    noise = (w * 0.25 * (x1 - x2) ** 2)[mask].mean(axis=-1)
    truth_noise = (w * 0.25 * (t1 - t2) ** 2)[mask].mean(axis=-1)
    bias = err - noise - truth_noise
    sigma_px = RELIEF_BLUR * mask.shape[1]
    var_x = relief_variance((luminance(x1), luminance(x2)), mask, sigma_px)
    var_t = relief_variance((luminance(t1), luminance(t2)), mask, sigma_px)
    relief = math.sqrt(max(var_x, 0.0) / var_t) if var_t > 0 else math.nan
    return {"relief": relief, "relief_var": var_x, "truth_relief_var": var_t,
            "rel_mse": float(err.mean()), "noise": float(noise.mean()), "bias2": float(bias.mean()),
            "bias2_se": float(bias.std(ddof=1) / math.sqrt(max(bias.size, 2))),
            "truth_noise": float(truth_noise.mean()),
            "energy": float(luminance(x)[mask].mean() / max(float(luminance(t)[mask].mean()), 1e-12))}


def texels_per_pixel(prepared: dict, half: float, res: int) -> float:
    """The map's covered texels per pixel of a view ``half`` wide, facing the surface: covered
    texels per unit of the low-poly's area times a pixel's area."""
    positions, _, _, faces = prepared["low"]
    corners = positions[faces]
    area = 0.5 * np.linalg.norm(np.cross(corners[:, 1] - corners[:, 0], corners[:, 2] - corners[:, 0]), axis=1).sum()
    covered = prepared["tilt"]["mikktspace"]["covered"]
    return float(covered / area * (2.0 * half / res) ** 2)


def method_seconds(cell, prepared, methods, frame, target, half, res, spp, seed, integrator: str) -> dict:
    """Each method's warm seconds per render at ``spp``: the median of its timed renders over
    TIME_ROUNDS rounds, one method's scene loaded at a time (:func:`validation.real_assets.timed_renders`)."""
    runs = {}
    for _ in range(RA.TIME_ROUNDS):
        for m in methods:
            s = RA.method_scene(m, cell, prepared, frame, target, half, res, spp, integrator=integrator)
            runs.setdefault(m.key, []).extend(RA.timed_renders(s, spp, seed, RA.TIME_MIN_S / RA.TIME_ROUNDS))
            del s
            gc.collect()
    return {k: float(np.median([r[0] for r in v])) for k, v in runs.items()}


def render_cell(cell: RA.Cell, prepared: dict, methods, frame: str, res: int, spp: int, truth_spp: int,
                run_seed: int = 0, timing: bool = True, integrator: str = "path", log=print) -> dict:
    """One cell: the truth's halves, the floor's (the truth again at ``spp``) and every method's,
    their split metrics, and (``timing``) the equal-time relMSE; every scene with ``integrator``."""
    seed = H.cell_seed(cell, run_seed) * 1000
    positions = B.mesh_arrays(prepared["high"])[0]
    target, half = camera(positions, cell.view)
    prepared["high"].set_bsdf(mi.load_dict(H.MATERIALS[cell.material]))
    truth_scene = RA.scene(prepared["high"], cell, target, half, res, spp, integrator=integrator)
    mask = RA.object_mask([truth_scene, RA.scene(RA.low_mesh(prepared["low"], "mitsuba"), cell, target, half,
                                                 res, spp, integrator=integrator)], res)
    truth = render_halves(truth_scene, truth_spp, seed + 100)
    again = split_metrics(render_halves(truth_scene, spp, seed + 200), truth, mask)
    floor = abs(again["bias2"]) + 2.0 * again["bias2_se"]
    out = {"cell": cell.name, "spp": spp, "truth_spp": truth_spp, "mask_px": int(mask.sum()),
           "texels_per_pixel": texels_per_pixel(prepared, half, res), "floor": floor, "again": again,
           "metrics": {}}
    for m in methods:
        s = RA.method_scene(m, cell, prepared, frame, target, half, res, spp, integrator=integrator)
        out["metrics"][m.key] = split_metrics(render_halves(s, spp, seed), truth, mask)
        del s
        gc.collect()
    best = min(out["metrics"][c]["rel_mse"] for c in CLASSIC if c in out["metrics"])   # main() needs one
    out["best_classic"] = best
    out["resolved"] = bool(floor <= RESOLVED * best)
    for r in out["metrics"].values():
        r["le_classic"] = bool(r["rel_mse"] <= best + 2.0 * floor)
    if timing:
        seconds = method_seconds(cell, prepared, methods, frame, target, half, res, spp, seed, integrator)
        t_ref = min(seconds[c] for c in CLASSIC if c in seconds)
        for k, r in out["metrics"].items():
            n = spp * t_ref / seconds[k]
            r.update(seconds=seconds[k], time_ratio=seconds[k] / t_ref, equal_time_spp=n,
                     equal_time_rel_mse=r["bias2"] + r["noise"] * spp / n)
        best_t = min(out["metrics"][c]["equal_time_rel_mse"] for c in CLASSIC if c in out["metrics"])
        for r in out["metrics"].values():
            r["equal_time_le_classic"] = bool(r["equal_time_rel_mse"] <= best_t + 2.0 * floor)
    log(f"{cell.name}: floor {floor:.3g} ({'resolved' if out['resolved'] else 'NOT resolved'}), "
        + ", ".join(f"{k} {v['rel_mse']:.3g} (bias² {v['bias2']:.3g})" for k, v in out["metrics"].items()))
    return out


# -- Summary and report ------------------------------------------------------------------------

def summarise(cells: list, keys: list) -> dict:
    """Per group (all cells, each asset, material, lighting, view): the geometric means of each
    method's relMSE, noise and equal-time relMSE, the mean of its bias² (an estimate that can be
    below 0 where the bias is under the floor), the cells where it is ≤ the better classic, and
    the resolved cells."""
    out = {}
    for name, rs in RA.cell_groups(cells).items():
        row = {"cells": len(rs), "resolved": sum(c["resolved"] for c in rs),
               "floor": TG.geomean([c["floor"] for c in rs]), "methods": {}}
        for k in keys:
            ms = [c["metrics"][k] for c in rs if k in c["metrics"]]
            row["methods"][k] = {
                **_split_summary(ms), "le_classic": sum(m["le_classic"] for m in ms),
                "equal_time_rel_mse": TG.geomean([m.get("equal_time_rel_mse") for m in ms]),
                "time_ratio": float(np.median([m["time_ratio"] for m in ms])) if ms and "time_ratio" in ms[0] else None,
                "equal_time_le_classic": sum(m.get("equal_time_le_classic", False) for m in ms),
                **relief_summary([m["relief"] for m in ms])}
        again = [c["again"] for c in rs]
        row["again"] = {**relief_summary([a["relief"] for a in again]), **_split_summary(again)}
        out[name] = row
    return out


def _split_summary(ms) -> dict:
    """The geometric means of relMSE and noise over the split metrics ``ms`` and the mean of bias²
    (an estimate that can be below 0 within the floor)."""
    return {"rel_mse": TG.geomean([m["rel_mse"] for m in ms]), "bias2": float(np.mean([m["bias2"] for m in ms])),
            "noise": TG.geomean([m["noise"] for m in ms])}


def relief_summary(contrasts) -> dict:
    """The geometric mean of relief contrasts (NaN ones left out: a truth without relief) and how
    many are within RELIEF_TOLERANCE of 1, of how many."""
    ok = [c for c in contrasts if math.isfinite(c) and c > 0]
    return {"relief": TG.geomean(ok) if ok else math.nan,
            "relief_kept": sum(abs(c - 1.0) <= RELIEF_TOLERANCE for c in ok), "relief_cells": len(ok)}


def _relief(value) -> str:
    return f"{value:.2f}" if math.isfinite(value) else "–"


def markdown(report: dict, keys: list) -> str:
    s = report["settings"]
    L = [f"# Real assets, bias² and noise apart{' (quick run)' if s['quick'] else ''}", "",
         f"Generated by `{s['command']}` in {s['elapsed_s'] / 60:.1f} min ({len(report['cells'])} cells; "
         f"Mitsuba {mi.__version__}, `{s['variant']}`, integrator `{s['integrator']}`); {s['res']}² px, "
         f"methods at {s['spp']} spp, the truth at {s['truth_spp']}, each as two independent halves; the "
         f"plugin's maps in the {s['frame']} frame. The method: `validation/real_assets_split.py`'s "
         "docstring and docs/validation.md.", "",
         "relMSE at equal spp = bias² + noise (geometric means; bias²: the arithmetic mean, an estimate that can fall below 0 within the floor); the floor: what a bias² estimate resolves (the truth again: "
         "|bias²| + 2 standard errors); resolved: floor ≤ 1/10 of the better classic's relMSE; ≤classic: "
         "relMSE ≤ the better classic's + 2 floors. Equal time: relMSE at the spp each method gets in the "
         "faster classic setting's time (bias² + noise·spp/n), geometric means; time: the median ratio of "
         "seconds per render to the faster classic's. Relief: the relief contrast, the standard deviation "
         "of the luminance's detail over the object (each image less its Gaussian blur of "
         f"{RELIEF_BLUR * s['res']:.0f} px) over the truth's, both without noise (the covariance of the "
         "two halves' details), geometric means; kept: cells within "
         f"±{RELIEF_TOLERANCE:.0%} of the truth's; the truth rendered again at the methods' spp shows "
         "what the instrument resolves, and its noise (its bias² is 0 up to the floor) the noise of a "
         "method that drew the truth exactly at that spp.", ""]
    for name, row in report["summary"].items():
        L += [f"## {name} ({row['cells']} cells, {row['resolved']} resolved; floor {TG.fmt(row['floor'])}; "
              f"relief of the truth again {_relief(row['again']['relief'])})", "",
              "| method | relMSE | bias² | noise | ≤classic | equal time: relMSE | ≤classic | time "
              "| relief | kept |",
              "|---|---|---|---|---|---|---|---|---|---|"]
        # (The truth rendered again at the methods' spp: its bias² is 0 up to the floor, its noise
        # that of a method that drew the truth exactly.)
        again = row["again"]
        L.append(f"| *the truth again* | {TG.fmt(again['rel_mse'])} | {TG.fmt(again['bias2'])} | "
                 f"{TG.fmt(again['noise'])} | – | – | – | – "
                 f"| {_relief(again['relief'])} | {again['relief_kept']}/{again['relief_cells']} |")
        for k in keys:
            m = row["methods"][k]
            t = "–" if m["time_ratio"] is None else f"{m['time_ratio']:.2f}×"
            kept = f"{m['relief_kept']}/{m['relief_cells']}"
            L.append(f"| {k} | {TG.fmt(m['rel_mse'])} | {TG.fmt(m['bias2'])} | {TG.fmt(m['noise'])} | "
                     f"{m['le_classic']}/{row['cells']} | {TG.fmt(m['equal_time_rel_mse'])} | "
                     f"{m['equal_time_le_classic']}/{row['cells']} | {t} | {_relief(m['relief'])} | {kept} |")
        L.append("")
    L += ["## Per cell", "", "| cell | texels/px | floor | resolved | the truth's noise | " + " | ".join(
          f"{k} relMSE (bias²)" for k in keys) + " |", "|---|---|---|---|---|" + "---|" * len(keys)]
    for c in report["cells"]:
        L.append(f"| {c['cell']} | {c['texels_per_pixel']:.0f} | {TG.fmt(c['floor'])} | "
                 f"{'yes' if c['resolved'] else 'no'} | {TG.fmt(c['again']['noise'])} | " + " | ".join(
                     f"{TG.fmt(c['metrics'][k]['rel_mse'])} ({TG.fmt(c['metrics'][k]['bias2'])})" for k in keys) + " |")
    L += ["", "## Relief contrast per cell", "", "| cell | truth again | " + " | ".join(keys) + " |",
          "|---|---|" + "---|" * len(keys)]
    for c in report["cells"]:
        L.append(f"| {c['cell']} | {_relief(c['again']['relief'])} | "
                 + " | ".join(_relief(c["metrics"][k]["relief"]) for k in keys) + " |")
    return "\n".join(L) + "\n"


def parse_args(argv=None):
    p = RA.cell_arguments(__doc__, OUT, FULL, f"method keys or plugin:MODEL specs (default: "
                          f"{','.join(METHODS)}); one of {' or '.join(CLASSIC)} is needed")
    for name in ("res", "spp", "truth_spp", "faces", "map_size"):
        p.add_argument("--" + name.replace("_", "-"), type=int, default=None)
    p.add_argument("--integrator", choices=RA.INTEGRATORS, default="path")
    p.add_argument("--frame", choices=B.TANGENT_FRAMES, default="mikktspace")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--no-timing", action="store_true", help="equal spp only")
    return p.parse_args(argv)


def options(args) -> dict:
    base = QUICK if args.quick else FULL
    opts = {k: getattr(args, k) if getattr(args, k, None) is not None else base[k] for k in base}
    for name, table in (("assets", RA.ASSETS), ("materials", H.MATERIALS), ("lightings", RA.LIGHTINGS),
                        ("views", VIEWS)):
        unknown = [v for v in opts[name] if v not in table]
        if unknown:
            sys.exit(f"unknown {name}: {', '.join(unknown)}; use {', '.join(table)}")
    for name in ("res", "spp", "truth_spp"):
        if opts[name] < 2:
            sys.exit(f"--{name.replace('_', '-')} {opts[name]}: expected at least 2 (two halves)")
    return opts


def main(argv=None):
    args = parse_args(argv)
    opts = options(args)
    methods = [H.method_from_spec(k) for k in (args.methods or METHODS)]
    keys = [m.key for m in methods]
    if not any(k in CLASSIC for k in keys):
        sys.exit(f"--methods needs {' or '.join(CLASSIC)} (the reference); got {','.join(keys)}")
    mi.set_variant(args.variant)
    import mfnormal

    mfnormal.register()
    t_start = time.time()
    prepared = {a: RA.prepare(a, opts["faces"], opts["map_size"]) for a in opts["assets"]}
    cells = [render_cell(RA.Cell(*c), prepared[c[0]], methods, args.frame, opts["res"], opts["spp"],
                         opts["truth_spp"], args.seed, not args.no_timing, args.integrator)
             for c in itertools.product(opts["assets"], opts["materials"], opts["lightings"], opts["views"])]
    command = "nice .venv/bin/python -m validation.real_assets_split" + "".join(f" {a}" for a in (argv or sys.argv[1:]))
    report = {"settings": {**opts, "quick": args.quick, "frame": args.frame, "variant": args.variant,
                           "integrator": args.integrator, "command": command, "methods": keys,
                           "elapsed_s": time.time() - t_start},
              "cells": cells, "summary": summarise(cells, keys)}
    args.out.mkdir(parents=True, exist_ok=True)
    stem = "real_assets_split_quick" if args.quick else "real_assets_split"
    md, js = markdown(report, keys), json.dumps(report, indent=1, default=float)
    atomic_write(args.out / f"{stem}.json", lambda p: Path(p).write_text(js))
    atomic_write(args.out / f"{stem}.md", lambda p: Path(p).write_text(md))
    print(f"wrote {args.out / stem}.{{md,json}} in {(time.time() - t_start) / 60:.1f} min")


if __name__ == "__main__":
    main()
