"""The docs' cross-references hold: every ``docs/<name>.md`` that the configs, the code, the scripts and the docs
name exists (references in ``docs/`` and measurements in ``docs/measurements/``), and every section such a
reference names in double quotes starts a section of that file.

A reference is the path followed, in the same sentence or comment, by one or more quoted names, e.g.
``docs/nrc.md, "Thick clouds"``, ``docs/nrc.md "Unbiased NRC"`` or
``(docs/measurements/nrc_defaults.md, "Defaults by measurement" and "Training budget on small images")``; a comment or a
paragraph may wrap it over lines. A section is a heading (``#`` to ``####``) or a paragraph's bold lead
(``**Light selection** (...)``, also in a list item), which the docs use as sub-sections. A name matches a
section whose text starts with it, backticks ignored. Markdown links to ``#anchors`` (the contents lists) must
resolve too. The references (``docs/*.md`` but the generated results page and its intro) carry no dated text:
dated runs go to ``docs/measurements/``. Reads files only: no rendering.
"""

import re
from pathlib import Path

REPO = Path(__file__).resolve().parents[1]
SOURCES = ("conf/**/*.yaml", "nrc/**/*.py", "scripts/*.py", "README.md", "docs/*.md", "docs/measurements/*.md")

NAME = r'"[^"\n]+"'
# the path; closing backticks / brackets; at least one of ", (" or a space; the quoted names joined by "," / and / or
REF = re.compile(r'(?<![\w/.-])docs/((?:measurements/)?[\w-]+)\.md[`\])]*'
                 rf'(?:[\s,(]+(?:sections?\s+)?({NAME}(?:\s*,?\s*(?:\band\s+|\bor\s+)?{NAME})*))?')
HEADING = re.compile(r"^#{1,4}\s+(.+?)\s*#*\s*$")
BOLD_LEAD = re.compile(r"^\s*(?:[-*]\s+)?\*\*(.+?)\*\*")
LINK = re.compile(r"\]\(((?:docs/|\.\./)?(?:measurements/)?[\w-]+\.md)?#([^)\s]+)\)")
DATE = re.compile(r"\b20\d\d-\d\d-\d\d\b")
NOTEBOOK = ("results.md", "results_intro.md")  # generated from dated runs / its hand-written intro


def _sources() -> list[Path]:
    return sorted({p for pattern in SOURCES for p in REPO.glob(pattern) if p.is_file()})


def _joined(text: str) -> str:
    """The text with its line breaks (and a wrapped comment's ``#``) turned into spaces."""
    return re.sub(r"[ \t]*\n[ \t]*(?:#[ \t]*)?", " ", text)


def _clean(name: str) -> str:
    return " ".join(name.replace("`", "").split())


def _lines_outside_code(text: str) -> list[str]:
    lines, fenced = [], False
    for line in text.splitlines():
        if line.lstrip().startswith("```"):
            fenced = not fenced
        elif not fenced:
            lines.append(line)
    return lines


def _sections(doc: Path) -> list[str]:
    out = []
    for line in _lines_outside_code(doc.read_text(encoding="utf-8")):
        m = HEADING.match(line) or BOLD_LEAD.match(line)
        if m:
            out.append(_clean(m.group(1)))
    return out


def _anchors(doc: Path) -> set[str]:
    """GitHub's heading anchors: lower case, punctuation dropped, spaces to hyphens, repeats numbered."""
    anchors, counts = set(), {}
    for line in _lines_outside_code(doc.read_text(encoding="utf-8")):
        m = HEADING.match(line)
        if m:
            slug = re.sub(r"[^\w\- ]", "", m.group(1).strip().lower()).replace(" ", "-")
            n = counts.get(slug, 0)
            counts[slug] = n + 1
            anchors.add(f"{slug}-{n}" if n else slug)
    return anchors


def _references() -> list[tuple[str, str, list[str]]]:
    """``(source, docs/<name>.md, [quoted names])`` for every ``docs/<name>.md`` in the sources."""
    refs = []
    for src in _sources():
        for m in REF.finditer(_joined(src.read_text(encoding="utf-8"))):
            names = re.findall(r'"([^"]+)"', m.group(2) or "")
            refs.append((str(src.relative_to(REPO)), f"docs/{m.group(1)}.md", names))
    return refs


def test_the_pattern_finds_the_known_references():
    refs = _references()
    assert ("conf/renderer/nrc.yaml", "docs/nrc.md", ["Frames bounded by work", "Current defaults and why"]) in refs
    assert ("conf/renderer/nrc.yaml", "docs/measurements/nrc_defaults.md", ["Thick clouds"]) in refs  # wrapped comment
    assert ("conf/renderer/nrc.yaml", "docs/nrc.md", ["Unbiased NRC"]) in refs  # no comma
    assert sum(bool(names) for _, _, names in refs) >= 30


def test_named_docs_exist_and_quoted_sections_start_a_heading():
    problems, sections = [], {}
    for src, doc, names in _references():
        path = REPO / doc
        if not path.is_file():
            problems.append(f"{src}: {doc} does not exist")
            continue
        if doc not in sections:
            sections[doc] = _sections(path)
        problems += [f'{src}: {doc}, "{name}" starts no heading there' for name in names
                     if not any(s.startswith(_clean(name)) for s in sections[doc])]
    assert not problems, "\n".join(problems)


def test_markdown_anchor_links_resolve():
    problems = []
    docs = [*sorted((REPO / "docs").glob("*.md")), *sorted((REPO / "docs/measurements").glob("*.md"))]
    for src in [REPO / "README.md", *docs]:
        for m in LINK.finditer(src.read_text(encoding="utf-8")):
            target = src if not m.group(1) else (REPO / m.group(1) if m.group(1).startswith("docs/")
                                                 else src.parent / m.group(1))
            if not target.is_file() or m.group(2) not in _anchors(target):
                problems.append(f"{src.relative_to(REPO)}: no anchor #{m.group(2)} in {target.relative_to(REPO)}")
    assert not problems, "\n".join(problems)


def test_references_carry_no_dates():
    """A reference says how it works and why; the dated runs behind it live in docs/measurements/."""
    problems = [f"{doc.relative_to(REPO)}:{i}: {line.strip()[:80]}"
                for doc in [REPO / "README.md", *sorted((REPO / "docs").glob("*.md"))] if doc.name not in NOTEBOOK
                for i, line in enumerate(doc.read_text(encoding="utf-8").splitlines(), 1) if DATE.search(line)]
    assert not problems, "\n".join(problems)
