"""``mfnormal compare`` and its HTML report; the bundled model scene (b).

One ``mfnormal compare model --quick`` run (a subprocess, tiny images) feeds the
report tests: the file is self-contained (every image an embedded PNG, nothing
fetched), and in headless Chromium every image loads, the comparison slider,
the flip mode and the method menus change what is shown, and the console stays
free of errors. The browser test is skipped, with the reason, when Chromium,
chromedriver or selenium is missing (``scripts/setup.sh`` installs them as root).

The other tests need no renders: the XML rewriting per method, the crop choice,
and the generated torus knot (seamless UVs, outward normals, and a tangent
frame whose t axis is the normal map's +y in Mitsuba).
"""

import html
import os
import re
import subprocess
import sys
import xml.etree.ElementTree as ET
from pathlib import Path

import numpy as np
import pytest

import mfnormal  # noqa: F401  (picks a working libLLVM before mitsuba loads)
import drjit as dr
import mitsuba as mi
from variant import VARIANT  # noqa: E402  (MFNORMAL_VARIANT, tests/variant.py)

mi.set_variant(VARIANT)
mfnormal.register()

from mfnormal.scenes import assets  # noqa: E402
from mfnormal.report import compare, coverage, metrics
from mfnormal.io import scene_xml
from mfnormal.methods import METHODS, PLUGIN  # noqa: E402
from mfnormal.io.images import png_bytes  # noqa: E402
from cli_checks import assert_one_line_error  # noqa: E402

ROOT = Path(__file__).resolve().parents[1]


@pytest.fixture(scope="module")
def report(tmp_path_factory):
    """``mfnormal compare model --quick`` with one validation figure: the report's path."""
    d = tmp_path_factory.mktemp("report")
    figures = d / "figures"
    figures.mkdir()
    (figures / "albedo.png").write_bytes(png_bytes(np.tile(np.arange(0, 256, 4, dtype=np.uint8), (32, 1))))
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    proc = subprocess.run([sys.executable, "-m", "mfnormal", "compare", "model", "--quick",
                           "-o", str(d / "out"), "--validation", str(figures)],
                          env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return d / "out" / "report.html"


# ---------------------------------------------------------------------------
# The report file
# ---------------------------------------------------------------------------

def test_report_embeds_every_image_and_fetches_nothing(report):
    text = report.read_text(encoding="utf-8")
    srcs = re.findall(r"""\bsrc=['"]([^'"]*)['"]""", text)
    assert len(srcs) > 8 * 3
    assert all(s.startswith("data:image/png;base64,") for s in srcs)
    # No URL the browser would fetch: no external scripts, styles, images or fonts.
    assert not re.search(r"""(src|href)=['"]?(https?:)?//""", text)
    assert "@import" not in text and "url(" not in text
    for method in METHODS:
        assert f"img-model-{method.key}" in text
    assert "white furnace" in text.lower() and "albedo.png" in text


def test_the_measurements_say_what_their_relmse_is_measured_against(report):
    """The table's relMSE is each method's noise against its own reference, not a distance to
    the truth: its header and caption say so where it is read."""
    text = report.read_text(encoding="utf-8")
    table = text[text.index("<table class=metrics>"):]
    table = table[:table.index("</table>")]
    assert "relMSE to its own reference" in table
    assert "<caption>" in table and "not its distance to the true geometry" in table


def test_compare_writes_a_render_and_a_reference_per_method(report):
    out = report.parent / "model"
    for method in METHODS:
        for name in (method.key, f"{method.key}_ref"):
            assert (out / f"{name}.exr").is_file() and (out / f"{name}.png").is_file()
    img = np.array(mi.Bitmap(str(out / "nonseparable_same.exr")))
    assert img.shape[1] == compare.QUICK.width and np.isfinite(img).all() and img.mean() > 0


def _wait(browser, script, timeout=20.0):
    from selenium.webdriver.support.ui import WebDriverWait
    WebDriverWait(browser, timeout).until(lambda d: d.execute_script(script))


def test_report_works_in_headless_chromium(report, browser):
    from selenium.webdriver.common.by import By
    from selenium.webdriver.common.keys import Keys
    from selenium.webdriver.support.ui import Select

    browser.get(report.as_uri())
    _wait(browser, "return document.readyState === 'complete' && "
                   "Array.from(document.images).every(i => i.complete)")

    # Every image decoded.
    broken = browser.execute_script(
        "return Array.from(document.images).filter(i => !(i.naturalWidth > 0)).map(i => i.alt)")
    assert broken == []
    assert browser.execute_script("return document.images.length") > 8 * 3

    sec = browser.find_element(By.ID, "scene-model")
    img_a = sec.find_element(By.CSS_SELECTOR, ".img-a")
    img_b = sec.find_element(By.CSS_SELECTOR, ".img-b")
    slider = sec.find_element(By.CSS_SELECTOR, ".slider")
    clip = lambda: browser.execute_script("return getComputedStyle(arguments[0]).clipPath", img_a)  # noqa: E731

    # The slider moves the split between the left and the right image.
    before = clip()
    assert "inset" in before
    slider.send_keys(Keys.HOME)
    at_left = clip()
    assert at_left != before and "100%" in at_left        # all of the right image
    slider.send_keys(Keys.END)
    assert clip() not in (before, at_left)                 # all of the left image

    # The menus choose which renders are compared.
    src_b = img_b.get_attribute("src")
    Select(sec.find_element(By.CSS_SELECTOR, ".sel-b")).select_by_value("flat")
    assert img_b.get_attribute("src") != src_b
    assert img_b.get_attribute("src") == sec.find_element(By.ID, "img-model-flat").get_attribute("src")

    # Flip mode shows one whole image at a time, and the button swaps it.
    sec.find_element(By.CSS_SELECTOR, "input.mode[value=flip]").click()
    assert clip() == "none"
    shown = img_a.value_of_css_property("visibility")
    sec.find_element(By.CSS_SELECTOR, "button.flip").click()
    assert img_a.value_of_css_property("visibility") != shown
    browser.find_element(By.TAG_NAME, "body").send_keys("f")
    assert img_a.value_of_css_property("visibility") == shown

    # No errors in the console (script errors, failed loads).
    errors = [e for e in browser.get_log("browser") if e["level"] in ("SEVERE", "ERROR")]
    assert errors == []

    # The measurements fit a 1280-px window: no table wider than the page, no sideways scroll.
    browser.set_window_size(1280, 900)
    width = browser.execute_script("return document.documentElement.clientWidth")
    rights = browser.execute_script("return Array.from(document.querySelectorAll('table.metrics'))"
                                    ".map(t => t.getBoundingClientRect().right)")
    assert rights and max(rights) <= width, (rights, width)
    assert browser.execute_script("return document.documentElement.scrollWidth") <= width
    browser.set_window_size(1400, 1000)

    shot = report.parent / "report_screenshot.png"
    browser.save_screenshot(str(shot))
    assert shot.stat().st_size > 10_000


# ---------------------------------------------------------------------------
# Rewriting scenes, choosing crops
# ---------------------------------------------------------------------------

def _demo_root():
    return ET.parse(assets.DEMO_XML).getroot()


def test_rewrite_swaps_every_normal_mapped_bsdf():
    root = _demo_root()
    n_plugin = sum(1 for b in root.iter("bsdf") if b.get("type") == PLUGIN)
    assert n_plugin == 2
    for method in METHODS:
        out = scene_xml.rewrite(root, method, {"strength": "1.0"})
        bsdfs = {b.get("type") for b in out.iter("bsdf")}
        shapes = [s.find("bsdf") for s in out.iter("shape")]
        if method.kind == "flat":
            assert PLUGIN not in bsdfs and "normalmap" not in bsdfs
            assert [b.get("type") for b in shapes] == ["roughconductor", "roughplastic"]
        elif method.kind == "classic":
            assert PLUGIN not in bsdfs
            for b in shapes:
                props = {c.get("name"): c.get("value") for c in b if c.tag != "bsdf"}
                assert b.get("type") == "normalmap" and "model" not in props and "strength" not in props
                flag = "true" if method.fixes else "false"
                assert props["flip_invalid_normals"] == props["use_shadowing_function"] == flag
        else:
            for b in shapes:
                props = {c.get("name"): c.get("value") for c in b if c.tag != "bsdf"}
                assert b.get("type") == PLUGIN and props["model"] == method.model
                assert props.get("tangent_facet", "specular") == method.tangent_facet


def test_choose_crops_gives_every_shape_its_best_window():
    score = np.zeros((2, 40, 60))
    score[0, 30:38, 50:58] = 1.0      # the big grazing region of shape 0
    score[0, 2:10, 2:10] = 0.5
    score[1, 20:24, 20:24] = 1.0      # a small one of shape 1
    crops = coverage.choose_crops(score, 3, 8)
    assert len(crops) == 3
    assert crops[0] == (50, 30, 8) and crops[1][0] <= 20 <= crops[1][0] + 4
    assert crops[2] == (2, 2, 8)
    assert coverage.choose_crops(np.zeros((10, 10)), 3, 4) == []


def test_rel_mse_and_near_black_fraction():
    ref = np.full((4, 4, 3), 0.5)
    assert metrics.rel_mse(ref, ref) == 0.0
    assert metrics.rel_mse(ref * 2, ref) == pytest.approx(0.25 / 0.26)
    img = ref.copy()
    img[0, 0] = 0
    mask = np.ones((4, 4), bool)
    assert metrics.near_black_fraction(img, mask, 0.01) == pytest.approx(1 / 16)



def test_compare_counts_and_reports_the_pixels_it_writes_as_zero(tmp_path):
    """A negative or NaN pixel of a method's render is written and scored as 0, and said so:
    counted per method (the report's columns) and warned about in the log, not clamped silently."""
    img = np.full((2, 3, 3), 0.25, np.float32)
    img[0, 0, 1] = -0.5
    img[1, 2, 0] = np.nan
    ref = np.full((2, 3, 3), 0.25, np.float32)
    ref[1, 1, 2] = -1e-3
    lines = []
    r = compare._record(0, 1, METHODS[0], img, ref, (1.0, 2.0), compare.QUICK, tmp_path, lines.append)
    assert (r["nonfinite"], r["negative"]) == (1, 2)
    assert r["image"].min() == 0.0 and np.isfinite(r["image"]).all() and r["ref"].min() == 0.0
    warnings = [line for line in lines if "warning" in line]
    assert len(warnings) == 2
    assert "1 pixel(s)" in warnings[0] and "NaN/Inf" in warnings[0]
    assert "2 pixel(s)" in warnings[1] and "negative" in warnings[1]
    written = mi.TensorXf(mi.Bitmap(str(tmp_path / f"{METHODS[0].key}.exr")))
    assert np.array(written).min() == 0.0
    before = len(lines)
    clean = compare._record(0, 1, METHODS[0], ref.clip(0), ref.clip(0), (1.0, 2.0), compare.QUICK,
                            tmp_path, lines.append)
    assert (clean["nonfinite"], clean["negative"]) == (0, 0)
    assert not any("warning" in line for line in lines[before:])

# ---------------------------------------------------------------------------
# Scene (b): the torus knot
# ---------------------------------------------------------------------------

def test_torus_knot_has_seamless_uvs_and_outward_normals():
    P, N, UV, F = assets.torus_knot_mesh()
    assert len(F) == 20_000
    assert np.allclose(np.linalg.norm(N, axis=1), 1.0, atol=1e-5)
    n_u, n_v = 400, 25
    grid = lambda a: a.reshape(n_u + 1, n_v + 1, -1)  # noqa: E731
    # Seams: duplicated vertices at the same place with the same normal, UVs an integer apart.
    for a in (P, N):
        assert np.allclose(grid(a)[0], grid(a)[-1], atol=1e-5)
        assert np.allclose(grid(a)[:, 0], grid(a)[:, -1], atol=1e-5)
    du = grid(UV)[-1, :, 0] - grid(UV)[0, :, 0]
    assert np.allclose(du, np.round(du[0])) and du[0] >= 1
    assert np.allclose(np.abs(grid(UV)[:, -1, 1] - grid(UV)[:, 0, 1]), 1.0)
    # Faces wind counter-clockwise seen from outside: face normals agree with vertex normals.
    fn = np.cross(P[F[:, 1]] - P[F[:, 0]], P[F[:, 2]] - P[F[:, 0]])
    assert np.all(np.sum(fn * N[F].mean(axis=1), axis=1) > 0)
    assert P[:, 1].min() >= 0.0 and P[:, 1].min() < 0.05     # resting on the floor


def test_knot_tangent_frame_matches_the_normal_map_convention(tmp_path):
    a = assets.generate_model_assets(tmp_path)
    mesh = mi.load_dict({"type": "ply", "filename": str(a["mesh"])})
    assert mesh.has_vertex_texcoords() and mesh.has_vertex_normals() and mesh.face_count() == 20_000
    # Hit the knot from many directions and compare the shading frame with the UV gradients.
    rng = np.random.default_rng(3)
    d = rng.normal(size=(4096, 3))
    d /= np.linalg.norm(d, axis=1, keepdims=True)
    o = np.array([0.0, 0.74, 0.0]) + 6.0 * d
    scene = mi.load_dict({"type": "scene", "knot": mesh})
    target = np.array([0.0, 0.74, 0.0]) + rng.uniform(-1.2, 1.2, size=(4096, 3)) * [1, 0.3, 1]
    dirs = target - o
    dirs /= np.linalg.norm(dirs, axis=1, keepdims=True)
    si = scene.ray_intersect(mi.Ray3f(mi.Point3f(*o.T), mi.Vector3f(*dirs.T)))
    hit = np.array(si.is_valid())
    assert hit.sum() > 1000
    t_dot_dpdv = np.array(dr.dot(si.sh_frame.t, dr.normalize(si.dp_dv)))[hit]
    s_dot_dpdu = np.array(dr.dot(si.sh_frame.s, dr.normalize(si.dp_du)))[hit]
    # Mitsuba's bitmaps put v = 0 on the top row, so image up (the map's +y, OpenGL) is -dp/dv.
    assert np.all(t_dot_dpdv < -0.95) and np.all(s_dot_dpdu > 0.95)
    tex = mi.load_dict({"type": "bitmap", "raw": True, "filter_type": "nearest",
                        "bitmap": mi.Bitmap(np.arange(4, dtype=np.float32).reshape(4, 1, 1).repeat(4, 1))})
    probe = dr.zeros(mi.SurfaceInteraction3f, 2)
    probe.uv = mi.Point2f([0.5, 0.5], [0.1, 0.9])
    assert list(np.array(tex.eval_1(probe))) == [0.0, 3.0]   # row 0 at v = 0


def test_domes_normal_map_bulges_out_in_the_opengl_convention():
    n = assets.make_domes_normalmap(size=256)
    assert np.allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)
    assert n[..., 2].min() > np.cos(np.radians(70.5))
    # A dome centred at the image origin (the lattice has a centre at x = y = 0, i.e. the corner):
    # texels to its lower right (image down = -y) lean right (+x) and down (-y).
    corner = n[3:10, 3:10]
    assert np.all(corner[..., 0] > 0) and np.all(corner[..., 1] < 0)


# ---------------------------------------------------------------------------
# The bundled dielectric scenes: water (d) and glass (e)
# ---------------------------------------------------------------------------

def test_ripples_normal_map_tiles_and_hits_its_max_tilt():
    n = assets.make_ripples_normalmap(size=128, max_tilt_deg=25.0)
    assert np.allclose(np.linalg.norm(n, axis=-1), 1.0, atol=1e-5)
    tilt = np.degrees(np.arccos(n[..., 2]))
    assert 24.0 < tilt.max() <= 25.0 + 1e-3 and np.median(tilt) > 5.0
    # Integer wave numbers: the last column continues into the first (a seamless tile).
    step = np.abs(n[:, 0] - n[:, -1]).max()
    assert step < 3 * np.abs(np.diff(n, axis=1)).max()


#: The paper's models only reflect: they refuse a transmitting nested BSDF by design.
PAPER_MODELS = {m.key for m in METHODS if m.kind == "microfacet" and m.model != "faithful"}


def run_compare(*args):
    env = dict(os.environ, PYTHONPATH=str(ROOT / "src"))
    return subprocess.run([sys.executable, "-m", "mfnormal", "compare", *map(str, args)], env=env,
                          capture_output=True, text=True, timeout=600)


@pytest.mark.parametrize("scene", ["water", pytest.param("glass", marks=pytest.mark.slow),
                                   pytest.param("underwater", marks=pytest.mark.slow)])
def test_compare_renders_the_dielectric_scenes_with_every_method(tmp_path, scene):
    """``mfnormal compare water --quick`` (and ``glass``): exit 0 and the report; a finite,
    non-negative render per method, except the paper's models, which refuse the transmitting
    material: no render, their cells say so with the reason, and the log names them; the floor is
    seen through the un-mapped surface (its render is not dark)."""
    proc = run_compare(scene, "--quick", "-o", tmp_path)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert PAPER_MODELS and "faithful" not in PAPER_MODELS
    text = (tmp_path / "report.html").read_text(encoding="utf-8")
    assert f"id='scene-{scene}'" in text
    for method in METHODS:
        exr = tmp_path / scene / f"{method.key}.exr"
        if method.key in PAPER_MODELS:
            assert not exr.exists() and f"img-{scene}-{method.key}" not in text
            reason = html.escape(f"transmits light, but model='{method.model}' only reflects")
            cell = re.search(f"<figure class=refused id='refused-{scene}-{method.key}'.*?</figure>", text)
            assert cell and "refuses this scene" in cell[0] and reason in cell[0], method.key
            assert "<img" not in cell[0]
            log = [ln for ln in proc.stdout.splitlines() if ln.split()[:2] == [method.key, "refuses"]]
            assert len(log) == 1 and f"model='{method.model}' only reflects" in log[0]
            continue
        img = np.array(mi.Bitmap(str(exr)))
        assert img.shape[1] == compare.QUICK.width and np.isfinite(img).all() and (img >= 0).all()
        assert f"img-{scene}-{method.key}" in text and f"refused-{scene}-{method.key}" not in text
    # Left out of the measurements: a row with the reason and no numbers.
    table = text[text.index("<table class=metrics>"):]
    table = table[:table.index("</table>")]
    refused_rows = re.findall(r"<tr class=refused>.*?</tr>", table)
    assert len(refused_rows) == len(PAPER_MODELS)
    assert all("refuses this scene" in row and " s</td>" not in row for row in refused_rows)
    flat = np.array(mi.Bitmap(str(tmp_path / scene / "flat_ref.exr")))
    assert flat.mean() > 0.05


def test_the_underwater_scene_looks_up_through_snells_window_and_beyond_it(tmp_path):
    """Scene (f) is what it says: every camera ray that meets the water meets it from below (the
    camera is in the water), the frame's top row looks up within Snell's window (48.8° from the
    vertical at ior 1.33) and its bottom row beyond it; rendered with the map flat (strength 0),
    the top shows the sky (bright, no checkerboard) and the bottom the floor reflected totally
    (the checkerboard's dark and light tiles, nothing of the sky); with the map, no pixel is NaN
    or black. 48 × 32 px at 16 spp: the flat surface is smooth, so rows differ by the scene, not
    by noise (the floor's tiles are 0.1 and 0.7 of the sky's light)."""
    b = assets.BUNDLED["underwater"]
    params = {k.lstrip("$"): str(v) for k, v in b.parameters(b.generate(tmp_path)).items()}

    def load(strength):
        return mi.load_file(str(b.xml), spp="16", width="48", height="32", strength=str(strength), **params)
    scene = load(0.0)
    sensor = scene.sensors()[0]
    rows = {}
    for name, y in (("top", 0.5), ("bottom", 31.5)):
        x = np.linspace(0.5, 47.5, 48)
        pos = mi.Point2f(x / 48.0, np.full(48, y / 32.0))
        ray, _ = sensor.sample_ray(0.0, 0.5, pos, mi.Point2f(0.5))
        si = scene.ray_intersect(ray)
        assert dr.all(si.is_valid()), name
        up = np.array(ray.d.y)
        assert (np.array(si.n.y) > 0.99).all() and (up > 0).all(), f"{name}: the rays meet the water from below"
        rows[name] = np.degrees(np.arccos(up))
    critical = np.degrees(np.arcsin(1.0 / 1.33))
    assert rows["top"].max() < critical - 5 and rows["bottom"].min() > critical + 5, rows
    flat = np.array(mi.render(scene)).mean(-1)
    top, bottom = flat[:3], flat[-8:]
    assert top.min() > 0.5 and top.std() < 0.1 * top.mean(), "the window shows the sky"
    assert np.percentile(bottom, 10) < 0.35 * np.percentile(bottom, 90), "the floor reflected beyond the window"
    mapped = np.array(mi.render(load(1.0)))
    assert np.isfinite(mapped).all() and (mapped.mean(-1) > 1e-3).all()


def test_compare_finds_refusals_from_the_scene_wherever_the_plugin_sits():
    """The methods that refuse a scene come from its loaded materials (the plugin nested in a
    ``blendbsdf`` too): the paper's models on a transmitting nested BSDF, none on a reflecting one."""
    def scene(nested):
        plugin = {"type": PLUGIN, "bsdf": nested,
                  "normalmap": {"type": "bitmap", "raw": True, "data": mi.TensorXf(np.full((4, 4, 3), 0.5, np.float32))}}
        return mi.load_dict({"type": "scene", "integrator": {"type": "path"},
                             "s": {"type": "rectangle",
                                   "bsdf": {"type": "blendbsdf", "weight": 0.5, "a": plugin,
                                            "b": {"type": "diffuse"}}}})
    refused = compare.refusals(scene({"type": "roughdielectric"}), METHODS)
    assert {m.key for m in refused} == PAPER_MODELS
    assert all(f"model='{m.model}' only reflects" in reason for m, reason in refused.items())
    assert compare.refusals(scene({"type": "roughconductor"}), METHODS) == {}


def test_compare_fails_in_one_line_on_a_broken_dielectric_scene(tmp_path):
    """A dielectric scene that cannot load (a missing normal map) is an error, not a refusal: one
    line, exit 2, nothing written; and so is a scene that every method asked for refuses."""
    proc = run_compare("water", "--quick", "-o", tmp_path / "a", "-D", "normalmap=missing.png")
    assert_one_line_error(proc, "cannot load water.xml", "missing.png")
    assert proc.returncode == 2 and "refuses" not in proc.stdout + proc.stderr
    assert not (tmp_path / "a" / "report.html").exists()
    proc = run_compare("water", "--quick", "-o", tmp_path / "b", "--methods", "analytic,separable_same")
    assert_one_line_error(proc, "water.xml", "every method refuses it", "model='analytic' only reflects")
    assert proc.returncode == 2 and not (tmp_path / "b" / "report.html").exists()
