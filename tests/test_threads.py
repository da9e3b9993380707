"""The commands render with at least two Dr.Jit threads: with one (a one-core machine's default:
no pool thread, the caller alone) Mitsuba's OpenEXR reader waits for ever for a task no thread
runs. Replayed in a child process set to one thread, which must then read an EXR through the
commands' variant setup within the time limit (it hangs past it without the floor)."""

import subprocess
import sys

CODE = """
import mfnormal, drjit as dr, mitsuba as mi, numpy as np, sys
mi.set_variant("llvm_ad_rgb")
mi.Bitmap(np.ones((4, 4, 3), np.float32)).write(sys.argv[1])
dr.set_thread_count(1)
from mfnormal.render.passes import MIN_THREADS, use_variant
use_variant("llvm_ad_rgb", RuntimeError, "unavailable", "cannot")
assert dr.thread_count() >= MIN_THREADS >= 2, dr.thread_count()
print(np.array(mi.Bitmap(sys.argv[1])).mean())
"""


def test_the_commands_read_an_exr_with_one_thread_set_before(tmp_path):
    proc = subprocess.run([sys.executable, "-c", CODE, str(tmp_path / "one.exr")], capture_output=True,
                          text=True, timeout=120)
    assert proc.returncode == 0, proc.stderr
    assert float(proc.stdout.split()[-1]) == 1.0


def test_a_render_runs_with_the_collector_off_and_leaves_it_as_it_was():
    """mfnormal.render.passes.collector_paused (docs/development.md, "Worker crashes"): while the
    commands render (``passes._render``), Python's cyclic collector is off, as a texture that the
    render traces sees; after, it is as it was; renders that overlap (threads) turn it back on only
    when the last one ends."""
    import gc

    import mitsuba as mi
    import numpy as np

    from mfnormal.render import passes

    seen = []

    class Probe(mi.Texture):
        def __init__(self, props):
            mi.Texture.__init__(self, props)

        def eval(self, si, active=True):
            seen.append(gc.isenabled())
            return mi.Color3f(0.5)

        def mean(self):
            return 0.5

        def traverse(self, callback):
            pass

    mi.register_texture("collector_probe", lambda props: Probe(props))
    scene = mi.load_dict({"type": "scene", "integrator": {"type": "direct"},
                          "sensor": {"type": "orthographic", "film": {"type": "hdrfilm", "width": 4, "height": 4},
                                     "to_world": mi.ScalarTransform4f().look_at(origin=[0, 0, 2], target=[0, 0, 0],
                                                                                up=[0, 1, 0])},
                          "plane": {"type": "rectangle",
                                    "bsdf": {"type": "diffuse", "reflectance": {"type": "collector_probe"}}},
                          "light": {"type": "constant"}})
    was = gc.isenabled()
    try:
        gc.enable()
        image = passes._render(scene, 1, 0, killable=False)
        assert seen and not any(seen), seen
        assert gc.isenabled() and np.isfinite(image).all() and image.mean() > 0
        first, second = passes.collector_paused(), passes.collector_paused()
        first.__enter__()
        second.__enter__()
        first.__exit__(None, None, None)
        assert not gc.isenabled()
        second.__exit__(None, None, None)
        assert gc.isenabled()
        gc.disable()
        with passes.collector_paused():
            pass
        assert not gc.isenabled()
    finally:
        (gc.enable if was else gc.disable)()
