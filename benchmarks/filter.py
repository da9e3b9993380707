r"""How close ``filter="lean"`` is to the texels it stands for, and how much of their spread it removes.

    python -m benchmarks.filter [--out DIR] [--map FILE] [--time]

A far pixel's sample lands on one texel of its footprint; what the pixel converges to is the
texels' mean. The filtered default (``normalmap_microfacet``, ``filter="lean"``) shades a mild
texel's footprint as one facet with a widened lobe (docs/normal_sources.md §5). This measures,
with the plugin's own ``eval`` (the default model, neighbours and all), at 256 footprints 8 texels
wide, each queried at 64 points drawn uniformly in it, with ``filter="none"`` and ``"lean"`` at the
same points and the same footprint:

- **mean**: the filtered values' sum over all points over the unfiltered ones' (1: no bias over
  the map);
- **spread**: the standard deviation of the values within a footprint (what a pixel's samples
  see), filtered over unfiltered, the root mean square over the footprints (1: no gain);
- **filtered**: the share of the points whose footprint the filter shades as one facet (the rest
  keep their texel: steep texels, flat ones whose class is exactly flat, and footprints too
  spread for the bound).

Where the texels send (almost) no light, below 1e-6, the table gives the filtered value itself.

Maps (256², :mod:`benchmarks.lean`'s): smooth Gaussian noise of rms slope 0.06 and 0.2 per axis,
and caps on a grid with flat ground between them (``bumps``) at strength 0.3. Nested BSDFs: gold
(``roughconductor``, α 0.05 and 0.2) and white diffuse. Directions (ω_i, ω_o): the mirror
configuration at 30°, a sun at 45° and a grazing sun at 80° seen from 5° off the normal, and a
view at 60° with a sun at 60° in another azimuth. ``--map FILE`` adds a map of your own (a raw
tangent-space normal map, e.g. a real asset's bake, which :mod:`validation.real_assets` caches
under ``~/.cache/mfnormal/assets/prepared``). Writes ``filter.json`` into ``--out`` (default
``out/benchmarks``) and prints the table.

``--time``: the cost too, as render time with the filter over without, the median of 5 interleaved
pairs of renders (each ended by ``dr.eval`` and ``dr.sync_thread``, after one untimed render that
compiles the kernels): a plane with the rms-0.06 noise map seen from afar under a sky and a sun,
384², 32 spp, ``mfnormal_path``, gold α 0.05 and white diffuse; the map tiled 8 times (far: about
25 texels per pixel, filtered) and once (close: under a texel per sample, nothing to filter, the
lookup's cost alone). Adds the key ``time`` to the JSON.
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import time
from pathlib import Path

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np

from benchmarks import lean

FOOTPRINTS, POINTS, WIDTH = 256, 64, 8
TINY = 1e-6         # a mean below this is no light: the table gives the filtered value, not a ratio


def direction(theta, phi=0.0):
    t = math.radians(theta)
    return (math.sin(t) * math.cos(phi), math.sin(t) * math.sin(phi), math.cos(t))


DIRECTIONS = {"mirror 30°": (direction(30, math.pi), direction(30)),
              "sun 45°, front": (direction(5), direction(45, 1.0)),
              "grazing sun, front": (direction(5), direction(80, 2.0)),
              "view 60°, sun 60°": (direction(60, math.pi), direction(60, 0.5))}
NESTED = {"gold α 0.05": {"type": "roughconductor", "material": "Au", "alpha": 0.05},
          "gold α 0.2": {"type": "roughconductor", "material": "Au", "alpha": 0.2},
          "white diffuse": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}}


def maps(extra: Path | None = None) -> dict:
    """The maps (RGB arrays in [0, 1], strength) by name; ``extra``: a file of your own too."""
    out = {"noise, rms slope 0.06": (lean.noise(rms=0.06), 1.0), "noise, rms slope 0.2": (lean.noise(rms=0.2), 1.0),
           "bumps, strength 0.3": (lean.bumps(), 0.3)}
    if extra is not None:
        bitmap = mi.Bitmap(str(extra))      # (raw: its values as stored, not linearised)
        bitmap = bitmap.convert(mi.Bitmap.PixelFormat.RGB, mi.Struct.Type.Float32, srgb_gamma=bitmap.srgb_gamma())
        out[extra.name] = (np.array(bitmap), 1.0)
    return out


def queries(rng, size):
    """Interactions at POINTS uniform points of each of FOOTPRINTS footprints WIDTH texels wide on a
    map ``size`` texels wide."""
    centres = rng.random((FOOTPRINTS, 2))
    uv = np.repeat(centres, POINTS, 0) + (rng.random((FOOTPRINTS * POINTS, 2)) - 0.5) * WIDTH / size
    si = dr.zeros(mi.SurfaceInteraction3f, FOOTPRINTS * POINTS)
    si.uv = mi.Point2f((uv[:, 0] % 1.0).astype(np.float32), (uv[:, 1] % 1.0).astype(np.float32))
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    si.n = mi.Normal3f(0, 0, 1)
    si.duv_dx = mi.Vector2f(WIDTH / size, 0.0)
    si.duv_dy = mi.Vector2f(0.0, WIDTH / size)
    return si


def filtered_share(source, si) -> float:
    """The share of the queries ``si`` whose footprint the filter shades as one facet (its normal
    or spread not the texel's own)."""
    w, v = source.footprint(si)
    point = mi.SurfaceInteraction3f(si)
    point.duv_dx = point.duv_dy = mi.Vector2f(0.0, 0.0)
    texel, _ = source.footprint(point)
    moved = np.any(np3(w) != np3(texel), axis=1)
    return float(np.mean(moved | (np.array(v) > 0.0)))


def np3(v):
    return np.stack([np.array(v.x), np.array(v.y), np.array(v.z)], -1)


def measure(extra: Path | None = None) -> list:
    rows = []
    for map_name, (rgb, strength) in maps(extra).items():
        bitmap = mi.Bitmap(rgb.astype(np.float32))
        for nested_name, nested in NESTED.items():
            plugins = {f: mi.load_dict({"type": "normalmap_microfacet", "filter": f, "strength": strength,
                                        "normalmap": {"type": "bitmap", "bitmap": bitmap, "raw": True},
                                        "bsdf": nested}) for f in ("none", "lean")}
            si = queries(np.random.default_rng(1), rgb.shape[1])
            filtered = filtered_share(plugins["lean"].source, si)
            for label, (wi, wo) in DIRECTIONS.items():
                si.wi = mi.Vector3f(*wi)
                values = {}
                for f, bsdf in plugins.items():
                    v = bsdf.eval(mi.BSDFContext(), si, mi.Vector3f(*wo))
                    values[f] = np.array((v[0] + v[1] + v[2]) / 3.0, np.float64).reshape(FOOTPRINTS, POINTS)
                plain, filt = values["none"], values["lean"]
                spread = math.sqrt(np.mean(plain.var(1)))
                rows.append({"map": map_name, "nested": nested_name, "directions": label, "filtered": filtered,
                             "texels": float(plain.mean()), "filtered_mean": float(filt.mean()),
                             "mean": float(filt.sum() / plain.sum()) if plain.sum() > 0 else float("nan"),
                             "spread": math.sqrt(np.mean(filt.var(1))) / spread if spread > 0 else float("nan")})
    return rows


def timing(res=384, spp=32, pairs=5) -> dict:
    """Render time with ``filter="lean"`` over ``"none"`` per view and nested BSDF (``--time``)."""
    rgb = lean.noise(rms=0.06).astype(np.float32)

    def scene(filter, nested, tiles):
        texture = {"type": "bitmap", "bitmap": mi.Bitmap(rgb), "raw": True,
                   "to_uv": mi.ScalarTransform4f().scale([tiles, tiles, 1])}
        return mi.load_dict({
            "type": "scene", "integrator": {"type": "mfnormal_path", "max_depth": 4},
            "sensor": {"type": "perspective", "fov": 30,
                       "to_world": mi.ScalarTransform4f().look_at([0, -4, 3], [0, 0, 0], [0, 0, 1]),
                       "film": {"type": "hdrfilm", "width": res, "height": res}},
            "plane": {"type": "rectangle", "bsdf": {"type": "normalmap_microfacet", "normalmap": texture,
                                                    "filter": filter, "bsdf": nested}},
            "sky": {"type": "constant", "radiance": 0.3},
            "sun": {"type": "directional", "direction": [0.0, -0.75, -0.6], "irradiance": 3.0}})

    out = {}
    for (view, tiles), name in itertools.product((("far", 8), ("close", 1)), ("gold α 0.05", "white diffuse")):
        scenes = {f: scene(f, NESTED[name], tiles) for f in ("none", "lean")}
        for sc in scenes.values():
            dr.eval(mi.render(sc, spp=spp))
        ratios = []
        for k in range(pairs):
            seconds = {}
            for f in (("none", "lean") if k % 2 == 0 else ("lean", "none")):
                start = time.perf_counter()
                dr.eval(mi.render(scenes[f], spp=spp, seed=k))
                dr.sync_thread()
                seconds[f] = time.perf_counter() - start
            ratios.append(seconds["lean"] / seconds["none"])
        out[f"{view}, {name}"] = float(np.median(ratios))
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/benchmarks"))
    parser.add_argument("--map", type=Path, default=None, help="a raw normal map of your own, measured too")
    parser.add_argument("--time", action="store_true", help="time renders with and without the filter too")
    args = parser.parse_args(argv)
    if args.map is not None and not args.map.is_file():
        parser.error(f"--map {args.map}: no such file; give a raw tangent-space normal map (PNG or EXR)")
    mi.set_variant("llvm_ad_rgb")
    args.out.mkdir(parents=True, exist_ok=True)
    rows = measure(args.map)
    print("| map | nested | filtered | directions | texels' mean | mean, filtered / texels | spread, filtered / texels |")
    print("|---|---|---|---|---|---|---|")
    for r in rows:
        if r["texels"] < TINY:      # (no texel sends light there: the filtered value itself)
            ratios = f"{r['filtered_mean']:.2g} (absolute) | – "
        else:
            ratios = f"{r['mean']:.3f} | {r['spread']:.3f} "
        print(f"| {r['map']} | {r['nested']} | {r['filtered']:.0%} | {r['directions']} | {r['texels']:.3g} "
              f"| {ratios}|")
    result = {"queries": rows}
    if args.time:
        result["time"] = timing()
        for name, ratio in result["time"].items():
            print(f"render time with the filter over without, {name}: {ratio:.3f}")
    (args.out / "filter.json").write_text(json.dumps(result, indent=1))
    print(f"wrote {args.out / 'filter.json'}")


if __name__ == "__main__":
    main()
