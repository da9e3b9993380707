"""The default model's lobes (docs/faithful.md §1, §4, §7), each a small class with its value and
density in radiance mode and its branch of the light-tracing sampler (:mod:`.adjoint`):

- :class:`Direct`: the facet lit directly past the neighbours, S(ω_o|ω_i)·f_p(ω_i, ω_o);
- :class:`Skim`, :class:`Retro`: the glossy light the neighbours block, bounced toward ω_o: on
  past them, or back the way it came (Texel.bounce);
- :class:`Fill`: the diffuse light the neighbours block, a cosine lobe about ω_g;
- :class:`Hidden`: the neighbours, where the texel is hidden, f_g(ω_i, ω_o);
- with a transmitting nested BSDF, :class:`~.transmission.Fold` and
  :class:`~.transmission.Sink` (:mod:`.transmission`).

A lobe's adjoint answers for each of its branches (:class:`Branch`: probability, frame, incident
direction) its density at b, its draw, whether a draw counts, and a delta draw's coefficient.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import drjit as dr
import mitsuba as mi

from mfnormal.models.faithful.nested import RADIANCE, Side, gate, macro_frame, select_sample, sided
from mfnormal.surface.microsurface import negate, score
from mfnormal.models.rng import SALT_FAITHFUL_SAMPLE, SLOT_FAITHFUL_WALL, hash_floats, uniform
from mfnormal.models.neighbourhood import INV_PI

# ⟨ω_h, ω_p⟩ of the near-horizon direction at which the diffuse fill reads the facet's lobe.
HORIZON_MU = 0.2
# The share of the blocked light's samples that the sampler gives the diffuse fill, for nested
# BSDFs with diffuse and glossy parts: the fill's albedo ρ_fill clipped to these bounds (the
# floor keeps the fill's lobe sampled where the bounced samples miss it; how: docs/faithful.md §8).
FILL_SHARE_MIN, FILL_SHARE_MAX = 0.05, 0.5

# The light-tracing sampler's branch probabilities (docs/faithful.md §8; with transmission's, in
# :mod:`.transmission`): any values keep its pdf exact (the mixture's); they sum to at most 0.95, so
# the radiance sampler from a keeps 5 % or more.
FILL_BRANCH_P = 0.05         # the fill's cosine lobe in b, which no other branch draws; it is small (B·ρ_fill)
BOUNCE_BRANCH_SCALE = 0.1    # per preimage d of a: this times V·(1 − S(d)), the share of light blocked toward d
BOUNCE_BRANCH_MIN = 0.025    # ... at least this on the facet where S(d) < 1: a small blocked share still gets samples
HIDDEN_BRANCH_SCALE = 0.3    # the hidden texel's neighbours: this times 1 − V at the flat lobe's centre
HIDDEN_BRANCH_MIN = 0.05     # ... at least this: a b away from that centre may still hide the texel


@dataclass
class Query:
    """One radiance-mode query of the texel's lobes (:meth:`Model.eval_pdf`): camera side ``wi``,
    light side ``wo`` (base frame), what the lobes share, and, with transmission, ``down``: where
    ω_o is on the far side of the macro surface from the camera."""

    sp: object
    tx: object
    wi: object
    wo: object
    pre: object                # tx.preimages(ω_o) in the camera's frame
    s_o: object                # S(ω_o|ω_i)
    on_texel: object
    si_p: object               # the facet's interaction for ω_i
    want_value: bool
    want_pdf: bool
    down: object               # None without transmission
    gated: bool                # whether a packet may skip terms no lane needs (nested.gate)


class Branch(NamedTuple):
    """One branch of the light-tracing sampler: its probability, its lobe, and the frame and
    incident direction (base frame) of its nested sample."""

    p: object
    lobe: object
    frame: object
    inc: object


class Lobe:
    """What every lobe offers the light-tracing sampler; by default no branch of its own."""

    #: Whether its branch draws the nested BSDF on the macro surface, as the radiance sampler's
    #: hidden branch does: a delta path from either has their summed probability.
    flat = False

    def __init__(self, parts):
        self.parts = parts                   # the nested BSDF's components (nested.Components)

    def branches(self, tx_a, texel_for):
        """This lobe's branches of the light-tracing sampler from ``tx_a.wi`` (``texel_for(b)``:
        the texel seen from b)."""
        return []

    def density(self, sp, tx_a, br, b, active):
        """The density at b of the branch ``br`` (where its samples count: :meth:`valid`)."""
        raise NotImplementedError

    def draw(self, sp, tx_a, br, on_k, s1, sample2, active, state):
        """``state`` = (bs, w, delta, ok) with the branch ``br``'s draw where ``on_k``: a nested sample."""
        bs, w, delta, ok = state
        bs_k, w_k = sp.sample(br.frame, br.inc, s1, sample2, active & on_k)
        bs = select_sample(on_k, bs_k, bs)
        w = dr.select(on_k, w_k, w)
        delta = dr.select(on_k, mi.has_flag(bs_k.sampled_type, mi.BSDFFlags.Delta), delta)
        valid_k = self.valid(bs_k, w_k, br.frame, br.inc, tx_a.wi_real)
        ok = dr.select(on_k, active & valid_k, ok)
        return bs, w, delta, ok

    def valid(self, bs, w, frame, inc, a):
        """Whether a nested sample of a branch counts (:meth:`density`'s region)."""
        ok = (bs.pdf > 0) & dr.any(w > 0)
        if not self.parts.transmission:
            return ok & (dr.dot(bs.wo, frame.n) > 0) & (bs.wo.z > 0)
        side = dr.dot(bs.wo, frame.n) * dr.dot(inc, frame.n)
        return self.valid_sides(ok, bs, side, a)

    def valid_sides(self, ok, bs, side, a):
        """:meth:`valid` with transmission (``side`` > 0: bs.wo on the incident side of the frame)."""
        return ok & (side > 0) & (a.z * bs.wo.z > 0)

    def delta(self, sp, tx_b, br, ratio, on_k):
        """eval*'s coefficient on a delta path drawn by ``br`` over that draw's probability
        (``ratio``: |⟨b,ω_g⟩|/|⟨a,ω_g⟩|); None: the branch draws no delta path of its own."""
        return None


# -- Reflection on the texel ------------------------------------------------------------------

class Direct(Lobe):
    """S(ω_o|ω_i)·f_p(ω_i, ω_o): the facet lit directly past the neighbours. Its adjoint is the
    radiance sampler's from a (:mod:`.adjoint`), so it has no branch of its own."""

    def eval_pdf(self, q):
        """(eval, pdf) of the facet lit directly, plus the light blocked toward the first preimage
        d = ω_o that skims on toward ω_o (:class:`Skim`'s term for it). Both read the facet's nested
        BSDF at ω_o: every lobe for the direct light and the pdfs, the glossy ones for the blocked
        light's value. One nested query gives what they share (for a nested BSDF without a diffuse
        lobe, all of it)."""
        sp, tx, s_o = q.sp, q.tx, q.s_o
        _, _, share = q.pre[0]
        full = mi.BSDFContext(RADIANCE)
        lit = q.on_texel & (s_o > 0)
        blocked = _preimage_blocked(q, 0, s_o)
        fused = _fused(self.parts, q.want_value)
        f, p = sided(sp, tx, full, sp.frame_p, q.wi, q.wo, (lit | blocked) if q.want_pdf or fused else lit,
                     q.want_value, q.want_pdf, q.si_p)
        weight = share * (1.0 - s_o)
        value = dr.select(lit, f, 0.0) * s_o
        pdf = dr.select(lit, p, 0.0) * s_o
        if self.parts.glossy and q.want_value:
            if not fused:
                glossy = mi.BSDFContext(RADIANCE, self.parts.glossy_mask)
                f, _ = sided(sp, tx, glossy, sp.frame_p, q.wi, q.wo, blocked, True, False, q.si_p)
            value = value + dr.select(blocked, f, 0.0) * weight
        if q.want_pdf:
            pdf = pdf + dr.select(blocked, p, 0.0) * weight
        return value, pdf


def _fused(parts, want_value):
    """Whether one nested query (every lobe) gives both a blocked preimage's glossy value and
    its pdf: a nested BSDF without a diffuse lobe, whose glossy part is all of it."""
    return want_value and parts.glossy and not parts.diffuse


def _preimage_blocked(q, k, s_d):
    """Where the light blocked toward the preimage ``k`` is bounced toward ω_o."""
    _, on_facet, share = q.pre[k]
    blocked = q.on_texel & on_facet & (s_d < 1.0) & (share > 0)
    if q.tx.sinks is not None:
        blocked &= negate(q.tx.sinks)
    return blocked


def _bounced(parts, q, k, s_d, acc):
    """``acc`` plus the light the neighbours block toward the preimage ``k`` of ω_o
    (:meth:`Texel.preimages`; S(d) = ``s_d``), bounced toward ω_o: the glossy part in eval, every
    lobe in the pdf."""
    f_b, p_b = acc
    sp, tx, wi = q.sp, q.tx, q.wi
    full, glossy = mi.BSDFContext(RADIANCE), mi.BSDFContext(RADIANCE, parts.glossy_mask)
    d, _, share = q.pre[k]
    blocked = _preimage_blocked(q, k, s_d)
    d = tx.to_camera(d)
    weight = share * (1.0 - s_d)
    if _fused(parts, q.want_value):
        f, p = sided(sp, tx, full, sp.frame_p, wi, d, blocked, True, q.want_pdf, q.si_p)
        f_b = f_b + f * weight
        if q.want_pdf:
            p_b = p_b + p * weight
        return f_b, p_b
    if parts.glossy and q.want_value:
        f, _ = sided(sp, tx, glossy, sp.frame_p, wi, d, blocked, True, False, q.si_p)
        f_b = f_b + f * weight
    if q.want_pdf:
        _, p = sided(sp, tx, full, sp.frame_p, wi, d, blocked, False, True, q.si_p)
        p_b = p_b + p * weight
    return f_b, p_b


class Skim(Lobe):
    """Blocked glossy light that skims on past the neighbours (d kept, folded above the macro
    plane), share 1 − w(ω_i) of it: preimages d = ω_o and its mirror image below the macro plane."""

    #: Its preimages in :meth:`Texel.preimages`.
    PREIMAGES = (0, 1)

    def share(self, w):
        """The share of blocked light that takes this lobe's map, given w(ω_i) (Texel.retro_share)."""
        return 1.0 - w

    def eval_pdf(self, q, acc):
        """``acc`` plus the light blocked toward ω_o's mirror image below the macro plane (the
        first preimage, ω_o, is :class:`Direct`'s: it shares its nested query)."""
        # (A preimage below the macro plane is never seen past the neighbours: S = 0.)
        return _bounced(self.parts, q, 1, mi.Float(0.0), acc)

    def branches(self, tx_a, texel_for):
        """b sampled on the facet from each of this lobe's preimages d of a, in proportion to the
        light blocked toward d."""
        if not self.parts.glossy:
            return []
        out, pre = [], tx_a.preimages(tx_a.wi)
        for k in self.PREIMAGES:
            d, on_facet, _ = pre[k]
            s_d = tx_a.seen(d)
            p = dr.select(on_facet & (s_d < 1.0),
                          dr.maximum(BOUNCE_BRANCH_SCALE * tx_a.vis * (1.0 - s_d), BOUNCE_BRANCH_MIN), 0.0)
            out.append(Branch(p, self, tx_a.sp.frame_p, tx_a.to_camera(d)))
        return out

    def density(self, sp, tx_a, br, b, active):
        a = tx_a.wi_real
        if self.parts.transmission:
            active = active & (a.z * b.z > 0)
        return sided(sp, tx_a, mi.BSDFContext(RADIANCE), br.frame, br.inc, b, active, False, True,
                     side=Side.REFLECT)[1]

    def delta(self, sp, tx_b, br, ratio, on_k):
        share = self.share(tx_b.retro_share())
        c_k = tx_b.vis * share * (1.0 - tx_b.seen(tx_b.to_camera(br.inc))) * ratio / dr.maximum(br.p, 1e-30)
        if tx_b.sinks is not None:
            c_k = dr.select(tx_b.sinks, 0.0, c_k)
        return c_k


class Retro(Skim):
    """Blocked glossy light that comes back the way it came (d mirrored about ω_p: a cavity's
    retro-reflection), share w(ω_i) of it: preimages the mirror images of ω_o and of its mirror
    image below the macro plane."""

    PREIMAGES = (2, 3)

    def share(self, w):
        return w

    def eval_pdf(self, q, acc):
        """``acc`` plus the light blocked toward this lobe's preimages, bounced toward ω_o."""
        for k in self.PREIMAGES:
            acc = _bounced(self.parts, q, k, q.tx.seen(q.pre[k][0]), acc)
        return acc


# -- The diffuse fill and the hidden texel ----------------------------------------------------

class Fill(Lobe):
    """The diffuse light the neighbours block, B(ω_i)·ρ_fill(ω_i)·⟨ω_o,ω_g⟩/π: re-emitted as a
    cosine lobe about ω_g. Its adjoint is a cosine lobe in b."""

    def energy(self, sp, tx):
        """The fill's energy B(ω_i)·ρ_fill(ω_i): the blocked diffuse light from ω_i (:meth:`rho`)."""
        if not self.parts.diffuse:
            return mi.Spectrum(0.0)
        rho = self.rho(sp, tx)
        return tx.blocked * rho * dr.minimum(rho, 1.0)

    def rho(self, sp, tx):
        """ρ_b(ω_i): the fill returns ρ_fill = ρ_b·min(ρ_b, 1) of the blocked diffuse light, what
        comes back after one bounce on a neighbour of the same material. B is a Lambertian facet's
        blocked share; ρ_b = π·min(f_d(ω_i, ω_p), f_d(ω_i, ω_h)/⟨ω_h,ω_p⟩) of the diffuse
        components, ω_h near the facet's horizon down-slope, where blocked light leaves: exact
        for Lambertian lobes, and below the blocked energy of lobes that fall off toward grazing
        (Fresnel-weighted ones, whose energy would otherwise exceed the nested albedo by ~1.5 %
        at 20°). White facets keep all of it (the white furnace is exact); darker ones lose what
        the neighbour absorbs, as the true geometry does.

        Computed once per texel (eval, pdf and the sampler's branch probabilities share it),
        masked independently of ω_o and of the caller's mask."""
        if tx.fill_rho is None:
            ctx = mi.BSDFContext(RADIANCE, self.parts.diffuse_mask)
            active = (tx.wi.z > 0) & (tx.vis > 0)
            wp = tx.wp
            down = wp.z * wp - mi.Vector3f(0.0, 0.0, 1.0)                 # −(ω_g − cosθ_p ω_p)
            n2 = dr.squared_norm(down)
            down = dr.select(n2 > 1e-12, down * dr.rsqrt(dr.maximum(n2, 1e-30)), sp.frame_p.s)
            w_h = HORIZON_MU * wp + math.sqrt(1.0 - HORIZON_MU ** 2) * down
            wi = tx.wi_real
            f_n, _ = sided(sp, tx, ctx, sp.frame_p, wi, tx.to_camera(wp), active, want_pdf=False)
            f_h, _ = sided(sp, tx, ctx, sp.frame_p, wi, tx.to_camera(w_h), active, want_pdf=False)
            tx.fill_rho = math.pi * dr.minimum(f_n, f_h / HORIZON_MU)
        return tx.fill_rho

    def probability(self, tx, fill_share):
        """The radiance sampler's probability of the fill's cosine lobe."""
        if self.parts.diffuse and self.parts.glossy:
            # The blocked light's samples, split between the fill and the texel's nested sample
            # (bounced when blocked) by the fill's share of it, ρ_fill (mean over the channels),
            # within fill_share, [FILL_SHARE_MIN, FILL_SHARE_MAX] by default.
            rho = self.rho(tx.sp, tx)
            share = dr.clip(dr.mean(rho * dr.minimum(rho, 1.0)), *fill_share)
            return tx.vis * tx.blocked * share
        if self.parts.diffuse:
            return tx.vis * tx.blocked
        return mi.Float(0.0)

    def branches(self, tx_a, texel_for):
        return [Branch(mi.Float(FILL_BRANCH_P), self, None, None)]

    def density(self, sp, tx_a, br, b, active):
        return (dr.maximum(tx_a.to_camera(b).z, 0.0) if self.parts.transmission else b.z) * INV_PI

    def draw(self, sp, tx_a, br, on_k, s1, sample2, active, state):
        """``state`` with a cosine-distributed b where ``on_k`` (never a delta path)."""
        bs, w, delta, ok = state
        bs.wo = dr.select(on_k, tx_a.to_camera(mi.warp.square_to_cosine_hemisphere(sample2)), bs.wo)
        delta &= negate(on_k)
        ok = dr.select(on_k, active, ok)
        return bs, w, delta, ok


class Hidden(Lobe):
    """(1 − V(ω_i))·f_g(ω_i, ω_o): the neighbours, where the texel is hidden (the nested BSDF on the
    macro surface, reflection and transmission). On a map whose slopes do not average to zero, the
    share ψ_w of them that are its walls (``tx.wall_share``) turns the light around: an upright wall
    mirrors it across its plane (M_wall, ``tx.wall_mirror``) before or after the macro surface's lobe,
    so ω_o gets (1 − ψ_w)·f_g(ω_i, ω_o) + ψ_w·f_g(ω_i, M_wall(ω_o)). M_wall keeps z: energy exact, and it
    commutes with f_g's reflection and refraction, so the radiance sampler's flipped samples are the
    adjoint's too (docs/faithful.md §7)."""

    flat = True

    def eval_pdf(self, q, active):
        """(f_g, its pdf), the walls' share mirrored; each part skipped by packets in which no lane
        sees past the texel or needs it (``q.gated``: the walls' by every packet of a map without)."""
        return self.mixture(q.sp, q.tx, q.wi, q.wo, active & (q.tx.vis < 1.0), q.want_value, q.want_pdf, q.gated)

    def mixture(self, sp, tx, inc, out, on, want_value, want_pdf, gated):
        """(1 − ψ_w)·f_g(inc, out) + ψ_w·f_g(inc, M_wall(out)) and its pdf, where ``on`` (base frame)."""
        full, share = mi.BSDFContext(RADIANCE), tx.wall_share
        zero = (mi.Spectrum(0.0), mi.Float(0.0))
        acc = []
        parts = ((out, on & (share < 1.0), 1.0 - share), (tx.wall_mirror(out), on & (share > 0.0), share))
        for d, on_d, weight in parts:
            f, p = gate(on_d, lambda d=d, on_d=on_d: sided(sp, tx, full, macro_frame(), inc, d, on_d, want_value,
                                                          want_pdf, side=Side.EITHER), zero, gated)
            acc.append((f * weight, p * weight))
        return acc[0][0] + acc[1][0], acc[0][1] + acc[1][1]

    def branches(self, tx_a, texel_for):
        """b sampled on ω_g from a, in proportion to the hidden share at the flat lobe's centre."""
        if not (self.parts.glossy or self.parts.transmission):
            return []
        a_real = tx_a.wi_real
        vis_c = texel_for(mi.Vector3f(-a_real.x, -a_real.y, a_real.z)).vis      # at the flat lobe's centre
        p = dr.maximum(HIDDEN_BRANCH_SCALE * (1.0 - vis_c), HIDDEN_BRANCH_MIN)
        return [Branch(p, self, macro_frame(), a_real)]

    def density(self, sp, tx_a, br, b, active):
        return self.mixture(sp, tx_a, br.inc, b, active, False, True, False)[1]

    def draw(self, sp, tx_a, br, on_k, s1, sample2, active, state):
        """:meth:`Lobe.draw`, its sample mirrored by the walls with probability ψ_w (:func:`wall_turn`)."""
        bs, w, delta, ok = super().draw(sp, tx_a, br, on_k, s1, sample2, active, state)
        bs.wo, w = wall_turn(tx_a, bs.wo, w, hash_floats(SALT_FAITHFUL_SAMPLE, s1, sample2.x, sample2.y), on_k)
        return bs, w, delta, ok

    def valid_sides(self, ok, bs, side, a):
        return ok & (bs.wo.z != 0)


def wall_turn(tx, wo, w, seed, on):
    """(ω_o, weight) of a sample on the hidden texel's neighbours, where ``on``: mirrored by the walls
    (M_wall) with probability ψ_w (``tx.wall_share``; decided with detached ψ_w, the weight times its
    score, so that its derivative accounts for ψ_w's)."""
    share = tx.wall_share
    walled = on & (uniform(seed, SLOT_FAITHFUL_WALL) < dr.detach(share))
    w_on = w * score(dr.select(walled, share, 1.0 - share))
    return dr.select(walled, tx.wall_mirror(wo), wo), dr.select(on, w_on, w)
