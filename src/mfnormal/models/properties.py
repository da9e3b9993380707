"""Typed plugin parameters: what each parameter of the project's plugins accepts, read from a
plugin's properties (XML, ``mi.load_dict``) and from ``mi.traverse`` updates alike.

XML gives a value its type by its tag (``<boolean>``, ``<integer>``, ``<float>``, ``<string>``),
``mi.load_dict`` by its Python type. As Mitsuba's own plugins do, these refuse a wrong type rather
than convert it: a boolean is a boolean (not the string ``"false"``, which Python's ``bool()``
takes for true), an integer an integer (not 1.5 or NaN, and within its range), a number a finite
int or float where it must be finite (not a string, not a boolean), a string one of its allowed
values. A wrong value raises a one-line ``ValueError`` that names the plugin, the parameter, what it
expects and what it got: ``mfnormal_path: terminator_offset must be a boolean (...), got 'false'
(a string)``.

A traversed parameter is a width-1 Dr.Jit array, so ``mi.traverse`` has already converted an
update to the array's type when ``parameters_changed`` sees it: :meth:`Param.check_update` checks
one number (an integer parameter is exposed as a float array, so that 1.5 reaches the check
instead of being truncated to 1).
"""

from __future__ import annotations

import math

import drjit as dr

INT32_MAX = 2 ** 31 - 1          # counters are 32-bit


def shown(value) -> str:
    """``value`` as an error message shows it: its text, and its type where that is what is wrong."""
    if isinstance(value, bool):
        return f"{value} (a boolean)"
    if isinstance(value, str):
        return f"{value!r} (a string)"
    if isinstance(value, (int, float)):
        return repr(value)
    return f"a value of type {type(value).__name__}"


def one(value, plugin: str, name: str):
    """A Python number from a width-1 Dr.Jit array (or the value itself); ValueError for another
    width (a parameter is one value per plugin)."""
    if not (dr.is_jit_v(value) and dr.depth_v(value) == 1):
        return value
    if dr.width(value) != 1:
        raise ValueError(f"{plugin}: {name} must be one number, got an array of width {dr.width(value)}")
    return dr.slice(value, 0)


class Param:
    """One parameter of a plugin: its name, its default, and what it expects (the phrase of its
    error message). Subclasses say which values they accept (:meth:`accepts`) and as what
    (:meth:`convert`)."""

    def __init__(self, plugin: str, name: str, default, expects: str):
        self.plugin, self.name, self.default, self.expects = plugin, name, default, expects

    def accepts(self, value) -> bool:
        raise NotImplementedError

    def convert(self, value):
        return value

    def fail(self, value):
        raise ValueError(f"{self.plugin}: {self.name} must be {self.expects}, got {shown(value)}")

    def check(self, value):
        """``value`` (a Python value, or a width-1 Dr.Jit array of one), checked and converted."""
        value = one(value, self.plugin, self.name)
        if not self.accepts(value):
            self.fail(value)
        return self.convert(value)

    def read(self, props):
        """The parameter's checked value in the plugin's ``props`` (its default where not given)."""
        if self.name not in props:
            return self.default
        return self.check(props.get(self.name))

    def check_update(self, value):
        """An ``mi.traverse`` update (a width-1 array, already of the exposed type), checked."""
        return self.check(value)


def _is_number(value) -> bool:
    return isinstance(value, (int, float)) and not isinstance(value, bool)


class Boolean(Param):
    def __init__(self, plugin: str, name: str, default: bool):
        super().__init__(plugin, name, default,
                         f"a boolean (<boolean name=\"{name}\" value=\"false\"/> in XML, False in Python)")

    def accepts(self, value) -> bool:
        return isinstance(value, bool)


class Integer(Param):
    """An integer in [lo, hi] (no boolean, no float)."""

    def __init__(self, plugin: str, name: str, default: int, lo: int, hi: int = INT32_MAX, expects: str = ""):
        super().__init__(plugin, name, default, expects or f"an integer between {lo} and {hi}")
        self.lo, self.hi = lo, hi

    def accepts(self, value) -> bool:
        return isinstance(value, int) and not isinstance(value, bool) and self.lo <= value <= self.hi

    def check_update(self, value):
        value = one(value, self.plugin, self.name)
        if isinstance(value, float) and value.is_integer():      # the exposed float array's value
            value = int(value)
        return self.check(value)


class Number(Param):
    """A finite number ≥ lo (an int or a float, no boolean), as a float."""

    def __init__(self, plugin: str, name: str, default: float, expects: str, lo: float = -math.inf):
        super().__init__(plugin, name, default, expects)
        self.lo = lo

    def accepts(self, value) -> bool:
        return _is_number(value) and math.isfinite(value) and value >= self.lo

    def convert(self, value) -> float:
        return float(value)


class Choice(Param):
    """One of a few strings."""

    def __init__(self, plugin: str, name: str, default: str, choices: tuple):
        super().__init__(plugin, name, default, "one of " + ", ".join(f"'{c}'" for c in choices))
        self.choices = choices

    def accepts(self, value) -> bool:
        return isinstance(value, str) and value in self.choices

    def fail(self, value):
        if isinstance(value, str):
            raise ValueError(f"{self.plugin}: unknown {self.name} '{value}'; use {self.expects}")
        super().fail(value)


class Text(Param):
    """A string that ``valid`` accepts."""

    def __init__(self, plugin: str, name: str, default: str, expects: str, valid):
        super().__init__(plugin, name, default, expects)
        self.valid = valid

    def accepts(self, value) -> bool:
        return isinstance(value, str) and self.valid(value)
