"""Rendering in passes: one accumulator, two pass schedules.

A render of N samples per pixel is split into passes, each one ``mi.render`` call,
whose images are averaged weighted by their sample counts (:func:`weighted_mean`, the
one accumulator: :func:`average_passes` feeds it renders made here,
:mod:`mfnormal.render.cluster` the chunks its workers rendered, in schedule order).
Two schedules use it:

- :func:`render_scene`, the command line's (``mfnormal render``, the demo at large
  sizes, and ``mfnormal render --cluster``, whose chunks are these passes): :func:`schedule`,
  :func:`pass_count` passes (8 by default, more where a pass would trace more
  than :data:`MAX_PASS_LANES` paths, which bounds its memory), :func:`pass_spp` samples
  and seed :func:`pass_seed` each; every channel of the film;
- :func:`render_rgb`, the comparisons' (``mfnormal compare``, the true-geometry
  harness): passes of at most ``per_pass`` samples with seeds ``seed``, ``seed + 1``,
  ...; the RGB channels.
"""

from __future__ import annotations

import gc
import signal
import threading
from contextlib import contextmanager

import numpy as np

import mitsuba as mi

__all__ = ["MAX_PASS_LANES", "pass_count", "pass_spp", "pass_seed", "schedule", "weighted_mean",
           "average_passes", "render_scene", "film_image", "render_rgb", "signals_end_the_process",
           "collector_paused"]

#: A render pass traces at most this many paths at once (pixels × samples per pass),
#: which bounds its memory; more samples take more passes.
MAX_PASS_LANES = 1 << 24


#: The fewest Dr.Jit threads the commands render with: with one (a one-core machine's default,
#: no pool thread, the caller alone) Mitsuba's OpenEXR reader and writer wait for ever for a
#: task no thread runs (`dr.set_thread_count(1); mi.Bitmap("x.exr")` hangs).
MIN_THREADS = 2


def use_variant(variant: str, error, unavailable: str, cannot: str):
    """Mitsuba in ``variant`` with the plugins registered and at least :data:`MIN_THREADS` Dr.Jit
    threads; ``error(unavailable)`` where this build lacks it, ``error(cannot + ": " + the
    cause)`` where it cannot be set (e.g. cuda_* without a GPU)."""
    import drjit as dr
    import mfnormal
    from mfnormal.io.messages import one_line

    if variant not in mi.variants():
        raise error(unavailable)
    if variant.startswith("cuda_") and not dr.has_backend(dr.JitBackend.CUDA):
        raise error(f"{cannot}: Dr.Jit finds no CUDA GPU on this machine; use an llvm_* variant "
                    "(e.g. llvm_ad_rgb) here")
    if mi.variant() != variant:
        try:
            mi.set_variant(variant)
        except Exception as exc:
            raise error(f"{cannot}: {one_line(exc)}") from None
    mfnormal.register()
    if dr.thread_count() < MIN_THREADS:
        dr.set_thread_count(MIN_THREADS)
    return mi


def pass_count(total: int, pixels: int, passes: int | None = None) -> int:
    """How many passes a render of ``total`` spp takes: ``passes`` (default 8, fewer for
    < 8 spp), more where a pass would trace more than :data:`MAX_PASS_LANES` paths.
    Pass ``i`` takes :func:`pass_spp` samples per pixel."""
    passes = max(1, min(total, passes or (8 if total >= 8 else total)))
    per_pass = max(1, MAX_PASS_LANES // max(1, pixels))      # samples per pixel a pass may take
    return max(passes, min(total, -(-total // per_pass)))


def pass_spp(total: int, passes: int, i: int) -> int:
    return total // passes + (1 if i < total % passes else 0)


def pass_seed(seed: int, i: int) -> int:
    """The seed of pass ``i`` of a render with ``seed`` (any 32-bit seed; the same as
    ``seed · 1000003 + i`` where that fits, which is one-to-one in ``seed``)."""
    return (seed * 1000003 + i) % (1 << 32)


def schedule(total: int, pixels: int, passes: int | None = None, seed: int = 0) -> list:
    """The passes ``(spp, seed)`` of :func:`render_scene`'s render of ``total`` spp on a film
    of ``pixels`` pixels (:func:`pass_count` of them)."""
    n = pass_count(total, pixels, passes)
    return [(pass_spp(total, n, i), pass_seed(seed, i)) for i in range(n)]


def weighted_mean(renders, count: int | None = None, progress=None) -> np.ndarray:
    """The mean of the images in ``renders``, an iterable of ``(spp, image)``, weighted by
    their spp (float64, summed in the iterable's order). ``progress(done, count)`` is called
    after each image."""
    acc, total = None, 0
    for i, (spp, img) in enumerate(renders):
        img = np.asarray(img, dtype=np.float64)
        acc = img * spp if acc is None else acc + img * spp
        total += spp
        if progress:
            progress(i + 1, count)
    return acc / total


@contextmanager
def signals_end_the_process(enabled: bool = True):
    """SIGTERM and SIGINT with their default action (the process ends at once) while the block
    runs, the handlers before it restored after it; a no-op unless ``enabled`` and in the main
    thread.

    A render pass runs in native code (Dr.Jit's kernels), where Python's signal handlers cannot
    run: the command line's handlers (:func:`mfnormal.io.inputs.raise_on_sigterm`, Ctrl-C's
    KeyboardInterrupt) would wait for the pass to end, minutes for a large one. During a pass
    nothing of the render is on disk yet (the outputs are written after the last pass), so the
    default action ends the render at once and leaves no file. Only the command line enables
    it: in an interactive Python Ctrl-C must not end the interpreter."""
    if not enabled or threading.current_thread() is not threading.main_thread():
        yield
        return
    names = [n for n in ("SIGTERM", "SIGINT") if hasattr(signal, n)]
    saved = {n: signal.signal(getattr(signal, n), signal.SIG_DFL) for n in names}
    try:
        yield
    finally:
        for n, handler in saved.items():
            signal.signal(getattr(signal, n), handler)


_PAUSED = [0, False]           # renders under collector_paused, and whether the collector was on
_PAUSED_LOCK = threading.Lock()


@contextmanager
def collector_paused():
    """Python's cyclic collector off while a render runs, as it was after the last overlapping
    render ends. Run on another thread (a Dask worker's event loop) or inside the plugin's Python
    code that Dr.Jit traces, it can free the Mitsuba/Dr.Jit objects of an earlier scene, left in
    reference cycles, while Dr.Jit is busy with this one: the test suite's worker processes
    crashed now and then that way (docs/development.md, "Worker crashes")."""
    with _PAUSED_LOCK:
        if _PAUSED[0] == 0:
            _PAUSED[1] = gc.isenabled()
            gc.disable()
        _PAUSED[0] += 1
    try:
        yield
    finally:
        with _PAUSED_LOCK:
            _PAUSED[0] -= 1
            if _PAUSED[0] == 0 and _PAUSED[1]:
                gc.enable()


def _render(scene, spp: int, seed: int, killable: bool) -> np.ndarray:
    with signals_end_the_process(killable), collector_paused():
        return np.array(mi.render(scene, spp=spp, seed=seed))


def average_passes(scene, passes, count: int | None = None, progress=None, killable: bool = False) -> np.ndarray:
    """The mean of the renders ``(spp, seed)`` in ``passes`` weighted by their spp:
    every channel of the film (H × W × C, float64). ``progress(done, count)`` is called
    after each pass. ``killable`` (the command line): SIGTERM and SIGINT end the process at once
    during a pass (:func:`signals_end_the_process`)."""
    renders = ((spp, _render(scene, spp, seed, killable)) for spp, seed in passes)
    return weighted_mean(renders, count, progress)


def render_scene(scene, spp: int | None = None, passes: int | None = None, seed: int = 0,
                 progress=None, killable: bool = False) -> np.ndarray:
    """The command line's render of ``scene`` at ``spp`` (default: its sampler's), in
    :func:`pass_count` passes; returns the film's channels (H × W × C, float32: RGB, Y,
    or with AOVs). ``killable``: as :func:`average_passes`'s."""
    sensor = scene.sensors()[0]
    total = int(spp or sensor.sampler().sample_count())
    pixels = int(np.prod([int(v) for v in sensor.film().crop_size()]))
    passes = schedule(total, pixels, passes, seed)
    return film_image(average_passes(scene, passes, len(passes), progress, killable))


def film_image(mean: np.ndarray) -> np.ndarray:
    """:func:`render_scene`'s result from the mean of its passes: H × W × C, float32."""
    out = mean.astype(np.float32)
    return out if out.ndim == 3 else out[..., None]


def render_rgb(scene, spp: int, seed: int, per_pass: int = 16) -> np.ndarray:
    """Linear RGB (H × W × 3, float64) of ``scene`` (loaded, or a scene dict) at ``spp``,
    in passes of at most ``per_pass`` samples with seeds ``seed``, ``seed + 1``, ... (mod 2^32)."""
    if isinstance(scene, dict):
        scene = mi.load_dict(scene)
    n = -(-spp // per_pass)
    passes = ((min(per_pass, spp - i * per_pass), (seed + i) % (1 << 32)) for i in range(n))
    return average_passes(scene, passes, n)[..., :3]
