"""word-calc: word-math problems as calculator demonstrations for the calc-words environment (torch-free)."""
import pytest

from posttrain.problems import env_problem
from posttrain.tasks import get_task, wordcalc as W, wordmath
from posttrain.verifiers.envs import parse_tool_calls
from posttrain.verifiers.envs.calc import WordCalcEnv, calculator


def test_every_demonstration_calls_the_tool_with_the_whole_expression_and_answers_its_result():
    env = WordCalcEnv()
    rows = W.make_examples(64, seed=0, split="train")
    assert get_task("word-calc") is W
    for k, row in enumerate(rows):
        msgs = row["messages"]
        assert [m["role"] for m in msgs[:2]] == ["system", "user"] and msgs[0] == env.reset({"prompt": "x"})[0]
        calls = [parse_tool_calls(m["content"]) for m in msgs if m["role"] == "assistant"][:-1]
        results = [m["content"] for m in msgs if m["role"] == "tool"]
        assert calls[-1][0].arguments == {"expression": row["meta"]["expression"]}
        assert results[-1] == calculator(row["meta"]["expression"]) == row["answer"]
        if k % W.RECOVERY_EVERY == W.RECOVERY_EVERY - 1:  # a refused call first, then the right one
            assert len(calls) == 2 and results[0].startswith("error: ValueError:")
        else:
            assert len(calls) == 1
        assert env.score({"answer": row["answer"]}, row["completion"]) == (1.0, "correct")
        assert env_problem(row)["prompt"] == msgs[1]["content"]  # GRPO starts the episode from the question
    assert W.evaluate([r["meta"] for r in rows], [r["completion"] for r in rows])["accuracy"] == 1.0


def test_expressions_follow_word_maths_operations():
    assert W.expression([["=", 1068], ["+", 806], ["-", 131]]) == "1068+806-131"
    assert W.expression([["=", 110], ["*", 25], ["+", 1016], ["/", 7]]) == "(110*25+1016)/7"
    for d in W.DIFFICULTIES:
        for row in wordmath.make_examples(50, seed=1, split="eval", difficulty=d):
            assert calculator(W.expression(row["meta"]["ops"])) == row["answer"]


def test_rows_are_seeded_split_and_levelled():
    a = W.make_examples(20, seed=3, split="train")
    assert a == W.make_examples(20, seed=3, split="train") and a != W.make_examples(20, seed=4, split="train")
    held = {r["meta"]["expression"] for r in W.make_examples(100, seed=0, split="eval")}
    assert not held & {r["meta"]["expression"] for r in W.make_examples(300, seed=0, split="train")}
    assert all(r["meta"]["difficulty"] == 5 for r in W.make_examples(5, seed=0, split="train", difficulty=5))
    with pytest.raises(ValueError, match="word-calc difficulty must be one of 4, 5"):
        W.make_examples(1, seed=0, split="train", difficulty=2)
