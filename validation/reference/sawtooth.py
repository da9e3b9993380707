"""Brute-force ray tracer of the periodic sawtooth microsurface (docs/model.md §2.2).

An independent numpy reference for the tests: it shares no code with ``mfnormal``
and uses none of the closed-form λ / G1 / κ formulas. Everything it reports comes
from intersecting rays with the actual line segments of the microsurface.

Geometry
--------
Local frame with ω_g = +z; ω_p is the perturbed normal (cosθ_p = wp.z > 0). The
tangent facet normal ω_t is the horizontal unit vector opposite to where ω_p
leans, ω_t = normalize(−p_x, −p_y, 0). We use the orthonormal basis

    e_x = ω_t (across the grooves),  e_y = ω_g × ω_t (along the grooves),  e_z = ω_g,

and write (X, Y, Z) for coordinates in it. The microsurface is extruded along e_y,
so only the cross-section (X, Z) matters for intersections: a 3-D ray
o + s·d moves in the cross-section as (X, Z) + s·(d_X, d_Z) with the same
parameter s, whatever d_Y is. In this basis ω_p = (−sinθ_p, 0, cosθ_p).

One period k (width W = cotθ_p, crest height 1) consists of

- the p facet: the segment from (kW, 0) up to ((k+1)W, 1). It rises toward +X
  with slope tanθ_p, i.e. it descends toward −ω_t, and its outward normal is
  (−sinθ_p, cosθ_p) = ω_p;
- the t facet: the vertical wall X = kW from (kW, 1) down to (kW, 0), at the low
  end of the p facet, outward normal (1, 0) = ω_t, facing back toward that p facet.
  Its top is the crest where the previous period's p facet ends.

Heights h ∈ [0, 1] are measured from the wall foot; on both facets height is linear
in arc length, so uniform heights are uniform area. Facets are one-sided: a ray only
hits a segment from its outward side (the other side is inside the solid), and a
ray leaving a planar facet cannot hit that same facet again.
"""

from __future__ import annotations

import numpy as np

P, T = 0, 1  # facet ids
# Rays are started exactly at the crest height; nothing lies above it.
CREST = 1.0
# A hit closer than this (in ray parameter) to the ray origin is ignored.
T_EPS = 1e-12


class Sawtooth:
    """The sawtooth of a perturbed normal ``wp`` (3-vector, wp[2] > 0, not vertical)."""

    def __init__(self, wp):
        wp = np.asarray(wp, dtype=np.float64)
        wp = wp / np.linalg.norm(wp)
        self.wp = wp
        self.cos_p = wp[2]
        self.sin_p = np.hypot(wp[0], wp[1])
        assert self.cos_p > 0 and self.sin_p > 0, "sawtooth needs 0 < θ_p < 90°"
        # Cross-section basis (e_x = ω_t, e_y = along grooves, e_z = ω_g).
        self.ex = np.array([-wp[0], -wp[1], 0.0]) / self.sin_p
        self.ez = np.array([0.0, 0.0, 1.0])
        self.ey = np.cross(self.ez, self.ex)
        self.wt = self.ex.copy()
        self.W = self.cos_p / self.sin_p  # period width: the p facet rises by 1 over cotθ_p

        # Segments of period 0 as (start, end) in the cross-section.
        self.seg = {P: (np.array([0.0, 0.0]), np.array([self.W, CREST])),
                    T: (np.array([0.0, CREST]), np.array([0.0, 0.0]))}
        # Outward normal of a segment a→b: rotate (b − a) clockwise, so the solid
        # lies to the right when walking a→b (below the ramp, behind the wall).
        self.n2 = {}
        for m, (a, b) in self.seg.items():
            e = b - a
            self.n2[m] = np.array([-e[1], e[0]]) / np.linalg.norm(e)
        self.n3 = {m: n[0] * self.ex + n[1] * self.ez for m, n in self.n2.items()}
        self._check_geometry()

    def _check_geometry(self):
        # Facet normals are the ones the model names: ω_p and ω_t.
        assert np.allclose(self.n3[P], self.wp, atol=1e-12), (self.n3[P], self.wp)
        assert np.allclose(self.n3[T], self.wt, atol=1e-12)
        assert abs(self.n3[T][2]) < 1e-15  # vertical wall
        # The wall faces the p facet of its own period (which lies at X > 0).
        assert self.n2[T][0] > 0
        # Periodic and closed: the p facet ends at the crest where the next wall starts.
        assert np.allclose(self.seg[P][1], self.seg[T][0] + [self.W, 0.0])
        # Mean plane is horizontal: Σ (facet length × normal) over a period = (0, W),
        # i.e. A_p ω_p + A_t ω_t = ω_g per unit geometric area.
        total = sum(np.linalg.norm(b - a) * self.n2[m] for m, (a, b) in self.seg.items())
        assert np.allclose(total, [0.0, self.W], atol=1e-12), total

    # ------------------------------------------------------------------ helpers
    def to_cross(self, v):
        """(…, 3) local directions → (X, Y, Z) components in the sawtooth basis."""
        v = np.asarray(v, dtype=np.float64)
        return v @ self.ex, v @ self.ey, v @ self.ez

    def to_local(self, X, Y, Z):
        return X[..., None] * self.ex + Y[..., None] * self.ey + Z[..., None] * self.ez

    def point(self, m, h):
        """Cross-section point on facet m (period 0) at height h."""
        if m == P:
            return h * self.W, h
        return np.zeros_like(h), h

    # -------------------------------------------------------------- intersection
    def intersect(self, ox, oz, dx, dz, own=None):
        """Nearest front-facing hit of rays (ox, oz) + s (dx, dz) with the periodic surface.

        Origins are in the cross-section with 0 ≤ oz ≤ 1. ``own`` (facet id per ray,
        or None) is the facet of period 0 the ray starts on, excluded from the search.
        The surface lies in the band 0 ≤ Z ≤ 1, so every period the ray crosses while
        inside the band is a candidate. They are tested in travel order, starting one
        period behind the origin's; a ray stops searching one period after the first
        period where it found a hit (later periods lie further along the ray).
        Returns (hit, facet, period, s, h): hit mask, facet id, period index, ray
        parameter and hit height.
        """
        n = ox.shape[0]
        # Horizontal reach while inside the band: up to Z = 1 (rising) or Z = 0 (falling).
        with np.errstate(divide="ignore", invalid="ignore"):
            reach = np.where(dz > 0, (CREST - oz) / dz, np.where(dz < 0, oz / -dz, np.inf))
            x_end = np.where(dx == 0, ox, ox + dx * reach)
        step = np.where(dx < 0, -1, 1)
        k0 = np.floor(ox / self.W).astype(np.int64)
        # Periods to test, in travel order: k0 − step … k_end + step.
        with np.errstate(invalid="ignore"):
            k_end = np.floor(np.clip(x_end, -1e15, 1e15) / self.W)
        n_per = np.where(dx == 0, 1, np.abs(k_end - k0) + 1).astype(np.int64)

        best_s = np.full(n, np.inf)
        best_m = np.full(n, -1)
        best_k = np.zeros(n, dtype=np.int64)
        best_h = np.zeros(n)
        found_at = np.full(n, 2**62)
        idx = np.arange(n)
        j = -1
        while idx.size:
            k = k0[idx] + step[idx] * j
            oxi, ozi, dxi, dzi = ox[idx], oz[idx], dx[idx], dz[idx]
            for m, (a, b) in self.seg.items():
                ax, az = a[0] + k * self.W, a[1]
                ex, ez = b[0] - a[0], b[1] - a[1]
                nx, nz = self.n2[m]
                ok = dxi * nx + dzi * nz < 0  # one-sided facets
                denom = dxi * ez - dzi * ex
                ok &= denom != 0
                if own is not None:
                    ok &= ~((k == 0) & (own[idx] == m))
                safe = np.where(ok, denom, 1.0)
                rx, rz = ax - oxi, az - ozi
                s = (rx * ez - rz * ex) / safe
                u = (rx * dzi - rz * dxi) / safe  # position along the segment, 0..1
                ok &= (s > T_EPS) & (u >= 0) & (u <= 1) & (s < best_s[idx])
                sel = idx[ok]
                best_s[sel] = s[ok]
                best_m[sel] = m
                best_k[sel] = k[ok]
                best_h[sel] = az + u[ok] * ez
                found_at[sel] = np.minimum(found_at[sel], j)
            j += 1
            assert j < 10**6, "runaway intersection search"
            keep = (j <= n_per[idx]) & (j <= found_at[idx] + 1)
            idx = idx[keep]
        hit = best_m >= 0
        # A downward ray always hits the surface before Z = 0.
        assert np.all(hit | (dz > 0)), "a downward ray missed the surface"
        return hit, best_m, best_k, best_s, np.clip(best_h, 0.0, 1.0)

    # ------------------------------------------------------------ estimators
    def first_hit(self, w, n_rays, rng):
        """Shoot parallel rays arriving from direction w (travelling along −w).

        ``w`` is one direction (3,) or one per ray (n_rays, 3). Ray origins are at the
        crest height with horizontal offsets uniform over one period: a parallel beam
        crosses any horizontal line uniformly, so this samples the beam per unit
        geometric area (nothing lies above the crest). Returns (facet, h): the facet
        hit first (P or T) and the hit height in [0, 1].
        """
        wx, _, wz = self.to_cross(np.asarray(w, dtype=np.float64))
        assert np.all(wz > 0), "first_hit needs directions above the mean plane"
        ox = rng.uniform(0.0, self.W, n_rays)
        oz = np.full(n_rays, CREST)
        dx = np.broadcast_to(-wx, (n_rays,)).copy()
        dz = np.broadcast_to(-wz, (n_rays,)).copy()
        hit, m, _, _, h = self.intersect(ox, oz, dx, dz)
        assert hit.all()
        return m, h

    def visible(self, m, w, n_pts, rng):
        """Which of n_pts points, uniform in height on facet m, see direction w directly.

        A point sees w if its facet faces w (the other side is inside the solid) and
        the ray from it toward w leaves through the crest height without hitting any
        other facet. Returns (visible mask, heights).
        """
        wx, _, wz = self.to_cross(np.asarray(w, dtype=np.float64))
        h = rng.uniform(0.0, 1.0, n_pts)
        ox, oz = self.point(m, h)
        dx = np.full(n_pts, wx)
        dz = np.full(n_pts, wz)
        faces = wx * self.n2[m][0] + wz * self.n2[m][1] > 0
        if not faces or wz <= 0:
            return np.zeros(n_pts, dtype=bool), h
        hit, *_ = self.intersect(ox, oz, dx, dz, own=np.full(n_pts, m))
        return ~hit, h

    # ------------------------------------------------------------ path tracing
    def sample_reflection(self, m, d, kind, rng):
        """Reflect travel directions d (n, 3, sawtooth basis) off facet m."""
        n3 = np.array([self.n2[m][0], 0.0, self.n2[m][1]])  # facet normal in (X, Y, Z)
        if kind == "mirror":
            return d - 2.0 * (d @ n3)[:, None] * n3
        assert kind == "lambert"
        # Cosine-weighted direction about the 3-D facet normal (Malley's method).
        k = d.shape[0]
        r = np.sqrt(rng.uniform(0.0, 1.0, k))
        phi = rng.uniform(0.0, 2.0 * np.pi, k)
        a, b = r * np.cos(phi), r * np.sin(phi)
        c = np.sqrt(np.maximum(0.0, 1.0 - r * r))
        # Orthonormal tangents of the facet: e_y is along the grooves, so it lies in
        # every facet plane; the second tangent is n × e_y.
        t1 = np.array([0.0, 1.0, 0.0])
        t2 = np.cross(n3, t1)
        return a[:, None] * t1 + b[:, None] * t2 + c[:, None] * n3


def trace_paths(wi, wp, n, rng, facet_p="lambert", facet_t="lambert", max_bounces=1000):
    """Trace n light paths into the sawtooth from direction wi (albedo-1 facets).

    Rays arrive from ``wi`` (travel direction −wi; one direction (3,) or one per path
    (n, 3)) at uniformly random offsets of one period and are followed through the
    microsurface. At every facet hit the travel direction d is replaced by

    - ``'mirror'``: the 3-D mirror image d − 2⟨d,ω_m⟩ω_m. ω_m lies in the
      cross-section plane, so the along-groove component d_Y is preserved;
    - ``'lambert'``: a fresh cosine-weighted direction about the 3-D facet normal ω_m
      (albedo 1, so no weight). d_Y is resampled with it.

    Intersections use only the cross-section motion (d_X, d_Z) of the 3-D unit
    direction, with the same ray parameter; d_Y only moves the ray along the grooves,
    where the surface is invariant. A path ends when its ray leaves through the crest
    height without a hit.

    Returns (wo, bounces): exit directions (n, 3) in the local frame (unit, pointing
    away from the surface) and the number of facet reflections per path. Paths still
    inside after ``max_bounces`` reflections get wo = NaN and bounces = max_bounces + 1.
    """
    st = Sawtooth(wp)
    kinds = {P: facet_p, T: facet_t}
    X, Y, Z = st.to_cross(np.asarray(wi, dtype=np.float64))
    assert np.all(Z > 0), "wi must be above the mean plane"
    m, h = st.first_hit(wi, n, rng)
    d = -np.stack(np.broadcast_arrays(X, Y, Z), axis=-1) * np.ones((n, 1))
    bounces = np.zeros(n, dtype=np.int64)
    wo = np.full((n, 3), np.nan)
    alive = np.arange(n)
    while alive.size and bounces[alive[0]] < max_bounces:
        # Reflect every live path at its current facet.
        dm = d[alive]
        for facet, kind in kinds.items():
            sel = m[alive] == facet
            if sel.any():
                dm[sel] = st.sample_reflection(facet, dm[sel], kind, rng)
        # Reflected directions leave their facet on its outward side.
        n_hit = np.where((m[alive] == P)[:, None], [st.n2[P][0], 0.0, st.n2[P][1]], [1.0, 0.0, 0.0])
        assert np.all(np.einsum("ij,ij->i", dm, n_hit) >= -1e-12)
        d[alive] = dm
        bounces[alive] += 1
        # Trace from the hit point (moved back to period 0) to the next facet.
        oz = h[alive]
        ox = np.where(m[alive] == P, oz * st.W, 0.0)
        hit, m_new, _, _, h_new = st.intersect(ox, oz, dm[:, 0], dm[:, 2], own=m[alive])
        # Escaped paths leave along their last direction.
        out = alive[~hit]
        wo[out] = st.to_local(d[out, 0], d[out, 1], d[out, 2])
        m[alive[hit]] = m_new[hit]
        h[alive[hit]] = h_new[hit]
        alive = alive[hit]
    bounces[alive] = max_bounces + 1
    return wo, bounces


def lambda_p(w, wp, n_rays, rng):
    """Monte Carlo λ_p(ω): fraction of parallel rays from ω that hit the p facet first."""
    m, _ = Sawtooth(wp).first_hit(w, n_rays, rng)
    return np.mean(m == P)


def G1(w, wp, facet, n_pts, rng):
    """Monte Carlo G1(ω, m): fraction of facet m's height range directly visible from ω."""
    vis, _ = Sawtooth(wp).visible(facet, w, n_pts, rng)
    return np.mean(vis)
