"""BSDFs that measure the plugin from the outside: call counters, a closed-form stub and shells.

The benchmark wraps the nested BSDF of ``normalmap_microfacet`` instead of patching
the package: ``bench_counting`` counts, per query lane, the calls that reach the
nested BSDF and the call sites each lane passes (masked or not); ``bench_stub`` is
a grey Lambertian in closed form (no texture, no Fresnel), so that timing the plugin
around it times the model's own logic; ``bench_total`` (:func:`wrap_totals`,
:func:`count_calls`) adds every call's active lanes to one total per BSDF, for the path
tracer's work per camera sample (:func:`path_vertices`); ``bench_shell_classic`` and
``bench_shell_hidden`` (:func:`shell_class`) keep ``normalmap_microfacet``'s normal decoding
and frames and replace its model by the least a model does (the cost floor,
``benchmarks/cost_floor.py``); ``bench_footprint_reader`` (:func:`wrap_readers`) reads the pixel's
footprint that the integrators give (``si.duv_dx``, ``si.duv_dy``), so that the cone's work is
not dead code (``benchmarks/footprint.py``). Call :func:`register` once the variant is set
(``mi.BSDF`` is the variant's class).
"""

from __future__ import annotations

OPS = ("eval", "pdf", "eval_pdf", "sample")
#: bench_total's totals: {label: {op: UInt64 array of one lane}}, filled by the BSDFs as they trace.
COUNTERS = {}


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


def counting_class():
    """``bench_counting``: a forwarding BSDF that counts, per query lane, its calls and call sites."""
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

    return Counting


def stub_class():
    """``bench_stub``: a grey Lambertian in closed form."""
    import drjit as dr
    import mitsuba as mi

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

    return Stub


def total_class():
    """``bench_total``: a forwarding BSDF that adds its calls' active lanes to COUNTERS."""
    import drjit as dr
    import mitsuba as mi

    class Total(forwarding_base()):
        """The BSDF ``bsdf``, each call adding its active lanes to COUNTERS[label][op]."""

        def __init__(self, props):
            super().__init__(props)
            self.label = props["label"]
            COUNTERS[self.label] = {op: dr.zeros(mi.UInt64, 1) for op in OPS}

        def _count(self, op, active):
            active = mi.Bool(active)
            dr.scatter_add(COUNTERS[self.label][op], mi.UInt64(1), mi.UInt32(0), active)

        def to_string(self):
            return f"Total[{self.label}: {self.inner}]"

    return Total


def footprint_reader_class():
    """``bench_footprint_reader``: a forwarding BSDF (``eval_pdf_sample`` too) whose values are
    the nested BSDF's times 1 + z·(u + |duv_dx| + |duv_dy|), z an opaque 0: the same image, with
    the footprint read. No BSDF reads it otherwise, and Dr.Jit drops what no output reads. The
    uv's u keeps the wrapper's work whether or not a footprint is given (without a live input
    Dr.Jit folds the wrapper away: 3 100 operations fewer in the demo's kernel)."""
    import drjit as dr
    import mitsuba as mi

    class FootprintReader(forwarding_base()):
        def __init__(self, props):
            super().__init__(props)
            self.zero = dr.opaque(mi.Float, 0.0)

        def _one(self, si):
            return 1.0 + self.zero * (si.uv.x + dr.norm(si.duv_dx) + dr.norm(si.duv_dy))

        def eval(self, ctx, si, wo, active=True):
            return self.inner.eval(ctx, si, wo, active) * self._one(si)

        def eval_pdf_sample(self, ctx, si, wo, sample1, sample2, active=True):
            value, pdf, bs, weight = self.inner.eval_pdf_sample(ctx, si, wo, sample1, sample2, active)
            one = self._one(si)
            return value * one, pdf, bs, weight * one

        def to_string(self):
            return f"FootprintReader[{self.inner}]"

    return FootprintReader


def shell_class(hidden: bool):
    """``normalmap_microfacet`` (the same properties, its normal decoding and shading frames) with
    its model replaced by the least one does, to time what any model must pay:

    - ``hidden`` False (``bench_shell_classic``): classic normal mapping, the nested BSDF on the
      texel's facet, below its horizon nothing (paths end there as the built-in's do);
    - ``hidden`` True (``bench_shell_hidden``): the texel seen with a share V and, where it is hidden,
      its neighbours (the nested BSDF on the macro surface): V·f_p + (1 − V)·f_g, a mixture pdf that is
      exact and a sampler that picks a frame, draws the nested BSDF there and evaluates both frames
      for its weight eval/pdf (as any model must whose pdf is exact). V = cos θ_p stands in for a
      model's V: none of the model's own arithmetic (Smith Λ, shadowing, the fill, the
      neighbourhood) is there."""
    import drjit as dr
    import mitsuba as mi
    from mfnormal.models.faithful.nested import macro_frame, select_frame
    from mfnormal.models.rng import ONE_MINUS_EPS
    from mfnormal.plugins.normalmap_microfacet import bsdf_class

    plugin_class = bsdf_class()

    class Shell(mi.BSDF):
        def __init__(self, props):
            mi.BSDF.__init__(self, props)
            self.plugin = plugin_class(props)
            self.m_flags = self.plugin.m_flags
            self.m_components = list(self.plugin.m_components)

        @staticmethod
        def _eval_pdf(sp, wo, active):
            active = mi.Bool(active) & (wo.z > 0)
            value, pdf = sp.eval_pdf(sp.frame_p, sp.wi, wo, active)
            if not hidden:
                return value, pdf
            vis = dr.clip(sp.wp.z, 0.0, 1.0)
            value_g, pdf_g = sp.eval_pdf(macro_frame(), sp.wi, wo, active)
            return dr.lerp(value_g, value, vis), dr.lerp(pdf_g, pdf, vis)

        def eval_pdf(self, ctx, si, wo, active=True):
            return self._eval_pdf(self.plugin.shading_point(ctx, si, active), wo, active)

        def eval(self, ctx, si, wo, active=True):
            return self.eval_pdf(ctx, si, wo, active)[0]

        def pdf(self, ctx, si, wo, active=True):
            return self.eval_pdf(ctx, si, wo, active)[1]

        def sample(self, ctx, si, sample1, sample2, active=True):
            sp = self.plugin.shading_point(ctx, si, active)
            active = mi.Bool(active)
            if not hidden:
                bs, weight = sp.sample(sp.frame_p, sp.wi, sample1, sample2, active)
                return bs, dr.select(active & (bs.wo.z > 0), weight, 0.0)
            vis = dr.clip(sp.wp.z, 0.0, 1.0)
            on_texel = sample1 < vis
            s1 = dr.select(on_texel, sample1 / dr.maximum(vis, 1e-30),
                           (sample1 - vis) / dr.maximum(1.0 - vis, 1e-30))
            frame = select_frame(on_texel, sp.frame_p, macro_frame())
            bs, _ = sp.sample(frame, sp.wi, dr.clip(s1, 0.0, ONE_MINUS_EPS), sample2, active)
            ok = active & (bs.wo.z > 0)
            value, pdf = self._eval_pdf(sp, bs.wo, ok)
            bs.pdf = pdf
            return bs, dr.select(ok & (pdf > 0), value / dr.select(pdf > 0, pdf, 1.0), 0.0)

        def to_string(self):
            return f"Shell[{'hidden texel' if hidden else 'classic'}: {self.plugin.nested}]"

    return Shell


def register():
    """Register ``bench_counting``, ``bench_stub``, ``bench_total``, ``bench_shell_classic``,
    ``bench_shell_hidden`` and ``bench_footprint_reader`` in the current variant."""
    import mitsuba as mi
    for name, cls in (("bench_counting", counting_class()), ("bench_stub", stub_class()),
                      ("bench_total", total_class()), ("bench_shell_classic", shell_class(False)),
                      ("bench_shell_hidden", shell_class(True)),
                      ("bench_footprint_reader", footprint_reader_class())):
        mi.register_bsdf(name, lambda props, cls=cls: cls(props))


def wrap_totals(scene: dict) -> dict:
    """Every shape's BSDF, and its nested BSDF (a child ``bsdf*``) if any, wrapped in
    ``bench_total`` (labels: the shape's key, and ``KEY.nested``); ``scene`` is changed in place."""
    def bsdf_keys(d):
        return [k for k, v in d.items() if k.startswith("bsdf") and isinstance(v, dict)]
    for key, v in scene.items():
        if not isinstance(v, dict):
            continue
        for kb in bsdf_keys(v):
            outer = v[kb]
            for kn in bsdf_keys(outer):
                outer[kn] = {"type": "bench_total", "label": f"{key}.nested", "bsdf": outer[kn]}
            v[kb] = {"type": "bench_total", "label": key, "bsdf": outer}
    return scene


def wrap_readers(scene: dict) -> dict:
    """Every shape's BSDF wrapped in ``bench_footprint_reader``; ``scene`` is changed in place."""
    for v in scene.values():
        if isinstance(v, dict):
            for kb in [k for k, b in v.items() if k.startswith("bsdf") and isinstance(b, dict)]:
                v[kb] = {"type": "bench_footprint_reader", "bsdf": v[kb]}
    return scene


def count_calls(scene: dict, spp: int, samples: int, seed: int = 100) -> dict:
    """{label: {op: calls per camera sample}} of one render of the scene dict ``scene`` (its
    BSDFs wrapped by :func:`wrap_totals`; ``samples`` camera samples in all). The counters make
    every call an indirect Python call: such a render is not for timing."""
    import drjit as dr
    import mitsuba as mi
    COUNTERS.clear()
    sc = mi.load_dict(wrap_totals(scene))
    img = mi.render(sc, spp=spp, seed=seed)
    dr.eval(img)
    return {label: {op: int(c[op][0]) / samples for op in OPS} for label, c in COUNTERS.items()}


def path_vertices(counts: dict) -> float:
    """Path vertices per camera sample: the shapes' BSDF samples (one per vertex at which the
    path tracer continues the path) in :func:`count_calls`' counts."""
    return sum(c["sample"] for label, c in counts.items() if not label.endswith(".nested"))
