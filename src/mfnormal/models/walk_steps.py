"""The random walk's state and the steps both of its loops are built from (docs/model.md §4).

A :class:`WalkParams` says which walk it is, a :class:`Walker` holds one walk per lane. A
loop iteration is one nested vertex: ``mirror_fold`` (with a mirror tangent facet, the bounce
off it to p or out, folded into the iteration of the p vertex that follows), then, in the
evaluation loop only, NEE toward ω_o (:mod:`~mfnormal.models.walk_nee`), then ``bounce``: the
nested BSDF's sample, ``cross`` to the other facet or out of the microsurface, ``roulette``.
``first_vertex`` puts a walker on the facet a ray from ω_i hits first and ``walk_loop`` runs
a loop body until every walker has left; the loops themselves are
:mod:`~mfnormal.models.walk_sample` (Algorithm 1) and :mod:`~mfnormal.models.walk_eval`
(Algorithms 2 and 3).

Random numbers: each decision reads its own counter of the walk's stream, named in one place,
:mod:`mfnormal.models.rng` (docs/model.md §6). Per facet bounce ``depth``: the escape of the
ray that leaves the vertex, ``slot_escape(depth)``; the nested sample's three numbers,
``slot_nested(depth, 0..2)`` (``nested_numbers``); Russian roulette, ``slot_roulette(depth)``;
the evaluation loop's connection sample, ``slot_connect(depth, 0..2)``. The start facet takes
``SLOT_START_FACET`` (eval) or the sample's own ``sample1`` (sample), whose rescaled rest and
``sample2`` also drive the first nested sample.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from mfnormal.surface import microsurface as ms
from mfnormal.surface.microsurface import negate
from mfnormal.models.rng import choose, slot_escape, slot_nested, slot_roulette, uniform
from mfnormal.surface.shading import broadcast, select_frame
from mfnormal.models.walk_pdf import first_interval
from mfnormal.models.walk_replay import _crest_jacobian, _g1_jacobian, _land_jacobian, attached_interval

# Default cap of a walk's facet bounces; walks still on the microsurface after it are dropped.
MAX_BOUNCES = 1024
# Default depth (facet bounces) from which walks play Russian roulette on their throughput.
RR_DEPTH = 3
# Default cap of the boost of the longer walks' share in the MIS pdf (GGX α ≤ 1/16 reaches it).
MIS_BOOST_MAX = 64.0


@dataclass(frozen=True)
class WalkParams:
    """What a random-walk model is: the plugin builds one per BSDF.

    ``separable`` and ``specular_tangent`` choose the kernel's code. The other three are
    read as values (Python numbers, or the plugin's opaque ``mi.UInt32`` / ``mi.Float``
    of width 1, which kernels take as inputs: a new value, e.g. from ``mi.traverse``, runs
    the kernels already compiled)."""

    separable: bool                      # reset H to [0, 1] at every vertex (the main paper's model)
    specular_tangent: bool               # the tangent facet is a mirror (Algorithm 3), else the nested BSDF
    max_bounces: int = MAX_BOUNCES       # facet bounces before a walk is dropped
    rr_depth: int = RR_DEPTH             # Russian roulette from this many bounces on (0: never)
    mis_boost_max: float = MIS_BOOST_MAX  # cap of the variance-aware MIS boost (1: none)
    # Call the nested BSDF through one callable per method (ShadingPoint.with_indirect_calls)
    # instead of inlining it at each of the walks' call sites: on the demo, kernels −13-20 %
    # operations, the first-render compile −5-15 % (ggx_0.05; roughplastic: none), the render time
    # +6-14 % (docs/model.md §4.9). Off: the render-time targets come first. Chooses the kernel's code.
    indirect_calls: bool = False
    # With a same-material tangent facet, connect each vertex to the next facet by an
    # MIS-weighted sample from ω_o (``connect``, docs/model.md §4.8); False: the plain
    # estimator, NEE alone (the reference the connection is tested against).
    connect: bool = True
    # The share ε of every binary decision (start facet, escape) taken with probability ½: the
    # walk takes a branch of probability p with (1 − ε)p + ε/2 and weights it by p over that
    # (``decision``). 0: each by its own p. The nudged evaluations that give a flat normal's
    # derivative set it (``DEFENSIVE``, docs/model.md §9): there the walk's branches onto the
    # tangent facet have probabilities ∝ its tilt, and their score terms 1/tilt. Chooses the
    # kernel's code.
    defensive: float = 0.0


# The defensive share of the nudged evaluations (WalkParams.defensive): at a flat map and at
# strength = 0 it cuts the standard error of the same-facet walks' derivatives 3-9× (0.2 and
# 0.8 measured worse; docs/model.md §9).
DEFENSIVE = 0.5


@dataclass
class Walker:
    """The state of one walk per lane: the loop state of both loops."""

    d: mi.Vector3f          # travel direction
    e: mi.Spectrum          # throughput
    on_p: mi.Bool           # the current facet is p (else t)
    a: mi.Float             # H = [a, b] on the current facet, as depths below the crest
    b: mi.Float
    depth: mi.UInt32        # facet bounces so far; at the exit, the walk's length
    walking: mi.Bool        # still on the microsurface
    escaped: mi.Bool        # left it (sample() returns only escaped walks)
    nondelta: mi.Bool       # sampled a non-delta lobe on the way
    ja: mi.Vector3f = None  # replayed non-separable walks: ∂a/∂ω_p and ∂b/∂ω_p (``Replay``)
    jb: mi.Vector3f = None
    p_in: mi.Float = None   # eval walks with a same-material t: the nested pdf of the sample that
                            # led here (0 at the start and after a delta lobe; ``connect``)


# -- Steps --------------------------------------------------------------------------------


def decision(params, p):
    """The probability with which a decision of probability p (detached) takes its branch:
    p, or with ``params.defensive`` = ε the defensive mixture (1 − ε)p + ε/2, with which a
    branch of probability p carries the weight p/((1 − ε)p + ε/2) (``weighted``)."""
    if not params.defensive:
        return p
    return (1.0 - params.defensive) * p + 0.5 * params.defensive


def weighted(params, prob, q):
    """``prob`` (the attached probability of the branch taken) over ``q`` (the detached
    probability with which it was taken, ``decision``): its value is the branch's weight, its
    relative derivative prob's; ``prob`` itself where decisions are not defensive (q = prob)."""
    return prob / q if params.defensive else prob


def start(sp, on_p, a, b, active):
    """A walker on facet ``on_p`` at depths [a, b], travelling along −ω_i."""
    n = dr.width(sp.wi)
    return Walker(d=dr.zeros(mi.Vector3f, n) - sp.wi, e=dr.full(mi.Spectrum, 1.0, n), on_p=mi.Bool(on_p),
                  a=dr.zeros(mi.Float, n) + a, b=dr.zeros(mi.Float, n) + b, depth=dr.zeros(mi.UInt32, n),
                  walking=mi.Bool(active), escaped=dr.zeros(mi.Bool, n), nondelta=dr.zeros(mi.Bool, n))


def vertex_frame(sp, params, on_p):
    """The frame of the facet a vertex is on (with a mirror t, a nested vertex is always on p)."""
    return sp.frame_p if params.specular_tangent else select_frame(on_p, sp.frame_p, sp.frame_t)


def cross(sp, params, on_p, d, a, b, ok, u):
    """A ray from depths [a, b] on facet ``on_p`` along d: leave the microsurface with the
    escape fraction (u decides), or land on the other facet (κ, docs/model.md §2.2).

    Returns (leaves, stays, a, b, prob, (τ, κ)): the depths are those on the other facet where
    it stays; prob is the probability of the branch taken (1 where not ok), with the
    derivatives of a, b and the geometry; with defensive decisions (``decision``) over the
    probability it was taken with, so that its value is the branch's weight. For a point
    interval (a = b) the escape is the binary test D < τ whatever u is (defensive decisions:
    the other branch has weight 0).
    """
    tau, k = sp.crest_map(on_p, d)
    p_leave = ms.escape_fraction(a, b, tau)
    q_leave = decision(params, dr.detach(p_leave))
    leaves = ok & (u < q_leave)
    stays = ok & negate(leaves)
    a_new, b_new = ms.land(a, b, tau, k)
    a = dr.select(stays, 0.0 if params.separable else a_new, a)
    b = dr.select(stays, 1.0 if params.separable else b_new, b)
    prob = dr.select(leaves, p_leave, dr.select(stays, 1.0 - p_leave, 1.0))
    prob = weighted(params, prob, dr.select(leaves, q_leave, dr.select(stays, 1.0 - q_leave, 1.0)))
    return leaves, stays, a, b, prob, (tau, k)


def _moved_interval(sp, w, stays, a, b, tau, k, d, d_pre, on_p, sign):
    """The walker's Jacobians after a crossing (replayed non-separable walks; a, b: before it)."""
    g_tau, g_k = _crest_jacobian(sp, on_p, d, d_pre, sign)
    ja, jb = _land_jacobian(dr.detach(a), dr.detach(b), w.ja, w.jb, dr.detach(tau), dr.detach(k), g_tau, g_k)
    w.ja, w.jb = dr.select(stays, ja, w.ja), dr.select(stays, jb, w.jb)


def mirror_fold(sp, w, params, seed, rp=None):
    """Reflect the walkers on a mirror t off it (flip_t) to p or out of the microsurface.

    A mirror vertex needs no nested call and gives no NEE: its bounce is folded into
    the iteration of the next p vertex, so a packet runs the nested calls once per p
    vertex. Its escape takes the slot of its own depth: the same random numbers, and
    the same results, as one vertex per iteration.

    Returns the direction after it, with its derivative (replay), for the vertex that follows
    in this iteration, and the probability of the escape decision's branch (1 off the mirror).
    """
    mirror = w.walking & negate(w.on_p)
    d_m = ms.flip_t(w.d, sp.wt)
    a, b = attached_interval(sp, w, rp)
    leaves, stays, a_m, b_m, prob, (tau, k) = cross(sp, params, mi.Bool(False), d_m, a, b,
                                                    mirror & (dr.dot(d_m, sp.wt) > 0),
                                                    uniform(seed, slot_escape(w.depth)))
    if rp is not None:
        rp.leave(d_m, leaves)
        if w.ja is not None:
            _moved_interval(sp, w, stays, a, b, tau, k, dr.detach(d_m), w.d, mi.Bool(False), -1.0)
    if params.defensive:
        w.e = dr.select(mirror, w.e * dr.detach(prob), w.e)
    d_att = dr.select(mirror, d_m, w.d)
    w.d = dr.detach(d_att)
    w.a, w.b = dr.select(mirror, dr.detach(a_m), w.a), dr.select(mirror, dr.detach(b_m), w.b)
    w.depth = dr.select(mirror, w.depth + 1, w.depth)
    w.escaped = w.escaped | leaves
    w.on_p = w.on_p | stays
    w.walking = w.walking & (negate(mirror) | (stays & (w.depth < params.max_bounces)))
    return d_att, dr.select(mirror, prob, 1.0)


def roulette(e, stays, depth, rr_depth, u):
    """Russian roulette on the throughput after the bounce at ``depth`` (from ``rr_depth`` on, 0: never):
    continue with probability q = min(1, max channel of e) and divide e by q. Unbiased; it
    ends the long walks of dark materials that cost a packet most of its time. q is a
    detached number to the estimator, so e/q stays unbiased for e's derivative. (e, stays)."""
    q = dr.minimum(dr.max(e), 1.0)
    play = stays & (rr_depth > 0) & (depth + 1 >= rr_depth) & (q < 1.0)
    survive = u < q
    e = dr.select(play & survive, e / dr.maximum(q, 1e-30), e)
    return e, stays & (negate(play) | survive)


def bounce(sp, w, params, seed, frame, s1, s2, d_in=None, rp=None):
    """The nested BSDF's sample at the walker's vertex (facet ``frame``, sample numbers s1, s2),
    lit along ``d_in`` (default the walker's direction), then cross to the other facet or out
    of the microsurface, then roulette.

    Replay: the sample's direction is detached and its weight's derivative is that of the
    attached nested eval (a delta lobe: of its weight), the escape's that of its probability."""
    d_in = w.d if d_in is None else d_in
    bs, weight = sp.sample(frame, -d_in, s1, s2, w.walking)
    delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    d_new = dr.detach(bs.wo)
    ok = (w.walking & (dr.dot(d_new, frame.n) > 0) & (bs.pdf > 0) & dr.any(weight > 0)
          & dr.all(dr.isfinite(weight)))
    if rp is not None:
        f = sp.eval(frame, -d_in, d_new, ok & negate(delta))
        rp.factor(dr.select(delta, weight, f), ok)
    w.nondelta = w.nondelta | (w.walking & negate(delta))
    if w.p_in is not None:
        w.p_in = dr.select(w.walking, dr.select(ok & negate(delta), dr.detach(bs.pdf), 0.0), w.p_in)
    w.e = dr.select(w.walking, w.e * dr.detach(weight), w.e)
    a, b = attached_interval(sp, w, rp)
    leaves, stays, a_new, b_new, prob, (tau, k) = cross(sp, params, w.on_p, d_new, a, b, ok,
                                                        uniform(seed, slot_escape(w.depth)))
    if rp is not None:
        rp.factor(prob, ok)
        rp.leave(bs.wo, leaves & delta)
        if w.ja is not None:
            _moved_interval(sp, w, stays, a, b, tau, k, d_new, d_new, w.on_p, 1.0)
    w.a, w.b = dr.detach(a_new), dr.detach(b_new)
    if params.defensive:
        w.e = dr.select(ok, w.e * dr.detach(prob), w.e)
    w.e, stays = roulette(w.e, stays, w.depth, params.rr_depth, uniform(seed, slot_roulette(w.depth)))
    w.d = dr.select(w.walking, d_new, w.d)
    w.depth = dr.select(w.walking, w.depth + 1, w.depth)
    w.escaped = w.escaped | leaves
    w.on_p = w.on_p ^ stays
    w.walking = stays & (w.depth < params.max_bounces)


def nested_numbers(seed, depth):
    """(sample1, sample2) of the nested sample at facet bounce ``depth``."""
    return (uniform(seed, slot_nested(depth, 0)),
            mi.Point2f(uniform(seed, slot_nested(depth, 1)), uniform(seed, slot_nested(depth, 2))))


# -- The loops' start and run ---------------------------------------------------------------


def first_vertex(sp, params, u, active, replay=False):
    """A walker on the facet a ray from ω_i hits first, chosen by λ_p(ω_i) with the number u;
    (walker, the probability of its choice (``weighted``, ``decision``), λ_p, the rest of u rescaled). ``replay``: the
    walker's values detached, with the non-separable interval's Jacobian."""
    lp = sp.lambda_p(sp.wi)
    q_p = decision(params, dr.detach(lp))
    on_p, rest = choose(u, q_p)
    a, b = first_interval(sp, params, on_p)
    walker = start(sp, on_p, dr.detach(a), dr.detach(b), active)
    if replay and not params.separable:
        walker.ja = dr.zeros(mi.Vector3f, dr.width(walker.a))
        walker.jb = _g1_jacobian(sp, dr.detach(sp.wi), on_p) + walker.ja
    p_start = weighted(params, dr.select(on_p, lp, 1.0 - lp), dr.select(on_p, q_p, 1.0 - q_p))
    if params.defensive:
        walker.e = walker.e * dr.detach(p_start)
    return walker, p_start, lp, rest


def walk_loop(state, body, label):
    """A walk loop: everything it reads is in ``state`` (broadcast to the walk's width); its
    derivative is a sum over iterations (``Replay``), so reverse mode needs no stored walk."""
    state = broadcast(state, dr.width(state[0].walking))
    return dr.while_loop(state, lambda w, *_: w.walking, body, max_iterations=-1, label=label)
