"""The random walks' derivatives: the replayed walk (docs/model.md §9).

With derivatives, a walk runs twice: once for its value, detached, and once more with the same
numbers for its derivative (:class:`Replay`), carrying the derivatives of the non-separable
walk's height interval along (``Walker.ja``, ``jb``, :func:`attached_interval` and the
jacobians of its moves). :func:`replays` says where a walk is replayed, :func:`calls` how the
nested BSDF is called (inlined, or through one callable per method).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi

from mfnormal.surface import microsurface as ms
from mfnormal.surface.microsurface import negate

def _rel(f):
    """f/detach(f) − 1: value 0, derivative df/f (per channel)."""
    fd = dr.detach(f)
    ok = fd != 0.0
    return dr.select(ok, f / dr.select(ok, fd, 1.0) - 1.0, 0.0)


@dataclass
class Replay:
    """A walk's derivative, built while the walk is replayed (loop state of the replay).

    The replayed walk carries only detached values from vertex to vertex; what a vertex
    adds or multiplies is recomputed attached to the microsurface (ω_p) and the nested
    BSDF, and ``G`` sums zero-valued terms whose derivative is the estimate's. For eval,
    L = Σ_k e_k N_k and dL = Σ_k e_k dN_k + Σ_j (what L gains after factor j)·df_j/f_j
    (the reformulation of path replay backpropagation, Vicini et al. 2021), which needs
    the walk's L from a first, primal pass (``total``) and the contributions so far
    (``done``); for sample, de = e·Σ_j df_j/f_j. The loop's derivative is thereby a sum
    over its iterations, which Dr.Jit reverses without storing the walk (its sum-style
    reverse mode, ``max_iterations=-1``). The non-separable walk's interval [a, b]
    depends on ω_p through every crossing before: the walker carries its Jacobian
    (``Walker.ja``, ``jb``), and a vertex uses a + ja·Δ with Δ = ω_p − detach(ω_p).
    """

    G: mi.Spectrum
    done: mi.Spectrum = None    # eval only
    total: mi.Spectrum = None
    exit: mi.Vector3f = None    # sample only: zero-valued, the exit direction's derivative

    def leave(self, d, mask):
        """The walk leaves along d (attached after a delta event: the mirror or a delta lobe):
        the exit direction takes d's derivative. (Directions are detached from one vertex
        to the next: a walk keeps the derivative of its last delta event only.)"""
        if self.exit is not None:
            self.exit = self.exit + dr.select(mask, d - dr.detach(d), 0.0)

    def factor(self, f, mask, after_extra=0.0):
        """e ← e·f for attached f (value detach(f)): G += (what L gains after it)·df/f."""
        rel = _rel(f)
        if self.total is not None:
            rel = (self.total - self.done + after_extra) * rel
        self.G = self.G + dr.select(mask, rel, 0.0)

    def add(self, c, mask):
        """L ← L + c for an attached contribution c (its throughput detached)."""
        self.G = self.G + dr.select(mask, c - dr.detach(c), 0.0)
        self.done = self.done + dr.select(mask, dr.detach(c), 0.0)


def replays(sp):
    """Whether a walk at ``sp`` needs its derivative: ω_p, ω_i or the nested BSDF (a probe
    evaluation, which costs nothing in kernels) carry derivatives."""
    if not dr.is_diff_v(mi.Float):
        return False
    return dr.grad_enabled(sp.wp) or dr.grad_enabled(sp.wi) or sp.nested_attached()


def calls(sp, params):
    """``sp`` with indirect nested calls where ``params.indirect_calls`` is set and no derivative
    is taken (``replays``): forward mode through a callable's implicit inputs (the nested
    BSDF's parameters) inside the walk loops fails in Dr.Jit 1.5 (an edge outside the
    dr.isolate_grad scope)."""
    return sp.with_indirect_calls() if params.indirect_calls and not replays(sp) else sp


def attached_interval(sp, w, rp):
    """The walker's [a, b] with the derivative of its dependence on ω_p (replayed
    non-separable walks), else as it is."""
    if rp is None or w.ja is None:
        return w.a, w.b
    delta = sp.wp - dr.detach(sp.wp)
    return w.a + dr.dot(w.ja, delta), w.b + dr.dot(w.jb, delta)


def _crest_jacobian(sp, on_p, d, d_pre, sign):
    """(∂τ/∂ω_p, ∂κ/∂ω_p) of ``sp.crest_map(on_p, d)`` for a ray along d (detached) whose
    across-groove component is x = −⟨d, ω_t⟩ = sign·⟨d_pre, p_xy⟩/sinθ_p: d = d_pre leaving
    a vertex (sign 1), or d = flip_t(d_pre) leaving the mirror (sign −1; d_z = d_pre_z, and
    only ω_t moves). With r = cotθ_p d_z/|x|: toward the wall τ = r/(1 + r), κ = 1 + r;
    from it τ = r, κ = 1/(1 − r) (microsurface.crest_map)."""
    wp, s, cot = dr.detach(sp.wp), dr.detach(sp.sin_p), dr.detach(sp.cot_p)
    ok = s > 0
    inv = dr.select(ok, dr.rcp(dr.select(ok, s, 1.0)), 0.0)
    c = d_pre.x * wp.x + d_pre.y * wp.y
    x = sign * c * inv
    g_x = (sign * inv) * mi.Vector3f(d_pre.x - c * wp.x * inv * inv, d_pre.y - c * wp.y * inv * inv, 0.0)
    g_cot = mi.Vector3f(-wp.z * wp.x, -wp.z * wp.y, s * s) * (inv * inv * inv)
    ax = dr.maximum(dr.abs(x), 1e-30)
    raw = cot * d.z / ax
    r = dr.clip(raw, -1e30, 1e30)
    free = ok & (dr.abs(raw) < 1e30) & (dr.abs(x) > 1e-30)
    g_r = dr.select(free, (d.z / ax) * g_cot - (cot * d.z * dr.sign(x) / (ax * ax)) * g_x, 0.0)
    to_wall = on_p & (x > 0)
    from_wall = negate(on_p) & (x < 0) & (r < 1.0)
    k_p, k_t = 1.0 + r, 1.0 - r
    g_tau = dr.select(to_wall & (k_p > 1e-30), g_r / (k_p * k_p), dr.select(from_wall, g_r, 0.0))
    g_k = dr.select(to_wall & (k_p > 1e-30), g_r,
                    dr.select(from_wall & (k_t > 1e-30), g_r / (k_t * k_t), 0.0))
    return g_tau, g_k


def _land_jacobian(lo, hi, j_lo, j_hi, tau, k, g_tau, g_k):
    """The Jacobians of microsurface.land's [lo', hi'] from those of lo, hi, τ and κ."""
    finite = k < ms.INF
    k, tau = dr.select(finite, k, 1.0), dr.select(finite, tau, 0.0)
    hi_raw, lo_raw = k * (hi - tau), k * (lo - tau)
    hi_new = dr.clip(hi_raw, 0.0, 1.0)
    g_hi = dr.select((hi_raw > 0.0) & (hi_raw < 1.0), (hi - tau) * g_k + k * (j_hi - g_tau), 0.0)
    g_lo = dr.select(lo_raw > hi_new, g_hi, dr.select(lo_raw > 0.0, (lo - tau) * g_k + k * (j_lo - g_tau), 0.0))
    return dr.select(finite, g_lo, 0.0), dr.select(finite, g_hi, 0.0)


def _g1_jacobian(sp, w, on_p):
    """∂G1(w, ω_m)/∂ω_p (microsurface.G1; ω_m = ω_p where on_p, else ω_t): the first
    interval's, G1 = wp_z w_z / Ã(w) below 1, Ã = ⟨w, ω_p⟩₊ + ⟨w_xy, −p_xy⟩₊."""
    wp = dr.detach(sp.wp)
    a_p, a_t = dr.dot(w, wp), -(w.x * wp.x + w.y * wp.y)
    total = dr.maximum(a_p, 0.0) + dr.maximum(a_t, 0.0)
    ok = total > 0
    inv = dr.select(ok, dr.rcp(dr.select(ok, total, 1.0)), 0.0)
    wz = dr.maximum(w.z, 0.0)
    g = wp.z * wz * inv
    g_total = dr.select(a_p > 0, w, 0.0) + dr.select(a_t > 0, mi.Vector3f(-w.x, -w.y, 0.0), 0.0)
    grad = (mi.Vector3f(0.0, 0.0, wz) - g * g_total) * inv
    facing = dr.select(on_p, a_p > 0, a_t > 0)
    return dr.select(facing & ok & (g < 1.0), grad, 0.0)
