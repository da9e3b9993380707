"""A normal map's slope moments, prefiltered for a pixel's footprint (LEAN mapping: Olano and
Baker, *LEAN mapping*, I3D 2010; LEADR mapping: Dupuy, Heitz, Iehl, Poulin, Neyret and
Ostromoukhov, SIGGRAPH Asia 2013).

A texel's decoded normal n (:func:`~mfnormal.surface.microsurface.decode_normal`, ``strength``
and the channel convention applied) is the slope s = (−n_x/n_z, −n_y/n_z) of its facet. What a
footprint covering many texels shows is the distribution of their slopes: its mean E[s] (the
mean facet) and its covariance E[s·sᵀ] − E[s]·E[s]ᵀ (the spread a filtered BSDF must add). Both
follow from five moments, (s_x, s_y, s_x², s_y², s_x·s_y), which average linearly, so a footprint's
moments are a mip-map's.

:class:`SlopePyramid` holds them. Level 0 is the map itself: its moments are a texel's own (a
point: no covariance), read from the map's lookup where they are needed, and not stored. Level
ℓ ≥ 1 is a grid ⌈w/2^ℓ⌉ × ⌈h/2^ℓ⌉, each entry the mean of the 2 × 2 entries of level ℓ − 1 below
it (at an odd edge the last row or column counts twice), down to 1 × 1. Five channels over a third
of the texels: 0.56 floats per texel beside a float map's three (:meth:`SlopePyramid.memory_ratio`).

It is built with Dr.Jit gathers from the map's texels (the bitmap's ``data``), so a texel's
derivative reaches every level above it (inverse rendering of the map through a filtered lookup),
and evaluated once: a render reads the stored levels, it does not rebuild them. :meth:`lookup`
reads the level of a footprint ``width`` texels wide, trilinearly: bilinear within the two levels
about log2(width) (wrapping, as a ``repeat`` bitmap does) and linear between them, level 0 being
the point lookup it is given.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mfnormal.surface.microsurface import decode_normal

#: The moments, in the order of :attr:`SlopePyramid.channels`.
MOMENTS = ("s_x", "s_y", "s_xx", "s_yy", "s_xy")
#: The filter's classes of texels by slope |s|, each below its bound: flat, then mild (steeper
#: texels are no class: a filtered lookup shades them as they are; normals/normal_map.py,
#: ``NormalMap.footprint``). A footprint's texels of one class are shaded as one facet with a
#: widened lobe. Flat texels are a class of their own, so that a map's flat ground keeps its sharp
#: highlight beside bumps (caps on flat ground at strength 0.3, gold α 0.05, mirror at 30°: 0.69 of
#: the texels' mean with one class, ``python -m benchmarks.filter``); at a mild bound of 0.5 the
#: Gaussian that stands for the mild texels spread light where none of them sends it (the real
#: assets' far views, docs/normal_sources.md §5).
FLAT_FILTER_SLOPE, MILD_FILTER_SLOPE = 0.02, 0.3
CLASS_BOUNDS = (FLAT_FILTER_SLOPE, MILD_FILTER_SLOPE)
#: Per class (:data:`CLASS_BOUNDS`): its share m of the texels, then their moments times m (s_x·s_y,
#: which a filtered lookup does not read, left out).
CLASS_MOMENTS = tuple(f"{c}_{name}" for c in ("flat", "mild") for name in ("m",) + MOMENTS[:4])


def slope_moments(n):
    """The five moments (s_x, s_y, s_x², s_y², s_x·s_y) of unit normals ``n`` (a Vector3f whose
    z is ≥ COS_P_MIN, as decoded normals are)."""
    inv = dr.rcp(n.z)
    sx, sy = -n.x * inv, -n.y * inv
    return [sx, sy, sx * sx, sy * sy, sx * sy]


def texel_class(moments):
    """The class of the texel of these five moments (:data:`CLASS_BOUNDS`): 0 flat, 1 mild, 2 steep
    (a UInt32 per lane)."""
    s2 = moments[2] + moments[3]
    return dr.select(s2 < FLAT_FILTER_SLOPE ** 2, mi.UInt32(0),
                     dr.select(s2 < MILD_FILTER_SLOPE ** 2, mi.UInt32(1), mi.UInt32(2)))


def class_moments(n):
    """The ten :data:`CLASS_MOMENTS` of unit normals ``n``: per class, m = 1 where the texel is of
    it (else 0), then its moments times m. A footprint's average of them is each class's share and
    that share's moments; divided by the share, the class's mean moments."""
    moments = slope_moments(n)
    c = texel_class(moments)
    out = []
    for k in range(len(CLASS_BOUNDS)):
        m = dr.select(c == k, 1.0, 0.0)
        out += [m] + [m * x for x in moments[:4]]
    return out


def class_point(n):
    """A texel's own moments in its class's group of :data:`CLASS_MOMENTS` (m = 1): what stands
    for level 0 in a class lookup (:meth:`SlopePyramid.lookup` with ``group`` its class)."""
    return [mi.Float(1.0)] + slope_moments(n)[:4]


def _halve(channels, width: int, height: int):
    """A level's channels (each row-major, ``width`` × ``height``) averaged over 2 × 2 blocks."""
    w2, h2 = (width + 1) // 2, (height + 1) // 2
    idx = dr.arange(mi.UInt32, w2 * h2)
    x, y = idx % w2, idx // w2
    below = [dr.minimum(2 * y + dy, height - 1) * width + dr.minimum(2 * x + dx, width - 1)
             for dy in (0, 1) for dx in (0, 1)]
    out = []
    for c in channels:
        acc = mi.Float(0.0)
        for index in below:
            acc += dr.gather(mi.Float, c, index)
        out.append(acc * 0.25)
    return out, w2, h2


class SlopePyramid:
    """The slope moments of a map's levels 1, 2, … (the module docstring), each channel of all
    levels in one array (level ℓ at ``offsets[ℓ]``, row-major, ``sizes[ℓ]`` = (width, height)).

    With ``groups`` G > 1 the channels are G groups of C (:data:`CLASS_MOMENTS`: a group per texel
    class), stored interleaved: C arrays, group g of cell i at i·G + g, so that a lookup reads the
    C channels of one group per lane (``group``), one gather each."""

    def __init__(self, texels, strength, directx: bool, moments_of=slope_moments, groups: int = 1):
        """From the map's texels (a tensor of shape (height, width, ≥ 3), as a bitmap's ``data``:
        floats, derivatives kept, or 8- and 16-bit integers, read as Mitsuba's bitmap reads them,
        over 255 and 65535), decoded with ``strength`` (a Float) and the convention; ``moments_of``
        the texel normals' channels (default: the five :data:`MOMENTS`; :func:`class_moments`, in
        ``groups`` groups)."""
        height, width, channels = (int(x) for x in texels.shape)
        idx = dr.arange(mi.UInt32, width * height) * channels
        rgb = mi.Color3f(*(dr.gather(mi.Float, _floats(texels), idx + c) for c in range(3)))
        moments = moments_of(decode_normal(rgb, strength, directx))
        self.width, self.height, self.map_floats = width, height, width * height * channels
        self.sizes, self.offsets, parts = [(width, height)], [0], [[] for _ in moments]
        w, h, total = width, height, 0
        while w > 1 or h > 1:
            moments, w, h = _halve(moments, w, h)
            dr.eval(*moments)
            self.sizes.append((w, h))
            self.offsets.append(total)
            total += w * h
            for part, m in zip(parts, moments):
                part.append(m)
        self.channels = [_concat(part) for part in parts] if total else []
        self.groups = groups
        if groups > 1 and self.channels:
            self.channels = _interleave(self.channels, groups)
        self._offset_array = mi.UInt32(np.array(self.offsets, np.uint32))
        dr.eval(*self.channels)

    @property
    def top(self) -> int:
        """The coarsest level's index (1 × 1; 0 for a 1 × 1 map)."""
        return len(self.sizes) - 1

    def memory_ratio(self) -> float:
        """The stored levels' floats over the map's (its texels × channels)."""
        return sum(dr.width(c) for c in self.channels) / self.map_floats

    def level(self, index: int) -> np.ndarray:
        """Level ``index`` ≥ 1 as numpy, shape (height, width, channels: group by group)."""
        (w, h), start = self.sizes[index], self.offsets[index]
        g = self.groups
        return np.stack([np.array(c, np.float64)[(start + np.arange(w * h)) * g + k].reshape(h, w)
                         for k in range(g) for c in self.channels], -1)

    def _bilinear(self, level, uv, active, group=None):
        """The channels of ``level`` (a UInt32 per lane, ≥ 1; of ``group``, a UInt32 per lane, with
        groups) at ``uv``, bilinear over its texel centres, wrapping (a ``repeat`` bitmap's lookup on
        that grid); 0 where not ``active``."""
        scale = mi.UInt32(1) << level
        w = (self.width + scale - 1) // scale                 # ⌈width / 2^ℓ⌉, as the levels were built
        h = (self.height + scale - 1) // scale
        offset = dr.gather(mi.UInt32, self._offset_array, level, active)
        x = uv.x * mi.Float(w) - 0.5
        y = uv.y * mi.Float(h) - 0.5
        x0, y0 = dr.floor(x), dr.floor(y)
        fx, fy = x - x0, y - y0
        xi, yi = _wrap(x0, w), _wrap(y0, h)
        out = [mi.Float(0.0) for _ in self.channels]
        for dy, wy in ((0, 1.0 - fy), (1, fy)):
            row = dr.select(yi + dy == h, 0, yi + dy)
            for dx, wx in ((0, 1.0 - fx), (1, fx)):
                col = dr.select(xi + dx == w, 0, xi + dx)
                index = offset + row * w + col
                if self.groups > 1:
                    index = index * self.groups + group
                for n, c in enumerate(self.channels):
                    out[n] = dr.fma(wx * wy, dr.gather(mi.Float, c, index, active), out[n])
        return out

    def lookup(self, uv, width, point, group=None):
        """The channels (with groups: of ``group``) of a footprint ``width`` texels of the map wide
        (a Float; ≤ 1: the point; not finite: the point) centred at ``uv`` (a Point2f): trilinear
        between the levels ⌊log2 width⌋ and the next, ``point`` (the channels of the map's own
        lookup at ``uv``) standing for level 0."""
        if self.top == 0:
            return list(point)
        width = dr.select(dr.isfinite(width), width, 0.0)      # (no footprint where it is not finite)
        lod = dr.clip(dr.log2(dr.maximum(width, 1.0)), 0.0, float(self.top))
        lower = dr.minimum(mi.UInt32(dr.floor(lod)), self.top - 1)
        f = lod - mi.Float(lower)
        coarse = self._bilinear(lower + 1, uv, f > 0, group)
        fine = self._bilinear(dr.maximum(lower, 1), uv, lower > 0, group)
        fine = [dr.select(lower == 0, p, m) for p, m in zip(point, fine)]
        return [dr.select(f > 0, dr.lerp(a, b, f), a) for a, b in zip(fine, coarse)]

    @staticmethod
    def covariance(moments):
        """(var_x, var_y, cov_xy) of the five moments, clamped to a positive semidefinite matrix
        (float rounding of E[s²] − E[s]² can go below 0)."""
        sx, sy, sxx, syy, sxy = moments
        vx = dr.maximum(sxx - sx * sx, 0.0)
        vy = dr.maximum(syy - sy * sy, 0.0)
        bound = dr.sqrt(vx * vy)
        return vx, vy, dr.clip(sxy - sx * sy, -bound, bound)


def _floats(texels):
    """A bitmap's ``data`` as one Float array, its 8- and 16-bit integers over their largest value."""
    kind = dr.type_v(texels)
    if kind in (dr.VarType.Float32, dr.VarType.Float64, dr.VarType.Float16):
        return mi.Float(texels.array)
    scale = {dr.VarType.UInt8: 255.0, dr.VarType.UInt16: 65535.0}.get(kind)
    if scale is None:
        raise ValueError(f"normalmap_microfacet: the normal map's texels are {kind}; use a float, "
                         "8-bit or 16-bit bitmap")
    return mi.Float(texels.array) * (1.0 / scale)


def _interleave(channels, groups: int):
    """``groups`` groups of C channels (each one array of the cells) as C arrays, group g of cell i
    at i·groups + g."""
    per = len(channels) // groups
    out = []
    for c in range(per):
        cells = dr.width(channels[c])
        merged = dr.zeros(mi.Float, cells * groups)
        for g in range(groups):
            dr.scatter(merged, channels[g * per + c], dr.arange(mi.UInt32, cells) * groups + g)
        out.append(merged)
    return out


def _wrap(i, n):
    """The integer-valued Float ``i`` modulo ``n`` (a UInt32 per lane), as a UInt32 in [0, n)."""
    nf = mi.Float(n)
    return dr.minimum(mi.UInt32(dr.maximum(i - nf * dr.floor(i / nf), 0.0)), n - 1)


def _concat(arrays):
    """One Float array of ``arrays`` in order (a gather from each, by a scatter into one)."""
    out = dr.zeros(mi.Float, sum(dr.width(a) for a in arrays))
    start = 0
    for a in arrays:
        dr.scatter(out, a, dr.arange(mi.UInt32, dr.width(a)) + start)
        start += dr.width(a)
    return out


def footprint_texels(si, width: int, height: int):
    """The footprint's width in texels of a ``width`` × ``height`` map: the longer of its uv
    axes (``si.duv_dx``, ``si.duv_dy``, each the step across the whole footprint) in texels;
    0 without a footprint."""
    def texels(d):
        return dr.sqrt(dr.square(d.x * width) + dr.square(d.y * height))
    return dr.maximum(texels(si.duv_dx), texels(si.duv_dy))

