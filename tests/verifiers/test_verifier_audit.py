"""The audit: math is clean on its own problems; naive verifiers get caught, with examples."""
import json
import time

import pytest

from posttrain.verifiers import get_verifier, run_audit
from posttrain.verifiers.base import AuditProblem, Verdict, Verifier

PROBLEMS = [AuditProblem(prompt=f"What is {a} times 7?", reference=str(7 * a), gold=f"{a} * 7 = {7 * a}. The answer is {7 * a}.")
            for a in (3, 5, 11, 13, 17)]


class Substring(Verifier):
    """The classic naive check: credit when the reference appears anywhere."""

    name = "substring"

    def check(self, completion, reference):
        ok = str(reference) in completion
        return Verdict(1.0 if ok else 0.0, "found" if ok else "absent")


class Always(Verifier):
    def __init__(self, score):
        self.name, self.score = f"always{score}", score

    def check(self, completion, reference):
        return Verdict(self.score, "constant")


class RaisesOnEmpty(Verifier):
    name = "raises_on_empty"

    def check(self, completion, reference):
        if not completion:
            raise IndexError("empty completion")
        return Verdict(1.0 if completion.rstrip(".").endswith(str(reference)) else 0.0, "suffix")


class SlowOnHuge(Verifier):
    name = "slow_on_huge"
    timeout_s = 0.5

    def check(self, completion, reference):
        if len(completion) > 100_000:
            time.sleep(60)
        return Verdict(1.0 if completion.rstrip(".").endswith(str(reference)) else 0.0, "suffix")


def test_math_audit_is_clean_on_its_own_problems():
    v = get_verifier("math")
    report = run_audit(v, v.audit_problems(30, seed=0), workers=2)
    assert report.ok, report.format()
    assert (len(report.false_positives), len(report.false_negatives), len(report.errors)) == (0, 0, 0)
    labels = report.by_label()
    for label in ("gold", "empty", "whitespace", "garbage", "prompt echo", "another problem's gold",
                  "several candidates", "several candidates (list)", "buried in ramble", "retraction",
                  "huge garbage", "huge output", "boxed hedge", "power tower"):
        assert labels[label]["run"] > 0, label
    assert labels["gold"]["run"] == 30 and labels["huge output"]["run"] == 2
    assert report.timeouts == 0 and report.crashes == 0


MATH_CATEGORY_LABELS = (
    "factorial of the answer", "factorial in prose", "factorial form", "number words", "wrong number words",
    "repeating decimal", "truncated decimal", "space thousands in prose", "retraction then answer",
    "answer then retraction", "negated alternative", "negated answer phrase", "sign-blind identity",
    "absolute value added", "absolute value dropped", "matrix entry changed", "matrix flattened",
    "matrix transposed", "vector as a tuple", "vector transposed", "unevaluated arithmetic")


def test_math_audit_covers_every_answer_category():
    from posttrain.verifiers.math_answer.verifier import _GENERATORS

    v = get_verifier("math")
    n = 2 * len(_GENERATORS)
    report = run_audit(v, v.audit_problems(n, seed=1), workers=2, huge_problems=0)
    assert report.ok, report.format()
    labels = report.by_label()
    for label in MATH_CATEGORY_LABELS:
        assert labels.get(label, {}).get("run", 0) > 0, label
    refs = [p.reference for p in v.audit_problems(n, seed=1)]
    assert any("pmatrix" in r and "&" in r for r in refs) and any("|" in r for r in refs)


def test_math_audit_in_strict_mode_is_clean():
    strict = get_verifier("math", require_simplified=True)
    problems = strict.audit_problems(27, seed=2)
    report = run_audit(strict, problems, workers=2, huge_problems=0)
    assert report.ok, report.format()
    closed = [c for c in report.cases if c.label == "unevaluated arithmetic"]
    assert closed and all(c.expected == 0.0 and c.score == 0.0 for c in closed)


def test_knights_audit_is_clean_with_other_role_words():
    v = get_verifier("knights_knaves")
    problems = v.audit_problems(14, seed=0)
    assert {tuple(p.reference.get("roles", ("knight", "knave"))) for p in problems} >= {
        ("knight", "knave"), ("saint", "sinner"), ("hero", "villain"), ("truth-teller", "liar"), ("knave", "knight")}
    report = run_audit(v, problems, workers=2, huge_problems=0)
    assert report.ok, report.format()
    labels = report.by_label()
    for label in ("plural capitalised role words", "truth-teller / liar words", "knight / knave words",
                  "standard reading of swapped words", "another puzzle's role words", "mixed words, one wrong"):
        assert labels.get(label, {}).get("run", 0) > 0, label


def test_naive_substring_check_is_caught():
    report = run_audit(Substring(), PROBLEMS, workers=1)
    assert not report.ok
    fp_labels = {c.label for c in report.false_positives}
    assert {"several candidates", "several candidates (list)", "buried in ramble", "retraction", "huge output"} <= fp_labels
    assert "gold" not in fp_labels and not report.false_negatives
    text = report.format()
    assert "PROBLEMS FOUND" in text and "false positives (first 5 of" in text and "[several candidates]" in text


def test_constant_verifiers_are_caught():
    yes = run_audit(Always(1.0), PROBLEMS, workers=1)
    assert {"empty", "garbage", "whitespace", "prompt echo"} <= {c.label for c in yes.false_positives}
    no = run_audit(Always(0.0), PROBLEMS, workers=1)
    assert [c.label for c in no.false_negatives] == ["gold"] * len(PROBLEMS)
    assert not no.false_positives


def test_verifier_errors_are_recorded_and_the_audit_goes_on():
    report = run_audit(RaisesOnEmpty(), PROBLEMS, workers=1)
    errors = report.errors
    assert len(errors) == len(PROBLEMS) and {c.label for c in errors} == {"empty"}
    assert errors[0].reason == "raised IndexError: empty completion"
    assert not report.ok
    assert report.by_label()["gold"] == {"run": 5, "false positive": 0, "false negative": 0, "error": 0}


def test_hangs_on_huge_outputs_are_counted_as_timeouts():
    report = run_audit(SlowOnHuge(), PROBLEMS, workers=2, huge_problems=1)
    assert report.timeouts == 2  # huge garbage + huge output of problem 0
    huge = [c for c in report.cases if c.label.startswith("huge")]
    assert [(c.reason, c.score, c.outcome) for c in huge] == [("timeout", 0.0, "ok")] * 2


def test_report_serialises():
    report = run_audit(Substring(), PROBLEMS[:3], workers=1, huge_problems=0)
    data = json.loads(json.dumps(report.to_dict()))
    assert data["verifier"] == "substring" and data["problems"] == 3 and data["ok"] is False
    assert data["false_positives"] == len(report.false_positives) == len(data["failures"])
    assert all(f["outcome"] == "false positive" for f in data["failures"])
    assert all(len(f["completion"]) < 400 for f in data["failures"])


def test_audit_needs_problems():
    with pytest.raises(ValueError):
        run_audit(Substring(), [])
