"""One-line error messages from Mitsuba's and Dr.Jit's (possibly nested, multi-line) exceptions.

Three layers hide the real cause of an error:

- Dr.Jit wraps an exception raised inside a kernel trace (``dr.while_loop``,
  ``dr.custom``, a virtual call) in another one that ends with "(see above)",
  keeping the original as ``__cause__`` (and ``__context__``): :func:`innermost`
  follows that chain.
- Mitsuba's XML parser prefixes each ``<include>`` level with a line "Error
  while loading a.xml (line 1, col 25): while processing <include>:"; the
  innermost line is the one that names the problem.
- Mitsuba's plugin errors carry the Python exception as a line
  ``ValueError: ...`` and list culprits on lines starting with ``- ``.
"""

from __future__ import annotations

import re

__all__ = ["innermost", "one_line"]

_LOCATION = re.compile(r"\[[\w./-]+:\d+\]\s*")
_INCLUDE = re.compile(r'^Error while loading "?([^"]+?)"? \(line \d+, col \d+\): while processing <include>:?$')


def innermost(exc: BaseException) -> BaseException:
    """The exception at the end of ``exc``'s ``__cause__`` chain (and of the implicit
    ``__context__`` chain where a message defers to it with "see above")."""
    seen = {id(exc)}
    while True:
        nxt = exc.__cause__
        if nxt is None and exc.__context__ is not None and "see above" in str(exc):
            nxt = exc.__context__
        if nxt is None or id(nxt) in seen:
            return exc
        seen.add(id(nxt))
        exc = nxt


def _includes(lines: list[str]) -> tuple[list[str], list[str]]:
    """(files of the leading ``<include>`` wrapper lines, the remaining lines)."""
    files = []
    while lines:
        match = _INCLUDE.match(_LOCATION.sub("", lines[0]))
        if not match:
            break
        if not files or files[-1] != match.group(1):
            files.append(match.group(1))
        lines = lines[1:]
    return files, lines


def one_line(exc: BaseException) -> str:
    """The gist of a (possibly multi-line, nested) Mitsuba or Dr.Jit error, in one line."""
    exc = innermost(exc)
    text = str(exc).strip()
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    if not lines:
        return type(exc).__name__
    # Mitsuba wraps plugin errors: keep the innermost message.
    for ln in reversed(lines):
        if re.match(r"^(ValueError|TypeError|RuntimeError|KeyError|Exception):", ln):
            return ln.split(":", 1)[1].strip()
    files, rest = _includes(lines)
    if files and rest:
        lines = rest
    msg = _LOCATION.sub("", lines[0])
    # Mitsuba lists the culprits on the following lines ("  - float \"bogus\": 1").
    items = [ln[1:].strip() for ln in lines[1:] if ln.startswith("- ")]
    msg = msg.rstrip(":") + (": " + "; ".join(items) if items else "")
    if files:
        msg += f" (in <include> of {' → '.join(files)})"
    return msg
