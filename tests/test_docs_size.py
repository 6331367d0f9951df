"""Docs pages are a user's guide: every ``docs/*.md`` page but the change log is at most 15,000
characters (issue 32); experiment logs live in ``docs/notes/``, which is exempt, and whose links
must resolve like the guide's. The README is a front door of at most 12,000 (issue 57): every
result lives on docs/results.md, which ``taskvar report`` writes."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_docs_links import broken_links  # tests/ is on sys.path (rootdir import mode)

ROOT = Path(__file__).resolve().parents[1]
LIMIT = 15_000
README_LIMIT = 12_000
EXEMPT = {"changelog.md"}
GUIDE = sorted(p for p in (ROOT / "docs").glob("*.md") if p.name not in EXEMPT)
NOTES = sorted((ROOT / "docs" / "notes").glob("*.md"))


@pytest.mark.parametrize("path", GUIDE, ids=lambda p: p.name)
def test_guide_page_within_limit(path: Path) -> None:
    size = len(path.read_bytes())
    assert size <= LIMIT, (
        f"docs/{path.name} is {size} characters (limit {LIMIT}): move logs, ablations and "
        "superseded results to docs/notes/ and link them"
    )


def test_readme_is_a_front_door() -> None:
    """Within its limit, opening with exactly the two set-up commands, and holding no Results
    markers (``taskvar report`` writes the Results to docs/results.md)."""
    text = (ROOT / "README.md").read_text(encoding="utf-8")
    size = len(text.encode())
    assert size <= README_LIMIT, (
        f"README.md is {size} characters (limit {README_LIMIT}): move detail to docs/ and link it"
    )
    first = text.split("```bash\n", 1)[1].split("```", 1)[0].splitlines()
    assert [line.split("#")[0].strip() for line in first] == ["make demo", "make test"]
    assert "report:results" not in text
    assert "report:results:start" in (ROOT / "docs" / "results.md").read_text(encoding="utf-8")


@pytest.mark.parametrize("path", NOTES, ids=lambda p: p.name)
def test_notes_links_resolve(path: Path) -> None:
    assert broken_links(path) == []
