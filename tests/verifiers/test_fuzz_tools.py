"""Fuzz tests (hypothesis) of the tool-call parser and the built-in tools: no text raises out of `parse_tool_calls` or
a shipped environment's `parse_calls`; every call found gets a tool message (the result, or one line `error: ...`)
that a tokenizer and a UTF-8 rollout file take; no argument crashes the calculator, the lookup tool or the Python
tool, or keeps one past its limit.

Inputs: (a) random text; (b) adversarial text built from tool-call fragments (tags, braces, quotes, escapes, brackets
nested thousands deep, numbers of thousands of digits, long runs); (c) well-formed calls with random JSON arguments,
which must also round-trip `format_tool_call`; (d) random and adversarial calculator expressions, lookups and Python
code. Each `@example` is an input that broke the step before the parser's limits (verifiers/envs/base.py).

Bounded: few examples, derandomized (the same ones every run, no `.hypothesis/` database), and every example asserts
a time bound far above what it takes, so an input that makes the code quadratic or hang fails instead of stalling the
suite. POSTTRAIN_FUZZ_SCALE=N runs N times the examples, drawn at random (a longer search for new failures).
"""
from __future__ import annotations

import json
import os
import re
import time

import pytest
from hypothesis import HealthCheck, assume, example, given, settings
from hypothesis import strategies as st

from posttrain.verifiers.envs import Episode, Limits, ToolCall, ToolRunner, Turn, format_tool_call, get_env
from posttrain.verifiers.envs import parse_tool_calls
from posttrain.verifiers.envs.registry import BUILTINS
from posttrain.verifiers.envs.runner import MAX_CONTENT_CHARS
from posttrain.verifiers.envs.tools import FACT_ATTRIBUTES, FactTable, PythonTool, calculator

SCALE = int(os.environ.get("POSTTRAIN_FUZZ_SCALE", "1"))
PARSE_SECONDS = 5.0  # the parser on a text of up to a few MB: milliseconds (the former regex was quadratic)
TOOL_SECONDS = 2.0  # a calculator or lookup call: well under a millisecond
ENVS = [get_env(name) for name in BUILTINS]
TABLE = FactTable(seed=0, size=200)
TOOLS = {"calculator": calculator, "lookup": TABLE.as_tool()}
LIMITS = Limits(max_calls_per_turn=64, tool_timeout_s=5.0)


def fuzz(examples: int):
    """The settings of a fuzz test: `examples` examples (times POSTTRAIN_FUZZ_SCALE), no deadline (each test bounds its
    own time), derandomized unless scaled."""
    return settings(max_examples=examples * SCALE, deadline=None, derandomize=SCALE == 1, database=None,
                    suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                           HealthCheck.large_base_example])


# --------------------------------------------------------------------------------------
# Strategies
# --------------------------------------------------------------------------------------
FRAGMENTS = ["<tool_call>", "</tool_call>", "<tool_call", "/tool_call>", "{", "}", "[", "]", '"', "'", "\\", '\\"',
             "\\\\", "\\u", "\\ud800", "\\udfff", "\\ud83d\\ude00", "\\u00e9", ":", ",", " ", "\n", "null", "true",
             "NaN", "-Infinity", "1e999", "-0", "0.5", '"name"', '"arguments"', '"calculator"', '"lookup"',
             '"expression"', '{"name": "calculator", "arguments": ', '{"name": "lookup", "arguments": {"name": ',
             '"arguments": "', '{"expression": "', "9**9**9", "(((", ")))", "é", "\u2028", "\x00"]
OPENERS = ["[", "{", '{"a": ', '[{"a": ', '"', "\\", "(", '{"name": "calculator", "arguments": ']

nested = st.builds(lambda opener, n: opener * n, st.sampled_from(OPENERS), st.integers(1, 5000))
balanced = st.integers(1, 3000).map(lambda n: "[" * n + "]" * n)
digits = st.builds(lambda sign, n: sign + "9" * n, st.sampled_from(["", "-"]), st.integers(1, 6000))
runs = st.builds(lambda s, n: s * n, st.sampled_from(FRAGMENTS + ["a"]), st.integers(1, 3000))
deep_call = st.integers(1, 3000).map(lambda n: '{"name": "calculator", "arguments": {"expression": '
                                               + "[" * n + '"1"' + "]" * n + "}}")
number_call = digits.map(lambda d: '{"name": "calculator", "arguments": {"expression": ' + d + "}}")
string_args = st.one_of(nested, balanced, digits).map(lambda s: '{"name": "calculator", "arguments": '
                                                                + json.dumps(s) + "}")
wrapped = st.one_of(nested, balanced, digits, deep_call, number_call, string_args, st.sampled_from(FRAGMENTS)).map(
    lambda body: "<tool_call>" + body + "</tool_call>")
piece = st.one_of(st.sampled_from(FRAGMENTS), st.text(max_size=12), nested, balanced, digits, runs, wrapped)
adversarial = st.lists(piece, max_size=20).map("".join)

scalars = st.none() | st.booleans() | st.integers() | st.floats(allow_nan=False) | st.text(max_size=20)
json_values = st.recursive(scalars, lambda kids: st.lists(kids, max_size=4)
                           | st.dictionaries(st.text(max_size=8), kids, max_size=4), max_leaves=25)
arguments = st.dictionaries(st.text(max_size=10), json_values, max_size=5)
names = st.text(min_size=1, max_size=20).filter(lambda s: s == s.strip() and s)
plain = st.text(max_size=40).filter(lambda s: "<tool_call>" not in s and "</tool_call>" not in s)

CALC_ALPHABET = "0123456789.+-*/%() \t\n" + "eE^x×÷−–,:_" + "١٢³½𝟗٫" + "\u2028\x00"
expressions = st.one_of(
    st.text(alphabet=CALC_ALPHABET, max_size=260),
    st.text(max_size=60),
    st.integers(0, 400).map(lambda n: "(" * n + "1" + ")" * n),
    st.integers(1, 120).map(lambda n: "9**" * n + "9"),
    st.integers(1, 80).map(lambda n: "2**" * n + "2"),
    st.integers(1, 300).map(lambda n: "9" * n),
    st.integers(1, 250).map(lambda n: "-" * n + "1"),
    st.builds(lambda a, b: f"{a}**{b}", st.integers(-10 ** 30, 10 ** 30), st.integers(-300, 300)),
    st.builds(lambda a, b: f"({a})/({b})**256", st.integers(-10 ** 30, 10 ** 30), st.integers(-10 ** 30, 10 ** 30)),
)


# --------------------------------------------------------------------------------------
# Checks
# --------------------------------------------------------------------------------------
OLD_SPLIT = re.compile(r"<tool_call>(.*?)</tool_call>", re.DOTALL)  # the parser's former block regex: the oracle


def is_utf8(value) -> bool:
    """Whether `value` dumps to JSON that encodes as UTF-8 (what a rollout file and a tokenizer need)."""
    try:
        json.dumps(value, ensure_ascii=False).encode("utf-8")
    except UnicodeEncodeError:
        return False
    return True


UNCLOSED = "malformed: <tool_call> without </tool_call>"


def check_calls(text: str, calls: list[ToolCall]) -> None:
    """What any parse of `text` must give: calls or malformed calls with a one-line reason, fields a rollout file
    takes, and (for a text short enough for the old regex) the blocks that regex finds, in order (a call refused for
    its size keeps the first 200 characters), then one call for an unclosed tag where the text outside them has one."""
    for call in calls:
        assert isinstance(call, ToolCall) and call.raw.startswith("<tool_call>")
        if call.error is None:
            assert isinstance(call.name, str) and call.name and isinstance(call.arguments, dict)
        else:
            assert call.error.startswith("malformed: ") and len(call.error.splitlines()) == 1, call.error
            assert len(call.error) < 200, call.error
        assert is_utf8([call.name, call.arguments, call.error]), call
    if len(text) <= 5000:
        blocks = [m.group(0) for m in OLD_SPLIT.finditer(text)]
        closed = [c for c in calls if c.error != UNCLOSED]
        assert len(closed) == len(blocks)
        assert all(b == c.raw or (len(c.raw) == 200 and b.startswith(c.raw)) for b, c in zip(blocks, closed))
        assert [c.error for c in calls[len(closed):]] == [UNCLOSED] * ("<tool_call>" in OLD_SPLIT.sub("", text))


def check_results(calls: list[ToolCall], results) -> None:
    """Every call answered, in order, by a tool message a tokenizer takes: the result, or one line `error: ...`."""
    assert [r.call for r in results] == calls
    for r in results:
        assert isinstance(r.content, str) and is_utf8(r.content)
        assert len(r.content) <= MAX_CONTENT_CHARS + 50
        if r.error is not None:
            assert r.content.startswith("error: ") and len(r.content.splitlines()) == 1, r.content


def parse_and_answer(text: str, runner: ToolRunner) -> None:
    """Parse `text` with the default parser and every shipped environment's, run the calls, save the episode."""
    t = time.perf_counter()
    calls = parse_tool_calls(text)
    assert time.perf_counter() - t < PARSE_SECONDS, f"parsing {len(text)} characters took too long"
    check_calls(text, calls)
    for env in ENVS:
        assert [(c.name, c.arguments, c.error) for c in env.parse_calls(text, None)] == [
            (c.name, c.arguments, c.error) for c in calls]
    t = time.perf_counter()
    results = runner.submit(TOOLS, calls, LIMITS).wait()
    assert time.perf_counter() - t < LIMITS.tool_timeout_s + TOOL_SECONDS
    check_results(calls, results)
    episode = Episode(problem={"prompt": "?"}, messages=[], turns=[Turn(text=text, results=results)], finish="answer")
    assert is_utf8(episode.to_dict())  # what the rollout file holds


# --------------------------------------------------------------------------------------
# The parser
# --------------------------------------------------------------------------------------
@pytest.fixture(scope="module")
def runner():
    with ToolRunner(workers=2) as tool_runner:
        yield tool_runner


@fuzz(150)
@given(text=st.text(max_size=2000))
def test_random_text_never_raises(runner, text):
    parse_and_answer(text, runner)


# What broke the step before the parser's limits: json.loads raised RecursionError on deep brackets and ValueError on an
# integer past 4300 digits (out of parse_tool_calls); a surrogate escape went into the tool message and the rollout
# file, where the tokenizer and the UTF-8 writer refuse it; many unclosed tags took the regex quadratic time.
REGRESSIONS = [
    "<tool_call>" + "[" * 5000 + "</tool_call>",
    '<tool_call>{"name": "calculator", "arguments": {"expression": ' + "[" * 2000 + "]" * 2000 + "}}</tool_call>",
    '<tool_call>{"name": "calculator", "arguments": {"expression": ' + "9" * 5000 + "}}</tool_call>",
    '<tool_call>{"name": "calculator", "arguments": "' + "[" * 2000 + '"}</tool_call>',
    '<tool_call>{"name": "calculator", "arguments": {"expression": "\\ud800"}}</tool_call>',
    "<tool_call>" * 20_000,
]


@fuzz(120)
@given(text=adversarial)
@example(text=REGRESSIONS[0])
@example(text=REGRESSIONS[1])
@example(text=REGRESSIONS[2])
@example(text=REGRESSIONS[3])
@example(text=REGRESSIONS[4])
@example(text=REGRESSIONS[5])
def test_adversarial_text_never_raises(runner, text):
    parse_and_answer(text, runner)


def test_the_regressions_are_malformed_calls_naming_the_limit(runner):
    says = ["nested deeper than 100 levels", "nested deeper than 100 levels", "number of more than 1000 digits",
            "nested deeper than 100 levels", "unpaired surrogate", "<tool_call> without </tool_call>"]
    for text, want in zip(REGRESSIONS, says):
        [result] = runner.submit(TOOLS, parse_tool_calls(text), LIMITS).wait()
        assert result.error == "malformed" and result.content.startswith("error: malformed: ")
        assert want in result.content, (text[:80], result.content)
    [call] = parse_tool_calls('<tool_call>"' + "a" * 99_999 + '"</tool_call>')
    assert call.error == "malformed: tool call longer than 100000 characters (100001)" and len(call.raw) == 200
    deep_string = json.dumps({"name": "calculator", "arguments": {"expression": "[" * 5000}})
    [call] = parse_tool_calls(f"<tool_call>{deep_string}</tool_call>")  # brackets inside a string are text
    assert call.error is None and call.arguments == {"expression": "[" * 5000}


@fuzz(150)
@given(st.lists(st.tuples(names, arguments), min_size=1, max_size=3), st.lists(plain, min_size=4, max_size=4))
def test_well_formed_calls_round_trip(calls, gaps):
    texts = [format_tool_call(name, args) for name, args in calls]
    assume(all("</tool_call>" not in t[len("<tool_call>"):-len("</tool_call>")] for t in texts))
    text = gaps[0] + "".join(t + g for t, g in zip(texts, gaps[1:]))
    t = time.perf_counter()
    parsed = parse_tool_calls(text)
    assert time.perf_counter() - t < PARSE_SECONDS
    check_calls(text, parsed)
    assert [(c.name, c.arguments, c.error) for c in parsed] == [(name, args, None) for name, args in calls]
    assert [format_tool_call(c.name, c.arguments) for c in parsed] == texts


# --------------------------------------------------------------------------------------
# The tools
# --------------------------------------------------------------------------------------
OUTPUT = re.compile(r"-?\d+(\.\d*[1-9])?|-?\d+/\d+ \(≈ -?[\d.E+-]+\)")


def check_calculator(expression) -> None:
    """`calculator(expression)` is a number in its output format, or a one-line ValueError (TypeError for a non-string),
    fast."""
    t = time.perf_counter()
    try:
        out = calculator(expression)
    except (ValueError, TypeError) as e:
        assert isinstance(e, ValueError) or not isinstance(expression, str)
        assert len(str(e).splitlines()) == 1 and len(str(e)) < 200 and is_utf8(str(e)), str(e)
    else:
        assert OUTPUT.fullmatch(out), out
    assert time.perf_counter() - t < TOOL_SECONDS, f"calculator({expression!r:.80}) took too long"


@fuzz(300)
@given(expressions)
@example("9**9**9")
@example("(" * 32 + "9**256" + ")" * 32)
@example("(10**199)**256")
@example("0.1**-256")
def test_calculator_answers_or_refuses_any_expression(expression):
    check_calculator(expression)


@fuzz(60)
@given(value=json_values)
def test_calculator_takes_any_json_value_through_the_runner(runner, value):
    check_calculator(value)
    calls = [ToolCall("calculator", {"expression": value}, "")]
    check_results(calls, runner.submit(TOOLS, calls, LIMITS).wait())


@fuzz(150)
@given(st.one_of(st.text(max_size=60), st.sampled_from(TABLE.names()).map(lambda s: f"  {s.upper()} ")),
       st.one_of(st.text(max_size=30), st.sampled_from(FACT_ATTRIBUTES), st.just("x" * 100_000)))
def test_lookup_answers_or_refuses_any_name(name, attribute):
    t = time.perf_counter()
    try:
        out = TOOLS["lookup"](name, attribute)
    except ValueError as e:
        assert len(str(e).splitlines()) == 1 and len(str(e)) < 200 and is_utf8(str(e)), str(e)
    else:
        assert out.isdigit() and attribute.strip().casefold() in FACT_ATTRIBUTES
    assert time.perf_counter() - t < TOOL_SECONDS


PYTHON = PythonTool(timeout_s=1.0, memory_mb=256, max_output_chars=200)
PYTHON_CODE = ["(" * 5000, "[" * 300 + "]" * 300, "x" * 20_001, "print(int('9' * 5000))",
               "import os; os.write(1, b'\\xff')", "raise SystemExit('\\udcff')", "1/0"]


@fuzz(8)
@given(code=st.one_of(st.text(max_size=200), st.sampled_from(PYTHON_CODE)))
@example(code="print('\\ud800')")
@example(code="while True: pass")
def test_python_tool_answers_any_code_within_its_limit(runner, code):
    """Every run comes back through the runner as text a tokenizer takes (before: a program printing an unpaired
    surrogate returned it as is, and the tokenizer refused the tool message), within the tool's time limit."""
    calls = [ToolCall("python", {"code": code}, "")]
    t = time.perf_counter()
    results = runner.submit({"python": PYTHON.as_tool()}, calls, Limits(tool_timeout_s=PYTHON.timeout_s + 4)).wait()
    assert time.perf_counter() - t < PYTHON.timeout_s + 4 + TOOL_SECONDS
    check_results(calls, results)
    assert results[0].error in (None, "exception"), results[0].content
