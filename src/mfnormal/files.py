"""Files written whole or not at all.

:func:`atomic_write_all` writes several files as one: each goes to a temporary file in its
folder first, and only when all are complete are they renamed (with SIGINT and SIGTERM held
back between the renames), so a failure (a full disk, a signal) leaves the previous files and no
temporary one. What the package writes (renders, reports, the bundled scenes' assets, baked
maps) goes through it.
"""

from __future__ import annotations

import os
import signal
import tempfile
from contextlib import contextmanager
from pathlib import Path

__all__ = ["atomic_write_all", "atomic_write", "write_bytes"]


def _temp_path(path: Path) -> str:
    fd, tmp = tempfile.mkstemp(prefix=f".{path.stem}.", suffix=path.suffix, dir=path.parent)
    os.close(fd)
    return tmp


def _umask() -> int:
    umask = os.umask(0)
    os.umask(umask)
    return umask


@contextmanager
def _signals_held():
    """SIGINT and SIGTERM wait until the block is done (where the platform allows it)."""
    sigs = {s for s in (getattr(signal, "SIGINT", None), getattr(signal, "SIGTERM", None)) if s}
    can = hasattr(signal, "pthread_sigmask")
    if can:
        old = signal.pthread_sigmask(signal.SIG_BLOCK, sigs)
    try:
        yield
    finally:
        if can:
            signal.pthread_sigmask(signal.SIG_SETMASK, old)


def atomic_write_all(items) -> list[Path]:
    """Write several files as one: ``items`` is a list of (path, write) where ``write(tmp)``
    writes the file's content to the temporary path ``tmp``. Every file is written to
    a temporary file next to its target first; then all are renamed, with SIGINT and
    SIGTERM held back between the renames. On any error (or signal) before the renames,
    the temporary files are removed and the targets are untouched."""
    items = [(Path(p), w) for p, w in items]
    umask = _umask()
    temps = []
    try:
        for path, write in items:
            path.parent.mkdir(parents=True, exist_ok=True)
            with _signals_held():            # created and registered for removal as one step
                temps.append(_temp_path(path))
            write(temps[-1])
            os.chmod(temps[-1], 0o666 & ~umask)   # mkstemp makes it private; give it the usual mode
        with _signals_held():
            done = []
            try:
                for (path, _), tmp in zip(items, temps):
                    os.replace(tmp, path)
                    done.append(path)
            except BaseException:
                for path in done:          # a half-renamed pair: remove its new half
                    try:
                        os.unlink(path)
                    except OSError:
                        pass
                raise
    except BaseException:
        for tmp in temps:
            try:
                os.unlink(tmp)
            except OSError:
                pass
        raise
    return [p for p, _ in items]


def atomic_write(path, write) -> Path:
    """Call ``write(tmp_path)`` then rename onto ``path``: no half-written file on error."""
    return atomic_write_all([(path, write)])[0]


def write_bytes(path, data: bytes) -> None:
    """Write ``data`` to ``path`` and make it durable: a full disk raises OSError here
    (Mitsuba's own file streams can lose a failed final flush)."""
    with open(path, "wb") as f:
        f.write(data)
        f.flush()
        os.fsync(f.fileno())
