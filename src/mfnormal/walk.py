"""The random-walk models: separable (main paper) and non-separable (supplemental).

One walk serves both (MODEL.md §2.4-2.5, §3.3-3.5). It starts on the facet that
a ray from ω_i hits first and bounces between the two facets until it leaves
the microsurface. The non-separable model tracks the interval H of heights the
walk can be at on the current facet, stored as depths below the crest (see
microsurface.py) (supplemental Algorithms 1-3: rays from a
uniform height in H stay uniform after each bounce, because the facets are
planar); the separable model is the same walk with H reset to [0, 1] at every
vertex, which forgets height correlation.

- ``sample``: the walk's exit direction and throughput (Algorithm 1, with the
  exit decided from the interval's escape fraction, which is the same random
  variable as tracing a ray from a uniformly drawn height);
- ``eval``: next-event estimation toward ω_o at every vertex (Algorithm 2; with
  a mirror tangent facet, Algorithm 3 and its H_r term), an unbiased estimate of
  f·⟨ω_o, ω_g⟩. The first nested vertex's NEE is Rao-Blackwellised: taken in
  expectation over the start facet (and the mirror's escape), so the low-order
  part of ``eval`` is deterministic and only the longer walks add noise;
- ``mis_pdf``: a deterministic function for MIS (MODEL.md §2.8): the exact
  density of the low-order terms plus a cosine lobe for the rest, that lobe
  boosted by the nested lobe's sharpness where longer walks are likely
  (variance-aware MIS: the rest's ``eval`` is the noisy part).

Walks play Russian roulette on their throughput from ``rr_depth`` facet bounces on.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from . import microsurface as ms
from .microsurface import negate
from .rng import (SALT_WALK_EVAL, SALT_WALK_SAMPLE, SLOT_START_FACET, SLOT_START_HEIGHT, choose, hash_floats,
                  slot_escape, slot_nested, slot_roulette, uniform)
from .shading import select_frame

# Default depth (facet bounces) from which walks play Russian roulette on their throughput.
RR_DEPTH = 3
# Default cap of the boost of the longer walks' share in the MIS pdf (GGX α ≤ 1/16 reaches it).
MIS_BOOST_MAX = 64.0


def _walk(sp, separable, specular_t, max_bounces, active, wo=None, sample1=None, sample2=None,
          sampled_height=False, rr_depth=0):
    """Run the walk; in eval mode (``wo`` given) accumulate NEE toward wo.

    ``sampled_height`` (non-separable only) replaces the height interval by one
    height drawn uniformly in it, with binary shadow tests: the naive evaluation
    that the supplemental's interval tracking improves on (kept for validation).
    Returns (exit direction, throughput, escaped, non-delta, L).
    """
    eval_mode = wo is not None
    wi = sp.wi
    n = dr.width(wi)
    wt, cot = sp.wt, ms.cot_p(sp.wp, sp.sin_p)
    active = mi.Bool(active) & (wi.z > 0)

    if eval_mode:
        seed = hash_floats(SALT_WALK_EVAL, wi.x, wi.y, wo.x, wo.y, sp.si.p.x, sp.si.p.y, sp.si.p.z)
        u0 = uniform(seed, SLOT_START_FACET)
    else:
        seed = hash_floats(SALT_WALK_SAMPLE, sample1, sample2.x, sample2.y)
        u0 = sample1

    # First facet, chosen by the intersection probability from wi.
    lp = sp.lambda_p(wi)
    on_p, s1_first = choose(u0, lp)
    # Initial depth interval [a, b]: the part of the facet visible from wi, the
    # top G1 of its height (Algorithm 2); the separable walk forgets it.
    a = mi.Float(0.0)
    b = mi.Float(1.0) if separable else sp.G1(wi, on_p)
    if sampled_height and not separable:
        a = b = uniform(seed, SLOT_START_HEIGHT) * sp.G1(wi, on_p)

    if eval_mode:
        g_o_p, g_o_t = sp.G1_p(wo), sp.G1_t(wo)
        if specular_t:
            wo_m, r_lo, r_hi = mirror_leg(sp, wo, g_o_t)

    # Rao-Blackwellised first vertex (eval only): the NEE at the first nested vertex
    # is taken in expectation over the random start facet and, with a mirror
    # tangent facet, over the mirror's escape, instead of along the one walk below.
    # It is the low-order part that dominates glossy facets, and it becomes
    # deterministic: the loop's first iteration evaluates the p start's NEE for every
    # walk (weighted λ_p, whichever facet the walk started on), t_start_nee adds the
    # t start's, and later iterations add the vertices after the first nested sample.
    rb = eval_mode and not sampled_height
    if rb:
        b_p = mi.Float(1.0) if separable else sp.G1_p(wi)
        L0 = t_start_nee(sp, wo, lp, separable, specular_t, max_bounces, active)

    state = (
        dr.zeros(mi.Vector3f, n) - wi,          # d: travel direction
        dr.full(mi.Spectrum, 1.0, n),           # e: throughput
        mi.Bool(on_p),                          # current facet
        dr.zeros(mi.Float, n) + a, dr.zeros(mi.Float, n) + b,  # H as depths [a, b]
        dr.zeros(mi.Spectrum, n),               # L: NEE estimate
        dr.zeros(mi.UInt32, n),                 # bounce count
        mi.Bool(active),                        # still walking
        dr.zeros(mi.Bool, n),                   # left the microsurface
        dr.zeros(mi.Bool, n),                   # sampled a non-delta lobe on the way
    )

    def cond(d, e, on_p, a, b, L, depth, walking, escaped, nondelta):
        return walking

    def move(on_p, d_new, a, b, ok, c):
        """Leave the microsurface, or land on the other facet (κ, §3.2): (leaves, stays, a, b)."""
        tau, k = ms.crest_map(on_p, d_new, wt, cot)
        leaves = ok & (uniform(seed, c) < ms.escape_fraction(a, b, tau))
        if sampled_height:
            leaves = ok & (a < tau)
        stays = ok & negate(leaves)
        # Land on the other facet (heights [κa, min(κb, 1)] in §3.2's terms).
        a_new, b_new = ms.land(a, b, tau, k)
        a = dr.select(stays, 0.0 if separable else a_new, a)
        b = dr.select(stays, 1.0 if separable else b_new, b)
        return leaves, stays, a, b

    def body(d, e, on_p, a, b, L, depth, walking, escaped, nondelta):
        at_start = depth == 0       # the first vertex (before a folded mirror bounce counts)
        if specular_t:
            # A mirror tangent facet needs no nested call and gives no NEE: its bounce is
            # folded into the iteration of the next p vertex, so a packet runs the nested
            # calls once per p vertex instead of once per vertex. (Same random numbers,
            # same results as one vertex per iteration.)
            mirror = walking & negate(on_p)
            d_m = ms.flip_t(d, wt)
            leaves, stays, a_m, b_m = move(mi.Bool(False), d_m, a, b, mirror & (dr.dot(d_m, wt) > 0),
                                           slot_escape(depth))
            d = dr.select(mirror, d_m, d)
            a, b = dr.select(mirror, a_m, a), dr.select(mirror, b_m, b)
            depth = dr.select(mirror, depth + 1, depth)
            escaped |= leaves
            on_p |= stays
            walking &= negate(mirror) | (stays & (depth < max_bounces))
        frame = sp.frame_p if specular_t else select_frame(on_p, sp.frame_p, sp.frame_t)

        # Next-event estimation toward wo from this vertex (Algorithms 2 and 3).
        if eval_mode:
            nee, w_in, f_n, h_a, h_b, scale = walking, -d, frame, a, b, e
            if rb:
                # First iteration: the p start's share of the Rao-Blackwellised first vertex.
                nee = dr.select(at_start, active, walking)
                w_in = dr.select(at_start, wi, w_in)
                if not specular_t:
                    f_n = select_frame(on_p | at_start, sp.frame_p, sp.frame_t)
                h_a, h_b = dr.select(at_start, 0.0, a), dr.select(at_start, b_p, b)
                scale = dr.select(at_start, mi.Spectrum(lp), e)
            on_p_n = (on_p | at_start) if rb else on_p
            g_o = g_o_p if specular_t else dr.select(on_p_n, g_o_p, g_o_t)
            w2 = ms.fraction_inside(h_a, h_b, 0.0, g_o)
            L += scale * sp.eval(f_n, w_in, wo, nee & (w2 > 0)) * w2
            if specular_t:
                wr = dr.select(g_o_t > 0, ms.fraction_inside(h_a, h_b, r_lo, r_hi), 0.0)
                L += scale * sp.eval(sp.frame_p, w_in, wo_m, nee & (wr > 0)) * wr

        # Continue: sample the facet's BSDF.
        first = depth == 0
        s1 = uniform(seed, slot_nested(depth, 0))
        if not eval_mode:
            s1 = dr.select(first, s1_first, s1)
        s2 = mi.Point2f(uniform(seed, slot_nested(depth, 1)), uniform(seed, slot_nested(depth, 2)))
        if not eval_mode:
            s2 = dr.select(first, mi.Point2f(sample2), s2)
        bs, w = sp.sample(frame, -d, s1, s2, walking)
        d_new = bs.wo
        ok = walking & (dr.dot(d_new, frame.n) > 0) & (bs.pdf > 0) & dr.any(w > 0) & dr.all(dr.isfinite(w))
        nondelta |= walking & negate(mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta))
        e = dr.select(walking, e * w, e)

        leaves, stays, a, b = move(on_p, d_new, a, b, ok, slot_escape(depth))
        if rr_depth > 0:
            # Russian roulette on the throughput from rr_depth bounces on: unbiased, and it
            # ends the long walks of dark materials that cost a packet most of its time.
            q = dr.minimum(dr.max(e), 1.0)
            roulette = stays & (depth + 1 >= rr_depth) & (q < 1.0)
            survive = uniform(seed, slot_roulette(depth)) < q
            e = dr.select(roulette & survive, e / dr.maximum(q, 1e-30), e)
            stays &= negate(roulette) | survive
        d = dr.select(walking, d_new, d)
        depth = dr.select(walking, depth + 1, depth)
        escaped |= leaves
        return (d, e, on_p ^ stays, a, b, L, depth, stays & (depth < max_bounces), escaped, nondelta)

    d, e, _, _, _, L, _, _, escaped, nondelta = dr.while_loop(state, cond, body, label="mfnormal_walk")
    return d, e, escaped, nondelta, (L + L0) if rb else L


def mirror_leg(sp, wo, g_o_t):
    """(ω'_o, lo, hi): the depths [lo, hi] on p whose ray along ω'_o = flip_t(ω_o)
    reflects off the mirror t toward ω_o (H_r, §3.5: heights [(1 − G1(ω_o, t))·h_r, h_r]
    with h_r = 1 − G1(ω'_o, p)); ``g_o_t`` = G1(ω_o, t)."""
    wo_m = sp.flip_t(wo)
    r_lo = sp.G1_p(wo_m)
    return wo_m, r_lo, dr.select(g_o_t > 0, r_lo + g_o_t * (1.0 - r_lo), r_lo)


def t_start_nee(sp, wo, lp, separable, specular_t, max_bounces, active):
    """λ_t(ω_i)·E[NEE toward wo at the first nested vertex of a walk that starts on t].

    With a mirror tangent facet the walk reflects to p first: λ_t·(1 − escape)·NEE
    at p lit from flip_t(ω_i) on the landed depth interval, NEE at p including the
    p→t→ω_o leg (H_r, §3.5); otherwise the NEE at t itself. (The p start's share,
    λ_p·NEE at p lit from ω_i, is the walk loop's first iteration.) The same terms,
    with pdf for eval, are in mis_pdf's explicit part.
    """
    wi = sp.wi
    wt, cot = sp.wt, ms.cot_p(sp.wp, sp.sin_p)
    g_o_t = sp.G1_t(wo)
    b_t = mi.Float(1.0) if separable else sp.G1_t(wi)
    if not specular_t:
        w_t = (1.0 - lp) * ms.fraction_inside(0.0, b_t, 0.0, g_o_t)
        return sp.eval(sp.frame_t, wi, wo, active & (w_t > 0)) * w_t
    # The mirror sends the ray along d_m = flip_t(−ω_i), toward p or out.
    d_m = ms.flip_t(-wi, wt)
    tau, k = ms.crest_map(mi.Bool(False), d_m, wt, cot)
    stay = (1.0 - lp) * (1.0 - ms.escape_fraction(0.0, b_t, tau)) * (1.0 if max_bounces > 1 else 0.0)
    a, b = (mi.Float(0.0), mi.Float(1.0)) if separable else ms.land(0.0, b_t, tau, k)
    wo_m, r_lo, r_hi = mirror_leg(sp, wo, g_o_t)
    w2 = stay * ms.fraction_inside(a, b, 0.0, sp.G1_p(wo))
    wr = stay * dr.select(g_o_t > 0, ms.fraction_inside(a, b, r_lo, r_hi), 0.0)
    return (sp.eval(sp.frame_p, -d_m, wo, active & (w2 > 0)) * w2
            + sp.eval(sp.frame_p, -d_m, wo_m, active & (wr > 0)) * wr)


def eval(sp, wo, separable, specular_t, max_bounces, active, sampled_height=False, rr_depth=0):
    """Unbiased NEE estimate of f·⟨wo, z⟩, deterministic per query."""
    active = mi.Bool(active) & (sp.wi.z > 0) & (wo.z > 0)
    L = _walk(sp, separable, specular_t, max_bounces, active, wo=wo, sampled_height=sampled_height,
              rr_depth=rr_depth)[4]
    return dr.select(active & dr.all(dr.isfinite(L)), dr.maximum(L, 0.0), 0.0)


def mis_pdf(sp, wo, separable, specular_t, active, boost_max=None):
    """Deterministic MIS pdf (MODEL.md §2.8): a density approximation, variance-aware boosted.

    The exact density of walks that leave after their first nested sample
    (with a mirror tangent facet: including the mirror legs i→p→t→o,
    i→t→p→o and i→t→p→t→o; with a same-material one, i→p→t→o and i→t→p→o
    with the t bounce approximated by a mirror), using the model's own escape
    probabilities, plus a cosine lobe of weight 1 − cosθ_p for the longer walks. For white
    Lambertian facets and a mirror tangent facet the separable walk's density
    is exactly cosθ_o/π (MODEL.md §2.7), and so is this pdf.

    The terms that ``eval`` estimates stochastically are multiplied by the boost c of
    ``stochastic_share_boost`` (variance-aware MIS; ``boost_max`` = 1 leaves the plain
    density approximation): with a same-material tangent facet the two-bounce
    terms, and for the longer walks a cosine lobe of weight (c − 1)·q2 is added, q2
    the chance of a second nested vertex for a walk whose first nested sample
    takes its lobe's centre (zero where that centre leaves the microsurface, so
    that light samples keep their weight where longer walks are rare).
    """
    wi = sp.wi
    active = mi.Bool(active) & (wi.z > 0) & (wo.z > 0)
    wt, cot = sp.wt, ms.cot_p(sp.wp, sp.sin_p)
    lp = sp.lambda_p(wi)
    true_, false_ = mi.Bool(True), mi.Bool(False)

    def start(on_p):
        """Initial depth interval on facet m, seen from wi."""
        return (mi.Float(0.0), mi.Float(1.0)) if separable else (mi.Float(0.0), sp.G1(wi, on_p))

    def escape(h, on_p, d):
        # A ray leaves facet m only above its plane: below it, κ = ∞ must not count as an
        # escape (nested pdfs such as llvm roughplastic's are not zero there).
        above = dr.dot(d, dr.select(on_p, sp.wp, wt)) > 0
        return dr.select(above, ms.escape_fraction(h[0], h[1], ms.crest_map(on_p, d, wt, cot)[0]), 0.0)

    def land(h, on_p, d):
        """Interval on the other facet reached by the rays that do not escape."""
        if separable:
            return mi.Float(0.0), mi.Float(1.0)
        return ms.land(h[0], h[1], *ms.crest_map(on_p, d, wt, cot))

    def second_visit(h, w_in):
        """P(a walk on p lit from w_in, its nested sample at the lobe centre (the mirror
        direction about ω_p), crosses to t and, reflected there as by a mirror, lands on p
        again): how likely a second nested vertex is. Exact for a mirror-like nested
        BSDF, which is where the boost is large."""
        d1 = 2.0 * dr.dot(w_in, sp.wp) * sp.wp - w_in
        q = (1.0 - escape(h, true_, d1)) * (1.0 - escape(land(h, true_, d1), false_, sp.flip_t(d1)))
        return dr.select(dr.dot(d1, sp.wp) > 0, q, 0.0)

    h_p = start(true_)
    stochastic = 0.0
    if specular_t:
        wo_m, wi_m = sp.flip_t(wo), sp.flip_t(wi)
        e1 = lp * escape(h_p, true_, wo)                                                  # i→p→o
        e2 = lp * (1.0 - escape(h_p, true_, wo_m)) * escape(land(h_p, true_, wo_m), false_, wo)  # i→p→t→o
        h_tp = land(start(false_), false_, -wi_m)
        e3 = (1.0 - lp) * escape(h_tp, true_, wo)                                        # i→t→p→o
        e4 = (1.0 - lp) * (1.0 - escape(h_tp, true_, wo_m)) * escape(land(h_tp, true_, wo_m), false_, wo)  # i→t→p→t→o
        explicit = (sp.pdf(sp.frame_p, wi, wo, active & (e1 > 0)) * e1
                    + sp.pdf(sp.frame_p, wi, wo_m, active & (e2 > 0)) * e2
                    + sp.pdf(sp.frame_p, wi_m, wo, active & (e3 > 0)) * e3
                    + sp.pdf(sp.frame_p, wi_m, wo_m, active & (e4 > 0)) * e4)
    else:
        e1 = lp * escape(h_p, true_, wo)                                                  # i→p→o
        e2 = (1.0 - lp) * escape(start(false_), false_, wo)                               # i→t→o
        # Two-bounce paths with the t bounce taken as a mirror: the centre of a glossy
        # tangent facet's lobe (exact for the specular facet, whose terms these are).
        # Without them BSDF samples reflected off a glossy wall got almost no MIS weight:
        # this pdf was 7-14× below the walk's density there at α = 0.05.
        wo_m, wi_m = sp.flip_t(wo), sp.flip_t(wi)
        e3 = lp * (1.0 - escape(h_p, true_, wo_m)) * escape(land(h_p, true_, wo_m), false_, wo)  # i→p→t→o
        e4 = (1.0 - lp) * escape(land(start(false_), false_, -wi_m), true_, wo)          # i→t→p→o
        explicit = (sp.pdf(sp.frame_p, wi, wo, active & (e1 > 0)) * e1
                    + sp.pdf(sp.frame_t, wi, wo, active & (e2 > 0)) * e2)
        # eval estimates these two-bounce paths stochastically (one glossy t sample), so
        # they take the variance-aware boost like the longer walks.
        stochastic = (sp.pdf(sp.frame_p, wi, wo_m, active & (e3 > 0)) * e3
                      + sp.pdf(sp.frame_p, wi_m, wo, active & (e4 > 0)) * e4)
    # 1 − cosθ_p as sin²θ_p/(1 + cosθ_p): never negative (a float32 unit ω_p can have z > 1)
    # and non-zero for tilts below float32's 1 − cos resolution (θ_p ≲ 3e-4).
    rest = sp.sin_p * sp.sin_p / (1.0 + sp.wp.z) * dr.maximum(wo.z, 0.0) * dr.inv_pi
    # Variance-aware MIS: the terms that eval estimates stochastically get the boost c;
    # the longer walks' share by the chance q2 that a walk has them (a cosine lobe of
    # weight c·q2 instead of the plain density's 1 − cosθ_p, where c > 1).
    boost_max = MIS_BOOST_MAX if boost_max is None else boost_max
    if boost_max > 1.0:
        c = stochastic_share_boost(sp, boost_max, active)
        h_t_first = h_tp if specular_t else land(start(false_), false_, -wi_m)
        q2 = lp * second_visit(h_p, wi) + (1.0 - lp) * second_visit(h_t_first, wi_m)
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


def sample(sp, sample1, sample2, separable, specular_t, max_bounces, active, boost_max=None, rr_depth=0):
    """Walk from wi until the ray leaves: (BSDFSample3f, throughput)."""
    d, e, escaped, nondelta, _ = _walk(sp, separable, specular_t, max_bounces, active,
                                       sample1=sample1, sample2=sample2, rr_depth=rr_depth)
    valid = escaped & (d.z > 0) & dr.all(dr.isfinite(e)) & dr.all(dr.isfinite(d))
    bs = dr.zeros(mi.BSDFSample3f, dr.width(d))
    bs.wo = dr.select(escaped & dr.all(dr.isfinite(d)), d, mi.Vector3f(0.0, 0.0, 1.0))
    bs.eta = 1.0
    bs.sampled_component = 0
    bs.sampled_type = dr.select(nondelta, mi.UInt32(+mi.BSDFFlags.GlossyReflection),
                                mi.UInt32(+mi.BSDFFlags.DeltaReflection))
    pdf = mis_pdf(sp, d, separable, specular_t, valid & nondelta, boost_max)
    bs.pdf = dr.select(nondelta, pdf, 1.0)
    valid &= bs.pdf > 0
    bs.pdf = dr.select(valid, bs.pdf, 0.0)
    return bs, dr.select(valid, dr.maximum(e, 0.0), 0.0)
