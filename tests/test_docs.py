"""The user documentation describes the product as it is: no issue numbers, commit hashes or
branch names (the history lives in git).

The user docs are the README and every text file under ``docs/``, ``schemas/``, ``examples/``
and ``recordings/`` (``docs/results/*.md`` included: ``bttsim study`` writes them).
"""

import re
from pathlib import Path

import pytest

pytestmark = pytest.mark.unit

REPO = Path(__file__).resolve().parents[1]
DOC_DIRS = ("docs", "schemas", "examples", "recordings")
TEXT_SUFFIXES = {".md", ".toml", ".py", ".proto", ".txt", ".json"}

#: Branch names the project has used, flagged when quoted or in backticks (`speed3`, 'merge');
#: ``main``, ``docs`` and ``views`` are left out (a function, a folder, a module), and ``main`` in
#: the history sense is caught by the "merge history" patterns.
BRANCH_NAMES = ("merge", "stream", "speed", "speed2", "speed3", "campview", "results", "nsvsim", "cliux",
                "modelcheck")

#: (what, pattern) pairs: each match in a user doc is a failure.
HISTORY = (
    ("issue or PR number", re.compile(r"\b(?:issues?|PRs?|pull requests?) ?#?\d+", re.IGNORECASE)),
    ("commit hash", re.compile(r"(?<![#\w.\-])(?=[0-9a-f]*\d)(?=[0-9a-f]*[a-f])[0-9a-f]{7,40}(?![\w\-])")),
    ("branch", re.compile(r"\bbranch(?:es|'s)?\b(?! cut)", re.IGNORECASE)),
    ("merge history", re.compile(r"\bmerged? (?:into |of |from )?(?:the )?`?(?:main|master)\b", re.IGNORECASE)),
    ("merge history", re.compile(r"\b(?:on|from|against) `?(?:main|master)\b`?(?! job)", re.IGNORECASE)),
    ("branch name", re.compile(r"(?<!:)[`'\"](?:%s)[`'\"]" % "|".join(BRANCH_NAMES))),
)
#: A float written without a dot (``12345e10``) is not a hash.
_FLOAT = re.compile(r"\d+e\d+")


def user_docs() -> list[Path]:
    """The README and every text file under the user-doc folders (tracked or not)."""
    files = [REPO / "README.md"]
    for d in DOC_DIRS:
        files += sorted(p for p in (REPO / d).rglob("*") if p.is_file() and p.suffix in TEXT_SUFFIXES)
    return files


def history_mentions(text: str) -> list[tuple[int, str, str]]:
    """``(line, what, match)`` for every issue number, commit hash or branch reference in ``text``."""
    found = []
    for n, line in enumerate(text.splitlines(), 1):
        for what, pattern in HISTORY:
            for m in pattern.finditer(line):
                if what == "commit hash" and _FLOAT.fullmatch(m.group()):
                    continue
                found.append((n, what, m.group()))
    return found


@pytest.mark.parametrize("text, what", [
    ("Non-synchronous vibration (issue 13).", "issue or PR number"),
    ("see issues #12", "issue or PR number"),
    ("measured against commit 90ceb36 in one session", "commit hash"),
    ("(commit 3e4a520)", "commit hash"),
    ("Third pass (branch `speed3`)", "branch"),
    ("the nsvsim branch's fields", "branch"),
    ("On the merged main at the end", "merge history"),
    ("1.246 s on main and 1.287 s", "merge history"),
    ("what the 'campview' work added", "branch name"),
], ids=["issue", "issue-hash", "hash", "hash-paren", "branch", "branch-possessive", "merged-main", "on-main",
        "branch-name"])
def test_history_is_flagged(text, what):
    assert what in {w for _, w, _ in history_mentions(text)}


@pytest.mark.parametrize("text", [
    "colour #1f77b4 and #d62728ff", "tol 1e-12, 3.0e10, 123456e10 and 1.23456e7", "0.0004375 m",
    "damping beta = 9e-6 s", "the main job: simulator and processor", "the cut nodes merged",
    "MAC 0.999999999998", "sha256 e3b0c44298fc1c149afbf4c8996fb92427ae41e4649b934ca495991b7852b855",
    "ND 14 issues a warning", "`bttsim_stream/bus/_gen/bttsim/v1/bttsim_pb2.py`", "the stream of TOAs",
    "`docs/results/`", "0x7f3a9c1b", "so the command line repeats :func:`main`", ":mod:`results`",
], ids=["colours", "floats", "digits", "exponent", "main-job", "merged-nodes", "mac", "sha256", "issues-verb",
        "path", "stream", "results-path", "hex-literal", "sphinx-main", "sphinx-role"])
def test_legitimate_text_is_not_flagged(text):
    assert history_mentions(text) == []


def test_user_docs_carry_no_history():
    problems = [f"{p.relative_to(REPO)}:{n}: {what}: {m!r}"
                for p in user_docs() for n, what, m in history_mentions(p.read_text(errors="replace"))]
    assert not problems, "user docs describe the product as it is now (history lives in git):\n" + "\n".join(problems)
