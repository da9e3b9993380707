"""The package as a user installs it: a wheel built from this checkout, installed into a fresh
virtual environment outside it, runs the command line from a folder outside it.

The wheel is built offline (``pip wheel --no-build-isolation --no-index``, setuptools from the
test's environment) from a copy of the checkout's files (tracked and untracked, not ignored), so
that the build writes nothing into the checkout. The fresh environment sees this environment's
third-party packages (Mitsuba, Dr.Jit, NumPy, ...) through a ``.pth`` file that names their folder
(a folder named in a ``.pth`` file is added to ``sys.path`` but its own ``.pth`` files are not
read, so this environment's editable install of the checkout is not); its ``mfnormal`` is the
wheel's, which a test asserts. The commands run with the installed console script ``mfnormal``,
no ``PYTHONPATH``, and an audit hook (a ``.pth`` file of the fresh environment) that records every
file or folder Python opens, tries to open or lists inside the checkout (other than this
environment, which may live there as ``.venv``) or inside the fresh environment outside its
site-packages and scripts (where a path relative to the repository lands from the installed
package): that record must be empty. So the tests fail if the wheel lacks package data (the
bundled scenes ``*.xml``), or if the package reads a path relative to the repository.

``mfnormal compare demo --quick`` runs two methods, the nested BSDF alone and the default model:
the bundled scene, its generated assets and the report are the same for any method list, and
``tests/test_report.py`` renders every method of the quick comparison from the checkout.
MFNORMAL_SLOW=1 also runs every method from the wheel.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import sys
import sysconfig
import textwrap
import zipfile
from pathlib import Path

import pytest

import mfnormal
from gltf_models import base_document, write_gltf

ROOT = Path(__file__).resolve().parents[1]
TIMEOUT = 600
SITE = "import sysconfig; print(sysconfig.get_paths()['purelib'])"

# Installed in the fresh environment: every path Python opens (or tries to) or lists inside
# MFNORMAL_WHEEL_WATCHED (the checkout; the fresh environment, where a path relative to the
# repository lands from the installed package) but outside MFNORMAL_WHEEL_ALLOWED (the test
# environment, the fresh one's site-packages and scripts) is written to MFNORMAL_WHEEL_LOG. The
# event comes before the open, so a failed attempt is recorded too. The log's descriptor is opened
# before the hook is added.
AUDIT = textwrap.dedent("""
    import os, sys
    _log = os.environ.get("MFNORMAL_WHEEL_LOG")
    if _log:
        _fd = os.open(_log, os.O_WRONLY | os.O_APPEND | os.O_CREAT, 0o644)
        _inside = tuple(p.rstrip(os.sep) + os.sep for p in os.environ["MFNORMAL_WHEEL_WATCHED"].split(os.pathsep))
        _allowed = tuple(p.rstrip(os.sep) + os.sep for p in os.environ["MFNORMAL_WHEEL_ALLOWED"].split(os.pathsep))

        def _hook(event, args):
            if event not in ("open", "os.listdir", "os.scandir", "glob.glob") or not args:
                return
            path = args[0]
            if isinstance(path, bytes):
                path = os.fsdecode(path)
            if not isinstance(path, str):
                return
            path = os.path.abspath(path) + os.sep
            if path.startswith(_inside) and not path.startswith(_allowed):
                os.write(_fd, f"{event} {path[:-1]}\\n".encode())

        sys.addaudithook(_hook)
""")


def _checkout_files() -> list[str]:
    out = subprocess.run(["git", "ls-files", "--cached", "--others", "--exclude-standard", "-z"],
                         cwd=ROOT, capture_output=True, check=True)
    return [name for name in out.stdout.decode().split("\0") if name and (ROOT / name).is_file()]


def _build_wheel(base: Path) -> Path:
    source = base / "source"
    for name in _checkout_files():
        (source / name).parent.mkdir(parents=True, exist_ok=True)
        shutil.copy2(ROOT / name, source / name)
    dist = base / "dist"
    proc = subprocess.run([sys.executable, "-m", "pip", "wheel", "--no-deps", "--no-build-isolation",
                           "--no-index", "--disable-pip-version-check", "-q", "-w", str(dist), str(source)],
                          cwd=base, capture_output=True, text=True, timeout=TIMEOUT, env=_clean_env())
    assert proc.returncode == 0, proc.stdout + proc.stderr
    (wheel,) = dist.glob("mfnormal-*.whl")
    return wheel


def _clean_env(**extra) -> dict:
    env = {k: v for k, v in os.environ.items() if k not in ("PYTHONPATH", "PYTHONHOME", "PYTHONSTARTUP")}
    env["PYTHONNOUSERSITE"] = "1"
    env.update(extra)
    return env


def _link_llvm_wheel(venv: Path) -> None:
    """A libLLVM that came as a wheel (karellen-llvm-core) lives in this environment's ``lib/``,
    where mfnormal looks under ``sys.prefix``: link it (and its runtime) into the fresh one."""
    if not mfnormal.LLVM_PATH.startswith(sys.prefix + os.sep):
        return
    for path in Path(sys.prefix, "lib").iterdir():
        if path.name.startswith("libLLVM") or path.name.endswith("-linux-gnu"):
            link = venv / "lib" / path.name
            if not link.exists():
                link.symlink_to(path)


def _fresh_venv(base: Path, wheel: Path) -> Path:
    venv = base / "venv"
    subprocess.run([sys.executable, "-m", "venv", "--without-pip", str(venv)], check=True, timeout=TIMEOUT)
    python = venv / "bin" / "python"
    site = Path(subprocess.run([str(python), "-c", SITE], capture_output=True, text=True, check=True).stdout.strip())
    (site / "test_environment.pth").write_text(sysconfig.get_paths()["purelib"] + "\n")
    (site / "_mfnormal_wheel_audit.py").write_text(AUDIT)
    (site / "_mfnormal_wheel_audit.pth").write_text("import _mfnormal_wheel_audit\n")
    _link_llvm_wheel(venv)
    proc = subprocess.run([sys.executable, "-m", "pip", "--python", str(python), "install", "--no-deps",
                           "--no-index", "--disable-pip-version-check", "-q", str(wheel)],
                          capture_output=True, text=True, timeout=TIMEOUT, env=_clean_env())
    assert proc.returncode == 0, proc.stdout + proc.stderr
    return venv


class Installed:
    """The fresh environment with the wheel installed, and a working folder outside the checkout."""

    def __init__(self, base: Path):
        self.wheel = _build_wheel(base)
        self.venv = _fresh_venv(base, self.wheel)
        self.work = base / "work"
        self.work.mkdir()
        self.log = base / "outside_reads.log"
        site = Path(subprocess.run([str(self.venv / "bin" / "python"), "-c", SITE], capture_output=True,
                                   text=True, check=True).stdout.strip())
        watched = {str(ROOT), os.path.realpath(ROOT), str(self.venv), os.path.realpath(self.venv)}
        allowed = {sys.prefix, os.path.realpath(sys.prefix), str(site), os.path.realpath(site),
                   str(self.venv / "bin"), os.path.realpath(self.venv / "bin")}
        self.env = _clean_env(MFNORMAL_WHEEL_LOG=str(self.log),
                              MFNORMAL_WHEEL_WATCHED=os.pathsep.join(sorted(watched)),
                              MFNORMAL_WHEEL_ALLOWED=os.pathsep.join(sorted(allowed)))

    def run(self, program: str, *args) -> subprocess.CompletedProcess:
        proc = subprocess.run([str(self.venv / "bin" / program), *map(str, args)], cwd=self.work,
                              env=self.env, capture_output=True, text=True, timeout=TIMEOUT)
        assert proc.returncode == 0, proc.stdout + proc.stderr
        return proc

    def outside_reads(self) -> list[str]:
        return self.log.read_text().splitlines() if self.log.exists() else []


@pytest.fixture(scope="module")
def installed(tmp_path_factory):
    base = tmp_path_factory.mktemp("wheel")
    assert not base.resolve().is_relative_to(ROOT.resolve())
    return Installed(base)


def test_the_wheel_holds_the_package_and_its_bundled_scenes(installed):
    names = zipfile.ZipFile(installed.wheel).namelist()
    scenes = sorted(p.name for p in (ROOT / "src" / "mfnormal" / "scenes").glob("*.xml"))
    assert scenes and all(f"mfnormal/scenes/{name}" in names for name in scenes), names
    assert "mfnormal/py.typed" in names, names      # PEP 561: type checkers read its hints
    assert not any(name.startswith(("validation/", "tests/", "benchmarks/")) for name in names), names


def test_the_installed_package_is_the_wheels(installed):
    proc = installed.run("python", "-c", "import mfnormal; print(mfnormal.__file__)")
    path = Path(proc.stdout.strip()).resolve()
    assert path.is_relative_to(installed.venv.resolve()), path
    assert installed.outside_reads() == []


def test_the_installed_command_tells_its_version(installed):
    proc = installed.run("mfnormal", "--version")
    assert proc.stdout.startswith(f"mfnormal {mfnormal.__version__} (Mitsuba "), proc.stdout
    assert installed.outside_reads() == []


def test_the_installed_demo_renders(installed):
    installed.run("mfnormal", "demo", "--spp", "2", "--resolution", "64x36", "-o", "demo/demo.png")
    for name in ("demo.exr", "demo.png"):
        assert (installed.work / "demo" / name).stat().st_size > 0, name
    assert installed.outside_reads() == []


@pytest.mark.parametrize("methods", [
    ["--methods", "flat,faithful"],
    pytest.param([], marks=pytest.mark.slow),
], ids=["two_methods", "every_method"])
def test_the_installed_compare_writes_its_report(installed, methods):
    out = installed.work / ("compare_" + ("_".join(methods[1:]) or "all"))
    installed.run("mfnormal", "compare", "demo", "--quick", *methods, "-o", out)
    report = (out / "report.html").read_text(encoding="utf-8")
    assert "relMSE" in report and "faithful" in report
    assert (out / "demo" / "faithful.exr").stat().st_size > 0
    assert installed.outside_reads() == []


def test_the_installed_package_renders_a_gltf_model(installed):
    doc, blobs = base_document()
    model = write_gltf(installed.work / "model", doc, blobs)
    installed.run("mfnormal", "render", model, "-o", "model_out/quad", "--spp", "2",
                  "-D", "width=24", "-D", "height=16")
    for name in ("quad.exr", "quad.png"):
        assert (installed.work / "model_out" / name).stat().st_size > 0, name
    assert installed.outside_reads() == []
