"""Smoke test of ``python -m benchmarks.run``: its ``--quick`` profile runs and reports every method.

Only the quick profile runs here (tiny image, one scene, one nested BSDF, under
two minutes): it proves the benchmark still works against the current plugin,
not how fast the plugin is. The full benchmark is run by hand
(``python -m benchmarks.run``). The quick run takes about two minutes, so the tests on its
output run with MFNORMAL_SLOW=1; the benchmark's pure functions are checked in the default run.
"""

import json
import subprocess
import sys
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
METHODS = ("builtin", "faithful", "analytic", "separable_specular", "separable_same",
           "nonseparable_specular", "nonseparable_same")


def run_module():
    """``benchmarks.run`` (for its pure functions)."""
    from benchmarks import run
    return run


@pytest.fixture(scope="module")
def quick_run(tmp_path_factory):
    out = tmp_path_factory.mktemp("bench")
    proc = subprocess.run([sys.executable, "-m", "benchmarks.run", "--quick", "--out", str(out)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    return out


@pytest.mark.slow
def test_quick_benchmark_writes_json_with_every_method_and_metric(quick_run):
    results = json.loads((quick_run / "results.json").read_text())
    assert results["config"]["name"] == "quick"
    assert {"cpu", "cores", "variant", "llvm_path"} <= set(results["machine"])
    assert "-m benchmarks.run --quick" in results["command"]
    for metric in ("render_time", "noise", "compile", "throughput"):
        methods = {row["method"] for row in results[metric]}
        expected = set(METHODS) - ({"builtin"} if metric == "render_time" else set())
        assert methods == expected, metric
    assert all("error" not in row for row in results["compile"])
    assert all(row["pass"] in (True, False) for row in results["render_time"])
    assert {s["status"] for s in results["summary"]} <= {"PASS", "FAIL", "n/a"}


@pytest.mark.slow
def test_quick_benchmark_scores_noise_without_the_sun_disc_on_every_scene(quick_run):
    """The noise scoring: relMSE is scored where the methods render the same content, the sky
    without its sun disc, on every scene, the constant-map control included (under the full sky
    its tangent facets add sun glints the built-in lacks); the full-sky ratio is reported beside it."""
    results = json.loads((quick_run / "results.json").read_text())
    assert {row["scene"] for row in results["noise"]} == {"plane", "control"}
    for row in results["noise"]:
        assert row["scored_on"] == "sunless", row["scene"]
        assert row["scored_ratio"] == row["sunless_relmse_ratio"]
        assert row["sunless_relmse"] != row["relmse"], (row["scene"], row["method"])
        assert row["relmse_ratio"] > 0 and row["sunless_relmse_ratio"] > 0


@pytest.mark.slow
def test_quick_benchmark_reports_the_median_of_its_cold_compile_runs(quick_run):
    """Metric 2 runs each method's cold compile ``compile_runs`` times (2 in the quick profile) and
    reports the median run (of two, the lower), every run's time beside it."""
    results = json.loads((quick_run / "results.json").read_text())
    runs = results["config"]["compile_runs"]
    assert runs == 2
    for row in results["compile"]:
        assert len(row["compile_s_runs"]) == runs, row["method"]
        assert row["compile_s"] == sorted(row["compile_s_runs"])[(runs - 1) // 2], row["method"]


def test_median_run_is_the_middle_run_whole():
    """run.median_run: the run with the median compile time, all of its fields (not a mix of runs),
    the lower middle one of an even count, every run's time in order; a failed run wins."""
    run = run_module()
    runs = [{"compile_s": 0.5, "ops": 1}, {"compile_s": 0.3, "ops": 2}, {"compile_s": 0.9, "ops": 3}]
    assert run.median_run(runs) == {"compile_s": 0.5, "ops": 1, "compile_s_runs": [0.5, 0.3, 0.9]}
    assert run.median_run(runs[:2])["ops"] == 2
    assert run.median_run(runs + [{"error": "worker exited 1"}]) == {"error": "worker exited 1"}


@pytest.mark.slow
def test_quick_benchmark_counts_path_vertices_of_every_method(quick_run):
    """Metric 1's path vertices per camera sample (probes.count_calls), for every timed method and
    the built-in, and the time ratio per vertex. On the plane, the only shape, every camera ray that
    hits it makes exactly one vertex (its continuation leaves to the sky), whatever the BSDF: the
    same seeds give every method the built-in's count exactly, and that count is the plane's share of
    the camera rays (0 < v < 1)."""
    results = json.loads((quick_run / "results.json").read_text())
    rows = [r for r in results["render_time"] if not r.get("integrator")]
    assert {r["method"] for r in rows} == set(METHODS) - {"builtin"}
    for r in rows:
        assert r["vertices"] > 0 and r["builtin_vertices"] > 0, (r["scene"], r["method"])
        assert r["vertex_ratio"] == pytest.approx(r["vertices"] / r["builtin_vertices"])
        assert r["ratio_per_vertex"] == pytest.approx(r["ratio"] / r["vertex_ratio"])
    plane = [r for r in rows if r["scene"] == "plane"]
    assert plane
    for r in plane:
        assert r["vertices"] == r["builtin_vertices"], r["method"]
        assert 0.0 < r["vertices"] < 1.0
    text = (quick_run / "RESULTS.md").read_text()
    assert "Path vertices per camera sample" in text and "time ratio per vertex" in text


@pytest.mark.slow
def test_quick_benchmark_writes_markdown_table_with_every_method(quick_run):
    text = (quick_run / "RESULTS.md").read_text()
    assert "## Targets" in text and "-m benchmarks.run --quick" in text
    for method in METHODS:
        assert f"| {method} |" in text, method


def test_normal_sources_benchmark_runs_and_reports_every_config(tmp_path):
    """``python -m benchmarks.normal_sources`` at a tiny size (2^10 queries, one rep, one model): every
    option × nested × call has a finite positive ratio (its timings mean nothing here)."""
    proc = subprocess.run([sys.executable, "-m", "benchmarks.normal_sources", "--queries", "10",
                           "--reps", "1", "--models", "analytic", "--out", str(tmp_path)], cwd=ROOT,
                          capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-2000:] + proc.stderr[-2000:]
    rows = json.loads((tmp_path / "normal_sources.json").read_text())["rows"]
    assert {(r["config"], r["call"]) for r in rows} == {
        (c, w) for c in ("heightmap", "geometric", "geometric_heightmap", "geometric_nomap")
        for w in ("eval", "eval_pdf", "sample")}
    assert all(r["ratio"] > 0 for r in rows)


def test_integrator_option_swaps_every_methods_path_tracer():
    """``--integrator mfnormal_path``: every method's scene gets it, the built-in's included (one
    integrator for the ratios); a scene without a path integrator is an error."""
    R = run_module()
    scene = {"type": "scene", "integrator": {"type": "path", "max_depth": 8}, "x": {"type": "sphere"}}
    swapped = R.with_integrator(scene, "mfnormal_path")
    assert swapped["integrator"] == {"type": "mfnormal_path", "max_depth": 8}
    assert scene["integrator"]["type"] == "path" and R.with_integrator(scene, "path") is scene
    ap, args = R.parse_args(["--profile", "all", "--integrator", "mfnormal_path"])
    profiles = R.selected_profiles(ap, args)
    assert profiles and all(p.integrator == "mfnormal_path" for p in profiles)
    for prof in profiles:
        assert R.method_integrator(prof, "builtin") == "mfnormal_path"
        assert R.method_integrator(prof, "separable_same") == "mfnormal_path"
    assert R.FULL.integrator == "path"          # the module's profiles are left as they are
    with pytest.raises(ValueError):
        R.with_integrator({"type": "scene"}, "mfnormal_path")


def test_busy_note_judges_the_load_before_the_run_not_the_runs_own():
    """run.busy_note: an idle machine (load 0.01 before) whose run ends at load 1.7 on 2 cores, its
    own Dr.Jit threads, gets no note; one already at 1.5 before the run is flagged, both loads named."""
    run = run_module()
    assert run.busy_note(0.01, 1.7, 2) is None
    note = run.busy_note(1.5, 1.9, 2)
    assert note is not None and "busy" in note and "1.5" in note and "1.9" in note


def test_water_profile_times_the_default_against_the_builtin_on_the_same_dielectric(tmp_path):
    """The water profile: the bundled water scene with its own dielectric, the built-in's scene is
    Mitsuba's normalmap wrapping that dielectric and the default's normalmap_microfacet around it,
    both loadable; ``--profile all`` runs it."""
    from variant import VARIANT

    R = run_module()
    R.import_mitsuba(VARIANT)
    assert R.WATER in R.PROFILES["all"] and R.WATER.nested == (R.NATIVE,)
    assets = R.prepare_assets(tmp_path, ("water",))
    for method, kind in (("builtin", "normalmap"), ("faithful", "normalmap_microfacet")):
        scene = R.scene_dict("water", assets, method, R.NATIVE, 16, 12, 1)
        (bsdf,) = [v for v in scene["water"].values() if isinstance(v, dict) and "bsdf" in v]
        assert bsdf["type"] == kind and bsdf["bsdf"]["type"] == "dielectric", bsdf
        assert R.mi.load_dict(scene) is not None


def test_results_copy_every_table_of_the_backward_benchmark_apart(tmp_path):
    """run.backward_section: RESULTS.md's copy of backward.md keeps both of its tables (the render +
    backward and the optimiser's step) and the line between them, so that they stay two tables,
    and nothing of the file's heading."""
    run = run_module()
    (tmp_path / "backward.md").write_text("# Reverse-mode cost\n\nWhat it measures.\n\n| a | b |\n|---|---|\n| 1 | 2 |\n"
                                          "\nThe step.\n\n| c | d | e |\n|---|---|---|\n| 3 | 4 | 5 |\n\n")
    lines = run.backward_section({"backward": {"command": "cmd", "duration_s": 3.0, "md": "backward.md"}}, tmp_path)
    assert lines[0].startswith("## Backward pass") and "`cmd` (3 s)" in lines[2]
    body = lines[4:]
    assert body == ["| a | b |", "|---|---|", "| 1 | 2 |", "", "The step.", "", "| c | d | e |", "|---|---|---|",
                    "| 3 | 4 | 5 |", ""]
