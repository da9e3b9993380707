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
  mirror's escape), so the low-order part of ``eval`` is deterministic;
- ``mis_pdf``: a deterministic function for MIS (§5): the exact density of the
  low-order terms plus a cosine lobe for the rest, boosted by the nested lobe's
  sharpness where longer walks are likely (variance-aware MIS).

Both loops are built from the same steps: ``mirror_fold`` (a mirror tangent
facet), ``add_nee`` (NEE at a vertex), ``bounce`` (nested sample, ``cross`` to
the other facet or out, ``roulette``). Each takes a :class:`WalkParams`; each
loop returns its :class:`Walker`, whose ``depth`` is the walk's bounce count.
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from . import microsurface as ms
from .microsurface import negate
from .rng import (SALT_WALK_EVAL, SALT_WALK_SAMPLE, SLOT_START_FACET, choose, hash_floats, slot_escape,
                  slot_nested, slot_roulette, uniform)
from .shading import select_frame

# Default cap of a walk's facet bounces; walks still on the microsurface after it are dropped.
MAX_BOUNCES = 1024
# Default depth (facet bounces) from which walks play Russian roulette on their throughput.
RR_DEPTH = 3
# Default cap of the boost of the longer walks' share in the MIS pdf (GGX α ≤ 1/16 reaches it).
MIS_BOOST_MAX = 64.0


@dataclass(frozen=True)
class WalkParams:
    """What a random-walk model is: the plugin builds one per BSDF."""

    separable: bool                      # reset H to [0, 1] at every vertex (the main paper's model)
    specular_tangent: bool               # the tangent facet is a mirror (Algorithm 3), else the nested BSDF
    max_bounces: int = MAX_BOUNCES       # facet bounces before a walk is dropped
    rr_depth: int = RR_DEPTH             # Russian roulette from this many bounces on (0: never)
    mis_boost_max: float = MIS_BOOST_MAX  # cap of the variance-aware MIS boost (1: none)


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


# -- Steps --------------------------------------------------------------------------------


def first_interval(sp, params, on_p):
    """(a, b): the depths on the first facet that a ray from ω_i can hit, [0, G1(ω_i, m)]
    (the top G1 of its height, Algorithm 2); [0, 1] for the separable walk."""
    return mi.Float(0.0), mi.Float(1.0) if params.separable else sp.G1(sp.wi, on_p)


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

    Returns (leaves, stays, a, b): the depths are those on the other facet where it stays.
    For a point interval (a = b) the escape is the binary test D < τ whatever u is.
    """
    tau, k = sp.crest_map(on_p, d)
    leaves = ok & (u < ms.escape_fraction(a, b, tau))
    stays = ok & negate(leaves)
    a_new, b_new = ms.land(a, b, tau, k)
    a = dr.select(stays, 0.0 if params.separable else a_new, a)
    b = dr.select(stays, 1.0 if params.separable else b_new, b)
    return leaves, stays, a, b


def mirror_fold(sp, w, params, seed):
    """Reflect the walkers on a mirror t off it (flip_t) to p or out of the microsurface.

    A mirror vertex needs no nested call and gives no NEE: its bounce is folded into
    the iteration of the next p vertex, so a packet runs the nested calls once per p
    vertex. Its escape takes the slot of its own depth: the same random numbers, and
    the same results, as one vertex per iteration.
    """
    mirror = w.walking & negate(w.on_p)
    d_m = ms.flip_t(w.d, sp.wt)
    leaves, stays, a_m, b_m = cross(sp, params, mi.Bool(False), d_m, w.a, w.b, mirror & (dr.dot(d_m, sp.wt) > 0),
                                    uniform(seed, slot_escape(w.depth)))
    w.d = dr.select(mirror, d_m, w.d)
    w.a, w.b = dr.select(mirror, a_m, w.a), dr.select(mirror, b_m, w.b)
    w.depth = dr.select(mirror, w.depth + 1, w.depth)
    w.escaped = w.escaped | leaves
    w.on_p = w.on_p | stays
    w.walking = w.walking & (negate(mirror) | (stays & (w.depth < params.max_bounces)))


def roulette(e, stays, depth, rr_depth, u):
    """Russian roulette on the throughput after the bounce at ``depth`` (from ``rr_depth`` on):
    continue with probability q = min(1, max channel of e) and divide e by q. Unbiased; it
    ends the long walks of dark materials that cost a packet most of its time. (e, stays)."""
    q = dr.minimum(dr.max(e), 1.0)
    play = stays & (depth + 1 >= rr_depth) & (q < 1.0)
    survive = u < q
    e = dr.select(play & survive, e / dr.maximum(q, 1e-30), e)
    return e, stays & (negate(play) | survive)


def bounce(sp, w, params, seed, frame, s1, s2):
    """The nested BSDF's sample at the walker's vertex (facet ``frame``, sample numbers s1, s2),
    then cross to the other facet or out of the microsurface, then roulette."""
    bs, weight = sp.sample(frame, -w.d, s1, s2, w.walking)
    d_new = bs.wo
    ok = (w.walking & (dr.dot(d_new, frame.n) > 0) & (bs.pdf > 0) & dr.any(weight > 0)
          & dr.all(dr.isfinite(weight)))
    w.nondelta = w.nondelta | (w.walking & negate(mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)))
    w.e = dr.select(w.walking, w.e * weight, w.e)
    leaves, stays, w.a, w.b = cross(sp, params, w.on_p, d_new, w.a, w.b, ok, uniform(seed, slot_escape(w.depth)))
    if params.rr_depth > 0:
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


def add_nee(L, sp, params, to, on_p, w_in, h_a, h_b, scale, active):
    """L plus the NEE toward ω_o from a vertex on facet ``on_p`` lit from ``w_in``, at depths
    [h_a, h_b], times ``scale`` (Algorithms 2 and 3): f_m(w_in, ω_o)⟨ω_o, ω_m⟩·G₂/|H| with
    G₂ = |H ∩ [0, G1(ω_o, m)]|; with a mirror t also f_p(w_in, ω'_o)⟨ω'_o, ω_p⟩·|H ∩ H_r|/|H|."""
    g_o = to.g_o_p if params.specular_tangent else dr.select(on_p, to.g_o_p, to.g_o_t)
    w2 = ms.fraction_inside(h_a, h_b, 0.0, g_o)
    L += scale * sp.eval(vertex_frame(sp, params, on_p), w_in, to.wo, active & (w2 > 0)) * w2
    if params.specular_tangent:
        wr = dr.select(to.g_o_t > 0, ms.fraction_inside(h_a, h_b, to.r_lo, to.r_hi), 0.0)
        L += scale * sp.eval(sp.frame_p, w_in, to.wo_m, active & (wr > 0)) * wr
    return L


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
    stay = (1.0 - lp) * (1.0 - ms.escape_fraction(0.0, b_t, tau)) * (1.0 if params.max_bounces > 1 else 0.0)
    a, b = (mi.Float(0.0), mi.Float(1.0)) if params.separable else ms.land(0.0, b_t, tau, k)
    wo_m, r_lo, r_hi = mirror_leg(sp, wo, g_o_t)
    w2 = stay * ms.fraction_inside(a, b, 0.0, sp.G1_p(wo))
    wr = stay * dr.select(g_o_t > 0, ms.fraction_inside(a, b, r_lo, r_hi), 0.0)
    return (sp.eval(sp.frame_p, -d_m, wo, active & (w2 > 0)) * w2
            + sp.eval(sp.frame_p, -d_m, wo_m, active & (wr > 0)) * wr)


# -- The loops ----------------------------------------------------------------------------


def sample_walk(sp, params, sample1, sample2, active):
    """Supplemental Algorithm 1: walk from ω_i until the ray leaves; the walker at its exit.

    The first facet is chosen by λ_p(ω_i) with ``sample1``, whose rescaled rest and
    ``sample2`` drive the first nested sample; later numbers come from a hash of them.
    """
    active = mi.Bool(active) & (sp.wi.z > 0)
    seed = hash_floats(SALT_WALK_SAMPLE, sample1, sample2.x, sample2.y)
    on_p, s1_first = choose(sample1, sp.lambda_p(sp.wi))
    walker = start(sp, on_p, *first_interval(sp, params, on_p), active)

    def body(w):
        if params.specular_tangent:
            mirror_fold(sp, w, params, seed)
        first = w.depth == 0
        s1, s2 = nested_numbers(seed, w.depth)
        bounce(sp, w, params, seed, vertex_frame(sp, params, w.on_p),
               dr.select(first, s1_first, s1), dr.select(first, mi.Point2f(sample2), s2))
        return (w,)

    return dr.while_loop((walker,), lambda w: w.walking, body, label="mfnormal_sample_walk")[0]


def eval_walk(sp, params, wo, active):
    """Supplemental Algorithms 2 (3 with a mirror t): NEE toward ω_o along a walk from ω_i.

    Returns (L, walker): L estimates f·⟨ω_o, ω_g⟩ without bias. The NEE at the first
    nested vertex is taken in expectation over the start facet (docs/model.md §4.5):
    the first iteration adds λ_p·NEE at p lit from ω_i for every walk, whichever facet
    it started on, ``t_start_share`` the t start's share, and later iterations the
    vertices after the first nested sample. Random numbers: a hash of (ω_i, ω_o, si.p).
    """
    wi = sp.wi
    active = mi.Bool(active) & (wi.z > 0)
    seed = hash_floats(SALT_WALK_EVAL, wi.x, wi.y, wo.x, wo.y, sp.si.p.x, sp.si.p.y, sp.si.p.z)
    lp = sp.lambda_p(wi)
    on_p, _ = choose(uniform(seed, SLOT_START_FACET), lp)
    walker = start(sp, on_p, *first_interval(sp, params, on_p), active)
    to = NeeTarget.toward(sp, params, wo)
    b_p = first_interval(sp, params, True)[1]
    L_t = t_start_share(sp, params, wo, lp, active)

    def body(w, L):
        at_start = w.depth == 0   # the first vertex (before a folded mirror bounce counts)
        if params.specular_tangent:
            mirror_fold(sp, w, params, seed)
        # NEE toward ω_o from this vertex; in the first iteration, the p start's share.
        L = add_nee(L, sp, params, to, w.on_p | at_start, dr.select(at_start, wi, -w.d),
                    dr.select(at_start, 0.0, w.a), dr.select(at_start, b_p, w.b),
                    dr.select(at_start, mi.Spectrum(lp), w.e), dr.select(at_start, active, w.walking))
        bounce(sp, w, params, seed, vertex_frame(sp, params, w.on_p), *nested_numbers(seed, w.depth))
        return w, L

    walker, L = dr.while_loop((walker, dr.zeros(mi.Spectrum, dr.width(wi))), lambda w, L: w.walking, body,
                              label="mfnormal_eval_walk")
    return L + L_t, walker


# -- The BSDF's sample, eval and pdf --------------------------------------------------------


def sample(sp, params, sample1, sample2, active):
    """Walk from wi until the ray leaves: (BSDFSample3f with the MIS pdf, throughput)."""
    w = sample_walk(sp, params, sample1, sample2, active)
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


def _escape(sp, h, on_p, d):
    """The fraction of rays from depths h = (a, b) on facet ``on_p`` along d that leave.

    Only above the facet's plane: below it, κ = ∞ must not count as an escape
    (nested pdfs such as llvm roughplastic's are not zero there)."""
    above = dr.dot(d, dr.select(on_p, sp.wp, sp.wt)) > 0
    return dr.select(above, ms.escape_fraction(h[0], h[1], sp.crest_map(on_p, d)[0]), 0.0)


def _land(sp, params, h, on_p, d):
    """The depths on the other facet reached by the rays from h along d that do not escape."""
    if params.separable:
        return mi.Float(0.0), mi.Float(1.0)
    return ms.land(h[0], h[1], *sp.crest_map(on_p, d))


def second_visit(sp, params, h, w_in):
    """P(a walk on p lit from w_in, its nested sample at the lobe centre (the mirror
    direction about ω_p), crosses to t and, reflected there as by a mirror, lands on p
    again): how likely a second nested vertex is. Exact for a mirror-like nested
    BSDF, which is where the boost is large."""
    p, t = mi.Bool(True), mi.Bool(False)
    d1 = 2.0 * dr.dot(w_in, sp.wp) * sp.wp - w_in
    q = (1.0 - _escape(sp, h, p, d1)) * (1.0 - _escape(sp, _land(sp, params, h, p, d1), t, sp.flip_t(d1)))
    return dr.select(dr.dot(d1, sp.wp) > 0, q, 0.0)


def mis_pdf(sp, params, wo, active):
    """Deterministic MIS pdf (docs/model.md §5): a density approximation, variance-aware boosted.

    The exact density of walks that leave after their first nested sample (with a
    mirror tangent facet: including the mirror legs i→p→t→o, i→t→p→o and i→t→p→t→o;
    with a same-material one, i→p→t→o and i→t→p→o with the t bounce approximated by
    a mirror), using the model's own escape probabilities, plus a cosine lobe of
    weight 1 − cosθ_p for the longer walks. For white Lambertian facets and a mirror
    tangent facet the separable walk's density is exactly cosθ_o/π (§4.7), and so is
    this pdf.

    The terms that ``eval`` estimates stochastically are multiplied by the boost c of
    ``stochastic_share_boost`` (variance-aware MIS; ``mis_boost_max`` = 1 leaves the
    plain density approximation): with a same-material tangent facet the two-bounce
    terms, and for the longer walks a cosine lobe of weight (c − 1)·q2 is added, q2
    the chance of a second nested vertex for a walk whose first nested sample takes
    its lobe's centre (zero where that centre leaves the microsurface, so that light
    samples keep their weight where longer walks are rare).
    """
    wi = sp.wi
    active = mi.Bool(active) & (wi.z > 0) & (wo.z > 0)
    p, t = mi.Bool(True), mi.Bool(False)
    lp = sp.lambda_p(wi)
    wo_m, wi_m = sp.flip_t(wo), sp.flip_t(wi)
    h_p = first_interval(sp, params, p)
    h_tp = _land(sp, params, first_interval(sp, params, t), t, -wi_m)   # on p after a t start's mirror bounce
    e_po = lp * _escape(sp, h_p, p, wo)                                                            # i→p→o
    e_pto = lp * (1.0 - _escape(sp, h_p, p, wo_m)) * _escape(sp, _land(sp, params, h_p, p, wo_m), t, wo)  # i→p→t→o
    e_tpo = (1.0 - lp) * _escape(sp, h_tp, p, wo)                                                  # i→t→p→o
    stochastic = 0.0
    if params.specular_tangent:
        e_tpto = ((1.0 - lp) * (1.0 - _escape(sp, h_tp, p, wo_m))
                  * _escape(sp, _land(sp, params, h_tp, p, wo_m), t, wo))                          # i→t→p→t→o
        explicit = (sp.pdf(sp.frame_p, wi, wo, active & (e_po > 0)) * e_po
                    + sp.pdf(sp.frame_p, wi, wo_m, active & (e_pto > 0)) * e_pto
                    + sp.pdf(sp.frame_p, wi_m, wo, active & (e_tpo > 0)) * e_tpo
                    + sp.pdf(sp.frame_p, wi_m, wo_m, active & (e_tpto > 0)) * e_tpto)
    else:
        e_to = (1.0 - lp) * _escape(sp, first_interval(sp, params, t), t, wo)                     # i→t→o
        explicit = (sp.pdf(sp.frame_p, wi, wo, active & (e_po > 0)) * e_po
                    + sp.pdf(sp.frame_t, wi, wo, active & (e_to > 0)) * e_to)
        # The two-bounce paths with the t bounce taken as a mirror (the centre of a glossy
        # tangent facet's lobe): without them BSDF samples reflected off a glossy wall got
        # almost no MIS weight (this pdf was 7-14× below the walk's density at α = 0.05).
        # eval estimates them stochastically (one glossy t sample): they take the boost.
        stochastic = (sp.pdf(sp.frame_p, wi, wo_m, active & (e_pto > 0)) * e_pto
                      + sp.pdf(sp.frame_p, wi_m, wo, active & (e_tpo > 0)) * e_tpo)
    # 1 − cosθ_p as sin²θ_p/(1 + cosθ_p): never negative (a float32 unit ω_p can have z > 1)
    # and non-zero for tilts below float32's 1 − cos resolution (θ_p ≲ 3e-4).
    rest = sp.sin_p * sp.sin_p / (1.0 + sp.wp.z) * dr.maximum(wo.z, 0.0) * dr.inv_pi
    if params.mis_boost_max > 1.0:
        # The longer walks' share by the chance q2 that a walk has them: a cosine lobe of
        # weight c·q2 instead of the plain density's 1 − cosθ_p, where c > 1.
        c = stochastic_share_boost(sp, params.mis_boost_max, active)
        q2 = lp * second_visit(sp, params, h_p, wi) + (1.0 - lp) * second_visit(sp, params, h_tp, wi_m)
        pdf = explicit + stochastic * c + rest + (c - 1.0) * q2 * dr.maximum(wo.z, 0.0) * dr.inv_pi
    else:
        pdf = explicit + stochastic + rest
    return dr.select(active & dr.isfinite(pdf), pdf, 0.0)


def stochastic_share_boost(sp, boost_max, active):
    """Variance-aware MIS factor for the longer walks' share of the MIS pdf.

    ``eval`` is exact-in-expectation but noisy for the walks past their first
    nested sample: one random direction per vertex, evaluated against a nested lobe
    that is as sharp as the material. Light samples weighted by that noisy value
    give fireflies on glossy facets; BSDF samples of the same paths have weights
    near the albedo. Variance-aware MIS (Grittmann et al. 2019) divides a
    technique's weight by the relative variance of its estimate; here it is
    applied as a boost of the BSDF technique's weight on the longer walks,
    proportional to the nested lobe's sharpness: π × the nested pdf of the
    mirror direction at normal incidence (1 for Lambertian, 1/(4α²) for GGX),
    clamped to [1, boost_max] (mis_pdf skips the boost for boost_max = 1 and keeps
    the density approximation). Deterministic per shading point, so MIS
    stays unbiased; the low-order terms, whose ``eval`` is deterministic, keep
    their exact density.
    """
    sharp = dr.pi * sp.pdf(sp.frame_p, sp.wp, sp.wp, active)
    return dr.clip(sharp, 1.0, boost_max)
