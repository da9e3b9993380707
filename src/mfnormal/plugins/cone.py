"""The pixel's footprint carried along a path as a ray cone (Akenine-Möller, Crassin, Boksansky,
Belcour, Panteleev and Wright, "Improved shader and texture level of detail using ray cones",
JCGT 10(1), 2021), shared by the integrators ``mfnormal_path`` and ``mfnormal_prb``.

A cone is two numbers per path: its width ``w`` (the diameter of its cross-section where the
path is) and its spread angle ``beta`` (the full angle at which the width grows, ``w + beta·t``
after a segment of length ``t``; either may be negative: a converging cone, whose footprint is
``|w|``). At each surface hit the cross-section, a disc of diameter ``|w|`` around the ray,
meets the tangent plane in an ellipse; its two axes, mapped to uv through ``dp_du``/``dp_dv``
(a 2 × 2 least-squares solve, as Mitsuba's ``compute_uv_partials``), are what the BSDF receives
in ``si.duv_dx`` and ``si.duv_dy``. Each axis is the uv step across the whole footprint, as a
ray differential's is across one pixel.

The rules, each a function below:

- the camera (:func:`camera_cone`): ``beta`` the angle between a ray and its neighbours of the
  next pixel (``d_x``, ``d_y``, averaged), ``w`` their origins' distance across the ray (0 for a
  pinhole or a thin lens, the pixel's size for an orthographic camera), from the ray
  differentials the sensor gives;
- a delta reflection (:func:`bounce`): ``beta + 2Δ``, where Δ is the signed angle by which the
  surface's normal turns across the footprint (:func:`normal_turn`, from ``si.dn_du``,
  ``si.dn_dv``; > 0 on a surface convex toward the ray: a convex mirror spreads the cone, a
  concave one focuses it; 0 on a flat surface);
- a delta transmission: ``beta/η + (1 - 1/η)·Δ`` (refraction at normal incidence);
- a null interaction (a pass-through): unchanged;
- a non-delta sample (glossy, diffuse): the cone whose solid angle is 1/pdf of the sampled
  direction, the share of directions the sample stands for (a Lambertian sample leaving along
  the normal: 120°; a narrow glossy lobe: a narrow cone), or the reflected cone if wider;
- ``|beta|`` ≤ π (a hemisphere): a cone never spreads wider.

The footprint is detached: it says where the BSDF is looked at, not what is differentiated.
"""

from __future__ import annotations

import math

import drjit as dr
import mitsuba as mi

BETA_MAX = math.pi      # the widest spread: a hemisphere's full angle
COS_MIN = 1e-2          # the footprint's stretch along a grazing ray stops at 100× (89.4°)
DET_MIN = 1e-6          # dp_du and dp_dv at less than 0.06° from parallel: no uv footprint

#: The interaction's fields the cone needs: the integrators' (``All``) and the shading normal's
#: derivatives ``dn_du``, ``dn_dv`` (:func:`normal_turn`).
RAY_FLAGS = mi.RayFlags.All | mi.RayFlags.dNSdUV


def camera_cone(ray, scale: float = 1.0):
    """The cone (w, beta) of a camera ray from its differentials (``scale``: a factor on both,
    as ``RayDifferential3f.scale_differential``); (0, 0) for a ray without differentials."""
    if not (isinstance(ray, mi.RayDifferential3f) and ray.has_differentials):
        return mi.Float(0.0), mi.Float(0.0)
    d = dr.detach(ray.d)
    beta, w = mi.Float(0.0), mi.Float(0.0)
    for o_n, d_n in ((dr.detach(ray.o_x), dr.detach(ray.d_x)), (dr.detach(ray.o_y), dr.detach(ray.d_y))):
        d_n = dr.normalize(d_n)
        # The angle between the two directions (atan2 form: exact near 0)
        beta += 2.0 * dr.atan2(dr.norm(d - d_n), dr.norm(d + d_n))
        offset = o_n - dr.detach(ray.o)
        w += dr.norm(offset - dr.dot(offset, d) * d)
    return w * (0.5 * scale), beta * (0.5 * scale)


def grown(w, beta, t):
    """The width after a segment of length ``t``."""
    return dr.fma(beta, t, w)


def axes(n, d, w):
    """The two axes of the cone's cross-section (width ``|w|``, direction ``d``) on the plane of
    normal ``n``: across the plane of incidence (length ``|w|``), then along it (``|w|/|cos θ|``,
    at most 1/``COS_MIN`` times ``|w|``). World vectors in the plane."""
    cos = dr.dot(d, n)
    across = dr.cross(n, d)
    sin = dr.norm(across)
    # At normal incidence the ellipse is a circle: any axis in the plane
    across = dr.select(sin > 1e-6, across / sin, mi.coordinate_system(n)[0])
    along = dr.cross(across, n)
    width = dr.abs(w)
    return across * width, along * (width / dr.maximum(dr.abs(cos), COS_MIN))


def to_uv(dp_du, dp_dv, a):
    """The uv step of the world vector ``a`` in the tangent plane: the least-squares solution of
    ``dp_du·du + dp_dv·dv = a``; 0 where dp_du and dp_dv are (nearly) parallel or zero (a
    degenerate parametrisation, a sphere's pole) and never NaN."""
    a00, a01, a11 = dr.dot(dp_du, dp_du), dr.dot(dp_du, dp_dv), dr.dot(dp_dv, dp_dv)
    det = dr.fma(a00, a11, -a01 * a01)
    regular = dr.isfinite(det) & (det > DET_MIN * a00 * a11) & (det > 0.0)
    inv_det = dr.select(regular, dr.rcp(det), 0.0)
    b0, b1 = dr.dot(dp_du, a), dr.dot(dp_dv, a)
    duv = mi.Vector2f(dr.fma(a11, b0, -a01 * b1), dr.fma(a00, b1, -a01 * b0)) * inv_det
    return dr.select(dr.isfinite(duv.x) & dr.isfinite(duv.y), duv, 0.0)


def with_footprint(si, d, w, active=True):
    """A copy of ``si`` whose ``duv_dx``, ``duv_dy`` are the cone's footprint in uv (the axes of
    :func:`axes` across and along the plane of incidence, detached; 0 where not ``active``, not
    valid or not finite). ``d``: the ray's direction, ``w``: the width at ``si``."""
    here = dr.detach(si)
    valid = mi.Bool(active) & here.is_valid() & dr.isfinite(w)
    across, along = axes(here.n, dr.detach(d), dr.detach(w))
    out = mi.SurfaceInteraction3f(si)
    out.duv_dx = dr.select(valid, to_uv(here.dp_du, here.dp_dv, across), 0.0)
    out.duv_dy = dr.select(valid, to_uv(here.dp_du, here.dp_dv, along), 0.0)
    return out


def at_hit(si, ray, w, beta):
    """At the hit ``si`` of ``ray`` (the cone (w, beta) at the ray's origin): ``si`` with its
    footprint (:func:`with_footprint`) and the cone's width there (``w`` where ``si`` is not
    valid). The segment's length is the distance from the origin to ``si.p``."""
    t = dr.norm(dr.detach(si.p) - dr.detach(ray.o))
    w = dr.select(si.is_valid(), grown(w, beta, t), w)
    return with_footprint(si, ray.d, w), w


def normal_turn(si):
    """The signed angle Δ by which the shading normal turns across ``si``'s footprint (from
    ``si.dn_du``, ``si.dn_dv``: the interaction needs ``RayFlags.dNSdUV``), so that a delta
    reflection adds 2Δ to the spread. Along the plane of incidence a normal turn κ·|a| over the
    footprint's axis ``a`` turns the reflected ray by 2κ|a|, across it by 2κ|a|·cos θ: the larger
    of the two. Positive where the surface is convex toward the arriving ray."""
    here = dr.detach(si)
    cos = dr.abs(here.wi.z)
    turns = []
    for duv, factor in ((here.duv_dx, cos), (here.duv_dy, 1.0)):
        a = here.dp_du * duv.x + here.dp_dv * duv.y
        dn = here.dn_du * duv.x + here.dn_dv * duv.y
        length2 = dr.squared_norm(a)
        # κ·|a| = <dn, a>/|a|: the normal's turn along a, in radians
        turns.append(dr.select(length2 > 0.0, dr.dot(dn, a) * dr.rsqrt(length2), 0.0) * factor)
    turn = dr.select(dr.abs(turns[0]) > dr.abs(turns[1]), turns[0], turns[1])
    turn = dr.mulsign(turn, here.wi.z)      # seen from behind the normal: convex becomes concave
    return dr.select(dr.isfinite(turn), turn, 0.0)


def lobe_spread(pdf):
    """The full angle of the cone whose solid angle is 1/``pdf`` (capped at a hemisphere's, π;
    π for a zero or non-finite pdf)."""
    cos_half = 1.0 - dr.rcp(2.0 * dr.pi * pdf)
    spread = 2.0 * dr.acos(dr.clip(cos_half, -1.0, 1.0))
    return dr.select(dr.isfinite(pdf) & (pdf > 0.0), dr.minimum(spread, BETA_MAX), BETA_MAX)


def bounce(beta, si, bs):
    """The spread after the BSDF sample ``bs`` at ``si`` (module docstring: the rules), from the
    spread ``beta`` that arrived (``si``: with its footprint, :func:`at_hit`)."""
    bs = dr.detach(bs)
    turn = normal_turn(si)
    delta = (mi.has_flag(bs.sampled_type, mi.BSDFFlags.DeltaReflection)
             | mi.has_flag(bs.sampled_type, mi.BSDFFlags.DeltaTransmission))
    null = mi.has_flag(bs.sampled_type, mi.BSDFFlags.Null)
    reflected = dr.detach(si.wi.z) * bs.wo.z > 0.0
    eta = dr.select(dr.isfinite(bs.eta) & (bs.eta > 0.0), bs.eta, 1.0)
    mirror = beta + 2.0 * turn
    refracted = beta / eta + (1.0 - dr.rcp(eta)) * turn
    specular = dr.select(reflected, mirror, refracted)
    glossy = dr.maximum(lobe_spread(bs.pdf), dr.abs(mirror))
    out = dr.select(null, beta, dr.select(delta, specular, glossy))
    return dr.clip(dr.select(dr.isfinite(out), out, BETA_MAX), -BETA_MAX, BETA_MAX)
