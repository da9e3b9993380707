"""The normal-map baker (``mfnormal.io.bake``, ``mfnormal bake``).

The references are independent of the baker's own frame code: a map baked from Mitsuba's
analytic sphere onto a low-poly UV sphere is read back the way renderers read it — Mitsuba
intersects the low-poly, its ``bitmap`` texture looks the map up (bilinear) at ``si.uv``,
and the texel is decoded in Mitsuba's ``si.sh_frame`` (``tangents="mitsuba"``) or in the
vertex tangent frame by the plugin's own :func:`~mfnormal.surface.shading.from_tangent_frame`
(``tangents="vertex_tangent"``) — and compared with the sphere's normal found in closed form
along the low-poly's normal. A surface baked onto itself gives the flat map.
"""

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from cli_checks import assert_error_line
from helpers import uv_sphere
from mfnormal.io import bake as B
from mfnormal.io.meshes import mitsuba_mesh
from mfnormal.surface.shading import from_tangent_frame

SIZE = 128


def low_mesh(arrays, tangents: bool):
    """The low-poly as a Mitsuba mesh: with MikkTSpace vertex tangents (``tangent_mesh``) or without."""
    if tangents:
        return B.tangent_mesh("low", *arrays)
    return mitsuba_mesh("low", mi.load_dict({"type": "diffuse"}), *arrays[:3], None, arrays[3])


def bumpy_sphere():
    """The high-poly: a 40 × 80 UV sphere whose radius varies by ±5 % (slopes up to about 20°)."""
    pos, _, uv, faces = uv_sphere(40, 80)
    bumpy = pos * (1.0 + 0.05 * np.sin(8 * np.pi * uv[:, :1]) * np.sin(4 * np.pi * uv[:, 1:]))
    high = mitsuba_mesh("high", mi.load_dict({"type": "diffuse"}), bumpy, pos, uv, None, faces)
    high.recompute_vertex_normals()
    return high


def as_np(v):
    return np.array(v, np.float64).reshape(3, -1).T


def hits_on(mesh, n: int = 4000, seed: int = 1):
    """The interactions of ``n`` rays towards the origin from random directions with ``mesh``."""
    rng = np.random.default_rng(seed)
    d = rng.normal(size=(n, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    scene = mi.load_dict({"type": "scene", "low": mesh})
    return scene.ray_intersect(mi.Ray3f(mi.Point3f(*(mi.Float(3.0 * c) for c in d.T)),
                                        mi.Vector3f(*(mi.Float(-c) for c in d.T))))


def read_back(map_path, mesh, frame: str, n: int = 4000, seed: int = 1):
    """(decoded world normal, low-poly point, low-poly shading normal) at ``n`` points of ``mesh``
    hit by rays towards the origin from random directions, the map read as renderers read it."""
    si = hits_on(mesh, n, seed)
    texture = mi.load_dict({"type": "bitmap", "filename": str(map_path), "raw": True})
    rgb = texture.eval(si)
    wp = dr.normalize(mi.Vector3f(2 * rgb[0] - 1, 2 * rgb[1] - 1, 2 * rgb[2] - 1))
    if frame == "mikktspace":
        wp = from_tangent_frame(wp, si.sh_frame, mi.Vector3f(mesh.eval_attribute_3("vertex_tangent", si)),
                                mesh.eval_attribute_1("vertex_tangent_sign", si))
    world = si.sh_frame.to_world(wp)
    valid = np.array(si.is_valid())
    assert valid.all()
    return as_np(world), as_np(si.p), as_np(si.sh_frame.n)


def sphere_distance_along(p, n):
    """The signed t at which the line p + t·n meets the unit sphere nearest to p (closed form)."""
    pn = np.sum(p * n, axis=1)
    disc = pn ** 2 - np.sum(p * p, axis=1) + 1.0
    t = -pn + np.sqrt(disc)
    return np.where(np.abs(t) <= np.abs(-pn - np.sqrt(disc)), t, -pn - np.sqrt(disc))


def sphere_normal_along(p, n):
    """The unit sphere's normal where the line p + t·n meets it nearest to p (closed form)."""
    q = p + sphere_distance_along(p, n)[:, None] * n
    return q / np.linalg.norm(q, axis=1, keepdims=True)


def angles_deg(a, b):
    return np.degrees(np.arccos(np.clip(np.sum(a * b, axis=1), -1.0, 1.0)))


@pytest.mark.parametrize("frame, p99_deg", [("mikktspace", 1.5), ("mitsuba", 3.0)])
def test_bake_of_the_analytic_sphere_decodes_to_its_normals(frame, p99_deg, tmp_path):
    """Rays from the low-poly's surface find Mitsuba's analytic sphere; the map, read back through
    Mitsuba's bitmap (bilinear) and the frame a renderer decodes in, gives the sphere's normal
    there: median below 0.3° (8-bit quantisation alone is up to 0.23° per channel), 99th
    percentile below 1.5° in the smooth MikkTSpace frame (measured 0.13° / 0.27°) and below 3°
    in Mitsuba's frame (0.14° / 1.9°), whose tangent turns from one triangle to the next, so
    that a bilinear lookup across a triangle edge mixes texels baked in different frames. The
    low poly's normals lean by up to 14° (median 10°), so a frame or sign error cannot pass."""
    arrays = uv_sphere(lean=0.25)
    mesh = low_mesh(arrays, frame == "mikktspace")
    baked = B.bake(mi.load_dict({"type": "sphere"}), mesh, SIZE, frame=frame)
    assert baked.missed == 0
    path = B.write_map(tmp_path / "map.png", baked.normals)
    world, p, n = read_back(path, mesh, frame)
    err = angles_deg(world, sphere_normal_along(p, n))
    assert np.median(err) < 0.3 and np.percentile(err, 99) < p99_deg, (np.median(err), np.percentile(err, 99))
    assert np.median(angles_deg(n, sphere_normal_along(p, n))) > 5.0


@pytest.mark.parametrize("frame", B.TANGENT_FRAMES)
def test_a_surface_baked_onto_itself_gives_the_flat_map(frame):
    """High-poly = low-poly: every covered texel is (0.5, 0.5, 1) within one 8-bit step, at
    height 0 (within float32 ray tracing's round-off, 1e-5 of the unit sphere's radius)."""
    arrays = uv_sphere(6, 12, lean=0.25)
    mesh = low_mesh(arrays, frame == "mikktspace")
    baked = B.bake(mesh, mesh, 64, frame=frame)
    rgb = B.encode_map(baked.normals).astype(float)[baked.covered]
    assert baked.covered.sum() > 0.8 * 64 * 64
    assert np.abs(rgb[:, :2] - 127.5).max() <= 1.0 and rgb[:, 2].min() >= 254
    assert np.abs(baked.heights).max() < 1e-5


def test_the_heights_are_the_high_polys_distance_along_the_low_polys_normal(tmp_path):
    """The heights baked from Mitsuba's analytic sphere onto the low-poly UV sphere (its normals
    leant by up to 14°), written as EXR and read back as renderers read them (Mitsuba's bitmap,
    bilinear, at the low-poly's ``si.uv``), are the signed distance from the low-poly's surface
    along its interpolated normal to the sphere, in closed form, at 512² texels: median within
    0.2 % of the heights' range, 99th percentile within 3 % (measured 0.05 % and 1.3 %: bilinear
    interpolation of heights that kink at the triangles' edges; both fall with the map's size,
    0.8 % and 9 % at 128²), positive where the sphere is outside. Fails if the sign or the texel
    layout were wrong (off by up to the heights' whole range) or the rays' start offset were
    left in (1.7e-4, 0.7 % of the range, everywhere)."""
    arrays = uv_sphere(lean=0.25)
    mesh = low_mesh(arrays, False)
    baked = B.bake(mi.load_dict({"type": "sphere"}), mesh, 512, frame="mitsuba")
    path = str(B.write_heights(tmp_path / "heights.exr", baked.heights))
    si = hits_on(mesh, seed=2)
    got = np.array(mi.load_dict({"type": "bitmap", "filename": str(path), "raw": True}).eval_1(si))
    want = sphere_distance_along(as_np(si.p), as_np(si.sh_frame.n))
    span = want.max() - want.min()
    assert want.max() > 0.01 and span > 0.01
    err = np.abs(got - want)
    assert np.median(err) < 0.002 * span and np.percentile(err, 99) < 0.03 * span, \
        (np.median(err), np.percentile(err, 99), span)


def test_the_heights_as_a_height_map_give_the_baked_normals_on_a_fine_low_poly():
    """The bumpy sphere (radius ±5 %: tilts to about 20°) baked onto a 20 × 40 UV sphere: its
    heights, given to ``normalmap_microfacet`` as ``heightmap`` (height_scale 1, Mitsuba
    ``bumpmap``'s convention), give the normals its normal map gives (Mitsuba's frame), median
    within 3.5° (measured 2.8°), closer than at half or twice the scale (4.3°, 9.6°) or with
    the sign flipped (17°): the heights' sign and world scale are the ones a renderer applies. (On
    coarse low-polys the two part more, median 10° on a 6 × 12 sphere: the bump convention tilts
    the normal in the interpolated shading frame and leaves out the flat triangles' own tilt
    against it; docs/cli.md.)"""
    low = low_mesh(uv_sphere(20, 40), False)
    baked = B.bake(bumpy_sphere(), low, 256, frame="mitsuba")
    normalmap = {"type": "bitmap", "raw": True, "bitmap": mi.Bitmap(
        np.ascontiguousarray(B.encode_map(baked.normals, 16) / 65535.0, np.float32))}
    heightmap = {"type": "bitmap", "raw": True, "bitmap": mi.Bitmap(
        np.ascontiguousarray(baked.heights, np.float32)[..., None])}
    si = hits_on(low, seed=2)

    def wp(**params):
        bsdf = mi.load_dict({"type": "normalmap_microfacet", "bsdf": {"type": "diffuse"}, **params})
        return as_np(bsdf.shading_point(mi.BSDFContext(), si).wp)
    want = wp(normalmap=normalmap)
    median = {scale: np.median(angles_deg(wp(heightmap=heightmap, height_scale=scale), want))
              for scale in (1.0, 0.5, 2.0, -1.0)}
    assert median[1.0] < 3.5 and median[1.0] < min(median[0.5], median[2.0], median[-1.0]), median


def test_padding_averages_the_heights_without_normalising():
    heights = np.zeros((7, 7, 1))
    known = np.zeros((7, 7), bool)
    known[3, 2], known[3, 4] = True, True
    heights[3, 2], heights[3, 4] = 0.2, 0.6
    out = B.dilate(heights, known, 1, unit=False)
    assert out[3, 3, 0] == pytest.approx(0.4) and out[2, 1, 0] == pytest.approx(0.2)
    assert out[3, 0, 0] == 0.0


def test_rasteriser_covers_each_texel_centre_once():
    """Two triangles splitting the unit square cover every texel centre exactly once, with
    barycentrics that reproduce the centre's uv; a triangle over half the square covers half."""
    uv = np.array([[0, 0], [1, 0], [1, 1], [0, 1]], float)
    texel, tri, bary = B.rasterise(uv, np.array([[0, 1, 2], [0, 2, 3]]), 16)
    assert np.array_equal(texel, np.arange(256))
    faces = np.array([[0, 1, 2], [0, 2, 3]])
    centre = np.einsum("kc,kcd->kd", bary, uv[faces[tri]])
    rows, cols = np.divmod(texel, 16)
    assert np.allclose(centre, np.stack([(cols + 0.5) / 16, (rows + 0.5) / 16], 1))
    half, _, _ = B.rasterise(uv, np.array([[0, 1, 2]]), 16)
    assert len(half) == 16 * 17 // 2          # centres on the diagonal count as inside


def test_padding_fills_a_ring_around_islands():
    normals = np.zeros((9, 9, 3))
    normals[..., 2] = 1.0
    known = np.zeros((9, 9), bool)
    known[4, 4] = True
    normals[4, 4] = [0.6, 0.0, 0.8]
    out = B.dilate(normals, known, 2)
    assert np.allclose(out[2:7, 2:7], [0.6, 0.0, 0.8])
    assert np.allclose(out[1, 1], [0, 0, 1]) and np.allclose(out[0, :], [0, 0, 1])


def test_sixteen_bit_maps_round_trip(tmp_path):
    normals = np.zeros((8, 8, 3))
    normals[...] = [0.28, -0.48, 0.83]
    path = B.write_map(tmp_path / "m16.png", normals / np.linalg.norm(normals[0, 0]), bits=16)
    data = np.array(mi.Bitmap(str(path)))
    assert data.dtype == np.uint16
    assert np.allclose(data / 65535.0 * 2 - 1, normals / np.linalg.norm(normals[0, 0]), atol=2e-5)


# -- The command line -------------------------------------------------------------------------------

@pytest.fixture(scope="module")
def meshes(tmp_path_factory):
    d = tmp_path_factory.mktemp("bake")
    arrays = uv_sphere(6, 12)
    low_mesh(arrays, False).write_ply(str(d / "low.ply"))
    mitsuba_mesh("nouv", mi.load_dict({"type": "diffuse"}), arrays[0], arrays[1], None, None,
                 arrays[3]).write_ply(str(d / "nouv.ply"))
    bumpy_sphere().write_ply(str(d / "high.ply"))
    (d / "file.txt").write_text("not a folder")
    return d


@pytest.mark.parametrize("args, needles", [
    (["missing.ply", "low.ply", "-o", "m.png"], ("high-poly mesh file not found",)),
    (["high.ply", "low.stl", "-o", "m.png"], ("low-poly mesh file not found",)),
    (["high.ply", "file.txt", "-o", "m.png"], ("expected a .ply or .obj mesh",)),
    (["high.ply", "nouv.ply", "-o", "m.png"], ("no UVs", "--unwrap")),
    (["high.ply", "low.ply", "-o", "m.png", "--size", "4"], ("--size 4", "8 to 8192")),
    (["high.ply", "low.ply", "-o", "m.png", "--size", "100000"], ("--size 100000",)),
    (["high.ply", "low.ply", "-o", "m.png", "--cage", "-1"], ("--cage -1.0",)),
    (["high.ply", "low.ply", "-o", "m.png", "--cage", "nan"], ("--cage nan",)),
    (["high.ply", "low.ply", "-o", "m.png", "--cage", "inf"], ("--cage inf", "finite distance")),
    (["high.ply", "low.ply", "-o", "m.png", "--padding", "-2"], ("--padding -2",)),
    (["high.ply", "low.ply", "-o", "m.exr"], ("ending in .png",)),
    (["high.ply", "low.ply", "-o", "file.txt/m.png"], ("is a file, not a folder",)),
    (["high.ply", "low.ply", "-o", "m.png", "--tangents", "world"], ("invalid choice",)),
    (["high.ply", "low.ply", "-o", "m.png", "--unwrap", "u.obj"], ("ending in .ply",)),
    (["high.ply", "low.ply", "-o", "m.png", "--heights", "m.png"], ("--heights", "ending in .exr")),
    (["high.ply", "low.ply", "-o", "m.png", "--heights", "file.txt/m.exr"], ("--heights", "is a file, not a folder")),
    (["high.ply", "low.ply"], ("-o/--output",)),
    (["high.ply", "low.ply", "-o", "m.png", "--tangent-mesh", "t.obj"], ("--tangent-mesh", "ending in .ply")),
    (["high.ply", "low.ply", "-o", "m.png", "--tangents", "mitsuba", "--tangent-mesh", "t.ply"],
     ("--tangent-mesh t.ply", "--tangents mikktspace")),
    (["high.ply", "low.ply", "-o", "m.png", "--tangent-mesh", "low.ply"], ("--tangent-mesh", "overwrite its input")),
])
def test_bake_command_rejects_bad_input_in_one_line(worker, meshes, args, needles):
    result = worker.run(["bake", *args], cwd=meshes)
    assert_error_line(result, *needles)
    assert not list(meshes.glob("m.*")) and not list(meshes.glob(".m.*"))


def test_bake_command_writes_the_map(worker, meshes):
    """``mfnormal bake`` writes an RGB PNG of the size asked for, with the bumps of the high-poly
    (a sphere whose radius varies by ±5 %: slopes up to about 20°) on the 12 × 6 sphere, and
    nothing else in the folder."""
    before = set(meshes.iterdir())
    result = worker.run(["bake", "high.ply", "low.ply", "-o", "map.png", "--size", "32"], cwd=meshes)
    assert result.rc == 0 and result.exception is None, result.describe()
    assert set(meshes.iterdir()) - before == {meshes / "map.png"}
    data = np.array(mi.Bitmap(str(meshes / "map.png")))
    assert data.shape == (32, 32, 3) and data.dtype == np.uint8
    tilt = np.degrees(np.arccos(np.clip((data[..., 2] / 255.0) * 2 - 1, -1, 1)))
    assert 10.0 < np.percentile(tilt, 90) < 30.0


def test_bake_command_writes_the_heights(worker, meshes):
    """``--heights`` writes a one-channel float EXR of the map's size beside the map: the bumpy
    sphere's radius varies by ±5 % around the 12 × 6 sphere, whose flat faces lie inside the unit
    sphere, so its heights span about −0.05 to +0.09 (measured), the map the same as without."""
    before = set(meshes.iterdir())
    result = worker.run(["bake", "high.ply", "low.ply", "-o", "hmap.png", "--size", "32",
                         "--heights", "heights.exr"], cwd=meshes)
    assert result.rc == 0 and result.exception is None, result.describe()
    assert set(meshes.iterdir()) - before == {meshes / "hmap.png", meshes / "heights.exr"}
    bitmap = mi.Bitmap(str(meshes / "heights.exr"))
    heights = np.array(bitmap)
    assert heights.shape in ((32, 32), (32, 32, 1)) and heights.dtype == np.float32
    assert -0.08 < heights.min() < -0.02 and 0.05 < heights.max() < 0.12
    plain = worker.run(["bake", "high.ply", "low.ply", "-o", "plain.png", "--size", "32"], cwd=meshes)
    assert plain.rc == 0
    assert np.array_equal(np.array(mi.Bitmap(str(meshes / "plain.png"))), np.array(mi.Bitmap(str(meshes / "hmap.png"))))


def test_bake_command_unwraps_a_mesh_without_uvs(worker, meshes):
    """``--unwrap`` gives the UV-less low-poly xatlas UVs, writes it as PLY (with UVs, the same
    triangles) and bakes onto it."""
    pytest.importorskip("xatlas")
    result = worker.run(["bake", "high.ply", "nouv.ply", "-o", "unwrapped.png", "--size", "32",
                         "--unwrap", "unwrapped.ply"], cwd=meshes)
    assert result.rc == 0 and result.exception is None, result.describe()
    mesh = mi.load_dict({"type": "ply", "filename": str(meshes / "unwrapped.ply")})
    assert mesh.has_vertex_texcoords() and mesh.face_count() == len(uv_sphere(6, 12)[3])
    uvs = B.mesh_arrays(mesh)[2]
    assert uvs.min() >= 0.0 and uvs.max() <= 1.0
    assert np.array(mi.Bitmap(str(meshes / "unwrapped.png"))).shape == (32, 32, 3)


def test_a_long_bake_reports_its_progress_in_at_most_three_lines():
    """``bake(progress=...)`` is called after every pass with the texels traced so far; the
    command's callback prints a line at each quarter, on stderr, for bakes of
    PROGRESS_PASSES passes or more (passes made small here), and nothing for shorter ones."""
    import io
    from mfnormal.cli import bake as cli_bake
    calls = []
    B.bake(bumpy_sphere(), low_mesh(uv_sphere(6, 12), False), 64, progress=lambda *a: calls.append(a),
           batches=B.Batches(trace=512))
    assert calls == [(min(k * 512, 64 * 64), 64 * 64) for k in range(1, 9)]
    stream = io.StringIO()
    report = cli_bake.progress_lines(64, 0.0, stream, per_pass=512)
    for done, total in calls:
        report(done, total)
    lines = stream.getvalue().splitlines()
    assert [ln.split(" texels")[0] for ln in lines] == [
        f"mfnormal: bake: {q} % of 4096" for q in (25, 50, 75)], lines
    assert cli_bake.progress_lines(32, 0.0, stream, per_pass=512) is None     # 2 passes: no report


TANGENT_SCENE = """<scene version="3.0.0">
    <integrator type="path"><integer name="max_depth" value="2"/></integrator>
    <sensor type="orthographic">
        <transform name="to_world"><scale x="1.1" y="1.1"/><lookat origin="0,-5,0" target="0,0,0" up="0,0,1"/></transform>
        <film type="hdrfilm"><integer name="width" value="16"/><integer name="height" value="16"/></film>
        <sampler type="independent"><integer name="sample_count" value="4"/></sampler>
    </sensor>
    <emitter type="directional"><vector name="direction" x="-1" y="0.5" z="-1"/></emitter>
    <shape type="ply">
        <string name="filename" value="$mesh"/>
        <bsdf type="normalmap_microfacet">
            <string name="tangents" value="vertex_tangent"/>
            <texture name="normalmap" type="bitmap">
                <string name="filename" value="tmap.png"/>
                <boolean name="raw" value="true"/>
            </texture>
            <bsdf type="diffuse"/>
        </bsdf>
    </shape>
</scene>
"""


def test_bake_command_writes_the_mesh_with_its_mikktspace_tangents_for_xml(worker, meshes):
    """``--tangent-mesh`` writes the low-poly with the MikkTSpace tangents the map was baked in
    (Mitsuba's ``write_ply`` keeps the attributes ``vertex_tangent``, ``vertex_tangent_sign``):
    read back, they are :func:`tangent_mesh`'s, and an XML scene renders the map on it as the
    Python route (``tangent_mesh``) does. On the low-poly without them the command warns, in one
    line, that the map falls back to Mitsuba's frame; on the tangent mesh it does not."""
    result = worker.run(["bake", "high.ply", "low.ply", "-o", "tmap.png", "--size", "32",
                         "--tangent-mesh", "tlow.ply"], cwd=meshes)
    assert result.rc == 0 and result.exception is None, result.describe()
    written = mi.load_dict({"type": "ply", "filename": str(meshes / "tlow.ply")})
    python_route = low_mesh(uv_sphere(6, 12), True)
    for key in ("vertex_positions", "vertex_texcoords", "vertex_tangent", "vertex_tangent_sign"):
        np.testing.assert_allclose(np.array(mi.traverse(written)[key]),
                                   np.array(mi.traverse(python_route)[key]), atol=1e-6, err_msg=key)
    (meshes / "tangents.xml").write_text(TANGENT_SCENE)
    for mesh in ("tlow.ply", "low.ply"):
        run = worker.run(["render", "tangents.xml", "-D", f"mesh={mesh}", "-o", meshes / f"render_{mesh[:-4]}"],
                         cwd=meshes)
        assert run.rc == 0, run.describe()
        warned = [ln for ln in run.stderr.splitlines() if "vertex attribute 'vertex_tangent'" in ln]
        assert len(warned) == (mesh == "low.ply"), run.stderr
        assert not warned or warned[0].startswith("mfnormal: warning: ") and "--tangent-mesh" in warned[0]
    scenes = {mesh: mi.load_file(str(meshes / "tangents.xml"), mesh=mesh) for mesh in ("tlow.ply", "low.ply")}
    images = {mesh: np.array(mi.render(scene, seed=0)) for mesh, scene in scenes.items()}
    scene = scenes["tlow.ply"]
    python_route.set_bsdf(scene.shapes()[0].bsdf())
    scene_python = mi.load_dict({"type": "scene", "integrator": scene.integrator(), "sensor": scene.sensors()[0],
                                 "sun": scene.emitters()[0], "shape": python_route})
    np.testing.assert_allclose(images["tlow.ply"], np.array(mi.render(scene_python, seed=0)), atol=1e-5)
    assert not np.allclose(images["tlow.ply"], images["low.ply"], atol=1e-3)   # the frames differ


def test_a_baked_map_renders_the_high_poly_shading_on_the_low_poly(tmp_path):
    """The bumpy sphere's MikkTSpace map on the 20 × 10 sphere, rendered by ``normalmap_microfacet``
    (default model, ``tangents="vertex_tangent"``) and by Mitsuba's ``normalmap`` on a map baked in
    Mitsuba's frame, under a sun 45° up from the side: relMSE against the bumpy sphere's own
    render (64 spp; over the pixels both spheres cover, less a pixel at the silhouettes) below
    half the bare low-poly's and half that of the same map with its green channel flipped
    (measured 0.025 and 0.026 against 0.065 bare and 0.080 flipped; the rest is what a map
    cannot change: the bumps' parallax and shadows, the low-poly's faceted shadow terminator)."""
    pos, _, uv, faces = uv_sphere(40, 80)
    bumpy = pos * (1.0 + 0.05 * np.sin(8 * np.pi * uv[:, :1]) * np.sin(4 * np.pi * uv[:, 1:]))
    high = mitsuba_mesh("high", mi.load_dict({"type": "diffuse"}), bumpy, pos, uv, None, faces)
    high.recompute_vertex_normals()
    arrays = uv_sphere()
    maps = {}
    for frame in B.TANGENT_FRAMES:
        maps[frame] = B.write_map(tmp_path / f"{frame}.png",
                                  B.bake(high, low_mesh(arrays, frame == "mikktspace"), 256, frame=frame).normals)
    nested = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.7}}

    def render(shape):
        scene = mi.load_dict({
            "type": "scene", "integrator": {"type": "path", "max_depth": 2},
            "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 32, "height": 32},
                       "to_world": mi.ScalarTransform4f().look_at([0, -5, 0], [0, 0, 0], [0, 0, 1])
                       @ mi.ScalarTransform4f().scale([1.1, 1.1, 1]),
                       "sampler": {"type": "independent", "sample_count": 64}},
            "sun": {"type": "directional", "direction": [-1.0, 0.5, -1.0], "irradiance": 3.0},
            "shape": shape})
        return np.array(mi.render(scene, seed=3), np.float64)

    def with_bsdf(mesh_fn, bsdf):
        mesh = mesh_fn()
        mesh.set_bsdf(mi.load_dict(bsdf))
        return mesh

    texture = {"type": "bitmap", "raw": True}
    truth = render(with_bsdf(lambda: high, nested))
    bare = render(with_bsdf(lambda: low_mesh(arrays, False), nested))
    plugin = render(with_bsdf(lambda: low_mesh(arrays, True), {
        "type": "normalmap_microfacet", "tangents": "vertex_tangent", "bsdf": nested,
        "normalmap": {**texture, "filename": str(maps["mikktspace"])}}))
    classic = render(with_bsdf(lambda: low_mesh(arrays, False), {
        "type": "normalmap", "bsdf": nested, "normalmap": {**texture, "filename": str(maps["mitsuba"])}}))
    flipped = render(with_bsdf(lambda: low_mesh(arrays, True), {
        "type": "normalmap_microfacet", "tangents": "vertex_tangent", "bsdf": nested,
        "normalmap_convention": "directx", "normalmap": {**texture, "filename": str(maps["mikktspace"])}}))
    covered = (truth.sum(-1) > 0) & (bare.sum(-1) > 0)
    mask = covered.copy()                  # less a pixel at the silhouettes, which the spheres differ in
    mask[1:-1, 1:-1] &= covered[:-2, 1:-1] & covered[2:, 1:-1] & covered[1:-1, :-2] & covered[1:-1, 2:]

    def err(img):
        return float(np.mean(((img - truth) ** 2 / (truth ** 2 + 1e-2))[mask]))

    assert err(plugin) < 0.5 * err(bare) and err(classic) < 0.5 * err(bare)
    assert err(plugin) < 0.5 * err(flipped)
