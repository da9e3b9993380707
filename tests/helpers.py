"""What the tests share: directions, normal-map texels, the plugin on a texel row, queries, tiny scenes
(dicts, and XML text for the command line).

Per-query normals come from an N×1 float32 bitmap with nearest filtering: a query
whose ``si.uv`` points at the centre of texel k sees the normal of texel k, so
one BSDF answers a batch of queries with different ω_p. ``si.p`` feeds the random
walks' eval hash, so queries that should be independent get distinct positions.
Everything here runs in the variant that is active when it is called.
"""

from __future__ import annotations

import math

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np

from validation.reference.arrays import aligned, floats, uints, vec3  # noqa: F401  (the tests' inputs too)

WHITE = {"type": "diffuse", "reflectance": {"type": "rgb", "value": [1.0, 1.0, 1.0]}}
#: The nested BSDFs the models' tests run on (those the acceptance criteria name).
NESTED = {
    "diffuse": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.2, 0.5, 0.9]}},
    "ggx_0.1": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.1},
    "ggx_0.5": {"type": "roughconductor", "distribution": "ggx", "alpha": 0.5},
    "roughplastic": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.3,
                     "diffuse_reflectance": {"type": "rgb", "value": [0.3, 0.6, 0.2]}},
}


# -- Directions and texels (numpy, float64) ------------------------------------------------


def sph(theta_deg, phi=0.0):
    """Unit vector(s) at polar angle θ (degrees) and azimuth φ (radians)."""
    t = np.radians(np.asarray(theta_deg, np.float64))
    phi = np.asarray(phi, np.float64)
    return np.stack(np.broadcast_arrays(np.sin(t) * np.cos(phi), np.sin(t) * np.sin(phi), np.cos(t)), -1)


def random_hemisphere(rng, n, z_min=0.0):
    """Uniform directions on the upper hemisphere (z > z_min)."""
    z = rng.uniform(z_min, 1.0, n)
    phi = rng.uniform(0.0, 2.0 * np.pi, n)
    r = np.sqrt(np.maximum(0.0, 1.0 - z * z))
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], -1)


def encode(wp):
    """Raw float32 texels whose decode 2·rgb − 1 is ω_p."""
    return (np.asarray(wp, np.float64) * 0.5 + 0.5).astype(np.float32)


def decode_ref(texels):
    """float64 normalize(2·rgb − 1) of float32 texels: the ω_p the plugin should see."""
    n = 2.0 * np.asarray(texels, np.float64) - 1.0
    return n / np.linalg.norm(n, axis=-1, keepdims=True)


def p_two_sided(z):
    """Two-sided normal p-value of z-scores."""
    return np.array([math.erfc(abs(x) / math.sqrt(2.0)) for x in np.ravel(z)]).reshape(np.shape(z))


# -- Dr.Jit <-> numpy ------------------------------------------------------------------------


def tensor(a):
    """mi.TensorXf from a float32 numpy array of any shape (:func:`aligned`)."""
    return mi.TensorXf(aligned(a))


def point2(a):
    """mi.Point2f from (n, 2) values (as float32, :func:`aligned`)."""
    a = np.asarray(a, np.float32).reshape(-1, 2)
    return mi.Point2f(aligned(a[:, 0]), aligned(a[:, 1]))


def np3(v, n=None):
    """(n, 3) float64 array from a Dr.Jit 3-vector or colour (width-1 literals broadcast to n)."""
    a = np.array(v, dtype=np.float64).reshape(3, -1).T
    return a if n is None else np.broadcast_to(a, (n, 3)).copy()


def np1(v, n=None):
    """(n,) float64 array from a Dr.Jit float (width-1 literals broadcast to n)."""
    a = np.array(v, dtype=np.float64).reshape(-1)
    return a if n is None else np.broadcast_to(a, (n,)).copy()


# -- The plugin and its queries ------------------------------------------------------------


def normalmap(texels):
    """A 1×N raw bitmap texture of the texels, nearest filtering."""
    tex = np.array(texels, np.float32).reshape(1, -1, 3).copy()
    return {"type": "bitmap", "bitmap": mi.Bitmap(tex), "raw": True, "filter_type": "nearest"}


def make_bsdf(nested, texels, model=None, tangent_facet=None, **params):
    """``normalmap_microfacet`` around ``nested`` on the texel row (model and tangent facet
    left to the plugin's defaults where None)."""
    d = {"type": "normalmap_microfacet", "normalmap": normalmap(texels), "bsdf": nested, **params}
    if model is not None:
        d["model"] = model
    if tangent_facet is not None:
        d["tangent_facet"] = tangent_facet
    return mi.load_dict(d)


def make_si(wi, n_texels=1, texel_index=None, p_index=None):
    """Interactions with wi (n×3) in the flat frame, uv on texel ``texel_index`` (default:
    query k on texel k mod n_texels) and si.p = (k mod 2²², k div 2²², 0) for the query
    numbers k = ``p_index`` (default: all at the origin)."""
    wi = np.asarray(wi, np.float64).reshape(-1, 3)
    n = wi.shape[0]
    if texel_index is None:
        texel_index = np.arange(n) % n_texels
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.wi = vec3(wi)
    u = (np.broadcast_to(np.asarray(texel_index, np.float64), (n,)) + 0.5) / n_texels
    si.uv = mi.Point2f(aligned(u), aligned(np.full(n, 0.5)))
    if p_index is not None:
        k = np.broadcast_to(np.asarray(p_index, np.int64), (n,))
        si.p = mi.Point3f(aligned(k % (1 << 22)), aligned(k // (1 << 22)), aligned(np.zeros(n)))
    si.sh_frame = mi.Frame3f(mi.Vector3f(1, 0, 0), mi.Vector3f(0, 1, 0), mi.Vector3f(0, 0, 1))
    si.n = mi.Normal3f(0, 0, 1)
    return si


# -- Tiny scenes ----------------------------------------------------------------------------


def bumps_normalmap(size=64, cells=4, radius=0.4):
    """Periodic grid of hemispherical bumps, OpenGL convention, as raw rgb in [0, 1]."""
    c = (np.arange(size) + 0.5) / size * cells
    x, y = np.meshgrid(c, c)
    dx, dy = x - np.floor(x) - 0.5, y - np.floor(y) - 0.5
    r2 = dx * dx + dy * dy
    inside = r2 < radius * radius
    h = np.sqrt(np.maximum(radius * radius - r2, 0.0))
    n = np.stack([np.where(inside, dx, 0.0), np.where(inside, -dy, 0.0),
                  np.where(inside, h, radius)], axis=-1)
    n /= np.linalg.norm(n, axis=-1, keepdims=True)
    return (n * 0.5 + 0.5).astype(np.float32)


def small_scene(normalmap_texels, spp=8, width=48, height=36):
    """A normal-mapped gold sphere on a normal-mapped diffuse ground, sky and sun (a dict)."""
    def material(nested):
        return {"type": "normalmap_microfacet",
                "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(normalmap_texels), "raw": True},
                "bsdf": nested}

    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 6},
        "sensor": {
            "type": "perspective", "fov": 45,
            "to_world": mi.ScalarTransform4f().look_at(origin=[0, 1.2, 4.5], target=[0, 0.6, 0],
                                                       up=[0, 1, 0]),
            "sampler": {"type": "independent", "sample_count": spp},
            "film": {"type": "hdrfilm", "width": width, "height": height,
                     "rfilter": {"type": "box"}},
        },
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.6}},
        "sun": {"type": "directional", "direction": [0.5, -0.6, -0.6],
                "irradiance": {"type": "rgb", "value": 3.0}},
        "sphere": {"type": "sphere", "center": [0, 1, 0], "radius": 1.0,
                   "bsdf": material({"type": "roughconductor", "material": "Au", "alpha": 0.2})},
        "ground": {"type": "rectangle",
                   "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(10),
                   "bsdf": material({"type": "diffuse",
                                     "reflectance": {"type": "rgb", "value": 0.5}})},
    }


# -- XML scenes for the command line (text: the tests replace parts of it) ---------------------


def xml_plugin(nested: str = '<bsdf type="diffuse"/>', extra: str = "", texture: str = "$nm") -> str:
    """A ``normalmap_microfacet`` element of model ``$model`` around ``nested``, its normal map
    the raw bitmap ``texture``, with ``extra`` properties."""
    return ('<bsdf type="normalmap_microfacet"><string name="model" value="$model"/>' + extra
            + f'<texture type="bitmap" name="normalmap"><string name="filename" value="{texture}"/>'
            '<boolean name="raw" value="true"/></texture>' + nested + "</bsdf>")


def xml_scene(shapes: str, defaults: dict, *, spp="1", width="24", height="16", max_depth=3, fov=None,
              origin="0, 2, 4", target="0, 0, 0", emitters='<emitter type="constant"/>') -> str:
    """A Mitsuba XML scene: the ``<default>`` parameters ``defaults``, a path tracer, a
    perspective camera at ``origin`` looking at ``target``, ``emitters`` and ``shapes``."""
    fov = "" if fov is None else f'<float name="fov" value="{fov}"/>'
    lines = ['<scene version="3.0.0">',
             *(f'    <default name="{k}" value="{v}"/>' for k, v in defaults.items()),
             f'    <integrator type="path"><integer name="max_depth" value="{max_depth}"/></integrator>',
             f'    <sensor type="perspective">{fov}',
             f'        <transform name="to_world"><lookat origin="{origin}" target="{target}" up="0, 1, 0"/>'
             '</transform>',
             f'        <sampler type="independent"><integer name="sample_count" value="{spp}"/></sampler>',
             f'        <film type="hdrfilm"><integer name="width" value="{width}"/>'
             f'<integer name="height" value="{height}"/></film>',
             '    </sensor>', f'    {emitters}', f'    {shapes}', '</scene>', '']
    return "\n".join(lines)


def write_maps(folder) -> None:
    """``normalmap.png`` (8 × 8, flat but for a tilted 4 × 4 square) and ``gray.png`` (the same
    size, one channel: not a normal map) in ``folder``, for the command line's scenes."""
    from mfnormal.io.images import png_bytes

    bumps = np.zeros((8, 8, 3), np.uint8)
    bumps[...] = (128, 128, 255)
    bumps[2:6, 2:6] = (200, 128, 220)
    (folder / "normalmap.png").write_bytes(png_bytes(bumps))
    (folder / "gray.png").write_bytes(png_bytes(np.full((8, 8), 128, np.uint8)))


def mesh(name, positions, normals, uvs, faces, bsdf: dict):
    """A Mitsuba mesh called ``name`` with vertex normals and uvs, its material ``bsdf`` (a dict)."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict(bsdf)
    m = mi.Mesh(name, len(positions), len(faces), props, has_vertex_normals=True, has_vertex_texcoords=True)
    params = mi.traverse(m)
    params["vertex_positions"] = floats(positions)
    params["vertex_normals"] = floats(normals)
    params["vertex_texcoords"] = floats(uvs)
    params["faces"] = uints(faces)
    params.update()
    return m


def light_tracing_agrees(imgs, n_blocks=(6, 8), block=4):
    """Path tracing against light tracing: ``imgs`` = {"path": renders, "ptracer": renders} (n
    renders each, H × W × 3). Per block of ``block``² pixels, Welch's t test of the difference
    (variances from the render-to-render spread, Welch-Satterthwaite degrees of freedom) over the
    blocks path tracing lights (mean > 1e-3). Returns (the lit blocks' p-values, their |z|, the
    images' mean ratio ptracer/path)."""
    from scipy import stats
    n = len(imgs["path"])
    blocks = {k: v.reshape(n, n_blocks[0], block, n_blocks[1], block, 3).mean(axis=(2, 4, 5))
              for k, v in imgs.items()}
    mean = {k: v.mean(0) for k, v in blocks.items()}
    var = {k: np.maximum(v.var(0, ddof=1) / n, 1e-12) for k, v in blocks.items()}
    lit = mean["path"] > 1e-3
    z = ((mean["path"] - mean["ptracer"]) / np.sqrt(var["path"] + var["ptracer"]))[lit]
    dof = ((var["path"] + var["ptracer"]) ** 2
           / (var["path"] ** 2 / (n - 1) + var["ptracer"] ** 2 / (n - 1)))[lit]
    return 2.0 * stats.t.sf(np.abs(z), dof), np.abs(z), imgs["ptracer"].mean() / imgs["path"].mean()


def assert_deterministic_and_smooth(bsdf, wi, wo, rng, what=""):
    """The same queries (wi, wo: n×3) give the same eval, and eval has no jumps in ω_i: jittering
    ω_i by 1e-4 rad (random directions from ``rng``) changes eval by < 1e-2 relative for 99.9 % of
    the queries and by < 3e-2 for all; and wherever the change exceeds 1e-3, jittering by 1e-5
    rad changes it ≥ 5× less (a continuous function scales ~10×, a jump not at all). Relative to
    the value, but never to less than 1 % of the batch's largest value."""
    n = len(wi)
    direction = rng.normal(size=(n, 3))
    direction -= (direction * wi).sum(1, keepdims=True) * wi
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)

    def jittered(delta):
        w = wi + delta * direction
        return w / np.linalg.norm(w, axis=1, keepdims=True)

    v1 = np3(bsdf.eval(mi.BSDFContext(), make_si(wi, n), vec3(wo)))
    np.testing.assert_array_equal(v1, np3(bsdf.eval(mi.BSDFContext(), make_si(wi, n), vec3(wo))))
    scale = np.maximum(v1.max(1), 1e-2 * v1.max())
    rel = {d: np.abs(np3(bsdf.eval(mi.BSDFContext(), make_si(jittered(d), n), vec3(wo))) - v1).max(1) / scale
           for d in (1e-4, 1e-5)}
    assert np.percentile(rel[1e-4], 99.9) < 1e-2 and rel[1e-4].max() < 3e-2, (what, rel[1e-4].max())
    moved = rel[1e-4] > 1e-3
    assert np.all(rel[1e-5][moved] < 0.2 * rel[1e-4][moved]), what


def skip_without_real_assets():
    """Skip a real-asset test (validation/real_assets.py) without its optional dependencies
    (``xatlas``, ``fast-simplification``) or, with an empty asset cache, without ``npm`` to fetch
    the bunny package."""
    import importlib.util
    import shutil

    import pytest
    from validation import assets

    missing = [m for m in ("xatlas", "fast_simplification") if importlib.util.find_spec(m) is None]
    if missing:
        pytest.skip(f"needs {', '.join(missing)} (pip install '.[assets]')")
    if not (assets.cache_dir() / assets.BUNNY).is_file() and shutil.which("npm") is None:
        pytest.skip("needs npm to fetch the bunny package (or it in the asset cache)")


def uv_sphere(n_theta: int = 10, n_phi: int = 20, lean: float = 0.0):
    """A unit UV sphere's (positions, normals, uvs, faces): u = φ/2π, v = θ/π (v = 0 at +z),
    the poles' zero-area triangles left out; its vertex normals leant by ``lean`` towards +x
    (n + lean·x, normalised), so that the map has to tilt them back."""
    theta, phi = np.meshgrid(np.linspace(0, np.pi, n_theta + 1), np.linspace(0, 2 * np.pi, n_phi + 1),
                             indexing="ij")
    pos = np.stack([np.sin(theta) * np.cos(phi), np.sin(theta) * np.sin(phi), np.cos(theta)], -1).reshape(-1, 3)
    uv = np.stack([phi / (2 * np.pi), theta / np.pi], -1).reshape(-1, 2)
    faces = []
    for i in range(n_theta):
        for j in range(n_phi):
            a = i * (n_phi + 1) + j
            b, c, d = a + 1, a + n_phi + 1, a + n_phi + 2
            if i > 0:
                faces.append((a, c, b))
            if i < n_theta - 1:
                faces.append((b, c, d))
    normals = pos + lean * np.array([1.0, 0.0, 0.0])
    return pos, normals / np.linalg.norm(normals, axis=1, keepdims=True), uv, np.array(faces)
