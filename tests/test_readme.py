"""The README is a front door: short, its first screen the pitch, the two commands and the tour, every relative
link resolving (files and GitHub heading anchors) and every `posttrain <command>` it shows a real command.
Nothing here loads a model; absolute http(s) links are not fetched."""
from __future__ import annotations

import contextlib
import io
import re
from pathlib import Path

import pytest

REPO = Path(__file__).resolve().parents[1]
README = REPO / "README.md"
LINKED_DOCS = [README, REPO / "verifiers" / "README.md"]
MAX_LINES = 284  # half of the 569 lines issue 33 found
MAX_BYTES = 22_500

INSTALL = ('python3 -m venv .venv && . .venv/bin/activate && pip install torch==2.13.0 && pip install ".[dev]" '
           '-c .ci/constraints.txt && posttrain sft --recipe tiny-summarize')


def slug(heading: str) -> str:
    """GitHub's anchor of a markdown heading: lowercase, punctuation dropped except hyphens and spaces (and
    underscores, which GitHub keeps), each space a hyphen."""
    text = re.sub(r"^#+\s*", "", heading.strip()).strip().lower()
    text = re.sub(r"[^\w\- ]", "", text)
    return text.replace(" ", "-")


def anchors(path: Path) -> set[str]:
    """The anchors of a markdown file's headings, outside code blocks; a repeated heading gets -1, -2, ..."""
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


def prose(text: str) -> str:
    """`text` without fenced code blocks and inline code spans (links there are not links)."""
    text = re.sub(r"^```.*?^```", "", text, flags=re.S | re.M)
    return re.sub(r"`[^`\n]*`", "", text)


def links(path: Path) -> list[str]:
    return re.findall(r"\]\(([^)\s]+)\)", prose(path.read_text(encoding="utf-8")))


@pytest.mark.parametrize("heading, want", [
    ("## Benchmarks (scripts/bench.py)", "benchmarks-scriptsbenchpy"),
    ("## E7: GRPO vs best-of-K and majority vote on tiny-math", "e7-grpo-vs-best-of-k-and-majority-vote-on-tiny-math"),
    ("## E7 on a real instruct model (smol-math)", "e7-on-a-real-instruct-model-smol-math"),
    ("## Real model: SmolLM2-135M-Instruct", "real-model-smollm2-135m-instruct"),
    ("## Lean forwards / engine internals", "lean-forwards--engine-internals"),
    ("## Several processes, GPUs", "several-processes-gpus"),
    ("### The GPU path: `scripts/gpu_check.py` and the suite on an NVIDIA H200, 2026-12-04",
     "the-gpu-path-scriptsgpu_checkpy-and-the-suite-on-an-nvidia-h200-2026-12-04"),
])
def test_slug_is_githubs(heading, want):
    assert slug(heading) == want


def test_repeated_headings_get_numbered_anchors(tmp_path):
    doc = tmp_path / "x.md"
    doc.write_text("# A\n## Notes\n```\n## not a heading\n```\n## Notes\n")
    assert anchors(doc) == {"a", "notes", "notes-1"}


def test_readme_is_short():
    text = README.read_text(encoding="utf-8")
    assert len(text.splitlines()) <= MAX_LINES, "README.md: move detail to RESULTS.md, data/README.md or docstrings"
    assert len(text.encode()) <= MAX_BYTES


def test_first_screen_has_the_two_commands_and_the_tour():
    first = "\n".join(README.read_text(encoding="utf-8").splitlines()[:60])
    assert INSTALL in first
    assert "\npython -m pytest -q\n" in first
    assert "## A five-command tour" in first
    tour = first[first.index("## A five-command tour"):]
    for command in ("posttrain dpo --recipe", "posttrain models fetch", "posttrain grpo --recipe smol-math",
                    "task.train_file=", "verifier=", "posttrain plot "):
        assert command in tour, command


@pytest.mark.parametrize("doc", LINKED_DOCS, ids=lambda p: str(p.relative_to(REPO)))
def test_every_relative_link_resolves(doc):
    bad = []
    for target in links(doc):
        if re.match(r"[a-z]+:", target):  # http(s), mailto: not fetched
            continue
        file, _, anchor = target.partition("#")
        path = (doc.parent / file).resolve() if file else doc
        if not path.exists():
            bad.append(f"{target}: no such file")
        elif anchor and path.suffix == ".md" and anchor not in anchors(path):
            bad.append(f"{target}: no heading with this anchor in {path.relative_to(REPO)}")
    assert not bad, f"{doc.relative_to(REPO)}: " + "; ".join(bad)


def test_every_posttrain_command_in_the_readme_exists():
    """Each `posttrain WORD` in a code block is a command `posttrain` knows: asking it for help never answers
    'unknown command' (a word that is not one does, the check of the check)."""
    from posttrain.cli import main

    blocks = re.findall(r"^```[a-z]*\n(.*?)^```", README.read_text(encoding="utf-8"), flags=re.S | re.M)
    named = {m for block in blocks for m in re.findall(r"(?:^|[\s;&|(])posttrain ([a-z][a-z_-]*)", block, flags=re.M)}
    assert {"sft", "dpo", "grpo", "plot", "models", "validate"} <= named

    def unknown(command: str) -> bool:
        err = io.StringIO()
        with contextlib.redirect_stdout(io.StringIO()), contextlib.redirect_stderr(err):
            try:
                main([command, "--help"])
            except SystemExit:  # argparse's --help
                pass
        return "unknown command" in err.getvalue()

    assert unknown("no-such-command")
    assert not [c for c in sorted(named) if unknown(c)]


def test_the_results_summary_quotes_only_current_figures():
    """Every decimal figure of the README's results summary is in RESULTS.md's current-figures table."""
    import re

    readme = (REPO / "README.md").read_text()
    start = readme.index("<!-- results-summary")
    summary = readme[start:readme.index("\n\n", readme.index("\n- ", start))]
    results = (REPO / "RESULTS.md").read_text()
    table = results[results.index("## Current figures"):]
    table = table[:table.index("\n## ", 1)] if "\n## " in table[1:] else table
    figures = re.findall(r"\d+\.\d+", summary)
    assert len(figures) >= 10
    missing = [f for f in figures if f not in table]
    assert not missing, f"README results figures not in RESULTS.md's current-figures table: {missing}"
