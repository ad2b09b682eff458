"""What the task modules' gold signals share (pure Python, no torch): the win-rate over a gold preference, and
for tasks with a numeric answer (tiny-math, word-math) the cached math verifier and the check of a row's answer."""
from __future__ import annotations

from typing import Any, Callable, Sequence

_verifiers: dict[str, Any] = {}


def verifier(spec: str):
    """`posttrain.verifiers.get_verifier(spec)`, built once per process."""
    if spec not in _verifiers:
        from posttrain.verifiers.registry import get_verifier

        _verifiers[spec] = get_verifier(spec)
    return _verifiers[spec]


def answer_of(meta: Any, i: int, task: str, example: str) -> str:
    """meta["answer"] as text; a ValueError naming the task, row i (0-based) and an `example` answer otherwise."""
    if not isinstance(meta, dict) or not isinstance(meta.get("answer"), (str, int)) or str(meta["answer"]).strip() == "":
        raise ValueError(f"{task} evaluate: row {i + 1}: meta has no 'answer' (the gold number as text, e.g. "
                         f"\"{example}\"); got {meta!r:.80}")
    return str(meta["answer"])


def prefer(a, b) -> int:
    """+1 if a > b, -1 if a < b, 0 if equal (scores or sort keys)."""
    return (a > b) - (a < b)


def win_rate(gold_prefer: Callable[[Any, str, str], int], metas: Sequence[dict[str, Any]], candidates: Sequence[str],
             baselines: Sequence[str]) -> float:
    """Fraction of examples where the candidate beats the baseline under `gold_prefer`; a tie counts half."""
    if not (len(metas) == len(candidates) == len(baselines)):
        raise ValueError(f"win_rate needs equal lengths, got {len(metas)} metas, "
                         f"{len(candidates)} candidates, {len(baselines)} baselines")
    if not metas:
        raise ValueError("win_rate of zero examples is undefined")
    return sum((gold_prefer(m, c, b) + 1) / 2 for m, c, b in zip(metas, candidates, baselines)) / len(metas)
