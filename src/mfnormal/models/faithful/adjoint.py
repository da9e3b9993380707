"""Light tracing with the default model: its adjoint eval*(a, b) = eval(b, a)·⟨b,ω_g⟩/⟨a,ω_g⟩
(Veach), sampled by a mixture of the radiance sampler from a and the lobes' own branches for the
parts whose weight depends on the camera side b, with that mixture's exact pdf
(docs/faithful.md §4, §7).

a is the light side (``tx_a.wi``), b the camera side; ``texel_for(b)`` builds the texel seen
from b. With transmission either side may be below the macro surface: |⟨b,ω_g⟩|/|⟨a,ω_g⟩|.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mfnormal.models.faithful.nested import finish
from mfnormal.surface.microsurface import negate, score
from mfnormal.models.rng import ONE_MINUS_EPS


def branches(model, tx_a, texel_for):
    """The sampler's extra branches, each lobe's in the order of ``model.adjoint_lobes``
    (:class:`~.lobes.Branch`)."""
    return [br for lobe in model.adjoint_lobes for br in lobe.branches(tx_a, texel_for)]


def eval_pdf(model, sp, tx_a, tx_b, active, texel_for, want_value=True, want_pdf=True):
    """(eval*, pdf*) for light tracing: light side ``tx_a.wi``, camera side ``tx_b.wi`` (base
    frame: ``wi_real``; with transmission either side, |⟨b,ω_g⟩|/|⟨a,ω_g⟩|)."""
    a, b = tx_a.wi_real, tx_b.wi_real
    trans = model.components.transmission
    if trans:
        active = active & (a.z != 0) & (b.z != 0)
    else:
        active = active & (a.z > 0) & (b.z > 0)
    value, pdf = mi.Spectrum(0.0), mi.Float(0.0)
    # With transmission the value is kept only where the sampler draws b (pdf* > 0): in float32 the
    # far tails of a rough facet's lobes can leave eval(b, a) > 0 where no branch from a reaches b.
    want_pdf = want_pdf or (want_value and trans)
    if want_value:
        value, _ = model.eval_pdf(sp, tx_b, a, active, want_pdf=False)
        value *= dr.abs(b.z) / dr.maximum(dr.abs(a.z), 1e-30) if trans else b.z / dr.maximum(a.z, 1e-30)
        value = dr.select(active & dr.all(dr.isfinite(value)), value, 0.0)
    if want_pdf:
        _, p_rad = model.eval_pdf(sp, tx_a, b, active, want_value=False)
        share = mi.Float(0.0)
        for br in branches(model, tx_a, texel_for):
            p_k = br.lobe.density(sp, tx_a, br, b, active & (br.p > 0))
            pdf, share = pdf + br.p * p_k, share + br.p
        pdf = pdf + (1.0 - share) * p_rad
        pdf = dr.select(active & dr.isfinite(pdf), dr.maximum(pdf, 0.0), 0.0)
        if want_value and trans:
            value = dr.select(pdf > 0, value, 0.0)
    return value, pdf


def sample(model, sp, tx_a, sample1, sample2, active, texel_for):
    """Light-tracing sample from the light side ``tx_a.wi``: (BSDFSample3f in the base frame, weight)."""
    extra = branches(model, tx_a, texel_for)
    # Choose a branch: the extra ones first (consecutive intervals), then the radiance sampler.
    # (The choice, and sample1's rescaling, with detached probabilities.)
    p_rad = 1.0 - sum((br.p for br in extra), mi.Float(0.0))
    c_rad = dr.detach(p_rad)
    picked, lo_k, width, acc = mi.UInt32(len(extra)), 1.0 - c_rad, c_rad, mi.Float(0.0)
    for k, br in enumerate(extra):
        p_k = dr.detach(br.p)
        hit = (sample1 >= acc) & (sample1 < acc + p_k)
        picked = dr.select(hit, k, picked)
        lo_k = dr.select(hit, acc, lo_k)
        width = dr.select(hit, p_k, width)
        acc = acc + p_k
    s1 = dr.clip((sample1 - lo_k) / dr.maximum(width, 1e-30), 0.0, ONE_MINUS_EPS)
    on_rad = picked == len(extra)
    dw = model.draw(sp, tx_a, s1, sample2, active & on_rad)
    state = (dw.bs, dw.w, dw.delta, dw.active)
    for k, br in enumerate(extra):
        state = br.lobe.draw(sp, tx_a, br, picked == k, s1, sample2, active, state)
    bs, w, delta, ok = state
    bs.wo = dr.select(delta, bs.wo, dr.detach(bs.wo))
    tx_b = texel_for(bs.wo)
    value, pdf = eval_pdf(model, sp, tx_a, tx_b, ok & negate(delta), texel_for)
    c_delta, prob_delta = _delta(model, sp, tx_a, tx_b, extra, dw, picked, p_rad, on_rad)
    weight = dr.select(delta, w * c_delta * score(prob_delta), value / dr.detach(dr.select(pdf > 0, pdf, 1.0)))
    bs.pdf = dr.select(delta, bs.pdf * prob_delta, pdf)
    return finish(bs, weight, ok)


def _delta(model, sp, tx_a, tx_b, extra, dw, picked, p_rad, on_rad):
    """Delta lobes: eval*'s coefficient on the sampled path over the draws that give that path,
    and their probability. A refracted path's coefficient carries the change of variables of
    the delta from a to b, |⟨a,ω_p⟩⟨b,ω_g⟩| / |⟨b,ω_p⟩⟨a,ω_g⟩| (1 for reflection)."""
    a, b = tx_a.wi_real, tx_b.wi_real
    trans = model.components.transmission
    ratio = dr.abs(b.z) / dr.maximum(dr.abs(a.z), 1e-30) if trans else b.z / dr.maximum(a.z, 1e-30)
    # The branches that draw the flat lobe, as the radiance sampler's hidden branch does (Hidden).
    flat = [(k, br) for k, br in enumerate(extra) if br.lobe.flat]
    p_hid_x = flat[0][1].p if flat else mi.Float(0.0)
    on_flat = on_rad & negate(dw.on_tex)
    for k, _ in flat:
        on_flat |= picked == k
    # Drawn by the radiance sampler: the facet lit directly (bounced light is never a delta path).
    c_delta = tx_b.vis * tx_b.seen(tx_b.to_camera(a)) * ratio / dr.maximum(p_rad * dw.prob, 1e-30)
    c_delta = dr.select(dw.bounced, 0.0, c_delta)
    prob_delta = p_rad * dw.prob
    if trans:
        refracted = tx_b.vis * ratio * dr.abs(dr.dot(a, sp.wp)) / dr.maximum(dr.abs(dr.dot(b, sp.wp)), 1e-30)
        c_through = dr.select(a.z * b.z < 0, refracted, 0.0) / dr.maximum(p_rad * dw.prob, 1e-30)
        c_delta = dr.select(dw.through, c_through, c_delta)
    c_delta = dr.select(on_flat, (1.0 - tx_b.vis) / dr.maximum(p_hid_x + p_rad * dw.b_hid, 1e-30), c_delta)
    prob_delta = dr.select(on_flat, p_hid_x + p_rad * dw.b_hid, prob_delta)
    # Drawn by a lobe's own branch.
    for k, br in enumerate(extra):
        on_k = picked == k
        c_k = br.lobe.delta(sp, tx_b, br, ratio, on_k)
        if c_k is None:
            continue
        c_delta = dr.select(on_k, c_k, c_delta)
        prob_delta = dr.select(on_k, br.p, prob_delta)
    return c_delta, prob_delta
