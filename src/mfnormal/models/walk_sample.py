"""The sampling loop: supplemental Algorithm 1, a walk from ω_i until the ray leaves (docs/model.md §4.2).

``sample_walk`` runs the loop: at each vertex the mirror fold (a mirror tangent facet) and the
nested sample, crossing to the other facet or out (:mod:`~mfnormal.models.walk_steps`). The exit
is decided from the interval's escape fraction, the same random variable as tracing a ray from a
uniformly drawn height. ``sample`` wraps the exit as the BSDF's sample (``exit_sample``), with
the MIS pdf of :mod:`~mfnormal.models.walk_pdf`. With derivatives the walk's Replay carries the
throughput's and the exit direction's (:mod:`~mfnormal.models.walk_replay`).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mfnormal.surface.microsurface import replace_grad
from mfnormal.models.rng import SALT_WALK_SAMPLE, hash_floats
from mfnormal.models.walk_pdf import mis_pdf
from mfnormal.models.walk_replay import Replay, calls, replays
from mfnormal.models.walk_steps import bounce, first_vertex, mirror_fold, nested_numbers, vertex_frame, walk_loop


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
    walker, p_start, _, s1_first = first_vertex(sp, params, sample1, active, replay)
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

    w, rp = walk_loop((walker, rp, sp.state(), seed, s1_first, mi.Point2f(sample2), p_start), body,
                      "mfnormal_sample_walk")[:2]
    return w, rp


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
