"""BSDF-level derivative checks: forward and reverse AD against central finite differences.

The loss is a BSDF query averaged over many queries: L(θ) = (1/n) Σ_k q_k(θ), with
q_k = the mean over RGB of ``eval`` (or of ``pdf``, or of a sample's weight times a fixed
test function of its direction). Every query answers with its own derivative in forward
mode, so the AD estimate comes with a standard error; the finite difference uses the same
queries at θ ± h (common random numbers: the walks hash their random numbers from the
query, never from θ), and its per-query differences give it a standard error too. The
two are paired query by query: ``se`` is the standard error of the mean of the per-query
differences AD − FD, the right yardstick for their agreement.

Parameters: ``strength``, a nested BSDF's float parameter (``nested_bsdf.alpha``), or one
texel channel of the normal map (``("texel", index, channel)`` on an N×1 map: every stored
row of column ``index``; Mitsuba stores a one-row bitmap as two).
"""

from __future__ import annotations

from dataclasses import dataclass

import drjit as dr
import mitsuba as mi
import numpy as np

from helpers import floats, make_si, point2, random_hemisphere, tensor, vec3


@dataclass
class Check:
    """One derivative: forward AD (mean, its standard error), reverse AD (None: not taken), FD
    (mean, its standard error), the paired standard error of AD − FD, and the standard error of the FD's
    mean over several steps (0 for one step; included in ``se``): its float32 rounding, and
    for a sample's weight also the branches that flip between steps."""
    ad: float
    ad_se: float
    rev: float | None
    fd: float
    fd_se: float
    se: float
    fd_step_se: float = 0.0

    def agrees(self, n_se=4.0, rel=0.03, atol=1e-7):
        """|AD − FD| within n_se paired standard errors plus rel × |FD| plus atol (float32
        rounding of the FD: ~ulp(L)/h; 0 where a tiny derivative must itself be checked), and the
        same for reverse mode, whose value is the forward mean's up to float rounding."""
        tol = n_se * self.se + rel * abs(self.fd) + atol
        return abs(self.ad - self.fd) <= tol and (self.rev is None or abs(self.rev - self.fd) <= tol + 1e-6 * abs(self.fd))

    def __str__(self):
        rev = "" if self.rev is None else f" (rev {self.rev:+.5g})"
        return (f"AD {self.ad:+.5g} ± {self.ad_se:.2g}{rev}, FD {self.fd:+.5g} "
                f"± {self.fd_se:.2g} (steps ± {self.fd_step_se:.2g}), paired SE {self.se:.2g}")


# The deterministic models' FD steps, as factors of h: nine steps from 0.8h to 1.2h, over which
# the O(h²) truncation moves by far less than the 3 % tolerance, while the float32 rounding
# changes from step to step. Measured (analytic, eval, the strength-zero one-sided FD at
# h = 1e-3, which is 0 in exact arithmetic): single-step FDs from −2.8e-7 to +4.1e-6 at steps
# 0.8e-3 … 1.2e-3 on an AVX-512 machine, −4.8e-6 to +2.1e-6 with Dr.Jit's LLVM target set to
# AVX2 (jit_llvm_set_target), and a CI machine −2.5e-6 at h = 1e-3. The standard error over the
# steps is their resolution.
STEPS = tuple(np.linspace(0.8, 1.2, 9))


def mean_over_steps(fds):
    """(the mean of the FD arrays ``fds``, one per step, and the standard error of its overall
    mean over the steps: 0 for one step)."""
    k = len(fds)
    se = float(np.std([f.mean() for f in fds], ddof=1) / np.sqrt(k)) if k > 1 else 0.0
    return np.mean(fds, axis=0), se


def queries(n, n_texels, seed=0, z_min=0.02, wi_z_max=1.0):
    """(si, wo, u): n queries on texels k mod n_texels, random wi (cosθ_i ≤ wi_z_max) and wo,
    distinct positions."""
    rng = np.random.default_rng(seed)
    wi = random_hemisphere(rng, n, z_min)
    if wi_z_max < 1.0:
        z = rng.uniform(z_min, wi_z_max, n)
        r = np.sqrt(1.0 - z * z)
        phi = np.arctan2(wi[:, 1], wi[:, 0])
        wi = np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)
    wo = random_hemisphere(rng, n, z_min)
    u = rng.random((n, 3)).astype(np.float32)
    si = make_si(wi, n_texels, p_index=np.arange(n))
    return si, vec3(wo), u


def _with_value(params, key, value):
    """Write θ = value into the parameter ``key``; returns the Dr.Jit array written."""
    if isinstance(key, tuple):
        _, index, channel = key
        data = np.array(params["normalmap.data"]).copy()
        data[:, index, channel] = value        # Mitsuba stores a 1-row bitmap as 2 rows
        key = "normalmap.data"
        arr = tensor(data)
    else:
        arr = type(params[key])(value)
    params[key] = arr
    params.update()
    return params[key]


def _value(params, key):
    if isinstance(key, tuple):
        _, index, channel = key
        return float(np.array(params["normalmap.data"])[0, index, channel])
    return float(np.array(params[key]).ravel()[0])


def test_function(w):
    """c(ω) = 1 + ω_x + ½ω_y: weights eval by its light direction (and a sample's weight by its
    direction), so that the loss sees where the lobes lie and not only how much energy leaves
    (which an energy-conserving model keeps nearly constant)."""
    return 1.0 + w.x + 0.5 * w.y


def query_values(bsdf, si, wo, u, what="eval", c=test_function):
    """Per-query values q_k: the RGB mean of eval·c(ω_o), of pdf·c(ω_o), or of a sample's
    weight·c(its direction) (c: :func:`test_function` unless given)."""
    ctx = mi.BSDFContext()
    if what == "eval":
        v = bsdf.eval(ctx, si, wo)
        return (v[0] + v[1] + v[2]) / 3.0 * c(wo)
    if what == "pdf":
        return bsdf.pdf(ctx, si, wo) * c(wo)
    if what == "sample":
        bs, w = bsdf.sample(ctx, si, floats(u[:, 0]), point2(u[:, 1:]))
        return (w[0] + w[1] + w[2]) / 3.0 * c(bs.wo)
    raise ValueError(what)


def _attached(bsdf, key):
    """(the BSDF's parameters, θ's value, the array that holds θ, with derivatives enabled)."""
    params = mi.traverse(bsdf)
    theta = _value(params, key)
    arr = _with_value(params, key, theta)
    dr.enable_grad(arr)
    params.update()
    return params, theta, arr


def forward(bsdf, key, si, wo, u, what="eval", c=test_function):
    """Every query's forward-mode derivative dq_k/dθ for the parameter ``key`` (numpy; ``c``:
    :func:`query_values`)."""
    params, theta, arr = _attached(bsdf, key)
    q = query_values(bsdf, si, wo, u, what, c)
    if isinstance(key, tuple):
        _, index, channel = key
        seed = np.zeros(np.array(arr).shape, np.float32)
        seed[:, index, channel] = 1.0
        dr.set_grad(arr, tensor(seed))
    else:
        dr.set_grad(arr, 1.0)
    d_q = np.array(dr.forward_to(q, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad), np.float64)
    _with_value(params, key, theta)
    return d_q


def reverse(bsdf, key, si, wo, u, what="eval"):
    """dL/dθ of the queries' mean L by reverse mode."""
    params, theta, arr = _attached(bsdf, key)
    loss = dr.mean(query_values(bsdf, si, wo, u, what))
    dr.backward(loss, flags=dr.ADFlag.Default | dr.ADFlag.AllowNoGrad)
    g = np.array(dr.grad(arr), np.float64)
    _with_value(params, key, theta)
    return float(g[:, key[1], key[2]].sum()) if isinstance(key, tuple) else float(g.ravel()[0])


def finite_differences(bsdf, key, si, wo, u, h, what="eval", one_sided=False, steps=(1.0,)):
    """Every query's FD at step h (common random numbers; ``one_sided``, ``steps``: :func:`check`):
    (their mean over the steps, the standard error of its overall mean over the steps)."""
    params = mi.traverse(bsdf)
    theta = _value(params, key)

    def at(x):
        _with_value(params, key, x)
        with dr.suspend_grad():
            return np.array(query_values(bsdf, si, wo, u, what), np.float64)
    fds = []
    base = at(theta) if one_sided else None
    for s in steps:
        hs = h * s
        if one_sided:
            fds.append((-3.0 * base + 4.0 * at(theta + hs) - at(theta + 2 * hs)) / (2 * hs))
        else:
            fds.append((at(theta + hs) - at(theta - hs)) / (2 * hs))
    _with_value(params, key, theta)
    return mean_over_steps(fds)


def paired(d_q, rev, fd):
    """The :class:`Check` of per-query derivatives ``d_q`` (reverse mode's ``rev``, or None)
    against ``fd`` = (per-query FDs, their steps' standard error)."""
    fd_q, step_se = fd
    n = d_q.size
    se = float((d_q - fd_q).std() / np.sqrt(n))
    return Check(ad=float(d_q.mean()), ad_se=float(d_q.std() / np.sqrt(n)), rev=rev,
                 fd=float(fd_q.mean()), fd_se=float(fd_q.std() / np.sqrt(n)),
                 se=float(np.hypot(se, step_se)), fd_step_se=step_se)


def check(bsdf, key, si, wo, u, h, what="eval", one_sided=False, steps=(1.0,)):
    """The :class:`Check` of dL/dθ for the parameter ``key`` at its current value, FD step h
    (``one_sided``: second-order forward difference (−3L(θ) + 4L(θ+h) − L(θ+2h))/2h, for θ on
    the boundary of its domain, e.g. strength = 0).

    ``steps``: the FD is the mean of the FDs at the steps h·s, s in ``steps``, and its rounding
    error the standard error of that mean. The deterministic models need it: their FD's
    float32 rounding does not average out over the queries, since it enters mostly through
    values the queries of one texel share (the texel's normal at θ ± h; four texels), and it
    depends on the CPU (LLVM's target: see :data:`STEPS`)."""
    d_q = forward(bsdf, key, si, wo, u, what)
    rev = reverse(bsdf, key, si, wo, u, what)
    return paired(d_q, rev, finite_differences(bsdf, key, si, wo, u, h, what, one_sided, steps))
