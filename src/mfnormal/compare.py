"""Render one scene with every normal-mapping method and measure each.

``mfnormal compare SCENE`` (see :mod:`mfnormal.cli`) is a thin layer over
:func:`compare`: it takes a Mitsuba XML scene whose normal-mapped materials are
``normalmap_microfacet`` BSDFs and renders it once per method of the catalogue
(:data:`mfnormal.methods.METHODS`), every such BSDF rewritten for the method
(:func:`mfnormal.scene_xml.rewrite`).

For each method it measures the render time, the relative MSE against a
higher-spp reference of the same method, and the fraction of near-black pixels
on the normal-mapped surfaces (and of pixels much darker than the flat render)
(:mod:`mfnormal.metrics`, on the pixels :mod:`mfnormal.coverage` finds);
:func:`mfnormal.bsdf_checks.bsdf_checks` adds the white-furnace albedo and the
reciprocity error of each method's BSDF alone. The results feed
:func:`mfnormal.report.write_report`, which only writes the HTML.

Bundled scenes (:data:`mfnormal.assets.BUNDLED`): ``demo`` (a), ``model`` (b) and
``eggcrate`` (c), with their assets generated on the fly.
"""

from __future__ import annotations

import dataclasses
import re
import time
import xml.etree.ElementTree as ET
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

import mfnormal
import drjit as dr
import mitsuba as mi

from . import report
from .assets import BUNDLED
from .bsdf_checks import bsdf_checks
from .coverage import choose_crops, surface_maps
from .images import atomic_write, png_bytes, sanitize, save_render, tonemap
from .messages import one_line
from .methods import METHOD_BY_KEY, METHODS, PLUGIN, Method
from .metrics import luminance, near_black_fraction, rel_mse
from .rendering import render_rgb
from .scene_checks import check_scene
from .scene_xml import (SceneError, defaults, film_size_parameters, read_scene, references,
                        rewrite, set_film_width)
from .validate import DEFAULT_LIMITS, check_render_size

__all__ = ["SceneSource", "scene_source", "Settings", "QUICK", "compare_scene", "compare"]

#: A pixel is near-black below this fraction of the median luminance of the
#: normal-mapped surface in the flat reference.
BLACK_FRACTION = 0.05
#: A pixel is darkened below this fraction of the flat reference's luminance at the same pixel.
DARKENED_FRACTION = 0.1
#: A normal-mapped pixel is grazing where the mean |cos| between view ray and normal is below this.
GRAZING_COS = 0.3


# ---------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------

@dataclass
class SceneSource:
    """An XML scene to compare: its file, ``$`` parameters and a display title."""
    name: str
    path: Path
    params: dict = field(default_factory=dict)
    title: str = ""


def scene_source(scene: str, assets_root, params: dict | None = None) -> SceneSource:
    """A bundled scene (:data:`mfnormal.assets.BUNDLED`, its assets generated under
    ``assets_root``) or an XML path."""
    params = dict(params or {})
    if scene in BUNDLED:
        b = BUNDLED[scene]
        assets = b.generate(Path(assets_root) / b.name)
        return SceneSource(b.name, b.xml, {**b.parameters(assets), **params}, b.title)
    path = Path(scene)
    if not path.is_file():
        raise SceneError(f"scene file not found: {path}"
                         + ("" if path.suffix else f" (bundled scenes: {', '.join(BUNDLED)})"))
    return SceneSource(path.stem, path, params, path.name)


def parse_scene(src: SceneSource):
    """(XML root, values of its ``$`` parameters: defaults overridden by ``src.params``)."""
    root = read_scene(src.path)
    values = defaults(root)
    values.update(src.params)
    n = sum(1 for el in root.iter("bsdf") if el.get("type") == PLUGIN)
    if n == 0:
        raise SceneError(f"{src.path.name} has no <bsdf type=\"{PLUGIN}\"> to compare "
                         "normal-mapping methods on")
    return root, values


def load_method_scene(src: SceneSource, root: ET.Element, values: dict, method: Method,
                      notes: set | None = None):
    """Load ``root`` rewritten for ``method`` in the active variant; check it."""
    xml = ET.tostring(rewrite(root, method, values, notes), encoding="unicode")
    params = src.params
    if method.kind != "microfacet":
        # Mitsuba rejects unused parameters: drop those only the plugin used
        # (a microfacet method keeps every reference, so it still reports typos).
        params = {k: v for k, v in params.items() if references(xml, k)}
    try:
        scene = mi.load_string(xml, **params)
    except Exception as exc:
        # Locations in the rewritten string mean nothing to the user (comments are gone).
        msg = re.sub(r"(While loading|At) string \(line \d+, col \d+\):\s*", "", one_line(exc))
        if "unused parameters" in msg:
            msg += " (compare sets the model and tangent_facet of each BSDF itself)"
        raise SceneError(f"cannot load {src.path.name} ({method.key}): {msg}") from None
    check_scene(scene, SceneError, src.path.name)
    return scene


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


def compare_scene(src: SceneSource, out_dir, settings: Settings, methods=METHODS, log=print,
                  limits=None) -> dict:
    """Render ``src`` with each method; write EXR/PNG per method into ``out_dir``.

    Returns the data of one report section (see :func:`mfnormal.report.write_report`).
    """
    with scene_folder(src.path):
        return _compare_scene(src, Path(out_dir), settings, methods, log, limits)


def _sized_scene(src: SceneSource, settings: Settings, limits):
    """(source, XML root, ``$`` values, width, height): the film scaled to the settings' width,
    the ``-D`` values it used up dropped from the source's parameters."""
    root, values = parse_scene(src)
    film_params = film_size_parameters(root)
    width, height = set_film_width(root, values, settings.width)
    # The film's $width / $height are substituted now: those -D values are used up.
    text = ET.tostring(root, encoding="unicode")
    src = dataclasses.replace(src, params={k: v for k, v in src.params.items()
                                           if k not in film_params or references(text, k)})
    check_render_size(width, height, limits or DEFAULT_LIMITS, f"{src.path.name}: the film")
    return src, root, values, width, height


def _render_methods(src, root, values, methods, settings, out_dir, notes, log) -> list:
    """Each method's render and reference (written as EXR/PNG pairs), with their times."""
    results = []
    for i, method in enumerate(methods):
        scene = load_method_scene(src, root, values, method, notes)
        t0 = time.perf_counter()
        img = render_rgb(scene, settings.spp, settings.seed * 1000, settings.pass_spp)
        t1 = time.perf_counter()
        ref = render_rgb(scene, settings.ref_spp, settings.seed * 1000 + 500_000, settings.pass_spp)
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
    return results


def _measure(results: list, mask: np.ndarray, crops: list) -> float:
    """Add each result's metrics, tonemapped image and crops; returns the near-black
    threshold (from the flat reference, or the first method's)."""
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
    return threshold


def _compare_scene(src: SceneSource, out_dir: Path, settings: Settings, methods, log, limits) -> dict:
    src, root, values, width, height = _sized_scene(src, settings, limits)
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

    results = _render_methods(src, root, values, methods, settings, out_dir, notes, log)
    threshold = _measure(results, mask, crops)
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
