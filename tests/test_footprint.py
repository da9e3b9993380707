"""The pixel's footprint in the integrators (``footprint``; src/mfnormal/plugins/cone.py): the
ray cone carried from the camera, and its ellipse in uv that the BSDF receives in
``si.duv_dx``, ``si.duv_dy``.

- First hit, a ground plane seen 50° to 85° off its normal by a 40° pinhole (256²): the
  footprint's ellipse in uv (its semi-axes, the singular values of [duv_dx duv_dy]) is the
  one of Mitsuba's own ray differentials (``si.compute_uv_partials`` on the same rays) within
  5 % (the cone is round where a perspective pixel's steps in x and y differ by cos φ off the
  axis, and it is the differentials' first order where a differential is a pixel's finite
  step), their areas within 4 %; through an orthographic camera (β0 = 0, w0 the pixel) the
  same ellipse within 1e-3. End to end, a probe BSDF that passes rays through, weighted by the
  footprint it receives, renders under ``mfnormal_path`` and ``mfnormal_prb`` the cone
  module's footprint of the pixel centres (rtol 1e-4; at 4 spp scaled by 1/√spp, as Mitsuba
  scales ``path``'s differentials: 4 %).
- Mirrors: off a flat mirror the width at the second hit is w0 + β0·(t1 + t2) (β0 measured
  from the neighbouring pixels' rays; rtol 1e-3); off a convex spherical mirror it is
  w1 + (β0 + 2·w1/(R·cos θ))·t2, checked against a brute force: two camera rays 1e-4 rad apart
  in the plane of incidence, traced in float64 to the sphere and the probe's plane, their
  separation across the reflected ray (within 1 %, measured 0.3 %, θ up to 39°). Seen from
  inside, a sphere's normal turns the other way (a focusing mirror).
- The rule at each bounce, on a flat surface: glossy or diffuse → the cone of solid angle
  1/pdf (or the arriving one if wider), mirror → unchanged, refraction → β/η, null →
  unchanged, |β| ≤ π.
- ``footprint`` false and true render the same image bit for bit (none of the scene's BSDFs
  reads it: ``normalmap_microfacet`` at its default ``filter="none"``), and
  false is ``path``; ``mfnormal_prb`` the same. A string for ``footprint`` is refused at load
  in one line naming it.
- ``mfnormal_prb``: the footprint is the same in the primal and the differential phase (a
  probe whose weight's relative derivative is its footprint: forward derivative = primal²,
  rtol 1e-5), and detached (no gradient on duv or the cone where the geometry has one).
- Degenerate uv (a sphere's pole, a mesh without uvs, a mesh whose uvs are all one point,
  dp_du and dp_dv parallel or not finite): finite footprints, 0 where no uv step exists.

Everything is deterministic (pixel centres: a stratified sampler without jitter).
"""

import math

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from variant import VARIANT  # noqa: E402
mi.set_variant(VARIANT)
mfnormal.register()

from helpers import bumps_normalmap, floats, mesh, small_scene, uints, uv_sphere  # noqa: E402
from param_fuzzing import assert_names, refusal  # noqa: E402
from mfnormal.plugins import cone  # noqa: E402

INTEGRATORS = ["mfnormal_path", "mfnormal_prb"]
MARK = 0.5          # the probe's third channel: the pixel's path went through the probe


class FootprintProbe(mi.BSDF):
    """Passes rays straight through (a delta transmission, η = 1) with the weight
    (|duv_dx|·e^(θ·|duv_dx|), |duv_dy|, MARK): what it sees of the footprint. Declares a
    stochastic eval, so that ``mfnormal_prb`` differentiates its sample's weight (θ)."""

    stochastic_eval = True

    def __init__(self, props):
        super().__init__(props)
        self.theta = mi.Float(0.0)
        self.m_flags = mi.BSDFFlags.DeltaTransmission | mi.BSDFFlags.FrontSide | mi.BSDFFlags.BackSide
        self.m_components = [self.m_flags]

    def sample(self, ctx, si, sample1, sample2, active=True):
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo, bs.pdf, bs.eta = -si.wi, mi.Float(1.0), mi.Float(1.0)
        bs.sampled_type = mi.UInt32(int(mi.BSDFFlags.DeltaTransmission))
        across = dr.norm(si.duv_dx)
        weight = mi.Color3f(across * dr.exp(self.theta * across), dr.norm(si.duv_dy), MARK)
        return bs, dr.select(active, weight, 0.0)

    def eval(self, ctx, si, wo, active=True):
        return mi.Color3f(0.0)

    def pdf(self, ctx, si, wo, active=True):
        return mi.Float(0.0)

    def eval_pdf(self, ctx, si, wo, active=True):
        return mi.Color3f(0.0), mi.Float(0.0)

    def traverse(self, callback):
        callback.put("theta", self.theta, mi.ParamFlags.Differentiable)

    def to_string(self):
        return "FootprintProbe[]"


@pytest.fixture(autouse=True)
def _probe():
    mi.register_bsdf("footprint_probe", lambda props: FootprintProbe(props))


def camera(origin, target, fov, res, spp=1):
    """A pinhole whose samples are the pixel centres (stratified, no jitter) at 1 spp."""
    return {"type": "perspective", "fov": fov,
            "to_world": mi.ScalarTransform4f().look_at(origin=origin, target=target, up=[0, 1, 0]),
            "sampler": {"type": "stratified", "sample_count": spp, "jitter": False},
            "film": {"type": "hdrfilm", "width": res, "height": res, "rfilter": {"type": "box"},
                     "pixel_format": "rgb"}}


def integrator(kind, footprint=True, max_depth=5):
    return {"type": kind, "max_depth": max_depth, "rr_depth": 100, "footprint": footprint}


def ground_scene(kind="mfnormal_path", res=256, spp=1, bsdf=None, sensor=None):
    """A 40 × 40 ground plane (y = 0) seen from 1 m above by a 40° frame tilted 20° down: 50°
    off its normal at the bottom edge, 87° at its far edge near the top."""
    return mi.load_dict({
        "type": "scene", "integrator": integrator(kind),
        "sensor": sensor or camera([0, 1, 0], [0, 1 - math.tan(math.radians(20)), -1], 40, res, spp),
        "sky": {"type": "constant"},
        "ground": {"type": "rectangle", "bsdf": bsdf or {"type": "footprint_probe"},
                   "to_world": mi.ScalarTransform4f().rotate([1, 0, 0], -90).scale(20)}})


def orthographic(res=64):
    """An orthographic camera that sees the ground 80° off its normal (a 2 × 2 view)."""
    d = camera([0, 1, 0], [0, 1 - math.tan(math.radians(10)), -1], 40, res)
    d["type"] = "orthographic"
    del d["fov"]
    return d


def pixel_rays(scene, spp=1, shift=(0, 0)):
    """The camera rays through the pixel centres (row-major), their differentials scaled by 1/√spp
    (``shift``: through the centres of the pixels that many pixels to the right and down)."""
    sensor = scene.sensors()[0]
    res = sensor.film().crop_size()
    y, x = np.mgrid[0:res[1], 0:res[0]]
    pos = mi.Point2f(mi.Float((x.ravel() + 0.5 + shift[0]) / res[0]),
                     mi.Float((y.ravel() + 0.5 + shift[1]) / res[1]))
    ray, _ = sensor.sample_ray_differential(0.0, 0.5, pos, mi.Point2f(0.5))
    ray.scale_differential(spp ** -0.5)
    return ray


def cone_footprint(scene, ray):
    """The cone module's first-hit footprint of ``ray``: (si, duv_dx, duv_dy)."""
    si = scene.ray_intersect(mi.Ray3f(ray), cone.RAY_FLAGS, True)
    w, beta = cone.camera_cone(ray)
    si, _ = cone.at_hit(si, ray, w, beta)
    return si, np.array(si.duv_dx).T, np.array(si.duv_dy).T


def semi_axes(a, b):
    """The singular values (largest first) of the 2 × 2 matrices [a b], a and b: (n, 2)."""
    return np.linalg.svd(np.stack([a, b], -1), compute_uv=False)


def render(scene, spp=0, seed=0):
    return np.array(mi.render(scene, spp=spp, seed=seed), dtype=np.float64)


# -- 1. The first hit against Mitsuba's ray differentials ------------------------------------------

def differentials_footprint(scene, ray):
    """Mitsuba's: ``si.compute_uv_partials`` of ``ray``'s differentials (duv_dx, duv_dy)."""
    si = scene.ray_intersect(mi.Ray3f(ray))
    si.compute_uv_partials(ray)
    return np.array(si.duv_dx).T, np.array(si.duv_dy).T


def test_first_hit_footprint_is_the_ray_differentials_ellipse():
    """Perspective, 256² film, 40°: every 7th pixel where the ground is seen 50°–85° off its
    normal. The cone's ellipse within 5 % of the differentials': the cone is round, while a
    perspective pixel's angular steps in x and y differ by cos φ at φ off the axis (the cone
    takes their mean: ≤ 3 % at the frame's edge, 20°), and a differential is a pixel's finite
    step, the cone its derivative (+3 % at 85°). Their areas within 4 %."""
    scene = ground_scene()
    ray = pixel_rays(scene)
    si, dx, dy = cone_footprint(scene, ray)
    ref_dx, ref_dy = differentials_footprint(scene, ray)
    angle = np.degrees(np.arccos(np.clip(np.abs(np.array(dr.dot(si.n, ray.d))), 0, 1)))
    pick = np.array(si.is_valid()) & (angle > 50) & (angle < 85) & (np.arange(angle.size) % 7 == 0)
    assert pick.sum() > 1000 and angle[pick].max() > 84.9
    ours, theirs = semi_axes(dx[pick], dy[pick]), semi_axes(ref_dx[pick], ref_dy[pick])
    rel = np.abs(ours / theirs - 1.0)
    assert rel.max() < 0.05, (rel.max(), angle[pick][np.argmax(rel.max(axis=1))])
    assert np.abs(ours.prod(1) / theirs.prod(1) - 1.0).max() < 0.04


def test_orthographic_footprint_is_the_ray_differentials_one():
    """Parallel rays (β0 = 0, w0 the pixel's size), the ground 80° off: the differentials are
    exact there, so the same ellipse up to their float rounding (1e-3: the
    differences of nearby points)."""
    scene = ground_scene(sensor=orthographic())
    ray = pixel_rays(scene)
    w, beta = cone.camera_cone(ray)
    assert np.all(np.array(beta) == 0) and np.allclose(np.array(w), 2 / 64, rtol=1e-4)
    _, dx, dy = cone_footprint(scene, ray)
    ours, theirs = semi_axes(dx, dy), semi_axes(*differentials_footprint(scene, ray))
    np.testing.assert_allclose(ours, theirs, rtol=1e-3)
    np.testing.assert_allclose(ours[:, 0] / ours[:, 1], 1 / math.cos(math.radians(80)), rtol=1e-3)


@pytest.mark.parametrize("kind", INTEGRATORS)
@pytest.mark.parametrize("spp", [1, 4])
def test_integrators_give_the_bsdf_the_cone_footprint(kind, spp):
    """The probe's image at 1 spp is the pixel centres' footprint; at 4 spp (the strata's
    centres) within 4 % of it scaled by 1/2, the footprint of one of 4 samples."""
    scene = ground_scene(kind, res=32, spp=spp)
    img = render(scene, spp=spp)
    _, dx, dy = cone_footprint(scene, pixel_rays(scene, spp))
    seen = img[..., 2].ravel() == MARK
    assert seen.sum() > 300
    got = img.reshape(-1, 3)[seen, :2]
    want = np.stack([np.linalg.norm(dx, axis=1), np.linalg.norm(dy, axis=1)], -1)[seen]
    assert np.all(want > 0)
    np.testing.assert_allclose(got, want, rtol=1e-4 if spp == 1 else 0.04)


# -- 2. Mirrors: the width at the second hit -----------------------------------------------------

CAMERA_Z, PROBE_Z, RES = 4.0, 6.0, 15


def mirror_scene(mirror, kind="mfnormal_path"):
    """``mirror`` (a shape dict, a perfect mirror) at the origin seen from z = 4 (a 30° pinhole,
    15²: the centre pixel's ray is the axis), the probe's plane at z = 6 behind the camera: the
    mirrored rays go through it to the sky."""
    mirror = dict(mirror, bsdf={"type": "conductor", "material": "none"})
    return mi.load_dict({
        "type": "scene", "integrator": integrator(kind),
        "sensor": camera([0, 0, CAMERA_Z], [0, 0, 0], 30, RES),
        "sky": {"type": "constant"}, "mirror": mirror,
        "probe": {"type": "rectangle", "bsdf": {"type": "footprint_probe"},
                  "to_world": mi.ScalarTransform4f().translate([0, 0, PROBE_Z]).scale(20)}})


def probe_width(img):
    """The cone's width where the rays cross the probe's plane: |duv_dx| (the footprint's axis
    across the plane of incidence, of length |w|) times |dp_du| = 40; NaN off the probe."""
    return np.where(img[..., 2] == MARK, img[..., 0] * 40.0, np.nan).ravel()


def pixel_spread(scene):
    """β0 per pixel, independently of the cone module: the mean angle between the pixel
    centre's ray and its neighbours' (the next pixel's centre in x, in y)."""
    d = np.array(pixel_rays(scene).d).T.astype(np.float64)
    angles = [np.arccos(np.clip(np.sum(d * np.array(pixel_rays(scene, shift=s).d).T, -1), -1, 1))
              for s in ((1, 0), (0, 1))]
    return 0.5 * (angles[0] + angles[1])


@pytest.mark.parametrize("kind", INTEGRATORS)
def test_a_flat_mirror_carries_the_cone_unchanged(kind):
    """A plane mirror tilted 10°: w = β0·(t1 + t2) at the probe (w0 = 0: a pinhole), rtol 1e-3."""
    mirror = {"type": "rectangle", "to_world": mi.ScalarTransform4f().rotate([0, 1, 0], 10).scale(5)}
    scene = mirror_scene(mirror, kind)
    width = probe_width(render(scene))
    ray = pixel_rays(scene)
    si1 = scene.ray_intersect(mi.Ray3f(ray))
    si2 = scene.ray_intersect(si1.spawn_ray(mi.reflect(-ray.d, si1.n)))
    t = np.array(si1.t) + np.array(si2.t)
    seen = ~np.isnan(width)
    assert seen.sum() == RES * RES
    np.testing.assert_allclose(width[seen], pixel_spread(scene)[seen] * t[seen], rtol=1e-3)


def brute_force_width(d, delta=1e-4, radius=1.0):
    """Per unit β0: the separation at the probe's plane, across the mirrored ray, of the camera
    rays ``d`` and ``d`` turned by ``delta`` in the plane of incidence, off the sphere of
    ``radius`` at the origin (float64, analytic), divided by ``delta``."""
    o = np.array([0.0, 0.0, CAMERA_Z])

    def trace(d):
        b = o @ d
        t1 = -b - np.sqrt(b * b - (o @ o - radius ** 2))
        p = o + t1 * d
        n = p / radius
        r = d - 2 * (d @ n) * n
        return p + (PROBE_Z - p[2]) / r[2] * r, r

    side = np.cross(np.cross(d, -o), d)          # in the plane of (d, the sphere's centre)
    side = side / np.linalg.norm(side) if np.linalg.norm(side) > 1e-12 else np.array([1.0, 0, 0])
    (p0, r0), (p1, _) = trace(d), trace(np.cos(delta) * d + np.sin(delta) * side)
    gap = p1 - p0
    return np.linalg.norm(gap - (gap @ r0) * r0) / delta


@pytest.mark.parametrize("kind", INTEGRATORS)
def test_a_convex_mirror_widens_the_cone_by_its_curvature(kind):
    """A unit sphere: β1 = β0 + 2·w1/(R·cos θ) (the normal turns by w1/(R cos θ) across the
    footprint along the plane of incidence), w = w1 + β1·t2 at the probe: equal to the brute
    force within 1 % (measured: 0.3 %) at every pixel whose mirrored ray reaches the probe (θ
    from 0, the centre pixel, to 39°), where a flat mirror's width would be 4.8-7.7× smaller."""
    pole_up = mi.ScalarTransform4f().rotate([1, 0, 0], 90)      # its uv's pole away from the view
    scene = mirror_scene({"type": "sphere", "radius": 1.0, "to_world": pole_up}, kind)
    width = probe_width(render(scene))
    d = np.array(pixel_rays(scene).d).T.astype(np.float64)
    seen = np.flatnonzero(~np.isnan(width))
    assert seen.size > 40 and RES * RES // 2 in seen
    brute = np.array([brute_force_width(d[i] / np.linalg.norm(d[i])) for i in seen])
    np.testing.assert_allclose(width[seen], pixel_spread(scene)[seen] * brute, rtol=0.01)


def test_a_concave_mirror_focuses_the_cone():
    """Seen from inside a sphere of radius 2 the normal turns the other way: Δ = -w/R."""
    scene = mi.load_dict({"type": "scene", "ball": {"type": "sphere", "radius": 2.0}})
    ray = mi.Ray3f(mi.Point3f(0.0), dr.normalize(mi.Vector3f(0.3, 0.2, 1.0)))
    si = scene.ray_intersect(ray, cone.RAY_FLAGS, True)
    si, w = cone.at_hit(si, ray, mi.Float(0.0), mi.Float(0.01))
    np.testing.assert_allclose(np.array(w), 0.02, rtol=1e-5)
    np.testing.assert_allclose(np.array(cone.normal_turn(si)), -0.02 / 2.0, rtol=1e-4)


def flat_hit():
    """A hit on the ground plane 60° off its normal, with its footprint (w = 0.1)."""
    scene = mi.load_dict({"type": "scene", "ground": {"type": "rectangle", "to_world": mi.ScalarTransform4f().scale(5)}})
    d = [math.sin(math.radians(60)), 0.0, -math.cos(math.radians(60))]
    ray = mi.Ray3f(mi.Point3f(-1.73205, 0.0, 1.0), mi.Vector3f(*d))
    si = scene.ray_intersect(ray, cone.RAY_FLAGS, True)
    return cone.at_hit(si, ray, mi.Float(0.1), mi.Float(0.0))[0]


def sampled(kind, pdf=1.0, eta=1.0, wo_z=0.5):
    bs = dr.zeros(mi.BSDFSample3f)
    bs.wo = mi.Vector3f(math.sqrt(1 - wo_z ** 2), 0.0, wo_z)
    bs.pdf, bs.eta, bs.sampled_type = mi.Float(pdf), mi.Float(eta), mi.UInt32(int(kind))
    return bs


@pytest.mark.parametrize("kind,pdf,eta,wo_z,beta_in,want", [
    (mi.BSDFFlags.DiffuseReflection, 1 / math.pi, 1.0, 0.5, 0.01, 2 * math.pi / 3),   # 1/pdf = π sr
    (mi.BSDFFlags.GlossyReflection, 100.0, 1.0, 0.5, 0.01, 2 * math.acos(1 - 1 / (200 * math.pi))),
    (mi.BSDFFlags.GlossyReflection, 100.0, 1.0, 0.5, 0.5, 0.5),             # a wider cone stays
    (mi.BSDFFlags.GlossyReflection, 0.0, 1.0, 0.5, 0.01, math.pi),          # no pdf: a hemisphere
    (mi.BSDFFlags.DiffuseReflection, 0.01, 1.0, 0.5, 0.01, math.pi),        # 1/pdf > 2π sr: capped
    (mi.BSDFFlags.DeltaReflection, 1.0, 1.0, 0.5, 0.01, 0.01),              # flat mirror: unchanged
    (mi.BSDFFlags.DeltaTransmission, 1.0, 1.5, -0.5, 0.03, 0.02),           # refraction: β/η
    (mi.BSDFFlags.Null, 1.0, 1.0, -0.5, 0.03, 0.03),                        # pass-through
    (mi.BSDFFlags.DeltaReflection, 1.0, 1.0, 0.5, 10.0, math.pi)])          # |β| ≤ π
def test_bounce_rules(kind, pdf, eta, wo_z, beta_in, want):
    """On a flat surface (no normal turn): a glossy or diffuse sample sets the spread to the cone
    whose solid angle is 1/pdf (at least the arriving one), a mirror keeps it, a refraction
    divides it by η, a null interaction keeps it."""
    si = flat_hit()
    beta = cone.bounce(mi.Float(beta_in), si, sampled(kind, pdf, eta, wo_z))
    np.testing.assert_allclose(np.array(beta), want, rtol=1e-5)


# -- 3. Images: unchanged, with the footprint on or off ----------------------------------------------

def busy_scene(kind, footprint, offset):
    """tests/helpers.py's normal-mapped gold sphere and ground, with a glass ball (delta
    reflection and transmission) and a smooth-shaded, normal-mapped mesh sphere (curvature from
    vertex normals; the terminator offset ``offset``): 32 × 24, 4 spp."""
    d = small_scene(bumps_normalmap(16), spp=4, width=32, height=24)
    d["integrator"] = {"type": kind, "max_depth": 6} if kind == "path" else integrator(kind, footprint, 6)
    if kind != "path":
        d["integrator"].update(rr_depth=5, terminator_offset=offset)
    d["glass"] = {"type": "sphere", "center": [1.4, 0.5, 0.8], "radius": 0.5, "bsdf": {"type": "dielectric"}}
    pos, normals, uvs, faces = uv_sphere(8, 12)
    bsdf = dict(d["sphere"]["bsdf"], bsdf={"type": "roughconductor", "alpha": 0.3})
    d["ball"] = mesh("ball", pos * 0.6 + [-1.5, 0.6, 0.5], normals, uvs, faces, bsdf)
    return mi.load_dict(d)


def test_footprint_off_and_on_render_path_s_image_bit_for_bit():
    """No BSDF reads the footprint yet: ``mfnormal_path`` with it off (and the terminator offset
    off) is ``path``; with it on, each integrator renders its image with it off."""
    cases = [("path", None, None), ("mfnormal_path", False, False), ("mfnormal_path", False, True),
             ("mfnormal_path", True, True), ("mfnormal_prb", False, True), ("mfnormal_prb", True, True)]
    images = {case: render(busy_scene(*case), seed=5) for case in cases}
    assert images[cases[0]].mean() > 0.05
    assert np.array_equal(images[("mfnormal_path", False, False)], images[("path", None, None)])
    assert np.array_equal(images[("mfnormal_path", True, True)], images[("mfnormal_path", False, True)])
    assert np.array_equal(images[("mfnormal_prb", True, True)], images[("mfnormal_prb", False, True)])


@pytest.mark.parametrize("kind", INTEGRATORS)
def test_footprint_is_a_boolean(kind):
    """A string (XML ``<string>``, or in a dict) is refused at load in one line naming it."""
    xml = (f'<scene version="3.0.0"><integrator type="{kind}"><string name="footprint" value="false"/>'
           '</integrator></scene>')
    for line in (refusal(lambda: mi.load_string(xml)),
                 refusal(lambda: mi.load_dict({"type": kind, "footprint": "false"}))):
        assert assert_names(line, kind, ["footprint"]) == "footprint"
        assert "must be a boolean" in line and '<boolean name="footprint"' in line, line
    assert mi.load_dict({"type": kind}).footprint is True
    assert mi.load_dict({"type": kind, "footprint": False}).footprint is False


# -- 4. mfnormal_prb: the same footprint in the primal and the differential phase, detached ----------

def probe_mesh_scene():
    """The ground of :func:`ground_scene` as a mesh (its vertices can carry gradients), the probe
    on it, under ``mfnormal_prb``; 32², 1 spp."""
    plane = mesh("ground", [[-20, 0, 20], [20, 0, 20], [20, 0, -20], [-20, 0, -20]], [[0, 1, 0]] * 4,
                 [[0, 0], [1, 0], [1, 1], [0, 1]], [[0, 1, 2], [0, 2, 3]], {"type": "footprint_probe"})
    return mi.load_dict({
        "type": "scene", "integrator": integrator("mfnormal_prb"),
        "sensor": camera([0, 1, 0], [0, 1 - math.tan(math.radians(20)), -1], 40, 32),
        "sky": {"type": "constant"}, "ground": plane})


def test_prb_replays_the_primal_footprint_detached():
    """The probe's weight e^(θ·|duv_dx|)·|duv_dx| (θ = 0): its relative derivative is the
    footprint the differential phase sees, so the forward derivative in θ is |duv_dx|primal ·
    |duv_dx|replay = primal² (rtol 1e-5). Where the geometry carries gradients (the mesh's
    vertices), the footprint and the cone carry none."""
    scene = probe_mesh_scene()
    primal = render(scene)
    seen = primal[..., 2] == MARK
    assert seen.sum() > 300
    params = mi.traverse(scene)
    dr.enable_grad(params["ground.vertex_positions"])
    dr.enable_grad(params["ground.bsdf.theta"])
    params.update()
    img = mi.render(scene, params, spp=1, seed=0)
    dr.set_grad(params["ground.bsdf.theta"], 1.0)
    dr.forward_to(img)
    grad = np.array(dr.grad(img), dtype=np.float64)
    np.testing.assert_allclose(grad[seen][:, 0], primal[seen][:, 0] ** 2, rtol=1e-5)
    ray = pixel_rays(scene)
    with dr.resume_grad():
        si = scene.ray_intersect(mi.Ray3f(ray), cone.RAY_FLAGS, True)
        w, beta = cone.camera_cone(ray)
        si, w = cone.at_hit(si, ray, w, beta)
        bs = dr.zeros(mi.BSDFSample3f)
        bs.wo, bs.pdf, bs.sampled_type = si.wi, mi.Float(1.0), mi.UInt32(int(mi.BSDFFlags.GlossyReflection))
        assert dr.grad_enabled(si.p)
        assert not dr.grad_enabled(si.duv_dx, si.duv_dy, w, cone.bounce(beta, si, bs))


# -- 5. Degenerate uv: no NaN ---------------------------------------------------------------------------

def test_a_degenerate_uv_map_gives_no_footprint_never_nan():
    """dp_du and dp_dv zero, parallel, within 0.06° of parallel, or not finite: the uv step is 0."""
    a = mi.Vector3f(0.1, 0.2, 0.0)
    for dp_du, dp_dv in [((0, 0, 0), (0, 1, 0)), ((0, 0, 0), (0, 0, 0)), ((1, 0, 0), (2, 0, 0)),
                         ((1, 0, 0), (1, 5e-4, 0)),
                         ((math.inf, 0, 0), (0, 1, 0)), ((math.nan, 0, 0), (0, 1, 0))]:
        duv = np.array(cone.to_uv(mi.Vector3f(*dp_du), mi.Vector3f(*dp_dv), a))
        assert np.all(duv == 0), (dp_du, dp_dv, duv)
    np.testing.assert_allclose(np.array(cone.to_uv(mi.Vector3f(2, 0, 0), mi.Vector3f(1, 1, 0), a)).ravel(),
                               [-0.05, 0.2], rtol=1e-6)


def flat_mesh(name, uvs=None):
    """A 2 × 2 square facing +z made of two triangles, the probe on it; without uvs if None."""
    props = mi.Properties()
    props["bsdf"] = mi.load_dict({"type": "footprint_probe"})
    square = mi.Mesh(name, 4, 2, props, has_vertex_normals=False, has_vertex_texcoords=uvs is not None)
    params = mi.traverse(square)
    params["vertex_positions"] = floats([[-1, -1, 0], [1, -1, 0], [1, 1, 0], [-1, 1, 0]])
    params["faces"] = uints([[0, 1, 2], [0, 2, 3]])
    if uvs is not None:
        params["vertex_texcoords"] = floats(uvs)
    params.update()
    return square


@pytest.mark.parametrize("shape", ["sphere's pole", "mesh without uvs", "uvs all one point"])
def test_degenerate_uv_surfaces_render_finite_footprints(shape):
    """Seen head-on from z = 4: a unit sphere at its pole (the centre pixel: dp_du = 0), a
    square without uvs (Mitsuba's uv: the barycentrics), a square whose uvs are all one point.
    Every footprint the probe sees is finite; at the pole it is 0, on the square without uvs
    it is not."""
    surface = {"sphere's pole": lambda: {"type": "sphere", "bsdf": {"type": "footprint_probe"}},
               "mesh without uvs": lambda: flat_mesh("bare"),
               "uvs all one point": lambda: flat_mesh("one_point", [[0.5, 0.5]] * 4)}[shape]()
    scene = mi.load_dict({"type": "scene", "integrator": integrator("mfnormal_path"),
                          "sensor": camera([0, 0, CAMERA_Z], [0, 0, 0], 30, RES),
                          "sky": {"type": "constant"}, "surface": surface})
    img = render(scene)
    assert np.all(np.isfinite(img)) and np.all(img >= 0)
    seen = img[..., 2] > 0.0
    centre = img[RES // 2, RES // 2]
    assert seen[RES // 2, RES // 2] and seen.sum() > 20
    if shape == "sphere's pole":
        assert np.all(centre[:2] == 0), centre
    if shape == "mesh without uvs":
        assert np.all(img[seen][:, :2] > 0)
