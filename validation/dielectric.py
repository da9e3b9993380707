"""Normal-mapped water and glass against the true geometry the map was baked from.

    nice .venv/bin/python -m validation.dielectric [--quick] [--out validation/results]
        [--materials water,rough_glass] [--steepness mild,steep] [--views oblique40,grazing,inside40]
        [--methods nomap,classic,...,plugin:MODEL] [--res 64] [--spp 64] [--ref-factor 4] [--seed 0]
        [--registered]

The cells: a flat dielectric interface (the plane z = mean height of
:mod:`validation.heightfield`) carrying the normal map baked from an egg-crate
heightfield (max tilt 20°, mild, or 50°, steep; two periods across the image), smooth
water (``dielectric``, ior 1.33) or rough glass (``roughdielectric``, GGX α 0.15,
ior 1.5), under the harness's sky (no sun: a delta light cannot reach the floor through
a smooth interface). Seen from above (40° and 75° from the normal), a diffuse
checkerboard floor lies :data:`FLOOR_DEPTH` below the surface; seen from inside
(``inside40``: the camera below the surface, looking up at 40° from its normal), there is
no floor: the sky through the surface, and what total internal reflection sends down
(the sky's ground). The truth is the dense displaced mesh of the same heightfield with
the same dielectric, rendered by Mitsuba's ``path`` (max_depth :data:`MAX_DEPTH`).

Methods (:data:`DEFAULT_METHODS`): the un-mapped interface, Mitsuba's ``normalmap``
(fixes off and on) around the same dielectric, ``normalmap_microfacet``'s default
model and the paper's models. A method whose scene does not load (a model that refuses
a transmitting nested BSDF) is recorded as refused, with its message.

Per cell and method: relMSE to the truth (metered exposure, as in
:func:`validation.heightfield.metrics`), its bias part (relMSE of 4 × 4-pixel block
means), the energy ratio (mean luminance / the truth's), the share of near-black pixels
where the truth is not near-black, and the noise floor (the truth rendered again at the
methods' spp with another seed). Before the cells, the harness checks itself
(:func:`flat_check`): a flat heightfield's displaced mesh must render like the plane.

``--registered`` renders every method on the normal map registered for the camera
(:func:`validation.heightfield.registered_map`: each camera ray reads the texel where it meets the
true surface, as a perfect parallax lookup would), which separates the error of where each texel
is seen from the error of what it shows.

Writes ``dielectric.md``, ``.json`` and ``.png`` (contact sheet) to ``--out``; ``--quick``
writes ``dielectric_quick.*`` (a 4-cell subset at 32² px, under a minute); ``--registered``
appends ``_registered`` to the name.
"""

from __future__ import annotations

import argparse
import itertools
import json
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
from validation import true_geometry as TG  # noqa: E402
from mfnormal.files import atomic_write  # noqa: E402

#: Max tilt (degrees) of the egg crate per steepness.
STEEPNESS = {"mild": 20.0, "steep": 50.0}
MATERIALS = ("water", "rough_glass")
VIEWS = ("oblique40", "grazing", "inside40")
#: The checkerboard floor's depth below the surface, world units (the image is 1 wide).
FLOOR_DEPTH = 0.25
MAX_DEPTH = 12
BIAS_BLOCK = 4
DEFAULT_METHODS = ("nomap", "classic", "classic_fixed", "plugin:", "analytic", "separable_specular",
                   "separable_same", "nonseparable_specular", "nonseparable_same")
FULL = dict(materials=list(MATERIALS), steepness=list(STEEPNESS), views=list(VIEWS), res=64, spp=64,
            ref_factor=4)
QUICK = dict(materials=["water", "rough_glass"], steepness=["mild", "steep"], views=["oblique40"],
             res=32, spp=16, ref_factor=4)


def harness_parser(module: str, doc: str, quick: str) -> argparse.ArgumentParser:
    """The options this harness and :mod:`validation.furnace_glass` share: --out, --quick (``quick``:
    its help), --methods, --seed; the module's docstring ``doc`` is the help's text."""
    p = argparse.ArgumentParser(prog=f"python -m {module}", description=doc.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter, epilog=doc)
    p.add_argument("--out", type=Path, default=ROOT / "out" / "validation")
    p.add_argument("--quick", action="store_true", help=quick)
    p.add_argument("--methods", type=H.split_methods, default=list(DEFAULT_METHODS),
                   help="validation.heightfield method keys or plugin:MODEL[:FACET][,k=v] ('plugin:': "
                        "the plugin's default model)")
    p.add_argument("--seed", type=int, default=0)
    return p


def parse_args(argv=None):
    p = harness_parser("validation.dielectric", __doc__, "4 cells at 32² px, 16 spp (under a minute)")
    for name in ("materials", "steepness", "views"):
        p.add_argument(f"--{name}", type=lambda s: s.split(","), default=None,
                       help=f"comma-separated subset (default: {','.join(FULL[name])})")
    p.add_argument("--res", type=int, default=None)
    p.add_argument("--spp", type=int, default=None, help="per method render")
    p.add_argument("--ref-factor", type=int, default=None, help="truth reference spp = this × spp")
    p.add_argument("--registered", action="store_true",
                   help="every method on the normal map registered for the camera (each camera ray "
                        "reads the texel where it meets the true surface: a perfect parallax lookup); "
                        "writes dielectric_registered.*")
    return p.parse_args(argv)


def method(spec: str) -> H.Method:
    """A harness method; ``plugin:`` alone is keyed ``default`` (the plugin's default model)."""
    if spec == "plugin:":
        return H.plugin_method(None, key="default", label="default")
    return H.method_from_spec(spec)


def cell(material: str, steepness: str, view: str) -> H.Cell:
    """One dielectric cell: the egg crate, the sky, the floor for views from above."""
    floor = 0.0 if H.VIEWS[view].theta > 90.0 else FLOOR_DEPTH
    return H.Cell("eggcrate", STEEPNESS[steepness], material, "sky", view, "magnified", floor=floor)


def cells(materials, steepness, views) -> list:
    # Material innermost: consecutive cells share the truth scene (its BVH is built once).
    return [cell(m, s, v) for s, v, m in itertools.product(steepness, views, materials)]


# ---------------------------------------------------------------------------
# Metrics
# ---------------------------------------------------------------------------

def dielectric_metrics(img: np.ndarray, truth: np.ndarray) -> dict:
    """:func:`validation.heightfield.metrics` plus ``bias`` (relMSE of :data:`BIAS_BLOCK`² block
    means, metered like relMSE: the part of the error that is not pixel noise), ``energy``
    (mean luminance / the truth's) and ``near_black_new`` (the share of pixels near-black in
    ``img`` and not in ``truth``)."""
    m = H.metrics(img, truth)
    k = H.exposure_scale(truth)
    m["bias"] = H.rel_mse(H.block_mean(img * k, BIAS_BLOCK), H.block_mean(truth * k, BIAS_BLOCK))
    m["energy"] = m["mean"] / max(float(H.luminance(truth).mean()), 1e-12)
    threshold = H.near_black_threshold(truth)
    m["near_black_new"] = float(np.mean((H.luminance(img) < threshold) & (H.luminance(truth) >= threshold)))
    return m


def measure_cell(c: H.Cell, methods, res: int, spp: int, ref_factor: int, seed: int,
                 registered: bool = False) -> dict:
    """:func:`validation.heightfield.render_cell` of ``c`` (max_depth :data:`MAX_DEPTH`; ``registered``:
    the methods on the registered normal map), scored with :func:`dielectric_metrics`; ``floor`` is
    the truth at spp, scored the same way."""
    r = H.render_cell(c, methods, res=res, spp=spp, ref_factor=ref_factor, max_depth=MAX_DEPTH,
                      seed=seed, registered=registered)
    r["metrics"] = {k: dielectric_metrics(r["images"][k], r["truth"]) for k in r["metrics"]}
    r["floor"] = dielectric_metrics(r["images"]["truth"], r["truth"])
    return r


def flat_check(material: str, view: str, res: int, spp: int, seed: int) -> dict:
    """The harness against itself: a flat heightfield (amplitude 0) as the dense displaced mesh
    and as the two-triangle plane, the same dielectric, no map. Returns the mesh's metrics
    against the plane's reference (4× spp) as ``mesh``, the noise floor (the plane at spp with
    another seed against that reference) as ``floor``, and ``same_seed``: relMSE of the mesh
    against the plane rendered with the mesh's seed (common random numbers: the same paths but
    for round-off in the intersections). An exact harness gets mesh ≈ floor, energy ≈ 1 and
    same_seed ≪ floor."""
    flat = H.Heightfield("eggcrate", 2, 0.0)
    floor = 0.0 if H.VIEWS[view].theta > 90.0 else FLOOR_DEPTH
    kw = dict(lighting="sky", view=view, res=res, spp=spp, max_depth=MAX_DEPTH, floor=floor)
    nested = H.MATERIALS[material]
    ref = H.render(H.scene_dict(flat, "plane", nested, **kw), 4 * spp, seed * 1000 + 100)
    mesh = H.render(H.scene_dict(flat, "true", nested, verts_per_period=64, **kw), spp, seed * 1000)
    plane_scene = mi.load_dict(H.scene_dict(flat, "plane", nested, **kw))
    plane = H.render(plane_scene, spp, seed * 1000 + 500)
    same = H.render(plane_scene, spp, seed * 1000)
    k = H.exposure_scale(ref)
    return {"material": material, "view": view, "mesh": dielectric_metrics(mesh, ref),
            "floor": dielectric_metrics(plane, ref), "same_seed": H.rel_mse(mesh * k, same * k)}


# ---------------------------------------------------------------------------
# Summary
# ---------------------------------------------------------------------------

def groups(cell_names) -> dict:
    """Cell subsets of the summary: name → predicate on the cell name."""
    g = {"all cells": lambda c: True,
         "mild (max tilt 20°)": lambda c: c.split("/")[1] == "20deg",
         "steep (max tilt 50°)": lambda c: c.split("/")[1] == "50deg",
         "floor through the surface": lambda c: "/floor" in c,
         "from inside": lambda c: "/inside" in c}
    for mat in MATERIALS:
        g[f"material {mat}"] = lambda c, mat=mat: c.split("/")[2] == mat
    return {k: v for k, v in g.items() if any(v(c) for c in cell_names)}


def _best_classic(r):
    have = [r["metrics"][c]["rel_mse"] for c in ("classic", "classic_fixed") if c in r["metrics"]]
    return min(have) if have else None


def summarise(results, keys) -> dict:
    """Per group: the floor's and each method's geometric means of relMSE and its bias part, the
    mean and range of the energy ratio (a method can render nothing: 0 has no geometric mean),
    the mean near-black share, and the cells where the method is ≤ the better classic and < the
    un-mapped plane."""
    out = {}
    for gname, pred in groups([r["cell"] for r in results]).items():
        rs = [r for r in results if pred(r["cell"])]
        row = {"cells": len(rs), "floor_rel_mse": TG.geomean([r["floor"]["rel_mse"] for r in rs]),
               "floor_bias": TG.geomean([r["floor"]["bias"] for r in rs]), "methods": {}, "refused": {}}
        for k in keys:
            have = [r for r in rs if k in r["metrics"]]
            row["refused"][k] = sum(1 for r in rs if k in r["errors"])
            if not have:
                continue
            m = [r["metrics"][k] for r in have]
            row["methods"][k] = {
                "cells": len(have), "rel_mse": TG.geomean([x["rel_mse"] for x in m]),
                "bias": TG.geomean([x["bias"] for x in m]),
                "energy": float(np.mean([x["energy"] for x in m])),
                "energy_range": [min(x["energy"] for x in m), max(x["energy"] for x in m)],
                "near_black_new": float(np.mean([x["near_black_new"] for x in m])),
                "le_classic": sum(1 for r in have if _best_classic(r) is not None
                                  and r["metrics"][k]["rel_mse"] <= _best_classic(r)),
                "lt_nomap": sum(1 for r in have if "nomap" in r["metrics"]
                                and r["metrics"][k]["rel_mse"] < r["metrics"]["nomap"]["rel_mse"])}
        out[gname] = row
    return out


# ---------------------------------------------------------------------------
# Markdown
# ---------------------------------------------------------------------------

def _pct(x):
    return "–" if x is None else f"{100 * x:.2f} %"


def _setup(settings) -> list:
    return [
        f"Generated by `{settings['command']}` in {settings['elapsed_s'] / 60:.1f} min "
        f"({settings['cells']} cells; Mitsuba {mi.__version__}, `llvm_ad_rgb`).", "",
        "**Setup** (`validation.dielectric`, on `validation.heightfield`): an egg-crate heightfield "
        f"(two periods across the image; max tilt {STEEPNESS['mild']:g}° mild, {STEEPNESS['steep']:g}° "
        "steep) is the surface of smooth water (`dielectric`, ior 1.33) or rough glass (`roughdielectric`, "
        "GGX α 0.15, ior 1.5). The truth: the dense displaced mesh (64 vertices per period, analytic vertex "
        "normals) with that dielectric; the methods: a two-triangle plane at the mean height with the normal "
        "map baked from the same heights (24 texels per period) around the same dielectric. Views: 40° "
        "(`oblique40`) and 75° (`grazing`) from the normal, a diffuse checkerboard floor (reflectance "
        f"0.1 / 0.7, checks 1/8 wide) {FLOOR_DEPTH:g} below the surface; `inside40`: the camera below the "
        "surface looking up, 40° from its normal, no floor (the sky through the surface, the sky's ground "
        "where total internal reflection sends the view down). The harness's sky, no sun (a delta light "
        "cannot reach the floor through a smooth interface). Orthographic camera, the surface fills the "
        f"frame; `path`, max_depth {MAX_DEPTH}, multi-jittered sampling, {settings['res']}² px, the "
        f"methods at {settings['spp']} spp, the truth's reference at {settings['ref_factor']}× that.", "",
        "**Metrics**: relMSE = mean((x − ref)²/(ref² + 1e-2)) after a metered exposure (both images "
        "scaled so the truth's mean luminance is 0.5); bias part = the same on 4 × 4-pixel block means "
        "(the error that is not pixel noise); energy = mean luminance / the truth's; near-black = the "
        "share of pixels whose luminance is below 5 % of the truth's median where the truth's is not; "
        "noise floor = the truth rendered again at the methods' spp with another seed, scored like a "
        "method. Summaries: geometric means of relMSE and bias part over the cells, the mean (and range) "
        "of the energy ratio, the mean near-black share; `≤ classic`: cells where the method's relMSE ≤ the better of "
        "Mitsuba's `normalmap` with fixes off and on; `< no map`: cells where it is below the un-mapped "
        "plane's.", ""]


def _registered_section() -> list:
    return [
        "**Registered** (`--registered`): every method renders the plane with the normal map registered "
        "for the camera (`validation.heightfield.registered_map`, at 4× the map's resolution): at each "
        "point of the plane, the texel where the camera ray through it meets the true surface. So every "
        "camera ray shades the texel the true geometry shows there, as a perfect parallax (relief) lookup "
        "would; rays that meet the surface later in a path (up from the floor, back from the sky's "
        "ground) read the same map, registered for the camera, not for them, and every ray still leaves "
        "from the plane. Against the same cells without registration (`dielectric.md`) this separates "
        "the error of where each texel is seen (parallax) from the error of what it shows.", ""]


def _flat_section(checks) -> list:
    L = ["## The harness against itself", "",
         "A flat heightfield (amplitude 0) as the dense displaced mesh against the two-triangle plane, "
         "the same dielectric, no map (the plane's reference at 4× the methods' spp): the mesh must score "
         "like the noise floor and keep the plane's energy; with the plane's own seed (common random "
         "numbers: the same paths, but for round-off in the intersections) it must match the plane "
         "far below the noise.", "",
         "| material | view | mesh relMSE | noise floor | mesh energy / plane | relMSE, same seed |",
         "|---|---|---|---|---|---|"]
    for c in checks:
        L.append(f"| {c['material']} | {c['view']} | {TG.fmt(c['mesh']['rel_mse'])} | "
                 f"{TG.fmt(c['floor']['rel_mse'])} | {TG.fmt(c['mesh']['energy'], 4)} | "
                 f"{TG.fmt(c['same_seed'])} |")
    return L + [""]


def _summary_section(summary, keys, labels) -> list:
    L = ["## Summary", ""]
    for gname, row in summary.items():
        L += [f"### {gname} ({row['cells']} cells)", ""]

        def line(k, m, row=row):
            lo, hi = m["energy_range"]
            return (f"| {labels.get(k, k)} | {TG.fmt(m['rel_mse'])} | {TG.fmt(m['bias'])} | "
                    f"{TG.fmt(m['energy'], 3)} ({TG.fmt(lo, 2)}–{TG.fmt(hi, 2)}) | {_pct(m['near_black_new'])} | "
                    f"{m['le_classic']}/{m['cells']} | {m['lt_nomap']}/{m['cells']} |")
        refused = {k: f"| {labels.get(k, k)} | refused in {n} of {row['cells']} cells | | | | | |"
                   for k, n in row["refused"].items() if n == row["cells"]}
        TG.method_table(L, "| method | relMSE | bias part | energy (range) | near-black | ≤ classic | < no map |",
                        f"| *noise floor* | {TG.fmt(row['floor_rel_mse'])} | {TG.fmt(row['floor_bias'])} | 1 | "
                        "| | |", keys,
                        row["methods"], line, refused)
    return L


def _cells_section(results, keys, labels) -> list:
    L = ["## Cells", "", "Per cell: heightfield / max tilt / material / lighting / view / magnification "
         "(/ floor depth); render time per method.", ""]
    for i, r in enumerate(results):
        L += [f"### {i + 1}. {r['cell']}", "",
              f"{r['spp']} spp (truth {r['ref_spp']}); truth mean luminance {TG.fmt(r['truth_stats']['mean'])}, "
              f"near-black {_pct(r['truth_stats']['near_black'])}.", ""]

        def line(k, m, r=r):
            bad = r.get("invalid", {}).get(k, {})
            flag = "" if not any(bad.values()) else f" ({bad['nonfinite']} NaN/Inf, {bad['negative']} < 0)"
            return (f"| {labels.get(k, k)} | {TG.fmt(m['rel_mse'])} | {TG.fmt(m['bias'])} | "
                    f"{TG.fmt(m['energy'], 3)} | {_pct(m['near_black_new'])} | {r['times'].get(k, 0):.1f}{flag} |")
        errors = {k: f"| {labels.get(k, k)} | refused: {e} | | | | |" for k, e in r["errors"].items()}
        f = r["floor"]
        TG.method_table(L, "| method | relMSE | bias part | energy | near-black | time (s) |",
                        f"| *noise floor* | {TG.fmt(f['rel_mse'])} | {TG.fmt(f['bias'])} | "
                        f"{TG.fmt(f['energy'], 3)} | {_pct(f['near_black_new'])} | {r['times'].get('truth', 0):.1f} |",
                        keys, r["metrics"], line, errors)
    return L


def markdown(report: dict, labels: dict, quick: bool = False) -> str:
    """The report of :func:`run` (``report``: its JSON data) as Markdown."""
    s = report["settings"]
    keys = s["methods"]
    L = ["# Normal-mapped dielectrics against true geometry" + (" (quick run)" if quick else ""), ""]
    L += _setup(s)
    if s.get("registered"):
        L += _registered_section()
    L += _flat_section(report.get("flat_checks", []))
    if report.get("summary"):
        L += _summary_section(report["summary"], keys, labels)
    L += [f"![contact sheet: per cell the truth, then each method]({s['stem']}.png)", ""]
    L += _cells_section(report.get("cells", []), keys, labels)
    return "\n".join(L) + "\n"


# ---------------------------------------------------------------------------

def run(args) -> dict:
    """Render the flat checks and the cells; write the report files. Returns the report data."""
    base = QUICK if args.quick else FULL
    opts = {k: getattr(args, k) if getattr(args, k, None) is not None else base[k] for k in base}
    for name, known in (("materials", MATERIALS), ("steepness", STEEPNESS), ("views", VIEWS)):
        unknown = [v for v in opts[name] if v not in known]
        if unknown:
            sys.exit(f"unknown {name}: {', '.join(unknown)}; use {', '.join(known)}")
    methods = [method(s) for s in args.methods]
    keys = [m.key for m in methods]
    labels = {"truth": "truth", **{m.key: m.label for m in methods}}
    registered = bool(getattr(args, "registered", False))
    stem = ("dielectric_quick" if args.quick else "dielectric") + ("_registered" if registered else "")
    res, spp, rf = opts["res"], opts["spp"], opts["ref_factor"]
    t_start = time.time()
    checks = [flat_check(mat, view, res, spp, 17 + args.seed) for mat in opts["materials"]
              for view in opts["views"]]
    results = []
    for i, c in enumerate(cells(opts["materials"], opts["steepness"], opts["views"])):
        t0 = time.time()
        results.append(measure_cell(c, methods, res, spp, rf, H.cell_seed(c, args.seed), registered))
        print(f"[{i + 1}] {c.name}: {time.time() - t0:.1f} s", flush=True)
    report = {"flat_checks": checks, "cells": [TG.strip_images(r) for r in results],
              "summary": summarise(results, keys)}
    report["settings"] = {"command": command("validation.dielectric", args.argv), "elapsed_s": time.time() - t_start, "cells": len(results),
                          "res": res, "spp": spp, "ref_factor": rf, "seed": args.seed, "methods": keys,
                          "registered": registered,
                          "stem": stem, "method_about": {m.key: m.about for m in methods}}
    write(report, results, labels, args.out, stem, args.quick)
    return report


def short_name(cell_name: str) -> str:
    """A cell's name without what every dielectric cell shares (the egg crate, the sky, the
    magnification): ``20deg / water / oblique40 / floor0.25``."""
    shared = {"eggcrate", "sky", "magnified"}
    return " / ".join(p for p in cell_name.split("/") if p not in shared)


def thumb_size(res: int) -> int:
    """Contact-sheet thumbnails: ``res`` px renders shrunk by an integer factor to ≥ 48 px, small
    ones enlarged by an integer factor to ≤ 64 px."""
    return res // max(1, res // 48) if res >= 48 else res * max(1, 64 // res)


def write(report, results, labels, out: Path, stem: str, quick: bool):
    """``stem``.md, .json and .png (the contact sheet of ``results``) in ``out``."""
    write_text_files(out, stem, markdown(report, labels, quick), report)
    for i, r in enumerate(results):
        r["index"] = i + 1
        r["label"] = short_name(r["cell"])
    if results:
        res = report["settings"]["res"]
        TG.contact_sheet(results, report["settings"]["methods"], labels, out / f"{stem}.png",
                         size=thumb_size(res), title="truth, then each method; one exposure per row")
    print(f"wrote {out / stem}.{{md,json,png}}")


def command(module: str, argv) -> str:
    """The command line that reproduces a run of ``module`` with ``argv``."""
    return f"nice .venv/bin/python -m {module}" + (" " + " ".join(argv) if argv else "")


def write_text_files(out: Path, stem: str, md: str, report: dict):
    """``stem``.md (``md``) and ``stem``.json (``report``) in ``out``, atomically."""
    out.mkdir(parents=True, exist_ok=True)
    atomic_write(out / f"{stem}.md", lambda p: Path(p).write_text(md))
    atomic_write(out / f"{stem}.json", lambda p: Path(p).write_text(json.dumps(report, indent=1, default=float)))


def main(argv=None, parse=None, runner=None):
    """Parse ``argv`` with ``parse`` (default :func:`parse_args`) and run ``runner`` (default
    :func:`run`) on it, the arguments kept as ``args.argv`` for the report's command line."""
    args = (parse or parse_args)(argv)
    args.argv = list(sys.argv[1:] if argv is None else argv)
    (runner or run)(args)


if __name__ == "__main__":
    main()
