"""Rendering in passes: one accumulator, two pass schedules.

A render of N samples per pixel is split into passes, each one ``mi.render`` call,
whose images are averaged weighted by their sample counts (:func:`average_passes`).
Two schedules use it:

- :func:`render_scene`, the command line's (``mfnormal render``, the demo at large
  sizes): :func:`pass_count` passes (8 by default, more where a pass would trace more
  than :data:`MAX_PASS_LANES` paths, which bounds its memory), :func:`pass_spp` samples
  and seed :func:`pass_seed` each; every channel of the film;
- :func:`render_rgb`, the comparisons' (``mfnormal compare``, the true-geometry
  harness): passes of at most ``per_pass`` samples with seeds ``seed``, ``seed + 1``,
  ...; the RGB channels.
"""

from __future__ import annotations

import numpy as np

import mitsuba as mi

__all__ = ["MAX_PASS_LANES", "pass_count", "pass_spp", "pass_seed", "average_passes",
           "render_scene", "render_rgb"]

#: A render pass traces at most this many paths at once (pixels × samples per pass),
#: which bounds its memory; more samples take more passes.
MAX_PASS_LANES = 1 << 24


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


def average_passes(scene, passes, count: int | None = None, progress=None) -> np.ndarray:
    """The mean of the renders ``(spp, seed)`` in ``passes`` weighted by their spp:
    every channel of the film (H × W × C, float64). ``progress(done, count)`` is called
    after each pass."""
    acc, total = None, 0
    for i, (spp, seed) in enumerate(passes):
        img = np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float64)
        acc = img * spp if acc is None else acc + img * spp
        total += spp
        if progress:
            progress(i + 1, count)
    return acc / total


def render_scene(scene, spp: int | None = None, passes: int | None = None, seed: int = 0,
                 progress=None) -> np.ndarray:
    """The command line's render of ``scene`` at ``spp`` (default: its sampler's), in
    :func:`pass_count` passes; returns the film's channels (H × W × C, float32: RGB, Y,
    or with AOVs)."""
    sensor = scene.sensors()[0]
    total = int(spp or sensor.sampler().sample_count())
    pixels = int(np.prod([int(v) for v in sensor.film().crop_size()]))
    n = pass_count(total, pixels, passes)
    schedule = ((pass_spp(total, n, i), pass_seed(seed, i)) for i in range(n))
    out = average_passes(scene, schedule, n, progress).astype(np.float32)
    return out if out.ndim == 3 else out[..., None]


def render_rgb(scene, spp: int, seed: int, per_pass: int = 16) -> np.ndarray:
    """Linear RGB (H × W × 3, float64) of ``scene`` (loaded, or a scene dict) at ``spp``,
    in passes of at most ``per_pass`` samples with seeds ``seed``, ``seed + 1``, ... (mod 2^32)."""
    if isinstance(scene, dict):
        scene = mi.load_dict(scene)
    n = -(-spp // per_pass)
    schedule = ((min(per_pass, spp - i * per_pass), (seed + i) % (1 << 32)) for i in range(n))
    return average_passes(scene, schedule, n)[..., :3]
