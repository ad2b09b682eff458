"""Logic-puzzle verifiers: seeded generators and exact checkers for three families.

    from posttrain.verifiers.logic import LogicVerifier, generate
    items = generate("countdown", 100, seed=0, split="train", difficulty=2)   # [{"prompt", "reference", "gold"}]
    LogicVerifier().check(completion, items[0]["reference"])                  # dispatches on reference["family"]

Families (registry name = reference "family"; details in each module's docstring):
- "countdown" (`CountdownVerifier`, verifiers/puzzles/countdown.py): an expression over the
  given numbers, each at most once, that equals the target; parsed with `ast`, exact Fractions.
- "knights_knaves" (`KnightsKnavesVerifier`, verifiers/puzzles/knights.py): name every
  inhabitant knight or knave; puzzles have a unique solution (brute force).
- "sudoku" (`SudokuVerifier`, verifiers/puzzles/sudoku.py): a completed 4x4 grid.

Every family: `generate(n, seed, split="train"|"test", difficulty)` is deterministic for its
arguments (a batch of n is a prefix of a larger batch with the same arguments; sudoku: among
batches no larger than its split's 212/76 grids); it returns distinct problems whose gold
scores 1 while no other problem's gold in the batch does, and its two splits never share a
problem (countdown: number ranges; knights: name lists; sudoku: solution grids). The answer
scope is shared with the math verifier: the last closed `<answer>...</answer>` pair, else the
text after `</think>` and its last `\\boxed{}` (verifiers/puzzles/common.py). Bad answers
score 0 with a reason; a malformed reference raises ValueError.

Standard library only.
"""
from __future__ import annotations

import importlib
from typing import Any

from posttrain.verifiers.base import AuditProblem, Verdict, Verifier
from posttrain.verifiers.puzzles.common import PuzzleVerifier, Split
from posttrain.verifiers.puzzles.countdown import CountdownVerifier
from posttrain.verifiers.puzzles.knights import KnightsKnavesVerifier
from posttrain.verifiers.puzzles.sudoku import SudokuVerifier

__all__ = ["CountdownVerifier", "KnightsKnavesVerifier", "SudokuVerifier", "LogicVerifier", "FAMILIES", "generate"]

FAMILIES: dict[str, type[PuzzleVerifier]] = {
    "countdown": CountdownVerifier,
    "knights_knaves": KnightsKnavesVerifier,
    "sudoku": SudokuVerifier,
}


def _family(family: str) -> type[PuzzleVerifier]:
    if family not in FAMILIES:
        raise ValueError(f"unknown logic family {family!r}; choose from {', '.join(FAMILIES)}")
    return FAMILIES[family]


def generate(family: str, n: int, seed: int = 0, split: Split = "train", difficulty: int | None = None) -> list[dict[str, Any]]:
    """`n` problems of one family: [{"prompt", "reference", "gold"}, ...] (difficulty: the family's default)."""
    cls = _family(family)
    return cls.generate(n, seed, split, cls.default_difficulty if difficulty is None else difficulty)


class LogicVerifier(Verifier):
    """Scores any logic family: dispatches on `reference["family"]`."""

    name = "logic"
    description = "Logic puzzles (countdown, knights_knaves, sudoku), dispatched on the reference's family"
    timeout_s = 5.0

    def __init__(self) -> None:
        self._verifiers = {family: cls() for family, cls in FAMILIES.items()}

    def _for(self, reference: Any) -> PuzzleVerifier:
        if not isinstance(reference, dict) or "family" not in reference:
            raise ValueError(f"logic reference must be a dict with a 'family' ({', '.join(FAMILIES)})")
        _family(reference["family"])
        return self._verifiers[reference["family"]]

    def check(self, completion: str, reference: Any) -> Verdict:
        verdict = self._for(reference).check(completion, reference)
        return Verdict(verdict.score, verdict.reason, {"family": reference["family"], **verdict.details})

    @staticmethod
    def generate(n: int, seed: int = 0, split: Split = "train", difficulty: int | None = None,
                 families: tuple[str, ...] = tuple(FAMILIES)) -> list[dict[str, Any]]:
        """`n` problems cycling over `families`; `difficulty` is clamped to each family's range."""
        def level(f: str) -> int | None:
            if difficulty is None:
                return None
            module = importlib.import_module(FAMILIES[f].__module__)
            return max(min(difficulty, module.DIFFICULTIES[-1]), module.DIFFICULTIES[0])

        per = {f: generate(f, -(-n // len(families)), seed, split, level(f)) for f in families}
        return [per[families[i % len(families)]][i // len(families)] for i in range(n)]

    def audit_problems(self, n: int, seed: int = 0) -> list[AuditProblem]:
        return [AuditProblem(x["prompt"], x["reference"], x["gold"]) for x in self.generate(n, seed)]

    def adversarial_cases(self, problem: AuditProblem) -> list[tuple[str, str, float]]:
        return self._for(problem.reference).adversarial_cases(problem)
