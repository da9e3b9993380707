"""Nested BSDFs that measure the plugin from the outside: a call counter and a closed-form stub.

The benchmark wraps the nested BSDF of ``normalmap_microfacet`` instead of patching
the package: ``bench_counting`` counts, per query lane, the calls that reach the
nested BSDF and the call sites each lane passes (masked or not); ``bench_stub`` is
a grey Lambertian in closed form (no texture, no Fresnel), so that timing the plugin
around it times the model's own logic. Call :func:`register` once the variant is set
(``mi.BSDF`` is the variant's class).
"""

from __future__ import annotations

OPS = ("eval", "pdf", "eval_pdf", "sample")


def forwarding_base():
    """A ``mi.BSDF`` class (of the current variant) that wraps the nested BSDF ``bsdf`` of
    its properties and forwards every call to it, after ``self._count(op, active)`` (a no-op
    here: subclasses count)."""
    import mitsuba as mi

    class Forwarding(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.inner = next(obj for _, obj in props.objects() if isinstance(obj, mi.BSDF))
            self.m_flags = self.inner.flags()
            self.m_components = [self.inner.flags(i) for i in range(self.inner.component_count())]

        def _count(self, op, active):
            pass

        def eval(self, ctx, si, wo, active=True):
            self._count("eval", active)
            return self.inner.eval(ctx, si, wo, active)

        def pdf(self, ctx, si, wo, active=True):
            self._count("pdf", active)
            return self.inner.pdf(ctx, si, wo, active)

        def eval_pdf(self, ctx, si, wo, active=True):
            self._count("eval_pdf", active)
            return self.inner.eval_pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            self._count("sample", active)
            return self.inner.sample(ctx, si, sample1, sample2, active)

    return Forwarding


def register():
    import drjit as dr
    import mitsuba as mi

    class Counting(forwarding_base()):
        """The nested BSDF ``bsdf``, counting its calls once ``reset(n)`` gave it n lanes."""

        def __init__(self, props):
            super().__init__(props)
            self.counts, self.sites = None, None

        def reset(self, n):
            self.counts = {op: dr.zeros(mi.UInt32, n) for op in OPS}
            self.sites = dr.zeros(mi.UInt32, n)

        def _count(self, op, active):
            if self.counts is not None:
                active = mi.Bool(active)
                lane = dr.arange(mi.UInt32, dr.width(active))
                dr.scatter_add(self.counts[op], mi.UInt32(1), lane, active)
                dr.scatter_add(self.sites, mi.UInt32(1), lane)

        def to_string(self):
            return f"Counting[{self.inner}]"

    class Stub(mi.BSDF):
        """f = 0.5/π (albedo 0.5), cosine-weighted sampling; nothing else."""

        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.m_flags = mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide
            self.m_components = [mi.BSDFFlags.DiffuseReflection | mi.BSDFFlags.FrontSide]

        def eval(self, ctx, si, wo, active=True):
            ok = mi.Bool(active) & (si.wi.z > 0)
            return dr.select(ok, mi.Spectrum(0.5 * dr.inv_pi * dr.maximum(wo.z, 0.0)), 0.0)

        def pdf(self, ctx, si, wo, active=True):
            ok = mi.Bool(active) & (si.wi.z > 0)
            return dr.select(ok, dr.inv_pi * dr.maximum(wo.z, 0.0), 0.0)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self.eval(ctx, si, wo, active), self.pdf(ctx, si, wo, active)

        def sample(self, ctx, si, sample1, sample2, active=True):
            ok = mi.Bool(active) & (si.wi.z > 0)
            local = mi.warp.square_to_cosine_hemisphere(sample2)
            bs = dr.zeros(mi.BSDFSample3f, dr.width(local))
            bs.wo = local
            bs.pdf = dr.select(ok, local.z * dr.inv_pi, 0.0)
            bs.eta = 1.0
            bs.sampled_type = mi.UInt32(+mi.BSDFFlags.DiffuseReflection)
            bs.sampled_component = 0
            return bs, dr.select(ok, mi.Spectrum(0.5), 0.0)

        def to_string(self):
            return "Stub[Lambertian 0.5]"

    mi.register_bsdf("bench_counting", lambda props: Counting(props))
    mi.register_bsdf("bench_stub", lambda props: Stub(props))
