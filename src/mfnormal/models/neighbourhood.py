"""The texel's neighbourhood, for the default model (docs/faithful.md): the map's principal rms
slopes, Smith masking by neighbours with those slopes, and B, the share of a Lambertian facet's
light that they block (a table over the facet's tilt and azimuth and G1(ω_i)).

The slopes are measured once per map (numpy, :func:`principal_slopes`; winsorised, so that a few
texels far steeper than the rest cannot make the whole map rough) and, where the map carries
derivatives, again as Dr.Jit values (:func:`attached_slopes`). The table is computed in numpy
(:func:`blocked_table`) and read in kernels (:func:`lookup`).
"""

from __future__ import annotations

import concurrent.futures
import functools
import math
import os

import drjit as dr
import mitsuba as mi
import numpy as np

INV_PI = 1.0 / math.pi
SQRT_PI = math.sqrt(math.pi)
# Λ(a) < 1e-8 beyond this a = 1/(√2 σ tanθ): treat as unmasked.
A_UNMASKED = 4.0


#: The alignment, in bytes, of the arrays handed to kernels from numpy (:func:`kernel_array`): the
#: widest vector load (AVX-512, 64 bytes).
KERNEL_ALIGN = 64


def kernel_array(cls, values: np.ndarray):
    """``cls(values)`` (a Dr.Jit array type; ``values`` flattened, of cls's dtype) in memory aligned
    to KERNEL_ALIGN bytes. Dr.Jit reads a numpy array's memory where it lies and compiles a kernel's
    loads for the alignment it finds there (32 bytes or not): an array made anew per ``mi.traverse``
    update from numpy lies where the allocator put it, so the same kernel would compile again,
    once per combination of its inputs' alignments."""
    values = np.ascontiguousarray(values).ravel()
    buffer = np.empty(values.nbytes + KERNEL_ALIGN, np.uint8)
    start = -buffer.ctypes.data % KERNEL_ALIGN
    aligned = buffer[start:start + values.nbytes].view(values.dtype)
    aligned[:] = values
    return cls(aligned)


# -- Smith masking by the neighbourhood -----------------------------------------------------------
#
# The neighbours' slopes are Beckmann-distributed with the map's own second moments about the
# macro normal, Σ = E[s sᵀ] of the slopes s = (−n_x/n_z, −n_y/n_z) in the map's tangent frame:
# principal rms slopes σ1 ≥ σ2 along the eigenvectors of Σ (at angle φ_e). A ribbed map is
# rough across its ribs and smooth along them; a constant tilt masks only along the tilt.

def smith_lambda(w, sigma1, sigma2):
    """Beckmann Λ(ω) for ``w`` given in the principal frame of the slopes (σ1 along x, σ2 along
    y); 0 where unmasked: a = ω_z / (√2 (σ1² ω_x² + σ2² ω_y²)^½)."""
    spread2 = dr.fma(sigma1 * sigma1, w.x * w.x, sigma2 * sigma2 * w.y * w.y)
    # (No spread, e.g. a smooth region's k = 0: unmasked, and no 0·∞ derivative of √ at 0.)
    some = spread2 > 1e-30
    spread = dr.sqrt(dr.select(some, spread2, 1.0))
    a = dr.maximum(w.z, 0.0) / dr.maximum(math.sqrt(2.0) * spread, 1e-30)
    a = dr.select(some, dr.maximum(a, 1e-7), 1e30)
    # Λ = e^(−a²)·(1/(2a√π) − erfcx(a)/2), erfcx(a) = e^(a²)erfc(a) ≈ P(1/(1 + p·a)) (Abramowitz &
    # Stegun 7.1.26, as _erf_np): one exp and no erf.
    t = dr.rcp(dr.fma(0.3275911, a, 1.0))
    erfcx = t * dr.fma(t, dr.fma(t, dr.fma(t, dr.fma(t, 1.061405429, -1.453152027), 1.421413741),
                             -0.284496736), 0.254829592)
    lam = dr.exp(-a * a) * dr.fma(dr.rcp(a), 0.5 / SQRT_PI, -0.5 * erfcx)
    return dr.select(a < A_UNMASKED, dr.maximum(lam, 0.0), 0.0)


def _erf_np(x):
    """erf for x ≥ 0 (Abramowitz & Stegun 7.1.26, |error| ≤ 1.5e-7), vectorised."""
    t = 1.0 / (1.0 + 0.3275911 * x)
    poly = t * (0.254829592 + t * (-0.284496736 + t * (1.421413741 + t * (-1.453152027 + t * 1.061405429))))
    return 1.0 - poly * np.exp(-x * x)


def smith_lambda_np(w, sigma1, sigma2, derivatives=False):
    """numpy twin of :func:`smith_lambda` (for the tables); ``w``: (..., 3). With
    ``derivatives``: (Λ, ∂Λ/∂σ1, ∂Λ/∂σ2), from ∂Λ/∂a = −e^(−a²)/(2a²√π) and
    ∂a/∂σ_k = −a σ_k w_k²/(σ1²w_x² + σ2²w_y²)."""
    spread2 = sigma1 ** 2 * w[..., 0] ** 2 + sigma2 ** 2 * w[..., 1] ** 2
    spread = np.sqrt(spread2)
    a_raw = np.maximum(w[..., 2], 0.0) / np.maximum(math.sqrt(2.0) * spread, 1e-30)
    a = np.clip(a_raw, 1e-7, 1e6)
    lam = 0.5 * (np.exp(-a * a) / (a * SQRT_PI) - (1.0 - _erf_np(a)))
    masked = a < A_UNMASKED
    lam = np.where(masked, np.maximum(lam, 0.0), 0.0)
    if not derivatives:
        return lam
    free = masked & (a_raw == a) & (spread2 > 0)
    d_a = np.where(free, -np.exp(-a * a) / (2.0 * a * a * SQRT_PI), 0.0)
    inv = np.where(free, 1.0 / np.maximum(spread2, 1e-300), 0.0)
    return (lam, d_a * (-a * sigma1 * w[..., 0] ** 2 * inv), d_a * (-a * sigma2 * w[..., 1] ** 2 * inv))


#: Winsorised slopes (docs/faithful.md §5): a texel's slope counts at most WINSOR_C times the map's
#: (winsorised) rms slope, and never less than WINSOR_FLOOR (tan 60°). The repository's maps reach
#: 1.2-2.5 times their rms (bumps, egg crates, noise at any steepness and resolution): they are never
#: capped, and their σ is the plain rms bit for bit.
WINSOR_C = 5.0
WINSOR_FLOOR = math.sqrt(3.0)


def slope_cap2(s2: np.ndarray, winsor=(WINSOR_C, WINSOR_FLOOR)):
    """The squared cap t² of the squared slope magnitudes ``s2`` (float64): None where no texel
    exceeds WINSOR_C × their rms (nothing capped), else the largest t² ≥ WINSOR_FLOOR² with
    t² = WINSOR_C² · mean(min(s2, t²)) (a texel at the clamp among 16² cannot make the whole map rough).
    Iterated from the plain rms: t² falls and the capped set grows, so at most len(s2) steps.
    ``winsor``: (WINSOR_C, WINSOR_FLOOR); (inf, inf) caps nothing."""
    n, c2, floor2 = len(s2), winsor[0] * winsor[0], winsor[1] * winsor[1]
    t2 = max(c2 * float(np.mean(s2)), floor2)
    if not float(np.max(s2, initial=0.0)) > t2:
        return None
    for _ in range(n + 1):
        capped = s2 > t2
        k, rest = int(capped.sum()), float(s2[~capped].sum())
        # Where the capped set is ``capped``, t² = c²(rest + k·t²)/n in closed form.
        new = max(floor2, c2 * rest / (n - c2 * k)) if n > c2 * k else floor2
        if np.array_equal(s2 > new, capped):
            return new
        t2 = new
    return t2


def _cap_attached(sx, sy, s2_np, t2):
    """sx, sy (Dr.Jit) with the slopes over the cap ``t2`` (slope_cap2 of their detached s2_np)
    scaled onto it; t² as a Dr.Jit value of the uncapped slopes where it is above the floor, so
    that the fixed point's derivative is exact."""
    n, c2 = len(s2_np), WINSOR_C * WINSOR_C
    capped_np = s2_np > t2
    capped = kernel_array(mi.Bool, capped_np)
    s2 = sx * sx + sy * sy
    if t2 > WINSOR_FLOOR * WINSOR_FLOOR:
        # (The capped count a kernel input: a literal would compile anew as it changes.)
        t2 = c2 * dr.sum(dr.select(capped, 0.0, s2)) / dr.opaque(mi.Float, n - c2 * int(capped_np.sum()))
    scale = dr.select(capped, dr.sqrt(t2 / dr.select(capped, s2, 1.0)), 1.0)
    return sx * scale, sy * scale


def attached_winsorised(wp, capped=True):
    """The slopes of the unit normals ``wp`` (Dr.Jit) as :func:`winsorised_slopes` gives them, with
    wp's derivatives (``capped`` false: not winsorised)."""
    z = dr.maximum(wp.z, 1e-3)
    sx, sy = -wp.x / z, -wp.y / z
    if capped:
        s2_np = np.square(np.array(dr.detach(sx), np.float64)) + np.square(np.array(dr.detach(sy), np.float64))
        t2 = slope_cap2(s2_np)
        if t2 is not None:
            sx, sy = _cap_attached(sx, sy, s2_np, t2)
    return sx, sy


def attached_slopes(wp, strength=None):
    """(σ1, σ2, φ_e) of the unit normals ``wp`` (a Dr.Jit Vector3f, e.g. the map decoded at
    texel centres) as Dr.Jit values that carry wp's derivatives: :func:`principal_slopes`'s
    quantities in closed form (the 2×2 eigenproblem), with its winsorised slopes. Where an
    eigenvalue or the anisotropy is zero (a flat or isotropic map) their square roots have no
    derivative; they get the central one, 0. ``strength``: wp was decoded at strength 1 and the map
    is used at this strength, 0: the slopes are strength × those of wp (exact while no normal is
    clamped; none is capped near strength 0, where every slope is below WINSOR_FLOOR), so that σ has
    its derivative at strength 0 (where √(σ²) has none)."""
    sx, sy = attached_winsorised(wp, capped=strength is None)
    a, b, c = dr.mean(sx * sx), dr.mean(sx * sy), dr.mean(sy * sy)
    q = dr.square(0.5 * (a - c)) + b * b
    iso = q > 1e-24
    r = dr.select(iso, dr.sqrt(dr.select(iso, q, 1.0)), 0.0)

    def root(x):
        ok = x > 1e-24
        return dr.select(ok, dr.sqrt(dr.select(ok, x, 1.0)), 0.0)

    s1, s2 = root(0.5 * (a + c) + r), root(0.5 * (a + c) - r)
    phi = dr.select(iso, 0.5 * dr.atan2(dr.select(iso, 2.0 * b, 0.0), dr.select(iso, a - c, 1.0)), 0.0)
    if strength is not None:
        s1, s2 = s1 * strength, s2 * strength
    return s1, s2, phi


def winsorised_slopes(normals: np.ndarray, winsor=(WINSOR_C, WINSOR_FLOOR)):
    """The slopes (s_x, s_y) = (−n_x/n_z, −n_y/n_z) of unit normals (…×3, flattened; float64), those
    over the cap of :func:`slope_cap2` scaled onto it."""
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    z = np.maximum(n[:, 2], 1e-3)
    sx, sy = -n[:, 0] / z, -n[:, 1] / z
    s2 = sx * sx + sy * sy
    t2 = slope_cap2(s2, winsor)
    if t2 is not None:
        scale = np.where(s2 > t2, np.sqrt(t2 / np.where(s2 > t2, s2, 1.0)), 1.0)
        sx, sy = sx * scale, sy * scale
    return sx, sy


def principal_slopes(normals: np.ndarray, winsor=(WINSOR_C, WINSOR_FLOOR)):
    """(σ1, σ2, φ_e): the principal rms slopes of unit normals (N×3) about the macro normal
    (σ1 ≥ σ2) and the angle of σ1's axis from the tangent frame's x axis. Slopes over the cap of
    :func:`slope_cap2` (a few texels far steeper than the rest, ``winsor`` its parameters) are
    scaled onto it first."""
    sx, sy = winsorised_slopes(normals, winsor)
    cov = np.array([[np.mean(sx * sx), np.mean(sx * sy)], [np.mean(sx * sy), np.mean(sy * sy)]])
    values, vectors = np.linalg.eigh(cov)                       # ascending
    s1, s2 = math.sqrt(max(values[1], 0.0)), math.sqrt(max(values[0], 0.0))
    return s1, s2, math.atan2(vectors[1, 1], vectors[0, 1])


# -- The blocked share of a Lambertian facet's light: B(cosθ_p, φ_p, G1(ω_i)) -------------------

TABLE_COS = 40      # θ_p from 0 to acos(COS_P_MIN), uniform in the angle (B changes fastest near 90°)
TABLE_PHI = 9       # the facet's azimuth in the slopes' principal frame, folded into [0, π/2]
TABLE_G = 40        # G1(ω_i)^⅓, G1 = 1/(1 + Λ(ω_i)), from 0 to 1 (B changes fastest as G1 → 0)
#: The quadrature (:func:`_lune_quadrature`): Gauss-Legendre nodes along the lune's edge axis and
#: across it, graded toward the macro plane (_QUAD_PSI of them: two thirds below the zenith's
#: angle, one third above it). 576 directions, within 7e-5 of a direct integration for rms slopes
#: from 0.01 to 35 (tests/test_faithful.py::test_blocked_table_entries_match_a_direct_integration).
_QUAD_BETA = 24
_QUAD_PSI = 24


def _gauss(a: float, b: float, n: int, grade: int = 1):
    """(nodes, weights) of n-point Gauss-Legendre on [a, b] in t ∈ [0, 1], x = a + (b − a)·t^grade:
    graded toward a (nodes t² apart there, for a layer at a)."""
    x, w = np.polynomial.legendre.leggauss(n)
    t, wt = 0.5 * (x + 1.0), 0.5 * w
    return a + (b - a) * t ** grade, wt * (b - a) * grade * t ** (grade - 1)


def _lune_quadrature(theta: float):
    """(β, ψ, weights) of a facet tilted by θ_p = ``theta``: Σ w·F(ω(β, ψ)) ≈ (1/π)∫ F⟨ω,ω_p⟩ dω
    over the directions above both the facet's plane and the macro plane (a lune).

    Both planes hold the axis t ⊥ the tilt; ω = cosβ·t + sinβ·(cosψ·e + sinψ·z), e the tilt's
    horizontal direction: the lune is β ∈ [0, π], ψ ∈ [0, π − θ_p], where dω = sinβ dβ dψ and
    ⟨ω,ω_p⟩ = sinβ·sin(ψ + θ_p), both smooth. What is not smooth is S: it falls to 0 in a layer
    above the macro plane (ψ → 0; as thin as 1/(1 + Λ_i) is small) and, for rough maps, peaks within
    ~1/σ of the zenith (β = ψ = π/2). So ψ's nodes are graded toward the plane and both axes are
    split at π/2, where Gauss-Legendre crowds its nodes (docs/faithful.md §1, the table B)."""
    b, wb = _gauss(0.0, 0.5 * math.pi, _QUAD_BETA // 2)
    beta, w_beta = np.concatenate([b, math.pi - b[::-1]]), np.concatenate([wb, wb[::-1]])
    low, w_low = _gauss(0.0, 0.5 * math.pi, _QUAD_PSI - _QUAD_PSI // 3, grade=2)
    high, w_high = _gauss(0.5 * math.pi, math.pi - theta, _QUAD_PSI // 3)
    psi, w_psi = np.concatenate([low, high]), np.concatenate([w_low, w_high])
    beta, psi = (a.ravel() for a in np.meshgrid(beta, psi, indexing="ij"))
    weights = np.outer(w_beta, w_psi).ravel() * np.sin(beta) ** 2 * np.sin(psi + theta) / math.pi
    return beta, psi, weights


@functools.lru_cache(maxsize=4)
def _table_directions(cos_min: float):
    """What :func:`blocked_table` integrates over, which no slope changes: per θ_p row (TABLE_COS
    steps from 0 to acos(``cos_min``)), the quadrature's directions for each azimuth φ_j
    (TABLE_PHI, _QUAD_BETA·_QUAD_PSI, 3), its weights (:func:`_lune_quadrature`; every
    direction lies above the macro plane) and the share (1 − cosθ_p)/2 of the facet's lobe below
    that plane. Built once (read-only); each table then only evaluates Λ and S on them."""
    rows = []
    for theta in np.linspace(0.0, math.acos(cos_min), TABLE_COS):
        beta, psi, weights = _lune_quadrature(float(theta))
        along, across = np.cos(beta), np.sin(beta)
        ds = []
        for phi in np.linspace(0.0, 0.5 * math.pi, TABLE_PHI):
            c, s = math.cos(phi), math.sin(phi)
            # t = (−sin φ, cos φ, 0), e = (cos φ, sin φ, 0), z = (0, 0, 1)
            horizontal = across * np.cos(psi)
            ds.append(np.stack([horizontal * c - along * s, horizontal * s + along * c, across * np.sin(psi)], -1))
        d = np.stack(ds)
        for a in (d, weights):
            a.setflags(write=False)
        rows.append((d, weights, 0.5 * (1.0 - math.cos(theta))))
    return tuple(rows)


def _table_row(row, a_i, sigma1: float, sigma2: float, derivatives: bool, work):
    """One θ_p row of :func:`blocked_table`: (B, ∂B/∂σ1, ∂B/∂σ2) over (φ_j, G1), ``a_i`` = 1 + Λ_i
    (TABLE_G × 1) of the G1 axis. B = (1 − cosθ_p)/2 + (1/π)∫_lune ⟨ω,ω_p⟩ (1 − S) dω: the share of
    the facet's lobe below the macro plane in closed form, and what the neighbours block above it,
    1 − S = Λ(ω)/(a_i + Λ(ω)), on each azimuth's directions (:func:`_lune_quadrature`); ∂B/∂σ_k
    from −∂S/∂Λ = a_i/(a_i + Λ(ω))². So a map without slopes blocks nothing above the plane
    exactly (B = 0 at θ_p = 0), and no sum of weights stands in for the lune's measure.

    The integrands are formed in float32 (half the time of float64's divisions) and summed in
    float64: each term's relative rounding is 6e-8, the sums' 3e-9 at most. ``work``: three
    buffers of shape (TABLE_PHI, TABLE_G, n), float32, float32 and float64, reused from row to row
    (fresh arrays of a few MB per row cost more in page faults than their arithmetic)."""
    d, weights, below = row
    parts = smith_lambda_np(d, sigma1, sigma2, derivatives=derivatives)
    lam, *dls = (x.astype(np.float32) for x in (parts if derivatives else (parts,)))
    a_i = a_i.astype(np.float32)[None]                  # (1, TABLE_G, 1) against (TABLE_PHI, 1, n)
    den, hidden, wide = work
    out = np.zeros((3, TABLE_PHI, TABLE_G))
    np.add(a_i, lam[:, None, :], out=den)
    np.divide(lam[:, None, :], den, out=hidden)
    np.copyto(wide, hidden)
    out[0] = below + wide @ weights
    if derivatives:
        np.subtract(1.0, hidden, out=hidden)
        np.divide(hidden, den, out=hidden)              # a_i/(a_i + Λ)²
        for n, dl in enumerate(dls, 1):
            np.copyto(wide, np.multiply(hidden, dl[:, None, :], out=den))
            out[n] = wide @ weights
    return out


def _scaled_tables(sigma1: float, sigma2: float, cos_min: float, derivatives: bool, scales, needed):
    """:func:`blocked_table` for each neighbourhood scale k of ``scales``, stacked on axis 2 (the
    derivatives with respect to the map's σ: k times the scaled neighbourhood's). Only the scales
    ``needed`` (indices) are computed; each other index holds the nearest needed one's table,
    which no lookup reads. The scales' tables are independent numpy work that releases the GIL:
    one thread each, up to the cores."""
    def one(k):
        t = blocked_table(k * sigma1, k * sigma2, cos_min, derivatives)
        return t if derivatives else (t,)
    needed = range(len(scales)) if needed is None else needed
    workers = min(len(needed), os.cpu_count() or 1)
    if workers > 1:
        with concurrent.futures.ThreadPoolExecutor(workers) as pool:
            parts = dict(zip(needed, pool.map(one, [scales[i] for i in needed])))
    else:
        parts = {i: one(scales[i]) for i in needed}
    source = [min(needed, key=lambda j: abs(j - i)) for i in range(len(scales))]
    # ∂B/∂σ of the map = k·∂B/∂σ of the scaled neighbourhood.
    out = tuple(np.ascontiguousarray(np.stack([parts[j][n] * (scales[j] if n else 1.0) for j in source], 2))
                for n in range(len(parts[needed[0]])))
    for a in out:
        a.setflags(write=False)
    return out if derivatives else out[0]


def needed_scales(k_grids, scales) -> tuple | None:
    """The indices of ``scales`` (:func:`local_scales`) that lookups can read, for neighbourhood
    scales k whose values lie between the least and the largest of the grids ``k_grids`` (the
    window's and the finer window's k: a texel's k is interpolated from them and capped at the
    last scale), with one scale to spare on each side; None (all of them) where a grid is not
    finite."""
    values = np.concatenate([np.asarray(g, np.float64).ravel() for g in k_grids])
    if values.size == 0 or not np.all(np.isfinite(values)):
        return None
    k_lo, k_hi = max(float(values.min()), 0.0), min(float(values.max()), scales[-1])
    steps = len(scales) - 1

    def node(k):
        return int(math.floor(min(k / (1.0 + k) / LOCAL_U_MAX, 1.0) * steps))
    return tuple(range(max(node(k_lo) - 1, 0), min(node(max(k_hi, k_lo)) + 2, steps) + 1))


@functools.lru_cache(maxsize=32)
def blocked_table(sigma1: float, sigma2: float, cos_min: float, derivatives: bool = False, scales=None,
                  needed=None):
    """B[i, j, k]: 1 − ∫ (1/π)⟨ω,ω_p⟩ S(ω|ω_i) dω for a white Lambertian facet at θ_p = θ_i
    (TABLE_COS steps from 0 to acos(``cos_min``)), azimuth φ_j (TABLE_PHI steps over [0, π/2])
    in the slopes' principal frame, and G1(ω_i) = g_k³ (g_k: TABLE_G steps from 0 to 1).

    With ``derivatives``: (B, ∂B/∂σ1, ∂B/∂σ2) at fixed G1(ω_i) (its own σ-dependence is the
    lookup's), by the same quadrature: ∂S/∂Λ(ω) = −(1 + Λ_i)/(1 + Λ_i + Λ(ω))². Cached (scenes
    that share a map rebuild the same tables after each update): treat the arrays as read-only.

    ``scales`` (a tuple, :func:`local_scales`): one table for each neighbourhood whose slopes are the
    map's times a scale k, shape (TABLE_COS, TABLE_PHI, len(scales), TABLE_G), read by :func:`lookup`
    with its ``k``; the derivatives are still with respect to the map's σ1, σ2. ``needed`` (a tuple
    of indices, :func:`needed_scales`; None: all): the scales a lookup can read, the only ones
    computed."""
    if scales is not None:
        return _scaled_tables(sigma1, sigma2, cos_min, derivatives, scales, needed)
    g = np.linspace(0.0, 1.0, TABLE_G) ** 3
    lam_i = np.where(g > 0, 1.0 / np.maximum(g, 1e-30) - 1.0, 1e30)[:, None]
    directions = _table_directions(cos_min)
    shape = (TABLE_PHI, TABLE_G, directions[0][0].shape[1])
    work = (np.empty(shape, np.float32), np.empty(shape, np.float32), np.empty(shape, np.float64))
    rows = [_table_row(row, 1.0 + lam_i, sigma1, sigma2, derivatives, work) for row in directions]
    table, d1, d2 = np.stack(rows, 1)
    out = (np.clip(table, 0.0, 1.0).astype(np.float32), d1.astype(np.float32), d2.astype(np.float32))
    for a in out:
        a.setflags(write=False)
    return out if derivatives else out[0]


def _gather(table, index):
    """table[index]: a Dr.Jit gather in JIT variants, numpy indexing in scalar ones."""
    if dr.is_jit_v(mi.Float):
        return dr.gather(mi.Float, table, index)
    return float(table[int(index)])


def _held(x, differentiable):
    """x, its derivative dropped where ``differentiable`` is false (same value either way)."""
    return dr.select(differentiable, x, dr.detach(x)) if dr.is_diff_v(x) else x


def _axis(x, n):
    """(cell, fraction) of x ∈ [0, 1] on an axis of n nodes."""
    x = dr.clip(x, 0.0, 1.0) * (n - 1)
    x0 = dr.minimum(mi.UInt32(x), n - 2)
    return x0, x - mi.Float(x0)


def _axes(cos_min, cos_p, phi, g):
    """The table's (cell, fraction) along θ_p, φ and G1^⅓. acos at 1 and ∛ at 0 have infinite
    derivatives: there the axis is held (the value is the same)."""
    c = dr.clip(cos_p, cos_min, 1.0)
    theta = _held(dr.acos(c), c < 1.0)
    g = dr.clip(g, 0.0, 1.0)
    return (_axis(theta * (1.0 / math.acos(cos_min)), TABLE_COS), _axis(phi * (2.0 / math.pi), TABLE_PHI),
            _axis(_held(dr.cbrt(g), g > 0.0), TABLE_G))


def lookup(table, cos_min, cos_p, phi, g, k=None):
    """Trilinear lookup of B(θ_p, φ ∈ [0, π/2], G1 = g) in the table (flat, G innermost); with the
    neighbourhood's scale ``k`` (a table of :func:`blocked_table`'s ``scales``), quadrilinear."""
    if k is not None:
        return _lookup_scaled(table, cos_min, cos_p, phi, g, k)
    (xc, fc), (xp, fp), (xg, fg) = _axes(cos_min, cos_p, phi, g)
    acc = mi.Float(0.0)
    for dc, wc in ((0, 1.0 - fc), (1, fc)):
        for dp, wph in ((0, 1.0 - fp), (1, fp)):
            base = ((xc + dc) * TABLE_PHI + (xp + dp)) * TABLE_G + xg
            v0, v1 = _gather(table, base), _gather(table, base + 1)
            acc += (wc * wph) * dr.lerp(v0, v1, fg)
    return acc


def rms_slope(normals: np.ndarray) -> float:
    """(Isotropic summary) √((σ1² + σ2²)/2) of :func:`principal_slopes`."""
    s1, s2, _ = principal_slopes(normals)
    return math.sqrt(0.5 * (s1 * s1 + s2 * s2))


# -- Local statistics: the neighbourhood around each texel ----------------------------------------
#
# A real map is heterogeneous: smooth plains next to craters, and slopes that hold the large-scale
# difference between the low- and high-poly shapes, which masks nothing at the texel's scale. With
# local statistics the neighbourhood of a texel has the map's principal slopes times k(uv):
# k² = (E_w[|s|²] − |E_w[s]|²)/(σ1² + σ2²), the slopes' variance about their mean under a Gaussian
# window w around the texel (LEAN mapping's moments, Olano and Baker 2010), over the map's.

#: The scales k of the local table: u = k/(1 + k) in LOCAL_STEPS steps from 0 to LOCAL_U_MAX (k ≤ 4).
LOCAL_STEPS = 9
#: The width of the finer window, in which a mild neighbourhood's scale k is measured, as a share
#: of the window's (``neighbourhood``): 3 of the default 8 texels (faithful.Model.local_stats).
FINE_WINDOW = 0.375
#: The finer window's least width in cells of the grid the statistics are computed on (up to
#: LOCAL_RES² samples of the map): on a map with more texels than that grid, 3 of 8 texels may be
#: less than a cell, where the grid sees no variation and k would be 0 by construction, not by
#: measurement. (Never wider than the window: there the two are the same.)
FINE_MIN_CELLS = 1.5
LOCAL_U_MAX = 0.8


def local_scales() -> tuple:
    u = np.linspace(0.0, LOCAL_U_MAX, LOCAL_STEPS)
    return tuple(float(x) for x in u / (1.0 - u))


def window_taps(width_cells: float, res: int):
    """(offsets, weights) of a normalised Gaussian of standard deviation ``width_cells`` / 2 grid
    cells, cut at 3 standard deviations and at half the grid (the grid wraps)."""
    sd = max(0.5 * float(width_cells), 1e-3)
    radius = int(min(math.ceil(3.0 * sd), (res - 1) // 2))
    offsets = np.arange(-radius, radius + 1)
    w = np.exp(-0.5 * (offsets / sd) ** 2)
    return offsets, w / w.sum()


def _blur_np(f, taps):
    offsets, weights = taps
    for axis in (0, 1):
        f = sum(w * np.roll(f, -o, axis) for o, w in zip(offsets, weights))
    return f


#: The share ψ = |μ|²/E[|s|²] of a map's second moment that its mean slope μ must hold for the map to
#: have walls (:func:`walls`): below it the mean is the seams' and tangent frames' of a real asset's
#: map (0.015-0.018 on the bunny's), which has no walls; above it the walls' share rises to 1 for a
#: constant map (how it was set: docs/faithful.md §8).
WALL_SHARE_MIN = 0.1


def walls(sx, sy):
    """(ψ_w, w_x, w_y): the share of the relief of a map with the winsorised slopes ``sx``, ``sy``
    (numpy, flat) that is walls, and their mean slope w = ψ_w·μ. A heightfield over a flat macro
    surface has slopes that average to zero; a map whose slopes average to μ ≠ 0 over the whole map
    has walls somewhere (a map tilted the same way everywhere is a sawtooth: tilted facets and
    upright walls). ψ_w rises from 0, where μ holds WALL_SHARE_MIN of the slopes' second moment,
    to 1 for a constant map (docs/faithful.md §7). Zero for a map without slopes."""
    sx, sy = np.asarray(sx, np.float64), np.asarray(sy, np.float64)
    total = float(np.mean(sx * sx + sy * sy)) if sx.size else 0.0
    if not total > 0:
        return 0.0, 0.0, 0.0
    mx, my = float(np.mean(sx)), float(np.mean(sy))
    share = min(max(((mx * mx + my * my) / total - WALL_SHARE_MIN) / (1.0 - WALL_SHARE_MIN), 0.0), 1.0)
    return share, share * mx, share * my


def attached_walls(sx, sy):
    """:func:`walls` as Dr.Jit values that carry the derivatives of the slopes ``sx``, ``sy``."""
    mx, my, total = dr.mean(sx), dr.mean(sy), dr.mean(sx * sx + sy * sy)
    psi = dr.select(total > 0, (mx * mx + my * my) / dr.maximum(total, 1e-30), 0.0)
    share = dr.clip((psi - WALL_SHARE_MIN) * (1.0 / (1.0 - WALL_SHARE_MIN)), 0.0, 1.0)
    return share, share * mx, share * my


def local_field(sx, sy, res: int, taps, total, wall=(0.0, 0.0)):
    """(k, m_x, m_y) on the res × res grid (numpy, float64, flat) from the winsorised slopes ``sx``,
    ``sy`` (flat, the grid's order), ``total`` = σ1² + σ2² of the map and its walls' mean slope
    ``wall`` (:func:`walls`' w): the neighbourhood's scale and its mean slope (the local macro
    surface). The walls are part of every neighbourhood: its mean plane is the window's mean slope
    less the walls', and its second moment about that plane the window's variance plus |w|²."""
    fx, fy = sx.reshape(res, res), sy.reshape(res, res)
    m2, mx, my = (_blur_np(f, taps) for f in (fx * fx + fy * fy, fx, fy))
    var = np.maximum(m2 - mx * mx - my * my, 0.0) + (wall[0] * wall[0] + wall[1] * wall[1])
    k = np.sqrt(var / total) if total > 0 else np.zeros_like(var)
    return k.ravel(), (mx - wall[0]).ravel(), (my - wall[1]).ravel()


def _blur_dr(f, res: int, taps):
    offsets, weights = taps
    i = dr.arange(mi.UInt32, res * res)
    row, col = i // res, i % res
    for axis in (0, 1):
        acc = mi.Float(0.0)
        for o, w in zip(offsets, weights):
            if axis == 0:
                j = ((row + mi.UInt32(int(o) % res)) % res) * res + col
            else:
                j = row * res + (col + mi.UInt32(int(o) % res)) % res
            acc += float(w) * dr.gather(mi.Float, f, j)
        f = acc
    return f


def attached_field(sx, sy, res: int, taps, s1, s2, wall=(0.0, 0.0)):
    """:func:`local_field` as Dr.Jit values that carry the derivatives of the slopes ``sx``, ``sy``
    (Dr.Jit, winsorised as :func:`attached_slopes`), of the map's σ1, σ2 and of ``wall``
    (:func:`attached_walls`' w)."""
    m2, mx, my = (_blur_dr(f, res, taps) for f in (sx * sx + sy * sy, sx, sy))
    wx, wy = wall
    var = dr.maximum(m2 - mx * mx - my * my, 0.0) + (wx * wx + wy * wy)
    total = s1 * s1 + s2 * s2
    ratio = dr.select(total > 0, var / dr.maximum(total, 1e-30), 0.0)
    ok = ratio > 1e-12
    return dr.select(ok, dr.sqrt(dr.select(ok, ratio, 1.0)), 0.0), mx - wx, my - wy


def field_lookup(fields, res: int, u, v):
    """Bilinear lookups of res × res grids (``fields``: flat arrays, u major; cell centres at
    (i + ½)/res) at (u, v), repeating outside the unit square: one value per field."""
    def axis(x):
        x = (x - dr.floor(x)) * res - 0.5
        x0 = dr.floor(x)
        f = x - x0
        i0 = mi.Int32(x0)
        i0 = dr.select(i0 < 0, i0 + res, i0)
        i1 = dr.select(i0 + 1 >= res, i0 + 1 - res, i0 + 1)
        return mi.UInt32(i0), mi.UInt32(i1), f
    a0, a1, fu = axis(u)
    b0, b1, fv = axis(v)

    def one(field):
        def at(a, b):
            return _gather(field, a * res + b)
        return dr.lerp(dr.lerp(at(a0, b0), at(a0, b1), fv), dr.lerp(at(a1, b0), at(a1, b1), fv), fu)
    return [one(f) for f in fields]


def _lookup_scaled(table, cos_min, cos_p, phi, g, k):
    """:func:`lookup` in a table of ``scales`` = :func:`local_scales`: linear in u = k/(1 + k)."""
    (xc, fc), (xp, fp), (xg, fg) = _axes(cos_min, cos_p, phi, g)
    xk, fk = _axis(k / (1.0 + k) * (1.0 / LOCAL_U_MAX), LOCAL_STEPS)
    acc = mi.Float(0.0)
    for dc, wc in ((0, 1.0 - fc), (1, fc)):
        for dp, wph in ((0, 1.0 - fp), (1, fp)):
            at_k = []
            for dk in (0, 1):
                base = (((xc + dc) * TABLE_PHI + (xp + dp)) * LOCAL_STEPS + (xk + dk)) * TABLE_G + xg
                at_k.append(dr.lerp(_gather(table, base), _gather(table, base + 1), fg))
            # Along k as a + (b − a)·f: where two scales' entries are equal (a map without
            # slopes), k's derivative is exactly 0, not the rounding of −w·a + w·a.
            acc += (wc * wph) * (at_k[0] + (at_k[1] - at_k[0]) * fk)
    return acc
