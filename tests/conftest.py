"""Shared test setup: every test starts in the suite's variant (``MFNORMAL_VARIANT``, default
llvm_ad_rgb: tests/variant.py) with the plugin registered; ``worker``, one command-line worker
process per test module (``tests/cli_worker.py``).

``import mfnormal`` comes first so that Dr.Jit loads a compatible libLLVM. An unknown variant,
or one this machine cannot run (``cuda_*`` without a GPU), stops the run with one line before
any test module is imported. Some tests switch to ``scalar_rgb``; the variant is
process-global and the plugin is registered per variant, so each test gets the suite's back.
"""

import pytest

import mfnormal  # noqa: F401
from variant import VARIANT, check


def pytest_configure(config):
    error = check()
    if error is not None:
        raise pytest.UsageError(error)


def pytest_report_header(config):
    return f"mfnormal: variant {VARIANT} (MFNORMAL_VARIANT)"


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
