"""Tangent-space normal maps (``normalmap``) as a source of the facet normal ω_p.

A texel's RGB decodes to n = 2·rgb − 1 (``normalmap_convention="directx"`` inverts green), its
x and y scaled by ``strength``, normalised and clamped to cosθ_p ≥ ``COS_P_MIN``
(:func:`~mfnormal.surface.microsurface.decode_normal`), in the base shading frame or the mesh's
vertex tangent frame (:mod:`mfnormal.normals.tangents`).

Two things beyond decoding live here. The map's uv transform (a bitmap's ``to_uv``) is applied
from kernel inputs (:meth:`NormalMap.map_rgb`), so plugins whose maps differ only in their
transforms trace the same code and Dr.Jit compiles the model once for all of them (docs/model.md
§4.9). And derivatives at a flat normal, where the models are not differentiable, are taken
from nudged normals (``nudge``, docs/model.md §9).
"""

from __future__ import annotations

import math
import re

import drjit as dr
import mitsuba as mi
import numpy as np

from mfnormal.surface.microsurface import SIN_P_EPS, decode_normal, spread
from mfnormal.models.neighbourhood import kernel_array
from mfnormal.surface.shading import from_tangent_frame, tangent_rotation
from mfnormal.normals.pyramid import (CLASS_BOUNDS, SlopePyramid, class_moments, class_point, footprint_texels,
                                     slope_moments, texel_class)
from mfnormal.normals.strength import fail
from mfnormal.normals.tangents import VertexTangents
from mfnormal.normals.uv import check_uv_transforms, finite_uv

CONVENTIONS = ("opengl", "directx")
# Derivatives at a flat normal (docs/model.md §9): the tilt of the nudged normals whose
# one-sided derivatives are averaged, and the strength at which strength = 0 is differentiated.
FLAT_NUDGE = 1e-3
STRENGTH_NUDGE = 1e-3
NUDGES = ((0, 1.0), (0, -1.0), (1, 1.0), (1, -1.0))   # (axis, sign): ±x, ±y of the map's frame
# Local statistics (the faithful model's ``neighbourhood``) are measured on the map's texels up to
# this resolution (a larger map is sampled at its texel centres on this grid).
LOCAL_RES = 1024
# A filtered lookup (``filter="lean"``) stands for a footprint's texels of a class by a Gaussian of
# their slopes (mean μ, variance v = var(s_x) + var(s_y)) only where its mass beyond the class's
# bound S (pyramid.CLASS_BOUNDS) is at most 1 %: v·ln(100) ≤ (S − |μ|)². Their slopes lie within
# S; a wider Gaussian would send light where none of them does (a sharp nested lobe's off-specular
# directions: 300-6000× the texels' mean without it, measured on a real asset's map).
FILTER_TAIL = math.log(100.0)


def channels_message(texture, what: str = "") -> str | None:
    """Why a bitmap ``texture`` cannot be a tangent-space normal map (its channel count is not 3;
    ``what``: how to name it, default its file name), or None."""
    params = mi.traverse(texture)
    if "data" not in params.keys():
        return None                # not a bitmap (a procedural texture: its eval_3 is checked where used)
    shape = params["data"].shape
    channels = shape[-1] if len(shape) == 3 else 1
    if channels == 3:
        return None
    if not what:
        name = re.search(r'name = "([^"]*)"', str(texture))
        what = f"'{name.group(1)}'" if name and name.group(1) else "(a bitmap)"
    return channel_count_message(what, channels)


#: Files whose values Mitsuba's ``bitmap`` reads as linear whatever ``raw`` says.
LINEAR_FORMATS = (".exr", ".hdr", ".rgbe", ".pfm")


#: Mitsuba's luminance weights: a 3-channel bitmap texture's ``mean`` is that of its lookups' luminance.
LUMINANCE = (0.212671, 0.715160, 0.072169)


def srgb_message(texture) -> str | None:
    """Why a bitmap ``texture`` read as sRGB colour (``raw`` false, a file Mitsuba decodes from
    sRGB: PNG, JPEG, ...) cannot be a normal map, or None. The sRGB curve bends the stored vectors:
    a flat texel (0.5, 0.5, 1) decodes to (0.21, 0.21, 1), 39° tilted. A bitmap given in Python
    (no file name) is decoded only where it is marked sRGB (8-bit ones from numpy are; float ones
    are linear): seen as lookups whose mean differs from the stored texels'."""
    text = str(texture)
    name = re.search(r'name = "([^"]*)"', text)
    if "raw = 0" not in text or name is None:
        return None
    if name.group(1):
        if name.group(1).lower().endswith(LINEAR_FORMATS):
            return None
        what = f"'{name.group(1)}'"
    elif _lookups_decode_srgb(texture, text):
        what = "(a Bitmap marked sRGB)"
    else:
        return None
    return (f"normal map {what} is read as sRGB colour (raw is false), which bends its "
            "vectors (a flat texel decodes 39° tilted): load it with raw=True "
            '(XML: <boolean name="raw" value="true"/>)')


def _lookups_decode_srgb(texture, text: str) -> bool:
    """Whether the lookups of a 3-channel bitmap ``texture`` (``text``: its description) are not
    its stored texels: Mitsuba's mean of the lookups' luminance against the texels' own."""
    mean = re.search(r"mean = \[?([^,\]\s]+)", text)
    params = mi.traverse(texture)
    if mean is None or "data" not in params.keys():
        return False
    texels = np.asarray(params["data"])
    if texels.ndim != 3 or texels.shape[-1] != 3:
        return False
    scale = np.iinfo(texels.dtype).max if np.issubdtype(texels.dtype, np.integer) else 1.0
    stored = float(np.mean(texels.reshape(-1, 3) @ np.array(LUMINANCE))) / scale
    return abs(float(mean.group(1)) - stored) > 1e-4 * max(1.0, abs(stored))


def channel_count_message(what: str, channels: int) -> str:
    """The one-line refusal of a normal map ``what`` that has ``channels`` channels, not 3."""
    return (f"normal map {what} has {channels} channel{'s' if channels != 1 else ''}; "
            "a tangent-space normal map needs 3 (RGB)")


class NormalMap:
    """ω_p from a tangent-space normal map texture, with ``strength`` (a
    :class:`~mfnormal.normals.Strength`) and the channel convention."""

    def __init__(self, texture, strength, directx: bool, tangents: VertexTangents | None):
        self.texture, self.strength, self.directx, self.tangents = texture, strength, directx, tangents
        self._pyramid = {}          # the slope-moment pyramids, by ``classes`` (:meth:`pyramid`)
        self.filtered = False       # ``filter="lean"``: ω_p is the footprint's mean facet (:meth:`footprint`)
        self._uv_checked = check_uv_transforms(texture, "normalmap")
        message = channels_message(texture) or srgb_message(texture)
        if message:
            fail(message)
        self.hoist_uv_transform()

    def facet_normal(self, si, active, nudge=None):
        """(ω_p in si.sh_frame, the map frame's tangent_rotation or None, whether ω_p carries
        derivatives).

        ``nudge`` (derivatives at a flat normal): ``"strength"`` (``"strength2"``): ω_p at
        strength + STRENGTH_NUDGE (+ twice it), the texel detached; ``(axis, sign)``: ω_p tilted
        by FLAT_NUDGE along ±x or ±y of the map's frame, the other axis detached.

        ``filtered``: ω_p is the facet of the footprint's mean slope (:meth:`footprint`), except
        under the strength nudges (the texel's: the pyramid holds the slopes at one strength)."""
        rgb = self.map_rgb(si, active)
        strength = spread(self.strength.value, dr.width(rgb))
        if isinstance(nudge, str):          # "strength", "strength2": at STRENGTH_NUDGE, twice it
            rgb, strength = dr.detach(rgb), strength + STRENGTH_NUDGE * (2.0 if nudge == "strength2" else 1.0)
        wp = decode_normal(rgb, strength, self.directx)
        if self.filtered and not isinstance(nudge, str):
            wp = self.footprint(si, active, wp)[0]
        attached = dr.grad_enabled(wp)
        if nudge is not None and not isinstance(nudge, str):
            axis, sign = nudge
            x = wp.x + sign * FLAT_NUDGE if axis == 0 else dr.detach(wp.x)
            y = wp.y + sign * FLAT_NUDGE if axis == 1 else dr.detach(wp.y)
            wp = dr.normalize(mi.Vector3f(x, y, wp.z))
        if self.tangents is None:
            return wp, None, attached
        tangent, sign = self.tangents.lookup(si, active)
        if tangent is None:
            return wp, None, attached      # scalar variants: a shape without tangents
        # (T and its sign are two attributes: Mitsuba 3.9.1's eval_attribute_x returns zeros.)
        return (from_tangent_frame(wp, si.sh_frame, tangent, sign),
                tangent_rotation(si.sh_frame, tangent, sign), attached)

    def hoist_uv_transform(self):
        """The map's uv transform (a bitmap's ``to_uv``) as kernel inputs, for :meth:`map_rgb`.

        Mitsuba's bitmap bakes its ``to_uv`` into the traced code as constants, so two plugins
        whose maps differ only in their transforms (the demo's sphere and its tiled floor) traced
        different code, and Dr.Jit compiled the whole model twice into a kernel: it merges the
        callables of a call's instances only where their code is the same (the demo with GGX 0.05,
        non-separable walk: 11601 operations and 0.54 s of LLVM time, against 7179 and 0.35 s with
        one transform for both). Identity, no ``to_uv`` or a scalar variant: None (``eval_3`` as it is)."""
        self.uv, self._uv_params, self._uv_matrix = None, None, None
        if not dr.is_jit_v(mi.Float):
            return
        params = mi.traverse(self.texture)
        if "to_uv" not in params.keys():
            return
        m = np.array(params["to_uv"].matrix, dtype=np.float64)
        if m.shape != (3, 3) or np.array_equal(m, np.eye(3)):
            return
        self.uv = [mi.Float(float(m[i, j])) for i in range(2) for j in range(3)]
        dr.make_opaque(*self.uv)
        self._uv_params, self._uv_matrix = params, m

    def map_rgb(self, si, active=True):
        """The map's RGB at ``si.uv``: ``eval_3``, with a hoisted uv transform
        (:meth:`hoist_uv_transform`) applied here from kernel inputs and the texture traced with
        the identity transform (restored at once; nothing is left changed). The same values bit for
        bit: the same fused multiply-adds as Mitsuba's ``Transform::transform_affine`` (the
        translation first, then the x and the y column). A texture whose ``to_uv`` changed since
        (set on the texture itself, e.g. one that two plugins share, where this plugin was not
        told) is evaluated as it is."""
        si = finite_uv(si)
        if self.uv is None:
            return self.texture.eval_3(si, active)
        current = self._uv_params["to_uv"]
        current = type(current)(current)            # a copy to restore: the entry aliases the texture's
        if not np.array_equal(np.array(current.matrix, dtype=np.float64), self._uv_matrix):
            return self.texture.eval_3(si, active)
        si_uv = mi.SurfaceInteraction3f(si)
        si_uv.uv = _affine_uv(self.uv, si.uv)
        si_uv = finite_uv(si_uv)                    # a transform that overflows
        self._uv_params["to_uv"] = type(current)()
        try:
            return self.texture.eval_3(si_uv, active)
        finally:
            self._uv_params["to_uv"] = current

    def flat_texels(self) -> bool:
        """Whether the map may decode to the flat normal somewhere (then AD takes the flat
        normal's derivatives from nudged normals, docs/model.md §9): a bitmap is checked texel
        by texel, any other texture is assumed to."""
        params = mi.traverse(self.texture)
        if "data" not in params.keys():
            return True
        data = np.array(params["data"], dtype=np.float64)
        if data.ndim != 3 or data.shape[-1] < 3:
            return True
        n = 2.0 * data[..., :3] - 1.0
        with np.errstate(invalid="ignore"):
            xy = np.hypot(n[..., 0], n[..., 1]) * min(self.strength.ok)
            flat = ~(xy > 2.0 * SIN_P_EPS * np.abs(n[..., 2]))    # NaN texels included
        return bool(flat.any())

    def _grid(self, res):
        """A res × res grid of texel centres on the unit square (numpy u, v)."""
        u = (np.arange(res) + 0.5) / res
        return np.meshgrid(u, u, indexing="ij")

    def _sampled(self, max_res=256):
        """(res, the map's RGB, its decoded unit normals) on a res × res grid of texel centres over
        the unit square (u major), res the map's resolution up to ``max_res`` (32 in scalar variants,
        where the normals are a numpy (res², 3) array and the RGB None)."""
        res = max_res if dr.is_jit_v(mi.Float) else 32
        params = mi.traverse(self.texture)
        if "data" in params.keys():
            shape = params["data"].shape
            res = min(res, max(shape[0], shape[1]))
        uu, vv = self._grid(res)
        if not dr.is_jit_v(mi.Float):
            return res, None, np.array([self._scalar_normal(x, y) for x, y in zip(uu.ravel(), vv.ravel())])
        si = dr.zeros(mi.SurfaceInteraction3f, res * res)
        # (Kernel inputs: aligned, so that the kernels that read them, AD's too, compile once.)
        si.uv = mi.Point2f(*(kernel_array(mi.Float, x.astype(np.float32)) for x in (uu, vv)))
        rgb = self.texture.eval_3(si)
        return res, rgb, decode_normal(rgb, self.strength.value, self.directx)

    def slopes(self, attached=False):
        """(σ1, σ2, φ_e), the map's principal rms slopes about the macro normal and their axis,
        from its decoded texels (neighbourhood.principal_slopes); and, where the map or ``strength``
        carry derivatives and ``attached``, the same as Dr.Jit values that carry them
        (neighbourhood.attached_slopes), else None."""
        from mfnormal.models.neighbourhood import attached_slopes, principal_slopes
        _, rgb, wp = self._sampled()
        if rgb is None:
            return principal_slopes(wp), None
        slopes = principal_slopes(np.stack([np.array(wp.x), np.array(wp.y), np.array(wp.z)], -1))
        if not (attached and dr.grad_enabled(wp)):
            return slopes, None
        if max(self.strength.ok) > 0:
            return slopes, attached_slopes(wp)
        return slopes, attached_slopes(decode_normal(rgb, 1.0, self.directx), self.strength.value)

    def walls(self, attached=False):
        """((ψ_w, w_x, w_y), the same as Dr.Jit values that carry the map's and ``strength``'s
        derivatives or None): the share of the map's relief that is walls and their mean slope in
        its tangent frame (neighbourhood.walls), from its decoded texels as :meth:`slopes` reads them."""
        from mfnormal.models import neighbourhood as nb
        _, rgb, wp = self._sampled()
        normals = wp if rgb is None else np.stack([np.array(wp.x), np.array(wp.y), np.array(wp.z)], -1)
        values = nb.walls(*nb.winsorised_slopes(normals))
        if rgb is None or not (attached and dr.grad_enabled(wp)):
            return values, None
        if max(self.strength.ok) > 0:
            return values, nb.attached_walls(*nb.attached_winsorised(wp))
        # (At strength 0 the slopes are strength × those at strength 1, none capped: w is strength ×
        # the walls' slope at strength 1, with its derivative there. A map without slopes has no
        # walls whatever its texels: ψ_w is 0 there, with no derivative.)
        unit = decode_normal(rgb, 1.0, self.directx)
        _, w1x, w1y = nb.attached_walls(*nb.attached_winsorised(unit, capped=False))
        return values, (mi.Float(0.0), w1x * self.strength.value, w1y * self.strength.value)

    def local(self, width: float, attached=False):
        """Local statistics (docs/faithful.md §5): ((k, m_x, m_y, k_fine), the same as Dr.Jit values
        that carry the map's and ``strength``'s derivatives or None, res, uv_of) for a Gaussian
        window ``width`` texels of the map wide (two standard deviations): the neighbourhood's scale
        and mean slope on the grid of :meth:`_sampled` (neighbourhood.local_field), its scale in a
        window FINE_WINDOW times as wide (what a mild neighbourhood's k is read from:
        faithful.Model.local_stats), and the function that gives the map's uv at a surface
        interaction (:meth:`map_uv`)."""
        from mfnormal.models import neighbourhood as nb
        res, rgb, wp = self._sampled(LOCAL_RES)
        params = mi.traverse(self.texture)
        texels = max(params["data"].shape[:2]) if "data" in params.keys() else res
        cells = width * res / texels
        taps = nb.window_taps(cells, res)
        fine = nb.window_taps(min(max(nb.FINE_WINDOW * cells, nb.FINE_MIN_CELLS), cells), res)

        def field(wp, attached):
            normals = wp if rgb is None else np.stack([np.array(wp.x), np.array(wp.y), np.array(wp.z)], -1)
            s1, s2, _ = nb.principal_slopes(normals)
            sx, sy = nb.winsorised_slopes(normals)
            total, wall = s1 * s1 + s2 * s2, nb.walls(sx, sy)[1:]
            out = nb.local_field(sx, sy, res, taps, total, wall) + nb.local_field(sx, sy, res, fine, total, wall)[:1]
            if not (attached and rgb is not None and dr.grad_enabled(wp)):
                return out, None
            a1, a2, _ = nb.attached_slopes(wp)
            ax, ay = nb.attached_winsorised(wp)
            aw = nb.attached_walls(ax, ay)[1:]
            return out, (nb.attached_field(ax, ay, res, taps, a1, a2, aw) +
                         nb.attached_field(ax, ay, res, fine, a1, a2, aw)[:1])
        values, values_ad = field(wp, attached)
        if rgb is not None and max(self.strength.ok) == 0:
            # k is the ratio of two variances that both scale with strength²: at strength 0 (no
            # slopes, no mean slope), k of the map at strength 1, which is its limit there.
            k1, k1_ad = field(decode_normal(rgb, 1.0, self.directx), attached)
            values = (k1[0],) + tuple(values[1:3]) + (k1[3],)
            if values_ad is not None:
                # (k1 carries the texels' derivatives, if they have any; strength's is 0.)
                k1_ad = [kernel_array(mi.Float, np.asarray(k1[i], np.float32)) if k1_ad is None else k1_ad[i] for i in (0, 3)]
                values_ad = (k1_ad[0],) + tuple(values_ad[1:3]) + (k1_ad[1],)
        return values, values_ad, res, self.map_uv

    def map_uv(self, si):
        """The uv at which :meth:`map_rgb` reads the map (its uv transform applied)."""
        si = finite_uv(si)
        if self.uv is not None:
            return _affine_uv(self.uv, si.uv)
        affine = self._uv_affine()
        return si.uv if affine is None else _affine_uv(affine, si.uv)

    def _uv_affine(self):
        """The map's uv transform (a bitmap's ``to_uv``) as (m00, m01, m02, m10, m11, m12), None
        where it has none or it is the identity."""
        params = mi.traverse(self.texture)
        if "to_uv" not in params.keys():
            return None
        m = np.array(params["to_uv"].matrix, dtype=np.float64)
        if m.shape != (3, 3) or np.array_equal(m, np.eye(3)):
            return None
        return tuple(float(m[i, j]) for i in range(2) for j in range(3))

    def _scalar_normal(self, x, y):
        s1 = mi.SurfaceInteraction3f()
        s1.uv = mi.Point2f(float(x), float(y))
        n = decode_normal(self.texture.eval_3(s1), self.strength.value, self.directx)
        return [n.x, n.y, n.z]

    def pyramid(self, classes: bool = False) -> SlopePyramid | None:
        """The map's slope-moment pyramid (:class:`~mfnormal.normals.pyramid.SlopePyramid`; None for
        a texture that is not a bitmap): built at the first call, from the texels as they are then
        (their derivatives included), and kept across renders until the map or ``strength`` changes.
        ``classes``: the pyramid of the texel classes' moments
        (:func:`~mfnormal.normals.pyramid.class_moments`), which a filtered lookup reads."""
        if self._pyramid.get(classes) is None and dr.is_jit_v(mi.Float):
            params = mi.traverse(self.texture)
            if "data" in params.keys() and len(params["data"].shape) == 3:
                self._pyramid[classes] = (
                    SlopePyramid(params["data"], self.strength.value, self.directx, class_moments, len(CLASS_BOUNDS))
                    if classes else SlopePyramid(params["data"], self.strength.value, self.directx))
        return self._pyramid.get(classes)

    def footprint(self, si, active=True, texel=None):
        """(ω, v): what a filtered lookup shades at ``si`` (``filter="lean"``), in the map's frame.

        Where the footprint that ``si`` carries is wider than a texel and the texel at ``si.uv``
        is flat or mild (its class, :data:`~mfnormal.normals.pyramid.CLASS_BOUNDS`), the footprint's
        texels of that class as one facet: ω the normal of their mean slope, v = var(s_x) +
        var(s_y) their slopes' spread (the trace of their covariance), where the Gaussian of those
        keeps within the class's bound (FILTER_TAIL). A steep texel is its own facet, as without a
        filter, so that a footprint's walls are not averaged into its plains: a sample shades its
        class's facet or its steep texel as the texel it lands on is one or the other, and the
        pixel converges to that mixture. Elsewhere (at most a texel wide, no footprint, no pyramid,
        a class too spread) the texel's own normal and 0. ``texel``: its decoded normal, if the
        caller has it."""
        if texel is None:
            rgb = self.map_rgb(si, active)
            texel = decode_normal(rgb, spread(self.strength.value, dr.width(rgb)), self.directx)
        found = self._footprint_moments(si, active, texel, classes=True)
        if found is None:
            return texel, mi.Float(0.0)
        (m, sx, sy, sxx, syy), width = found
        c = texel_class(slope_moments(texel))
        bound = dr.select(c == 0, CLASS_BOUNDS[0], CLASS_BOUNDS[1])
        share = dr.maximum(m, 1e-6)
        mx, my = sx / share, sy / share
        v = dr.maximum(sxx / share - mx * mx, 0.0) + dr.maximum(syy / share - my * my, 0.0)
        # (The pyramid reads the point where the width is not finite.)
        wide = dr.isfinite(width) & (width > 1.0) & (c < 2) & (m > 1e-6)
        room = dr.maximum(bound - dr.sqrt(mx * mx + my * my), 0.0)
        wide &= v * FILTER_TAIL <= room * room
        mean = dr.normalize(mi.Vector3f(-mx, -my, 1.0))
        return (mi.Vector3f(*(dr.select(wide, a, b) for a, b in zip(mean, texel))), dr.select(wide, v, 0.0))

    def footprint_moments(self, si, active=True):
        """The slope moments (:data:`~mfnormal.normals.pyramid.MOMENTS`) of the map over the footprint
        that ``si`` carries (``si.duv_dx``, ``si.duv_dy``: its axes in uv; none: the texel at
        ``si.uv``), from the pyramid; None without one. The map's uv transform applies to the
        footprint's axes as to the point."""
        if self.pyramid() is None:
            return None
        rgb = self.map_rgb(si, active)
        return self._footprint_moments(si, active, decode_normal(rgb, spread(self.strength.value, dr.width(rgb)),
                                                                 self.directx))[0]

    def _footprint_moments(self, si, active, texel, classes=False):
        """(the moments of :meth:`footprint_moments`, or with ``classes`` the classes', and the
        footprint's width in texels), the texel's decoded normal ``texel`` standing for level 0;
        None without a pyramid."""
        pyramid = self.pyramid(classes)
        if pyramid is None:
            return None
        # (With classes, the group of the texel's own class; a steep texel's is not read.)
        group = dr.minimum(texel_class(slope_moments(texel)), len(CLASS_BOUNDS) - 1) if classes else None
        point = class_point(texel) if classes else slope_moments(texel)
        axes = mi.SurfaceInteraction3f(si)
        affine = self._uv_affine()
        if affine is not None:
            m00, m01, _, m10, m11, _ = affine

            def linear(d):
                return mi.Vector2f(m00 * d.x + m01 * d.y, m10 * d.x + m11 * d.y)
            axes.duv_dx, axes.duv_dy = linear(si.duv_dx), linear(si.duv_dy)
        width = footprint_texels(axes, pyramid.width, pyramid.height)
        return pyramid.lookup(self.map_uv(si), width, point, group), width

    def parameters_changed(self, keys):
        if not keys or any(k == "strength" or k.startswith("normalmap") for k in keys):
            self._pyramid = {}
        if not keys or any(k.startswith("normalmap") for k in keys):
            self._uv_checked = check_uv_transforms(self.texture, "normalmap", self._uv_checked)
            self.hoist_uv_transform()

    def describe(self) -> str:
        return f"  normalmap={self.texture},\n"


def _affine_uv(matrix, uv):
    """The affine uv transform (m00, m01, m02, m10, m11, m12) applied to ``uv`` with the fused
    multiply-adds of Mitsuba's ``Transform::transform_affine`` (the translation first, then the
    x and the y column): its values bit for bit."""
    m00, m01, m02, m10, m11, m12 = matrix
    u, v = uv.x, uv.y
    return mi.Point2f(dr.fma(m01, v, dr.fma(m00, u, m02)), dr.fma(m11, v, dr.fma(m10, u, m12)))
