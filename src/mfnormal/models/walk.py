"""The random-walk models: separable (main paper) and non-separable (supplemental).

One walk serves both (docs/model.md §4). It starts on the facet that a ray
from ω_i hits first and bounces between the two facets until it leaves the
microsurface. The non-separable model tracks the interval H of heights the walk
can be at on the current facet, stored as depths below the crest (§1, §2.2): rays
from a uniform height in H stay uniform after each bounce, because the facets
are planar. The separable model is the same walk with H reset to [0, 1] at
every vertex, which forgets height correlation (§4.1).

- ``sample_walk`` (:mod:`~mfnormal.models.walk_sample`): the sampling loop (supplemental
  Algorithm 1, the exit decided from the interval's escape fraction, the same random
  variable as tracing a ray from a uniformly drawn height); ``sample`` wraps its exit as a
  BSDF sample;
- ``eval_walk`` (:mod:`~mfnormal.models.walk_eval`): the evaluation loop, next-event estimation toward ω_o at every
  vertex (Algorithm 2; with a mirror tangent facet, Algorithm 3 and its H_r
  term), an unbiased estimate of f·⟨ω_o, ω_g⟩. Its first nested vertex is
  Rao-Blackwellised (§4.5): taken in expectation over the start facet (and the
  mirror's escape), so the low-order part of ``eval`` is deterministic; with a
  same-material tangent facet each vertex also connects to the next facet by a
  sample from ω_o, MIS-weighted against the walk's own (``connect``, §4.8; the NEE steps
  are :mod:`~mfnormal.models.walk_nee`);
- ``mis_pdf`` (:mod:`~mfnormal.models.walk_pdf`): a deterministic function for MIS (§5): the
  exact density of the low-order terms plus a cosine lobe for the rest, boosted by the nested
  lobe's sharpness where longer walks are likely (variance-aware MIS).
- ``eval_sample`` (here): both from one walk (§4.10, primal only): ``eval_walk`` run with
  ``sample_walk``'s numbers, so its walker is ``sample``'s and its L an unbiased ``eval``.

Both loops are built from the same steps (:mod:`~mfnormal.models.walk_steps`, which also
writes down the walk's random-number layout): ``mirror_fold`` (a mirror tangent
facet), ``add_nee`` (NEE at a vertex), ``bounce`` (nested sample, ``cross`` to
the other facet or out, ``roulette``). Each takes a :class:`WalkParams`; each
loop returns its :class:`Walker`, whose ``depth`` is the walk's bounce count.

Derivatives (docs/model.md §9, :mod:`~mfnormal.models.walk_replay`): both loops carry everything they read as loop state
and have a ``max_iterations`` hint (``max_bounces``: no walk iterates more), so forward
and reverse mode run through them. The estimators' derivatives are unbiased: every
decision (start facet, escape, roulette) is taken with detached numbers, and the
throughput carries p/detach(p) for the branch taken (value 1: ``score``), so that
the probability's derivative is accounted for; a nested sample's direction is detached
and its weight replaced by the attached eval over the detached pdf (Mitsuba's detached
sampling), except for delta lobes, whose direction is a differentiable function of the
geometry; roulette's probability is detached. None of this changes a value: in primal
kernels the extra terms are constant-folded away.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mfnormal.models.walk_eval import eval, eval_walk
from mfnormal.models.walk_sample import exit_sample, sample, sample_walk
from mfnormal.models.walk_steps import DEFENSIVE, MAX_BOUNCES, MIS_BOOST_MAX, RR_DEPTH, Walker, WalkParams

__all__ = ["WalkParams", "Walker", "MAX_BOUNCES", "RR_DEPTH", "MIS_BOOST_MAX", "DEFENSIVE", "sample_walk",
           "eval_walk", "sample", "exit_sample", "eval", "eval_sample"]


def eval_sample(sp, params, wo, sample1, sample2, active):
    """``eval`` at wo and ``sample`` from one walk (primal only: without derivatives).

    The walk is ``sample``'s (the same numbers, so the same exit, sample and weight, bit for
    bit) and does ``eval_walk``'s NEE toward wo at its vertices. The value is an unbiased
    estimate of f·⟨wo, z⟩ like ``eval``'s, but from the sample's numbers instead of a hash of
    the query; its correlation with the sample leaves a path tracer unbiased (the NEE and the
    continuation are added). Returns (value, (BSDFSample3f, weight))."""
    walking = mi.Bool(active) & (sp.wi.z > 0)
    on = walking & (wo.z > 0)
    L, w = eval_walk(sp, params, wo, on, (sample1, sample2, walking))
    value = dr.select(on & dr.all(dr.isfinite(L)), dr.maximum(L, 0.0), 0.0)
    return value, exit_sample(sp, params, w)
