"""The environment protocol without torch: the default tool-call format, every bad call answered as a tool message
(never raised), the tool runner's limits, the registry, and the calc environment's problems, reward and audit."""
import time

import pytest

from posttrain.verifiers.envs import (Environment, Episode, Limits, ToolRunner, Turn, episode_metrics, format_tool_call,
                                      get_env, list_envs, parse_tool_calls)
from posttrain.verifiers.envs.calc import AUDIT, CalcEnv, last_integer


def add(a: int, b: int) -> str:
    """Add two integers.

    Args:
        a: the first number
        b: the second number
    """
    return str(a + b)


def boom(x: int) -> str:
    """Fail.

    Args:
        x: anything
    """
    raise ZeroDivisionError("no way\nsecond line")


def nap(seconds: float) -> str:
    """Sleep.

    Args:
        seconds: how long
    """
    time.sleep(seconds)
    return "awake"


TOOLS = {"add": add, "boom": boom, "nap": nap}


def run(text: str, limits: Limits = Limits(tool_timeout_s=0.3)):
    with ToolRunner(workers=2) as runner:
        return runner.submit(TOOLS, parse_tool_calls(text), limits).wait()


def test_the_default_format_round_trips():
    text = "let me add " + format_tool_call("add", {"a": 2, "b": 3}) + " then wait"
    [call] = parse_tool_calls(text)
    assert (call.name, call.arguments, call.error) == ("add", {"a": 2, "b": 3}, None)
    [res] = run(text)
    assert (res.content, res.error) == ("5", None)


@pytest.mark.parametrize("text, kind, says", [
    ("<tool_call>{not json}</tool_call>", "malformed", "error: malformed: not JSON"),
    ('<tool_call>{"arguments": {}}</tool_call>', "malformed", 'expected {"name": "...", "arguments": {...}}'),
    ('<tool_call>{"name": "add", "arguments": [1, 2]}</tool_call>', "malformed", "'arguments' must be an object"),
    ('<tool_call>{"name": "add", "arguments": {"a": 1}', "malformed", "<tool_call> without </tool_call>"),
    ('<tool_call>{"name": "mul", "arguments": {}}</tool_call>', "unknown_tool", "unknown tool 'mul'; the tools are: add, boom, nap"),
    ('<tool_call>{"name": "add", "arguments": {"a": 1}}</tool_call>', "bad_arguments", "missing a required argument: 'b'"),
    ('<tool_call>{"name": "add", "arguments": {"a": 1, "b": 2, "c": 3}}</tool_call>', "bad_arguments", "unexpected keyword"),
    ('<tool_call>{"name": "boom", "arguments": {"x": 1}}</tool_call>', "exception", "error: ZeroDivisionError: no way"),
    ('<tool_call>{"name": "nap", "arguments": {"seconds": 5}}</tool_call>', "timeout", "error: timeout after 0.3 s"),
])
def test_every_bad_call_comes_back_as_a_tool_message_naming_the_error(text, kind, says):
    t = time.monotonic()
    [res] = run(text)
    assert time.monotonic() - t < 2.0
    assert res.error == kind and says in res.content and res.content.startswith("error: ")
    assert "\n" not in res.content


def test_calls_past_the_turn_limit_are_refused_and_counted():
    text = "".join(format_tool_call("add", {"a": i, "b": 1}) for i in range(5))
    res = run(text, Limits(max_calls_per_turn=3, tool_timeout_s=1.0))
    assert [r.content for r in res[:3]] == ["1", "2", "3"]
    assert [r.error for r in res[3:]] == ["too_many_calls"] * 2
    ep = Episode(problem={}, messages=[], turns=[Turn("x", results=res)], finish="answer")
    m = episode_metrics([ep.to_dict()])
    assert m["env/tool_calls"] == 5 and m["env/valid_calls"] == 3 and m["env/errors/too_many_calls"] == 2


def test_calls_of_one_turn_run_concurrently():
    text = "".join(format_tool_call("nap", {"seconds": 0.4}) for _ in range(2))
    t = time.monotonic()
    res = run(text, Limits(tool_timeout_s=3.0))
    assert [r.content for r in res] == ["awake", "awake"] and time.monotonic() - t < 0.75


def test_tool_schemas_come_from_get_json_schema():
    pytest.importorskip("transformers")
    env = CalcEnv()
    [schema] = env.tool_schemas()
    assert schema["function"]["name"] == "calculator"
    assert "expression" in schema["function"]["parameters"]["properties"]
    system = env.reset({"prompt": "What is 2 * 3?"})[0]
    assert system["role"] == "system" and '"name": "calculator"' in system["content"] and "<tool_call>" in system["content"]


def test_calc_problems_are_seeded_and_their_answers_exact():
    a, b = CalcEnv.problems(20, seed=1), CalcEnv.problems(20, seed=1)
    assert a == b and a != CalcEnv.problems(20, seed=2)
    for p in a + CalcEnv.problems(20, seed=0, difficulty=3):
        assert int(p["answer"]) == eval(p["expression"])  # the test may use eval; the tool never does
    with pytest.raises(ValueError, match="difficulty must be 1, 2 or 3"):
        CalcEnv.problems(1, difficulty=4)


@pytest.mark.parametrize("answer, finish, expected", AUDIT)
def test_calc_reward_audit(answer, finish, expected):
    problem = {"prompt": "What is 347 * 582?", "answer": "201954"}
    assert CalcEnv().score(problem, answer, finish)[0] == expected


def test_calc_digit_credit_scores_near_misses_below_one_and_every_hack_zero():
    problem = {"answer": "201954"}
    env = CalcEnv(digit_credit=0.5)
    assert env.score(problem, "201954")[0] == 1.0
    assert env.score(problem, "201955") == (0.5 * 5 / 6, "wrong (digit credit)")  # 5 of 6 digits in place
    assert env.score(problem, "2019540")[0] == 0.0  # another length: no credit
    for answer, finish, expected in AUDIT:  # the audited hacks still score what they scored
        if expected == 0.0 and answer != "201955":
            assert env.score(problem, answer, finish)[0] == 0.0, answer
    with pytest.raises(ValueError, match="digit_credit"):
        CalcEnv(digit_credit=1.0)


def test_last_integer_reads_digit_groups():
    assert last_integer("it is 201,954.") == (201954, 1)
    assert last_integer("3 and 4") == (4, 2)
    assert last_integer("none") == (None, 0)


def test_the_registry_finds_built_ins_files_and_says_what_is_wrong(tmp_path):
    env = get_env("calc", max_turns=2)
    assert isinstance(env, CalcEnv) and env.limits.max_turns == 2
    assert ("calc", CalcEnv.description, "built-in") in list_envs()
    f = tmp_path / "mine.py"
    f.write_text("from posttrain.verifiers.envs import Environment\n"
                 "class Mine(Environment):\n    name = 'mine'\n    def reward(self, episode):\n        return 1.0\n")
    assert get_env(f"{f}:Mine").name == "mine"
    with pytest.raises(ValueError, match="unknown environment 'nope'; available: calc"):
        get_env("nope")
    with pytest.raises(ValueError, match="has no attribute 'Other' \\(it defines: Mine\\)"):
        get_env(f"{f}:Other")
    with pytest.raises(ValueError, match="environment file not found"):
        get_env(str(tmp_path / "missing.py") + ":X")
    with pytest.raises(ValueError, match="Limits.max_turns must be a positive integer"):
        get_env("calc", max_turns=0)
    with pytest.raises(ValueError, match="unexpected keyword argument 'colour'"):
        get_env("calc", colour=1)


def test_calc_scores_an_endless_integer_zero_with_its_reason():
    env = CalcEnv()
    problem = {"prompt": "What is 347 * 582?", "answer": "201954"}
    assert env.score(problem, "The answer is " + "9" * 5000) == (0.0, "an integer of more than 1000 digits")
    assert last_integer("x " + "1" * 1000) == (int("1" * 1000), 1) and last_integer("no digits") == (None, 0)
