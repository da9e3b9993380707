r"""
.. _bsdf-normalmap_microfacet:

Microfacet-based normal mapping (:monosp:`normalmap_microfacet`)
----------------------------------------------------------------

.. pluginparameters::

 * - normalmap
   - |texture| or |string|
   - Tangent-space normal map, decoded as :math:`n = 2\,\mathrm{rgb} - 1` in the
     base shading frame (like Mitsuba's built-in ``normalmap``). Give a
     ``bitmap`` texture with ``raw=true``, or a file name (loaded raw).
 * - (nested bsdf)
   - |bsdf|
   - The material of the microfacets: any Mitsuba BSDF (its reflection part).
 * - model
   - |string|
   - ``analytic`` (default): the paper's default model, paths of up to two
     facet bounces with a mirror tangent facet, deterministic ``eval`` and the
     exact ``pdf`` of its sampler. (``separable`` and ``nonseparable``: the
     random-walk models, not available yet.)
 * - normalmap_convention
   - |string|
   - ``opengl`` (default, +Y up, what Mitsuba's ``normalmap`` assumes) or
     ``directx`` (green channel inverted).
 * - strength
   - |float|
   - Scales the tangent-space x and y before normalising (glTF's
     ``normalTexture.scale``); 0 gives the flat surface. Default: 1.
     (Exposed, |exposed|)

Robust normal mapping after Schüßler, Heitz, Hanika and Dachsbacher,
*Microfacet-based Normal Mapping for Robust Monte Carlo Path Tracing*
(SIGGRAPH Asia 2017). Each shading point is a microsurface of two facets: the
perturbed facet :math:`\omega_p` (the normal map's normal, made of the nested
material) and a tangent facet :math:`\omega_t` (a vertical mirror wall). Light
reflects off them with masking and shadowing, so the BSDF is reciprocal,
never gains energy, and has no black fringes or light leaks at grazing angles
where classic normal mapping breaks.

Contracts (each one is tested):

- ``eval`` returns :math:`f\cdot\langle\omega_o,\omega_g\rangle` in the base
  shading frame (:math:`\omega_g` = +z of ``si.sh_frame``), zero below it;
- ``eval_pdf`` equals ``(eval, pdf)``; ``pdf`` is the exact density of
  ``sample`` and a deterministic function of (wi, wo);
- a sample's weight equals ``eval / pdf`` (for delta nested lobes it is the
  unbiased path weight);
- normals that are NaN, infinite, zero, or point below the horizon never
  produce NaN: they decode to the flat normal, or are clamped to
  :math:`\cos\theta_p \ge 0.02`. A flat map reproduces the nested BSDF.

Cost of ``analytic``: 3 nested ``eval_pdf`` per ``eval``/``pdf`` query and
1 nested ``sample`` + 3 nested ``eval_pdf`` per ``sample`` query.

.. tabs::
    .. code-tab:: xml

        <bsdf type="normalmap_microfacet">
            <texture name="normalmap" type="bitmap">
                <string name="filename" value="normals.png"/>
                <boolean name="raw" value="true"/>
            </texture>
            <bsdf type="roughconductor">
                <float name="alpha" value="0.2"/>
            </bsdf>
        </bsdf>

    .. code-tab:: python

        'type': 'normalmap_microfacet',
        'normalmap': {'type': 'bitmap', 'filename': 'normals.png', 'raw': True},
        'bsdf': {'type': 'roughconductor', 'alpha': 0.2}
"""

from __future__ import annotations

import struct

import drjit as dr
import mitsuba as mi

from . import microsurface as ms

MODELS = ("analytic",)
FUTURE_MODELS = ("separable", "nonseparable")
CONVENTIONS = ("opengl", "directx")
ONE_MINUS_EPS = 0.99999994  # largest float32 below 1


def _fail(msg: str):
    raise ValueError(f"normalmap_microfacet: {msg}")


def _bits(x):
    """The IEEE bits of a float32 (Dr.Jit array or, in scalar variants, a Python float)."""
    if isinstance(x, float):
        return struct.unpack("<I", struct.pack("<f", x))[0]
    return dr.reinterpret_array(mi.UInt32, mi.Float32(x))


def _hash01(sample1, sample2):
    """An extra uniform number derived from the sample (for the masking test).

    The nested sampler receives (sample1, sample2) untouched where possible, so
    a flat normal map reproduces its samples exactly; this hash of their bits is
    independent of the nested sample in practice.
    """
    a, b, c = _bits(sample1), _bits(sample2.x), _bits(sample2.y)
    v0, v1 = mi.sample_tea_32(a ^ ((c * 0x9E3779B9) & 0xFFFFFFFF), b, 4)
    return mi.Float(dr.minimum(mi.Float32(v0 ^ v1) * (1.0 / 4294967296.0), ONE_MINUS_EPS))


class NormalMapMicrofacet(mi.BSDF):
    def __init__(self, props: mi.Properties):
        mi.BSDF.__init__(self, props)

        # Nested BSDF and normal map
        self.nested = None
        self.normalmap = None
        for name, obj in props.objects():
            if isinstance(obj, mi.BSDF):
                if self.nested is not None:
                    _fail("expects exactly one nested BSDF, got several")
                self.nested = obj
            elif isinstance(obj, mi.Texture) and name == "normalmap":
                self.normalmap = obj
        if self.normalmap is None and "normalmap" in props.keys():
            value = props["normalmap"]
            if isinstance(value, str):
                self.normalmap = mi.load_dict({"type": "bitmap", "filename": value, "raw": True})
        if self.nested is None:
            _fail("needs a nested BSDF (e.g. <bsdf type=\"diffuse\"/> inside it)")
        if self.normalmap is None:
            _fail("needs a texture named 'normalmap' (a raw bitmap: <texture name=\"normalmap\" "
                  "type=\"bitmap\"> with <boolean name=\"raw\" value=\"true\"/>)")

        # Model parameters
        self.model = props.get("model", "analytic")
        if self.model in FUTURE_MODELS:
            _fail(f"model '{self.model}' is not implemented yet; use model='analytic'")
        if self.model not in MODELS:
            _fail(f"unknown model '{self.model}'; choose one of {', '.join(MODELS)}")
        tangent_facet = props.get("tangent_facet", "specular")
        if tangent_facet != "specular":
            _fail(f"tangent_facet '{tangent_facet}' is not available for model '{self.model}', "
                  "whose tangent facet is always a mirror ('specular')")
        convention = props.get("normalmap_convention", "opengl")
        if convention not in CONVENTIONS:
            _fail(f"unknown normalmap_convention '{convention}'; use 'opengl' or 'directx'")
        self.directx = convention == "directx"
        strength = float(props.get("strength", 1.0))
        if not (strength >= 0.0 and strength < float("inf")):
            _fail(f"strength must be a finite number >= 0, got {strength}")
        self.strength = mi.Float(strength)
        dr.make_opaque(self.strength)

        # Reflection components of the nested BSDF
        components = []
        for i in range(self.nested.component_count()):
            components.append(self.nested.flags(i))
        self.m_components = components
        self.m_flags = self.nested.flags() | mi.BSDFFlags.FrontSide

    def traverse(self, callback):
        callback.put("nested_bsdf", self.nested, mi.ParamFlags.Differentiable)
        callback.put("normalmap", self.normalmap, mi.ParamFlags.Differentiable)
        callback.put("strength", self.strength, mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys):
        if "strength" in keys:
            dr.make_opaque(self.strength)

    # -- Geometry of the microsurface at a shading point ----------------------

    def _microsurface(self, si, active):
        """(ω_p, ω_t, sinθ_p, p-facet frame) in the base shading frame."""
        rgb = self.normalmap.eval_3(si, active)
        wp = ms.decode_normal(rgb, self.strength, self.directx)
        wt, sin_p = ms.tangent_facet(wp)
        return wp, wt, sin_p, ms.facet_frame(wp)

    @staticmethod
    def _facet_si(si, frame, wi):
        """Copy of ``si`` whose shading frame is the facet's, seen from ``wi``."""
        si_f = mi.SurfaceInteraction3f(si)
        si_f.sh_frame = mi.Frame3f(si.to_world(frame.s), si.to_world(frame.t), si.to_world(frame.n))
        si_f.wi = frame.to_local(wi)
        return si_f

    # -- The analytic model (MODEL.md §2.6) ------------------------------------

    def _analytic(self, ctx, si, wo, active, want_value=True, want_pdf=True):
        wp, wt, sin_p, frame = self._microsurface(si, active)
        wi = si.wi
        active = active & (wi.z > 0) & (wo.z > 0)
        lp = ms.lambda_p(wi, wp, wt, sin_p)
        lt = 1.0 - lp

        wo_m = ms.flip_t(wo, wt)
        si_i = self._facet_si(si, frame, wi)
        si_im = self._facet_si(si, frame, ms.flip_t(wi, wt))
        g_o_p = ms.G1_p(wo, wp, wt, sin_p)
        g_om_p = ms.G1_p(wo_m, wp, wt, sin_p)
        g_o_t = ms.G1_t(wo, wp, wt, sin_p)

        # Path weights: i→p→o, i→p→t→o, i→t→p→o
        c1 = lp * g_o_p
        c2 = dr.select(g_o_t > 0, lp * (1.0 - g_om_p), 0.0)
        c3 = dr.select(g_o_p > 0, lt, 0.0)
        a1, a2, a3 = active & (c1 > 0), active & (c2 > 0), active & (c3 > 0)
        wo_f, wo_mf = frame.to_local(wo), frame.to_local(wo_m)

        value, pdf = mi.Spectrum(0.0), mi.Float(0.0)
        if want_value and want_pdf:
            f1, p1 = self.nested.eval_pdf(ctx, si_i, wo_f, a1)
            f2, p2 = self.nested.eval_pdf(ctx, si_i, wo_mf, a2)
            f3, p3 = self.nested.eval_pdf(ctx, si_im, wo_f, a3)
        elif want_value:
            f1 = self.nested.eval(ctx, si_i, wo_f, a1)
            f2 = self.nested.eval(ctx, si_i, wo_mf, a2)
            f3 = self.nested.eval(ctx, si_im, wo_f, a3)
        else:
            p1 = self.nested.pdf(ctx, si_i, wo_f, a1)
            p2 = self.nested.pdf(ctx, si_i, wo_mf, a2)
            p3 = self.nested.pdf(ctx, si_im, wo_f, a3)

        if want_value:
            value = (dr.select(a1, f1, 0.0) * c1
                     + dr.select(a2, f2, 0.0) * (c2 * g_o_t)
                     + dr.select(a3, f3, 0.0) * (c3 * g_o_p))
            value = dr.select(active & dr.all(dr.isfinite(value)), dr.maximum(value, 0.0), 0.0)
        if want_pdf:
            pdf = (dr.select(a1, p1, 0.0) * c1 + dr.select(a2, p2, 0.0) * c2
                   + dr.select(a3, p3, 0.0) * c3)
            pdf = dr.select(active & dr.isfinite(pdf), dr.maximum(pdf, 0.0), 0.0)
        return value, pdf

    # -- BSDF interface ----------------------------------------------------------

    def sample(self, ctx, si, sample1, sample2, active=True):
        wp, wt, sin_p, frame = self._microsurface(si, active)
        wi = si.wi
        active = mi.Bool(active) & (wi.z > 0)

        # Choose the first facet hit from wi; reuse sample1 for the nested BSDF.
        lp = ms.lambda_p(wi, wp, wt, sin_p)
        on_p = sample1 < lp
        s1 = dr.select(on_p, sample1 / dr.maximum(lp, 1e-30), (sample1 - lp) / dr.maximum(1.0 - lp, 1e-30))
        s1 = dr.clip(s1, 0.0, ONE_MINUS_EPS)

        # Light reaches p directly, or after mirroring off the tangent facet.
        wi_p = dr.select(on_p, wi, ms.flip_t(wi, wt))
        bs, w = self.nested.sample(ctx, self._facet_si(si, frame, wi_p), s1, sample2, active)
        w_p = frame.to_world(bs.wo)
        g_p = ms.G1_p(w_p, wp, wt, sin_p)

        # Leave after p, or hit the tangent facet and mirror (p→t→o).
        to_t = on_p & (_hash01(sample1, sample2) >= g_p)
        wo = dr.select(to_t, ms.flip_t(w_p, wt), w_p)
        g_o_t = ms.G1_t(wo, wp, wt, sin_p)
        path = dr.select(to_t, g_o_t, g_p)
        prob = dr.select(on_p, lp * dr.select(to_t, 1.0 - g_p, g_p), 1.0 - lp)
        active &= (bs.pdf > 0) & (path > 0) & (wo.z > 0) & dr.all(dr.isfinite(wo))

        # Smooth lobes: weight = eval/pdf with the exact pdf. Delta lobes: path weight.
        delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        value, pdf = self._analytic(ctx, si, wo, active & ms.negate(delta))
        weight = dr.select(delta, w * path, value / dr.select(pdf > 0, pdf, 1.0))
        bs.pdf = dr.select(delta, bs.pdf * prob, pdf)
        active &= (bs.pdf > 0) & dr.all(dr.isfinite(weight))

        bs.wo = wo
        bs.pdf = dr.select(active, bs.pdf, 0.0)
        return bs, dr.select(active, dr.maximum(weight, 0.0), 0.0)

    def eval(self, ctx, si, wo, active=True):
        return self._analytic(ctx, si, wo, mi.Bool(active), want_pdf=False)[0]

    def pdf(self, ctx, si, wo, active=True):
        return self._analytic(ctx, si, wo, mi.Bool(active), want_value=False)[1]

    def eval_pdf(self, ctx, si, wo, active=True):
        return self._analytic(ctx, si, wo, mi.Bool(active))

    def to_string(self):
        return (f"NormalMapMicrofacet[model={self.model}, strength={self.strength}, "
                f"convention={'directx' if self.directx else 'opengl'},\n"
                f"  normalmap={self.normalmap},\n  bsdf={self.nested}]")

