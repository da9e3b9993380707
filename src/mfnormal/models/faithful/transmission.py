"""The default model's lobes for a nested BSDF that transmits (docs/faithful.md §7), as
:mod:`.lobes`: the light the facet transmits toward the far side of the macro surface from the
camera (:class:`Fold`), and the reflected light the neighbours block that sinks below them
(:class:`Sink`).
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mfnormal.models.faithful.lobes import Branch, Lobe
from mfnormal.models.faithful.nested import RADIANCE, Side, crossing_eta, gate, mirror_z, sided

# Their branches of the light-tracing sampler (see lobes.FILL_BRANCH_P).
FOLD_BRANCH_P = 0.1          # b refracted from F(a), where F(a) is on the facet's refracting side
SINK_BRANCH_P = 0.05         # each of the two sunk reflections (a below the surface): a dielectric reflects little


class _Across(Lobe):
    """A lobe of light that crosses the macro surface: its branches sample the facet, and count
    in a region of b that :meth:`region` gives."""

    def region(self, si_f, b_f, a, b):
        raise NotImplementedError

    def density(self, sp, tx_a, br, b, active):
        si_f = sp.facet_si(br.frame, br.inc)
        b_f = br.frame.to_local(b)
        on = active & self.region(si_f, b_f, tx_a.wi_real, b)
        return dr.select(on, sp.nested.pdf(mi.BSDFContext(RADIANCE), si_f, b_f, on), 0.0)


class Fold(_Across):
    """Light the facet transmits toward ω_o on the far side of the macro surface from the camera:
    straight from the facet, or folded there from its mirror image F(ω_o) (a refracted direction on
    the camera's side of the macro surface, the side classic normal mapping sends it to). The
    neighbours block transmitted light too; it leaves below them (M_T(d) = (d_x, d_y, −|d_z|) in
    the camera's frame, a piecewise isometry: energy exact), so blocked or not, d below the macro
    plane leaves as d, and S_T cancels: eval gets f_p^T(ω_i, ω_o) + f_p^T(ω_i, F(ω_o)), the pdf
    likewise (docs/faithful.md §7)."""

    def eval_pdf(self, q, acc):
        f_b, p_b = acc
        full = mi.BSDFContext(RADIANCE)
        on = q.down & (q.tx.vis > 0)
        for d in (q.wo, mirror_z(q.wo)):
            f, p = sided(q.sp, q.tx, full, q.sp.frame_p, q.wi, d, on, q.want_value, q.want_pdf, q.si_p,
                         Side.TRANSMIT)
            f_b, p_b = f_b + f, p_b + p
        return f_b, p_b

    def branches(self, tx_a, texel_for):
        """b refracted on the facet from F(a), where F(a) lies on the facet's side that a refracted
        camera ray would leave from: f_p(b, F(a)), which radiance sampling from a does not reach."""
        if not self.parts.transmission:
            return []
        on = dr.dot(mirror_z(tx_a.wi), tx_a.wp) > 0
        return [Branch(dr.select(on, FOLD_BRANCH_P, 0.0), self, tx_a.sp.frame_p, mirror_z(tx_a.wi_real))]

    def region(self, si_f, b_f, a, b):
        return (si_f.wi.z * b_f.z < 0) & (a.z * b.z < 0)

    def valid_sides(self, ok, bs, side, a):
        return ok & (side < 0) & (a.z * bs.wo.z < 0)

    def delta(self, sp, tx_b, br, ratio, on_k):
        b = tx_b.wi_real
        return tx_b.vis * ratio * dr.abs(dr.dot(br.inc, sp.wp)) / dr.maximum(dr.abs(dr.dot(b, sp.wp)) * br.p, 1e-30)


class Sink(_Across):
    """Seen from above (``tx.sinks``), the reflected light the neighbours block meets their
    interface and sinks below it by the same map M_T as :class:`Fold`'s: a reflected d leaves past
    the neighbours with S(d|ω_i) (0 below the macro plane), else below them, so ω_o below the surface
    also gets the facet's glossy reflection f_p^R(ω_i, ω_o) and f_p^R(ω_i, F(ω_o)), each times 1 − S
    (every lobe in the pdf), with the radiance scaling 1/η² of light that crosses the interface
    (:func:`~.nested.crossing_eta`); the diffuse part's blocked light stays the fill's."""

    def eval_pdf(self, q, acc):
        """``acc`` plus the sunk light toward ω_o (skipped by packets with no such lane, ``q.gated``)."""
        f_b, p_b = acc
        tx = q.tx
        full, glossy = mi.BSDFContext(RADIANCE), mi.BSDFContext(RADIANCE, self.parts.glossy_mask)
        on = q.down & (tx.vis > 0)
        pre = [(d, tx.seen(tx.to_camera(d))) for d in (q.wo, mirror_z(q.wo))]
        sunk = [on & tx.sinks & (s_d < 1.0) for _, s_d in pre]

        def sinking():
            f_s, p_s = f_b, p_b
            if q.want_value and self.parts.glossy:
                scale = dr.rcp(dr.square(crossing_eta(q.sp, q.si_p, sunk[0] | sunk[1])))
            for (d, s_d), on_d in zip(pre, sunk):
                if q.want_value and self.parts.glossy:
                    f, _ = sided(q.sp, tx, glossy, q.sp.frame_p, q.wi, d, on_d, True, False, q.si_p, Side.REFLECT)
                    f_s = f_s + f * ((1.0 - s_d) * scale)
                if q.want_pdf:
                    _, p = sided(q.sp, tx, full, q.sp.frame_p, q.wi, d, on_d, False, True, q.si_p, Side.REFLECT)
                    p_s = p_s + p * (1.0 - s_d)
            return f_s, p_s
        return gate(sunk[0] | sunk[1], sinking, (f_b, p_b), q.gated)

    def branches(self, tx_a, texel_for):
        """For a below the macro plane, b reflected on the facet from a and from F(a)."""
        if not self.parts.transmission:
            return []
        a_real, sp = tx_a.wi_real, tx_a.sp
        out = []
        for inc in (a_real, mirror_z(a_real)):
            on = (a_real.z < 0) & (dr.dot(inc, sp.wp) > 0)
            out.append(Branch(dr.select(on, SINK_BRANCH_P, 0.0), self, sp.frame_p, inc))
        return out

    def region(self, si_f, b_f, a, b):
        return (si_f.wi.z > 0) & (b_f.z > 0) & (a.z < 0) & (b.z > 0)

    def valid_sides(self, ok, bs, side, a):
        return ok & (side > 0) & (a.z < 0) & (bs.wo.z > 0)

    def delta(self, sp, tx_b, br, ratio, on_k):
        eta_b = crossing_eta(sp, sp.facet_si(sp.frame_p, tx_b.wi_real), on_k)
        return tx_b.vis * (1.0 - tx_b.seen(tx_b.to_camera(br.inc))) * ratio / dr.maximum(
            br.p * dr.square(eta_b), 1e-30)
