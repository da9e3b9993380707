#!/usr/bin/env python
"""Is ``mfnormal_path`` noisier than ``path`` for the mirror-facet walks? The benchmark's noise
metric, repeated over independent blocks of seeds.

    PYTHONPATH=src python benchmarks/fused_noise.py [--cells plane:ggx_0.05:separable_specular ...]
        [--blocks 8] [--size 192x144] [--ref-spp 2048] [--out benchmarks/fused_noise.json]
    python benchmarks/fused_noise.py --report-only benchmarks/fused_noise.json

run.py's metric 3 scores a method by the relMSE of ``noise_seeds`` (6) renders at 16 spp
(seeds 20000…20005) against a 256-spp reference. Its full run under ``mfnormal_path`` (stop 24,
benchmarks/mfnormal_path/RESULTS.md) put the mirror-facet walks over GGX α 0.05 at 7–8× their
relMSE under ``path`` on three cells, and docs/model.md §4.10 blamed the fused walk's
correlation. Per cell, this script renders the scene without its sun disc (as metric 3 scores
it) under both integrators and the built-in under ``path``, at the benchmark's size and spp:

- one shared reference per cell (``--ref-spp`` per integrator, both averaged: the two
  integrators render the same expectation; the reference noise is removed as run.py does);
- ``--blocks`` independent estimates of the benchmark's number: block b renders 6 images at
  16 spp with seeds base_b … base_b + 5, base_0 = 20000 (the benchmark's seeds), base_b =
  20000 + 1000·b, and scores their mean relMSE;
- per integrator the blocks' median, min and max, their mean (all blocks' renders pooled:
  the best estimate of the per-sample relMSE here), and the per-block ratio
  mfnormal_path/path (the same seeds: the same camera rays and light samples).

A heavy-tailed estimator (rare, very bright samples) shows as blocks that disagree by far more
than their sampling error; then one block, as in the benchmark, says little. Writes ``--out``
and a table beside it (``.md``; ``--report-only`` rewrites it from the JSON).
"""

from __future__ import annotations

import argparse
import json
import statistics
import sys
import time
from pathlib import Path

import numpy as np

sys.path.insert(0, str(Path(__file__).resolve().parent))
import run as R  # noqa: E402

CELLS = ("plane:ggx_0.05:separable_specular", "plane:ggx_0.05:nonseparable_specular",
         "control:ggx_0.05:nonseparable_specular")
SPP, SEEDS, REF_PASS = 16, 6, 64


def block_relmse(scene, ref: np.ndarray, ref_spp: int, base: int) -> float:
    """run.py's metric-3 number for the seed block starting at ``base``."""
    from mfnormal.report.metrics import rel_mse
    errs = [rel_mse(x, ref) for x in R.noise_renders(scene, SPP, SEEDS, base)]
    return R.reference_noise_removed(float(np.mean(errs)), SPP, ref_spp)


def measure(cell: str, assets: dict, size, blocks: int, ref_spp: int) -> dict:
    scene_name, nested, method = cell.split(":")
    W, H = size
    configs = {"builtin/path": ("builtin", "path"), "path": (method, "path"),
               "mfnormal_path": (method, "mfnormal_path")}
    scenes = {k: R.load_scene(scene_name, assets, m, nested, W, H, SPP, sunless=True, integrator=i)
              for k, (m, i) in configs.items()}
    refs = {k: R.reference_image(sc, ref_spp, REF_PASS)[0] for k, sc in scenes.items()}
    shared = 0.5 * (refs["path"] + refs["mfnormal_path"])
    from mfnormal.report.metrics import rel_mse
    out = {"cell": cell, "size": f"{W}x{H}", "ref_spp": ref_spp,
           "ref_difference_relmse": rel_mse(refs["mfnormal_path"], refs["path"])}
    bases = [20_000 + 1000 * b for b in range(blocks)]
    for k, sc in scenes.items():
        ref, n_ref = (refs[k], ref_spp) if k == "builtin/path" else (shared, 2 * ref_spp)
        out[k] = [block_relmse(sc, ref, n_ref, base) for base in bases]
        R.log(f"  {cell} {k:14s} " + " ".join(f"{x:.4g}" for x in out[k]))
    out["bases"] = bases
    return out


def summary(rows) -> str:
    lines = ["| cell | blocks | built-in (path) median | walk under path: median [min, max] | "
             "under mfnormal_path: median [min, max] | pooled: built-in, path, mfnormal_path | "
             "per-block ratio mfnormal_path/path: median [min, max] | block 0 (the benchmark's seeds): ratio |",
             "|---|---|---|---|---|---|---|---|"]
    for r in rows:
        p, f = r["path"], r["mfnormal_path"]
        ratio = [b / a for a, b in zip(p, f)]

        def span(x):
            return f"{statistics.median(x):.4g} [{min(x):.4g}, {max(x):.4g}]"
        lines.append(f"| {r['cell']} | {len(p)} | {statistics.median(r['builtin/path']):.4g} | {span(p)} | "
                     f"{span(f)} | {np.mean(r['builtin/path']):.4g}, {np.mean(p):.4g}, {np.mean(f):.4g} | "
                     f"{statistics.median(ratio):.2f} [{min(ratio):.2f}, {max(ratio):.2f}] | "
                     f"{ratio[0]:.2f} |")
    return "\n".join(lines)


def report(doc: dict) -> str:
    """The Markdown beside the JSON, from the JSON document alone."""
    rows = doc["rows"]
    return (f"# `path` vs `mfnormal_path`: the benchmark's noise metric over independent seed blocks\n\n"
            f"- command: `{doc['command']}`\n- {len(rows)} cells, sky without its sun disc, "
            f"{rows[0]['size'].replace('x', '×')}, {SEEDS} renders × {SPP} spp per block, reference "
            f"{rows[0]['ref_spp']} spp per integrator (the walk's two averaged), {doc['seconds'] / 60:.1f} min\n\n"
            f"{summary(rows)}\n")


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--cells", nargs="+", default=list(CELLS), help="SCENE:NESTED:METHOD")
    ap.add_argument("--blocks", type=int, default=8)
    ap.add_argument("--size", default="192x144")
    ap.add_argument("--ref-spp", type=int, default=2048)
    ap.add_argument("--out", type=Path, default=Path(__file__).resolve().parent / "fused_noise.json")
    ap.add_argument("--report-only", type=Path, metavar="JSON", help="rewrite the .md beside JSON from it")
    args = ap.parse_args(argv)
    if args.report_only is not None:
        args.report_only.with_suffix(".md").write_text(report(json.loads(args.report_only.read_text())))
        return 0
    size = tuple(int(x) for x in args.size.split("x"))
    R.import_mitsuba()
    t0 = time.time()
    scenes = sorted({c.split(":")[0] for c in args.cells})
    with R.temporary_assets(scenes, "mfnormal_fused_noise_") as assets:
        rows = [measure(c, assets, size, args.blocks, args.ref_spp) for c in args.cells]
    doc = {"command": " ".join(["benchmarks/fused_noise.py"] + (argv if argv is not None else sys.argv[1:])),
           "machine": R.machine_info(), "seconds": time.time() - t0, "rows": rows}
    args.out.write_text(json.dumps(doc, indent=1))
    args.out.with_suffix(".md").write_text(report(doc))
    print(summary(rows))
    return 0


if __name__ == "__main__":
    sys.exit(main())
