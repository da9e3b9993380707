r"""
.. _bsdf-normalmap_microfacet:

Microfacet-based normal mapping (:monosp:`normalmap_microfacet`)
----------------------------------------------------------------

.. pluginparameters::

 * - normalmap
   - |texture| or |string|
   - Tangent-space normal map, decoded as :math:`n = 2\,\mathrm{rgb} - 1` in the
     base shading frame (like Mitsuba's built-in ``normalmap``). Give a
     ``bitmap`` texture with ``raw=true``, or a file name (loaded raw). A bitmap
     needs 3 channels, and its uv transform ``to_uv`` (also a nested texture's)
     finite values, at load and in ``mi.traverse`` updates (else a one-line
     ``ValueError``); a NaN or infinite uv is looked up at uv = 0.
 * - heightmap
   - |texture| or |string|
   - Instead of ``normalmap``: a height map (a ``bitmap``, ``raw=true``,
     bilinear: ω_p comes from its uv gradient ``eval_1_grad``). ω_p is the
     normal of the surface displaced along its normal by
     ``height_scale · strength · h(u, v)``, exactly Mitsuba ``bumpmap``'s
     perturbed normal for the same texture and ``scale`` (tested), mapped
     through the tangent frame (``tangents`` respected). docs/normal_sources.md.
 * - height_scale
   - |float|
   - Height map only: what Mitsuba's ``bumpmap`` calls ``scale``: the heights'
     scale (world units per texture unit where dp/du, dp/dv have unit length).
     Default: 1; any finite number (negative inverts the relief).
 * - macro_normal
   - |string|
   - ``shading`` (default): the microsurface's macro normal is the shading
     normal ``si.sh_frame.n``; for ``faithful``, where a camera below it sees
     the triangle (a coarse mesh's rim), the triangle's normal, as
     ``geometric`` has it (the paper's models show nothing there).
     ``geometric``: it is the true triangle normal
     ``si.n``, and ω_p is the interpolated shading normal with the map (if any)
     applied on top of it. Without a map this is the shadow-terminator fix for
     smooth-shaded low-poly meshes (``eval`` then returns f·⟨ω_o, si.n⟩;
     directions stay in ``si.sh_frame`` for the integrator).
 * - (nested bsdf)
   - |bsdf|
   - The material of the microfacets: any Mitsuba BSDF. A transmitting one
     (``dielectric``, ``roughdielectric``, ``thindielectric``, ``principled``
     with ``spec_trans`` > 0, or a ``blendbsdf``/``twosided`` of one) is
     normal-mapped on both sides by ``faithful``, which refracts (seen from
     above and from inside the medium; docs/faithful.md §7); the paper's models
     only reflect and refuse it (a one-line ``ValueError``).
 * - model
   - |string|
   - ``faithful`` (default): the texel as the true geometry around it shows
     it (docs/faithful.md): the nested BSDF on the facet, masked and shadowed
     by the neighbours around it (``neighbourhood``), the neighbours where the
     texel is hidden, and the light they block re-emitted, so white facets
     stay white and energy never exceeds the nested albedo; deterministic
     ``eval``, exact ``pdf``; not reciprocal (light tracing gets its adjoint).
     With a transmitting nested BSDF it refracts: the facet's transmitted
     light leaves on the far side of the macro surface (a refracted direction
     on the camera's side is folded across it), reflected light its
     neighbours block seen from above sinks below the surface through their
     interface, and a smooth lossless dielectric keeps reflection +
     transmission = 1.
     ``analytic``: the paper's default model, paths of up to two
     facet bounces with a mirror tangent facet, deterministic ``eval`` and the
     exact ``pdf`` of its sampler. ``separable``: the main paper's random walk
     over all bounce orders (separable masking-shadowing). ``nonseparable``:
     the supplemental's walk with height-correlated masking-shadowing, which
     equals ray tracing the sawtooth microsurface exactly.
 * - neighbourhood
   - |float|
   - ``faithful`` only: the width, in texels of the map, of the window
     around a texel whose slopes are its neighbourhood (default 8; a Gaussian
     of standard deviation half of it). The texel's projected area is taken
     on the window's mean plane and its neighbours have the window's slope
     variance (LEAN mapping's moments, the map's anisotropy): a smooth region
     of a real map (the low-poly's shape difference) shades as classic
     normal mapping, a rough one is masked and shadowed by its own relief.
     0: the whole map's rms slopes about the macro normal for every texel.
     Measured on normal maps; a height map always uses the whole map's.
 * - tangent_facet
   - |string|
   - Random-walk models only: ``specular`` (default; the tangent facet is a
     perfect mirror) or ``same`` (the nested BSDF on both facets). ``analytic``
     always uses a mirror and, like ``faithful``, rejects ``same``.
 * - max_bounces
   - |int|
   - Random-walk models only: bounce cap of the walk (default 1024). Paths
     still on the microsurface after it are dropped; the energy this loses is
     measured by the test suite (below 1e-4 of the albedo for θ_p ≤ 80°).
     (Exposed, a kernel input: a new value compiles no kernel. It is exposed as a
     float64 array, so that an update to 1.5 is refused, not truncated to 1.)
 * - rr_depth
   - |int|
   - Random-walk models only: Russian roulette from this many facet bounces on
     (default 3; 0 turns it off). A walk then continues with probability
     min(1, its largest throughput channel) and divides its throughput by it:
     unbiased, and dark materials (roughplastic, coloured metals) no longer run
     long walks that carry little energy. White facets are never rouletted.
     (Exposed, a kernel input, like ``max_bounces``.)
 * - mis_boost_max
   - |float|
   - Random-walk models only: cap of the variance-aware MIS boost (default 64).
     Walks longer than one nested bounce have a noisy ``eval`` on glossy
     facets; the walks' ``pdf`` boosts their share by the nested lobe's
     sharpness (1 for Lambertian, 1/(4α²) for GGX) up to this cap, weighted by
     how likely such walks are from ω_i, so that light samples of those paths
     lose MIS weight to BSDF samples. 1 turns it off: ``pdf`` is then the plain
     density approximation. MIS stays unbiased either way. (Exposed, a kernel
     input.) Updates through ``mi.traverse`` are checked as at load: a value out
     of range raises the same one-line error and the values before it stay.
 * - filter
   - |string|
   - ``faithful`` with a ``normalmap`` only: what a lookup reads where the pixel's footprint
     (``si.duv_dx``, ``si.duv_dy``, which ``mfnormal_path`` and ``mfnormal_prb`` give with their
     ``footprint`` on) covers more than a texel. ``none`` (default): the texel at its centre, as
     without a footprint. ``lean``: where the texel is mild (slope below 0.3), the footprint's mild
     texels as one facet, from the map's slope-moment pyramid: the normal of their mean slope
     and, for a ``roughconductor`` with one uniform ``alpha``, its lobe widened by their slope
     variance v, α' = √(α² + v) (LEAN mapping), its albedo kept; only where the Gaussian of their
     slopes stays within that bound. A steep texel is shaded as it is. Filters diffuse nested
     BSDFs and ``roughconductor``; others are shaded per texel (a warning says so). Derivatives
     reach the texels through the pyramid. What it gains and loses: docs/normal_sources.md.
 * - normalmap_convention
   - |string|
   - ``opengl`` (default, +Y up, what Mitsuba's ``normalmap`` assumes) or
     ``directx`` (green channel inverted).
 * - strength
   - |float|
   - Scales the tangent-space x and y before normalising (glTF's
     ``normalTexture.scale``); 0 gives the flat surface. Default: 1. A finite
     number ≥ 0, in the constructor and in ``mi.traverse`` updates alike (an
     update to NaN, ±inf or a negative value raises and keeps the previous
     strength); values above ``STRENGTH_MAX`` = 1e6 act as 1e6, which tilts
     every texel that is not exactly flat to the steepest facet already for
     8- and 16-bit maps, and keeps the decoding from overflowing to the flat
     normal. (Exposed and differentiable in ``mi.traverse``.)
 * - tangents
   - |string|
   - The tangent frame the map is decoded in. ``mitsuba`` (default): the
     base shading frame ``si.sh_frame``, whose tangent Mitsuba builds per
     triangle from the UV derivatives. A mesh attribute name such as
     ``vertex_tangent``: the baker's (MikkTSpace, glTF) per-vertex frame
     T, B = sign·(N×T), N, with T the interpolated 3-float attribute ``NAME``
     and sign the 1-float attribute ``NAME_sign`` (glTF's ``TANGENT.w``), so
     maps baked in MikkTSpace, mirrored UV islands included, come out right.
     Shapes without the attribute fall back to ``mitsuba`` (``mfnormal render`` warns;
     ``mfnormal bake --tangent-mesh`` writes a mesh with them).
     (:func:`mfnormal.io.gltf.load_gltf` adds both attributes.)

Every parameter is typed (``mfnormal.models.properties``): a boolean, an integer in its range,
a finite number or one of its strings, as the table says. A value of another type (the string
``"abc"`` for a number, 1.5 or NaN for an integer, ``<string>`` where the table says |float|)
is refused at load, in XML and ``mi.load_dict`` alike, with a one-line ``ValueError`` that names
the parameter and what it expects; so is an ``mi.traverse`` update of an exposed parameter
(``strength``, ``max_bounces``, ``rr_depth``, ``mis_boost_max``) to a wrong number, and the
values before it stay. (A string assigned to an exposed parameter is refused by ``mi.traverse``
itself, as it converts the value to the parameter's array type.)

Robust normal mapping after Schüßler, Heitz, Hanika and Dachsbacher,
*Microfacet-based Normal Mapping for Robust Monte Carlo Path Tracing*
(SIGGRAPH Asia 2017). In the paper's models each shading point is a microsurface
of two facets: the perturbed facet :math:`\omega_p` (the normal map's normal,
made of the nested material) and a tangent facet :math:`\omega_t` (a vertical
mirror wall). Light reflects off them with masking and shadowing, so the BSDF is
reciprocal, never gains energy, and has no black fringes or light leaks at grazing
angles where classic normal mapping breaks; but the mirror wall cancels the map's
relief. The default ``faithful`` model keeps the robustness except reciprocity
(which, with a white furnace, rules out relief: docs/faithful.md §2) and looks
like the true geometry the map was baked from.

Contracts (each one is tested):

- ``eval`` returns :math:`f\cdot\langle\omega_o,\omega_g\rangle` in the base
  shading frame (:math:`\omega_g` = +z of ``si.sh_frame``; with
  ``macro_normal="geometric"`` :math:`\omega_g` = ``si.n`` turned to the shading
  normal's side, directions still in ``si.sh_frame``), zero below it, except
  for ``faithful`` with a transmitting nested BSDF, which answers for ω_i and
  ω_o on either side (the nested BSDF's radiance scaling across the interface
  included);
- ``eval_diffuse_reflectance`` (the ``aov`` integrator's ``albedo``, what denoisers read) is
  the nested BSDF's at the hit;
- ``eval_pdf`` equals ``(eval, pdf)``; ``pdf`` is a deterministic function of
  (wi, wo): for ``faithful`` and ``analytic`` the exact density of ``sample``, for
  the random walks a function for MIS (below);
- a sample's weight is ``eval / pdf`` (``faithful``, ``analytic``; for delta nested
  lobes the unbiased path weight), or the walk's throughput, an unbiased estimate of it;
- ``faithful`` in ``TransportMode.Importance`` (light tracing) returns its adjoint,
  eval*(a, b) = eval(b, a)·⟨b,ω_g⟩/⟨a,ω_g⟩; the other models are reciprocal;
  with ``macro_normal="geometric"`` every model's ``TransportMode.Importance``
  eval is divided by the shading-normal correction Mitsuba's ``ptracer``
  applies (the microsurface lies on the true triangle and needs none), so light
  tracing matches path tracing;
- normals that are NaN, infinite, zero, or point below the horizon never
  produce NaN: they decode to the flat normal, or are clamped to
  :math:`\cos\theta_p \ge 0.02`. A flat map reproduces the nested BSDF;
- a direction within :math:`10^{-12}` of the macro plane (:math:`|\cos\theta| < 10^{-12}`)
  lies on it: ``eval`` and ``pdf`` are 0 there for every model (below that, float32
  products of two such cosines underflow, and the pdf could be 0 where ``eval`` was not).

For the random-walk models ``eval`` is an unbiased stochastic estimate
(next-event estimation along a walk whose random numbers are a hash of the
query, so it is deterministic per query; its first vertex is taken in
expectation over the start facet, so the low-order part is exact), ``sample``
returns the walk's exit direction and throughput, and ``pdf`` is a
deterministic function for multiple importance sampling: the walk's exact
low-order density plus a cosine lobe for the longer walks, whose share is
boosted where ``eval`` is noisy (see ``mis_boost_max``). MIS stays unbiased
with any such function.

Which model? ``faithful`` is the default: no extra variance, 3-5 nested
evaluations per query, as close to the true geometry as classic normal mapping
on mild maps and robust on steep ones. ``analytic``, the paper's default: no
extra variance, about 3 nested evaluations per query, exactly reciprocal, but it
drops paths with three or more facet bounces (it darkens steep normals) and its
mirror paths cancel the relief. ``separable`` and
``nonseparable`` conserve energy (a white nested BSDF stays white) at the cost
of a stochastic ``eval`` and a walk of a few bounces per query (more for steep
normals); ``nonseparable`` is the physically exact one (height-correlated),
``separable`` the main paper's approximation. ``tangent_facet=specular`` keeps
the look closest to classic normal mapping; ``same`` spreads the material over
both facets.

``eval_pdf_sample`` (eval and pdf at ``wo`` and a sample, as Mitsuba's) runs one walk for
the random-walk models (``sample``'s walk with ``eval``'s NEE toward ``wo``; docs/model.md
§4.10), ``eval_pdf`` then ``sample`` for the others and wherever derivatives are taken. Mitsuba
3.9.1's own path tracers never call it for a Python BSDF; the ``mfnormal_path`` integrator
(registered with this plugin) does.

Costs per query: ``faithful`` 3 nested ``eval_pdf`` per ``eval``/``pdf`` (5 for a
nested BSDF with both diffuse and other components), 1 nested ``sample`` more per
``sample`` (each ``eval`` skips, per SIMD packet, the bounce terms no lane needs). ``analytic`` 3 nested ``eval_pdf`` per ``eval``/``pdf``, and
1 nested ``sample`` + 3 nested ``eval_pdf`` per ``sample``. Random walks: per
bounce 1 nested ``sample`` and (``eval`` only) 1 nested ``eval``, 2 with a mirror
tangent facet, plus 1 (2 with a mirror) for the first vertex's other start facet;
plus the MIS pdf (3-5 nested ``pdf``). A ``heightmap`` costs what a normal map
does (one gradient lookup instead of a colour lookup); ``macro_normal="geometric"``
adds a frame change of ω_i, ω_o and ω_p (about 60 kernel operations per query),
and without a map it is cheaper than the normal-map path
(``benchmarks/normal_sources.py``).

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

import warnings

import drjit as dr
import mitsuba as mi

from mfnormal.models import interface
from mfnormal.models.interface import DEFAULT_MODEL, MODELS
from mfnormal.surface.microsurface import negate, replace_grad
from mfnormal.surface.shading import off_horizon
from mfnormal.normals.normal_map import NUDGES, NormalMap
from mfnormal.normals import source
from mfnormal.normals.source import MITSUBA_TANGENTS, from_properties
from mfnormal.normals.strength import STRENGTH, STRENGTH_MAX, fail
from mfnormal.plugins import widened
from mfnormal.plugins.variant_class import variant_subclass

__all__ = ["NormalMapMicrofacet", "bsdf_class", "MODELS", "DEFAULT_MODEL", "STRENGTH_MAX", "PARAMS"]

#: Every parameter but the nested BSDF, typed (mfnormal.models.properties): read at load, and
#: the exposed ones (``strength`` and the walk's) checked on ``mi.traverse`` updates.
PARAMS = (source.MAP_FILES["normalmap"], source.MAP_FILES["heightmap"], source.HEIGHT_SCALE, source.MACRO_NORMAL,
          interface.MODEL, interface.NEIGHBOURHOOD_PARAM, interface.TANGENT_FACET, *interface.WALK_PARAMS,
          source.CONVENTION, STRENGTH, source.TANGENTS, source.FILTER)


class NormalMapMicrofacet:
    """The plugin's methods; :func:`bsdf_class` binds them to the active variant's ``mi.BSDF``.

    It owns the nested BSDF, the normal source (``self.source``: a normal map, a height map or
    none, :mod:`mfnormal.normals`), the macro normal (``self.macro``) and the model
    (``self.model``, :mod:`mfnormal.models.interface`), and calls them in Mitsuba's method order."""

    def __init__(self, props: mi.Properties):
        type(self).__mro__[1].__init__(self, props)   # the variant's mi.BSDF
        self.nested, self.source, self.macro, self.strength = from_properties(props)
        self.normalmap = self.source.texture if isinstance(self.source, NormalMap) else None
        self.model = interface.from_properties(props, self.nested, self.source)
        if self.model.turns_at_rims:
            self.macro = self.macro.turning()
        self._flat_texels = self.source.flat_texels()
        self.filter = source.FILTER.read(props)
        self.twin = self._filtered() if self.filter != "none" else None

        # The models refract only where the nested BSDF transmits (the paper's models refuse it:
        # interface.make); otherwise they report the nested BSDF's reflection components.
        keep = +mi.BSDFFlags.All if interface.transmits(self.nested) else ~mi.BSDFFlags.Transmission
        self.m_components = [self.nested.flags(i) & keep for i in range(self.nested.component_count())]
        self.m_flags = (self.nested.flags() & keep) | mi.BSDFFlags.FrontSide

    def _filtered(self):
        """Turn on the footprint filter (``filter="lean"``) where the nested BSDF allows it: the
        map reads its footprint's mean facet, and a rough conductor's lobe is widened by the
        footprint's spread (its twin, :mod:`~mfnormal.plugins.widened`, returned). A purely
        diffuse nested BSDF needs no widening (None is returned); any other keeps the texel
        (a warning says so): a glossy lobe left as narrow as a texel's would be too sharp on the
        mean facet, and a smooth one would flatten the footprint to a mirror of its mean."""
        if self.model.name != "faithful":
            fail(f"filter='{self.filter}' needs model=\"faithful\" (the default); model='{self.model.name}' "
                 "shades the texel as it is: use filter=\"none\" with it")
        if self.normalmap is None:
            fail(f"filter='{self.filter}' needs a 'normalmap' (its slope pyramid); use filter=\"none\" "
                 "with a height map or without a map")
        twin = widened.twin(self.nested)
        flags = self.nested.flags()
        diffuse_only = mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection) and not any(
            mi.has_flag(flags, f) for f in (mi.BSDFFlags.Glossy, mi.BSDFFlags.Delta, mi.BSDFFlags.Transmission))
        if twin is None and not diffuse_only:
            warnings.warn(f"normalmap_microfacet: filter='{self.filter}' filters diffuse nested BSDFs and "
                          f"roughconductor with one uniform alpha; {self.nested.class_name()} is shaded per "
                          "texel", stacklevel=2)
            return None
        self.source.filtered = True
        self.source.pyramid(classes=True)  # (built here and on updates: a render's symbolic calls cannot)
        return twin

    def traverse(self, callback):
        # None of them moves geometry, so none is discontinuous in Mitsuba's sense (visibility).
        callback.put("nested_bsdf", self.nested, mi.ParamFlags.Differentiable)
        if self.source.texture is not None:
            name = "normalmap" if self.normalmap is not None else "heightmap"
            callback.put(name, self.source.texture, mi.ParamFlags.Differentiable)
        callback.put("strength", self.strength.value, mi.ParamFlags.Differentiable)
        self.model.traverse(callback)

    def parameters_changed(self, keys):
        if self.twin is not None and (not keys or any(k.startswith("nested_bsdf") for k in keys)):
            self.twin.follow()
        self.model.parameters_changed(keys)
        if "strength" in keys:
            self.strength.changed()
        self.source.parameters_changed(keys)
        if not keys or any(k == "strength" or k.startswith(("normalmap", "heightmap")) for k in keys):
            self._flat_texels = self.source.flat_texels()
            self.model.map_changed(self.source)
            if getattr(self.source, "filtered", False):
                self.source.pyramid(classes=True)

    def shading_point(self, ctx, si, active=True, nudge=None):
        """The microsurface at ``si``: ω_p from the normal source, in the macro normal's frame
        (``nudge``: :meth:`mfnormal.normals.normal_map.NormalMap.facet_normal`); with a widened
        twin (``filter``), the twin on it and the footprint's slope spread for it."""
        if self.twin is None:
            return self.macro.shading_point(self.source, self.nested, ctx, si, active, nudge)
        sp = self.macro.shading_point(self.source, self.twin, ctx, si, active, nudge)
        sp.spread = self.source.footprint(si, active)[1]
        return sp

    def _differentiable(self, ctx, si, active, fn):
        """``fn(sp)`` (a tuple of Dr.Jit arrays) at the microsurface of ``si``, with the
        derivatives of the normal at a flat ω_p (docs/model.md §9).

        A flat normal is where the models are not differentiable: the tangent facet grows like
        |tilt|, its direction jumps with the tilt's. Where the map or ``strength`` carry
        derivatives, they are taken (values unchanged) from nudged normals instead: at
        ``strength`` = 0 the one-sided derivative extrapolated from ω_p at strengths h and 2h
        (2f'(h) − f'(2h), second order; the texels' derivatives are 0); at a flat texel per axis
        of the map's frame, from the mean of ω_p tilted by ±h along it (the central derivative of
        each channel, what central differences measure). Primal kernels never trace the nudges."""
        sp = self.shading_point(ctx, si, active)
        out = fn(sp)
        if not sp.attached or not dr.is_diff_v(mi.Float):
            return out
        if max(self.strength.ok) == 0.0:
            # f'(0) = 2 f'(h) − f'(2h) + O(h²): the specular-tangent models' f'(0) is ~0, and
            # f'(h) alone would be off by f''·h.
            g1 = fn(self.shading_point(ctx, si, active, "strength"))
            g2 = fn(self.shading_point(ctx, si, active, "strength2"))
            return tuple(replace_grad(o, 2.0 * a - b) for o, a, b in zip(out, g1, g2))
        if not self._flat_texels:
            return out
        if not self.model.smooth_at_flat and dr.grad_enabled(self.source.map_rgb(si, active)):
            warnings.warn(self.flat_notice(), stacklevel=2)
        flat = sp.sin_p == 0.0
        nudged = [fn(self.shading_point(ctx, si, active, n)) for n in NUDGES]
        out_ = []
        for k, o in enumerate(out):
            grad = 0.5 * (nudged[0][k] + nudged[1][k] + nudged[2][k] + nudged[3][k]) - o
            out_.append(dr.select(flat, replace_grad(o, grad), o))
        return tuple(out_)

    def flat_notice(self) -> str:
        """The one line that says a two-facet model has no derivative at the map's flat texels."""
        return (f"normalmap_microfacet: model='{self.model.name}' has no derivative at a flat normal "
                "(the map has flat texels, where its one-sided derivatives differ); it gives their mean, "
                "the central derivative; for a derivative that exists there use model=\"faithful\"")

    def _eval_pdf(self, ctx, sp, wo, active, want_value=True, want_pdf=True):
        """The model's (eval, pdf) at the microsurface ``sp``, ``wo`` in the shading frame, turned
        into the macro frame and the value weighed as the frame change needs (``sp.macro``:
        normals/macro.py; unchanged in the shading frame)."""
        wo_m = sp.macro.to_macro(wo)
        value, pdf = self.model.eval_pdf(ctx, sp, off_horizon(wo_m), mi.Bool(active), want_value, want_pdf)
        return (sp.macro.weigh(ctx, sp, value, wo, wo_m) if want_value else value), pdf

    def sample(self, ctx, si, sample1, sample2, active=True):
        sp = self.shading_point(ctx, si, active)
        bs, weight = self.model.sample(ctx, sp, sample1, sample2, active)
        # The flat normal's derivatives (a point of the geometric macro normal carries none: not attached).
        if sp.attached and (self._flat_texels or max(self.strength.ok) == 0.0):
            bs, weight = self._flat_sample(ctx, si, sp, bs, weight, active)
        return sp.macro.to_shading(ctx, sp, bs, weight)

    def _flat_sample(self, ctx, si, sp, bs, weight, active):
        """A smooth lobe's sample (bs, weight) with the flat normal's derivatives
        (:meth:`_differentiable`) of eval and pdf at its detached direction: a deterministic
        model's weight eval/pdf takes ∂eval/pdf. A walk's weight w (at flat lanes; elsewhere the
        walk's own derivative) takes w·∂eval/eval: w's mean given the direction is eval over the
        walk's density, and at a flat normal eval is exact (the nested BSDF), its derivative an
        estimate independent of w, so the product's mean is ∂eval over that density."""
        smooth = mi.Bool(active) & negate(mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)) & (bs.pdf > 0)
        if not self.model.deterministic:
            smooth &= sp.sin_p == 0.0
        wo = dr.detach(bs.wo)
        value, pdf = self._differentiable(ctx, si, active, lambda at: self._eval_pdf(ctx, at, wo, smooth))
        if self.model.deterministic:
            grad = value / dr.detach(dr.select(pdf > 0, pdf, 1.0))
        else:
            f = dr.detach(value)
            grad = dr.select(f > 0, dr.detach(weight) * value / dr.select(f > 0, f, 1.0), 0.0)
        weight = dr.select(smooth, replace_grad(weight, grad), weight)
        bs.pdf = dr.select(smooth, replace_grad(bs.pdf, pdf), bs.pdf)
        return bs, weight

    def eval(self, ctx, si, wo, active=True):
        return self._differentiable(ctx, si, active,
                                    lambda sp: self._eval_pdf(ctx, sp, wo, active, want_pdf=False)[:1])[0]

    def pdf(self, ctx, si, wo, active=True):
        return self._differentiable(ctx, si, active,
                                    lambda sp: self._eval_pdf(ctx, sp, wo, active, want_value=False)[1:])[0]

    def eval_pdf(self, ctx, si, wo, active=True):
        return self._differentiable(ctx, si, active, lambda sp: self._eval_pdf(ctx, sp, wo, active))

    def eval_pdf_sample(self, ctx, si, wo, sample1, sample2, active=True):
        """(eval, pdf) at ``wo`` and a sample, as Mitsuba's ``eval_pdf_sample``: (value, pdf, bs,
        weight). Mitsuba 3.9.1's path tracers do not call it for a Python BSDF (its trampoline
        runs ``eval_pdf`` and then ``sample``); the ``mfnormal_path`` integrator does.

        Where the model fuses the two (the random walks: ONE walk, ``sample``'s, with ``eval``'s
        NEE toward ``wo``; the same sample and weight bit for bit, an unbiased ``eval``, the same
        deterministic pdf), that call; elsewhere (and wherever derivatives are taken) ``eval_pdf``
        then ``sample``, as Mitsuba's default."""
        sp = self.shading_point(ctx, si, active) if self.model.stochastic_eval else None
        if sp is None or not self.model.fuses(sp):
            value, pdf = self.eval_pdf(ctx, si, wo, active)
            bs, weight = self.sample(ctx, si, sample1, sample2, active)
            return value, pdf, bs, weight
        active = mi.Bool(active)
        wo_m = off_horizon(sp.macro.to_macro(wo))
        value, pdf, (bs, weight) = self.model.eval_pdf_sample(ctx, sp, wo_m, sample1, sample2, active)
        value = sp.macro.weigh(ctx, sp, value, wo, wo_m)
        bs, weight = sp.macro.to_shading(ctx, sp, bs, weight)
        return value, pdf, bs, weight

    def eval_diffuse_reflectance(self, si, active=True):
        """The nested BSDF's diffuse reflectance (albedo) at the hit, as Mitsuba's ``normalmap``
        forwards it: what the ``aov`` integrator's ``albedo`` and denoisers read."""
        return self.nested.eval_diffuse_reflectance(si, active)

    @property
    def stochastic_eval(self) -> bool:
        """The walks' ``eval`` is an estimate: ``mfnormal_prb`` differentiates their sampled light
        through the sample weight (mfnormal_prb.py)."""
        return self.model.stochastic_eval

    def to_string(self):
        m, tangents = self.model, self.source.tangents
        return (f"NormalMapMicrofacet[model={m.name}, tangent_facet={m.tangent_facet}, rr_depth={m.ok[1]}, "
                f"mis_boost_max={m.ok[2]}, strength={self.strength.value}, "
                f"convention={'directx' if getattr(self.source, 'directx', False) else 'opengl'}, "
                f"tangents={tangents.name if tangents else MITSUBA_TANGENTS}, macro_normal={self.macro.name}, "
                f"filter={self.filter},\n"
                + self.source.describe() + f"  bsdf={self.nested}]")


def bsdf_class() -> type:
    """``NormalMapMicrofacet`` as a subclass of the active variant's ``mi.BSDF``."""
    return variant_subclass(NormalMapMicrofacet, mi.BSDF)
