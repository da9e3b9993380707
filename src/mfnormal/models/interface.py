"""The models behind one interface.

Each model turns a :class:`~mfnormal.models.shading.ShadingPoint` (the two-facet microsurface
at a hit, directions in its base frame) into a BSDF. The plugin calls every model the same way,
without asking which it is:

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
non-separable random walks, :mod:`mfnormal.models.walk`). :func:`from_properties` builds one
from the plugin's parameters.
"""

from __future__ import annotations

import dataclasses

import drjit as dr
import mitsuba as mi

from mfnormal.models import analytic, faithful, walk
from mfnormal.models.walk_pdf import mis_pdf
from mfnormal.models.walk_replay import replays
from mfnormal.models.microsurface import COS_P_MIN
from mfnormal.models.properties import INT32_MAX, Choice, Integer, Number

MODELS = ("faithful", "analytic", "separable", "nonseparable")
DEFAULT_MODEL = "faithful"
TANGENT_FACETS = ("specular", "same")
#: The faithful model's local statistics: the width of the window around a texel, in the map's
#: texels (0: the whole map's slopes for every texel; docs/faithful.md §5).
NEIGHBOURHOOD = 8.0

# The models' parameters (mfnormal.models.properties); the walk's are kernel inputs, exposed.
PLUGIN = "normalmap_microfacet"
MODEL = Choice(PLUGIN, "model", DEFAULT_MODEL, MODELS)
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


class _Deterministic:
    """What the two deterministic models share: no fused call, no parameters of their own."""

    deterministic = True
    stochastic_eval = False

    def fuses(self, sp) -> bool:
        return False

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

    def eval_pdf(self, ctx, sp, wo, active, want_value=True, want_pdf=True):
        return analytic.eval_pdf(sp, wo, active, want_value, want_pdf)

    def sample(self, ctx, sp, sample1, sample2, active):
        return analytic.sample(sp, sample1, sample2, mi.Bool(active))


class Faithful(_Deterministic):
    """The default model (docs/faithful.md); not reciprocal, so light tracing
    (``TransportMode.Importance``) gets its adjoint. ``core`` holds the map's slopes and tables."""

    name = "faithful"
    smooth_at_flat = True

    def __init__(self, nested, source, neighbourhood=0.0):
        self.neighbourhood = neighbourhood
        self.core = faithful.Model(nested, source.slopes()[0], COS_P_MIN, local=self._local(source))

    def _local(self, source, attached=False):
        """The local statistics' field (faithful.Model.set_slopes), or None: the map's slopes for
        every texel (``neighbourhood`` 0, or a normal source without a map of normals)."""
        if self.neighbourhood <= 0 or not hasattr(source, "local"):
            return None
        return source.local(self.neighbourhood, attached)

    def map_changed(self, source):
        self.core.set_slopes(*source.slopes(attached=True), local=self._local(source, attached=True))

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

    def __init__(self, name, tangent_facet, values):
        self.name, self.tangent_facet = name, tangent_facet
        self.max_bounces, self.rr_depth = mi.Float64(values[0]), mi.Float64(values[1])
        self.mis_boost_max = mi.Float(values[2])
        self.ok = values
        dr.make_opaque(self.max_bounces, self.rr_depth, self.mis_boost_max)

    @property
    def params(self):
        """The walk's :class:`walk.WalkParams`; its values are this model's opaque arrays (cast to
        the walk counter's type), read when a kernel is traced."""
        return walk.WalkParams(separable=self.name == "separable",
                               specular_tangent=self.tangent_facet == "specular",
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


def transmits(nested) -> bool:
    """Whether the nested BSDF has a transmitting component (Mitsuba's flags)."""
    return mi.has_flag(nested.flags(), mi.BSDFFlags.Transmission)


def refusal(name, nested) -> str | None:
    """Why the model called ``name`` refuses the nested BSDF ``nested`` by design (one line), or
    None: the paper's models only reflect, so they refuse a transmitting one."""
    if name != "faithful" and transmits(nested):
        return (f"the nested BSDF {nested.class_name()} transmits light, but model='{name}' only "
                "reflects; use model=\"faithful\" (the default), which refracts")
    return None


def make(name, tangent_facet, nested, source, walk_values, neighbourhood=0.0):
    """The model called ``name`` (``MODELS``) with its parameters (each already of its type and
    range: :data:`MODEL`, :data:`TANGENT_FACET`, :data:`WALK_PARAMS`, :data:`NEIGHBOURHOOD_PARAM`),
    checked together."""
    if name in ("analytic", "faithful") and tangent_facet != "specular":
        _fail(f"tangent_facet 'same' needs model='separable' or 'nonseparable'; the {name} "
              "model has no tangent facet of the nested material")
    refused = refusal(name, nested)
    if refused:
        _fail(refused)
    if name == "faithful":
        model = Faithful(nested, source, neighbourhood)
    elif name == "analytic":
        model = Analytic()
    else:
        return Walk(name, tangent_facet, walk_values)
    model.tangent_facet, model.ok = tangent_facet, walk_values    # the walk values, checked and shown
    return model


def from_properties(props, nested, source):
    """The model a ``normalmap_microfacet``'s properties ask for (``model``, ``tangent_facet``,
    ``max_bounces``, ``rr_depth``, ``mis_boost_max``, ``neighbourhood``), checked."""
    return make(MODEL.read(props), TANGENT_FACET.read(props), nested, source,
                tuple(p.read(props) for p in WALK_PARAMS), NEIGHBOURHOOD_PARAM.read(props))
