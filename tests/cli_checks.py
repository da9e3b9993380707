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
