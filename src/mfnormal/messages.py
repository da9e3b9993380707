"""One-line error messages from Mitsuba's (possibly nested, multi-line) exceptions."""

from __future__ import annotations

import re


def one_line(exc: BaseException) -> str:
    """The gist of a (possibly multi-line, nested) Mitsuba error."""
    text = str(exc).strip()
    # Mitsuba wraps plugin errors: keep the innermost message.
    lines = [ln.strip() for ln in text.splitlines() if ln.strip()]
    for ln in reversed(lines):
        if re.match(r"^(ValueError|TypeError|RuntimeError|KeyError|Exception):", ln):
            return ln.split(":", 1)[1].strip()
    msg = lines[0] if lines else type(exc).__name__
    msg = re.sub(r"\[[\w./]+:\d+\]\s*", "", msg)
    # Mitsuba lists the culprits on the following lines ("  - float \"bogus\": 1").
    items = [ln[1:].strip() for ln in lines[1:] if ln.startswith("- ")]
    return msg.rstrip(":") + (": " + "; ".join(items) if items else "")
