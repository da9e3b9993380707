"""Exit-direction histograms of the random-walk models next to the brute-force sawtooth tracer.

Shared by ``tests/test_nonseparable_vs_sawtooth.py`` and by anything that wants to
plot the comparison (``from validation.reference import sawtooth_compare``).
Needs ``llvm_ad_rgb`` active and ``mfnormal.register()`` called for the model parts.

Cases (docs/model.md §4, §7): white Lambertian p facets, a mirror or white Lambertian
tangent facet, θ_p ∈ {30°, 60°}, θ_i ∈ {20°, 70°}, ω_i on the side ω_p leans to
("toward", λ_p = 1) or on the tangent-wall side ("away"). The tilt azimuth is 40°
and ω_i's azimuth is 15° off the tilt plane, so no direction lies on a frame axis
or in the symmetry plane of the sawtooth.

Cells: N_U bins of u = cos²θ_o times N_PHI bins of φ_o − φ_p. A cosine-weighted
(Lambertian) exit distribution puts equal mass 1/(N_U·N_PHI) in every cell.

A histogram is returned as the per-cell mean of the path weight times the cell
indicator, ``p`` (it estimates ∫_cell f·cosθ_o dω_o), with ``var`` its binomial-style
variance (second moment minus square, over N) and ``var0`` its second moment over
N (the Poisson form, used by the two-sample χ² statistic).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np
from scipy import stats

from . import sawtooth as sw

PHI_P_DEG = 40.0       # azimuth of the tilt of ω_p
PHI_I_OFFSET_DEG = 15.0  # ω_i's azimuth off the tilt plane
N_U, N_PHI = 6, 8
N_CELLS = N_U * N_PHI
U_EDGES = np.linspace(0.0, 1.0, N_U + 1)
PHI_EDGES = np.linspace(0.0, 2.0 * np.pi, N_PHI + 1)  # of φ_o − φ_p, wrapped to [0, 2π)


@dataclass(frozen=True)
class Case:
    tangent_facet: str  # 'specular' (mirror wall) or 'same' (white Lambertian wall)
    theta_p: float      # degrees
    theta_i: float      # degrees
    side: str           # 'toward' (ω_i on the side ω_p leans to) or 'away'

    @property
    def id(self):
        return f"{self.tangent_facet}-p{self.theta_p:g}-i{self.theta_i:g}-{self.side}"

    @property
    def grazing(self):
        return self.theta_i >= 60.0

    @property
    def wp(self):
        return sph(self.theta_p, PHI_P_DEG)

    @property
    def wi(self):
        phi = PHI_P_DEG + PHI_I_OFFSET_DEG + (0.0 if self.side == "toward" else 180.0)
        return sph(self.theta_i, phi)


CASES = [Case(tf, tp, ti, side)
         for tf in ("specular", "same") for tp in (30.0, 60.0)
         for ti in (20.0, 70.0) for side in ("toward", "away")]


def sph(theta_deg, phi_deg):
    t, p = np.radians(theta_deg), np.radians(phi_deg)
    return np.array([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)])


# -- Cells -------------------------------------------------------------------------------


def cell_index(wo):
    """Cell of each exit direction (n, 3); −1 for NaN or non-upward directions."""
    wo = np.asarray(wo, np.float64)
    ok = np.isfinite(wo).all(axis=1) & (wo[:, 2] > 0)
    r = np.linalg.norm(np.where(ok[:, None], wo, 1.0), axis=1)
    u = np.clip((wo[:, 2] / r) ** 2, 0.0, np.nextafter(1.0, 0.0))
    phi = np.mod(np.arctan2(wo[:, 1], wo[:, 0]) - np.radians(PHI_P_DEG), 2.0 * np.pi)
    iu = np.clip(np.searchsorted(U_EDGES, u, side="right") - 1, 0, N_U - 1)
    iphi = np.clip(np.searchsorted(PHI_EDGES, phi, side="right") - 1, 0, N_PHI - 1)
    return np.where(ok, iu * N_PHI + iphi, -1)


def cell_directions(m_per_cell, rng):
    """Cosine-weighted directions stratified over the cells: (N_CELLS·m, 3), cell-major.

    Inside a cell (u, φ) is uniform, which is the cosine-weighted density
    cosθ/π · N_CELLS restricted to the cell (the cells have equal cosine measure).
    """
    iu, iphi = np.divmod(np.repeat(np.arange(N_CELLS), m_per_cell), N_PHI)
    u = U_EDGES[iu] + rng.random(iu.size) * (1.0 / N_U)
    phi = PHI_EDGES[iphi] + rng.random(iu.size) * (2.0 * np.pi / N_PHI) + np.radians(PHI_P_DEG)
    sin_t = np.sqrt(np.maximum(0.0, 1.0 - u))
    cos_t = np.sqrt(np.maximum(u, 1e-12))
    return np.stack([sin_t * np.cos(phi), sin_t * np.sin(phi), cos_t], axis=1)


def histogram(wo, weight):
    """Per-cell (p, var, var0) of the weighted exit directions (see module docstring)."""
    n = len(wo)
    weight = np.nan_to_num(np.asarray(weight, np.float64))
    c = cell_index(wo)
    ok = c >= 0
    s1 = np.bincount(c[ok], weight[ok], N_CELLS)
    s2 = np.bincount(c[ok], weight[ok] ** 2, N_CELLS)
    p = s1 / n
    return p, np.maximum(s2 / n - p * p, 0.0) / n, s2 / n / n


# -- Paths -------------------------------------------------------------------------------


def tracer_paths(case, n, seed):
    """(wo, weight) of n paths of the brute-force sawtooth tracer (weights 1; 0 if stuck)."""
    wo, _ = sw.trace_paths(case.wi, case.wp, n, np.random.default_rng(seed), facet_p="lambert",
                           facet_t="mirror" if case.tangent_facet == "specular" else "lambert")
    return wo, np.isfinite(wo[:, 0]).astype(np.float64)


def make_bsdf(model, tangent_facet, wp):
    """The plugin with a constant normal ω_p and a white Lambertian nested BSDF."""
    import mitsuba as mi
    tex = np.zeros((1, 1, 3), np.float32)
    tex[...] = np.asarray(wp) * 0.5 + 0.5
    return mi.load_dict({
        "type": "normalmap_microfacet", "model": model, "tangent_facet": tangent_facet,
        "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(tex), "raw": True,
                      "filter_type": "nearest"},
        "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}})


def _si(wi, n, p_y=None):
    """n interactions with the single direction wi; with p_y, query k gets si.p = (k, p_y, 0)."""
    import drjit as dr
    import mitsuba as mi
    from helpers import floats
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    wi = np.asarray(wi, np.float64)
    si.wi = mi.Vector3f(*[float(c) for c in wi])
    if p_y is not None:
        si.p = mi.Point3f(floats(np.arange(n)), float(p_y), 0.0)
    return si


def model_paths(case, model, n, seed):
    """(wo, weight) of n ``sample()`` calls of the plugin (weight: red channel of the throughput)."""
    import mitsuba as mi
    from helpers import floats
    bsdf = make_bsdf(model, case.tangent_facet, case.wp)
    u = np.random.default_rng(seed).random((3, n), dtype=np.float32)
    bs, w = bsdf.sample(mi.BSDFContext(), _si(case.wi, n), floats(u[0]), mi.Point2f(floats(u[1]), floats(u[2])))
    wo = np.array(bs.wo, np.float64).T
    return wo, np.array(w, np.float64)[0]


def eval_cells(case, model, m_per_cell, seed):
    """Per-cell (integral, variance) of the plugin's ``eval()`` (= f·cosθ_o) over each cell.

    m_per_cell cosine-weighted directions per cell; query k uses si.p = (k, seed, 0)
    (exact in float32), so every query draws its own NEE walk. ∫_cell eval dω = (π/N_CELLS)·E[eval/cosθ_o].
    """
    import mitsuba as mi
    from helpers import vec3
    bsdf = make_bsdf(model, case.tangent_facet, case.wp)
    wo = cell_directions(m_per_cell, np.random.default_rng(seed))
    n = len(wo)
    si = _si(case.wi, n, p_y=seed)
    wo_v = vec3(wo)
    f = np.array(bsdf.eval(mi.BSDFContext(), si, wo_v), np.float64)[0]
    g = (f / wo[:, 2]).reshape(N_CELLS, m_per_cell) * (np.pi / N_CELLS)
    return g.mean(axis=1), g.var(axis=1, ddof=1) / m_per_cell


# -- Statistics --------------------------------------------------------------------------


def two_sample_chi2(h1, h2, min_count=10.0):
    """χ² statistic, degrees of freedom and p-value of two histograms (p, var, var0).

    Σ (p₁ − p₂)² / (var0₁ + var0₂) over cells with enough entries; for unit weights
    and equal N this is the textbook Σ (a − b)²/(a + b), χ²-distributed with
    (cells − 1) degrees of freedom when both histograms sample one distribution.
    """
    p1, _, v1 = h1
    p2, _, v2 = h2
    # Cells with fewer than min_count expected entries are left out (χ² needs counts).
    counts = (p1 + p2) ** 2 / np.maximum(v1 + v2, 1e-300)
    use = counts >= min_count
    chi2 = float(np.sum((p1 - p2)[use] ** 2 / (v1 + v2)[use]))
    dof = max(int(use.sum()) - 1, 1)
    return chi2, dof, float(stats.chi2.sf(chi2, dof))


def cell_z(p1, var1, p2, var2):
    """Per-cell z-scores of two independent estimates."""
    return (p1 - p2) / np.sqrt(np.maximum(var1 + var2, 1e-300))


def sidak_p(z):
    """Šidák-corrected p-value of the largest |z| among len(z) two-sided tests."""
    p_min = float(2.0 * stats.norm.sf(np.max(np.abs(z))))
    return float(-np.expm1(len(z) * np.log1p(-min(p_min, 1.0 - 1e-16)))) if p_min < 1 else 1.0


def l1(p1, p2):
    return float(np.sum(np.abs(p1 - p2)))


# -- For plots ---------------------------------------------------------------------------


def case_histograms(case, n=200_000, seed=0, models=("nonseparable", "separable"), eval_per_cell=0):
    """Per-case histograms for plotting: {'tracer': (p, var, var0), model: (p, var, var0), ...}.

    Cells are indexed iu·N_PHI + iφ (edges ``U_EDGES`` of cos²θ_o, ``PHI_EDGES`` of
    φ_o − φ_p); reshape p to (N_U, N_PHI) for an image. With ``eval_per_cell`` > 0 the
    entries 'eval:<model>' hold (integral, variance) of ``eval()`` over each cell.
    """
    out = {"tracer": histogram(*tracer_paths(case, n, seed))}
    for k, model in enumerate(models):
        out[model] = histogram(*model_paths(case, model, n, seed + 1 + k))
        if eval_per_cell:
            out["eval:" + model] = eval_cells(case, model, eval_per_cell, seed + 101 + k)
    return out
