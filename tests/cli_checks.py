"""Shared check of the CLI's error contract: one line on stderr, non-zero exit."""


def assert_one_line_error(proc, *needles):
    """The process failed with exactly one `mfnormal: error:` line containing every needle."""
    err = proc.stderr.strip()
    assert proc.returncode != 0, proc.stdout + proc.stderr
    assert "Traceback" not in err, err
    lines = err.splitlines()
    assert len(lines) == 1, err
    assert lines[0].startswith("mfnormal: error: "), err
    for needle in needles:
        assert needle in lines[0], f"{needle!r} not in {lines[0]!r}"


def assert_error_line(result, *needles):
    """A worker Result: exit 2 and exactly one line 'mfnormal: error: ...' with the needles."""
    assert result.exception is None and result.died is None and not result.timed_out, result.describe()
    err = result.stderr.strip()
    assert result.rc == 2, result.describe()
    lines = err.splitlines()
    assert len(lines) == 1 and lines[0].startswith("mfnormal: error: "), err
    for needle in needles:
        assert needle in lines[0], f"{needle!r} not in {lines[0]!r}"
    return lines[0]
