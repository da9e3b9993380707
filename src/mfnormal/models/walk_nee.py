"""Next-event estimation toward ω_o at a walk's vertex: the evaluation loop's steps (docs/model.md §4.3-4.8).

``add_nee`` is the NEE of Algorithms 2 and 3 at a vertex lit from w_in on a depth interval H:
f_m(w_in, ω_o)⟨ω_o, ω_m⟩ times the share of H that sees ω_o (G₂), and with a mirror tangent
facet also the leg that reflects off it toward ω_o (``mirror_leg``, H_r). A :class:`NeeTarget`
holds what every vertex's NEE needs of ω_o. With a same-material tangent facet, ``connect``
adds each vertex's MIS-weighted connection to the next facet by a sample from ω_o, and
``connected_nee`` weights the walk's own NEE against it (``connection_weight``, the balance
heuristic). ``t_start_share`` is the first nested vertex's NEE of a walk that starts on t, taken
in expectation (§4.5).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from mfnormal.surface import microsurface as ms
from mfnormal.surface.microsurface import negate
from mfnormal.models.rng import slot_connect, uniform
from mfnormal.surface.shading import select_frame
from mfnormal.models.walk_pdf import first_interval
from mfnormal.models.walk_steps import vertex_frame


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

