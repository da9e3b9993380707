"""The package as a user meets it first: the plugins follow ``mi.set_variant`` without a call of
``mfnormal.register()``, and the README's Python quick start runs as written.

Each check runs in a process of its own: the Mitsuba variant is global to a process."""

import re
import subprocess
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]


def _python(code: str, cwd=ROOT) -> subprocess.CompletedProcess:
    return subprocess.run([sys.executable, "-c", code], cwd=cwd, capture_output=True, text=True, timeout=300)


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
