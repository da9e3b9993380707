"""Render one scene with every normal-mapping method and measure each.

``mfnormal compare SCENE`` (see :mod:`mfnormal.cli`) is a thin layer over
:func:`compare`: it takes a Mitsuba XML scene whose normal-mapped materials are
``normalmap_microfacet`` BSDFs and renders it once per method of the catalogue
(:data:`mfnormal.methods.METHODS`), every such BSDF rewritten for the method
(:func:`mfnormal.io.scene_xml.rewrite`).

For each method it measures the render time, the relative MSE against a
higher-spp reference of the same method, and the fraction of near-black pixels
on the normal-mapped surfaces (and of pixels much darker than the flat render)
(:mod:`mfnormal.report.metrics`, on the pixels :mod:`mfnormal.report.coverage` finds);
:func:`mfnormal.report.bsdf_checks.bsdf_checks` adds the white-furnace albedo and the
reciprocity error of each method's BSDF alone. A method whose model refuses the scene's
material by design (:func:`mfnormal.models.interface.refusal`: the paper's models on a
transmitting nested BSDF, read from the scene loaded with the default model) is not rendered:
the report shows its reason in place of its render and measurements. The results feed
:func:`mfnormal.report.html.write_report`, which only writes the HTML.

Bundled scenes (:data:`mfnormal.scenes.assets.BUNDLED`): ``demo`` (a), ``model`` (b),
``eggcrate`` (c), ``water`` (d), ``glass`` (e) and ``underwater`` (f), with their assets
generated on the fly.
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

from mfnormal.report import html as report
from mfnormal.scenes.assets import BUNDLED
from mfnormal.report.bsdf_checks import bsdf_checks
from mfnormal.report.coverage import choose_crops, surface_maps
from mfnormal.files import atomic_write
from mfnormal.io.images import png_bytes, sanitize_counts, save_render, tonemap
from mfnormal.io.messages import one_line
from mfnormal.methods import METHOD_BY_KEY, METHODS, PLUGIN, Method
from mfnormal.report.metrics import luminance, near_black_fraction, rel_mse
from mfnormal.render.passes import render_rgb
from mfnormal.io.scene_checks import check_scene, plugin_instances
from mfnormal.models.interface import DEFAULT_MODEL, refusal
from mfnormal.io.scene_xml import (SceneError, defaults, film_size_parameters, read_scene, references,
                        rewrite, set_film_width)
from mfnormal.io.inputs import DEFAULT_LIMITS, check_render_size

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
    """A bundled scene (:data:`mfnormal.scenes.assets.BUNDLED`, its assets generated under
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


def method_xml(src: SceneSource, root: ET.Element, values: dict, method: Method,
               notes: set | None = None) -> tuple:
    """(XML text, ``$`` parameters) of ``root`` rewritten for ``method``."""
    xml = ET.tostring(rewrite(root, method, values, notes), encoding="unicode")
    params = src.params
    if method.kind != "microfacet":
        # Mitsuba rejects unused parameters: drop those only the plugin used
        # (a microfacet method keeps every reference, so it still reports typos).
        params = {k: v for k, v in params.items() if references(xml, k)}
    return xml, params


def load_method_scene(src: SceneSource, root: ET.Element, values: dict, method: Method,
                      notes: set | None = None):
    """Load ``root`` rewritten for ``method`` in the active variant; check it."""
    xml, params = method_xml(src, root, values, method, notes)
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
                  limits=None, cluster=None):
    """Render ``src`` with each method; write EXR/PNG per method into ``out_dir``.

    Returns the data of one report section (see :func:`mfnormal.report.html.write_report`);
    with ``cluster`` (a :class:`mfnormal.render.cluster.Cluster`), a function that returns it
    once the renders, submitted to the cluster now, are done.
    """
    with scene_folder(src.path):
        finish = _start_scene(src, Path(out_dir), settings, methods, log, limits, cluster)
        return finish if cluster is not None else finish()


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


def _seeds(settings: Settings) -> tuple:
    """The (render, reference) seeds of :func:`mfnormal.render.passes.render_rgb`."""
    return settings.seed * 1000, settings.seed * 1000 + 500_000


def _record(i, n, method, img, ref, times, settings, out_dir, log) -> dict:
    """One method's result, its render and reference written as EXR/PNG pairs."""
    img32, bad, neg = sanitize_counts(img.astype(np.float32))
    ref32, bad_ref, neg_ref = sanitize_counts(ref.astype(np.float32))
    save_render(img32, out_dir / method.key)
    save_render(ref32, out_dir / f"{method.key}_ref")
    log(f"  [{i + 1}/{n}] {method.key:<22} {times[0]:6.1f} s ({settings.spp} spp), "
        f"reference {times[1]:6.1f} s ({settings.ref_spp} spp)")
    for what, count in (("NaN/Inf", bad + bad_ref), ("negative", neg + neg_ref)):
        if count:
            log(f"  warning: {method.key}: {count} pixel(s) of its render and reference had "
                f"{what} values and were written and scored as 0")
    return {"method": method, "image": img32, "ref": ref32, "time": times[0],
            "ref_time": times[1], "nonfinite": bad + bad_ref, "negative": neg + neg_ref}


def _render_methods(src, root, values, methods, settings, out_dir, notes, log) -> list:
    """Each method's render and reference (written as EXR/PNG pairs), with their times."""
    results = []
    seed, ref_seed = _seeds(settings)
    for i, method in enumerate(methods):
        scene = load_method_scene(src, root, values, method, notes)
        t0 = time.perf_counter()
        img = render_rgb(scene, settings.spp, seed, settings.pass_spp)
        t1 = time.perf_counter()
        ref = render_rgb(scene, settings.ref_spp, ref_seed, settings.pass_spp)
        t2 = time.perf_counter()
        del scene
        results.append(_record(i, len(methods), method, img, ref, (t1 - t0, t2 - t1), settings,
                               out_dir, log))
    return results


def _submit_methods(src, root, values, methods, settings, out_dir, notes, log, cluster):
    """:func:`_render_methods` on ``cluster``: each render and reference one task, submitted
    now (every scene checked here first, as a local run would); returns the function
    that collects and records them."""
    from mfnormal.render.bundle import SceneSpec, files_digest, xml_bundle

    bundles, files = [], {}
    for method in methods:
        load_method_scene(src, root, values, method, notes)     # its errors, here
        xml, params = method_xml(src, root, values, method, notes)
        text, params, named = xml_bundle(xml, src.path.parent, params)
        files.update(named)
        bundles.append((text, tuple(sorted(params.items()))))
    digest = files_digest(files)
    seed, ref_seed = _seeds(settings)
    jobs = []
    for text, params in bundles:
        spec = SceneSpec("xml", text, params, files=digest)
        jobs += [(spec, settings.spp, seed, settings.pass_spp),
                 (spec, settings.ref_spp, ref_seed, settings.pass_spp)]
    collect = cluster.render_rgb_many(jobs, files, digest)

    def finish() -> list:
        done = collect()
        return [_record(i, len(methods), m, done[2 * i][0], done[2 * i + 1][0],
                        (done[2 * i][1], done[2 * i + 1][1]), settings, out_dir, log)
                for i, m in enumerate(methods)]
    return finish


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


def _start_scene(src: SceneSource, out_dir: Path, settings: Settings, methods, log, limits,
                 cluster=None):
    """What :func:`compare_scene` does, as a function that returns the section: the
    renders are submitted to ``cluster`` now, or (None) made here when it is called."""
    src, root, values, width, height = _sized_scene(src, settings, limits)
    notes: set = set()

    # The default model loads every material: its scene shows which methods refuse it, which
    # pixels show normal-mapped shapes, and where they are seen at grazing angles.
    probe = load_method_scene(src, root, values, METHOD_BY_KEY[DEFAULT_MODEL], notes)
    methods, refused = _methods_to_render(src, probe, methods, log)
    coverage_by_shape, mean_cos = surface_maps(probe)
    del probe
    coverage = coverage_by_shape.sum(axis=0)
    mask = coverage >= 1.0                     # fully covered: no background or edge blending
    grazing = (coverage > 0) & (mean_cos < GRAZING_COS)
    crop_size = max(12, min(width, height) // 5)
    crops = choose_crops(coverage_by_shape * (grazing + 0.02), settings.crops, crop_size)

    if cluster is None:
        def render():
            return _render_methods(src, root, values, methods, settings, out_dir, notes, log)
    else:
        render = _submit_methods(src, root, values, methods, settings, out_dir, notes, log, cluster)

    def finish() -> dict:
        results = render()
        threshold = _measure(results, mask, crops)
        mask_png = tonemap(np.repeat((0.3 * (coverage > 0) + 0.7 * grazing)[..., None], 3, axis=-1))
        atomic_write(out_dir / "mask.png", lambda p: Path(p).write_bytes(png_bytes(mask_png)))
        return _section(src, width, height, settings, crops, mask, grazing, threshold, notes,
                        results, refused, mask_png)
    return finish


def refusals(scene, methods) -> dict:
    """``{method: reason}`` for each of ``methods`` whose model refuses a ``normalmap_microfacet``
    of the loaded ``scene`` by design (:func:`mfnormal.models.interface.refusal`: the paper's
    models on a transmitting nested BSDF), in the order of ``methods``."""
    nested = [bsdf.nested for bsdf in plugin_instances(scene)]
    out = {}
    for method in methods:
        if method.kind == "microfacet":
            reason = next(filter(None, (refusal(method.model, n) for n in nested)), None)
            if reason:
                out[method] = reason
    return out


def _methods_to_render(src: SceneSource, probe, methods, log) -> tuple:
    """(the methods to render, ``{method: reason}`` of those that refuse the scene), each refusal
    logged; a SceneError when every method refuses it."""
    refused = refusals(probe, methods)
    for method, reason in refused.items():
        log(f"  {method.key:<22} refuses this scene, not rendered: {reason}")
    rendered = [m for m in methods if m not in refused]
    if not rendered:
        method, reason = next(iter(refused.items()))
        raise SceneError(f"cannot compare {src.path.name}: every method refuses it "
                         f"({method.key}: {reason})")
    return rendered, refused


def _section(src, width, height, settings, crops, mask, grazing, threshold, notes, results,
             refused, mask_png) -> dict:
    return {"name": src.name, "title": src.title, "path": str(src.path), "width": width,
            "height": height, "spp": settings.spp, "ref_spp": settings.ref_spp, "crops": crops,
            "mask_fraction": float(mask.mean()), "grazing_fraction": float(grazing.mean()),
            "black_threshold": threshold, "notes": sorted(notes), "results": results,
            "refused": [{"method": m, "reason": r} for m, r in refused.items()],
            "mask_png": mask_png}


def _checks(methods, settings: Settings, log, collect=None) -> list:
    """:func:`mfnormal.report.bsdf_checks.bsdf_checks` of each method (``collect()``: their results
    from the cluster)."""
    log("BSDF checks (white furnace, reciprocity)")
    if collect is not None:
        return [{"method": m, **c} for m, c in zip(methods, collect())]
    checks = []
    for method in methods:
        t0 = time.perf_counter()
        checks.append({"method": method, **bsdf_checks(method, settings.check_samples,
                                                       repeats=settings.check_repeats)})
        log(f"  {method.key:<22} {time.perf_counter() - t0:5.1f} s")
    return checks


def compare(scenes, out_dir, settings: Settings = Settings(), methods=METHODS, validation=None,
            params: dict | None = None, log=print, command: str = "", limits=None,
            cluster=None) -> Path:
    """Compare ``methods`` on each scene (bundled name or XML path); write
    ``out_dir/report.html`` and the renders (``out_dir/<scene>/<method>.exr|png``).
    With ``cluster`` (a :class:`mfnormal.render.cluster.Cluster`) every scene's renders and
    references, and the BSDF checks, are submitted first, then collected: the same seeds, the same numbers."""
    out_dir = Path(out_dir)
    started = time.perf_counter()
    sections, names = [], []
    for name in scenes:
        src = scene_source(name, out_dir / "assets", params)
        # A name usable in file names and HTML ids, unique within the report.
        src.name = re.sub(r"[^\w-]", "_", src.name) or "scene"
        while src.name in names:
            src.name += "_"
        names.append(src.name)
        log(f"scene {src.name} ({src.path})")
        sections.append(compare_scene(src, out_dir / src.name, settings, methods, log, limits, cluster))
    collect = None
    if cluster is not None:
        collect = cluster.call_each(bsdf_checks, [((m, settings.check_samples), {"repeats": settings.check_repeats})
                                                  for m in methods])
        sections = [finish() for finish in sections]
    checks = _checks(methods, settings, log, collect)
    figures = report.find_figures(validation) if validation else []
    meta = {"command": command, "variant": mi.variant(), "mitsuba": mi.__version__,
            "drjit": dr.__version__, "llvm": mfnormal.LLVM_PATH,
            "threads": dr.thread_count(), "total_time": time.perf_counter() - started}
    path = report.write_report(out_dir / "report.html", sections, checks, figures, meta)
    log(f"total {meta['total_time']:.1f} s")
    return path
