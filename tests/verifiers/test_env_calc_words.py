"""The calc-words environment: word problems with the calculator, rewarded by the math verifier (torch-free)."""
import pytest

from posttrain.verifiers.envs import get_env, list_envs
from posttrain.verifiers.envs.calc import WORD_AUDIT, WordCalcEnv, calculator

PROBLEM = {"prompt": "Nora collected 1068 pencils. A friend gives her 806 more pencils. She gives away 131 pencils. "
                     "How many pencils does Nora have at the end?", "answer": "1743"}


@pytest.mark.parametrize("answer, finish, expected", WORD_AUDIT)
def test_calc_words_reward_audit(answer, finish, expected):
    assert WordCalcEnv().score(PROBLEM, answer, finish)[0] == expected


def test_calc_words_is_built_in_with_its_tools_and_limits():
    assert any(name == "calc-words" and origin == "built-in" for name, _, origin in list_envs())
    env = get_env("calc-words", max_turns=3)
    assert isinstance(env, WordCalcEnv) and env.limits.max_turns == 3 and env.limits.max_total_tokens == 512
    assert list(env.tool_functions()) == ["calculator"]
    assert list(WordCalcEnv(python=True).tool_functions()) == ["calculator", "python"]
    first = env.reset(PROBLEM)
    assert [m["role"] for m in first] == ["system", "user"] and first[1]["content"] == PROBLEM["prompt"]
    assert '"name": "calculator"' in first[0]["content"] and "<tool_call>" in first[0]["content"]


def test_calc_words_episode_with_a_tool_call_is_rewarded_on_its_answer():
    from posttrain.verifiers.envs import Episode

    env = WordCalcEnv()
    ep = Episode(problem=PROBLEM, messages=env.reset(PROBLEM))
    calls = env.parse_calls('<tool_call>{"name": "calculator", "arguments": {"expression": "1068+806-131"}}'
                            '</tool_call>', ep)
    assert [(c.name, c.arguments) for c in calls] == [("calculator", {"expression": "1068+806-131"})]
    assert calculator("1068+806-131") == "1743"
    ep.finish = "answer"
    assert env.score(PROBLEM, "She ends with 1743 pencils. The answer is 1743.", ep.finish) == (1.0, "correct")
