"""The default model: the tilted facet as the true geometry around it shows it (docs/faithful.md).

A texel of a normal map baked from a heightfield is a small piece of surface with
normal ω_p among neighbours whose slopes average to zero. Seen from the camera
direction ω_i (``si.wi``) and lit from ω_o, it shows

    eval(ω_i, ω_o) = V(ω_i)·[ f_p(ω_i, ω_o)·S(ω_o|ω_i)                       lit directly
                             + f_p^gl(ω_i, T⁻¹ω_o)·(1 − S(T⁻¹ω_o|ω_i))     glossy light the neighbours block
                             + B(ω_i)·ρ_d(ω_i)·⟨ω_o, ω_g⟩/π ]              diffuse light the neighbours block
                   + (1 − V(ω_i))·f_g(ω_i, ω_o)                             the neighbours, where the texel is hidden

- f_p, f_g: the nested f·cos on the facet (frame ω_p) and on the macro surface
  (frame ω_g); f_p^gl its non-diffuse components, ρ_d its diffuse albedo;
- V(ω) = min(1, R(ω)·G1(ω)): the share of the texel's footprint in which a ray from ω
  hits the texel, R(ω) = ⟨ω,ω_p⟩₊ / (cosθ_p⟨ω,ω_g⟩) its projected area and G1 Smith's
  masking by neighbours whose slopes have the map's own rms slope σ (Beckmann);
- S(ω|ω_i) = χ⁺(⟨ω,ω_p⟩)χ⁺(⟨ω,ω_g⟩)·(1 + Λ(ω_i)) / (1 + Λ(ω_i) + Λ(ω)): the chance that a
  visible point of the texel sees ω past its neighbours (height-correlated Smith);
- light the neighbours block is not lost: its glossy part leaves in the direction it
  would have had on the macro surface (T rotates ω_p onto ω_g: energy exact, one nested
  call), its diffuse part as a cosine lobe weighted by B(ω_i), the blocked share of a
  Lambertian facet's light (a table, exact for Lambertian facets).

So the white furnace is exactly the nested albedo (1 for white facets), energy never
exceeds it, nothing turns black, and the texel keeps classic normal mapping's relief
under directional light (the ⟨ω_o, ω_p⟩ of f_p). The model is **not reciprocal** in
the macro frame: a reciprocal BSDF that is white in the white furnace has the same
view-averaged response to every light direction for every texel, i.e. no relief
(docs/faithful.md). Light tracing sees the adjoint (``TransportMode.Importance``):
eval*(a, b) = eval(b, a)·⟨b, ω_g⟩ / ⟨a, ω_g⟩, so path tracing and light tracing agree.

A nested BSDF that transmits is normal-mapped on both sides (docs/faithful.md §7): the facet's
transmitted light leaves on the far side of the macro surface (folded there from the camera's
side), and a camera below the surface sees the mirrored heightfield (:class:`Texel`).

The neighbourhood (the map's slopes, Smith masking by them, the blocked-light table) is
:mod:`mfnormal.models.neighbourhood`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from mfnormal.models.microsurface import negate, replace_grad, score
from mfnormal.models.neighbourhood import (INV_PI, _held, blocked_table, field_lookup, kernel_array, local_scales,
                                           lookup, smith_lambda)
from mfnormal.models.rng import (ONE_MINUS_EPS, SALT_FAITHFUL_SAMPLE, SLOT_FAITHFUL_BLOCKED, SLOT_FAITHFUL_RETRO,
                                 hash_floats, uniform)
from mfnormal.models.shading import from_tangent_rotation, to_tangent_frame


# -- The model at one shading point ------------------------------------------------------------

def macro_frame():
    return mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))


GLOSSY_MASK = mi.BSDFFlags.All & ~mi.BSDFFlags.DiffuseReflection


class Lobes:
    """Which nested components exist, decided once per plugin (Python bools, baked into kernels).

    The diffuse components' blocked light goes to the fill, the others' is bounced; that
    needs a nested BSDF that honours ``BSDFContext.type_mask`` (Mitsuba's ``principled`` does
    not: it returns its whole value under either mask). One that does not is treated as all
    diffuse: all its blocked light goes to the fill (bounced as a mirror, the diffuse part of
    such a material would light the slopes facing away from the sun like a mirror would:
    measured on the ribs of Khronos' ClearCoatTest, relMSE to their geometry 0.017 against 0.0016
    filled).
    """

    def __init__(self, nested):
        flags = nested.flags()
        diffuse = mi.has_flag(flags, mi.BSDFFlags.DiffuseReflection)
        glossy = mi.has_flag(flags, mi.BSDFFlags.GlossyReflection) or \
            mi.has_flag(flags, mi.BSDFFlags.DeltaReflection)
        self.diffuse_mask, self.glossy_mask = +mi.BSDFFlags.DiffuseReflection, GLOSSY_MASK
        if diffuse and glossy and not _honours_type_mask(nested):
            glossy = False
            self.diffuse_mask = +mi.BSDFFlags.All
        self.diffuse, self.glossy = diffuse, glossy
        # A transmitting nested BSDF: both hemispheres (Texel's mirrored frame, Model._transmitted).
        self.transmission = mi.has_flag(flags, mi.BSDFFlags.Transmission)


def _honours_type_mask(nested) -> bool:
    """Whether eval(diffuse only) + eval(the rest) = eval(all) at a few fixed queries."""
    pairs = [((0.3, 0.2, 0.93), (-0.5, 0.1, 0.86)), ((0.0, 0.0, 1.0), (0.6, -0.3, 0.74)),
             ((0.8, 0.1, 0.59), (-0.2, -0.6, 0.77)), ((-0.1, 0.7, 0.7), (0.1, 0.1, 0.99))]
    for wi, wo in pairs:
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
        si.n = mi.Normal3f(0, 0, 1)
        si.uv = mi.Point2f(0.5, 0.5)
        si.wi = dr.normalize(mi.Vector3f(*wi))
        o = dr.normalize(mi.Vector3f(*wo))
        full = nested.eval(mi.BSDFContext(), si, o)
        d = nested.eval(mi.BSDFContext(mi.TransportMode.Radiance, mi.BSDFFlags.DiffuseReflection), si, o)
        g = nested.eval(mi.BSDFContext(mi.TransportMode.Radiance, GLOSSY_MASK), si, o)
        full, rest = np.array(full, dtype=np.float64).ravel(), np.array(d + g, dtype=np.float64).ravel()
        if np.any(np.abs(full - rest) > 1e-4 * np.abs(full) + 1e-7):
            return False
    return True


class Texel:
    """Geometry of one texel among its neighbours, seen from ω_i, in the camera's frame.

    That is the base frame for a camera above the macro surface. For a transmitting nested
    BSDF the camera may be below it (inside the water or glass): seen from there the surface is
    the heightfield −h, so its geometry (V, S, Λ, the bounce) is that of the mirrored frame
    F(x, y, z) = (x, y, −z), in which the camera is above and the texel's normal is
    F(−ω_p) = (−p_x, −p_y, p_z), with the same slopes' σ (Λ is even in the slopes). ``wi`` and
    ``wp`` are in the camera's frame, ``wi_real`` in the base frame; :meth:`to_camera` maps
    between the two (F is its own inverse); the nested BSDF is always called in the base frame."""

    def __init__(self, sp, model, wi):
        self.sp, self.model, self.wi_real = sp, model, wi
        self.flip = None              # where the camera is below the macro surface (None: never)
        wp = sp.wp
        if model.lobes.transmission:
            self.flip = wi.z < 0
            wi = self.to_camera(wi)
            wp = self._camera_side(wp)
        self.wi, self.wp = wi, wp
        self.fill_rho = None          # Model._fill_rho's, once computed
        # With local statistics: the neighbourhood's slopes are the map's times k, and its mean
        # normal ω_m is the macro surface the texel's projected area is measured on (None: the
        # map's slopes, about ω_g).
        self.k, wm = model.local_stats(sp)
        self.lam_i = self.smith_lambda(wi)
        g1_i = dr.rcp(1.0 + self.lam_i)
        if wm is None:
            proj = dr.maximum(dr.dot(wi, wp), 0.0) / (wp.z * dr.maximum(wi.z, 1e-30))
            self.vis = dr.minimum(1.0, proj * g1_i)
        else:
            # (R on a plane between the texel's own and its neighbourhood's mean plane: OWN_PLANE_K.)
            t = dr.minimum(self.k * (1.0 / OWN_PLANE_K), 1.0)
            if model.flat:
                # (A flat map, e.g. at strength 0: ω_t = ω_p = ω_m = ω_g for every t, so nothing
                # flows through t; k still carries the texels' derivatives there, and its path
                # through the nudged normals of strength 0 would not cancel exactly.)
                t = dr.detach(t)
            wt = dr.normalize(dr.fma(t, self._camera_side(wm) - wp, wp))
            self.vis = _visible_share(wi, wp, wt, g1_i)
        # With transmission, seen from above: the reflected light the neighbours block meets their
        # interface and sinks below it (Model._transmitted) instead of bouncing back up (None: never).
        self.sinks = None if self.flip is None else negate(self.flip)
        p_e = self.principal(wp)
        # (atan2's derivative is 0/0 at a flat normal: held there.)
        phi = _held(dr.atan2(dr.abs(p_e.y), dr.abs(p_e.x)), (p_e.x != 0.0) | (p_e.y != 0.0))
        self.blocked = model.blocked(wp.z, phi, g1_i, self.k)

    def _camera_side(self, w):
        """A normal ``w`` (base frame) as the camera sees it: mirrored where it is below (F(−w))."""
        if self.flip is None:
            return w
        return mi.Vector3f(dr.select(self.flip, -w.x, w.x), dr.select(self.flip, -w.y, w.y), w.z)

    def to_camera(self, w):
        """``w`` from the base frame to the camera's (and back): F where the camera is below."""
        if self.flip is None:
            return w
        return mi.Vector3f(w.x, w.y, dr.select(self.flip, -w.z, w.z))

    def principal(self, w):
        """``w`` (base frame) in the principal frame of the map's slopes."""
        if self.sp.map_rotation is not None:
            w = to_tangent_frame(w, self.sp.map_rotation)
        c, s = self.model.cos_e, self.model.sin_e
        return mi.Vector3f(c * w.x + s * w.y, c * w.y - s * w.x, w.z)

    def smith_lambda(self, w):
        s1, s2 = self.model.sigma1, self.model.sigma2
        if self.k is not None:
            s1, s2 = s1 * self.k, s2 * self.k
        return smith_lambda(self.principal(w), s1, s2)

    def seen(self, w):
        """S(ω|ω_i): a visible point of the texel sees ω past the neighbours (0 below either horizon)."""
        up = (w.z > 0) & (dr.dot(w, self.wp) > 0)
        lam = self.smith_lambda(w)
        return dr.select(up, (1.0 + self.lam_i) / (1.0 + self.lam_i + lam), 0.0)

    def _mirror(self, w):
        return 2.0 * dr.dot(w, self.wp) * self.wp - w

    def retro_share(self):
        """w(ω_i) = 1 − S(r|ω_i), r the facet's mirror direction of ω_i: how much of the glossy
        lobe's centre the neighbours block. Blocked light of a lobe whose centre escapes (the
        tails of mild texels' lobes) skims on past the neighbours, mirrored off the macro plane;
        that of a lobe whose centre is blocked is trapped in a cavity and comes back (retro-
        reflection); w blends the two (continuous in ω_i)."""
        blocked = 1.0 - self.seen(self._mirror(self.wi))
        if self.k is None:
            return blocked
        # With local statistics a smooth region (k → 0) is a plane, which has no cavity to send
        # light back: its blocked light (what leaves below the macro plane) skims on. So the share
        # fades with k below RETRO_K, which also keeps w continuous in ω_i where the neighbours'
        # Λ, ∝ k, no longer smooths S's step at the macro horizon.
        # And a cavity sends light back only if its walls are steep: the share also fades with the
        # neighbourhood's rms slope k·σ below RETRO_SLOPE (a mild neighbourhood's blocked light, e.g.
        # a facet's mirror direction under the macro plane at an object's limb, skims on).
        rms = self.k * self.model.rms_slope()
        return blocked * dr.minimum(self.k * (1.0 / RETRO_K), 1.0) * dr.minimum(rms * (1.0 / RETRO_SLOPE), 1.0)

    def bounce(self, d, retro):
        """M(d): where blocked light travelling along d leaves: back the way the facet's mirror
        lobe came (``retro``: d mirrored about ω_p, which takes the lobe's centre to ω_i) or on
        (d as it is); either folded above the macro plane if it heads down. Piecewise
        isometries onto ω_g's hemisphere, so the bounced light keeps its energy exactly."""
        r = dr.select(retro, self._mirror(d), d)
        return mi.Vector3f(r.x, r.y, dr.abs(r.z))

    def preimages(self, w):
        """The blocked directions d that the bounce takes to ω, as (d, lies on the facet, the share
        of blocked light that takes that map): two for skimming on, two for retro-reflection."""
        wp, share = self.wp, self.retro_share()
        below = mi.Vector3f(w.x, w.y, -w.z)
        out = []
        for d, weight in ((w, 1.0 - share), (below, 1.0 - share),
                          (self._mirror(w), share), (self._mirror(below), share)):
            out.append((d, dr.dot(d, wp) > 0, weight))
        return out


#: With local statistics, the neighbourhood scale k below which a texel's blocked glossy light is
#: less and less retro-reflected (Texel.retro_share): 0 for a plane (k = 0).
RETRO_K = 0.5
#: With local statistics, the neighbourhood's rms slope (k times the map's) below which a texel's
#: blocked glossy light is less and less retro-reflected (Texel.retro_share): tan 26.6°. Measured
#: against 1 (tan 45°): the real assets the same (relMSE 0.0407 / 0.0408), the steep periodic cells
#: 0.248 against 0.279 (docs/faithful.md §1.1).
RETRO_SLOPE = 0.5
#: With local statistics, the texel's projected area R is taken on its neighbourhood's mean plane,
#: whose cosines with ω_i and ω_p count at least this share of their cosines with ω_g: R stays
#: finite, and V continuous, where ω_i skims or passes under that plane while it sees the facet.
MEAN_PLANE_MIN = 0.5
#: With local statistics, the texel's projected area R is taken on a plane between its own and its
#: neighbourhood's mean plane, ω_t ∝ ω_p + t·(ω_m − ω_p), t = min(1, k / OWN_PLANE_K): a texel in a
#: smooth neighbourhood (k → 0) is the surface there and is foreshortened only as that surface is;
#: one among neighbours as rough as the map's (k ≥ 2) is a facet on their mean plane. Measured
#: against the mean plane alone (t = 1): real assets relMSE 0.0407 → 0.0398 (at or below classic
#: normal mapping in 43 → 46 of 48 cells), the periodic grid the same within 1 % (docs/faithful.md §1.1).
OWN_PLANE_K = 2.0
#: With local statistics, the neighbourhood's rms slope (k times the map's) from which its k is the
#: window's alone; below it k moves toward the finer window's (neighbourhood.FINE_WINDOW), all of
#: it for a flat neighbourhood (Model.local_stats). Measured (docs/faithful.md §1.1): the real
#: assets' relMSE 0.0398 → 0.0391 (0.0391 → 0.0385 given the map in Mitsuba's frame, classic normal
#: mapping 0.0386); the periodic grid's mild cells 0.00676 → 0.00708 (classic 0.00742), steep
#: 0.247 → 0.256, steep grazing 0.436 → 0.459 (classic 0.553). 0.5 kept more of the steep cells
#: (0.247, 0.437) and less of the real assets (0.0393; Mitsuba's frame 0.0386).
MILD_SLOPE = 1.0


def _visible_share(wi, wp, wm, g1):
    """V = min(1, R·G1) with local statistics: R = ⟨ω_i,ω_p⟩₊/(⟨ω_p,ω_m⟩⟨ω_i,ω_m⟩) the texel's projected
    area on the plane with normal ``wm`` (its neighbourhood's mean plane, or between that and its own:
    OWN_PLANE_K), each cosine at least MEAN_PLANE_MIN times
    its cosine with ω_g (so R is the map-wide one where ω_m = ω_g, and V falls continuously to 0 at
    the facet's horizon). (Written so that no derivative is 0·∞ where R is large.)"""
    cos_i = dr.dot(wi, wp)
    num = dr.maximum(cos_i, 0.0) * g1
    den = (dr.maximum(dr.dot(wp, wm), MEAN_PLANE_MIN * wp.z) *
           dr.maximum(dr.dot(wi, wm), MEAN_PLANE_MIN * dr.maximum(wi.z, 1e-30)))
    full = num >= den
    return dr.select(full, 1.0, num / dr.select(full, 1.0, den))


def _gated(cond, fn, otherwise, gated=True):
    """``fn()`` where ``cond``, ``otherwise`` elsewhere, for an ``fn`` that gives ``otherwise``
    where ``cond`` is false (its nested calls masked by it): the same values as ``fn()``, but a
    SIMD packet in which no lane needs ``fn`` skips it (a symbolic ``dr.if_stmt``: LLVM branches
    per packet; derivatives flow through it). ``gated`` false: ``fn()`` as it is."""
    if not gated:
        return fn()
    if not dr.is_jit_v(mi.Float):
        return fn() if cond else otherwise
    return dr.if_stmt((), cond, fn, lambda: otherwise)


def _nested(sp, ctx, frame, wi, wo, active, want_value=True, want_pdf=True, si_f=None):
    """(f·cos, pdf) of the nested BSDF with context ``ctx`` on the facet with ``frame``
    (``si_f``: ``sp.facet_si(frame, wi)``, if the caller has it)."""
    si_f, wo_f, active = sp._facet_query(frame, wi, wo, active, si_f)
    return _call(sp, ctx, si_f, wo_f, active, want_value, want_pdf)


def _call(sp, ctx, si_f, wo_f, active, want_value, want_pdf):
    """The nested BSDF's (f·cos, pdf) at the facet query (``si_f``, ``wo_f``), zero where inactive."""
    if want_value and want_pdf:
        v, p = sp.nested.eval_pdf(ctx, si_f, wo_f, active)
    elif want_value:
        v, p = sp.nested.eval(ctx, si_f, wo_f, active), mi.Float(0.0)
    else:
        v, p = mi.Spectrum(0.0), sp.nested.pdf(ctx, si_f, wo_f, active)
    return dr.select(active, v, 0.0), dr.select(active, p, 0.0)


# Which side of the facet a nested query's ω_o must be on, seen from the camera's side of it.
REFLECT, TRANSMIT, EITHER = "reflect", "transmit", "either"


def _sided(sp, tx, ctx, frame, wi, wo, active, want_value=True, want_pdf=True, si_f=None, side=REFLECT):
    """:func:`_nested` (base-frame ``wi``, ``wo``) for a texel ``tx`` that may be seen from below:
    active where ``wi`` is on the camera's side of ``frame`` (for a camera below, the facet's
    lower side) and ``wo`` on the ``side`` asked for. Without transmission, :func:`_nested`."""
    if tx.flip is None:
        return _nested(sp, ctx, frame, wi, wo, active, want_value, want_pdf, si_f)
    si_f = sp.facet_si(frame, wi) if si_f is None else si_f
    wo_f = frame.to_local(wo)
    sign = dr.select(tx.flip, -1.0, 1.0)
    c_o = sign * wo_f.z
    on_side = {REFLECT: c_o > 0, TRANSMIT: c_o < 0, EITHER: c_o != 0}[side]
    active = active & (sign * si_f.wi.z > 0) & on_side
    return _call(sp, ctx, si_f, wo_f, active, want_value, want_pdf)


def _mirror_z(w):
    """F(w) = (w_x, w_y, −w_z): the mirror image of ``w`` in the macro plane."""
    return mi.Vector3f(w.x, w.y, -w.z)


RADIANCE = mi.TransportMode.Radiance


def _crossing_eta(sp, si_f, active):
    """η of the interface on the facet of ``si_f`` (seen from its ``wi``): the relative index
    (``bs.eta``) of a transmitted nested sample, 1 where there is none. Light that crosses into
    the far side carries Mitsuba's radiance scaling 1/η² (:meth:`Model._transmitted`)."""
    ctx = mi.BSDFContext(RADIANCE, mi.BSDFFlags.Transmission)
    bs, w = sp.nested.sample(ctx, si_f, mi.Float(0.5), mi.Point2f(0.5, 0.5), active)
    ok = active & (bs.pdf > 0) & (si_f.wi.z * bs.wo.z < 0) & (bs.eta > 0)
    return dr.select(ok, bs.eta, 1.0)

# ⟨ω_h, ω_p⟩ of the near-horizon direction at which the diffuse fill reads the facet's lobe.
HORIZON_MU = 0.2
# The share of the blocked light's samples that the sampler gives the diffuse fill, for nested
# BSDFs with diffuse and glossy parts: the fill's albedo ρ_fill clipped to these bounds (the
# floor keeps the fill's lobe sampled where the bounced samples miss it). Measured, plane with
# roughplastic (diffuse 0.2), sunless sky, per-sample relMSE: a fixed 0.5 gives 1.36× the
# built-in's, this 1.29× (docs/faithful.md).
FILL_SHARE_MIN, FILL_SHARE_MAX = 0.05, 0.5


@dataclass
class _Query:
    """What :meth:`Model.eval_pdf` hands its bounced terms (:meth:`Model._bounced`)."""

    sp: object
    tx: object
    wi: object
    pre: object
    s_o: object
    on_texel: object
    si_p: object
    want_value: bool
    want_pdf: bool


class Model:
    """The faithful model for one plugin instance: its lobes, the map's σ and the Lambertian table."""

    def __init__(self, nested, slopes, cos_min: float, fill_share=(FILL_SHARE_MIN, FILL_SHARE_MAX), local=None):
        self.lobes = Lobes(nested)
        self.fill_share = fill_share
        self.cos_min = cos_min
        self.set_slopes(slopes, local=local)

    def rms_slope(self):
        """The map's rms slope σ = ((σ1² + σ2²)/2)^½ (a neighbourhood's is k·σ), with σ1's and
        σ2's derivatives."""
        s1, s2 = self.sigma1, self.sigma2
        return dr.sqrt(0.5 * dr.fma(s1, s1, s2 * s2))

    def local_stats(self, sp):
        """(k, ω_m) at the shading point with local statistics: the scale of its neighbourhood's
        slopes and the neighbourhood's mean normal (the local macro surface, base frame); (None,
        None) where the model uses the map's for every texel."""
        if self.local is None:
            return None, None
        fields, res, uv_of = self.local
        uv = uv_of(sp.si)
        k, mx, my, *fine = field_lookup(fields, res, uv.x, uv.y)
        # (The table's k ends at local_scales()[-1]: Λ must not see a rougher neighbourhood than B.)
        k = dr.minimum(k, self.k_max)
        if fine:
            # A mild neighbourhood's slopes vary over the window mostly with the surface's shape
            # (the low-poly against the high-poly), which masks nothing at the texel's scale: its k
            # is read from the finer window (where that is lower: at a crease the finer window can
            # see more), a steep one's (rms slope k·σ at least MILD_SLOPE) from the window, and one
            # between from both, in proportion.
            steep = dr.minimum(k * self.rms_slope() * (1.0 / MILD_SLOPE), 1.0)
            k = dr.lerp(dr.minimum(fine[0], k), k, steep)
        wm = dr.normalize(mi.Vector3f(-mx, -my, 1.0))
        if sp.map_rotation is not None:
            wm = from_tangent_rotation(wm, sp.map_rotation)
        return k, wm

    def set_slopes(self, slopes, attached=None, local=None):
        """(Re)build what depends on the map's slopes ``(σ1, σ2, φ_e)`` (principal_slopes);
        they enter the kernels as opaque values, so a new map compiles nothing new.

        ``attached``: the same slopes as Dr.Jit values that carry derivatives (with respect to
        the map and ``strength``: :func:`attached_slopes`), or None. σ and φ_e then carry those
        derivatives into every query (a texel moves the map's rms slope by O(1/texels)), and the
        table B(σ1, σ2) its own, from tables of ∂B/∂σ1 and ∂B/∂σ2 (docs/faithful.md §6). The
        values are the numpy ones either way.

        ``local``: ((k, m_x, m_y), the same as Dr.Jit values that carry derivatives or None, res,
        uv_of): the neighbourhood's scale k and mean slope on a res × res grid of the map (numpy;
        :func:`neighbourhood.local_field`), and the map's uv at a surface interaction; None: every
        texel has the map's neighbourhood about ω_g. The table then has an axis in k."""
        s1, s2, phi_e = (float(x) for x in slopes)
        self.flat = s1 == 0.0 and s2 == 0.0         # every texel flat (or strength 0)
        self.local, scales = None, None
        if local is not None:
            fields, fields_ad, res, uv_of = local
            scales = local_scales()
            self.k_max = scales[-1]
            values = []
            for n, field in enumerate(fields):
                field = np.asarray(field, np.float32).ravel()
                if dr.is_jit_v(mi.Float):
                    field = kernel_array(mi.Float, field)
                    if fields_ad is not None:
                        field = replace_grad(field, fields_ad[n])
                    else:
                        dr.make_opaque(field)
                values.append(field)
            self.local = (values, res, uv_of)
        self.slopes = (s1, s2, phi_e)
        self.sigma1, self.sigma2 = mi.Float(s1), mi.Float(s2)
        self.cos_e, self.sin_e = mi.Float(math.cos(phi_e)), mi.Float(math.sin(phi_e))
        self.d_tables = None
        if attached is not None and dr.is_jit_v(mi.Float):
            a1, a2, phi = attached
            # φ_e's value, the derivative of phi; φ_e a kernel input (a literal would compile anew per map)
            phi = phi + (dr.opaque(mi.Float, phi_e) - dr.detach(phi))
            self.sigma1, self.sigma2 = replace_grad(self.sigma1, a1), replace_grad(self.sigma2, a2)
            self.cos_e, self.sin_e = replace_grad(self.cos_e, dr.cos(phi)), replace_grad(self.sin_e, dr.sin(phi))
            table, t1, t2 = blocked_table(s1, s2, self.cos_min, derivatives=True, scales=scales)
            self.d_tables = (kernel_array(mi.Float, t1), kernel_array(mi.Float, t2))
            dr.make_opaque(*self.d_tables)
        else:
            table = blocked_table(s1, s2, self.cos_min, scales=scales)
        table = table.ravel()
        if dr.is_jit_v(mi.Float):
            self.table = kernel_array(mi.Float, table)
            dr.make_opaque(self.sigma1, self.sigma2, self.cos_e, self.sin_e, self.table)
        else:
            self.table = table

    def blocked(self, cos_p, phi, g, k=None):
        """B(cosθ_p, φ, G1(ω_i)) from the table (at the neighbourhood's scale ``k``, with local
        statistics), with its derivative with respect to σ1, σ2 when they carry one."""
        value = lookup(self.table, self.cos_min, cos_p, phi, g, k)
        if self.d_tables is None:
            return value
        s1, s2 = dr.detach(self.sigma1), dr.detach(self.sigma2)
        return replace_grad(value, value + lookup(self.d_tables[0], self.cos_min, cos_p, phi, g, k) * (self.sigma1 - s1)
                            + lookup(self.d_tables[1], self.cos_min, cos_p, phi, g, k) * (self.sigma2 - s2))

    def texel(self, sp, wi):
        return Texel(sp, self, wi)

    def _fill(self, sp, tx):
        """The diffuse fill's energy B(ω_i)·ρ_fill(ω_i): the blocked diffuse light from ω_i,
        re-emitted as a cosine lobe about ω_g (:meth:`_fill_rho`)."""
        if not self.lobes.diffuse:
            return mi.Spectrum(0.0)
        rho = self._fill_rho(sp, tx)
        return tx.blocked * rho * dr.minimum(rho, 1.0)

    def _fill_rho(self, sp, tx):
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
            ctx = mi.BSDFContext(RADIANCE, self.lobes.diffuse_mask)
            active = (tx.wi.z > 0) & (tx.vis > 0)
            wp = tx.wp
            down = wp.z * wp - mi.Vector3f(0.0, 0.0, 1.0)                 # −(ω_g − cosθ_p ω_p)
            n2 = dr.squared_norm(down)
            down = dr.select(n2 > 1e-12, down * dr.rsqrt(dr.maximum(n2, 1e-30)), sp.frame_p.s)
            w_h = HORIZON_MU * wp + math.sqrt(1.0 - HORIZON_MU ** 2) * down
            wi = tx.wi_real
            f_n, _ = _sided(sp, tx, ctx, sp.frame_p, wi, tx.to_camera(wp), active, want_pdf=False)
            f_h, _ = _sided(sp, tx, ctx, sp.frame_p, wi, tx.to_camera(w_h), active, want_pdf=False)
            tx.fill_rho = math.pi * dr.minimum(f_n, f_h / HORIZON_MU)
        return tx.fill_rho

    def _branches(self, tx):
        """The sampler's branch probabilities: the texel (a nested sample, bounced if blocked),
        the diffuse fill, the hidden texel's neighbours."""
        if self.lobes.diffuse and self.lobes.glossy:
            # The blocked light's samples, split between the fill and the texel's nested sample
            # (bounced when blocked) by the fill's share of it, ρ_fill (mean over the channels),
            # within self.fill_share, [FILL_SHARE_MIN, FILL_SHARE_MAX] by default.
            rho = self._fill_rho(tx.sp, tx)
            share = dr.clip(dr.mean(rho * dr.minimum(rho, 1.0)), *self.fill_share)
            p_fill = tx.vis * tx.blocked * share
        elif self.lobes.diffuse:
            p_fill = tx.vis * tx.blocked
        else:
            p_fill = mi.Float(0.0)
        return tx.vis - p_fill, p_fill, 1.0 - tx.vis

    def eval_pdf(self, sp, tx, wo, active, want_value=True, want_pdf=True, gated=None):
        """(eval, pdf) in radiance mode: camera side ``tx.wi``, light side ``wo``.

        ``gated``: terms that no lane of a SIMD packet needs (the retro-reflected and below-plane
        preimages, the hidden texel) are skipped (:func:`_gated`: the same values, bit for bit);
        None: wherever nothing the query reads carries derivatives (:meth:`_gates`).
        What the texel shares with the ``sample`` at the same path vertex (Λ(ω_i), V, B, the
        fill) is traced before the branches, so Dr.Jit's common-subexpression elimination still
        shares it (a branch opens a scope that shares nothing with the outside)."""
        if gated is None:
            gated = self._gates(sp, tx, wo)
        wi, wo_g = tx.wi, tx.to_camera(wo)
        trans = self.lobes.transmission
        # (With transmission ω_o lies on either side: its side decides which terms it gets.)
        either = active & (wi.z > 0) & (wo_g.z != 0) if trans else None
        active = active & (wi.z > 0) & (wo_g.z > 0)
        full = mi.BSDFContext(RADIANCE)
        on_texel = active & (tx.vis > 0)
        value, pdf = mi.Spectrum(0.0), mi.Float(0.0)

        # The diffuse fill's lobe (before any branch, and masked independently of ω_o and of the
        # caller's mask, so that the eval_pdf and sample of one path vertex share it; the lanes
        # it adds are masked out below).
        fill = self._fill(sp, tx) if want_value else None
        # Lit directly past the neighbours, and the light the neighbours block that skims on
        # toward ω_o (the first preimage, d = ω_o: one nested query serves both).
        s_o = tx.seen(wo_g)
        si_p = sp.facet_si(sp.frame_p, tx.wi_real)
        pre = tx.preimages(wo_g)
        q = _Query(sp, tx, tx.wi_real, pre, s_o, on_texel, si_p, want_value, want_pdf)
        acc = self._direct(q, wo)
        # Light the neighbours block, bounced toward ω_o: the glossy part in eval (the diffuse
        # part is the fill), every lobe in the sampler's pdf. A preimage below the macro plane
        # is never seen past the neighbours (S = 0: ω_o is above it here). The retro-reflected
        # pair (share w > 0) and the one below the plane are skipped by packets that need neither.
        # (One branch for the three: each branch's scope repeats the nested BSDF's own ω_i terms,
        # 3 % more kernel operations with two.)
        rare = on_texel & ((pre[1][1] & (pre[1][2] > 0)) | (pre[2][2] > 0))
        value_t, pdf_t = _gated(rare, lambda: self._bounced(q, (1, 2, 3), acc), acc, gated)
        if trans:
            value_t, pdf_t = self._transmitted(q, wo, either & (wo_g.z < 0), (value_t, pdf_t), gated)
            active = either
        # The neighbours, where the texel is hidden.
        f_hid, p_hid = _gated(active & (tx.vis < 1.0), lambda: _sided(
            sp, tx, full, macro_frame(), tx.wi_real, wo, active & (tx.vis < 1.0), want_value, want_pdf,
            side=EITHER), (mi.Spectrum(0.0), mi.Float(0.0)), gated)
        cos_fill = dr.maximum(wo_g.z, 0.0) if trans else wo.z

        if want_value:
            value = tx.vis * (value_t + fill * (cos_fill * INV_PI)) + (1.0 - tx.vis) * f_hid
            value = dr.select(active & dr.all(dr.isfinite(value)), dr.maximum(value, 0.0), 0.0)
        if want_pdf:
            b_tex, b_fill, b_hid = self._branches(tx)
            pdf = b_tex * pdf_t + b_fill * (cos_fill * INV_PI) + b_hid * p_hid
            pdf = dr.select(active & dr.isfinite(pdf), dr.maximum(pdf, 0.0), 0.0)
        return value, pdf

    def _transmitted(self, q, wo, down, acc, gated):
        """``acc`` plus the light the facet transmits toward ω_o, on the far side of the macro
        surface from the camera (``down``): straight from the facet, or folded there from its
        mirror image F(ω_o) (a refracted direction on the camera's side of the macro surface, the
        side classic normal mapping sends it to). The neighbours block transmitted light too;
        it leaves below them (M_T(d) = (d_x, d_y, −|d_z|) in the camera's frame, a piecewise
        isometry: energy exact), so blocked or not, d below the macro plane leaves as d, and
        S_T cancels: eval gets f_p^T(ω_i, ω_o) + f_p^T(ω_i, F(ω_o)), the pdf likewise.

        Seen from above (``tx.sinks``), the reflected light the neighbours block meets their
        interface and sinks below it by the same map M_T: a reflected d leaves past the neighbours
        with S(d|ω_i) (0 below the macro plane), else below them, so ω_o also gets the facet's
        glossy reflection f_p^R(ω_i, ω_o) and f_p^R(ω_i, F(ω_o)), each times 1 − S (every lobe
        in the pdf), with the radiance scaling 1/η² of light that crosses the interface
        (:func:`_crossing_eta`); the diffuse part's blocked light stays the fill's. (Skipped by
        packets with no such lane, ``gated``: :func:`_gated`.)"""
        f_b, p_b = acc
        tx = q.tx
        full = mi.BSDFContext(RADIANCE)
        on = down & (tx.vis > 0)
        for d in (wo, _mirror_z(wo)):
            f, p = _sided(q.sp, tx, full, q.sp.frame_p, q.wi, d, on, q.want_value, q.want_pdf, q.si_p, TRANSMIT)
            f_b, p_b = f_b + f, p_b + p
        glossy = mi.BSDFContext(RADIANCE, self.lobes.glossy_mask)
        pre = [(d, tx.seen(tx.to_camera(d))) for d in (wo, _mirror_z(wo))]
        sunk = [on & tx.sinks & (s_d < 1.0) for _, s_d in pre]

        def sinking():
            f_s, p_s = f_b, p_b
            if q.want_value and self.lobes.glossy:
                scale = dr.rcp(dr.square(_crossing_eta(q.sp, q.si_p, sunk[0] | sunk[1])))
            for (d, s_d), on_d in zip(pre, sunk):
                if q.want_value and self.lobes.glossy:
                    f, _ = _sided(q.sp, tx, glossy, q.sp.frame_p, q.wi, d, on_d, True, False, q.si_p, REFLECT)
                    f_s = f_s + f * ((1.0 - s_d) * scale)
                if q.want_pdf:
                    _, p = _sided(q.sp, tx, full, q.sp.frame_p, q.wi, d, on_d, False, True, q.si_p, REFLECT)
                    p_s = p_s + p * (1.0 - s_d)
            return f_s, p_s
        return _gated(sunk[0] | sunk[1], sinking, (f_b, p_b), gated)

    def _fused(self, want_value):
        """Whether one nested query (every lobe) gives both a blocked preimage's glossy value and
        its pdf: a nested BSDF without a diffuse lobe, whose glossy part is all of it."""
        return want_value and self.lobes.glossy and not self.lobes.diffuse

    def _preimage_blocked(self, q, k, s_d):
        """Where the light blocked toward the preimage ``k`` is bounced toward ω_o."""
        _, on_facet, share = q.pre[k]
        blocked = q.on_texel & on_facet & (s_d < 1.0) & (share > 0)
        if q.tx.sinks is not None:
            blocked &= negate(q.tx.sinks)
        return blocked

    def _direct(self, q, wo):
        """(eval, pdf) of the facet lit directly past the neighbours, S(ω_o)·f_p(ω_i, ω_o), plus the
        light blocked toward the first preimage d = ω_o that skims on toward ω_o (:meth:`_bounced`'s
        term for it). Both read the facet's nested BSDF at ω_o: every lobe for the direct light and
        the pdfs, the glossy ones for the blocked light's value. One nested query gives what they
        share (for a nested BSDF without a diffuse lobe, all of it)."""
        sp, tx, s_o = q.sp, q.tx, q.s_o
        _, _, share = q.pre[0]
        full = mi.BSDFContext(RADIANCE)
        lit = q.on_texel & (s_o > 0)
        blocked = self._preimage_blocked(q, 0, s_o)
        fused = self._fused(q.want_value)
        f, p = _sided(sp, tx, full, sp.frame_p, q.wi, wo, (lit | blocked) if q.want_pdf or fused else lit,
                      q.want_value, q.want_pdf, q.si_p)
        weight = share * (1.0 - s_o)
        value = dr.select(lit, f, 0.0) * s_o
        pdf = dr.select(lit, p, 0.0) * s_o
        if self.lobes.glossy and q.want_value:
            if not fused:
                glossy = mi.BSDFContext(RADIANCE, self.lobes.glossy_mask)
                f, _ = _sided(sp, tx, glossy, sp.frame_p, q.wi, wo, blocked, True, False, q.si_p)
            value = value + dr.select(blocked, f, 0.0) * weight
        if q.want_pdf:
            pdf = pdf + dr.select(blocked, p, 0.0) * weight
        return value, pdf

    def _bounced(self, q, ks, acc):
        """``acc`` plus the light the neighbours block toward the preimages ``ks`` (not the first:
        :meth:`_direct`) of ω_o (:meth:`Texel.preimages`), bounced toward ω_o: the glossy part in
        eval, every lobe in the pdf."""
        f_b, p_b = acc
        sp, tx, wi = q.sp, q.tx, q.wi
        full, glossy = mi.BSDFContext(RADIANCE), mi.BSDFContext(RADIANCE, self.lobes.glossy_mask)
        for k in ks:
            d, _, share = q.pre[k]
            s_d = mi.Float(0.0) if k == 1 else tx.seen(d)
            blocked = self._preimage_blocked(q, k, s_d)
            d = tx.to_camera(d)
            weight = share * (1.0 - s_d)
            if self._fused(q.want_value):
                f, p = _sided(sp, tx, full, sp.frame_p, wi, d, blocked, True, q.want_pdf, q.si_p)
                f_b = f_b + f * weight
                if q.want_pdf:
                    p_b = p_b + p * weight
                continue
            if self.lobes.glossy and q.want_value:
                f, _ = _sided(sp, tx, glossy, sp.frame_p, wi, d, blocked, True, False, q.si_p)
                f_b = f_b + f * weight
            if q.want_pdf:
                _, p = _sided(sp, tx, full, sp.frame_p, wi, d, blocked, False, True, q.si_p)
                p_b = p_b + p * weight
        return f_b, p_b

    def _draw(self, sp, tx, sample1, sample2, active):
        """One draw of the radiance-mode sampler from ``tx.wi``: the exit direction and its path."""
        wi, trans = tx.wi, self.lobes.transmission
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
        frame = _select_frame(on_tex, sp.frame_p, macro_frame())
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
            # Transmitted through the facet: leaves below the macro surface (Model._transmitted).
            through = on_tex & (dr.dot(d, tx.wp) < 0)
            bounced &= negate(through)
        wo = dr.select(bounced, tx.bounce(d, retro), d)
        if trans:
            # (Blocked reflected light seen from above sinks below the neighbours the same way.)
            sunk = bounced & tx.sinks
            wo = dr.select(through | sunk, mi.Vector3f(d.x, d.y, -dr.abs(d.z)), wo)
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
            eta_s = _crossing_eta(sp, sp.facet_si(sp.frame_p, tx.wi_real), active & sunk)
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
        """Whether a query may skip, per SIMD packet, the terms no lane needs (:func:`_gated`):
        where nothing it reads carries derivatives (:meth:`_derivatives`, ω_i and ``directions``:
        moving geometry or emitters)."""
        return not (self._derivatives(sp) or dr.grad_enabled(tx.wi, *directions))

    def sample(self, sp, tx, sample1, sample2, active):
        """Radiance-mode sample from ``tx.wi``: (BSDFSample3f in the base frame, weight).

        Derivatives: a smooth lobe's direction is detached, its weight eval(θ)/detach(pdf);
        a delta lobe's direction and weight are differentiable functions, times the score
        p/detach(p) of the branch it took (microsurface.score)."""
        dw = self._draw(sp, tx, sample1, sample2, active)
        bs, active = dw.bs, dw.active
        bs.wo = dr.select(dw.delta, bs.wo, dr.detach(bs.wo))
        value, pdf = self.eval_pdf(sp, tx, bs.wo, active & negate(dw.delta), gated=self._gates(sp, tx))
        # Delta lobes (non-diffuse, so bounced ones are the eval's too): the path weight, the
        # branch probabilities cancelling against the eval's factors.
        w_delta = dw.w * dr.select(dw.on_tex, tx.vis / dr.maximum(dw.b_tex, 1e-30),
                                   (1.0 - tx.vis) / dr.maximum(dw.b_hid, 1e-30))
        weight = dr.select(dw.delta, w_delta * score(dw.prob), value / dr.detach(dr.select(pdf > 0, pdf, 1.0)))
        bs.pdf = dr.select(dw.delta, bs.pdf * dw.prob, pdf)
        return _finish(bs, weight, active)

    # -- Light tracing: the adjoint eval*(a, b) = eval(b, a)·⟨b, ω_g⟩/⟨a, ω_g⟩ -------------------

    def _adjoint_branches(self, tx_a, texel_for):
        """The adjoint sampler's extra branches, for the parts of eval* that radiance sampling from
        a does not cover (their weight depends on the camera side b): the fill (a cosine lobe about
        ω_g) and, for glossy lobes, b sampled on the facet from each preimage d of a under the bounce
        and b sampled on ω_g from a (the hidden texel's neighbours); with transmission, the hidden
        texel's neighbours always, b refracted on the facet from F(a) (the fold, where F(a)
        lies on the facet's side that a refracted camera ray would leave from), and, for a below the
        macro plane, b reflected on the facet from a and from F(a) (the reflected light that sinks
        below the neighbours of a texel seen from above: Model._transmitted).
        Returns [(probability, kind, frame, incident direction in the base frame), ...]."""
        sp, a, a_real = tx_a.sp, tx_a.wi, tx_a.wi_real
        branches = [(mi.Float(0.05), "cosine", None, None)]
        if self.lobes.glossy:
            for k, (d, on_facet, share) in enumerate(tx_a.preimages(a)):
                s_d = tx_a.seen(d)
                p = dr.select(on_facet & (s_d < 1.0), dr.maximum(0.1 * tx_a.vis * (1.0 - s_d), 0.025), 0.0)
                branches.append((p, "retro" if k >= 2 else "skim", sp.frame_p, tx_a.to_camera(d)))
        if self.lobes.glossy or self.lobes.transmission:
            vis_c = texel_for(mi.Vector3f(-a_real.x, -a_real.y, a_real.z)).vis      # at the flat lobe's centre
            branches.append((dr.maximum(0.3 * (1.0 - vis_c), 0.05), "hidden", macro_frame(), a_real))
        if self.lobes.transmission:
            on = dr.dot(_mirror_z(a), tx_a.wp) > 0
            branches.append((dr.select(on, 0.1, 0.0), "fold", sp.frame_p, _mirror_z(a_real)))
            for inc in (a_real, _mirror_z(a_real)):
                on = (a_real.z < 0) & (dr.dot(inc, sp.wp) > 0)
                branches.append((dr.select(on, 0.05, 0.0), "sink", sp.frame_p, inc))
        return branches

    def _adjoint_branch_pdf(self, sp, tx_a, kind, frame, inc, b, active):
        """The density at b of one extra branch of the adjoint sampler (where its samples count:
        :meth:`_adjoint_branch_valid`)."""
        a, ctx = tx_a.wi_real, mi.BSDFContext(RADIANCE)
        trans = self.lobes.transmission
        if kind == "cosine":
            return (dr.maximum(tx_a.to_camera(b).z, 0.0) if trans else b.z) * INV_PI
        if kind in ("fold", "sink"):
            si_f = sp.facet_si(frame, inc)
            b_f = frame.to_local(b)
            if kind == "fold":
                on = active & (si_f.wi.z * b_f.z < 0) & (a.z * b.z < 0)
            else:
                on = active & (si_f.wi.z > 0) & (b_f.z > 0) & (a.z < 0) & (b.z > 0)
            return dr.select(on, sp.nested.pdf(ctx, si_f, b_f, on), 0.0)
        side = EITHER if kind == "hidden" else REFLECT
        if trans and kind != "hidden":
            active = active & (a.z * b.z > 0)
        return _sided(sp, tx_a, ctx, frame, inc, b, active, False, True, side=side)[1]

    @staticmethod
    def _adjoint_branch_valid(kind, bs, w, frame, inc, a, trans):
        """Whether a nested sample of an extra branch counts (:meth:`_adjoint_branch_pdf`'s region)."""
        ok = (bs.pdf > 0) & dr.any(w > 0)
        if not trans:
            return ok & (dr.dot(bs.wo, frame.n) > 0) & (bs.wo.z > 0)
        side = dr.dot(bs.wo, frame.n) * dr.dot(inc, frame.n)
        if kind == "hidden":
            return ok & (bs.wo.z != 0)
        if kind == "fold":
            return ok & (side < 0) & (a.z * bs.wo.z < 0)
        if kind == "sink":
            return ok & (side > 0) & (a.z < 0) & (bs.wo.z > 0)
        return ok & (side > 0) & (a.z * bs.wo.z > 0)

    def eval_pdf_adjoint(self, sp, tx_a, tx_b, active, texel_for, want_value=True, want_pdf=True):
        """(eval*, pdf*) for light tracing: light side ``tx_a.wi``, camera side ``tx_b.wi`` (base
        frame: ``wi_real``; with transmission either side, |⟨b,ω_g⟩|/|⟨a,ω_g⟩|)."""
        a, b = tx_a.wi_real, tx_b.wi_real
        trans = self.lobes.transmission
        if trans:
            active = active & (a.z != 0) & (b.z != 0)
        else:
            active = active & (a.z > 0) & (b.z > 0)
        value, pdf = mi.Spectrum(0.0), mi.Float(0.0)
        if want_value:
            value, _ = self.eval_pdf(sp, tx_b, a, active, want_pdf=False)
            value *= dr.abs(b.z) / dr.maximum(dr.abs(a.z), 1e-30) if trans else b.z / dr.maximum(a.z, 1e-30)
            value = dr.select(active & dr.all(dr.isfinite(value)), value, 0.0)
        if want_pdf:
            _, p_rad = self.eval_pdf(sp, tx_a, b, active, want_value=False)
            share = mi.Float(0.0)
            for p, kind, frame, inc in self._adjoint_branches(tx_a, texel_for):
                p_k = self._adjoint_branch_pdf(sp, tx_a, kind, frame, inc, b, active & (p > 0))
                pdf, share = pdf + p * p_k, share + p
            pdf = pdf + (1.0 - share) * p_rad
            pdf = dr.select(active & dr.isfinite(pdf), dr.maximum(pdf, 0.0), 0.0)
        return value, pdf

    def sample_adjoint(self, sp, tx_a, sample1, sample2, active, texel_for):
        """Light-tracing sample from the light side ``tx_a.wi``; ``texel_for(b)`` builds the texel seen from b."""
        extra = self._adjoint_branches(tx_a, texel_for)
        # Choose a branch: the extra ones first (consecutive intervals), then the radiance sampler.
        # (The choice, and sample1's rescaling, with detached probabilities.)
        p_rad = 1.0 - sum((br[0] for br in extra), mi.Float(0.0))
        c_rad = dr.detach(p_rad)
        picked, lo_k, width, acc = mi.UInt32(len(extra)), 1.0 - c_rad, c_rad, mi.Float(0.0)
        for k, br in enumerate(extra):
            p_k = dr.detach(br[0])
            hit = (sample1 >= acc) & (sample1 < acc + p_k)
            picked = dr.select(hit, k, picked)
            lo_k = dr.select(hit, acc, lo_k)
            width = dr.select(hit, p_k, width)
            acc = acc + p_k
        s1 = dr.clip((sample1 - lo_k) / dr.maximum(width, 1e-30), 0.0, ONE_MINUS_EPS)
        on_rad = picked == len(extra)
        dw = self._draw(sp, tx_a, s1, sample2, active & on_rad)
        bs, w, delta, ok = dw.bs, dw.w, dw.delta, dw.active
        for k, (p, kind, frame, inc) in enumerate(extra):
            on_k = picked == k
            if kind == "cosine":
                bs.wo = dr.select(on_k, tx_a.to_camera(mi.warp.square_to_cosine_hemisphere(sample2)), bs.wo)
                delta &= negate(on_k)
                ok = dr.select(on_k, active, ok)
                continue
            bs_k, w_k = sp.sample(frame, inc, s1, sample2, active & on_k)
            bs = _select_sample(on_k, bs_k, bs)
            w = dr.select(on_k, w_k, w)
            delta = dr.select(on_k, mi.has_flag(bs_k.sampled_type, mi.BSDFFlags.Delta), delta)
            valid_k = self._adjoint_branch_valid(kind, bs_k, w_k, frame, inc, tx_a.wi_real, self.lobes.transmission)
            ok = dr.select(on_k, active & valid_k, ok)
        bs.wo = dr.select(delta, bs.wo, dr.detach(bs.wo))
        tx_b = texel_for(bs.wo)
        value, pdf = self.eval_pdf_adjoint(sp, tx_a, tx_b, ok & negate(delta), texel_for)
        c_delta, prob_delta = self._adjoint_delta(sp, tx_a, tx_b, extra, dw, picked, p_rad, on_rad)
        weight = dr.select(delta, w * c_delta * score(prob_delta), value / dr.detach(dr.select(pdf > 0, pdf, 1.0)))
        bs.pdf = dr.select(delta, bs.pdf * prob_delta, pdf)
        return _finish(bs, weight, ok)

    def _adjoint_delta(self, sp, tx_a, tx_b, extra, dw, picked, p_rad, on_rad):
        """Delta lobes: eval*'s coefficient on the sampled path over the draws that give that path,
        and their probability. A refracted path's coefficient carries the change of variables of
        the delta from a to b, |⟨a,ω_p⟩⟨b,ω_g⟩| / |⟨b,ω_p⟩⟨a,ω_g⟩| (1 for reflection)."""
        a, b = tx_a.wi_real, tx_b.wi_real
        trans = self.lobes.transmission
        ratio = dr.abs(b.z) / dr.maximum(dr.abs(a.z), 1e-30) if trans else b.z / dr.maximum(a.z, 1e-30)
        kinds = [br[1] for br in extra]
        k_hid = kinds.index("hidden") if "hidden" in kinds else None
        p_hid_x = extra[k_hid][0] if k_hid is not None else mi.Float(0.0)
        on_flat = on_rad & negate(dw.on_tex)
        if k_hid is not None:
            on_flat |= picked == k_hid
        c_delta = tx_b.vis * tx_b.seen(tx_b.to_camera(a)) * ratio / dr.maximum(p_rad * dw.prob, 1e-30)
        c_delta = dr.select(dw.bounced, 0.0, c_delta)
        prob_delta = p_rad * dw.prob
        if trans:
            refracted = tx_b.vis * ratio * dr.abs(dr.dot(a, sp.wp)) / dr.maximum(dr.abs(dr.dot(b, sp.wp)), 1e-30)
            c_through = dr.select(a.z * b.z < 0, refracted, 0.0) / dr.maximum(p_rad * dw.prob, 1e-30)
            c_delta = dr.select(dw.through, c_through, c_delta)
        c_delta = dr.select(on_flat, (1.0 - tx_b.vis) / dr.maximum(p_hid_x + p_rad * dw.b_hid, 1e-30), c_delta)
        prob_delta = dr.select(on_flat, p_hid_x + p_rad * dw.b_hid, prob_delta)
        share_b = tx_b.retro_share()
        for k, (p, kind, frame, inc) in enumerate(extra):
            if kind in ("skim", "retro"):
                share = share_b if kind == "retro" else 1.0 - share_b
                c_k = tx_b.vis * share * (1.0 - tx_b.seen(tx_b.to_camera(inc))) * ratio / dr.maximum(p, 1e-30)
                if tx_b.sinks is not None:
                    c_k = dr.select(tx_b.sinks, 0.0, c_k)
            elif kind == "sink":
                eta_b = _crossing_eta(sp, sp.facet_si(sp.frame_p, b), picked == k)
                c_k = tx_b.vis * (1.0 - tx_b.seen(tx_b.to_camera(inc))) * ratio / dr.maximum(
                    p * dr.square(eta_b), 1e-30)
            elif kind == "fold":
                c_k = tx_b.vis * ratio * dr.abs(dr.dot(inc, sp.wp)) / dr.maximum(
                    dr.abs(dr.dot(b, sp.wp)) * p, 1e-30)
            else:
                continue
            c_delta = dr.select(picked == k, c_k, c_delta)
            prob_delta = dr.select(picked == k, p, prob_delta)
        return c_delta, prob_delta


class _Draw:
    def __init__(self, bs, w, active, delta, on_tex, bounced, prob, b_tex, b_hid, through=None):
        self.bs, self.w, self.active, self.delta = bs, w, active, delta
        self.on_tex, self.bounced, self.prob, self.b_tex, self.b_hid = on_tex, bounced, prob, b_tex, b_hid
        self.through = through          # transmitted through the facet (with transmission)


def _finish(bs, weight, active):
    active &= (bs.pdf > 0) & dr.all(dr.isfinite(weight))
    bs.wo = dr.select(active, bs.wo, mi.Vector3f(0.0, 0.0, 1.0))   # never a NaN direction
    bs.pdf = dr.select(active, bs.pdf, 0.0)
    return bs, dr.select(active, dr.maximum(weight, 0.0), 0.0)


def _select_sample(mask, a, b):
    bs = dr.zeros(mi.BSDFSample3f, dr.width(mask))
    for name in ("wo", "pdf", "eta", "sampled_type", "sampled_component"):
        setattr(bs, name, dr.select(mask, getattr(a, name), getattr(b, name)))
    return bs


def _select_frame(mask, a, b):
    return mi.Frame3f(dr.select(mask, a.s, b.s), dr.select(mask, a.t, b.t), dr.select(mask, a.n, b.n))


# -- The map's rms slope --------------------------------------------------------------------
