"""The "Writing a verifier" guide: its snippets are the example file, which loads by path, scores and audits clean."""
import os
import re
import subprocess
import sys

from posttrain.verifiers import combine, get_verifier, run_audit, score_batch
from posttrain.verifiers.registry import FunctionVerifier

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))
README = os.path.join(REPO, "verifiers", "README.md")
EXAMPLE = os.path.join(REPO, "verifiers", "examples", "multiple_choice.py")


def guide_snippets():
    text = open(README, encoding="utf-8").read()
    guide = text[text.index("## Writing a verifier"):text.index("## Benchmarks")]
    return re.findall(r"```python\n(.*?)```", guide, re.S)


def test_guide_snippets_are_the_example_file():
    source = open(EXAMPLE, encoding="utf-8").read()
    snippets = guide_snippets()
    assert len(snippets) >= 4
    for snippet in snippets:
        if snippet.startswith("mc = get_verifier"):
            continue  # usage, exercised below
        assert snippet in source, snippet


def test_example_loads_by_path_scores_and_audits_clean():
    spec = f"{EXAMPLE}:MultipleChoiceVerifier"
    v = get_verifier(spec)
    assert v.name == "multiple_choice"
    out = score_batch(v, ["It is (B).", "(A) or (B)", "no idea", "I think A. No, it is C."], ["B", "B", "B", "C"], workers=1)
    assert [(o.score, o.reason) for o in out] == [(1.0, "correct"), (0.0, "multiple answers"), (0.0, "no answer found"),
                                                 (1.0, "correct")]
    report = run_audit(v, v.audit_problems(20, seed=0), workers=1)
    assert report.ok, report.format()
    assert report.by_label()["two letters"]["run"] == 20


def test_example_usage_snippet_and_function():
    mc = get_verifier(f"{EXAMPLE}:MultipleChoiceVerifier")
    reward = combine((mc, 0.9), (get_verifier("format", tags="answer"), 0.1))
    assert reward.check("<answer>(C)</answer>", "C").score == 1.0
    assert reward.check("(C)", "C").score == 0.9
    fn = get_verifier(f"{EXAMPLE}:exact_letter")
    assert isinstance(fn, FunctionVerifier) and fn.check("(C)", "C").score == 1.0 and fn.check("C!", "C").score == 0.0


def test_example_cli_audit():
    proc = subprocess.run([sys.executable, "-m", "posttrain.verifiers.cli", "audit", f"{EXAMPLE}:MultipleChoiceVerifier",
                           "--n", "10", "--workers", "1"], cwd=REPO, capture_output=True, text=True, timeout=120)
    assert proc.returncode == 0, proc.stdout + proc.stderr
    assert "-> OK" in proc.stdout
