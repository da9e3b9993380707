"""The package as a user meets it first: the plugins follow ``mi.set_variant`` without a call of
``mfnormal.register()``, and the README's Python quick start runs as written.

Each check runs in a process of its own: the Mitsuba variant is global to a process."""

import os
import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
ENV = dict(os.environ, PYTHONPATH=str(ROOT / "src"))      # this checkout's package


def _python(code: str, cwd=ROOT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, env=ENV, capture_output=True, text=True,
                          timeout=300)


def test_a_variant_set_after_the_import_has_the_plugins_without_register():
    code = ("import mfnormal, mitsuba as mi\n"
            "for variant in ('llvm_ad_mono', 'llvm_ad_rgb'):\n"
            "    mi.set_variant(variant)\n"
            "    mi.load_dict({'type': 'normalmap_microfacet', 'macro_normal': 'geometric',\n"
            "                  'bsdf': {'type': 'diffuse'}})\n"
            "    mi.load_dict({'type': 'mfnormal_path'})\n"
            "print('loaded')\n")
    proc = _python(code)
    assert proc.returncode == 0 and "loaded" in proc.stdout, proc.stdout + proc.stderr


def python_blocks(path: Path) -> list[str]:
    """The ```python blocks of a markdown file."""
    return re.findall(r"^```python\n(.*?)^```", path.read_text(encoding="utf-8"), re.S | re.M)


def test_the_quick_start_snippets_run_as_written():
    """The first Python block of the README and of the documentation's front page, run from the
    repository's root (where a user who followed the install is)."""
    for page in (ROOT / "README.md", ROOT / "docs" / "index.md"):
        snippet = python_blocks(page)[0]
        proc = _python(snippet + "\nprint(type(bsdf).__name__)\n")
        assert proc.returncode == 0, f"{page.name}'s quick start fails:\n{proc.stderr}"
        assert "NormalMapMicrofacet" in proc.stdout, proc.stdout + proc.stderr


TROUBLESHOOTING = ROOT / "docs" / "troubleshooting.md"

WRONG_MODEL = """
import mfnormal, mitsuba as mi
mi.set_variant("llvm_ad_rgb")
try:
    mi.load_dict({"type": "normalmap_microfacet", "model": "faithfull",
                  "normalmap": {"type": "bitmap", "filename": "examples/normals.png", "raw": True},
                  "bsdf": {"type": "roughconductor", "alpha": 0.2}})
except RuntimeError as exc:
    lines = str(exc).strip().splitlines()
    print(lines[0]); print(lines[-1])
"""


def test_the_troubleshooting_page_shows_the_errors_as_they_are():
    """docs/troubleshooting.md quotes what a user sees: Mitsuba's wrapper line and our message
    last for a wrong parameter through Python, and Mitsuba's "not found" for a process that never
    imported mfnormal. Each quoted line is produced here again (a Mitsuba that words them
    otherwise fails this test, so the page is updated with it)."""
    page = TROUBLESHOOTING.read_text(encoding="utf-8")
    first, last = _python(WRONG_MODEL).stdout.strip().splitlines()
    assert last.startswith("ValueError: normalmap_microfacet: unknown model 'faithfull'") and last in page
    assert "RuntimeError: " + first in page, first
    code = ("import mitsuba as mi\nmi.set_variant('llvm_ad_rgb')\n"
            "try:\n    mi.load_dict({'type': 'normalmap_microfacet'})\n"
            "except RuntimeError as exc:\n    print(str(exc).strip().splitlines()[-1])\n")
    not_found = _python(code).stdout.strip()
    assert not_found.endswith('Plugin "normalmap_microfacet" not found!'), not_found
    assert '[PluginManager] Plugin "normalmap_microfacet" not found!' in page


def test_the_command_line_prints_the_same_message_as_one_line(tmp_path):
    scene = tmp_path / "scene.xml"
    scene.write_text('<scene version="3.0.0"><integrator type="path"/><shape type="sphere">'
                     '<bsdf type="normalmap_microfacet"><string name="model" value="faithfull"/>'
                     f'<string name="normalmap" value="{ROOT / "examples" / "normals.png"}"/>'
                     '<bsdf type="roughconductor"/></bsdf></shape></scene>')
    proc = subprocess.run([sys.executable, "-m", "mfnormal", "render", "scene.xml", "-o", "out/scene"],
                          cwd=tmp_path, env=ENV, capture_output=True, text=True, timeout=300)
    assert proc.returncode == 2 and not (tmp_path / "out").exists()
    (line,) = proc.stderr.strip().splitlines()
    assert line in TROUBLESHOOTING.read_text(encoding="utf-8"), line


# Every harness with an --out option: run as a user runs it (python -m MODULE, from the repository's
# root), with no arguments, up to the parsing of its command line.
HARNESSES = ("validation.run", "validation.true_geometry", "validation.real_assets", "validation.real_assets_split",
             "validation.dielectric", "validation.furnace_glass", "validation.normal_sources",
             "validation.inverse_rendering", "validation.inverse_water", "benchmarks.run", "benchmarks.backward",
             "benchmarks.cost_floor", "benchmarks.experiments", "benchmarks.normal_sources", "benchmarks.lean")

DEFAULT_OUTS = """
import argparse, runpy, sys
from pathlib import Path
parse = argparse.ArgumentParser.parse_args

class Parsed(BaseException):
    pass

def parse_only(self, args=None, namespace=None):
    raise Parsed(getattr(parse(self, [], namespace), "out", None))

argparse.ArgumentParser.parse_args = parse_only
for module in sys.argv[1:]:
    sys.argv = [module]
    try:
        runpy.run_module(module, run_name="__main__", alter_sys=True)
    except Parsed as parsed:
        print(module, Path(str(parsed.args[0])).resolve())
    else:
        print(module, "no --out parsed")
"""


def test_harnesses_write_outside_the_tracked_tree_by_default():
    """Run without ``--out``, no validation or benchmark harness writes over the committed
    results or figures: each default output folder is under out/, which git ignores. (The
    committed results are rewritten only with an explicit ``--out validation/results`` etc.)"""
    proc = subprocess.run([sys.executable, "-c", DEFAULT_OUTS, *HARNESSES], cwd=ROOT, env=ENV,
                          capture_output=True, text=True, timeout=600)
    outs = dict(line.split(" ", 1) for line in proc.stdout.splitlines() if line.startswith(HARNESSES))
    assert set(outs) == set(HARNESSES), proc.stdout + proc.stderr
    for script, out in outs.items():
        assert Path(out).is_relative_to(ROOT / "out"), f"{script} writes to {out} by default"
        ignored = subprocess.run(["git", "check-ignore", "-q", out], cwd=ROOT)
        assert ignored.returncode == 0, f"{script}'s default {out} is not ignored by git"


def test_real_assets_without_its_extra_says_which_extra_in_one_line(tmp_path):
    """``python -m validation.real_assets`` without fast-simplification (the ``assets`` extra) stops
    before any work with one line that names the extra, not a ModuleNotFoundError traceback."""
    code = ("import sys\nsys.modules['fast_simplification'] = None   # as if not installed\n"
            "from validation import real_assets\n"
            f"real_assets.main(['--quick', '--out', {str(tmp_path / 'out')!r}])\n")
    proc = _python(code)
    assert proc.returncode == 1, proc.stdout + proc.stderr
    (line,) = proc.stderr.strip().splitlines()
    assert "fast_simplification" in line and "pip install '.[assets]'" in line, line
    assert not (tmp_path / "out").exists()


def test_the_differentiable_pages_float_map_snippet_runs():
    """docs/differentiable.md's snippet that loads a PNG map as floats for optimising: its
    ``normalmap.data`` is a float tensor the optimizer takes (an 8-bit one it refuses)."""
    page = ROOT / "docs" / "differentiable.md"
    snippet = next(b for b in python_blocks(page) if '"format": "variant"' in b)
    code = ("import mfnormal, mitsuba as mi, drjit as dr\nmi.set_variant('llvm_ad_rgb')\n" + snippet
            + "print(type(params['normalmap.data']).__name__, dr.grad_enabled(opt['normalmap.data']))\n")
    proc = _python(code)
    assert proc.returncode == 0, proc.stderr
    assert proc.stdout.split() == ["TensorXf", "True"], proc.stdout


def test_the_public_api_is_annotated():
    """Every parameter and return value of the package's exported functions (mfnormal, the
    baker, the command line's entry points) has a type hint (the wheel ships py.typed)."""
    import importlib
    import inspect
    public = {"mfnormal": None, "mfnormal._llvm": ["ensure_llvm"], "mfnormal.io.bake": None,
              "mfnormal.cli.commands": None, "mfnormal.cli.loading": None, "mfnormal.cli.bake": None}
    missing = []
    for name, names in public.items():
        module = importlib.import_module(name)
        for attr in names or module.__all__:
            fn = getattr(module, attr)
            if not inspect.isfunction(fn):
                continue
            sig = inspect.signature(fn)
            missing += [f"{name}.{attr}({p})" for p, v in sig.parameters.items() if v.annotation is v.empty]
            if sig.return_annotation is sig.empty:
                missing.append(f"{name}.{attr} -> ?")
    assert not missing, missing
