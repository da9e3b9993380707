"""The naive evaluation of the non-separable model: one sampled height, binary shadow tests.

Supplemental §3: evaluating Algorithm 1 with next-event estimation needs a height
on the microsurface; this estimator draws it once, uniformly in the part of the
first facet seen from ω_i, and tests every NEE and every escape against it. The
supplemental's Algorithms 2/3 (``mfnormal.models.walk.eval_walk``) track the interval of
possible heights instead, which is this estimator's expectation given the path:
same mean, less variance (tests/test_walk.py, validation/run.py's ``variance``).

It is the package's evaluation loop without its Rao-Blackwellised first vertex,
started from a point interval [h, h]: for a point, ``walk_steps.cross``'s escape is the
binary test and ``walk_nee.add_nee``'s interval weights are 0 or 1. It shares the
walk's steps and random numbers, so the two estimators are paired per query.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mfnormal.models import rng, walk_nee, walk_steps


def naive_eval(sp, wo, specular_tangent, max_bounces=walk_steps.MAX_BOUNCES):
    """Unbiased estimate of f·⟨wo, z⟩ of the non-separable walk from a sampled first height."""
    params = walk_steps.WalkParams(separable=False, specular_tangent=specular_tangent, max_bounces=max_bounces,
                                   rr_depth=0)
    wi = sp.wi
    active = mi.Bool(True) & (wi.z > 0) & (wo.z > 0)
    seed = rng.hash_floats(rng.SALT_WALK_EVAL, wi.x, wi.y, wo.x, wo.y, sp.si.p.x, sp.si.p.y, sp.si.p.z)
    on_p, _ = rng.choose(rng.uniform(seed, rng.SLOT_START_FACET), sp.lambda_p(wi))
    h = rng.uniform(seed, rng.SLOT_START_HEIGHT) * sp.G1(wi, on_p)
    walker = walk_steps.start(sp, on_p, h, h, active)
    to = walk_nee.NeeTarget.toward(sp, params, wo)

    def body(w, L):
        if specular_tangent:
            walk_steps.mirror_fold(sp, w, params, seed)
        L = walk_nee.add_nee(L, sp, params, to, w.on_p, -w.d, w.a, w.b, w.e, w.walking)
        walk_steps.bounce(sp, w, params, seed, walk_steps.vertex_frame(sp, params, w.on_p),
                          *walk_steps.nested_numbers(seed, w.depth))
        return w, L

    _, L = dr.while_loop((walker, dr.zeros(mi.Spectrum, dr.width(wi))), lambda w, L: w.walking, body,
                         label="naive_walk")
    return dr.select(active & dr.all(dr.isfinite(L)), dr.maximum(L, 0.0), 0.0)
