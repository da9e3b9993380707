"""Reference: Mitsuba's own ray tracer on a real triangle mesh of the sawtooth microsurface.

An independent reference for the tests of ``normalmap_microfacet``: it imports
``mfnormal`` only so that a working libLLVM is selected, and uses none of the
package's model code and none of the closed-form λ / G1 / κ formulas. The
reflectance of the microgeometry is measured by shooting rays at an actual mesh
with ``scene.ray_intersect`` and scattering them with the facets' own Mitsuba
BSDFs (``si.bsdf().sample``) until they escape.

Geometry (docs/model.md §2.2)
------------------------------
All directions are in the *tilt frame*: ω_g = +z and ω_p leans toward +x,
ω_p = (sinθ_p, 0, cosθ_p). The tangent facet normal is ω_t = normalize(−p_x, −p_y, 0)
= (−1, 0, 0). The cross-section basis of ``sawtooth.py`` is

    e_X = ω_t,  e_Y = ω_g × ω_t = (0, −1, 0),  e_Z = ω_g,

a right-handed basis, so cross products (face normals) carry over unchanged.
Period k (width W = cotθ_p, crest height 1) is, in (X, Z):

- the p facet from (kW, 0) up to ((k+1)W, 1): it descends toward −ω_t with slope
  tanθ_p and its outward normal is ω_p;
- the t facet, the vertical wall X = kW from Z = 0 to Z = 1 at the low end of that
  p facet, with outward normal ω_t (facing back toward it).

Both are extruded along e_Y into long quads (two triangles each) and kept as two
separate meshes, each with its own BSDF. :class:`SawtoothScene` asserts the face
normals Mitsuba computes for every triangle.

Tracing
-------
Rays arrive from ω_i (they travel along −ω_i) and start just above the crest, at
horizontal offsets uniform over one period: a parallel beam crosses any horizontal
line uniformly, so this samples the beam per unit geometric area. At every hit the
hit shape's BSDF samples the continuation (``bsdf.sample(ctx, si, u1, u2)``) and the
throughput is multiplied by its weight; a ray that finds no hit has escaped.

The surface is invariant under translations by whole periods across the grooves
and by any distance along them. Before each new ray is spawned, the hit point is
translated by such a symmetry back into the central period (X ∈ [0, W), Y = 0).
This changes nothing about the geometry the ray sees, but keeps every coordinate
small however far a ray travels along a groove, so float32 positions stay accurate
to ~1e-7. The new ray starts SPAWN_OFFSET = 1e-5 off the facet, on the side it
leaves to. (``si.spawn_ray`` would offset by ~1e-4·(1 + |p|): in the concave corner
at a wall's foot that starts ~1.5e-4 of all rays (θ_p = 60°) behind the other
facet; ``trace(..., offset=None)`` uses it.) Rays that hit a facet from inside or
slip through an edge are counted as ``leaked`` and dropped: ≤ 1.5e-5 of the rays. The
mesh extends ±200 periods across and ±10⁴ crest heights along the grooves, far
beyond the central region the rays start from.
"""

from __future__ import annotations

import os
from dataclasses import dataclass

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np

from validation.reference.arrays import floats, uints, vec3

#: The variant it renders in: the test suite's (``MFNORMAL_VARIANT``, tests/variant.py), by default
#: ``llvm_ad_rgb``.
VARIANT = os.environ.get("MFNORMAL_VARIANT", "").strip() or "llvm_ad_rgb"
# Ray origins start this far above the crest (nothing lies above Z = 1).
START_ABOVE = 1e-2
# Distance by which a new ray starts off its facet (crest height 1; hit points are
# accurate to ~1e-7, so this avoids self-intersection with a 100× margin).
SPAWN_OFFSET = 1e-5

WHITE_DIFFUSE = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}
# A perfect mirror with reflectance 1 and no Fresnel term: the specular tangent facet.
MIRROR = {"type": "conductor", "material": "none"}


def set_variant():
    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)


def sph(theta_deg, phi_deg=0.0):
    """Unit direction with polar angle θ and azimuth φ (degrees), in the tilt frame."""
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


def rotate_z(v, angle):
    """Rotate (…, 3) vectors about +z by ``angle`` radians."""
    v = np.asarray(v, np.float64)
    c, s = np.cos(angle), np.sin(angle)
    return np.stack([c * v[..., 0] - s * v[..., 1], s * v[..., 0] + c * v[..., 1], v[..., 2]], -1)


def _vec3(a):
    return vec3(a)


def _np3(v):
    return np.array(v, dtype=np.float64).reshape(3, -1).T


def _gray(spectrum):
    """Mean of the rgb channels of a Dr.Jit colour, as float64 numpy (n,)."""
    return np.array(spectrum, dtype=np.float64).reshape(3, -1).mean(axis=0)


# -- The mesh --------------------------------------------------------------------------------


class SawtoothScene:
    """A Mitsuba scene of the sawtooth microsurface of tilt ``theta_p_deg`` (0 < θ_p < 90°).

    ``p_bsdf`` and ``t_bsdf`` are Mitsuba BSDF dicts for the p facets and the t walls.
    Attributes: ``scene``, ``p_mesh``, ``t_mesh``, ``p_shape`` (a ``ShapePtr`` to compare
    ``si.shape`` with), ``wp``, ``wt``, ``eX``, ``eY``, ``eZ`` (tilt frame) and the period ``W``.
    """

    def __init__(self, theta_p_deg: float, p_bsdf: dict, t_bsdf: dict, half_periods: int = 200,
                 half_length: float = 1e4):
        set_variant()
        theta = np.radians(theta_p_deg)
        assert 0.0 < theta < 0.5 * np.pi
        self.cos_p, self.sin_p = np.cos(theta), np.sin(theta)
        self.W = self.cos_p / self.sin_p
        self.wp = np.array([self.sin_p, 0.0, self.cos_p])
        self.wt = np.array([-1.0, 0.0, 0.0])
        self.eX = self.wt
        self.eY = np.cross([0.0, 0.0, 1.0], self.eX)
        self.eZ = np.array([0.0, 0.0, 1.0])

        # One quad per period and facet, in cross-section coordinates (X, Y, Z).
        k = np.arange(-half_periods, half_periods, dtype=np.float64)[:, None]
        L = half_length
        x0, x1 = k * self.W, (k + 1) * self.W
        zero, one = np.zeros_like(k), np.ones_like(k)
        quad_p = np.stack([np.hstack([x0, -L * one, zero]), np.hstack([x1, -L * one, one]),
                           np.hstack([x1, L * one, one]), np.hstack([x0, L * one, zero])], 1)
        quad_t = np.stack([np.hstack([x0, -L * one, one]), np.hstack([x0, -L * one, zero]),
                           np.hstack([x0, L * one, zero]), np.hstack([x0, L * one, one])], 1)

        self.p_mesh = self._mesh("p_facets", quad_p, p_bsdf)
        self.t_mesh = self._mesh("t_facets", quad_t, t_bsdf)
        self._check_normals(self.p_mesh, self.wp)
        self._check_normals(self.t_mesh, self.wt)
        self.scene = mi.load_dict({"type": "scene", "p": self.p_mesh, "t": self.t_mesh})
        self.p_shape = mi.ShapePtr(self.p_mesh)

    def to_world(self, X, Y, Z):
        return X[..., None] * self.eX + Y[..., None] * self.eY + Z[..., None] * self.eZ

    def _mesh(self, name, quads, bsdf):
        n = quads.shape[0]
        verts = self.to_world(quads[..., 0], quads[..., 1], quads[..., 2]).reshape(-1, 3)
        base = 4 * np.arange(n, dtype=np.uint32)[:, None]
        faces = np.concatenate([base + [0, 1, 2], base + [0, 2, 3]]).astype(np.uint32)
        props = mi.Properties()
        props["bsdf"] = mi.load_dict(bsdf)
        mesh = mi.Mesh(name, verts.shape[0], faces.shape[0], props)
        params = mi.traverse(mesh)
        params["vertex_positions"] = floats(verts)
        params["faces"] = uints(faces)
        params.update()
        return mesh

    @staticmethod
    def _check_normals(mesh, normal):
        # Every triangle's face normal, as Mitsuba computes it, is the facet normal.
        n = _np3(mesh.face_normal(dr.arange(mi.UInt32, mesh.face_count())))
        assert n.shape[0] == mesh.face_count()
        err = np.max(np.linalg.norm(n - normal, axis=1))
        assert err < 1e-5, f"{mesh.id()}: face normals deviate from {normal} by {err}"


@dataclass
class Trace:
    """Result of :func:`trace`: one row per incident ray."""
    wo: np.ndarray           # (n, 3) exit direction, tilt frame (zero where the ray died)
    weight: np.ndarray       # (n,) throughput (mean of rgb); 0 for absorbed, leaked or capped rays
    first_is_p: np.ndarray   # (n,) bool: the first hit was a p facet
    bounces: np.ndarray      # (n,) number of facet hits
    leaked: int              # rays that hit a facet from inside or escaped downward (should be ~0)
    capped: int              # rays still on the surface after max_bounces (dropped)


def trace(geo: SawtoothScene, wi, n: int, seed: int = 0, max_bounces: int = 200,
          offset: float | None = SPAWN_OFFSET) -> Trace:
    """Trace ``n`` rays arriving from ``wi`` (tilt frame) through the microgeometry of ``geo``.

    One vectorised step per bounce, inside a Dr.Jit symbolic loop (a single kernel):
    ``scene.ray_intersect`` → ``si.bsdf().sample`` → throughput × weight → next ray from
    the hit point moved into the central period. Lanes stop when their ray escapes (no
    hit), their throughput is 0, or after ``max_bounces`` hits.

    ``offset`` is the distance by which a new ray's origin is pushed off its facet
    (toward the side the ray leaves to); ``None`` uses ``si.spawn_ray`` as is, whose
    offset of ~1e-4·(1 + |p|) makes ~1e-4 of the rays that bounce in a concave corner
    start behind the other facet (counted in ``leaked``).
    """
    set_variant()
    wi = np.asarray(wi, np.float64) / np.linalg.norm(wi)
    assert wi[2] > 0
    ctx = mi.BSDFContext()
    eX, eZ = mi.Vector3f(*map(float, geo.eX)), mi.Vector3f(*map(float, geo.eZ))
    W = dr.opaque(mi.Float, geo.W)
    p_shape = geo.p_shape
    scene = geo.scene

    # Parallel beam from ω_i, uniform over one period just above the crest
    rng = mi.PCG32(n, initstate=dr.opaque(mi.UInt64, seed), initseq=dr.arange(mi.UInt64, n))
    X = rng.next_float32() * W
    o = X * eX + (1.0 + START_ABOVE) * eZ
    ray = mi.Ray3f(o, dr.zeros(mi.Vector3f, n) + mi.Vector3f(*[dr.opaque(mi.Float, float(c)) for c in -wi]))

    def cond(ray, beta, active, bounce, first_p, wo, leaked, rng):
        return active

    def body(ray, beta, active, bounce, first_p, wo, leaked, rng):
        si = scene.ray_intersect(ray, active)
        hit = active & si.is_valid()
        first_p = dr.select(active & (bounce == 0), si.shape == p_shape, first_p)

        # Escaped rays are recorded; a ray leaving downward slipped through a facet or an
        # edge (~1e-7 of the rays graze the crest edge shared by the two meshes exactly)
        escaped = active & ~si.is_valid()
        wo = dr.select(escaped, ray.d, wo)
        leaked |= escaped & (ray.d.z <= 0)
        leaked |= hit & (dr.dot(si.n, ray.d) > 0)

        # Scatter with the hit facet's BSDF
        bsdf = si.bsdf(ray)
        u1 = rng.next_float32()
        u2 = mi.Point2f(rng.next_float32(), rng.next_float32())
        bs, w = bsdf.sample(ctx, si, u1, u2, hit)
        beta = dr.select(hit, beta * (w.x + w.y + w.z) / 3.0, beta)

        # Next ray from the hit point translated into the central period
        X = dr.dot(si.p, eX)
        Z = dr.dot(si.p, eZ)
        p = (X - dr.floor(X / W) * W) * eX + Z * eZ
        d = si.to_world(bs.wo)
        if offset is None:
            si_c = mi.SurfaceInteraction3f(si)
            si_c.p = p
            new_ray = si_c.spawn_ray(d)
        else:
            n_side = dr.mulsign(mi.Vector3f(si.n), dr.dot(si.n, d))
            new_ray = mi.Ray3f(p + offset * n_side, d)
        ray = dr.select(hit, new_ray, ray)
        bounce = dr.select(hit, bounce + 1, bounce)
        ok = hit & (beta > 0) & dr.isfinite(beta)
        beta = dr.select(ok | escaped, beta, 0.0)
        active = ok & (bounce < max_bounces)
        return ray, beta, active, bounce, first_p, wo, leaked, rng

    state = (ray, dr.ones(mi.Float, n), dr.full(mi.Bool, True, n), dr.zeros(mi.UInt32, n),
             dr.zeros(mi.Bool, n), dr.zeros(mi.Vector3f, n), dr.zeros(mi.Bool, n), rng)
    ray, beta, active, bounce, first_p, wo, leaked, rng = dr.while_loop(state, cond, body)

    wo = _np3(wo)
    bounce = np.array(bounce, np.int64)
    escaped = np.any(wo != 0, axis=1)
    leaked = np.array(leaked, bool)
    weight = np.where(escaped & ~leaked, np.array(beta, np.float64), 0.0)
    capped = int(np.sum(~escaped & (bounce >= max_bounces) & (np.array(beta) > 0)))
    return Trace(wo, weight, np.array(first_p, bool), bounce, int(leaked.sum()), capped)


# -- The plugin ------------------------------------------------------------------------------


def plugin_sample(theta_p_deg: float, nested: dict, model: str, tangent_facet: str, wi, n: int,
                  seed: int = 1, phi_p: float = 0.0):
    """Sample ``normalmap_microfacet`` with a constant normal map ω_p and incident ``wi``.

    ``wi`` and the returned exit directions are in the tilt frame; the plugin itself
    sees the tilt frame rotated by ``phi_p`` about ω_g (ω_p tilted toward azimuth
    ``phi_p`` of its shading frame), which exercises its facet frames. Returns
    (wo (n, 3), weight (n,)).
    """
    set_variant()
    mfnormal.register()
    wp = rotate_z(np.array([np.sin(np.radians(theta_p_deg)), 0.0, np.cos(np.radians(theta_p_deg))]), phi_p)
    tex = (0.5 * wp + 0.5).astype(np.float32).reshape(1, 1, 3)
    bsdf = mi.load_dict({"type": "normalmap_microfacet", "model": model, "tangent_facet": tangent_facet,
                         "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(tex), "raw": True,
                                       "filter_type": "nearest"},
                         "bsdf": nested})
    rng = np.random.default_rng(seed)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = _vec3(np.broadcast_to(rotate_z(wi, phi_p), (n, 3)))
    si.uv = mi.Point2f(0.5, 0.5)
    si.n = mi.Normal3f(0, 0, 1)
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    bs, w = bsdf.sample(mi.BSDFContext(), si, floats(rng.random(n, np.float32)),
                        mi.Point2f(floats(rng.random(n, np.float32)), floats(rng.random(n, np.float32))))
    wo = rotate_z(_np3(bs.wo), -phi_p)
    w = _gray(w)
    w = np.where(np.isfinite(w), w, 0.0)
    return wo, w


# -- Histograms ------------------------------------------------------------------------------


def histogram(wo, weight, n_cos: int = 8, n_phi: int = 8):
    """Throughput-weighted histogram of exit directions in cells of (cosθ, φ).

    Returns (mean, var), both (n_cos, n_phi): the fraction of incident energy leaving
    through each cell (per incident ray) and the variance of that estimate.
    cosθ ∈ [0, 1] and φ ∈ [0, 2π) (φ = 0 toward the tilt of ω_p) in equal steps.
    """
    wo = np.asarray(wo, np.float64)
    weight = np.asarray(weight, np.float64)
    n = weight.size
    ok = (weight != 0) & (wo[:, 2] > 0)
    ci = np.clip((wo[ok, 2] * n_cos).astype(np.int64), 0, n_cos - 1)
    phi = np.mod(np.arctan2(wo[ok, 1], wo[ok, 0]), 2.0 * np.pi)
    pj = np.clip((phi / (2.0 * np.pi) * n_phi).astype(np.int64), 0, n_phi - 1)
    cell = ci * n_phi + pj
    s1 = np.bincount(cell, weight[ok], n_cos * n_phi)
    s2 = np.bincount(cell, weight[ok] ** 2, n_cos * n_phi)
    mean = s1 / n
    var = np.maximum(s2 / n - mean ** 2, 0.0) / n
    return mean.reshape(n_cos, n_phi), var.reshape(n_cos, n_phi)


def compare_histograms(theta_p_deg: float, theta_i_deg: float, phi_i_deg: float, nested: dict,
                       tangent_facet: str, models=("nonseparable", "separable"), n: int = 1_000_000,
                       seed: int = 0, phi_p: float = 0.0, n_cos: int = 8, n_phi: int = 8) -> dict:
    """Ray-traced and model exit histograms for one configuration, for tests and plots.

    The microgeometry is the sawtooth of tilt ``theta_p_deg`` with ``nested`` on the p
    facets and, on the t walls, a perfect mirror (``tangent_facet='specular'``) or
    ``nested`` too (``'same'``). Light arrives from ω_i = (θ_i, φ_i) in the tilt frame
    (φ_i = 0: toward the direction ω_p leans, the side λ_p(ω_i) = 1; 180: the t side).
    ``n`` rays are traced through the mesh with Mitsuba and ``n`` samples drawn from
    each plugin model (``phi_p`` rotates the plugin's shading frame, see
    :func:`plugin_sample`).

    Returns a dict with
      - ``cos_edges`` (n_cos+1,), ``phi_edges`` (n_phi+1,) in radians: the cell edges;
      - ``reference``: (mean, var) from :func:`histogram` of the ray-traced exits;
      - one entry per model name: (mean, var) of the plugin's samples;
      - ``trace``: the :class:`Trace` (first-hit facets, bounces, leaked, capped);
      - ``wi``: ω_i in the tilt frame; ``l1``: {model: :func:`l1` distance to the reference}.
    Plot ``mean`` per cell (e.g. divided by the cell's solid angle, Δcosθ·Δφ, for the
    cosine-weighted BRDF f·cosθ_o) on polar axes.
    """
    t_bsdf = MIRROR if tangent_facet == "specular" else nested
    geo = SawtoothScene(theta_p_deg, nested, t_bsdf)
    wi = sph(theta_i_deg, phi_i_deg)
    tr = trace(geo, wi, n, seed=seed)
    out = {"cos_edges": np.linspace(0.0, 1.0, n_cos + 1),
           "phi_edges": np.linspace(0.0, 2.0 * np.pi, n_phi + 1),
           "reference": histogram(tr.wo, tr.weight, n_cos, n_phi), "trace": tr}
    for k, model in enumerate(models):
        wo, w = plugin_sample(theta_p_deg, nested, model, tangent_facet, wi, n, seed=seed + 1 + k,
                              phi_p=phi_p)
        out[model] = histogram(wo, w, n_cos, n_phi)
    out["wi"] = wi
    out["l1"] = {model: l1(out[model], out["reference"]) for model in models}
    return out


def z_scores(a, b):
    """Per-cell z of two (mean, var) histograms; cells where both are empty give 0."""
    (ma, va), (mb, vb) = a, b
    s = np.sqrt(va + vb)
    return np.where(s > 0, (ma - mb) / np.where(s > 0, s, 1.0), np.where(ma == mb, 0.0, np.inf))


def l1(a, b):
    """L1 distance Σ|a − b| of two histograms' means (twice the total-variation distance)."""
    return float(np.abs(a[0] - b[0]).sum())
