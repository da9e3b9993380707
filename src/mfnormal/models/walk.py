"""The random-walk models: separable (main paper) and non-separable (supplemental).

One walk serves both (docs/model.md §4). It starts on the facet that a ray
from ω_i hits first and bounces between the two facets until it leaves the
microsurface. The non-separable model tracks the interval H of heights the walk
can be at on the current facet, stored as depths below the crest (§1, §2.2): rays
from a uniform height in H stay uniform after each bounce, because the facets
are planar. The separable model is the same walk with H reset to [0, 1] at
every vertex, which forgets height correlation (§4.1).

- ``sample_walk``: the sampling loop (supplemental Algorithm 1, the exit decided
  from the interval's escape fraction, the same random variable as tracing a ray
  from a uniformly drawn height); ``sample`` wraps its exit as a BSDF sample;
- ``eval_walk``: the evaluation loop, next-event estimation toward ω_o at every
  vertex (Algorithm 2; with a mirror tangent facet, Algorithm 3 and its H_r
  term), an unbiased estimate of f·⟨ω_o, ω_g⟩. Its first nested vertex is
  Rao-Blackwellised (§4.5): taken in expectation over the start facet (and the
  mirror's escape), so the low-order part of ``eval`` is deterministic; with a
  same-material tangent facet each vertex also connects to the next facet by a
  sample from ω_o, MIS-weighted against the walk's own (``connect``, §4.8);
- ``mis_pdf`` (:mod:`~mfnormal.models.walk_pdf`): a deterministic function for MIS (§5): the
  exact density of the low-order terms plus a cosine lobe for the rest, boosted by the nested
  lobe's sharpness where longer walks are likely (variance-aware MIS).
- ``eval_sample``: both from one walk (§4.10, primal only): ``eval_walk`` run with
  ``sample_walk``'s numbers, so its walker is ``sample``'s and its L an unbiased ``eval``.

Both loops are built from the same steps: ``mirror_fold`` (a mirror tangent
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

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from mfnormal.surface import microsurface as ms
from mfnormal.surface.microsurface import negate, replace_grad
from mfnormal.models.rng import (SALT_WALK_EVAL, SALT_WALK_SAMPLE, SLOT_START_FACET, choose, hash_floats, slot_connect,
                  slot_escape, slot_nested, slot_roulette, uniform)
from mfnormal.surface.shading import broadcast, select_frame
from mfnormal.models.walk_pdf import first_interval, mis_pdf
from mfnormal.models.walk_replay import (Replay, _crest_jacobian, _g1_jacobian, _land_jacobian, attached_interval,
                                         calls, replays)

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


@dataclass
class NeeTarget:
    """ω_o and what NEE toward it needs at every vertex: G1(ω_o, p), G1(ω_o, t) and, with a
    mirror t, ω'_o = flip_t(ω_o) with H_r = [r_lo, r_hi] (``mirror_leg``)."""

    wo: mi.Vector3f
    g_o_p: mi.Float
    g_o_t: mi.Float
    wo_m: mi.Vector3f = None
    r_lo: mi.Float = None
    r_hi: mi.Float = None

    @classmethod
    def toward(cls, sp, params, wo):
        target = cls(wo, sp.G1_p(wo), sp.G1_t(wo))
        if params.specular_tangent:
            target.wo_m, target.r_lo, target.r_hi = mirror_leg(sp, wo, target.g_o_t)
        return target


def mirror_leg(sp, wo, g_o_t):
    """(ω'_o, lo, hi): the depths [lo, hi] on p whose ray along ω'_o = flip_t(ω_o)
    reflects off the mirror t toward ω_o (H_r, docs/model.md §4.4: heights
    [(1 − G1(ω_o, t))·h_r, h_r] with h_r = 1 − G1(ω'_o, p)); ``g_o_t`` = G1(ω_o, t)."""
    wo_m = sp.flip_t(wo)
    r_lo = sp.G1_p(wo_m)
    return wo_m, r_lo, dr.select(g_o_t > 0, r_lo + g_o_t * (1.0 - r_lo), r_lo)


def add_nee(L, sp, params, to, on_p, w_in, h_a, h_b, scale, active, p_in=None):
    """L plus the NEE toward ω_o from a vertex on facet ``on_p`` lit from ``w_in``, at depths
    [h_a, h_b], times ``scale`` (Algorithms 2 and 3): f_m(w_in, ω_o)⟨ω_o, ω_m⟩·G₂/|H| with
    G₂ = |H ∩ [0, G1(ω_o, m)]|; with a mirror t also f_p(w_in, ω'_o)⟨ω'_o, ω_p⟩·|H ∩ H_r|/|H|.
    ``p_in``: the walk's ``Walker.p_in`` (a same-material t), for ``connected_nee``."""
    g_o = to.g_o_p if params.specular_tangent else dr.select(on_p, to.g_o_p, to.g_o_t)
    w2 = ms.fraction_inside(h_a, h_b, 0.0, g_o)
    frame = vertex_frame(sp, params, on_p)
    if p_in is None:
        L += scale * sp.eval(frame, w_in, to.wo, active & (w2 > 0)) * w2
    else:
        L += scale * connected_nee(sp, frame, w_in, to.wo, p_in, active & (w2 > 0), params.connect) * w2
    if params.specular_tangent:
        wr = dr.select(to.g_o_t > 0, ms.fraction_inside(h_a, h_b, to.r_lo, to.r_hi), 0.0)
        L += scale * sp.eval(sp.frame_p, w_in, to.wo_m, active & (wr > 0)) * wr
    return L


def connect(sp, params, w, to, seed, a, b, rp=None):
    """The eval walk's MIS connection from the walker's vertex to the other facet (a
    same-material tangent facet, docs/model.md §4.8): the next vertex's NEE term

        e·∫ f_m(w_in, d)⟨d, ω_m⟩·(1 − escape(d))·G₂'(d)·f_m'(−d, ω_o)⟨ω_o, ω_m'⟩ dd

    estimated from a direction sampled at the other facet m' lit from ω_o (u ~ f_m'(ω_o, ·),
    d = −u; f_m'(−d, ω_o) = f_m'(ω_o, u) by the nested BSDF's reciprocity), weighted by the
    balance heuristic against the walk's own sample d ~ f_m(w_in, ·), whose NEE at the next
    vertex takes the complementary weight (``connection_weight``). Where both lobes are narrow
    the walk's sample rarely meets the next lobe's peak toward ω_o; this sample starts there.
    The escape and the landed depths [a', b'] are taken in expectation. Only where the walk
    can have a next vertex (``max_bounces``); delta samples are left to the walk.

    Returns (the contribution, times the walker's throughput; the lanes it is defined on).
    Replay: f_m' is the attached nested eval at the detached direction, the pdfs detached."""
    on_p = w.on_p
    frame_m = select_frame(on_p, sp.frame_p, sp.frame_t)
    frame_n = select_frame(on_p, sp.frame_t, sp.frame_p)
    on = w.walking & (w.depth + 1 < params.max_bounces)
    s2 = mi.Point2f(uniform(seed, slot_connect(w.depth, 1)), uniform(seed, slot_connect(w.depth, 2)))
    bs, weight = sp.sample(frame_n, to.wo, uniform(seed, slot_connect(w.depth, 0)), s2, on)
    u = dr.detach(bs.wo)
    cos_u, p_n = dr.dot(u, frame_n.n), dr.detach(bs.pdf)
    ok = (on & negate(mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)) & (p_n > 0) & (cos_u > 0)
          & (dr.dot(u, frame_m.n) < 0) & dr.all(dr.isfinite(weight)))
    # (Elsewhere a direction off the facet: the crest map's derivative is not finite there.)
    d = dr.select(ok, -u, frame_m.n)
    f_m, p_m = sp.eval_pdf(frame_m, -w.d, d, ok)
    tau, k = sp.crest_map(on_p, d)
    a_n, b_n = (mi.Float(0.0), mi.Float(1.0)) if params.separable else ms.land(a, b, tau, k)
    g2 = (1.0 - ms.escape_fraction(a, b, tau)) * ms.fraction_inside(a_n, b_n, 0.0,
                                                                      dr.select(on_p, to.g_o_t, to.g_o_p))
    ok &= g2 > 0
    if rp is None:
        f_n = weight * (p_n * dr.dot(to.wo, frame_n.n) / dr.select(ok, cos_u, 1.0))
    else:
        f_n = sp.eval(frame_n, u, to.wo, ok)
    c = w.e * f_m * g2 * f_n / dr.select(ok, dr.detach(p_m) + p_n, 1.0)
    return dr.select(ok, c, 0.0), ok


def connected_nee(sp, frame, w_in, wo, p_in, active, weighted=True):
    """f_m(w_in, ω_o)⟨ω_o, ω_m⟩ at a vertex that the walk reached by its own nested sample
    (density p_in > 0), times the balance-heuristic weight against ``connect``'s sample of
    the same direction from ω_o (``connection_weight``). One nested call, eval_pdf from ω_o
    toward w_in: its pdf is p_o, its value f_m(ω_o, w_in)⟨w_in, ω_m⟩, which reciprocity
    turns into the NEE's (×⟨ω_o, ω_m⟩/⟨w_in, ω_m⟩). Where p_in = 0 (the first vertex, after a
    delta lobe) the plain eval from w_in, weight 1; ``weighted`` false (no connection): weight 1."""
    swap = p_in > 0
    value, p_o = sp.eval_pdf(frame, dr.select(swap, wo, w_in), dr.select(swap, w_in, wo), active)
    cos_in = dr.dot(w_in, frame.n)
    f = dr.select(swap, value * (dr.dot(wo, frame.n) / dr.select(swap & (cos_in > 0), cos_in, 1.0)), value)
    return f * connection_weight(p_in, dr.detach(p_o)) if weighted else f


def connection_weight(p_in, p_o):
    """The balance-heuristic weight p_in/(p_in + p_o) of the walk's own sample (density p_in)
    against ``connect``'s sample of the same direction from ω_o (density p_o); 1 where p_in = 0."""
    return dr.select(p_in > 0, p_in / dr.maximum(p_in + p_o, 1e-30), 1.0)


def t_start_share(sp, params, wo, lp, active):
    """λ_t(ω_i)·E[NEE toward wo at the first nested vertex of a walk that starts on t].

    With a mirror tangent facet the walk reflects to p first: λ_t·(1 − escape)·NEE
    at p lit from flip_t(ω_i) on the landed depth interval, including the p→t→ω_o
    leg (H_r); otherwise the NEE at t itself. (The p start's share, λ_p·NEE at p lit
    from ω_i, is the evaluation loop's first iteration; docs/model.md §4.5.) The same
    terms, with pdf for eval, are in mis_pdf's explicit part.
    """
    wi = sp.wi
    g_o_t = sp.G1_t(wo)
    b_t = first_interval(sp, params, False)[1]
    if not params.specular_tangent:
        w_t = (1.0 - lp) * ms.fraction_inside(0.0, b_t, 0.0, g_o_t)
        return sp.eval(sp.frame_t, wi, wo, active & (w_t > 0)) * w_t
    # The mirror sends the ray along d_m = flip_t(−ω_i), toward p or out.
    d_m = ms.flip_t(-wi, sp.wt)
    tau, k = sp.crest_map(mi.Bool(False), d_m)
    stay = (1.0 - lp) * (1.0 - ms.escape_fraction(0.0, b_t, tau)) * dr.select(params.max_bounces > 1, 1.0, 0.0)
    a, b = (mi.Float(0.0), mi.Float(1.0)) if params.separable else ms.land(0.0, b_t, tau, k)
    wo_m, r_lo, r_hi = mirror_leg(sp, wo, g_o_t)
    w2 = stay * ms.fraction_inside(a, b, 0.0, sp.G1_p(wo))
    wr = stay * dr.select(g_o_t > 0, ms.fraction_inside(a, b, r_lo, r_hi), 0.0)
    return (sp.eval(sp.frame_p, -d_m, wo, active & (w2 > 0)) * w2
            + sp.eval(sp.frame_p, -d_m, wo_m, active & (wr > 0)) * wr)


# -- The loops ----------------------------------------------------------------------------


def _first_vertex(sp, params, u, active, replay=False):
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


def _loop(state, body, label):
    """A walk loop: everything it reads is in ``state`` (broadcast to the walk's width); its
    derivative is a sum over iterations (``Replay``), so reverse mode needs no stored walk."""
    state = broadcast(state, dr.width(state[0].walking))
    return dr.while_loop(state, lambda w, *_: w.walking, body, max_iterations=-1, label=label)


def sample_walk(sp, params, sample1, sample2, active):
    """Supplemental Algorithm 1: walk from ω_i until the ray leaves; the walker at its exit.

    The first facet is chosen by λ_p(ω_i) with ``sample1``, whose rescaled rest and
    ``sample2`` drive the first nested sample; later numbers come from a hash of them.
    """
    return _sample_walk(sp, params, sample1, sample2, active)[0]


def _sample_walk(sp, params, sample1, sample2, active):
    """:func:`sample_walk` and its Replay (the throughput's derivative; None without)."""
    sp = calls(sp, params)
    active = mi.Bool(active) & (sp.wi.z > 0)
    seed = hash_floats(SALT_WALK_SAMPLE, sample1, sample2.x, sample2.y)
    replay = replays(sp)
    walker, p_start, _, s1_first = _first_vertex(sp, params, sample1, active, replay)
    n = dr.width(active)
    rp = Replay(dr.zeros(mi.Spectrum, n), exit=dr.zeros(mi.Vector3f, n)) if replay else None

    def body(w, rp, geometry, seed, s1_first, sample2, p_start):
        at = sp.with_state(geometry)
        if rp is not None:
            rp.factor(p_start, w.depth == 0)
        d_in = w.d
        if params.specular_tangent:
            d_in, p_fold = mirror_fold(at, w, params, seed, rp)
            if rp is not None:
                rp.factor(p_fold, True)
        first = w.depth == 0
        s1, s2 = nested_numbers(seed, w.depth)
        bounce(at, w, params, seed, vertex_frame(at, params, w.on_p),
               dr.select(first, s1_first, s1), dr.select(first, sample2, s2), d_in, rp)
        return w, rp, geometry, seed, s1_first, sample2, p_start

    w, rp = _loop((walker, rp, sp.state(), seed, s1_first, mi.Point2f(sample2), p_start), body,
                  "mfnormal_sample_walk")[:2]
    return w, rp


def _eval_run(sp, params, wo, u_start, walk_active, active, seed, numbers, rp):
    """One pass of :func:`eval_walk`'s walk (``rp``: the replay that takes L's derivative, or None):
    (walker, L, rp, the first vertex's λ_p-weighted light)."""
    walker, p_start, lp, s1_first = _first_vertex(sp, params, u_start, walk_active, rp is not None)
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
    w, L, rp = _loop(state, body, "mfnormal_eval_walk")[:3]
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


# -- The BSDF's sample, eval and pdf --------------------------------------------------------


def sample(sp, params, sample1, sample2, active):
    """Walk from wi until the ray leaves: (BSDFSample3f with the MIS pdf, throughput)."""
    w, rp = _sample_walk(sp, params, sample1, sample2, active)
    if rp is not None:
        w.e = replace_grad(w.e, w.e * rp.G)
        w.d = replace_grad(w.d, w.d + rp.exit)
    return exit_sample(sp, params, w)


def exit_sample(sp, params, w):
    """A finished walker as the BSDF's sample: (BSDFSample3f with the MIS pdf, throughput);
    walks that did not escape, or escaped below the horizon, give pdf and weight 0."""
    valid = w.escaped & (w.d.z > 0) & dr.all(dr.isfinite(w.e)) & dr.all(dr.isfinite(w.d))
    bs = dr.zeros(mi.BSDFSample3f, dr.width(w.d))
    bs.wo = dr.select(w.escaped & dr.all(dr.isfinite(w.d)), w.d, mi.Vector3f(0.0, 0.0, 1.0))
    bs.eta = 1.0
    bs.sampled_component = 0
    bs.sampled_type = dr.select(w.nondelta, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                mi.UInt32(+mi.BSDFFlags.DeltaReflection))
    pdf = mis_pdf(sp, params, w.d, valid & w.nondelta)
    bs.pdf = dr.select(w.nondelta, pdf, 1.0)
    valid &= bs.pdf > 0
    bs.pdf = dr.select(valid, bs.pdf, 0.0)
    return bs, dr.select(valid, dr.maximum(w.e, 0.0), 0.0)


def eval(sp, params, wo, active):
    """Unbiased NEE estimate of f·⟨wo, z⟩, deterministic per query."""
    active = mi.Bool(active) & (sp.wi.z > 0) & (wo.z > 0)
    L = eval_walk(sp, params, wo, active)[0]
    return dr.select(active & dr.all(dr.isfinite(L)), dr.maximum(L, 0.0), 0.0)


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
