"""Docs pages are a user's guide: every ``docs/*.md`` page but the change log is at most 15,000
characters (issue 32); experiment logs live in ``docs/notes/``, which is exempt, and whose links
must resolve like the guide's."""

from __future__ import annotations

from pathlib import Path

import pytest
from test_docs_links import broken_links  # tests/ is on sys.path (rootdir import mode)

ROOT = Path(__file__).resolve().parents[1]
LIMIT = 15_000
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


@pytest.mark.parametrize("path", NOTES, ids=lambda p: p.name)
def test_notes_links_resolve(path: Path) -> None:
    assert broken_links(path) == []
