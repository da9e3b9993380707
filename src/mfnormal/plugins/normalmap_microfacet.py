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
   - Height map only: the heights' scale, Mitsuba ``bumpmap``'s ``scale``
     (world units per texture unit where dp/du, dp/dv have unit length).
     Default: 1; any finite number (negative inverts the relief).
 * - macro_normal
   - |string|
   - ``shading`` (default): the microsurface's macro normal is the shading
     normal ``si.sh_frame.n``. ``geometric``: it is the true triangle normal
     ``si.n``, and ω_p is the interpolated shading normal with the map (if any)
     applied on top of it. Without a map this is the shadow-terminator fix for
     smooth-shaded low-poly meshes (``eval`` then returns f·⟨ω_o, si.n⟩;
     directions stay in ``si.sh_frame`` for the integrator).
 * - (nested bsdf)
   - |bsdf|
   - The material of the microfacets: any Mitsuba BSDF (its reflection part).
 * - model
   - |string|
   - ``faithful`` (default): the texel as the true geometry around it shows
     it (docs/faithful.md): the nested BSDF on the facet, masked and shadowed
     by neighbours with the map's own rms slope, the neighbours where the
     texel is hidden, and the light they block re-emitted, so white facets
     stay white and energy never exceeds the nested albedo; deterministic
     ``eval``, exact ``pdf``; not reciprocal (light tracing gets its adjoint).
     ``analytic``: the paper's default model, paths of up to two
     facet bounces with a mirror tangent facet, deterministic ``eval`` and the
     exact ``pdf`` of its sampler. ``separable``: the main paper's random walk
     over all bounce orders (separable masking-shadowing). ``nonseparable``:
     the supplemental's walk with height-correlated masking-shadowing, which
     equals ray tracing the sawtooth microsurface exactly.
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
     (Exposed, a kernel input: a new value compiles no kernel.)
 * - rr_depth
   - |int|
   - Random-walk models only: Russian roulette from this many facet bounces on
     (default 3; 0 turns it off). A walk then continues with probability
     min(1, its largest throughput channel) and divides its throughput by it:
     unbiased, and dark materials (roughplastic, coloured metals) no longer run
     long walks that carry little energy. White facets are never rouletted.
     (Exposed, a kernel input.)
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
     normal. (Exposed, |exposed|)
 * - tangents
   - |string|
   - The tangent frame the map is decoded in. ``mitsuba`` (default): the
     base shading frame ``si.sh_frame``, whose tangent Mitsuba builds per
     triangle from the UV derivatives. A mesh attribute name such as
     ``vertex_tangent``: the baker's (MikkTSpace, glTF) per-vertex frame
     T, B = sign·(N×T), N, with T the interpolated 3-float attribute ``NAME``
     and sign the 1-float attribute ``NAME_sign`` (glTF's ``TANGENT.w``), so
     maps baked in MikkTSpace, mirrored UV islands included, come out right.
     Shapes without the attribute fall back to ``mitsuba``.
     (:func:`mfnormal.io.gltf.load_gltf` adds both attributes.)

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
  normal's side, directions still in ``si.sh_frame``), zero below it;
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
  :math:`\cos\theta_p \ge 0.02`. A flat map reproduces the nested BSDF.

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

import drjit as dr
import mitsuba as mi

from mfnormal.models import analytic, faithful, walk
from mfnormal.normals import sources as normals
from mfnormal.models.microsurface import COS_P_MIN, SIN_P_EPS, decode_normal, negate, replace_grad
from mfnormal.models.shading import ShadingPoint, from_tangent_frame, tangent_rotation
from mfnormal.plugins.variant_class import variant_subclass

MODELS = ("faithful", "analytic", "separable", "nonseparable")
DEFAULT_MODEL = "faithful"
INT32_MAX = 2 ** 31 - 1          # walk counters are 32-bit
TANGENT_FACETS = ("specular", "same")
CONVENTIONS = ("opengl", "directx")
MITSUBA_TANGENTS = "mitsuba"


STRENGTH_MAX = 1e6
# Derivatives at a flat normal (docs/model.md §9): the tilt of the nudged normals whose
# one-sided derivatives are averaged, and the strength at which strength = 0 is differentiated.
FLAT_NUDGE = 1e-3
STRENGTH_NUDGE = 1e-3
NUDGES = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0))   # (axis, sign): ±x, ±y of the map's frame


def _fail(msg: str):
    raise ValueError(f"normalmap_microfacet: {msg}")


def _checked_strength(values) -> list:
    """``strength`` values as floats, each finite and ≥ 0 (else ValueError), capped at STRENGTH_MAX."""
    import numpy as np

    values = np.array(values, dtype=np.float64).ravel().tolist()
    bad = [v for v in values if not (0.0 <= v < float("inf"))]
    if bad or not values:
        _fail(f"strength must be a finite number >= 0, got {bad[0] if bad else 'no value'}")
    return [min(v, STRENGTH_MAX) for v in values]


WALK_KEYS = ("max_bounces", "rr_depth", "mis_boost_max")


def _checked_walk_values(max_bounces, rr_depth, mis_boost_max) -> tuple:
    """(max_bounces, rr_depth, mis_boost_max) as int, int, float, each in its range (else ValueError)."""
    max_bounces, rr_depth, mis_boost_max = int(max_bounces), int(rr_depth), float(mis_boost_max)
    if not (1 <= max_bounces <= INT32_MAX):
        _fail(f"max_bounces must be between 1 and {INT32_MAX}, got {max_bounces}")
    if not (0 <= rr_depth <= INT32_MAX):
        _fail(f"rr_depth must be between 0 (0 turns Russian roulette off) and {INT32_MAX}, got {rr_depth}")
    if not (1.0 <= mis_boost_max < float("inf")):
        _fail(f"mis_boost_max must be a finite number >= 1 (1 turns the boost off), got {mis_boost_max}")
    return max_bounces, rr_depth, mis_boost_max


def _scalar(x):
    """The value of a width-1 Dr.Jit array (or a Python number) as a Python number."""
    return dr.slice(x, 0) if dr.is_array_v(x) else x


class NormalMapMicrofacet:
    """The plugin's methods; :func:`bsdf_class` binds them to the active variant's ``mi.BSDF``."""

    def __init__(self, props: mi.Properties):
        type(self).__mro__[1].__init__(self, props)   # the variant's mi.BSDF

        self._load_inputs(props)

        # Model parameters
        self.model = props.get("model", DEFAULT_MODEL)
        if self.model not in MODELS:
            _fail(f"unknown model '{self.model}'; choose one of {', '.join(MODELS)}")
        self.tangent_facet = props.get("tangent_facet", "specular")
        if self.tangent_facet not in TANGENT_FACETS:
            _fail(f"unknown tangent_facet '{self.tangent_facet}'; use 'specular' or 'same'")
        if self.model in ("analytic", "faithful") and self.tangent_facet != "specular":
            _fail(f"tangent_facet 'same' needs model='separable' or 'nonseparable'; the {self.model} "
                  "model has no tangent facet of the nested material")
        self._walk_ok = _checked_walk_values(props.get("max_bounces", walk.MAX_BOUNCES),
                                             props.get("rr_depth", walk.RR_DEPTH),
                                             props.get("mis_boost_max", walk.MIS_BOOST_MAX))
        # Kernel inputs, not constants: a new value (mi.traverse) runs the kernels already compiled.
        self.max_bounces, self.rr_depth = mi.Int32(self._walk_ok[0]), mi.Int32(self._walk_ok[1])
        self.mis_boost_max = mi.Float(self._walk_ok[2])
        dr.make_opaque(self.max_bounces, self.rr_depth, self.mis_boost_max)
        convention = props.get("normalmap_convention", "opengl")
        if convention not in CONVENTIONS:
            _fail(f"unknown normalmap_convention '{convention}'; use 'opengl' or 'directx'")
        if convention != "opengl" and self.normalmap is None:
            _fail("normalmap_convention applies to normal maps only (a height map has no channel order)")
        self.directx = convention == "directx"
        strength = _checked_strength(float(props.get("strength", 1.0)))[0]
        self.strength = mi.Float(strength)
        self._strength_ok = [strength]
        dr.make_opaque(self.strength)
        tangents = props.get("tangents", MITSUBA_TANGENTS)
        if tangents != MITSUBA_TANGENTS and not tangents.startswith("vertex_"):
            _fail(f"tangents must be '{MITSUBA_TANGENTS}' or a vertex attribute name such as "
                  f"'vertex_tangent', got '{tangents}'")
        self.tangent_attr = None if tangents == MITSUBA_TANGENTS else tangents
        self._hoist_uv_transform()
        self._flat_texels = self._has_flat_texels()
        self.faithful = (faithful.Model(self.nested, self._map_slopes()[0], COS_P_MIN)
                         if self.model == "faithful" else None)

        # The nested BSDF's components; the microsurface only reflects.
        # The microsurface only reflects: report the nested BSDF's reflection components.
        reflect = ~mi.BSDFFlags.Transmission
        self.m_components = [self.nested.flags(i) & reflect for i in range(self.nested.component_count())]
        self.m_flags = (self.nested.flags() & reflect) | mi.BSDFFlags.FrontSide
        if mi.has_flag(self.nested.flags(), mi.BSDFFlags.Transmission):
            mi.Log(mi.LogLevel.Warn,
                   f"normalmap_microfacet: the nested BSDF {str(self.nested).split('[')[0]} transmits light, "
                   "but the microsurface only reflects: its transmission is dropped (that light is "
                   "absorbed) and only its reflection is normal-mapped. For a refracting surface use "
                   "Mitsuba's 'normalmap' BSDF.")

    def _load_inputs(self, props):
        """The nested BSDF and the normal source: a normal map, a height map, or (with
        ``macro_normal="geometric"``) the interpolated shading normal alone."""
        self.nested = None
        self.normalmap = None
        self.heightmap = None
        for name, obj in props.objects():
            if isinstance(obj, mi.BSDF):
                if self.nested is not None:
                    _fail("expects exactly one nested BSDF, got several")
                self.nested = obj
            elif isinstance(obj, mi.Texture) and name == "normalmap":
                self.normalmap = obj
            elif isinstance(obj, mi.Texture) and name == "heightmap":
                self.heightmap = obj
        if self.normalmap is None and "normalmap" in props.keys():
            value = props["normalmap"]
            if isinstance(value, str):
                self.normalmap = mi.load_dict({"type": "bitmap", "filename": value, "raw": True})
        if self.heightmap is None and "heightmap" in props.keys():
            value = props["heightmap"]
            if isinstance(value, str):
                self.heightmap = mi.load_dict({"type": "bitmap", "filename": value, "raw": True})
        if self.nested is None:
            _fail("needs a nested BSDF (e.g. <bsdf type=\"diffuse\"/> inside it)")
        self.macro_normal = props.get("macro_normal", "shading")
        if self.macro_normal not in normals.MACRO_NORMALS:
            _fail(f"unknown macro_normal '{self.macro_normal}'; use 'shading' or 'geometric'")
        self.macro_geometric = self.macro_normal == "geometric"
        if self.normalmap is not None and self.heightmap is not None:
            _fail("takes a 'normalmap' or a 'heightmap', not both")
        if self.normalmap is None and self.heightmap is None and not self.macro_geometric:
            _fail("needs a texture named 'normalmap' (a raw bitmap: <texture name=\"normalmap\" "
                  "type=\"bitmap\"> with <boolean name=\"raw\" value=\"true\"/>) or 'heightmap' "
                  "(or macro_normal=\"geometric\" for a smooth-shaded mesh without a map)")
        self.height_scale = float(props.get("height_scale", 1.0))
        if not (abs(self.height_scale) < float("inf")):
            _fail(f"height_scale must be a finite number, got {self.height_scale}")
        if self.heightmap is not None:
            self._check_heightmap()

    def traverse(self, callback):
        # None of them moves geometry, so none is discontinuous in Mitsuba's sense (visibility).
        callback.put("nested_bsdf", self.nested, mi.ParamFlags.Differentiable)
        if self.normalmap is not None:
            callback.put("normalmap", self.normalmap, mi.ParamFlags.Differentiable)
        if self.heightmap is not None:
            callback.put("heightmap", self.heightmap, mi.ParamFlags.Differentiable)
        callback.put("strength", self.strength, mi.ParamFlags.Differentiable)
        if self.model not in ("analytic", "faithful"):
            for key in WALK_KEYS:
                callback.put(key, getattr(self, key), mi.ParamFlags.NonDifferentiable)

    @property
    def walk_params(self):
        """The random walk's :class:`walk.WalkParams` (None for the other models); its values are
        this BSDF's opaque arrays (cast to the walk counter's type), read when a kernel is traced."""
        if self.model in ("analytic", "faithful"):
            return None
        return walk.WalkParams(separable=self.model == "separable", specular_tangent=self.tangent_facet == "specular",
                               max_bounces=mi.UInt32(self.max_bounces), rr_depth=mi.UInt32(self.rr_depth),
                               mis_boost_max=self.mis_boost_max)

    def _walk_values_changed(self):
        """Check the walk parameters after a ``mi.traverse`` update: out of range, the update is refused
        (ValueError, the values before it kept), else they stay kernel inputs (opaque)."""
        try:
            self._walk_ok = _checked_walk_values(*(_scalar(getattr(self, k)) for k in WALK_KEYS))
        finally:
            for key, value in zip(WALK_KEYS, self._walk_ok):
                mi.set_property(getattr(self, key), type(getattr(self, key))(value))
                dr.make_opaque(getattr(self, key))

    def parameters_changed(self, keys):
        if any(k in WALK_KEYS for k in keys):
            self._walk_values_changed()
        if "strength" in keys:
            # In place: a ParameterTree from mi.traverse keeps referring to this array.
            try:
                values = _checked_strength(self.strength)
            except ValueError:
                mi.set_property(self.strength, mi.Float(self._strength_ok))   # the update is refused
                dr.make_opaque(self.strength)
                raise
            if max(values) >= STRENGTH_MAX:
                mi.set_property(self.strength, mi.Float(values))
            self._strength_ok = values
            dr.make_opaque(self.strength)
        if not keys or any(k.startswith("normalmap") for k in keys):
            self._hoist_uv_transform()
        if not keys or any(k == "strength" or k.startswith(("normalmap", "heightmap")) for k in keys):
            self._flat_texels = self._has_flat_texels()
            if self.faithful is not None:
                self.faithful.set_slopes(*self._map_slopes(attached=True))

    def _hoist_uv_transform(self):
        """The normal map's uv transform (a bitmap's ``to_uv``) as kernel inputs, for :meth:`map_rgb`.

        Mitsuba's bitmap bakes its ``to_uv`` into the traced code as constants, so two plugins
        whose maps differ only in their transforms (the demo's sphere and its tiled floor) traced
        different code, and Dr.Jit compiled the whole model twice into a kernel: it merges the
        callables of a call's instances only where their code is the same (the demo with GGX 0.05,
        non-separable walk: 11601 operations and 0.54 s of LLVM time, against 7179 and 0.35 s with
        one transform for both). Identity, no ``to_uv`` or a scalar variant: None (``eval_3`` as it is)."""
        import numpy as np
        self._uv, self._uv_params, self._uv_matrix = None, None, None
        if self.normalmap is None or not dr.is_jit_v(mi.Float):
            return
        params = mi.traverse(self.normalmap)
        if "to_uv" not in params.keys():
            return
        m = np.array(params["to_uv"].matrix, dtype=np.float64)
        if m.shape != (3, 3) or np.array_equal(m, np.eye(3)):
            return
        self._uv = [mi.Float(float(m[i, j])) for i in range(2) for j in range(3)]
        dr.make_opaque(*self._uv)
        self._uv_params, self._uv_matrix = params, m

    def map_rgb(self, si, active=True):
        """The normal map's RGB at ``si.uv``: ``eval_3``, with a hoisted uv transform
        (:meth:`_hoist_uv_transform`) applied here from kernel inputs and the texture traced with
        the identity transform (restored at once; nothing is left changed). The same values bit for
        bit: the same fused multiply-adds as Mitsuba's ``Transform::transform_affine`` (the
        translation first, then the x and the y column). A texture whose ``to_uv`` changed since
        (set on the texture itself, e.g. one that two plugins share, where this plugin was not
        told) is evaluated as it is."""
        import numpy as np
        if self._uv is None:
            return self.normalmap.eval_3(si, active)
        current = self._uv_params["to_uv"]
        current = type(current)(current)            # a copy to restore: the entry aliases the texture's
        if not np.array_equal(np.array(current.matrix, dtype=np.float64), self._uv_matrix):
            return self.normalmap.eval_3(si, active)
        m00, m01, m02, m10, m11, m12 = self._uv
        u, v = si.uv.x, si.uv.y
        si_uv = mi.SurfaceInteraction3f(si)
        si_uv.uv = mi.Point2f(dr.fma(m01, v, dr.fma(m00, u, m02)), dr.fma(m11, v, dr.fma(m10, u, m12)))
        self._uv_params["to_uv"] = type(current)()
        try:
            return self.normalmap.eval_3(si_uv, active)
        finally:
            self._uv_params["to_uv"] = current

    def _has_flat_texels(self) -> bool:
        """Whether the map may decode to the flat normal somewhere (then AD takes the flat
        normal's derivatives from nudged normals, docs/model.md §9): a bitmap is checked texel
        by texel, any other texture is assumed to."""
        import numpy as np
        if self.normalmap is None:          # height maps and macro_normal="geometric": no nudges
            return False
        params = mi.traverse(self.normalmap)
        if "data" not in params.keys():
            return True
        data = np.array(params["data"], dtype=np.float64)
        if data.ndim != 3 or data.shape[-1] < 3:
            return True
        n = 2.0 * data[..., :3] - 1.0
        with np.errstate(invalid="ignore"):
            xy = np.hypot(n[..., 0], n[..., 1]) * min(self._strength_ok)
            flat = ~(xy > 2.0 * SIN_P_EPS * np.abs(n[..., 2]))    # NaN texels included
        return bool(flat.any())

    def _map_slopes(self, attached=False):
        """(σ1, σ2, φ_e), the map's principal rms slopes about the macro normal and their axis,
        from its decoded texels (faithful.principal_slopes); and, where the map or ``strength``
        carry derivatives and ``attached``, the same as Dr.Jit values that carry them
        (faithful.attached_slopes), else None."""
        import numpy as np
        res = 256 if dr.is_jit_v(mi.Float) else 32
        if self.normalmap is None:
            return self._height_map_slopes(res), None
        params = mi.traverse(self.normalmap)
        if "data" in params.keys():
            shape = params["data"].shape
            res = min(res, max(shape[0], shape[1]))
        u = (np.arange(res) + 0.5) / res
        uu, vv = np.meshgrid(u, u, indexing="ij")
        if dr.is_jit_v(mi.Float):
            si = dr.zeros(mi.SurfaceInteraction3f, res * res)
            si.uv = mi.Point2f(mi.Float(uu.ravel()), mi.Float(vv.ravel()))
            rgb = self.normalmap.eval_3(si)
            wp = decode_normal(rgb, self.strength, self.directx)
            normals = np.stack([np.array(wp.x), np.array(wp.y), np.array(wp.z)], -1)
            slopes = faithful.principal_slopes(normals)
            if not (attached and dr.grad_enabled(wp)):
                return slopes, None
            if max(self._strength_ok) > 0:
                return slopes, faithful.attached_slopes(wp)
            return slopes, faithful.attached_slopes(decode_normal(rgb, 1.0, self.directx), self.strength)
        else:
            normals = []
            for x, y in zip(uu.ravel(), vv.ravel()):
                s1 = mi.SurfaceInteraction3f()
                s1.uv = mi.Point2f(float(x), float(y))
                n = decode_normal(self.normalmap.eval_3(s1), self.strength, self.directx)
                normals.append([n.x, n.y, n.z])
        return faithful.principal_slopes(np.array(normals)), None

    def _height_map_slopes(self, res):
        """_map_slopes of a height map (on the unit square: normals.height_map_normals, twice the
        texel resolution: the bilinear gradient is linear across a cell); no map: flat (σ = 0)."""
        if self.heightmap is None:
            return 0.0, 0.0, 0.0
        params = mi.traverse(self.heightmap)
        if "data" in params.keys():
            shape = params["data"].shape
            res = min(2 * res, 2 * max(shape[0], shape[1]))
        scale = self.height_scale * float(_scalar(self.strength))
        return faithful.principal_slopes(normals.height_map_normals(self.heightmap, scale, res))

    def _check_heightmap(self):
        """A height map needs the texture's uv gradient (``eval_1_grad``: bitmaps, whose gradient is
        zero with nearest filtering)."""
        si = dr.zeros(mi.SurfaceInteraction3f)
        try:
            self.heightmap.eval_1_grad(si)
        except Exception as e:  # noqa: BLE001  (Mitsuba raises RuntimeError / NotImplementedError)
            _fail(f"heightmap needs a texture with a uv gradient (eval_1_grad: a bitmap, raw=true), "
                  f"{str(self.heightmap).split('[')[0]} has none ({str(e).strip().splitlines()[-1][:120]})")

    def shading_point(self, ctx, si, active=True, nudge=None):
        """The microsurface at ``si``: ω_p from the normal map, in the base shading frame.

        ``nudge`` (derivatives at a flat normal, :meth:`_differentiable`): ``"strength"``
        (``"strength2"``): ω_p at strength + STRENGTH_NUDGE (+ twice it), the texel detached; ``(axis, sign)``: ω_p tilted by
        FLAT_NUDGE along ±x or ±y of the map's frame, the other axis detached.
        A height map or macro_normal="geometric": normals.shading_point (no nudges: their
        derivatives are the normal's own)."""
        if self.heightmap is not None or self.macro_geometric:
            sp = normals.shading_point(self, ctx, si, active)
            sp.attached = False
            return sp
        rgb = self.map_rgb(si, active)
        strength = self.strength
        if isinstance(nudge, str):          # "strength", "strength2": at STRENGTH_NUDGE, twice it
            rgb, strength = dr.detach(rgb), strength + STRENGTH_NUDGE * (2.0 if nudge == "strength2" else 1.0)
        wp = decode_normal(rgb, strength, self.directx)
        attached = dr.grad_enabled(wp)
        if nudge is not None and not isinstance(nudge, str):
            axis, sign = nudge
            x = wp.x + sign * FLAT_NUDGE if axis == 0 else dr.detach(wp.x)
            y = wp.y + sign * FLAT_NUDGE if axis == 1 else dr.detach(wp.y)
            wp = dr.normalize(mi.Vector3f(x, y, wp.z))
        rotation = None
        if self.tangent_attr is not None:
            wp, rotation = self._from_vertex_tangents(si, wp, active)
        sp = ShadingPoint(self.nested, ctx, si, wp)
        sp.map_rotation = rotation
        sp.attached = attached
        return sp

    def _differentiable(self, ctx, si, active, fn):
        """``fn(sp)`` (a tuple of Dr.Jit arrays) at the microsurface of ``si``, with the
        derivatives of the normal at a flat ω_p (docs/model.md §9).

        A flat normal is where the models are not differentiable: the tangent facet grows like
        |tilt|, its direction jumps with the tilt's. Where the map or ``strength`` carry
        derivatives, they are taken (values unchanged) from nudged normals instead: at
        ``strength`` = 0 the one-sided derivative extrapolated from ω_p at strengths h and 2h
        (h = STRENGTH_NUDGE: 2f'(h) − f'(2h), second order; the texels' derivatives are 0); at a flat texel per axis of the map's frame, from the mean of ω_p
        tilted by ±FLAT_NUDGE along it (the central derivative of each channel, what central
        differences measure). Primal kernels never trace the nudges."""
        sp = self.shading_point(ctx, si, active)
        out = fn(sp)
        if not sp.attached or not dr.is_diff_v(mi.Float):
            return out
        if max(self._strength_ok) == 0.0:
            # f'(0) = 2 f'(h) − f'(2h) + O(h²): the specular-tangent models' f'(0) is ~0, and
            # f'(h) alone would be off by f''·h.
            g1 = fn(self.shading_point(ctx, si, active, "strength"))
            g2 = fn(self.shading_point(ctx, si, active, "strength2"))
            return tuple(replace_grad(o, 2.0 * a - b) for o, a, b in zip(out, g1, g2))
        if not self._flat_texels:
            return out
        flat = sp.sin_p == 0.0
        nudged = [fn(self.shading_point(ctx, si, active, n)) for n in NUDGES]
        out_ = []
        for k, o in enumerate(out):
            grad = 0.5 * (nudged[0][k] + nudged[1][k] + nudged[2][k] + nudged[3][k]) - o
            out_.append(dr.select(flat, replace_grad(o, grad), o))
        return tuple(out_)

    def _vertex_tangent(self, si, active):
        """(T, sign) of the vertex tangent frame at ``si`` (world space), (None, None) where a scalar
        variant's shape has no such attribute (JIT variants: T = 0 there, which from_tangent_frame and
        tangent_rotation treat as missing)."""
        name, shape = self.tangent_attr, si.shape
        if not dr.is_jit_v(mi.Float) and (shape is None or not shape.is_mesh()
                                          or not shape.has_attribute(name)):
            return None, None
        tangent = mi.Vector3f(shape.eval_attribute_3(name, si, active))
        sign = shape.eval_attribute_1(name + "_sign", si, active) if (
            dr.is_jit_v(mi.Float) or shape.has_attribute(name + "_sign")) else 1.0
        return tangent, sign

    def _from_vertex_tangents(self, si, wp, active):
        """(ω_p decoded in the mesh's vertex tangent frame and re-expressed in ``si.sh_frame``,
        that frame's turn against ``si.sh_frame``: shading.tangent_rotation or None)."""
        tangent, sign = self._vertex_tangent(si, active)
        if tangent is None:
            return wp, None      # scalar variants: a shape without tangents
        # (T and its sign are two attributes: Mitsuba 3.9.1's eval_attribute_x returns zeros.)
        return (from_tangent_frame(wp, si.sh_frame, tangent, sign),
                tangent_rotation(si.sh_frame, tangent, sign))

    def _texel(self, sp, wi=None):
        return self.faithful.texel(sp, sp.wi if wi is None else wi)

    def _faithful_eval_pdf(self, ctx, sp, wo, active, want_value=True, want_pdf=True):
        """The faithful model's (eval, pdf); light tracing (``TransportMode.Importance``) gets its
        adjoint, for it is the one model that is not reciprocal."""
        if ctx.mode == mi.TransportMode.Importance:
            return self.faithful.eval_pdf_adjoint(sp, self._texel(sp), self._texel(sp, wo), active,
                                                  lambda b: self._texel(sp, b), want_value, want_pdf)
        return self.faithful.eval_pdf(sp, self._texel(sp), wo, active, want_value, want_pdf)

    def _eval_pdf(self, ctx, sp, wo, active, want_value=True, want_pdf=True):
        """(eval, pdf) of the model at the microsurface ``sp`` (what is not wanted is 0)."""
        active = mi.Bool(active)
        if self.model == "faithful":
            return self._faithful_eval_pdf(ctx, sp, wo, active, want_value, want_pdf)
        if self.model == "analytic":
            return analytic.eval_pdf(sp, wo, active, want_value, want_pdf)
        return (walk.eval(sp, self.walk_params, wo, active) if want_value else mi.Spectrum(0.0),
                walk.mis_pdf(sp, self.walk_params, wo, active) if want_pdf else mi.Float(0.0))

    def sample(self, ctx, si, sample1, sample2, active=True):
        sp = self.shading_point(ctx, si, active)
        macro = normals.macro_of(sp)
        bs, weight = self._sample_sp(ctx, sp, sample1, sample2, active)
        if macro is not None:
            # macro_normal="geometric": the model samples in the triangle's frame G (normals.py).
            wo_m = mi.Vector3f(bs.wo)          # a copy: assigning bs.wo writes into the struct
            bs.wo = macro.from_macro(wo_m)
            k = macro.adjoint(ctx, sp, bs.wo, wo_m)
            return bs, weight if k is None else weight * k
        if self.model != "faithful" and self.model != "analytic":
            return bs, weight
        if sp.attached and (self._flat_texels or max(self._strength_ok) == 0.0):
            # A smooth lobe's weight eval/detach(pdf) and its pdf, with the flat normal's
            # derivatives (_differentiable) at the sample's (detached) direction.
            smooth = mi.Bool(active) & negate(mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)) & (bs.pdf > 0)
            wo = dr.detach(bs.wo)
            value, pdf = self._differentiable(ctx, si, active, lambda at: self._eval_pdf(ctx, at, wo, smooth))
            grad = value / dr.detach(dr.select(pdf > 0, pdf, 1.0))
            weight = dr.select(smooth, replace_grad(weight, grad), weight)
            bs.pdf = dr.select(smooth, replace_grad(bs.pdf, pdf), bs.pdf)
        return bs, weight

    def _sample_sp(self, ctx, sp, sample1, sample2, active):
        """The model's sample at the microsurface ``sp`` (directions in its base frame)."""
        if self.model == "analytic":
            return analytic.sample(sp, sample1, sample2, mi.Bool(active))
        if self.model == "faithful":
            if ctx.mode == mi.TransportMode.Importance:
                return self.faithful.sample_adjoint(sp, self._texel(sp), sample1, sample2, mi.Bool(active),
                                                    lambda b: self._texel(sp, b))
            return self.faithful.sample(sp, self._texel(sp), sample1, sample2, mi.Bool(active))
        return walk.sample(sp, self.walk_params, sample1, sample2, mi.Bool(active))

    def _macro_eval_pdf(self, ctx, sp, wo, active, want_value=True, want_pdf=True):
        """:meth:`_eval_pdf` with ``wo`` in the macro frame of ``macro_normal="geometric"``
        (normals.py; the value times the frame change's adjoint factor), else as it is."""
        macro = normals.macro_of(sp)
        if macro is None:
            return self._eval_pdf(ctx, sp, wo, active, want_value, want_pdf)
        wo_m = macro.to_macro(wo)
        value, pdf = self._eval_pdf(ctx, sp, wo_m, active, want_value, want_pdf)
        k = macro.adjoint(ctx, sp, wo, wo_m) if want_value else None
        return (value if k is None else value * k), pdf

    def eval(self, ctx, si, wo, active=True):
        return self._differentiable(ctx, si, active,
                                    lambda sp: self._macro_eval_pdf(ctx, sp, wo, active, want_pdf=False)[:1])[0]

    def pdf(self, ctx, si, wo, active=True):
        return self._differentiable(ctx, si, active,
                                    lambda sp: self._macro_eval_pdf(ctx, sp, wo, active, want_value=False)[1:])[0]

    def eval_pdf(self, ctx, si, wo, active=True):
        return self._differentiable(ctx, si, active, lambda sp: self._macro_eval_pdf(ctx, sp, wo, active))

    def eval_pdf_sample(self, ctx, si, wo, sample1, sample2, active=True):
        """(eval, pdf) at ``wo`` and a sample, as Mitsuba's ``eval_pdf_sample``: (value, pdf, bs,
        weight). Mitsuba 3.9.1's path tracers do not call it for a Python BSDF (its trampoline
        runs ``eval_pdf`` and then ``sample``); the ``mfnormal_path`` integrator does.

        The random walks run ONE walk (walk.eval_sample): ``sample``'s walk (the same sample and
        weight, bit for bit) with ``eval``'s NEE toward ``wo`` (an unbiased estimate of ``eval``
        from the sample's numbers; the pdf is the same deterministic ``mis_pdf``). Where
        derivatives are taken (walk.replays), and for ``faithful`` and ``analytic`` (their setup is
        already shared in a kernel by Dr.Jit's common-subexpression elimination), it is
        ``eval_pdf`` then ``sample``, as Mitsuba's default."""
        if self.model in ("faithful", "analytic"):
            return self._eval_pdf_then_sample(ctx, si, wo, sample1, sample2, active)
        sp = self.shading_point(ctx, si, active)
        if (sp.attached and dr.is_diff_v(mi.Float)) or walk.replays(sp):
            return self._eval_pdf_then_sample(ctx, si, wo, sample1, sample2, active)
        macro = normals.macro_of(sp)
        active = mi.Bool(active)
        wo_m = wo if macro is None else macro.to_macro(wo)
        value, (bs, weight) = walk.eval_sample(sp, self.walk_params, wo_m, sample1, sample2, active)
        pdf = walk.mis_pdf(sp, self.walk_params, wo_m, active)
        if macro is not None:
            k = macro.adjoint(ctx, sp, wo, wo_m)
            value = value if k is None else value * k
            bs_wo_m = mi.Vector3f(bs.wo)        # a copy: assigning bs.wo writes into the struct
            bs.wo = macro.from_macro(bs_wo_m)
            k = macro.adjoint(ctx, sp, bs.wo, bs_wo_m)
            weight = weight if k is None else weight * k
        return value, pdf, bs, weight

    def _eval_pdf_then_sample(self, ctx, si, wo, sample1, sample2, active):
        """Mitsuba's default ``eval_pdf_sample``: ``eval_pdf`` at ``wo``, then ``sample``."""
        value, pdf = self.eval_pdf(ctx, si, wo, active)
        bs, weight = self.sample(ctx, si, sample1, sample2, active)
        return value, pdf, bs, weight

    @property
    def stochastic_eval(self) -> bool:
        """The walks' ``eval`` is an estimate: ``mfnormal_prb`` differentiates their sampled light
        through the sample weight (ad_integrator.py)."""
        return self.model in ("separable", "nonseparable")

    def to_string(self):
        return (f"NormalMapMicrofacet[model={self.model}, tangent_facet={self.tangent_facet}, "
                f"rr_depth={self._walk_ok[1]}, mis_boost_max={self._walk_ok[2]}, strength={self.strength}, "
                f"convention={'directx' if self.directx else 'opengl'}, "
                f"tangents={self.tangent_attr or MITSUBA_TANGENTS}, macro_normal={self.macro_normal},\n"
                + (f"  heightmap={self.heightmap}, height_scale={self.height_scale},\n" if self.heightmap is not None
                   else f"  normalmap={self.normalmap},\n")
                + f"  bsdf={self.nested}]")


def bsdf_class() -> type:
    """``NormalMapMicrofacet`` as a subclass of the active variant's ``mi.BSDF``."""
    return variant_subclass(NormalMapMicrofacet, mi.BSDF)
