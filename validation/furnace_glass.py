"""A normal-mapped glass sphere in a white furnace: every method against the exact answer 1.

    nice .venv/bin/python -m validation.furnace_glass [--quick] [--out validation/results]
        [--tilts 20,50] [--methods nomap,classic,...,plugin:MODEL] [--res 64] [--spp 256]

A sphere (radius 1) of smooth glass (``dielectric``, ior 1.5) carrying the normal map baked
from a bumpy sphere (an egg crate of 8 × 4 periods over the sphere's uv, max tilt 20° and 50°:
:func:`bump_height`, :func:`sphere_map`) in a constant environment of radiance 1
(``constant``), rendered by ``path`` with max_depth :data:`MAX_DEPTH` and Russian roulette
off. The truth is that bumpy sphere as a dense triangle mesh (:func:`truth_mesh`). A lossless
dielectric is invisible there, bumps or not: every pixel of the true geometry is exactly 1 (its
render shows it, at this depth too: no light stays trapped inside). Per method: the mean over
the sphere's pixels (pixel centres within 0.95 of its radius) and the share of those pixels
off by more than 5 % and 10 %.

Rough glass (``roughdielectric``, GGX α 0.15, ior 1.5) loses some light on its own (single
scattering), and more where its surface is bumpy: its reference is the true geometry
(rendered at 4× spp), and each method is measured against it: the ratio of the means, and the
share of pixels off by more than 5 % and 10 % of the reference's pixel.

``--map constant``: every texel tilted by the tilt toward dp/du instead (a 4 × 4 map,
:func:`constant_map`). That is the normal field of no surface on a closed body (its slopes
average to the tilt, so it has walls somewhere); smooth glass only, against the exact 1 (no true
geometry to render: the reference column is the exact 1).

Writes ``furnace_glass.md``, ``.json`` and ``.png`` (one row per material and tilt) to
``--out``; ``--quick`` writes ``furnace_glass_quick.*`` (32² px, 64 spp, a few seconds);
``--map constant`` writes ``furnace_glass_constant[_quick].*``.
"""

from __future__ import annotations

import functools
import math
import time

import mfnormal  # noqa: E402  (first: selects a working libLLVM)

import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

mi.set_variant("llvm_ad_rgb")
mfnormal.register()

from validation import heightfield as H  # noqa: E402
from validation import true_geometry as TG  # noqa: E402
from validation.dielectric import (command, harness_parser, main as dielectric_main, method,  # noqa: E402
                                   thumb_size, write_text_files)

MAX_DEPTH = 64
#: The sphere's uv carries this many periods of the map (u around the equator, v pole to pole).
UV_PERIODS = (8, 4)
#: Texels per period of the baked map.
MAP_RES = 64
#: The true sphere's vertices per ring (128 per period around; rings: half as many, pole to pole).
TRUTH_AROUND = 1024
#: Sphere pixels: pixel centres within this fraction of the radius (no silhouette pixels).
MASK_RADIUS = 0.95
#: The orthographic frame's half-width (the sphere's radius is 1).
HALF_WIDTH = 1.1
GLASS = {
    "smooth_glass": {"type": "dielectric", "int_ior": 1.5, "ext_ior": 1.0},
    "rough_glass": {"type": "roughdielectric", "distribution": "ggx", "alpha": 0.15, "int_ior": 1.5,
                    "ext_ior": 1.0},
}
OFF = (0.05, 0.10)


def parse_args(argv=None):
    p = harness_parser("validation.furnace_glass", __doc__, "32² px, 64 spp (a few seconds)")
    p.add_argument("--tilts", type=lambda s: [float(t) for t in s.split(",")], default=[20.0, 50.0],
                   help="max tilts of the egg-crate map, degrees")
    p.add_argument("--materials", type=lambda s: s.split(","), default=None,
                   help=f"comma-separated subset (default: {','.join(GLASS)}; with --map constant: smooth_glass)")
    p.add_argument("--res", type=int, default=None, help="default 64 (quick: 32)")
    p.add_argument("--spp", type=int, default=None, help="per method render, default 1024 (quick: 64)")
    p.add_argument("--map", choices=("bumps", "constant"), default="bumps",
                   help="bumps: the map baked from the bumpy sphere (default); constant: every texel tilted "
                        "by the tilt toward dp/du (smooth glass only)")
    args = p.parse_args(argv)
    if args.materials is None:
        args.materials = ["smooth_glass"] if args.map == "constant" else list(GLASS)
    if args.map == "constant" and args.materials != ["smooth_glass"]:
        p.error("--map constant takes --materials smooth_glass only: rough glass has no reference without "
                "a true surface")
    return args


# -- The bumpy sphere: its surface, the map baked from it, its mesh -----------------------------
#
# Radius r(θ, φ) = 1 + h, h = A·sinθ·sin(2π·8u)·sin(2π·4v) in Mitsuba's sphere uv (u = φ/2π around
# +z, v = θ/π from the +z pole): an egg crate of UV_PERIODS periods, tapered by sinθ so that its
# tilts stay bounded toward the poles (where the u-periods shrink); A is chosen so that the normal's
# largest tilt from the radial direction is the cell's.


def bump_height(theta, phi, amp: float):
    """``(h, ∂h/∂θ, ∂h/∂φ)`` of the bumps at polar angle ``theta`` and azimuth ``phi``."""
    a, b = UV_PERIODS[0] * phi, 2 * UV_PERIODS[1] * theta
    s = np.sin(a) * np.sin(b)
    h = amp * np.sin(theta) * s
    h_theta = amp * (np.cos(theta) * s + np.sin(theta) * 2 * UV_PERIODS[1] * np.sin(a) * np.cos(b))
    h_phi = amp * np.sin(theta) * UV_PERIODS[0] * np.cos(a) * np.sin(b)
    return h, h_theta, h_phi


def bump_normal_local(theta, phi, amp: float) -> np.ndarray:
    """The bumpy surface's unit normal in the sphere's frame (ê_φ, −ê_θ, r̂) at (θ, φ): what
    Mitsuba's ``normalmap`` decodes a texel in (x along dp/du = ê_φ, y = n × x = −ê_θ, z = n).
    From r(θ, φ) = (1 + h)·r̂: n ∝ (1 + h)·r̂ − ∂h/∂θ·ê_θ − ∂h/∂φ / sinθ·ê_φ."""
    h, h_theta, h_phi = bump_height(theta, phi, amp)
    n = np.stack([-h_phi / np.maximum(np.sin(theta), 1e-12), h_theta, 1.0 + h], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


@functools.lru_cache(maxsize=None)
def bump_amplitude(max_tilt: float) -> float:
    """A such that the bumps' largest tilt from the radial direction is ``max_tilt`` degrees
    (bisection on a fine grid of one period, θ in [1°, 179°]; 2.6 s, so cached: the map and the
    mesh of a cell both need it)."""
    theta = np.linspace(math.radians(1.0), math.radians(179.0), 1441)
    phi = np.linspace(0.0, 2 * math.pi / UV_PERIODS[0], 241)
    T, P = np.meshgrid(theta, phi, indexing="ij")
    lo, hi = 0.0, 1.0
    for _ in range(50):
        amp = 0.5 * (lo + hi)
        tilt = np.degrees(np.arccos(np.clip(bump_normal_local(T, P, amp)[..., 2], -1.0, 1.0)))
        lo, hi = (lo, amp) if tilt.max() > max_tilt else (amp, hi)
    return 0.5 * (lo + hi)


def sphere_map(max_tilt: float) -> dict:
    """The bumps' normal map, baked from their surface, as a bitmap texture over the sphere's uv:
    MAP_RES texels per period, texel centres at ((c + ½)/W, (r + ½)/H), row 0 = v ≈ 0 (+z pole)."""
    amp = bump_amplitude(max_tilt)
    w, h = MAP_RES * UV_PERIODS[0], MAP_RES * UV_PERIODS[1]
    u, v = (np.arange(w) + 0.5) / w, (np.arange(h) + 0.5) / h
    phi, theta = np.meshgrid(2 * math.pi * u, math.pi * v, indexing="xy")
    return H.bitmap_texture(H.encode_normals(bump_normal_local(theta, phi, amp)))


def constant_map(tilt: float) -> dict:
    """A 4 × 4 map whose every texel is tilted by ``tilt`` degrees toward dp/du (+x of the sphere's
    tangent frame): the same tilt everywhere, a sawtooth's facets without its walls."""
    n = np.array([math.sin(math.radians(tilt)), 0.0, math.cos(math.radians(tilt))])
    return H.bitmap_texture(H.encode_normals(np.tile(n, (4, 4, 1))))


def truth_mesh(max_tilt: float, bsdf, around: int = TRUTH_AROUND, name: str = "true_sphere") -> "mi.Mesh":
    """The bumpy sphere the map was baked from, as a triangle mesh: ``around`` vertices per ring,
    ``around``/2 − 1 rings and a vertex at each pole, flat faces (no shading normals: the
    geometry itself), the sphere's uv; ``bsdf``: a dict or a loaded BSDF."""
    amp = bump_amplitude(max_tilt)
    nu, nv = int(around), int(around) // 2
    theta, phi = np.arange(1, nv) * math.pi / nv, np.arange(nu) * 2 * math.pi / nu
    T, P = np.meshgrid(theta, phi, indexing="ij")
    h = bump_height(T, P, amp)[0]
    st = np.sin(T)
    r_hat = np.stack([st * np.cos(P), st * np.sin(P), np.cos(T)], axis=-1)
    pos = ((1.0 + h)[..., None] * r_hat).reshape(-1, 3)
    uvs = np.stack([P / (2 * math.pi), T / math.pi], axis=-1).reshape(-1, 2)
    north, south = len(pos), len(pos) + 1                        # h = 0 at the poles (sinθ = 0)
    pos = np.vstack([pos, [[0.0, 0.0, 1.0], [0.0, 0.0, -1.0]]])
    uvs = np.vstack([uvs, [[0.0, 0.0], [0.0, 1.0]]])
    j = np.arange(nu)

    def idx(i, jj):
        return i * nu + jj % nu
    faces = [np.stack([np.full(nu, north), idx(0, j), idx(0, j + 1)], axis=-1)]     # outward, CCW
    for i in range(nv - 2):
        a, b, c, d = idx(i, j), idx(i, j + 1), idx(i + 1, j), idx(i + 1, j + 1)
        faces += [np.stack([a, c, d], axis=-1), np.stack([a, d, b], axis=-1)]
    faces.append(np.stack([idx(nv - 2, j), np.full(nu, south), idx(nv - 2, j + 1)], axis=-1))
    return H.triangle_mesh(name, pos, None, uvs, np.vstack(faces), bsdf)


def furnace_scene(bsdf: dict, res: int, spp: int, shape=None) -> dict:
    """The sphere with ``bsdf`` (or ``shape``: e.g. :func:`truth_mesh`) in the constant environment 1,
    seen along +y, orthographic."""
    to_world = mi.ScalarTransform4f().look_at(origin=[0.0, -10.0, 0.0], target=[0.0, 0.0, 0.0],
                                              up=[0.0, 0.0, 1.0])
    return {"type": "scene",
            "integrator": {"type": "path", "max_depth": MAX_DEPTH, "rr_depth": MAX_DEPTH + 1},
            "sensor": {"type": "orthographic",
                       "to_world": to_world @ mi.ScalarTransform4f().scale([HALF_WIDTH, HALF_WIDTH, 1.0]),
                       "near_clip": 1.0, "far_clip": 100.0,
                       "sampler": {"type": "independent", "sample_count": int(spp)},
                       "film": {"type": "hdrfilm", "width": int(res), "height": int(res),
                                "pixel_format": "rgb", "rfilter": {"type": "box"}}},
            "sphere": shape if shape is not None else {"type": "sphere", "radius": 1.0, "bsdf": bsdf},
            "furnace": {"type": "constant", "radiance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}}


def sphere_mask(res: int) -> np.ndarray:
    """The pixels whose centres lie within :data:`MASK_RADIUS` of the sphere's radius."""
    t = ((np.arange(res) + 0.5) / res * 2.0 - 1.0) * HALF_WIDTH
    x, y = np.meshgrid(t, t)
    return np.hypot(x, y) < MASK_RADIUS


def furnace_metrics(img: np.ndarray, ref, mask: np.ndarray) -> dict:
    """Over the sphere's pixels: the mean luminance, its ratio to the reference's (``ref``: an
    image, or 1 for the exact answer), and the shares of pixels off the reference's pixel by
    more than each of :data:`OFF` (relative)."""
    y = H.luminance(img)[mask]
    yr = H.luminance(ref)[mask] if isinstance(ref, np.ndarray) else np.full_like(y, float(ref))
    dev = np.abs(y / np.maximum(yr, 1e-12) - 1.0)
    return {"mean": float(y.mean()), "ratio": float(y.mean() / max(yr.mean(), 1e-12)),
            **{f"off_{round(100 * o)}": float(np.mean(dev > o)) for o in OFF}}


def render_sphere(bsdf: dict, res: int, spp: int, seed: int, shape=None) -> tuple:
    """``(image, nonfinite, negative)`` of the sphere with ``bsdf`` (or of ``shape``; see
    :func:`validation.heightfield.render_counted`); ``ValueError`` if the scene does not load."""
    try:
        scene = mi.load_dict(furnace_scene(bsdf, res, spp, shape))
    except Exception as e:   # a model that refuses the nested BSDF: recorded, not fatal
        raise ValueError(f"{type(e).__name__}: {str(e).strip().splitlines()[-1][:300]}") from None
    return H.render_counted(scene, spp, seed)


def measure(material: str, max_tilt: float, methods, res: int, spp: int, seed: int, kind: str = "bumps") -> dict:
    """Every method on the ``material`` sphere with the ``max_tilt`` map, and the true geometry
    (:func:`truth_mesh`, another seed). The reference: 1 for smooth glass (the true geometry's
    render is scored against it too); for rough glass, the true geometry at 4× spp. ``kind``
    ``constant``: the :func:`constant_map` of that tilt, smooth glass, no true geometry (its image is
    the exact 1). Returns a row: ``cell``, ``truth`` (the true geometry's image), ``truth_metrics``,
    ``images``, ``metrics`` ({key: :func:`furnace_metrics`}), ``errors`` (methods that refused),
    ``invalid``, ``times``."""
    constant = kind == "constant"
    nested, mask = GLASS[material], sphere_mask(res)
    tex = constant_map(max_tilt) if constant else sphere_map(max_tilt)
    exact = material == "smooth_glass"
    truth_spp = spp if exact else 4 * spp
    truth = np.ones((res, res, 3)) if constant else \
        render_sphere(nested, res, truth_spp, seed + 100, shape=truth_mesh(max_tilt, nested))[0]
    ref = np.ones((res, res, 3)) if exact else truth
    row = {"cell": f"{material}/{'constant ' if constant else ''}{max_tilt:g}deg", "material": material,
           "tilt": max_tilt, "spp": spp, "map": kind,
           "truth": truth, "reference": "exact (1)" if exact else f"true geometry, {truth_spp} spp",
           "reference_mean": float(H.luminance(ref)[mask].mean()), "truth_spp": truth_spp,
           "truth_metrics": furnace_metrics(truth, 1.0, mask) if exact and not constant else None,
           "images": {}, "metrics": {}, "errors": {}, "invalid": {}, "times": {}}
    for m in methods:
        t0 = time.time()
        try:
            img, nonfinite, negative = render_sphere(m.bsdf(nested, tex), res, spp, seed)
        except ValueError as e:
            row["errors"][m.key] = str(e)
            continue
        row["times"][m.key] = time.time() - t0
        row["images"][m.key] = img
        row["invalid"][m.key] = {"nonfinite": nonfinite, "negative": negative}
        row["metrics"][m.key] = furnace_metrics(img, 1.0 if exact else ref, mask)
    return row


def _pct(x):
    return f"{100 * x:.1f} %"


def markdown(report: dict, labels: dict, quick: bool = False) -> str:
    """The report of :func:`run` (``report``: its JSON data) as Markdown."""
    s = report["settings"]
    L = ["# Normal-mapped glass in a white furnace" + (" (quick run)" if quick else ""), "",
         f"Generated by `{s['command']}` in {s['elapsed_s'] / 60:.1f} min (Mitsuba {mi.__version__}, "
         "`llvm_ad_rgb`).", "",
         "A glass sphere (ior 1.5, radius 1) with the normal map baked from a bumpy sphere (an egg crate of "
         f"{UV_PERIODS[0]} × {UV_PERIODS[1]} periods over its uv, tapered by sinθ toward the poles; "
         f"{MAP_RES} texels per period) in a constant environment of radiance 1; `path`, max_depth {MAX_DEPTH}, "
         f"Russian roulette off, {s['res']}² px, {s['spp']} spp, orthographic. The true geometry: that bumpy "
         f"sphere as a triangle mesh ({TRUTH_AROUND} × {TRUTH_AROUND // 2} vertices, flat faces). "
         "Smooth glass (`dielectric`) is invisible in the furnace with or without bumps: the exact answer "
         "is 1 at every pixel, and the true geometry renders it at this depth. Rough glass (`roughdielectric`, "
         "GGX α 0.15) loses light on its own (single scattering), more on a bumpy surface: its reference is "
         "the true geometry. Over the sphere's pixels (centres "
         f"within {MASK_RADIUS:g} of its radius): the mean, its ratio to the reference's, and the share of "
         "pixels off the reference's by more than 5 % and 10 % (Monte Carlo noise included: at this spp "
         "the un-mapped rough sphere's own render is off its own 4× spp render in about 0.5 % of its pixels).",
         ""]
    if s.get("map") == "constant":
        L += ["This run's map is not the bumps' but a constant one (`--map constant`): every texel tilted by the "
              "row's tilt toward dp/du (4 × 4 texels). That is the normal field of no surface on a closed body "
              "(its slopes average to the tilt: it has walls somewhere), so there is no true geometry to render; "
              "smooth glass is still invisible in the furnace, the exact answer 1.", ""]
    for row in report["rows"]:
        L += [f"## {row['cell']} (reference: {row['reference']}, mean {TG.fmt(row['reference_mean'], 4)})", ""]

        def line(k, m, row=row):
            bad = row["invalid"].get(k, {})
            flag = "" if not any(bad.values()) else f" ({bad['nonfinite']} NaN/Inf, {bad['negative']} < 0)"
            return (f"| {labels.get(k, k)} | {TG.fmt(m['mean'], 4)} | {TG.fmt(m['ratio'], 4)} | "
                    f"{_pct(m['off_5'])} | {_pct(m['off_10'])} |{flag}")
        errors = {k: f"| {labels.get(k, k)} | refused: {e} | | | |" for k, e in row["errors"].items()}
        if row["material"] == "smooth_glass":
            head = "| *exact* | 1 | 1 | 0 % | 0 % |"
            if row["truth_metrics"] is not None:
                head += "\n" + line("*true geometry*", row["truth_metrics"])
        else:
            head = f"| *true geometry, {row['truth_spp']} spp* | {TG.fmt(row['reference_mean'], 4)} | 1 | | |"
        TG.method_table(L, "| method | mean | mean / reference | off > 5 % | off > 10 % |", head,
                        s["methods"], row["metrics"], line, errors)
    L += [f"![the spheres: per row the reference, then each method]({s['stem']}.png)", ""]
    return "\n".join(L) + "\n"


def run(args) -> dict:
    res = args.res or (32 if args.quick else 64)
    spp = args.spp or (64 if args.quick else 1024)
    methods = [method(s) for s in args.methods]
    keys = [m.key for m in methods]
    labels = {"truth": "reference", **{m.key: m.label for m in methods}}
    stem = "furnace_glass" + ("_constant" if args.map == "constant" else "") + ("_quick" if args.quick else "")
    t_start = time.time()
    rows = []
    for material in args.materials:
        for tilt in args.tilts:
            rows.append(measure(material, tilt, methods, res, spp, 1000 * args.seed + round(tilt), args.map))
            print(f"{rows[-1]['cell']}: " + ", ".join(f"{k} {m['mean']:.3f}" for k, m in rows[-1]["metrics"].items()),
                  flush=True)
    cmd = command("validation.furnace_glass", args.argv)
    report = {"rows": [{k: v for k, v in r.items() if k not in ("truth", "images", "index")} for r in rows],
              "settings": {"command": cmd, "elapsed_s": time.time() - t_start, "res": res, "spp": spp,
                           "seed": args.seed, "methods": keys, "stem": stem, "map": args.map}}
    write_text_files(args.out, stem, markdown(report, labels, args.quick), report)
    for r in rows:
        r["index"] = r["cell"]
    TG.contact_sheet(rows, keys, labels, args.out / f"{stem}.png", size=thumb_size(res),
                     title="reference, then each method; exposure: the reference's mean")
    print(f"wrote {args.out / stem}.{{md,json,png}}")
    return report


def main(argv=None):
    dielectric_main(argv, parse_args, run)


if __name__ == "__main__":
    main()
