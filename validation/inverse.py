"""Inverse rendering of a normal map: recover a tangent-space normal map from a few renders.

A plane carries a normal-mapped material (Mitsuba's ``normalmap``, or
``normalmap_microfacet`` with one of its models); a few images of a target surface, each
lit by one directional sun, are matched by optimising the map's texels with Adam, from a
flat map (the usual start), through Mitsuba's ``prb`` integrator. The target is either the
same method with the true map (:func:`same_method_targets`) or the true geometry, a
displaced heightfield mesh (:func:`true_geometry_targets`). The score is the mean angle
between the recovered texel normals and the true ones (:func:`texel_error`).

Used by ``examples/inverse_rendering.py`` (a one-minute run with a loss curve and the maps),
``validation/inverse_rendering.py`` (every method, both targets, results in
``validation/results/inverse_rendering.md``) and the tests.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field

import numpy as np

import mfnormal  # noqa: F401  (before mitsuba: selects a working libLLVM)
import drjit as dr
import mitsuba as mi

from validation import heightfield as H

#: Methods: Mitsuba's ``normalmap`` (its default fixes on) and each model of ours.
METHODS = {
    "builtin": None,
    "faithful": ("faithful", None),
    "analytic": ("analytic", None),
    "separable_specular": ("separable", "specular"),
    "separable_same": ("separable", "same"),
    "nonseparable_specular": ("nonseparable", "specular"),
    "nonseparable_same": ("nonseparable", "same"),
}

#: The material: the issue's roughplastic, α = 0.2 (its α is not optimised).
MATERIAL = {"type": "roughplastic", "distribution": "ggx", "alpha": 0.2,
            "diffuse_reflectance": {"type": "rgb", "value": [0.6, 0.6, 0.6]}}


@dataclass
class Setup:
    """What an inverse-rendering run is: the true surface, the views and the optimiser."""

    heightfield: H.Heightfield = None          # default: bumps, 2 periods, 35° max tilt
    texels: int = 16                           # the map's resolution (per axis)
    res: int = 64                              # image resolution
    spp: int = 16                              # samples per pixel of each optimisation render
    target_spp: int = 256
    suns: tuple = ((40.0, 0.0), (40.0, 120.0), (40.0, 240.0))   # (elevation, azimuth) in degrees
    irradiance: float = 3.0
    iterations: int = 120
    lr: float = 0.02
    # None: Adam at the constant rate lr; else the rate falls geometrically from lr at the first
    # iteration to lr_final at the last, so the texels settle where the gradient's noise would
    # otherwise keep them moving by about lr per step
    lr_final: float = None
    seed: int = 0                              # iteration k renders with seed + k
    unit_texels: bool = False                  # after each step, rescale each texel to a unit normal
    # The default model's map-wide slopes σ follow the map; False: their derivative is dropped
    # (σ is set from the map's values before each render, a block-coordinate scheme), a
    # diagnostic of what that map-wide coupling does to the optimisation
    # (validation/results/inverse_rendering.md).
    slope_derivatives: bool = True
    material: dict = field(default_factory=lambda: dict(MATERIAL))
    # The renders to match: (lighting, view) pairs (heightfield.LIGHTINGS / VIEWS names or
    # objects); None: one per sun, frontal
    shots: tuple = None
    floor: float = 0.0                         # > 0: a checkerboard floor that far below (water)
    max_depth: int = 2                         # prb's and the same-method target's path depth

    def __post_init__(self):
        if self.heightfield is None:
            self.heightfield = H.bumps(periods=2, max_tilt=35.0)


def lightings(setup):
    return [H.Lighting(f"sun{k}", el, az, setup.irradiance, 0.0) for k, (el, az) in enumerate(setup.suns)]


def shots(setup):
    """The (lighting, view) of each render to match: ``setup.shots``, or one per sun, frontal."""
    if setup.shots is not None:
        return list(setup.shots)
    return [(light, "frontal") for light in lightings(setup)]


def flat_map(setup):
    """The start: every texel (0.5, 0.5, 1), the flat normal."""
    return np.tile(np.array([0.5, 0.5, 1.0], np.float32), (setup.texels, setup.texels, 1))


def true_normals(setup):
    """The true surface's unit normals at the texel centres (texels × texels × 3)."""
    return H.texel_normals(setup.heightfield, setup.texels)


def method_bsdf(method, nested, texture):
    """The BSDF dict of ``method`` (a METHODS key) around ``nested`` with the map ``texture``."""
    spec = METHODS[method]
    if spec is None:
        return {"type": "normalmap", "normalmap": texture, "bsdf": nested}
    model, facet = spec
    d = {"type": "normalmap_microfacet", "normalmap": texture, "bsdf": nested, "model": model}
    if facet is not None:
        d["tangent_facet"] = facet
    return d


def _plane_scenes(setup, method, texels):
    """One plane scene per sun, ``method`` with the map ``texels``, prb integrator. The scenes share
    one BSDF (one map to optimise): every live instance of a Python BSDF is traced into each render's
    calls, so one instance per sun made each render about three times as slow (docs/differentiable.md)."""
    bsdf = mi.load_dict(method_bsdf(method, setup.material, H.bitmap_texture(texels)))
    return [mi.load_dict(H.scene_dict(setup.heightfield, "plane", bsdf,
                                      lighting=light, view=view, res=setup.res, spp=setup.spp,
                                      sampler="independent", floor=setup.floor,
                                      integrator={"type": "prb", "max_depth": setup.max_depth}))
            for light, view in shots(setup)]


def same_method_targets(setup, method):
    """Renders of the plane with the true map, by ``method`` itself (path tracing, target_spp)."""
    scenes = _plane_scenes(setup, method, H.encode_normals(true_normals(setup)))
    path = mi.load_dict({"type": "path", "max_depth": setup.max_depth})
    return [mi.render(s, spp=setup.target_spp, seed=1234, integrator=path) for s in scenes]


def true_geometry_targets(setup, verts_per_period=64, max_depth=8):
    """Renders of the true geometry: the heightfield as a dense displaced mesh of the bare
    material (path tracing, every bounce up to max_depth)."""
    out = []
    for light, view in shots(setup):
        scene = mi.load_dict(H.scene_dict(setup.heightfield, "true", setup.material, lighting=light,
                                          view=view, res=setup.res, spp=setup.target_spp, floor=setup.floor,
                                          max_depth=max_depth, verts_per_period=verts_per_period))
        out.append(mi.render(scene, spp=setup.target_spp, seed=1234))
    return out


def texel_error(texels, normals):
    """Mean angle in degrees between the texels' decoded normals normalize(2·rgb − 1) and the
    unit ``normals``."""
    n = 2.0 * np.asarray(texels, np.float64)[..., :3] - 1.0
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    cos = np.clip(np.sum(n * normals, axis=-1), -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).mean())


def _decode(rgb):
    n = 2.0 * np.asarray(rgb, np.float64)[..., :3] - 1.0
    return n / np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)


def encode_unit(texels):
    """Texels rescaled to unit normals n·0.5 + 0.5 (n = normalize(2·rgb − 1); a zero vector
    becomes the flat normal): a step then turns a texel's normal by at most about its size,
    where a texel near rgb (0.5, 0.5, 0.5) could flip across the horizon in one step."""
    n = 2.0 * np.asarray(texels, np.float64)[..., :3] - 1.0
    length = np.linalg.norm(n, axis=-1, keepdims=True)
    n = np.where(length > 1e-6, n / np.maximum(length, 1e-12), np.array([0.0, 0.0, 1.0]))
    return (n * 0.5 + 0.5).astype(np.float32)


def bilinear_normals(texels, x, y):
    """The map's normals at world points (x, y) the way the plane shades with them: the bitmap's
    bilinear filter on the stored rgb (repeat wrap; uv = (x, 1 − y), row 0 at y ≈ 1, texel
    centres at heightfield.texel_centres), then decoded and normalised."""
    return _decode(H.bilinear(np.asarray(texels, np.float64)[..., :3], x, y))


def surface_error(setup, texels, per_texel: int = 16):
    """Mean angle in degrees between the map as rendered (:func:`bilinear_normals`) and the true
    surface normal, over ``per_texel``² points per texel (cell centres of a fine grid over the
    map's unit square): the error over the whole surface, where :func:`texel_error` looks only
    at the texel centres (which a bilinear map need not match to fit the surface best)."""
    n = np.asarray(texels).shape[0] * per_texel
    t = (np.arange(n) + 0.5) / n
    x, y = np.meshgrid(t, 1.0 - t, indexing="xy")
    cos = np.clip(np.sum(bilinear_normals(texels, x, y) * setup.heightfield.normal(x, y), axis=-1), -1.0, 1.0)
    return float(np.degrees(np.arccos(cos)).mean())


@dataclass
class Result:
    method: str
    loss: list           # per iteration, before its step
    error: list          # mean texel error (degrees) per iteration, before its step; last: final
    texels: np.ndarray   # the recovered map
    seconds: float
    first_step: float    # max |Δ texel| of the first step
    lr: list = None      # the learning rate of each iteration's step


def _faithful_models(scene):
    """The default model (``faithful.Model``) of each shape's ``normalmap_microfacet`` in ``scene``."""
    for shape in scene.shapes():
        model = getattr(getattr(shape.bsdf(), "model", None), "core", None)   # interface.Faithful.core
        if model is not None:
            yield model


def _detach_slopes(scene):
    """The faithful model's map-wide slopes in ``scene`` without their derivative (same values)."""
    for model in _faithful_models(scene):
        model.set_slopes(model.slopes)


def optimise(setup, method, targets, iterations=None, log=None):
    """Adam on the map's texels from a flat map, the L2 distance of ``method``'s prb renders to
    ``targets`` (one per shot); texels clamped to [0, 1] after each step; the rate constant, or
    falling to ``setup.lr_final``."""
    iterations = setup.iterations if iterations is None else iterations
    scenes = _plane_scenes(setup, method, flat_map(setup))
    params = [mi.traverse(s) for s in scenes]
    key = next(k for k in params[0].keys() if k.endswith("normalmap.data"))
    opt = mi.ad.Adam(lr=setup.lr)
    opt[key] = params[0][key]
    truth = true_normals(setup)
    loss_hist, err_hist, lr_hist = [], [], []
    start, first_step = time.time(), 0.0
    for it in range(iterations):
        if setup.lr_final is not None:
            opt.set_learning_rate(setup.lr * (setup.lr_final / setup.lr) ** (it / max(iterations - 1, 1)))
        lr_hist.append(float(opt.learning_rate()))
        before = np.array(opt[key])
        err_hist.append(texel_error(before, truth))
        total = 0.0
        for p, scene, target in zip(params, scenes, targets):
            p[key] = opt[key]
            p.update()
            if not setup.slope_derivatives:
                _detach_slopes(scene)
            img = mi.render(scene, p, spp=setup.spp, seed=setup.seed + it)
            loss = dr.mean(dr.square(img - target), axis=None)
            dr.backward(loss)
            total += float(np.array(loss).ravel()[0])
        loss_hist.append(total)
        opt.step()
        opt[key] = dr.clip(opt[key], 0.0, 1.0)
        if setup.unit_texels:
            opt[key] = mi.TensorXf(encode_unit(np.array(opt[key])))
        if it == 0:
            first_step = float(np.abs(np.array(opt[key]) - before).max())
        if log is not None and (it % 20 == 0 or it == iterations - 1):
            log(f"  {method:22s} it {it:4d}  loss {total:.3e}  texel error {err_hist[-1]:6.2f}°")
    final = np.array(opt[key])
    err_hist.append(texel_error(final, truth))
    return Result(method, loss_hist, err_hist, final, time.time() - start, first_step, lr_hist)


def normal_image(texels):
    """A map as an RGB image in [0, 1] (what it stores: n·0.5 + 0.5, renormalised)."""
    n = 2.0 * np.asarray(texels, np.float64)[..., :3] - 1.0
    n /= np.maximum(np.linalg.norm(n, axis=-1, keepdims=True), 1e-12)
    return np.clip(n * 0.5 + 0.5, 0.0, 1.0)
