"""mfnormal: microfacet-based normal mapping (Schüßler et al. 2017) for Mitsuba 3.

``import mfnormal`` first makes sure Dr.Jit will load a compatible libLLVM (see
``mfnormal._llvm``), then registers the ``normalmap_microfacet`` BSDF plugin, the
``mfnormal_path`` integrator (``mfnormal.plugins.mfnormal_path``) and, in the ``*_ad_*`` variants, the
``mfnormal_prb`` AD integrator (``mfnormal.plugins.mfnormal_prb``: unbiased render derivatives for the
random-walk models) for the active Mitsuba variant, and again for every variant set after it
(``mi.set_variant``: through Mitsuba's variant callback, as Mitsuba's own Python plugins are).
"""

from __future__ import annotations  # ``str | None`` annotations on Python 3.9

from mfnormal._llvm import LLVMError, ensure_llvm

LLVM_PATH = ensure_llvm()

import warnings  # noqa: E402

import mitsuba as mi  # noqa: E402

__version__ = "0.1.0"
__all__ = ["register", "LLVM_PATH", "LLVMError", "__version__"]

_registered: set[str] = set()
_warned_scalar = False


def register(variant: str | None = None) -> str | None:
    """Register the plugins for ``variant`` (default: the active one); idempotent. ``import
    mfnormal`` calls it, and so does every ``mi.set_variant`` after the import.

    Returns the variant registered for, or None when no variant is active.
    """
    global _warned_scalar
    if variant is not None:
        mi.set_variant(variant)
    variant = mi.variant()
    if variant is None:
        return None
    if variant.startswith("scalar") and not _warned_scalar:
        _warned_scalar = True
        warnings.warn(f"mfnormal: the Python BSDF runs ~100x slower in '{variant}' than in "
                      "'llvm_ad_rgb'; use a JIT variant for rendering", RuntimeWarning, stacklevel=2)
    if variant not in _registered:
        from mfnormal.plugins import mfnormal_path as integrator, normalmap_microfacet as plugin
        cls = plugin.bsdf_class()
        mi.register_bsdf("normalmap_microfacet", lambda props: cls(props))
        path_cls = integrator.integrator_class()
        mi.register_integrator("mfnormal_path", lambda props: path_cls(props))
        if "_ad_" in variant:
            from mfnormal.plugins import mfnormal_prb as ad_integrator
            integ = ad_integrator.integrator_class()
            mi.register_integrator("mfnormal_prb", lambda props: integ(props))
        _registered.add(variant)
    return variant


def _on_variant(old: str | None, new: str | None) -> None:
    """Mitsuba's variant callback (``mi.detail.add_variant_callback``): every variant set after
    ``import mfnormal`` gets the plugins, without a call of :func:`register`."""
    if new is not None:
        register()


register()
mi.detail.add_variant_callback(_on_variant)
