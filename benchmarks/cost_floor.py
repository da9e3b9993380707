"""The cost floor: what the least model of the default's kind costs against Mitsuba's ``normalmap``.

    python -m benchmarks.cost_floor [--quick] [--scenes demo,model] [--reps 4] [--out benchmarks/cost_floor]

The production profile's scenes (``python -m benchmarks.run --profile production``: 1280×720, 16 spp,
the scenes' own materials) rendered with the built-in and, interleaved with it at equal spp,

- ``faithful``: the default model;
- ``bench_shell_classic``: the plugin's normal decoding and frames with classic normal mapping as
  its model (benchmarks/probes.py): what the plugin's shell costs by itself;
- ``bench_shell_hidden``: the same shell with the least a model does that shows the texel's
  neighbours where the texel is hidden and has an exact pdf: two nested ``eval_pdf`` per ``eval``,
  a nested sample and the two again per ``sample`` (V = cos θ_p in place of a model's V; no Smith
  Λ, no shadowing, no fill, no neighbourhood, no bounced light).

Each row gives the median time ratio over the interleaved pairs, the path vertices per camera
sample against the built-in's (counted at 192×144) and the time ratio per path vertex. The
default keeps light the built-in loses (its paths are longer); the shells lose it below the
facet's horizon as the built-in does. So the floor for a model that keeps that light, as the
default must (the white furnace), is the hidden shell's time per vertex times the default's vertex
ratio: the last column.
"""

from __future__ import annotations

import argparse
import json
import sys
import tempfile
import time
from pathlib import Path

from benchmarks import run as R      # scenes, timing, path vertices

OUT = Path(__file__).resolve().parents[1] / "out" / "benchmarks" / "cost_floor"   # --out benchmarks/cost_floor: the committed one
SHELLS = ("bench_shell_classic", "bench_shell_hidden")
METHODS = ("faithful",) + SHELLS


def method_dict(name: str, assets: dict, method: str, width: int, height: int, spp: int) -> dict:
    """The scene ``name`` for ``method``: the built-in, the default, or a shell (the default's scene
    with each ``normalmap_microfacet`` replaced by the shell, its properties kept)."""
    from mfnormal.io.scene_xml import rewrite_dict
    if method in ("builtin", "faithful"):
        return R.scene_dict(name, assets, method, R.NATIVE, width, height, spp)

    def rewrite(v):
        v["type"] = method
    return rewrite_dict(R.scene_dict(name, assets, "faithful", R.NATIVE, width, height, spp),
                        "normalmap_microfacet", rewrite, "normalmap_microfacet BSDF")


def vertices(name: str, assets: dict, method: str, size, spp: int) -> float:
    from benchmarks import probes
    w, h = size
    return probes.path_vertices(probes.count_calls(method_dict(name, assets, method, w, h, spp), spp, w * h * spp))


def measure(name: str, assets: dict, width: int, height: int, spp: int, reps: int, vertex_size) -> list:
    mi = R.mi
    scenes = {m: mi.load_dict(method_dict(name, assets, m, width, height, spp)) for m in ("builtin",) + METHODS}
    for s in scenes.values():
        R.timed_render(s, spp, 0)
    base_v = vertices(name, assets, "builtin", vertex_size, spp)
    rows = []
    for m in METHODS:
        tb, tm, ratios = R.interleaved_pairs(scenes["builtin"], scenes[m], spp, reps)
        v = vertices(name, assets, m, vertex_size, spp)
        row = {"scene": name, "method": m, "builtin_s": R.median(tb), "method_s": R.median(tm),
               "ratio": R.median(ratios), "ratios": ratios, "vertices": v, "builtin_vertices": base_v,
               "vertex_ratio": v / base_v, "ratio_per_vertex": R.median(ratios) / (v / base_v)}
        rows.append(row)
        R.log(f"  {name:6s} {m:20s} ratio {row['ratio']:.3f} [{min(ratios):.2f}, {max(ratios):.2f}], "
              f"vertices {row['vertex_ratio']:.3f}x, per vertex {row['ratio_per_vertex']:.3f}")
    default = next(r for r in rows if r["method"] == "faithful")
    for r in rows:
        r["at_default_paths"] = r["ratio_per_vertex"] * default["vertex_ratio"]
    return rows


LABELS = {"faithful": "`faithful` (the default)", "bench_shell_classic": "shell: classic normal mapping",
          "bench_shell_hidden": "shell: texel + hidden texel, exact pdf"}


def markdown(report: dict) -> str:
    s = report["settings"]
    lines = [
        "# The cost floor: the least model of the default's kind against Mitsuba's `normalmap`", "",
        f"- command: `{s['command']}`",
        f"- machine: {s['machine']}; variant `{s['variant']}`; started {s['started']}, {s['minutes']:.1f} min",
        f"- {s['width']}×{s['height']}, {s['spp']} spp, {s['reps']} interleaved pairs per row; path vertices "
        f"counted at {s['vertex_size'][0]}×{s['vertex_size'][1]}", "",
        "Time ratio: the median over the pairs (their range in brackets). Vertices: path vertices per camera "
        "sample against the built-in's. Per vertex: the time ratio over the vertex ratio. At the default's "
        "paths: per vertex times the default's vertex ratio, what the row would cost if it kept the light "
        "the default keeps (the shells end paths below the facet's horizon, as the built-in does).", "",
        "| scene | method | time ratio | vertices | per vertex | at the default's paths |",
        "|---|---|---|---|---|---|",
    ]
    for r in report["rows"]:
        lines.append(f"| {r['scene']} | {LABELS[r['method']]} | {r['ratio']:.3f} [{min(r['ratios']):.2f}, "
                     f"{max(r['ratios']):.2f}] | {r['vertex_ratio']:.3f} | {r['ratio_per_vertex']:.3f} | "
                     f"{r['at_default_paths']:.3f} |")
    return "\n".join(lines) + "\n"


def _machine() -> str:
    m = R.machine_info()
    return (f"{m['cpu']}, {m['cores']} cores ({m['drjit_threads']} Dr.Jit threads, {m['simd_lanes']} SIMD lanes), "
            f"Mitsuba {m['mitsuba']}, Dr.Jit {m['drjit']}, load average at start {m['loadavg_start'][0]:.2f}")


def main(argv=None):
    p = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    p.add_argument("--quick", action="store_true", help="tiny smoke run (seconds), numbers meaningless")
    p.add_argument("--scenes", type=lambda t: t.split(","), default=["demo", "model"])
    p.add_argument("--reps", type=int, default=4)
    p.add_argument("--variant", default=R.VARIANT)
    p.add_argument("--out", type=Path, default=OUT)
    args = p.parse_args(argv)
    bad = [n for n in args.scenes if n not in ("demo", "model")]
    if bad:
        p.error(f"unknown scene(s) {', '.join(bad)}: choose from demo, model")
    R.import_mitsuba(args.variant)
    width, height, spp = (64, 36, 2) if args.quick else (R.PRODUCTION.width, R.PRODUCTION.height, R.PRODUCTION.spp)
    reps = 1 if args.quick else args.reps
    vertex_size = (32, 18) if args.quick else R.PRODUCTION.vertex_size
    t0, started = time.time(), time.strftime("%Y-%m-%d %H:%M:%S UTC", time.gmtime())
    rows = []
    with tempfile.TemporaryDirectory(prefix="mfnormal_cost_floor_") as tmp:
        assets = R.prepare_assets(Path(tmp), args.scenes)
        for name in args.scenes:
            rows += measure(name, assets, width, height, spp, reps, vertex_size)
    report = {"settings": {"command": "python -m benchmarks.cost_floor " + " ".join(argv or sys.argv[1:]),
                           "machine": _machine(),
                           "variant": args.variant, "started": started, "minutes": (time.time() - t0) / 60,
                           "width": width, "height": height, "spp": spp, "reps": reps,
                           "vertex_size": list(vertex_size), "quick": args.quick},
              "rows": rows}
    args.out.mkdir(parents=True, exist_ok=True)
    (args.out / "results.json").write_text(json.dumps(report, indent=1))
    (args.out / "RESULTS.md").write_text(markdown(report))
    R.log(f"wrote {args.out / 'RESULTS.md'}")


if __name__ == "__main__":
    main()
