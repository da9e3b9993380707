"""The macro normal (``macro_normal``): the base frame the models work in.

**The macro normal** (``macro_normal``): ``shading`` (default) keeps the base frame
``si.sh_frame``; for the default model, a camera on or below the shading plane that sees the
triangle (at a coarse mesh's rim the interpolated normal can face away from a triangle the camera
sees) sees the microsurface on the triangle instead, as ``geometric`` has it (:func:`turned_normal`;
in radiance mode: light tracing drops those paths itself, below). ``geometric`` makes the true
triangle normal ``si.n`` (oriented to the shading normal's side) the microsurface's macro normal,
and the interpolated shading normal, with the map on top of it, the facet ω_p: the base frame G
has n = si.n and s, t = ``sh_frame``'s s, t turned by the smallest rotation that takes the
shading normal to n (:class:`Macro`). Then

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

from mfnormal.surface.microsurface import COS_P_MIN
from mfnormal.surface.shading import ShadingPoint, tangent_rotation

MACRO_NORMALS = ("shading", "geometric")
#: ``eval`` in light tracing is the adjoint times ⟨b,n_s⟩⟨a,n_g⟩/(⟨a,n_s⟩⟨b,n_g⟩), capped here
#: (the ratio is ``ptracer``'s correction inverted; it only exceeds this within ~1e-6 of a horizon).
ADJOINT_MAX = 1e6
#: A camera below the shading plane sees the microsurface on the triangle where its cosine to the
#: triangle's normal is above this (:func:`turned_normal`): not where the two normals are the same but
#: for rounding (a plane's, cos ~1e-7), nor within 0.006° of the triangle's plane.
TURN_MIN_COS = 1e-4
#: si.n whose squared length is at most this (or not finite) is degenerate.
NORMAL_MIN2 = 1e-12


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

    def weigh(self, ctx, sp, value, b, b_m):
        """``value`` (``eval`` at ω_o = ``b``, ``b_m`` in G) times :meth:`adjoint` in light tracing."""
        k = self.adjoint(ctx, sp, b, b_m)
        return value if k is None else value * k

    def to_shading(self, ctx, sp, bs, weight) -> tuple:
        """A sample of the model in G, its direction in the shading frame (and its weight as
        :meth:`weigh` gives a value)."""
        wo_m = mi.Vector3f(bs.wo)          # a copy: assigning bs.wo writes into the struct
        bs.wo = self.from_macro(wo_m)
        return bs, self.weigh(ctx, sp, weight, bs.wo, wo_m)


def on_macro(si, macro: Macro, wp):
    """(si seen in G: its shading frame G, ω_i in G; ω_p turned into G) for the macro frame
    ``macro``."""
    g = macro.frame()
    si_g = mi.SurfaceInteraction3f(si)
    si_g.sh_frame = mi.Frame3f(si.to_world(g.s), si.to_world(g.t), si.to_world(g.n))
    si_g.wi = macro.to_macro(si.wi)
    return si_g, to_upper_hemisphere(macro.to_macro(wp))


def turned_normal(si):
    """(n, turned): with ``macro_normal="shading"``, the macro normal a camera at ``si.wi`` sees the
    microsurface on, in the shading frame: the shading normal (0, 0, 1), except where the camera is
    on or below the shading plane while the triangle faces it (cosine above TURN_MIN_COS: a coarse
    mesh's interpolated normal can face away from a triangle the camera sees, at an object's rim):
    there the triangle's normal (:func:`triangle_normal`), as ``macro_normal="geometric"`` has it.
    ``turned``: where it is."""
    n_g = triangle_normal(si)
    turned = (si.wi.z <= 0.0) & (dr.dot(si.wi, n_g) > TURN_MIN_COS)
    return dr.select(turned, n_g, mi.Vector3f(0, 0, 1)), turned


def _derivatives(sp, si) -> bool:
    """Whether the shading point ``sp`` at ``si`` carries derivatives (the map's, ``strength``'s, the
    nested BSDF's parameters', or the hit's). There the microsurface stays on the shading plane
    (:class:`ShadingMacro`): Dr.Jit 1.5 compiles ``mfnormal_prb``'s and Mitsuba's ``prb``'s
    forward-mode derivatives through the turned frame into invalid LLVM IR ("invalid redefinition
    of function")."""
    return sp.attached or dr.grad_enabled(si.wi, si.n, si.sh_frame.n) or sp.nested_attached()


class ShadingMacro:
    """``macro_normal="shading"``: the microsurface in ``si.sh_frame`` (its macro frame the null
    :class:`~mfnormal.surface.shading.ShadingFrame`); for a model that ``turns`` (the default's), a
    camera below the shading plane that sees the triangle sees the microsurface on the triangle
    (:func:`turned_normal`), where it would see nothing; in radiance mode only (light tracing's
    ``ptracer`` drops the paths whose camera side lies below the shading plane and above the
    triangle whatever the BSDF returns: module docstring, so the adjoint is unchanged), and where
    nothing carries derivatives (:func:`_derivatives`)."""

    name = "shading"

    def __init__(self, turns: bool = False):
        self.turns = turns

    def turning(self):
        """This macro normal for a model that sees the triangle from below the shading plane
        (``Model.turns_at_rims``)."""
        return ShadingMacro(turns=True)

    def shading_point(self, source, nested, ctx, si, active, nudge=None):
        wp, rotation, attached = source.facet_normal(si, active, nudge)
        plain = ShadingPoint(nested, ctx, si, wp, map_rotation=rotation, attached=attached,
                             nudged=nudge is not None)
        if not self.turns or ctx.mode != mi.TransportMode.Radiance or _derivatives(plain, si):
            return plain
        n, turned = turned_normal(si)
        macro = Macro(n)
        si_g, wp_g = on_macro(si, macro, wp)
        si_m = mi.SurfaceInteraction3f(si)
        frame, g = si.sh_frame, si_g.sh_frame
        si_m.sh_frame = mi.Frame3f(*(dr.select(turned, a, b)
                                     for a, b in ((g.s, frame.s), (g.t, frame.t), (g.n, frame.n))))
        si_m.wi = dr.select(turned, si_g.wi, si.wi)
        if rotation is not None:
            # (The map's tangent as decoded, in the shading plane, turned with it: no second lookup.)
            tx, ty, sign, ok = rotation
            turned_rotation = tangent_rotation(si_m.sh_frame, frame.to_world(mi.Vector3f(tx, ty, 0.0)), sign)
            rotation = tuple(dr.select(turned, a, b) for a, b in zip(turned_rotation[:3], rotation[:3])) + (
                ok & dr.select(turned, turned_rotation[3], True),)
        wp = dr.select(turned, wp_g, wp)
        return ShadingPoint(nested, ctx, si_m, wp, map_rotation=rotation, attached=attached,
                            nudged=nudge is not None, macro=macro)


class GeometricMacro:
    """``macro_normal="geometric"``: the microsurface on the true triangle (:class:`Macro`);
    ω_p, the interpolated normal with the map on top of it, turned into its frame G."""

    name = "geometric"

    def turning(self):
        """Itself: a camera that sees the triangle is above this macro normal."""
        return self

    def shading_point(self, source, nested, ctx, si, active, nudge=None):
        wp, rotation, _ = source.facet_normal(si, active)
        macro = Macro(triangle_normal(si))
        si_g, wp_g = on_macro(si, macro, wp)
        if source.tangents is not None and rotation is not None:
            tangent, sign = source.tangents.lookup(si, active)
            rotation = tangent_rotation(si_g.sh_frame, tangent, sign)
        return ShadingPoint(nested, ctx, si_g, wp_g, map_rotation=rotation, macro=macro)


def macro_normal(name: str):
    """The macro normal called ``name`` (``MACRO_NORMALS``)."""
    return {"shading": ShadingMacro, "geometric": GeometricMacro}[name]()
