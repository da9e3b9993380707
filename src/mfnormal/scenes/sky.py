"""Procedural skies: lat-long environment maps with a horizon-to-zenith gradient, a ground and a sun.

:func:`envmap` is the one sky of the package: a :class:`Gradient` (its colours,
its shape towards the zenith, a hard or a smooth horizon) and an optional sun,
either a :class:`GlowSun` (a bright Gaussian blob with a soft glow, given by its
radiance) or a :class:`DiskSun` (a disk given by its irradiance). The presets are
the skies of the bundled scenes (:data:`DEMO`), of glTF models without lights
(:data:`GLTF`) and of the true-geometry harness (:data:`HAZY`, without a sun).

Layout: Mitsuba's ``envmap`` with identity ``to_world``: y is up, row 0 is the
zenith, the pixel at ``(u, v)`` looks along
``(sin θ sin φ, cos θ, −sin θ cos φ)`` with ``φ = 2π u``, ``θ = π v``.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

__all__ = ["Gradient", "GlowSun", "DiskSun", "DEMO", "GLTF", "HAZY", "directions", "envmap"]


@dataclass(frozen=True)
class Gradient:
    """``scale ·`` (the horizon colour blended into the zenith's by ``up^exponent``, up = the
    direction's y) above the horizon, ``scale · ground`` below it; ``horizon_blur`` > 0 blends
    the two over that much of ``up`` (0: a hard horizon)."""
    zenith: tuple
    horizon: tuple
    ground: tuple
    exponent: float = 1.0
    scale: float = 1.0
    horizon_blur: float = 0.0


@dataclass(frozen=True)
class GlowSun:
    """A Gaussian blob of ``radiance`` and angular size ``size_deg`` plus a soft glow (2·e^(−α/0.25)
    at angle α), centred on ``direction`` (world space, normalised here)."""
    direction: tuple = (-0.75, 0.34, -0.56)
    radiance: float = 700.0
    size_deg: float = 4.0


@dataclass(frozen=True)
class DiskSun:
    """A disk of ``radius_deg`` at ``elevation_deg`` above the horizon and ``azimuth_deg`` from +z
    toward +x, whose irradiance at normal incidence is ``irradiance``."""
    elevation_deg: float = 40.0
    azimuth_deg: float = -35.0
    irradiance: float = 3.0
    radius_deg: float = 3.0


#: The bundled scenes' sky: warm horizon, blue zenith, smooth horizon (~3°).
DEMO = Gradient(zenith=(0.22, 0.38, 0.8), horizon=(1.0, 0.95, 0.88), ground=(0.22, 0.19, 0.16),
                exponent=0.45, scale=0.7, horizon_blur=0.05)
#: The sky of glTF models without lights: a linear gradient, hard horizon, dark grey ground.
GLTF = Gradient(zenith=(0.25, 0.38, 0.70), horizon=(0.75, 0.78, 0.85), ground=(0.12, 0.11, 0.10),
                exponent=1.0, scale=0.6)
#: The true-geometry harness's sky: bright hazy horizon to blue zenith (√up), dark ground.
HAZY = Gradient(zenith=(0.30, 0.45, 0.80), horizon=(0.80, 0.83, 0.88), ground=(0.10, 0.09, 0.08),
                exponent=0.5, scale=0.5)


def _angles(width: int, height: int):
    """(θ, φ) of every pixel centre (height × width)."""
    u = (np.arange(width) + 0.5) / width
    v = (np.arange(height) + 0.5) / height
    phi, theta = np.meshgrid(2.0 * np.pi * u, np.pi * v)
    return theta, phi


def directions(width: int, height: int) -> np.ndarray:
    """World direction of every pixel centre of a lat-long map (height × width × 3)."""
    theta, phi = _angles(width, height)
    return np.stack([np.sin(theta) * np.sin(phi), np.cos(theta),
                     -np.sin(theta) * np.cos(phi)], axis=-1)


def _gradient(up: np.ndarray, g: Gradient) -> np.ndarray:
    t = np.clip(up, 0.0, 1.0) ** g.exponent
    sky = np.array(g.horizon) * (1.0 - t) + np.array(g.zenith) * t
    ground = np.array(g.ground)
    if g.horizon_blur > 0:
        w = np.clip(up / g.horizon_blur + 0.5, 0.0, 1.0)
        return g.scale * (sky * w + ground * (1.0 - w))
    return np.where(up > 0, sky, ground) * g.scale


def _glow(rgb: np.ndarray, d: np.ndarray, sun: GlowSun) -> np.ndarray:
    s = np.asarray(sun.direction, dtype=np.float64)
    s /= np.linalg.norm(s)
    ang = np.arccos(np.clip(d @ s, -1.0, 1.0)[..., None])
    sigma = np.radians(sun.size_deg)
    colour = np.array([1.0, 0.93, 0.82])
    return rgb + colour * (sun.radiance * np.exp(-0.5 * (ang / sigma) ** 2)
                           + 2.0 * np.exp(-ang / 0.25))     # blob + soft glow


def _disk(rgb: np.ndarray, d: np.ndarray, theta: np.ndarray, sun: DiskSun) -> np.ndarray:
    el, az = math.radians(sun.elevation_deg), math.radians(sun.azimuth_deg)
    s = np.array([math.sin(az) * math.cos(el), math.sin(el), math.cos(az) * math.cos(el)])
    disk = (d @ s) > math.cos(math.radians(sun.radius_deg))
    height, width = theta.shape
    pixel_sr = (2 * np.pi / width) * (np.pi / height) * np.sin(theta)
    irradiance = np.sum(pixel_sr[disk] * (d[disk] @ s))
    rgb[disk] = np.array([1.0, 0.95, 0.88]) * (sun.irradiance / irradiance)
    return rgb


def envmap(width: int, height: int | None = None, gradient: Gradient = DEMO, sun=None) -> np.ndarray:
    """Linear RGB radiance (height × width × 3, float32; height defaults to width / 2): the
    ``gradient`` sky and ground with an optional :class:`GlowSun` or :class:`DiskSun`."""
    height = width // 2 if height is None else height
    theta, _ = _angles(width, height)
    d = directions(width, height)
    rgb = _gradient(d[..., 1:2], gradient)
    if isinstance(sun, GlowSun):
        rgb = _glow(rgb, d, sun)
    elif isinstance(sun, DiskSun):
        rgb = _disk(rgb, d, theta, sun)
    return np.ascontiguousarray(rgb, dtype=np.float32)
