"""The nested BSDF's twin whose microfacet roughness the footprint widens (``filter="lean"``).

A footprint over many texels shows their slopes' spread; LEAN mapping (Olano and Baker, I3D
2010) shades it as one facet whose microfacet roughness is widened by it:
α' = √(α² + σ_x² + σ_y²) (exact for a Beckmann distribution, whose slope variance per axis is
α²/2; for GGX the same rule, as specular anti-aliasing uses it). Mitsuba's ``roughconductor`` reads
its roughness as a texture at the query, so the twin is the same plugin with the same parameters,
its ``alpha`` a :class:`WidenedAlpha` that adds the spread the query carries in ``si.duv_dx.x`` (a
field it does not read; :meth:`mfnormal.surface.shading.ShadingPoint.facet_si` writes it), and its
value times the albedo ratio that keeps white facets white (:class:`Twin`).

The twin is made only where it reproduces the nested BSDF exactly at zero spread (checked at a
few queries); other nested BSDFs (diffuse, plastic, a dielectric, an anisotropic or textured
roughness, a spectral variant's material tables) are not widened: :func:`twin` returns None.
"""

from __future__ import annotations

import re

import drjit as dr
import mitsuba as mi
import numpy as np

from mfnormal.plugins.variant_class import variant_subclass

#: Mitsuba's plugins whose roughness is a texture read at the query, by class name, that the twin
#: widens (a ``roughdielectric``'s albedo depends on η and the side as well: not yet widened).
WIDENABLE = {"RoughConductor": "roughconductor"}
#: The albedo table's grid (:class:`Albedo`): cosines 0..1 and roughnesses 0..ALPHA_MAX (beyond: ALPHA_MAX's).
ALBEDO_MU, ALBEDO_ALPHA, ALPHA_MAX = 33, 49, 1.5


class WidenedAlpha:
    """α' = √(α² + max(si.duv_dx.x, 0)): a microfacet roughness ``alpha`` widened by the slope
    variance a query carries (0: ``alpha`` itself, bit for bit)."""

    def __init__(self, props):
        type(self).__mro__[1].__init__(self, props)   # the variant's mi.Texture
        self.alpha = mi.Float(props.get("alpha", 0.1))

    def eval_1(self, si, active=True):
        spread = dr.maximum(si.duv_dx.x, 0.0)
        return dr.select(spread > 0.0, dr.sqrt(dr.fma(self.alpha, self.alpha, spread)), self.alpha)

    def eval(self, si, active=True):
        return mi.Color3f(self.eval_1(si, active)) if mi.is_rgb else mi.Spectrum(self.eval_1(si, active))

    def mean(self):
        return float(np.array(self.alpha).ravel()[0])

    def traverse(self, callback):
        callback.put("alpha", self.alpha, mi.ParamFlags.Differentiable)

    def parameters_changed(self, keys):
        pass

    def to_string(self):
        return f"WidenedAlpha[alpha={self.mean()}]"


def _alpha_texture(alpha):
    props = mi.Properties()
    props["alpha"] = float(alpha)
    return variant_subclass(WidenedAlpha, mi.Texture)(props)


def _value_dict(value):
    """A Mitsuba spectrum dictionary of a traversed ``*.value`` (a Float or a Color3f)."""
    v = np.array(value, dtype=np.float64).ravel()
    if v.size == 1:
        return {"type": "uniform", "value": float(v[0])}
    if v.size == 3 and mi.is_rgb:
        return {"type": "rgb", "value": [float(x) for x in v]}
    return None


class Albedo:
    """E(μ, α): the directional albedo of a white (Fresnel 1) microfacet conductor of a
    distribution (Mitsuba's ``roughconductor``, ``material="none"``), seen at cosine μ, on a grid
    of ALBEDO_MU × ALBEDO_ALPHA (α up to ALPHA_MAX), each cell the mean sample weight of 64 × 64
    stratified visible-normal samples (the weight G2/G1 lies in [0, 1]: the cells' standard errors
    are below 1e-3), the roughnesses spaced as the square of a uniform grid (finer where E changes
    fastest, at small α). Bilinear between cells; made once per distribution."""

    _made: dict[tuple, "Albedo"] = {}

    def __init__(self, distribution: str):
        texture = _alpha_texture(0.0)
        white = mi.load_dict({"type": "roughconductor", "material": "none", "distribution": distribution,
                              "alpha": texture})
        n, side = ALBEDO_MU * ALBEDO_ALPHA, 64
        cell = dr.arange(mi.UInt32, n * side * side)
        k, j = cell // (side * side), cell % (side * side)
        mu = dr.maximum(mi.Float(k // ALBEDO_ALPHA) / (ALBEDO_MU - 1), 2e-3)
        alpha = dr.square(mi.Float(k % ALBEDO_ALPHA) / (ALBEDO_ALPHA - 1)) * ALPHA_MAX
        si = dr.zeros(mi.SurfaceInteraction3f, dr.width(cell))
        si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
        si.wi = mi.Vector3f(dr.safe_sqrt(1.0 - mu * mu), 0.0, mu)
        si.duv_dx = mi.Vector2f(dr.maximum(alpha * alpha, 1e-12), 0.0)
        u = mi.Point2f((mi.Float(j % side) + 0.5) / side, (mi.Float(j // side) + 0.5) / side)
        _, weight = white.sample(mi.BSDFContext(), si, mi.Float(0.5), u)
        w = np.array(dr.select(dr.all(dr.isfinite(weight)), weight[0] if mi.is_rgb else weight, 0.0),
                     dtype=np.float64)
        table = w.reshape(ALBEDO_MU * ALBEDO_ALPHA, side * side).mean(axis=1)
        self.table = mi.Float(table.astype(np.float32))
        self.values = table.reshape(ALBEDO_MU, ALBEDO_ALPHA)

    @classmethod
    def of(cls, distribution: str) -> "Albedo":
        if (distribution, mi.variant()) not in cls._made:
            cls._made[distribution, mi.variant()] = cls(distribution)
        return cls._made[distribution, mi.variant()]

    def __call__(self, mu, alpha):
        """E at cosine ``mu`` (|μ|, clamped to [0, 1]) and roughness ``alpha`` (clamped to [0, ALPHA_MAX])."""
        x = dr.clip(dr.abs(mu), 0.0, 1.0) * (ALBEDO_MU - 1)
        y = dr.sqrt(dr.clip(alpha, 0.0, ALPHA_MAX) / ALPHA_MAX) * (ALBEDO_ALPHA - 1)
        x0 = dr.minimum(mi.UInt32(x), ALBEDO_MU - 2)
        y0 = dr.minimum(mi.UInt32(y), ALBEDO_ALPHA - 2)
        fx, fy = x - mi.Float(x0), y - mi.Float(y0)
        out = mi.Float(0.0)
        for dx, wx in ((0, 1.0 - fx), (1, fx)):
            for dy, wy in ((0, 1.0 - fy), (1, fy)):
                out = dr.fma(wx * wy, dr.gather(mi.Float, self.table, (x0 + dx) * ALBEDO_ALPHA + y0 + dy), out)
        return out


def _twin_dict(nested, params):
    """The dictionary of ``nested``'s twin and its alpha texture, or None where the parameters
    are not plain values (an anisotropic or textured roughness, a texture, spectral data)."""
    kind = WIDENABLE.get(nested.class_name())
    keys = set(params.keys())
    if kind is None or "alpha.value" not in keys:
        return None
    text = str(nested)
    distribution = re.search(r"distribution = (\w+)", text)
    visible = re.search(r"sample_visible = (\d)", text)
    if distribution is None or visible is None:
        return None
    texture = _alpha_texture(np.array(params["alpha.value"]).ravel()[0])
    d = {"type": kind, "distribution": distribution.group(1), "sample_visible": visible.group(1) == "1",
         "alpha": texture}
    for key in keys - {"alpha.value"}:
        if key == "eta" and kind == "roughdielectric":
            d["int_ior"], d["ext_ior"] = float(np.array(params[key]).ravel()[0]), 1.0
        elif key.endswith(".value") and key.count(".") == 1:
            spectrum = _value_dict(params[key])
            if spectrum is None:
                return None
            d[key[:-len(".value")]] = spectrum
        else:
            return None
    return d, texture


def _same(a, b) -> bool:
    """Whether BSDFs ``a`` and ``b`` agree (eval, pdf, a sample) at a few fixed queries."""
    pairs = [((0.3, 0.2, 0.93), (-0.5, 0.1, 0.86)), ((0.0, 0.0, 1.0), (0.6, -0.3, 0.74)),
             ((0.8, 0.1, 0.59), (-0.7, -0.1, 0.7)), ((-0.1, 0.7, 0.7), (0.1, -0.6, -0.79))]
    ctx = mi.BSDFContext()
    for wi, wo in pairs:
        si = dr.zeros(mi.SurfaceInteraction3f)
        si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
        si.n, si.uv = mi.Normal3f(0, 0, 1), mi.Point2f(0.5, 0.5)
        si.wi = dr.normalize(mi.Vector3f(*wi))
        o = dr.normalize(mi.Vector3f(*wo))
        outs = []
        for bsdf in (a, b):
            value, pdf = bsdf.eval_pdf(ctx, si, o)
            bs, weight = bsdf.sample(ctx, si, mi.Float(0.3), mi.Point2f(0.6, 0.2))
            outs.append(np.concatenate([np.array(x, dtype=np.float64).ravel()
                                        for x in (value, pdf, bs.wo, bs.pdf, weight)]))
        if not np.allclose(outs[0], outs[1], rtol=1e-5, atol=1e-7):
            return False
    return True


class Twin:
    """The nested BSDF's widened twin and how it follows the nested BSDF's parameters
    (:meth:`follow`: the values, their derivatives included, after a ``mi.traverse`` update).

    It answers as a BSDF (``eval``, ``pdf``, ``eval_pdf``, ``sample``; the rest is the nested
    BSDF's): the same plugin with the widened roughness α' (:class:`WidenedAlpha`), its value and
    sample weight times E(μ_i, α)/E(μ_i, α') (:class:`Albedo`), so that at every incident cosine
    μ_i its white albedo stays the nested BSDF's. Widening alone loses light that the microfacets
    of the wider lobe mask (single scattering: 5 % at α' = 0.5 seen from above, 20 % at μ_i = 0.2);
    the footprint's slopes are the relief of the map, which the model masks already, not a
    rougher material. Its pdf is the widened plugin's, so a sample's weight is value/pdf."""

    def __init__(self, nested, bsdf, texture, albedo):
        self.nested, self.bsdf, self.texture, self.albedo = nested, bsdf, texture, albedo

    def gain(self, si):
        """E(μ_i, α)/E(μ_i, α') at the query ``si`` (1 where it carries no spread)."""
        spread = dr.maximum(si.duv_dx.x, 0.0)
        alpha = self.texture.alpha
        widened = dr.sqrt(dr.fma(alpha, alpha, spread))
        mu = si.wi.z
        ratio = self.albedo(mu, alpha) / dr.maximum(self.albedo(mu, widened), 1e-6)
        return dr.select(spread > 0.0, ratio, 1.0)

    def eval(self, ctx, si, wo, active=True):
        return self.bsdf.eval(ctx, si, wo, active) * self.gain(si)

    def pdf(self, ctx, si, wo, active=True):
        return self.bsdf.pdf(ctx, si, wo, active)

    def eval_pdf(self, ctx, si, wo, active=True):
        value, pdf = self.bsdf.eval_pdf(ctx, si, wo, active)
        return value * self.gain(si), pdf

    def sample(self, ctx, si, sample1, sample2, active=True):
        bs, weight = self.bsdf.sample(ctx, si, sample1, sample2, active)
        return bs, weight * self.gain(si)

    def __getattr__(self, name):      # (flags(), component_count(), ...: the nested BSDF's)
        if name in ("nested", "bsdf", "texture", "albedo"):
            raise AttributeError(name)
        return getattr(self.nested, name)

    def follow(self):
        """Copy the nested BSDF's parameters into the twin (the alpha into its texture)."""
        source, target = mi.traverse(self.nested), mi.traverse(self.bsdf)
        for key in source.keys():
            if key == "alpha.value":
                self.texture.alpha = mi.Float(source[key])
            elif key in target.keys():
                target[key] = source[key]
        target.update()


def twin(nested) -> Twin | None:
    """The widened twin of ``nested`` (:class:`Twin`), or None where it cannot be widened."""
    if not dr.is_jit_v(mi.Float):
        return None
    made = _twin_dict(nested, mi.traverse(nested))
    if made is None:
        return None
    d, texture = made
    try:
        bsdf = mi.load_dict(d)
    except Exception:       # (a parameter this plugin does not take under that name)
        return None
    out = Twin(nested, bsdf, texture, Albedo.of(d["distribution"]))
    out.follow()
    return out if _same(nested, bsdf) else None
