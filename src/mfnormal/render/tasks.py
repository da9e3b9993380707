"""What a cluster's worker runs (:mod:`mfnormal.render.cluster` submits it).

A task renders in the client's ``--variant`` unless its worker was started with its own
(:mod:`mfnormal.render.worker`); tasks in one worker process run one at a time. Every task first
checks that its worker runs the client's Mitsuba, Dr.Jit and mfnormal (its source, hashed:
:func:`versions`), and keeps the last two scenes it loaded.
"""

from __future__ import annotations

import hashlib
import importlib.metadata
import os
import threading
import time
import warnings
from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache
from pathlib import Path

import numpy as np

from mfnormal.render.bundle import SceneSpec, bundle_name
from mfnormal.render.passes import MIN_THREADS, collector_paused, render_rgb, use_variant

__all__ = ["versions", "mismatch", "Env", "set_worker_variant", "render_chunk", "render_rgb_job",
           "variant_job", "worker_info", "held_files"]


# Versions

@lru_cache(maxsize=None)
def _package_version() -> str:
    """mfnormal's version and a hash of its source (a changed checkout is another version)."""
    try:
        version = importlib.metadata.version("mfnormal")
    except importlib.metadata.PackageNotFoundError:
        version = "unknown"
    digest = hashlib.sha256()
    package = Path(__file__).resolve().parents[1]
    for path in sorted(package.rglob("*.py")):
        digest.update(path.relative_to(package).as_posix().encode() + b"\0" + path.read_bytes())
    return f"{version}+{digest.hexdigest()[:10]}"


def versions() -> dict:
    """The versions a worker must share with its client."""
    import drjit as dr
    import mitsuba as mi

    return {"mitsuba": mi.__version__, "drjit": dr.__version__, "mfnormal": _package_version()}


def mismatch(theirs: dict, ours: dict, who: str) -> str | None:
    """One line naming what differs between ``theirs`` and the client's ``ours``, or None."""
    diff = [f"{k} {theirs.get(k)} (the client has {v})" for k, v in ours.items() if theirs.get(k) != v]
    if not diff:
        return None
    return (f"{who} runs {', '.join(diff)}; every worker needs the client's Mitsuba, Dr.Jit and "
            "mfnormal: refusing to mix them")


# A worker's state and tasks

#: The variant this worker process was started with (:mod:`mfnormal.render.worker`), if any, and
#: why it cannot use it (then it refuses every task: Dask only logs a failed preload).
WORKER_VARIANT: str | None = None
WORKER_PROBLEM: str | None = None
_LOCK = threading.Lock()
_SCENES: OrderedDict = OrderedDict()


@dataclass(frozen=True)
class Env:
    """What a task needs besides its scene: the client's variant, versions and, for
    ``local:N``, the Dr.Jit threads of each worker (None: all of its machine's; never
    under :data:`MIN_THREADS`)."""
    variant: str
    versions: dict
    threads: int | None = None


def set_worker_variant(variant: str | None) -> None:
    """Make ``variant`` this worker process's variant (every task renders in it)."""
    global WORKER_VARIANT, WORKER_PROBLEM
    WORKER_VARIANT, WORKER_PROBLEM = variant or None, None
    if variant:
        try:
            _use_variant(variant)
        except RuntimeError as exc:
            WORKER_PROBLEM = str(exc)
            raise


def _use_variant(variant: str):
    return use_variant(variant, RuntimeError, f"variant '{variant}' is not available in this worker's Mitsuba build",
                       f"this worker cannot use variant '{variant}'")


def _prepare(env: Env):
    """Mitsuba in the worker's variant, after the version check; raises RuntimeError."""
    import drjit as dr

    problem = WORKER_PROBLEM or mismatch(versions(), env.versions, f"worker (pid {os.getpid()})")
    if problem:
        raise RuntimeError(problem)
    mi = _use_variant(WORKER_VARIANT or env.variant)
    threads = max(MIN_THREADS, env.threads or dr.thread_count())
    if dr.thread_count() != threads:
        dr.set_thread_count(threads)
    return mi


def _materialise(files: dict, digest: str) -> Path:
    """A folder of this worker holding ``files`` (each written once, atomically)."""
    import tempfile

    try:
        from distributed import get_worker
        base = Path(get_worker().local_directory)
    except (ImportError, ValueError):
        base = Path(tempfile.gettempdir())
    folder = base / "mfnormal-scenes" / digest
    folder.mkdir(parents=True, exist_ok=True)
    for name, data in files.items():
        target = folder / name
        if not target.exists():
            tmp = folder / f".{name}.{os.getpid()}.tmp"
            tmp.write_bytes(data)
            os.replace(tmp, target)
    return folder


def _scene(mi, spec: SceneSpec, files: dict | None):
    """The loaded scene of ``spec`` (the last two are kept per process). Its warnings are
    not repeated: the client loaded it first and showed them."""
    key = (mi.variant(), spec)
    if key in _SCENES:
        _SCENES.move_to_end(key)
        return _SCENES[key]
    with warnings.catch_warnings():
        warnings.simplefilter("ignore")
        scene = _load(mi, spec, files)
    _SCENES[key] = scene
    while len(_SCENES) > 2:
        _SCENES.popitem(last=False)
    return scene


def _load(mi, spec: SceneSpec, files: dict | None):
    params = dict(spec.params)
    folder = None if spec.shared else _materialise(files or {}, spec.files)
    if spec.kind == "gltf":
        from mfnormal.io.gltf import load_gltf
        path = spec.source if spec.shared else folder / spec.source
        scene = mi.load_dict(load_gltf(path, limits=spec.limits, **params))
    elif spec.shared:
        scene = mi.load_file(spec.source, **params)
    else:
        path = folder / bundle_name(spec.source.encode(), "scene.xml")
        if not path.exists():
            path.write_text(spec.source, encoding="utf-8")
        scene = mi.load_file(str(path), **params)
    return scene


def render_chunk(env: Env, spec: SceneSpec, files, spp: int, seed: int) -> tuple:
    """One chunk, on a worker: (spp, the film's channels as float32 H × W × C, variant)."""
    with _LOCK:
        mi = _prepare(env)
        scene = _scene(mi, spec, files)
        with collector_paused():
            return spp, np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float32), mi.variant()


def render_rgb_job(env: Env, spec: SceneSpec, files, spp: int, seed: int, per_pass: int) -> tuple:
    """:func:`mfnormal.render.passes.render_rgb` on a worker: (RGB, render seconds)."""
    with _LOCK:
        mi = _prepare(env)
        scene = _scene(mi, spec, files)
        t0 = time.perf_counter()
        return render_rgb(scene, spp, seed, per_pass), time.perf_counter() - t0


def variant_job(env: Env, function, args: tuple, kwargs: dict):
    """``function(*args, **kwargs)`` on a worker, in the client's variant: work that needs Mitsuba
    but no scene (the report's BSDF checks, :func:`mfnormal.report.bsdf_checks.bsdf_checks`)."""
    with _LOCK:
        _prepare(env)
        return function(*args, **kwargs)


def worker_info() -> dict:
    """This worker's versions, the variant it was started with and why it cannot use it."""
    return {"versions": versions(), "variant": WORKER_VARIANT, "problem": WORKER_PROBLEM}


def held_files(files: dict) -> dict:
    """The task that holds a scene's files (:meth:`mfnormal.render.cluster.Cluster._send`: a lost copy is recomputed)."""
    return files
