"""The normal map's or height map's ``strength``, checked at load and on every update."""

from __future__ import annotations

import drjit as dr
import mitsuba as mi

from mfnormal.models.properties import Number

#: ``strength`` values above this act as it (keeps the decoding from overflowing).
STRENGTH_MAX = 1e6


def fail(msg: str):
    raise ValueError(f"normalmap_microfacet: {msg}")


#: ``strength``: read at load and checked on every update alike.
STRENGTH = Number("normalmap_microfacet", "strength", 1.0, "a finite number >= 0", lo=0.0)


class Strength:
    """The map's ``strength``: an opaque kernel input (a new value compiles nothing), checked at
    load and on every ``mi.traverse`` update (a bad update raises and keeps the previous value)."""

    def __init__(self, props):
        self.ok = [min(STRENGTH.read(props), STRENGTH_MAX)]
        self.value = mi.Float(self.ok[0])
        dr.make_opaque(self.value)

    def changed(self):
        """Check an update made in place (a ParameterTree from mi.traverse keeps referring to
        ``value``): refused (ValueError, the values before it restored), or capped and kept."""
        try:
            values = [min(STRENGTH.check_update(self.value), STRENGTH_MAX)]
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
