"""The calc-words environment: word problems with the calculator, rewarded by the math verifier (torch-free)."""
import pytest

from posttrain.verifiers.envs import get_env, list_envs
from posttrain.verifiers.envs.calc import PARTIAL_AUDIT, WORD_AUDIT, WORD_PROBLEM, WordCalcEnv, calculator

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


def _episode(problem, expressions, answer, finish):
    """An episode whose first turn makes `expressions`' calculator calls (refused ones answered with the error)."""
    from posttrain.verifiers.envs import Episode
    from posttrain.verifiers.envs.base import ToolCall, ToolResult, Turn

    results = []
    for e in expressions:
        call = ToolCall("calculator", {"expression": e}, "")
        try:
            results.append(ToolResult(call, calculator(e)))
        except ValueError as err:
            results.append(ToolResult(call, f"error: {err}", "exception"))
    turns = [Turn("", results=results)] if results else []
    return Episode(problem=problem, messages=[], turns=turns + [Turn(answer)], finish=finish)


@pytest.mark.parametrize("case, expressions, answer, finish, expected", PARTIAL_AUDIT,
                         ids=[row[0] for row in PARTIAL_AUDIT])
def test_calc_words_partial_credit_audit(case, expressions, answer, finish, expected):
    reward = WordCalcEnv(partial_credit=0.6).reward(_episode(WORD_PROBLEM, expressions, answer, finish))
    assert reward == pytest.approx(expected)
    # without partial credit every wrong episode scores 0, and the right one 1
    plain = WordCalcEnv().reward(_episode(WORD_PROBLEM, expressions, answer, finish))
    assert plain == (1.0 if expected == 1.0 else 0.0)


def test_calc_words_partial_credit_ranks_each_hack_below_the_episode_it_imitates():
    env = WordCalcEnv(partial_credit=0.6)
    score = {case: env.reward(_episode(WORD_PROBLEM, e, a, f)) for case, e, a, f, _ in PARTIAL_AUDIT}
    assert score["hack: padding with a number of its own"] < score["every number, a wrong sign"]
    assert score["hack: fishing over the numbers"] < score["every number, a wrong sign"]
    assert score["hack: a call without the problem's numbers"] == score["no call, wrong answer"] == 0.0
    assert score["every number, a wrong sign"] < score["right call, its result ignored"] < 1.0
    assert max(s for s in score.values() if s < 1.0) < env.partial_credit + 1e-12


def test_calc_words_partial_credit_parts_by_hand():
    from posttrain.verifiers.envs.calc import credit_parts, running_totals

    assert running_totals(WORD_PROBLEM) == {1068, 1874, 1743}
    share = {"prompt": "Mia has 96 stickers. She shares them equally among 7 friends.", "answer": "96/7",
             "meta": {"ops": [["=", 96], ["/", 7]]}}
    from fractions import Fraction
    assert running_totals(share) == {96, Fraction(96, 7)}
    assert running_totals({"prompt": "x", "answer": "12"}) == {12}  # a row without ops: the answer alone
    ep = _episode(share, ["96/7"], "about 13", "answer")
    assert credit_parts(share, ep.tool_results()) == {"call": 1.0, "numbers": 1.0, "value": 1.0}  # "96/7 (≈ 13.7)"
    # a chained call may use an earlier result; a made-up number counts against the numbers part
    ep = _episode(WORD_PROBLEM, ["1068+806", "1874-131-2"], "1741", "answer")
    assert credit_parts(WORD_PROBLEM, ep.tool_results()) == {"call": 1.0, "numbers": 3 / 4, "value": 0.5}


@pytest.mark.parametrize("bad", [1.0, -0.1, "half"])
def test_calc_words_partial_credit_out_of_range_is_refused(bad):
    with pytest.raises(ValueError, match="calc-words partial_credit must be in \\[0, 1\\)"):
        WordCalcEnv(partial_credit=bad)


def test_calc_words_metrics_report_the_credit_parts_and_the_trainers_average_them():
    """`metrics` (asked after `reward`) gives the partial-credit parts of a wrong answer; `episode_metrics` averages
    each name over the episodes that report it, as `env/<name>`."""
    from posttrain.verifiers.envs import episode_metrics

    env = WordCalcEnv(partial_credit=0.6)
    chained = _episode(WORD_PROBLEM, ["1068+806", "1874-131-2"], "1741", "answer")  # parts 1, 3/4, 1/2 (by hand)
    no_call = _episode(WORD_PROBLEM, [], "12", "answer")  # wrong, no call: parts all 0, no credit
    right = _episode(WORD_PROBLEM, ["1068+806-131"], "The answer is 1743.", "answer")
    dicts = []
    for ep in (chained, no_call, right):
        env.reward(ep)
        dicts.append({**ep.to_dict(), "metrics": env.metrics(ep)})
    assert dicts[0]["metrics"] == {"reward_parts/call": 1.0, "reward_parts/numbers": 0.75, "reward_parts/value": 0.5,
                                   "partial_credit": 1.0}
    assert dicts[1]["metrics"]["partial_credit"] == 0.0 and dicts[2]["metrics"] == {}  # a right answer: no parts
    m = episode_metrics(dicts)
    assert m["env/reward_parts/numbers"] == pytest.approx((0.75 + dicts[1]["metrics"]["reward_parts/numbers"]) / 2)
    assert m["env/partial_credit"] == 0.5 and "env/reward_parts/call" in m and m["env/tool_calls"] > 0
    plain = WordCalcEnv()  # without partial credit: no parts, no metrics
    plain.reward(no_call_again := _episode(WORD_PROBLEM, [], "12", "answer"))
    assert plain.metrics(no_call_again) == {}
