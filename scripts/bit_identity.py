"""Record the plugin's outputs on a fixed query set, or check them bit for bit.

    .venv/bin/python -m scripts.bit_identity record OUT.npz
    .venv/bin/python -m scripts.bit_identity compare OUT.npz [--only SUBSTRING]

(from the repository's root: the naive estimator is ``validation.reference``'s).

For refactors that must not change behaviour: record on the code before the
change (keep the file outside git), compare after it. Every configuration
(model × tangent facet × nested BSDF, each normal source on a smooth-shaded
mesh — vertex tangents, height map, the geometric macro normal with and
without a map — forward-mode derivatives along the map's texels, and a few with other ``max_bounces``,
``rr_depth``, ``mis_boost_max``, ``strength`` and convention values) answers
the same ``N_QUERIES`` queries through the plugin's ``eval``, ``pdf``,
``eval_pdf`` and ``sample`` (direction, pdf, weight, sampled type and
component) in ``llvm_ad_rgb``; a small set also in ``scalar_rgb``; and the
non-separable naive sampled-height estimator (the validation reference) on its
own query set. ``compare`` checks every array with ``np.array_equal`` and
also bit for bit (IEEE bits, so that a sign of zero would show), and exits
non-zero on any difference.

The query set mixes what breaks things: normals from flat (exactly, and a
1e-7 tilt) to the 88.9° clamp and beyond (clamped), NaN and zero texels;
cosine-distributed, grazing (cosθ down to 1e-7), in-plane and below-surface
directions; ω_o at ω_i's mirror image about ω_g (the glossy peak); sample
numbers at 0 and just below 1; random shading frames and positions.
"""

from __future__ import annotations

import argparse
import sys

import mfnormal  # first: selects a working libLLVM

import drjit as dr
import mitsuba as mi
import numpy as np

N_QUERIES = 1 << 16
N_SCALAR = 48
N_NAIVE = 1 << 16
TEX = 64   # the normal map (and the principled BSDF's textures) are TEX × TEX texels

MODELS = [("faithful", "specular"), ("analytic", "specular"), ("separable", "specular"), ("separable", "same"),
          ("nonseparable", "specular"), ("nonseparable", "same")]


def _texture(rgb):
    return {"type": "bitmap", "bitmap": mi.Bitmap(np.ascontiguousarray(rgb, np.float32)), "raw": True,
            "filter_type": "nearest"}


def nested_bsdfs():
    rng = np.random.default_rng(7)
    base = rng.uniform(0.05, 0.95, (TEX, TEX, 3))
    rough = rng.uniform(0.02, 0.9, (TEX, TEX, 1))
    return {
        "diffuse": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.2, 0.5, 0.9]}},
        "ggx005": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.05},
        "ggx03": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.3},
        "roughplastic": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.3,
                         "diffuse_reflectance": {"type": "rgb", "value": [0.3, 0.6, 0.2]}},
        "conductor": {"type": "conductor"},
        "principled": {"type": "principled", "base_color": _texture(base), "roughness": _texture(rough),
                       "metallic": 0.4, "specular": 0.6},
    }


# (model, tangent facet, nested, extra plugin parameters): other parameter values.
EXTRA = [
    ("separable", "specular", "ggx03", {"max_bounces": 7, "rr_depth": 5, "mis_boost_max": 8.0}),
    ("separable", "same", "ggx005", {"rr_depth": 0, "mis_boost_max": 1.0}),
    ("nonseparable", "specular", "roughplastic", {"max_bounces": 1}),
    ("nonseparable", "specular", "ggx005", {"max_bounces": 2, "mis_boost_max": 1.0}),
    ("nonseparable", "same", "diffuse", {"max_bounces": 2, "rr_depth": 1}),
    ("nonseparable", "same", "ggx03", {"rr_depth": 0, "max_bounces": 3000}),
    ("separable", "specular", "diffuse", {"max_bounces": 1, "rr_depth": 1}),
    ("analytic", "specular", "ggx03", {"strength": 0.7, "normalmap_convention": "directx"}),
    ("faithful", "specular", "roughplastic", {"strength": 0.7, "normalmap_convention": "directx"}),
    (None, None, "roughplastic", {}),              # the plugin's defaults (no model given)
    ("faithful", "specular", "roughplastic", {"strength": 0.0}),
    ("analytic", "specular", "diffuse", {"strength": 0.0}),
    ("nonseparable", "same", "ggx03", {"strength": 0.0}),
]
#: Configurations also answered in TransportMode.Importance (keys ".../importance_*").
IMPORTANCE = ("faithful-specular-", "analytic-specular-", "default-")


def configurations():
    nested = nested_bsdfs()
    out = {}
    for model, tf in MODELS:
        for name, spec in nested.items():
            out[f"{model}-{tf}-{name}"] = (model, tf, spec, {})
    for model, tf, name, extra in EXTRA:
        tag = ",".join(f"{k}={v}" for k, v in extra.items())
        key = f"{model}-{tf}-{name}-{tag}" if model else f"default-{name}"
        out[key] = (model, tf, nested[name], extra)
    return out


def unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def directions(rng, n):
    """Cosine-distributed, grazing, in-plane and below-surface unit directions (float64)."""
    u1, u2 = rng.random(n), rng.random(n)
    r, phi = np.sqrt(u1), 2 * np.pi * u2
    d = np.stack([r * np.cos(phi), r * np.sin(phi), np.sqrt(1 - u1)], -1)
    kind = rng.random(n)
    grazing = kind < 0.15
    z = 10.0 ** rng.uniform(-7, -1, n)
    s = np.sqrt(1 - z * z)
    d[grazing] = np.stack([s * np.cos(phi), s * np.sin(phi), z], -1)[grazing]
    d[(kind >= 0.15) & (kind < 0.17), 2] = 0.0                           # in the plane
    below = (kind >= 0.17) & (kind < 0.21)
    d[below, 2] = -d[below, 2]                                           # below the surface
    return unit(d)


def texels(rng):
    """TEX² raw normal-map texels: tilts up to and past the clamp, flat, near-flat, bad ones."""
    n = TEX * TEX
    theta = np.radians(np.where(rng.random(n) < 0.8, rng.uniform(0, 80, n), rng.uniform(80, 95, n)))
    phi = rng.uniform(0, 2 * np.pi, n)
    wp = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1)
    t = wp * 0.5 + 0.5
    t[::97] = [0.5, 0.5, 1.0]                      # flat
    t[1::97] = [0.5 + 2.0 ** -24, 0.5, 1.0]        # within an ulp of flat
    t[2::211] = [np.nan, 0.5, 1.0]                 # NaN texel
    t[3::211] = [0.5, 0.5, 0.5]                    # zero normal
    return t.reshape(TEX, TEX, 3).astype(np.float32)


def queries(n, seed=1):
    """Numpy arrays of one query set: uv (texel centres), wi, wo, si.p, frame, s1, s2."""
    rng = np.random.default_rng(seed)
    k = rng.integers(0, TEX * TEX, n)
    uv = np.stack([(k % TEX + 0.5) / TEX, (k // TEX + 0.5) / TEX], -1)
    wi, wo = directions(rng, n), directions(rng, n)
    peak = rng.random(n) < 0.1
    wo[peak] = wi[peak] * [-1.0, -1.0, 1.0]        # ω_i's mirror image about ω_g
    p = rng.uniform(-10, 10, (n, 3))
    # A random orthonormal shading frame per query.
    nrm = unit(rng.normal(size=(n, 3)))
    s = unit(np.cross(nrm, unit(rng.normal(size=(n, 3)))))
    t = np.cross(nrm, s)
    u = rng.random((n, 3))
    edge = rng.random(n)
    u[edge < 0.02] = 0.0
    u[(edge >= 0.02) & (edge < 0.04)] = 1.0 - 2.0 ** -24
    return dict(uv=uv, wi=wi, wo=wo, p=p, s=s, t=t, n=nrm, u=u)


def _f(a):
    return mi.Float(np.ascontiguousarray(a, np.float32))


def interaction(q):
    si = dr.zeros(mi.SurfaceInteraction3f, len(q["wi"]))
    si.uv = mi.Point2f(_f(q["uv"][:, 0]), _f(q["uv"][:, 1]))
    si.p = mi.Point3f(*(_f(q["p"][:, i]) for i in range(3)))
    si.sh_frame = mi.Frame3f(*(mi.Vector3f(*(_f(q[k][:, i]) for i in range(3))) for k in "stn"))
    si.n = mi.Normal3f(si.sh_frame.n)
    si.wi = mi.Vector3f(*(_f(q["wi"][:, i]) for i in range(3)))
    return si


def plugin(model, tf, nested, extra, tex):
    d = {"type": "normalmap_microfacet", "normalmap": _texture(tex), "bsdf": nested, **extra}
    if model is not None:
        d["model"] = model
    if model not in (None, "analytic", "faithful"):
        d["tangent_facet"] = tf
    return mi.load_dict(d)


def _np(x, dtype=np.float32):
    return np.array(x, dtype=dtype)


def answers(bsdf, si, q, mode=mi.TransportMode.Radiance):
    """The plugin's eval, pdf, eval_pdf and sample at ``si`` for the query set ``q`` (numpy arrays)."""
    ctx = mi.BSDFContext(mode)
    wo = mi.Vector3f(*(_f(q["wo"][:, i]) for i in range(3)))
    out = {"eval": _np(bsdf.eval(ctx, si, wo)), "pdf": _np(bsdf.pdf(ctx, si, wo))}
    value, pdf = bsdf.eval_pdf(ctx, si, wo)
    out.update(eval_pdf_value=_np(value), eval_pdf_pdf=_np(pdf))
    bs, w = bsdf.sample(ctx, si, _f(q["u"][:, 0]), mi.Point2f(_f(q["u"][:, 1]), _f(q["u"][:, 2])))
    out.update(sample_wo=_np(bs.wo), sample_pdf=_np(bs.pdf), sample_weight=_np(w),
               sample_type=_np(bs.sampled_type, np.uint32), sample_component=_np(bs.sampled_component, np.uint32),
               sample_eta=_np(bs.eta))
    return out


def run_jit(bsdf, q, mode=mi.TransportMode.Radiance):
    return answers(bsdf, interaction(q), q, mode)


def run_scalar(bsdf, q):
    ctx = mi.BSDFContext()
    rows = {k: [] for k in ("eval", "pdf", "eval_pdf_value", "eval_pdf_pdf", "sample_wo", "sample_pdf",
                            "sample_weight", "sample_type")}
    for j in range(len(q["wi"])):
        si = mi.SurfaceInteraction3f()
        si.uv = mi.Point2f(*map(float, np.float32(q["uv"][j])))
        si.p = mi.Point3f(*map(float, np.float32(q["p"][j])))
        si.sh_frame = mi.Frame3f(*(mi.Vector3f(*map(float, np.float32(q[k][j]))) for k in "stn"))
        si.n = mi.Normal3f(si.sh_frame.n)
        si.wi = mi.Vector3f(*map(float, np.float32(q["wi"][j])))
        wo = mi.Vector3f(*map(float, np.float32(q["wo"][j])))
        rows["eval"].append(list(bsdf.eval(ctx, si, wo)))
        rows["pdf"].append(bsdf.pdf(ctx, si, wo))
        value, pdf = bsdf.eval_pdf(ctx, si, wo)
        rows["eval_pdf_value"].append(list(value))
        rows["eval_pdf_pdf"].append(pdf)
        u = np.float32(q["u"][j])
        bs, w = bsdf.sample(ctx, si, float(u[0]), mi.Point2f(float(u[1]), float(u[2])))
        rows["sample_wo"].append(list(bs.wo))
        rows["sample_pdf"].append(bs.pdf)
        rows["sample_weight"].append(list(w))
        rows["sample_type"].append(int(bs.sampled_type))
    return {k: np.array(v, np.uint32 if k == "sample_type" else np.float32) for k, v in rows.items()}


def naive_estimates(tf, nested, q, tex):
    """The non-separable naive sampled-height estimator on the queries (ω_p from ``tex``)."""
    from mfnormal.surface.microsurface import decode_normal
    from mfnormal.surface.shading import ShadingPoint
    si = interaction(q)
    wo = mi.Vector3f(*(_f(q["wo"][:, i]) for i in range(3)))
    rgb = mi.load_dict(_texture(tex)).eval_3(si)
    sp = ShadingPoint(mi.load_dict(nested), mi.BSDFContext(), si, decode_normal(rgb, mi.Float(1.0), False))
    return {"naive_eval": _np(naive_eval(sp, wo, tf == "specular"))}


def naive_eval(sp, wo, specular):
    from validation.reference.naive_walk import naive_eval as naive
    return naive(sp, wo, specular)


# -- Normal sources on a mesh: vertex tangents, height maps, the geometric macro normal ------------

#: Two non-planar quads (skewed uvs, the second mirrored in u), smooth-shaded: si.n != sh_frame.n.
MESH_P = np.array([[0, 0, 0], [1, 0, 0.2], [1.2, 1, 0.1], [0.1, 1, -0.1],
                   [2, 0, 0], [3, 0, -0.1], [3.1, 1, 0.15], [2.1, 0.9, 0]], np.float64)
MESH_UV = np.array([[0.05, 0.1], [0.7, 0.15], [0.9, 0.8], [0.15, 0.6],
                    [0.9, 0.1], [0.2, 0.05], [0.1, 0.7], [0.85, 0.75]], np.float64)
MESH_F = np.array([[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]])

#: (normal source, extra plugin parameters); ``heightmap`` replaces the normal map.
SOURCES = {
    "tangents": {"tangents": "vertex_tangent"},
    "heightmap": {"heightmap": None, "height_scale": 0.05},
    "geometric": {"macro_normal": "geometric"},
    "geometric_nomap": {"macro_normal": "geometric", "normalmap": None},
    "geometric_heightmap": {"macro_normal": "geometric", "heightmap": None, "height_scale": 0.05},
}


def mesh_plugin(model, tf, nested, source, tex):
    d = {"type": "normalmap_microfacet", "normalmap": _texture(tex), "bsdf": nested}
    for k, v in SOURCES[source].items():
        if k == "heightmap":
            h = np.ascontiguousarray(tex[..., :1] + 0.3 * tex[..., 1:2], np.float32)
            h = np.nan_to_num(h, nan=0.5)
            d.pop("normalmap")
            d["heightmap"] = {"type": "bitmap", "bitmap": mi.Bitmap(h), "raw": True, "filter_type": "bilinear"}
        elif v is None:
            d.pop(k)
        else:
            d[k] = v
    if model is not None:
        d["model"] = model
    if model not in (None, "analytic", "faithful"):
        d["tangent_facet"] = tf
    return mi.load_dict(d)


def _face_points(rng, n):
    """n random points inside the mesh's triangles, and their unit face normals."""
    f = rng.integers(0, len(MESH_F), n)
    b = rng.dirichlet([1, 1, 1], n) * 0.98 + 0.02 / 3
    tri = MESH_P[MESH_F[f]]
    fn = np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0])
    return np.einsum("nk,nkd->nd", b, tri), fn / np.linalg.norm(fn, axis=1, keepdims=True)


def mesh_hits(bsdf, q):
    """Interactions on the two quads (the plugin as their material), rays along −(face normal)."""
    rng = np.random.default_rng(11)
    n = len(q["wi"])
    props = mi.Properties()
    props["bsdf"] = bsdf
    mesh = mi.Mesh("quads", len(MESH_P), len(MESH_F), props, has_vertex_normals=True, has_vertex_texcoords=True)
    params = mi.traverse(mesh)
    t = np.radians(rng.uniform(0, 25, len(MESH_P)))
    ph = rng.uniform(0, 2 * np.pi, len(MESH_P))
    normals = np.stack([np.sin(t) * np.cos(ph), np.sin(t) * np.sin(ph), np.cos(t)], -1)
    for key, value in (("vertex_positions", MESH_P), ("vertex_normals", normals), ("vertex_texcoords", MESH_UV)):
        params[key] = mi.Float(np.float32(value).ravel())
    params["faces"] = mi.UInt32(MESH_F.astype(np.uint32).ravel())
    params.update()
    tangent = unit(np.cross(normals, unit(rng.normal(size=(len(MESH_P), 3)))))
    mesh.add_attribute("vertex_tangent", 3, np.float32(tangent).ravel())
    mesh.add_attribute("vertex_tangent_sign", 1, np.float32(np.where(np.arange(len(MESH_P)) < 4, 1.0, -1.0)))
    scene = mi.load_dict({"type": "scene", "mesh": mesh})
    p, fn = _face_points(rng, n)
    o = p + 0.5 * fn
    ray = mi.Ray3f(mi.Point3f(*(_f(o[:, i]) for i in range(3))), mi.Vector3f(*(_f(-fn[:, i]) for i in range(3))))
    si = scene.ray_intersect(ray)
    si.wi = mi.Vector3f(*(_f(q["wi"][:, i]) for i in range(3)))
    return si, bsdf


def run_mesh(model, tf, nested, source, tex, q, mode=mi.TransportMode.Radiance):
    """run_jit's outputs at interactions on a smooth-shaded mesh (the normal sources' inputs)."""
    si, bsdf = mesh_hits(mesh_plugin(model, tf, nested, source, tex), q)
    out = answers(bsdf, si, q, mode)
    return {k: v for k, v in out.items() if k not in ("sample_component", "sample_eta")}


def run_grad(model, tf, nested, tex, q):
    """Forward-mode derivatives of eval and of the sample weight along a fixed direction of the
    normal map's texels (per query: gathers only, so the same numbers on every run; a reverse-mode
    gradient of the map sums queries with atomic adds in a thread-dependent order)."""
    bsdf = plugin(model, tf, nested, {}, tex)
    params = mi.traverse(bsdf)
    key = "normalmap.data"
    direction = mi.TensorXf(np.random.default_rng(8).uniform(-0.1, 0.1, np.array(params[key]).shape).astype(np.float32))
    out = {}
    for what in ("eval", "sample_weight"):
        data = mi.TensorXf(params[key])
        dr.enable_grad(data)
        params[key] = data
        params.update()
        si = interaction(q)
        ctx = mi.BSDFContext()
        if what == "eval":
            y = bsdf.eval(ctx, si, mi.Vector3f(*(_f(q["wo"][:, i]) for i in range(3))))
        else:
            y = bsdf.sample(ctx, si, _f(q["u"][:, 0]), mi.Point2f(_f(q["u"][:, 1]), _f(q["u"][:, 2])))[1]
        dr.set_grad(data, direction)
        out[f"grad_{what}"] = _np(dr.forward_to(y))
    return out


def record_sources(out, only, tex):
    """The normal sources (SOURCES) for every model × tangent facet on two nested BSDFs, and gradients."""
    q = queries(N_QUERIES // 4, seed=5)
    nested = nested_bsdfs()
    for model, tf in MODELS:
        for name in ("diffuse", "ggx03"):
            for source in SOURCES:
                key = f"mesh/{model}-{tf}-{name}-{source}"
                if only and only not in key:
                    continue
                for what, a in run_mesh(model, tf, nested[name], source, tex, q).items():
                    out[f"{key}/{what}"] = a
                if model == "faithful" or source.startswith("geometric"):
                    for what, a in run_mesh(model, tf, nested[name], source, tex, q,
                                            mi.TransportMode.Importance).items():
                        out[f"{key}/importance_{what}"] = a
                print(f"  {key}", flush=True)
    qg = queries(N_QUERIES // 16, seed=6)
    for model, tf in MODELS:
        key = f"grad/{model}-{tf}-ggx03"
        if only and only not in key:
            continue
        for what, a in run_grad(model, tf, nested["ggx03"], tex, qg).items():
            out[f"{key}/{what}"] = a
        print(f"  {key}", flush=True)


def record(only=None):
    """{key: array} for every configuration (keys "config/what")."""
    mi.set_variant("llvm_ad_rgb")
    mfnormal.register()
    tex = texels(np.random.default_rng(3))
    q = queries(N_QUERIES)
    out = {}
    for name, (model, tf, nested, extra) in configurations().items():
        if only and only not in f"llvm/{name}":
            continue
        bsdf = plugin(model, tf, nested, extra, tex)
        for what, a in run_jit(bsdf, q).items():
            out[f"llvm/{name}/{what}"] = a
        if name.startswith(IMPORTANCE):
            for what, a in run_jit(bsdf, q, mi.TransportMode.Importance).items():
                out[f"llvm/{name}/importance_{what}"] = a
        print(f"  llvm {name}", flush=True)
    record_sources(out, only, tex)
    qn = queries(N_NAIVE, seed=2)
    for tf in ("specular", "same"):
        for name in ("diffuse", "ggx03"):
            if only and only not in f"naive/{tf}-{name}":
                continue
            for what, a in naive_estimates(tf, nested_bsdfs()[name], qn, tex).items():
                out[f"naive/{tf}-{name}/{what}"] = a
            print(f"  naive {tf} {name}", flush=True)
    qs = queries(N_SCALAR, seed=4)
    mi.set_variant("scalar_rgb")
    mfnormal.register()
    try:
        for model, tf in MODELS:
            for name in ("diffuse", "roughplastic"):
                key = f"{model}-{tf}-{name}"
                if only and only not in f"scalar/{key}":
                    continue
                for what, a in run_scalar(plugin(model, tf, nested_bsdfs()[name], {}, tex), qs).items():
                    out[f"scalar/{key}/{what}"] = a
                print(f"  scalar {key}", flush=True)
    finally:
        mi.set_variant("llvm_ad_rgb")
        mfnormal.register()
    return out


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("action", choices=["record", "compare"])
    parser.add_argument("file")
    parser.add_argument("--only", help="only the configurations whose key (e.g. llvm/separable-same-ggx03, "
                        "naive/specular-diffuse, scalar/analytic-specular-diffuse) contains this")
    args = parser.parse_args(argv)
    import warnings
    warnings.simplefilter("ignore", RuntimeWarning)   # the scalar variant's slowness warning
    mi.set_log_level(mi.LogLevel.Error)               # the transmission-dropped warning
    got = record(args.only)
    if args.action == "record":
        np.savez_compressed(args.file, **got)
        print(f"recorded {len(got)} arrays ({sum(a.size for a in got.values())} numbers) in {args.file}")
        return 0
    want = dict(np.load(args.file))
    if args.only:
        want = {k: v for k, v in want.items() if args.only in k.rsplit("/", 1)[0]}
    missing = sorted(set(want) - set(got))
    bad = []
    for key in sorted(set(want) & set(got)):
        a, b = want[key], got[key]
        same = a.shape == b.shape and np.array_equal(a, b)
        bits = same and np.array_equal(a.view(np.uint32), b.view(np.uint32))
        if not bits:
            diff = "shape" if a.shape != b.shape else f"{np.sum(a != b)} of {a.size} differ"
            bad.append(f"{key}: {'array_equal but not bitwise (signed zeros)' if same else diff}")
    n = sum(a.size for k, a in want.items() if k in got)
    print(f"compared {len(want) - len(missing)} arrays ({n} numbers): "
          + ("all bit-identical" if not bad and not missing else f"{len(bad)} differ, {len(missing)} missing"))
    for line in bad + [f"{k}: missing" for k in missing]:
        print("  " + line)
    return 1 if bad or missing else 0


if __name__ == "__main__":
    sys.exit(main())
