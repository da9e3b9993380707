"""Re-run the validation of the random-walk models and write its figures and tables.

    .venv/bin/python -m validation.run [--out validation/results] [--quick]

Writes PNG figures and ``RESULTS.md`` (tables with the measured numbers) to ``--out``:

- ``microgeometry_polar.png``: exit distributions of the ray-traced sawtooth mesh
  (Mitsuba's own ray tracer on real microgeometry, ``validation/reference/microgeometry.py``) next to
  the ``nonseparable`` and ``separable`` models, on polar axes;
- ``l1_distances.png``: L1 distance of each model to the ray-traced reference;
- ``furnace.png``: white-furnace albedo of every model against θ_i;
- ``variance.png``: variance of the non-separable ``eval``: naive sampled height
  against the supplemental's interval tracking;
- ``mis_pdf.png``: total-variation distance between the MIS pdf (its density part,
  ``mis_boost_max=1``) and the walk's actual sampling density.

The references are :mod:`validation.reference` (independent of the model code: a ray
tracer of real microgeometry, the naive sampled-height estimator), which the tests share.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

import mfnormal  # noqa: E402  (first: selects a working libLLVM)

import drjit as dr  # noqa: E402
import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

WHITE = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}
GGX = {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3, "material": "none"}
WALKS = [("separable", "specular"), ("separable", "same"), ("nonseparable", "specular"), ("nonseparable", "same")]


def sph(theta_deg, phi_deg=0.0):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def make_bsdf(model, tangent_facet, theta_p_deg, nested=WHITE, **params):
    tex = np.zeros((1, 1, 3), np.float32)
    tex[...] = sph(theta_p_deg) * 0.5 + 0.5
    d = {"type": "normalmap_microfacet", "model": model,
         "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(tex), "raw": True, "filter_type": "nearest"},
         "bsdf": nested}
    if model != "analytic":
        d["tangent_facet"] = tangent_facet
    return mi.load_dict({**d, **params})


def interaction(wi, n, p_offset=0):
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = mi.Vector3f(*[float(x) for x in wi])
    si.p = mi.Point3f(dr.arange(mi.Float, n) + p_offset, 0.0, 0.0)
    return si


def sample(bsdf, wi, n, seed):
    rng = np.random.default_rng(seed)
    u = rng.random((3, n), dtype=np.float32)
    bs, w = bsdf.sample(mi.BSDFContext(), interaction(wi, n), mi.Float(u[0]), mi.Point2f(u[1], u[2]))
    return np.array(bs.wo).T, np.array(w)[0] if np.array(w).ndim == 2 and np.array(w).shape[0] == 3 else np.array(w)


def bar_chart(path, labels, bars, ylabel, title=None, log=False, figsize=(8, 3.5), fontsize=6, rotation=90):
    """A bar chart of one or more named series (``bars``: {name: values}) over ``labels``, saved to ``path``."""
    import matplotlib.pyplot as plt
    fig, ax = plt.subplots(figsize=figsize)
    x = np.arange(len(labels))
    width = 0.8 / len(bars)
    for k, (name, values) in enumerate(bars.items()):
        ax.bar(x + (k - (len(bars) - 1) / 2) * width, values, width, label=name)
    if log:
        ax.axhline(1.0, color="k", lw=0.5)
        ax.set_yscale("log")
    ax.set_xticks(x, labels, rotation=rotation, fontsize=fontsize)
    ax.set_ylabel(ylabel)
    if title:
        ax.set_title(title)
    if len(bars) > 1:
        ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=90)
    plt.close(fig)


def cosine_directions(n, seed):
    """Stratified cosine-weighted directions (pdf = cosθ/π)."""
    rng = np.random.default_rng(seed)
    u = (np.arange(n) + rng.random(n)) / n
    v = rng.random(n)
    r, phi = np.sqrt(u), 2 * np.pi * v
    return np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(np.maximum(1 - u, 0))], -1)


# -- Figures -------------------------------------------------------------------------------


def microgeometry(out, quick, results):
    import matplotlib.pyplot as plt
    from validation.reference import microgeometry as mg

    n = 200_000 if quick else 1_000_000
    cases = [(60, 70, 0, WHITE, "specular", "Lambert p, mirror t"),
             (60, 70, 0, WHITE, "same", "Lambert p and t"),
             (30, 70, 180, WHITE, "specular", "Lambert p, mirror t"),
             (60, 20, 180, GGX, "specular", "GGX 0.3 p, mirror t")]
    rows = []
    fig, axes = plt.subplots(len(cases), 3, subplot_kw={"projection": "polar"}, figsize=(10, 3.2 * len(cases)))
    for row, (tp, ti, pi_, nested, tf, label) in enumerate(cases):
        h = mg.compare_histograms(tp, ti, pi_, nested, tf, n=n, seed=row)
        ce, pe = h["cos_edges"], h["phi_edges"]
        solid = np.outer(np.diff(ce), np.diff(pe))
        r_edges = np.sqrt(1 - ce ** 2)[::-1]  # radius = sinθ, outer ring = horizon
        for col, key in enumerate(["reference", "nonseparable", "separable"]):
            density = (h[key][0] / solid)[::-1]
            ax = axes[row, col]
            ax.pcolormesh(pe, r_edges, density, shading="flat", vmin=0,
                          vmax=(h["reference"][0] / solid).max())
            ax.set_yticklabels([])
            ax.set_xticklabels([])
            name = {"reference": "ray-traced mesh"}.get(key, key)
            extra = "" if key == "reference" else f"\nL1 = {h['l1'][key]:.3f}"
            ax.set_title(f"{name}{extra}", fontsize=9)
        axes[row, 0].set_ylabel(f"{label}\nθp={tp}° θi={ti}° φi={pi_}°", labelpad=30, fontsize=9)
        rows.append({"case": f"{label}, θp={tp}, θi={ti}, φi={pi_}", **{k: round(v, 4) for k, v in h["l1"].items()}})
    fig.suptitle("Exit radiance f·cosθ_o (polar: radius sinθ_o, angle φ_o; φ=0 toward the tilt)")
    fig.tight_layout()
    fig.savefig(out / "microgeometry_polar.png", dpi=90)
    plt.close(fig)

    bar_chart(out / "l1_distances.png", [r["case"].replace(", θ", "\nθ") for r in rows],
              {m: [r[m] for r in rows] for m in ("nonseparable", "separable")}, "L1 to ray-traced mesh",
              fontsize=7, rotation=0)
    results["microgeometry_l1"] = {"samples": n, "rows": rows}


def furnace(out, quick, results):
    import matplotlib.pyplot as plt

    n = 100_000 if quick else 400_000
    thetas_i = [0, 30, 60, 75, 85, 89]
    table = []
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.5), sharey=True)
    for ax, tp in zip(axes, [30, 60, 80]):
        for model, tf in [("analytic", "specular")] + WALKS:
            b = make_bsdf(model, tf, tp)
            for side in (0, 180):
                albedo = [float(sample(b, sph(ti, side), n, seed=ti)[1].mean()) for ti in thetas_i]
                table.append({"model": model, "tangent_facet": tf, "theta_p": tp, "phi_i": side,
                              "albedo": dict(zip(thetas_i, [round(a, 4) for a in albedo]))})
                style = "-" if side == 0 else "--"
                ax.plot(thetas_i, albedo, style, label=f"{model}/{tf} φi={side}" if tp == 30 else None)
        ax.axhline(np.cos(np.radians(tp)), color="gray", lw=0.5)
        ax.set_title(f"θp = {tp}° (gray: cosθp)")
        ax.set_xlabel("θi (deg)")
    axes[0].set_ylabel("albedo (white Lambertian facets)")
    fig.legend(loc="lower center", ncol=5, fontsize=7)
    fig.tight_layout(rect=(0, 0.12, 1, 1))
    fig.savefig(out / "furnace.png", dpi=90)
    plt.close(fig)
    results["furnace"] = {"samples": n, "rows": table}


def variance(out, quick, results):
    from mfnormal.models import walk
    from mfnormal.surface.microsurface import decode_normal
    from mfnormal.surface.shading import ShadingPoint
    from validation.reference.naive_walk import naive_eval

    n = 50_000 if quick else 200_000
    nested = mi.load_dict(WHITE)
    rows = []
    for tf in ("specular", "same"):
        for tp in (30, 60):
            for ti, to in ((20, 40), (70, 30), (70, 80)):
                for side in (0, 180):
                    si = interaction(sph(ti, side), n)
                    rgb = mi.Vector3f(*[float(c) for c in sph(tp) * 0.5 + 0.5])
                    sp = ShadingPoint(nested, mi.BSDFContext(), si, decode_normal(rgb, 1.0, False))
                    wo = sph(to, side + 150)
                    wo_v = mi.Vector3f(*[float(c) for c in wo])
                    est = {}
                    params = walk.WalkParams(separable=False, specular_tangent=tf == "specular", rr_depth=0)
                    for naive in (False, True):
                        L = naive_eval(sp, wo_v, tf == "specular") if naive else walk.eval(sp, params, wo_v, True)
                        est[naive] = np.array(L)[0]
                    m0, m1 = est[False].mean(), est[True].mean()
                    v0, v1 = est[False].var(), est[True].var()
                    rows.append({"tangent_facet": tf, "theta_p": tp, "theta_i": ti, "theta_o": to, "phi_i": side,
                                 "mean_interval": round(float(m0), 5), "mean_naive": round(float(m1), 5),
                                 "variance_ratio": round(float(v1 / v0), 2) if v0 > 0 else None})
    bar_chart(out / "variance.png", [f"{r['tangent_facet'][:4]} p{r['theta_p']} i{r['theta_i']}/{r['phi_i']}"
                                     f" o{r['theta_o']}" for r in rows],
              {"ratio": [r["variance_ratio"] or np.nan for r in rows]}, "Var(naive) / Var(interval)",
              "Non-separable eval: height-interval tracking (Algorithm 2/3) vs a sampled height", log=True)
    results["variance"] = {"samples": n, "rows": rows}


def mis_pdf(out, quick, results):

    n = 200_000 if quick else 1_000_000
    n_cos, n_phi = 16, 32
    # cell-centre quadrature of the pdf (8x8 points per cell)
    k = 8
    cu = (np.arange(n_cos * k) + 0.5) / (n_cos * k)
    pu = (np.arange(n_phi * k) + 0.5) / (n_phi * k) * 2 * np.pi
    C, P = np.meshgrid(cu, pu, indexing="ij")
    S = np.sqrt(1 - C ** 2)
    grid = np.stack([S * np.cos(P), S * np.sin(P), C], -1).reshape(-1, 3)
    rows = []
    for nested_name, nested in (("diffuse", WHITE), ("roughconductor 0.3", GGX)):
        for model, tf in WALKS:
            for tp, ti, side in ((30, 30, 0), (60, 30, 0), (60, 70, 180), (80, 60, 0)):
                # The density part of the MIS pdf (mis_boost_max = 1: no variance-aware boost),
                # against the unweighted exits of walks without Russian roulette.
                b = make_bsdf(model, tf, tp, nested, mis_boost_max=1.0, rr_depth=0)
                wo, w = sample(b, sph(ti, side), n, seed=tp + ti)
                ok = w > 0
                ci = np.clip((wo[ok, 2] * n_cos).astype(int), 0, n_cos - 1)
                pj = np.clip((np.mod(np.arctan2(wo[ok, 1], wo[ok, 0]), 2 * np.pi) / (2 * np.pi) * n_phi).astype(int),
                             0, n_phi - 1)
                hist = np.bincount(ci * n_phi + pj, minlength=n_cos * n_phi) / ok.sum()
                si = interaction(sph(ti, side), len(grid))
                pdf = np.array(b.pdf(mi.BSDFContext(), si, mi.Vector3f(*[grid[:, i].astype(np.float32) for i in range(3)])))
                cell_pdf = (pdf.reshape(n_cos, k, n_phi, k).mean(axis=(1, 3)) * (2 * np.pi / n_phi) * (1 / n_cos)).ravel()
                mass = cell_pdf.sum()
                tv = 0.5 * np.abs(hist - cell_pdf / mass).sum()
                rows.append({"nested": nested_name, "model": model, "tangent_facet": tf, "theta_p": tp,
                             "theta_i": ti, "phi_i": side, "pdf_mass": round(float(mass), 3), "tv": round(float(tv), 3)})
    bar_chart(out / "mis_pdf.png", [f"{r['nested'][:5]} {r['model'][:6]}/{r['tangent_facet'][:4]} p{r['theta_p']} "
                                    f"i{r['theta_i']}/{r['phi_i']}" for r in rows],
              {"tv": [r["tv"] for r in rows]}, "TV(pdf, sampler)",
              "MIS pdf vs the walk's sampling density (total variation, 16x32 cells)", figsize=(9, 3.5))
    results["mis_pdf"] = {"samples": n, "rows": rows}


def write_markdown(out, results, elapsed):
    lines = ["# Validation results", "",
             f"Written by `validation/run.py` in {elapsed:.0f} s ({mi.variant()}, libLLVM {mfnormal.LLVM_PATH}).", ""]
    for name, title in (("microgeometry_l1", "Models vs Mitsuba ray tracing of the real sawtooth mesh (L1)"),
                        ("furnace", "White furnace"), ("variance", "Interval tracking vs sampled height"),
                        ("mis_pdf", "MIS pdf vs sampling density")):
        if name not in results:
            continue
        rows = results[name]["rows"]
        lines += [f"## {title}", "", f"{results[name]['samples']} samples per case.", ""]
        keys = list(rows[0].keys())
        lines.append("| " + " | ".join(keys) + " |")
        lines.append("|" + "---|" * len(keys))
        for r in rows:
            lines.append("| " + " | ".join(str(r[k]) for k in keys) + " |")
        lines.append("")
    for png in sorted(out.glob("*.png")):
        lines.append(f"![{png.stem}]({png.name})")
    (out / "RESULTS.md").write_text("\n".join(lines) + "\n")
    (out / "results.json").write_text(json.dumps(results, indent=1, ensure_ascii=False))


STEPS = {"microgeometry": microgeometry, "furnace": furnace, "variance": variance, "mis_pdf": mis_pdf}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", default=str(ROOT / "out" / "validation"),
                        help="output folder (default: out/validation; --out validation/results rewrites the committed results)")
    parser.add_argument("--quick", action="store_true", help="fewer samples (about a minute)")
    parser.add_argument("--only", nargs="*", choices=sorted(STEPS), help="run only these steps")
    args = parser.parse_args(argv)
    import matplotlib
    matplotlib.use("Agg")
    mi.set_variant("llvm_ad_rgb")
    mfnormal.register()
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)
    results, start = {}, time.time()
    for name in args.only or STEPS:
        t = time.time()
        STEPS[name](out, args.quick, results)
        print(f"{name}: {time.time() - t:.0f} s", flush=True)
    write_markdown(out, results, time.time() - start)
    print(f"wrote {out / 'RESULTS.md'}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
