"""Shared test setup: every test starts in llvm_ad_rgb with the plugin registered; ``worker``,
one command-line worker process per test module (``tests/cli_worker.py``).

``import mfnormal`` comes first so that Dr.Jit loads a compatible libLLVM. Some
tests switch to ``scalar_rgb``; the variant is process-global and the plugin is
registered per variant, so each test gets llvm_ad_rgb back.
"""

import pytest

import mfnormal

VARIANT = "llvm_ad_rgb"


@pytest.fixture(autouse=True)
def _llvm_variant():
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
