r"""Benchmark ``normalmap_microfacet`` against Mitsuba's built-in ``normalmap``.

    python -m benchmarks.run [--quick] [--profile full|production|water|all] [--variant V] [--out benchmarks]

One run measures, side by side, every method on every scene and nested BSDF:

- methods: ``builtin`` (Mitsuba's ``normalmap`` wrapping the same nested BSDF,
  its default fixes on), ``analytic``, ``separable`` x {specular, same},
  ``nonseparable`` x {specular, same};
- scenes: (a) the bundled demo (:mod:`mfnormal.cli.demo`), (b) the bundled torus
  knot (:mod:`mfnormal.scenes.assets`, when present), (c) a plane with a generated
  normal map seen at grazing angles; every normal-mapped BSDF's nested BSDF is
  replaced by the one under test;
  (d) ``control``: scene (c) with a constant normal map (every texel 40° from the
  macro normal): the constant-map control, where every method renders the same smooth content;
- nested BSDFs: diffuse, roughconductor GGX α = 0.05 and 0.3, roughplastic;
- ``water`` (its own profile): the bundled water scene (:mod:`mfnormal.scenes.assets`, a smooth
  dielectric surface with a ripple map over a floor), its own dielectric, the default model
  against the built-in wrapping the same dielectric: render time only.

Profiles: ``full`` (192×144, 16 spp, every metric), ``production`` (1280×720 on the
demo and the torus knot with the scenes' own materials: render time and compile only;
sized to about 15 minutes on 2 idle cores, see PRODUCTION), ``water`` (the water scene,
render time, under a minute) and ``quick`` (a smoke test).
The default, ``--profile all``, runs ``full``, ``production`` and ``water``, and the reverse-mode
benchmark ``benchmarks/backward.py`` (its table is copied into RESULTS.md).

Metrics:

1. render time at equal spp, warm, interleaved A/B pairs (builtin, method,
   builtin, method, ...), the median of the per-pair ratios;
2. JIT compile time of the first render with a cold kernel cache: a
   subprocess per configuration with a fresh ``DRJIT_CACHE_DIR``; first render
   minus warm render (Dr.Jit's kernel history gives the codegen/LLVM split);
3. noise at equal time: relMSE against a high-spp reference of the same
   method, each method at the spp it reaches in the built-in's time budget
   (from metric 1), as the ratio to the built-in's relMSE. Scored only where the
   methods render the same content: every scene under the
   benchmark's sky without its sun disc (``sunless``), the constant-map control (d)
   included. The full sky's ratios are reported, not scored: the microfacet models
   render sun glints through tangent-facet paths that classic normal mapping does not
   have, and so they do on the constant map (its tangent facet is as tilted as the
   map's: in RESULTS.md the control's full-sky walk cells are 7.2-15x at GGX 0.05).
   For estimators with a heavy tail (the mirror-facet walks over GGX 0.05) one such
   number (6 renders, a 256-spp reference) is itself noisy: repeated over independent
   seed blocks it spreads 7-31x (docs/diagnoses.md);
4. BSDF throughput: sample/eval queries per second on 2^20 random queries
   (random wi, wo, and normals from a texture), random-walk lengths, nested
   calls per query, and the share of time spent in nested BSDF calls (the
   plugin timed with the nested BSDF replaced by a closed-form stub); calls
   and stub are nested BSDFs of ``probes.py``, walk lengths the walk loops'
   own bounce counter (nothing in the package is patched);
5. peak memory: max RSS of the metric-2 subprocess.

Writes ``results.json`` and ``RESULTS.md`` into ``--out``. ``--quick`` runs a
subset at tiny sizes (a smoke test, about 2 minutes on 2 cores); its timings mean nothing.
``--variant`` (default llvm_ad_rgb) renders in another Mitsuba variant, e.g.
``cuda_ad_rgb`` on a GPU; an unknown or unusable variant is a one-line error.
"""

from __future__ import annotations

import argparse
import contextlib
import copy
import json
import math
import os
import platform
import resource
import shlex
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from dataclasses import asdict, dataclass
from pathlib import Path

import numpy as np

HERE = Path(__file__).resolve().parent

# The methods measured, by their key in the catalogue mfnormal.methods (which defines them;
# only the names here: Mitsuba is imported later, see import_mitsuba). "builtin" is Mitsuba's
# normalmap with its default fixes on, the catalogue's classic_fixed.
METHOD_KEYS = ("builtin", "faithful", "analytic", "separable_specular", "separable_same",
               "nonseparable_specular", "nonseparable_same")


def catalogue_method(key: str):
    """The mfnormal.methods.Method measured as ``key``."""
    from mfnormal.methods import METHOD_BY_KEY
    return METHOD_BY_KEY["classic_fixed" if key == "builtin" else key]


NESTED = {
    "diffuse": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.5, 0.5, 0.5]}},
    "ggx_0.05": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.05, "material": "Au"},
    "ggx_0.3": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3, "material": "Au"},
    "roughplastic": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.1,
                     "diffuse_reflectance": {"type": "rgb", "value": [0.2, 0.22, 0.26]}},
}
# The production profile's nested BSDFs: the scenes' own materials (nothing replaced).
NATIVE = "native"
# Which noise target applies to a nested BSDF. roughplastic is scored with the rough
# conductors (≤ 6×): its GGX α 0.1 coating is the narrow lobe that the walks' NEE meets at
# every vertex, as with the conductors; its diffuse base only adds low-variance light.
NESTED_CLASS = {"diffuse": "diffuse", "ggx_0.05": "conductor", "ggx_0.3": "conductor",
                "roughplastic": "conductor", NATIVE: None}

FULL_SCENES = ("demo", "model", "plane", "control")
SCENES = FULL_SCENES + ("water",)
SCENE_TITLES = {"demo": "(a) demo: sphere + ground", "model": "(b) torus knot, 20k triangles",
                "plane": "(c) plane at grazing view",
                "control": "(d) scene (c) with a constant normal map (40°): the constant-map control",
                "water": "the bundled water scene: a smooth dielectric with a ripple map over a floor"}
# The constant-map control's normal: θ, φ (degrees) in the map's tangent frame (φ = 0: across the view).
CONTROL_NORMAL = (40.0, 0.0)

VARIANT = "llvm_ad_rgb"          # --variant
# The integrators a profile can render under (Profile.integrator, --integrator): Mitsuba's "path",
# or "mfnormal_path" (mfnormal.plugins.mfnormal_path: path calling the plugin's fused eval_pdf_sample).
INTEGRATORS = ("path", "mfnormal_path")
MAX_DEPTH = 8

# Targets: the method's value / the built-in's.
TIME_TARGET = {"faithful": 1.25, "analytic": 1.25, "separable": 1.5, "nonseparable": 1.6}
NOISE_TARGET = {"faithful": 1.3, "analytic": 1.3, "walk_diffuse": 3.0, "walk_conductor": 6.0}
# The models with a deterministic eval (the rest are random walks).
DETERMINISTIC = ("faithful", "analytic")
COMPILE_TARGET = 2.0


@dataclass
class Profile:
    name: str
    scenes: tuple
    nested: tuple
    methods: tuple
    width: int
    height: int
    spp: int              # metric 1 (equal spp) and the built-in's budget in metric 3
    reps: int             # A/B pairs per method
    ref_spp: int          # metric 3 reference, rendered in passes of ref_pass
    ref_pass: int
    noise_seeds: int      # metric 3 renders averaged per method
    queries: int          # metric 4
    tput_reps: int
    stub_reps: int
    compile_warm_reps: int
    # Metric 2's cold runs per method (fresh processes, interleaved over the methods): the row is
    # the median run. One cold compile moves by ±20 % from run to run on a shared machine.
    compile_runs: int = 1
    metrics: tuple = ("render", "noise", "compile", "throughput")
    compile_scenes: tuple = ()      # the scenes of metric 2 (empty: every scene)
    # Metric 1's path vertices per camera sample, counted at this (width, height) for every method
    # (probes.count_calls; a counted render is not timed); None: not counted.
    vertex_size: tuple | None = None
    # The integrator every method renders under, the built-in's included, so that the ratios
    # compare BSDFs under one integrator (mfnormal_path renders the built-in faster than path
    # does, 0.82-0.97x, docs/diagnoses.md: that is not the plugin's merit); under another than
    # path the built-in is timed once more under path (a row with no target).
    integrator: str = "path"


FULL = Profile("full", FULL_SCENES, tuple(NESTED), METHOD_KEYS, width=192, height=144, spp=16, reps=5,
               ref_spp=256, ref_pass=32, noise_seeds=6, queries=1 << 20, tput_reps=5, stub_reps=3,
               compile_warm_reps=2, compile_runs=3)
# 1280×720 with the scenes' own materials. Sized from single renders (llvm_ad_rgb, 2 cores shared
# at load 7: the demo 3.9 s / 6.9 s for the built-in / nonseparable_same at 4 spp, the torus knot
# 9.0 s / 10.3 s; linear in spp, so ~2.5× faster idle): 16 spp and 4 A/B pairs, per scene 7 warm-up
# + 48 paired + 7 compile renders (the compile from the kernel history, no warm render), about
# 8 + 10 min on 2 idle cores. (64 spp would take an hour.) Two pairs were too few: on a shared
# 2-core machine one pair's ratio moves by ±8 % (6 pairs of analytic on the demo: 1.03-1.37).
PRODUCTION = Profile("production", ("demo", "model"), (NATIVE,), METHOD_KEYS, width=1280, height=720, spp=16,
                     reps=4, ref_spp=0, ref_pass=1, noise_seeds=0, queries=0, tput_reps=0, stub_reps=1,
                     compile_warm_reps=0, compile_runs=3, metrics=("render", "compile"), vertex_size=(192, 144))
QUICK = Profile("quick", ("plane", "control"), ("diffuse",), METHOD_KEYS, width=32, height=24, spp=2, reps=2,
                ref_spp=16, ref_pass=16, noise_seeds=1, queries=1 << 12, tput_reps=2, stub_reps=1,
                compile_warm_reps=1, compile_runs=2, compile_scenes=("plane",), vertex_size=(32, 24))
# The water scene with its own dielectric: the default model against the built-in wrapping the same
# dielectric, render time at equal spp only (the other methods absorb the transmitted light).
WATER = Profile("water", ("water",), (NATIVE,), ("builtin", "faithful"), width=384, height=256, spp=32,
                reps=6, ref_spp=0, ref_pass=1, noise_seeds=0, queries=0, tput_reps=0, stub_reps=1,
                compile_warm_reps=0, metrics=("render",))
PROFILES = {"full": (FULL,), "production": (PRODUCTION,), "water": (WATER,), "all": (FULL, PRODUCTION, WATER)}


def log(msg: str):
    print(msg, flush=True)


def median(xs):
    return float(statistics.median(xs)) if xs else float("nan")


def geomean(xs):
    xs = [x for x in xs if x is not None and x > 0 and math.isfinite(x)]
    return float(math.exp(sum(map(math.log, xs)) / len(xs))) if xs else float("nan")


# ---------------------------------------------------------------------------
# Mitsuba (imported lazily: a worker sets DRJIT_CACHE_DIR first)
# ---------------------------------------------------------------------------

def import_mitsuba(variant: str | None = None):
    """Mitsuba in ``variant`` (default VARIANT) with the plugin and the probes registered; an
    unknown or unusable variant raises mfnormal.cli.commands.CLIError (one line)."""
    global mfnormal, mi, dr
    import mfnormal          # noqa: F401  (before mitsuba: selects a working libLLVM)
    import drjit as dr
    import mitsuba as mi
    from mfnormal.cli.commands import setup_variant
    setup_variant(variant or VARIANT)
    from benchmarks import probes
    probes.register()
    return mfnormal, mi, dr


# ---------------------------------------------------------------------------
# Scenes
# ---------------------------------------------------------------------------

def make_plane_normalmap(size: int = 256, waves: int = 7, max_tilt_deg: float = 65.0,
                         seed: int = 7) -> np.ndarray:
    """Unit tangent-space normals (OpenGL convention) of a periodic sum of sine
    waves, scaled so the steepest normal tilts ``max_tilt_deg``."""
    rng = np.random.default_rng(seed)
    c = (np.arange(size) + 0.5) / size * 2.0 * np.pi
    x, y = np.meshgrid(c, c)                         # y grows downwards (rows)
    hx, hy = np.zeros_like(x), np.zeros_like(x)
    for _ in range(waves):
        kx, ky = rng.integers(-5, 6, 2)
        if kx == 0 and ky == 0:
            kx = 3
        amp, phase = rng.uniform(0.3, 1.0) / math.hypot(kx, ky), rng.uniform(0, 2 * np.pi)
        arg = kx * x + ky * y + phase
        hx += amp * kx * np.cos(arg)
        hy += amp * ky * np.cos(arg)
    slope = np.hypot(hx, hy).max()
    s = math.tan(math.radians(max_tilt_deg)) / slope
    n = np.stack([-s * hx, s * hy, np.ones_like(x)], axis=-1)   # image y down, normal y up
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return n.astype(np.float32)


def prepare_assets(root: Path, scenes) -> dict:
    """Generate every scene's assets under ``root``; returns what :func:`scene_dict` needs."""
    from mfnormal.scenes import assets as bundled, sky
    out = {}
    demo_assets = bundled.generate_demo_assets(root / "demo")
    out["demo"] = {"dir": str(root / "demo")}
    # The same sky without its sun disc (the glow stays): the control of the noise diagnosis.
    sunless = root / "sky_without_sun_disc.exr"
    sunless_sky = sky.envmap(256, 128, sky.DEMO, sky.GlowSun(radiance=0.0))
    mi.Bitmap(sunless_sky, mi.Bitmap.PixelFormat.RGB).write(str(sunless))
    out["sunless_envmap"] = str(sunless)
    if "plane" in scenes:
        path = root / "plane" / "waves.png"
        path.parent.mkdir(parents=True, exist_ok=True)
        mi.Bitmap(bundled.encode_normalmap(make_plane_normalmap())).write(str(path))
        out["plane"] = {"normalmap": str(path), "envmap": str(demo_assets["envmap"])}
    if "control" in scenes:
        path = write_constant_normalmap(root / "control" / "constant.png", *CONTROL_NORMAL)
        out["control"] = {"normalmap": str(path), "envmap": str(demo_assets["envmap"])}
    if "water" in scenes:
        a = bundled.generate_water_assets(root / "water")
        out["water"] = {"xml": str(bundled.WATER_XML), "params": bundled.map_and_sky_parameters(a)}
    if "model" in scenes:
        try:
            a = bundled.generate_model_assets(root / "model")
            out["model"] = {"xml": str(bundled.MODEL_XML), "dir": str(root / "model"),
                            "params": bundled.model_parameters(a)}
        except Exception as exc:       # scene (b) is optional
            out["model"] = {"error": f"{type(exc).__name__}: {exc}"}
    return out


def write_constant_normalmap(path: Path, theta_deg: float, phi_deg: float) -> Path:
    """A 4×4 normal map (PNG, raw encoding) whose every texel is the unit normal at polar angle θ
    and azimuth φ (degrees) in the tangent frame: the constant-map control."""
    from mfnormal.scenes.assets import encode_normalmap
    t, f = math.radians(theta_deg), math.radians(phi_deg)
    n = np.array([math.sin(t) * math.cos(f), math.sin(t) * math.sin(f), math.cos(t)], np.float32)
    path.parent.mkdir(parents=True, exist_ok=True)
    mi.Bitmap(encode_normalmap(np.tile(n, (4, 4, 1)))).write(str(path))
    return path


def nested_spec(nested: str, probe: str | None = None) -> dict | None:
    """The nested BSDF ``nested``: as is, wrapped in the call counter (``probe="counting"``)
    or replaced by the closed-form stub (``probe="stub"``), see probes.py; None for NATIVE
    (the scene's own nested BSDFs)."""
    if nested == NATIVE:
        return None
    if probe == "stub":
        return {"type": "bench_stub"}
    spec = copy.deepcopy(NESTED[nested])
    return {"type": "bench_counting", "bsdf": spec} if probe == "counting" else spec


def swap_bsdfs(scene: dict, method: str, nested: dict) -> dict:
    """Rewrite every ``normalmap_microfacet`` in ``scene`` for ``method`` around ``nested``
    (None: around its own nested BSDF)."""
    from mfnormal.io.scene_xml import rewrite_dict
    m = catalogue_method(method)

    def rewrite(v):
        if nested is not None:
            for kk in [kk for kk, vv in v.items() if isinstance(vv, dict) and kk != "normalmap"]:
                del v[kk]
            v["bsdf"] = copy.deepcopy(nested)
        for p in ("model", "tangent_facet", "max_bounces"):
            v.pop(p, None)
        if m.kind == "classic":
            v["type"] = "normalmap"
            for p in ("strength", "normalmap_convention"):
                v.pop(p, None)
            v.update(flip_invalid_normals=m.fixes, use_shadowing_function=m.fixes)
        else:
            v.update(m.plugin_params())
    return rewrite_dict(scene, "normalmap_microfacet", rewrite, "normalmap_microfacet BSDF")


def scene_dict(name: str, assets: dict, method: str, nested: str, width: int, height: int,
               spp: int, probe: str | None = None) -> dict:
    from mfnormal.cli import demo
    from mfnormal.io.scene_xml import xml_to_dict
    if name == "demo":
        base = demo.demo_scene(model="analytic", spp=spp, resolution=(width, height),
                               assets_dir=assets["demo"]["dir"], max_depth=MAX_DEPTH)
    elif name in ("model", "water"):
        a = assets[name]
        if "error" in a:
            raise RuntimeError(a["error"])
        base = xml_to_dict(a["xml"], **a["params"], spp=spp, width=width, height=height,
                           max_depth=MAX_DEPTH)
    elif name in ("plane", "control"):
        a = assets[name]
        T = mi.ScalarTransform4f
        base = {
            "type": "scene",
            "integrator": {"type": "path", "max_depth": MAX_DEPTH},
            "sensor": {
                "type": "perspective", "fov": 40.0,
                "to_world": T().look_at(origin=[0, 0.55, 5.5], target=[0, 0, -2], up=[0, 1, 0]),
                "sampler": {"type": "independent", "sample_count": spp},
                "film": {"type": "hdrfilm", "width": width, "height": height, "pixel_format": "rgb",
                         "rfilter": {"type": "gaussian"}},
            },
            "emitter": {"type": "envmap", "filename": a["envmap"]},
            "plane": {
                "type": "rectangle",
                "to_world": T().rotate([1, 0, 0], -90).scale(8),
                "bsdf": {"type": "normalmap_microfacet",
                         "normalmap": {"type": "bitmap", "filename": a["normalmap"], "raw": True,
                                       "to_uv": T().scale([8, -8, 1])},
                         "bsdf": {"type": "diffuse"}},
            },
        }
    else:
        raise ValueError(f"unknown scene {name!r}")
    return swap_bsdfs(base, method, nested_spec(nested, probe))


def method_integrator(prof: Profile, method: str) -> str:
    """The integrator ``method`` renders under in ``prof``: the profile's, the built-in's included."""
    return prof.integrator


def load_scene(name, assets, method, nested, width, height, spp, sunless=False, probe=None, integrator="path"):
    d = scene_dict(name, assets, method, nested, width, height, spp, probe)
    if sunless:
        d = with_envmap(d, assets["sunless_envmap"])
    return mi.load_dict(with_integrator(d, integrator))


def with_integrator(scene: dict, integrator: str) -> dict:
    """``scene`` with its ``path`` integrator replaced by ``integrator`` (its parameters kept),
    e.g. ``mfnormal_path`` (mfnormal.plugins.mfnormal_path); "path" leaves it as it is."""
    if integrator == "path":
        return scene
    found = [k for k, v in scene.items() if isinstance(v, dict) and v.get("type") == "path"]
    if not found:
        raise ValueError("the scene has no 'path' integrator to replace")
    return {**scene, **{k: {**scene[k], "type": integrator} for k in found}}


def with_envmap(scene: dict, filename: str) -> dict:
    """``scene`` with every ``envmap`` emitter reading ``filename``."""
    from mfnormal.io.scene_xml import rewrite_dict

    def rewrite(v):
        v["filename"] = filename
    return rewrite_dict(scene, "envmap", rewrite, "envmap emitter")


def timed_render(scene, spp: int, seed: int):
    """(seconds, image): one render, evaluated and synchronised."""
    t0 = time.perf_counter()
    img = mi.render(scene, spp=spp, seed=seed)
    dr.eval(img)
    dr.sync_thread()
    return time.perf_counter() - t0, img


def interleaved_pairs(base, scene, spp: int, reps: int):
    """Metric 1's timing: ``reps`` warm renders of ``base`` and ``scene`` interleaved (base,
    scene, base, scene, ...; seeds 100, 101, ...): (base's seconds, scene's seconds, the
    per-pair ratios scene / base)."""
    tb, tm = [], []
    for r in range(reps):
        tb.append(timed_render(base, spp, 100 + r)[0])
        tm.append(timed_render(scene, spp, 100 + r)[0])
    return tb, tm, [a / b for a, b in zip(tm, tb)]


@contextlib.contextmanager
def temporary_assets(scenes, prefix="mfnormal_bench_assets_"):
    """:func:`prepare_assets` of ``scenes`` in a temporary folder, removed on exit."""
    root = Path(tempfile.mkdtemp(prefix=prefix))
    try:
        yield prepare_assets(root, scenes)
    finally:
        shutil.rmtree(root, ignore_errors=True)


def to_numpy(img) -> np.ndarray:
    x = np.array(img, dtype=np.float64)[..., :3]
    return np.where(np.isfinite(x), np.maximum(x, 0.0), 0.0)


# ---------------------------------------------------------------------------
# Metric 2 and 5: cold first render and memory, one subprocess per configuration
# ---------------------------------------------------------------------------

def memory_mb() -> dict:
    """This process's resident set now and its peak (Linux: /proc/self/status; getrusage's
    ru_maxrss is no good in a child process, it keeps the parent's peak across exec)."""
    out = {}
    with contextlib.suppress(OSError):
        for line in Path("/proc/self/status").read_text().splitlines():
            key, _, value = line.partition(":")
            if key in ("VmRSS", "VmHWM"):
                out[key] = int(value.split()[0]) / 1024.0
    if "VmHWM" not in out:
        scale = 1024.0 if sys.platform != "darwin" else 1024.0 * 1024.0
        out["VmHWM"] = out["VmRSS"] = resource.getrusage(resource.RUSAGE_SELF).ru_maxrss / scale
    return out


def worker_main(args: dict) -> dict:
    """Runs in a fresh process whose DRJIT_CACHE_DIR is an empty directory."""
    rss0 = memory_mb()["VmHWM"]
    import_mitsuba(args.get("variant"))
    return _worker(args, rss0)


def _worker(args: dict, rss0) -> dict:
    scene = load_scene(args["scene"], args["assets"], args["method"], args["nested"],
                       args["width"], args["height"], args["spp"], probe="stub" if args.get("stub") else None,
                       integrator=args.get("integrator", "path"))
    rss_load = memory_mb()["VmRSS"]
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    dr.kernel_history_clear()
    first, _ = timed_render(scene, args["spp"], 0)
    hist = [h for h in dr.kernel_history() if h.get("cache_hit") is not None]
    compiled = [h for h in hist if not h["cache_hit"]]
    warm = [timed_render(scene, args["spp"], i + 1)[0] for i in range(args["warm_reps"])]
    hist_warm = [h for h in dr.kernel_history() if h.get("cache_hit") is not None]
    mem = memory_mb()
    # Without warm renders (production: a render takes seconds), the compile time is what the
    # kernel history says the first render's new kernels took to build (codegen + LLVM backend).
    jit_s = sum((h.get("codegen_time") or 0.0) + (h.get("backend_time") or 0.0) for h in compiled) / 1e3
    return {
        "first_s": first, "warm_s": median(warm),
        "compile_s": max(first - median(warm), 0.0) if warm else jit_s, "compile_from": "first - warm" if warm
        else "kernel history (codegen + backend)",
        "backend_s": sum(h.get("backend_time") or 0.0 for h in compiled) / 1e3,
        "codegen_s": sum(h.get("codegen_time") or 0.0 for h in hist) / 1e3,
        "kernels_compiled": len(compiled),
        "max_kernel_ops": max((h.get("operation_count") or 0 for h in hist), default=0),
        "warm_codegen_s": sum(h.get("codegen_time") or 0.0 for h in hist_warm) / 1e3 / max(len(warm), 1),
        "rss_start_mb": rss0, "rss_after_load_mb": rss_load, "rss_end_mb": mem["VmRSS"],
        "rss_peak_mb": mem["VmHWM"], "rss_render_mb": mem["VmHWM"] - rss_load,
    }


def run_worker(args: dict, timeout: float = 900.0) -> dict:
    cache = tempfile.mkdtemp(prefix="mfnormal_bench_drjit_")
    env = dict(os.environ, DRJIT_CACHE_DIR=cache)
    try:
        proc = subprocess.run([sys.executable, "-m", "benchmarks.run", "--worker", json.dumps(args)],
                              cwd=HERE.parent, env=env, capture_output=True, text=True, timeout=timeout)
    finally:
        shutil.rmtree(cache, ignore_errors=True)
    for line in reversed(proc.stdout.splitlines()):
        if line.startswith("RESULT "):
            return json.loads(line[len("RESULT "):])
    tail = (proc.stderr or proc.stdout).strip().splitlines()[-3:]
    return {"error": f"worker exited {proc.returncode}: {' | '.join(tail)}"}


# ---------------------------------------------------------------------------
# Metric 4: BSDF throughput, walk lengths, nested calls
# ---------------------------------------------------------------------------

def packet_width() -> int:
    """Dr.Jit's LLVM vector width on this CPU (lanes that loop together)."""
    flags = ""
    with contextlib.suppress(OSError):
        flags = Path("/proc/cpuinfo").read_text()
    return 16 if " avx512f" in flags else 8 if " avx" in flags else 4


def random_normalmap_texture(size: int = 256, max_tilt_deg: float = 75.0, seed: int = 3):
    rng = np.random.default_rng(seed)
    th = np.radians(rng.uniform(0.0, max_tilt_deg, (size, size)))
    ph = rng.uniform(0.0, 2 * np.pi, (size, size))
    n = np.stack([np.sin(th) * np.cos(ph), np.sin(th) * np.sin(ph), np.cos(th)], axis=-1)
    return mi.load_dict({"type": "bitmap", "bitmap": mi.Bitmap((n * 0.5 + 0.5).astype(np.float32)),
                         "raw": True, "filter_type": "nearest"})


def make_queries(n: int, coherent: int = 1, seed: int = 11):
    """Random shading points: uv (→ normal), wi, wo, sample1, sample2. With
    ``coherent`` > 1, groups of that many consecutive lanes share uv and wi
    (like the samples of one pixel)."""
    rng = np.random.default_rng(seed)
    m = n // coherent

    def shared(a):
        return np.repeat(a, coherent, axis=0)

    def hemi(k):
        z, phi = rng.uniform(0, 1, k), rng.uniform(0, 2 * np.pi, k)
        r = np.sqrt(np.maximum(1 - z * z, 0))
        return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)

    uv, p, wi = shared(rng.uniform(0, 1, (m, 2))), shared(rng.uniform(0, 1, (m, 3))), shared(hemi(m))
    wo, s1, s2 = hemi(n), rng.uniform(0, 1, n), rng.uniform(0, 1, (n, 2))
    F = mi.Float
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.t = F(np.ones(n, np.float32))
    si.p = mi.Point3f(*(F(p[:, i].astype(np.float32)) for i in range(3)))
    si.uv = mi.Point2f(F(uv[:, 0].astype(np.float32)), F(uv[:, 1].astype(np.float32)))
    zero, one = dr.zeros(F, n), dr.ones(F, n)
    si.n = mi.Normal3f(zero, zero, one)
    si.sh_frame = mi.Frame3f(mi.Vector3f(one, zero, zero), mi.Vector3f(zero, one, zero),
                             mi.Vector3f(zero, zero, one))
    si.dp_du, si.dp_dv = mi.Vector3f(one, zero, zero), mi.Vector3f(zero, one, zero)
    si.wi = mi.Vector3f(*(F(wi[:, i].astype(np.float32)) for i in range(3)))
    wo = mi.Vector3f(*(F(wo[:, i].astype(np.float32)) for i in range(3)))
    s1 = F(s1.astype(np.float32))
    s2 = mi.Point2f(F(s2[:, 0].astype(np.float32)), F(s2[:, 1].astype(np.float32)))
    dr.eval(si, wo, s1, s2)
    return si, wo, s1, s2


def make_bsdf(method: str, nested: str, texture, probe: str | None = None, **params):
    """``method`` around the nested BSDF ``nested`` (see nested_spec), with plugin ``params``."""
    from mfnormal.methods import plugin_bsdf
    m = catalogue_method(method)
    if m.kind == "classic":
        return mi.load_dict(m.bsdf(nested_spec(nested, probe), texture))
    return mi.load_dict(plugin_bsdf(nested_spec(nested, probe), texture, **m.plugin_params(), **params))


def time_queries(fn, reps: int):
    """(median wall seconds, median kernel execution seconds) of ``fn()`` after a warm-up."""
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    out = fn()
    dr.eval(out)
    dr.sync_thread()
    dr.kernel_history_clear()
    walls, kernels = [], []
    for _ in range(reps):
        t0 = time.perf_counter()
        out = fn()
        dr.eval(out)
        dr.sync_thread()
        walls.append(time.perf_counter() - t0)
        kernels.append(sum(h.get("execution_time") or 0.0 for h in dr.kernel_history()) / 1e3)
    dr.set_flag(dr.JitFlag.KernelHistory, False)
    return median(walls), median(kernels)


def nested_calls(bsdf, mode: str, queries):
    """Per lane: the calls that reach the nested BSDF, per method, and the call sites passed
    (``bsdf`` made with ``probe="counting"``)."""
    si, wo, s1, s2 = queries
    counter = bsdf.nested
    counter.reset(dr.width(si.wi))
    out = bsdf.sample(mi.BSDFContext(), si, s1, s2) if mode == "sample" else bsdf.eval(mi.BSDFContext(), si, wo)
    dr.eval(out, counter.counts, counter.sites)
    return ({op: np.array(c, dtype=np.float64) for op, c in counter.counts.items()},
            np.array(counter.sites, dtype=np.float64))


def walk_lengths(bsdf, mode: str, queries):
    """Facet bounces per lane of the model's walk (the walk loops' own counter), or None for
    a model without a walk. Each lane walks as in ``bsdf.sample`` / ``bsdf.eval``."""
    from mfnormal.models import walk
    if not hasattr(bsdf.model, "params"):
        return None
    si, wo, s1, s2 = queries
    sp = bsdf.shading_point(mi.BSDFContext(), si)
    if mode == "sample":
        w = walk.sample_walk(sp, bsdf.model.params, s1, s2, mi.Bool(True))
    else:
        w = walk.eval_walk(sp, bsdf.model.params, wo, wo.z > 0)[1]
    dr.eval(w.depth)
    return np.array(w.depth, dtype=np.float64)


def walk_stats(lengths, width: int) -> dict:
    L = np.array(lengths, dtype=np.float64)
    packets = L[: len(L) // width * width].reshape(-1, width).max(axis=1)
    return {"mean": float(L.mean()), "p99": float(np.percentile(L, 99)), "max": float(L.max()),
            "packet_max_mean": float(packets.mean()),
            "simd_efficiency": float(L.mean() / max(packets.mean(), 1e-30))}


def throughput(nested: str, methods, prof: Profile) -> list:
    n = prof.queries
    texture = random_normalmap_texture()
    ctx = mi.BSDFContext()
    width = packet_width()
    rows = []
    queries = {1: make_queries(n), width: make_queries(n, coherent=width)}
    si, wo, s1, s2 = queries[1]

    # The nested BSDF alone, in the flat frame: the cost of one nested call.
    base = mi.load_dict(copy.deepcopy(NESTED[nested]))
    t_ns, _ = time_queries(lambda: base.sample(ctx, si, s1, s2), prof.tput_reps)
    t_ne, _ = time_queries(lambda: base.eval(ctx, si, wo), prof.tput_reps)
    t_np, _ = time_queries(lambda: base.pdf(ctx, si, wo), prof.tput_reps)
    nested_cost = {"sample": t_ns / n, "eval": t_ne / n, "pdf": t_np / n, "eval_pdf": t_ne / n}

    for method in methods:
        bsdf = make_bsdf(method, nested, texture)
        counted = make_bsdf(method, nested, texture, probe="counting") if method != "builtin" else None
        row = {"nested": nested, "method": method, "queries": n}
        ws, ks = time_queries(lambda: bsdf.sample(ctx, si, s1, s2), prof.tput_reps)
        we, ke = time_queries(lambda: bsdf.eval(ctx, si, wo), prof.tput_reps)
        row.update(sample_qps=n / ws, eval_qps=n / we, sample_kernel_s=ks, eval_kernel_s=ke,
                   sample_s=ws, eval_s=we)
        row["nested_alone"] = {"sample_qps": n / t_ns, "eval_qps": n / t_ne, "pdf_qps": n / t_np}
        if method != "builtin":
            # Nested calls and walk lengths per query (executed lanes, not SIMD work).
            for mode in ("sample", "eval"):
                for coh, q in queries.items():
                    counts, sites = nested_calls(counted, mode, q)
                    calls = {op: float(c.mean()) for op, c in counts.items()}
                    lengths = walk_lengths(bsdf, mode, q)
                    walk = walk_stats(lengths, width) if lengths is not None else None
                    # A packet runs every call site until its longest lane is done.
                    simd_calls = float(sites[: n // width * width].reshape(-1, width).max(axis=1).mean())
                    tag = "" if coh == 1 else "_coherent"
                    row[f"{mode}_simd_nested_calls{tag}"] = simd_calls
                    if coh == 1:
                        row[f"{mode}_nested_calls"] = calls
                        row[f"{mode}_nested_time_est_s"] = sum(calls[op] * nested_cost[op] * n
                                                               for op in calls)
                    row[f"{mode}_walk{tag}"] = walk
            # The model around the closed-form stub.
            stub = make_bsdf(method, nested, texture, probe="stub")
            ss, _ = time_queries(lambda: stub.sample(ctx, si, s1, s2), prof.stub_reps)
            se, _ = time_queries(lambda: stub.eval(ctx, si, wo), prof.stub_reps)
            row.update(stub_sample_s=ss, stub_eval_s=se,
                       sample_nested_share=max(0.0, 1.0 - ss / ws), eval_nested_share=max(0.0, 1.0 - se / we))
        rows.append(row)
        log(f"  throughput {nested:12s} {method:22s} sample {n / ws / 1e6:7.3f} Mq/s  "
            f"eval {n / we / 1e6:7.3f} Mq/s")
    for row in rows:
        b = rows[0] if rows[0]["method"] == "builtin" else None
        if b is not None:
            row["sample_slowdown"] = b["sample_qps"] / row["sample_qps"]
            row["eval_slowdown"] = b["eval_qps"] / row["eval_qps"]
    return rows


# ---------------------------------------------------------------------------
# Metrics 1 and 3: rendering in the main process
# ---------------------------------------------------------------------------

def render_metrics(scene: str, nested: str, assets: dict, prof: Profile) -> tuple:
    """Metrics 1 and 3 of one scene and nested BSDF: (render-time rows, noise rows)."""
    W, H, spp = prof.width, prof.height, prof.spp
    scenes = {m: load_scene(scene, assets, m, nested, W, H, spp, integrator=method_integrator(prof, m))
              for m in prof.methods}
    for m in prof.methods:                              # JIT-compile (warm-up)
        timed_render(scenes[m], spp, 0)
    timing = render_time(scene, nested, assets, prof, scenes)
    if "noise" not in prof.metrics:
        return timing, []
    ratio_of = {t["method"]: t["ratio"] for t in timing}
    ratio_of["builtin"] = 1.0
    return timing, noise_metrics(scene, nested, assets, prof, scenes, ratio_of)


def render_time(scene, nested, assets, prof, scenes) -> list:
    """Metric 1: interleaved A/B pairs (built-in, method) at equal spp; the misses profiled with
    the nested calls stubbed out."""
    W, H, spp = prof.width, prof.height, prof.spp
    timing = []
    for m in prof.methods:
        if m == "builtin":
            continue
        tb, tm, ratios = interleaved_pairs(scenes["builtin"], scenes[m], spp, prof.reps)
        target = TIME_TARGET[catalogue_method(m).model]
        ratio = median(ratios)
        timing.append({"profile": prof.name, "scene": scene, "nested": nested, "method": m,
                       "builtin_s": median(tb), "method_s": median(tm), "ratio": ratio, "ratios": ratios,
                       "ratio_min": min(ratios), "ratio_max": max(ratios),
                       "target": target, "pass": ratio <= target})
        log(f"  time   {scene:7s} {nested:12s} {m:22s} {median(tm):6.3f} s vs {median(tb):6.3f} s"
            f"  ratio {ratio:5.2f} [{min(ratios):.2f}, {max(ratios):.2f}]")
    if prof.integrator != "path":
        # The integrators themselves: the built-in under prof.integrator against it under path.
        own = load_scene(scene, assets, "builtin", nested, W, H, spp)
        timed_render(own, spp, 0)
        timed_render(scenes["builtin"], spp, 0)       # (a new scene's BSDFs may change its kernel)
        tb, tm, ratios = interleaved_pairs(own, scenes["builtin"], spp, prof.reps)
        timing.append({"profile": prof.name, "scene": scene, "nested": nested, "method": "builtin",
                       "integrator": prof.integrator, "builtin_s": median(tb), "method_s": median(tm),
                       "ratio": median(ratios), "ratios": ratios, "ratio_min": min(ratios),
                       "ratio_max": max(ratios), "target": None, "pass": None})
        log(f"  time   {scene:7s} {nested:12s} builtin under {prof.integrator} / under path: {median(ratios):5.2f}")
    for row in timing:
        if row["pass"] is not False or nested == NATIVE:
            continue
        stubbed = load_scene(scene, assets, row["method"], nested, W, H, spp, probe="stub",
                             integrator=method_integrator(prof, row["method"]))
        timed_render(stubbed, spp, 0)
        ts = median([timed_render(stubbed, spp, 300 + r)[0] for r in range(3)])
        row.update(stub_s=ts, stub_ratio=ts / row["builtin_s"],
                   render_nested_share=max(0.0, 1.0 - ts / row["method_s"]))
        log(f"         stubbed nested calls: {ts:6.3f} s (ratio {ts / row['builtin_s']:.2f}, nested "
            f"share {100 * row['render_nested_share']:.0f} %)")
    if prof.vertex_size is not None:
        add_path_vertices(timing, scene, nested, assets, prof)
    return timing


def path_vertices(scene, nested, method, assets, prof) -> float:
    """Path vertices per camera sample of ``method`` (probes.path_vertices) in a counted render at
    ``prof.vertex_size``: the same camera, so the same count as at the profile's own size up to
    the sampling noise of a 192×144 render (under 0.1 % at 16 spp)."""
    from benchmarks import probes      # (registered by import_mitsuba)
    W, H = prof.vertex_size
    d = scene_dict(scene, assets, method, nested, W, H, prof.spp)
    return probes.path_vertices(probes.count_calls(with_integrator(d, method_integrator(prof, method)), prof.spp,
                                                   W * H * prof.spp))


def add_path_vertices(timing, scene, nested, assets, prof):
    """Each timed row with the path vertices per camera sample of its method and of the built-in,
    and its time ratio per path vertex (time ratio / vertex ratio): a method whose paths are longer
    (it ends fewer of them) does more work per camera sample."""
    base = path_vertices(scene, nested, "builtin", assets, prof)
    for row in timing:
        if row.get("integrator"):
            continue
        v = path_vertices(scene, nested, row["method"], assets, prof)
        row.update(vertices=v, builtin_vertices=base, vertex_ratio=v / base,
                   ratio_per_vertex=row["ratio"] / (v / base))
        log(f"  vertices {scene:7s} {nested:12s} {row['method']:22s} {v:.4f} per sample vs {base:.4f} "
            f"({v / base:.3f}x): time ratio per vertex {row['ratio_per_vertex']:.2f}")


def noise_metrics(scene, nested, assets, prof, scenes, ratio_of) -> list:
    """Metric 3: equal-time relMSE under the full sky (reported) and under the sky without its
    sun disc (scored, on every scene), every method at the spp it reaches in the built-in's time."""
    W, H = prof.width, prof.height
    noise = []
    for m in prof.methods:
        m_spp = max(1, int(round(prof.spp / ratio_of[m])))
        n = equal_time_noise(scenes[m], m_spp, prof)
        noise.append({"profile": prof.name, "scene": scene, "nested": nested, "method": m, "spp": m_spp,
                      "ref_spp": n["ref_spp"], "time_ratio": ratio_of[m], "relmse": n["relmse"],
                      "relmse_raw": n["relmse_raw"], "ref_mean": n["ref_mean"], "top_pixel_error_share": n["top"]})
    for row in noise:
        n = equal_time_noise(load_scene(scene, assets, row["method"], nested, W, H, prof.spp, sunless=True,
                                        integrator=method_integrator(prof, row["method"])), row["spp"], prof)
        row["sunless_relmse"] = n["relmse"]
    base = next(r for r in noise if r["method"] == "builtin")
    for row in noise:
        row["relmse_ratio"] = row["relmse"] / base["relmse"] if base["relmse"] > 0 else float("nan")
        # Per-sample variance ratio (relMSE at equal spp): separates estimator noise from speed.
        row["variance_per_sample_ratio"] = row["relmse_ratio"] * row["spp"] / prof.spp
        row["ref_mean_ratio"] = row["ref_mean"] / base["ref_mean"] if base["ref_mean"] > 0 else float("nan")
        target = noise_target(row["method"], nested)
        b = base["sunless_relmse"]
        row.update(target=target, sunless_builtin_relmse=b,
                   sunless_relmse_ratio=row["sunless_relmse"] / b if b > 0 else float("nan"), scored_on="sunless")
        row["scored_ratio"] = row["sunless_relmse_ratio"]
        row["pass"] = None if target is None else row["scored_ratio"] <= target
        row["sun_pass"] = None if target is None else row["relmse_ratio"] <= target   # reported only
        log(f"  noise  {scene:7s} {nested:12s} {row['method']:22s} {row['spp']:3d} spp  relMSE "
            f"{row['relmse']:.4g}  ratio {row['relmse_ratio']:5.2f}  without the sun disc "
            f"{row['sunless_relmse_ratio']:5.2f}")
    return noise


def reference_image(scene, ref_spp: int, ref_pass: int):
    """(the mean of ``ref_spp // ref_pass`` renders of ``ref_pass`` spp, seeds 10000…, its spp):
    metric 3's high-spp reference."""
    acc = None
    passes = max(1, ref_spp // ref_pass)
    for i in range(passes):
        img = to_numpy(timed_render(scene, ref_pass, 10_000 + i)[1])
        acc = img if acc is None else acc + img
    return acc / passes, passes * ref_pass


def noise_renders(scene, spp: int, seeds: int, base: int = 20_000) -> list:
    """Metric 3's noisy renders: ``seeds`` images of ``spp`` spp, seeds base, base + 1, …"""
    return [to_numpy(timed_render(scene, spp, base + s)[1]) for s in range(seeds)]


def reference_noise_removed(relmse: float, spp: int, ref_spp: int) -> float:
    """E[(x − ref)²] = σ²/spp + σ²/ref_spp: the relMSE of an spp-sample render with the
    reference's share removed."""
    return relmse / (1.0 + spp / ref_spp)


def equal_time_noise(scene, spp: int, prof: Profile) -> dict:
    """relMSE of ``spp``-sample renders (mean of ``prof.noise_seeds``) against a high-spp
    reference of the same scene, with the reference's own noise removed."""
    from mfnormal.report.metrics import rel_mse, rel_se
    ref, ref_spp = reference_image(scene, prof.ref_spp, prof.ref_pass)
    imgs = noise_renders(scene, spp, prof.noise_seeds)
    errs = [rel_mse(x, ref) for x in imgs]
    # Fireflies: the share of the squared error in the worst 0.1 % of the pixels.
    e = rel_se(imgs[0], ref).mean(axis=-1).ravel()
    top = float(np.sort(e)[::-1][: max(1, e.size // 1000)].sum() / max(e.sum(), 1e-30))
    return {"relmse": reference_noise_removed(float(np.mean(errs)), spp, ref_spp), "relmse_raw": float(np.mean(errs)),
            "ref_spp": ref_spp, "ref_mean": float(ref.mean()), "top": top}


def noise_target(method: str, nested: str):
    if method == "builtin":
        return None
    if method in DETERMINISTIC:
        return NOISE_TARGET[method]
    cls = NESTED_CLASS[nested]
    return None if cls is None else NOISE_TARGET[f"walk_{cls}"]


# ---------------------------------------------------------------------------
# Machine description, summary and report
# ---------------------------------------------------------------------------

def machine_info() -> dict:
    cpu = platform.processor() or platform.machine()
    with contextlib.suppress(OSError):
        for line in Path("/proc/cpuinfo").read_text().splitlines():
            if line.startswith("model name"):
                cpu = line.split(":", 1)[1].strip()
                break
    import drjit.detail
    return {
        "cpu": cpu, "cores": os.cpu_count(), "drjit_threads": dr.thread_count(),
        "simd_lanes": packet_width(), "platform": platform.platform(),
        "python": platform.python_version(), "mitsuba": mi.__version__, "drjit": dr.__version__,
        "variant": mi.variant(), "llvm_path": str(mfnormal.LLVM_PATH),
        "llvm_version": llvm_version(drjit.detail),
        "loadavg_start": list(os.getloadavg()),
    }


def llvm_version(detail) -> str:
    """Dr.Jit's libLLVM version, or '–' where it has none loaded (a cuda_* variant may not)."""
    try:
        return ".".join(map(str, detail.llvm_version()))
    except Exception:  # noqa: BLE001
        return "–"


def git_state() -> dict:
    """The commit measured, and the model files that differ from it."""
    def git(*args):
        with contextlib.suppress(OSError, subprocess.SubprocessError):
            return subprocess.run(["git", *args], cwd=HERE.parent, capture_output=True, text=True,
                                  timeout=10).stdout
        return ""
    return {"commit": git("rev-parse", "--short", "HEAD").strip(),
            "modified": [ln[3:] for ln in git("status", "--porcelain", "--", "src").splitlines()]}


def summarize(results: dict) -> list:
    """One row per target: how many cells pass."""
    rows = []

    def add(name, cells):
        cells = [c for c in cells if c.get("pass") is not None]
        failed = [c for c in cells if not c["pass"]]
        rows.append({"target": name, "cells": len(cells), "passed": len(cells) - len(failed),
                     "status": "n/a" if not cells else "PASS" if not failed else "FAIL",
                     "worst": max((c["_value"] for c in cells), default=None),
                     "failed": [cell_name(c) for c in failed]})

    t = results["render_time"]
    for model, lim in TIME_TARGET.items():
        add(f"render time at equal spp: {model} ≤ {lim}×",
            [dict(c, _value=c["ratio"]) for c in t if catalogue_method(c["method"]).model == model])
    # Noise: the content-equal cells only (the sky without its sun disc, every scene; scored_ratio).
    nz = [c for c in results["noise"] if c["method"] != "builtin"]
    ce = "content-equal cells"
    for model in DETERMINISTIC:
        add(f"equal-time relMSE ({ce}): {model} ≤ {NOISE_TARGET[model]}×",
            [dict(c, _value=c["scored_ratio"]) for c in nz if c["method"] == model])
    add(f"equal-time relMSE ({ce}): random walks, diffuse ≤ {NOISE_TARGET['walk_diffuse']}×",
        [dict(c, _value=c["scored_ratio"]) for c in nz if c["method"] not in DETERMINISTIC
         and NESTED_CLASS[c["nested"]] == "diffuse"])
    add(f"equal-time relMSE ({ce}): random walks, rough conductors and roughplastic ≤ "
        f"{NOISE_TARGET['walk_conductor']}×",
        [dict(c, _value=c["scored_ratio"]) for c in nz if c["method"] not in DETERMINISTIC
         and NESTED_CLASS[c["nested"]] == "conductor"])
    add(f"first-render JIT compile ≤ {COMPILE_TARGET}× the built-in's",
        [dict(c, _value=c["compile_ratio"]) for c in results["compile"]
         if c["method"] != "builtin" and c.get("compile_ratio") is not None])
    return rows


def cell_name(c: dict) -> str:
    """scene/nested/method, prefixed by the profile where it is not the full one."""
    name = f"{c['scene']}/{c['nested']}/{c['method']}"
    return name if c.get("profile", "full") in ("full", "quick") else f"{c['profile']}:{name}"


def fmt(x, spec=".2f", none="–"):
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return none
    return format(x, spec)


def mark(ok):
    return "–" if ok is None else "✅" if ok else "❌"


def why_lines(results: dict) -> list:
    """Evidence for each failing target, from the throughput and kernel measurements."""
    fails_t = [c for c in results["render_time"] if c["pass"] is False]
    fails_n = [c for c in results["noise"] if c.get("pass") is False]
    fails_c = [c for c in results["compile"] if c.get("pass") is False]
    return ((why_time_lines(results, fails_t) if fails_t else [])
            + (why_compile_lines(results, fails_c) if fails_c else [])
            + (why_noise_lines(results, fails_n) if fails_n else []))


def table_lines(intro: str, header: list, rows: list) -> list:
    """Markdown lines: a paragraph, then a table of ``header`` over ``rows`` (each a list of cells)."""
    return ([intro, "", "| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
            + ["| " + " | ".join(row) + " |" for row in rows] + [""])


def why_time_lines(results: dict, fails: list) -> list:
    """The render-time misses with their path vertices, stubbed ratio and BSDF-level costs."""
    tput = {(r["nested"], r["method"]): r for r in results["throughput"]}
    rows = []
    for c in fails:
        r = tput.get((c["nested"], c["method"]), {})
        w, wc = r.get("sample_walk") or {}, r.get("sample_walk_coherent") or {}
        walk = (f"{fmt(w.get('mean'))} / {fmt(w.get('p99'), '.0f')} / {fmt(wc.get('packet_max_mean'))}"
                if w else "no walk")
        calls = {m: (f"{fmt(sum(r[f'{m}_nested_calls'].values()))} / "
                     f"{fmt(r.get(f'{m}_simd_nested_calls_coherent'))}") if f"{m}_nested_calls" in r else "–"
                 for m in ("eval", "sample")}
        share = c.get("render_nested_share")
        rows.append([c["scene"], c["nested"], c["method"], fmt(c["ratio"]), fmt(c.get("vertex_ratio"), ".3f"),
                     fmt(c.get("ratio_per_vertex")), fmt(c.get("stub_ratio")),
                     f"{fmt(None if share is None else 100 * share, '.0f')} %",
                     f"{fmt(r.get('eval_slowdown'))}× / {fmt(r.get('sample_slowdown'))}×",
                     calls["eval"], calls["sample"], walk])
    return table_lines(
        "**Render time.** For each miss: the path vertices per camera sample against the "
        "built-in's and the time ratio per path vertex (profiles that count them), the "
        "render time ratio with the nested calls "
        "replaced by a closed-form stub (what the model's own logic costs), the share "
        "of the render spent in nested calls, and the BSDF-level costs of metric 4 "
        "(nested calls per query executed / SIMD: every call site runs on all lanes of "
        "a packet until its longest walk ends):",
        ["scene", "nested", "method", "time ratio", "path vertices per sample / built-in's",
         "time ratio per path vertex", "stubbed ratio", "nested share of render", "eval / sample slowdown",
         "nested calls / eval", "nested calls / sample", "walk mean / p99 / SIMD bounces (coherent)"], rows)


def miss_table(intro: str, header: list, fails: list, measured: list, cells) -> list:
    """:func:`table_lines` of the failing cells ``fails``, a row ``cells(c, b)`` per cell c, b the
    built-in's row of c's scene and nested BSDF in ``measured`` (or {})."""
    base = {(r["scene"], r["nested"]): r for r in measured if r["method"] == "builtin"}
    return table_lines(intro, header, [cells(c, base.get((c["scene"], c["nested"]), {})) for c in fails])


def why_compile_lines(results: dict, fails: list) -> list:
    """The compile misses with their kernel sizes against the built-in's."""
    return miss_table(
        "**JIT compile.** Kernel size (Dr.Jit operations in the largest kernel of the "
        "first render) against the built-in's, for the failing cells:",
        ["scene", "nested", "method", "compile s (built-in)", "LLVM backend s", "ops (built-in)",
         "compile s / ops with nested calls stubbed"], fails, results["compile"],
        lambda c, b: [c["scene"], c["nested"], c["method"], f"{fmt(c['compile_s'])} ({fmt(b.get('compile_s'))})",
                      fmt(c.get("backend_s")), f"{c.get('max_kernel_ops')} ({b.get('max_kernel_ops')})",
                      f"{fmt(c.get('stub_compile_s'))} / {c.get('stub_max_kernel_ops', '–')}"])


def why_noise_lines(results: dict, fails: list) -> list:
    """The equal-time noise misses: variance or time, and how concentrated the error is."""
    return miss_table(
        "**Equal-time noise.** The failing content-equal cells, scored without the sun "
        "disc; beside them the full-sky ratio. relMSE ratio = (per-sample variance ratio) × "
        "(time ratio): which of the two dominates (under the full sky):",
        ["scene", "nested", "method", "relMSE ratio, sky without its sun disc (scored)", "target",
         "full-sky relMSE ratio", "per-sample variance ratio", "time ratio", "reference mean / built-in's",
         "error share of worst 0.1 % pixels (built-in)"], fails, results["noise"],
        lambda c, b: [c["scene"], c["nested"], c["method"], f"{fmt(c.get('scored_ratio'))} {mark(c['pass'])}",
                      fmt(c["target"], ".1f"), fmt(c["relmse_ratio"]), fmt(c["variance_per_sample_ratio"]),
                      fmt(c["time_ratio"]), fmt(c.get("ref_mean_ratio")),
                      f"{fmt(c.get('top_pixel_error_share'))} ({fmt(b.get('top_pixel_error_share'))})"]) + [
        "A large per-sample variance ratio with a similar reference mean and most of the "
        "error in a few pixels points at fireflies or sub-pixel glints; "
        "`benchmarks/experiments.py` (control, evalnoise, mispdf) and "
        "the path tracer's two strategies (docs/diagnoses.md) separate them.", ""]


def cell_table(results: dict, prof: dict) -> list:
    """The per-cell table of one profile (its rows in results' render_time, noise and compile)."""
    name = prof["name"]

    def rows(metric):
        return {(c["scene"], c["nested"], c["method"]): c for c in results[metric]
                if c.get("profile", results["config"]["name"]) == name}
    t, n, c = rows("render_time"), rows("noise"), rows("compile")
    if not (t or n or c):
        return []
    L = [f"## Per scene, nested BSDF and method: profile `{name}` ({prof['width']}×{prof['height']}, "
         f"{prof['spp']} spp, {prof['reps']} A/B pairs)", "",
         "Ratios are method / built-in (same scene and nested BSDF). Time: median of the "
         "per-pair ratios of interleaved warm renders at equal spp. Noise: relMSE at the spp the "
         "method reaches in the built-in's time, each against its own high-spp reference: under the "
         "full sky (reported) and without the sun disc (scored, every scene); "
         "the mark is the scored one's. Compile: first render with an empty kernel cache minus a warm "
         "render (without warm renders: the kernel history's codegen + backend time), the median of "
         f"{prof.get('compile_runs', 1)} such run(s) in fresh processes. RSS: peak resident memory of "
         "that subprocess (VmHWM), and in brackets its growth over the loaded scene (the render's own memory)."
         + (" `native`: the scenes' own materials." if NATIVE in prof["nested"] else ""), "",
         "| scene | nested | method | time s | time ratio | | spp @ equal time | relMSE | "
         "relMSE ratio (full sky) | relMSE ratio (without sun disc) | | compile s | compile ratio | | "
         "peak RSS MB |",
         "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|"]
    order = list(NESTED) + [NATIVE]
    keys = sorted(set(t) | set(n) | set(c), key=lambda k: (SCENES.index(k[0]), order.index(k[1]),
                                                             METHOD_KEYS.index(k[2])))
    for k in keys:
        tt, nn, cc = t.get(k, {}), n.get(k, {}), c.get(k, {})
        ts = tt.get("method_s") if k[2] != "builtin" else None
        if k[2] == "builtin":
            others = [v["builtin_s"] for kk, v in t.items() if kk[:2] == k[:2]]
            ts = median(others) if others else None
        ratio = fmt(tt.get("ratio")) + (f" (under `{tt['integrator']}` / `path`)" if tt.get("integrator") else "")
        L.append(f"| {k[0]} | {k[1]} | {k[2]} | {fmt(ts, '.3f')} | {ratio} | "
                 f"{mark(tt.get('pass'))} | {nn.get('spp', '–')} | {fmt(nn.get('relmse'), '.3g')} | "
                 f"{fmt(nn.get('relmse_ratio'))} | {fmt(nn.get('sunless_relmse_ratio'))} | {mark(nn.get('pass'))} | "
                 f"{fmt(cc.get('compile_s'))} | {fmt(cc.get('compile_ratio'))} | {mark(cc.get('pass'))} | "
                 f"{fmt(cc.get('rss_peak_mb'), '.0f')} ({fmt(cc.get('rss_render_mb'), '.0f')}) |")
    L.append("")
    counted = [k for k in keys if "vertex_ratio" in t.get(k, {})]
    if counted:
        W, H = prof.get("vertex_size") or ("?", "?")
        L += [f"Path vertices per camera sample (the shapes' BSDF samples, counted in a {W}×{H} render "
              "of the same camera, `benchmarks/probes.py`), against the built-in's, and the time ratio "
              "per path vertex (time ratio / vertex ratio): a method whose paths are longer (it ends "
              "fewer of them: no sample below the macro surface, more energy kept past Russian "
              "roulette) does more work per camera sample.", "",
              "| scene | nested | method | vertices per sample (built-in's) | vertex ratio | time ratio | "
              "time ratio per vertex |", "|---|---|---|---|---|---|---|"]
        for k in counted:
            tt = t[k]
            L.append(f"| {k[0]} | {k[1]} | {k[2]} | {fmt(tt['vertices'], '.4f')} ({fmt(tt['builtin_vertices'], '.4f')}) "
                     f"| {fmt(tt['vertex_ratio'], '.3f')} | {fmt(tt['ratio'])} | {fmt(tt['ratio_per_vertex'])} |")
        L.append("")
    return L


def backward_section(results: dict, folder: Path) -> list:
    """The reverse-mode benchmark's table (benchmarks/backward.py, run by the full run, its files
    beside RESULTS.md in ``folder``) and its link."""
    b = results.get("backward")
    if not b:
        return []
    L = ["## Backward pass (benchmarks/backward.py)", ""]
    if "error" in b:
        return L + [f"Not recorded: {b['error']}", ""]
    name = Path(b["md"]).name
    text = (folder / name).read_text() if (folder / name).exists() else ""
    lines = text.splitlines()
    # Its tables and what stands between them (the optimiser's step has its own), as they are.
    first = next((i for i, ln in enumerate(lines) if ln.startswith("|")), len(lines))
    tables = lines[first:]
    while tables and not tables[-1].strip():
        tables.pop()
    return L + [f"`{b['command']}` ({b['duration_s']:.0f} s), from [{name}]({name}):", ""] + tables + [""]


def write_markdown(results: dict, path: Path):
    """RESULTS.md at ``path``: the run, the targets, each profile's cells, the backward pass,
    throughput and why targets fail."""
    L = header_lines(results)
    if results.get("notes"):
        L += ["Notes:", ""] + [f"- {n}" for n in results["notes"]] + [""]

    L += ["## Targets", "", "| target | cells passing | worst | status |", "|---|---|---|---|"]
    for s in results["summary"]:
        L.append(f"| {s['target']} | {s['passed']}/{s['cells']} | {fmt(s['worst'])} | {s['status']} |")
    L.append("")

    # One table per profile: every (scene, nested, method).
    for prof in results.get("configs", [results["config"]]):
        L += cell_table(results, prof)
    L += backward_section(results, path.parent)
    L += throughput_lines(results)

    why = why_lines(results)
    if why:
        L += ["## Why targets fail", ""] + why
        if (path.parent / "experiments.md").exists():
            L += ["What-if variants of the model code (RNG, bounce cap, merged nested calls, reuse of "
                  "the sampled term) and the noise diagnostics: [experiments.md](experiments.md) "
                  "(`python -m benchmarks.experiments`).", ""]
    L += ["## Reproduce", "", "```sh", results["command"], "```", ""]
    path.write_text("\n".join(L))


def header_lines(results: dict) -> list:
    """RESULTS.md's title and the run's command, machine, code and profiles."""
    m, cfg = results["machine"], results["config"]
    L = ["# mfnormal benchmark: `normalmap_microfacet` vs Mitsuba's `normalmap`", ""]
    if cfg["name"] == "quick":
        L += ["> **Quick smoke run** (tiny image, subset): the numbers below check that the "
              "benchmark runs; they are not measurements.", ""]
    L += [f"- command: `{results['command']}`",
          f"- machine: {m['cpu']}, {m['cores']} cores ({m['drjit_threads']} Dr.Jit threads, "
          f"{m['simd_lanes']} SIMD lanes), {m['platform']}",
          f"- variant `{m['variant']}`, Mitsuba {m['mitsuba']}, Dr.Jit {m['drjit']}, "
          f"LLVM {m['llvm_version']} (`{m['llvm_path']}`)",
          f"- load average at start {fmt(m['loadavg_start'][0])}, at end "
          f"{fmt(results['loadavg_end'][0])}; wall time {results['duration_s'] / 60:.1f} min; "
          f"started {results['started']}",
          *([f"- integrator: every method, the built-in included, under `{results['integrator']}` "
             "(mfnormal.plugins.mfnormal_path); the built-in's time under it over its time under Mitsuba's `path` "
             "is the built-in row's time ratio"] if results.get("integrator", "path") != "path" else []),
          f"- code: commit `{results['git']['commit']}`"
          + (f", with uncommitted changes in {', '.join(results['git']['modified'])}"
             if results['git']['modified'] else ""),
          *[f"- profile `{p['name']}`: {p['width']}×{p['height']}, {p['spp']} spp, {p['reps']} A/B pairs"
            + (f", reference {p['ref_spp']} spp, {p['queries']} BSDF queries" if "noise" in p.get("metrics", ("noise",))
               else f", metrics: {', '.join(p['metrics'])}")
            for p in results.get("configs", [cfg])],
          ""]
    return L


def throughput_lines(results: dict) -> list:
    """Metric 4's section: queries per second, nested calls, walk lengths and the nested share."""
    m = results["machine"]
    L = ["## BSDF throughput (metric 4)", "",
         f"{results['config']['queries']} queries: wi, wo uniform on the hemisphere, normals from a "
         "256² texture of random normals (θ_p uniform in [0°, 75°], nearest filtering). "
         "Mq/s = 10⁶ queries per second (wall, median). Nested calls: nested BSDF calls "
         "per query that reach the nested BSDF (eval + pdf + eval_pdf + sample), and in "
         "brackets the calls the CPU runs per query (a packet runs every call site on all its "
         "lanes until its longest walk ends; random lanes). Walk: facet bounces of the random "
         "walk per query in `sample` (the walk loop's counter; a mirror bounce shares its "
         "loop iteration with the next nested vertex); SIMD = the mean over "
         f"{m['simd_lanes']}-lane packets of the longest walk in the packet (what the CPU "
         "executes), for random lanes / for packets that share wi and the normal. Nested "
         "share: 1 − time with the nested BSDF replaced by a closed-form Lambertian stub.", "",
         "| nested | method | sample Mq/s | eval Mq/s | sample ×builtin | eval ×builtin | "
         "nested calls sample / eval | walk mean / p99 / max | SIMD bounces random / coherent | "
         "nested share sample / eval |",
         "|---|---|---|---|---|---|---|---|---|---|"]
    for r in results["throughput"]:
        w, wc = r.get("sample_walk"), r.get("sample_walk_coherent")
        walk = f"{fmt(w['mean'])} / {fmt(w['p99'], '.0f')} / {fmt(w['max'], '.0f')}" if w else "–"
        simd = f"{fmt(w['packet_max_mean'])} / {fmt(wc['packet_max_mean'])}" if w and wc else "–"
        calls = (f"{fmt(sum(r['sample_nested_calls'].values()))} ({fmt(r['sample_simd_nested_calls'])}) / "
                 f"{fmt(sum(r['eval_nested_calls'].values()))} ({fmt(r['eval_simd_nested_calls'])})"
                 if "sample_nested_calls" in r else "1 / 1")
        share = (f"{fmt(100 * r['sample_nested_share'], '.0f')} % / {fmt(100 * r['eval_nested_share'], '.0f')} %"
                 if "sample_nested_share" in r else "–")
        L.append(f"| {r['nested']} | {r['method']} | {fmt(r['sample_qps'] / 1e6, '.3f')} | "
                 f"{fmt(r['eval_qps'] / 1e6, '.3f')} | {fmt(r.get('sample_slowdown'))} | "
                 f"{fmt(r.get('eval_slowdown'))} | {calls} | {walk} | {simd} | {share} |")
    L.append("")
    nested_alone = {r["nested"]: r["nested_alone"] for r in results["throughput"]}
    if nested_alone:
        L.append("Nested BSDF alone (one call per query, flat frame): " + "; ".join(
            f"{k} sample {v['sample_qps'] / 1e6:.2f} / eval {v['eval_qps'] / 1e6:.2f} / pdf "
            f"{v['pdf_qps'] / 1e6:.2f} Mq/s" for k, v in nested_alone.items()) + ".")
        L.append("")
    return L


# ---------------------------------------------------------------------------
# Main
# ---------------------------------------------------------------------------

def parse_args(argv):
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0],
                                 formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--quick", action="store_true", help="tiny smoke run (about 2 min), numbers meaningless")
    ap.add_argument("--profile", choices=sorted(PROFILES), default="all",
                    help="full (192×144, every metric), production (1280×720: time and compile), water "
                         "(the water scene: time), or all (the three, and benchmarks/backward.py; the default)")
    ap.add_argument("--variant", default=VARIANT, help=f"Mitsuba variant (default {VARIANT}; e.g. cuda_ad_rgb)")
    ap.add_argument("--out", default=str(HERE.parent / "out" / "benchmarks"),
                    help="output directory (default: out/benchmarks; --out benchmarks rewrites the committed results)")
    ap.add_argument("--scenes", help=f"comma-separated subset of {','.join(SCENES)}")
    ap.add_argument("--nested", help=f"comma-separated subset of {','.join(NESTED)}")
    ap.add_argument("--skip", default="", help="comma-separated metrics to skip: render,compile,throughput,backward")
    ap.add_argument("--integrator", choices=INTEGRATORS, default="path",
                    help="the integrator every method renders under, the built-in's included (default path)")
    ap.add_argument("--report-only", action="store_true",
                    help="rewrite RESULTS.md from the results.json already in --out")
    ap.add_argument("--worker", help=argparse.SUPPRESS)
    return ap, ap.parse_args(argv)


def selected_profiles(ap, args) -> list:
    profiles = [copy.copy(p) for p in ((QUICK,) if args.quick else PROFILES[args.profile])]
    for prof in profiles:
        prof.integrator = args.integrator
        if args.scenes:
            bad = {s for s in args.scenes.split(",") if s} - set(SCENES)
            if bad:
                ap.error(f"unknown scene(s) {sorted(bad)}")
            prof.scenes = tuple(s for s in args.scenes.split(",") if s in prof.scenes)
        if args.nested and prof.nested != (NATIVE,):
            prof.nested = tuple(s for s in args.nested.split(",") if s)
            bad = set(prof.nested) - set(NESTED)
            if bad:
                ap.error(f"unknown nested BSDF(s) {sorted(bad)}")
    return profiles


def main(argv=None) -> int:
    argv = list(sys.argv[1:] if argv is None else argv)
    ap, args = parse_args(argv)
    if args.worker:
        print("RESULT " + json.dumps(worker_main(json.loads(args.worker))), flush=True)
        return 0
    if args.report_only:
        results = json.loads((Path(args.out) / "results.json").read_text())
        results["summary"] = summarize(results)
        write_markdown(results, Path(args.out) / "RESULTS.md")
        log(f"wrote {Path(args.out) / 'RESULTS.md'}")
        return 0
    profiles = selected_profiles(ap, args)
    skip = set(filter(None, args.skip.split(",")))
    out = Path(args.out)
    out.mkdir(parents=True, exist_ok=True)

    t_start = time.time()
    from mfnormal.cli.commands import CLIError
    try:
        import_mitsuba(args.variant)
    except CLIError as exc:
        ap.error(str(exc))
    exe = sys.executable
    py = os.path.relpath(exe) if exe.startswith(os.getcwd() + os.sep) else exe
    results = {
        "command": shlex.join([py, "-m", "benchmarks.run", *argv]),
        "started": time.strftime("%Y-%m-%d %H:%M:%S %Z"),
        "machine": machine_info(),
        "git": git_state(),
        "config": asdict(profiles[0]),
        "configs": [asdict(p) for p in profiles],
        "targets": {"render_time": TIME_TARGET, "noise": NOISE_TARGET, "compile": COMPILE_TARGET},
        "render_time": [], "noise": [], "compile": [], "throughput": [], "notes": [],
        "integrator": args.integrator,
    }
    log(f"mfnormal benchmark ({', '.join(p.name for p in profiles)}, {mi.variant()}): "
        f"{results['machine']['cpu']}, {results['machine']['cores']} cores, "
        f"load {results['machine']['loadavg_start'][0]:.1f}")
    with temporary_assets(sorted({s for p in profiles for s in p.scenes})) as assets:
        for prof in profiles:
            run_profile(prof, assets, results, skip, args.variant)
    if args.profile == "all" and not args.quick and "backward" not in skip:
        results["backward"] = run_backward(out, args.variant)
    finish(results, out, t_start)
    return 0


def run_profile(prof: Profile, assets: dict, results: dict, skip: set, variant: str):
    """Every metric of ``prof`` that is not skipped, appended to ``results``."""
    scenes = []
    for s in prof.scenes:
        if s == "model" and "error" in assets.get("model", {}):
            results["notes"].append(f"scene (b) skipped: {assets['model']['error']}")
            continue
        scenes.append(s)
    if "render" in prof.metrics and "render" not in skip:             # metrics 1 and 3
        for s in scenes:
            for nested in prof.nested:
                log(f"[render {prof.name}] {s} / {nested}")
                try:
                    timing, noise = render_metrics(s, nested, assets, prof)
                except Exception as exc:          # report it, measure the rest
                    results["notes"].append(f"render metrics failed for {prof.name}:{s}/{nested}: "
                                            f"{type(exc).__name__}: {exc}")
                    log(f"  failed: {exc}")
                    continue
                results["render_time"] += timing
                results["noise"] += noise
    if "compile" in prof.metrics and "compile" not in skip:           # metrics 2 and 5
        for s in scenes:
            if prof.compile_scenes and s not in prof.compile_scenes:
                continue
            for nested in prof.nested:
                results["compile"] += compile_metrics(s, nested, assets, prof, variant)
    if "throughput" in prof.metrics and "throughput" not in skip:     # metric 4
        for nested in prof.nested:
            log(f"[throughput] {nested}")
            try:
                results["throughput"] += throughput(nested, prof.methods, prof)
            except Exception as exc:
                results["notes"].append(f"throughput failed for {nested}: {type(exc).__name__}: {exc}")
                log(f"  failed: {exc}")


def median_run(runs: list) -> dict:
    """Of one cell's cold compile runs, the run with the median compile time (the lower middle
    one for an even count), with every run's time in ``compile_s_runs`` (in run order); the
    first failed run, if any failed."""
    failed = [r for r in runs if "error" in r]
    if failed:
        return dict(failed[0])
    row = dict(sorted(runs, key=lambda r: r["compile_s"])[(len(runs) - 1) // 2])
    row["compile_s_runs"] = [r["compile_s"] for r in runs]
    return row


def compile_metrics(s: str, nested: str, assets: dict, prof: Profile, variant: str) -> list:
    """Metrics 2 and 5 of one scene and nested BSDF: a subprocess per method with an empty kernel
    cache, ``prof.compile_runs`` times (interleaved over the methods, so that a change of load
    reaches them all), the median run reported (:func:`median_run`)."""
    rows = []
    job = {"scene": s, "nested": nested, "assets": assets, "width": prof.width, "height": prof.height,
           "spp": prof.spp, "warm_reps": prof.compile_warm_reps, "variant": variant}
    runs = {m: [] for m in prof.methods}
    for _ in range(prof.compile_runs):
        for m in prof.methods:
            runs[m].append(run_worker(dict(job, method=m, integrator=method_integrator(prof, m))))
    for m in prof.methods:
        r = median_run(runs[m])
        r.update(profile=prof.name, scene=s, nested=nested, method=m)
        rows.append(r)
        log(f"  compile {s:7s} {nested:12s} {m:22s} "
            + (r["error"] if "error" in r else
               f"first {r['first_s']:.2f} s, warm {fmt(r['warm_s'])} s, compile "
               f"{r['compile_s']:.2f} s (runs {', '.join(f'{x:.2f}' for x in r['compile_s_runs'])}), "
               f"ops {r['max_kernel_ops']}, RSS {r['rss_peak_mb']:.0f} MB"))
    b = next((r for r in rows if r["method"] == "builtin" and "error" not in r), None)
    for r in rows:
        if "error" in r or b is None:
            r.update(compile_ratio=None)
            r["pass"] = None
            continue
        r["compile_ratio"] = r["compile_s"] / max(b["compile_s"], 1e-3)
        r["rss_ratio"] = r["rss_peak_mb"] / b["rss_peak_mb"]
        r["target"] = None if r["method"] == "builtin" else COMPILE_TARGET
        r["pass"] = None if r["method"] == "builtin" else r["compile_ratio"] <= COMPILE_TARGET
        if r["pass"] is False and prof.name != "production":
            # Profile: the same configuration with the nested calls stubbed out.
            st = run_worker(dict(job, method=r["method"], stub=True, integrator=method_integrator(prof, r["method"])))
            if "error" not in st:
                r.update(stub_compile_s=st["compile_s"], stub_max_kernel_ops=st["max_kernel_ops"],
                         stub_backend_s=st["backend_s"])
    return rows


def run_backward(out: Path, variant: str) -> dict:
    """``python -m benchmarks.backward`` (its defaults) into ``out``: its files there (names relative to
    ``out``), or why not."""
    cmd = [sys.executable, "-m", "benchmarks.backward", "--out", str(Path(out).resolve()), "--variant", variant]
    log("[backward] " + shlex.join(cmd))
    t0 = time.time()
    proc = subprocess.run(cmd, cwd=HERE.parent, capture_output=True, text=True)
    if proc.returncode != 0:
        return {"error": f"backward.py exited {proc.returncode}: {(proc.stderr or proc.stdout).strip()[-300:]}"}
    return {"command": f"python -m benchmarks.backward --variant {variant}", "md": "backward.md",
            "json": "backward.json", "duration_s": time.time() - t0}


def busy_note(load_start: float, load_end: float, cores: int):
    """The note that the timings are noisy, or None. Judged by the load average before the run:
    the one at its end is mostly the run's own Dr.Jit threads (an idle 2-core machine ends a full
    run at about 1.7), so it is reported, not judged."""
    if load_start <= 0.5 * cores:
        return None
    return (f"the machine was busy before the run (load average {load_start:.1f} on {cores} cores; "
            f"{load_end:.1f} at its end, this run's own threads included): timings are noisy; re-run "
            "on an idle machine before trusting the pass/fail of the time-based targets")


def finish(results: dict, out: Path, t_start: float):
    results["loadavg_end"] = list(os.getloadavg())
    results["duration_s"] = time.time() - t_start
    results["summary"] = summarize(results)
    busy = busy_note(results["machine"]["loadavg_start"][0], results["loadavg_end"][0], os.cpu_count() or 1)
    if busy:
        results["notes"].append(busy)
    results["notes"].append(
        "walk lengths are the walk loops' bounce counter (mfnormal.models.walk.sample_walk / eval_walk); "
        "nested calls are counted, and the nested BSDF stubbed, by the nested BSDFs of "
        "benchmarks/probes.py")
    (out / "results.json").write_text(json.dumps(results, indent=1, default=float))
    write_markdown(results, out / "RESULTS.md")
    log(f"wrote {out / 'results.json'} and {out / 'RESULTS.md'} in {results['duration_s']:.0f} s")
    for s in results["summary"]:
        log(f"  {s['status']:4s} {s['target']}  ({s['passed']}/{s['cells']})")


if __name__ == "__main__":
    sys.exit(main())
