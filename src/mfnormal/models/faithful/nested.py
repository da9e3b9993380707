"""The nested BSDF as the default model queries it: on the texel's facet or on the macro surface,
from either side, gated per SIMD packet.

:class:`Components` says once per plugin which components the nested BSDF has; :func:`sided` is
every query of its value and density; :func:`gate` skips a query that no lane of a packet needs.
"""

from __future__ import annotations

import enum

import drjit as dr
import mitsuba as mi
import numpy as np

RADIANCE = mi.TransportMode.Radiance
GLOSSY_MASK = mi.BSDFFlags.All & ~mi.BSDFFlags.DiffuseReflection


def macro_frame():
    """The macro surface's frame in the base frame: ω_g = +z."""
    return mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))


class Components:
    """Which nested components exist, decided once per plugin (Python bools, baked into kernels).

    The diffuse components' blocked light goes to the fill, the others' is bounced; that
    needs a nested BSDF that honours ``BSDFContext.type_mask`` (Mitsuba's ``principled`` does
    not: it returns its whole value under either mask). One that does not is treated as all
    diffuse: all its blocked light goes to the fill (bounced as a mirror, the diffuse part of
    such a material would light the slopes facing away from the sun like a mirror would;
    docs/faithful.md §1).
    """

    def __init__(self, nested):
        flags = nested.flags()
        diffuse = mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection)
        glossy = mi.has_flag(flags, mi.BSDFFlags.GlossyReflection) or \
            mi.has_flag(flags, mi.BSDFFlags.DeltaReflection)
        self.diffuse_mask, self.glossy_mask = +mi.BSDFFlags.DiffuseReflection, GLOSSY_MASK
        if diffuse and glossy and not _honours_type_mask(nested):
            glossy = False
            self.diffuse_mask = +mi.BSDFFlags.All
        self.diffuse, self.glossy = diffuse, glossy
        # A transmitting nested BSDF: both hemispheres (the texel's mirrored frame, the Fold and Sink lobes).
        self.transmission = mi.has_flag(flags, mi.BSDFFlags.Transmission)


def _honours_type_mask(nested) -> bool:
    """Whether eval(diffuse only) + eval(the rest) = eval(all) at a few fixed queries."""
    pairs = [((0.3, 0.2, 0.93), (-0.5, 0.1, 0.86)), ((0.0, 0.0, 1.0), (0.6, -0.3, 0.74)),
             ((0.8, 0.1, 0.59), (-0.2, -0.6, 0.77)), ((-0.1, 0.7, 0.7), (0.1, 0.1, 0.99))]
    for wi, wo in pairs:
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
        si.n = mi.Normal3f(0, 0, 1)
        si.uv = mi.Point2f(0.5, 0.5)
        si.wi = dr.normalize(mi.Vector3f(*wi))
        o = dr.normalize(mi.Vector3f(*wo))
        full = nested.eval(mi.BSDFContext(), si, o)
        d = nested.eval(mi.BSDFContext(mi.TransportMode.Radiance, mi.BSDFFlags.DiffuseReflection), si, o)
        g = nested.eval(mi.BSDFContext(mi.TransportMode.Radiance, GLOSSY_MASK), si, o)
        full, rest = np.array(full, dtype=np.float64).ravel(), np.array(d + g, dtype=np.float64).ravel()
        if np.any(np.abs(full - rest) > 1e-4 * np.abs(full) + 1e-7):
            return False
    return True


def gate(cond, fn, otherwise, gated=True):
    """``fn()`` where ``cond``, ``otherwise`` elsewhere, for an ``fn`` that gives ``otherwise``
    where ``cond`` is false (its nested calls masked by it): the same values as ``fn()``, but a
    SIMD packet in which no lane needs ``fn`` skips it (a symbolic ``dr.if_stmt``: LLVM branches
    per packet; derivatives flow through it). ``gated`` false: ``fn()`` as it is."""
    if not gated:
        return fn()
    if not dr.is_jit_v(mi.Float):
        return fn() if cond else otherwise
    return dr.if_stmt((), cond, fn, lambda: otherwise)


def nested(sp, ctx, frame, wi, wo, active, want_value=True, want_pdf=True, si_f=None):
    """(f·cos, pdf) of the nested BSDF with context ``ctx`` on the facet with ``frame``
    (``si_f``: ``sp.facet_si(frame, wi)``, if the caller has it)."""
    si_f, wo_f, active = sp._facet_query(frame, wi, wo, active, si_f)
    return _call(sp, ctx, si_f, wo_f, active, want_value, want_pdf)


def _call(sp, ctx, si_f, wo_f, active, want_value, want_pdf):
    """The nested BSDF's (f·cos, pdf) at the facet query (``si_f``, ``wo_f``), zero where inactive."""
    if want_value and want_pdf:
        v, p = sp.nested.eval_pdf(ctx, si_f, wo_f, active)
    elif want_value:
        v, p = sp.nested.eval(ctx, si_f, wo_f, active), mi.Float(0.0)
    else:
        v, p = mi.Spectrum(0.0), sp.nested.pdf(ctx, si_f, wo_f, active)
    return dr.select(active, v, 0.0), dr.select(active, p, 0.0)


class Side(enum.Enum):
    """Which side of the facet a nested query's ω_o must be on, seen from the camera's side of it."""

    REFLECT = "reflect"
    TRANSMIT = "transmit"
    EITHER = "either"

    def holds(self, c_o):
        """Whether ω_o, with cosine ``c_o`` to the facet on the camera's side, is on this side."""
        return {Side.REFLECT: c_o > 0, Side.TRANSMIT: c_o < 0, Side.EITHER: c_o != 0}[self]


def sided(sp, tx, ctx, frame, wi, wo, active, want_value=True, want_pdf=True, si_f=None, side=Side.REFLECT):
    """:func:`nested` (base-frame ``wi``, ``wo``) for a texel ``tx`` that may be seen from below:
    active where ``wi`` is on the camera's side of ``frame`` (for a camera below, the facet's
    lower side) and ``wo`` on the ``side`` asked for. Without transmission, :func:`nested`."""
    if tx.flip is None:
        return nested(sp, ctx, frame, wi, wo, active, want_value, want_pdf, si_f)
    si_f = sp.facet_si(frame, wi) if si_f is None else si_f
    wo_f = frame.to_local(wo)
    sign = dr.select(tx.flip, -1.0, 1.0)
    c_o = sign * wo_f.z
    on_side = side.holds(c_o)
    active = active & (sign * si_f.wi.z > 0) & on_side
    return _call(sp, ctx, si_f, wo_f, active, want_value, want_pdf)


def mirror_z(w):
    """F(w) = (w_x, w_y, −w_z): the mirror image of ``w`` in the macro plane."""
    return mi.Vector3f(w.x, w.y, -w.z)


def crossing_eta(sp, si_f, active):
    """η of the interface on the facet of ``si_f`` (seen from its ``wi``): the relative index
    (``bs.eta``) of a transmitted nested sample, 1 where there is none. Light that crosses into
    the far side carries Mitsuba's radiance scaling 1/η² (:class:`~.transmission.Sink`)."""
    ctx = mi.BSDFContext(RADIANCE, mi.BSDFFlags.Transmission)
    bs, w = sp.nested.sample(ctx, si_f, mi.Float(0.5), mi.Point2f(0.5, 0.5), active)
    ok = active & (bs.pdf > 0) & (si_f.wi.z * bs.wo.z < 0) & (bs.eta > 0)
    return dr.select(ok, bs.eta, 1.0)


# -- Samples -----------------------------------------------------------------------------------

def finish(bs, weight, active):
    """A sample and its weight, zero (and a finite direction) where it does not count."""
    active &= (bs.pdf > 0) & dr.all(dr.isfinite(weight))
    bs.wo = dr.select(active, bs.wo, mi.Vector3f(0.0, 0.0, 1.0))   # never a NaN direction
    bs.pdf = dr.select(active, bs.pdf, 0.0)
    return bs, dr.select(active, dr.maximum(weight, 0.0), 0.0)


def select_sample(mask, a, b):
    """The BSDF sample ``a`` where ``mask``, ``b`` elsewhere."""
    bs = dr.zeros(mi.BSDFSample3f, dr.width(mask))
    for name in ("wo", "pdf", "eta", "sampled_type", "sampled_component"):
        setattr(bs, name, dr.select(mask, getattr(a, name), getattr(b, name)))
    return bs


def select_frame(mask, a, b):
    """The frame ``a`` where ``mask``, ``b`` elsewhere."""
    return mi.Frame3f(dr.select(mask, a.s, b.s), dr.select(mask, a.t, b.t), dr.select(mask, a.n, b.n))
