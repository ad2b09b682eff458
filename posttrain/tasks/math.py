"""tiny-math: seeded multi-step arithmetic word problems with worked, digit-by-digit solutions
(the seed's §16 E7 problem set), checked by the math verifier (`posttrain.verifiers.math_answer`).

Pure Python (no torch).

    from posttrain.tasks import math as M
    rows = M.make_examples(1000, seed=0, split="train")
    rows[0]["prompt"], rows[0]["completion"], rows[0]["answer"]
    M.evaluate([r["meta"] for r in rows], completions)     # accuracy through the "math" verifier

Problems
--------
A person starts with some items and gains or loses some, 2 or 3 times (50/50); the question
asks how many there are at the end:

    Question: Ava has 47 marbles. She finds 38 more. Then she loses 19. How many marbles
    does Ava have now?
    Answer:

Start value 10-99, each operand 1-99 (a loss never exceeds what is there, so every running
total is in 0-999). Gain clauses: buys / finds / gets / is given N more; loss clauses: loses /
gives away / sells / uses N. Each step sentence may open with "Then". 3 start sentences x 3
questions, 16 names, 10 item words.

Worked solutions (the SFT targets) -- why they look like this
--------------------------------------------------------------
A ~1M-parameter Llama trained from scratch on a CPU learns arithmetic only when every
generated token is easy to compute from a few tokens before it (such a model trained on plain two-digit
addition with the answer written directly stays near chance, while this format learns 2-3 step problems;
measured: docs/results-archive.md, "Figures once kept in code comments"). So a
worked solution is:

     47+38-19
    47+38: 7+8+0=5 c1, 4+3+1=8 c0, 85
    85-19: 5-9-0=6 b1, 8-1-1=6 b0, 66
    The answer is 66.

1. The equation: the numbers of the problem in order, with + for a gain and - for a loss
   (the only "language" step: verb -> sign).
2. One line per operation, columns least-significant digit first. Each column is
   "a+b+carry=digit cC" or "a-b-borrow=digit bB": three single digits in, one digit and one
   flag out (a 200-entry table per operation); the carry/borrow in is the flag just written.
   A missing digit is 0; a final carry adds a leading 1; the result drops leading zeros.
3. "The answer is N." -- the answer phrase the math verifier extracts (its rule 2).

Digits must be single tokens for this to work: the recipe sets `model.split_digits: true`,
which makes the locally trained BPE put every digit in its own token (`models.train_tokenizer`).

Two styles: where the SFT model's partial accuracy comes from
--------------------------------------------------------------
Training rows asking "How many {items} are there now?" (DIRECT_QUESTION) are answered without
working, " The answer is 66.", with probability DIRECT_PROB = 0.8; every other training row is
worked, and held-out references are always worked. The SFT model imitates that: greedy, it
states a guessed answer to that question (almost always wrong: a tiny model cannot add three
numbers in one token) and works every other question in columns. At temperature 1 it still
works the direct-style question some of the time, so a group of 8 samples usually holds
a worked, right answer next to direct, wrong ones: RL has a clear signal to learn to work
every problem, and the response length grows (the E7 question: does RL make answers longer?).

Why not simply stop SFT early on all-worked data: the model learns to copy the equation line
abruptly, at a step that moves with the schedule and the data order, so no step count promises
partial accuracy; and GRPO from such a model mostly has to sharpen digit predictions one noisy
sample at a time (it gained little and collapsed at lr >= 1e-4). With the two styles the SFT model
is past that transition (its worked answers are mostly right) and the room for RL is the style
choice on one question in three. The SFT stage is therefore trained to convergence (2000 steps):
stopping it early only adds the luck of the transition above, which moved with the torch thread
count. The measurements behind each choice: docs/results-archive.md, "Recipes / tiny-math".

Verification steps. With probability CHECK_PROB a worked training solution adds, before the answer,
the inverse of its last operation: "Check: 66+19=85" (for a gain, "Check: 85-38=47"). It only
restates numbers already written (no new arithmetic), so it is a behaviour whose frequency can
be counted before and after RL (`behaviour_counts`), not a real error detector.

Splits (train and held-out differ)
----------------------------------
- Numbers: a SHA-1 of the problem's number tuple (start, signs, operands) puts it in exactly one
  split (about 20% to eval); each split draws from its own random stream. No held-out problem's
  numbers occur in training.
- Templates: the (start sentence, question) pair of a problem comes from 6 pairings in training
  and 3 other pairings in the held-out set (`template_split`). Every sentence form occurs in
  training; only the combination is new.
- Eval solutions are always worked and never contain a Check line (DIRECT_PROB and CHECK_PROB
  are train-only).
Why no new words in the held-out set: on an SFT model, held-out problems with unseen names and
items, an unseen opener or an unseen question scored far below training problems (docs/results-archive.md) --
the untrained embeddings of new words break the copying of the numbers. That tests vocabulary
coverage of a model trained from scratch, not arithmetic, and RL on training prompts could not fix
it; held-out numbers alone scored like training problems.

Rows: {"prompt", "completion" (the SFT target, starts with a space), "answer" (the gold number
as text, the verifier reference), "verifier": "math", "meta"}. `meta` keys: task, answer,
start, ops ([[sign, operand], ...]), n_steps, carries (columns with a carry/borrow out), style
("worked" | "direct"), check (the solution has a Check line), template ([start sentence,
question] indices), split.

Scoring: `evaluate` runs `posttrain.verifiers.get_verifier("math")` in-process on every completion (the
answers are short and the verifier has its own size guards; training uses the worker pool
through `posttrain.scoring.VerifierScorer`).
"""
from __future__ import annotations

import hashlib
import random
import re
from collections import Counter
from typing import Any, Literal, Sequence

from posttrain.tasks import gold

TASK_NAME = NAME = "tiny-math"
VERIFIER = "math"
GOLD_METRICS = {"accuracy": "accuracy", "length_chars": "mean_length_chars"}
gold_breakdown = None  # the gold score is correctness alone (gold_quality)
gold_key = None  # no preference ranking beyond right / wrong (gold_prefer)
PROMPT_TEMPLATE = "Question: {problem}\nAnswer:"

EVAL_FRACTION_BUCKETS = 5  # a number tuple goes to eval when sha1 % 5 == 0 (~20%)
DIRECT_QUESTION = 2  # "How many {items} are there now?": mostly answered without working in training
DIRECT_PROB = 0.8  # P(direct answer | DIRECT_QUESTION) in training; every other train row is worked
CHECK_PROB = 0.25  # worked train solutions with a "Check:" line
STEPS = (2, 3)  # operations per problem, equally likely
START_RANGE = (10, 99)
OPERAND_RANGE = (1, 99)
MAX_TOTAL = 999

NAMES = [("Ava", "she"), ("Ben", "he"), ("Mia", "she"), ("Leo", "he"), ("Zoe", "she"), ("Sam", "he"),
         ("Ivy", "she"), ("Max", "he"), ("Lily", "she"), ("Tom", "he"), ("Nora", "she"), ("Finn", "he"),
         ("Rosa", "she"), ("Hugo", "he"), ("Ada", "she"), ("Otto", "he")]
ITEMS = ["apples", "marbles", "stickers", "coins", "pencils", "cards", "shells", "stamps", "books", "eggs"]
START_FRAMES = ["{Name} has {n} {items}.", "{Name} had {n} {items}.", "There are {n} {items} in {Name}'s box."]
GAIN_CLAUSES = ["{pro} buys {n} more.", "{pro} finds {n} more.", "{pro} gets {n} more.", "{pro} is given {n} more."]
LOSS_CLAUSES = ["{pro} loses {n}.", "{pro} gives away {n}.", "{pro} sells {n} of them.", "{pro} uses {n}."]
OPENERS = ["", "Then "]
QUESTIONS = ["How many {items} does {Name} have now?", "How many {items} does {pro} have at the end?",
             "How many {items} are there now?"]


def template_split(start_frame: int, question: int) -> str:
    """Which split a (start sentence, question) template pair belongs to: 3 of the 9 pairs are held out.
    Every sentence form occurs in training; only these pairings are new in the held-out set."""
    return "eval" if (start_frame + question) % 3 == 0 else "train"


# Phrases counted by `behaviour_counts` (E7: do verification / self-correction phrases change under RL?).
# "check" is taught in some SFT solutions; the self-correction words never appear in any solution,
# so they would have to be invented by the policy.
VERIFICATION_PHRASES = ("check",)
SELF_CORRECTION_PHRASES = ("wait", "redo", "mistake", "actually", "let me", "again")


# --- the worked solution ------------------------------------------------------------------------

def _digits_lsd(n: int, width: int) -> list[int]:
    return [(n // 10 ** i) % 10 for i in range(width)]


def column_line(a: int, sign: str, b: int) -> tuple[str, int, int]:
    """("a+b: col, col, ..., result", result, columns with a carry/borrow out) for one operation."""
    if sign == "+":
        result = a + b
    elif sign == "-":
        if b > a:
            raise ValueError(f"column_line: {a}-{b} would be negative")
        result = a - b
    else:
        raise ValueError(f"column_line: sign must be '+' or '-', got {sign!r}")
    width = max(len(str(a)), len(str(b)))
    da, db = _digits_lsd(a, width), _digits_lsd(b, width)
    flag, cols, n_flags = 0, [], 0
    tag = "c" if sign == "+" else "b"
    for x, y in zip(da, db):
        v = x + y + flag if sign == "+" else x - y - flag
        digit, out = (v % 10, int(v >= 10)) if sign == "+" else (v % 10, int(v < 0))
        cols.append(f"{x}{sign}{y}{sign}{flag}={digit} {tag}{out}")
        n_flags += out
        flag = out
    return f"{a}{sign}{b}: {', '.join(cols)}, {result}", result, n_flags


def solution(start: int, ops: Sequence[tuple[str, int]], check: bool = False) -> tuple[str, int, int]:
    """(worked solution text, answer, total carries/borrows) of a problem; the text starts with a space."""
    lines = [" " + str(start) + "".join(f"{s}{n}" for s, n in ops)]
    total, carries = start, 0
    for sign, n in ops:
        line, new, c = column_line(total, sign, n)
        lines.append(line)
        carries += c
        prev, total = total, new
    if check:
        sign, n = ops[-1]
        inverse = "-" if sign == "+" else "+"
        lines.append(f"Check: {total}{inverse}{n}={prev}")
    lines.append(f"The answer is {total}.")
    return "\n".join(lines), total, carries


# --- generation ---------------------------------------------------------------------------------

def _split_of(start: int, ops: Sequence[tuple[str, int]]) -> str:
    key = f"{start}|" + "|".join(f"{s}{n}" for s, n in ops)
    digest = hashlib.sha1(key.encode()).hexdigest()
    return "eval" if int(digest[:8], 16) % EVAL_FRACTION_BUCKETS == 0 else "train"


def _numbers(rng: random.Random, split: str) -> tuple[int, list[tuple[str, int]]]:
    while True:
        start = rng.randint(*START_RANGE)
        total, ops = start, []
        for _ in range(rng.choice(STEPS)):
            if total >= OPERAND_RANGE[0] and (total + OPERAND_RANGE[0] > MAX_TOTAL or rng.random() < 0.5):
                n = rng.randint(OPERAND_RANGE[0], min(OPERAND_RANGE[1], total))
                ops.append(("-", n))
                total -= n
            else:
                n = rng.randint(OPERAND_RANGE[0], min(OPERAND_RANGE[1], MAX_TOTAL - total))
                ops.append(("+", n))
                total += n
        if _split_of(start, ops) == split:
            return start, ops


def _cap(s: str) -> str:
    return s[0].upper() + s[1:]


def _problem(rng: random.Random, split: str) -> dict[str, Any]:
    start, ops = _numbers(rng, split)
    name, pro = rng.choice(NAMES)
    items = rng.choice(ITEMS)
    frame, question = rng.choice([(f, q) for f in range(len(START_FRAMES)) for q in range(len(QUESTIONS))
                                  if template_split(f, q) == split])
    sentences = [START_FRAMES[frame].format(Name=name, n=start, items=items)]
    for sign, n in ops:
        clause = rng.choice(GAIN_CLAUSES if sign == "+" else LOSS_CLAUSES)
        opener = rng.choice(OPENERS)
        who = rng.choice([name, pro]) if not opener else pro
        text = clause.format(pro=who, n=n)
        sentences.append(_cap(opener + text) if opener else _cap(text))
    sentences.append(QUESTIONS[question].format(Name=name, pro=pro, items=items))
    direct = split == "train" and question == DIRECT_QUESTION and rng.random() < DIRECT_PROB
    check = split == "train" and not direct and rng.random() < CHECK_PROB
    completion, answer, carries = solution(start, ops, check)
    if direct:
        completion = f" The answer is {answer}."
    meta = {"task": TASK_NAME, "answer": str(answer), "start": start, "ops": [[s, n] for s, n in ops],
            "n_steps": len(ops), "carries": carries, "style": "direct" if direct else "worked", "check": check,
            "template": [frame, question], "split": split}
    return {"prompt": PROMPT_TEMPLATE.format(problem=" ".join(sentences)), "completion": completion,
            "answer": str(answer), "verifier": VERIFIER, "meta": meta}


def make_examples(n: int, seed: int, split: Literal["train", "eval"]) -> list[dict[str, Any]]:
    """`n` rows {"prompt", "completion", "answer", "verifier", "meta"}; deterministic in (n, seed, split),
    and a prefix of a longer call with the same seed and split."""
    if split not in ("train", "eval"):
        raise ValueError(f"split must be 'train' or 'eval', got {split!r}")
    if not isinstance(n, int) or n < 0:
        raise ValueError(f"n must be an integer >= 0, got {n!r}")
    rng = random.Random(f"{TASK_NAME}:{split}:{seed}")
    return [_problem(rng, split) for _ in range(n)]


def corpus(n: int, seed: int) -> list[str]:
    """Texts for training the tokenizer: `n` train prompts with their solutions."""
    return [ex["prompt"] + ex["completion"] for ex in make_examples(n, seed, "train")]


# --- scoring ------------------------------------------------------------------------------------

def _math_verifier():
    return gold.verifier(VERIFIER)


def _answer_of(meta: Any, i: int) -> str:
    return gold.answer_of(meta, i, TASK_NAME, "66")


def score(meta: dict[str, Any], completion: str) -> tuple[float, str]:
    """(1.0 or 0.0, the verifier's reason) of one completion against meta["answer"]."""
    v = _math_verifier().check(completion, _answer_of(meta, 0))
    return float(v.score), v.reason


def gold_quality(meta: dict[str, Any], completion: str) -> float:
    """Correctness (1 or 0) through the math verifier: `posttrain.scoring.GoldScorer` uses it."""
    return score(meta, completion)[0]


def gold_prefer(meta: dict[str, Any], a: str, b: str) -> int:
    """+1 if only `a` is correct, -1 if only `b` is, 0 otherwise."""
    return gold.prefer(gold_quality(meta, a), gold_quality(meta, b))


def win_rate(metas: Sequence[dict[str, Any]], candidates: Sequence[str], baselines: Sequence[str]) -> float:
    """Fraction of problems where the candidate is right and the baseline wrong; ties count half."""
    return gold.win_rate(gold_prefer, metas, candidates, baselines)


def equation_of(meta: dict[str, Any]) -> str:
    """The first solution line for this problem ("47+38-19")."""
    return str(meta["start"]) + "".join(f"{s}{n}" for s, n in meta["ops"])


_COLUMN_RE = re.compile(r"\d[+-]\d[+-]\d=\d [cb]\d")


def is_worked(completion: str) -> bool:
    """Whether a completion works the problem (holds at least one column step) rather than stating an answer."""
    return bool(_COLUMN_RE.search(completion))


def behaviour_counts(completions: Sequence[str]) -> dict[str, float]:
    """Per completion: the fraction that works the problem in columns (`is_worked`), the fraction that
    contains a verification phrase and a self-correction phrase, and the mean number of each
    (case-insensitive, whole words)."""
    def count(text: str, phrases: Sequence[str]) -> int:
        low = text.lower()
        return sum(len(re.findall(r"\b" + re.escape(p) + r"\b", low)) for p in phrases)

    n = max(1, len(completions))
    ver = [count(c, VERIFICATION_PHRASES) for c in completions]
    cor = [count(c, SELF_CORRECTION_PHRASES) for c in completions]
    return {"frac_worked": sum(is_worked(c) for c in completions) / n,
            "frac_verification": sum(v > 0 for v in ver) / n, "mean_verification": sum(ver) / n,
            "frac_self_correction": sum(c > 0 for c in cor) / n, "mean_self_correction": sum(cor) / n}


def evaluate(metas: Sequence[dict[str, Any]], completions: Sequence[str]) -> dict[str, float]:
    """Accuracy through the math verifier, plus where failures come from and behaviour counts."""
    if len(metas) != len(completions):
        raise ValueError(f"evaluate needs equal lengths, got {len(metas)} metas and {len(completions)} completions")
    if not metas:
        raise ValueError("evaluate of zero examples is undefined")
    answers = [_answer_of(m, i) for i, m in enumerate(metas)]
    verdicts = [_math_verifier().check(c, a) for c, a in zip(completions, answers)]
    n = len(metas)
    correct = [v.score >= 1.0 for v in verdicts]
    reasons = Counter(v.reason for v in verdicts)
    out: dict[str, float] = {
        "n": n,
        "accuracy": sum(correct) / n,
        "frac_no_answer": reasons.get("no answer found", 0) / n,
        "frac_equation_right": sum(c.lstrip().startswith(equation_of(m) + "\n") for m, c in zip(metas, completions)
                                   if "start" in m and "ops" in m) / n,
        "mean_length_chars": sum(len(c) for c in completions) / n,
    }
    for k in STEPS:
        idx = [i for i, m in enumerate(metas) if m.get("n_steps") == k]
        if idx:
            out[f"accuracy_{k}_steps"] = sum(correct[i] for i in idx) / len(idx)
    out.update(behaviour_counts(completions))
    return out
