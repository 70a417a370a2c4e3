"""The manual holds together: every relative link of the README and docs/ resolves (the file, and the
heading an ``#anchor`` names, as GitHub spells it), the README stays short, and no page speaks of the
development set-up (``.ci``, a ``../shared`` folder, the real data's place) or of issue numbers."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README_MAX_LINES = 120

_FENCE = re.compile(r"^\s*(```|~~~)")
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")
_LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_CODE_SPAN = re.compile(r"(`+)(.+?)\1")
_FORBIDDEN = {
    "the CI script folder .ci": re.compile(r"(?<![\w.])\.ci\b"),
    "a ../shared folder": re.compile(r"\.\./shared\b"),
    "the real data's folder": re.compile(r"shared/realdata"),
    "an issue number": re.compile(r"(?<![\w&/(])#\d+\b|\bissues?\s+#?\d+\b", re.IGNORECASE),
}


def doc_files() -> list[Path]:
    return [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]


def prose_lines(text: str) -> list[tuple[int, str]]:
    """The lines outside fenced code blocks, numbered from 1."""
    lines, fenced = [], False
    for number, line in enumerate(text.splitlines(), start=1):
        if _FENCE.match(line):
            fenced = not fenced
            continue
        if not fenced:
            lines.append((number, line))
    return lines


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: link targets and code marks dropped, lower case, punctuation other
    than ``-`` and ``_`` removed, each space a ``-``."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading)
    text = text.replace("`", "").lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    seen: dict[str, int] = {}
    found = set()
    for _, line in prose_lines(path.read_text(encoding="utf-8")):
        match = _HEADING.match(line)
        if match is None:
            continue
        base = slug(match.group(2))
        count = seen.get(base, 0)
        seen[base] = count + 1
        found.add(base if count == 0 else f"{base}-{count}")
    return found


def links(path: Path) -> list[tuple[int, str]]:
    """Relative link targets of a page (outside code), with their line numbers."""
    found = []
    for number, line in prose_lines(path.read_text(encoding="utf-8")):
        line = _CODE_SPAN.sub("", line)
        for match in _LINK.finditer(line):
            target = match.group(1)
            if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.IGNORECASE):  # http:, https:, mailto:
                continue
            found.append((number, target))
    return found


def broken_links(path: Path, root: Path = REPO) -> list[str]:
    """One line per link of ``path`` whose file or heading is missing, paths relative to ``root``."""
    broken = []
    for number, target in links(path):
        file_part, _, anchor = target.partition("#")
        linked = (path.parent / file_part).resolve() if file_part else path
        where = f"{path.relative_to(root)}:{number}: {target}"
        if not linked.exists():
            broken.append(f"{where}: no such file")
        elif anchor and linked.suffix == ".md" and anchor not in anchors(linked):
            broken.append(f"{where}: no heading #{anchor} in {linked.relative_to(root)}")
    return broken


def test_the_manual_has_its_pages() -> None:
    names = {p.name for p in (REPO / "docs").glob("*.md")}
    for page in (
        "getting-started.md",
        "cameras-and-calibration.md",
        "tracking-and-states.md",
        "outputs-and-viewer.md",
        "batch-and-cluster.md",
        "troubleshooting.md",
        "configuration.md",
        "development.md",
    ):
        assert page in names


@pytest.mark.parametrize("path", doc_files(), ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(path: Path) -> None:
    assert broken_links(path) == []


def test_a_broken_link_and_a_missing_anchor_are_found(tmp_path: Path) -> None:
    # given: a page linking to a missing file, a missing heading and two good targets
    (tmp_path / "other.md").write_text("# Other page\n\n## Rigid groups (`--learn-groups`)\n")
    page = tmp_path / "page.md"
    page.write_text(
        "# Page\n\n[gone](gone.md) and [no heading](other.md#nowhere), "
        "[fine](other.md#rigid-groups---learn-groups) and [here](#page).\n"
        "```\n[in code](ignored.md)\n```\n"
    )
    # when
    broken = broken_links(page, root=tmp_path)
    # then
    assert broken == [
        "page.md:3: gone.md: no such file",
        "page.md:3: other.md#nowhere: no heading #nowhere in other.md",
    ]


def test_the_readme_is_short() -> None:
    lines = (REPO / "README.md").read_text(encoding="utf-8").splitlines()
    assert len(lines) <= README_MAX_LINES, f"README.md has {len(lines)} lines, at most {README_MAX_LINES}"


@pytest.mark.parametrize("path", doc_files(), ids=lambda p: str(p.relative_to(REPO)))
def test_no_page_speaks_of_the_development_set_up_or_issue_numbers(path: Path) -> None:
    found = [
        f"{path.relative_to(REPO)}:{number}: {what}: {line.strip()[:100]}"
        for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), start=1)
        for what, pattern in _FORBIDDEN.items()
        if pattern.search(line)
    ]
    assert found == []


@pytest.mark.parametrize(
    "line",
    ["run through `.ci/run`", "under ../shared/realdata", "see issue 35", "fixed in #33", "Issue 19's targets"],
)
def test_the_forbidden_patterns_catch_what_they_mean(line: str) -> None:
    assert any(pattern.search(line) for pattern in _FORBIDDEN.values())


@pytest.mark.parametrize(
    "line",
    ["[offline](#offline-replay)", "https://github.com/rerun-io/rerun/issues/12623", "a .cid file", "x.ci2"],
)
def test_the_forbidden_patterns_leave_ordinary_text_alone(line: str) -> None:
    assert not any(pattern.search(line) for pattern in _FORBIDDEN.values())


def test_every_page_the_code_names_exists() -> None:
    # help texts, messages and docstrings point users at pages of the manual by their path
    named = {
        (path.relative_to(REPO), match.group(0))
        for folder in ("ar_anchor", "tests")
        for path in (REPO / folder).rglob("*.py")
        for match in re.finditer(r"docs/[\w./-]+?\.md\b", path.read_text(encoding="utf-8"))
    }
    assert named, "no page named: the search is broken"
    missing = sorted(f"{where}: {page}" for where, page in named if not (REPO / page).is_file())
    assert missing == []
