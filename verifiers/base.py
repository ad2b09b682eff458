"""The verifier interface: a name, one completion scored against a reference, a Verdict back.

Contract (every verifier, built-in or third-party, follows it):
- `check(completion, reference) -> Verdict` is deterministic: same inputs, same verdict.
- Bad *model output* (no answer found, wrong answer, code that fails its tests, a
  malformed expression) is a Verdict with score 0.0 and a short reason. It never raises.
- A bug in the verifier itself, or a malformed *reference* (the problem set is wrong,
  not the model), raises. Hiding our own bugs as score 0 would silently poison a reward.
- Scores lie in [0, 1]. `details` holds what a user wants to see when auditing
  (the extracted answer, the tests that failed, ...); it must be JSON-serialisable.

This module imports nothing outside the standard library: the verifier layer works
without torch.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from typing import Any


@dataclass(frozen=True)
class Verdict:
    """The result of scoring one completion."""

    score: float
    reason: str
    details: dict[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not isinstance(self.score, (int, float)) or math.isnan(self.score) or not 0.0 <= self.score <= 1.0:
            raise ValueError(f"Verdict.score must be a number in [0, 1], got {self.score!r}")

    @property
    def passed(self) -> bool:
        return self.score >= 1.0

    def to_dict(self) -> dict[str, Any]:
        return {"score": float(self.score), "reason": self.reason, "details": dict(self.details)}


@dataclass(frozen=True)
class AuditProblem:
    """One problem for `posttrain verify audit`: what the model saw, the reference, a gold completion."""

    prompt: str
    reference: Any
    gold: str


class Verifier:
    """Base class for verifiers. Subclasses set `name` and implement `check`.

    `timeout_s` is the default wall-clock limit the runner applies to one `check` call.
    """

    name: str = ""
    description: str = ""
    timeout_s: float = 10.0
    # True only for checks that are cheap and cannot run away on their own (regex and
    # length work on the completion, no sympy, no exec). The runner may then score them
    # in the calling process (still under a wall-clock limit, see verifiers/runner.py)
    # instead of paying a process round-trip.
    in_process: bool = False

    def warmup(self) -> None:
        """Prepare expensive state (imports, tables) once per process.

        The runner calls it in each worker before the first check, outside the per-item
        time limit, so a slow import does not read as a timeout. Optional.
        """

    def check(self, completion: str, reference: Any) -> Verdict:  # pragma: no cover - interface
        raise NotImplementedError

    def audit_problems(self, n: int, seed: int = 0) -> list[AuditProblem]:
        """A seeded problem set with gold completions for the audit. Optional."""
        raise NotImplementedError(f"verifier {self.name!r} ships no audit problems; pass --problems FILE.jsonl")

    def adversarial_cases(self, problem: AuditProblem) -> list[tuple[str, str, float]]:
        """Verifier-specific reward hacks for the audit: (label, completion, expected score).

        The audit adds these to its generic catalogue (empty, garbage, several candidate
        answers, buried answer, retraction, huge output). Optional.
        """
        return []

    def __call__(self, completion: str, reference: Any) -> Verdict:
        return self.check(completion, reference)

    def __repr__(self) -> str:
        return f"{type(self).__name__}(name={self.name!r})"
