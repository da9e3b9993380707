"""Pick a libLLVM that Dr.Jit 1.5 can use, before Dr.Jit first loads.

Dr.Jit's LLVM backend aborts the whole process ("LLVM ERROR: Cannot select:
fminimum") with libLLVM 14, 15 and 16, which is what Debian 12 ships by
default. This module finds a compatible libLLVM (major version >= 17) and points
``DRJIT_LIBLLVM_PATH`` at it, so that users never see that crash.

Search order:

1. ``DRJIT_LIBLLVM_PATH`` if the user set it (respected as is);
2. system libraries: ``libLLVM.so.<N>*``, ``libLLVM-<N>.so*`` and
   ``/usr/lib/llvm-<N>/lib`` for N >= 17 (Debian's ``libllvm19``, ...);
3. the ``karellen-llvm-core`` wheel (libLLVM 23) inside the active Python
   prefix, whose bundled libc++/libc++abi/libunwind are preloaded first.

It must not import drjit or mitsuba.
"""

from __future__ import annotations

import ctypes
import glob
import os
import re
import sys

MIN_MAJOR = 17

FIX = ("install a libLLVM >= 17: 'apt-get install libllvm19' (Debian/Ubuntu), or "
       "'pip install karellen-llvm-core', or set DRJIT_LIBLLVM_PATH to such a libLLVM.so")


class LLVMError(ImportError):
    """No usable libLLVM: the message names the fix."""


def llvm_major(path: str) -> int | None:
    """Major version encoded in a libLLVM file name, e.g. libLLVM.so.19.1 -> 19."""
    name = os.path.basename(os.path.realpath(path)) if os.path.exists(path) else os.path.basename(path)
    for candidate in (name, os.path.basename(path)):
        m = (re.search(r"libLLVM[-.]so\.(\d+)", candidate)
             or re.search(r"libLLVM-(\d+)", candidate)
             or re.search(r"llvm-(\d+)", path))
        if m:
            return int(m.group(1))
    return None


def _system_candidates() -> list[str]:
    patterns = [
        "/usr/lib/*/libLLVM.so.*", "/usr/lib/*/libLLVM-*.so*", "/usr/lib/llvm-*/lib/libLLVM*.so*",
        "/usr/lib64/libLLVM*.so*", "/usr/lib/libLLVM*.so*", "/usr/local/lib/libLLVM*.so*",
        "/opt/homebrew/opt/llvm/lib/libLLVM.dylib", "/usr/local/opt/llvm/lib/libLLVM.dylib",
    ]
    found = []
    for pattern in patterns:
        found += [p for p in glob.glob(pattern) if os.path.isfile(p)]
    return found


def _wheel_candidates() -> list[tuple[str, list[str]]]:
    """libLLVM from the karellen-llvm-core wheel, with the runtime it needs preloaded."""
    out = []
    for prefix in dict.fromkeys([sys.prefix, sys.base_prefix, os.path.dirname(os.path.dirname(sys.executable))]):
        for lib in glob.glob(os.path.join(prefix, "lib", "libLLVM.so.*")):
            runtime_dir = glob.glob(os.path.join(prefix, "lib", "*-linux-gnu"))
            preload = []
            for d in runtime_dir:
                for stem in ("libunwind.so", "libc++abi.so", "libc++.so"):
                    hits = sorted(glob.glob(os.path.join(d, stem + ".*")), key=len)
                    preload += hits[:1]
            out.append((lib, preload))
    return out


def _loaded_llvm() -> list[str]:
    """libLLVM files already mapped into this process (Linux only)."""
    try:
        with open("/proc/self/maps") as f:
            return sorted({line.split()[-1] for line in f if "libLLVM" in line and "/" in line})
    except OSError:
        return []


def find_llvm(system: list[str] | None = None,
              wheels: list[tuple[str, list[str]]] | None = None) -> tuple[str, list[str]] | None:
    """Best compatible libLLVM as (path, libraries to preload), or None.

    ``system`` (library paths) and ``wheels`` ((path, preload) pairs) are the candidates;
    by default this machine's (:func:`_system_candidates`, :func:`_wheel_candidates`).
    """
    system = _system_candidates() if system is None else system
    wheels = _wheel_candidates() if wheels is None else wheels
    best = None
    for path in system:
        major = llvm_major(path)
        if major is not None and major >= MIN_MAJOR and (best is None or major > best[0]):
            best = (major, path, [])
    for path, preload in wheels:
        major = llvm_major(path)
        if major is not None and major >= MIN_MAJOR and best is None:
            best = (major, path, preload)
    return None if best is None else (best[1], best[2])


def ensure_llvm(environ: dict[str, str] | None = None, loaded: list[str] | None = None, system: list[str] | None = None,
                wheels: list[tuple[str, list[str]]] | None = None) -> str:
    """Make sure Dr.Jit will load a compatible libLLVM; return its path.

    Raises LLVMError (a one-line message naming the fix) when there is none, or
    when Dr.Jit already loaded an incompatible one in this process.

    ``environ`` (read for, and given, ``DRJIT_LIBLLVM_PATH``), ``loaded`` (the libLLVM files
    this process has mapped) and the candidates ``system`` and ``wheels`` (:func:`find_llvm`)
    are this process's and this machine's by default.
    """
    environ = os.environ if environ is None else environ
    loaded = _loaded_llvm() if loaded is None else loaded
    for lib in loaded:
        major = llvm_major(lib)
        if major is not None and major < MIN_MAJOR:
            raise LLVMError(f"Dr.Jit already loaded {lib} (LLVM {major}), which crashes Dr.Jit 1.5; "
                            f"import mfnormal before drjit/mitsuba, or {FIX}")
    user = environ.get("DRJIT_LIBLLVM_PATH")
    if user:
        major = llvm_major(user)
        if major is not None and major < MIN_MAJOR:
            raise LLVMError(f"DRJIT_LIBLLVM_PATH={user} is LLVM {major}, which crashes Dr.Jit 1.5; {FIX}")
        return user
    if "drjit" in sys.modules and loaded:
        return loaded[0]
    found = find_llvm(system, wheels)
    if found is None:
        raise LLVMError(f"mfnormal: no compatible libLLVM found (Dr.Jit 1.5 crashes with LLVM <= 16); {FIX}")
    path, preload = found
    for lib in preload:
        ctypes.CDLL(lib, mode=ctypes.RTLD_GLOBAL)
    environ["DRJIT_LIBLLVM_PATH"] = path
    return path


if __name__ == "__main__":  # used by scripts/setup.sh: exit 0 if a compatible libLLVM exists
    found = find_llvm()
    print(found[0] if found else "none")
    sys.exit(0 if found else 1)
