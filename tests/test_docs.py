"""The front page and the docs: links that resolve, a short README, every doc reachable.

README.md is the front page: short, and linking every page under docs/ directly, so a
new user reaches each one in one step.  Every relative link in README.md and docs/*.md
must point at a file of the repository (and at a heading of it, for `file.md#anchor`).
No network: http(s) links are not followed.
"""

from __future__ import annotations

import re
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parent.parent
README = ROOT / "README.md"
DOCS = ROOT / "docs"
PAGES = [README, *sorted(DOCS.glob("*.md"))]

README_MAX_CHARS = 6000

_FENCE = re.compile(r"^\s*(```|~~~)")
_INLINE_CODE = re.compile(r"(`+)(?:(?!\1).)+?\1")
# [text](target) and ![alt](target), with an optional "title"; <target> allowed
_INLINE_LINK = re.compile(r"!?\[[^\]]*\]\(\s*<?([^)\s>]*)>?(?:\s+\"[^\"]*\")?\s*\)")
# [label]: target
_REF_LINK = re.compile(r"^\s{0,3}\[[^\]]+\]:\s*<?(\S+?)>?(?:\s+.*)?$")
_EXTERNAL = re.compile(r"^[a-z][a-z0-9+.-]*:", re.IGNORECASE)  # http:, https:, mailto:, ...


def _prose_lines(text: str, *, keep_inline_code: bool = False) -> list[str]:
    """The lines outside fenced code blocks, with inline code spans removed (or kept)."""
    out, in_fence = [], False
    for line in text.splitlines():
        if _FENCE.match(line):
            in_fence = not in_fence
            continue
        if not in_fence:
            out.append(line if keep_inline_code else _INLINE_CODE.sub("", line))
    return out


def _links(page: Path) -> list[str]:
    targets = []
    for line in _prose_lines(page.read_text(encoding="utf-8")):
        targets += _INLINE_LINK.findall(line)
        ref = _REF_LINK.match(line)
        if ref:
            targets.append(ref.group(1))
    return targets


def _relative_links(page: Path) -> list[str]:
    return [t for t in _links(page) if t and not _EXTERNAL.match(t) and not t.startswith("#")]


def _slug(heading: str) -> str:
    """GitHub's anchor for a heading: lower case, punctuation dropped, spaces to '-'."""
    text = re.sub(r"\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip().lower())  # a link: its text
    return re.sub(r"[^\w\- ]", "", text).replace(" ", "-")


def _anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    anchors = set()
    for line in _prose_lines(page.read_text(encoding="utf-8"), keep_inline_code=True):
        m = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if not m:
            continue
        slug = _slug(m.group(1))
        n = seen.get(slug, 0)
        seen[slug] = n + 1
        anchors.add(slug if n == 0 else f"{slug}-{n}")
    return anchors


@pytest.mark.parametrize("page", PAGES, ids=lambda p: str(p.relative_to(ROOT)))
def test_every_relative_link_points_at_a_file_of_the_repository(page: Path) -> None:
    broken = []
    for target in _relative_links(page):
        path, _, anchor = target.partition("#")
        dest = (page.parent / path).resolve()
        if not dest.exists():
            broken.append(f"{target}: no such file")
        elif ROOT not in dest.parents and dest != ROOT:
            broken.append(f"{target}: outside the repository")
        elif anchor and dest.suffix == ".md" and anchor not in _anchors(dest):
            broken.append(f"{target}: no heading #{anchor} in {dest.relative_to(ROOT)}")
    assert not broken, f"{page.relative_to(ROOT)}: " + "; ".join(broken)


def test_the_readme_is_a_short_front_page() -> None:
    size = len(README.read_text(encoding="utf-8"))
    assert size < README_MAX_CHARS, (
        f"README.md has {size} characters (limit {README_MAX_CHARS}): move the detail to "
        "docs/ and link it")


def test_the_readme_links_every_page_under_docs() -> None:
    linked = {(README.parent / t.partition("#")[0]).resolve() for t in _relative_links(README)}
    unlinked = [p.name for p in sorted(DOCS.glob("*.md")) if p.resolve() not in linked]
    assert not unlinked, f"docs not linked from README.md: {', '.join(unlinked)}"


def test_the_link_finder_sees_links_and_skips_code() -> None:
    page = (
        "See [a](docs/a.md), ![pic](docs/p.png) and [web](https://example.org/x).\n"
        "`[not a link](nowhere.md)` in code, [anchor](#here).\n"
        "```\n"
        "[also code](nowhere.md)\n"
        "```\n"
        "[ref]: docs/b.md\n"
    )
    lines = _prose_lines(page)
    found = [t for line in lines for t in _INLINE_LINK.findall(line)]
    assert found == ["docs/a.md", "docs/p.png", "https://example.org/x", "#here"]
    assert _REF_LINK.match(lines[-1]).group(1) == "docs/b.md"  # type: ignore[union-attr]
    assert _slug("The enabling switch (hold-to-run)") == "the-enabling-switch-hold-to-run"
    assert _slug("On the simulated robot (`make run`)") == "on-the-simulated-robot-make-run"
    assert _slug("Whole-body caps from ISO/TS 15066") == "whole-body-caps-from-isots-15066"
    assert _slug("`loop.rate_hz`, [links](x.md)") == "looprate_hz-links"
    assert "on-the-simulated-robot-make-run" in _anchors(DOCS / "running.md")
