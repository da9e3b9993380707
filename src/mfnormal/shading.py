"""One shading point seen as a two-facet microsurface, with the nested BSDF on its facets.

The models (``analytic``, ``walk``) work on a :class:`ShadingPoint`: directions in
the base shading frame (ω_g = +z), the facet normals ω_p and ω_t, their frames,
and the nested BSDF evaluated or sampled in a facet's frame.
"""

from __future__ import annotations

import struct

import drjit as dr
import mitsuba as mi

from . import microsurface as ms

ONE_MINUS_EPS = 0.99999994  # largest float32 below 1


def bits(x):
    """The IEEE bits of a float32 (Dr.Jit array or, in scalar variants, a Python float)."""
    if isinstance(x, float):
        return struct.unpack("<I", struct.pack("<f", x))[0]
    return dr.reinterpret_array(mi.UInt32, mi.Float32(x))


def hash_floats(salt, *values):
    """A well-mixed 32-bit seed from float inputs (TEA chained over their bits)."""
    h = mi.UInt32(salt)
    for v in values:
        h, _ = mi.sample_tea_32(h, bits(v), 4)
    return h


def uniform(seed, counter):
    """The counter-th uniform number of the stream ``seed`` (stateless, deterministic)."""
    return dr.minimum(mi.sample_tea_float32(seed, counter, 6), ONE_MINUS_EPS)


def select_frame(mask, a, b):
    return mi.Frame3f(dr.select(mask, a.s, b.s), dr.select(mask, a.t, b.t), dr.select(mask, a.n, b.n))


class ShadingPoint:
    """Microsurface geometry and nested-BSDF access at a batch of shading points."""

    def __init__(self, nested, ctx, si, wp):
        self.nested = nested
        self.ctx = ctx
        self.si = si
        self.wi = si.wi
        self.wp = wp
        self.wt, self.sin_p = ms.tangent_facet(wp)
        self.frame_p = ms.facet_frame(wp)
        self.frame_t = ms.facet_frame(self.wt)

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

    # The nested BSDF on a facet
    def facet_si(self, frame, wi):
        """Copy of ``si`` whose shading frame is the facet's, lit/seen from ``wi``."""
        si = self.si
        si_f = mi.SurfaceInteraction3f(si)
        si_f.sh_frame = mi.Frame3f(si.to_world(frame.s), si.to_world(frame.t), si.to_world(frame.n))
        si_f.wi = frame.to_local(wi)
        return si_f

    def eval(self, frame, wi, wo, active):
        """Nested f·⟨wo, ω_m⟩ on the facet with ``frame``; zero where inactive."""
        value = self.nested.eval(self.ctx, self.facet_si(frame, wi), frame.to_local(wo), active)
        return dr.select(active, value, 0.0)

    def pdf(self, frame, wi, wo, active):
        """Nested pdf on the facet; zero unless both directions are above it
        (some nested pdfs, e.g. llvm roughplastic's, are not zero below)."""
        wo_f = frame.to_local(wo)
        si_f = self.facet_si(frame, wi)
        active = active & (wo_f.z > 0) & (si_f.wi.z > 0)
        value = self.nested.pdf(self.ctx, si_f, wo_f, active)
        return dr.select(active, value, 0.0)

    def eval_pdf(self, frame, wi, wo, active):
        wo_f = frame.to_local(wo)
        si_f = self.facet_si(frame, wi)
        active = active & (wo_f.z > 0) & (si_f.wi.z > 0)
        value, pdf = self.nested.eval_pdf(self.ctx, si_f, wo_f, active)
        return dr.select(active, value, 0.0), dr.select(active, pdf, 0.0)

    def sample(self, frame, wi, sample1, sample2, active):
        """Nested sample on a facet: (BSDFSample with wo in the base frame, weight)."""
        bs, weight = self.nested.sample(self.ctx, self.facet_si(frame, wi), sample1, sample2, active)
        bs.wo = frame.to_world(bs.wo)
        return bs, dr.select(active, weight, 0.0)
