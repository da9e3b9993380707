"""The shadow terminator of smooth-shaded low-poly meshes, against the true sphere.

A low-poly icosphere (vertices on the unit sphere, vertex normals = the true sphere's normals at
the vertices, so the interpolated normal at a point is exactly the radial direction through it)
is rendered against Mitsuba's analytic ``sphere`` under a sun at grazing incidence on part of the
visible disc, for several tessellations and BSDF wrappers (:data:`METHODS`):

- ``plain``: the material on the mesh, shaded with the interpolated normals;
- ``normalmap_flat``: Mitsuba's ``normalmap`` with a flat map and its defaults (its shadowing
  term, Conty Estevez et al. 2019, and its flip of invalid normals);
- ``chiang``: a Chiang, Li & Burley (2019) shadowing term on the light side
  (:class:`ChiangTerminator`, plugin ``chiang_terminator``, the reference written here);
- ``geometric``: ``normalmap_microfacet`` with no map and ``macro_normal="geometric"`` (ours;
  ``geometric_MODEL`` for other models);
- ``flat``: face normals (the facets a terminator fix should not bring back);
- ``offset``: the material as in ``plain``, rendered by ``mfnormal_path`` with its
  ``terminator_offset`` (shadow rays from the smooth surface, Hanika 2021); ``offset_geometric``:
  ``geometric`` rendered so (:data:`INTEGRATORS`; every other method is rendered by ``path``).

:func:`render_case` renders the truth and every method and measures, per method, the error in
the **terminator band** (pixels whose true normal is within :data:`BAND_DEG` of the sun's
horizon) and over the whole disc, and the share of near-black pixels; and the same in the band
against the **corresponding point** of the true sphere (``band_corr``): a mesh pixel is compared
with the truth at the radial projection q = p/|p| of its hit point p, the point whose normal its
vertex normals interpolate (they are the sphere's, so the interpolated normal at p is exactly q),
band by q's normal (:func:`corresponding_truth`). The pixel-aligned band error also holds the
mesh's shape: the hit point lies inside the sphere, its interpolated normal is q, not the true
normal at the pixel, which no shading and no shadow ray changes (measured: most of what remains
with the offset); the corresponding-point error holds only what the shading and the shadow rays
do.

Why a BSDF cannot remove the whole artifact (measured, see validation/results/normal_sources.md;
the integrators' shadow-ray offset does: validation/results/terminator.md):
on a convex mesh a shadow ray toward a direction below a triangle's plane enters the mesh and is
blocked, so every BSDF is dark on the triangles that face away from the sun while the true
sphere is still lit (dimly) over part of them; above a triangle's plane the interpolated normal
already gives the true sphere's cosine. A BSDF decides only the transition at the triangle's
own horizon (a step, or a fade like Chiang's) and what the camera side does where the
interpolated normal faces away from the camera (black for Mitsuba's BSDFs).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import mfnormal  # noqa: F401  (before mitsuba: selects a working libLLVM)
import drjit as dr
import mitsuba as mi
import numpy as np

from validation.heightfield import triangle_mesh

__all__ = ["icosphere", "lowpoly_mesh", "ChiangTerminator", "register", "METHODS", "MATERIALS",
           "INTEGRATORS", "Case", "scene_dict", "render", "render_case", "band_mask", "BAND_DEG", "chiang_G",
           "corresponding_truth"]

#: The terminator band: pixels whose true normal is within this many degrees of the sun's horizon.
BAND_DEG = 25.0
#: Near-black: luminance below this fraction of the truth's luminance at the same pixel.
BLACK_FRACTION = 0.1


# -- Geometry ----------------------------------------------------------------------------------

#: A fixed rotation of the icosphere (axis, degrees): its vertex rings then do not line up with
#: the view or the sun (an unrotated icosphere has vertices exactly on the silhouette seen from +z).
ROTATION = ((0.3, 0.8, 0.5), 23.0)


def _rotation_matrix():
    axis, deg = ROTATION
    a = np.asarray(axis, np.float64) / np.linalg.norm(axis)
    t = math.radians(deg)
    k = np.array([[0, -a[2], a[1]], [a[2], 0, -a[0]], [-a[1], a[0], 0]])
    return np.eye(3) + math.sin(t) * k + (1 - math.cos(t)) * (k @ k)


def icosphere(level: int):
    """(positions, faces) of the unit icosphere subdivided ``level`` times (20·4^level triangles),
    vertices on the unit sphere, faces counter-clockwise seen from outside, turned by
    :data:`ROTATION`."""
    t = (1.0 + math.sqrt(5.0)) / 2.0
    v = [(-1, t, 0), (1, t, 0), (-1, -t, 0), (1, -t, 0), (0, -1, t), (0, 1, t), (0, -1, -t), (0, 1, -t),
         (t, 0, -1), (t, 0, 1), (-t, 0, -1), (-t, 0, 1)]
    f = [(0, 11, 5), (0, 5, 1), (0, 1, 7), (0, 7, 10), (0, 10, 11), (1, 5, 9), (5, 11, 4), (11, 10, 2),
         (10, 7, 6), (7, 1, 8), (3, 9, 4), (3, 4, 2), (3, 2, 6), (3, 6, 8), (3, 8, 9), (4, 9, 5),
         (2, 4, 11), (6, 2, 10), (8, 6, 7), (9, 8, 1)]
    verts = [np.array(p, np.float64) / np.linalg.norm(p) for p in v]
    faces = list(f)
    for _ in range(int(level)):
        cache, out = {}, []

        def mid(a, b):
            key = (min(a, b), max(a, b))
            if key not in cache:
                m = verts[a] + verts[b]
                verts.append(m / np.linalg.norm(m))
                cache[key] = len(verts) - 1
            return cache[key]
        for a, b, c in faces:
            ab, bc, ca = mid(a, b), mid(b, c), mid(c, a)
            out += [(a, ab, ca), (b, bc, ab), (c, ca, bc), (ab, bc, ca)]
        faces = out
    return np.array(verts) @ _rotation_matrix().T, np.array(faces, np.int64)


def lowpoly_mesh(level: int, bsdf, smooth: bool = True, name: str = "lowpoly") -> "mi.Mesh":
    """The icosphere as a Mitsuba mesh with the true sphere's normals at its vertices (``smooth``)
    or face normals (flat shading: vertices split per face), UVs from longitude/latitude."""
    pos, faces = icosphere(level)
    if not smooth:
        pos = pos[faces].reshape(-1, 3)
        faces = np.arange(len(pos)).reshape(-1, 3)
        fn = np.cross(pos[1::3] - pos[0::3], pos[2::3] - pos[0::3])
        nrm = np.repeat(fn / np.linalg.norm(fn, axis=1, keepdims=True), 3, axis=0)
    else:
        nrm = pos / np.linalg.norm(pos, axis=1, keepdims=True)
    uv = np.stack([0.5 + np.arctan2(pos[:, 1], pos[:, 0]) / (2 * np.pi),
                   np.arccos(np.clip(pos[:, 2], -1, 1)) / np.pi], 1)
    return triangle_mesh(name, pos, nrm, uv, faces, bsdf)


# -- The Chiang-style reference term ------------------------------------------------------------

def chiang_G(cos_g, cos_s, cos_gs):
    """Chiang, Li & Burley 2019 ("Taming the shadow terminator"): g = ⟨n_g,ω⟩/(⟨n_s,ω⟩⟨n_g,n_s⟩),
    G = 1 for g ≥ 1, 0 for g ≤ 0 (or ω below the triangle), −g³ + g² + g between (as Cycles'
    ``bump_shadowing_term``)."""
    den = cos_s * cos_gs
    g = cos_g / dr.select(den > 0, den, 1.0)
    smooth = g * (1.0 + g * (1.0 - g))
    out = dr.select(g >= 1.0, 1.0, dr.select(g > 0.0, smooth, 0.0))
    return dr.select((cos_g > 0) & (den > 0), out, dr.select(cos_g > 0, 1.0, 0.0))


class _Chiang:
    """A BSDF wrapper multiplying its nested BSDF by :func:`chiang_G` of the light-side direction
    ω_o, with n_g = ``si.n`` and n_s = ``si.sh_frame.n`` (a reference: not reciprocal, not energy
    conserving, like the production terms it stands for)."""

    def __init__(self, props):
        type(self).__mro__[1].__init__(self, props)
        self.nested = None
        for _, obj in props.objects():
            if isinstance(obj, mi.BSDF):
                self.nested = obj
        if self.nested is None:
            raise ValueError("chiang_terminator: needs a nested BSDF")
        self.m_components = [self.nested.flags(i) for i in range(self.nested.component_count())]
        self.m_flags = self.nested.flags()

    @staticmethod
    def _term(si, wo):
        ng = si.sh_frame.to_local(mi.Vector3f(si.n))
        ng = dr.select(ng.z < 0, -ng, ng)
        return chiang_G(dr.dot(ng, wo), wo.z, ng.z)

    def sample(self, ctx, si, s1, s2, active=True):
        bs, w = self.nested.sample(ctx, si, s1, s2, active)
        return bs, w * self._term(si, bs.wo)

    def eval(self, ctx, si, wo, active=True):
        return self.nested.eval(ctx, si, wo, active) * self._term(si, wo)

    def pdf(self, ctx, si, wo, active=True):
        return self.nested.pdf(ctx, si, wo, active)

    def eval_pdf(self, ctx, si, wo, active=True):
        v, p = self.nested.eval_pdf(ctx, si, wo, active)
        return v * self._term(si, wo), p

    def traverse(self, callback):
        callback.put("nested_bsdf", self.nested, mi.ParamFlags.Differentiable)

    def to_string(self):
        return f"ChiangTerminator[{self.nested}]"


ChiangTerminator = _Chiang
_registered: set = set()


def register():
    """Register ``chiang_terminator`` for the active variant (idempotent)."""
    import mfnormal
    mfnormal.register()
    variant = mi.variant()
    if variant not in _registered:
        methods = {k: v for k, v in vars(_Chiang).items() if k not in ("__dict__", "__weakref__")}
        cls = type("ChiangTerminator", (mi.BSDF,), methods)
        mi.register_bsdf("chiang_terminator", lambda props: cls(props))
        _registered.add(variant)


# -- Methods, materials, scenes ------------------------------------------------------------------

def _ours(model=None):
    def wrap(nested):
        d = {"type": "normalmap_microfacet", "macro_normal": "geometric", "bsdf": nested}
        if model:
            d["model"] = model
        return d
    return wrap


METHODS = {
    "plain": lambda nested: nested,
    "normalmap_flat": lambda nested: {"type": "normalmap", "bsdf": nested, "normalmap": {
        "type": "bitmap", "bitmap": mi.Bitmap(np.full((1, 1, 3), [0.5, 0.5, 1.0], np.float32)), "raw": True}},
    "chiang": lambda nested: {"type": "chiang_terminator", "bsdf": nested},
    "geometric": _ours(),
    "geometric_analytic": _ours("analytic"),
    "geometric_nonseparable": _ours("nonseparable"),
    "flat": lambda nested: nested,        # with face normals (lowpoly_mesh(smooth=False))
}
METHODS["offset"] = METHODS["plain"]
METHODS["offset_geometric"] = METHODS["geometric"]
DEFAULT_METHODS = ("plain", "normalmap_flat", "chiang", "geometric", "flat")
OFFSET_METHODS = ("plain", "geometric", "offset", "offset_geometric")

#: The integrator of a method (``path``, with ``scene_dict``'s max_depth, where not named here).
INTEGRATORS = {"offset": {"type": "mfnormal_path", "max_depth": 6, "terminator_offset": True},
               "offset_geometric": {"type": "mfnormal_path", "max_depth": 6, "terminator_offset": True}}

MATERIALS = {
    "diffuse": {"type": "diffuse", "reflectance": {"type": "rgb", "value": [0.8, 0.8, 0.8]}},
    "glossy": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.15,
               "diffuse_reflectance": {"type": "rgb", "value": [0.5, 0.2, 0.1]}},
}


@dataclass(frozen=True)
class Case:
    """A tessellation (icosphere ``level``: 20·4^level triangles), a material, the sun's angle from
    the view axis (degrees; the terminator crosses the disc), an ambient sky radiance."""
    level: int = 1
    material: str = "diffuse"
    sun_deg: float = 70.0
    sky: float = 0.05

    @property
    def triangles(self) -> int:
        return 20 * 4 ** self.level

    @property
    def name(self) -> str:
        return f"{self.triangles}tri/{self.material}/sun{self.sun_deg:g}"

    def sun(self):
        """Unit vector toward the sun: ``sun_deg`` from the view axis (+z), toward +x and a little +y."""
        t, p = math.radians(self.sun_deg), math.radians(20.0)
        return np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])


def scene_dict(case: Case, shape: dict | "mi.Shape", res: int = 128, spp: int = 64,
               integrator: dict | None = None) -> dict:
    """The shape under the case's sun and sky, an orthographic camera on +z framing the unit disc."""
    l = case.sun()
    d = {"type": "scene", "integrator": integrator or {"type": "path", "max_depth": 6},
         "sensor": {"type": "orthographic",
                    "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 5], target=[0, 0, 0], up=[0, 1, 0])
                    @ mi.ScalarTransform4f().scale([1.05, 1.05, 1.0]),
                    "sampler": {"type": "independent", "sample_count": int(spp)},
                    "film": {"type": "hdrfilm", "width": int(res), "height": int(res), "pixel_format": "rgba",
                             "rfilter": {"type": "box"}}},
         "sun": {"type": "directional", "direction": (-l).tolist(),
                 "irradiance": {"type": "rgb", "value": 3.0}},
         "shape": shape}
    if case.sky > 0:
        d["sky"] = {"type": "constant", "radiance": {"type": "rgb", "value": float(case.sky)}}
    return d


def truth_shape(material: dict) -> dict:
    return {"type": "sphere", "center": [0, 0, 0], "radius": 1.0, "bsdf": material}


def method_shape(case: Case, method: str, material: dict):
    register()
    return lowpoly_mesh(case.level, METHODS[method](material), smooth=method != "flat")


def render(scene, spp: int, seed: int, pass_spp: int = 64) -> np.ndarray:
    """RGBA (H×W×4 float64) at ``spp`` in passes."""
    scene = mi.load_dict(scene) if isinstance(scene, dict) else scene
    acc, done, i = 0.0, 0, 0
    while done < spp:
        n = min(pass_spp, spp - done)
        acc = acc + np.array(mi.render(scene, spp=n, seed=seed + i), np.float64) * n
        done, i = done + n, i + 1
    out = acc / spp
    return np.where(np.isfinite(out), out, 0.0)


FRAME = 1.05      # the orthographic camera sees [−FRAME, FRAME]² of the (x, y) plane


def pixel_centres(res: int):
    """World (x, y) of the pixel centres (image right = +x, up = +y), res × res each."""
    t = (np.arange(res) + 0.5) / res * 2.0 - 1.0
    x, y = np.meshgrid(t * FRAME, -t * FRAME, indexing="xy")
    return x, y


def true_normals(case: Case, res: int) -> np.ndarray:
    """The unit sphere's normal at each pixel centre (H×W×3, 0 off the disc)."""
    x, y = pixel_centres(res)
    z2 = 1.0 - x * x - y * y
    n = np.stack([x, y, np.sqrt(np.maximum(z2, 0.0))], -1)
    return np.where((z2 > 0)[..., None], n, 0.0)


def mesh_normals(level: int, res: int) -> np.ndarray:
    """The icosphere's geometric (triangle) normal at each pixel centre, seen from +z (0 off it)."""
    x, y = pixel_centres(res)
    scene = mi.load_dict({"type": "scene", "mesh": lowpoly_mesh(level, None)})
    o = mi.Point3f(mi.Float(x.ravel()), mi.Float(y.ravel()), mi.Float(np.full(x.size, 5.0)))
    ray = mi.Ray3f(o, mi.Vector3f(0.0, 0.0, -1.0))
    si = scene.ray_intersect(ray)
    n = np.array(si.n, np.float64).T.reshape(res, res, 3)
    return np.where(np.array(si.is_valid()).reshape(res, res)[..., None], n, 0.0)


def band_mask(normals: np.ndarray, sun: np.ndarray, band_deg: float = BAND_DEG) -> np.ndarray:
    """Pixels whose true normal is within ``band_deg`` of the sun's horizon (either side)."""
    on = np.linalg.norm(normals, axis=-1) > 0.5
    elev = np.degrees(np.arcsin(np.clip(normals @ sun, -1, 1)))
    return on & (np.abs(elev) < band_deg)


def luminance(img):
    return img[..., :3] @ np.array([0.2126, 0.7152, 0.0722])


#: Errors are also taken on BLOCK × BLOCK pixel means (blocks wholly inside the mask): the
#: images' bias with 1/BLOCK² of their noise.
BLOCK = 4


def _blocks(a, b):
    H, W = a.shape[:2]
    return a[:H // b * b, :W // b * b].reshape(H // b, b, W // b, b, *a.shape[2:]).mean(axis=(1, 3))


def _errors(img, truth, mask, block=BLOCK):
    """Luminance errors over ``mask`` relative to the truth's mean there: ``mae``, ``rmse``, ``bias``
    per pixel, ``mae_block`` on block means; ``black``: pixels below BLACK_FRACTION of the truth at
    that pixel, ``black_any``: below BLACK_FRACTION of the truth's median (the harness' near-black)."""
    y_all, yt_all = luminance(img), luminance(truth)
    y, yt = y_all[mask], yt_all[mask]
    mean = max(float(yt.mean()), 1e-12)
    full = _blocks(mask.astype(np.float64), block) > 0.999
    yb, ytb = _blocks(y_all, block)[full], _blocks(yt_all, block)[full]
    return {"mae": float(np.mean(np.abs(y - yt)) / mean),
            "mae_block": float(np.mean(np.abs(yb - ytb)) / mean) if yb.size else float("nan"),
            "rmse": float(np.sqrt(np.mean((y - yt) ** 2)) / mean),
            "bias": float((y.mean() - yt.mean()) / mean),
            "black": float(np.mean(y < BLACK_FRACTION * yt)),
            "black_any": float(np.mean(y < BLACK_FRACTION * max(float(np.median(yt)), 1e-12))),
            "pixels": int(mask.sum()), "blocks": int(full.sum())}


def render_case(case: Case, methods=DEFAULT_METHODS, res: int = 128, spp: int = 64, ref_factor: int = 4,
                seed: int = 0, log=None, with_oracle: bool = False) -> dict:
    """Render the truth (``ref_factor × spp``, and once at ``spp`` for the noise floor) and every
    method at ``spp``; errors in the band and on the disc (pixel centres on both the sphere and
    the mesh) per method. Returns a dict of metrics and images."""
    log = log or (lambda *a: None)
    register()
    material = MATERIALS[case.material]
    truth = render(scene_dict(case, truth_shape(material), res, spp), spp * ref_factor, seed * 1000 + 100)
    floor_img = render(scene_dict(case, truth_shape(material), res, spp), spp, seed * 1000 + 500)
    normals = true_normals(case, res)
    band = band_mask(normals, case.sun())
    # Pixels on both the sphere and the mesh (the mesh's silhouette is inside the sphere's).
    cover = (np.linalg.norm(normals, axis=-1) > 0.5) & (np.linalg.norm(mesh_normals(case.level, res), axis=-1) > 0.5)
    out = {"case": case.name, "images": {"truth": truth}, "metrics": {}, "band_pixels": int((band & cover).sum()),
           "cover": cover, "band": band}
    corr, corr_band = corresponding_truth(case, truth, res)
    out["corr_band"] = corr_band
    for m in methods:
        img = render(scene_dict(case, method_shape(case, m, material), res, spp, INTEGRATORS.get(m)), spp,
                     seed * 1000)
        out["images"][m] = img
        out["metrics"][m] = {"band": _errors(img, truth, band & cover), "disc": _errors(img, truth, cover),
                             "band_corr": _errors(img, corr, corr_band)}
        mb, md, mc = (out["metrics"][m][k] for k in ("band", "disc", "band_corr"))
        log(f"  {m:24s} band mae {mb['mae']:.4f} block {mb['mae_block']:.4f} rmse {mb['rmse']:.4f} "
            f"black {mb['black']:.4f} | disc mae {md['mae']:.4f} block {md['mae_block']:.4f} black {md['black']:.4f}"
            f" | corr block {mc['mae_block']:.4f} black {mc['black']:.4f}")
    if with_oracle:
        img = oracle(case, res, spp, seed)
        out["images"]["oracle"] = img
        out["metrics"]["oracle"] = {"band": _errors(img, truth, band & cover), "disc": _errors(img, truth, cover)}
        mb, md = out["metrics"]["oracle"]["band"], out["metrics"]["oracle"]["disc"]
        log(f"  {'oracle (bound)':24s} band mae {mb['mae']:.4f} block {mb['mae_block']:.4f} rmse {mb['rmse']:.4f} "
            f"| disc mae {md['mae']:.4f} block {md['mae_block']:.4f}")
    out["floor"] = {"band": _errors(floor_img, truth, band & cover), "disc": _errors(floor_img, truth, cover),
                    "band_corr": _errors(corresponding_truth(case, floor_img, res)[0], corr, corr_band)}
    log(f"  {'(noise floor)':24s} band mae {out['floor']['band']['mae']:.4f} block {out['floor']['band']['mae_block']:.4f}"
        f" | disc mae {out['floor']['disc']['mae']:.4f} block {out['floor']['disc']['mae_block']:.4f}")
    return out


def mesh_points(level: int, res: int):
    """The icosphere's hit point at each pixel centre seen from +z (H×W×3) and where there is one."""
    x, y = pixel_centres(res)
    scene = mi.load_dict({"type": "scene", "mesh": lowpoly_mesh(level, None)})
    o = mi.Point3f(mi.Float(x.ravel()), mi.Float(y.ravel()), mi.Float(np.full(x.size, 5.0)))
    si = scene.ray_intersect(mi.Ray3f(o, mi.Vector3f(0.0, 0.0, -1.0)))
    return (np.array(si.p, np.float64).T.reshape(res, res, 3), np.array(si.is_valid()).reshape(res, res))


def corresponding_truth(case: Case, truth: np.ndarray, res: int, band_deg: float = BAND_DEG):
    """The truth image resampled (bilinearly) at the corresponding point of each mesh pixel, the
    radial projection q = p/|p| of its hit point p, and the band of q's normal (q facing the
    camera by more than 0.05, its 1-pixel neighbourhood on the disc)."""
    from scipy.ndimage import map_coordinates
    p, valid = mesh_points(case.level, res)
    q = p / np.maximum(np.linalg.norm(p, axis=-1, keepdims=True), 1e-12)
    row = (1.0 - q[..., 1] / FRAME) / 2.0 * res - 0.5
    col = (q[..., 0] / FRAME + 1.0) / 2.0 * res - 0.5
    out = np.stack([map_coordinates(truth[..., c], [row.ravel(), col.ravel()], order=1, mode="nearest")
                    .reshape(res, res) for c in range(truth.shape[-1])], -1)
    x, y = pixel_centres(res)
    inside = np.hypot(x, y) < 1.0 - 2.0 * FRAME / res      # the truth's pixels well inside the disc
    rim = map_coordinates(inside.astype(np.float64), [row.ravel(), col.ravel()], order=1).reshape(res, res)
    ok = valid & (q[..., 2] > 0.05) & (rim > 0.999)
    return out, ok & band_mask(np.where(ok[..., None], q, 0.0), case.sun(), band_deg)


def oracle(case: Case, res: int, spp: int, seed: int = 0) -> np.ndarray:
    """The best a BSDF on the mesh can do under the integrator's shadow rays: the truth where the
    mesh's triangle at the pixel faces the sun, the truth without the sun elsewhere (a shadow ray
    toward a sun below the triangle's plane enters the convex mesh and is blocked)."""
    material = MATERIALS[case.material]
    truth = render(scene_dict(case, truth_shape(material), res, spp), spp, seed * 1000 + 700)
    nosun = scene_dict(case, truth_shape(material), res, spp)
    del nosun["sun"]
    dark = render(nosun, spp, seed * 1000 + 800)
    lit = (mesh_normals(case.level, res) @ case.sun()) > 0
    return np.where(lit[..., None], truth, dark)


# -- The shadow-ray offset, measured ----------------------------------------------------------------

def offset_report(levels=(1, 2), materials=("diffuse", "glossy"), res=128, spp=256, log=print,
                  methods=OFFSET_METHODS) -> str:
    """The markdown table of ``methods`` (:data:`OFFSET_METHODS`: interpolated normals and
    ``geometric``, each without and with ``mfnormal_path``'s terminator offset) on each case:
    block MAE in the band, pixel-aligned and against the corresponding point, near-black band
    pixels, disc error."""
    lines = ["| case | method | band error | band error, corresponding point | black (band) | disc error |",
             "|---|---|---|---|---|---|"]
    for level in levels:
        for material in materials:
            case = Case(level, material)
            log(case.name)
            r = render_case(case, methods, res=res, spp=spp, log=log)
            for m in methods:
                mb, mc, md = (r["metrics"][m][k] for k in ("band", "band_corr", "disc"))
                lines.append(f"| {case.name} | {m} | {mb['mae_block']:.4f} | {mc['mae_block']:.4f} | "
                             f"{max(mb['black'], mc['black']):.4f} | {md['mae_block']:.4f} |")
            fb, fc = r["floor"]["band"], r["floor"]["band_corr"]
            lines.append(f"| {case.name} | (noise floor) | {fb['mae_block']:.4f} | {fc['mae_block']:.4f} | | |")
    return "\n".join(lines) + "\n"


def main(argv=None):
    """``python -m validation.terminator [--levels 1,2] [--materials diffuse,glossy]
    [--methods plain,geometric,offset,offset_geometric] [--res 128] [--spp 256] [--out FILE]``"""
    import argparse
    ap = argparse.ArgumentParser(description=main.__doc__)
    ap.add_argument("--levels", default="1,2")
    ap.add_argument("--materials", default="diffuse,glossy")
    ap.add_argument("--methods", default=",".join(OFFSET_METHODS))
    ap.add_argument("--res", type=int, default=128)
    ap.add_argument("--spp", type=int, default=256)
    ap.add_argument("--out", default=None, help="write the table to this markdown file")
    args = ap.parse_args(argv)
    table = offset_report(tuple(int(x) for x in args.levels.split(",")), tuple(args.materials.split(",")),
                          args.res, args.spp, methods=tuple(args.methods.split(",")))
    print(table)
    if args.out:
        from pathlib import Path
        Path(args.out).write_text(f"`python -m validation.terminator --levels {args.levels} --materials "
                                  f"{args.materials} --methods {args.methods} --res {args.res} --spp {args.spp}`"
                                  f" (truth at 4× spp; errors: mean |ΔY| / mean Y of the truth over 4×4-pixel "
                                  f"blocks)\n\n" + table)


if __name__ == "__main__":
    mi.set_variant("llvm_ad_rgb")
    main()
