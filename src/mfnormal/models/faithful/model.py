"""The default model at one shading point: eval, pdf and the radiance-mode sampler over its
lobes (:mod:`.lobes`, :mod:`.transmission`), with the adjoint for light tracing (:mod:`.adjoint`)."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mfnormal.models.faithful.adjoint import eval_pdf as adjoint_eval_pdf
from mfnormal.models.faithful.adjoint import sample as adjoint_sample
from mfnormal.models.faithful.lobes import (FILL_SHARE_MAX, FILL_SHARE_MIN, Direct, Fill, Hidden, Query, Retro, Skim,
                                            wall_turn)
from mfnormal.models.faithful.nested import Components, crossing_eta, finish, gate, macro_frame, select_frame
from mfnormal.models.faithful.tables import MapStatistics
from mfnormal.models.faithful.texel import Texel
from mfnormal.models.faithful.transmission import Fold, Sink
from mfnormal.surface.microsurface import negate, score
from mfnormal.models.neighbourhood import INV_PI
from mfnormal.models.rng import (ONE_MINUS_EPS, SALT_FAITHFUL_SAMPLE, SLOT_FAITHFUL_BLOCKED, SLOT_FAITHFUL_RETRO,
                                 hash_floats, uniform)


class Model(MapStatistics):
    """The faithful model for one plugin instance: its lobes, the map's σ and the Lambertian table."""

    def __init__(self, nested, slopes, cos_min: float, fill_share=(FILL_SHARE_MIN, FILL_SHARE_MAX), local=None,
                 wall=None):
        self.components = parts = Components(nested)
        self.direct, self.skim, self.retro, self.fill = Direct(parts), Skim(parts), Retro(parts), Fill(parts)
        self.hidden, self.fold, self.sink = Hidden(parts), Fold(parts), Sink(parts)
        # The light the neighbours block that is bounced (the rarely needed preimages: one gate).
        self.bounced_lobes = (self.skim, self.retro)
        # The light that crosses the macro surface, with a transmitting nested BSDF.
        self.crossing_lobes = (self.fold, self.sink) if parts.transmission else ()
        # The light-tracing sampler's branches, in the order of its intervals (adjoint.py).
        self.adjoint_lobes = (self.fill, self.skim, self.retro, self.hidden, self.fold, self.sink)
        self.fill_share = fill_share
        self.cos_min = cos_min
        self.set_slopes(slopes, local=local, wall=wall)

    def texel(self, sp, wi):
        """The texel at ``sp`` seen from ``wi`` (base frame)."""
        return Texel(sp, self, wi)

    def _branches(self, tx):
        """The sampler's branch probabilities: the texel (a nested sample, bounced if blocked),
        the diffuse fill, the hidden texel's neighbours."""
        p_fill = self.fill.probability(tx, self.fill_share)
        return tx.vis - p_fill, p_fill, 1.0 - tx.vis

    def eval_pdf(self, sp, tx, wo, active, want_value=True, want_pdf=True, gated=None):
        """(eval, pdf) in radiance mode: camera side ``tx.wi``, light side ``wo``.

        ``gated``: terms that no lane of a SIMD packet needs (the retro-reflected and below-plane
        preimages, the sunk light, the hidden texel) are skipped (:func:`~.nested.gate`: the same
        values, bit for bit); None: wherever nothing the query reads carries derivatives
        (:meth:`_gates`). What the texel shares with the ``sample`` at the same path vertex (Λ(ω_i),
        V, B, the fill) is traced before the branches, so Dr.Jit's common-subexpression elimination
        still shares it (a branch opens a scope that shares nothing with the outside)."""
        if gated is None:
            gated = self._gates(sp, tx, wo)
        wi, wo_g = tx.wi, tx.to_camera(wo)
        trans = self.components.transmission
        # (With transmission ω_o lies on either side: its side decides which terms it gets.)
        either = active & (wi.z > 0) & (wo_g.z != 0) if trans else None
        active = active & (wi.z > 0) & (wo_g.z > 0)
        on_texel = active & (tx.vis > 0)
        value, pdf = mi.Spectrum(0.0), mi.Float(0.0)

        # The diffuse fill's lobe (before any branch, and masked independently of ω_o and of the
        # caller's mask, so that the eval_pdf and sample of one path vertex share it; the lanes
        # it adds are masked out below).
        fill = self.fill.energy(sp, tx) if want_value else None
        # Lit directly past the neighbours, and the light the neighbours block that skims on
        # toward ω_o (the first preimage, d = ω_o: one nested query serves both).
        s_o = tx.seen(wo_g)
        si_p = sp.facet_si(sp.frame_p, tx.wi_real)
        pre = tx.preimages(wo_g)
        down = either & (wo_g.z < 0) if trans else None
        q = Query(sp, tx, tx.wi_real, wo, pre, s_o, on_texel, si_p, want_value, want_pdf, down, gated)
        acc = self.direct.eval_pdf(q)
        # Light the neighbours block, bounced toward ω_o: the glossy part in eval (the diffuse
        # part is the fill), every lobe in the sampler's pdf. The retro-reflected pair (share
        # w > 0) and the preimage below the plane are skipped by packets that need neither (one
        # branch for the three: each branch's scope repeats the nested BSDF's own ω_i terms).
        rare = on_texel & ((pre[1][1] & (pre[1][2] > 0)) | (pre[2][2] > 0))
        value_t, pdf_t = gate(rare, lambda: _add(self.bounced_lobes, q, acc), acc, gated)
        value_t, pdf_t = _add(self.crossing_lobes, q, (value_t, pdf_t))
        if trans:
            active = either
        f_hid, p_hid = self.hidden.eval_pdf(q, active)
        cos_fill = dr.maximum(wo_g.z, 0.0) if trans else wo.z

        if want_value:
            value = tx.vis * (value_t + fill * (cos_fill * INV_PI)) + (1.0 - tx.vis) * f_hid
            value = dr.select(active & dr.all(dr.isfinite(value)), dr.maximum(value, 0.0), 0.0)
        if want_pdf:
            b_tex, b_fill, b_hid = self._branches(tx)
            pdf = b_tex * pdf_t + b_fill * (cos_fill * INV_PI) + b_hid * p_hid
            pdf = dr.select(active & dr.isfinite(pdf), dr.maximum(pdf, 0.0), 0.0)
        return value, pdf

    def draw(self, sp, tx, sample1, sample2, active):
        """One draw of the radiance-mode sampler from ``tx.wi``: the exit direction and its path."""
        wi, trans = tx.wi, self.components.transmission
        active = active & (wi.z > 0)
        b_tex, b_fill, b_hid = self._branches(tx)
        # The branch is chosen, and sample1 rescaled, with detached probabilities.
        c_tex, c_fill, c_hid = dr.detach(b_tex), dr.detach(b_fill), dr.detach(b_hid)
        on_tex = sample1 < c_tex
        on_fill = negate(on_tex) & (sample1 < c_tex + c_fill)
        on_hid = negate(on_tex | on_fill)
        lo = dr.select(on_tex, 0.0, dr.select(on_fill, c_tex, c_tex + c_fill))
        width = dr.select(on_tex, c_tex, dr.select(on_fill, c_fill, c_hid))
        s1 = dr.clip((sample1 - lo) / dr.maximum(width, 1e-30), 0.0, ONE_MINUS_EPS)

        # Nested sample on the facet (texel branch) or on the macro surface (hidden branch).
        frame = select_frame(on_tex, sp.frame_p, macro_frame())
        bs, w = sp.sample(frame, tx.wi_real, s1, sample2, active & (on_tex | on_hid))
        d = tx.to_camera(bs.wo)
        # Texel branch: the sample leaves past the neighbours, or is blocked and bounced.
        seed = hash_floats(SALT_FAITHFUL_SAMPLE, sample1, sample2.x, sample2.y)
        s_b = tx.seen(d)
        # (Decisions with detached probabilities; the draw's prob keeps them attached: score.)
        bounced = on_tex & (uniform(seed, SLOT_FAITHFUL_BLOCKED) >= dr.detach(s_b))
        w_retro = tx.retro_share()
        retro = uniform(seed, SLOT_FAITHFUL_RETRO) < dr.detach(w_retro)
        if trans:
            # Transmitted through the facet: leaves below the macro surface (transmission.Fold).
            through = on_tex & (dr.dot(d, tx.wp) < 0)
            bounced &= negate(through)
        wo = dr.select(bounced, tx.bounce(d, retro), d)
        if trans:
            # (Blocked reflected light seen from above sinks below the neighbours the same way: transmission.Sink.)
            sunk = bounced & tx.sinks
            wo = dr.select(through | sunk, mi.Vector3f(d.x, d.y, -dr.abs(d.z)), wo)
        # Hidden branch: the share of the neighbours that are walls turns the sample around (Hidden).
        wo, w = wall_turn(tx, wo, w, seed, on_hid)
        # Diffuse fill: a cosine lobe about ω_g.
        wo = dr.select(on_fill, mi.warp.square_to_cosine_hemisphere(sample2), wo)
        # A nested sample counts only if it is one: positive weight, on the upper side of its frame
        # (with transmission: on either side).
        side = dr.dot(bs.wo, frame.n)
        valid = (bs.pdf > 0) & dr.any(w > 0) & ((side != 0) if trans else (side > 0))
        ok = dr.select(on_fill, True, valid) & ((wo.z != 0) if trans else (wo.z > 0)) & dr.all(dr.isfinite(wo)) & \
            (width > 0)
        delta = negate(on_fill) & mi.has_flag(bs.sampled_type, mi.BSDFFlags.Delta)
        bs.sampled_type = dr.select(on_fill, mi.UInt32(+mi.BSDFFlags.DiffuseReflection), bs.sampled_type)
        bs.sampled_component = dr.select(on_fill, mi.UInt32(0), bs.sampled_component)
        bs.wo = tx.to_camera(wo)
        # The draw's probability factor for delta lobes (the nested pdf times this).
        share = dr.select(retro, w_retro, 1.0 - w_retro)
        p_exit = dr.select(bounced, (1.0 - s_b) * share, s_b)
        if trans:
            p_exit = dr.select(through, 1.0, dr.select(sunk, 1.0 - s_b, p_exit))
            # (Sunk light crosses the interface: its radiance scaling and η, as the eval's.)
            eta_s = crossing_eta(sp, sp.facet_si(sp.frame_p, tx.wi_real), active & sunk)
            w = dr.select(sunk, w * dr.rcp(dr.square(eta_s)), w)
            bs.eta = dr.select(on_fill, 1.0, dr.select(sunk, eta_s, bs.eta))
        prob = dr.select(on_tex, b_tex * p_exit, b_hid)
        return _Draw(bs, w, active & ok, delta, on_tex, bounced, prob, b_tex, b_hid, through if trans else None)


    def _derivatives(self, sp):
        """Whether anything this point's queries read carries derivatives (the normal, the
        map-wide slopes, the nested BSDF). Then no query gates its terms (:meth:`_gates`): a
        symbolic ``dr.if_stmt`` inside the BSDF's call lets Dr.Jit 1.5 differentiate the values
        it captures outside the call's scope, which fails under Mitsuba's ``path``
        (render_forward: "forward-propagate derivatives across edge ... outside of the current
        dr.isolate_grad() scope"; render_backward: invalid LLVM IR). The values are the same."""
        return sp.attached or self.d_tables is not None or sp.nested_attached()

    def _gates(self, sp, tx, *directions):
        """Whether a query may skip, per SIMD packet, the terms no lane needs (:func:`~.nested.gate`):
        where nothing it reads carries derivatives (:meth:`_derivatives`, ω_i and ``directions``:
        moving geometry or emitters)."""
        return not (self._derivatives(sp) or dr.grad_enabled(tx.wi, *directions))

    def sample(self, sp, tx, sample1, sample2, active):
        """Radiance-mode sample from ``tx.wi``: (BSDFSample3f in the base frame, weight).

        Derivatives: a smooth lobe's direction is detached, its weight eval(θ)/detach(pdf);
        a delta lobe's direction and weight are differentiable functions, times the score
        p/detach(p) of the branch it took (microsurface.score)."""
        dw = self.draw(sp, tx, sample1, sample2, active)
        bs, active = dw.bs, dw.active
        bs.wo = dr.select(dw.delta, bs.wo, dr.detach(bs.wo))
        value, pdf = self.eval_pdf(sp, tx, bs.wo, active & negate(dw.delta), gated=self._gates(sp, tx))
        # Delta lobes (non-diffuse, so bounced ones are the eval's too): the path weight, the
        # branch probabilities cancelling against the eval's factors.
        w_delta = dw.w * dr.select(dw.on_tex, tx.vis / dr.maximum(dw.b_tex, 1e-30),
                                   (1.0 - tx.vis) / dr.maximum(dw.b_hid, 1e-30))
        weight = dr.select(dw.delta, w_delta * score(dw.prob), value / dr.detach(dr.select(pdf > 0, pdf, 1.0)))
        bs.pdf = dr.select(dw.delta, bs.pdf * dw.prob, pdf)
        return finish(bs, weight, active)

    # -- Light tracing: the adjoint eval*(a, b) = eval(b, a)·⟨b, ω_g⟩/⟨a, ω_g⟩ (adjoint.py) ------

    def eval_pdf_adjoint(self, sp, tx_a, tx_b, active, texel_for, want_value=True, want_pdf=True):
        """(eval*, pdf*): light side ``tx_a.wi``, camera side ``tx_b.wi`` (:func:`.adjoint.eval_pdf`)."""
        return adjoint_eval_pdf(self, sp, tx_a, tx_b, active, texel_for, want_value, want_pdf)

    def sample_adjoint(self, sp, tx_a, sample1, sample2, active, texel_for):
        """Light-tracing sample from the light side ``tx_a.wi``; ``texel_for(b)`` builds the texel seen
        from b (:func:`.adjoint.sample`)."""
        return adjoint_sample(self, sp, tx_a, sample1, sample2, active, texel_for)


def _add(lobes, q, acc):
    """``acc`` plus each of ``lobes``' (value, pdf) for the query ``q``, in order."""
    for lobe in lobes:
        acc = lobe.eval_pdf(q, acc)
    return acc


class _Draw:
    """One draw of the radiance-mode sampler (:meth:`Model.draw`)."""

    def __init__(self, bs, w, active, delta, on_tex, bounced, prob, b_tex, b_hid, through=None):
        self.bs, self.w, self.active, self.delta = bs, w, active, delta
        self.on_tex, self.bounced, self.prob, self.b_tex, self.b_hid = on_tex, bounced, prob, b_tex, b_hid
        self.through = through          # transmitted through the facet (with transmission)
