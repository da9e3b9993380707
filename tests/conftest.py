"""Shared test setup: every test starts in the suite's variant (``MFNORMAL_VARIANT``, default
llvm_ad_rgb: tests/variant.py) with the plugin registered; ``worker``, one command-line worker
process per test module (``tests/cli_worker.py``).

``import mfnormal`` comes first so that Dr.Jit loads a compatible libLLVM. An unknown variant,
or one this machine cannot run (``cuda_*`` without a GPU), stops the run with one line before
any test module is imported. Some tests switch to ``scalar_rgb``; the variant is
process-global and the plugin is registered per variant, so each test gets the suite's back.
"""

import os
import shutil

import pytest

import mfnormal  # noqa: F401
import crash_rerun
from tiers import FULL, slow_reason
from variant import VARIANT, check


def pytest_configure(config):
    error = check()
    if error is not None:
        raise pytest.UsageError(error)
    # A test whose worker process dies runs again alone at the end (tests/crash_rerun.py).
    if not config.pluginmanager.has_plugin("crash_rerun"):
        config.pluginmanager.register(crash_rerun, "crash_rerun")


def pytest_report_header(config):
    return f"mfnormal: variant {VARIANT} (MFNORMAL_VARIANT)"


# -- Slow tests ------------------------------------------------------------------------------------
# ``@pytest.mark.slow``: scale tests, and the cases of a check beyond those the default run keeps
# (every model and contract has at least one case in the default run), marked in their modules
# or listed with what covers them in tests/tiers.py. They run with MFNORMAL_SLOW=1.

def pytest_collection_modifyitems(config, items):
    for item in items:
        if slow_reason(item.nodeid) is not None:
            item.add_marker(pytest.mark.slow)
    if FULL:
        return
    skip = pytest.mark.skip(reason="slow: MFNORMAL_SLOW=1 runs it")
    for item in items:
        if item.get_closest_marker("slow") is not None:
            item.add_marker(skip)


# -- Garbage collection between tests only ----------------------------------------------------------
# Under pytest-xdist a test process has a second Python thread (execnet's, which receives the
# controller's messages). Python's cyclic collector runs on whichever thread allocates past its
# threshold: on that thread, or on the test's thread inside a Dr.Jit call that runs Python code (a
# Python plugin traced into a kernel), it frees Mitsuba/Dr.Jit objects that earlier tests left in
# reference cycles (scenes and their plugins) while Dr.Jit is busy on the test's thread. Worker
# processes then segfaulted or aborted now and then, in a different test each time (a render of
# Mitsuba's own bumpmap, a prb render), each passing when run again. So in the test processes the
# collector runs only here, on the test's thread, between tests: the young generations after
# every test, all of them every FULL_COLLECT_EVERY tests.
FULL_COLLECT_EVERY = 25
_tests_since_full_collect = [0]


@pytest.fixture(autouse=True)
def _collect_between_tests():
    import gc

    gc.disable()
    yield
    _tests_since_full_collect[0] += 1
    if _tests_since_full_collect[0] >= FULL_COLLECT_EVERY:
        _tests_since_full_collect[0] = 0
        gc.collect()
    else:
        gc.collect(1)


@pytest.fixture(autouse=True)
def _suite_variant():
    import mitsuba as mi

    if mi.variant() != VARIANT:
        mi.set_variant(VARIANT)
    mfnormal.register()


@pytest.fixture(scope="module")
def worker():
    from cli_worker import Worker

    w = Worker()
    yield w
    w.close()


# -- Exit ------------------------------------------------------------------------------------------
# With this suite's ~700 tests, the interpreter's own teardown after pytest has finished
# (every test passed, the summary printed) segfaults inside Dr.Jit 1.5 (rc 139, no Python
# frame: faulthandler prints nothing), while each test file run alone exits cleanly. The crash
# is in the order in which Python frees Mitsuba/Dr.Jit objects still alive at shutdown (a
# scene freed by the cyclic collector during a later kernel launch crashes the same way), not
# in a test. So the run frees what it can while Dr.Jit is alive and then ends the process
# with pytest's own exit status, skipping the teardown. Reproduce without it:
# MFNORMAL_NO_FAST_EXIT=1 .venv/bin/python -m pytest -q   (rc 139 after "N passed").

def pytest_sessionfinish(session, exitstatus):
    # (session.exitstatus: crash_rerun's run of the crashed tests may have changed it.)
    session.config._mfnormal_exitstatus = int(session.exitstatus)


@pytest.hookimpl(trylast=True)
def pytest_unconfigure(config):
    import gc
    import os
    import sys

    status = getattr(config, "_mfnormal_exitstatus", None)
    if status is None or os.environ.get("MFNORMAL_NO_FAST_EXIT"):
        return
    gc.collect()
    import drjit as dr

    dr.sync_thread()
    sys.stdout.flush()
    sys.stderr.flush()
    os._exit(status)


# -- A headless Chromium for the browser tests (the report, the documentation) --------------------

def _chromium():
    for name in ("chromium", "chromium-browser", "google-chrome"):
        path = shutil.which(name)
        if path:
            return path
    return None


BROWSER_FLAGS = ["--headless", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                 "--disable-background-networking", "--disable-component-update", "--disable-sync",
                 "--disable-dev-shm-usage", "--window-size=1400,1000"]


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    webdriver = pytest.importorskip("selenium.webdriver", reason="selenium is not installed "
                                    "(pip install -e '.[test]')")
    chromium, driver = _chromium(), shutil.which("chromedriver")
    if not chromium or not driver:
        pytest.skip("no headless browser: install Debian's chromium and chromium-driver "
                    "(scripts/setup.sh does, as root)")
    from selenium.webdriver.chrome.service import Service

    options = webdriver.ChromeOptions()
    options.binary_location = chromium
    for flag in BROWSER_FLAGS:
        options.add_argument(flag)
    options.add_argument(f"--user-data-dir={tmp_path_factory.mktemp('chromium-profile')}")
    options.set_capability("goog:loggingPrefs", {"browser": "ALL"})
    drv = webdriver.Chrome(service=Service(driver), options=options)
    drv.set_page_load_timeout(60)
    yield drv
    drv.quit()
