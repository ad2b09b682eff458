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
# tiny-calc's recipe sets task.options.tool_rate; the same recipe with task.name=tiny-calc-direct takes it and
# answers every row directly all the same
OPTIONS = {"tool_rate": "accepted and ignored (tiny-calc's option): every row is answered directly"}


def make_examples(n: int, seed: int, split: Literal["train", "eval"], tool_rate: float = 1.0) -> list[dict[str, Any]]:
    """`n` rows of `split`: {"prompt": the question, "completion": the answer, "answer", "meta"}; the problems of
    tiny-calc's rows, whatever `tool_rate`."""
    return [{"prompt": calc.problem_of(r)["prompt"], "completion": r["answer"], "answer": r["answer"],
             "meta": r["meta"]} for r in calc.make_examples(n, seed, split)]


def corpus(n: int, seed: int) -> list[str]:
    return [f"{r['prompt']} {r['completion']}" for r in make_examples(n, seed, "train")]


def evaluate(metas: Sequence[dict[str, Any]], completions: Sequence[str]) -> dict[str, float]:
    return calc.evaluate(metas, completions)
