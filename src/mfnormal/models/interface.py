"""The models behind one interface.

Each model turns a :class:`~mfnormal.surface.shading.ShadingPoint` (the two-facet microsurface
at a hit, directions in its base frame) into a BSDF. The plugin calls every model the same way
(:class:`Model`), without asking which it is:

- ``eval_pdf(ctx, sp, wo, active, want_value, want_pdf)``: f·⟨ω_o, ω_g⟩ and the pdf (what is not
  wanted is 0); in ``TransportMode.Importance`` the model's adjoint;
- ``sample(ctx, sp, sample1, sample2, active)``: (BSDFSample3f, weight);
- ``fuses(sp)`` and ``eval_pdf_sample(ctx, sp, wo, sample1, sample2, active)``: the fused call,
  where the model has one that is cheaper than ``eval_pdf`` then ``sample``;
- ``deterministic``: ``eval`` is exact and a sample's weight is eval/pdf, else both are
  estimates (at a flat normal the plugin takes the weight's derivative from ``eval``'s either
  way: ∂eval/pdf, or a walk's weight times ∂eval/eval);
- ``smooth_at_flat``: the model is differentiable at a flat normal; the two-facet models are
  not (their tangent facet grows like the tilt: one-sided derivatives differ, docs/model.md §9),
  and the plugin says so where their derivative is taken there;
- ``traverse``, ``parameters_changed`` (the model's own parameters) and ``map_changed(source)``
  (the normal source changed: the faithful model re-measures the map's slopes).

The models: :class:`Faithful` (the default, :mod:`mfnormal.models.faithful`), :class:`Analytic`
(the paper's, :mod:`mfnormal.models.analytic`) and :class:`Walk` (the separable and
non-separable random walks, :mod:`mfnormal.models.walk`), each registered under its name in
:data:`REGISTRY` with what it accepts (a tangent facet of the nested material, a transmitting
nested BSDF); :func:`from_properties` builds one from the plugin's parameters.
"""

from __future__ import annotations

import dataclasses
from typing import Protocol, runtime_checkable

import drjit as dr
import mitsuba as mi

from mfnormal.models import analytic, faithful, walk
from mfnormal.models.walk_pdf import mis_pdf
from mfnormal.models.walk_replay import replays
from mfnormal.surface.microsurface import COS_P_MIN
from mfnormal.models.properties import INT32_MAX, Choice, Integer, Number

DEFAULT_MODEL = "faithful"
TANGENT_FACETS = ("specular", "same")
#: The faithful model's local statistics: the width of the window around a texel, in the map's
#: texels (0: the whole map's slopes for every texel; docs/faithful.md §5).
NEIGHBOURHOOD = 8.0

# The models' parameters (mfnormal.models.properties); the walk's are kernel inputs, exposed.
# (``model``, :data:`MODEL`, is read from :data:`REGISTRY`, below the models.)
PLUGIN = "normalmap_microfacet"
TANGENT_FACET = Choice(PLUGIN, "tangent_facet", "specular", TANGENT_FACETS)
NEIGHBOURHOOD_PARAM = Number(PLUGIN, "neighbourhood", NEIGHBOURHOOD,
                             "a finite number of texels >= 0 (0: the whole map)", lo=0.0)
WALK_PARAMS = (
    Integer(PLUGIN, "max_bounces", walk.MAX_BOUNCES, 1, expects=f"between 1 and {INT32_MAX} (an integer)"),
    Integer(PLUGIN, "rr_depth", walk.RR_DEPTH, 0,
            expects=f"between 0 (0 turns Russian roulette off) and {INT32_MAX} (an integer)"),
    Number(PLUGIN, "mis_boost_max", walk.MIS_BOOST_MAX, "a finite number >= 1 (1 turns the boost off)", lo=1.0))
WALK_KEYS = tuple(p.name for p in WALK_PARAMS)


def _fail(msg: str):
    raise ValueError(f"{PLUGIN}: {msg}")


@runtime_checkable
class Model(Protocol):
    """What every model offers the plugin (the module docstring), and what :func:`make` reads of
    its class: ``tangent_facets`` (the ``tangent_facet`` values it takes) and ``refracts``
    (whether it takes a transmitting nested BSDF)."""

    name: str
    tangent_facet: str
    ok: tuple                   # the walk parameters, checked (shown by the plugin's to_string)
    deterministic: bool
    stochastic_eval: bool
    smooth_at_flat: bool
    tangent_facets: tuple
    refracts: bool
    turns_at_rims: bool         # a camera below the shading plane sees it on the triangle (normals/macro.py)

    def eval_pdf(self, ctx, sp, wo, active, want_value=True, want_pdf=True) -> tuple: ...

    def sample(self, ctx, sp, sample1, sample2, active) -> tuple: ...

    def fuses(self, sp) -> bool: ...

    def eval_pdf_sample(self, ctx, sp, wo, sample1, sample2, active) -> tuple: ...

    def traverse(self, callback) -> None: ...

    def parameters_changed(self, keys) -> None: ...

    def map_changed(self, source) -> None: ...


class _Deterministic:
    """What the two deterministic models share: no fused call, no parameters of their own, a
    mirror tangent facet only."""

    deterministic = True
    stochastic_eval = False
    tangent_facets = ("specular",)

    def __init__(self, tangent_facet, nested, source, walk_values, neighbourhood=0.0):
        self.tangent_facet, self.ok = tangent_facet, walk_values    # the walk values, checked and shown

    def fuses(self, sp) -> bool:
        return False

    def eval_pdf_sample(self, ctx, sp, wo, sample1, sample2, active):
        """``eval_pdf`` then ``sample``: no call fuses them (:meth:`fuses`)."""
        return (*self.eval_pdf(ctx, sp, wo, active), self.sample(ctx, sp, sample1, sample2, active))

    def traverse(self, callback):
        pass

    def parameters_changed(self, keys):
        pass

    def map_changed(self, source):
        pass


class Analytic(_Deterministic):
    """The paper's analytic model: paths of up to two facet bounces, a mirror tangent facet;
    reciprocal, so its adjoint is itself."""

    name = "analytic"
    smooth_at_flat = False
    refracts = False
    turns_at_rims = False

    def eval_pdf(self, ctx, sp, wo, active, want_value=True, want_pdf=True):
        return analytic.eval_pdf(sp, wo, active, want_value, want_pdf)

    def sample(self, ctx, sp, sample1, sample2, active):
        return analytic.sample(sp, sample1, sample2, mi.Bool(active))


class Faithful(_Deterministic):
    """The default model (docs/faithful.md); not reciprocal, so light tracing
    (``TransportMode.Importance``) gets its adjoint. ``core`` holds the map's slopes and tables."""

    name = "faithful"
    smooth_at_flat = True
    refracts = True
    turns_at_rims = True

    def __init__(self, tangent_facet, nested, source, walk_values, neighbourhood=0.0):
        super().__init__(tangent_facet, nested, source, walk_values)
        self.neighbourhood = neighbourhood
        self.core = faithful.Model(nested, source.slopes()[0], COS_P_MIN, local=self._local(source),
                                   wall=source.walls())

    def _local(self, source, attached=False):
        """The local statistics' field (faithful.Model.set_slopes), or None: the map's slopes for
        every texel (``neighbourhood`` 0, or a normal source without a map of normals)."""
        if self.neighbourhood <= 0:
            return None
        return source.local(self.neighbourhood, attached)

    def map_changed(self, source):
        self.core.set_slopes(*source.slopes(attached=True), local=self._local(source, attached=True),
                             wall=source.walls(attached=True))

    def _texel(self, sp, wi=None):
        return self.core.texel(sp, sp.wi if wi is None else wi)

    def eval_pdf(self, ctx, sp, wo, active, want_value=True, want_pdf=True):
        if ctx.mode == mi.TransportMode.Importance:
            return self.core.eval_pdf_adjoint(sp, self._texel(sp), self._texel(sp, wo), active,
                                              lambda b: self._texel(sp, b), want_value, want_pdf)
        return self.core.eval_pdf(sp, self._texel(sp), wo, active, want_value, want_pdf)

    def sample(self, ctx, sp, sample1, sample2, active):
        if ctx.mode == mi.TransportMode.Importance:
            return self.core.sample_adjoint(sp, self._texel(sp), sample1, sample2, mi.Bool(active),
                                            lambda b: self._texel(sp, b))
        return self.core.sample(sp, self._texel(sp), sample1, sample2, mi.Bool(active))


class Walk:
    """The random walks (``separable``, ``nonseparable``) over the microsurface: a stochastic
    ``eval`` (unbiased, deterministic per query), the walk's exit as the sample, a deterministic
    MIS ``pdf``, and one walk for ``eval_pdf_sample``. ``max_bounces``, ``rr_depth`` and
    ``mis_boost_max`` are kernel inputs: a new value (``mi.traverse``) compiles nothing. The two
    integers are exposed as float64 arrays, so that an update to 1.5 is refused, not truncated."""

    deterministic = False
    stochastic_eval = True
    smooth_at_flat = False
    tangent_facets = TANGENT_FACETS
    refracts = False
    turns_at_rims = False
    separable: bool             # the separable walk (:class:`SeparableWalk`), else the height-correlated one

    def __init__(self, tangent_facet, nested, source, values, neighbourhood=0.0):
        self.tangent_facet = tangent_facet
        self.specular_tangent = tangent_facet == "specular"
        self.max_bounces, self.rr_depth = mi.Float64(values[0]), mi.Float64(values[1])
        self.mis_boost_max = mi.Float(values[2])
        self.ok = values
        dr.make_opaque(self.max_bounces, self.rr_depth, self.mis_boost_max)

    @property
    def params(self):
        """The walk's :class:`walk.WalkParams`; its values are this model's opaque arrays (cast to
        the walk counter's type), read when a kernel is traced."""
        return walk.WalkParams(separable=self.separable, specular_tangent=self.specular_tangent,
                               max_bounces=mi.UInt32(self.max_bounces), rr_depth=mi.UInt32(self.rr_depth),
                               mis_boost_max=self.mis_boost_max)

    def traverse(self, callback):
        for key in WALK_KEYS:
            callback.put(key, getattr(self, key), mi.ParamFlags.NonDifferentiable)

    def parameters_changed(self, keys):
        """Check the walk parameters after a ``mi.traverse`` update: out of range, the update is refused
        (ValueError, the values before it kept), else they stay kernel inputs (opaque)."""
        if not any(k in WALK_KEYS for k in keys):
            return
        try:
            self.ok = tuple(p.check_update(getattr(self, p.name)) for p in WALK_PARAMS)
        finally:
            for key, value in zip(WALK_KEYS, self.ok):
                mi.set_property(getattr(self, key), type(getattr(self, key))(value))
                dr.make_opaque(getattr(self, key))

    def map_changed(self, source):
        pass

    def eval_pdf(self, ctx, sp, wo, active, want_value=True, want_pdf=True):
        params = self.params
        if sp.nudged:
            # Only a flat normal's derivative is taken here: the defensive decisions keep its
            # variance bounded (WalkParams.defensive); values elsewhere are unchanged.
            params = dataclasses.replace(params, defensive=walk.DEFENSIVE)
        return (walk.eval(sp, params, wo, active) if want_value else mi.Spectrum(0.0),
                mis_pdf(sp, params, wo, active) if want_pdf else mi.Float(0.0))

    def sample(self, ctx, sp, sample1, sample2, active):
        return walk.sample(sp, self.params, sample1, sample2, mi.Bool(active))

    def fuses(self, sp) -> bool:
        """One walk serves both (walk.eval_sample), except where derivatives are taken."""
        return not ((sp.attached and dr.is_diff_v(mi.Float)) or replays(sp))

    def eval_pdf_sample(self, ctx, sp, wo, sample1, sample2, active):
        """(value, pdf, (bs, weight)): ``sample``'s walk with ``eval``'s NEE toward ``wo``."""
        params = self.params
        value, sampled = walk.eval_sample(sp, params, wo, sample1, sample2, active)
        return value, mis_pdf(sp, params, wo, active), sampled


class SeparableWalk(Walk):
    """The walk with separable masking-shadowing: the height interval reset to [0, 1] at every
    vertex (docs/model.md §2.5)."""

    name = "separable"
    separable = True


class NonseparableWalk(Walk):
    """The walk with height-correlated masking-shadowing (the supplemental's interval tracking)."""

    name = "nonseparable"
    separable = False


#: Every model under its name (``model``), the default first.
REGISTRY: dict[str, type[Model]] = {m.name: m for m in (Faithful, Analytic, SeparableWalk, NonseparableWalk)}
MODELS = tuple(REGISTRY)
MODEL = Choice(PLUGIN, "model", DEFAULT_MODEL, MODELS)


def transmits(nested) -> bool:
    """Whether the nested BSDF has a transmitting component (Mitsuba's flags)."""
    return mi.has_flag(nested.flags(), mi.BSDFFlags.Transmission)


def refusal(name, nested) -> str | None:
    """Why the model called ``name`` refuses the nested BSDF ``nested`` by design (one line), or
    None: the paper's models only reflect, so they refuse a transmitting one."""
    if not REGISTRY[name].refracts and transmits(nested):
        return (f"the nested BSDF {nested.class_name()} transmits light, but model='{name}' only "
                "reflects; use model=\"faithful\" (the default), which refracts")
    return None


def make(name, tangent_facet, nested, source, walk_values, neighbourhood=0.0) -> Model:
    """The model called ``name`` (:data:`REGISTRY`) with its parameters (each already of its type
    and range: :data:`MODEL`, :data:`TANGENT_FACET`, :data:`WALK_PARAMS`, :data:`NEIGHBOURHOOD_PARAM`),
    checked together."""
    model = REGISTRY[name]
    if tangent_facet not in model.tangent_facets:
        takers = " or ".join(f"'{n}'" for n, m in REGISTRY.items() if tangent_facet in m.tangent_facets)
        _fail(f"tangent_facet '{tangent_facet}' needs model={takers}; the {name} "
              "model has no tangent facet of the nested material")
    refused = refusal(name, nested)
    if refused:
        _fail(refused)
    return model(tangent_facet, nested, source, walk_values, neighbourhood)


def from_properties(props, nested, source):
    """The model a ``normalmap_microfacet``'s properties ask for (``model``, ``tangent_facet``,
    ``max_bounces``, ``rr_depth``, ``mis_boost_max``, ``neighbourhood``), checked."""
    return make(MODEL.read(props), TANGENT_FACET.read(props), nested, source,
                tuple(p.read(props) for p in WALK_PARAMS), NEIGHBOURHOOD_PARAM.read(props))
