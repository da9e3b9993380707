"""Fuzzing the other normal sources of ``normalmap_microfacet``: ``heightmap`` and
``macro_normal="geometric"``, for every model × tangent facet.

The hostile inputs are the ones these options add to the normal-map path's
(tests/test_fuzz.py):

- height maps with NaN, ±Inf, huge (1e30) and denormal heights next to ordinary ones
  (bilinear: their gradient is NaN/Inf/huge across a whole cell), ``height_scale`` from
  0 and 1e-30 to −3 and 1e6;
- per-query triangle normals ``si.n``: ordinary tilts up to 89°, exactly the shading normal,
  its opposite, perpendicular to it (the wedge at a smooth mesh's silhouette), beyond 90°, zero,
  NaN, huge; per-query ``dp_du``/``dp_dv``: ordinary, zero, NaN, parallel, huge, tiny;
- directions: test_fuzz's special directions and random ones in the shading frame, and as
  many again in the triangle's frame (grazing its plane down to 1e-8, exactly in it, below it);
- the normal maps of test_fuzz (NaN, Inf, zero, horizontal, downward texels) under the
  geometric macro normal.

Checked on every query (exactly, no tolerance unless stated): eval, pdf, eval_pdf and the
sample's weight and pdf finite and ≥ 0; eval and pdf zero unless ω_i and ω_o lie above the
macro plane (the shading plane for ``heightmap``; for ``geometric`` the triangle's, oriented to
the shading normal's side, or the shading plane where si.n is degenerate: |si.n|² in float32
≤ 1e-12 or not finite); pdf > 0 wherever
eval > 1e-30; eval_pdf = (eval, pdf) (relative 1e-4 for faithful/analytic, bit for bit for the
walks); a sample with weight > 0 is a finite unit vector above the macro plane with pdf > 0;
white furnace (white Lambertian facets, GROUPS groups of one (si.n, uv, ω_i) each): mean
sample weight ≤ 1 + 2e-3 + 5 standard errors. Each call runs under a watchdog.

One example per (model, config) with fixed seeds; the nested BSDF rotates over the cases
(white diffuse, roughplastic, roughconductor α 1e-3…1). ``MFNORMAL_FUZZ_LONG=1`` runs 12
examples per case (every nested kind) with 4× the queries.
"""

import faulthandler
import os
import time
import zlib

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
from variant import VARIANT  # noqa: E402  (MFNORMAL_VARIANT, tests/variant.py)
import numpy as np
import pytest

mi.set_variant(VARIANT)
mfnormal.register()

from helpers import floats, np1, np3, point2, vec3  # noqa: E402
from test_fuzz import SPECIAL_DIRECTIONS, SPECIAL_TEXELS, random_directions, random_texels  # noqa: E402

LONG = os.environ.get("MFNORMAL_FUZZ_LONG", "") not in ("", "0")
EXAMPLES = 12 if LONG else 1
QUERIES = (1 << 18) if LONG else (1 << 16)
GROUPS, GROUP_M = 16, 4096
SLACK = 2e-3
HANG_S = 300.0
TEX = 64
EVAL_UNDERFLOW = 1e-30
ONE_MINUS_EPS = float(np.float32(1.0 - 2.0 ** -24))
NAN, INF = float("nan"), float("inf")

MODELS = [("faithful", "specular"), ("analytic", "specular"), ("separable", "specular"), ("separable", "same"),
          ("nonseparable", "specular"), ("nonseparable", "same")]
CONFIGS = ["heightmap", "geometric_nomap", "geometric_normalmap", "geometric_heightmap"]
WHITE = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}


def nested(kind, rng):
    if kind == 0:
        return WHITE
    if kind == 1:
        return {"type": "roughplastic", "distribution": "ggx", "alpha": float(rng.choice([0.01, 0.3, 1.0])),
                "diffuse_reflectance": {"type": "rgb", "value": rng.uniform(0, 1, 3).tolist()}}
    return {"type": "roughconductor", "distribution": str(rng.choice(["ggx", "beckmann"])),
            "alpha": float(rng.choice([1e-3, 0.05, 0.5, 1.0]))}


def hostile_heights(rng):
    """TEX × TEX heights: smooth random ones with special values sprinkled in."""
    h = rng.normal(0, rng.choice([1e-3, 0.05, 0.5]), (TEX, TEX))
    specials = [NAN, INF, -INF, 1e30, -1e30, 1e-40, 0.0, 3.4e38]
    k = rng.integers(0, TEX * TEX, 24)
    h.ravel()[k] = rng.choice(specials, 24)
    return h.astype(np.float32)


def unit(v):
    with np.errstate(invalid="ignore", divide="ignore"):
        return v / np.linalg.norm(v, axis=-1, keepdims=True)


def triangle_normals(rng, n):
    """Per-query si.n: ordinary tilts and the degenerate cases of the module docstring."""
    t = np.radians(rng.uniform(0, 89, n))
    p = rng.uniform(0, 2 * np.pi, n)
    ng = np.stack([np.sin(t) * np.cos(p), np.sin(t) * np.sin(p), np.cos(t)], 1)
    kind = rng.integers(0, 20, n)
    ng[kind == 0] = [0, 0, 1]
    ng[kind == 1] = [0, 0, -1]
    ng[kind == 2, 2] = 0.0
    ng[kind == 3, 2] *= -1.0                                      # beyond 90°
    ng[kind == 4] = 0.0
    ng[kind == 5] = [NAN, 0, 1]
    ng[kind == 6] *= 1e30
    ng[kind == 7] = [1e-40, 0, 1e-40]
    return ng


def parametrisation(rng, n):
    du = rng.normal(0, 1, (n, 3))
    dv = rng.normal(0, 1, (n, 3))
    kind = rng.integers(0, 20, n)
    du[kind == 0] = 0.0
    dv[kind == 1] = [NAN, 0, 0]
    dv[kind == 2] = du[kind == 2] * 3.0                           # parallel
    du[kind == 3] *= 1e30
    dv[kind == 4] *= 1e-30
    return du, dv


def macro_planes(ng, geometric):
    """The macro normal per query, numpy: the shading normal, or si.n turned to its side
    (the shading normal where si.n is degenerate), as the plugin defines it."""
    n = len(ng)
    z = np.tile([0.0, 0.0, 1.0], (n, 1))
    if not geometric:
        return z
    with np.errstate(invalid="ignore", over="ignore"):
        g = ng.astype(np.float32)
        len2 = np.sum(g * g, 1, dtype=np.float32)
        ok = np.isfinite(len2) & (len2 > 1e-12)
    out = z.copy()
    out[ok] = unit(g[ok].astype(np.float64))
    out[ok] *= np.where(out[ok, 2] < 0, -1.0, 1.0)[:, None]
    return out


def in_frame(d, n):
    """Directions d given in a frame whose z is n (per row)."""
    a = np.where(np.abs(n[:, :1]) < 0.9, [[1.0, 0, 0]], [[0, 1.0, 0]])
    s = unit(np.cross(n, a))
    t = np.cross(n, s)
    return d[:, :1] * s + d[:, 1:2] * t + d[:, 2:3] * n


def directions(rng, n, macro):
    """Half in the shading frame (special and random), half in the macro frame."""
    d = random_directions(rng, n)
    special = rng.random(n) < 0.1
    d[special] = SPECIAL_DIRECTIONS[rng.integers(0, len(SPECIAL_DIRECTIONS), special.sum())]
    m = rng.random(n) < 0.5
    d[m] = in_frame(d[m], macro[m])
    return d


def build(config, rng, n):
    """The queries: si (n), wi, wo, u, macro normals and the white-furnace slice."""
    geometric = config.startswith("geometric")
    ng = triangle_normals(rng, n) if geometric else np.tile([0.0, 0.0, 1.0], (n, 1))
    g = GROUPS * GROUP_M
    start = n - g
    ng[start:] = np.repeat(ng[start:start + GROUPS], GROUP_M, 0)
    macro = macro_planes(ng, geometric)
    wi, wo = directions(rng, n, macro), directions(rng, n, macro)
    wi_g = wi[start:start + GROUPS].copy()
    wi_g *= np.where(np.sum(wi_g * macro[start:start + GROUPS], 1) < 0, -1.0, 1.0)[:, None]
    wi[start:] = np.repeat(wi_g, GROUP_M, 0)
    du, dv = parametrisation(rng, n)
    uv = rng.random((n, 2))
    uv[start:] = np.repeat(uv[start:start + GROUPS], GROUP_M, 0)
    du[start:], dv[start:] = np.repeat(du[start:start + GROUPS], GROUP_M, 0), np.repeat(dv[start:start + GROUPS], GROUP_M, 0)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    with np.errstate(over="ignore"):
        si.n = mi.Normal3f(*(floats(ng[:, i]) for i in range(3)))
        si.dp_du, si.dp_dv = vec3(du), vec3(dv)
    si.uv = point2(uv)
    k = np.arange(n)
    si.p = mi.Point3f(floats(k % 4096), floats(k // 4096), floats(np.zeros(n)))
    si.wi = vec3(wi)
    u = np.minimum(rng.random((n, 3)), ONE_MINUS_EPS).astype(np.float32)
    return si, wi.astype(np.float32).astype(np.float64), wo.astype(np.float32), u, macro, slice(start, n)


def make_bsdf(model, facet, config, rng, kind):
    spec = {"type": "normalmap_microfacet", "model": model, "bsdf": nested(kind, rng)}
    if model not in ("faithful", "analytic"):
        spec["tangent_facet"] = facet
    if config.startswith("geometric"):
        spec["macro_normal"] = "geometric"
    if config.endswith("heightmap"):
        spec["heightmap"] = {"type": "bitmap", "bitmap": mi.Bitmap(hostile_heights(rng)[..., None]), "raw": True,
                             "filter_type": "bilinear", "wrap_mode": "repeat"}
        spec["height_scale"] = float(rng.choice([0.0, 1e-30, 1.0, 100.0, -3.0, 1e6]))
    if config == "geometric_normalmap":
        texels = np.concatenate([SPECIAL_TEXELS, random_texels(rng, TEX * TEX - len(SPECIAL_TEXELS))])
        rng.shuffle(texels)
        spec["normalmap"] = {"type": "bitmap", "bitmap": mi.Bitmap(texels.reshape(TEX, TEX, 3).copy()),
                             "raw": True, "filter_type": "nearest"}
        spec["strength"] = float(rng.choice([1.0, 0.0, 100.0]))
    return spec, mi.load_dict(spec)


def timed(fn):
    faulthandler.dump_traceback_later(HANG_S, exit=True)
    try:
        start = time.perf_counter()
        out = fn()
        assert time.perf_counter() - start < HANG_S
        return out
    finally:
        faulthandler.cancel_dump_traceback_later()


@pytest.mark.parametrize("config", CONFIGS)
@pytest.mark.parametrize("model,facet", MODELS, ids=[f"{m}-{t}" for m, t in MODELS])
def test_fuzzed_normal_sources_are_finite_valid_and_bounded(model, facet, config):
    for example in range(EXAMPLES):
        seed = zlib.crc32(f"{model}-{facet}-{config}-{example}".encode())
        rng = np.random.default_rng(seed)
        kind = (MODELS.index((model, facet)) + CONFIGS.index(config) + example) % 3
        spec, bsdf = make_bsdf(model, facet, config, rng, kind)
        n = QUERIES
        si, wi, wo, u, macro, furnace = build(config, rng, n)
        ctx = mi.BSDFContext()
        value, pdf = timed(lambda: (lambda v, p: (np3(v, n), np1(p, n)))(*bsdf.eval_pdf(ctx, si, vec3(wo))))
        value1 = timed(lambda: np3(bsdf.eval(ctx, si, vec3(wo)), n))
        pdf1 = timed(lambda: np1(bsdf.pdf(ctx, si, vec3(wo)), n))
        bs, w = bsdf.sample(ctx, si, floats(u[:, 0]), point2(u[:, 1:]))
        s_wo, s_pdf, s_w = timed(lambda: (np3(bs.wo, n), np1(bs.pdf, n), np3(w, n)))

        failures = []

        def check(cond, what):
            cond = np.asarray(cond)
            if not cond.all():
                q = np.flatnonzero(~cond)[:3]
                failures.append(f"{what}: {np.sum(~cond)} queries, e.g. " + "; ".join(
                    f"si.n {np.array(si.n).T[k].tolist()}, wi {wi[k].tolist()}, wo {wo[k].tolist()}, "
                    f"eval {value[k].tolist()}, pdf {pdf[k]}, sample {s_wo[k].tolist()} w {s_w[k].tolist()}"
                    for k in q))

        for name, x in (("eval", value), ("pdf", pdf), ("eval()", value1), ("pdf()", pdf1),
                        ("sample weight", s_w), ("sample pdf", s_pdf)):
            x2 = x.reshape(n, -1)
            check(np.all(np.isfinite(x2) & (x2 >= 0), 1), f"{name} not finite and ≥ 0")
        with np.errstate(invalid="ignore"):
            above = (np.sum(wi * macro, 1) > 0) & (np.sum(wo * macro, 1) > 0)
        # Directions within float32 rounding of the macro plane may land on either side.
        near = (np.abs(np.sum(wi * macro, 1)) < 1e-5) | (np.abs(np.sum(wo * macro, 1)) < 1e-5)
        check(np.all(value == 0, 1) | above | near, "eval ≠ 0 below the macro plane")
        check((pdf == 0) | above | near, "pdf ≠ 0 below the macro plane")
        check((pdf > 0) | np.all(value <= EVAL_UNDERFLOW, 1), "eval > 0 where pdf = 0")
        if model in ("faithful", "analytic"):
            check(np.abs(pdf1 - pdf) <= 1e-4 * pdf, "pdf() ≠ eval_pdf's pdf")
            check(np.all(np.abs(value1 - value) <= 1e-4 * value, 1), "eval() ≠ eval_pdf's value")
        else:
            check(pdf1 == pdf, "pdf() ≠ eval_pdf's pdf")
            check(np.all(value1 == value, 1), "eval() ≠ eval_pdf's value")
        live = np.any(s_w > 0, 1)
        with np.errstate(invalid="ignore"):
            check(~live | (np.all(np.isfinite(s_wo), 1) & (np.abs(np.linalg.norm(s_wo, axis=1) - 1) <= 1e-4)),
                  "sampled direction not unit length")
            check(~live | (np.sum(s_wo * macro, 1) > -1e-6), "sampled direction below the macro plane")
        check(~live | (s_pdf > 0), "sample with weight > 0 has pdf 0")
        # Not trivially dead. A white diffuse facet's sample always leaves with weight > 0: most
        # queries from above the macro plane are live (94.6-99.4 % measured). A lossy nested BSDF
        # on a map whose slopes all lie near the 88.9° clamp can leave few alive, as each bounce's
        # nested sample may fail (6 % from above with the separable walk, roughplastic,
        # height_scale 1e6), but never none.
        with np.errstate(invalid="ignore"):
            up = np.sum(wi * macro, 1) > 0
        assert live[up].mean() > 0.5 if kind == 0 else live.any(), (spec["bsdf"], live[up].mean())
        # (A lobe of α ≤ 1e-3 is non-zero on too few random ω_o to count.)
        assert np.any(value > 0) or spec["bsdf"].get("alpha", 1.0) < 0.01, spec["bsdf"]
        if kind == 0:
            y = s_w[furnace, 0].reshape(GROUPS, GROUP_M)
            mean, sem = y.mean(1), y.std(1) / np.sqrt(GROUP_M)
            check(mean <= 1 + SLACK + 5 * sem, f"white furnace: mean weight {mean.max():.5f}")
        assert not failures, f"{spec['bsdf']}, seed {seed}:\n" + "\n".join(failures)
