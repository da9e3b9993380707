"""The dielectric true-geometry harness (``validation.dielectric``) and the glass furnace
(``validation.furnace_glass``): the set-ups are right before any method is judged by them.

Tiny renders (16-32 px, 4-16 spp), fixed seeds. What is checked: the truth's flat mesh renders
like the flat plane (so the displaced mesh is a faithful truth), the un-mapped smooth glass
sphere is 1 in the furnace (so the furnace is deep enough and lossless), every method renders
a finite, non-negative dielectric cell or is recorded as refused, and the report writers. The
methods' scores are the reports' (validation/results/dielectric.md, furnace_glass.md), not
asserted here.
"""

import numpy as np
import pytest

import mfnormal  # noqa: F401  (first: selects a working libLLVM)
import mitsuba as mi
from variant import VARIANT  # noqa: E402  (MFNORMAL_VARIANT, tests/variant.py)

mi.set_variant(VARIANT)
mfnormal.register()

from validation import dielectric as D  # noqa: E402
from validation import furnace_glass as F  # noqa: E402
from validation import heightfield as H  # noqa: E402


@pytest.mark.parametrize("material, view", [
    ("water", "oblique40"),
    ("water", "inside40"),
    pytest.param("rough_glass", "grazing", marks=pytest.mark.slow),
    pytest.param("rough_glass", "inside40", marks=pytest.mark.slow),
])
def test_a_flat_heightfields_displaced_mesh_renders_like_the_flat_plane(material, view):
    """The truth's mesh of a flat heightfield against the two-triangle plane, the same dielectric
    (over the floor, or seen from inside). With the plane's own seed the paths are the same but
    for round-off in the intersections: relMSE < 1e-3 (measured ≤ 2e-5 in every material and
    view at 32² px, 16 spp, where the noise between two seeds is 8e-4 to 0.2: a mesh at another
    height, with flipped normals or without the floor differs by the latter). With another seed
    the mesh scores like the noise floor (≤ 1.5×; measured 1.04-1.07×)."""
    c = D.flat_check(material, view, res=32, spp=16, seed=3)
    assert c["same_seed"] < 1e-3, c["same_seed"]
    assert c["mesh"]["rel_mse"] <= 1.5 * c["floor"]["rel_mse"] + 1e-4, (c["mesh"], c["floor"])
    assert abs(c["mesh"]["energy"] - 1.0) < 0.05, c["mesh"]["energy"]


def test_the_smooth_glass_sphere_without_a_map_is_white_in_the_furnace():
    """A smooth glass sphere in a constant environment 1 is invisible: every sphere pixel 1 ± 1 %
    (paths of smooth glass carry weight 1, so only a path cut short by the depth limit or Russian
    roulette, or lost light, moves a pixel: measured 1.0000). The same furnace sees classic normal
    mapping's loss with 50° bumps (measured 0.46): the set-up can fail."""
    res, mask = 24, F.sphere_mask(24)
    img, nonfinite, negative = F.render_sphere(F.GLASS["smooth_glass"], res, 16, seed=1)
    m = F.furnace_metrics(img, 1.0, mask)
    assert abs(m["mean"] - 1.0) < 0.01 and m["off_5"] == 0.0, m
    assert nonfinite == negative == 0
    classic = H.METHODS["classic_fixed"].bsdf(F.GLASS["smooth_glass"], F.sphere_map(50.0))
    assert F.furnace_metrics(F.render_sphere(classic, res, 16, seed=1)[0], 1.0, mask)["mean"] < 0.7


def test_the_true_bumpy_sphere_is_the_surface_the_glass_map_was_baked_from():
    """The furnace's truth (``truth_mesh``) and map (``sphere_map``) are one surface: the mesh's
    faces tilt up to the asked 50° from the radial direction (measured 49.9° at 256 vertices per
    ring), and under a sun on a white-ish diffuse sphere Mitsuba's ``normalmap`` with the baked map
    renders close to the mesh (relMSE 0.012 at 20°, 32² px, 64 spp), far closer than with the map's
    x or y flipped (0.30, 0.082: a wrong tangent-frame convention) or without it (0.106)."""
    mesh = F.truth_mesh(50.0, None, around=256)
    params = mi.traverse(mesh)
    p = np.array(params["vertex_positions"]).reshape(-1, 3)
    f = np.array(params["faces"]).reshape(-1, 3)
    a, b, c = p[f[:, 0]], p[f[:, 1]], p[f[:, 2]]
    n = np.cross(b - a, c - a)
    radial = (a + b + c) / 3.0
    cos = np.sum(n * radial, axis=1) / (np.linalg.norm(n, axis=1) * np.linalg.norm(radial, axis=1))
    assert cos.min() > 0.0                                       # every face faces outward
    assert abs(np.degrees(np.arccos(cos.min())) - 50.0) < 1.5, np.degrees(np.arccos(cos.min()))

    res, mask = 32, F.sphere_mask(32)
    diffuse = {"type": "diffuse", "reflectance": {"type": "rgb", "value": 0.7}}

    def sunlit(shape):
        scene = F.furnace_scene(diffuse, res, 64, shape)
        scene["furnace"] = {"type": "directional", "direction": [-0.6, 0.5, -0.3],
                            "irradiance": {"type": "rgb", "value": 3.0}}
        return H.luminance(np.array(mi.render(mi.load_dict(scene), seed=2)))[mask]
    truth = sunlit(F.truth_mesh(20.0, diffuse, around=256))
    tex = F.sphere_map(20.0)
    rgb = np.array(tex["bitmap"])
    err = {}
    for name, channel in (("baked", None), ("x flipped", 0), ("y flipped", 1), ("no map", -1)):
        bsdf = diffuse
        if channel != -1:
            m = rgb.copy()
            if channel is not None:
                m[..., channel] = 1.0 - m[..., channel]
            bsdf = {"type": "normalmap", "normalmap": dict(tex, bitmap=mi.Bitmap(m)), "bsdf": diffuse}
        y = sunlit({"type": "sphere", "radius": 1.0, "bsdf": bsdf})
        err[name] = float(np.mean((y - truth) ** 2 / (truth ** 2 + 1e-2)))
    assert err["baked"] < 0.3 * min(v for k, v in err.items() if k != "baked"), err


def test_the_true_bumpy_glass_sphere_is_white_in_the_furnace():
    """The furnace's truth for smooth glass: the bumpy sphere as a mesh of lossless glass keeps all
    the light at the harness's max_depth (no path is cut while trapped inside): every pixel 1
    (measured 1.0000001, none off by 5 %, at 24² px and 16 spp)."""
    res, mask = 24, F.sphere_mask(24)
    mesh = F.truth_mesh(50.0, F.GLASS["smooth_glass"], around=256)
    img, nonfinite, negative = F.render_sphere(None, res, 16, seed=1, shape=mesh)
    m = F.furnace_metrics(img, 1.0, mask)
    assert abs(m["mean"] - 1.0) < 1e-3 and m["off_5"] == 0.0, m
    assert nonfinite == negative == 0


@pytest.mark.parametrize("material, steepness, view, delta_paths", [
    ("water", "steep", "inside40", True),
    pytest.param("rough_glass", "mild", "oblique40", False, marks=pytest.mark.slow),
])
def test_every_method_renders_a_dielectric_cell_or_is_recorded_as_refused(material, steepness, view,
                                                                          delta_paths):
    """Every method of the default list renders finite, non-negative values (before the harness
    sets NaN/Inf to 0) and is scored, or its load error is recorded as a refusal; a model the
    plugin does not have is such a refusal. Smooth water seen from inside has only delta paths,
    each ending in the sky (through the surface) or in its ground (by reflection), both far above
    the near-black threshold: there no pixel of the un-mapped plane is near-black (over a floor, at
    4 spp, a few are by chance: the dark checks)."""
    methods = [D.method(s) for s in D.DEFAULT_METHODS] + [D.method("plugin:no_such_model")]
    r = D.measure_cell(D.cell(material, steepness, view), methods, res=16, spp=4, ref_factor=2, seed=5)
    # The paper's models only reflect: a transmitting nested BSDF is their one-line load error,
    # which names the default as the model that refracts.
    paper = {m.key for m in methods[:-1] if m.key not in ("nomap", "classic", "classic_fixed", "default")}
    assert paper and set(r["errors"]) == paper | {"no_such_model"}, r["errors"]
    assert all("faithful" in r["errors"][k] and "\n" not in r["errors"][k] for k in paper), r["errors"]
    for m in methods[:-1]:
        if m.key in paper:
            continue
        assert r["invalid"][m.key] == {"nonfinite": 0, "negative": 0}, m.key
        assert np.isfinite(list(r["metrics"][m.key].values())).all(), m.key
    assert r["floor"]["energy"] > 0
    if delta_paths:
        assert r["metrics"]["nomap"]["near_black_new"] == 0.0


def _result(name, rel, errors=None):
    """A cell result as :func:`validation.dielectric.measure_cell` returns it, with given relMSEs."""
    metric = lambda x: {"rel_mse": x, "bias": x / 4, "energy": 0.5, "near_black_new": 0.25}  # noqa: E731
    return {"cell": name, "metrics": {k: metric(v) for k, v in rel.items()}, "errors": errors or {},
            "floor": metric(0.01), "truth_stats": {"mean": 0.2, "near_black": 0.0}, "times": {},
            "invalid": {}, "spp": 4, "ref_spp": 16}


def test_the_dielectric_summary_and_report_count_what_they_say():
    """Geometric means, the ≤ classic and < no map counts, refusals in the summary and per cell."""
    a = "eggcrate/20deg/water/sky/oblique40/magnified/floor0.25"
    b = "eggcrate/50deg/water/sky/inside40/magnified"
    results = [_result(a, {"nomap": 0.4, "classic": 0.1, "classic_fixed": 0.2, "default": 0.1},
                       {"analytic": "ValueError: refuses transmission"}),
               _result(b, {"nomap": 0.4, "classic": 0.1, "classic_fixed": 0.2, "default": 0.4},
                       {"analytic": "ValueError: refuses transmission"})]
    keys = ["nomap", "classic", "classic_fixed", "default", "analytic"]
    s = D.summarise(results, keys)
    assert set(s) == {"all cells", "mild (max tilt 20°)", "steep (max tilt 50°)",
                      "floor through the surface", "from inside", "material water"}
    d = s["all cells"]["methods"]["default"]
    assert d["rel_mse"] == pytest.approx(0.2) and d["bias"] == pytest.approx(0.05)
    assert (d["le_classic"], d["lt_nomap"]) == (1, 1) and s["all cells"]["refused"]["analytic"] == 2
    assert s["from inside"]["methods"]["default"]["le_classic"] == 0 and s["from inside"]["cells"] == 1
    assert "analytic" not in s["all cells"]["methods"]
    settings = {"command": "python -m validation.dielectric --quick", "elapsed_s": 6.0, "cells": 2,
                "res": 16, "spp": 4, "ref_factor": 4, "methods": keys, "stem": "dielectric_quick"}
    md = D.markdown({"cells": results, "summary": s, "settings": settings,
                     "flat_checks": [{"material": "water", "view": "oblique40", "mesh": {"rel_mse": 0.02, "energy": 1.001},
                                      "floor": {"rel_mse": 0.019}, "same_seed": 1e-5}]},
                    {"default": "default"}, quick=True)
    assert "python -m validation.dielectric --quick" in md
    assert "| default | 0.2 | 0.05 | 0.5 (0.5–0.5) | 25.00 % | 1/2 | 1/2 |" in md
    assert "| analytic | refused in 2 of 2 cells |" in md and "refused: ValueError: refuses transmission" in md
    assert "| water | oblique40 | 0.02 | 0.019 | 1.001 | 1.00e-05 |" in md
    assert "(dielectric_quick.png)" in md


def test_the_furnace_report_lists_every_method_and_refusal():
    row = {"cell": "smooth_glass/50deg", "material": "smooth_glass", "tilt": 50.0, "spp": 4,
           "reference": "exact (1)", "reference_mean": 1.0, "times": {}, "truth_spp": 4,
           "truth_metrics": {"mean": 0.99999, "ratio": 0.99999, "off_5": 0.0, "off_10": 0.0},
           "metrics": {"classic": {"mean": 0.456, "ratio": 0.456, "off_5": 0.99, "off_10": 0.97}},
           "errors": {"analytic": "ValueError: refuses transmission"},
           "invalid": {"classic": {"nonfinite": 0, "negative": 0}}}
    settings = {"command": "python -m validation.furnace_glass", "elapsed_s": 1.0, "res": 16, "spp": 4,
                "methods": ["classic", "analytic"], "stem": "furnace_glass"}
    md = F.markdown({"rows": [row], "settings": settings}, {"classic": "normalmap"})
    assert "| normalmap | 0.456 | 0.456 | 99.0 % | 97.0 % |" in md
    assert "| analytic | refused: ValueError: refuses transmission |" in md and "| *exact* | 1 |" in md
    assert "| *true geometry* | 1 | 1 | 0.0 % | 0.0 % |" in md


def test_the_harness_commands_document_themselves(capsys):
    for module in (D, F):
        with pytest.raises(SystemExit) as exit_:
            module.parse_args(["--help"])
        assert exit_.value.code == 0
        out = capsys.readouterr().out
        assert "--quick" in out and "--methods" in out and module.__doc__.split("\n\n")[0] in out


def test_the_cells_views_and_floor_are_where_the_names_say():
    """From inside, the camera is below the surface looking up and sees the same footprint as
    from above at the same angle; a floor cell has its checkerboard floor below the surface and
    its name says so, and a cell without a floor keeps the name (and seed) it always had."""
    inside, above = D.cell("water", "mild", "inside40"), D.cell("water", "mild", "oblique40")
    assert H.footprint(H.VIEWS["inside40"]) == pytest.approx(H.footprint(H.VIEWS["oblique40"]))
    scene = inside.truth_scene(res=8, spp=1)
    origin = np.array(scene["sensor"]["to_world"].matrix)[:3, 3]
    assert origin[2] < inside.hf().height_range[0] and "floor" not in scene
    floor = above.plane_scene(D.method("nomap"), res=8, spp=1)["floor"]
    z = np.array(mi.traverse(floor)["vertex_positions"]).reshape(-1, 3)[:, 2]
    assert np.allclose(z, above.hf().mean_height - D.FLOOR_DEPTH)
    assert above.name.endswith("/floor0.25") and "floor" not in inside.name
    plain = H.Cell("eggcrate", "mild", "diffuse", "sky_sun", "frontal", "magnified")
    assert plain.name == "eggcrate/mild/diffuse/sky_sun/frontal/magnified"


def test_registering_the_map_for_the_camera_takes_away_the_parallax_error():
    """``--registered``: every method renders the normal map registered for the camera (4× its
    resolution; the height map stays the baked one), and the report says so. Registered, classic
    normal mapping's error from inside steep water (mostly where each texel is seen: the truth's
    bands of total internal reflection lie beside the texels that make them) falls to under half
    of what it is on the baked map (measured at 96² px, 256 spp: 0.30 → 0.12); without the
    registration (or with the baked map passed through) it would not."""
    c = D.cell("water", "steep", "inside40")
    baked, reg = c.maps(), c.maps(registered=True)
    assert np.array(reg["normalmap"]["bitmap"]).shape[0] == 4 * np.array(baked["normalmap"]["bitmap"]).shape[0]
    assert np.array_equal(np.array(reg["heightmap"]["bitmap"]), np.array(baked["heightmap"]["bitmap"]))
    classic = [D.method("classic")]
    plain = D.measure_cell(c, classic, res=32, spp=16, ref_factor=4, seed=3)
    registered = D.measure_cell(c, classic, res=32, spp=16, ref_factor=4, seed=3, registered=True)
    assert registered["metrics"]["classic"]["rel_mse"] < 0.5 * plain["metrics"]["classic"]["rel_mse"]
    settings = {"command": "python -m validation.dielectric --registered", "elapsed_s": 1.0, "cells": 0,
                "res": 32, "spp": 16, "ref_factor": 4, "methods": ["classic"], "stem": "dielectric_registered",
                "registered": True}
    assert "**Registered** (`--registered`)" in D.markdown({"settings": settings}, {})
    assert "**Registered**" not in D.markdown({"settings": {**settings, "registered": False}}, {})
