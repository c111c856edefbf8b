"""Every relative link of README.md and docs/*.md reaches a file, and every ``#anchor`` a heading of it.

Anchors are made as GitHub makes them from a heading: lower case, every character but letters, digits,
``_``, ``-`` and spaces dropped, spaces turned into ``-``; a repeated heading gets ``-1``, ``-2``...
Links inside fenced code blocks are not links.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
_LINK = re.compile(r"\[[^\]]*\]\(([^)\s]+)\)")
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*$")


def _prose_lines(text: str):
    """``(line number, line)`` of the lines outside fenced code blocks."""
    fenced = False
    for i, line in enumerate(text.splitlines(), 1):
        if line.lstrip().startswith("```"):
            fenced = not fenced
            continue
        if not fenced:
            yield i, line


def heading_anchors(text: str) -> set[str]:
    """The anchors of a markdown page's headings, as GitHub makes them."""
    out, seen = set(), {}
    for _i, line in _prose_lines(text):
        m = _HEADING.match(line)
        if m:
            base = re.sub(r"[^\w\- ]", "", m.group(2).lower()).replace(" ", "-")
            n = seen.get(base, 0)
            seen[base] = n + 1
            out.add(base if n == 0 else f"{base}-{n}")
    return out


def broken_links(page: Path) -> list[str]:
    """``"line: target (why)"`` for every relative link of ``page`` that reaches no file or no heading."""
    bad = []
    for i, line in _prose_lines(page.read_text()):
        for target in _LINK.findall(line):
            if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: ...
                continue
            path, _, anchor = target.partition("#")
            dest = (page.parent / path).resolve() if path else page
            if not dest.exists():
                bad.append(f"{i}: {target} (no such file)")
            elif anchor and dest.suffix == ".md" and anchor not in heading_anchors(dest.read_text()):
                bad.append(f"{i}: {target} (no such heading)")
    return bad


def test_anchors_follow_github_rules():
    text = "# Rigid SfM (`viewpoints/sfm.py`)\n## Small classes: 8 views, three seeds\n## Notes\n## Notes\n" \
           "```\n# not a heading\n```\n"
    assert heading_anchors(text) == {"rigid-sfm-viewpointssfmpy", "small-classes-8-views-three-seeds", "notes",
                                     "notes-1"}


def test_broken_links_are_found(tmp_path):
    (tmp_path / "other.md").write_text("# A page\n")
    page = tmp_path / "page.md"
    page.write_text("[ok](other.md#a-page) [web](https://example.org/x#y) [self](#top)\n# Top\n"
                    "[gone](missing.md) [bad](other.md#nowhere)\n```\n[in code](missing.md)\n```\n")
    assert broken_links(page) == ["3: missing.md (no such file)", "3: other.md#nowhere (no such heading)"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_link_of_the_docs_resolves(page):
    assert broken_links(page) == []
