r"""How far one Gaussian of a footprint's slopes (LEAN mapping) is from the texels it stands for.

    python -m benchmarks.lean [--out DIR]

A pixel far away covers a whole map; what it converges to is the map's texels shaded one by one
and averaged. LEAN mapping (Olano and Baker, I3D 2010) replaces them by one facet, the normal of
their mean slope, whose microfacet roughness is widened by their slope variance:
α' = √(α² + σ_x² + σ_y²) for a Beckmann distribution (α² = 2σ² per axis). This measures the two
on a nested rough conductor (Beckmann, α 0.05 and 0.3, Mitsuba's ``roughconductor``), each texel
shaded classically (the nested BSDF in its own frame, ⟨ω_o, n⟩ included, no neighbours):

- **texels**: the mean of the nested f·cos over 2^16 points of the map (bilinear lookups);
- **LEAN**: the nested BSDF with α' on the mean slope's facet, its moments read from the top
  level of the map's slope-moment pyramid (:mod:`mfnormal.normals.pyramid`);
- **with a flat share**: two such lobes, one for the texels whose slope is within α/2 of flat and
  one for the rest, each on its own mean slope with its own variance, weighted by their shares (a
  candidate for maps whose slopes are not one Gaussian).

Two 256² maps, each at ``strength`` 0.3 and 1: ``bumps``, spherical caps on a grid with flat ground
between them (a panel with rivets, a tiled floor), and ``noise``, a smooth Gaussian random
height field (slopes close to Gaussian, what LEAN assumes). Directions: the mirror
configuration at 30° and 60° from the normal (the flat ground's highlight), and an off-specular
pair. Writes ``lean.json`` into ``--out`` (default ``out/benchmarks``) and prints the table.
"""

from __future__ import annotations

import argparse
import json
import math
from pathlib import Path

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np

from mfnormal.normals.pyramid import SlopePyramid
from mfnormal.surface.microsurface import decode_normal

SIZE = 256
QUERIES = 1 << 16
DIRECTIONS = {           # (ω_i, ω_o), unnormalised
    "mirror 30°": ((0.0, -0.5, 0.866), (0.0, 0.5, 0.866)),
    "mirror 60°": ((0.0, -0.866, 0.5), (0.0, 0.866, 0.5)),
    "off-specular": ((0.2, -0.3, 0.93), (0.5, 0.4, 0.77)),
}


def bumps(cells=8, radius=0.45):
    """Spherical caps of ``radius`` cells on a ``cells`` × ``cells`` grid, flat between them (RGB)."""
    x = (np.arange(SIZE) + 0.5) / SIZE * cells
    fx, fy = np.meshgrid(x % 1.0 - 0.5, x % 1.0 - 0.5)
    r2 = fx * fx + fy * fy
    inside = r2 < radius * radius
    z = np.sqrt(np.maximum(radius * radius - r2, 1e-6))            # the sphere's outward normal
    n = np.where(inside[..., None], np.stack([fx, fy, z], -1), np.array([0.0, 0.0, 1.0]))
    return 0.5 * n / np.linalg.norm(n, axis=-1, keepdims=True) + 0.5


def noise(seed=3, smooth=4.0, rms=0.35):
    """The normals of a smooth Gaussian random height field (periodic) with rms slope ``rms``."""
    rng = np.random.default_rng(seed)
    k = np.fft.fftfreq(SIZE) * SIZE
    kx, ky = np.meshgrid(k, k)
    spectrum = np.exp(-(kx * kx + ky * ky) / (2 * smooth * smooth))
    h = np.real(np.fft.ifft2(np.fft.fft2(rng.normal(size=(SIZE, SIZE))) * spectrum))
    gy, gx = np.gradient(h)
    scale = rms / math.sqrt(np.mean(gx * gx + gy * gy) / 2.0)
    n = np.stack([-gx * scale, -gy * scale, np.ones_like(h)], -1)
    return 0.5 * n / np.linalg.norm(n, axis=-1, keepdims=True) + 0.5


def frame_of(n):
    """A shading frame around the normals ``n`` (a Vector3f)."""
    s, t = mi.coordinate_system(n)
    return mi.Frame3f(s, t, n)


def nested_value(alpha, normals, wi, wo):
    """Mean over the lanes of the RGB-mean f·cos of a Beckmann conductor of ``alpha`` on facets ``normals``."""
    bsdf = mi.load_dict({"type": "roughconductor", "distribution": "beckmann", "alpha": alpha})
    width = dr.width(normals)
    si = dr.zeros(mi.SurfaceInteraction3f, width)
    frame = frame_of(normals)
    si.sh_frame = frame
    si.wi = frame.to_local(mi.Vector3f(*wi))
    value = bsdf.eval(mi.BSDFContext(), si, frame.to_local(mi.Vector3f(*wo)), si.wi.z > 0)
    return float(np.mean(np.array((value[0] + value[1] + value[2]) / 3.0)))


def case(rgb, strength, alpha, wi, wo):
    """(texels, LEAN, LEAN with a flat share, rms slope per axis) for one map, strength, α and
    direction pair."""
    texture = mi.load_dict({"type": "bitmap", "bitmap": mi.Bitmap(rgb.astype(np.float32)), "raw": True})
    rng = np.random.default_rng(0)
    si = dr.zeros(mi.SurfaceInteraction3f, QUERIES)
    si.uv = mi.Point2f(*(rng.random((2, QUERIES)).astype(np.float32)))
    texels = nested_value(alpha, decode_normal(texture.eval_3(si), strength, False), wi, wo)
    pyramid = SlopePyramid(mi.traverse(texture)["data"], mi.Float(strength), False)
    sx, sy, sxx, syy, sxy = pyramid.level(pyramid.top)[0, 0]
    spread = max(sxx - sx * sx, 0.0) + max(syy - sy * sy, 0.0)
    lean = _lobe(alpha, (sx, sy), spread, wi, wo)
    return texels, lean, _flat_share(texture, strength, alpha, wi, wo), math.sqrt(spread / 2.0)


def _lobe(alpha, mean, spread, wi, wo):
    """The nested f·cos on the facet of slope ``mean`` with α widened by the slope ``spread``."""
    facet = dr.normalize(mi.Vector3f(-float(mean[0]), -float(mean[1]), 1.0))
    return nested_value(math.sqrt(alpha * alpha + spread), facet, wi, wo)


def _flat_share(texture, strength, alpha, wi, wo):
    """Two lobes instead of one: the texels whose slope is within α/2 of flat and the others, each
    as LEAN's one Gaussian (its mean slope, α widened by its variance), weighted by their shares."""
    si = dr.zeros(mi.SurfaceInteraction3f, SIZE * SIZE)
    centres = (np.arange(SIZE) + 0.5) / SIZE
    u, v = np.meshgrid(centres, centres)
    si.uv = mi.Point2f(u.ravel().astype(np.float32), v.ravel().astype(np.float32))
    n = decode_normal(texture.eval_3(si), strength, False)
    s = -np.stack([np.array(n.x), np.array(n.y)], -1) / np.array(n.z)[:, None]
    flat = np.hypot(s[:, 0], s[:, 1]) < 0.5 * alpha
    value = 0.0
    for part in (flat, ~flat):
        if part.any():
            mean = s[part].mean(0)
            spread = float(np.sum(s[part].var(0)))
            value += part.mean() * _lobe(alpha, mean, spread, wi, wo)
    return value


def measure() -> list:
    """Every case of the module docstring: dicts of map, strength, sigma (rms slope per axis), alpha,
    directions, texels, lean."""
    rows = []
    for name, rgb in (("bumps", bumps()), ("noise", noise())):
        for strength in (0.3, 1.0):
            for alpha in (0.05, 0.3):
                for label, (wi, wo) in DIRECTIONS.items():
                    wi_n, wo_n = (tuple(float(x) for x in np.array(w) / np.linalg.norm(w)) for w in (wi, wo))
                    texels, lean, two, sigma = case(rgb, strength, alpha, wi_n, wo_n)
                    rows.append({"map": name, "strength": strength, "sigma": sigma, "alpha": alpha,
                                 "directions": label, "texels": texels, "lean": lean, "flat_share": two})
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--out", type=Path, default=Path("out/benchmarks"))
    args = parser.parse_args(argv)
    mi.set_variant("llvm_ad_rgb")
    out = args.out
    out.mkdir(parents=True, exist_ok=True)
    rows = measure()
    print("| map | strength | rms slope per axis | α | directions | texels | LEAN / texels | with a flat share / texels |")
    print("|---|---|---|---|---|---|---|---|")
    for r in rows:
        print(f"| {r['map']} | {r['strength']} | {r['sigma']:.3f} | {r['alpha']} | {r['directions']} "
              f"| {r['texels']:.4g} | {r['lean'] / r['texels']:.3g} | {r['flat_share'] / r['texels']:.3g} |")
    (out / "lean.json").write_text(json.dumps(rows, indent=1))
    print(f"wrote {out / 'lean.json'}")


if __name__ == "__main__":
    main()
