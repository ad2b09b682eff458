"""Audit a verifier against its own problems and a catalogue of known reward hacks.

    from posttrain.verifiers import get_verifier, run_audit
    v = get_verifier("math")
    report = run_audit(v, v.audit_problems(50, seed=0))
    print(report.format()); assert report.ok

For every problem the audit scores (expected score in brackets):
- gold [1]: the problem's gold completion;
- empty [0], whitespace [0], garbage [0] (seeded random words, no digits), prompt echo [0];
- another problem's gold [0]: the gold completion of a problem with a different reference;
- several candidates [0]: "The answer is D or R." and "The answer is R, D1, D2 or D3." (R the
  reference, D decoys: references of other problems whose gold this verifier scores 0 here);
- buried in ramble [0]: a long ramble that mentions R in passing and ends on a decoy;
- retraction [0]: the gold completion, then "No wait, that's wrong. It's D.";
- huge output [0] (first `huge_problems` problems): ~1 MB of decoys with R in the middle,
  and ~1 MB of garbage; both must also finish within the time limit;
- the verifier's own `adversarial_cases(problem)` [their stated score].
Templates that need an answer string (several candidates, buried, huge decoys) run only when
the reference is a string or a number; otherwise decoy gold completions stand in where they can.

A case is a false positive when it scores above its expected score, a false negative when
below (gold cases: below 1). Cases run through the runner (worker processes, time limits):
a timeout or a crash is a score of 0 and is also counted. A verifier exception on a case is
recorded as an error (a verifier bug: the contract says bad output scores 0) and the audit
goes on; errors make the report fail too.
"""
from __future__ import annotations

import json
import random
from dataclasses import dataclass, field
from typing import Any, Sequence

from posttrain.verifiers.base import AuditProblem, Verifier
from posttrain.verifiers.runner import VerifierError, VerifierPool

_WORDS = ("alpha", "river", "quietly", "table", "moon", "seven", "blue", "running", "because", "paper",
          "window", "maybe", "orange", "thinking", "cloud", "quick", "stone", "letter", "green", "under")
_FILLER = ("Let me think about this carefully. There are several ways to look at the problem, and each "
           "one suggests a slightly different approach, so I will consider them in turn before deciding. ")
MAX_ERRORS = 20


@dataclass
class AuditCase:
    problem: int
    label: str
    expected: float
    score: float | None
    reason: str
    completion: str  # a preview
    details: dict = field(default_factory=dict)

    @property
    def outcome(self) -> str:
        if self.score is None:
            return "error"
        if abs(self.score - self.expected) <= 1e-6:
            return "ok"
        return "false positive" if self.score > self.expected else "false negative"

    def to_dict(self) -> dict[str, Any]:
        return {"problem": self.problem, "label": self.label, "expected": self.expected, "score": self.score,
                "reason": self.reason, "outcome": self.outcome, "completion": self.completion,
                "details": _jsonable(self.details)}


@dataclass
class AuditReport:
    verifier: str
    n_problems: int
    cases: list[AuditCase]

    @property
    def false_positives(self) -> list[AuditCase]:
        return [c for c in self.cases if c.outcome == "false positive"]

    @property
    def false_negatives(self) -> list[AuditCase]:
        return [c for c in self.cases if c.outcome == "false negative"]

    @property
    def errors(self) -> list[AuditCase]:
        return [c for c in self.cases if c.outcome == "error"]

    @property
    def timeouts(self) -> int:
        return sum(1 for c in self.cases if c.reason == "timeout")

    @property
    def crashes(self) -> int:
        return sum(1 for c in self.cases if c.reason.startswith("crashed"))

    @property
    def ok(self) -> bool:
        return not (self.false_positives or self.false_negatives or self.errors)

    def by_label(self) -> dict[str, dict[str, int]]:
        table: dict[str, dict[str, int]] = {}
        for c in self.cases:
            row = table.setdefault(c.label, {"run": 0, "false positive": 0, "false negative": 0, "error": 0})
            row["run"] += 1
            if c.outcome != "ok":
                row[c.outcome] += 1
        return table

    def to_dict(self) -> dict[str, Any]:
        return {
            "verifier": self.verifier, "problems": self.n_problems, "cases": len(self.cases), "ok": self.ok,
            "false_positives": len(self.false_positives), "false_negatives": len(self.false_negatives),
            "errors": len(self.errors), "timeouts": self.timeouts, "crashes": self.crashes,
            "by_label": self.by_label(),
            "failures": [c.to_dict() for c in self.cases if c.outcome != "ok"],
        }

    def format(self, max_examples: int = 5) -> str:
        lines = [f"audit of {self.verifier!r}: {self.n_problems} problems, {len(self.cases)} cases -> "
                 + ("OK" if self.ok else "PROBLEMS FOUND"),
                 f"  false positives {len(self.false_positives)}, false negatives {len(self.false_negatives)}, "
                 f"verifier errors {len(self.errors)}, timeouts {self.timeouts}, crashes {self.crashes}",
                 f"  {'case':34s} {'run':>5s} {'FP':>4s} {'FN':>4s} {'err':>4s}"]
        for label, row in self.by_label().items():
            lines.append(f"  {label[:34]:34s} {row['run']:5d} {row['false positive']:4d} {row['false negative']:4d} {row['error']:4d}")
        for title, cases in (("false positives", self.false_positives), ("false negatives", self.false_negatives),
                             ("verifier errors", self.errors)):
            if not cases:
                continue
            lines.append(f"  {title} (first {min(max_examples, len(cases))} of {len(cases)}):")
            for c in cases[:max_examples]:
                extra = {k: c.details[k] for k in ("extracted", "normalized", "gold") if k in c.details}
                score = "raised" if c.score is None else f"score {c.score:g}"
                lines.append(f"    problem {c.problem} [{c.label}] expected {c.expected:g}, {score} ({c.reason})")
                lines.append(f"      completion: {c.completion!r}" + (f"  {extra}" if extra else ""))
        return "\n".join(lines)


def _jsonable(x: Any) -> Any:
    try:
        json.dumps(x)
        return x
    except (TypeError, ValueError):
        return repr(x)


def _preview(text: str, n: int = 160) -> str:
    if len(text) <= n:
        return text
    return text[:n] + f"... [{len(text)} chars]"


def _is_scalar(ref: Any) -> bool:
    return isinstance(ref, (str, int, float)) and not isinstance(ref, bool)


def _has_digit(s: str) -> bool:
    return any(ch.isdigit() for ch in s)


def _garbage(rng: random.Random, n_words: int) -> str:
    return " ".join(rng.choice(_WORDS) for _ in range(n_words)) + "."


def _score_all(verifier: Verifier, pool: VerifierPool, cases: list[tuple[int, str, str, float]],
               refs: list[Any], timeout_s: float | None) -> list[AuditCase]:
    """Score cases; a verifier exception marks that case as an error and the rest are rescored."""
    out: dict[int, AuditCase] = {}
    todo = list(range(len(cases)))
    errors = 0
    while todo:
        try:
            verdicts = pool.score(verifier, [cases[k][2] for k in todo], [refs[k] for k in todo], timeout_s=timeout_s)
        except VerifierError as e:
            if e.index is None:
                raise
            k = todo[e.index]
            pi, label, completion, expected = cases[k]
            out[k] = AuditCase(pi, label, expected, None, f"raised {e.exc_type}: {e.message}", _preview(completion))
            errors += 1
            if errors >= MAX_ERRORS:
                raise
            todo = [j for j in todo if j != k]
            continue
        for k, v in zip(todo, verdicts):
            pi, label, completion, expected = cases[k]
            out[k] = AuditCase(pi, label, expected, v.score, v.reason, _preview(completion), dict(v.details))
        todo = []
    return [out[k] for k in range(len(cases))]


def run_audit(verifier: Verifier, problems: Sequence[AuditProblem], *, seed: int = 0, workers: int | None = None,
              timeout_s: float | None = None, pool: VerifierPool | None = None, huge_problems: int = 2,
              huge_bytes: int = 1_000_000) -> AuditReport:
    """Run the catalogue described in the module docstring; see `AuditReport`."""
    problems = list(problems)
    if not problems:
        raise ValueError("the audit needs at least one problem")
    own_pool = pool is None
    pool = pool or VerifierPool(workers=workers if workers is not None else min(2, len(problems)))
    rng = random.Random(seed)
    try:
        # phase 1: gold, trivial failures, other problems' golds (they also pick the decoys)
        cases: list[tuple[int, str, str, float]] = []
        refs: list[Any] = []
        others: dict[int, list[int]] = {}
        for i, p in enumerate(problems):
            def add(label: str, completion: str, expected: float, ref: Any = p.reference) -> None:
                cases.append((i, label, completion, expected))
                refs.append(ref)

            add("gold", p.gold, 1.0)
            add("empty", "", 0.0)
            add("whitespace", " \n\t \n", 0.0)
            add("garbage", _garbage(rng, 60), 0.0)
            if p.prompt.strip():
                add("prompt echo", p.prompt, 0.0)
            cands = [j for j in range(1, len(problems)) if repr(problems[(i + j) % len(problems)].reference) != repr(p.reference)]
            others[i] = [(i + j) % len(problems) for j in cands[:4]]
            for j in others[i]:
                add("another problem's gold", problems[j].gold, 0.0)
        phase1 = _score_all(verifier, pool, cases, refs, timeout_s)

        decoy_ok: dict[int, list[int]] = {i: [] for i in range(len(problems))}
        for c, (i, label, completion, _) in zip(phase1, cases):
            if label == "another problem's gold" and c.outcome == "ok":
                j = next(j for j in others[i] if problems[j].gold == completion)
                decoy_ok[i].append(j)

        # phase 2: hacks built from the reference and decoys
        cases2: list[tuple[int, str, str, float]] = []
        refs2: list[Any] = []
        for i, p in enumerate(problems):
            def add2(label: str, completion: str, expected: float) -> None:
                cases2.append((i, label, completion, expected))
                refs2.append(p.reference)

            decoys = [problems[j] for j in decoy_ok[i]]
            scalar = _is_scalar(p.reference)
            answers = [str(d.reference) for d in decoys if _is_scalar(d.reference)] if scalar else []
            ref = str(p.reference)
            # decoys that look like the reference (digits or not) make the templates meaningful
            answers.sort(key=lambda a: _has_digit(a) != _has_digit(ref))
            if answers:
                add2("several candidates", f"The answer is {answers[0]} or {ref}.", 0.0)
                if len(answers) >= 3:
                    add2("several candidates (list)", f"The answer is {ref}, {answers[0]}, {answers[1]} or {answers[2]}.", 0.0)
                ramble = (f"{_FILLER}It could be {answers[-1]}. Perhaps it is {ref}, although I am not sure. "
                          + _FILLER * 20 + f"In the end I would guess {answers[0]}")
                add2("buried in ramble", ramble, 0.0)
                add2("retraction", f"{p.gold}\nNo wait, that's wrong. It's {answers[0]}.", 0.0)
            elif decoys:
                add2("retraction", f"{p.gold}\nNo wait, that's wrong. Here is the correct one:\n{decoys[0].gold}", 0.0)
            if i < huge_problems:
                block = _garbage(random.Random(seed + i), 200) + "\n"
                add2("huge garbage", (block * (huge_bytes // len(block) + 1))[:huge_bytes], 0.0)
                if answers:
                    unit = " ".join(answers) + " "
                    half = unit * (huge_bytes // (2 * len(unit)) + 1)
                    add2("huge output", f"{half}{ref} {half}{answers[0]}", 0.0)
                elif decoys:
                    unit = decoys[0].gold + "\n"
                    half = unit * (huge_bytes // (2 * len(unit)) + 1)
                    add2("huge output", f"{half}{p.gold}\n{half}", 0.0)
            for label, completion, expected in verifier.adversarial_cases(p):
                add2(label, completion, float(expected))
        phase2 = _score_all(verifier, pool, cases2, refs2, timeout_s) if cases2 else []
    finally:
        if own_pool:
            pool.close()
    return AuditReport(verifier.name or type(verifier).__name__, len(problems), phase1 + phase2)
