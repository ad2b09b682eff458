"""tiny-calc-direct: tiny-calc's problems answered directly, without the tool (the no-tools baseline of tiny-calc).

    posttrain sft --recipe tiny-calc task.name=tiny-calc-direct run.output_dir=runs/no-tools

The same problems, splits and answer rule as `posttrain.tasks.calc`; a row is the question and its answer as a
plain prompt / completion, so the model must multiply in its head.
"""
from __future__ import annotations

from typing import Any, Literal, Sequence

from posttrain.tasks import calc

NAME = "tiny-calc-direct"
VERIFIER = None
GOLD_METRICS = calc.GOLD_METRICS
gold_quality = gold_breakdown = gold_key = gold_prefer = win_rate = None


def make_examples(n: int, seed: int, split: Literal["train", "eval"]) -> list[dict[str, Any]]:
    """`n` rows of `split`: {"prompt": the question, "completion": the answer, "answer", "meta"}."""
    return [{"prompt": calc.problem_of(r)["prompt"], "completion": r["answer"], "answer": r["answer"],
             "meta": r["meta"]} for r in calc.make_examples(n, seed, split)]


def corpus(n: int, seed: int) -> list[str]:
    return [f"{r['prompt']} {r['completion']}" for r in make_examples(n, seed, "train")]


def evaluate(metas: Sequence[dict[str, Any]], completions: Sequence[str]) -> dict[str, float]:
    return calc.evaluate(metas, completions)
