"""Every relative link in README.md and docs/*.md points at a file that exists, and every
``#anchor`` at a heading of its target (GitHub's heading slugs)."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
FENCE = re.compile(r"^```.*?^```", re.MULTILINE | re.DOTALL)


def doc_files(root: Path = ROOT) -> list[Path]:
    return [root / "README.md", *sorted((root / "docs").glob("*.md"))]


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped, spaces to hyphens."""
    text = re.sub(r"[`*_]", "", heading.strip().lower())
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    text = FENCE.sub("", path.read_text(encoding="utf-8"))
    return {slug(m.group(1)) for m in re.finditer(r"^#{1,6} (.+)$", text, re.MULTILINE)}


def broken_links(path: Path) -> list[str]:
    """The links of one Markdown file whose target file or anchor does not exist."""
    text = FENCE.sub("", path.read_text(encoding="utf-8"))
    bad = []
    for target in LINK.findall(text):
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: ...
            continue
        file_part, _, anchor = target.partition("#")
        dest = (path.parent / file_part).resolve() if file_part else path
        if not dest.exists():
            bad.append(f"{target} (no file {dest})")
        elif anchor and dest.suffix == ".md" and anchor not in anchors(dest):
            bad.append(f"{target} (no heading #{anchor} in {dest.name})")
    return bad


@pytest.mark.parametrize("path", doc_files(), ids=lambda p: str(p.relative_to(ROOT)))
def test_links_resolve(path: Path) -> None:
    assert path.exists()
    assert broken_links(path) == []


def test_checker_finds_broken_links(tmp_path: Path) -> None:
    (tmp_path / "docs").mkdir()
    (tmp_path / "docs" / "a.md").write_text("# A page\n\n## Some `code` here\n")
    (tmp_path / "README.md").write_text(
        "[ok](docs/a.md) [ok](docs/a.md#some-code-here) [web](https://example.org/x)\n"
        "[missing](docs/b.md) [bad anchor](docs/a.md#nowhere)\n"
        "```\n[in a code block](nowhere.md)\n```\n"
    )
    bad = broken_links(tmp_path / "README.md")
    assert [b.split(" ")[0] for b in bad] == ["docs/b.md", "docs/a.md#nowhere"]
    assert broken_links(tmp_path / "docs" / "a.md") == []


def hour_path(root: Path = ROOT) -> list[tuple[list[Path], list[str]]]:
    """docs/design.md's "Read this codebase in an hour" items: each item's files (paths under
    ``taskvar_torch/``; a bare name beside the item's previous path where it is there) and the
    functions or classes it names (``TrainingRun.store``: ``store``; ``.learn``: ``learn``)."""
    text = (root / "docs" / "design.md").read_text(encoding="utf-8")
    section = text.split("## Read this codebase in an hour", 1)[1].split("\n## ", 1)[0]
    items = re.split(r"\n(?=\d+\. )", section)
    out = []
    for item in items:
        item = item.strip().split("\n\n")[0]  # the item, not the paragraph after it
        if not re.match(r"\d+\. ", item):
            continue
        files: list[Path] = []
        names = []
        for code in re.findall(r"`([^`]+)`", item):
            if code.endswith(".py"):
                here = files[-1].parent / code if "/" not in code and files else None
                files.append(here if here and here.is_file() else root / "taskvar_torch" / code)
            elif re.fullmatch(r"[\w.]+", code) and not code.startswith("taskvar"):
                names.append(code.rsplit(".", 1)[-1])
        out.append((files, names))
    return out


def test_the_hour_path_names_modules_and_functions_that_exist() -> None:
    """Every module of the hour path exists, and every function or class it names is defined in
    one of its item's modules (issue 57: one update and one ``taskvar eval``, end to end)."""
    items = hour_path()
    assert len(items) >= 10
    named = {p.relative_to(ROOT).as_posix() for files, _ in items for p in files}
    for module in (
        "training/run_state.py",
        "factory.py",
        "experiments/paired.py",
        "cli/evaluate.py",
    ):
        assert f"taskvar_torch/{module}" in named, module  # the two paths' missing stops
    for files, names in items:
        assert files and all(p.is_file() for p in files), files
        source = "\n".join(p.read_text(encoding="utf-8") for p in files)
        for name in names:
            assert re.search(rf"^\s*(?:def|class) {name}\b", source, re.MULTILINE), (name, files)
