"""The two-facet microsurface of Schüßler et al. 2017 (docs/model.md §2.1-2.3).

Pure functions on Dr.Jit arrays of the active Mitsuba variant. Every direction is
expressed in the local frame whose +z axis is the geometric (base shading) normal
ω_g; directions point away from the surface.

- ``wp``: perturbed facet normal ω_p (unit, wp.z > 0);
- ``wt``: tangent facet normal ω_t, a vertical wall facing away from where ω_p
  leans; ``sin_p`` = sinθ_p is its area factor;
- λ_p, λ_t: probability that a ray from ω hits p or t first;
- G1(ω, ω_m): visible fraction of facet m seen from ω (Smith form, robust t̃
  variant of docs/model.md §2.1: no division by sinθ_p).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

# Smallest cosθ_p we accept: steeper normals are clamped to this (docs/model.md §8).
COS_P_MIN = 0.02
# Below this sinθ_p the tangent facet has no area and ω_t is arbitrary.
SIN_P_EPS = 1e-7


def decode_normal(rgb, strength, directx):
    """Tangent-space normal from a raw normal-map texel, robust to bad texels.

    n = (2·rgb − 1) with x, y scaled by ``strength`` (and y negated for the
    DirectX convention), normalised, clamped so that cosθ_p ≥ COS_P_MIN.
    NaN/Inf/zero texels and normals pointing straight down decode to the flat
    normal (0, 0, 1).
    """
    n = mi.Vector3f(dr.fma(rgb[0], 2.0, -1.0),
                    dr.fma(rgb[1], 2.0, -1.0),
                    dr.fma(rgb[2], 2.0, -1.0))
    n.y = dr.select(directx, -n.y, n.y)
    n.x *= strength
    n.y *= strength
    return upper_unit(n, 1e-20)


def upper_unit(n, min_norm2):
    """``n`` normalised and clamped into the upper hemisphere as decoded normals are: NaN/Inf
    vectors and those with |n|² ≤ ``min_norm2`` give (0, 0, 1); cosθ below COS_P_MIN is raised
    to it, keeping the azimuth (straight down: (0, 0, 1))."""
    bad = negate(dr.isfinite(n.x) & dr.isfinite(n.y) & dr.isfinite(n.z))
    norm2 = dr.squared_norm(n)
    bad |= negate((norm2 > min_norm2) & dr.isfinite(norm2))
    n = dr.select(bad, mi.Vector3f(0, 0, 1), n)
    n = n * dr.rsqrt(dr.select(bad, 1.0, norm2))
    # Clamp into the upper hemisphere: keep the azimuth, limit the tilt.
    xy2 = dr.fma(n.x, n.x, n.y * n.y)
    lean = xy2 > 1e-30
    too_steep = n.z < COS_P_MIN
    scale = dr.sqrt((1.0 - COS_P_MIN * COS_P_MIN) / dr.select(lean, xy2, 1.0))
    clamped = mi.Vector3f(n.x * scale, n.y * scale, COS_P_MIN)
    n = dr.select(too_steep & lean, clamped, n)
    n = dr.select(too_steep & negate(lean), mi.Vector3f(0, 0, 1), n)
    return n


def tangent_facet(wp):
    """(ω_t, sinθ_p): the unit tangent-facet normal and the tilt's sine.

    ω_t = (−p_x, −p_y, 0)/sinθ_p; for ω_p = ω_g we return an arbitrary
    horizontal ω_t with sinθ_p = 0, which gives the tangent facet zero area.
    """
    sin_p = dr.sqrt(dr.fma(wp.x, wp.x, wp.y * wp.y))
    flat = sin_p < SIN_P_EPS
    inv = dr.select(flat, 0.0, dr.rcp(dr.maximum(sin_p, SIN_P_EPS)))
    wt = mi.Vector3f(dr.select(flat, 1.0, -wp.x * inv), -wp.y * inv, 0.0)
    return wt, dr.select(flat, 0.0, sin_p)


def replace_grad(a, b):
    """The value of ``a`` with the derivative of ``b`` (``dr.replace_grad``) in AD variants;
    ``a`` in the others (Dr.Jit 1.5's replace_grad crashes on scalar types). Without
    derivatives it is ``a`` itself: the terms in ``b`` cost nothing in primal kernels."""
    return dr.replace_grad(a, b) if dr.is_diff_v(a) and dr.is_diff_v(b) else a


def spread(value, width: int):
    """``value`` (one Dr.Jit value shared by every lane, e.g. a map-wide statistic or ``strength``)
    gathered onto ``width`` lanes where it carries derivatives: the same value, bit for bit, whose
    adjoint reverse mode sums over the lanes once, by one scatter into it inside the kernel. A size-1
    value used directly in wider operations gets its adjoint summed at every such use instead, each
    sum a reduction that ends a kernel. Without derivatives (or one lane): ``value`` itself."""
    if width <= 1 or not dr.is_jit_v(value) or not dr.grad_enabled(value) or dr.width(value) != 1:
        return value
    return dr.gather(type(value), value, dr.zeros(mi.UInt32, width))


def score(p):
    """p/detach(p): value 1, derivative dp/p. An estimator that takes a branch of probability p
    with detached random numbers multiplies by it, so that its derivative accounts for p's
    (the score-function term); a literal 1 without derivatives (nothing in primal kernels)."""
    ok = p > 0
    return replace_grad(mi.Float(1.0), dr.select(ok, p / dr.detach(dr.select(ok, p, 1.0)), 1.0))


def negate(mask):
    """Logical not that also works on the Python bools of scalar variants."""
    return dr.select(mask, False, True)


def _pos(x):
    return dr.maximum(x, 0.0)


def projected_area_sum(w, wp, wt, sin_p):
    """Ã(ω) = ⟨ω,ω_p⟩₊ + sinθ_p⟨ω,ω_t⟩₊ = cosθ_p · (a_p(ω) + a_t(ω))."""
    return _pos(dr.dot(w, wp)) + sin_p * _pos(dr.dot(w, wt))


def lambda_p(w, wp, wt, sin_p):
    """Probability that a ray arriving from direction ω hits the p facet first."""
    a_p = _pos(dr.dot(w, wp))
    total = a_p + sin_p * _pos(dr.dot(w, wt))
    return dr.select(total > 0, a_p / dr.select(total > 0, total, 1.0), 1.0)


def lambda_t(w, wp, wt, sin_p):
    """1 − λ_p(ω), computed directly (no cancellation when ω_p ≈ ω_g)."""
    a_p = _pos(dr.dot(w, wp))
    a_t = sin_p * _pos(dr.dot(w, wt))
    total = a_p + a_t
    return dr.select(total > 0, a_t / dr.select(total > 0, total, 1.0), 0.0)


def one_minus_G1_p(w, wp):
    """1 − G1(ω, ω_p) without cancellation: ⟨ω_xy, p_xy⟩₊ / ⟨ω, ω_p⟩ (1 where G1 = 0).

    From G1 = cosθ_p⟨ω,ω_g⟩/⟨ω,ω_p⟩ when ⟨ω,ω_t⟩ ≤ 0 and G1 = 1 otherwise; exact
    reciprocity of the analytic model rests on this small number (docs/model.md §3.3).
    """
    cos_p = dr.dot(w, wp)
    num = _pos(dr.fma(w.x, wp.x, w.y * wp.y))
    ok = (cos_p > 0) & (w.z > 0)
    return dr.select(ok, dr.minimum(num / dr.select(ok, cos_p, 1.0), 1.0), 1.0)


def G1(w, wm, wp, wt, sin_p):
    """Masking of facet ω_m (ω_p or ω_t) seen from ω: χ⁺⟨ω,ω_m⟩·min(1, cosθ_p⟨ω,ω_g⟩₊/Ã(ω))."""
    total = projected_area_sum(w, wp, wt, sin_p)
    g = wp.z * _pos(w.z) / dr.select(total > 0, total, 1.0)
    return dr.select((dr.dot(w, wm) > 0) & (total > 0), dr.minimum(g, 1.0), 0.0)


def G1_p(w, wp, wt, sin_p):
    return G1(w, wp, wp, wt, sin_p)


def G1_t(w, wp, wt, sin_p):
    return G1(w, wt, wp, wt, sin_p)


def flip_t(w, wt):
    """Mirror image across the tangent-facet plane: ω − 2⟨ω,ω_t⟩ω_t."""
    return w - 2.0 * dr.dot(w, wt) * wt


def facet_frame(wm):
    """Local frame of facet m: the minimal rotation taking ω_g = z to ω_m.

    Continuous in ω_m, identity at ω_m = z (docs/model.md §2.3); needs wm.z > -1.
    """
    k = dr.rcp(1.0 + wm.z)
    s = mi.Vector3f(1.0 - wm.x * wm.x * k, -wm.x * wm.y * k, -wm.x)
    t = mi.Vector3f(-wm.x * wm.y * k, 1.0 - wm.y * wm.y * k, -wm.y)
    return mi.Frame3f(s, t, wm)


# -- The sawtooth height map (docs/model.md §1, §2.2) --------------------------------
#
# Crest height 1; heights h ∈ [0, 1] measured from the foot of the t wall. A ray
# leaving facet m at height h with travel direction d hits the other facet at
# height κ_m(d)·h; κ = ∞ (or h' > 1) means it leaves the microsurface.
#
# The walk stores *depths below the crest*, D = 1 − h, not heights: every walk seen
# from grazing ω_i starts in the thin band [0, G1(ω_i)] under the crest, and G1 can
# be far below float32's spacing of 6e-8 under 1, where heights would round to the
# crest and bias the NEE weights (+18 % energy at θ_p = 89°, ω_i.z = 1e-6). In
# depth, h' = κh reads D' = κ·(D − τ) with τ = 1 − 1/κ: the ray leaves iff D < τ.

INF = float("inf")


def cot_p(wp, sin_p):
    """cotθ_p, huge but finite for the flat normal (the t facet then has no area)."""
    return wp.z / dr.maximum(sin_p, 1e-30)


def crest_map(on_p, d, wt, cot):
    """(τ, κ) for a ray leaving p (on_p) or t in travel direction d.

    A ray from depth D leaves the microsurface iff D < τ, and otherwise lands on
    the other facet at depth κ·(D − τ). With r = cotθ_p·d_z/|d_x| (d_x across the
    groove): toward the wall ahead of p, κ = 1 + r and τ = r/(1 + r); from t away
    from it, κ = 1/(1 − r) and τ = r; any other way the ray leaves (κ = τ = ∞).
    τ is computed from r directly, so it keeps full precision when tiny.
    """
    x = -dr.dot(d, wt)   # across-groove component, > 0 toward the wall ahead of p
    # Clamped finite: a flat normal (cot = 1e30) and a ray along the groove would give ±∞,
    # and then τ = ∞/∞ = NaN.
    r = dr.clip(cot * d.z / dr.maximum(dr.abs(x), 1e-30), -1e30, 1e30)
    to_wall = on_p & (x > 0)
    from_wall = negate(on_p) & (x < 0) & (r < 1.0)
    k_p = dr.maximum(1.0 + r, 1e-30)   # r > −1 above p's plane; the clamp catches rounding
    tau = dr.select(to_wall, r / k_p, dr.select(from_wall, r, INF))
    k = dr.select(to_wall, k_p, dr.select(from_wall, dr.rcp(dr.maximum(1.0 - r, 1e-30)), INF))
    return tau, k


def escape_fraction(lo, hi, tau):
    """|[lo, hi] ∩ [0, τ)| / |[lo, hi]| for depths: the chance that a ray from a uniform depth leaves.

    For a point interval (lo = hi, e.g. the crest seen from a grazing ω_i) it is
    1 if lo < τ, else 0.
    """
    frac = _pos(dr.minimum(hi, tau) - lo) / dr.maximum(hi - lo, 1e-30)
    return dr.select(hi > lo, dr.minimum(frac, 1.0), dr.select(lo < tau, 1.0, 0.0))


def land(lo, hi, tau, k):
    """Depth interval on the other facet reached by the rays from [lo, hi] that stay.

    [κ(lo − τ), κ(hi − τ)] clipped to [0, 1] and kept with lo ≤ hi (a rounding
    error can let a ray stay with D < τ; it then sits at the crest). For κ = ∞
    every ray leaves: the result is [0, 0] rather than NaN.
    """
    finite = k < INF
    k, tau = dr.select(finite, k, 1.0), dr.select(finite, tau, 0.0)
    hi_new = dr.clip(k * (hi - tau), 0.0, 1.0)
    lo_new = dr.minimum(_pos(k * (lo - tau)), hi_new)
    return dr.select(finite, lo_new, 0.0), dr.select(finite, hi_new, 0.0)


def overlap(a, b, lo, hi):
    """|[a, b] ∩ [lo, hi]|."""
    return dr.maximum(dr.minimum(b, hi) - dr.maximum(a, lo), 0.0)


def fraction_inside(a, b, lo, hi):
    """|[a, b] ∩ [lo, hi]| / |[a, b]|; for a point (a = b), whether it lies in [lo, hi]."""
    point = (a >= lo) & (a <= hi)
    return dr.select(b - a > 0, overlap(a, b, lo, hi) / dr.maximum(b - a, 1e-30),
                     dr.select(point, 1.0, 0.0))
