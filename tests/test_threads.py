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
