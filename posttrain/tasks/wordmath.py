"""word-math: seeded natural-language word problems of 1-3 steps for a real instruct model (the smol-math
recipe; the seed's E7 "take a small instruction-tuned LM"), checked by the math verifier.

Pure Python (no torch).

    from posttrain.tasks import wordmath as W
    rows = W.make_examples(500, seed=0, split="eval", difficulty=1)
    rows[0]["prompt"]     # 'Mia has 14 stickers. She buys 7 more stickers. How many stickers does Mia have now?'
    rows[0]["answer"]     # '21'
    W.evaluate([r["meta"] for r in rows], completions)

Where tiny-math is written for a ~1M model trained from scratch (digit-by-digit worked solutions, one
sentence frame), word-math is written for a model that already reads English and does some arithmetic:
the prompt is the problem alone (the recipe sends it through the model's chat template), and the model
answers in whatever form it already uses -- SmolLM2-135M-Instruct writes GSM8K-style "... = 12 pencils.
#### 12" or "The answer is: 12"; the math verifier reads "the answer is", "####" and, failing those, the
last number (`verifiers/math_answer`).

Problems
--------
A story keeps a running total through 1-3 operations, and the question asks for it at the end:
- a start: "{Name} has a {items}." (no operation) or "{Name} buys a bags of {items}. Each bag has b
  {items}." (one multiplication: a groups of b);
- then gains (+n), losses (-n, never below zero) and, as the last step only, an equal share (/k, exact):
  "She shares them equally among 4 friends. How many stickers does each friend get?".
Each clause kind has 4-5 phrasings, 12 items and 12 names; `meta["ops"]` lists the operations, so the
reference is computed, never parsed back from text.

The difficulty knob (`task.difficulty`, levels 1-3)
---------------------------------------------------
Measured on SmolLM2-135M-Instruct before any training (docs/results-archive.md, "Recipes / smol-math"): a single
addition of numbers up to 10 is right about a third of the time greedy, and the misses are mostly not
arithmetic: the model states the right sum, then keeps writing ("... so he now has 7 - 5 = 2 pencils")
and its last number is wrong; two steps drop it much lower (the figures: docs/results-archive.md, "Figures once kept
in code comments"). So the levels are:

    level  operations  +/- operands (train / held-out)  factors, divisors (train / held-out)
    1      1           1-20  / 1-30                      2-9  / 2-12
    2      1-2         1-50  / 1-75                      2-12 / 2-15
    3      2-3         1-100 / 1-150                     2-12 / 2-20
    4      1-2         100-999 / 100-1999                12-99 / 12-120   (for a calculator: smol-tools)
    5      2-3         1000-9999 / 1000-14999            12-99 / 12-150   (for a calculator)

Level 1 is the smol-math recipe's (partial accuracy, room to learn); 2 and 3 are for a stronger model
or a later curriculum stage; 4 and 5 (totals up to 100,000 and 1,000,000) are for a model with a calculator
tool (the smol-tools recipe, the `calc-words` environment), whose numbers it cannot add in its head.

Splits (train and held-out differ)
----------------------------------
- Numbers: a SHA-1 of the problem's operation tuple puts it in exactly one split (~20% to eval); the
  held-out operand ranges also reach past the training ones (table above), so held-out problems
  include numbers larger than any trained on.
- Templates: the last phrasing of every clause kind and of the question is used only in the held-out
  set, and one item word and one name pair occur only there. Training prompts never hold them.
  (A pretrained model reads new words; a model trained from scratch would not -- tiny-math's held-out
  set keeps its vocabulary for that reason.)

Rows: {"prompt", "completion" (a short worked solution, " 12 + 5 = 17\\n17 - 3 = 14\\n#### 14", for an
optional format SFT or the tiny preset), "answer" (the gold number as text, the verifier reference),
"verifier": "math", "meta"}. `meta`: task, answer, ops ([[op, n], ...], op in "=", "+", "-", "*", "/"),
n_steps, template (the phrasing indices), difficulty, split.

Behaviour counts (E7): `behaviour_counts` counts verification phrases ("check", "verify", "let me
check", "double-check"), self-correction phrases ("wait", "actually", "mistake", "let me re-",
"correction", "oops") and re-computation lines (an equation line "a op b = c" whose left side already
appeared earlier in the same completion) per completion.
"""
from __future__ import annotations

import hashlib
import random
import re
from collections import Counter
from dataclasses import dataclass
from typing import Any, Literal, Sequence

from posttrain.tasks import gold

NAME = TASK_NAME = "word-math"
VERIFIER = "math"
GOLD_METRICS = {"accuracy": "accuracy", "length_chars": "mean_length_chars"}
gold_breakdown = None
gold_key = None

EVAL_FRACTION_BUCKETS = 5  # an operation tuple goes to eval when sha1 % 5 == 0 (~20%)


@dataclass(frozen=True)
class Level:
    steps: tuple[int, ...]  # operations per problem (drawn uniformly)
    add: tuple[tuple[int, int], tuple[int, int]]  # +/- operand range (train, eval); also the start value's
    factor: tuple[tuple[int, int], tuple[int, int]]  # multiplication factors and divisors (train, eval)
    max_total: int = 2000  # the running total's bound (a problem past it is drawn again)


LEVELS: dict[int, Level] = {
    1: Level(steps=(1,), add=((1, 20), (1, 30)), factor=((2, 9), (2, 12))),
    2: Level(steps=(1, 2), add=((1, 50), (1, 75)), factor=((2, 12), (2, 15))),
    3: Level(steps=(2, 3), add=((1, 100), (1, 150)), factor=((2, 12), (2, 20))),
    # for a calculator (the smol-tools recipe): 3-4 digit numbers that a 135M model gets wrong in its head
    4: Level(steps=(1, 2), add=((100, 999), (100, 1999)), factor=((12, 99), (12, 120)), max_total=100_000),
    5: Level(steps=(2, 3), add=((1000, 9999), (1000, 14999)), factor=((12, 99), (12, 150)), max_total=1_000_000),
}
DIFFICULTIES = tuple(LEVELS)
CORPUS_LEVELS = (1, 2, 3)  # the tiny preset's tokenizer texts (levels 4-5 came later; the corpus kept its texts)
DEFAULT_DIFFICULTY = 1

# (name, subject pronoun, object pronoun); the last pair is held-out only.
NAMES = [("Ava", "she", "her"), ("Ben", "he", "him"), ("Mia", "she", "her"), ("Leo", "he", "him"),
         ("Zoe", "she", "her"), ("Sam", "he", "him"), ("Ivy", "she", "her"), ("Max", "he", "him"),
         ("Lily", "she", "her"), ("Tom", "he", "him"), ("Nora", "she", "her"), ("Omar", "he", "him")]
ITEMS = ["apples", "marbles", "stickers", "cookies", "pencils", "cards", "shells", "stamps", "books",
         "eggs", "flowers", "crayons"]  # the last is held-out only

# Clause phrasings; in every list the LAST entry is held-out only.
START_HAS = ["{Name} has {a} {items}.", "{Name} had {a} {items}.", "There are {a} {items} in {Name}'s bag.",
             "{Name} collected {a} {items}.", "{Name} owns {a} {items}."]
START_GROUPS = ["{Name} buys {a} bags of {items}. Each bag has {b} {items}.",
                "{Name} has {a} boxes with {b} {items} in each box.",
                "{Name} gets {b} {items} every day for {a} days.",
                "{Name} makes {a} piles of {items} with {b} {items} in each pile.",
                "{Name} fills {a} jars with {b} {items} each."]
GAIN = ["{Pro} gets {n} more {items}.", "{Pro} buys {n} more {items}.", "{Pro} finds {n} more {items}.",
        "A friend gives {obj} {n} more {items}.", "{Pro} wins {n} more {items}."]
LOSS = ["{Pro} gives away {n} {items}.", "{Pro} loses {n} {items}.", "{Pro} sells {n} of the {items}.",
        "{Pro} uses {n} {items}.", "{Pro} gives {n} {items} to a friend."]
SHARE = [("{Pro} shares them equally among {k} friends.", "How many {items} does each friend get?"),
         ("{Pro} puts them into {k} equal piles.", "How many {items} are in each pile?"),
         ("{Pro} splits them evenly between {k} boxes.", "How many {items} go in each box?"),
         ("{Pro} packs them equally into {k} bags.", "How many {items} are in each bag?")]
QUESTIONS = ["How many {items} does {Name} have now?", "How many {items} does {pro} have in total?",
             "How many {items} does {Name} have at the end?", "How many {items} are there now?",
             "How many {items} does {Name} end up with?"]

VERIFICATION_PHRASES = ("check", "verify", "double-check", "let me check", "to confirm")
SELF_CORRECTION_PHRASES = ("wait", "actually", "mistake", "oops", "correction", "let me re", "recalculate",
                           "let's re", "i made")


def _pool(options: Sequence, split: str) -> list[int]:
    """Indices of `options` usable in `split`: training excludes the last one; held-out uses all of them."""
    n = len(options)
    return list(range(n - 1)) if split == "train" else list(range(n))


def _split_of(ops: Sequence[tuple[str, int]]) -> str:
    key = "|".join(f"{o}{n}" for o, n in ops)
    return "eval" if int(hashlib.sha1(key.encode()).hexdigest()[:8], 16) % EVAL_FRACTION_BUCKETS == 0 else "train"


def apply(ops: Sequence[tuple[str, int]]) -> int:
    """The running total after `ops` ([("=", a), ("*", b), ("+", n), ("-", n), ("/", k)])."""
    total = 0
    for op, n in ops:
        if op == "=":
            total = n
        elif op == "+":
            total += n
        elif op == "-":
            if n > total:
                raise ValueError(f"word-math: {total} - {n} would be negative")
            total -= n
        elif op == "*":
            total *= n
        elif op == "/":
            if n <= 0 or total % n:
                raise ValueError(f"word-math: {total} / {n} is not an exact share")
            total //= n
        else:
            raise ValueError(f"word-math: unknown operation {op!r}")
    return total


def solution(ops: Sequence[tuple[str, int]]) -> str:
    """A short worked solution (starts with a space): one equation line per operation, then "#### N"."""
    total, lines = ops[0][1], []
    for op, n in ops[1:]:
        new = apply([("=", total), (op, n)])
        lines.append(f"{total} {'x' if op == '*' else op} {n} = {new}")
        total = new
    return " " + "\n".join(lines + [f"#### {total}"])


def _numbers(rng: random.Random, level: Level, split: str) -> list[tuple[str, int]]:
    lo, hi = level.add[split == "eval"]
    flo, fhi = level.factor[split == "eval"]
    for _ in range(1000):
        steps = rng.choice(level.steps)
        groups = rng.random() < 0.3  # the start is a multiplication (one of the steps)
        ops: list[tuple[str, int]] = [("=", rng.randint(flo, fhi) if groups else rng.randint(max(lo, 2), hi))]
        if groups:
            ops.append(("*", rng.randint(flo, fhi)))
        total = apply(ops)
        while len(ops) - 1 < steps:
            last = len(ops) - 1 == steps - 1
            k = rng.randint(flo, fhi)
            if last and rng.random() < 0.25 and total % k == 0 and total // k >= 1 and total > k:
                ops.append(("/", k))
            elif total > lo and rng.random() < 0.5:  # (lo is 1 at levels 1-3: total >= 2)
                ops.append(("-", rng.randint(lo, min(hi, total - 1))))
            else:
                ops.append(("+", rng.randint(lo, hi)))
            total = apply(ops)
        if total <= level.max_total and _split_of(ops) == split:
            return ops
    raise RuntimeError("word-math: no problem found in 1000 draws (a bug in the level table)")  # pragma: no cover


def _cap(s: str) -> str:
    return s[0].upper() + s[1:]


def _problem(rng: random.Random, split: str, difficulty: int) -> dict[str, Any]:
    level = LEVELS[difficulty]
    ops = _numbers(rng, level, split)
    name, pro, obj = NAMES[rng.choice(_pool(NAMES, split))]
    items = ITEMS[rng.choice(_pool(ITEMS, split))]
    template: list[int] = []
    if len(ops) > 1 and ops[1][0] == "*":
        t = rng.choice(_pool(START_GROUPS, split))
        sentences = [START_GROUPS[t].format(Name=name, a=ops[0][1], b=ops[1][1], items=items)]
        rest = ops[2:]
    else:
        t = rng.choice(_pool(START_HAS, split))
        sentences = [START_HAS[t].format(Name=name, a=ops[0][1], items=items)]
        rest = ops[1:]
    template.append(t)
    question = None
    for op, n in rest:
        if op == "/":
            t = rng.choice(_pool(SHARE, split))
            clause, question = SHARE[t]
            sentences.append(_cap(clause.format(Pro=pro, k=n)))
            question = question.format(items=items)
        else:
            phrasings = GAIN if op == "+" else LOSS
            t = rng.choice(_pool(phrasings, split))
            sentences.append(_cap(phrasings[t].format(Pro=rng.choice([name, pro]), obj=obj, n=n, items=items)))
        template.append(t)
    if question is None:
        t = rng.choice(_pool(QUESTIONS, split))
        question = QUESTIONS[t].format(items=items, Name=name, pro=pro)
        template.append(t)
    answer = str(apply(ops))
    meta = {"task": NAME, "answer": answer, "ops": [[o, n] for o, n in ops], "n_steps": len(ops) - 1,
            "template": template, "difficulty": difficulty, "split": split}
    return {"prompt": " ".join(sentences + [_cap(question)]), "completion": solution(ops), "answer": answer,
            "verifier": VERIFIER, "meta": meta}


def make_examples(n: int, seed: int, split: Literal["train", "eval"],
                  difficulty: int = DEFAULT_DIFFICULTY) -> list[dict[str, Any]]:
    """`n` rows {"prompt", "completion", "answer", "verifier", "meta"} of level `difficulty` (1-5);
    deterministic in (n, seed, split, difficulty), and a prefix of a longer call."""
    if split not in ("train", "eval"):
        raise ValueError(f"split must be 'train' or 'eval', got {split!r}")
    if not isinstance(n, int) or isinstance(n, bool) or n < 0:
        raise ValueError(f"n must be an integer >= 0, got {n!r}")
    if difficulty not in LEVELS:
        raise ValueError(f"word-math difficulty must be one of {', '.join(map(str, DIFFICULTIES))}, got {difficulty!r}")
    rng = random.Random(f"{NAME}:{split}:{difficulty}:{seed}")
    return [_problem(rng, split, difficulty) for _ in range(n)]


def corpus(n: int, seed: int) -> list[str]:
    """Tokenizer texts (the tiny preset): problems and solutions of every level and both splits."""
    rows = [r for d in CORPUS_LEVELS for split in ("train", "eval")
            for r in make_examples(max(1, n // (2 * len(CORPUS_LEVELS))), seed, split, d)]
    return [r["prompt"] + r["completion"] for r in rows]


# --- scoring ------------------------------------------------------------------------------------

def _math_verifier():
    return gold.verifier(VERIFIER)


def _answer_of(meta: Any, i: int) -> str:
    return gold.answer_of(meta, i, NAME, "12")


def gold_quality(meta: dict[str, Any], completion: str) -> float:
    """Correctness (1 or 0) through the math verifier."""
    return float(_math_verifier().check(completion, _answer_of(meta, 0)).score)


def gold_prefer(meta: dict[str, Any], a: str, b: str) -> int:
    """+1 if only `a` is correct, -1 if only `b` is, 0 otherwise."""
    return gold.prefer(gold_quality(meta, a), gold_quality(meta, b))


def win_rate(metas: Sequence[dict[str, Any]], candidates: Sequence[str], baselines: Sequence[str]) -> float:
    """Fraction of problems where the candidate is right and the baseline wrong; ties count half."""
    return gold.win_rate(gold_prefer, metas, candidates, baselines)


_EQUATION_RE = re.compile(r"(\d[\d,]*(?:\s*[-+*/x×÷]\s*\d[\d,]*)+)\s*=\s*\d")


def recomputations(completion: str) -> int:
    """Equation lines ("a + b = c") whose left side already appeared earlier in the completion."""
    seen: set[str] = set()
    repeats = 0
    for m in _EQUATION_RE.finditer(completion):
        lhs = re.sub(r"\s+", "", m.group(1)).replace(",", "")
        repeats += lhs in seen
        seen.add(lhs)
    return repeats


def _count(text: str, phrases: Sequence[str]) -> int:
    low = text.lower()
    return sum(len(re.findall(r"\b" + re.escape(p) + (r"\b" if p[-1].isalpha() and not p.endswith(" re") else ""),
                              low)) for p in phrases)


def behaviour_counts(completions: Sequence[str]) -> dict[str, float]:
    """Per completion: the fraction with a verification phrase, a self-correction phrase and a re-computation
    line, and the mean count of each (case-insensitive, whole words)."""
    n = max(1, len(completions))
    ver = [_count(c, VERIFICATION_PHRASES) for c in completions]
    cor = [_count(c, SELF_CORRECTION_PHRASES) for c in completions]
    rec = [recomputations(c) for c in completions]
    return {"frac_verification": sum(v > 0 for v in ver) / n, "mean_verification": sum(ver) / n,
            "frac_self_correction": sum(c > 0 for c in cor) / n, "mean_self_correction": sum(cor) / n,
            "frac_recomputation": sum(r > 0 for r in rec) / n, "mean_recomputation": sum(rec) / n}


def evaluate(metas: Sequence[dict[str, Any]], completions: Sequence[str]) -> dict[str, float]:
    """Accuracy through the math verifier (overall and per step count), where answers come from, length and
    behaviour counts."""
    if len(metas) != len(completions):
        raise ValueError(f"evaluate needs equal lengths, got {len(metas)} metas and {len(completions)} completions")
    if not metas:
        raise ValueError("evaluate of zero examples is undefined")
    answers = [_answer_of(m, i) for i, m in enumerate(metas)]
    verdicts = [_math_verifier().check(c, a) for c, a in zip(completions, answers)]
    n = len(metas)
    correct = [v.score >= 1.0 for v in verdicts]
    reasons = Counter(v.reason for v in verdicts)
    rules = Counter((v.details or {}).get("rule") for v in verdicts)
    out: dict[str, float] = {
        "n": n,
        "accuracy": sum(correct) / n,
        "frac_no_answer": reasons.get("no answer found", 0) / n,
        "frac_explicit_answer": (rules.get("answer phrase", 0) + rules.get("####", 0) + rules.get("boxed", 0)) / n,
        "mean_length_chars": sum(len(c) for c in completions) / n,
    }
    for k in sorted({m.get("n_steps") for m in metas if isinstance(m.get("n_steps"), int)}):
        idx = [i for i, m in enumerate(metas) if m.get("n_steps") == k]
        out[f"accuracy_{k}_steps"] = sum(correct[i] for i in idx) / len(idx)
    out.update(behaviour_counts(completions))
    return out
