"""The real-asset harness's equal-time mode (``python -m validation.real_assets --equal-time``).

The spp rule alone (no rendering), and one quick cell end to end: the small npm ``bunny``
(fetched into the asset cache on first use), 300 triangles, a 256² map, the limb view at 32²
px and 4 spp (a few seconds); skipped without the optional ``assets`` dependencies
(``xatlas``, ``fast-simplification``) or, with an empty cache, without ``npm``.
"""

import json
import math

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import mitsuba as mi
import pytest

from helpers import skip_without_real_assets


def test_the_equal_time_spp_gives_a_slower_method_fewer_samples():
    """The reference keeps the cell's spp; a method twice as slow gets half (4 → 2, 32 spp,
    which multijitter takes as 35 → 16), one twice as fast twice as many; multijitter's counts
    are the ones Mitsuba's sampler takes, and an equal-time count is one it takes as asked."""
    from validation import real_assets as R

    sampler = mi.load_dict({"type": "multijitter", "sample_count": 1})
    for n in range(1, 80):
        sampler.set_sample_count(n)
        assert R.multijitter_count(n) == sampler.sample_count(), n
    assert R.samples_taken("multijitter", 100) == 64 + 36 and R.samples_taken("independent", 35) == 35
    for spp in (1, 4, 32, 128):
        assert R.equal_time_spp(spp, 0.1, 0.1) == spp
    assert R.equal_time_spp(4, 1.0, 2.0) == 2 and R.equal_time_spp(4, 1.0, 0.5) == 8
    assert R.equal_time_spp(32, 1.0, 2.0) == 16 and R.equal_time_spp(32, 1.0, 1.4) == 25
    assert R.equal_time_spp(32, 1.0, 1.2, "independent") == 27
    assert R.equal_time_spp(4, 1.0, 100.0) == 1
    for ratio in (0.7, 1.3, 1.7, 2.9):
        n = R.equal_time_spp(32, 1.0, ratio)
        assert R.samples_taken("multijitter", n) == n


def test_equal_time_needs_the_reference_among_the_methods(capsys):
    """Without classic or classic_fixed among --methods, one line and no rendering."""
    from validation import real_assets

    with pytest.raises(SystemExit) as exit_:
        real_assets.main(["--quick", "--equal-time", "--methods", "nomap,faithful", "--out", "/nonexistent"])
    assert "--equal-time needs classic or classic_fixed" in str(exit_.value)
    assert "\n" not in str(exit_.value)


def test_quick_cell_at_equal_time(tmp_path):
    """One quick cell (limb, 4 spp) with classic and faithful: classic, the reference, keeps the
    cell's spp and its equal-spp render (the same relMSE); faithful gets the spp its recorded time
    per render gives (2.4×–4.4× classic's measured at this size, most of it the cost of tracing its
    code per render; the rule itself is the test above, so nothing here depends on the timing);
    every number in the JSON's new key is finite, and the equal-spp keys are as without the flag."""
    skip_without_real_assets()
    from validation import real_assets as R

    argv = ["--quick", "--views", "limb", "--methods", "classic,faithful", "--out", str(tmp_path)]
    report = R.main(argv + ["--equal-time"])
    saved = json.loads((tmp_path / "real_assets_quick.json").read_text())
    assert set(saved) == {"settings", "assets", "cells", "summary", "equal_time"}
    assert "## Equal time" in (tmp_path / "real_assets_quick.md").read_text()
    eq = saved["equal_time"]
    assert eq["reference"] == "classic" and eq["sampler"] == "multijitter"
    (cell,), (equal_spp,) = eq["cells"], saved["cells"]
    assert "equal_time" not in equal_spp
    spp = equal_spp["spp"]
    assert cell["spp"] == spp == 4
    ms = cell["methods"]
    assert set(ms) == {"classic", "faithful"}
    for key, m in ms.items():
        for name in ("seconds", "cpu_seconds", "time_ratio", "spp", "spp_taken", "est_time_ratio", "rel_mse",
                     "bias", "near_black", "energy", "floor"):
            assert math.isfinite(m[name]), (key, name)
        assert m["seconds"] > 0 and m["rel_mse"] > 0 and m["floor"] > 0 and m["renders"] >= R.TIME_ROUNDS
        assert m["spp"] == R.equal_time_spp(spp, ms["classic"]["seconds"], m["seconds"])
        assert str(m["spp"]) in cell["floors"]
    ref = ms["classic"]
    assert ref["spp"] == spp and ref["time_ratio"] == 1.0
    assert ref["rel_mse"] == equal_spp["metrics"]["classic"]["rel_mse"]
    assert ref["floor"] == equal_spp["floor"]["rel_mse"]
    assert ms["faithful"]["time_ratio"] == ms["faithful"]["seconds"] / ref["seconds"]
    for m in eq["summary"]["methods"].values():
        assert all(math.isfinite(m[k]) for k in ("rel_mse", "bias", "time_ratio", "spp"))
    assert report["equal_time"]["summary"]["methods"]["faithful"]["cells"] == 1
