"""tiny-math: generation, splits, worked solutions checked by the math verifier, evaluate, bad rows,
and the digit-splitting tokenizer the recipe relies on."""
from __future__ import annotations

import re

import pytest

from posttrain.tasks import get_task
from posttrain.tasks import math as M


@pytest.fixture(scope="module")
def train():
    return M.make_examples(500, seed=0, split="train")


@pytest.fixture(scope="module")
def eval_set():
    return M.make_examples(500, seed=0, split="eval")


def numbers_of(row) -> tuple:
    meta = row["meta"]
    return (meta["start"],) + tuple((s, n) for s, n in meta["ops"])


# --- generation ------------------------------------------------------------------------------------

def test_registered():
    assert get_task("tiny-math") is M


def test_deterministic_per_seed_and_prefix_stable():
    a = M.make_examples(50, seed=3, split="train")
    assert a == M.make_examples(50, seed=3, split="train")
    assert a[:10] == M.make_examples(10, seed=3, split="train")
    assert a != M.make_examples(50, seed=4, split="train")
    assert M.make_examples(0, seed=3, split="eval") == []


def test_bad_arguments():
    with pytest.raises(ValueError, match="split must be 'train' or 'eval'"):
        M.make_examples(1, seed=0, split="test")  # type: ignore[arg-type]
    with pytest.raises(ValueError, match="n must be an integer >= 0"):
        M.make_examples(-1, seed=0, split="train")


def test_row_format(train):
    for row in train:
        assert row["prompt"].startswith("Question: ") and row["prompt"].endswith("\nAnswer:")
        assert row["completion"].startswith(" ")
        assert row["verifier"] == "math"
        assert row["answer"] == row["meta"]["answer"] == str(int(row["answer"]))
        assert row["meta"]["n_steps"] in M.STEPS and len(row["meta"]["ops"]) == row["meta"]["n_steps"]
        assert row["completion"].rstrip().endswith(f"The answer is {row['answer']}.")
    # the rows are valid under both schemas the trainers read: sft (prompt, completion) and verifiable
    from posttrain.data import validate_rows

    validate_rows(train, "sft")
    validate_rows(train, "verifiable")


def test_number_ranges_and_mix(train):
    for row in train:
        meta = row["meta"]
        assert M.START_RANGE[0] <= meta["start"] <= M.START_RANGE[1]
        total = meta["start"]
        for sign, n in meta["ops"]:
            assert M.OPERAND_RANGE[0] <= n <= M.OPERAND_RANGE[1]
            total = total + n if sign == "+" else total - n
            assert 0 <= total <= M.MAX_TOTAL
        assert total == int(meta["answer"])
    steps = [r["meta"]["n_steps"] for r in train]
    assert 0.35 < steps.count(2) / len(steps) < 0.65
    signs = [s for r in train for s, _ in r["meta"]["ops"]]
    assert 0.35 < signs.count("+") / len(signs) < 0.65
    worked = [r for r in train if r["meta"]["style"] == "worked"]
    checks = sum(r["meta"]["check"] for r in worked) / len(worked)
    assert abs(checks - M.CHECK_PROB) < 0.08


def test_two_styles(train, eval_set):
    """Training answers the DIRECT_QUESTION phrasing mostly without working; everything else is worked."""
    direct = [r for r in train if r["meta"]["style"] == "direct"]
    asked = [r for r in train if r["meta"]["template"][1] == M.DIRECT_QUESTION]
    assert direct and all(r["meta"]["template"][1] == M.DIRECT_QUESTION for r in direct)
    assert abs(len(direct) / len(asked) - M.DIRECT_PROB) < 0.1
    for r in direct:
        assert r["completion"] == f" The answer is {r['answer']}." and not r["meta"]["check"]
        assert not M.is_worked(r["completion"])
    assert all(M.is_worked(r["completion"]) for r in train if r["meta"]["style"] == "worked")
    # held-out references are always worked, the held-out set does ask the direct question
    assert all(r["meta"]["style"] == "worked" for r in eval_set)
    assert any(r["meta"]["template"][1] == M.DIRECT_QUESTION for r in eval_set)


def test_splits_differ(train, eval_set):
    # no held-out number tuple occurs in training (also not under another seed), nor any prompt
    held = {numbers_of(r) for r in eval_set}
    assert not held & {numbers_of(r) for r in train}
    assert not held & {numbers_of(r) for r in M.make_examples(500, seed=9, split="train")}
    assert not {r["prompt"] for r in eval_set} & {r["prompt"] for r in train}
    # the (start sentence, question) pairings are disjoint, each sentence form is seen in training
    train_t = {tuple(r["meta"]["template"]) for r in train}
    eval_t = {tuple(r["meta"]["template"]) for r in eval_set}
    assert train_t and eval_t and not train_t & eval_t
    assert {f for f, _ in eval_t} <= {f for f, _ in train_t} and {q for _, q in eval_t} <= {q for _, q in train_t}
    # held-out solutions never carry a Check line; some training solutions do
    assert not any(r["meta"]["check"] or "Check:" in r["completion"] for r in eval_set)
    assert any("Check:" in r["completion"] for r in train)


# --- worked solutions ------------------------------------------------------------------------------

def test_column_lines_hand_computed():
    assert M.column_line(47, "+", 38) == ("47+38: 7+8+0=5 c1, 4+3+1=8 c0, 85", 85, 1)
    assert M.column_line(85, "-", 19) == ("85-19: 5-9-0=6 b1, 8-1-1=6 b0, 66", 66, 1)
    assert M.column_line(95, "+", 38)[0] == "95+38: 5+8+0=3 c1, 9+3+1=3 c1, 133"  # final carry -> leading 1
    assert M.column_line(85, "-", 79)[0] == "85-79: 5-9-0=6 b1, 8-7-1=0 b0, 6"  # leading zero dropped
    assert M.column_line(104, "-", 4)[0] == "104-4: 4-4-0=0 b0, 0-0-0=0 b0, 1-0-0=1 b0, 100"
    assert M.column_line(9, "-", 9)[0] == "9-9: 9-9-0=0 b0, 0"
    with pytest.raises(ValueError, match="negative"):
        M.column_line(5, "-", 9)
    text, answer, carries = M.solution(47, [("+", 38), ("-", 19)], check=True)
    assert text == (" 47+38-19\n47+38: 7+8+0=5 c1, 4+3+1=8 c0, 85\n85-19: 5-9-0=6 b1, 8-1-1=6 b0, 66\n"
                    "Check: 66+19=85\nThe answer is 66.")
    assert (answer, carries) == (66, 2)


_COL = re.compile(r"(\d)([+-])(\d)\2(\d)=(\d) ([cb])(\d)")


def test_every_column_is_right(train, eval_set):
    """Re-derive every column of every worked solution from its three input digits."""
    for row in train + eval_set:
        for a, sign, b, flag, digit, tag, out in _COL.findall(row["completion"]):
            a, b, flag, digit, out = int(a), int(b), int(flag), int(digit), int(out)
            v = a + b + flag if sign == "+" else a - b - flag
            assert digit == v % 10 and tag == ("c" if sign == "+" else "b")
            assert out == (int(v >= 10) if sign == "+" else int(v < 0)), row["completion"]


def test_the_verifier_scores_every_gold_solution_1(train, eval_set):
    from posttrain.verifiers.registry import get_verifier

    verifier = get_verifier("math")
    for row in train + eval_set:
        verdict = verifier.check(row["completion"], row["answer"])
        assert verdict.score == 1.0, (row["completion"], verdict)


# --- evaluate --------------------------------------------------------------------------------------

def test_evaluate_gold_wrong_and_missing(train, eval_set):
    rows = eval_set[:40]
    metas = [r["meta"] for r in rows]
    gold = M.evaluate(metas, [r["completion"] for r in rows])
    assert gold["accuracy"] == 1.0 and gold["frac_equation_right"] == 1.0 and gold["n"] == 40
    assert gold["frac_no_answer"] == 0.0 and gold["frac_verification"] == 0.0 and gold["frac_worked"] == 1.0
    assert gold["accuracy_2_steps"] == 1.0 and gold["accuracy_3_steps"] == 1.0

    wrong = [r["completion"].replace(f"The answer is {r['answer']}.", f"The answer is {int(r['answer']) + 1}.")
             for r in rows]
    assert M.evaluate(metas, wrong)["accuracy"] == 0.0
    half = [c if i % 2 else "" for i, c in enumerate(wrong)]
    m = M.evaluate(metas, half)
    assert m["accuracy"] == 0.0 and m["frac_no_answer"] == 0.5
    # a retraction after the answer voids it (the verifier's rule), a boxed answer counts
    assert M.score(rows[0]["meta"], f"The answer is {rows[0]['answer']}. Wait, no.")[0] == 0.0
    assert M.score(rows[0]["meta"], f"\\boxed{{{rows[0]['answer']}}}") == (1.0, "correct")

    with_check = [r for r in train if r["meta"]["check"]][:5]
    b = M.behaviour_counts([r["completion"] for r in with_check] + ["Let me redo this. Wait, check again."])
    assert b["frac_verification"] == 1.0 and b["mean_verification"] == 1.0
    assert b["frac_self_correction"] == pytest.approx(1 / 6) and b["mean_self_correction"] == pytest.approx(4 / 6)


def test_win_rate_and_gold_prefer(eval_set):
    rows = eval_set[:4]
    metas = [r["meta"] for r in rows]
    right = [r["completion"] for r in rows]
    wrong = ["The answer is -1."] * 4
    assert M.gold_prefer(metas[0], right[0], wrong[0]) == 1 and M.gold_prefer(metas[0], wrong[0], right[0]) == -1
    assert M.win_rate(metas, right, wrong) == 1.0
    assert M.win_rate(metas, right, right) == 0.5
    assert M.win_rate(metas, [right[0], wrong[1], right[2], wrong[3]], wrong) == 0.75
    from posttrain.scoring import GoldScorer

    assert GoldScorer("tiny-math").score([r["prompt"] for r in rows], right[:2] + wrong[:2], metas).rewards == \
        [1.0, 1.0, 0.0, 0.0]


def test_bad_rows(eval_set):
    metas = [r["meta"] for r in eval_set[:3]]
    with pytest.raises(ValueError, match="equal lengths"):
        M.evaluate(metas, ["x"])
    with pytest.raises(ValueError, match="zero examples"):
        M.evaluate([], [])
    broken = [metas[0], {"task": "tiny-math"}, metas[2]]
    with pytest.raises(ValueError, match=r"row 2: meta has no 'answer'"):
        M.evaluate(broken, ["a", "b", "c"])
    with pytest.raises(ValueError, match=r"row 1: meta has no 'answer'"):
        M.evaluate([None], ["a"])  # type: ignore[list-item]
    with pytest.raises(ValueError, match="equal lengths"):
        M.win_rate(metas, ["a"], ["b"])


# --- the tokenizer and the recipe ------------------------------------------------------------------

def test_split_digits_tokenizer_makes_every_digit_a_token():
    from posttrain.models import train_tokenizer

    texts = M.corpus(300, seed=0)
    row = M.make_examples(1, seed=0, split="train")[0]
    split = train_tokenizer(texts, vocab_size=512, split_digits=True)
    for text in (row["prompt"], row["completion"], " 123 4567"):
        ids = split(text, add_special_tokens=False)["input_ids"]
        toks = [split.decode([i]) for i in ids]
        assert all(not any(ch.isdigit() for ch in t) or t.strip().isdigit() and len(t.strip()) == 1 for t in toks), toks
        assert all(len(t) == 1 for t in toks if t.strip().isdigit()), toks  # no space glued to a digit either
        assert split.decode(ids) == text
    # the default (off) is unchanged: BPE merges frequent numbers
    merged = train_tokenizer(texts, vocab_size=512)
    assert any(sum(ch.isdigit() for ch in merged.decode([i])) > 1 for i in merged(row["completion"])["input_ids"])


def test_recipe_loads_with_digit_splitting():
    from posttrain.cli import STAGES
    from posttrain.config import resolve

    for stage in ("sft", "eval"):
        res = resolve("tiny-math", stage, STAGES[stage].load()[0], [])
        assert res.task.name == "tiny-math" and res.model.split_digits is True
        assert res.stage_cfg.max_new_tokens >= 160  # the longest worked solution is ~160 tokens


def test_evaluate_through_the_eval_path():
    """What `posttrain eval` runs: greedy completions from the rollout engine, the task's metrics, win rate."""
    import torch

    from posttrain import evaluation
    from posttrain.models import build_model, train_tokenizer

    torch.manual_seed(0)
    tok = train_tokenizer(M.corpus(200, seed=0), vocab_size=384, split_digits=True)
    model = build_model("tiny", tok, seed=0)
    rows = M.make_examples(4, seed=0, split="eval")
    out = evaluation.evaluate_model("tiny-math", model, tok, rows, max_new_tokens=8)
    assert out["n"] == 4 and out["accuracy"] == 0.0 and len(out["_completions"]) == 4
    gold = [r["completion"] for r in rows]
    assert evaluation.win_rate("tiny-math", rows, gold, out["_completions"]) == 1.0
