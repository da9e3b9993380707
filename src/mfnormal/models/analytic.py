"""The paper's default model: up to two facet bounces, mirror tangent facet (docs/model.md §3).

    f(ω_i,ω_o)⟨ω_o,ω_g⟩ = λ_p(ω_i)·[ f_p(ω_i,ω_o) G1(ω_o,p)                                   i→p→o
                                   + f_p(ω_i,ω'_o)(1 − G1(ω'_o,p)) G1(ω_o,t) ]            i→p→t→o
                        + λ_t(ω_i)·  f_p(ω'_i,ω_o) G1(ω_o,p)                                i→t→p→o

with ω' = flip_t(ω) and f_p the nested f·cos in the p frame. Its sampler leaves p along
a nested sample d directly or after the mirror in proportion to the energy each way carries,
G1(d,p) : (1 − G1(d,p)) G1(ω'_d,t) (``exit_split``), so its pdf is the three terms with the
nested pdf in place of f, the first two divided by that energy E(d) at their d (ω_o, ω'_o),
the third without its G1(ω_o,p).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mfnormal.models import rng
from mfnormal.surface.microsurface import negate, score


def exit_split(sp, d, d_m):
    """(G1(d, p), (1 − G1(d, p))·G1(d_m, t)) with d_m = flip_t(d): the energy a ray leaving p
    along d carries out directly, and after mirroring off the tangent facet (docs/model.md §3.2)."""
    return sp.G1_p(d), sp.one_minus_G1_p(d) * sp.G1_t(d_m)


def exit_energy(sp, d, d_m):
    """E(d) = G1(d, p) + (1 − G1(d, p))·G1(d_m, t): the energy leaving p along d in two bounces."""
    direct, mirrored = exit_split(sp, d, d_m)
    return direct + mirrored


def eval_pdf(sp, wo, active, want_value=True, want_pdf=True):
    """(f·⟨wo,z⟩, pdf) of the analytic model at the shading point ``sp``."""
    wi = sp.wi
    active = active & (wi.z > 0) & (wo.z > 0)
    lp = sp.lambda_p(wi)
    wo_m = sp.flip_t(wo)
    wi_m = sp.flip_t(wi)
    g_o_p, g_o_t = sp.G1_p(wo), sp.G1_t(wo)

    # Probability of each path's facet sequence: i→p→o, i→p→t→o, i→t→p→o.
    # (1 − G1) and λ_t are computed directly: term 2 at (i,o) equals term 3 at
    # (o,i) only if these small numbers keep their digits.
    c1 = lp * g_o_p
    c2 = dr.select(g_o_t > 0, lp * sp.one_minus_G1_p(wo_m), 0.0)
    c3 = dr.select(g_o_p > 0, sp.lambda_t(wi), 0.0)
    a1, a2, a3 = active & (c1 > 0), active & (c2 > 0), active & (c3 > 0)
    frame = sp.frame_p

    value, pdf = mi.Spectrum(0.0), mi.Float(0.0)
    if want_value and want_pdf:
        (f1, p1), (f2, p2), (f3, p3) = (sp.eval_pdf(frame, wi, wo, a1), sp.eval_pdf(frame, wi, wo_m, a2),
                                        sp.eval_pdf(frame, wi_m, wo, a3))
    elif want_value:
        f1, f2, f3 = sp.eval(frame, wi, wo, a1), sp.eval(frame, wi, wo_m, a2), sp.eval(frame, wi_m, wo, a3)
    else:
        p1, p2, p3 = sp.pdf(frame, wi, wo, a1), sp.pdf(frame, wi, wo_m, a2), sp.pdf(frame, wi_m, wo, a3)

    if want_value:
        value = f1 * c1 + f2 * (c2 * g_o_t) + f3 * (c3 * g_o_p)
        value = dr.select(active & dr.all(dr.isfinite(value)), dr.maximum(value, 0.0), 0.0)
    if want_pdf:
        # The sampler's exit split (exit_split): the first two terms over the energy E(d)
        # leaving p along d = ω_o and d = ω'_o.
        e1, e2 = exit_energy(sp, wo, wo_m), exit_energy(sp, wo_m, wo)
        pdf = (p1 * dr.select(e1 > 0, c1 / dr.select(e1 > 0, e1, 1.0), 0.0)
               + p2 * dr.select(e2 > 0, c2 * g_o_t / dr.select(e2 > 0, e2, 1.0), 0.0) + p3 * c3)
        pdf = dr.select(active & dr.isfinite(pdf), dr.maximum(pdf, 0.0), 0.0)
    return value, pdf


def sample(sp, sample1, sample2, active):
    """Sample the analytic model; returns (BSDFSample3f, weight = eval/pdf).

    Derivatives: a smooth lobe's direction is detached, its weight eval(θ)/detach(pdf) and
    its pdf attached (Mitsuba's detached sampling); a delta lobe's direction and weight are
    differentiable functions, times the ``score`` (microsurface.score) of the facet choices that led to it."""
    wi = sp.wi
    active = active & (wi.z > 0)

    # Choose the first facet hit from wi; reuse sample1 for the nested BSDF.
    lp = sp.lambda_p(wi)
    on_p, s1 = rng.choose(sample1, dr.detach(lp))

    # Light reaches p directly, or after mirroring off the tangent facet.
    bs, w = sp.sample(sp.frame_p, dr.select(on_p, wi, sp.flip_t(wi)), s1, sample2, active)
    d_m = sp.flip_t(bs.wo)
    direct, mirrored = exit_split(sp, bs.wo, d_m)
    energy = direct + mirrored
    safe = dr.select(energy > 0, energy, 1.0)
    leave, mirror = dr.select(energy > 0, direct / safe, 1.0), dr.select(energy > 0, mirrored / safe, 0.0)

    # From p, leave along d or mirror off the tangent facet (p→t→o), in proportion to the
    # energy each way carries; after i→t→p the ray leaves, carrying G1(d, p).
    seed = rng.hash_floats(rng.SALT_ANALYTIC_SAMPLE, sample1, sample2.x, sample2.y)
    to_t = on_p & (rng.uniform(seed, rng.SLOT_ANALYTIC_SHADOW) >= dr.detach(leave))
    wo = dr.select(to_t, d_m, bs.wo)
    path = dr.select(on_p, energy, direct)
    prob = dr.select(on_p, lp * dr.select(to_t, mirror, leave), 1.0 - lp)
    active &= (bs.pdf > 0) & (path > 0) & (wo.z > 0) & dr.all(dr.isfinite(wo))

    # Smooth lobes: weight = eval/pdf with the exact pdf. Delta lobes: the path weight.
    delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
    wo = dr.select(delta, wo, dr.detach(wo))
    value, pdf = eval_pdf(sp, wo, active & negate(delta))
    weight = dr.select(delta, w * path * score(prob), value / dr.detach(dr.select(pdf > 0, pdf, 1.0)))
    bs.pdf = dr.select(delta, bs.pdf * prob, pdf)
    active &= (bs.pdf > 0) & dr.all(dr.isfinite(weight))

    bs.wo = dr.select(active, wo, mi.Vector3f(0.0, 0.0, 1.0))   # never a NaN direction
    bs.pdf = dr.select(active, bs.pdf, 0.0)
    return bs, dr.select(active, dr.maximum(weight, 0.0), 0.0)
