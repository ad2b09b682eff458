"""tiny-countdown: Countdown puzzles (reach a target with + - * / over three numbers) for the logic GRPO recipe.

CPU:        posttrain grpo --recipe tiny-countdown          (SFT first, then GRPO; see the recipe header)
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain grpo --recipe tiny-countdown model.path=small

Pure Python (no torch). The checker is the verifier layer's (`verifiers/puzzles/countdown.py`,
registry name "countdown"); this module generates problems a tiny model can read and learn from,
with their solutions for SFT and a gold evaluation.

Example (JSON-serialisable):

    {"prompt": "Use 7 46 10 to make 36.\n",
     "completion": "<answer>46 - 10</answer>",
     "answer": {"family": "countdown", "numbers": [7, 46, 10], "target": 36, ...},   # verifier reference
     "meta": {"task": "tiny-countdown", "reference": {...same...}, "gold": "46 - 10"}}

Choices (a tiny model SFT'd on the verifier generator's full difficulty-1 problems, golds of two
operations written out one per line, solved none of its samples, so RL had nothing to reinforce;
docs/results-archive.md, "Recipes / tiny-countdown"):
- Three numbers, a target made from exactly TWO of them with one operation (+, -, *, / with an
  exact integer result; operator drawn uniformly, the problem redrawn unless the target is in
  10..100 and not itself one of the numbers): the third number is a distractor. A solution is a choice
  of two numbers and an operator (24 ordered choices, some equivalent), which a tiny model can learn
  partly from magnitudes (a target above both numbers: + or *) and improve by trial: GRPO sees
  groups with reward variance. (The generator of `verifiers/puzzles/countdown.py` is not used: its
  one-operation problems with small targets thin out quickly under its uniqueness rules.)
- The completion is the expression in <answer> tags, nothing else (the scope the countdown and
  format verifiers read); no arithmetic is written out, the verifier does it.
- Splits: a SHA-1 of the problem (sorted numbers, target) sends about 20% of problems to "eval" and
  the rest to "train", both drawn from the same number distribution (1..50, 60% of them 1..10): the
  held-out set tests new problems, not new number ranges. (With the verifier generator's split,
  held-out problems always holding a number in 51..100, the SFT model solved far fewer of them than
  of the training problems, leaving RL little to show on held-out data.)
  The reference is the countdown verifier's ({"family", "numbers", "target"}).
- `make_examples(n, seed, split)` is deterministic, and a prefix of a longer call (one seeded
  stream; duplicates, same numbers and target, are skipped).
"""
from __future__ import annotations

import hashlib
import random
from typing import Any, Literal, Sequence

from posttrain.verifiers.puzzles import countdown as _cd  # the checker

NAME = "tiny-countdown"
VERIFIER = "countdown"
GOLD_METRICS = {"accuracy": "accuracy", "length_chars": "length_chars"}
# The verifier is the only signal: no gold score, preference or win-rate (posttrain.tasks.Task).
gold_quality = gold_breakdown = gold_key = gold_prefer = win_rate = None
"""The verifier spec GRPO uses when the recipe sets none (`grpo.verifier: auto`)."""
MAX_TARGET = 100
EVAL_FRACTION = 0.2


def prompt_text(numbers: Sequence[int], target: int) -> str:
    return f"Use {' '.join(map(str, numbers))} to make {target}.\n"


def _numbers(rng: random.Random) -> list[int]:
    return [rng.randint(1, 10) if rng.random() < 0.6 else rng.randint(11, 50) for _ in range(3)]


def _split_of(numbers: Sequence[int], target: int) -> str:
    h = hashlib.sha1(f"{sorted(numbers)}/{target}".encode()).digest()
    return "eval" if h[0] < 256 * EVAL_FRACTION else "train"


def _problem(rng: random.Random, split: str) -> dict[str, Any] | None:
    numbers = _numbers(rng)
    i, j = rng.sample(range(3), 2)
    a, b = numbers[i], numbers[j]
    options = {"+": a + b, "-": a - b, "*": a * b, "/": a // b if b > 1 and a % b == 0 else None}
    op = rng.choice("+-*/")
    if options[op] is None or not 10 <= options[op] <= MAX_TARGET or options[op] in numbers:
        return None  # redrawn: the operators stay balanced (drawing among the valid ones favours +)
    if _split_of(numbers, options[op]) != split:
        return None
    ref = {"family": "countdown", "numbers": numbers, "target": options[op], "split": split}
    gold = f"{a} {op} {b}"
    return {"prompt": prompt_text(numbers, ref["target"]), "completion": f"<answer>{gold}</answer>",
            "answer": ref, "meta": {"task": NAME, "reference": ref, "gold": gold}}


def make_examples(n: int, seed: int, split: Literal["train", "eval"]) -> list[dict[str, Any]]:
    """`n` problems of `split` with their solutions (see the module docstring)."""
    if split not in ("train", "eval"):
        raise ValueError(f"split must be 'train' or 'eval', got {split!r}")
    rng = random.Random(f"posttrain/{NAME}/{split}/{seed}")
    rows: list[dict[str, Any]] = []
    seen: set[tuple] = set()
    for _ in range(200 * n + 1000):
        if len(rows) >= n:
            break
        row = _problem(rng, split)
        if row is None:
            continue
        key = (tuple(sorted(row["answer"]["numbers"])), row["answer"]["target"])
        if key not in seen:
            seen.add(key)
            rows.append(row)
    if len(rows) < n:
        raise ValueError(f"tiny-countdown: only {len(rows)} distinct {split} problems found, asked for {n}")
    return rows


def corpus(n: int, seed: int) -> list[str]:
    """Prompt + worked solution texts (tokenizer training): both splits, so every number has tokens."""
    rows = make_examples(n, seed, "train") + make_examples(max(1, n // 4), seed, "eval")
    return [r["prompt"] + r["completion"] for r in rows]


def evaluate(metas: Sequence[dict[str, Any]], completions: Sequence[str]) -> dict[str, float]:
    """accuracy (the countdown verifier passes), format (an <answer> tag is present), mean completion length."""
    v = _cd.CountdownVerifier()
    scores = [v.check(c, m["reference"]).score for m, c in zip(metas, completions)]
    n = max(1, len(completions))
    return {"accuracy": sum(s >= 1.0 for s in scores) / n,
            "format": sum("<answer>" in c and "</answer>" in c for c in completions) / n,
            "length_chars": sum(len(c) for c in completions) / n}
