"""The package must pick a libLLVM that Dr.Jit 1.5 can use, or fail with one clear line."""

import glob
import importlib.util
import os
import subprocess
import sys

import pytest

LLVM_PY = os.path.join(os.path.dirname(__file__), "..", "src", "mfnormal", "_llvm.py")
OLD_LLVM = sorted(glob.glob("/usr/lib/*/libLLVM-1[456].so*") + glob.glob("/usr/lib/*/libLLVM.so.1[456]*"))


def load_selector():
    """A fresh copy of mfnormal._llvm that does not import the package (nor Dr.Jit)."""
    spec = importlib.util.spec_from_file_location("llvm_selector_under_test", LLVM_PY)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def run_python(code, **env):
    full_env = {k: v for k, v in os.environ.items() if k != "DRJIT_LIBLLVM_PATH"}
    full_env.update(env)
    return subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, env=full_env, timeout=300)


@pytest.mark.parametrize("path, major", [
    ("/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1", 19),
    ("/usr/lib/x86_64-linux-gnu/libLLVM-15.so.1", 15),
    ("/usr/lib/llvm-18/lib/libLLVM.so", 18),
    ("/venv/lib/libLLVM.so.23.1", 23),
    ("/usr/lib/x86_64-linux-gnu/libLLVM-14.0.6.so.1", 14),
])
def test_llvm_major_is_read_from_the_file_name(path, major):
    assert load_selector().llvm_major(path) == major


def test_old_system_llvm_is_never_chosen():
    sel = load_selector()
    assert sel.find_llvm(system=["/usr/lib/x/libLLVM-15.so.1", "/usr/lib/x/libLLVM-14.so"], wheels=[]) is None
    assert sel.find_llvm(system=["/usr/lib/x/libLLVM-15.so.1", "/usr/lib/x/libLLVM.so.19.1"],
                         wheels=[]) == ("/usr/lib/x/libLLVM.so.19.1", [])


def test_a_system_llvm_is_preferred_to_the_wheel_and_the_newest_wins():
    sel = load_selector()
    wheel = ("/venv/lib/libLLVM.so.23.1", ["/venv/lib/x86_64-linux-gnu/libc++.so.1"])
    assert sel.find_llvm(system=["/usr/lib/x/libLLVM.so.18.1", "/usr/lib/x/libLLVM.so.19.1"],
                         wheels=[wheel]) == ("/usr/lib/x/libLLVM.so.19.1", [])
    assert sel.find_llvm(system=["/usr/lib/x/libLLVM-15.so.1"], wheels=[wheel]) == wheel


def test_no_compatible_llvm_fails_with_one_line_naming_the_fix():
    sel = load_selector()
    environ = {}
    with pytest.raises(ImportError) as err:
        sel.ensure_llvm(environ=environ, loaded=[], system=["/usr/lib/x/libLLVM-15.so.1"], wheels=[])
    message = str(err.value)
    assert "\n" not in message
    assert "libllvm19" in message and "karellen-llvm-core" in message
    assert environ == {}


def test_the_chosen_llvm_is_handed_to_drjit_through_the_environment():
    sel = load_selector()
    environ = {}
    path = sel.ensure_llvm(environ=environ, loaded=[], system=["/usr/lib/x/libLLVM.so.19.1"], wheels=[])
    assert path == "/usr/lib/x/libLLVM.so.19.1" and environ == {"DRJIT_LIBLLVM_PATH": path}


def test_an_old_llvm_named_by_the_user_or_already_loaded_is_refused():
    sel = load_selector()
    good = ["/usr/lib/x/libLLVM.so.19.1"]
    with pytest.raises(ImportError, match="DRJIT_LIBLLVM_PATH=.*crashes Dr.Jit"):
        sel.ensure_llvm(environ={"DRJIT_LIBLLVM_PATH": "/usr/lib/x/libLLVM-15.so.1"}, loaded=[],
                        system=good, wheels=[])
    with pytest.raises(ImportError, match="already loaded"):
        sel.ensure_llvm(environ={}, loaded=["/usr/lib/x/libLLVM-15.so.1"], system=good, wheels=[])


def test_import_picks_a_working_llvm_and_runs_a_kernel():
    out = run_python("import mfnormal, os, mitsuba as mi, drjit as dr\n"
                     "mi.set_variant('llvm_ad_rgb')\n"
                     "x = dr.minimum(dr.arange(mi.Float, 8), 3.0)\n"
                     "print(int(x[7]), os.environ['DRJIT_LIBLLVM_PATH'])")
    assert out.returncode == 0, out.stderr
    value, path = out.stdout.split()
    assert value == "3"
    assert load_selector().llvm_major(path) >= 17


def test_user_setting_is_respected():
    sel = load_selector()
    found = sel.find_llvm()
    if found is None:
        pytest.skip("no compatible libLLVM on this machine")
    out = run_python("import mfnormal, os; print(os.environ['DRJIT_LIBLLVM_PATH'])", DRJIT_LIBLLVM_PATH=found[0])
    assert out.returncode == 0 and out.stdout.strip() == found[0]


@pytest.mark.skipif(not OLD_LLVM, reason="no libLLVM 14-16 on this machine")
def test_user_setting_an_old_llvm_gets_a_clear_error_not_the_crash():
    out = run_python("import mfnormal", DRJIT_LIBLLVM_PATH=OLD_LLVM[0])
    assert out.returncode != 0
    last = out.stderr.strip().splitlines()[-1]
    assert "LLVMError" in last and "crashes Dr.Jit" in last and "libllvm19" in last
    assert "Cannot select" not in out.stderr


@pytest.mark.skipif(not OLD_LLVM, reason="no libLLVM 14-16 on this machine")
def test_old_llvm_already_loaded_is_reported():
    out = run_python(f"import ctypes; ctypes.CDLL({OLD_LLVM[0]!r}); import mfnormal")
    assert out.returncode != 0
    assert "already loaded" in out.stderr.strip().splitlines()[-1]
