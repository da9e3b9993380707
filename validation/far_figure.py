"""A far view side by side at equal time: classic normal mapping, the default, the default with
``filter="lean"``, and the truth (the high-poly the map was baked from), one real-asset cell.

    nice .venv/bin/python -m validation.far_figure [--cell bunny/gold/grazing_sun/far] [--res 192]
        [--spp 16] [--truth-spp 1024] [--faces 1000] [--map-size 1024] [--out docs/far_filter.png]

The cell's scenes are :mod:`validation.real_assets_split`'s (the asset decimated to ``--faces``
triangles, its map baked at ``--map-size``²), every one with ``mfnormal_path`` (its
footprint on) and the independent sampler (any sample count, as asked). Each method's warm seconds
per render at ``--spp`` are measured as the harness measures them
(:func:`validation.real_assets_split.method_seconds`: rounds over the methods, one scene alive at a
time); classic normal mapping (Mitsuba's ``normalmap``, fixes off) renders at ``--spp``, the
others at the spp they get in its time. The panels show the object's bounding box, exposed as the
harness meters it (the truth's mean luminance over the object → 0.5) and tone-mapped as its contact
sheets are; each title gives the method and its spp. It prints each one's relMSE against the truth
over the object, which for one render at these spp is decided by a few bright pixels (the gold's
interreflections, which the truth has too) and changes by 10× from one run to the next: the
averages over cells are the harness's (``validation.real_assets_split``), not this. Writes the
PNG to ``--out``.
"""

from __future__ import annotations

import argparse
import gc
import sys
from pathlib import Path

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import mitsuba as mi
import numpy as np

from mfnormal.files import atomic_write
from mfnormal.io.images import tonemap
from mfnormal.report.metrics import luminance
from validation import heightfield as H
from validation import real_assets as RA
from validation import real_assets_split as S
from mfnormal.io import bake as B

METHODS = (("classic", "classic normal mapping"), ("plugin:faithful", "the default"),
           ("plugin:faithful,filter=lean", "the default, filter=\"lean\""))
INTEGRATOR = "mfnormal_path"


def parse_args(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--cell", default="bunny/gold/grazing_sun/far", help="asset/material/lighting/view")
    p.add_argument("--res", type=int, default=192)
    p.add_argument("--spp", type=int, default=16, help="classic normal mapping's spp (the time budget)")
    p.add_argument("--truth-spp", type=int, default=1024)
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--faces", type=int, default=S.FULL["faces"])
    p.add_argument("--map-size", type=int, default=S.FULL["map_size"])
    p.add_argument("--out", type=Path, default=Path("docs/far_filter.png"))
    args = p.parse_args(argv)
    parts = args.cell.split("/")
    tables = (RA.ASSETS, H.MATERIALS, RA.LIGHTINGS, S.VIEWS)
    if len(parts) != 4 or any(x not in t for x, t in zip(parts, tables)):
        p.error(f"--cell {args.cell}: expected asset/material/lighting/view, each one of "
                + "; ".join(", ".join(t) for t in tables))
    if min(args.res, args.spp, args.truth_spp, args.faces, args.map_size) < 1:
        p.error("--res, --spp, --truth-spp, --faces and --map-size must be at least 1")
    return args


def figure(panels, path: Path, title: str):
    """The panels (title, image) side by side, with their titles, as a PNG."""
    import matplotlib
    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(panels), figsize=(2.4 * len(panels), 2.75), dpi=100)
    for ax, (name, img) in zip(axes, panels):
        ax.imshow(img, interpolation="nearest")
        ax.set_title(name, fontsize=7)
        ax.axis("off")
    fig.suptitle(title, fontsize=8)
    fig.tight_layout()
    atomic_write(path, lambda p: fig.savefig(p, format="png"))
    plt.close(fig)


def main(argv=None):
    args = parse_args(argv)
    mi.set_variant("llvm_ad_rgb")
    mfnormal.register()
    cell = RA.Cell(*args.cell.split("/"))
    prepared = RA.prepare(cell.asset, args.faces, args.map_size)
    target, half = S.camera(B.mesh_arrays(prepared["high"])[0], cell.view)
    res, spp = args.res, args.spp
    prepared["high"].set_bsdf(mi.load_dict(H.MATERIALS[cell.material]))
    truth_scene = RA.scene(prepared["high"], cell, target, half, res, spp, "independent", INTEGRATOR)
    mask = RA.object_mask([truth_scene, RA.scene(RA.low_mesh(prepared["low"], "mitsuba"), cell, target, half,
                                                 res, spp, integrator=INTEGRATOR)], res)
    truth = H.render(truth_scene, args.truth_spp, args.seed + 100)
    del truth_scene
    gc.collect()
    methods = [(H.method_from_spec(spec), label) for spec, label in METHODS]
    seconds = S.method_seconds(cell, prepared, [m for m, _ in methods], "mikktspace", target, half, res, spp,
                               args.seed, INTEGRATOR)
    k = H.EXPOSURE_MEAN / max(float(luminance(truth)[mask].mean()), 1e-12)
    rows, cols = np.flatnonzero(mask.any(axis=1)), np.flatnonzero(mask.any(axis=0))
    box = (slice(max(rows[0] - 2, 0), rows[-1] + 3), slice(max(cols[0] - 2, 0), cols[-1] + 3))
    panels = []
    for m, label in methods:
        n = max(1, round(spp * seconds["classic"] / seconds[m.key]))
        s = RA.method_scene(m, cell, prepared, "mikktspace", target, half, res, n, "independent", INTEGRATOR)
        img = H.render(s, n, args.seed)
        del s
        gc.collect()
        score = RA.object_metrics(img, truth, mask)["rel_mse"]
        print(f"{label}: {n} spp ({seconds[m.key] / seconds['classic']:.2f}× classic's time per sample·spp), "
              f"relMSE {score:.4f}")
        panels.append((f"{label}\n{n} spp", tonemap(img[box] * k)))
    panels.append((f"the truth (high-poly)\n{args.truth_spp} spp", tonemap(truth[box] * k)))
    figure(panels, args.out, f"{args.cell}: equal time (classic at {spp} spp), {res}² px, mfnormal_path")
    print(f"wrote {args.out}")
    return 0


if __name__ == "__main__":
    sys.exit(main())
