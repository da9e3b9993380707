"""A test whose worker process dies runs again once, alone, in a fresh process at the run's end.

A worker process used to segfault or abort now and then inside Dr.Jit (docs/development.md, "Worker
crashes", with the likely cause and its mitigation in tests/conftest.py): a different test each
time, one that passed when it ran again. pytest-xdist reports such a crash as a failure of the test that was running, and
with ``--dist loadfile`` (pyproject.toml) it cannot schedule that test again. So the controller
records the test as **crashed** (a category of its own in the summary, letter ``C``, not a failure)
and, when the run ends, runs every crashed test in one fresh ``pytest -n 0`` process, whose
summary it prints: the run fails if any of them fails or crashes there. A failed assertion is
never run again; only a worker's death is.

Registered by tests/conftest.py; ``-p crash_rerun`` loads it elsewhere (tests/test_crash_rerun.py).
"""

from __future__ import annotations

import subprocess
import sys

import pytest

#: The tests whose worker died, in the order they crashed (node ids).
CRASHED: list[str] = []


@pytest.hookimpl(optionalhook=True)
def pytest_handlecrashitem(crashitem, report, sched):
    CRASHED.append(crashitem)
    report.outcome = "crashed"


def pytest_report_teststatus(report, config):
    if report.outcome == "crashed":
        return "crashed", "C", "CRASHED"
    return None


@pytest.hookimpl(tryfirst=True)
def pytest_sessionfinish(session, exitstatus):
    """Where a worker died: the crashed tests once more in a fresh process; the run fails if
    that run does."""
    if not CRASHED:
        return
    out = session.config.pluginmanager.get_plugin("terminalreporter")
    say = out.write_line if out is not None else print
    say(f"\ncrash_rerun: {len(CRASHED)} test(s) whose worker died, run again alone in a fresh process: "
        + " ".join(CRASHED))
    run = subprocess.run([sys.executable, "-m", "pytest", "-q", "-n", "0", "-p", "no:cacheprovider", *CRASHED],
                         cwd=session.config.rootpath, capture_output=True, text=True)
    for line in (run.stdout + run.stderr).strip().splitlines()[-15:]:
        say(f"crash_rerun: {line}")
    if run.returncode != 0:
        say(f"crash_rerun: the run again failed (exit status {run.returncode})")
        session.exitstatus = pytest.ExitCode.TESTS_FAILED
