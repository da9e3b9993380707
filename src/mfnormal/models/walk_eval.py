"""The evaluation loop: supplemental Algorithms 2 and 3, NEE toward ω_o along a walk (docs/model.md §4.3-4.5).

``eval_walk`` walks from ω_i as the sampling loop does (:mod:`~mfnormal.models.walk_steps`) and
adds at every vertex the NEE toward ω_o (:mod:`~mfnormal.models.walk_nee`): an unbiased estimate
of f·⟨ω_o, ω_g⟩. Its first nested vertex is taken in expectation over the start facet (§4.5):
the first iteration adds the p start's share, ``t_start_share`` the t start's. Its numbers are a
hash of the query, or the sampling loop's (the fused walk of ``walk.eval_sample``). With
derivatives the walk runs twice: for L, then replayed for L's derivative
(:mod:`~mfnormal.models.walk_replay`). ``eval`` is the BSDF's value.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mfnormal.surface.microsurface import negate, replace_grad
from mfnormal.models.rng import SALT_WALK_EVAL, SALT_WALK_SAMPLE, SLOT_START_FACET, hash_floats, uniform
from mfnormal.models.walk_nee import NeeTarget, add_nee, connect, t_start_share
from mfnormal.models.walk_pdf import first_interval
from mfnormal.models.walk_replay import Replay, attached_interval, calls, replays
from mfnormal.models.walk_steps import bounce, first_vertex, mirror_fold, nested_numbers, vertex_frame, walk_loop


def _eval_run(sp, params, wo, u_start, walk_active, active, seed, numbers, rp):
    """One pass of :func:`eval_walk`'s walk (``rp``: the replay that takes L's derivative, or None):
    (walker, L, rp, the first vertex's λ_p-weighted light)."""
    walker, p_start, lp, s1_first = first_vertex(sp, params, u_start, walk_active, rp is not None)
    first = None if numbers is None else (s1_first, mi.Point2f(numbers[1]))
    if not params.specular_tangent:
        walker.p_in = dr.zeros(mi.Float, dr.width(walker.a))
    to = NeeTarget.toward(sp, params, wo)
    b_p = first_interval(sp, params, True)[1]

    def body(w, L, rp, geometry, seed, to, lp, b_p, active, p_start, first):
        at = sp.with_state(geometry)
        at_start = w.depth == 0   # the first vertex (before a folded mirror bounce counts)
        d_in, p_fold = w.d, None
        if params.specular_tangent:
            folded = w.walking & negate(w.on_p)
            d_in, p_fold = mirror_fold(at, w, params, seed, rp)
        # NEE toward ω_o from this vertex; in the first iteration, the p start's share.
        a, b = attached_interval(at, w, rp)
        on = dr.select(at_start, active, w.walking & active)   # (eval: w.walking ⊆ active)
        nee = (at, params, to, w.on_p | at_start, dr.select(at_start, at.wi, -d_in), dr.select(at_start, 0.0, a),
               dr.select(at_start, b_p, b), dr.select(at_start, mi.Spectrum(lp), w.e), on, w.p_in)
        if not params.specular_tangent and params.connect:
            c_next, on_next = connect(at, params, w, to, seed, a, b, rp)
            if rp is None:
                L += c_next
            else:
                rp.add(c_next, on_next)
        if rp is None:
            L = add_nee(L, *nee)
        else:
            c = add_nee(mi.Spectrum(0.0), *nee)
            rp.add(c, on)
            # The start's choice and the mirror's escape came before this NEE, which only
            # the latter affects (the first NEE is the start's expectation); the
            # connection from the start facet depends on the choice.
            rp.factor(p_start, at_start & active,
                          0.0 if params.specular_tangent or not params.connect else dr.detach(c_next))
            if p_fold is not None:
                rp.factor(p_fold, folded, dr.select(at_start, 0.0, dr.detach(c)))
        s1, s2 = nested_numbers(seed, w.depth)
        if first is not None:       # the fused walk: the sample walk's first nested sample
            s1, s2 = dr.select(w.depth == 0, first[0], s1), dr.select(w.depth == 0, first[1], s2)
        bounce(at, w, params, seed, vertex_frame(at, params, w.on_p), s1, s2, d_in, rp)
        return w, L, rp, geometry, seed, to, lp, b_p, active, p_start, first

    state = (walker, dr.zeros(mi.Spectrum, dr.width(active)), rp, sp.state(), seed, to, lp, b_p, active,
             p_start, first)
    w, L, rp = walk_loop(state, body, "mfnormal_eval_walk")[:3]
    return w, L, rp, lp


def eval_walk(sp, params, wo, active, numbers=None):
    """Supplemental Algorithms 2 (3 with a mirror t): NEE toward ω_o along a walk from ω_i.

    Returns (L, walker): L estimates f·⟨ω_o, ω_g⟩ without bias. The NEE at the first
    nested vertex is taken in expectation over the start facet (docs/model.md §4.5):
    the first iteration adds λ_p·NEE at p lit from ω_i for every walk, whichever facet
    it started on, ``t_start_share`` the t start's share, and later iterations the
    vertices after the first nested sample. Random numbers: a hash of (ω_i, ω_o, si.p).
    With derivatives the walk runs twice: for L, then replayed for L's derivative (Replay).

    ``numbers`` = (sample1, sample2, walk_active): the fused walk of :func:`eval_sample`
    (primal only). The walk then takes the sample walk's numbers (its start facet, first
    nested sample and seed), so its walker is ``sample_walk``'s, and runs on ``walk_active``
    (ω_i above the horizon) while the NEE is only taken on ``active``.
    """
    sp = calls(sp, params)
    wi = sp.wi
    active = mi.Bool(active) & (wi.z > 0)
    if numbers is None:
        seed = hash_floats(SALT_WALK_EVAL, dr.detach(wi.x), dr.detach(wi.y), dr.detach(wo.x), dr.detach(wo.y),
                           sp.si.p.x, sp.si.p.y, sp.si.p.z)
        u_start, walk_active = uniform(seed, SLOT_START_FACET), active
    else:
        sample1, sample2, walk_active = numbers
        seed = hash_floats(SALT_WALK_SAMPLE, sample1, sample2.x, sample2.y)
        u_start, walk_active = sample1, mi.Bool(walk_active) & (wi.z > 0)

    args = (params, wo, u_start, walk_active, active, seed, numbers)
    if not replays(sp):
        walker, L, _, lp = _eval_run(sp, *args, None)
        return L + t_start_share(sp, params, wo, lp, active), walker
    # (Not dr.suspend_grad(): inside a virtual call, e.g. Mitsuba's BSDF dispatch, it loses the
    # replay's derivatives in Dr.Jit 1.5. The nested BSDF's parameters may still reach L.)
    walker, L, _, _ = _eval_run(sp.detached(), *args, None)
    L = dr.detach(L)
    _, _, rp, lp = _eval_run(sp, *args, Replay(dr.zeros(mi.Spectrum, dr.width(active)), dr.zeros(mi.Spectrum, dr.width(active)),
                                  L))
    return replace_grad(L, rp.G) + t_start_share(sp, params, wo, lp, active), walker


def eval(sp, params, wo, active):
    """Unbiased NEE estimate of f·⟨wo, z⟩, deterministic per query."""
    active = mi.Bool(active) & (sp.wi.z > 0) & (wo.z > 0)
    L = eval_walk(sp, params, wo, active)[0]
    return dr.select(active & dr.all(dr.isfinite(L)), dr.maximum(L, 0.0), 0.0)
