r"""
.. _integrator-mfnormal_path:

Path tracer calling each BSDF's eval_pdf_sample (:monosp:`mfnormal_path`)
-------------------------------------------------------------------------

.. pluginparameters::

 * - max_depth
   - |int|
   - Longest path depth (-1: unbounded; 1: only directly visible emitters). Default: -1, as ``path``.
 * - rr_depth
   - |int|
   - Depth from which Russian roulette may stop a path. Default: 5, as ``path``.
 * - hide_emitters
   - |bool|
   - Hide directly visible emitters. Default: false.
 * - terminator_offset
   - |bool|
   - Start shadow rays and outgoing rays on smooth-shaded meshes from the smooth surface their
     vertex normals describe (Hanika 2021), which removes the stair-stepped shadow terminator of
     low-poly meshes; false: from the triangle, as ``path``. Default: true. A triangle with odd
     vertex normals (one more than 60° off its face normal, or normals on both sides of its
     plane) keeps the flat triangle.
 * - footprint
   - |bool|
   - Carry the pixel's footprint along each path as a ray cone and give it to the BSDF at every
     surface hit, in uv (``si.duv_dx``, ``si.duv_dy``); false: those stay 0 ("no footprint"),
     as with ``path``. Default: true. Only ``normalmap_microfacet`` with ``filter="lean"`` reads
     it; with every other BSDF images are the same either way, bit for bit.

Each parameter takes only its type (``<integer>``, ``<boolean>``; in Python an int, a bool) in
its range: anything else, e.g. ``<string name="terminator_offset" value="false"/>`` or a
``max_depth`` of 1.5, is refused at load with a one-line ``ValueError`` naming the parameter.

Mitsuba 3.9.1's ``path`` calls ``bsdf->eval_pdf_sample(ctx, si, wo, s1, s2)`` at every
vertex (the NEE toward the light sample ``wo`` and the continuation sample), but its Python
trampoline does not forward that method: for a Python BSDF the C++ default runs
``eval_pdf`` and then ``sample``. For the random-walk models these are two walks, two loops
with their own SIMD tails; ``normalmap_microfacet``'s ``eval_pdf_sample`` does both with
one walk. This integrator is ``path`` (the same algorithm and the same order of the
sampler's numbers: an image of built-in BSDFs equals ``path``'s to float rounding) whose
BSDF call is a ``dr.dispatch`` over the shapes' BSDFs, so that a Python BSDF's own
``eval_pdf_sample`` runs (a built-in's is its C++ method).

**The shadow terminator.** On a mesh with vertex normals (smooth shading) the interpolated normal
faces the light over part of the triangles that face away from it; a shadow ray from the flat
triangle toward such a light enters the mesh and is blocked, and the lit region ends in the
stair-stepped line of the triangle edges. With ``terminator_offset`` (the default) the shadow ray
starts from the point of the smooth surface that the vertex normals imply (Hanika, "Hacking the
shadow terminator", Ray Tracing Gems II, 2021; Cycles' geometry offset): the hit point projected
onto the tangent planes of the triangle's three vertices (outward only) and the projections
interpolated with its barycentrics. The light sample is drawn from that point, and a BSDF-sampled
ray that leaves on the interpolated normal's side starts there too, so that light sampling and
BSDF sampling see the same visibility (MIS combines them); rays toward the other side, flat
triangles, triangles with odd vertex normals (their tangent planes are no surface near the
triangle: the origin would move across it or below its plane) and other shapes are unchanged. With ``terminator_offset`` false the image is
``path``'s. The offset is not reciprocal: Mitsuba's light tracer (``ptracer``) still sees the
triangles' terminator, so the two agree only away from it.

**The pixel's footprint** (``footprint``, ``src/mfnormal/plugins/cone.py``). A ray cone
(Akenine-Möller et al., "Improved shader and texture level of detail using ray cones", JCGT
2021) leaves the camera with the spread and width of the sensor's ray differentials (as
``path`` receives them: scaled by 1/√spp, the share of the pixel one sample covers, so that a
filter by the footprint vanishes as the sample count grows); its width grows by its spread
along each segment. At each hit the BSDF receives the two axes of the cone's cross-section on
the tangent plane, mapped to uv (``si.duv_dx``: across the plane of incidence, of the cone's
width; ``si.duv_dy``: along it, stretched by 1/cos θ; each the uv step across the whole
footprint, as a ray differential's across a pixel; 0 where the surface has no regular uv
parametrisation, e.g. a sphere's pole). After the bounce its spread changes: a mirror
reflection adds twice the angle by which the surface's normal turns across the footprint
(``si.dn_du``, ``si.dn_dv``: a convex mirror widens the cone, a concave one focuses it, a flat
one keeps it); a delta refraction scales it by 1/η (plus (1 − 1/η) times that turn); a glossy
or diffuse sample sets it to the cone whose solid angle is 1/pdf of the sampled direction (at
least the mirror's); a null interaction keeps it. The footprint is detached.

Primal rendering only: it does not re-evaluate the BSDF for derivatives as ``path`` does;
under AD (a ray that carries derivatives) it raises, use ``prb`` there (``mfnormal_prb`` for
the random walks). Unpolarised variants only.

.. tabs::
    .. code-tab:: xml

        <integrator type="mfnormal_path">
            <integer name="max_depth" value="8"/>
            <boolean name="terminator_offset" value="true"/>
            <boolean name="footprint" value="true"/>
        </integrator>

    .. code-tab:: python

        'type': 'mfnormal_path',
        'max_depth': 8,
        'terminator_offset': True,
        'footprint': True
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mfnormal.models.properties import INT32_MAX, Boolean, Integer
from mfnormal.plugins import cone, terminator
from mfnormal.plugins.variant_class import variant_subclass

RR_PROB_MAX = 0.95      # path's cap of the Russian roulette survival probability


def integrator_params(plugin: str, max_depth: int) -> tuple:
    """The parameters of the integrator ``plugin`` (``max_depth``: its default), typed and in
    ``path``'s ranges: (max_depth, rr_depth, hide_emitters, terminator_offset, footprint)."""
    return (Integer(plugin, "max_depth", max_depth, -1,
                    expects=f"-1 (unbounded) or an integer between 0 and {INT32_MAX}"),
            Integer(plugin, "rr_depth", 5, 1), Boolean(plugin, "hide_emitters", False),
            Boolean(plugin, "terminator_offset", True), Boolean(plugin, "footprint", True))


PARAMS = integrator_params("mfnormal_path", -1)


def mis_weight(pdf_a, pdf_b):
    """The power heuristic (exponent 2) of technique a against b, 0 where not finite, detached."""
    a, b = pdf_a * pdf_a, pdf_b * pdf_b
    w = a / (a + b)
    return dr.detach(dr.select(dr.isfinite(w), w, 0.0))


def _eval_pdf_sample(bsdf, ctx, si, wo, sample1, sample2):
    """The BSDF's ``eval_pdf_sample`` through ``dr.dispatch``: a Python BSDF's own method."""
    return dr.dispatch(bsdf, lambda inst, *args: inst.eval_pdf_sample(*args), ctx, si, wo, sample1, sample2)


class MfnormalPath:
    """The integrator's methods; :func:`integrator_class` binds them to the variant's
    ``mi.SamplingIntegrator``."""

    def __init__(self, props: mi.Properties):
        values = tuple(p.read(props) for p in PARAMS)
        type(self).__mro__[1].__init__(self, props)   # the variant's mi.SamplingIntegrator
        max_depth, self.rr_depth, self.hide_emitters, self.terminator_offset, self.footprint = values
        self.max_depth = 0xFFFFFFFF if max_depth == -1 else max_depth    # path's uint32 cast of -1
        if mi.is_polarized:
            raise ValueError("mfnormal_path: polarised variants are not supported (use 'path')")

    def sample(self, scene, sampler, ray, medium=None, active=True):
        if self.max_depth == 0:
            return mi.Spectrum(0.0), mi.Bool(False), []
        footprint = cone.camera_cone(ray) if self.footprint else ()   # path's rays: scaled by 1/√spp
        ray = mi.Ray3f(ray)
        active = mi.Bool(active)
        valid_ray = mi.Bool((not self.hide_emitters) and scene.environment() is not None)
        pi = scene.ray_intersect_preliminary(ray, True, False, 0, 0, active)
        if self.hide_emitters:
            skip = pi.is_valid() & (pi.shape.emitter() != None) & active  # noqa: E711  (a Dr.Jit mask)
            si = pi.compute_surface_interaction(ray, mi.RayFlags.Minimal, skip)
            pi[skip] = self.skip_area_emitters(scene, si.spawn_ray(ray.d), True, skip)
        state = (ray, pi, mi.Spectrum(1.0), mi.Spectrum(0.0), mi.Float(1.0), mi.UInt32(0), valid_ray,
                 dr.zeros(mi.Interaction3f), mi.Float(1.0), mi.Bool(True), active, sampler) + footprint
        offset = self.terminator_offset and terminator.applies(scene)
        out = dr.while_loop(state, lambda *s: s[10], lambda *s: self._vertex(scene, offset, *s),
                            label="mfnormal_path")
        result, valid_ray = out[3], out[6]
        return dr.select(valid_ray, result, 0.0), valid_ray, []

    def _vertex(self, scene, offset, ray, pi, throughput, result, eta, depth, valid_ray, prev_si, prev_pdf,
                prev_delta, active, sampler, *footprint):
        """One iteration of the path loop: emission hit, NEE, BSDF sample, Russian roulette
        (``offset``: rays start on the smooth surface, :mod:`mfnormal.plugins.terminator`;
        ``footprint``: the ray cone (w, beta), :mod:`mfnormal.plugins.cone`)."""
        si = pi.compute_surface_interaction(ray, cone.RAY_FLAGS if footprint else mi.RayFlags.All)
        if footprint:
            si, w = cone.at_hit(si, ray, *footprint)
        result = self._emission(scene, si, prev_si, prev_pdf, prev_delta, throughput, result)
        active_next = (depth + 1 < self.max_depth) & si.is_valid()
        bsdf = si.bsdf(mi.RayDifferential3f(ray))
        active_em = active_next & mi.has_flag(bsdf.flags(), mi.BSDFFlags.Smooth)
        if offset:
            shift = terminator.smooth_shift(si, pi.prim_uv)
            ds, em_weight = terminator.sample_emitter(scene, si, shift, sampler.next_2d(), active_em)
        else:
            ds, em_weight = scene.sample_emitter_direction(si, sampler.next_2d(), True, active_em)
        active_em &= ds.pdf != 0.0
        wo = si.to_local(ds.d)
        sample1 = sampler.next_1d()
        sample2 = sampler.next_2d()
        value, pdf, bs, weight = _eval_pdf_sample(bsdf, mi.BSDFContext(), si, wo, sample1, sample2)
        mis_em = dr.select(ds.delta, 1.0, mis_weight(ds.pdf, pdf))
        result[active_em] = dr.fma(throughput, value * em_weight * mis_em, result)
        origin = si
        if offset:
            origin = terminator.moved(si, terminator.outward(si, shift, si.to_world(bs.wo)))
        ray = origin.spawn_ray(si.to_world(bs.wo))
        if dr.grad_enabled(ray):
            raise NotImplementedError("mfnormal_path renders primal images only: use 'prb' for "
                                      "derivatives ('mfnormal_prb' for the random-walk models)")
        if footprint:
            footprint = (w, cone.bounce(footprint[1], si, bs))
        throughput = throughput * weight
        eta = eta * bs.eta
        valid_ray |= active & si.is_valid() & ~mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
        prev_si = mi.Interaction3f(origin)
        prev_pdf = bs.pdf
        prev_delta = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        depth[si.is_valid()] += 1
        throughput_max = dr.max(mi.unpolarized_spectrum(throughput))
        rr_prob = dr.minimum(throughput_max * (eta * eta), RR_PROB_MAX)
        rr_active = depth >= self.rr_depth
        rr_continue = sampler.next_1d() < rr_prob
        throughput[rr_active] *= dr.rcp(dr.detach(rr_prob))
        active = active_next & (~rr_active | rr_continue) & (throughput_max != 0.0)
        pi = scene.ray_intersect_preliminary(ray, False, dr.flag(dr.JitFlag.SymbolicLoops), 0, 0, active)
        return (ray, pi, throughput, result, eta, depth, valid_ray, prev_si, prev_pdf, prev_delta, active,
                sampler, *footprint)

    def _emission(self, scene, si, prev_si, prev_pdf, prev_delta, throughput, result):
        """``result`` plus the emission of the surface or environment the ray hit, MIS-weighted
        against the emitter sample of the previous vertex."""
        ds = mi.DirectionSample3f(scene, si, prev_si)
        em_pdf = scene.pdf_emitter_direction(prev_si, ds, ~prev_delta)
        mis_bsdf = mis_weight(prev_pdf, em_pdf)
        return dr.fma(throughput, ds.emitter.eval(si, prev_pdf > 0.0) * mis_bsdf, result)

    def aov_names(self):
        return []

    def to_string(self):
        return (f"MfnormalPath[max_depth={self.max_depth}, rr_depth={self.rr_depth}, "
                f"terminator_offset={self.terminator_offset}, footprint={self.footprint}]")


def integrator_class() -> type:
    """``MfnormalPath`` as a subclass of the active variant's ``mi.SamplingIntegrator``."""
    return variant_subclass(MfnormalPath, mi.SamplingIntegrator)
