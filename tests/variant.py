"""The variant the test suite runs in: ``MFNORMAL_VARIANT`` (default ``llvm_ad_rgb``).

``MFNORMAL_VARIANT=cuda_ad_rgb .venv/bin/python -m pytest -q`` runs the suite on a GPU.
conftest.py checks the name before any test module is imported (an unknown variant, or
one this machine cannot run, e.g. ``cuda_*`` without a GPU, stops the run with one line);
the test modules set it with ``mi.set_variant(VARIANT)``. Tests that compare against
``scalar_rgb`` or that are about libLLVM name their variants themselves.
"""

import os

DEFAULT = "llvm_ad_rgb"
VARIANT = os.environ.get("MFNORMAL_VARIANT", "").strip() or DEFAULT


def check() -> str | None:
    """Set VARIANT with the plugin registered; None, or the one-line reason it cannot be used."""
    import mitsuba as mi

    if VARIANT not in mi.variants():
        return (f"MFNORMAL_VARIANT={VARIANT}: not a variant of this Mitsuba build; choose one of "
                f"{', '.join(v for v in mi.variants() if 'rgb' in v)}")
    try:
        mi.set_variant(VARIANT)
    except Exception as exc:  # noqa: BLE001  (cuda_* without a GPU: ImportError)
        return f"MFNORMAL_VARIANT={VARIANT}: cannot use it here: {str(exc).strip().splitlines()[0]}"
    return None
