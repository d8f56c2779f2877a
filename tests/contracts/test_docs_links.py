"""Every relative link in the docs and the README lands: its file exists and, where it names a
heading (`page.md#anchor`), the page has that heading.  And every citation of a heading in code,
tests and docs (``docs/camera.md, 'Calibrated intervals'``) names a heading the page has.

Docs cite each other by heading ("docs/camera.md, 'Calibrated intervals'"); when a section moves to
a history page or is renamed, a link to its old anchor silently leads nowhere.  Anchors are GitHub's
slugs (lower case, punctuation but ``-`` and ``_`` dropped, spaces to ``-``, ``-1``, ``-2`` … for
repeats); links are read with markdown-it-py, so code spans and fenced blocks are not links.
"""

from __future__ import annotations

import functools
import re
from pathlib import Path

import pytest
from markdown_it import MarkdownIt

ROOT = Path(__file__).resolve().parents[2]
PAGES = sorted([*ROOT.glob("docs/**/*.md"), ROOT / "README.md"])
_MD = MarkdownIt("commonmark").enable("table")


def slug(text: str) -> str:
    """GitHub's anchor for a heading's text."""
    return re.sub(r"[^\w\- ]", "", text.strip().lower()).replace(" ", "-")


@functools.cache
def anchors(page: Path) -> frozenset[str]:
    tokens = _MD.parse(page.read_text(encoding="utf-8"))
    seen: dict[str, int] = {}
    out = set()
    for tok, nxt in zip(tokens, tokens[1:]):
        if tok.type != "heading_open":
            continue
        text = "".join(c.content for c in nxt.children or [] if c.type in ("text", "code_inline"))
        s = slug(text)
        n = seen.get(s, 0)
        seen[s] = n + 1
        out.add(s if n == 0 else f"{s}-{n}")
    return frozenset(out)


def links(page: Path) -> list[str]:
    return [
        c.attrs["href"]
        for tok in _MD.parse(page.read_text(encoding="utf-8"))
        for c in tok.children or []
        if c.type == "link_open"
    ]


def broken(page: Path) -> list[str]:
    bad = []
    for href in links(page):
        if re.match(r"^[a-z][a-z0-9+.-]*:", href):  # http:, mailto: ... not checked (no network)
            continue
        path, _, anchor = href.partition("#")
        target = (page.parent / path).resolve() if path else page
        if not target.exists():
            bad.append(f"{href}: no such file")
        elif anchor and target.suffix == ".md" and anchor not in anchors(target):
            where = target.relative_to(ROOT) if target.is_relative_to(ROOT) else target.name
            bad.append(f"{href}: no heading with that anchor in {where}")
    return bad


def test_slug_follows_github():
    assert slug("Look-alikes (`gap/selection.py: told_apart`)") == "look-alikes-gapselectionpy-told_apart"
    assert slug("Model-form term: the depth mode, and where d's bias comes from") == (
        "model-form-term-the-depth-mode-and-where-ds-bias-comes-from"
    )


def test_the_checker_finds_a_broken_link(tmp_path):
    (tmp_path / "b.md").write_text("# Other page\n")
    (tmp_path / "a.md").write_text(
        "# Top\n\n[ok](#top) [gone](#nowhere) [page](b.md#other-page) [heading](b.md#top) [file](c.md) `[code](d.md)`\n"
    )
    assert broken(tmp_path / "a.md") == [
        "#nowhere: no heading with that anchor in a.md",
        "b.md#top: no heading with that anchor in b.md",
        "c.md: no such file",
    ]


#: ``docs/<page>.md, 'Heading'`` (or "Heading"); the quote may hold an apostrophe, so the cited text is
#: checked as a prefix of a heading (``'Method'`` cites "Method (`gap/diagnose.py` and …)").
CITATION = re.compile(r"""docs/([\w/\-]+\.md),?\s+(['"])(.+?)\2""", re.S)
SOURCES = sorted(
    p
    for pattern in ("docs/**/*.md", "README.md", "Makefile", "*/**/*.py")
    for p in ROOT.glob(pattern)
    if not {".venv", "build", "data"} & set(p.relative_to(ROOT).parts) and p != Path(__file__).resolve()
)


def plain(text: str) -> str:
    """A heading or a cited text without markup, comment markers and line breaks, lower case."""
    text = re.sub(r"(?m)[`*]|^\s*#:?", "", text)
    return " ".join(text.split()).lower()


@functools.cache
def titles(page: Path) -> tuple[str, ...]:
    """The page's headings; a history page's "4k. " labels dropped."""
    tokens = _MD.parse(page.read_text(encoding="utf-8"))
    return tuple(
        re.sub(r"^\d+[a-z]*\.\s+", "", plain(nxt.content))
        for tok, nxt in zip(tokens, tokens[1:])
        if tok.type == "heading_open"
    )


def bad_citations(path: Path) -> list[str]:
    bad = []
    for m in CITATION.finditer(path.read_text(encoding="utf-8", errors="replace")):
        page, cited = ROOT / "docs" / m.group(1), plain(m.group(3))
        if len(cited) > 160:  # two quotes that do not belong together
            continue
        if not page.exists():
            bad.append(f"{m.group(0)!r}: no such page")
        elif not any(t.startswith(cited) for t in titles(page)):
            bad.append(f"{m.group(0)!r}: no such heading")
    return bad


def test_the_citation_checker_finds_a_missing_heading(tmp_path):
    src = tmp_path / "x.py"
    src.write_text("# docs/gap.md, 'Method' and docs/gap.md, 'No such heading' and docs/nope.md, 'X'\n")
    assert bad_citations(src) == [
        "\"docs/gap.md, 'No such heading'\": no such heading",
        "\"docs/nope.md, 'X'\": no such page",
    ]


@pytest.mark.parametrize("path", SOURCES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_cited_heading_exists(path):
    assert bad_citations(path) == []


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_lands(page):
    assert broken(page) == []
