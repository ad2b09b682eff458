"""gym:NAME: any reasoning-gym procedural dataset as a posttrain task (`pip install "posttrain[gym]"`).

CPU:        posttrain grpo --recipe gym-chain-sum                  (SFT first, then GRPO; see the recipe header)
            posttrain grpo --recipe tiny-math task.name=gym:leg_counting grpo.verifier=gym   (any other dataset)
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain grpo --recipe gym-chain-sum model.path=small

`task.name=gym:basic_arithmetic` (or any of reasoning-gym's 100+ dataset names: `python -c "import
reasoning_gym; print(sorted(reasoning_gym.factory.DATASETS))"`) gives a Task (posttrain.tasks.Task) whose rows
are that dataset's seeded questions, scored by the `gym` verifier (verifiers/gym.py: the dataset's own
`score_answer`, through posttrain's worker pool, timeouts and audit). Options of the dataset's config follow
the name after commas: `gym:chain_sum,max_terms=2,max_digits=2` (values read as YAML; unknown ones and values
the dataset refuses are errors naming them). Pure Python, no torch.

Rows (JSON-serialisable):

    {"prompt": "Calculate 5 - 3 - 6.\nGive only the final answer, as <answer>...</answer>.\n",
     "completion": "<answer>-4</answer>",                       # the dataset's answer: SFT's target
     "answer": {"dataset": "basic_arithmetic", "entry": {...}},  # the verifier reference
     "verifier": "gym",
     "meta": {"task": "gym:basic_arithmetic", "reference": {...same...}}}

Choices:
- Seeded and split like our own generators: one reasoning-gym stream per (dataset, seed), and a SHA-1 of the
  question sends about 10% of questions to "eval", the rest to "train", so the splits never share a question
  and each is a prefix of a longer call (questions repeated within a split are skipped).
- The prompt is the dataset's question plus one line asking for the answer in <answer> tags (the format the
  verifier reads, and reasoning-gym's own prompts ask for); the completion is the bare answer in tags (these
  datasets carry no worked solutions).
- Difficulty is the dataset's configuration, as the options set it (`task.difficulty` stays 0); our exact checkers
  (countdown, knights-and-knaves, sudoku: the `logic` verifiers) stay the defaults of our own tasks.
- Held-out metrics: accuracy (score 1), mean score (partial credit counts) and the <answer> format rate.
"""
from __future__ import annotations

import dataclasses
import hashlib
import json
from typing import Any, Literal, Sequence

import yaml

PREFIX = "gym:"
INSTRUCTION = "Give only the final answer, as <answer>...</answer>."
EVAL_FRACTION = 0.1
GOLD_METRICS = {"accuracy": "accuracy", "score": "mean_score"}


def _split_of(question: str) -> str:
    return "eval" if hashlib.sha1(question.encode()).digest()[0] < 256 * EVAL_FRACTION else "train"


def _jsonable(entry: dict) -> dict:
    """The entry as JSON gives it back (tuples as lists), so scoring sees the same reference a file would hold."""
    return json.loads(json.dumps({k: entry[k] for k in ("question", "answer", "metadata")}, default=str))


class GymTask:
    """A Task (posttrain.tasks.Task) over one reasoning-gym dataset."""

    VERIFIER = "gym"
    GOLD_METRICS = GOLD_METRICS
    # The verifier is the only signal: no gold score, preference or win-rate.
    gold_quality = gold_breakdown = gold_key = gold_prefer = win_rate = None

    def __init__(self, spec: str):
        from posttrain.verifiers.gym import require_reasoning_gym

        rg = require_reasoning_gym()
        dataset, *pairs = spec.split(",")
        if dataset not in rg.factory.DATASETS:
            close = sorted(d for d in rg.factory.DATASETS if dataset.split("_")[0] in d)[:8]
            raise ValueError(f"reasoning-gym has no dataset {dataset!r}" + (f" (similar: {', '.join(close)})" if close
                                                                          else ""))
        fields = {f.name for f in dataclasses.fields(rg.factory.DATASETS[dataset][1])} - {"seed", "size"}
        self.options: dict[str, Any] = {}
        for pair in pairs:
            key, sep, value = pair.partition("=")
            if not sep or key not in fields:
                raise ValueError(f"gym:{spec}: option {pair!r}: {dataset}'s options are {', '.join(sorted(fields))} "
                                 f"(as gym:{dataset},KEY=VALUE,...)")
            self.options[key] = yaml.safe_load(value)  # 2 -> int, 0.5 -> float, true -> bool, [1, 2] -> list
        self.dataset, self.NAME = dataset, PREFIX + spec
        self.__name__ = f"posttrain.tasks.gym[{spec}]"  # named like a module in check_task's messages
        self.make_examples(1, 0, "train")  # options the dataset's config refuses stop here, naming them

    def make_examples(self, n: int, seed: int, split: Literal["train", "eval"]) -> list[dict[str, Any]]:
        """`n` questions of `split` with their answers (see the module docstring)."""
        from posttrain.verifiers.gym import require_reasoning_gym

        if split not in ("train", "eval"):
            raise ValueError(f"split must be 'train' or 'eval', got {split!r}")
        stream_seed = int.from_bytes(hashlib.sha1(f"posttrain/gym/{self.dataset}/{seed}".encode()).digest()[:4], "big")
        budget = 40 * n + 200
        try:
            ds = require_reasoning_gym().create_dataset(self.dataset, size=budget, seed=stream_seed, **self.options)
        except (AssertionError, ValueError, TypeError) as e:  # the dataset's config validation
            raise ValueError(f"{self.NAME}: reasoning-gym refuses these options: {e or type(e).__name__}") from None
        rows: list[dict[str, Any]] = []
        seen: set[str] = set()
        for i in range(budget):
            if len(rows) >= n:
                break
            entry = ds[i]
            question = entry["question"]
            if question in seen or _split_of(question) != split:
                continue
            seen.add(question)
            ref = {"dataset": self.dataset, "entry": _jsonable(entry)}
            rows.append({"prompt": f"{question}\n{INSTRUCTION}\n", "completion": f"<answer>{entry['answer']}</answer>",
                         "answer": ref, "verifier": "gym", "meta": {"task": self.NAME, "reference": ref}})
        if len(rows) < n:
            raise ValueError(f"{self.NAME}: only {len(rows)} distinct {split} questions in {budget} draws, asked for {n}")
        return rows

    def corpus(self, n: int, seed: int) -> list[str]:
        """Prompt + answer texts of both splits (tokenizer training)."""
        rows = self.make_examples(n, seed, "train") + self.make_examples(max(1, n // 8), seed, "eval")
        return [r["prompt"] + r["completion"] for r in rows]

    def evaluate(self, metas: Sequence[dict[str, Any]], completions: Sequence[str]) -> dict[str, float]:
        """accuracy (the gym verifier scores 1), mean_score (partial credit), format (an <answer> tag)."""
        from posttrain.verifiers.gym import GymVerifier

        v = GymVerifier()
        scores = [v.check(c, m["reference"]).score for m, c in zip(metas, completions)]
        n = max(1, len(completions))
        return {"accuracy": sum(s >= 1.0 for s in scores) / n, "mean_score": sum(scores) / n,
                "format": sum(v.extract(c) is not None for c in completions) / n}


_TASKS: dict[str, GymTask] = {}


def task(spec: str) -> GymTask:
    """The (cached) GymTask of `DATASET[,KEY=VALUE,...]` (a reasoning-gym dataset and options of its config)."""
    if spec not in _TASKS:
        _TASKS[spec] = GymTask(spec)
    return _TASKS[spec]
