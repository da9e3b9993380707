"""Render one scene with every normal-mapping method and measure each.

``mfnormal compare SCENE`` (see :mod:`mfnormal.cli`) is a thin layer over
:func:`compare`: it takes a Mitsuba XML scene whose normal-mapped materials are
``normalmap_microfacet`` BSDFs and renders it once per :data:`METHODS` entry,
rewriting every such BSDF:

- ``flat``: the nested BSDF alone (no normal map);
- ``classic`` / ``classic_fixed``: Mitsuba's built-in ``normalmap`` with its
  fixes (``flip_invalid_normals``, ``use_shadowing_function``) off / on;
- ``analytic``, ``separable_*``, ``nonseparable_*``: ``normalmap_microfacet``
  with each model and tangent facet.

For each method it measures the render time, the relative MSE against a
higher-spp reference of the same method, and the fraction of near-black pixels
on the normal-mapped surfaces (and of pixels much darker than the flat
render); :func:`bsdf_checks` adds the white-furnace
albedo and the reciprocity error of each method's BSDF alone. The results feed
:func:`mfnormal.report.write_report`.

Bundled scenes: ``demo`` (scene (a), :mod:`mfnormal.demo`) and ``model``
(scene (b), :mod:`mfnormal.assets`), with their assets generated on the fly.
"""

from __future__ import annotations

import copy
import dataclasses
import re
import time
from contextlib import contextmanager
import xml.etree.ElementTree as ET
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import mfnormal  # noqa: F401  (before mitsuba: selects a working libLLVM)
import drjit as dr
import mitsuba as mi

from .images import atomic_write, sanitize, save_render, tonemap
from .messages import one_line
from .report import png_bytes
from .scene_checks import check_scene, normal_mapped_shapes

__all__ = ["Method", "METHODS", "SceneError", "SceneSource", "scene_source", "rewrite",
           "surface_maps", "rel_mse", "near_black_fraction", "choose_crops", "bsdf_checks",
           "compare"]

PLUGIN = "normalmap_microfacet"
BUNDLED = ("demo", "model", "eggcrate")

#: relMSE = mean((x − ref)² / (ref² + REL_MSE_EPS))
REL_MSE_EPS = 1e-2
#: A pixel is near-black below this fraction of the median luminance of the
#: normal-mapped surface in the flat reference.
BLACK_FRACTION = 0.05
#: A pixel is darkened below this fraction of the flat reference's luminance at the same pixel.
DARKENED_FRACTION = 0.1
#: A normal-mapped pixel is grazing where the mean |cos| between view ray and normal is below this.
GRAZING_COS = 0.3


class SceneError(Exception):
    """A problem with the user's scene (reported as one line by the CLI)."""


@dataclass(frozen=True)
class Method:
    key: str
    label: str
    kind: str                       # 'flat', 'classic' or 'microfacet'
    model: str | None = None
    tangent_facet: str | None = None
    fixes: bool = False
    about: str = ""


METHODS = (
    Method("flat", "flat", "flat", about="the nested BSDF alone, no normal map"),
    Method("classic", "normalmap", "classic", fixes=False,
           about="Mitsuba's normalmap, flip_invalid_normals and use_shadowing_function "
                 "off: classic normal mapping"),
    Method("classic_fixed", "normalmap + fixes", "classic", fixes=True,
           about="Mitsuba's normalmap with flip_invalid_normals and use_shadowing_function "
                 "on (its defaults)"),
    Method("faithful", "faithful (default)", "microfacet", "faithful", "specular",
           about="normalmap_microfacet, model=faithful (the default): the texel among neighbours "
                 "of the map's own rms slope, energy kept, light tracing sees its adjoint"),
    Method("analytic", "analytic", "microfacet", "analytic", "specular",
           about="normalmap_microfacet, model=analytic (≤ 2 facet bounces, mirror tangent facet)"),
    Method("separable_specular", "separable / specular", "microfacet", "separable", "specular",
           about="random walk, separable masking-shadowing, mirror tangent facet"),
    Method("separable_same", "separable / same", "microfacet", "separable", "same",
           about="random walk, separable masking-shadowing, nested material on the tangent facet"),
    Method("nonseparable_specular", "nonseparable / specular", "microfacet", "nonseparable",
           "specular", about="random walk, height-correlated masking-shadowing, mirror tangent facet"),
    Method("nonseparable_same", "nonseparable / same", "microfacet", "nonseparable", "same",
           about="random walk, height-correlated masking-shadowing, nested material on the "
                 "tangent facet"),
)
METHOD_BY_KEY = {m.key: m for m in METHODS}


# ---------------------------------------------------------------------------
# Scenes and their rewriting
# ---------------------------------------------------------------------------

@dataclass
class SceneSource:
    """An XML scene to compare: its file, ``$`` parameters and a display title."""
    name: str
    path: Path
    params: dict = field(default_factory=dict)
    title: str = ""


def scene_source(scene: str, assets_root, params: dict | None = None) -> SceneSource:
    """``demo`` / ``model`` (generating their assets under ``assets_root``) or an XML path."""
    params = dict(params or {})
    if scene == "demo":
        from . import demo
        assets = demo.generate_assets(Path(assets_root) / "demo")
        return SceneSource("demo", demo.SCENE_XML, {
            "normalmap": str(Path(assets["normalmap"]).resolve()),
            "envmap": str(Path(assets["envmap"]).resolve()), **params},
            "(a) demo: sphere and ground plane")
    if scene == "model":
        from . import assets as model_assets
        assets = model_assets.generate_model_assets(Path(assets_root) / "model")
        return SceneSource("model", model_assets.MODEL_XML,
                           {**model_assets.model_parameters(assets), **params},
                           "(b) model: torus knot with textured roughness")
    if scene == "eggcrate":
        from . import assets as model_assets
        assets = model_assets.generate_eggcrate_assets(Path(assets_root) / "eggcrate")
        return SceneSource("eggcrate", model_assets.EGGCRATE_XML,
                           {**model_assets.eggcrate_parameters(assets), **params},
                           "(c) egg crate: glossy metal at 78° from the vertical")
    path = Path(scene)
    if not path.is_file():
        raise SceneError(f"scene file not found: {path}"
                         + ("" if path.suffix else f" (bundled scenes: {', '.join(BUNDLED)})"))
    return SceneSource(path.stem, path, params, path.name)


def _substitute(text: str, values: dict) -> str:
    return re.sub(r"\$(\w+)", lambda m: str(values.get(m.group(1), m.group(0))), text)


def parse_scene(src: SceneSource):
    """(XML root, values of its ``$`` parameters: defaults overridden by ``src.params``)."""
    try:
        root = ET.parse(src.path).getroot()
    except ET.ParseError as exc:
        raise SceneError(f"cannot parse {src.path.name}: {exc}") from None
    if root.tag != "scene":
        raise SceneError(f"{src.path.name}: the root element is <{root.tag}>, not <scene>")
    values = {d.get("name"): d.get("value") for d in root.iter("default")}
    values.update(src.params)
    n = sum(1 for el in root.iter("bsdf") if el.get("type") == PLUGIN)
    if n == 0:
        raise SceneError(f"{src.path.name} has no <bsdf type=\"{PLUGIN}\"> to compare "
                         "normal-mapping methods on")
    return root, values


def _remove_props(el, names):
    for child in list(el):
        if child.tag != "bsdf" and child.get("name") in names:
            el.remove(child)


def _set_prop(el, tag, name, value):
    _remove_props(el, {name})
    el.insert(0, ET.Element(tag, name=name, value=value))


def _convert(el: ET.Element, method: Method, values: dict, notes: set) -> ET.Element:
    """One ``normalmap_microfacet`` element rewritten for ``method``."""
    el = copy.deepcopy(el)
    if method.kind == "microfacet":
        _set_prop(el, "string", "model", method.model)
        if method.model in ("analytic", "faithful"):
            _remove_props(el, {"tangent_facet"})
        else:
            _set_prop(el, "string", "tangent_facet", method.tangent_facet)
        return el

    nested = [c for c in el if c.tag == "bsdf" or (c.tag == "ref" and c.get("name") != "normalmap")]
    if method.kind == "flat":
        if len(nested) != 1:
            raise SceneError(f"a {PLUGIN} BSDF needs exactly one nested BSDF, found {len(nested)}")
        flat = copy.deepcopy(nested[0])
        if el.get("id"):
            if flat.tag == "ref":
                raise SceneError(f"cannot replace {PLUGIN} '{el.get('id')}' by its nested "
                                 "<ref> BSDF: give the nested BSDF inline")
            flat.set("id", el.get("id"))
        flat.attrib.pop("name", None)
        if el.get("name"):
            flat.set("name", el.get("name"))
        return flat

    # Mitsuba's normalmap: same texture and nested BSDF, none of the plugin's options.
    props = {c.get("name"): _substitute(c.get("value", ""), values) for c in el if c.tag != "bsdf"}
    try:
        strength = float(props.get("strength", 1.0))
    except ValueError:                         # an unresolved $parameter: the plugin will say
        strength = 1.0
    if strength != 1.0:
        notes.add(f"Mitsuba's normalmap has no strength parameter: it uses the map as is "
                  f"(the scene's strength is {props['strength']}).")
    if props.get("normalmap_convention", "opengl") != "opengl":
        notes.add("Mitsuba's normalmap assumes the OpenGL convention; the scene's map is DirectX.")
    el.set("type", "normalmap")
    for child in list(el):
        if child.tag == "string" and child.get("name") == "normalmap":
            tex = ET.Element("texture", type="bitmap", name="normalmap")
            ET.SubElement(tex, "string", name="filename", value=child.get("value"))
            ET.SubElement(tex, "boolean", name="raw", value="true")
            el.remove(child)
            el.insert(0, tex)
    _remove_props(el, {"model", "tangent_facet", "max_bounces", "strength", "normalmap_convention"})
    flag = "true" if method.fixes else "false"
    _set_prop(el, "boolean", "use_shadowing_function", flag)
    _set_prop(el, "boolean", "flip_invalid_normals", flag)
    return el


def rewrite(root: ET.Element, method: Method, values: dict | None = None,
            notes: set | None = None) -> ET.Element:
    """A copy of the scene with every ``normalmap_microfacet`` BSDF rewritten for ``method``."""
    root = copy.deepcopy(root)
    values = values or {}
    notes = set() if notes is None else notes
    targets = [(parent, i) for parent in root.iter() for i, child in enumerate(parent)
               if child.tag == "bsdf" and child.get("type") == PLUGIN]
    for parent, i in targets:
        parent[i] = _convert(parent[i], method, values, notes)
    return root


def film_size_parameters(root: ET.Element) -> set:
    """The ``$`` parameters that the films' width and height refer to."""
    return {name for film in root.iter("film") for c in film
            if c.tag == "integer" and c.get("name") in ("width", "height")
            for name in re.findall(r"\$(\w+)", c.get("value", ""))}


def set_film_width(root: ET.Element, values: dict, width: int | None) -> tuple:
    """Scale the film down to ``width`` pixels (keeping its aspect ratio); returns (w, h)."""
    sizes = []
    for film in root.iter("film"):
        def get(name, default):
            for c in film:
                if c.tag == "integer" and c.get("name") == name:
                    return int(float(_substitute(c.get("value"), values)))
            return default
        w, h = get("width", 768), get("height", 576)
        if width is not None and w > width:
            w, h = width, max(1, int(round(h * width / w)))
        for name, v in (("width", w), ("height", h)):
            _remove_props(film, {name})
            film.insert(0, ET.Element("integer", name=name, value=str(v)))
        sizes.append((w, h))
    return sizes[0] if sizes else (768, 576)


def load_method_scene(src: SceneSource, root: ET.Element, values: dict, method: Method,
                      notes: set | None = None):
    """Load ``root`` rewritten for ``method`` in the active variant; check it."""
    xml = ET.tostring(rewrite(root, method, values, notes), encoding="unicode")
    params = src.params
    if method.kind != "microfacet":
        # Mitsuba rejects unused parameters: drop those only the plugin used
        # (a microfacet method keeps every reference, so it still reports typos).
        params = {k: v for k, v in params.items() if re.search(rf"\${k}\b", xml)}
    try:
        scene = mi.load_string(xml, **params)
    except Exception as exc:
        # Locations in the rewritten string mean nothing to the user (comments are gone).
        msg = re.sub(r"(While loading|At) string \(line \d+, col \d+\):\s*", "", one_line(exc))
        if "unused parameters" in msg:
            msg += " (compare sets the model and tangent_facet of each BSDF itself)"
        raise SceneError(f"cannot load {src.path.name} ({method.key}): {msg}") from None
    try:
        check_scene(scene)
    except ValueError as exc:
        raise SceneError(f"{src.path.name}: {exc}") from None
    return scene


# ---------------------------------------------------------------------------
# Rendering and image metrics
# ---------------------------------------------------------------------------

def render_image(scene, spp: int, seed: int, pass_spp: int = 16) -> np.ndarray:
    """Linear RGB (H x W x 3, float64) at ``spp``, rendered in passes of ≤ ``pass_spp``."""
    acc, done, i = None, 0, 0
    while done < spp:
        n = min(pass_spp, spp - done)
        img = np.array(mi.render(scene, spp=n, seed=(seed + i) % (1 << 32)), dtype=np.float64)[..., :3]
        acc = img * n if acc is None else acc + img * n
        done, i = done + n, i + 1
    return acc / spp


def surface_maps(scene, sub: int = 4):
    """Per pixel of the first sensor, from ``sub`` x ``sub`` primary rays: the
    coverage of each normal-mapped shape (k x H x W, in [0, 1]) and the mean
    |cos| between the view ray and the shading normal on them (H x W)."""
    sensor = scene.sensors()[0]
    W, H = (int(v) for v in sensor.film().crop_size())
    shapes = normal_mapped_shapes(scene)
    n = W * H * sub * sub
    idx = dr.arange(mi.UInt32, n)
    pix, k = idx // (sub * sub), idx % (sub * sub)
    x = mi.Float(pix % W) + (mi.Float(k % sub) + 0.5) / sub
    y = mi.Float(pix // W) + (mi.Float(k // sub) + 0.5) / sub
    ray, _ = sensor.sample_ray(0.0, 0.5, mi.Point2f(x / W, y / H), mi.Point2f(0.5))
    si = scene.ray_intersect(ray)
    hits = [np.array(si.is_valid() & (si.shape == mi.ShapePtr(s)), dtype=np.float64) for s in shapes]
    hits = np.stack(hits).reshape(len(shapes), H, W, sub * sub) if hits else np.zeros((0, H, W, sub * sub))
    cos = np.array(dr.abs(dr.dot(si.sh_frame.n, ray.d)), dtype=np.float64).reshape(H, W, sub * sub)
    any_hit = hits.sum(axis=0)
    mean_cos = (cos * any_hit).sum(axis=-1) / np.maximum(any_hit.sum(axis=-1), 1.0)
    coverage = hits.mean(axis=-1)
    return coverage, np.where(coverage.sum(axis=0) > 0, mean_cos, 1.0)


def luminance(rgb: np.ndarray) -> np.ndarray:
    return rgb[..., 0] * 0.2126 + rgb[..., 1] * 0.7152 + rgb[..., 2] * 0.0722


def rel_mse(x: np.ndarray, ref: np.ndarray, mask: np.ndarray | None = None) -> float:
    """mean((x − ref)² / (ref² + 1e-2)) over pixels (in ``mask``) and channels."""
    err = (x - ref) ** 2 / (ref ** 2 + REL_MSE_EPS)
    if mask is not None:
        err = err[mask]
    return float(err.mean()) if err.size else float("nan")


def near_black_fraction(rgb: np.ndarray, mask: np.ndarray, threshold) -> float:
    """Fraction of ``mask`` pixels whose luminance is below ``threshold`` (a number,
    or an image of per-pixel thresholds)."""
    if not mask.any():
        return float("nan")
    below = luminance(rgb) < threshold
    return float(below[mask].mean())


def _best_window(score: np.ndarray, size: int):
    """(sum, x, y) of the ``size`` x ``size`` window of ``score`` with the largest sum."""
    H, W = score.shape
    S = np.pad(score.cumsum(0).cumsum(1), ((1, 0), (1, 0)))
    step = max(1, size // 4)
    ys = np.append(np.arange(0, H - size, step), H - size)
    xs = np.append(np.arange(0, W - size, step), W - size)
    sums = (S[ys[:, None] + size, xs[None, :] + size] - S[ys[:, None], xs[None, :] + size]
            - S[ys[:, None] + size, xs[None, :]] + S[ys[:, None], xs[None, :]])
    iy, ix = np.unravel_index(np.argmax(sums), sums.shape)
    return float(sums[iy, ix]), int(xs[ix]), int(ys[iy])


def choose_crops(scores, n: int, size: int) -> list:
    """Up to ``n`` non-overlapping ``size`` x ``size`` windows ``(x, y, size)``.

    ``scores`` is one map (H x W) or a stack of maps (k x H x W, e.g. one per
    shape): first the best window of each map in turn (so every shape with a
    grazing region gets a crop), then greedily by their sum."""
    scores = np.array(scores, dtype=np.float64, ndmin=3)
    H, W = scores.shape[1:]
    size = max(1, min(size, W, H))
    order = list(np.argsort(-scores.sum(axis=(1, 2)))) + [None] * n
    crops = []
    for i in order:
        if len(crops) >= n:
            break
        total, x0, y0 = _best_window(scores.sum(axis=0) if i is None else scores[i], size)
        if total <= 0:
            continue
        crops.append((x0, y0, size))
        m = size // 4
        scores[:, max(0, y0 - m):y0 + size + m, max(0, x0 - m):x0 + size + m] = 0
    return crops


# ---------------------------------------------------------------------------
# The BSDFs alone: white furnace and reciprocity
# ---------------------------------------------------------------------------

CHECK_TILTS = (30.0, 60.0)           # θ_p of the constant normal map, degrees
CHECK_THETA_I = (0.0, 60.0, 85.0)    # θ_i of the furnace test, degrees


def _bsdf_dict(method: Method, theta_p: float) -> dict:
    t = np.radians(theta_p)
    n = np.array([np.sin(t), 0.0, np.cos(t)])
    texel = np.tile((n * 0.5 + 0.5).astype(np.float32), (2, 2, 1))
    tex = {"type": "bitmap", "bitmap": mi.Bitmap(texel, mi.Bitmap.PixelFormat.RGB), "raw": True}
    nested = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}
    if method.kind == "flat":
        return nested
    if method.kind == "classic":
        return {"type": "normalmap", "normalmap": tex, "bsdf": nested,
                "flip_invalid_normals": method.fixes, "use_shadowing_function": method.fixes}
    d = {"type": PLUGIN, "normalmap": tex, "bsdf": nested, "model": method.model}
    if method.model not in ("analytic", "faithful"):
        d["tangent_facet"] = method.tangent_facet
    return d


def _surface_interaction(wi: np.ndarray, rng) -> "mi.SurfaceInteraction3f":
    n = len(wi)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.p = mi.Point3f(*rng.uniform(-1.0, 1.0, (3, n)))   # the walks hash p: one stream per query
    si.n = mi.Normal3f(0.0, 0.0, 1.0)
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    si.dp_du, si.dp_dv = mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0)
    si.uv = mi.Point2f(0.5, 0.5)
    si.wi = mi.Vector3f(*wi.T)
    si.t = 1.0
    return si


def _direction(theta_deg, phi_deg):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], axis=-1)


def bsdf_checks(method: Method, samples: int = 1 << 16, pairs: int = 12, repeats: int = 2048,
                seed: int = 7) -> dict:
    """White-furnace albedo and reciprocity of ``method`` with a white Lambertian
    nested BSDF under a constant normal map tilted by each of :data:`CHECK_TILTS`
    (azimuth 0).

    - ``albedo[(θ_p, θ_i)]``: mean sample weight for ω_i at θ_i, azimuth 195°
      (the side away from the tilt, 15° off its plane), over ``samples`` samples;
    - ``reciprocity[θ_p]``: over ``pairs`` random direction pairs (θ ≤ 85°),
      mean of |f(i, o) − f(o, i)| / ((f(i, o) + f(o, i)) / 2), with
      f = eval / cosθ_o averaged over ``repeats`` queries at distinct points
      (the random walks' ``eval`` is a stochastic estimate); ``reciprocity_se``
      is the same ratio for one standard error of the difference, the noise
      floor of the measurement.
    """
    rng = np.random.default_rng(seed)
    ctx = mi.BSDFContext()
    out = {"albedo": {}, "reciprocity": {}, "reciprocity_se": {}}
    for theta_p in CHECK_TILTS:
        bsdf = mi.load_dict(_bsdf_dict(method, theta_p))
        # White furnace: E[weight] is the albedo.
        wi = np.repeat(_direction(np.array(CHECK_THETA_I), 195.0), samples, axis=0)
        si = _surface_interaction(wi, rng)
        s1 = mi.Float(rng.random(len(wi)))
        s2 = mi.Point2f(*rng.random((2, len(wi))))
        _, weight = bsdf.sample(ctx, si, s1, s2)
        w = np.nan_to_num(np.array(weight[0], dtype=np.float64)).reshape(len(CHECK_THETA_I), samples)
        for theta_i, a in zip(CHECK_THETA_I, w.mean(axis=1)):
            out["albedo"][(theta_p, theta_i)] = float(a)

        # Reciprocity: f(i, o) against f(o, i) on the same pairs.
        theta = np.degrees(np.arccos(rng.uniform(np.cos(np.radians(85.0)), 1.0, (2, pairs))))
        phi = rng.uniform(0.0, 360.0, (2, pairs))
        a_dir, b_dir = _direction(theta[0], phi[0]), _direction(theta[1], phi[1])
        wi = np.repeat(np.concatenate([a_dir, b_dir]), repeats, axis=0)
        wo = np.repeat(np.concatenate([b_dir, a_dir]), repeats, axis=0)
        value = bsdf.eval(ctx, _surface_interaction(wi, rng), mi.Vector3f(*wo.T))
        f = np.nan_to_num(np.array(value[0], dtype=np.float64)) / wo[:, 2]
        f = f.reshape(2, pairs, repeats)
        mean, var = f.mean(axis=-1), f.var(axis=-1) / repeats
        avg = 0.5 * (mean[0] + mean[1])
        ok = avg > 1e-6
        out["reciprocity"][theta_p] = float(np.mean(np.abs(mean[0] - mean[1])[ok] / avg[ok])) if ok.any() else 0.0
        out["reciprocity_se"][theta_p] = float(np.mean(np.sqrt(var[0] + var[1])[ok] / avg[ok])) if ok.any() else 0.0
    return out


# ---------------------------------------------------------------------------
# The comparison
# ---------------------------------------------------------------------------

@dataclass
class Settings:
    spp: int = 32
    ref_spp: int = 128
    width: int | None = 320
    seed: int = 0
    crops: int = 3
    check_samples: int = 1 << 16
    check_repeats: int = 2048
    pass_spp: int = 16


QUICK = Settings(spp=2, ref_spp=4, width=64, crops=2, check_samples=1 << 10, check_repeats=64)


@contextmanager
def scene_folder(path: Path):
    """Mitsuba's file resolver searches ``path``'s folder first while the block runs, and
    is restored afterwards (so the next scene never finds its files in this one's folder)."""
    thread = mi.Thread.thread()
    saved = mi.FileResolver(thread.file_resolver())
    resolver = mi.FileResolver(saved)
    resolver.prepend(str(Path(path).resolve().parent))
    thread.set_file_resolver(resolver)
    try:
        yield
    finally:
        thread.set_file_resolver(saved)


def compare_scene(src: SceneSource, out_dir, settings: Settings, methods=METHODS, log=print,
                  limits=None) -> dict:
    """Render ``src`` with each method; write EXR/PNG per method into ``out_dir``.

    Returns the data of one report section (see :func:`mfnormal.report.write_report`).
    """
    with scene_folder(src.path):
        return _compare_scene(src, out_dir, settings, methods, log, limits)


def _compare_scene(src: SceneSource, out_dir, settings: Settings, methods, log, limits) -> dict:
    from .validate import DEFAULT_LIMITS, check_render_size

    out_dir = Path(out_dir)
    root, values = parse_scene(src)
    film_params = film_size_parameters(root)
    width, height = set_film_width(root, values, settings.width)
    # The film's $width / $height are substituted now: those -D values are used up.
    text = ET.tostring(root, encoding="unicode")
    src = dataclasses.replace(src, params={k: v for k, v in src.params.items()
                                           if k not in film_params or re.search(rf"\${k}\b", text)})
    check_render_size(width, height, limits or DEFAULT_LIMITS, f"{src.path.name}: the film")
    notes: set = set()

    # Which pixels show normal-mapped shapes, and where they are seen at grazing angles.
    probe = load_method_scene(src, root, values, METHOD_BY_KEY["analytic"], notes)
    coverage_by_shape, mean_cos = surface_maps(probe)
    del probe
    coverage = coverage_by_shape.sum(axis=0)
    mask = coverage >= 1.0                     # fully covered: no background or edge blending
    grazing = (coverage > 0) & (mean_cos < GRAZING_COS)
    crop_size = max(12, min(width, height) // 5)
    crops = choose_crops(coverage_by_shape * (grazing + 0.02), settings.crops, crop_size)

    results = []
    for i, method in enumerate(methods):
        scene = load_method_scene(src, root, values, method, notes)
        t0 = time.perf_counter()
        img = render_image(scene, settings.spp, settings.seed * 1000, settings.pass_spp)
        t1 = time.perf_counter()
        ref = render_image(scene, settings.ref_spp, settings.seed * 1000 + 500_000, settings.pass_spp)
        t2 = time.perf_counter()
        del scene
        img32, bad = sanitize(img.astype(np.float32))
        ref32, bad_ref = sanitize(ref.astype(np.float32))
        save_render(img32, out_dir / method.key)
        save_render(ref32, out_dir / f"{method.key}_ref")
        results.append({"method": method, "image": img32, "ref": ref32, "time": t1 - t0,
                        "ref_time": t2 - t1, "nonfinite": bad + bad_ref})
        log(f"  [{i + 1}/{len(methods)}] {method.key:<22} {t1 - t0:6.1f} s ({settings.spp} spp), "
            f"reference {t2 - t1:6.1f} s ({settings.ref_spp} spp)")

    # Metrics: the black thresholds come from the flat reference (or the first method's).
    base = next((r for r in results if r["method"].kind == "flat"), results[0])
    base_lum = luminance(base["ref"])
    threshold = BLACK_FRACTION * float(np.median(base_lum[mask])) if mask.any() else 0.0
    for r in results:
        r["rel_mse"] = rel_mse(r["image"], r["ref"])
        r["rel_mse_mask"] = rel_mse(r["image"], r["ref"], mask)
        r["black"] = near_black_fraction(r["image"], mask, threshold)
        r["black_ref"] = near_black_fraction(r["ref"], mask, threshold)
        r["darkened"] = near_black_fraction(r["ref"], mask, DARKENED_FRACTION * base_lum)
        r["png"] = tonemap(r["image"])
        r["crops"] = [r["png"][y:y + s, x:x + s] for x, y, s in crops]
    mask_png = tonemap(np.repeat((0.3 * (coverage > 0) + 0.7 * grazing)[..., None], 3, axis=-1))
    atomic_write(out_dir / "mask.png", lambda p: Path(p).write_bytes(png_bytes(mask_png)))
    return {"name": src.name, "title": src.title, "path": str(src.path), "width": width,
            "height": height, "spp": settings.spp, "ref_spp": settings.ref_spp, "crops": crops,
            "mask_fraction": float(mask.mean()), "grazing_fraction": float(grazing.mean()),
            "black_threshold": threshold, "notes": sorted(notes), "results": results,
            "mask_png": mask_png}


def compare(scenes, out_dir, settings: Settings = Settings(), methods=METHODS, validation=None,
            params: dict | None = None, log=print, command: str = "", limits=None) -> Path:
    """Compare ``methods`` on each scene (bundled name or XML path); write
    ``out_dir/report.html`` and the renders (``out_dir/<scene>/<method>.exr|png``)."""
    from . import report

    out_dir = Path(out_dir)
    started = time.perf_counter()
    sections = []
    for name in scenes:
        src = scene_source(name, out_dir / "assets", params)
        # A name usable in file names and HTML ids, unique within the report.
        src.name = re.sub(r"[^\w-]", "_", src.name) or "scene"
        while any(s["name"] == src.name for s in sections):
            src.name += "_"
        log(f"scene {src.name} ({src.path})")
        sections.append(compare_scene(src, out_dir / src.name, settings, methods, log, limits))
    log("BSDF checks (white furnace, reciprocity)")
    checks = []
    for method in methods:
        t0 = time.perf_counter()
        checks.append({"method": method, **bsdf_checks(method, settings.check_samples,
                                                       repeats=settings.check_repeats)})
        log(f"  {method.key:<22} {time.perf_counter() - t0:5.1f} s")
    figures = report.find_figures(validation) if validation else []
    meta = {"command": command, "variant": mi.variant(), "mitsuba": mi.__version__,
            "drjit": dr.__version__, "llvm": mfnormal.LLVM_PATH,
            "threads": dr.thread_count(), "total_time": time.perf_counter() - started}
    path = report.write_report(out_dir / "report.html", sections, checks, figures, meta)
    log(f"total {meta['total_time']:.1f} s")
    return path
