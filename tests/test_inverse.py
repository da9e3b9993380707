"""Inverse rendering from a flat map (mfnormal.inverse), a small version of the issue-16 setup.

A plane under a 16² map (roughplastic α 0.2), 3 suns, Adam from a flat map, the target
rendered by the same method with the true map; res 16², 4 spp, 20 iterations (~25 s CPU on 2
cores). The default model must reach the built-in's mean texel error + 1°; analytic must
make a nonzero first step and reduce the error. (The full runs, every model and the
true-geometry target: validation/inverse_rendering.py.)
"""

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import mitsuba as mi
from variant import VARIANT  # noqa: E402  (MFNORMAL_VARIANT, tests/variant.py)
import pytest

mi.set_variant(VARIANT)
mfnormal.register()

from mfnormal import inverse as I  # noqa: E402

SETUP = dict(res=16, spp=4, target_spp=64, iterations=20, lr=0.03)


@pytest.fixture(scope="module")
def runs():
    setup = I.Setup(**SETUP)
    return {m: I.optimise(setup, m, I.same_method_targets(setup, m)) for m in ("builtin", "faithful", "analytic")}


def test_default_model_recovers_the_map_as_well_as_the_builtin(runs):
    b, f = runs["builtin"], runs["faithful"]
    print(f"builtin {b.error[0]:.2f}° → {b.error[-1]:.2f}°, faithful {f.error[0]:.2f}° → {f.error[-1]:.2f}°")
    assert f.first_step > 0.5 * SETUP["lr"]
    assert f.error[-1] <= b.error[-1] + 1.0
    assert f.error[-1] < 0.5 * f.error[0]


def test_analytic_moves_from_the_flat_start_and_improves(runs):
    a = runs["analytic"]
    print(f"analytic {a.error[0]:.2f}° → {a.error[-1]:.2f}°, first step {a.first_step:.3g}")
    assert a.first_step > 0.5 * SETUP["lr"]
    assert a.error[-1] < a.error[0] - 1.0
    assert a.loss[-1] < 0.5 * a.loss[0]
