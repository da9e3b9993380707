"""The repository's documents and code speak of the project, not of how it was built.

Every tracked text file (``git ls-files``) is searched for process words: numbered
development stops ("stop 28", "stops 29-30"), references to this project's tracker
("issue 18", "Issue-16", "#18", "the tracker"), notes about which machine or accelerator
was lent, "session", and paths of the machine the project was built on (``/work/...``).
Upstream issues are cited by their repository, ``mitsuba-renderer/mitsuba3#885``, which
the tracker pattern does not match. The patterns leave ordinary uses alone: CSS colours
(``#222;``), HTML character references (``&#38;``), markdown anchors (``#1-notation``),
pytest's session API (``pytest_sessionfinish(session, ...)``, ``session.config``,
``scope="session"``).
"""

import re
import subprocess
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
THIS = Path(__file__).resolve().relative_to(ROOT).as_posix()

PATTERNS = {
    "development stop": r"\bstops? \d+",
    "tracker issue": r"\bissues?[ -]#?\d+",
    "tracker number": r"(?<![\w&/#])#\d{1,4}(?![\w-]|\s*;)",
    "tracker": r"\btrackers?\b",
    "machine lent": r"\blent\b",
    "session": r"(?<![\w.(\"'])sessions?\b(?!\.\w|[(\"'=])",
    "build machine path": r"(?<![\w.])/work/",
}
PROCESS_WORDS = re.compile("|".join(f"(?P<{re.sub(r'[^a-z]', '_', name)}>{rx})"
                                    for name, rx in PATTERNS.items()), re.IGNORECASE)


def tracked_text_files():
    """The repository's tracked files that are text (UTF-8, no NUL byte), except this test."""
    try:
        out = subprocess.run(["git", "ls-files", "-z"], cwd=ROOT, capture_output=True, check=True).stdout
    except (OSError, subprocess.CalledProcessError) as exc:
        pytest.skip(f"not a git checkout ({exc})")
    for name in out.decode("utf-8").split("\0"):
        if not name or name == THIS:
            continue
        path = ROOT / name
        if not path.is_file():
            continue
        data = path.read_bytes()
        if b"\0" in data:
            continue
        try:
            yield name, data.decode("utf-8")
        except UnicodeDecodeError:
            continue


def process_word_hits(text):
    """(line number, matched text, line) of every process word in ``text``."""
    hits = []
    for number, line in enumerate(text.splitlines(), 1):
        for match in PROCESS_WORDS.finditer(line):
            hits.append((number, match.group(0), line.strip()))
    return hits


@pytest.mark.parametrize("text", [
    "measured at stop 28 on an idle machine", "the blocks written by stops 29-30",
    "Targets (issue 18): render time", "Issue-16 follow-up 4", "the fused call (issue #18)",
    "fixed in #18.", "(see #7)", "the closing note of the tracker", "no GPU was lent to it",
    "the same driver, same session", "computed once per session)", "in one session.", "--out /work/notes/s28/prod",
])
def test_the_patterns_find_process_words(text):
    assert process_word_hits(text), text


@pytest.mark.parametrize("text", [
    "cited as mitsuba-renderer/mitsuba3#885", "body { color: #222; background: #fafafa; }",
    "border: 1px solid #999; }", "&#38; &#x26;", "[notation](#1-notation-and-conventions)",
    "def pytest_sessionfinish(session, exitstatus):", "session.config._status = 1",
    '@pytest.fixture(scope="session")', "the walk stops at the crest", "a stop-gradient",
    "issues a warning", "# 2. The virtual environment", "see /workspace/x or ../work/", "silent",
])
def test_the_patterns_leave_ordinary_words(text):
    assert not process_word_hits(text), process_word_hits(text)


def test_no_process_words_in_the_repository():
    found = []
    for name, text in tracked_text_files():
        found += [f"{name}:{number}: {word!r} in: {line[:160]}" for number, word, line in process_word_hits(text)]
    assert not found, (f"{len(found)} process words in tracked files (write of the project, "
                       "cite upstream issues as owner/repo#N):\n" + "\n".join(found))
