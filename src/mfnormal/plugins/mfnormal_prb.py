r"""
.. _integrator-mfnormal_prb:

Path replay backpropagation for stochastic BSDFs (:monosp:`mfnormal_prb`)
-------------------------------------------------------------------------

.. pluginparameters::

 * - max_depth
   - |int|
   - Longest path depth (-1: unbounded; 2: direct light only). Default: 6, as ``prb``.
 * - rr_depth, hide_emitters, terminator_offset, footprint
   - |int|, |bool|, |bool|, |bool|
   - As for :ref:`mfnormal_path <integrator-mfnormal_path>` (defaults 5, false, true, true):
     Russian roulette from ``rr_depth`` on, as ``prb``; with ``terminator_offset`` false, shadow
     rays and outgoing rays start from the triangle, as ``prb``; ``footprint``: the pixel's
     footprint in uv at every hit (``si.duv_dx``, ``si.duv_dy``). Typed as there: a value of
     another type or out of range is refused at load, naming the parameter (``prb`` takes a
     ``max_depth`` of 1.5 or 2^40 and fails later).

Mitsuba's ``prb`` (detached path replay: NEE with MIS, emitter hits, Russian roulette, the
area Jacobian of moving geometry) with one change, for BSDFs whose ``eval`` is a Monte Carlo
estimate (the random-walk models ``separable`` and ``nonseparable``; docs/model.md §9).

``prb`` differentiates the light that arrives through a BSDF sample, L·f/p, by the relative
derivative of a re-evaluation, L·∂f/f. For a deterministic ``eval`` that is exact; for an
estimate f̂ it is L·∂f̂/f̂, a ratio of estimates whose expectation is not ∂f/f: biased
(measured for the walks under a constant environment: +14 % to +26 %). Here, at a BSDF that
declares ``stochastic_eval`` (the walks of ``normalmap_microfacet``), the adjoint pass instead
re-draws ``bsdf.sample`` with the primal pass's sample numbers, gradients on, and uses the
relative derivative of its **weight**: the walks' weight carries an unbiased derivative
(score terms p/detach(p) for each of the walk's decisions, detached directions; models/walk.py).
Every other BSDF (built-in ones, the deterministic models ``faithful`` and ``analytic``) is
differentiated exactly as ``prb`` does, through ``bsdf.eval`` (tested equal to ``prb``).
Light from NEE is linear in the eval estimate and needs nothing new.

The shadow terminator of smooth-shaded meshes is handled as in ``mfnormal_path``
(``terminator_offset``): light samples and rays leaving on the interpolated normal's side start
from the smooth surface point, whose displacement from the hit point is detached (it moves
with the triangle; its own dependence on moving vertices and normals is not differentiated).
With ``terminator_offset`` false the integrator is ``prb`` with the change above.

The pixel's footprint (``footprint``) is ``mfnormal_path``'s ray cone, with the same rules and
the same camera cone (``prb`` draws its camera rays with one pixel's differentials; they are
scaled here by 1/√spp, as ``path`` scales them). It is detached and computed from the same
detached rays and samples in the primal and the differential phase, so the BSDF sees the same
footprint in both.

Limitations: a walk nested inside another BSDF (``twosided``, ``blendbsdf``) is seen as that
BSDF, i.e. differentiated as ``prb`` does (biased); for the walks the cosine's and the BSDF's
dependence on moving geometry is not differentiated (the Jacobian J is still applied): use
it for material parameters. A mirror-facet walk's sample that leaves by the mirror has a
direction that moves with the map; detached replay does not follow it, so those walks'
texel derivatives are biased where the incident radiance varies with direction (measured
in docs/model.md §9; zero under a constant environment).

.. tabs::

    .. code-tab:: python

        'type': 'mfnormal_prb',
        'max_depth': 6,
        'footprint': True
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mfnormal.plugins import cone, terminator
from mfnormal.plugins.mfnormal_path import integrator_params
from mfnormal.plugins.variant_class import variant_subclass

PARAMS = integrator_params("mfnormal_prb", 6)


def _is_stochastic(bsdf):
    """Per BSDF instance (``dr.dispatch``): does it declare a stochastic ``eval``?"""
    return mi.Bool(bool(getattr(bsdf, "stochastic_eval", False)))


def _indirect_factor(ctx, si, bsdf, wo, sample1, sample2, active):
    """The value whose relative derivative stands for the sampled light's: at a BSDF with a
    stochastic ``eval``, the weight of the sample re-drawn with the primal's numbers; at any
    other, as ``prb``: eval at ``wo``."""
    stochastic = dr.detach(dr.dispatch(bsdf, _is_stochastic)) & active
    weight = bsdf.sample(ctx, si, sample1, sample2, stochastic)[1]
    value = bsdf.eval(ctx, si, wo, active & ~stochastic)
    return dr.select(stochastic, weight, value)


def _surface(pi, ray, pi_prev, ray_prev, depth, primal, shift_prev=None, footprint=None):
    """The interaction, attached to moving geometry (``prb``): si, with si.wi following the
    motion of the previous vertex (the ray's origin: ``shift_prev`` off it, if given), and the
    ray cone ``footprint`` (w, beta) grown to it, si carrying its footprint (None: none)."""
    flags = mi.RayFlags.All if footprint is None else cone.RAY_FLAGS
    with dr.resume_grad(when=not primal):
        si = pi.compute_surface_interaction(ray, ray_flags=flags)
        if not primal:
            prev = pi_prev.compute_surface_interaction(ray_prev, ray_flags=mi.RayFlags.Minimal)
            origin = prev.p if shift_prev is None else prev.p + shift_prev
            here = dr.detach(si)
            wi = here.to_local(dr.normalize(origin - here.p))
            si.wi = dr.select(depth >= 1, dr.replace_grad(si.wi, wi), si.wi)
    if footprint is None:
        return si, None
    si, w = cone.at_hit(si, ray, *footprint)
    return si, (w, footprint[1])


def _next_event(scene, sampler, ctx, si, bsdf, beta, active_em, primal, shift=None):
    """Light sampling with MIS (``prb``): the detached sample, its contribution recomputed
    differentiably (emitter values, the area Jacobian, BSDF value and pdf); from ``si.p + shift``
    (:mod:`mfnormal.plugins.terminator`) if given."""
    common = mi.ad.integrators.common
    if shift is None:
        ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
    else:
        ds, em_weight = terminator.sample_emitter(scene, si, shift, sampler.next_2d(), active_em)
    active_em &= ds.pdf != 0.0
    with dr.resume_grad(when=not primal):
        ref = si if shift is None else terminator.moved(si, shift)
        if not primal:
            flags = ds.emitter.flags()
            surface = mi.has_flag(flags, mi.EmitterFlags.Surface)
            infinite = mi.has_flag(flags, mi.EmitterFlags.Infinite)
            textured = active_em & surface & mi.has_flag(flags, mi.EmitterFlags.SpatiallyVarying)
            ray_em = ref.spawn_ray_to(ds.p)
            ray_em.o = dr.fma(ray_em.d, ray_em.maxt, ray_em.o)
            ray_em.maxt = dr.largest(ray_em.maxt)
            ds_diff = mi.DirectionSample3f(scene, scene.ray_intersect(ray_em, textured), ref)
            ds_diff = dr.select(textured, ds_diff, dr.zeros(mi.DirectionSample3f))
            ds_diff.d = dr.select(textured, ds_diff.d, dr.normalize(ds.p - ref.p))
            ds_diff.d = dr.select(~infinite, ds_diff.d, ds.d)
            ds = dr.replace_grad(ds, ds_diff)
            J = common.solid_angle_to_area_jacobian(ref.p, dr.detach(ds.p), dr.detach(ds.n),
                                                    active_em & surface)
            inv_pdf = dr.select(ds.pdf != 0, dr.rcp(ds.pdf), 0)
            em_value = scene.eval_emitter_direction(ref, ds, active_em)
            em_weight = dr.replace_grad(em_weight, em_value * dr.detach(inv_pdf)) * dr.relative_grad(J)
        value, pdf = bsdf.eval_pdf(ctx, si, si.to_local(ds.d), active_em)
        mis = dr.select(ds.delta, 1, common.mis_weight(ds.pdf, pdf))
        return beta * mis * value * em_weight


def _replay(mode, ctx, si, bsdf, ray_next, pi_next, sample1, sample2, L, Le, Lr_dir, dL, active,
            shift=None):
    """The differential phase at one vertex: this vertex's contributions made differentiable,
    the sampled light's through :func:`_indirect_factor`; propagated forward (returns the
    new δL) or backward. ``shift``: the sampled ray's origin off ``si.p``."""
    si_next = pi_next.compute_surface_interaction(ray_next, ray_flags=mi.RayFlags.Minimal, active=active)
    with dr.resume_grad():
        hit = active & si_next.is_valid()
        origin = si.p if shift is None else si.p + shift
        J = mi.ad.integrators.common.solid_angle_to_area_jacobian(origin, si_next.p, si_next.n, hit)
        wo_world = dr.replace_grad(ray_next.d, dr.select(si_next.is_valid(),
                                                         dr.normalize(si_next.p - origin), ray_next.d))
        factor = _indirect_factor(ctx, si, bsdf, si.to_local(wo_world), sample1, sample2, active)
        Lo = Le + Lr_dir + L * dr.relative_grad(factor) * dr.relative_grad(J)
        if dr.flag(dr.JitFlag.VCallRecord) and not dr.grad_enabled(Lo):
            raise RuntimeError("mfnormal_prb: the differential phase's contribution is not attached "
                               "to the AD graph (no scene parameter with gradients enabled?)")
        if mode == dr.ADMode.Backward:
            dr.backward_from(dL * Lo)
            return dL
        return dL + dr.forward_to(Lo)


def _leave(si, bs, shift, footprint):
    """The BSDF-sampled ray, its origin's shift off ``si.p`` (None without the offset), the
    detached origin, the reference of the next vertex's MIS, and the ray cone after the bounce
    (None without one)."""
    d = si.to_world(bs.wo)
    if footprint is not None:
        footprint = (footprint[0], cone.bounce(footprint[1], si, bs))
    if shift is None:
        return si.spawn_ray(d), None, dr.detach(si, True), footprint
    shift = terminator.outward(si, shift, d)
    origin = terminator.moved(si, shift)
    return origin.spawn_ray(d), shift, dr.detach(origin, True), footprint


class MfnormalPRB:
    """The integrator's methods; :func:`integrator_class` binds them to the active variant's
    ``RBIntegrator`` (Mitsuba's base of ``prb``: render, render_forward, render_backward)."""

    def __init__(self, props: mi.Properties):
        values = {p.name: p.read(props) for p in PARAMS}   # typed, before the base reads them untyped
        type(self).__mro__[1].__init__(self, props)   # the variant's RBIntegrator
        self.terminator_offset, self.footprint = values["terminator_offset"], values["footprint"]

    def _skip_emitters(self, scene, ray, pi, active):
        """``hide_emitters``: the first hit behind directly visible area emitters."""
        skip = pi.is_valid() & (pi.shape.emitter() != None) & active  # noqa: E711 (Dr.Jit mask)
        ray_skip = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, skip).spawn_ray(ray.d)
        pi[skip] = self.skip_area_emitters(scene, ray_skip, True, skip)
        return pi

    def _camera_cone(self, ray, sampler):
        """The camera ray's cone (w, beta) (None without ``footprint``): as ``path``'s, whose
        rays' differentials are scaled by 1/√spp (``prb`` draws one pixel's). Detached, from the
        same rays in the primal and the differential phase."""
        return cone.camera_cone(ray, sampler.sample_count() ** -0.5) if self.footprint else None

    @dr.syntax
    def sample(self, mode, scene, sampler, ray, δL, state_in, active, **kwargs):
        """``ADIntegrator.sample``: (radiance or its derivative, valid, [], radiance state)."""
        primal = mode == dr.ADMode.Primal
        ctx, footprint = mi.BSDFContext(), self._camera_cone(ray, sampler)
        ray = mi.Ray3f(dr.detach(ray))
        depth, L = mi.UInt32(0), mi.Spectrum(0 if primal else state_in)
        δL = mi.Spectrum(δL if δL is not None else 0)
        β, η, active = mi.Spectrum(1), mi.Float(1), mi.Bool(active)
        pi = scene.ray_intersect_preliminary(ray, coherent=True, reorder=False, active=active)
        ray_prev, pi_prev = mi.Ray3f(ray), dr.zeros(mi.PreliminaryIntersection3f)
        si_prev = dr.zeros(mi.SurfaceInteraction3f)
        pdf_prev, delta_prev = mi.Float(1.0), mi.Bool(True)
        if dr.hint(self.hide_emitters, mode="scalar"):
            pi = self._skip_emitters(scene, ray, pi, active)
        offset = self.terminator_offset and terminator.applies(scene)
        shift_prev = mi.Vector3f(0.0) if offset else None   # the ray's origin off its vertex

        while dr.hint(active, max_iterations=self.max_depth, label=f"mfnormal_prb ({mode.name})"):
            active_next = mi.Bool(active)
            si, footprint = _surface(pi, ray, pi_prev, ray_prev, depth, primal, shift_prev, footprint)
            bsdf = si.bsdf(ray)
            # Emitter hit, MIS-weighted against the previous vertex's light sample
            if dr.hint(self.hide_emitters, mode="scalar"):
                active_next &= ~((depth == 0) & ~si.is_valid())
            ds = mi.DirectionSample3f(scene, si=si, ref=si_prev)
            mis = mi.ad.integrators.common.mis_weight(pdf_prev, scene.pdf_emitter_direction(si_prev, ds, ~delta_prev))
            with dr.resume_grad(when=not primal):
                Le = β * mis * ds.emitter.eval(si, active_next)
            # Light sampling
            active_next &= (depth + 1 < self.max_depth) & si.is_valid()
            active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
            shift = terminator.smooth_shift(si, pi.prim_uv) if offset else None
            Lr_dir = _next_event(scene, sampler, ctx, si, bsdf, β, active_em, primal, shift)
            # Detached BSDF sampling (its sample numbers kept for the replay)
            sample1, sample2 = sampler.next_1d(), sampler.next_2d()
            bs, weight = bsdf.sample(ctx, si, sample1, sample2, active_next)
            L = (L + Le + Lr_dir) if primal else (L - Le - Lr_dir)
            ray_next, shift_next, si_prev, footprint = _leave(si, bs, shift, footprint)
            η *= bs.eta
            β *= weight
            pdf_prev, delta_prev = bs.pdf, mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
            # Russian roulette (prb's rule)
            β_max = dr.max(mi.unpolarized_spectrum(β))
            active_next &= β_max != 0
            rr_prob = dr.minimum(β_max * η**2, .95)
            rr_active = depth >= self.rr_depth
            β[rr_active] *= dr.rcp(rr_prob)
            active_next &= ~rr_active | (sampler.next_1d() < rr_prob)
            pi_next = scene.ray_intersect_preliminary(ray_next, coherent=False, reorder=False,
                                                      active=active_next)
            if dr.hint(not primal, mode="scalar"):
                δL = _replay(mode, ctx, si, bsdf, ray_next, pi_next, sample1, sample2, L, Le, Lr_dir,
                             δL, active_next, shift_next)
            depth[si.is_valid()] += 1
            active = active_next
            pi_prev, pi, ray_prev, ray = pi, pi_next, ray, ray_next
            shift_prev = shift_next

        return (L if primal else δL, depth != 0, [], L)


def integrator_class() -> type:
    """``MfnormalPRB`` as a subclass of the active variant's ``RBIntegrator``."""
    return variant_subclass(MfnormalPRB, mi.ad.integrators.common.RBIntegrator)
