"""tests/crash_rerun.py: a test whose worker process dies runs again once, alone, in a fresh process,
and the session's exit status is that run's; a failed assertion is not run again."""

from pathlib import Path

TESTS = Path(__file__).resolve().parent


def _project(pytester, body):
    pytester.makeconftest(f"import sys\nsys.path.insert(0, {str(TESTS)!r})\npytest_plugins = ['crash_rerun']\n")
    pytester.makepyfile(test_dies=body)
    return pytester.runpytest_subprocess("-n", "1", "-p", "no:cacheprovider")


def test_a_test_whose_worker_dies_once_passes_when_run_again(pytester):
    mark = pytester.path / "died"
    result = _project(pytester, f"""
import os, pathlib

def test_dies_the_first_time():
    mark = pathlib.Path({str(mark)!r})
    if not mark.exists():
        mark.write_text("once")
        os.abort()

def test_passes():
    pass
""")
    assert mark.exists(), result.stdout.str()
    result.stdout.fnmatch_lines(["*crash_rerun: 1 test(s) whose worker died*test_dies.py::test_dies_the_first_time*",
                                 "*crash_rerun: 1 passed*", "*1 passed, 1 crashed*"])
    assert result.ret == 0


def test_a_test_that_dies_again_fails_the_session_and_an_assertion_is_not_run_again(pytester):
    count = pytester.path / "runs"
    result = _project(pytester, f"""
import os, pathlib

def test_always_dies():
    os.abort()

def test_fails():
    runs = pathlib.Path({str(count)!r})
    runs.write_text(runs.read_text() + "x" if runs.exists() else "x")
    assert False
""")
    result.stdout.fnmatch_lines(["*crash_rerun: 1 test(s) whose worker died*test_dies.py::test_always_dies*",
                                 "*crash_rerun: the run again failed*", "*1 failed, 1 crashed*"])
    assert result.ret == 1
    assert count.read_text() == "x"
