"""Run ``mfnormal`` commands in a long-lived child process, under a time and memory bound.

Starting a process per command costs ~2 s (importing Mitsuba); the fuzzers run
hundreds of commands. :class:`Worker` keeps one child (``python cli_worker.py``)
that runs ``mfnormal.cli.commands.main(args)`` for each request and answers with the exit
code, what the command wrote to stdout and stderr (file descriptors 1 and 2, so
Mitsuba's native output is included), the files it opened and whether an
exception escaped ``main``. The child's address space is capped (RLIMIT_AS,
``MEMORY_GIB``); the parent kills it after ``timeout`` seconds and starts a new
one for the next request. A child that dies (a signal: segfault, abort) is
reported as such, so a crash of the code under test fails a test instead of
taking pytest down.

Opened files: a ``sys.addaudithook`` in the child records the path of every
``open`` event for reading (``open()``, ``os.open``: every file the loader reads). Native
reads by Mitsuba (textures of an XML scene) are not seen; the glTF loader reads
every file in Python.
"""

from __future__ import annotations

import json
import os
import select
import subprocess
import sys
import time
from dataclasses import dataclass, field
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
MEMORY_GIB = 6


@dataclass
class Result:
    rc: int | None               # main's return value (None: it did not return)
    stdout: str = ""
    stderr: str = ""
    opened: list = field(default_factory=list)   # files opened for reading
    exception: str | None = None  # the traceback of an exception that escaped main
    died: int | None = None      # the child's exit status when it died (negative: a signal)
    timed_out: bool = False
    seconds: float = 0.0

    def describe(self) -> str:
        if self.timed_out:
            return f"timed out after {self.seconds:.0f} s"
        if self.died is not None:
            return f"the process died (status {self.died}); stderr: {self.stderr[-2000:]}"
        if self.exception:
            return f"exception escaped main: {self.exception[-3000:]}"
        return f"rc={self.rc}; stderr: {self.stderr[-2000:]}"


class Worker:
    def __init__(self, memory_gib: int = MEMORY_GIB):
        import tempfile

        self.memory_gib = memory_gib
        self.proc = None
        self.started = 0
        self.err_path = Path(tempfile.mkdtemp(prefix="mfnormal-worker.")) / "stderr"

    def _start(self):
        env = dict(os.environ, PYTHONPATH=os.pathsep.join([str(ROOT / "src"), str(ROOT / "tests")]),
                   MFNORMAL_WORKER_GIB=str(self.memory_gib))
        env.pop("MFNORMAL_DEBUG", None)
        self.proc = subprocess.Popen([sys.executable, str(Path(__file__).resolve())], stdin=subprocess.PIPE,
                                     stdout=subprocess.PIPE, stderr=subprocess.DEVNULL, env=env)
        self.started += 1

    def close(self):
        if self.proc is not None:
            try:
                self.proc.stdin.close()
                self.proc.wait(timeout=10)
            except Exception:  # noqa: BLE001
                self.proc.kill()
                self.proc.wait()
            self.proc = None

    def run(self, args, cwd, timeout: float = 120.0) -> Result:
        """``mfnormal ARGS`` in ``cwd``."""
        if self.proc is None or self.proc.poll() is not None:
            self._start()
        request = json.dumps({"args": [str(a) for a in args], "cwd": str(cwd),
                              "err": str(self.err_path)}) + "\n"
        start = time.monotonic()
        try:
            self.proc.stdin.write(request.encode())
            self.proc.stdin.flush()
        except BrokenPipeError:
            pass
        line = b""
        fd = self.proc.stdout.fileno()
        while not line.endswith(b"\n"):
            left = timeout - (time.monotonic() - start)
            if left <= 0:
                self.proc.kill()
                self.proc.wait()
                self.proc = None
                return Result(None, timed_out=True, seconds=time.monotonic() - start)
            ready, _, _ = select.select([fd], [], [], min(left, 1.0))
            if ready:
                chunk = os.read(fd, 1 << 20)
                if not chunk:         # the child died
                    status = self.proc.wait()
                    self.proc = None
                    err = _read_quietly(self.err_path)
                    return Result(None, died=status, stderr=err, seconds=time.monotonic() - start)
                line += chunk
        reply = json.loads(line.decode())
        return Result(reply["rc"], reply["stdout"], reply["stderr"], reply["opened"], reply["exception"],
                      seconds=time.monotonic() - start)


    def completed(self, args, cwd, timeout: float = 300.0) -> subprocess.CompletedProcess:
        """:meth:`run` as the process a user would see: its exit code, stdout and stderr. A crash,
        an exception escaping ``main`` (a traceback, in a process of its own) or a timeout fails
        the calling test here."""
        result = self.run(args, cwd, timeout)
        assert result.rc is not None, result.describe()
        return subprocess.CompletedProcess([str(a) for a in args], result.rc, result.stdout, result.stderr)


def _read_quietly(path: Path) -> str:
    try:
        return path.read_text(errors="replace")
    except OSError:
        return ""


# -- The child -----------------------------------------------------------------------------------

def _serve():
    import resource
    import tempfile
    import traceback

    gib = int(os.environ.get("MFNORMAL_WORKER_GIB", MEMORY_GIB))
    resource.setrlimit(resource.RLIMIT_AS, (gib << 30, gib << 30))
    opened = []
    recording = [False]

    def audit(event, args):
        # ("open", (path, mode, flags)): record the files opened for reading.
        if recording[0] and event == "open" and args and isinstance(args[0], (str, bytes, os.PathLike)):
            mode = args[1] if len(args) > 1 and isinstance(args[1], str) else ""
            flags = args[2] if len(args) > 2 and isinstance(args[2], int) else 0
            if not (set(mode) & set("wax+")) and not flags & (os.O_WRONLY | os.O_RDWR | os.O_CREAT):
                opened.append(os.fsdecode(args[0]))

    sys.addaudithook(audit)
    from mfnormal.cli import commands as cli   # noqa: F401  (imports Mitsuba once)

    replies = os.fdopen(os.dup(1), "w")
    for line in sys.stdin:
        request = json.loads(line)
        cwd = request["cwd"]
        os.chdir(cwd)
        out = tempfile.TemporaryFile()
        err = open(request["err"], "w+b")     # read by the parent if this process dies
        saved = os.dup(1), os.dup(2)
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(out.fileno(), 1)
        os.dup2(err.fileno(), 2)
        opened.clear()
        recording[0] = True
        rc, exc = None, None
        try:
            rc = cli.main(request["args"])
        except BaseException:  # noqa: BLE001  (anything that escapes main is a finding)
            exc = traceback.format_exc()
        recording[0] = False
        sys.stdout.flush()
        sys.stderr.flush()
        os.dup2(saved[0], 1)
        os.dup2(saved[1], 2)
        os.close(saved[0])
        os.close(saved[1])
        out.seek(0)
        err.seek(0)
        reply = {"rc": rc, "stdout": out.read().decode(errors="replace"),
                 "stderr": err.read().decode(errors="replace"), "opened": list(opened), "exception": exc}
        out.close()
        err.close()
        replies.write(json.dumps(reply) + "\n")
        replies.flush()


if __name__ == "__main__":
    _serve()
