"""Every relative link of README.md and docs/*.md reaches a file, and every ``#anchor`` a heading of it; a
page's **Contents** list names its ``##`` and ``###`` headings, in order.

Anchors are made as GitHub makes them from a heading: lower case, every character but letters, digits,
``_``, ``-`` and spaces dropped, spaces turned into ``-``; a repeated heading gets ``-1``, ``-2``...
Inline links (their text may run over lines; a title and angle brackets allowed) and reference definitions
are checked; fenced code blocks hold no links and no headings.
"""
from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[1]
PAGES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md"))]
_INLINE = re.compile(r"\[(?:[^\[\]]|\[[^\[\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
_REFERENCE = re.compile(r"^ {0,3}\[[^\]]+\]:\s*<?([^\s>]+)>?", re.M)
_HEADING = re.compile(r"^(#{1,6})\s+(.*?)(?:\s+#+)?\s*$")
_CONTENTS_ITEM = re.compile(r"^( *)- \[(.*)\]\(#([^)]*)\)$")


def prose(text: str) -> str:
    """``text`` with the lines of fenced code blocks (and their fences) blanked: line numbers are kept."""
    out, fence = [], None
    for line in text.splitlines():
        mark = line.lstrip()[:3]
        if fence is None and mark in ("```", "~~~"):
            fence, line = mark, ""
        elif fence is not None:
            fence = None if mark == fence else fence
            line = ""
        out.append(line)
    return "\n".join(out)


def headings(text: str) -> list[tuple[int, str, str]]:
    """``(level, title, anchor)`` of a markdown page's headings, anchors as GitHub makes them."""
    out, seen = [], {}
    for line in prose(text).splitlines():
        m = _HEADING.match(line)
        if m:
            base = re.sub(r"[^\w\- ]", "", m.group(2).lower()).replace(" ", "-")
            n = seen.get(base, 0)
            seen[base] = n + 1
            out.append((len(m.group(1)), m.group(2), base if n == 0 else f"{base}-{n}"))
    return out


def broken_links(page: Path) -> list[str]:
    """``"line: target (why)"`` for every relative link of ``page`` that reaches no file or no heading."""
    text = prose(page.read_text())
    bad = []
    for m in [*_INLINE.finditer(text), *_REFERENCE.finditer(text)]:
        target = m.group(1)
        if re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: ...
            continue
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve() if path else page
        line = text.count("\n", 0, m.start()) + 1
        if not dest.exists():
            bad.append(f"{line}: {target} (no such file)")
        elif anchor and dest.suffix == ".md" and anchor not in {a for _l, _t, a in headings(dest.read_text())}:
            bad.append(f"{line}: {target} (no such heading)")
    return sorted(bad, key=lambda b: int(b.split(":")[0]))


def contents_list(text: str) -> list[tuple[int, str, str]] | None:
    """``(level, title, anchor)`` of the list under a page's ``**Contents**`` line (two spaces of indent: one
    level down from ``##``), or ``None`` without one."""
    lines = text.splitlines()
    if "**Contents**" not in lines:
        return None
    out = []
    for line in lines[lines.index("**Contents**") + 1:]:
        m = _CONTENTS_ITEM.match(line)
        if m:
            out.append((2 + len(m.group(1)) // 2, m.group(2), m.group(3)))
        elif line.strip() or out:
            break
    return out


def test_anchors_follow_github_rules():
    text = ("# Rigid SfM (`viewpoints/sfm.py`)\n## Small classes: 8 views, three seeds\n## Notes\n## Notes ##\n"
            "```\n# not a heading\n```\n~~~\n## nor this\n~~~\n")
    assert [a for _l, _t, a in headings(text)] == ["rigid-sfm-viewpointssfmpy", "small-classes-8-views-three-seeds",
                                                    "notes", "notes-1"]


def test_broken_links_are_found(tmp_path):
    (tmp_path / "other.md").write_text("# A page\n")
    page = tmp_path / "page.md"
    page.write_text("[ok](other.md#a-page) [web](https://example.org/x#y) [self](#top)\n# Top\n"
                    "[gone](missing.md) [bad](other.md#nowhere)\n```\n[in code](missing.md)\n```\n"
                    "[titled](gone2.md \"a title\") [<angle>](<other.md#a-page>) [text\nover lines](other.md#no)\n"
                    "[ref]: missing3.md#x\n")
    assert broken_links(page) == ["3: missing.md (no such file)", "3: other.md#nowhere (no such heading)",
                                  "7: gone2.md (no such file)", "7: other.md#no (no such heading)",
                                  "9: missing3.md#x (no such file)"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.name)
def test_every_link_of_the_docs_resolves(page):
    assert broken_links(page) == []


def test_a_contents_list_must_match_the_headings():
    page = "# T\n\n**Contents**\n\n- [A](#a)\n  - [B](#b)\n\n## A\n### B\n## C\n"
    assert contents_list(page) == [(2, "A", "a"), (3, "B", "b")]
    assert [h for h in headings(page) if h[0] in (2, 3)] != contents_list(page)  # C is missing from the list
    assert contents_list("# T\n## A\n") is None


@pytest.mark.parametrize("page", [p for p in PAGES if contents_list(p.read_text()) is not None], ids=lambda p: p.name)
def test_every_contents_list_names_its_pages_headings(page):
    text = page.read_text()
    assert contents_list(text) == [h for h in headings(text) if h[0] in (2, 3)]
