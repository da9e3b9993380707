"""The random walks' ``max_bounces``, ``rr_depth`` and ``mis_boost_max`` are kernel inputs.

They are exposed to ``mi.traverse``; a new value set there (``params.update()``) is
checked like one given at load, and takes effect without compiling a kernel: two
renders with different values launch the same kernels (Dr.Jit's kernel history: the
same kernel hashes, every launch a cache hit), and the render after the update is the
render of a scene loaded with the new value.
"""

import drjit as dr
import mitsuba as mi
import numpy as np
import pytest

from helpers import bumps_normalmap, floats, point2

SEED, SPP = 5, 4
# (parameter, a value other than the default) for each walk parameter.
CHANGES = [("max_bounces", 1), ("rr_depth", 0), ("mis_boost_max", 1.0)]


def scene_dict(model="nonseparable", tangent_facet="specular", **params):
    """A normal-mapped gold sphere (the BSDF ``mat``) under a constant sky and a sun."""
    T = mi.ScalarTransform4f
    return {
        "type": "scene",
        "integrator": {"type": "path", "max_depth": 4},
        "sensor": {"type": "perspective", "fov": 35,
                   "to_world": T().look_at(origin=[0, 0, 4], target=[0, 0, 0], up=[0, 1, 0]),
                   "sampler": {"type": "independent", "sample_count": SPP},
                   "film": {"type": "hdrfilm", "width": 24, "height": 24, "rfilter": {"type": "box"}}},
        "sky": {"type": "constant", "radiance": {"type": "rgb", "value": 0.6}},
        "sun": {"type": "directional", "direction": [0.5, -0.6, -0.6], "irradiance": {"type": "rgb", "value": 3.0}},
        "mat": {"type": "normalmap_microfacet", "model": model, "tangent_facet": tangent_facet,
                "normalmap": {"type": "bitmap", "bitmap": mi.Bitmap(bumps_normalmap(cells=2, radius=0.49)),
                              "raw": True},
                "bsdf": {"type": "roughconductor", "material": "Au", "alpha": 0.2}, **params},
        "sphere": {"type": "sphere", "bsdf": {"type": "ref", "id": "mat"}},
    }


def values(params):
    """The walk parameters of ``mat`` in ``params``, as Python numbers."""
    return [np.array(params[f"mat.{k}"]).item() for k, _ in CHANGES]


def render_with_history(scene):
    """(image, the hashes of the JIT kernels it launched, whether every launch was a cache hit)."""
    dr.kernel_history_clear()
    img = mi.render(scene, seed=SEED)
    dr.eval(img)
    dr.sync_thread()
    hist = [h for h in dr.kernel_history() if h["type"] == dr.KernelType.JIT]
    return np.array(img), {h["hash"] for h in hist}, all(h["cache_hit"] for h in hist)


@pytest.fixture
def kernel_history():
    flag = dr.flag(dr.JitFlag.KernelHistory)
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    yield
    dr.kernel_history_clear()
    dr.set_flag(dr.JitFlag.KernelHistory, flag)


def test_walk_parameters_are_exposed_to_traverse():
    params = mi.traverse(mi.load_dict(scene_dict()))
    assert {f"mat.{k}" for k, _ in CHANGES} <= set(params.keys())
    assert values(params) == [1024, 3, 64.0]
    for key, _ in CHANGES:
        assert not params.flags(f"mat.{key}") & mi.ParamFlags.Differentiable
    # The models without a walk do not have them.
    for model in ("faithful", "analytic"):
        keys = set(mi.traverse(mi.load_dict(scene_dict(model))).keys())
        assert not any(k.endswith(("max_bounces", "rr_depth", "mis_boost_max")) for k in keys)


@pytest.mark.parametrize("model,tangent_facet", [("nonseparable", "specular"), ("separable", "same")])
@pytest.mark.parametrize("key,value", CHANGES)
def test_a_new_value_runs_the_same_kernels_and_takes_effect(kernel_history, model, tangent_facet, key, value):
    scene = mi.load_dict(scene_dict(model, tangent_facet))
    render_with_history(scene)                 # the first render also evaluates the scene's data
    before, hashes, _ = render_with_history(scene)
    again, hashes_again, hit = render_with_history(scene)
    assert hashes and hashes_again == hashes and hit          # the check itself: a warm render
    params = mi.traverse(scene)
    params[f"mat.{key}"] = value
    params.update()
    after, hashes_after, hit_after = render_with_history(scene)
    assert hashes_after <= hashes, "the new value compiled new kernels"
    assert hit_after
    # The new value is in effect: the render of a scene loaded with it.
    loaded = np.array(mi.render(mi.load_dict(scene_dict(model, tangent_facet, **{key: value})), seed=SEED))
    np.testing.assert_array_equal(after, loaded)
    np.testing.assert_array_equal(before, again)
    assert not np.array_equal(after, before)
    if key == "max_bounces":
        # One facet bounce loses the energy of the longer walks (gold, tilts to 78°).
        assert after.mean() < 0.97 * before.mean()


@pytest.mark.parametrize("key,bad,message", [
    ("max_bounces", 0, "max_bounces must be between 1"),
    ("rr_depth", -1, "rr_depth must be between 0"),
    ("mis_boost_max", 0.5, "mis_boost_max must be a finite number >= 1"),
    ("mis_boost_max", float("nan"), "mis_boost_max must be a finite number >= 1"),
    ("mis_boost_max", float("inf"), "mis_boost_max must be a finite number >= 1"),
])
def test_an_update_out_of_range_is_refused_in_one_line(key, bad, message):
    scene = mi.load_dict(scene_dict())
    before = np.array(mi.render(scene, seed=SEED))
    params = mi.traverse(scene)
    params[f"mat.{key}"] = bad
    with pytest.raises(ValueError, match=message) as err:
        params.update()
    text = str(err.value)
    # Release the exception now: its traceback holds this frame (a cycle) and the BSDF, and a scene
    # freed by Python's cyclic GC in the middle of a later render crashes Dr.Jit 1.5 (seen with the
    # strength update's refusal on 22fac64 too).
    del err
    assert "\n" not in text
    # The values before the update stay, and so does the image.
    assert values(mi.traverse(scene)) == [1024, 3, 64.0]
    np.testing.assert_array_equal(np.array(mi.render(scene, seed=SEED)), before)


def test_a_max_bounces_update_caps_the_walk():
    """The walk loops read the updated cap: white Lambertian facets tilted 80° (long walks), the
    sampling walk's longest bounce count over 4096 queries is above 8, and exactly 8 after an
    update to 8 (the walks that reach the cap stop there)."""
    from helpers import WHITE, encode, make_bsdf, make_si, random_hemisphere, sph
    from mfnormal.models import walk

    rng = np.random.default_rng(3)
    bsdf = make_bsdf(WHITE, encode(sph([80.0])), "nonseparable", "specular")
    si = make_si(random_hemisphere(rng, 4096, z_min=0.05))
    u = rng.random((4096, 3)).astype(np.float32)

    def longest():
        sp = bsdf.shading_point(mi.BSDFContext(), si)
        w = walk.sample_walk(sp, bsdf.model.params, floats(u[:, 0]), point2(u[:, 1:]), True)
        return int(np.array(w.depth).max())

    assert longest() > 8
    params = mi.traverse(bsdf)
    params["max_bounces"] = 8
    params.update()
    assert longest() == 8
