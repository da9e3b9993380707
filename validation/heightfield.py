"""True geometry for normal maps: periodic heightfields, their baked maps, dense meshes, scenes.

A normal map stands in for geometry, so the test of a normal-mapping method is
whether a coarse surface with the baked map looks like the fine surface the map
was baked from. This module builds both sides of that comparison from one
periodic heightfield ``z = h(x, y)``:

- **heightfields** (:class:`Heightfield`) on the unit square ``[0, 1]²``,
  periodic with ``periods`` repetitions along x and y: :func:`bumps` (smooth,
  compactly supported bumps), :func:`egg_crate` (``A sin sin``) and
  :func:`noise` (band-limited periodic noise, a fixed-seed Fourier series).
  Heights and gradients are analytic everywhere. The amplitude is set by a
  target maximum (or median) tilt, :data:`STEEPNESS` names the presets, and
  :func:`tilt_stats` reports median / p99 / max tilt.
- **maps**: :func:`normal_map` (tangent-space normals encoded ``n·0.5 + 0.5``),
  :func:`height_map` (the heights, for bump/height mapping) and
  :func:`texel_normals` (the exact unit normals per texel);
- **meshes**: :func:`displaced_mesh` (the true surface, a dense triangle mesh
  with analytic vertex normals) and :func:`plane_mesh` (the coarse surface: two
  triangles over the same extent, at the heightfield's mean height);
- **scenes**: :func:`scene_dict` for either surface under a :data:`LIGHTINGS`
  preset, a :data:`VIEWS` preset (orthographic, the surface fills the image),
  with a :data:`MATERIALS` BSDF wrapped by a :class:`Method`;
- **metrics**: :func:`metrics` (relMSE, mean ``|ln Y/Y_true|``, contrast,
  near-black fraction) and :func:`render_cell`, which renders the truth, its
  noise floor and every method for one :class:`Cell`.

Conventions (verified by ``tests/test_heightfield.py``)
------------------------------------------------------
World: z up, the plane is ``[0, 1]²`` in (x, y) (it repeats outside it). UVs on
both meshes are ``u = x, v = 1 − y``. Mitsuba's bitmaps put ``v = 0`` in the
image's first (top) row and texel centres at ``(i + ½)/res``, so image column
``c`` is ``x = (c + ½)/res`` and row ``r`` is ``y = 1 − (r + ½)/res``: the image
shows the plane as seen from above with +x right and +y up. On such a mesh
Mitsuba gives ``dp/du = +x``, ``dp/dv = −y`` and the shading frame
``s = +x, t = n × s = +y, n = +z``; the normal map's channels are the normal's
components in that frame, so its tangent-space normal is the world normal
``(−h_x, −h_y, 1)/‖·‖``: green points to +y, the image's top (the OpenGL
convention, what Mitsuba's ``normalmap`` and ``normalmap_microfacet``'s
default ``tangents="mitsuba"`` decode). The sensors look at the plane with
image up = +y (frontal) or from −y with image up = +z (grazing), so renders
show the plane the way the maps do.
"""

from __future__ import annotations

import inspect
import math
import zlib
from dataclasses import dataclass, field, replace
from functools import lru_cache
from typing import Callable

import numpy as np

import mfnormal  # noqa: F401  (before mitsuba: selects a working libLLVM)
import mitsuba as mi

from mfnormal.scenes import sky
from mfnormal.methods import METHODS as CATALOGUE, METHOD_BY_KEY, plugin_bsdf
from mfnormal.report.metrics import REL_MSE_EPS, luminance, rel_mse
from mfnormal.render.passes import render_rgb

__all__ = [
    "Heightfield", "bumps", "egg_crate", "noise", "make_heightfield", "KINDS", "STEEPNESS",
    "tilt_stats", "texel_centres", "normal_map", "height_map", "texel_normals", "encode_normals",
    "bitmap_texture", "displaced_arrays", "displaced_mesh", "plane_mesh", "triangle_mesh",
    "View", "Lighting", "Magnification", "VIEWS", "LIGHTINGS", "MAGNIFICATIONS", "MATERIALS",
    "scene_dict", "floor_mesh", "FLOOR_CHECKS", "footprint", "Method", "METHODS", "DEFAULT_METHODS",
    "plugin_method", "heightmap_method", "method_from_spec", "metrics", "near_black_threshold", "Cell", "render", "render_counted",
    "render_cell", "cell_seed", "cell_metrics", "block_mean", "exposure_scale", "EXPOSURE_MEAN", "rel_mse", "luminance", "REL_MSE_EPS", "LN_FLOOR", "BLACK_FRACTION",
]


# ---------------------------------------------------------------------------
# Heightfields
# ---------------------------------------------------------------------------

KINDS = ("bumps", "eggcrate", "noise")

#: Steepness presets: the target maximum tilt in degrees.
STEEPNESS = {"mild": 28.0, "steep": 65.0}

_STATS_GRID = 384          # samples per period (per axis) for tilt statistics and the mean height


@dataclass(frozen=True)
class Heightfield:
    """``h(x, y) = amplitude · s(periods·x, periods·y)`` with ``s`` of period 1 in both axes.

    ``kind`` selects the unit shape ``s``; ``params`` holds its fixed-seed data
    (bump centres/radii/heights or noise modes) as nested tuples, so a
    heightfield is hashable and reproducible. x, y and h are in world units
    (the plane is ``[0, 1]²``).
    """
    kind: str
    periods: int
    amplitude: float
    params: tuple = ()
    seed: int = 0

    @property
    def period(self) -> float:
        return 1.0 / self.periods

    def eval(self, x, y):
        """``(h, ∂h/∂x, ∂h/∂y)`` at world points (arrays of any shape)."""
        X = np.asarray(x, np.float64) * self.periods
        Y = np.asarray(y, np.float64) * self.periods
        s, sx, sy = _shape(self.kind, self.params, X, Y)
        k = self.amplitude * self.periods
        return self.amplitude * s, k * sx, k * sy

    def height(self, x, y):
        return self.eval(x, y)[0]

    def normal(self, x, y):
        """Unit world normals ``(−h_x, −h_y, 1)/‖·‖``, shape ``(..., 3)``."""
        _, hx, hy = self.eval(x, y)
        n = np.stack([-hx, -hy, np.ones_like(hx)], axis=-1)
        return n / np.linalg.norm(n, axis=-1, keepdims=True)

    def period_grid(self, n: int = _STATS_GRID):
        """``(h, h_x, h_y)`` on an ``n × n`` cell-centred grid over one period."""
        t = (np.arange(n) + 0.5) / n * self.period
        X, Y = np.meshgrid(t, t, indexing="xy")
        return self.eval(X, Y)

    @property
    def mean_height(self) -> float:
        """Mean of h over a period (exact for the trigonometric kinds, ~1e-6 relative for bumps)."""
        return _height_stats(self)[0]

    @property
    def height_range(self) -> tuple[float, float]:
        return _height_stats(self)[1:]

    def with_periods(self, periods: int) -> "Heightfield":
        """The same shape and tilts repeated ``periods`` times (heights scale with the period)."""
        return replace(self, periods=int(periods), amplitude=self.amplitude * self.periods / periods)

    def describe(self) -> str:
        st = tilt_stats(self)
        return (f"{self.kind} ×{self.periods}² (seed {self.seed}): tilt median {st['median']:.1f}°, "
                f"p99 {st['p99']:.1f}°, max {st['max']:.1f}°")


@lru_cache(maxsize=64)
def _height_stats(hf: Heightfield):
    h = hf.period_grid()[0]
    return float(h.mean()), float(h.min()), float(h.max())


def _wrap(d):
    """Minimum-image displacement on the unit torus."""
    return d - np.round(d)


def _shape(kind, params, X, Y):
    """Unit shape ``s`` and its gradient in period coordinates (period 1)."""
    if kind == "eggcrate":
        a, b = 2 * np.pi * X, 2 * np.pi * Y
        return (np.sin(a) * np.sin(b), 2 * np.pi * np.cos(a) * np.sin(b),
                2 * np.pi * np.sin(a) * np.cos(b))
    s, sx, sy = np.zeros_like(X), np.zeros_like(X), np.zeros_like(X)
    if kind == "bumps":
        # b(r) = H (1 − (r/R)²)³ for r < R: C² with compact support (R < ½, one image per bump).
        for cx, cy, R, H in params:
            dx, dy = _wrap(X - cx), _wrap(Y - cy)
            q = (dx * dx + dy * dy) / (R * R)
            w = np.clip(1.0 - q, 0.0, None)
            s += H * w ** 3
            g = -6.0 * H * w ** 2 / (R * R)
            sx += g * dx
            sy += g * dy
        return s, sx, sy
    if kind == "noise":
        for k1, k2, a, phi in params:
            arg = 2 * np.pi * (k1 * X + k2 * Y) + phi
            s += a * np.cos(arg)
            d = -2 * np.pi * a * np.sin(arg)
            sx += k1 * d
            sy += k2 * d
        return s, sx, sy
    raise ValueError(f"unknown heightfield kind '{kind}'; use one of {', '.join(KINDS)}")


def _scaled(kind, params, periods, max_tilt, median_tilt, seed) -> Heightfield:
    if (max_tilt is None) == (median_tilt is None):
        raise ValueError("give exactly one of max_tilt and median_tilt (degrees)")
    unit = Heightfield(kind, int(periods), 1.0, params, seed)
    _, hx, hy = unit.period_grid()
    slope = np.hypot(hx, hy)
    if max_tilt is not None:
        ref, target = slope.max(), max_tilt
    else:
        ref, target = np.median(slope), median_tilt
    if not 0.0 < target < 89.0:
        raise ValueError(f"target tilt must be in (0°, 89°), got {target}")
    return replace(unit, amplitude=float(math.tan(math.radians(target)) / ref))


def egg_crate(periods: int = 2, max_tilt: float | None = None, median_tilt: float | None = None) -> Heightfield:
    """``A sin(2π p x) sin(2π p y)``; its max tilt is ``atan(2π p A)``."""
    return _scaled("eggcrate", (), periods, max_tilt, median_tilt, 0)


def bumps(periods: int = 2, max_tilt: float | None = None, median_tilt: float | None = None,
          count: int = 5, seed: int = 1) -> Heightfield:
    """``count`` smooth bumps per period (profile ``(1 − r²/R²)³``, height ∝ radius, R in [0.2, 0.36]
    periods), placed at fixed-seed random positions; overlapping bumps add."""
    rng = np.random.default_rng(seed)
    params = []
    for _ in range(count):
        cx, cy = rng.random(2)
        R = rng.uniform(0.2, 0.36)
        params.append((float(cx), float(cy), float(R), float(R)))
    return _scaled("bumps", tuple(params), periods, max_tilt, median_tilt, seed)


def noise(periods: int = 2, max_tilt: float | None = None, median_tilt: float | None = None,
          band: tuple[float, float] = (1.0, 3.0), slope: float = 1.0, seed: int = 7) -> Heightfield:
    """Band-limited periodic noise: ``Σ a_k cos(2π k·X + φ_k)`` over the integer wave vectors
    ``k`` (one per ± pair) with ``band[0] ≤ |k| ≤ band[1]`` cycles per period, Gaussian
    amplitudes of spectral fall-off ``|k|^−(1 + slope)`` and uniform phases, fixed seed.
    (An FFT-filtered white noise, written as its Fourier series so it is analytic everywhere.)"""
    rng = np.random.default_rng(seed)
    kmax = int(math.floor(band[1]))
    params = []
    for k1 in range(0, kmax + 1):
        for k2 in range(-kmax, kmax + 1):
            if k1 == 0 and k2 <= 0:
                continue                      # one of each ± pair, no DC
            r = math.hypot(k1, k2)
            if not band[0] <= r <= band[1]:
                continue
            a = rng.normal() * r ** (-(1.0 + slope))
            phi = rng.uniform(0, 2 * np.pi)
            params.append((k1, k2, float(a), float(phi)))
    return _scaled("noise", tuple(params), periods, max_tilt, median_tilt, seed)


_GENERATORS = {"bumps": bumps, "eggcrate": egg_crate, "noise": noise}


def make_heightfield(kind: str, steepness="mild", periods: int = 2, **kwargs) -> Heightfield:
    """A generator by name with a :data:`STEEPNESS` preset (or a max tilt in degrees)."""
    if kind not in _GENERATORS:
        raise ValueError(f"unknown heightfield kind '{kind}'; use one of {', '.join(KINDS)}")
    max_tilt = STEEPNESS[steepness] if isinstance(steepness, str) else float(steepness)
    if not kwargs:
        return _preset(kind, max_tilt, int(periods))
    return _GENERATORS[kind](periods=periods, max_tilt=max_tilt, **kwargs)


@lru_cache(maxsize=128)
def _preset(kind, max_tilt, periods):
    return _GENERATORS[kind](periods=periods, max_tilt=max_tilt)


def tilt_stats(hf: Heightfield, n: int = _STATS_GRID) -> dict:
    """Tilt of the surface normal from +z in degrees over a period: median, mean, p99, max;
    plus the mean height and the peak-to-peak height (world units)."""
    h, hx, hy = hf.period_grid(n)
    tilt = np.degrees(np.arctan(np.hypot(hx, hy)))
    return {"median": float(np.median(tilt)), "mean": float(tilt.mean()),
            "p99": float(np.percentile(tilt, 99)), "max": float(tilt.max()),
            "mean_height": float(h.mean()), "peak_to_peak": float(h.max() - h.min())}


# ---------------------------------------------------------------------------
# Maps
# ---------------------------------------------------------------------------

def texel_centres(res: int):
    """World (x, y) of the texel centres of a ``res × res`` map over ``[0, 1]²`` (row 0 = top = y≈1)."""
    t = (np.arange(res) + 0.5) / res
    x, y = np.meshgrid(t, 1.0 - t, indexing="xy")      # x varies along columns, y down the rows
    return x, y


def texel_normals(hf: Heightfield, res: int, gradient: str = "analytic") -> np.ndarray:
    """Unit tangent-space (= world) normals at the texel centres, ``res × res × 3`` float64.

    ``gradient="analytic"``: from the analytic gradient. ``"central"``: central
    differences of the heights sampled at the texel centres (periodic grid, the
    way a baker without the analytic surface does it; O(Δ²) error).
    """
    x, y = texel_centres(res)
    if gradient == "analytic":
        return hf.normal(x, y)
    if gradient != "central":
        raise ValueError("gradient must be 'analytic' or 'central'")
    h = hf.height(x, y)
    d = 1.0 / res
    hx = (np.roll(h, -1, axis=1) - np.roll(h, 1, axis=1)) / (2 * d)
    hy = (np.roll(h, 1, axis=0) - np.roll(h, -1, axis=0)) / (2 * d)   # row r−1 is at y + d
    n = np.stack([-hx, -hy, np.ones_like(hx)], axis=-1)
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def encode_normals(n: np.ndarray) -> np.ndarray:
    """``n·0.5 + 0.5`` as float32 (what ``normalmap`` decodes as ``2·rgb − 1``)."""
    return (np.asarray(n) * 0.5 + 0.5).astype(np.float32)


def normal_map(hf: Heightfield, res: int, gradient: str = "analytic") -> np.ndarray:
    """The tangent-space normal map of ``hf`` over ``[0, 1]²``: ``res × res × 3`` float32,
    encoded ``n·0.5 + 0.5``, OpenGL convention in Mitsuba's frame on :func:`plane_mesh`
    (see the module docstring). Periodic, so it tiles with the bitmap's repeat wrap mode."""
    return encode_normals(texel_normals(hf, res, gradient))


def height_map(hf: Heightfield, res: int, relative: bool = True) -> np.ndarray:
    """The heights at the texel centres, ``res × res`` float32 in world units, same layout
    as :func:`normal_map` (minus the mean height when ``relative``: the plane's level)."""
    x, y = texel_centres(res)
    h = hf.height(x, y)
    if relative:
        h = h - hf.mean_height
    return h.astype(np.float32)


#: Steps of :func:`first_hit`'s march across the heights' slab (then bisection).
HIT_STEPS = 2000
HIT_BISECTIONS = 40


def first_hit(hf: Heightfield, x, y, z0: float, d) -> np.ndarray:
    """Where the ray that crosses the plane z = ``z0`` at (``x``, ``y``) along −``d`` (``d``: the
    unit direction toward the camera, either side of the plane) first meets the heightfield:
    the parameter t of the point (x, y, z0) + t·d, for arrays ``x``, ``y``. A march from the
    camera's side of the heights' slab in :data:`HIT_STEPS` steps (far finer than the egg crate's
    features at any view of the harnesses), refined by bisection. 0 where ``d`` is parallel to the
    plane (no camera there)."""
    x, y = np.asarray(x, np.float64), np.asarray(y, np.float64)
    d = np.asarray(d, np.float64)
    if abs(d[2]) < 1e-9:
        return np.zeros_like(x)
    lo, hi = hf.height_range
    t_near, t_far = sorted([(lo - z0) / d[2], (hi - z0) / d[2]], reverse=True)
    side = 1.0 if d[2] > 0 else -1.0

    def above(t):      # > 0 on the camera's side of the surface
        return side * ((z0 + t * d[2]) - hf.height(x + t * d[0], y + t * d[1]))

    span = (t_near - t_far) * (1 + 1e-6)
    t_in, t_out = np.full(x.shape, np.nan), np.full(x.shape, np.nan)
    prev_t, prev_g = t_near + 1e-9 * span, above(t_near + 1e-9 * span)
    for i in range(1, HIT_STEPS + 1):
        t = t_near + 1e-9 * span - span * i / HIT_STEPS
        g = above(t)
        new = np.isnan(t_in) & (prev_g > 0) & (g <= 0)
        t_in[new], t_out[new] = prev_t, t
        prev_t, prev_g = t, g
    t_in, t_out = np.where(np.isnan(t_in), 0.0, t_in), np.where(np.isnan(t_out), 0.0, t_out)
    for _ in range(HIT_BISECTIONS):
        mid = 0.5 * (t_in + t_out)
        outside = above(mid) > 0
        t_in, t_out = np.where(outside, mid, t_in), np.where(outside, t_out, mid)
    return 0.5 * (t_in + t_out)


def bilinear(img: np.ndarray, x, y) -> np.ndarray:
    """A map in :func:`texel_centres`' layout (H × W × C, periodic) read bilinearly, as Mitsuba's
    ``bitmap`` with ``wrap_mode="repeat"`` reads it, at world points (``x``, ``y``)."""
    res_y, res_x = img.shape[:2]
    u, v = np.asarray(x) * res_x - 0.5, (1.0 - np.asarray(y)) * res_y - 0.5
    i0, j0 = np.floor(u).astype(np.int64), np.floor(v).astype(np.int64)
    fu, fv = (u - i0)[..., None], (v - j0)[..., None]

    def at(j, i):
        return img[j % res_y, i % res_x]
    return ((at(j0, i0) * (1 - fu) + at(j0, i0 + 1) * fu) * (1 - fv)
            + (at(j0 + 1, i0) * (1 - fu) + at(j0 + 1, i0 + 1) * fu) * fv)


def registered_map(hf: Heightfield, img: np.ndarray, d, upsample: int = 4) -> np.ndarray:
    """``img`` (a map over [0, 1]², e.g. :func:`normal_map`) registered for a camera in direction
    ``d`` (unit, toward the camera; orthographic): at each point of the plane z = mean height, the
    texel where the camera ray through that point meets the true surface (:func:`first_hit`),
    read bilinearly; at ``upsample`` × the map's resolution, so the occlusion edges stay sharp.
    Rendering the plane with it puts every camera ray's texel where the true geometry has it:
    what a perfect parallax (relief) lookup would give the camera rays."""
    res = img.shape[0] * int(upsample)
    x, y = texel_centres(res)
    t = first_hit(hf, x, y, hf.mean_height, d)
    return bilinear(np.asarray(img, np.float64), x + t * d[0], y + t * d[1]).astype(np.float32)


@lru_cache(maxsize=4)
def _registered_normal_map(hf: Heightfield, res: int, theta: float) -> np.ndarray:
    """:func:`normal_map` registered for the harness's camera at ``theta``: 4× the magnified map's
    resolution, a minified map (384 texels wide) as it is. Cached: the cells that differ only in
    material or lighting share it (the march is the slow part)."""
    return registered_map(hf, normal_map(hf, res), _direction(theta, CAMERA_AZIMUTH), upsample=max(1, 192 // res))


def bitmap_texture(img: np.ndarray, filter_type: str = "bilinear") -> dict:
    """A raw, repeating Mitsuba ``bitmap`` texture dict of an array (H×W or H×W×3)."""
    arr = np.ascontiguousarray(img, np.float32)
    if arr.ndim == 2:
        arr = arr[..., None]
    return {"type": "bitmap", "bitmap": mi.Bitmap(arr), "raw": True,
            "filter_type": filter_type, "wrap_mode": "repeat"}


# ---------------------------------------------------------------------------
# Meshes
# ---------------------------------------------------------------------------

_ARRAY_CACHE: dict = {}


def _snap(extent, step):
    x0, x1, y0, y1 = extent
    return (math.floor(x0 / step + 1e-9) * step, math.ceil(x1 / step - 1e-9) * step,
            math.floor(y0 / step + 1e-9) * step, math.ceil(y1 / step - 1e-9) * step)


def displaced_arrays(hf: Heightfield, extent, verts_per_period: int = 32):
    """Numpy arrays ``(positions, normals, uvs, faces)`` of the surface ``z = h(x, y)`` over
    ``extent = (x0, x1, y0, y1)`` (snapped outwards to the vertex grid): a regular grid of
    ``verts_per_period`` vertices per period, analytic unit normals, UVs ``(x, 1 − y)``,
    two triangles per cell with alternating diagonals, counter-clockwise seen from +z.
    Cached (the last few calls)."""
    step = hf.period / int(verts_per_period)
    ext = _snap(extent, step)
    key = (hf, ext, int(verts_per_period))
    if key in _ARRAY_CACHE:
        return _ARRAY_CACHE[key]
    nx = int(round((ext[1] - ext[0]) / step)) + 1
    ny = int(round((ext[3] - ext[2]) / step)) + 1
    # Heights and normals repeat with the period: evaluate one period of the grid and tile.
    i0 = int(round(ext[0] / step))
    j0 = int(round(ext[2] / step))
    M = int(verts_per_period)
    t = np.arange(M) * step
    Xp, Yp = np.meshgrid(t, t, indexing="xy")
    hp, hxp, hyp = hf.eval(Xp, Yp)
    ii = (i0 + np.arange(nx)) % M
    jj = (j0 + np.arange(ny)) % M
    h, hx, hy = (a[np.ix_(jj, ii)] for a in (hp, hxp, hyp))
    xs = (i0 + np.arange(nx)) * step
    ys = (j0 + np.arange(ny)) * step
    X, Y = np.meshgrid(xs, ys, indexing="xy")                   # row j: y, column i: x
    pos = np.stack([X, Y, h], axis=-1).reshape(-1, 3)
    nrm = np.stack([-hx, -hy, np.ones_like(hx)], axis=-1).reshape(-1, 3)
    nrm /= np.linalg.norm(nrm, axis=1, keepdims=True)
    uv = np.stack([X, 1.0 - Y], axis=-1).reshape(-1, 2)
    jc, ic = np.meshgrid(np.arange(ny - 1), np.arange(nx - 1), indexing="ij")
    a = (jc * nx + ic).ravel()
    b, c, d = a + 1, a + nx + 1, a + nx              # (i,j), (i+1,j), (i+1,j+1), (i,j+1)
    alt = ((jc + ic) % 2 == 1).ravel()
    f1 = np.where(alt[:, None], np.stack([a, b, d], 1), np.stack([a, b, c], 1))
    f2 = np.where(alt[:, None], np.stack([b, c, d], 1), np.stack([a, c, d], 1))
    faces = np.concatenate([f1, f2], axis=0)
    out = (pos.astype(np.float32), nrm.astype(np.float32), uv.astype(np.float32),
           faces.astype(np.uint32))
    if len(_ARRAY_CACHE) >= 4:
        _ARRAY_CACHE.pop(next(iter(_ARRAY_CACHE)))
    _ARRAY_CACHE[key] = out
    return out


def triangle_mesh(name, positions, normals, uvs, faces, bsdf):
    """A Mitsuba mesh of these vertex arrays (positions, unit normals or None for flat faces, uvs)
    and faces, with ``bsdf`` (a dict or a loaded BSDF; None: Mitsuba's default)."""
    props = mi.Properties()
    if bsdf is not None:
        props["bsdf"] = mi.load_dict(bsdf) if isinstance(bsdf, dict) else bsdf
    mesh = mi.Mesh(name, len(positions), len(faces), props, has_vertex_normals=normals is not None,
                   has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    params["vertex_positions"] = mi.Float(np.ascontiguousarray(positions, np.float32).ravel())
    if normals is not None:
        params["vertex_normals"] = mi.Float(np.ascontiguousarray(normals, np.float32).ravel())
    params["vertex_texcoords"] = mi.Float(np.ascontiguousarray(uvs, np.float32).ravel())
    params["faces"] = mi.UInt32(np.ascontiguousarray(faces, np.uint32).ravel())
    params.update()
    return mesh


def displaced_mesh(hf: Heightfield, extent, verts_per_period: int = 32, bsdf=None,
                   name: str = "true_surface") -> "mi.Mesh":
    """The true surface as a Mitsuba mesh (see :func:`displaced_arrays`); ``bsdf``: a dict or
    a loaded BSDF."""
    return triangle_mesh(name, *displaced_arrays(hf, extent, verts_per_period), bsdf)


def plane_mesh(extent=(0.0, 1.0, 0.0, 1.0), z: float = 0.0, bsdf=None, name: str = "plane") -> "mi.Mesh":
    """The coarse surface: two triangles over ``extent`` at height ``z``, normal +z, UVs
    ``(x, 1 − y)`` as on :func:`displaced_mesh` (``dp/du = +x``, ``dp/dv = −y``)."""
    x0, x1, y0, y1 = extent
    pos = np.array([[x0, y0, z], [x1, y0, z], [x1, y1, z], [x0, y1, z]], np.float64)
    nrm = np.tile([0.0, 0.0, 1.0], (4, 1))
    uv = np.stack([pos[:, 0], 1.0 - pos[:, 1]], axis=1)
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    return triangle_mesh(name, pos, nrm, uv, faces, bsdf)


# ---------------------------------------------------------------------------
# Views, lightings, magnifications, materials
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class View:
    """Orthographic camera at ``theta`` degrees from +z, on the −y side (azimuth −90°), looking
    at the plane's centre; the image spans x ∈ [0, 1] and the plane's whole visible extent.
    ``theta`` > 90° puts the camera below the plane, looking up at its underside (180° − theta
    from −z)."""
    name: str
    theta: float


@dataclass(frozen=True)
class Lighting:
    """A directional sun at ``sun_elevation`` (degrees above the plane) and ``sun_azimuth``
    (degrees from +x toward +y; the camera sits at −90°), irradiance ``sun_irradiance`` at normal
    incidence; plus a smooth sky envmap (no disc) scaled by ``sky`` (0: none)."""
    name: str
    sun_elevation: float
    sun_azimuth: float
    sun_irradiance: float = 3.0
    sky: float = 1.0


@dataclass(frozen=True)
class Magnification:
    """``periods`` repetitions over the plane (= across the image width), a normal map of
    ``texels_per_period`` texels per period, a true mesh of ``verts_per_period`` vertices per
    period (per axis)."""
    name: str
    periods: int
    texels_per_period: int
    verts_per_period: int
    metric_block: int = 1


VIEWS = {
    "frontal": View("frontal", 0.0),
    "grazing": View("grazing", 75.0),
    "grazing78": View("grazing78", 78.0),
    # The dielectric cells (validation/dielectric.py): 40° from the normal, and 40° from the
    # normal below the surface (a camera in the water or glass, looking up).
    "oblique40": View("oblique40", 40.0),
    "inside40": View("inside40", 140.0),
}

LIGHTINGS = {
    # Sun behind-right of the surface as the camera sees it, 45° up: glossy highlights in both views.
    "sky_sun": Lighting("sky_sun", 45.0, 30.0, 3.0, 1.0),
    # Sun 80° from the normal, from +x (the image's right): long shadows across the image.
    "grazing_sun": Lighting("grazing_sun", 10.0, 0.0, 3.0, 0.1),
    "grazing_sun_nosky": Lighting("grazing_sun_nosky", 10.0, 0.0, 3.0, 0.0),
    # The diffuse-relief scene of validation/true_geometry.py: a 45° sun, no sky.
    "sun45": Lighting("sun45", 45.0, 0.0, 3.0, 0.0),
    # The convention test's light: 45° up, azimuth 30° (x and y gradients both matter), no sky.
    "test_sun": Lighting("test_sun", 45.0, 30.0, 3.0, 0.0),
    # The sky alone (no sun: a delta light cannot reach a floor through a smooth dielectric).
    "sky": Lighting("sky", 90.0, 0.0, 0.0, 1.0),
}

MAGNIFICATIONS = {
    # 2 periods across the image: at 96 px a texel covers 2 × 2 pixels (frontal).
    "magnified": Magnification("magnified", 2, 24, 64),
    # 24 periods across: 384 texels over 96 px, 4 × 4 texels per pixel (frontal); 32 vertices
    # per period (steep bumps, grazing view and sun, truth energy against 48 vertices: 16 → −14.5 %,
    # 32 → −2.3 %; frontal, 32 against 64: +0.2 %). Metrics on 4 × 4-pixel block means (one period per block,
    # frontal at 96 px): the pixel-scale pattern of a minified surface is moiré and glints, what
    # matters is its aggregate; the block mean is a 24² render with 16× the spp.
    "minified": Magnification("minified", 24, 16, 32, 4),
}


def _rgb(v):
    return {"type": "rgb", "value": [float(c) for c in v]}


MATERIALS = {
    "diffuse": {"type": "diffuse", "reflectance": _rgb([0.8, 0.8, 0.8])},
    "plastic": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.3,
                "diffuse_reflectance": _rgb([0.55, 0.25, 0.12])},
    "aluminium": {"type": "roughconductor", "material": "Al", "distribution": "ggx", "alpha": 0.2},
    "gold": {"type": "roughconductor", "material": "Au", "distribution": "ggx", "alpha": 0.05},
    "glossy_metal": {"type": "roughconductor", "material": "Al", "distribution": "ggx", "alpha": 0.0225},
    # Dielectric interfaces (validation/dielectric.py): the plane is the surface of the water or glass.
    "water": {"type": "dielectric", "int_ior": 1.33, "ext_ior": 1.0},
    "rough_glass": {"type": "roughdielectric", "distribution": "ggx", "alpha": 0.15,
                    "int_ior": 1.5, "ext_ior": 1.0},
}


def _sky_to_world():
    return mi.ScalarTransform4f().rotate([1.0, 0.0, 0.0], 90.0)      # envmap +Y → world +Z


def _direction(theta_deg, phi_deg):
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    return np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])


CAMERA_AZIMUTH = -90.0


def footprint(view: View):
    """(x0, x1, y0, y1): the part of the plane z = mean the camera sees (x ∈ [0, 1] across)."""
    half_y = 0.5 / abs(math.cos(math.radians(view.theta)))
    return (0.0, 1.0, 0.5 - half_y, 0.5 + half_y)


def _extent(hf: Heightfield, view: View, lighting: Lighting, margin=None):
    """The footprint grown by a margin that holds every shadow and occluder of the footprint:
    peak-to-peak height over the tangent of the lowest elevation of sun or view (≥ 5°), plus
    one period; at least two periods."""
    lo, hi = hf.height_range
    if margin is None:
        elev = min(lighting.sun_elevation, abs(90.0 - view.theta))
        elev = max(elev, 5.0)
        margin = max(2 * hf.period, (hi - lo) / math.tan(math.radians(elev)) + hf.period)
    x0, x1, y0, y1 = footprint(view)
    return (x0 - margin, x1 + margin, y0 - margin, y1 + margin)


def _sensor(view: View, z: float, res: int, spp: int, sampler: str = "multijitter") -> dict:
    target = np.array([0.5, 0.5, z])
    d = _direction(view.theta, CAMERA_AZIMUTH)
    origin = target + 20.0 * d
    up = [0.0, 1.0, 0.0] if view.theta < 1e-6 else [0.0, 0.0, 1.0]
    to_world = mi.ScalarTransform4f().look_at(origin=origin.tolist(), target=target.tolist(), up=up)
    return {"type": "orthographic",
            "to_world": to_world @ mi.ScalarTransform4f().scale([0.5, 0.5, 1.0]),
            "near_clip": 1.0, "far_clip": 100.0,
            "sampler": {"type": sampler, "sample_count": int(spp)},
            "film": {"type": "hdrfilm", "width": int(res), "height": int(res),
                     "pixel_format": "rgb", "rfilter": {"type": "box"}}}


def _emitters(lighting: Lighting) -> dict:
    em = {}
    sun = _direction(90.0 - lighting.sun_elevation, lighting.sun_azimuth)
    if lighting.sun_irradiance > 0:
        em["sun"] = {"type": "directional", "direction": (-sun).tolist(),
                     "irradiance": _rgb(np.array([1.0, 0.96, 0.90]) * lighting.sun_irradiance)}
    if lighting.sky > 0:
        em["sky"] = {"type": "envmap", "bitmap": mi.Bitmap(sky.envmap(128, gradient=sky.HAZY) * lighting.sky),
                     "to_world": _sky_to_world()}
    return em


#: The floor under a dielectric surface: checks of ``1 / (2 FLOOR_CHECKS)`` world units (a
#: quarter period of the magnified heightfields), diffuse, dark and light grey.
FLOOR_CHECKS = 4
FLOOR_REFLECTANCE = (0.1, 0.7)


def floor_mesh(extent, z: float, name: str = "floor") -> "mi.Mesh":
    """A diffuse checkerboard floor (:data:`FLOOR_CHECKS`, :data:`FLOOR_REFLECTANCE`) at height
    ``z`` over ``extent``: what is seen through a water or glass surface above it."""
    dark, light = FLOOR_REFLECTANCE
    checker = {"type": "checkerboard", "color0": _rgb([dark] * 3), "color1": _rgb([light] * 3),
               "to_uv": mi.ScalarTransform4f().scale([FLOOR_CHECKS, FLOOR_CHECKS, 1.0])}
    return plane_mesh(extent, z, {"type": "diffuse", "reflectance": checker}, name)


def _lookup(table, key, what):
    if isinstance(key, str):
        if key not in table:
            raise ValueError(f"unknown {what} '{key}'; use one of {', '.join(table)}")
        return table[key]
    return key


def scene_dict(hf: Heightfield, surface: str, bsdf: dict, lighting="sky_sun", view="frontal",
               res: int = 128, spp: int = 64, max_depth: int = 8, verts_per_period: int = 32,
               margin: float | None = None, sampler: str = "multijitter",
               integrator: dict | None = None, floor: float = 0.0) -> dict:
    """A Mitsuba scene dict: ``surface="true"`` (the dense :func:`displaced_mesh`, ``bsdf`` =
    the material) or ``"plane"`` (:func:`plane_mesh` at the mean height, ``bsdf`` = the
    material wrapped by a normal-mapping method), over the view's footprint plus a margin;
    ``path`` integrator with ``max_depth`` (or ``integrator``, e.g. ``prb`` for inverse rendering);
    orthographic sensor of ``res²`` pixels, ``sampler`` with ``spp``. The extent is the view's
    footprint plus a margin that holds every shadow and occluder of it (``margin``: override).
    ``floor`` > 0 adds a :func:`floor_mesh` that far below the mean height, over the extent grown
    by one unit (for dielectric surfaces: what is seen through them)."""
    lighting = _lookup(LIGHTINGS, lighting, "lighting")
    view = _lookup(VIEWS, view, "view")
    ext = _extent(hf, view, lighting, margin)
    z = hf.mean_height
    if surface == "true":
        shape = displaced_mesh(hf, ext, verts_per_period, bsdf)
    elif surface == "plane":
        shape = plane_mesh(ext, z, bsdf)
    else:
        raise ValueError("surface must be 'true' or 'plane'")
    extra = {}
    if floor > 0:
        x0, x1, y0, y1 = ext
        extra["floor"] = floor_mesh((x0 - 1.0, x1 + 1.0, y0 - 1.0, y1 + 1.0), z - float(floor))
    return {"type": "scene",
            "integrator": integrator or {"type": "path", "max_depth": int(max_depth)},
            "sensor": _sensor(view, z, res, spp, sampler),
            "surface": shape, **extra, **_emitters(lighting)}


# ---------------------------------------------------------------------------
# Normal-mapping methods
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Method:
    """A way to put the map on the plane: ``wrap(nested, normalmap)`` → BSDF dict, where
    ``nested`` is the material dict and ``normalmap`` the bitmap texture dict of the baked map.
    A ``wrap`` that also takes a ``maps`` keyword gets a dict with ``heightmap`` (the heights'
    texture, world units, relative to the plane), ``normals`` (the exact unit normals per texel,
    numpy) and ``res`` too (for height/bump-map methods)."""
    key: str
    label: str
    wrap: Callable
    about: str = ""

    def bsdf(self, nested: dict, normalmap: dict, maps: dict | None = None) -> dict:
        try:
            takes_maps = "maps" in inspect.signature(self.wrap).parameters
        except (TypeError, ValueError):
            takes_maps = False
        if takes_maps:
            return self.wrap(nested, normalmap, maps=maps or {})
        return self.wrap(nested, normalmap)


def plugin_method(model: str | None = None, tangent_facet: str | None = None, key: str | None = None,
                  label: str | None = None, **params) -> Method:
    """``normalmap_microfacet`` with ``model`` (None: the plugin's default, whatever it is),
    ``tangent_facet`` and any other plugin parameters. The model string is passed through
    unchecked, so models that do not exist yet can be listed (loading then fails for them)."""
    extra = {"model": model} if model is not None else {}
    if tangent_facet is not None:
        extra["tangent_facet"] = tangent_facet
    extra.update(params)

    def wrap(nested, normalmap):
        return plugin_bsdf(nested, normalmap, **extra)

    name = model or "default"
    if tangent_facet is not None:
        name += f"_{tangent_facet}"
    name += "".join(f"_{k}{v}" for k, v in params.items())
    return Method(key or name, label or name.replace("_", " "), wrap,
                  f"normalmap_microfacet {extra}" if extra else "normalmap_microfacet (default model)")


def _bumpmap(nested, normalmap, maps):
    return {"type": "bumpmap", "bsdf": nested, "scale": 1.0, "texture": maps["heightmap"]}


def heightmap_method(model: str | None = None, key: str | None = None, **params) -> Method:
    """``normalmap_microfacet`` on the baked *height* map (``heightmap``, ``height_scale`` 1: the
    heights are in world units on the plane, whose dp/du, dp/dv have unit length), ``model``
    None: the plugin's default."""
    extra = {"model": model} if model is not None else {}
    extra.update(params)

    def wrap(nested, normalmap, maps):
        return {"type": "normalmap_microfacet", "heightmap": maps["heightmap"], "height_scale": 1.0,
                "bsdf": nested, **extra}

    name = key or ("heightmap" + (f"_{model}" if model else "") + "".join(f"_{k}{v}" for k, v in params.items()))
    return Method(name, name.replace("_", " "), wrap, f"normalmap_microfacet on the height map {extra}")


def _catalogued(key: str, about: str, new_key: str | None = None, label: str | None = None) -> Method:
    """A method of :mod:`mfnormal.methods` with this harness's description (and key, label)."""
    m = METHOD_BY_KEY[key]
    return Method(new_key or m.key, label or m.label, m.bsdf, about)


#: The catalogue's methods (:mod:`mfnormal.methods`; its ``flat`` is ``nomap`` here, and its
#: ``normalmap_microfacet`` methods are :func:`plugin_method`'s), and ``bumpmap``.
METHODS = {m.key: m for m in (
    _catalogued("flat", "the nested BSDF alone on the plane", "nomap", "no map"),
    _catalogued("classic", "Mitsuba normalmap, flip_invalid_normals / use_shadowing_function off"),
    _catalogued("classic_fixed",
                "Mitsuba normalmap, flip_invalid_normals / use_shadowing_function on (its defaults)"),
    *(plugin_method(**m.plugin_params()) for m in CATALOGUE if m.kind == "microfacet"),
    Method("bumpmap", "bumpmap", _bumpmap, "Mitsuba bumpmap on the baked height map (scale 1)"),
    heightmap_method(),
    heightmap_method("analytic"),
    heightmap_method("separable"),
    heightmap_method("nonseparable"),
)}

#: The methods of the default grid.
DEFAULT_METHODS = ("nomap", "classic", "classic_fixed", "plugin:faithful", "analytic",
                   "separable_specular", "separable_same", "nonseparable_specular", "nonseparable_same")


def split_methods(text: str) -> list:
    """A comma-separated list of method specs (:func:`method_from_spec`), where a spec's own
    ``name=value`` items stay with it: ``classic,plugin:faithful,neighbourhood=8`` is two specs."""
    out = []
    for item in text.split(","):
        if out and "=" in item and out[-1].startswith("plugin:"):
            out[-1] += "," + item
        else:
            out.append(item)
    return out


def method_from_spec(spec: str) -> Method:
    """A :data:`METHODS` key, or ``plugin:MODEL[:TANGENT_FACET][,name=value...]`` for any
    ``normalmap_microfacet`` configuration (values parsed as int, float, bool or string);
    ``plugin:`` alone is the plugin's default model."""
    if spec in METHODS:
        return METHODS[spec]
    if not spec.startswith("plugin:"):
        raise ValueError(f"unknown method '{spec}'; use one of {', '.join(METHODS)} or "
                         "plugin:MODEL[:TANGENT_FACET][,name=value...]")
    head, *kv = spec[len("plugin:"):].split(",")
    model, _, facet = head.partition(":")
    params = {}
    for item in kv:
        k, _, v = item.partition("=")
        params[k.strip()] = _parse_value(v.strip())
    return plugin_method(model or None, facet or None, **params)


def _parse_value(v: str):
    if v.lower() in ("true", "false"):
        return v.lower() == "true"
    for t in (int, float):
        try:
            return t(v)
        except ValueError:
            pass
    return v


# ---------------------------------------------------------------------------
# Metrics
# ---------------------------------------------------------------------------

#: |ln| error floor: ln((Y + f)/(Y_true + f)) with f = LN_FLOOR × the truth's median luminance.
LN_FLOOR = 0.01
#: Near-black: luminance below BLACK_FRACTION × the truth's median luminance.
BLACK_FRACTION = 0.05
#: relMSE is taken after a metered exposure: both images scaled by EXPOSURE_MEAN / mean(Y_true).
EXPOSURE_MEAN = 0.5


def near_black_threshold(truth: np.ndarray) -> float:
    return BLACK_FRACTION * float(np.median(luminance(truth)))


def exposure_scale(truth: np.ndarray) -> float:
    """The factor that brings the truth's mean luminance to EXPOSURE_MEAN."""
    return EXPOSURE_MEAN / max(float(luminance(truth).mean()), 1e-12)


def metrics(img: np.ndarray, truth: np.ndarray) -> dict:
    """Image metrics of ``img`` against the reference ``truth`` (both H×W×3 linear, the whole
    frame: the surface fills it, so there are no masks):

    - ``rel_mse``: the project's relMSE, mean((x − ref)²/(ref² + 1e-2)) over pixels and
      channels (:func:`mfnormal.report.metrics.rel_mse`), after a metered exposure: both images times
      :func:`exposure_scale` (the truth's mean luminance → 0.5), so that the 1e-2 regulariser
      means the same (ref luminance ≈ 20 % of the mean) in bright and dark cells;
      ``rel_mse_raw``: the same on the unscaled renders;
    - ``ln_err``: mean |ln((Y + f)/(Y_true + f))| of luminance, f = LN_FLOOR·median(Y_true);
    - ``contrast``: std/mean of the luminance of ``img`` (the whole frame);
    - ``near_black``: fraction of pixels with Y < BLACK_FRACTION·median(Y_true);
    - ``mean``: mean luminance (its ratio to the truth's: the energy).
    """
    y, yt = luminance(img), luminance(truth)
    floor = LN_FLOOR * float(np.median(yt))
    k = exposure_scale(truth)
    return {"rel_mse": rel_mse(img * k, truth * k),
            "rel_mse_raw": rel_mse(img, truth),
            "ln_err": float(np.mean(np.abs(np.log((y + floor) / (yt + floor))))),
            "contrast": float(y.std() / max(y.mean(), 1e-12)),
            "near_black": float(np.mean(y < near_black_threshold(truth))),
            "mean": float(y.mean())}


# ---------------------------------------------------------------------------
# Cells: one comparison
# ---------------------------------------------------------------------------

@dataclass(frozen=True)
class Cell:
    """One comparison: a heightfield kind and steepness (a :data:`STEEPNESS` name or a max tilt
    in degrees), a :data:`MATERIALS` name (or a BSDF dict via ``material_dict``), a lighting,
    a view and a magnification (names of the presets); ``floor`` > 0: a checkerboard floor that
    far below the surface (:func:`scene_dict`), for dielectric materials."""
    heightfield: str = "bumps"
    steepness: object = "mild"
    material: str = "diffuse"
    lighting: str = "sky_sun"
    view: str = "frontal"
    magnification: str = "magnified"
    material_dict: tuple = field(default=(), compare=False)
    floor: float = 0.0

    @property
    def name(self) -> str:
        st = self.steepness if isinstance(self.steepness, str) else f"{self.steepness:g}deg"
        return "/".join([self.heightfield, st, self.material, self.lighting, self.view,
                         self.magnification] + ([f"floor{self.floor:g}"] if self.floor > 0 else []))

    @property
    def spp_factor(self) -> int:
        """4 for glossy materials (GGX α ≤ 0.05: sub-pixel sun highlights converge slowly), else 1."""
        return 4 if float(self.nested().get("alpha", 1.0)) <= 0.05 else 1

    @property
    def metric_block(self) -> int:
        return MAGNIFICATIONS[self.magnification].metric_block

    def hf(self) -> Heightfield:
        mag = MAGNIFICATIONS[self.magnification]
        return make_heightfield(self.heightfield, self.steepness, periods=mag.periods)

    def nested(self) -> dict:
        return dict(self.material_dict) if self.material_dict else MATERIALS[self.material]

    def maps(self, registered: bool = False) -> dict:
        """The baked maps; ``registered``: the normal map :func:`registered_map` for the camera
        (the height map, the exact normals and ``res`` stay the baked ones)."""
        hf, mag = self.hf(), MAGNIFICATIONS[self.magnification]
        res = mag.periods * mag.texels_per_period
        nmap = _registered_normal_map(hf, res, VIEWS[self.view].theta) if registered else normal_map(hf, res)
        return {"normalmap": bitmap_texture(nmap),
                "heightmap": bitmap_texture(height_map(hf, res)),
                "normals": texel_normals(hf, res), "res": res}

    def truth_scene(self, res=96, spp=64, max_depth=8, **kwargs) -> dict:
        """The dense true mesh with the material (``kwargs``: :func:`scene_dict`'s)."""
        mag = MAGNIFICATIONS[self.magnification]
        return scene_dict(self.hf(), "true", self.nested(), self.lighting, self.view, res, spp,
                          max_depth, mag.verts_per_period, floor=self.floor, **kwargs)

    def plane_scene(self, method: Method, res=96, spp=64, max_depth=8, maps=None, **kwargs) -> dict:
        """The plane with the material wrapped by ``method`` around the baked map."""
        maps = maps or self.maps()
        bsdf = method.bsdf(self.nested(), maps["normalmap"], maps)
        return scene_dict(self.hf(), "plane", bsdf, self.lighting, self.view, res, spp, max_depth,
                          floor=self.floor, **kwargs)


def render(scene, spp: int, seed: int, pass_spp: int = 64) -> np.ndarray:
    """Linear RGB (H×W×3 float64) of a scene (dict or loaded) at ``spp``, in passes of
    ≤ ``pass_spp`` (seeds ``seed``, ``seed + 1``, ...; keep seed ranges of renders that must be
    independent apart: :func:`render_cell` uses multiples of 1000); NaN/Inf → 0."""
    return render_counted(scene, spp, seed, pass_spp)[0]


def render_counted(scene, spp: int, seed: int, pass_spp: int = 64) -> tuple:
    """:func:`render` and the number of values (pixels × channels) it set to 0 because they were
    NaN or Inf, and of those that are negative: ``(image, nonfinite, negative)``."""
    out = render_rgb(scene, spp, seed, pass_spp)
    finite = np.isfinite(out)
    return np.where(finite, out, 0.0), int((~finite).sum()), int((out[finite] < 0).sum())


def block_mean(img: np.ndarray, b: int) -> np.ndarray:
    """Means over ``b × b`` pixel blocks (H and W must be multiples of ``b``)."""
    if b == 1:
        return img
    H, W = img.shape[:2]
    if H % b or W % b:
        raise ValueError(f"image size {W}x{H} is not a multiple of the metric block {b}")
    return img.reshape(H // b, b, W // b, b, -1).mean(axis=(1, 3))


def cell_metrics(img: np.ndarray, truth: np.ndarray, block: int = 1) -> dict:
    """:func:`metrics` on ``block × block`` block means (the cell's metric resolution), plus the
    per-pixel ``rel_mse_px`` and ``near_black_px`` (near-black is always counted per pixel:
    black pixels are a per-pixel artifact)."""
    m = metrics(block_mean(img, block), block_mean(truth, block))
    px = metrics(img, truth) if block > 1 else m
    m["rel_mse_px"] = px["rel_mse"]
    m["near_black_px"] = px["near_black"]
    return m


_TRUTH_SCENES: dict = {}


def _truth_scene(cell: Cell, res, spp, max_depth):
    """The loaded truth scene of ``cell``; the last one is kept and reused (its mesh's BSDF
    swapped) for the next cell with the same geometry, lighting and view: building the BVH of
    a dense mesh costs more than rendering it. Identical results to a fresh load (tested)."""
    key = (cell.hf(), cell.lighting, cell.view, MAGNIFICATIONS[cell.magnification].verts_per_period,
           int(res), int(max_depth), cell.floor)
    hit = _TRUTH_SCENES.get(key)
    if hit is None:
        _TRUTH_SCENES.clear()
        scene = mi.load_dict(cell.truth_scene(res, spp, max_depth))
        _TRUTH_SCENES[key] = hit = (scene, cell.nested())
    scene, material = hit
    if material != cell.nested():
        mesh = next(s for s in scene.shapes() if s.id() == "surface")
        mesh.set_bsdf(mi.load_dict(cell.nested()))
        _TRUTH_SCENES[key] = (scene, cell.nested())
    return scene


def cell_seed(cell: Cell, run_seed: int = 0) -> int:
    """A seed that depends only on the cell (and ``run_seed``): a cell renders the same numbers
    whatever else a run contains."""
    return (zlib.crc32(cell.name.encode()) + 7919 * int(run_seed)) % 1_000_000


def render_cell(cell: Cell, methods, res: int = 96, spp: int = 64, ref_factor: int = 4,
                max_depth: int = 8, seed: int | None = None, pass_spp: int = 64,
                method_noise: bool = False, log=None, registered: bool = False) -> dict:
    """Render one cell and measure every method against the truth (``registered``: every method
    on the normal map registered for the camera, :meth:`Cell.maps`).

    ``spp`` is per method render (times ``cell.spp_factor``). The truth is rendered at
    ``ref_factor × spp`` (the reference every metric compares with) and once more at ``spp``
    with an independent seed: the latter's metrics are the **noise floor**, the score an
    exact, unbiased method with the truth's variance gets at the methods' spp (its relMSE
    includes the reference's own noise, as every method's does). ``method_noise`` renders
    each method twice more and reports ``self_noise`` = relMSE(a, b)/2 at the metric
    resolution (≈ the method's own variance term).

    Returns a dict: ``cell`` (name), ``truth`` (the reference image), ``images`` (``truth``
    at spp, and each method), ``metrics`` {key: :func:`cell_metrics`}, ``floor`` (the truth at
    spp), ``truth_stats`` (the reference against itself: its contrast, mean), ``times``,
    ``errors`` {key: message} for methods whose scene failed to load (e.g. a model the plugin
    does not have), ``invalid`` {key: {"nonfinite": n, "negative": n}} (values of each method's
    render that were NaN/Inf, set to 0, or negative), ``tilts``, ``spp``, ``ref_spp``, ``block``,
    ``seed``.

    Seeds (``seed``, default :func:`cell_seed`): methods ``1000·seed + i`` (the same for every
    method: common random numbers), the reference ``+ 100 + i``, the floor render ``+ 500 + i``,
    ``method_noise`` ``+ 200 + i`` / ``+ 300 + i`` (i: the pass, ≤ 64 spp each).
    """
    import time

    log = log or (lambda *a: None)
    mfnormal.register()            # the plugin for the active variant
    seed = cell_seed(cell) if seed is None else int(seed)
    spp = int(spp) * cell.spp_factor
    block = cell.metric_block
    hf = cell.hf()
    maps = cell.maps(registered)
    out = {"cell": cell.name, "images": {}, "metrics": {}, "times": {}, "errors": {}, "invalid": {},
           "tilts": tilt_stats(hf), "spp": spp, "ref_spp": spp * ref_factor, "block": block,
           "self_noise": {}, "seed": seed}
    t0 = time.time()
    truth_scene = _truth_scene(cell, res, spp, max_depth)
    truth = render(truth_scene, spp * ref_factor, seed * 1000 + 100, pass_spp)
    out["times"]["truth_ref"] = time.time() - t0
    t0 = time.time()
    truth_lo = render(truth_scene, spp, seed * 1000 + 500, pass_spp)
    out["times"]["truth"] = time.time() - t0
    out["truth"] = truth
    out["images"]["truth"] = truth_lo
    out["floor"] = cell_metrics(truth_lo, truth, block)
    out["truth_stats"] = cell_metrics(truth, truth, block)
    log(f"  truth {out['times']['truth_ref']:.1f}+{out['times']['truth']:.1f} s, "
        f"floor relMSE {out['floor']['rel_mse']:.4g}")
    for m in methods:
        t0 = time.time()
        try:
            scene = mi.load_dict(cell.plane_scene(m, res, spp, max_depth, maps))
        except Exception as e:   # a candidate model that does not load: report it, go on
            out["errors"][m.key] = f"{type(e).__name__}: {str(e).strip().splitlines()[-1][:300]}"
            log(f"  {m.key}: {out['errors'][m.key]}")
            continue
        img, nonfinite, negative = render_counted(scene, spp, seed * 1000, pass_spp)
        out["times"][m.key] = time.time() - t0
        out["invalid"][m.key] = {"nonfinite": nonfinite, "negative": negative}
        out["images"][m.key] = img
        out["metrics"][m.key] = cell_metrics(img, truth, block)
        if method_noise:
            a = block_mean(render(scene, spp, seed * 1000 + 200, pass_spp), block)
            b = block_mean(render(scene, spp, seed * 1000 + 300, pass_spp), block)
            k = exposure_scale(block_mean(truth, block))
            out["self_noise"][m.key] = 0.5 * rel_mse(a * k, b * k)
        log(f"  {m.key:24s} relMSE {out['metrics'][m.key]['rel_mse']:.4g}  "
            f"({out['times'][m.key]:.1f} s)")
    return out
