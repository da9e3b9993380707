"""What the two fuzzers (``test_cli_fuzz.py``, ``test_gltf_fuzz.py``) share.

- :func:`input_count` and :func:`fuzz_test`: ``QUICK`` inputs in the default run and
  ``CI`` with ``MFNORMAL_SLOW=1``, derandomised (the same every run), unless
  ``MFNORMAL_FUZZ_LONG=1`` (``LONG`` random inputs, the Hypothesis seed of a failure
  printed); ``MFNORMAL_FUZZ_INPUTS=N`` sets the count;
- :class:`Stats`: the inputs run, their outcomes and time, printed at the end
  (``pytest -s``), and ``MFNORMAL_FUZZ_LOG=FILE``, each input's exit code and last
  stderr line appended to FILE;
- :func:`render_or_one_line_error`: the contract of every input: exit 0 with only
  warnings on stderr and the outputs written, or exit 2 with exactly one
  ``mfnormal: error:`` line (after at most some warnings) and nothing written;
  never a timeout, a dead worker or an exception escaping ``main``.
"""

from __future__ import annotations

import os
import shutil
import tempfile
import time
from contextlib import contextmanager
from pathlib import Path

import pytest
from hypothesis import HealthCheck, Phase, given, settings
from hypothesis import strategies as st

from tiers import FULL

LONG = os.environ.get("MFNORMAL_FUZZ_LONG", "") not in ("", "0")
LOG = os.environ.get("MFNORMAL_FUZZ_LOG")


def input_count(ci: int, long: int, quick: int | None = None) -> int:
    """How many inputs a fuzz test runs: ``quick`` (where given) in the default run, ``ci`` with
    ``MFNORMAL_SLOW=1``, ``long`` with ``MFNORMAL_FUZZ_LONG=1``, or ``MFNORMAL_FUZZ_INPUTS``."""
    default = long if LONG else (ci if FULL or quick is None else quick)
    return int(os.environ.get("MFNORMAL_FUZZ_INPUTS", default))


def fuzz_test(inputs: int):
    """A fuzz test of ``inputs`` examples, drawing from Hypothesis's ``data`` strategy."""
    fuzz = settings(max_examples=inputs, derandomize=not LONG, database=None, deadline=None,
                    print_blob=LONG, phases=(Phase.explicit, Phase.generate, Phase.shrink),
                    suppress_health_check=list(HealthCheck))
    return lambda test: fuzz(given(data=st.data())(test))


class Stats:
    """Inputs run, rendered and refused, and the seconds they took."""

    def __init__(self, name: str, digits: int = 1):
        self.name, self.digits = name, digits
        self.counts = {"inputs": 0, "render": 0, "error": 0}
        self.seconds = 0.0

    def log(self, result, extra: str = ""):
        """Append the input's exit code and last stderr line (and ``extra``) to the log file."""
        if LOG:
            lines = result.stderr.strip().splitlines()
            with open(LOG, "a") as f:
                f.write(f"{result.rc}\t{lines[-1] if lines else ''}{extra}\n")

    def count(self, outcome: str):
        self.counts["inputs"] += 1
        self.counts[outcome] += 1

    @contextmanager
    def sandbox(self, prefix: str):
        """A fresh temporary folder for one input, removed after it; its time is counted."""
        start = time.perf_counter()
        root = Path(tempfile.mkdtemp(prefix=prefix))
        try:
            yield root
        finally:
            shutil.rmtree(root, ignore_errors=True)
            self.seconds += time.perf_counter() - start

    def report(self):
        c = self.counts
        if c["inputs"]:
            print(f"\n{self.name}: {c['inputs']} inputs ({c['render']} rendered, {c['error']} one-line "
                  f"errors) in {self.seconds:.1f} s: {c['inputs'] / self.seconds:.{self.digits}f} inputs/s")

    def report_fixture(self):
        """A module fixture that prints the report after the module's tests."""
        @pytest.fixture(scope="module", autouse=True)
        def report_throughput():
            yield
            self.report()
        return report_throughput


def render_or_one_line_error(result, timeout: float, check_rendered, check_nothing_written) -> str:
    """'render' or 'error' (see the module docstring); ``check_rendered()`` and
    ``check_nothing_written()`` assert what each outcome leaves on disk."""
    assert not result.timed_out, f"no answer within {timeout:.0f} s"
    assert result.died is None, result.describe()
    assert result.exception is None, result.describe()
    lines = [ln for ln in result.stderr.strip().splitlines() if ln.strip()]
    if result.rc == 0:
        assert all(ln.startswith("mfnormal: warning: ") for ln in lines), result.stderr
        check_rendered()
        return "render"
    assert result.rc == 2, result.describe()
    assert lines and lines[-1].startswith("mfnormal: error: "), result.stderr
    assert all(ln.startswith("mfnormal: warning: ") for ln in lines[:-1]), result.stderr
    check_nothing_written()
    return "error"
