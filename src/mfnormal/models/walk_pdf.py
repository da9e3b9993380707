"""The random walks' MIS pdf (docs/model.md §5): a deterministic function of (ω_i, ω_o).

The exact density of the walk's low-order exits (the first bounce off either facet, and the
second and third vertices a mirror tangent facet makes likely) plus a cosine lobe for the
longer walks, whose share is boosted by the nested lobe's sharpness where longer walks are
likely (variance-aware MIS, capped at ``mis_boost_max``). MIS stays unbiased with any such
function; ``mis_boost_max=1`` gives the plain density approximation.
"""

from __future__ import annotations

from dataclasses import replace

import drjit as dr
import mitsuba as mi

from mfnormal.surface import microsurface as ms
from mfnormal.surface.microsurface import negate
from mfnormal.surface.shading import select_frame
from mfnormal.models.walk_replay import calls


def first_interval(sp, params, on_p):
    """(a, b): the depths on the first facet that a ray from ω_i can hit, [0, G1(ω_i, m)]
    (the top G1 of its height, Algorithm 2); [0, 1] for the separable walk."""
    return mi.Float(0.0), mi.Float(1.0) if params.separable else sp.G1(sp.wi, on_p)


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


def glossy_wall_terms(sp, params, wo, lp, active):
    """The MIS pdf's terms for the walks that ``eval`` estimates stochastically with a
    same-material tangent facet (they take the boost, docs/model.md §5): the two-vertex
    walks i→p→t→o and i→t→p→o with the t bounce taken as a mirror (the centre of a glossy
    wall's lobe; without them BSDF samples reflected off a glossy wall got almost no MIS
    weight: this pdf was 7-14× below the walk's density at α = 0.05), and the three-vertex
    walks (``third_vertex``), which the plain density leaves to its cosine rest. Their reach
    and escape probabilities are the separable model's, for both models: the non-separable
    model's depth intervals make them exactly zero at some lobe centres whose neighbourhood
    the glossy walks still reach (the pdf was 33× below the walk's density there).
    Returns (the two-vertex terms, the three-vertex terms)."""
    loose = replace(params, separable=True)
    p, t = mi.Bool(True), mi.Bool(False)
    wi = sp.wi
    wo_m, wi_m = sp.flip_t(wo), sp.flip_t(wi)
    h = first_interval(sp, loose, p)
    e_pto = lp * (1.0 - _escape(sp, h, p, wo_m)) * _escape(sp, h, t, wo)           # i→p→t→o
    e_tpo = (1.0 - lp) * _escape(sp, h, p, wo)                                      # i→t→p→o
    two = (sp.pdf(sp.frame_p, wi, wo_m, active & (e_pto > 0)) * e_pto
           + sp.pdf(sp.frame_p, wi_m, wo, active & (e_tpo > 0)) * e_tpo)
    return two, third_vertex(sp, loose, h, wo, lp, active)


def third_vertex(sp, params, h, wo, lp, active):
    """The density toward wo of the walks whose first two nested samples take their lobes'
    centres (the mirror directions about the first facet and then about the other) and whose
    third vertex, on the first facet again, leaves toward wo: share·P(reach it)·(escape
    toward wo)·its nested pdf. With a same-material tangent facet these three-vertex walks
    (p → t → p, share λ_p; t → p → t, share λ_t) give narrow lobes of their own, far from the
    two-vertex terms (the pdf was 50-100× below the walk's density there at GGX α = 0.05,
    docs/model.md §5). Of the two starts the one with the larger weight gives the term (one
    nested call; a deterministic choice, which MIS allows)."""
    q_p, v_p = _third_vertex_reach(sp, params, h, mi.Bool(True), wo, lp)
    q_t, v_t = _third_vertex_reach(sp, params, h, mi.Bool(False), wo, 1.0 - lp)
    use_p = q_p >= q_t
    q = dr.maximum(q_p, q_t)
    return sp.pdf(select_frame(use_p, sp.frame_p, sp.frame_t), dr.select(use_p, v_p, v_t), wo, active & (q > 0)) * q


def _third_vertex_reach(sp, params, h, on_p, wo, share):
    """(share·P(reach the third vertex)·escape toward wo, the direction it is lit from) for a
    walk from ω_i that starts on facet ``on_p`` at depths h (``third_vertex``)."""
    off = negate(on_p)
    frame = select_frame(on_p, sp.frame_p, sp.frame_t)
    n_other = dr.select(on_p, sp.wt, sp.wp)
    d1 = 2.0 * dr.dot(sp.wi, frame.n) * frame.n - sp.wi
    d2 = d1 - 2.0 * dr.dot(d1, n_other) * n_other
    h2 = _land(sp, params, h, on_p, d1)
    q = (share * (1.0 - _escape(sp, h, on_p, d1)) * (1.0 - _escape(sp, h2, off, d2))
         * _escape(sp, _land(sp, params, h2, off, d2), on_p, wo))
    return dr.select((dr.dot(d1, frame.n) > 0) & (dr.dot(d2, n_other) > 0), q, 0.0), -d2


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
    sp = calls(sp, params)
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
    stochastic = longer = 0.0
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
        stochastic, longer = glossy_wall_terms(sp, params, wo, lp, active)
    # 1 − cosθ_p as sin²θ_p/(1 + cosθ_p): never negative (a float32 unit ω_p can have z > 1)
    # and non-zero for tilts below float32's 1 − cos resolution (θ_p ≲ 3e-4).
    rest = sp.sin_p * sp.sin_p / (1.0 + sp.wp.z) * dr.maximum(wo.z, 0.0) * dr.inv_pi
    # The longer walks' share by the chance q2 that a walk has them: a cosine lobe of weight
    # c·q2 instead of the plain density's 1 − cosθ_p, where c > 1, and with a same-material
    # tangent facet the three-vertex lobes (a select, not a branch: mis_boost_max is a
    # kernel input).
    c = stochastic_share_boost(sp, params.mis_boost_max, active)
    q2 = lp * second_visit(sp, params, h_p, wi) + (1.0 - lp) * second_visit(sp, params, h_tp, wi_m)
    boosted = explicit + stochastic * c + rest + (c - 1.0) * q2 * dr.maximum(wo.z, 0.0) * dr.inv_pi
    if not params.specular_tangent:
        boosted += (c - 1.0) * longer
    pdf = dr.select(params.mis_boost_max > 1.0, boosted, explicit + stochastic + rest)
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
    clamped to [1, boost_max] (mis_pdf selects the density approximation for
    boost_max = 1). Deterministic per shading point, so MIS
    stays unbiased; the low-order terms, whose ``eval`` is deterministic, keep
    their exact density.
    """
    sharp = dr.pi * sp.pdf(sp.frame_p, sp.wp, sp.wp, active)
    return dr.clip(sharp, 1.0, boost_max)
