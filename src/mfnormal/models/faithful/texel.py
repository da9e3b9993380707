"""A texel among its neighbours, seen from ω_i: the texel statistics of the default model
(docs/faithful.md §1, §1.1).

V(ω_i), the share of the texel's footprint that a ray from ω_i hits; S(ω|ω_i), the chance that a
visible point of it sees ω past its neighbours (height-correlated Smith); B(ω_i), the blocked
share of a Lambertian facet's light; and where the light the neighbours block leaves (the bounce
M and its preimages). The map's slopes and tables they read are :mod:`.tables`'.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mfnormal.surface.microsurface import negate
from mfnormal.models.neighbourhood import _held, smith_lambda
from mfnormal.surface.shading import to_tangent_frame

#: With local statistics, the neighbourhood scale k below which a texel's blocked glossy light is
#: less and less retro-reflected (Texel.retro_share): 0 for a plane (k = 0), which has no cavity.
RETRO_K = 0.5
#: With local statistics, the neighbourhood's rms slope (k times the map's) below which a texel's
#: blocked glossy light is less and less retro-reflected (Texel.retro_share): tan 26.6°; a cavity
#: sends light back only if its walls are steep (how it was set: docs/faithful.md §8).
RETRO_SLOPE = 0.5
#: With local statistics, the texel's projected area R is taken on its neighbourhood's mean plane,
#: whose cosines with ω_i and ω_p count at least this share of their cosines with ω_g: R stays
#: finite, and V continuous, where ω_i skims or passes under that plane while it sees the facet.
MEAN_PLANE_MIN = 0.5
#: With local statistics, the texel's projected area R is taken on a plane between its own and its
#: neighbourhood's mean plane, ω_t ∝ ω_p + t·(ω_m − ω_p), t = min(1, k / OWN_PLANE_K): a texel in a
#: smooth neighbourhood (k → 0) is the surface there and is foreshortened only as that surface is;
#: one among neighbours as rough as the map's (k ≥ 2) is a facet on their mean plane (how it was
#: set: docs/faithful.md §8).
OWN_PLANE_K = 2.0


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
        # (The map's statistics spread over the query's lanes where they carry derivatives.)
        model = model.at_width(dr.width(wi))
        self.sp, self.model, self.wi_real = sp, model, wi
        self.flip = None              # where the camera is below the macro surface (None: never)
        wp = sp.wp
        if model.components.transmission:
            self.flip = wi.z < 0
            wi = self.to_camera(wi)
            wp = self._camera_side(wp)
        self.wi, self.wp = wi, wp
        self.fill_rho = None          # lobes.Fill.rho's, once computed
        # The share of the neighbours hiding the texel that are the map's walls, and their normal
        # (MapStatistics.walls; lobes.Hidden).
        self.wall_share, self.wall_n = model.walls(sp)
        # With local statistics: the neighbourhood's slopes are the map's times k, and its mean
        # normal ω_m is the macro surface the texel's projected area is measured on (None: the
        # map's slopes, about ω_g).
        self.k, wm = model.local_stats(sp)
        # The share of the neighbourhood's relief that is the map's walls (None without local
        # statistics: MapStatistics.neighbourhood_walls).
        self.local_walls = None if self.k is None else model.neighbourhood_walls(self.k)
        self.lam_i = self.smith_lambda(wi)
        g1_i = dr.rcp(1.0 + self.lam_i)
        if wm is None:
            proj = dr.maximum(dr.dot(wi, wp), 0.0) / (wp.z * dr.maximum(wi.z, 1e-30))
            self.vis = dr.minimum(1.0, proj * g1_i)
        else:
            # (R on a plane between the texel's own and its neighbourhood's mean plane: OWN_PLANE_K;
            # on the mean plane where the neighbourhood's relief is walls: upright, they take no
            # footprint from ω_g, so there a texel among them is a facet on their mean plane.)
            t = dr.lerp(dr.minimum(self.k * (1.0 / OWN_PLANE_K), 1.0), 1.0, self.local_walls)
            if model.flat:
                # (A flat map, e.g. at strength 0: ω_t = ω_p = ω_m = ω_g for every t, so nothing
                # flows through t; k still carries the texels' derivatives there, and its path
                # through the nudged normals of strength 0 would not cancel exactly.)
                t = dr.detach(t)
            wt = dr.normalize(dr.fma(t, self._camera_side(wm) - wp, wp))
            self.vis = visible_share(wi, wp, wt, g1_i)
        # With transmission, seen from above: the reflected light the neighbours block meets their
        # interface and sinks below it (transmission.Sink) instead of bouncing back up (None: never).
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

    def wall_mirror(self, w):
        """M_wall(w): ``w`` (either frame) mirrored in the plane of the map's walls, which stand
        upright on the macro surface: z is kept, so M_wall commutes with :meth:`to_camera` and with the
        macro surface's own reflection and refraction."""
        return w - 2.0 * dr.dot(w, self.wall_n) * self.wall_n

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
        # Walls are steep whatever the facets' slope: the share of the relief that is walls sends
        # its blocked light back at any k.
        rms = self.k * self.model.rms_slope()
        fade = dr.minimum(self.k * (1.0 / RETRO_K), 1.0) * dr.minimum(rms * (1.0 / RETRO_SLOPE), 1.0)
        return blocked * dr.lerp(fade, 1.0, self.local_walls)

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


def visible_share(wi, wp, wm, g1):
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

