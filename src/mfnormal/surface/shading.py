"""One shading point seen as a two-facet microsurface, with the nested BSDF on its facets.

The models (``analytic``, ``walk``) work on a :class:`ShadingPoint`: directions in
the base shading frame (ω_g = +z), the facet normals ω_p and ω_t, their frames,
and the nested BSDF evaluated or sampled in a facet's frame.
"""

from __future__ import annotations

import copy
import dataclasses
from typing import Protocol, runtime_checkable

import drjit as dr
import mitsuba as mi

from mfnormal.surface import microsurface as ms


def tangent_rotation(frame, tangent, sign):
    """(tx, ty, s, ok): the vertex tangent frame T, B = sign·(N×T), N in ``frame``'s local
    coordinates, T = (tx, ty, 0), s = ±1; ok where T is usable (not zero, not parallel to N)."""
    t = frame.to_local(tangent)
    len2 = dr.fma(t.x, t.x, t.y * t.y)
    ok = (len2 > 1e-6 * dr.squared_norm(t)) & (len2 > 0.0)
    inv = dr.rsqrt(dr.select(ok, len2, 1.0))
    return t.x * inv, t.y * inv, dr.select(sign < 0.0, -1.0, 1.0), ok


def from_tangent_frame(wp, frame, tangent, sign):
    """ω_p decoded in a vertex tangent frame, re-expressed in ``frame`` (the base shading frame).

    The tangent frame is MikkTSpace's and glTF's: T = ``tangent`` (world space,
    e.g. interpolated per vertex) made orthogonal to N = ``frame.n``,
    B = sign·(N×T), N. Both frames share N, so only x and y turn (or mirror,
    for sign < 0) and ω_p's tilt is kept. Where T is missing (zero) or
    parallel to N, ω_p is returned unchanged: the map is decoded in ``frame``.
    """
    return from_tangent_rotation(wp, tangent_rotation(frame, tangent, sign))


def from_tangent_rotation(w, rotation):
    """``w`` given in the vertex tangent frame, in the base frame: the inverse of
    :func:`to_tangent_frame` (``rotation`` from :func:`tangent_rotation`)."""
    tx, ty, s, ok = rotation
    # In local coordinates N = (0, 0, 1), T = (tx, ty, 0) and N×T = (−ty, tx, 0).
    x = tx * w.x - s * ty * w.y
    y = ty * w.x + s * tx * w.y
    return dr.select(ok, mi.Vector3f(x, y, w.z), w)


def to_tangent_frame(w, rotation):
    """The inverse of :func:`from_tangent_frame`'s turn: ``w`` (base frame) in the vertex
    tangent frame's x, y (z unchanged); ``rotation`` from :func:`tangent_rotation`."""
    tx, ty, s, ok = rotation
    x = tx * w.x + ty * w.y
    y = s * (tx * w.y - ty * w.x)
    return dr.select(ok, mi.Vector3f(x, y, w.z), w)


def broadcast(tree, n):
    """``tree`` (tuples, lists, dataclasses and Dr.Jit structs of Dr.Jit arrays) with every
    array of one lane widened to n lanes (a differentiable gather). A loop's state must have
    the loop's width for reverse mode (Dr.Jit 1.5 cannot store a width-1 variable's
    trajectory), and the models' inputs mix widths (e.g. one shading frame for all queries)."""
    if not dr.is_jit_v(mi.Float) or n <= 1 or tree is None:
        return tree
    if isinstance(tree, (tuple, list)):
        return type(tree)(broadcast(x, n) for x in tree)
    if dataclasses.is_dataclass(tree) and not isinstance(tree, type):
        return dataclasses.replace(tree, **{f.name: broadcast(getattr(tree, f.name), n)
                                            for f in dataclasses.fields(tree)})
    if hasattr(type(tree), "DRJIT_STRUCT"):
        out = type(tree)(tree)
        for name in type(tree).DRJIT_STRUCT:
            setattr(out, name, broadcast(getattr(tree, name), n))
        return out
    if dr.is_array_v(tree) and dr.depth_v(tree) > 1:
        return type(tree)(*(broadcast(c, n) for c in tree))     # each component (a Vector3f's x, y, z)
    if dr.is_array_v(tree) and dr.width(tree) == 1:
        return dr.gather(type(tree), tree, dr.zeros(mi.UInt32, n))
    return tree


def select_frame(mask, a, b):
    return mi.Frame3f(dr.select(mask, a.s, b.s), dr.select(mask, a.t, b.t), dr.select(mask, a.n, b.n))


# Directions closer to the macro plane than this (|cosθ| < HORIZON_COS, 1e-12 rad) lie on it:
# every model gives them eval = pdf = 0. Below it the models' float32 products of two such
# cosines with their masking factors underflow: the pdf reached 0 where eval did not (eval 0.24
# at ω_i = ω_o with cosθ = 1.2e-38; 2e-29 at cosθ_o = 1.9e-28), which MIS cannot reach by BSDF
# sampling. The band holds no energy a render can see.
HORIZON_COS = 1e-12


def off_horizon(w):
    """``w`` with its z set to 0 where |z| < HORIZON_COS (on the macro plane)."""
    return mi.Vector3f(w.x, w.y, dr.select(dr.abs(w.z) < HORIZON_COS, 0.0, w.z))


@runtime_checkable
class MacroFrame(Protocol):
    """The microsurface's base frame G seen from the shading frame ``si.sh_frame`` (the macro
    normal, :mod:`mfnormal.normals.macro`): how directions and values cross between the two."""

    def to_macro(self, w):
        """``w`` (shading frame) in G."""

    def from_macro(self, w):
        """``w`` (in G) in the shading frame."""

    def weigh(self, ctx, sp: ShadingPoint, value, b, b_m):
        """``value`` (a model's ``eval`` at ω_o = ``b`` in the shading frame, ``b_m`` in G) as the
        integrator needs it: in light tracing, times the frame change's adjoint factor."""

    def to_shading(self, ctx, sp: ShadingPoint, bs, weight) -> tuple:
        """(bs, weight) of a model's sample in G, its direction in the shading frame (and the weight
        as :meth:`weigh` gives a value)."""


class ShadingFrame:
    """The null :class:`MacroFrame` (``macro_normal="shading"``): G is the shading frame, so
    directions and values pass unchanged."""

    def to_macro(self, w):
        return w

    def from_macro(self, w):
        return w

    def weigh(self, ctx, sp, value, b, b_m):
        return value

    def to_shading(self, ctx, sp, bs, weight) -> tuple:
        return bs, weight


SHADING_FRAME = ShadingFrame()


class ShadingPoint:
    """Microsurface geometry and nested-BSDF access at a batch of shading points.

    Its Dr.Jit arrays (``ARRAYS``) are what a model's loops read: they pass them as loop
    state (:meth:`state`, :meth:`with_state`), so that derivatives flow through the loops
    in both AD modes (a value a loop body captures from outside is not differentiated).
    Every field is declared (``__slots__``): the normal source's (``map_rotation``, ``attached``,
    ``nudged``) and the macro normal's (``macro``) are given when the point is made
    (:mod:`mfnormal.normals.macro`).
    """

    ARRAYS = ("si", "wi", "wp", "wt", "sin_p", "frame_p", "frame_t", "cot_p")
    __slots__ = ARRAYS + ("nested", "ctx", "map_rotation", "attached", "nudged", "macro", "indirect", "spread")
    nested: mi.BSDF                 # the nested BSDF, on both facets
    ctx: mi.BSDFContext
    si: mi.SurfaceInteraction3f     # the hit, its shading frame the base frame (ω_g = +z)
    wi: mi.Vector3f                 # ω_i in the base frame, off the horizon (:func:`off_horizon`)
    wp: mi.Vector3f                 # ω_p; ω_g where the tangent facet has no area
    wt: mi.Vector3f                 # ω_t, the tangent facet's normal
    sin_p: mi.Float
    frame_p: mi.Frame3f             # the facets' frames (microsurface.facet_frame)
    frame_t: mi.Frame3f
    cot_p: mi.Float
    map_rotation: tuple | None      # the vertex tangent frame the map was decoded in (tangent_rotation), None: this frame
    attached: bool                  # ω_p carries derivatives (the map's or ``strength``'s)
    nudged: bool                    # a nudged normal's point: evaluated only for a flat normal's derivatives
    macro: MacroFrame               # the base frame seen from the shading frame
    indirect: bool                  # nested-BSDF calls through a callable (:meth:`_nested`), else inlined
    spread: mi.Float | None         # the footprint's slope variance, for a widened nested BSDF (:meth:`facet_si`)

    def __init__(self, nested, ctx, si, wp, map_rotation: tuple | None = None, attached: bool = False,
                 nudged: bool = False, macro: MacroFrame = SHADING_FRAME):
        self.nested = nested
        self.ctx = ctx
        self.si = si
        self.wi = off_horizon(si.wi)
        self.wt, self.sin_p = ms.tangent_facet(wp)
        # Where the tangent facet has no area (sinθ_p < SIN_P_EPS), ω_p = ω_g exactly:
        # masking (from ω_p) and the height map (from sinθ_p) then agree.
        self.wp = dr.select(self.sin_p > 0, wp, mi.Vector3f(0.0, 0.0, 1.0))
        self.frame_p = ms.facet_frame(self.wp)
        self.frame_t = ms.facet_frame(self.wt)
        self.cot_p = ms.cot_p(self.wp, self.sin_p)
        self.map_rotation, self.attached, self.nudged, self.macro = map_rotation, attached, nudged, macro
        self.indirect = False
        self.spread = None

    def with_indirect_calls(self):
        """A copy of this point whose nested-BSDF calls are indirect (:meth:`_nested`)."""
        sp = copy.copy(self)
        sp.indirect = True
        return sp

    def _nested(self, method, *args):
        """``self.nested.<method>(ctx, *args)``: inlined, or where ``indirect`` (JIT variants) a
        one-target ``dr.switch``. Dr.Jit compiles such a callable once per kernel for all the
        call sites whose traced code is the same (it deduplicates identical callables), where an
        inlined call copies the nested BSDF's code into the kernel at every site (docs/model.md
        §2.3). The switch zeroes its outputs on the lanes it does not run (e.g. a sample's eta
        and type, which the faithful and analytic models read there: they stay inlined)."""
        fn = getattr(self.nested, method)
        if not (self.indirect and dr.is_jit_v(mi.Float)):
            return fn(self.ctx, *args)
        ctx = self.ctx
        return dr.switch(dr.zeros(mi.UInt32, dr.width(args[-1])), [lambda *a: fn(ctx, *a)], *args)

    def state(self):
        """The Dr.Jit arrays of this point, as a list (for a loop's state)."""
        return [getattr(self, name) for name in self.ARRAYS]

    def with_state(self, state):
        """A copy of this point whose arrays are ``state`` (from :meth:`state`, inside a loop)."""
        sp = copy.copy(self)
        for name, value in zip(self.ARRAYS, state):
            setattr(sp, name, value)
        return sp

    def detached(self):
        """A copy of this point whose arrays carry no derivatives."""
        return self.with_state([dr.detach(x) for x in self.state()])

    def nested_attached(self):
        """Whether the nested BSDF's value carries derivatives (its parameters, or textures,
        have them enabled): a probe evaluation whose traced code is never compiled."""
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
        si.n, si.uv, si.wi = mi.Normal3f(0, 0, 1), mi.Point2f(0.5, 0.5), mi.Vector3f(0.6, 0.0, 0.8)
        return dr.grad_enabled(self.nested.eval(self.ctx, si, mi.Vector3f(-0.6, 0.0, 0.8)))

    # Masking and intersection probabilities at this point
    def lambda_p(self, w):
        return ms.lambda_p(w, self.wp, self.wt, self.sin_p)

    def lambda_t(self, w):
        return ms.lambda_t(w, self.wp, self.wt, self.sin_p)

    def one_minus_G1_p(self, w):
        return ms.one_minus_G1_p(w, self.wp)

    def G1_p(self, w):
        return ms.G1_p(w, self.wp, self.wt, self.sin_p)

    def G1_t(self, w):
        return ms.G1_t(w, self.wp, self.wt, self.sin_p)

    def G1(self, w, on_p):
        return dr.select(on_p, self.G1_p(w), self.G1_t(w))

    def flip_t(self, w):
        return ms.flip_t(w, self.wt)

    def crest_map(self, on_p, d):
        """(τ, κ) of a ray leaving facet p (``on_p``) or t along d (microsurface.crest_map)."""
        return ms.crest_map(on_p, d, self.wt, self.cot_p)

    # The nested BSDF on a facet
    def facet_si(self, frame, wi):
        """Copy of ``si`` whose shading frame is the facet's, lit/seen from ``wi``; with a
        ``spread`` (a filtered footprint's slope variance), carrying it in ``duv_dx.x`` for the
        nested BSDF's widened twin (:mod:`mfnormal.plugins.widened`) on the lanes whose ``frame``
        is the texel's facet (``frame_p``): the footprint's facets are what it widens, not the
        macro surface's nested lobe."""
        si = self.si
        si_f = mi.SurfaceInteraction3f(si)
        si_f.sh_frame = mi.Frame3f(si.to_world(frame.s), si.to_world(frame.t), si.to_world(frame.n))
        si_f.wi = frame.to_local(wi)
        if self.spread is not None:
            on_facet = (frame.n.x == self.frame_p.n.x) & (frame.n.y == self.frame_p.n.y) & \
                (frame.n.z == self.frame_p.n.z)
            si_f.duv_dx = mi.Vector2f(dr.select(on_facet, self.spread, 0.0), 0.0)
        return si_f

    def _facet_query(self, frame, wi, wo, active, si_f=None):
        """(si, wo, active) on the facet; active only where both directions are above it
        (``si_f``: :meth:`facet_si` of ``frame`` and ``wi``, if the caller has it).

        A facet only reflects: no transmitted lobe, and some nested pdfs (e.g.
        llvm roughplastic's) are not zero below the facet.
        """
        wo_f = frame.to_local(wo)
        si_f = self.facet_si(frame, wi) if si_f is None else si_f
        return si_f, wo_f, active & (wo_f.z > 0) & (si_f.wi.z > 0)

    def eval(self, frame, wi, wo, active):
        """Nested f·⟨wo, ω_m⟩ on the facet with ``frame``; zero where inactive."""
        si_f, wo_f, active = self._facet_query(frame, wi, wo, active)
        return dr.select(active, self._nested("eval", si_f, wo_f, active), 0.0)

    def pdf(self, frame, wi, wo, active):
        si_f, wo_f, active = self._facet_query(frame, wi, wo, active)
        return dr.select(active, self._nested("pdf", si_f, wo_f, active), 0.0)

    def eval_pdf(self, frame, wi, wo, active):
        si_f, wo_f, active = self._facet_query(frame, wi, wo, active)
        value, pdf = self._nested("eval_pdf", si_f, wo_f, active)
        return dr.select(active, value, 0.0), dr.select(active, pdf, 0.0)

    def sample(self, frame, wi, sample1, sample2, active):
        """Nested sample on a facet: (BSDFSample with wo in the base frame, weight)."""
        bs, weight = self._nested("sample", self.facet_si(frame, wi), sample1, sample2, active)
        bs.wo = frame.to_world(bs.wo)
        return bs, dr.select(active, weight, 0.0)
