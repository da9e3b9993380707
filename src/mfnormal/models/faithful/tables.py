"""What the default model knows of its map: the principal rms slopes σ1, σ2 and their axis φ_e,
the blocked-light table B over them, the mean slope of its walls, and, with local statistics, the
grids of each neighbourhood's scale k and mean slope (docs/faithful.md §1, §1.1, §7).

They enter the kernels as opaque values, so a new map compiles nothing new; where the map
carries derivatives, they carry them into every query (docs/faithful.md §6). The table and the
grids are computed by :mod:`mfnormal.models.neighbourhood`.
"""

from __future__ import annotations

import copy
import math

import drjit as dr
import mitsuba as mi
import numpy as np

from mfnormal.surface.microsurface import replace_grad, spread
from mfnormal.models.neighbourhood import blocked_table, field_lookup, kernel_array, local_scales, lookup, needed_scales
from mfnormal.surface.shading import from_tangent_rotation

#: With local statistics, the neighbourhood's rms slope (k times the map's) from which its k is the
#: window's alone; below it k moves toward the finer window's (neighbourhood.FINE_WINDOW), all of it
#: for a flat neighbourhood (MapStatistics.local_stats; how it was set: docs/faithful.md §8).
MILD_SLOPE = 1.0
#: A table with derivatives follows σ1, σ2 to first order (B + ∂B/∂σ1·Δσ1 + ∂B/∂σ2·Δσ2, from
#: the tables of ∂B/∂σ it carries) while both stay within this relative distance of the σ it was
#: built at; farther, it is built anew there (MapStatistics.set_slopes). An optimiser moves σ by
#: 0.05–0.5 % a step; within 1 % the expansion is within 2e-5 of the table built at the new σ,
#: below the quadrature's own 7e-5 (docs/faithful.md §6).
TABLE_FOLLOW = 0.01


class MapStatistics:
    """The map's slopes σ1, σ2, φ_e, the table B(σ1, σ2) and the local statistics' grids, for one
    plugin instance (:meth:`set_slopes`), and what a texel reads of them."""

    wall = (0.0, 0.0, 0.0)      # the share of the map's relief that is walls and their mean slope (set_slopes)
    _built = None               # the last table built with derivatives (_followed_table), or None
    #: The map-wide values a texel reads, one each (set_slopes): where they carry derivatives,
    #: :meth:`at_width` spreads them over a query's lanes.
    MAP_WIDE = ("sigma1", "sigma2", "cos_e", "sin_e", "wall_share", "wall_x", "wall_y")

    def at_width(self, width: int):
        """These statistics for a query of ``width`` lanes: where the map-wide values carry
        derivatives, each spread onto the lanes once (microsurface.spread: the same values, and one
        reduction of each one's adjoint per backward pass instead of one at each use, about 200 per
        query); without derivatives, these statistics themselves."""
        values = [getattr(self, name) for name in self.MAP_WIDE]
        spread_values = [spread(value, width) for value in values]
        if all(s is v for s, v in zip(spread_values, values)):
            return self
        view = copy.copy(self)
        for name, value in zip(self.MAP_WIDE, spread_values):
            setattr(view, name, value)
        return view

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

    def walls(self, sp):
        """(ψ_w, n_w): the share of the map's relief that is walls (neighbourhood.walls: 1 for a map
        tilted the same way everywhere, 0 for one whose slopes average to zero), and the walls'
        normal (base frame, in the macro plane, along their mean slope w; any unit vector of the
        plane where there are none)."""
        wx, wy = self.wall_x, self.wall_y
        w2 = dr.fma(wx, wx, wy * wy)
        some = w2 > 0
        n = mi.Vector3f(dr.select(some, wx, 1.0), dr.select(some, wy, 0.0), 0.0) * dr.rsqrt(dr.select(some, w2, 1.0))
        if sp.map_rotation is not None:
            n = from_tangent_rotation(n, sp.map_rotation)
        return self.wall_share, n

    def neighbourhood_walls(self, k):
        """With local statistics: the share |w|²/(k²(σ1² + σ2²)) of the neighbourhood's second moment
        about its mean plane (scale ``k``) that the map's walls hold (neighbourhood.local_field): 1 for a
        map tilted the same way everywhere, 0 for one whose slopes average to zero."""
        walls = dr.fma(self.wall_x, self.wall_x, self.wall_y * self.wall_y)
        spread = k * k * dr.fma(self.sigma1, self.sigma1, self.sigma2 * self.sigma2)
        some = spread > 0
        return dr.select(some, dr.minimum(walls / dr.select(some, spread, 1.0), 1.0), 0.0)

    def set_slopes(self, slopes, attached=None, local=None, wall=None):
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
        texel has the map's neighbourhood about ω_g. The table then has an axis in k.

        ``wall``: ((ψ_w, w_x, w_y), the same as Dr.Jit values that carry derivatives or None): the
        share of the map's relief that is walls and their mean slope (neighbourhood.walls); None:
        the walls as they were (no derivatives), none at first."""
        self._set_wall(wall)
        s1, s2, phi_e = (float(x) for x in slopes)
        self.flat = s1 == 0.0 and s2 == 0.0         # every texel flat (or strength 0)
        self.local, scales, needed = None, None, None
        if local is not None:
            scales = local_scales()
            self.k_max = scales[-1]
            self.local = _local_grids(local)
            fields = local[0]
            needed = needed_scales([fields[0]] + list(fields[3:]), scales)
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
            table, self.d_tables = self._followed_table(s1, s2, scales, needed)
        else:
            table = blocked_table(s1, s2, self.cos_min, scales=scales, needed=needed)
        table = table.ravel()
        if dr.is_jit_v(mi.Float):
            self.table = kernel_array(mi.Float, table)
            dr.make_opaque(self.sigma1, self.sigma2, self.cos_e, self.sin_e, self.table)
        else:
            self.table = table

    def _followed_table(self, s1, s2, scales, needed):
        """(B at σ1 = ``s1``, σ2 = ``s2``, the tables of ∂B/∂σ1 and ∂B/∂σ2 as opaque kernel inputs) for
        a map that carries derivatives: the last table built with derivatives, followed to first order
        (TABLE_FOLLOW), where that one was built at the same scales (at least the ``needed`` ones) and
        at a σ within TABLE_FOLLOW of these; else the table built here (blocked_table), from which the
        next ones follow. So an optimiser's update, whose σ moves a little, builds no table: the σ a
        table is followed from, and so its values to within 2e-5, depend on the updates before."""
        built = self._built
        if built is not None and built.covers(self.cos_min, scales, needed, s1, s2):
            return built.follow(s1, s2), built.d_tables
        table, t1, t2 = blocked_table(s1, s2, self.cos_min, derivatives=True, scales=scales, needed=needed)
        d_tables = (kernel_array(mi.Float, t1), kernel_array(mi.Float, t2))
        dr.make_opaque(*d_tables)
        self._built = _BuiltTable(self.cos_min, scales, needed, s1, s2, (table, t1, t2), d_tables)
        return table, d_tables

    def _set_wall(self, wall):
        """The walls' share ψ_w and mean slope (w_x, w_y) as opaque kernel inputs, with their
        derivatives where ``wall`` carries them (:meth:`set_slopes`)."""
        if wall is None:
            wall = (self.wall, None)
        values, attached = wall
        self.wall = tuple(float(x) for x in values)
        own = [mi.Float(x) for x in self.wall]
        if dr.is_jit_v(mi.Float):
            if attached is not None:
                own = [replace_grad(x, a) for x, a in zip(own, attached)]
            dr.make_opaque(*own)
        self.wall_share, self.wall_x, self.wall_y = own

    def blocked(self, cos_p, phi, g, k=None):
        """B(cosθ_p, φ, G1(ω_i)) from the table (at the neighbourhood's scale ``k``, with local
        statistics), with its derivative with respect to σ1, σ2 when they carry one."""
        value = lookup(self.table, self.cos_min, cos_p, phi, g, k)
        if self.d_tables is None:
            return value
        s1, s2 = dr.detach(self.sigma1), dr.detach(self.sigma2)
        return replace_grad(value, value + lookup(self.d_tables[0], self.cos_min, cos_p, phi, g, k) * (self.sigma1 - s1)
                            + lookup(self.d_tables[1], self.cos_min, cos_p, phi, g, k) * (self.sigma2 - s2))


class _BuiltTable:
    """A table B built with its derivatives at σ1, σ2 (MapStatistics._followed_table): what the
    tables of later σ near it follow from."""

    def __init__(self, cos_min, scales, needed, s1, s2, tables, d_tables):
        self.cos_min, self.scales, self.needed, self.s1, self.s2 = cos_min, scales, needed, s1, s2
        self.tables, self.d_tables = tables, d_tables

    def covers(self, cos_min, scales, needed, s1, s2) -> bool:
        """Whether a table at σ1 = ``s1``, σ2 = ``s2`` (at the scales ``needed`` of ``scales``) may
        follow from this one: the same axes, every needed scale computed here, each σ within
        TABLE_FOLLOW of this one's (a flat map's σ of 0 only from itself)."""
        if cos_min != self.cos_min or scales != self.scales:
            return False
        if self.needed is not None and (needed is None or not set(needed) <= set(self.needed)):
            return False
        return all(abs(s - own) <= TABLE_FOLLOW * own for s, own in ((s1, self.s1), (s2, self.s2)))

    def follow(self, s1, s2):
        """B at σ1 = ``s1``, σ2 = ``s2`` to first order from this table (in [0, 1], as built)."""
        table, t1, t2 = self.tables
        out = table + t1 * np.float32(s1 - self.s1) + t2 * np.float32(s2 - self.s2)
        return np.clip(out, 0.0, 1.0, out=out)


def _local_grids(local):
    """(grids, res, uv_of) from :meth:`MapStatistics.set_slopes`'s ``local``: each grid as an opaque
    Dr.Jit array, with the attached grid's derivatives where there is one."""
    fields, fields_ad, res, uv_of = local
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
    return values, res, uv_of
