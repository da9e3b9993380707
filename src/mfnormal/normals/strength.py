"""The normal map's or height map's ``strength``, checked at load and on every update."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

#: ``strength`` values above this act as it (keeps the decoding from overflowing).
STRENGTH_MAX = 1e6


def fail(msg: str):
    raise ValueError(f"normalmap_microfacet: {msg}")


def checked_strength(values) -> list:
    """``strength`` values as floats, each finite and ≥ 0 (else ValueError), capped at STRENGTH_MAX."""
    import numpy as np

    values = np.array(values, dtype=np.float64).ravel().tolist()
    if len(values) > 1:
        fail(f"strength must be one number, got {len(values)} (an array of width {len(values)})")
    bad = [v for v in values if not (0.0 <= v < float("inf"))]
    if bad or not values:
        fail(f"strength must be a finite number >= 0, got {bad[0] if bad else 'no value'}")
    return [min(v, STRENGTH_MAX) for v in values]


class Strength:
    """The map's ``strength``: an opaque kernel input (a new value compiles nothing), checked at
    load and on every ``mi.traverse`` update (a bad update raises and keeps the previous value)."""

    def __init__(self, value: float):
        self.ok = checked_strength(float(value))
        self.value = mi.Float(self.ok[0])
        dr.make_opaque(self.value)

    def changed(self):
        """Check an update made in place (a ParameterTree from mi.traverse keeps referring to
        ``value``): refused (ValueError, the values before it restored), or capped and kept."""
        try:
            values = checked_strength(self.value)
        except ValueError:
            mi.set_property(self.value, mi.Float(self.ok))
            dr.make_opaque(self.value)
            raise
        if max(values) >= STRENGTH_MAX:
            mi.set_property(self.value, mi.Float(values))
        self.ok = values
        dr.make_opaque(self.value)

    def first(self) -> float:
        """The first value as a Python number."""
        x = self.value
        return dr.slice(x, 0) if dr.is_array_v(x) else x
