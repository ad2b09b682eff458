"""tiny-code: write a one-line Python function from a sentence, checked by unit tests in the code sandbox.

CPU:        posttrain grpo --recipe tiny-code             (SFT first, then GRPO; see the recipe header)
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain grpo --recipe tiny-code model.path=small

Pure Python (no torch). The checker is the verifier layer's code sandbox (registry name "code",
`verifiers/code_sandbox`): the completion is run in a sandboxed process against the reference's
asserts. This module generates the problems, worked solutions for SFT and the gold evaluation.

Example (JSON-serialisable):

    {"prompt": "Write a Python function add_7(x) that returns x plus 7.\\n",
     "completion": "def add_7(x):\\n    return x + 7\\n",
     "answer": {"tests": ["assert add_7(3) == 10", ...], "entry_point": "add_7"},   # verifier reference
     "meta": {"task": "tiny-code", "reference": {...same...}, "template": "add", "constants": [7],
              "phrasing": 0, "solution": "x + 7"}}

Problems: 14 templates (arithmetic on an int, predicates, min / max, list sum / count / first
item, string repeat / length), each with one or two integer constants (2..20, second 1..9), two
phrasings, and a parameter name drawn from a few; the function name is the template's verb and
the constants (`add_7`, `affine_3_5`). Each problem gets 3 asserts on seeded inputs (for ints: a multiple of the
constant, a value above it, one below it), the expected
values computed by running the reference body in this process. The completion is the bare
function (no markdown fence: the sandbox extracts unfenced code as is).

Splits: a SHA-1 of (template, constants, phrasing) sends about 20% of the problem space to
"eval" and the rest to "train"; the vocabulary is shared, so held-out problems are new
combinations of seen pieces, not unseen words. `make_examples(n, seed, split)` is deterministic
and a prefix of a longer call with the same seed and split; problems repeat within a split
(with fresh test inputs) when n exceeds its size (about 1,900 train problems).
"""
from __future__ import annotations

import hashlib
import random
from typing import Any, Callable, Literal, Sequence

NAME = "tiny-code"
VERIFIER = "code"
GOLD_METRICS = {"accuracy": "accuracy", "length_chars": "length_chars"}
# The verifier is the only signal: no gold score, preference or win-rate (posttrain.tasks.Task).
gold_quality = gold_breakdown = gold_key = gold_prefer = win_rate = None
"""The verifier spec GRPO uses when the recipe sets none (`grpo.verifier: auto`)."""
EVAL_FRACTION = 0.2

# key, argument kind, two phrasings ({p}: parameter, {a}, {b}: constants), body, number of constants
_TEMPLATES: list[tuple[str, str, tuple[str, str], str, int]] = [
    ("add", "int", ("returns {p} plus {a}", "adds {a} to {p}"), "{p} + {a}", 1),
    ("sub", "int", ("returns {p} minus {a}", "subtracts {a} from {p}"), "{p} - {a}", 1),
    ("times", "int", ("returns {p} times {a}", "multiplies {p} by {a}"), "{p} * {a}", 1),
    ("mod", "int", ("returns {p} modulo {a}", "returns the remainder of {p} divided by {a}"), "{p} % {a}", 1),
    ("divisible", "int", ("returns True when {p} is divisible by {a}", "checks whether {a} divides {p}"),
     "{p} % {a} == 0", 1),
    ("above", "int", ("returns True when {p} is greater than {a}", "checks whether {p} exceeds {a}"), "{p} > {a}", 1),
    ("cap", "int", ("returns the smaller of {p} and {a}", "returns {p} but at most {a}"), "min({p}, {a})", 1),
    ("floor", "int", ("returns the larger of {p} and {a}", "returns {p} but at least {a}"), "max({p}, {a})", 1),
    ("affine", "int", ("returns {p} times {a} plus {b}", "multiplies {p} by {a} and adds {b}"), "{p} * {a} + {b}", 2),
    ("sum_plus", "list", ("returns the sum of the list {p} plus {a}", "adds {a} to the total of the list {p}"),
     "sum({p}) + {a}", 1),
    ("count", "list",
     ("returns how many times {a} occurs in the list {p}", "counts the items of the list {p} equal to {a}"),
     "{p}.count({a})", 1),
    ("first_plus", "list",
     ("returns the first item of the list {p} plus {a}", "adds {a} to the first item of the list {p}"),
     "{p}[0] + {a}", 1),
    ("repeat", "str", ("returns the string {p} repeated {a} times", "repeats the string {p} {a} times"),
     "{p} * {a}", 1),
    ("len_plus", "str", ("returns the length of the string {p} plus {a}", "adds {a} to the length of the string {p}"),
     "len({p}) + {a}", 1),
]
_PARAMS = {"int": ("x", "n", "v"), "list": ("xs", "items", "nums"), "str": ("s", "text", "word")}
_A = range(2, 21)
_B = range(1, 10)
_WORDS = ("ab", "cat", "sun", "x", "tree", "go", "blue", "hello")


def _split_of(key: str, a: int, b: int, phrasing: int) -> str:
    h = hashlib.sha1(f"{key}/{a}/{b}/{phrasing}".encode()).digest()
    return "eval" if h[0] < 256 * EVAL_FRACTION else "train"


def _problems(split: str) -> list[tuple[int, int, int, int]]:
    """(template index, a, b, phrasing) of every problem of `split`, in a fixed order."""
    out = []
    for t, (key, _, _, _, n_const) in enumerate(_TEMPLATES):
        for a in _A:
            for b in (_B if n_const == 2 else [0]):
                for ph in (0, 1):
                    if _split_of(key, a, b, ph) == split:
                        out.append((t, a, b, ph))
    return out


def _inputs(kind: str, rng: random.Random, a: int, i: int) -> Any:
    if kind == "int":  # a multiple of a, a value above a, one below: the asserts tell the templates apart
        return (a * rng.randint(1, 4), rng.randint(a + 1, a + 20), rng.randint(-10, a - 1))[i % 3]
    if kind == "list":
        return [rng.choice([a, rng.randint(0, 30)]) for _ in range(rng.randint(1, 5))]
    return rng.choice(_WORDS)


def _function(body: str, param: str) -> Callable[[Any], Any]:
    code = compile(f"lambda {param}: {body}", "<reference>", "eval")
    return eval(code, {"__builtins__": {"sum": sum, "min": min, "max": max, "len": len}})  # our own template


def _example(rng: random.Random, problem: tuple[int, int, int, int]) -> dict[str, Any]:
    t, a, b, ph = problem
    key, kind, phrasings, body_t, n_const = _TEMPLATES[t]
    param = rng.choice(_PARAMS[kind])
    name = f"{key}_{a}" + (f"_{b}" if n_const == 2 else "")
    body = body_t.format(p=param, a=a, b=b)
    fn = _function(body, param)
    tests, seen, i = [], set(), 0
    while len(tests) < 3:
        arg = _inputs(kind, rng, a, i)
        i += 1
        if repr(arg) in seen:
            continue
        seen.add(repr(arg))
        tests.append(f"assert {name}({arg!r}) == {fn(arg)!r}")
    reference = {"tests": tests, "entry_point": name}
    sentence = phrasings[ph].format(p=param, a=a, b=b)
    return {"prompt": f"Write a Python function {name}({param}) that {sentence}.\n",
            "completion": f"def {name}({param}):\n    return {body}\n",
            "answer": reference,
            "meta": {"task": NAME, "reference": reference, "template": key, "constants": [a, b][:n_const],
                     "phrasing": ph, "solution": body}}


def make_examples(n: int, seed: int, split: Literal["train", "eval"]) -> list[dict[str, Any]]:
    """`n` problems of `split` (module docstring): a seeded shuffle of the split's problems, cycled."""
    if split not in ("train", "eval"):
        raise ValueError(f"split must be 'train' or 'eval', got {split!r}")
    problems = _problems(split)
    rng = random.Random(f"posttrain/tiny-code/{split}/{seed}")
    rows: list[dict[str, Any]] = []
    while len(rows) < n:
        order = problems[:]
        rng.shuffle(order)
        for p in order[: n - len(rows)]:
            rows.append(_example(rng, p))
    return rows


def corpus(n: int, seed: int) -> list[str]:
    """Prompt + solution texts of both splits (tokenizer training)."""
    rows = make_examples(n, seed, "train") + make_examples(max(1, n // 4), seed, "eval")
    return [r["prompt"] + r["completion"] for r in rows]


def evaluate(metas: Sequence[dict[str, Any]], completions: Sequence[str], workers: int = 2) -> dict[str, float]:
    """accuracy (every test passes in the sandbox), tests_passed (fraction of tests), mean completion length."""
    from posttrain.verifiers.code_sandbox import CodeVerifier
    from posttrain.verifiers.runner import score_batch

    verdicts = score_batch(CodeVerifier(partial_credit=True), list(completions), [m["reference"] for m in metas],
                           workers=workers)
    n = max(1, len(completions))
    return {"accuracy": sum(v.score >= 1.0 for v in verdicts) / n,
            "tests_passed": sum(v.score for v in verdicts) / n,
            "length_chars": sum(len(c) for c in completions) / n}
