"""Every relative link in README.md and docs/**/*.md resolves: the file exists and, for `#anchor`
links, the target Markdown file has a heading with that anchor (GitHub's rule)."""

import re
from functools import cache
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
PAGES = [REPO / "README.md", *sorted((REPO / "docs").rglob("*.md"))]
LINK = re.compile(r"!?\[(?:[^\]\[]|\[[^\]]*\])*\]\(([^)\s]+)(?:\s+\"[^\"]*\")?\)")
FENCE = re.compile(r"^\s*(```|~~~)")


def prose_lines(text: str):
    """The lines outside fenced code blocks and HTML comments (neither is rendered)."""
    fenced = False
    for line in re.sub(r"<!--.*?-->", "", text, flags=re.DOTALL).splitlines():
        if FENCE.match(line):
            fenced = not fenced
        elif not fenced:
            yield line


def link_targets(line: str) -> list[str]:
    """The link and image targets of a prose line; inline code holds none."""
    return LINK.findall(re.sub(r"`[^`]*`", "", line))


def slug(heading: str) -> str:
    """GitHub's anchor of a heading: lower case, punctuation dropped (not - or _), spaces to hyphens."""
    text = re.sub(r"[^\w\- ]", "", heading.strip().lower())
    return text.replace(" ", "-")


@cache
def anchors(page: Path) -> set[str]:
    seen: dict[str, int] = {}
    found = set()
    for line in prose_lines(page.read_text()):
        match = re.match(r"^#{1,6}\s+(.*?)\s*#*\s*$", line)
        if match:
            base = slug(match.group(1))
            n = seen.get(base, 0)
            found.add(base if n == 0 else f"{base}-{n}")
            seen[base] = n + 1
    return found


def links(page: Path):
    for line in prose_lines(page.read_text()):
        for target in link_targets(line):
            if not re.match(r"^[a-z][a-z0-9+.-]*:", target):  # http:, https:, mailto: are not checked
                yield target


def test_the_checker_reads_github_anchors_and_skips_code():
    assert slug("SDP h = 4 on Can: the zero primer costs the first descent (measured)") == (
        "sdp-h--4-on-can-the-zero-primer-costs-the-first-descent-measured"
    )
    assert slug("On time: delay-aware streaming (`--policy.max_delay`)") == (
        "on-time-delay-aware-streaming---policymax_delay"
    )
    text = "see [a](x.md#y)\n```\n[b](nothing.md)\n```\n`[c](code.md)` and ![d](img.png)\n"
    text += "<!--\n![e](e.png)\n-->"
    assert [t for line in prose_lines(text) for t in link_targets(line)] == ["x.md#y", "img.png"]


@pytest.mark.parametrize("page", PAGES, ids=lambda p: p.relative_to(REPO).as_posix())
def test_relative_links_resolve(page):
    broken = []
    for target in links(page):
        path, _, anchor = target.partition("#")
        resolved = (page.parent / path).resolve() if path else page
        if not resolved.exists():
            broken.append(f"{target}: no file {resolved}")
        elif anchor and resolved.suffix == ".md" and anchor not in anchors(resolved):
            broken.append(f"{target}: no heading with anchor #{anchor} in {resolved.relative_to(REPO)}")
    assert not broken, "broken links in " + page.relative_to(REPO).as_posix() + ":\n" + "\n".join(broken)
