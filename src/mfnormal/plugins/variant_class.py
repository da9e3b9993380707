"""Binding a plain Python class to the active Mitsuba variant's base class.

Mitsuba's Python base classes (``mi.BSDF``, ``mi.SamplingIntegrator``, ...) are per variant,
so the plugin classes are written as plain classes and bound on registration: one subclass
of the variant's base per (class, variant), with the class's own methods and properties.
"""

from __future__ import annotations

import mitsuba as mi

_classes: dict[tuple, type] = {}


def variant_subclass(cls: type, base: type) -> type:
    """``cls`` as a subclass of ``base`` (a class of the active variant), made once per variant."""
    key = (cls, mi.variant())
    if key not in _classes:
        methods = {k: v for k, v in vars(cls).items() if k not in ("__dict__", "__weakref__")}
        _classes[key] = type(cls.__name__, (base,), methods)
    return _classes[key]
