"""Where a render shows normal-mapped surfaces, and where it sees them at grazing angles.

:func:`surface_maps` traces primary rays of a scene's first sensor: per pixel, the
coverage of each normal-mapped shape and the mean |cos| between view ray and shading
normal on them. :func:`choose_crops` picks the windows with the most of a score
(``mfnormal compare`` zooms into the grazing-angle regions of each shape).
"""

from __future__ import annotations

import numpy as np

import drjit as dr
import mitsuba as mi

from mfnormal.io.scene_checks import normal_mapped_shapes

__all__ = ["surface_maps", "choose_crops"]


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
