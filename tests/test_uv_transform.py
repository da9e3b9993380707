"""The normal map's uv transform as a kernel input (``NormalMap.hoist_uv_transform``, ``map_rgb``).

Mitsuba's bitmap bakes its ``to_uv`` into traced code as constants, so plugins whose maps
differed only in their transforms traced different code and Dr.Jit compiled the whole model
once per plugin into a kernel. The plugin now applies the transform itself from opaque values
and traces the texture with the identity: the same lookups bit for bit, and such plugins share
one compiled callable.
"""

import mfnormal  # noqa: F401  (first: selects a working libLLVM)

import drjit as dr
import mitsuba as mi
from variant import VARIANT  # noqa: E402  (MFNORMAL_VARIANT, tests/variant.py)
import numpy as np
import pytest

mi.set_variant(VARIANT)
mfnormal.register()

from helpers import floats, tensor  # noqa: E402

JIT = dr.is_jit_v(mi.Float)
pytestmark = pytest.mark.skipif(not JIT, reason="the transform is hoisted in JIT variants only")

# Scale, rotation and translation: no entry is 0 or 1, so no operation folds away.
TRANSFORM = mi.ScalarTransform4f().translate([0.37, -0.11, 0]).rotate([0, 0, 1], 33.0).scale([8.3, -5.7, 1])
OTHER = mi.ScalarTransform4f().scale([3.0, 2.0, 1])


def texels(seed=1, shape=(37, 53)):
    return tensor(np.random.default_rng(seed).random((*shape, 3)))


def bsdf(to_uv, filter_type="bilinear", model="analytic", data=None):
    return mi.load_dict({"type": "normalmap_microfacet", "model": model, "bsdf": {"type": "diffuse"},
                         "normalmap": {"type": "bitmap", "data": texels() if data is None else data, "raw": True,
                                       "filter_type": filter_type, "to_uv": to_uv}})


def queries(n=1 << 16, seed=2):
    rng = np.random.default_rng(seed)
    si = dr.zeros(mi.SurfaceInteraction3f, n)
    si.uv = mi.Point2f(floats(rng.random(n).astype(np.float32) * 3 - 1),
                       floats(rng.random(n).astype(np.float32) * 3 - 1))
    return si


def bits(x):
    return np.array(x, dtype=np.float32).view(np.uint32)


@pytest.mark.parametrize("filter_type", ["nearest", "bilinear"])
def test_map_lookup_is_the_textures_own_bit_for_bit(filter_type):
    """map_rgb (the hoisted transform) against the bitmap's own eval_3 with its to_uv, at uvs over
    three periods: equal bit for bit; the texture's to_uv is left as it was."""
    b = bsdf(TRANSFORM, filter_type)
    assert b.source.uv is not None, "a non-identity to_uv is hoisted"
    si = queries()
    ref, got = b.normalmap.eval_3(si), b.source.map_rgb(si)
    assert np.array_equal(bits(ref), bits(got))
    kept = np.array(mi.traverse(b.normalmap)["to_uv"].matrix)
    fresh = mi.load_dict({"type": "bitmap", "data": texels(), "raw": True, "to_uv": TRANSFORM})
    assert np.array_equal(kept, np.array(mi.traverse(fresh)["to_uv"].matrix)), "the texture keeps its to_uv"


def test_identity_transform_is_not_hoisted():
    assert bsdf(mi.ScalarTransform4f()).source.uv is None


def test_a_new_to_uv_from_traverse_takes_effect():
    """Updating ``normalmap.to_uv`` through mi.traverse re-hoists it: the lookups follow the new
    transform (the texture's own eval_3 with it, bit for bit) and differ from the old ones."""
    b = bsdf(TRANSFORM)
    si = queries()
    before = np.array(b.source.map_rgb(si))
    params = mi.traverse(b)
    params["normalmap.to_uv"] = mi.ScalarAffineTransform3f(mi.ScalarMatrix3f(np.diag([3.0, 2.0, 1.0])))
    params.update()
    after = b.source.map_rgb(si)
    assert np.array_equal(bits(after), bits(b.normalmap.eval_3(si)))
    assert not np.array_equal(bits(after), bits(before))


def test_a_to_uv_set_on_the_texture_alone_is_honoured_and_kept():
    """A to_uv set on the texture itself (this plugin not told: e.g. a texture two plugins share,
    updated through one of them) is looked up as the texture has it, and stays set."""
    b = bsdf(TRANSFORM)
    si = queries()
    params = mi.traverse(b.normalmap)
    params["to_uv"] = mi.ScalarAffineTransform3f(mi.ScalarMatrix3f(np.diag([3.0, 2.0, 1.0])))
    params.update()
    got = b.source.map_rgb(si)
    assert np.array_equal(np.array(mi.traverse(b.normalmap)["to_uv"].matrix), np.diag([3.0, 2.0, 1.0]))
    assert np.array_equal(bits(got), bits(b.normalmap.eval_3(si)))


def scene(transforms, model):
    """Two rectangles side by side, each with its own plugin over its own map, seen from above."""
    shapes = {}
    for k, t in enumerate(transforms):
        shapes[f"quad{k}"] = {"type": "rectangle", "bsdf": bsdf(t, model=model, data=texels(seed=10 + k)),
                              "to_world": mi.ScalarTransform4f().translate([2.2 * k - 1.1, 0, 0])}
    return mi.load_dict({
        "type": "scene", "integrator": {"type": "path", "max_depth": 3},
        "sensor": {"type": "perspective", "fov": 60,
                   "to_world": mi.ScalarTransform4f().look_at(origin=[0, -1, 3], target=[0, 0, 0], up=[0, 1, 0]),
                   "film": {"type": "hdrfilm", "width": 16, "height": 8, "pixel_format": "rgb"},
                   "sampler": {"type": "independent", "sample_count": 1}},
        "light": {"type": "constant"}, **shapes})


def largest_kernel(sc):
    dr.set_flag(dr.JitFlag.KernelHistory, True)
    try:
        dr.kernel_history_clear()
        dr.eval(mi.render(sc, spp=1, seed=1))
        return max(h.get("operation_count") or 0 for h in dr.kernel_history())
    finally:
        dr.set_flag(dr.JitFlag.KernelHistory, False)


@pytest.mark.parametrize("model", ["faithful", "nonseparable"])
def test_plugins_that_differ_only_in_their_maps_transforms_share_one_callable(model):
    """Two plugins over different maps with different to_uv trace the same code as two with the
    same to_uv: the render's largest kernel has as many operations (Dr.Jit merges the instances'
    identical callables). Before, each transform's constants made its own copy of the model
    (measured on the benchmark's demo: 11601 against 7179 operations for the non-separable walk)."""
    same = largest_kernel(scene([TRANSFORM, TRANSFORM], model))
    different = largest_kernel(scene([TRANSFORM, OTHER], model))
    assert different == same, (different, same)
