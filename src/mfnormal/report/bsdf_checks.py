"""The BSDFs alone: the white-furnace albedo and the reciprocity error of a method.

:func:`bsdf_checks` measures a :class:`mfnormal.methods.Method` with a white
Lambertian nested BSDF under constant normal maps (no scene, no renderer): what
``mfnormal compare`` reports next to its renders.
"""

from __future__ import annotations

import numpy as np

import drjit as dr
import mitsuba as mi

from mfnormal.methods import Method

__all__ = ["CHECK_TILTS", "CHECK_THETA_I", "bsdf_checks"]

CHECK_TILTS = (30.0, 60.0)           # θ_p of the constant normal map, degrees
CHECK_THETA_I = (0.0, 60.0, 85.0)    # θ_i of the furnace test, degrees


def _bsdf_dict(method: Method, theta_p: float) -> dict:
    """``method`` around a white Lambertian BSDF, under a constant map tilted by ``theta_p``."""
    t = np.radians(theta_p)
    n = np.array([np.sin(t), 0.0, np.cos(t)])
    texel = np.tile((n * 0.5 + 0.5).astype(np.float32), (2, 2, 1))
    tex = {"type": "bitmap", "bitmap": mi.Bitmap(texel, mi.Bitmap.PixelFormat.RGB), "raw": True}
    nested = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}
    return method.bsdf(nested, tex)


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
