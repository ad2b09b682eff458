"""data/word-calc-own.jsonl: 60 word problems written by hand, in phrasings apart from word-math's templates, held out
for the smol-tools recipe (calc-words; grpo.eval_file=data/word-calc-own.jsonl) and never trained or tuned on.

Checked here: each row's answer is its `meta.ops` evaluated in order (exact, integer, never below zero), the prompt's
numbers are exactly the operands, the numbers and answers are level-4-like, prompts are unique and share no 8-word
sequence with any prompt word-math writes at levels 4-5 (either split), and the project's loaders read the file as
GRPO problems (schema "verifiable" with its checks, and the environment's "prompt" rows). Torch-free checks, but
the loaders' module imports torch (as the conftest does).
"""
from __future__ import annotations

import json
import re
from collections import Counter
from fractions import Fraction
from pathlib import Path

import pytest

from posttrain.tasks import wordmath
from posttrain.verifiers.envs.calc import INTEGER, WordCalcEnv, calculator, running_totals

FILE = Path(__file__).resolve().parents[2] / "data" / "word-calc-own.jsonl"
N_ROWS = 60
OPERAND = (100, 9999)
MAX_ANSWER = 100_000
NGRAM = 8
GENERATED = 2000  # word-math rows per (level, split) compared against


def _rows() -> list[dict]:
    return [json.loads(line) for line in FILE.read_text(encoding="utf-8").splitlines() if line.strip()]


ROWS = _rows()


def _evaluate(ops: list) -> list[int]:
    """The running totals of `ops` in order; asserts every step is exact, integer and non-negative."""
    assert ops and ops[0][0] == "=", ops
    totals = []
    total = ops[0][1]
    for i, (op, n) in enumerate(ops[1:], 1):
        if op == "+":
            total += n
        elif op == "-":
            total -= n
        elif op == "*":
            total *= n
        elif op == "/":
            assert i == len(ops) - 1, f"a share is the last step only: {ops}"
            assert total % n == 0, f"{total} / {n} is not exact"
            total //= n
        else:
            raise AssertionError(f"unknown operation {op!r} in {ops}")
        assert isinstance(total, int) and total >= 0, f"running total {total} below zero in {ops}"
        totals.append(total)
    return totals


def _words(text: str) -> list[str]:
    return ["#" if w.isdigit() else w for w in re.findall(r"[a-z']+|\d+", text.lower())]


def _ngrams(text: str) -> set[tuple[str, ...]]:
    w = _words(text)
    return {tuple(w[i:i + NGRAM]) for i in range(len(w) - NGRAM + 1)}


def test_sixty_rows_in_the_verifiable_form():
    assert len(ROWS) == N_ROWS
    for i, row in enumerate(ROWS, 1):
        assert set(row) == {"prompt", "answer", "verifier", "meta"}, i
        assert row["verifier"] == "math" and isinstance(row["prompt"], str) and row["prompt"].strip(), i
        assert isinstance(row["answer"], str) and re.fullmatch(r"0|[1-9]\d*", row["answer"]), i
        assert row["meta"]["source"] == "own" and set(row["meta"]) == {"ops", "source"}, i


@pytest.mark.parametrize("i", range(N_ROWS))
def test_answer_is_the_ops_evaluated_in_order(i):
    row = ROWS[i]
    ops = row["meta"]["ops"]
    assert 2 <= len(ops) <= 3, f"1-2 operations: {ops}"
    for op, n in ops:
        assert op in ("=", "+", "-", "*", "/") and type(n) is int, ops
        assert OPERAND[0] <= n <= OPERAND[1], f"operand {n} outside {OPERAND}"
    assert [op for op, _ in ops].count("=") == 1
    totals = _evaluate(ops)
    assert row["answer"] == str(totals[-1]) and 0 <= totals[-1] <= MAX_ANSWER
    assert max(totals) <= MAX_ANSWER
    assert wordmath.apply([tuple(o) for o in ops]) == totals[-1]  # the generator's own evaluation agrees
    # the environment's partial credit reads the same running totals
    assert running_totals(row) == {Fraction(ops[0][1])} | {Fraction(t) for t in totals}
    # the whole expression as word-calc's demonstrations write it (a share divides everything before it)
    from posttrain.tasks.wordcalc import expression

    assert calculator(expression(ops)) == row["answer"]


@pytest.mark.parametrize("i", range(N_ROWS))
def test_prompt_numbers_are_exactly_the_operands(i):
    row = ROWS[i]
    operands = Counter(n for _, n in row["meta"]["ops"])
    assert Counter(int(x) for x in re.findall(r"\d+", row["prompt"])) == operands, row["prompt"]
    # calc-words' credit_parts reads the prompt's numbers with INTEGER (digit groups "1 204" joined): the same ones
    assert Counter(int(re.sub(r"[, ]", "", x)) for x in INTEGER.findall(row["prompt"])) == operands, row["prompt"]


def test_prompts_are_unique():
    norm = [" ".join(row["prompt"].lower().split()) for row in ROWS]
    assert len(set(norm)) == len(norm), [p for p, c in Counter(norm).items() if c > 1]


def test_mix_of_operations():
    kinds = ["".join(op for op, _ in row["meta"]["ops"][1:]) for row in ROWS]
    one = sum(len(k) == 1 for k in kinds)
    assert 0.3 <= one / N_ROWS <= 0.5, Counter(kinds)
    assert sum("*" in k for k in kinds) >= 8 and sum("/" in k for k in kinds) >= 5, Counter(kinds)


def test_no_names_or_item_words_of_the_generator():
    vocab = {name.lower() for name, _, _ in wordmath.NAMES}
    vocab |= {w for item in wordmath.ITEMS for w in (item, item.rstrip("s"), item.removesuffix("es"))}
    for row in ROWS:
        used = vocab & set(_words(row["prompt"]))
        assert not used, (row["prompt"], used)


@pytest.fixture(scope="module")
def generated_ngrams() -> set[tuple[str, ...]]:
    grams: set[tuple[str, ...]] = set()
    for level in (4, 5):
        for split in ("train", "eval"):
            for r in wordmath.make_examples(GENERATED, 0, split, level):
                grams |= _ngrams(r["prompt"])
    return grams


def test_no_eight_word_sequence_shared_with_the_generator(generated_ngrams):
    assert len(generated_ngrams) > 1000  # the comparison saw the templates
    shared = {row["prompt"]: sorted(_ngrams(row["prompt"]) & generated_ngrams) for row in ROWS}
    assert not {p: g for p, g in shared.items() if g}


def test_loads_as_grpo_problems_with_the_projects_checks():
    """grpo.eval_file's path through `posttrain.problems`: `split_rows` (load_rows, schema "verifiable") and
    `check_problems` (on_bad_rows=error), then the verifier `auto` picks from the rows' `verifier` field."""
    from posttrain import tasks
    from posttrain.config import TaskConfig
    from posttrain.problems import build_verifier, check_problems, split_rows

    task_cfg = TaskConfig(name="word-calc")
    rows, source = split_rows(task_cfg, "eval", str(FILE), "verifiable")
    problems, skipped = check_problems(rows, source, "error")
    assert skipped == [] and len(problems) == N_ROWS and source == str(FILE)
    assert [p.prompt for p in problems] == [r["prompt"] for r in ROWS]
    assert [p.reference for p in problems] == [r["answer"] for r in ROWS]
    assert [r["meta"] for r in rows] == [r["meta"] for r in ROWS]  # meta (ops, source) comes through as written
    verifier = build_verifier("auto", {}, tasks.get_task("word-calc"), rows)
    assert verifier.name == "math"
    assert all(verifier.check(f"The answer is {r['answer']}.", r["answer"]).score == 1.0 for r in ROWS)


def test_loads_as_calc_words_episodes():
    """With grpo.env set (smol-tools: calc-words) the file is read with schema "prompt" and each row becomes the
    environment's problem (`env_problem`): the question as the user turn, the answer and meta.ops for the reward."""
    from posttrain.config import TaskConfig
    from posttrain.problems import env_problem, split_rows

    rows, _ = split_rows(TaskConfig(name="word-calc"), "eval", str(FILE), "prompt")
    env = WordCalcEnv(partial_credit=0.5)
    assert len(rows) == N_ROWS
    for row, own in zip(rows, ROWS):
        problem = env_problem(row)
        assert problem["answer"] == own["answer"] and problem["meta"]["ops"] == own["meta"]["ops"]
        assert env.reset(problem)[-1]["content"] == own["prompt"]
        assert env.score(problem, f"The answer is {own['answer']}.")[0] == 1.0
