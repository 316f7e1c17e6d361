"""Every relative link of the documentation (README.md, docs/*.md, tests/README.md) reaches its file, and every
``#anchor`` a heading of that file, as GitHub renders them. The guides link into their logs section by section
(docs/training.md → docs/training_log.md, …), so a heading renamed or moved there breaks links silently; this
catches it. The anchor rule is GitHub's (github-slugger: lower case, characters other than letters, digits,
``-``, ``_`` and spaces dropped, each space a ``-``, a repeated heading suffixed ``-1``, ``-2``, …), checked
against anchors GitHub gives for such headings."""

from __future__ import annotations

import re
import unicodedata
from pathlib import Path

import pytest

ROOT = Path(__file__).resolve().parents[2]
DOC_FILES = [ROOT / "README.md", *sorted((ROOT / "docs").glob("*.md")), ROOT / "tests" / "README.md"]

LINK = re.compile(r"!?\[(?:[^\[\]]|\[[^\]]*\])*\]\(\s*<?([^)\s>]+)>?(?:\s+\"[^\"]*\")?\s*\)")
FENCE = re.compile(r"^\s*(```|~~~)")
HEADING = re.compile(r"^(#{1,6})\s+(.*?)\s*#*\s*$")


def _prose_lines(text: str) -> list[str]:
    """The lines of a markdown text with fenced blocks blanked and inline code spans masked (no links there)."""
    out, fenced = [], False
    for line in text.splitlines():
        if FENCE.match(line):
            fenced = not fenced
            out.append("")
        elif fenced:
            out.append("")
        else:
            out.append(re.sub(r"`[^`]*`", lambda m: " " * len(m.group(0)), line))
    return out


def github_slug(heading: str) -> str:
    """GitHub's anchor of a heading's text (before the duplicate suffix)."""
    text = re.sub(r"!?\[([^\]]*)\]\([^)]*\)", r"\1", heading.strip().lower())  # a link: its text
    text = re.sub(r"<[^>]+>", "", text)  # inline HTML
    kept = (ch for ch in text if ch in " -_" or unicodedata.category(ch)[0] in "LN" or unicodedata.category(ch) == "Mn")
    return "".join("-" if ch == " " else ch for ch in kept)


def anchors(path: Path) -> set[str]:
    """The anchors of a markdown file: its headings' slugs (repeats suffixed) and explicit ``<a name|id=…>``."""
    text = path.read_text(encoding="utf-8")
    seen: dict[str, int] = {}
    found = set(re.findall(r"<a\s+(?:name|id)=\"([^\"]+)\"", text))
    for line, raw in zip(_prose_lines(text), text.splitlines()):
        m = HEADING.match(raw) if line else None
        if m:
            base = github_slug(m.group(2))
            n = seen.get(base, 0)
            seen[base] = n + 1
            found.add(base if n == 0 else f"{base}-{n}")
    return found


def broken_links(files: list[Path]) -> tuple[int, list[str]]:
    """(the number of relative links in ``files``, a line for each that does not resolve)."""
    total, broken, cache = 0, [], {}
    for f in files:
        for i, line in enumerate(_prose_lines(f.read_text(encoding="utf-8")), 1):
            for target in LINK.findall(line):
                if re.match(r"^[a-z][a-z0-9+.-]*:", target, re.I):  # http:, mailto:, …
                    continue
                total += 1
                path_part, _, frag = target.partition("#")
                dest = (f.parent / path_part).resolve() if path_part else f
                where = f"{f}:{i}: {target}"
                if not dest.exists():
                    broken.append(f"{where} (no such file)")
                elif frag and dest.suffix != ".md":
                    broken.append(f"{where} (an anchor into a file that is not markdown)")
                elif frag and frag not in cache.setdefault(dest, anchors(dest) if dest.suffix == ".md" else set()):
                    broken.append(f"{where} (no heading with the anchor #{frag})")
    return total, broken


@pytest.mark.parametrize("heading, anchor", [
    ("Hello World", "hello-world"),
    ("What's new?", "whats-new"),
    ("The `quick` preset", "the-quick-preset"),
    ("## `model.kind = mosaic` (`hsicam.models.mosaic`)"[3:], "modelkind--mosaic-hsicammodelsmosaic"),
    ("Spectral or spatial? The spectral oracle (session 18)", "spectral-or-spatial-the-spectral-oracle-session-18"),
    ("DOE/CFA ablation, by session", "doecfa-ablation-by-session"),
    ("snake_case and Ümlaut", "snake_case-and-ümlaut"),
    ("A [link](x.md) in a heading", "a-link-in-a-heading"),
])
def test_github_slug(heading, anchor):
    assert github_slug(heading) == anchor


def test_repeated_headings_get_suffixes_and_fenced_ones_none(tmp_path):
    doc = tmp_path / "a.md"
    doc.write_text("# Notes\n\n## Notes\n\n```\n# not a heading\n```\n\n### Notes\n<a name=\"here\"></a>\n")
    assert anchors(doc) == {"notes", "notes-1", "notes-2", "here"}


def test_a_broken_file_or_anchor_is_reported_and_code_is_not_read(tmp_path):
    (tmp_path / "b.md").write_text("# Part one\n")
    doc = tmp_path / "a.md"
    doc.write_text("[ok](b.md#part-one) [gone](c.md) [bad](b.md#part-two) [web](https://example.org/x#y)\n"
                   "`[code](nowhere.md)`\n```\n[fenced](nowhere.md)\n```\n[self](#top)\n# Top\n")
    total, broken = broken_links([doc])
    assert total == 4
    assert broken == [f"{doc}:1: c.md (no such file)", f"{doc}:1: b.md#part-two (no heading with the anchor #part-two)"]


def test_every_relative_link_of_the_docs_resolves():
    total, broken = broken_links(DOC_FILES)
    assert total > 100, total  # the guides link into their logs: a parser that found none would pass vacuously
    assert not broken, "\n".join(broken)
