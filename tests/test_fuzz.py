"""Property-based fuzzing of ``normalmap_microfacet``: no NaN, no hang, no energy gain.

Every model × tangent facet (faithful, analytic; separable and non-separable with a mirror
or a same-material tangent facet) × nested BSDF (diffuse, roughconductor with
α ∈ [1e-4, 1], roughplastic, principled, a delta ``conductor``, the plugin around
``twosided`` and ``twosided`` around the plugin; for the default model also the transmitting
``roughdielectric`` and a delta ``dielectric``) is a pytest case; the default run keeps 24 of the 44
(``DEFAULT_PAIRS``: every model with the branches of its own, every nested BSDF with a
deterministic model and a walk), MFNORMAL_SLOW=1 runs them all. Where the plugin refracts (the
default model with a transmitting nested BSDF, a principled with spec_trans > 0 included), eval
and samples may lie on either side of the surface. In each case
Hypothesis draws what is a *value* in the kernels (the nested BSDF's parameters,
``strength`` ∈ [0, 100] including 0, denormals and 100, the map convention, the
bounce cap, extra adversarial texels — any float32, NaN and ±Inf included — and
extra grazing directions, and a seed); numpy then builds a batch of QUERIES
vectorised queries around those values (``build_batch``):

- every special texel × every special ω_i × every special ω_o (NaN, ±Inf, zero
  vector, exactly flat, horizontal, pointing down, denormal, huge; directions at
  normal incidence, grazing down to 1e-7 and to a denormal z, exactly tangent,
  the zero vector, below the surface);
- directions exactly in, or grazing, the planes of the query's own facets ω_p and
  ω_t and their mirror images (where masking and the mirror flips switch);
- ALBEDO_GROUPS groups of ALBEDO_M queries with one (texel, ω_i) each, for the
  white-furnace bound;
- a random bulk: tilts up to and beyond the horizon, ω_i and ω_o on the whole
  sphere with a share grazing at 10^U(−8, −1).

Per-query normals come from an N_TEXELS×1 float32 bitmap with nearest filtering
(si.uv at texel centres); si.p is the query number (the walks' eval hash).

Checked on every query (exactly, no tolerance unless stated):
- ``eval``, ``pdf``, ``eval_pdf`` and ``sample``'s weight and pdf are finite and
  ≥ 0; eval and pdf are zero unless ω_i and ω_o are above the surface (for
  ``twosided`` around the plugin: on the same side);
- ``eval_pdf`` equals (``eval``, ``pdf``) (relative 1e-4 for the faithful and analytic
  models, whose code paths differ by a few ulps; bit for bit for the walks);
- pdf > 0 wherever eval > EVAL_UNDERFLOW = 1e-30 (else MIS could never reach
  that direction by BSDF sampling);
- a sample with non-zero weight has a finite, unit-length (|‖ω_o‖ − 1| ≤ 1e-4)
  direction above the surface (same side as ω_i) and pdf > 0; no sample from
  ω_i at or below the surface;
- every call returns within HANG_S seconds (walks stop within their cap): a
  watchdog (``faulthandler``) ends the process with a traceback if one does not,
  because a JIT kernel cannot be interrupted otherwise;
- white furnace, for the nested BSDFs that conserve energy in Mitsuba itself
  (diffuse, roughconductor, conductor, linear roughplastic, and ``twosided`` of
  them; except where the plugin is exactly its nested BSDF and the gain is that
  BSDF's own: ``inherited_gain``): per albedo group the mean sample weight, and for non-delta nested BSDFs
  the cosine-sampled estimate of ∫eval dω_o, are ≤ 1 + ALBEDO_SLACK + 5 standard
  errors per channel (false alarm < 3e-7 per group and channel for a correct
  BSDF). ALBEDO_SLACK covers Mitsuba's own float32 excess: the furnace-white
  roughconductor's sample weight is 1.00006 at every ω_i (measured), which a walk
  with a same-material tangent facet compounds over its bounces.
  Not checked for ``principled`` (Mitsuba's principled reaches an albedo of 7.4
  by itself at grazing incidence with sheen = 1, measured) nor for nonlinear
  roughplastic (Mitsuba's reaches 1.16 with a white diffuse base). The standard
  error comes from the same samples, so a heavy tail widens the bound rather than
  raising false alarms: GGX without visible-normal sampling has sample weights up
  to ~1/cosθ_i at facet-grazing incidence (a group mean of 42 ± 9 was seen), and
  with α ≈ 1e-4 the cosine-sampled ∫eval is a few spikes. There the check only
  catches gross gains; the tight furnace tests are in test_analytic.py and
  test_walk.py. (Each run prints the worst group per case: ``pytest -s``.)

CI runs FUZZ_EXAMPLES = 2 Hypothesis examples per case with QUERIES = 2^19
queries each (≥ 10^6 per configuration), derandomised (fixed seed; the first
example is Hypothesis's simplest one, which the strategies make hostile:
strength 100, α = 1e-4, ...). ``MFNORMAL_FUZZ_LONG=1`` runs 20 random examples
of 2^20 queries per case (``MFNORMAL_FUZZ_EXAMPLES=N`` overrides the count);
a failing long run prints the Hypothesis seed to reproduce it. Shrinking is off:
a failure names the offending queries (texel, ω_i, ω_o, sample numbers) itself,
and each run costs seconds.
"""

import faulthandler
import os
import time

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest
from hypothesis import HealthCheck, Phase, example, given, settings
from hypothesis import strategies as st

from variant import VARIANT  # noqa: E402  (MFNORMAL_VARIANT, tests/variant.py)
mi.set_variant(VARIANT)
mfnormal.register()

import helpers  # noqa: E402
from helpers import np1, np3, vec3  # noqa: E402

LONG = os.environ.get("MFNORMAL_FUZZ_LONG", "") not in ("", "0")
FUZZ_EXAMPLES = int(os.environ.get("MFNORMAL_FUZZ_EXAMPLES", 20 if LONG else 2))
QUERIES = (1 << 20) if LONG else (1 << 19)   # per example
N_TEXELS = 4096                                # fixed: the texture's size is the same in every kernel
HANG_S = 300.0                                 # per call (a 2^20 walk batch takes ≤ 20 s here)
ALBEDO_GROUPS, ALBEDO_M = 32, 4096
ALBEDO_SLACK = 2e-3
UNIT_TOL = 1e-4
# eval below this may come with pdf = 0: ω_o within ~1e-30 of the horizon, where the
# pdf's extra factors underflow float32 or round κ to exactly 1 (seen: eval 4e-37 at
# ω_o.z = 1.7e-35, a mirror path with G1 = 1e-28). No energy lives there.
EVAL_UNDERFLOW = 1e-30
ONE_MINUS_EPS = float(np.float32(1.0 - 2.0 ** -24))

MODELS = [("faithful", "specular"), ("analytic", "specular"), ("separable", "specular"), ("separable", "same"),
          ("nonseparable", "specular"), ("nonseparable", "same")]
NESTED_KINDS = ["diffuse", "roughconductor", "roughplastic", "principled", "conductor",
                "plugin_around_twosided", "twosided_around_plugin", "roughdielectric", "dielectric"]
# Nested BSDFs that transmit: the default model only (the paper's models refuse them at load).
TRANSMITTING_KINDS = ("roughdielectric", "dielectric")

FUZZ_SETTINGS = settings(max_examples=FUZZ_EXAMPLES, derandomize=not LONG, database=None, deadline=None,
                         phases=(Phase.explicit, Phase.generate), print_blob=LONG,
                         suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])


# -- Special values --------------------------------------------------------------------------

NAN, INF = float("nan"), float("inf")
DENORMAL = 1e-40          # a float32 denormal
SPECIAL_TEXELS = np.array([
    [0.5, 0.5, 1.0],                                                   # exactly flat
    [NAN, 0.5, 1.0], [0.5, NAN, 1.0], [0.5, 0.5, NAN], [NAN, NAN, NAN],  # NaN
    [INF, 0.5, 1.0], [0.5, -INF, 1.0], [0.5, 0.5, INF], [-INF, INF, -INF],  # ±Inf
    [0.0, 0.0, 0.0], [0.5, 0.5, 0.5],                                  # zero texel, zero normal
    [1.0, 0.5, 0.5], [0.5, 0.0, 0.5], [0.85355339, 0.85355339, 0.5],   # exactly horizontal
    [0.5, 0.5, 0.0], [0.9, 0.6, 0.1], [0.5, 0.5 + 2 ** -24, 0.0],       # pointing down, below
    [0.5 + 2 ** -24, 0.5, 1.0], [0.5, 0.5 - 2 ** -25, 1.0],            # within an ulp of flat
    [0.5 + 2 ** -24, 0.5, 0.5 + 2 ** -24],                             # tiny vector at 45°
    [DENORMAL, DENORMAL, DENORMAL], [0.5, 0.5, 0.5 + DENORMAL],        # denormal texels
    [1e30, -1e30, 1e30], [3.4e38, 3.4e38, 3.4e38], [-3.4e38, 0.5, 1.0],  # huge: 2·rgb − 1 overflows
    [0.99, 0.5, 0.51], [1.0, 1.0, 1.0], [0.0, 1.0, 0.6],               # steep, ordinary, out of range
], np.float32)


def unit(v):
    v = np.asarray(v, np.float64)
    n = np.linalg.norm(v, axis=-1, keepdims=True)
    return np.where(n > 0, v / np.where(n > 0, n, 1.0), 0.0)


SPECIAL_DIRECTIONS = np.concatenate([unit([
    [0, 0, 1], [1e-7, 0, 1], [0.3, 0.2, 0.932738],                     # normal incidence, ordinary
    [1, 0, 1e-7], [-1, 0, 1e-7], [0, 1, 1e-7], [0.6, -0.8, 1e-7],       # grazing at 1e-7
    [1, 0, 1e-4], [0.6, 0.8, 1e-3],
    [1, 0, 0], [-1, 0, 0], [0, -1, 0], [0.6, 0.8, 0],                  # exactly tangent
    [1, 0, -1e-7], [0.5, 0, -0.866025], [0, 0, -1], [0.3, -0.2, -0.9],  # below the surface
]), np.array([[1.0, 0.0, DENORMAL], [0.0, 1.0, -DENORMAL], [0.0, 0.0, 0.0]])])  # denormal z, zero vector
SPECIAL_U = np.array([0.0, 0.5, ONE_MINUS_EPS])


# -- Hypothesis strategies: what is a value in the kernels -----------------------------------


def unit_float(lo=0.0, hi=1.0):
    # No values below 1e-30: Mitsuba passes texture values through a string, and std::stof
    # rejects what underflows float32 (1e-40, and FLT_MIN printed to 6 digits).
    return st.one_of(st.sampled_from([hi, lo]),
                     st.floats(lo, hi, width=32).map(lambda x: x if abs(x) >= 1e-30 else 0.0))


def log_uniform(lo, hi):
    return st.floats(np.log10(lo), np.log10(hi)).map(lambda e: float(10.0 ** e))


def rgb(lo=0.0, hi=1.0):
    return st.lists(unit_float(lo, hi), min_size=3, max_size=3).map(lambda v: {"type": "rgb", "value": v})


alpha = st.one_of(st.sampled_from([1e-4, 1.0]), log_uniform(1e-4, 1.0))


@st.composite
def roughconductor(draw):
    spec = {"type": "roughconductor", "distribution": draw(st.sampled_from(["ggx", "beckmann"])),
            "material": draw(st.sampled_from(["none", "Au"])),
            "sample_visible": draw(st.booleans())}
    if draw(st.booleans()):
        spec["alpha"] = draw(alpha)
    else:
        spec["alpha_u"], spec["alpha_v"] = draw(alpha), draw(alpha)
    return spec


@st.composite
def roughplastic(draw):
    return {"type": "roughplastic", "distribution": draw(st.sampled_from(["ggx", "beckmann"])),
            "alpha": draw(alpha), "int_ior": draw(st.floats(1.01, 2.5)),
            "diffuse_reflectance": draw(rgb()), "nonlinear": draw(st.booleans())}


@st.composite
def principled(draw, transmits=True):
    """Mitsuba's principled; ``transmits`` False: spec_trans = 0 (the paper's models refuse a
    nested BSDF that transmits)."""
    spec = {"type": "principled", "base_color": draw(rgb())}
    for name in ("roughness", "metallic", "specular", "anisotropic", "sheen", "sheen_tint",
                 "clearcoat", "clearcoat_gloss", "spec_tint", "spec_trans"):
        spec[name] = draw(unit_float())
    if not transmits:
        spec["spec_trans"] = 0.0
    return spec


NESTED_STRATEGIES = {
    "diffuse": rgb().map(lambda c: {"type": "diffuse", "reflectance": c}),
    "roughconductor": roughconductor(),
    "roughplastic": roughplastic(),
    "principled": principled(),
    "conductor": st.sampled_from(["none", "Au"]).map(lambda m: {"type": "conductor", "material": m}),
}
NESTED_STRATEGIES["roughdielectric"] = st.fixed_dictionaries({
    "type": st.just("roughdielectric"), "distribution": st.sampled_from(["ggx", "beckmann"]), "alpha": alpha,
    "int_ior": st.floats(1.01, 2.5), "sample_visible": st.booleans()})
NESTED_STRATEGIES["dielectric"] = st.floats(1.01, 2.5).map(lambda eta: {"type": "dielectric", "int_ior": eta})
NESTED_STRATEGIES["plugin_around_twosided"] = st.one_of(
    NESTED_STRATEGIES["roughconductor"], NESTED_STRATEGIES["diffuse"]).map(lambda b: {"type": "twosided", "bsdf": b})
NESTED_STRATEGIES["twosided_around_plugin"] = st.one_of(NESTED_STRATEGIES["diffuse"], NESTED_STRATEGIES["roughplastic"])

strength = st.one_of(st.sampled_from([100.0, 0.0, DENORMAL, 1e-7, 1.0]), st.floats(0.0, 100.0))
any_float32 = st.floats(width=32, allow_nan=True, allow_infinity=True, allow_subnormal=True)


@st.composite
def extra_directions(draw):
    """Grazing (z = 10^−k, k ≤ 8) or arbitrary directions at drawn azimuths, and raw float32 triples."""
    out = []
    for _ in range(draw(st.integers(0, 6))):
        phi = draw(st.floats(0.0, 2.0 * np.pi))
        z = draw(st.one_of(st.floats(-8.0, -0.5).map(lambda e: 10.0 ** e), st.floats(-1.0, 1.0)))
        r = np.sqrt(max(0.0, 1.0 - z * z))
        out.append([r * np.cos(phi), r * np.sin(phi), z])
    return np.array(out, np.float64).reshape(-1, 3)


def fuzz_case(kind, model):
    walk = model not in ("analytic", "faithful")
    nested = principled(transmits=False) if kind == "principled" and model != "faithful" else NESTED_STRATEGIES[kind]
    return st.fixed_dictionaries({
        "nested": nested,
        "strength": strength,
        "convention": st.sampled_from(["opengl", "directx"]),
        "max_bounces": st.sampled_from([1024, 1, 2, 64]) if walk else st.just(1024),
        "mis_boost_max": st.sampled_from([64.0, 1.0, 1e6]) if walk else st.just(64.0),
        "extra_texels": st.lists(st.lists(any_float32, min_size=3, max_size=3), max_size=12),
        "extra_directions": extra_directions(),
        "seed": st.integers(0, 2 ** 32 - 1),
    })


# -- The query batch -----------------------------------------------------------------------------


def decode_ref(texels, strength, directx):
    """ω_p the plugin should decode (float64; bad texels → flat, below the horizon → cosθ_p = 0.02).

    Only used to aim directions at the facet planes, so it need not match to the ulp.
    """
    strength = float(np.float32(strength))     # the plugin holds it in float32
    with np.errstate(all="ignore"):
        n = 2.0 * texels.astype(np.float64) - 1.0
        if directx:
            n[:, 1] = -n[:, 1]
        n[:, :2] *= strength
        norm = np.linalg.norm(n, axis=1)
        ok = np.isfinite(norm) & (norm > 1e-10)
        n = np.where(ok[:, None], n / np.where(ok, norm, 1.0)[:, None], [0.0, 0.0, 1.0])
        xy = np.hypot(n[:, 0], n[:, 1])
        lean = xy * xy > 1e-30
        steep = n[:, 2] < 0.02
        scale = np.sqrt(1 - 0.02 ** 2) / np.where(lean, xy, 1.0)
        clamped = np.stack([n[:, 0] * scale, n[:, 1] * scale, np.full(len(n), 0.02)], 1)
        n = np.where((steep & lean)[:, None], clamped, n)
        return np.where((steep & ~lean)[:, None], [0.0, 0.0, 1.0], n)


def random_sphere(rng, n):
    return unit(rng.normal(size=(n, 3)))


def random_directions(rng, n):
    """Uniform on the sphere, with a fifth grazing at z = ±10^U(−8, −1)."""
    d = random_sphere(rng, n)
    g = rng.random(n) < 0.2
    z = np.sign(rng.random(g.sum()) - 0.2) * 10.0 ** rng.uniform(-8, -1, g.sum())
    phi = rng.uniform(0, 2 * np.pi, g.sum())
    r = np.sqrt(1 - z * z)
    d[g] = np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)
    return d


def random_texels(rng, n):
    """Tilts with cosθ_p uniform in [−0.1, 1] (a tenth below the horizon, clamped to 88.9°),
    plus a tenth raw uniform rgb."""
    cos_p = rng.uniform(-0.1, 1.0, n)
    phi = rng.uniform(0, 2 * np.pi, n)
    s = np.sqrt(1 - cos_p ** 2)
    t = np.stack([s * np.cos(phi), s * np.sin(phi), cos_p], 1) * 0.5 + 0.5
    raw = rng.random(n) < 0.1
    t[raw] = rng.random((raw.sum(), 3))
    return t.astype(np.float32)


def facet_plane_directions(rng, wp):
    """Per row of ω_p, a direction in or near a facet plane (p, t, flip_t of p), or ±ω_p / ±ω_t."""
    n = len(wp)
    xy = np.hypot(wp[:, 0], wp[:, 1])
    wt = np.where((xy > 0)[:, None], np.stack([-wp[:, 0], -wp[:, 1], 0 * xy], 1) / np.where(xy > 0, xy, 1)[:, None],
                  [1.0, 0.0, 0.0])
    flip = lambda w: w - 2 * np.sum(w * wt, 1, keepdims=True) * wt  # noqa: E731
    choice = rng.integers(0, 6, n)
    normal = np.where((choice % 3 == 0)[:, None], wp, np.where((choice % 3 == 1)[:, None], wt, flip(wp)))
    in_plane = unit(np.cross(normal, random_sphere(rng, n)))
    eps = np.where(choice < 3, 0.0, 10.0 ** rng.uniform(-7, -3, n))[:, None]
    d = unit(in_plane + eps * normal)
    # A few are the facet normals themselves.
    special = rng.random(n) < 0.1
    d[special] = np.where((rng.random(special.sum()) < 0.5)[:, None], wp[special], wt[special])
    # Mostly above the surface: these are about masking, not about the lower hemisphere.
    d[:, 2] = np.where(rng.random(n) < 0.85, np.abs(d[:, 2]), d[:, 2])
    return d


def build_batch(case, n):
    """The texels and n queries (texel index, ω_i, ω_o, u ∈ [0,1)³) of one Hypothesis example."""
    rng = np.random.default_rng(case["seed"])
    extra = np.array(case["extra_texels"], np.float32).reshape(-1, 3)
    special = np.concatenate([SPECIAL_TEXELS, extra])
    texels = np.concatenate([special, random_texels(rng, N_TEXELS - len(special))])
    wp = decode_ref(texels, case["strength"], case["convention"] == "directx")
    dirs = np.concatenate([SPECIAL_DIRECTIONS, case["extra_directions"]])

    # Every special texel × ω_i × ω_o.
    t, i, o = (a.ravel() for a in np.meshgrid(np.arange(len(special)), np.arange(len(dirs)),
                                              np.arange(len(dirs)), indexing="ij"))
    blocks = [(t, dirs[i], dirs[o])]
    # Facet planes of the query's own normal.
    m = n // 8
    t = rng.integers(0, N_TEXELS, m)
    blocks.append((t, np.where((rng.random(m) < 0.5)[:, None], facet_plane_directions(rng, wp[t]),
                               random_directions(rng, m)), facet_plane_directions(rng, wp[t])))
    # White-furnace groups: one (texel, ω_i) each, cosine-distributed ω_o.
    g = ALBEDO_GROUPS
    t_g = np.concatenate([rng.integers(0, len(special), g // 4), rng.integers(0, N_TEXELS, g - g // 4)])
    wi_g = np.concatenate([dirs[rng.integers(0, len(dirs), g // 4)], random_directions(rng, g - g // 4)])
    wi_g[:, 2] = np.abs(wi_g[:, 2])
    u = rng.random((g * ALBEDO_M, 2))
    r, phi = np.sqrt(u[:, 0]), 2 * np.pi * u[:, 1]
    wo_cos = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u[:, 0])], 1)
    blocks.append((np.repeat(t_g, ALBEDO_M), np.repeat(wi_g, ALBEDO_M, 0), wo_cos))
    # Random bulk.
    rest = n - sum(len(b[0]) for b in blocks)
    assert rest > n // 4
    blocks.append((rng.integers(0, N_TEXELS, rest), random_directions(rng, rest), random_directions(rng, rest)))

    # Sort the facet-plane and bulk blocks by tilt: a SIMD packet then holds walks of
    # similar length (a packet runs as long as its longest walk), which halves the runtime.
    for j in (1, 3):
        order = np.argsort(wp[blocks[j][0], 2], kind="stable")
        blocks[j] = tuple(x[order] for x in blocks[j])
    t = np.concatenate([b[0] for b in blocks])
    wi = np.concatenate([b[1] for b in blocks]).astype(np.float32)
    wo = np.concatenate([b[2] for b in blocks]).astype(np.float32)
    u = rng.random((n, 3))
    start = len(blocks[0][0]) + len(blocks[1][0])
    albedo = slice(start, start + g * ALBEDO_M)
    # Sample numbers at the ends of [0, 1) for 2 % of the queries, outside the white-furnace
    # groups: there the mean sample weight estimates the albedo only with uniform numbers (the
    # edges select the far tails of a sharp lobe, where a weight is ~1/cosθ_i: a group at
    # ω_i.z = 1e-7 with 27 such draws out of 4096 read 33 ± 6).
    edge = rng.random(n) < 0.02
    edge[albedo] = False
    u[edge] = SPECIAL_U[rng.integers(0, 3, (edge.sum(), 3))]
    return texels, t, wi, wo, np.minimum(u, ONE_MINUS_EPS).astype(np.float32), albedo


# -- Running the queries ---------------------------------------------------------------------------


def make_bsdf(model, tangent_facet, kind, case, texels):
    plugin = {"type": "normalmap_microfacet", "model": model, "tangent_facet": tangent_facet,
              "strength": case["strength"], "normalmap_convention": case["convention"],
              "max_bounces": case["max_bounces"], "mis_boost_max": case["mis_boost_max"], "bsdf": case["nested"],
              "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(texels.reshape(1, -1, 3).copy()), "raw": True,
                            "filter_type": "nearest"}}
    return mi.load_dict({"type": "twosided", "bsdf": plugin} if kind == "twosided_around_plugin" else plugin)


def inherited_zero_pdf(case, kind, si, wo, value, pdf):
    """Queries where the plugin is exactly its nested BSDF (a flat texel: same eval, bit for
    bit) and the nested BSDF itself returns eval > 0 with pdf = 0. Mitsuba's roughplastic
    does (Beckmann α = 1, diffuse reflectance 1e-7, ω_i = ω_o = 1e-7 above the horizon:
    eval 5.9e-16, pdf 0, its specular pdf underflows); no normal mapping can repair that.
    Only these queries are exempt from the eval > 0 ⇒ pdf > 0 check."""
    suspect = (pdf == 0) & np.any(value > EVAL_UNDERFLOW, 1)
    if not suspect.any():
        return suspect
    q = np.flatnonzero(suspect)
    # (``twosided`` around the plugin: the nested BSDF behind the same two-sided flip.)
    own = {"type": "twosided", "bsdf": case["nested"]} if kind == "twosided_around_plugin" else case["nested"]
    nested = mi.load_dict(own)
    sub = dr.gather(type(si), si, helpers.uints(q))
    ctx = mi.BSDFContext()
    own_value, own_pdf = nested.eval_pdf(ctx, sub, vec3(wo[q]))
    own_value, own_pdf = np3(own_value, len(q)), np1(own_pdf, len(q))
    out = np.zeros_like(suspect)
    out[q] = (own_pdf == 0) & np.all(own_value == value[q], 1)
    return out


def inherited_gain(case, si, s_wo, weights, q, u, tilt):
    """Whether albedo group ``q`` (query indices, sample numbers ``u``, texel tilt ``tilt`` rad)
    is one whose gain is the nested BSDF's own. Mitsuba's roughconductor (Beckmann, one α ≤ 1e-3,
    ``sample_visible`` false) at ω_i 1e-7 above the horizon has pdf() ≈ 0.6× its own sample's
    pdf (median): eval/pdf on its own samples averages 1.62 against its sample weight's 0.91 (α
    (1, 1e-4)); a model that weighs a nested sample by eval/pdf cannot repair that. Exempt:
    - the plugin is exactly its nested BSDF (a flat texel): each weight equals the nested eval/pdf
      at that sample's direction (relative 1e-4, as eval = eval_pdf for the deterministic
      models: their code paths differ by a few ulps), and their mean exceeds the bound;
    - or the texel is within 1e-3 rad of flat (its facet frame is the macro frame but for that)
      and the nested BSDF's own eval/pdf on its own samples from the same numbers exceeds the
      bound with a mean the plugin's does not exceed (5 combined standard errors): faithful on a
      1e-5 tilt, α (1.3e-4, 0.22) gold, read 1.38 ± 0.03.
    Only such groups are exempt from the furnace bound."""
    nested = mi.load_dict(case["nested"])
    sub = dr.gather(type(si), si, helpers.uints(q))
    ctx = mi.BSDFContext()

    def ratio(wo):
        value, pdf = nested.eval_pdf(ctx, sub, vec3(wo))
        value, pdf = np3(value, len(q)), np1(pdf, len(q))
        return np.where(pdf[:, None] > 0, value / np.where(pdf > 0, pdf, 1.0)[:, None], 0.0)

    bound = 1.0 + ALBEDO_SLACK
    own = ratio(s_wo[q])
    if np.allclose(weights, own, rtol=1e-4, atol=1e-7):
        return own.mean(0).max() > bound
    if tilt >= 1e-3:
        return False
    bs, _ = nested.sample(ctx, sub, mi.Float(u[q, 0]), mi.Point2f(u[q, 1], u[q, 2]))
    own = ratio(np3(bs.wo, len(q)))
    sem = np.sqrt(weights.var(0) / len(q) + own.var(0) / len(q))
    return own.mean(0).max() > bound and bool(np.all(weights.mean(0) <= own.mean(0) + 5 * sem))


def make_si(t, wi):
    """Queries on texels t with directions wi, query k at si.p = (k, 0, 0)."""
    return helpers.make_si(wi, N_TEXELS, t, np.arange(len(t)))


def timed(label, fn, timings):
    """Run fn (which must return numpy arrays, forcing evaluation) under a watchdog."""
    faulthandler.dump_traceback_later(HANG_S, exit=True)
    start = time.perf_counter()
    try:
        out = fn()
    finally:
        faulthandler.cancel_dump_traceback_later()
    elapsed = time.perf_counter() - start
    timings[label] = elapsed
    assert elapsed < HANG_S, f"{label} took {elapsed:.0f} s"
    return out


def transmits(kind, nested):
    """Whether the plugin refracts (the default model with a nested BSDF that transmits): its
    eval and samples then cover both sides of the surface."""
    return kind in TRANSMITTING_KINDS or (kind == "principled" and nested.get("spec_trans", 0.0) > 0)


def energy_conserving(kind, nested):
    inner = nested["bsdf"] if nested["type"] == "twosided" else nested
    # (Transmitted radiance-mode weights carry the 1/η² radiance scaling: test_faithful_transmission.)
    if kind == "principled" or inner.get("nonlinear", False) or kind in TRANSMITTING_KINDS:
        return False
    return True


def black(nested):
    """A diffuse nested BSDF (or twosided of one) with reflectance 0: every weight is 0."""
    inner = nested["bsdf"] if nested["type"] == "twosided" else nested
    return inner["type"] == "diffuse" and not any(inner["reflectance"]["value"])


def dead_on_its_own(nested, si, wo, u):
    """Whether the nested BSDF alone gives no sample a weight > 0 and no query an eval > 0 on
    these queries (Mitsuba's principled with roughness 0, metallic 1 and a black base colour, or
    an anisotropic one of roughness 0 and metallic 1, is): then the plugin at ``strength`` 0,
    exactly that BSDF, is dead too."""
    bsdf, ctx = mi.load_dict(nested), mi.BSDFContext()
    _, w = bsdf.sample(ctx, si, mi.Float(u[:, 0]), mi.Point2f(u[:, 1], u[:, 2]))
    return not np.any(np3(w, len(u)) > 0) and not np.any(np3(bsdf.eval(ctx, si, vec3(wo)), len(u)) > 0)


def check(cond, what, failures, describe):
    """Record a failure naming up to three offending queries."""
    cond = np.asarray(cond)
    if not cond.all():
        bad = np.flatnonzero(~cond)
        failures.append(f"{what}: {bad.size} queries, e.g. " + "; ".join(describe(k) for k in bad[:3]))


# The model × nested BSDF cases of the default run. A model takes one code path for every smooth,
# one-sided nested BSDF (it calls the nested eval, pdf and sample through Mitsuba's interface);
# the delta ``conductor`` and a two-sided nested BSDF take their own branches in every model, and
# ``twosided`` around the plugin its front-side flip in the plugin. So the default run keeps, per
# model, the conductor and the plugin around ``twosided``; each smooth nested BSDF with a
# deterministic model and a walk (roughconductor, whose α reaches 1e-4, with three); and
# ``twosided`` around the plugin with a deterministic model and a walk. MFNORMAL_SLOW=1 (and
# MFNORMAL_FUZZ_LONG=1) runs every pair.
DEFAULT_PAIRS = {
    ("faithful", "roughconductor"), ("faithful", "roughplastic"), ("faithful", "twosided_around_plugin"),
    ("faithful", "roughdielectric"),
    ("analytic", "diffuse"), ("analytic", "principled"),
    ("separable-specular", "diffuse"),
    ("separable-same", "roughconductor"), ("separable-same", "twosided_around_plugin"),
    ("nonseparable-specular", "roughplastic"),
    ("nonseparable-same", "roughconductor"), ("nonseparable-same", "principled"),
} | {(m if m in ("faithful", "analytic") else f"{m}-{t}", k) for m, t in MODELS
     for k in ("conductor", "plugin_around_twosided")}


def fuzz_params():
    out = []
    for m, t in MODELS:
        name = m if m in ("faithful", "analytic") else f"{m}-{t}"
        for kind in NESTED_KINDS:
            if kind in TRANSMITTING_KINDS and m != "faithful":
                continue
            slow = () if LONG or (name, kind) in DEFAULT_PAIRS else (pytest.mark.slow,)
            out.append(pytest.param(m, t, kind, id=f"{m}-{t}-{kind}", marks=slow))
    return out


@pytest.mark.parametrize("model,tangent_facet,kind", fuzz_params())
@FUZZ_SETTINGS
@given(data=st.data())
def test_fuzzed_queries_are_finite_valid_and_bounded(model, tangent_facet, kind, data):
    case = data.draw(fuzz_case(kind, model), label="case")
    texels, t, wi, wo, u, albedo = build_batch(case, QUERIES)
    n = len(t)
    bsdf = make_bsdf(model, tangent_facet, kind, case, texels)
    ctx = mi.BSDFContext()
    si = make_si(t, wi)

    def eval_pdf():
        value, pdf = bsdf.eval_pdf(ctx, si, vec3(wo))
        return np3(value, n), np1(pdf, n)

    def sample():
        bs, weight = bsdf.sample(ctx, si, helpers.floats(u[:, 0]), helpers.point2(u[:, 1:]))
        return np3(bs.wo, n), np1(bs.pdf, n), np3(weight, n)

    # A walk's eval is eval_pdf's first half, bit for bit: check it on a slice only.
    k = n if model in ("analytic", "faithful") else 1 << 16
    timings = {}
    value, pdf = timed("eval_pdf", eval_pdf, timings)
    pdf_only = timed("pdf", lambda: np1(bsdf.pdf(ctx, si, vec3(wo)), n), timings)
    value_only = timed("eval", lambda: np3(bsdf.eval(ctx, make_si(t[:k], wi[:k]), vec3(wo[:k])), k), timings)
    s_wo, s_pdf, s_w = timed("sample", sample, timings)

    def describe(q):
        return (f"texel {texels[t[q]].tolist()} (#{t[q]}), wi {wi[q].tolist()}, wo {wo[q].tolist()}, "
                f"u {u[q].tolist()}: eval {value[q].tolist()}, pdf {pdf[q]}, sample wo {s_wo[q].tolist()} "
                f"weight {s_w[q].tolist()} pdf {s_pdf[q]}")

    failures = []
    two = kind == "twosided_around_plugin"
    through = transmits(kind, case["nested"])
    wi_z, wo_z = wi[:, 2].astype(np.float64), wo[:, 2].astype(np.float64)
    same_side = (wi_z * wo_z > 0) if two else (wi_z * wo_z != 0) if through else (wi_z > 0) & (wo_z > 0)
    for name, x in (("eval", value), ("pdf", pdf), ("pdf()", pdf_only), ("eval()", value_only),
                    ("sample weight", s_w), ("sample pdf", s_pdf)):
        x2 = x.reshape(len(x), -1)
        check(np.all(np.isfinite(x2) & (x2 >= 0), 1), f"{name} not finite and ≥ 0", failures, describe)
    check(np.all(value == 0, 1) | same_side, "eval ≠ 0 below the surface", failures, describe)
    check((pdf == 0) | same_side, "pdf ≠ 0 below the surface", failures, describe)
    check((pdf > 0) | np.all(value <= EVAL_UNDERFLOW, 1) | inherited_zero_pdf(case, kind, si, wo, value, pdf),
          "eval > 0 where pdf = 0", failures, describe)
    if model in ("analytic", "faithful"):
        check(np.abs(pdf_only - pdf) <= 1e-4 * pdf, "pdf() ≠ eval_pdf's pdf", failures, describe)
        check(np.all(np.abs(value_only - value) <= 1e-4 * value, 1), "eval() ≠ eval_pdf's value", failures, describe)
    else:
        check(pdf_only == pdf, "pdf() ≠ eval_pdf's pdf", failures, describe)
        check(np.all(value_only == value[:k], 1), "eval() ≠ eval_pdf's value", failures, describe)

    live = np.any(s_w > 0, 1)
    side = np.sign(wi_z) if two else 1.0
    with np.errstate(invalid="ignore"):
        length = np.linalg.norm(s_wo, axis=1)
        check(~live | (np.all(np.isfinite(s_wo), 1) & (np.abs(length - 1) <= UNIT_TOL)),
              "sampled direction not unit length", failures, describe)
        check(~live | ((s_wo[:, 2] != 0) if through else (s_wo[:, 2] * side > 0)),
              "sampled direction not above the surface", failures, describe)
    check(~live | (s_pdf > 0), "sample with weight > 0 has pdf 0", failures, describe)
    check(~live | (wi_z != 0) if two or through else ~live | (wi_z > 0), "sample from below the surface",
          failures, describe)
    # The batch must not be trivially dead (a sharp lobe, α = 1e-4, is non-zero on few ω_o,
    # a delta conductor on none; a principled with spec_trans = 1 reflects little; a nested BSDF
    # may be dead on its own).
    dead = black(case["nested"]) or ((not live.any() or not np.any(value > 0))
                                     and dead_on_its_own(case["nested"], si, wo, u))
    assert live.any() or dead, "no sample has weight > 0"
    assert kind in ("conductor", "dielectric") or dead or np.any(value > 0), "eval is zero everywhere"

    # White furnace: mean sample weight and ∫eval dω per (texel, ω_i) group.
    albedo_note = ""
    if energy_conserving(kind, case["nested"]):
        g = ALBEDO_GROUPS
        weight = s_w[albedo].reshape(g, ALBEDO_M, 3)
        integrand = (np.pi * value[albedo] / np.maximum(wo_z[albedo], 1e-30)[:, None]).reshape(g, ALBEDO_M, 3)
        for label, y in (("sample weights", weight), ("∫eval", integrand)):
            mean, sem = y.mean(1), y.std(1) / np.sqrt(ALBEDO_M)
            j = np.unravel_index(np.argmax(mean), mean.shape)
            albedo_note += f", max albedo by {label} {mean[j]:.4f} ± {sem[j]:.4f} (group {j[0]})"
            bad = mean > 1.0 + ALBEDO_SLACK + 5 * sem
            if label == "sample weights":
                for j in np.flatnonzero(bad.any(1)):
                    q = np.arange(albedo.start + j * ALBEDO_M, albedo.start + (j + 1) * ALBEDO_M)
                    wp = decode_ref(texels[t[q[:1]]], case["strength"], case["convention"] == "directx")[0]
                    tilt = float(np.arccos(np.clip(wp[2], -1.0, 1.0)))
                    if inherited_gain(case, si, s_wo, s_w[q], q, u, tilt):
                        bad[j] = False
                        albedo_note += f" (group {j}: the nested BSDF's own gain)"
            if bad.any():
                j = np.argwhere(bad)[0]
                q = albedo.start + j[0] * ALBEDO_M
                failures.append(f"albedo by {label} {mean[tuple(j)]:.5f} ± {sem[tuple(j)]:.5f} > 1 "
                                f"at texel {texels[t[q]].tolist()}, wi {wi[q].tolist()}")
    print(f"\n{model}-{tangent_facet} {kind}: {n} queries; "
          + ", ".join(f"{k} {v:.2f}s" for k, v in timings.items()) + albedo_note)
    assert not failures, f"case {case}:\n" + "\n".join(failures)


# -- Texture coordinates: hostile uvs and uv transforms ----------------------------------------------

UV_QUERIES = 1 << 14
HOSTILE_UV = [NAN, INF, -INF, 3e38, -1e30, DENORMAL, 0.25]
HEIGHT_TEXELS = np.linspace(0.0, 1.0, 16, dtype=np.float32).reshape(4, 4, 1)


@st.composite
def uv_case(draw):
    """A map (normal or height), a uv transform (none, finite, or with NaN/±inf in a drawn entry)
    and the share of queries whose surface uv is one of HOSTILE_UV."""
    bad = draw(st.sampled_from([NAN, INF, -INF]))
    finite = draw(st.floats(-1e9, 1e9))
    return {"map": draw(st.sampled_from(["normalmap", "heightmap"])),
            "to_uv": draw(st.sampled_from([None, "finite", "scale", "translate", "rotate"])),
            "bad": bad, "finite": finite, "share": draw(st.sampled_from([1.0, 0.5, 0.05])),
            "seed": draw(st.integers(0, 2 ** 32 - 1))}


def uv_transform(case):
    """The case's ``to_uv`` (None without one) and whether it holds a non-finite value."""
    kind, x = case["to_uv"], case["finite"] if case["to_uv"] == "finite" else case["bad"]
    if kind is None:
        return None, False
    if kind in ("finite", "scale"):
        return mi.ScalarTransform4f().scale([x, 2.0, 1.0]), kind != "finite"
    if kind == "translate":
        return mi.ScalarTransform4f().translate([0.5, x, 0.0]), True
    return mi.ScalarTransform4f().rotate([0, 0, 1], x), True


def uv_queries(case, n):
    """Interactions (flat frame, unit dp_du and dp_dv) with random ω_i and a share of hostile uvs,
    and random ω_o."""
    rng = np.random.default_rng(case["seed"])
    wi, wo = random_directions(rng, n), random_directions(rng, n)
    wi[:, 2] = np.abs(wi[:, 2])
    si = helpers.make_si(wi, 1, np.zeros(n, np.int64), np.arange(n))
    uv = rng.random((n, 2)).astype(np.float32)
    bad = rng.random((n, 2)) < case["share"]
    uv[bad] = np.float32(HOSTILE_UV)[rng.integers(0, len(HOSTILE_UV), bad.sum())]
    si.uv = mi.Point2f(helpers.floats(uv[:, 0]), helpers.floats(uv[:, 1]))
    si.dp_du, si.dp_dv = mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0)
    return si, vec3(wo), rng.random((n, 3)).astype(np.float32)


# The default run: a deterministic model and a walk (the lookup they share is the fix); the rest slow.
UV_DEFAULT = {("analytic", "specular"), ("nonseparable", "specular")}


@pytest.mark.parametrize("model,tangent_facet", [
    pytest.param(m, t, id=f"{m}-{t}", marks=() if LONG or (m, t) in UV_DEFAULT else (pytest.mark.slow,))
    for m, t in MODELS])
@settings(max_examples=int(os.environ.get("MFNORMAL_FUZZ_EXAMPLES", 20 if LONG else 2)), derandomize=not LONG,
          database=None, deadline=None, phases=(Phase.explicit, Phase.generate), print_blob=LONG)
@given(case=uv_case())
@example(case={"map": "heightmap", "to_uv": "scale", "bad": INF, "finite": 1.0, "share": 1.0, "seed": 1})
@example(case={"map": "normalmap", "to_uv": "finite", "bad": NAN, "finite": 3.0, "share": 0.5, "seed": 2})
@example(case={"map": "heightmap", "to_uv": None, "bad": NAN, "finite": 1.0, "share": 0.5, "seed": 3})
def test_fuzzed_uvs_and_uv_transforms_are_refused_or_finite(model, tangent_facet, case):
    """A map's ``to_uv`` with NaN or ±inf in any entry (scale, translate, rotate) is refused at
    load in one line that names it; otherwise queries whose surface uv is NaN, ±inf, huge or
    denormal return finite, non-negative values within HANG_S (they are looked up at uv = 0;
    before, Mitsuba's bitmap read outside its data and the walks' loops never ended)."""
    texels = HEIGHT_TEXELS if case["map"] == "heightmap" else SPECIAL_TEXELS[:16].reshape(4, 4, 3)
    texture = {"type": "bitmap", "raw": True, "bitmap": mi.Bitmap(np.ascontiguousarray(texels, np.float32))}
    transform, refused = uv_transform(case)
    if transform is not None:
        texture["to_uv"] = transform
    spec = {"type": "normalmap_microfacet", "model": model, "tangent_facet": tangent_facet,
            case["map"]: texture, "bsdf": {"type": "roughconductor", "alpha": 0.3}}
    if refused:
        with pytest.raises(RuntimeError) as info:
            mi.load_dict(spec)
        last = str(info.value).strip().splitlines()[-1]
        assert last.startswith(f"ValueError: normalmap_microfacet: the {case['map']} texture's to_uv holds NaN"), last
        return
    bsdf = mi.load_dict(spec)
    si, wo, u = uv_queries(case, UV_QUERIES)
    ctx = mi.BSDFContext()

    def run():
        value, pdf = bsdf.eval_pdf(ctx, si, wo)
        bs, weight = bsdf.sample(ctx, si, helpers.floats(u[:, 0]), helpers.point2(u[:, 1:]))
        return [np3(value, UV_QUERIES), np1(pdf, UV_QUERIES), np3(weight, UV_QUERIES), np1(bs.pdf, UV_QUERIES)]

    for name, x in zip(("eval", "pdf", "sample weight", "sample pdf"), timed("uv queries", run, {})):
        assert np.all(np.isfinite(x) & (x >= 0)), f"{name} not finite and >= 0 for case {case}"


# -- Regressions: the inputs the fuzzer found -------------------------------------------------------

WHITE = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}


def one_texel_bsdf(model, tangent_facet, texel, nested=WHITE, **kwargs):
    return mi.load_dict({"type": "normalmap_microfacet", "model": model, "tangent_facet": tangent_facet,
                         "bsdf": nested, **kwargs,
                         "normalmap": {"type": "bitmap", "raw": True, "filter_type": "nearest",
                                       "bitmap": mi.Bitmap(np.float32(texel).reshape(1, 1, 3))}})


def same_query(wi, n):
    """n copies of the query ω_i on the single texel, si.p = 0 … n−1 (the walks' eval hash)."""
    return make_si(np.zeros(n, np.int64), np.repeat(np.float32([wi]), n, 0))


@pytest.mark.parametrize("tangent_facet", ["specular", "same"])
def test_nonseparable_walk_conserves_energy_at_grazing_incidence(tangent_facet):
    """ω_i 1.7e-8 above the horizon on a normal clamped to θ_p = 88.9° (texel far past the
    horizon, strength 100): 1 − G1(ω_i) rounds to 1, so the start interval is the point
    [1, 1] (the crest). Its escape fraction was 0 (width 0), so walks never left: the
    sampler lost 90 % of the energy (albedo 0.097) and eval's NEE, repeated up to the cap,
    gained it (∫eval = 6.7). Now a point interval leaves iff it lies above the escape
    threshold (κa > 1; in depths, D < τ).
    White Lambertian facets, 2^18 queries: sample albedo in [0.98, 1] (the cap loses
    ~0.6 % at this tilt; weights are 0 or 1) and ∫eval (cosine-sampled) within 5σ of it.
    """
    texel, wi = [0.9933537840843201, 0.9862515926361084, 0.6495002508163452], [0.3574351966381073, 0.9339379072189331, 1.6525966373137635e-08]
    bsdf = one_texel_bsdf("nonseparable", tangent_facet, texel, strength=100.0)
    m = 1 << 18
    rng = np.random.default_rng(30)
    si, ctx = same_query(wi, m), mi.BSDFContext()
    u = rng.random((m, 3)).astype(np.float32)
    weight = np3(bsdf.sample(ctx, si, helpers.floats(u[:, 0]), helpers.point2(u[:, 1:]))[1], m)
    r, phi = np.sqrt(u[:, 1]), 2 * np.pi * u[:, 2]
    wo = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u[:, 1])], 1).astype(np.float32)
    y = np.pi * np3(bsdf.eval(ctx, si, vec3(wo)), m)[:, 0] / wo[:, 2]
    a_sample, a_eval, se = weight[:, 0].mean(), y.mean(), y.std() / np.sqrt(m)
    assert 0.98 <= a_sample <= 1.0, a_sample
    assert abs(a_eval - a_sample) <= 5 * se, (a_eval, se, a_sample)


def test_nonseparable_pdf_is_not_lost_to_infinity_times_zero():
    """A steep normal (strength 100) and a ray that always leaves (κ = ∞): mis_pdf's landed
    interval was ∞·0 = NaN, which zeroed the whole pdf where eval > 0 (285 of 5e5
    random queries; this one is on a knife edge, one ulp off in ω_i it passed). Now
    pdf > 0 there."""
    bsdf = one_texel_bsdf("nonseparable", "specular", [0.7449556589126587, 0.7162244319915771, 0.8784754872322083],
                          strength=100.0)
    si = same_query([0.6333194971084595, -0.717473030090332, 0.29006707668304443], 1)
    wo = vec3(np.float32([[-0.6446252465248108, 0.7364800572395325, 0.20507419109344482]]))
    value, pdf = np3(bsdf.eval(mi.BSDFContext(), si, wo), 1), np1(bsdf.pdf(mi.BSDFContext(), si, wo), 1)
    assert value[0, 0] > 0 and pdf[0] > 0.01, (value, pdf)


WALK_MODELS = [m for m in MODELS if m[0] in ("separable", "nonseparable")]


@pytest.mark.parametrize("model,tangent_facet", WALK_MODELS, ids=[f"{m}-{t}" for m, t in WALK_MODELS])
def test_walk_pdf_cosine_term_is_never_negative_nor_zero(model, tangent_facet):
    """mis_pdf's cosine lobe had weight 1 − cosθ_p: −1.2e-7 when a float32 unit ω_p has
    z > 1 (strength 1e-7: pdf −3.8e-8 for a delta conductor), and 0 for tilts below
    ~3e-4 (a 1.2e-5 tilt, ω_i 1e-7 above the horizon on the tangent facet's side: eval
    > 0 through i→t→p→o, pdf 0). Now sin²θ_p/(1 + cosθ_p)."""
    ctx = mi.BSDFContext()
    bsdf = one_texel_bsdf(model, tangent_facet, [0.8702607154846191, 0.2578945755958557, 0.7330064177513123], {"type": "conductor"},
                          strength=1e-7)
    wi = [-0.42218920588493347, -0.6456694602966309, 0.6362918019294739]
    wo = [-0.029614564031362534, -0.045290641486644745, 0.9985347986221313]
    pdf = np1(bsdf.pdf(ctx, same_query(wi, 1), vec3(np.float32([wo]))), 1)
    assert pdf[0] >= 0, pdf
    bsdf = one_texel_bsdf(model, tangent_facet, [0.5000000596046448, 0.5, 1.0], strength=100.0)
    n = 4096
    si, wo = same_query([-1.0, 0.0, 1e-7], n), vec3(np.float32([[0.0, 0.0, 1.0]]))
    value, pdf = np3(bsdf.eval(ctx, si, wo), n), np1(bsdf.pdf(ctx, si, wo), n)
    assert np.all(pdf > 0), pdf[:1]
    if tangent_facet == "same":          # the mirror reflects ω_i along the horizon: no path to +z
        assert np.any(value > 0)


def test_the_inherited_gain_exemption_covers_only_a_flat_texel():
    """The long fuzzer's find: Mitsuba's Beckmann roughconductor, α (1, 1e-4), sample_visible
    false, ω_i 1e-7 above the horizon: its own eval/pdf averages > 1 on its samples, and the
    plugin on a flat texel reproduces it exactly (exempt). On a tilted texel the plugin's weights
    are its own: not exempt, whatever their mean."""
    nested = {"type": "roughconductor", "distribution": "beckmann", "material": "none", "sample_visible": False,
              "alpha_u": 1.0, "alpha_v": 0.0001}
    n = 4096
    rng = np.random.default_rng(8)
    u = rng.random((n, 3)).astype(np.float32)
    out = []
    for texel in ([0.5000000596046448, 0.5, 1.0], [0.7, 0.5, 0.9]):
        bsdf = one_texel_bsdf("analytic", "specular", texel, nested, strength=100.0)
        si = same_query([0.0, 1.0, 1e-7], n)
        bs, w = bsdf.sample(mi.BSDFContext(), si, mi.Float(u[:, 0]), mi.Point2f(u[:, 1], u[:, 2]))
        wp = decode_ref(np.float32([texel]), 100.0, False)[0]
        out.append(inherited_gain({"nested": nested}, si, np3(bs.wo, n), np3(w, n), np.arange(n), u,
                                  float(np.arccos(np.clip(wp[2], -1.0, 1.0)))))
    assert out == [True, False], out


def test_directions_within_1e_12_of_the_horizon_lie_on_it():
    """The long fuzzer's finds: a horizontal texel, the non-separable walk with a mirror tangent
    facet, ω_i = ω_o with cosθ = 1.2e-38 (float32's smallest normal number): eval 0.24, pdf 0,
    the pdf's products of the two cosines underflowing; and a flat texel with cosθ_o = 1.9e-28:
    eval 2e-29, pdf 0. Within HORIZON_COS = 1e-12 of the macro plane a direction now lies on it:
    eval = pdf = 0 for every model, from either side (``twosided``), so eval > 0 ⇒ pdf > 0 holds
    there; just outside the band, queries answer as before (bit for bit: scripts/bit_identity.py)."""
    ctx, z_min = mi.BSDFContext(), float(np.finfo(np.float32).tiny)
    band = 1e-12                                   # mfnormal.surface.shading.HORIZON_COS
    wi = [[0.738468587398529, 0.6742879152297974, z_min], [0.738468587398529, 0.6742879152297974, -z_min],
          [1.0, 0.0, 1e-7], [0.6, 0.8, 0.5 * band], [0.6, 0.8, 0.5]]
    wo = [wi[0], wi[1], [0.22017772495746613, -0.9754597544670105, 1.9257723792436607e-28],
          [0.6, -0.8, 0.5], [-0.6, 0.8, -0.5 * band]]
    for model, tangent_facet in MODELS:
        for texel in ([1.0, 0.5, 0.5], [0.5, 0.4999999701976776, 1.0]):
            bsdf = mi.load_dict({"type": "twosided", "bsdf": {
                "type": "normalmap_microfacet", "model": model, "tangent_facet": tangent_facet, "max_bounces": 2,
                "bsdf": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 0.415, 1.0]}},
                "normalmap": {"type": "bitmap", "raw": True, "filter_type": "nearest",
                              "bitmap": mi.Bitmap(np.float32(texel).reshape(1, 1, 3))}}})
            n = 1024
            si = make_si(np.zeros(5 * n, np.int64), np.repeat(np.float32(wi), n, 0))
            value, pdf = bsdf.eval_pdf(ctx, si, vec3(np.repeat(np.float32(wo), n, 0)))
            value, pdf = np3(value, 5 * n), np1(pdf, 5 * n)
            assert not np.any(value > 0), (model, tangent_facet, texel, value.reshape(5, n, 3).max((1, 2)))
            assert not np.any(pdf > 0), (model, tangent_facet, texel, pdf.reshape(5, n).max(1))


def test_tilt_below_sin_p_eps_is_exactly_flat():
    """A tilt of 6e-8 (< SIN_P_EPS = 1e-7: the tangent facet gets no area) was flat for the
    height map but tilted for masking: a separable/specular walk found a mirror path that
    its pdf (κ = ∞, flat) did not (eval 5.2e-5, pdf 0; Beckmann α = 1e-4, DirectX map).
    Now ω_p = ω_g exactly there: every model gives the flat map's results bit for bit."""
    nested = {"type": "roughconductor", "distribution": "beckmann", "alpha": 1e-4, "sample_visible": True}
    ctx, n = mi.BSDFContext(), 4096
    rng = np.random.default_rng(31)
    # The query the fuzzer found, then random ones (half of them grazing).
    wi = np.concatenate([np.tile([0.6, -0.8, 1e-7], (n // 2, 1)), random_directions(rng, n // 2)]).astype(np.float32)
    wo = np.concatenate([np.tile([0.6, 0.8, 0.001], (n // 2, 1)), random_directions(rng, n // 2)]).astype(np.float32)
    for model, tangent_facet in MODELS:
        out = []
        for texel in ([0.5, 0.4999999701976776, 1.0], [0.5, 0.5, 1.0]):
            bsdf = one_texel_bsdf(model, tangent_facet, texel, nested, normalmap_convention="directx")
            si = make_si(np.zeros(n, np.int64), wi)
            out.append((np3(bsdf.eval(ctx, si, vec3(wo)), n), np1(bsdf.pdf(ctx, si, vec3(wo)), n)))
        assert np.array_equal(out[0][0], out[1][0]) and np.array_equal(out[0][1], out[1][1]), model


@pytest.mark.parametrize("model", ["faithful", "analytic"])
def test_eval_equals_eval_pdf_with_a_transmitting_nested_bsdf(model):
    """Principled with spec_trans = 1, nearly flat map (strength 1e-7), ω_i and ω_o grazing:
    the analytic model's p→t mirror term evaluated the nested BSDF at a direction below the
    p facet, where it transmits: eval 1.9e-9, eval_pdf (which gated it) 1.8e-16. The analytic
    model now refuses a transmitting nested BSDF at load; the default, which refracts, gives
    eval = eval_pdf's value bit for bit at that query."""
    nested = {"type": "principled", "roughness": 0.166, "specular": 1.0, "anisotropic": 0.534,
              "clearcoat": 1.0, "clearcoat_gloss": 1.0, "spec_trans": 1.0}
    texel = [0.7677456736564636, 0.544303297996521, 0.9199398756027222]
    if model == "analytic":
        with pytest.raises(RuntimeError, match="transmits light"):
            one_texel_bsdf(model, "specular", texel, nested, strength=1e-7)
        return
    bsdf = one_texel_bsdf(model, "specular", texel, nested, strength=1e-7)
    si = same_query([-0.5026869177818298, 0.8644685745239258, 2.293029233157995e-08], 1)
    wo = vec3(np.float32([[0.10951605439186096, -0.9939849972724915, 3.5039218193588795e-09]]))
    value = np3(bsdf.eval(mi.BSDFContext(), si, wo), 1)
    value_ep = np3(bsdf.eval_pdf(mi.BSDFContext(), si, wo)[0], 1)
    assert np.array_equal(value, value_ep), (value, value_ep)


def _tilted_texel(theta_deg):
    t = np.radians(theta_deg)
    return [(np.sin(t) + 1) / 2, 0.5, (np.cos(t) + 1) / 2]


HORIZON_CASES = {
    # found by a long fuzz run: ω_i.z = 7.6e-7, a texel clamped to θ_p = 88.85°: ∫eval was 1.18
    "fuzz-88.85deg": ("same", [0.44772037863731384, 0.3402320146560669, 0.9708938598632812], 100.0,
                      [-0.9959351420402527, -0.09007339924573898, 7.575813469884451e-07]),
    # ω_i 1e-6 above the horizon, facing the tangent walls: ∫eval was 1.053 (13σ) and 1.024 (6σ)
    "same-80deg": ("same", _tilted_texel(80.0), 1.0, [-1.0, 0.0, 1e-6]),
    "same-60deg": ("same", _tilted_texel(60.0), 1.0, [-1.0, 0.0, 1e-6]),
}


@pytest.mark.parametrize("case", list(HORIZON_CASES))
def test_nonseparable_eval_is_unbiased_within_1e_6_of_the_horizon(case):
    """Heights near the crest lose float32 precision: from ω_i within ~1e-6 of the
    horizon the start interval [1 − G1(ω_i), 1] has G1 ≈ 1e-6 … 4e-8, at or below
    float32's spacing of 6e-8 under 1, so heights tracked as such are quantised and the NEE
    weights |H ∩ V|/|H| biased (white Lambertian facets: ∫eval 1.18 against a sampled
    albedo of 0.99 in the fuzz case; +5 % at θ_p = 80°). The walk tracks depths
    below the crest (microsurface.crest_map), which keep full precision there.
    ∫eval (cosine-sampled) must match the sampler's albedo within 5 standard errors of
    the eval estimate (2^18 queries; heights instead of depths are off by 6σ to 25σ here)."""
    tangent_facet, texel, strength, wi = HORIZON_CASES[case]
    bsdf = one_texel_bsdf("nonseparable", tangent_facet, texel, strength=strength)
    m = 1 << 18
    u = np.random.default_rng(32).random((m, 3)).astype(np.float32)
    si, ctx = same_query(wi, m), mi.BSDFContext()
    weight = np3(bsdf.sample(ctx, si, helpers.floats(u[:, 0]), helpers.point2(u[:, 1:]))[1], m)
    r, phi = np.sqrt(u[:, 1]), 2 * np.pi * u[:, 2]
    wo = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u[:, 1])], 1).astype(np.float32)
    y = np.pi * np3(bsdf.eval(ctx, si, vec3(wo)), m)[:, 0] / wo[:, 2]
    assert weight[:, 0].mean() >= 0.98, weight[:, 0].mean()
    assert abs(y.mean() - weight[:, 0].mean()) <= 5 * y.std() / np.sqrt(m), (y.mean(), weight[:, 0].mean())


def test_zero_pdf_exemption_covers_only_the_nested_bsdfs_own_zero_pdf():
    """The fuzz check eval > 0 ⇒ pdf > 0 exempts queries where the plugin is its nested BSDF
    and that BSDF itself has pdf 0 (found by the fuzzer: Mitsuba's roughplastic at 1e-7
    grazing, ``inherited_zero_pdf``). The exemption must stay that narrow: a tilted texel
    (the plugin differs from the nested BSDF) is never exempt."""
    nested = {"type": "roughplastic", "distribution": "beckmann", "alpha": 1.0, "int_ior": 1.939,
              "diffuse_reflectance": {"type": "rgb", "value": [0.0, 0.0, 1e-7]}, "nonlinear": False}
    case = {"nested": nested, "strength": 1.0, "convention": "opengl", "max_bounces": 1, "mis_boost_max": 64.0}
    wi = np.float32([[1.0, 0.0, 1e-7]] * 3)
    wo = np.float32([[1.0, 0.0, 1e-7], [0.0, 1.0, 1e-7], [0.6, -0.8, 1e-7]])
    for texel, exempt in (([0.5, 0.5, 1.0], True), ([0.8, 0.5, 0.9], False)):
        texels = np.tile(np.float32(texel), (N_TEXELS, 1))
        bsdf = make_bsdf("separable", "specular", "roughplastic", case, texels)
        si = make_si(np.zeros(3, np.int64), wi)
        value, pdf = bsdf.eval_pdf(mi.BSDFContext(), si, vec3(wo))
        value, pdf = np3(value, 3), np1(pdf, 3)
        flagged = inherited_zero_pdf(case, "roughplastic", si, wo, value, pdf)
        if exempt:   # the nested BSDF's own violation, inherited exactly
            assert np.all(pdf == 0) and np.all(value[:, 2] > 0) and flagged.all(), (value, pdf)
        else:
            assert not flagged.any(), (value, pdf)
