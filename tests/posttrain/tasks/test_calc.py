"""tiny-calc: calculator demonstrations, the tool_rate option and task.options (torch-free)."""
import pytest

from posttrain.config import TaskConfig
from posttrain.errors import ConfigError
from posttrain.tasks import calc as C, get_task, load_split, option_kwargs
from posttrain.verifiers.envs.calc import calculator


def _calls(row):
    return [m for m in row["messages"] if m["role"] == "assistant" and "<tool_call>" in m["content"]]


def test_default_every_demonstration_calls_the_calculator_and_some_recover():
    rows = C.make_examples(200, seed=0, split="train")
    assert rows == C.make_examples(200, seed=0, split="train")
    assert all(r["meta"]["tool"] for r in rows)
    for k, r in enumerate(rows):
        tool_msgs = [m["content"] for m in r["messages"] if m["role"] == "tool"]
        assert tool_msgs[-1] == calculator(r["meta"]["expression"]) == r["answer"] == r["completion"]
        recovers = k % C.RECOVERY_EVERY == C.RECOVERY_EVERY - 1
        assert len(_calls(r)) == 1 + recovers
        assert tool_msgs[0].startswith("error:") == recovers


def test_tool_rate_mixes_direct_answers_and_keeps_each_problem_s_kind():
    rows = C.make_examples(600, seed=0, split="train", tool_rate=0.3)
    with_tool = [r for r in rows if r["meta"]["tool"]]
    assert 0.25 < len(with_tool) / len(rows) < 0.35  # a hash of the expression: ~Binomial(600, 0.3)
    for r in rows:
        if not r["meta"]["tool"]:  # the system message and the question, then the answer at once
            assert [m["role"] for m in r["messages"]] == ["system", "user", "assistant"]
            assert r["messages"][-1]["content"] == r["completion"] == C.DIRECT_PREFIX + r["answer"]
            assert r["answer"] == calculator(r["meta"]["expression"])
        else:
            assert len(_calls(r)) >= 1
    # the same problems as the all-tool rows, in the same order; a problem's kind does not depend on n
    assert [r["meta"]["expression"] for r in rows] == [r["meta"]["expression"]
                                                       for r in C.make_examples(600, 0, "train")]
    assert [r["meta"]["tool"] for r in rows[:50]] == [r["meta"]["tool"]
                                                      for r in C.make_examples(50, 0, "train", tool_rate=0.3)]
    assert not any(r["meta"]["tool"] for r in C.make_examples(50, 0, "train", tool_rate=0))
    assert all(r["meta"]["tool"] for r in C.make_examples(50, 0, "eval", tool_rate=0))  # held out: always the tool
    # recoveries stay one in RECOVERY_EVERY of the demonstrations that call the tool
    recover = [len(_calls(r)) == 2 for r in with_tool]
    assert recover == [k % C.RECOVERY_EVERY == C.RECOVERY_EVERY - 1 for k in range(len(with_tool))]


@pytest.mark.parametrize("bad", [1.5, -0.1, "half", True])
def test_bad_tool_rate_names_the_option(bad):
    with pytest.raises(ConfigError, match="task.options.tool_rate: a fraction from 0 to 1"):
        C.make_examples(5, seed=0, split="train", tool_rate=bad)


def test_task_options_reach_make_examples_and_unknown_ones_are_named():
    rows = load_split(TaskConfig(name="tiny-calc", n_eval=40, options={"tool_rate": 0.0}), "eval")
    assert len(rows) == 40 and all(r["meta"]["tool"] for r in rows)
    rows = load_split(TaskConfig(name="tiny-calc", n_train=40, options={"tool_rate": 0.0}), "train")
    assert len(rows) == 40 and not any(r["meta"]["tool"] for r in rows)
    assert option_kwargs(get_task("tiny-calc"), TaskConfig(name="tiny-calc")) == {}
    with pytest.raises(ConfigError, match=r"task.options.rate: task 'tiny-calc' has no option 'rate' "
                                          r"\(its options: tool_rate\)"):
        load_split(TaskConfig(name="tiny-calc", options={"rate": 0.5}), "train")
    with pytest.raises(ConfigError, match=r"task.options.tool_rate: task 'tiny-math' has no option 'tool_rate' "
                                          r"\(it has none\)"):
        load_split(TaskConfig(name="tiny-math", options={"tool_rate": 0.5}), "train")
