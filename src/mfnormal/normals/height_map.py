"""Height maps (``heightmap``, ``height_scale``) as a source of the facet normal ω_p.

**Height maps** (``heightmap``, ``height_scale``): ω_p is the normal of the surface displaced by
``height_scale · strength · h(u, v)`` along the normal, the convention of Mitsuba's ``bumpmap``
(its ``scale``): with g = (∂h/∂u, ∂h/∂v) from the texture's ``eval_1_grad`` (a bilinear
bitmap's exact derivative, what ``bumpmap`` uses) and the tangent-plane parts a, b of
``si.dp_du``, ``si.dp_dv`` in the base frame, ω_p ∝ (a + g_u n) × (b + g_v n), oriented to +z:

    ω_p ∝ sign(J)·(g_v a_y − g_u b_y, g_u b_x − g_v a_x, J),   J = a_x b_y − a_y b_x

(:func:`height_normal`; the same normal as ``bumpmap``'s for the same texture and scale, tested).
With ``tangents="vertex_tangent"`` the derivative's directions are the vertex frame's T and
B = sign·(N×T) (B points to the image's up, −v, as MikkTSpace computed for (u, 1 − v) and as
Mitsuba's t does on a mesh with unmirrored UVs) and its lengths those of a, b:
ω_p ∝ (−g_u/|a|, g_v/|b|, 1) in T, B, N, the normal map a baker would derive from the same
heights in texture space (:func:`texture_space_normal`). Where the parametrisation is degenerate
(no UVs, a zero ``dp_du``), one uv unit is one world unit along s and −t. Non-finite gradients
give the flat normal; normals are clamped to cosθ_p ≥ ``COS_P_MIN`` as decoded maps are.
"""

from __future__ import annotations

import drjit as dr
import mitsuba as mi
import numpy as np

from mfnormal.surface.microsurface import spread, upper_unit
from mfnormal.surface.shading import from_tangent_frame, tangent_rotation
from mfnormal.normals.strength import fail
from mfnormal.normals.tangents import VertexTangents
from mfnormal.normals.uv import check_uv_transforms, finite_uv


def unit_normal(n):
    """``n`` normalised and clamped into the upper hemisphere as decoded maps are: non-finite or
    zero vectors give (0, 0, 1); cosθ below COS_P_MIN is raised to it, keeping the azimuth."""
    return upper_unit(n, 1e-30)


def _scaled(n):
    """``n`` divided by its largest component's magnitude (keeps float32 in range before normalising)."""
    m = dr.maximum(dr.maximum(dr.abs(n.x), dr.abs(n.y)), dr.abs(n.z))
    ok = (m > 0) & dr.isfinite(m)
    return dr.select(ok, n / dr.select(ok, m, 1.0), n)


def _tangent_parts(frame, dp_du, dp_dv):
    """(a, b, ok): dp_du and dp_dv in ``frame``'s local x, y (their tangent-plane parts) and
    where the parametrisation is usable (finite, |J| not negligible against |a||b|)."""
    a, b = frame.to_local(mi.Vector3f(dp_du)), frame.to_local(mi.Vector3f(dp_dv))
    a = mi.Vector2f(a.x, a.y)
    b = mi.Vector2f(b.x, b.y)
    j = a.x * b.y - a.y * b.x
    ok = dr.isfinite(j) & (dr.abs(j) > 1e-6 * dr.sqrt(dr.squared_norm(a) * dr.squared_norm(b))) & (j != 0)
    return a, b, j, ok


def height_normal(grad, frame, dp_du, dp_dv):
    """ω_p in ``frame`` (the base shading frame) of the surface displaced along its normal by a
    height of uv gradient ``grad`` (already scaled): Mitsuba ``bumpmap``'s normal (module docstring).
    A degenerate parametrisation uses one uv unit = one world unit along s and −t."""
    a, b, j, ok = _tangent_parts(frame, dp_du, dp_dv)
    a = dr.select(ok, a, mi.Vector2f(1.0, 0.0))
    b = dr.select(ok, b, mi.Vector2f(0.0, -1.0))
    j = dr.select(ok, j, -1.0)
    sgn = dr.select(j < 0, -1.0, 1.0)
    gu, gv = grad.x, grad.y
    n = mi.Vector3f(sgn * (gv * a.y - gu * b.y), sgn * (gu * b.x - gv * a.x), dr.abs(j))
    return unit_normal(_scaled(n))


def texture_space_normal(grad, frame, dp_du, dp_dv):
    """ω_p in the map's own tangent frame (T, B up the image, N) from the scaled uv gradient:
    (−g_u/|a|, g_v/|b|, 1) normalised, |a|, |b| the tangent-plane lengths of dp_du, dp_dv
    (1 where the parametrisation is degenerate)."""
    a, b, _, ok = _tangent_parts(frame, dp_du, dp_dv)
    la = dr.select(ok, dr.norm(a), 1.0)
    lb = dr.select(ok, dr.norm(b), 1.0)
    return unit_normal(_scaled(mi.Vector3f(-grad.x * lb, grad.y * la, la * lb)))


def height_map_normals(texture, scale: float, res: int):
    """Unit normals (N×3, numpy) of a height map on the unit square (one uv unit = one world unit
    along s and −t, the :func:`height_normal` fallback) at a ``res × res`` grid of cell centres:
    what ``plugin._map_slopes`` measures the faithful model's neighbourhood on."""
    u = (np.arange(res) + 0.5) / res
    uu, vv = np.meshgrid(u, u, indexing="ij")
    if dr.is_jit_v(mi.Float):
        si = dr.zeros(mi.SurfaceInteraction3f, res * res)
        si.uv = mi.Point2f(mi.Float(uu.ravel()), mi.Float(vv.ravel()))
        g = texture.eval_1_grad(si)
        gu, gv = np.array(g.x, np.float64) * scale, np.array(g.y, np.float64) * scale
    else:
        gu, gv = np.zeros(res * res), np.zeros(res * res)
        for k, (x, y) in enumerate(zip(uu.ravel(), vv.ravel())):
            s1 = mi.SurfaceInteraction3f()
            s1.uv = mi.Point2f(float(x), float(y))
            g = texture.eval_1_grad(s1)
            gu[k], gv[k] = float(g[0]) * scale, float(g[1]) * scale
    n = np.stack([-gu, gv, np.ones_like(gu)], -1)
    n[~np.all(np.isfinite(n), 1)] = [0.0, 0.0, 1.0]
    return n / np.linalg.norm(n, axis=1, keepdims=True)


class HeightMap:
    """ω_p from a height map's uv gradient (module docstring), with ``strength`` and
    ``height_scale``, in the base shading frame or through the mesh's vertex tangents."""

    def __init__(self, texture, height_scale: float, strength, tangents: VertexTangents | None):
        self.texture, self.height_scale, self.strength, self.tangents = texture, height_scale, strength, tangents
        self._uv_checked = check_uv_transforms(texture, "heightmap")     # before any lookup (eval_1_grad)
        si = dr.zeros(mi.SurfaceInteraction3f)
        try:
            texture.eval_1_grad(si)
        except Exception as e:  # noqa: BLE001  (Mitsuba raises RuntimeError / NotImplementedError)
            fail(f"heightmap needs a texture with a uv gradient (eval_1_grad: a bitmap, raw=true), "
                 f"{str(texture).split('[')[0]} has none ({str(e).strip().splitlines()[-1][:120]})")

    def facet_normal(self, si, active, nudge=None):
        """(ω_p in si.sh_frame, the map frame's tangent_rotation or None, False: a height map's
        derivatives are its normal's own, no nudges)."""
        grad = mi.Vector2f(self.texture.eval_1_grad(finite_uv(si), active))
        grad = grad * (self.height_scale * spread(self.strength.value, dr.width(grad)))
        wp = height_normal(grad, si.sh_frame, si.dp_du, si.dp_dv)
        rotation = None
        if self.tangents is not None:
            tangent, sign = self.tangents.lookup(si, active)
            if tangent is not None:
                rotation = tangent_rotation(si.sh_frame, tangent, sign)
                ts = texture_space_normal(grad, si.sh_frame, si.dp_du, si.dp_dv)
                wp = dr.select(rotation[3], from_tangent_frame(ts, si.sh_frame, tangent, sign), wp)
        return wp, rotation, False

    def flat_texels(self) -> bool:
        return False

    def slopes(self, attached=False):
        """The map's principal rms slopes (σ1, σ2, φ_e) on the unit square (:func:`height_map_normals`,
        twice the texel resolution: the bilinear gradient is linear across a cell), and None."""
        from mfnormal.models.neighbourhood import principal_slopes
        res = 256 if dr.is_jit_v(mi.Float) else 32
        params = mi.traverse(self.texture)
        if "data" in params.keys():
            shape = params["data"].shape
            res = min(2 * res, 2 * max(shape[0], shape[1]))
        scale = self.height_scale * self.strength.first()
        return principal_slopes(height_map_normals(self.texture, scale, res)), None

    def walls(self, attached=False):
        """((0, 0, 0), None): a height map is the surface itself, whose walls are its own slopes."""
        return (0.0, 0.0, 0.0), None

    def local(self, width: float, attached=False):
        """None: the faithful model reads a height map's slopes for every texel."""
        return None

    def parameters_changed(self, keys):
        if not keys or any(k.startswith("heightmap") for k in keys):
            self._uv_checked = check_uv_transforms(self.texture, "heightmap", self._uv_checked)

    def describe(self) -> str:
        return f"  heightmap={self.texture}, height_scale={self.height_scale},\n"
