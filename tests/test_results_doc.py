"""RESULTS.md stays readable: the current-figures table and the latest run of each headline, at most 1,200 lines;
superseded runs, per-run logs and long investigations live in docs/results-archive.md under the same headline
names. Every link between the two (and from README.md / ARCHITECTURE.md into them) resolves: the file exists and
its #anchor is a heading there, by GitHub's anchor rule. Pure text: nothing here imports torch."""
from __future__ import annotations

import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
RESULTS = REPO / "RESULTS.md"
ARCHIVE = REPO / "docs" / "results-archive.md"
MAX_LINES = 1_200  # issue 50 part 6: it had grown to 3,064
DOCS = [RESULTS, ARCHIVE]  # every link checked
CITING = [REPO / "README.md", REPO / "ARCHITECTURE.md"]  # their links into DOCS checked


def slug(heading: str) -> str:
    """GitHub's anchor of a markdown heading: lowercase; every character but letters, digits, spaces, hyphens and
    underscores dropped; each space a hyphen."""
    text = re.sub(r"^#+\s*", "", heading.strip()).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The anchors of a markdown file's headings, outside fenced code; a repeated heading gets -1, -2, ..."""
    seen: dict[str, int] = {}
    out = set()
    fenced = False
    for line in path.read_text(encoding="utf-8").splitlines():
        if line.startswith("```"):
            fenced = not fenced
            continue
        if fenced or not re.match(r"#{1,6} ", line):
            continue
        base = slug(line)
        n = seen.get(base, 0)
        out.add(base if n == 0 else f"{base}-{n}")
        seen[base] = n + 1
    return out


def links(path: Path) -> list[tuple[int, str]]:
    """(line number, target) of each markdown link outside fenced code and inline code spans."""
    out = []
    fenced = False
    for number, line in enumerate(path.read_text(encoding="utf-8").splitlines(), 1):
        if line.startswith("```"):
            fenced = not fenced
            continue
        if fenced:
            continue
        out += [(number, target) for target in re.findall(r"\]\(([^)\s]+)\)", re.sub(r"`[^`\n]*`", "", line))]
    return out


def broken(doc: Path, only_into: list[Path] | None = None) -> list[str]:
    """'file:line: link: why' for each local link of `doc` that does not resolve (restricted to links whose target
    file is one of `only_into`, when given)."""
    bad = []
    for number, target in links(doc):
        if re.match(r"[a-z]+:", target):  # http(s), mailto: not fetched
            continue
        file, _, anchor = target.partition("#")
        path = (doc.parent / file).resolve() if file else doc
        if only_into is not None and path not in only_into:
            continue
        where = f"{doc.relative_to(REPO)}:{number}: ({target})"
        if not path.exists():
            bad.append(f"{where}: no such file")
        elif anchor and path.suffix == ".md" and anchor not in anchors(path):
            bad.append(f"{where}: no heading with this anchor in {path.relative_to(REPO)}")
    return bad


@pytest.mark.parametrize("heading, want", [
    ("## Benchmarks (scripts/bench.py)", "benchmarks-scriptsbenchpy"),
    ("### Is E7 real's drift bf16? Yes: GRPO took pi_old from a bf16 sampler (issue 49 part 1), 2026-12-07",
     "is-e7-reals-drift-bf16-yes-grpo-took-pi_old-from-a-bf16-sampler-issue-49-part-1-2026-12-07"),
    ("## Lean forwards / engine internals", "lean-forwards--engine-internals"),
])
def test_slug_is_githubs(heading, want):
    assert slug(heading) == want


def test_anchors_number_repeats_and_skip_code(tmp_path):
    doc = tmp_path / "x.md"
    doc.write_text("# A\n## Runs\n```bash\n# not a heading\n```\n## Runs\n")
    assert anchors(doc) == {"a", "runs", "runs-1"}


def test_results_is_at_most_1200_lines():
    n = len(RESULTS.read_text(encoding="utf-8").splitlines())
    assert n <= MAX_LINES, (f"RESULTS.md: {n} lines, more than {MAX_LINES}: move superseded runs, per-run logs and "
                            f"long investigations to docs/results-archive.md under the same headline, and leave a "
                            f"one-line pointer")


def test_the_archive_exists_and_results_links_to_it():
    assert ARCHIVE.exists(), "docs/results-archive.md: missing (RESULTS.md's superseded runs live there)"
    into = [(n, t) for n, t in links(RESULTS) if t.partition("#")[0] == "docs/results-archive.md"]
    assert into, "RESULTS.md: no link to docs/results-archive.md"
    back = [(n, t) for n, t in links(ARCHIVE) if t.partition("#")[0] == "../RESULTS.md"]
    assert back, "docs/results-archive.md: no link back to RESULTS.md"


@pytest.mark.parametrize("doc", DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_every_link_resolves(doc):
    bad = broken(doc)
    assert not bad, "\n".join(bad)


@pytest.mark.parametrize("doc", CITING, ids=lambda p: str(p.relative_to(REPO)))
def test_links_into_results_and_its_archive_resolve(doc):
    bad = broken(doc, only_into=[p.resolve() for p in DOCS])
    assert not bad, "\n".join(bad)


def test_the_learning_check_bands_stay_in_results():
    """scripts/learning_check.py parses the bands between these markers in RESULTS.md."""
    text = RESULTS.read_text(encoding="utf-8")
    section = text[text.index("\n## The learning check\n"):]
    section = section[:section.index("\n## ", 1)]
    assert "<!-- learning-check-bands -->" in section and "<!-- /learning-check-bands -->" in section, \
        "RESULTS.md: the learning-check band markers left the section \"The learning check\""
