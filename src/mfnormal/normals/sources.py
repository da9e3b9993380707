"""Every source of shading normals (issue 17): height maps, and the true triangle as the macro surface.

The models work on a :class:`~mfnormal.models.shading.ShadingPoint`: a facet normal ω_p in a base
frame whose +z is the microsurface's macro normal ω_g. By default ω_p comes from a normal map
and the base frame is Mitsuba's shading frame ``si.sh_frame`` (``plugin.shading_point``). This
module adds the other inputs, without touching that path:

**Height maps** (``heightmap``, ``height_scale``): ω_p is the normal of the surface displaced by
``height_scale · strength · h(u, v)`` along the normal, the convention of Mitsuba's ``bumpmap``
(its ``scale``): with g = (∂h/∂u, ∂h/∂v) from the texture's ``eval_1_grad`` (a bilinear
bitmap's exact derivative, what ``bumpmap`` uses) and the tangent-plane parts a, b of
``si.dp_du``, ``si.dp_dv`` in the base frame, ω_p ∝ (a + g_u n) × (b + g_v n), oriented to +z:

    ω_p ∝ sign(J)·(g_v a_y − g_u b_y, g_u b_x − g_v a_x, J),   J = a_x b_y − a_y b_x

(:func:`height_normal`; the same normal as ``bumpmap``'s for the same texture and scale, tested).
With ``tangents="vertex_tangent"`` the derivative's directions are the vertex frame's T and
B = sign·(N×T) (B points to the image's up, −v, as MikkTSpace computed for (u, 1 − v) and as
Mitsuba's t does on a mesh with unmirrored UVs) and its lengths those of a, b:
ω_p ∝ (−g_u/|a|, g_v/|b|, 1) in T, B, N, the normal map a baker would derive from the same
heights in texture space (:func:`texture_space_normal`). Where the parametrisation is degenerate
(no UVs, a zero ``dp_du``), one uv unit is one world unit along s and −t. Non-finite gradients
give the flat normal; normals are clamped to cosθ_p ≥ ``COS_P_MIN`` as decoded maps are.

**The macro normal** (``macro_normal``): ``shading`` (default) keeps the base frame
``si.sh_frame``. ``geometric`` makes the true triangle normal ``si.n`` (oriented to the shading
normal's side) the microsurface's macro normal, and the interpolated shading normal, with the
map on top of it, the facet ω_p: the base frame G has n = si.n and s, t = ``sh_frame``'s s, t
turned by the smallest rotation that takes the shading normal to n (:class:`Macro`). Then

- ``eval`` returns f·⟨ω_o, si.n⟩: the cosine of the surface the light actually falls on. Mitsuba's
  path tracer multiplies the throughput by ``eval`` as is, so radiance is right with it;
- directions cross the frames on the way in and out (ω_i, ω_o and sampled directions stay in
  ``si.sh_frame``'s local coordinates for the integrator), pdfs are densities of directions and
  do not change;
- light tracing: Mitsuba's ``ptracer`` multiplies ``eval`` in ``TransportMode.Importance`` by
  Veach's shading-normal correction |⟨a,n_s⟩⟨b,n_g⟩ / (⟨b,n_s⟩⟨a,n_g⟩)| (a = si.wi, the light
  side; b = ω_o, the camera side) and drops paths where a direction lies on different sides of
  n_s and n_g. A microsurface on the true triangle needs no correction, so its adjoint is
  returned times the inverse, ⟨b,n_s⟩⟨a,n_g⟩ / (⟨a,n_s⟩⟨b,n_g⟩) (:meth:`Macro.adjoint`), and zero
  where ``ptracer`` drops the path anyway. Path tracing and light tracing then agree, except in
  that wedge, which ``ptracer`` leaves out and path tracing keeps.

With no map, ``macro_normal="geometric"`` is the microsurface of a smooth-shaded mesh: ω_p is
the interpolated normal on its triangle (the shadow-terminator case).
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mfnormal.models.microsurface import COS_P_MIN, negate, upper_unit
from mfnormal.models.shading import ShadingPoint, from_tangent_frame, tangent_rotation

MACRO_NORMALS = ("shading", "geometric")
#: ``eval`` in light tracing is the adjoint times ⟨b,n_s⟩⟨a,n_g⟩/(⟨a,n_s⟩⟨b,n_g⟩), capped here
#: (the ratio is ``ptracer``'s correction inverted; it only exceeds this within ~1e-6 of a horizon).
ADJOINT_MAX = 1e6
#: si.n whose squared length is at most this (or not finite) is degenerate.
NORMAL_MIN2 = 1e-12


def unit_normal(n):
    """``n`` normalised and clamped into the upper hemisphere as decoded maps are: non-finite or
    zero vectors give (0, 0, 1); cosθ below COS_P_MIN is raised to it, keeping the azimuth."""
    return upper_unit(n, 1e-30)


def _scaled(n):
    """``n`` divided by its largest component's magnitude (keeps float32 in range before normalising)."""
    m = dr.maximum(dr.maximum(dr.abs(n.x), dr.abs(n.y)), dr.abs(n.z))
    ok = (m > 0) & dr.isfinite(m)
    return dr.select(ok, n / dr.select(ok, m, 1.0), n)


def _tangent_parts(frame, dp_du, dp_dv):
    """(a, b, ok): dp_du and dp_dv in ``frame``'s local x, y (their tangent-plane parts) and
    where the parametrisation is usable (finite, |J| not negligible against |a||b|)."""
    a, b = frame.to_local(mi.Vector3f(dp_du)), frame.to_local(mi.Vector3f(dp_dv))
    a = mi.Vector2f(a.x, a.y)
    b = mi.Vector2f(b.x, b.y)
    j = a.x * b.y - a.y * b.x
    ok = dr.isfinite(j) & (dr.abs(j) > 1e-6 * dr.sqrt(dr.squared_norm(a) * dr.squared_norm(b))) & (j != 0)
    return a, b, j, ok


def height_normal(grad, frame, dp_du, dp_dv):
    """ω_p in ``frame`` (the base shading frame) of the surface displaced along its normal by a
    height of uv gradient ``grad`` (already scaled): Mitsuba ``bumpmap``'s normal (module docstring).
    A degenerate parametrisation uses one uv unit = one world unit along s and −t."""
    a, b, j, ok = _tangent_parts(frame, dp_du, dp_dv)
    a = dr.select(ok, a, mi.Vector2f(1.0, 0.0))
    b = dr.select(ok, b, mi.Vector2f(0.0, -1.0))
    j = dr.select(ok, j, -1.0)
    sgn = dr.select(j < 0, -1.0, 1.0)
    gu, gv = grad.x, grad.y
    n = mi.Vector3f(sgn * (gv * a.y - gu * b.y), sgn * (gu * b.x - gv * a.x), dr.abs(j))
    return unit_normal(_scaled(n))


def texture_space_normal(grad, frame, dp_du, dp_dv):
    """ω_p in the map's own tangent frame (T, B up the image, N) from the scaled uv gradient:
    (−g_u/|a|, g_v/|b|, 1) normalised, |a|, |b| the tangent-plane lengths of dp_du, dp_dv
    (1 where the parametrisation is degenerate)."""
    a, b, _, ok = _tangent_parts(frame, dp_du, dp_dv)
    la = dr.select(ok, dr.norm(a), 1.0)
    lb = dr.select(ok, dr.norm(b), 1.0)
    return unit_normal(_scaled(mi.Vector3f(-grad.x * lb, grad.y * la, la * lb)))


def triangle_normal(si):
    """si.n in ``si.sh_frame``'s local coordinates, unit, turned to the shading normal's side
    (z ≥ 0); (0, 0, 1) where it is degenerate (|si.n|² not finite or ≤ ``NORMAL_MIN2``: zero,
    NaN, or so long that float32 overflows)."""
    n = si.sh_frame.to_local(mi.Vector3f(si.n))
    len2 = dr.squared_norm(n)
    ok = (len2 > NORMAL_MIN2) & (len2 < math.inf)     # len2 ≥ 0: the isfinite test, one op less
    return dr.select(ok, n * dr.mulsign(dr.rsqrt(len2), n.z), mi.Vector3f(0, 0, 1))


def geometric_frame(si):
    """G, the frame of the true triangle normal in ``si.sh_frame``'s local coordinates: n =
    :func:`triangle_normal`, s and t the shading frame's x and y turned by the smallest rotation
    that takes its normal (z) to n (:class:`Macro`)."""
    return Macro(triangle_normal(si)).frame()


def to_upper_hemisphere(n):
    """A unit vector with cosθ below COS_P_MIN raised to it, keeping the azimuth (the clamp of
    decoded maps), for ``n`` not within 1e-15 of straight down (there it is not unit).

    :func:`shading_point` passes ω_p turned into G: ω_p lies within 88.9° of the shading normal
    (the clamp) and si.n within 90° of it, so ω_p is at most 178.9° from si.n and
    sin²θ ≥ 4e-4 (the decoded maps' test for no azimuth, and its select, cannot fire here)."""
    xy2 = dr.fma(n.x, n.x, n.y * n.y)
    scale = math.sqrt(1.0 - COS_P_MIN * COS_P_MIN) * dr.rsqrt(dr.maximum(xy2, 1e-30))
    return dr.select(n.z < COS_P_MIN, mi.Vector3f(n.x * scale, n.y * scale, COS_P_MIN), n)


class Macro:
    """The geometric macro frame G at a batch of shading points (``macro_normal="geometric"``):
    the rotation R by the smallest angle that takes z (the shading normal) to the triangle's
    normal n = (x, y, z), z ≥ 0, in the shading frame's local coordinates. With k = 1/(1 + z),
    R's columns are s = (1 − k x², −k x y, −x), t = (−k x y, 1 − k y², −y) and n; R and Rᵀ
    apply in 6-7 operations (they run on every query: benchmarks/normal_sources.py)."""

    def __init__(self, n):
        self.n = n
        self.k = dr.rcp(1.0 + n.z)

    def frame(self):
        x, y, k = self.n.x, self.n.y, self.k
        kxy = -k * x * y
        return mi.Frame3f(mi.Vector3f(dr.fma(-k * x, x, 1.0), kxy, -x),
                          mi.Vector3f(kxy, dr.fma(-k * y, y, 1.0), -y), self.n)

    def to_macro(self, w):
        """Rᵀ w: ``w`` (shading frame) in G."""
        x, y, z = self.n.x, self.n.y, self.n.z
        p = dr.fma(x, w.x, y * w.y)
        e = dr.fma(self.k, p, w.z)
        return mi.Vector3f(dr.fma(-x, e, w.x), dr.fma(-y, e, w.y), dr.fma(z, w.z, p))

    def from_macro(self, w):
        """R w: ``w`` (in G) in the shading frame."""
        x, y, z = self.n.x, self.n.y, self.n.z
        p = dr.fma(x, w.x, y * w.y)
        e = dr.fma(-self.k, p, w.z)
        return mi.Vector3f(dr.fma(x, e, w.x), dr.fma(y, e, w.y), dr.fma(z, w.z, -p))

    def adjoint(self, ctx, sp, b, b_m):
        """The factor of ``eval`` in light tracing (module docstring), None in radiance mode:
        ``sp`` the shading point (its ω_i = a in G), ``b`` = ω_o in the shading frame, ``b_m`` in G."""
        if ctx.mode != mi.TransportMode.Importance:
            return None
        a_m = sp.wi
        a = self.from_macro(a_m)
        valid = (a.z * a_m.z > 0) & (b.z * b_m.z > 0)
        den = a.z * b_m.z
        k = dr.abs(b.z * a_m.z) / dr.select(valid, dr.abs(den), 1.0)
        return dr.select(valid & dr.isfinite(k), dr.minimum(k, ADJOINT_MAX), 0.0)


def macro_of(sp):
    """The :class:`Macro` of a shading point, None for the shading frame."""
    return getattr(sp, "macro", None)


def _facet_normal(plugin, si, active):
    """(ω_p in si.sh_frame, the map frame's tangent_rotation or None) from the plugin's map:
    normal map, height map or none (the shading normal itself)."""
    from mfnormal.models.microsurface import decode_normal
    rotation = None
    if plugin.heightmap is not None:
        grad = mi.Vector2f(plugin.heightmap.eval_1_grad(si, active)) * (plugin.height_scale * plugin.strength)
        wp = height_normal(grad, si.sh_frame, si.dp_du, si.dp_dv)
        if plugin.tangent_attr is not None:
            tangent, sign = plugin._vertex_tangent(si, active)
            if tangent is not None:
                rotation = tangent_rotation(si.sh_frame, tangent, sign)
                ts = texture_space_normal(grad, si.sh_frame, si.dp_du, si.dp_dv)
                wp = dr.select(rotation[3], from_tangent_frame(ts, si.sh_frame, tangent, sign), wp)
        return wp, rotation
    if plugin.normalmap is not None:
        wp = decode_normal(plugin.map_rgb(si, active), plugin.strength, plugin.directx)
        if plugin.tangent_attr is not None:
            wp, rotation = plugin._from_vertex_tangents(si, wp, active)
        return wp, rotation
    return mi.Vector3f(0.0, 0.0, 1.0), None


def shading_point(plugin, ctx, si, active=True):
    """The microsurface at ``si`` for the inputs of this module (height map, geometric macro
    normal); ``plugin.shading_point`` hands over to it when either is set."""
    wp, rotation = _facet_normal(plugin, si, active)
    if not plugin.macro_geometric:
        sp = ShadingPoint(plugin.nested, ctx, si, wp)
        sp.map_rotation = rotation
        sp.macro = None
        return sp
    macro = Macro(triangle_normal(si))
    g = macro.frame()
    si_g = mi.SurfaceInteraction3f(si)
    si_g.sh_frame = mi.Frame3f(si.to_world(g.s), si.to_world(g.t), si.to_world(g.n))
    si_g.wi = macro.to_macro(si.wi)
    sp = ShadingPoint(plugin.nested, ctx, si_g, to_upper_hemisphere(macro.to_macro(wp)))
    if plugin.tangent_attr is not None and rotation is not None:
        tangent, sign = plugin._vertex_tangent(si, active)
        rotation = tangent_rotation(si_g.sh_frame, tangent, sign)
    sp.map_rotation = rotation
    sp.macro = macro
    return sp


# -- The map's slopes for the faithful model -----------------------------------------------------

def height_map_normals(texture, scale: float, res: int):
    """Unit normals (N×3, numpy) of a height map on the unit square (one uv unit = one world unit
    along s and −t, the :func:`height_normal` fallback) at a ``res × res`` grid of cell centres:
    what ``plugin._map_slopes`` measures the faithful model's neighbourhood on."""
    u = (np.arange(res) + 0.5) / res
    uu, vv = np.meshgrid(u, u, indexing="ij")
    if dr.is_jit_v(mi.Float):
        si = dr.zeros(mi.SurfaceInteraction3f, res * res)
        si.uv = mi.Point2f(mi.Float(uu.ravel()), mi.Float(vv.ravel()))
        g = texture.eval_1_grad(si)
        gu, gv = np.array(g.x, np.float64) * scale, np.array(g.y, np.float64) * scale
    else:
        gu, gv = np.zeros(res * res), np.zeros(res * res)
        for k, (x, y) in enumerate(zip(uu.ravel(), vv.ravel())):
            s1 = mi.SurfaceInteraction3f()
            s1.uv = mi.Point2f(float(x), float(y))
            g = texture.eval_1_grad(s1)
            gu[k], gv[k] = float(g[0]) * scale, float(g[1]) * scale
    n = np.stack([-gu, gv, np.ones_like(gu)], -1)
    n[~np.all(np.isfinite(n), 1)] = [0.0, 0.0, 1.0]
    return n / np.linalg.norm(n, axis=1, keepdims=True)
