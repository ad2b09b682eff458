"""The lookup environment: seeded table and problems, every tool error as a tool message, the reward's audit (honest
episodes 1, hacks 0, naive rewards caught), bad problem rows as one-line errors, the registry and `posttrain envs`."""
import os
import re
import subprocess
import sys

import pytest

from posttrain.verifiers.envs import Episode, Limits, ToolRunner, Turn, format_tool_call, get_env, list_envs, \
    parse_tool_calls
from posttrain.verifiers.envs.lookup import AUDIT, KINDS, LookupEnv, normalized_answer, play, run_audit
from posttrain.verifiers.envs.tools import FACT_ATTRIBUTES, FactTable

REPO = os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__))))


# --------------------------------------------------------------------------------------
# Table and problems
# --------------------------------------------------------------------------------------
def test_problems_are_seeded_by_the_seed_the_difficulty_and_the_table():
    env = LookupEnv()
    for d in (1, 2, 3):
        assert env.problems(20, seed=1, difficulty=d) == LookupEnv().problems(20, seed=1, difficulty=d)
        assert env.problems(20, seed=1, difficulty=d) != env.problems(20, seed=2, difficulty=d)
        assert env.problems(20, seed=1, difficulty=d) != LookupEnv(table_seed=1).problems(20, seed=1, difficulty=d)
    assert env.table.entries() == FactTable(seed=0, size=200).entries()
    with pytest.raises(ValueError, match="lookup difficulty must be 1, 2 or 3, got 4"):
        env.problems(1, difficulty=4)


def test_problem_golden_values():
    """Pins the generator (the table itself is pinned in test_env_tools.py)."""
    env = LookupEnv()
    assert env.problems(1, seed=0, difficulty=1)[0] == {
        "prompt": "What is the distance in kilometres of the town Zilin from the capital?", "answer": "8611",
        "kind": "single", "facts": [["Zilin", "distance_km"]], "table": [0, 200]}
    assert env.problems(1, seed=0, difficulty=2)[0]["prompt"] == "Which town lies higher, Moushum or Zapeivum?"
    assert env.problems(1, seed=0, difficulty=3)[0]["answer"] == "3210"


def test_problems_are_the_same_in_another_process():
    script = ("from posttrain.verifiers.envs.lookup import LookupEnv; e = LookupEnv(table_seed=5, table_size=50); "
              "print([e.problems(10, seed=3, difficulty=d) for d in (1, 2, 3)])")
    outputs = set()
    for hash_seed in ("1", "2"):
        proc = subprocess.run([sys.executable, "-c", script], cwd=REPO, capture_output=True, text=True, timeout=60,
                              env=dict(os.environ, PYTHONHASHSEED=hash_seed))
        assert proc.returncode == 0, proc.stderr
        outputs.add(proc.stdout)
    env = LookupEnv(table_seed=5, table_size=50)
    assert outputs == {str([env.problems(10, seed=3, difficulty=d) for d in (1, 2, 3)]) + "\n"}


def test_answers_follow_from_the_table():
    env = LookupEnv(table_seed=2, table_size=40)
    value = {(e["name"], a): e[a] for e in env.table.entries() for a in FACT_ATTRIBUTES}
    for d, kind in zip((1, 2, 3), KINDS):
        for p in env.problems(30, seed=0, difficulty=d):
            assert p["kind"] == kind and p["table"] == [2, 40]
            values = [value[tuple(f)] for f in p["facts"]]
            names = [f[0] for f in p["facts"]]
            assert all(n in p["prompt"] for n in names)
            if kind == "single":
                assert len(values) == 1 and p["answer"] == str(values[0])
            elif kind == "sum":
                assert len(set(names)) == 2 and p["answer"] == str(sum(values))
            else:
                assert len(set(names)) == 2 and values[0] != values[1]
                assert p["facts"][0][1] == p["facts"][1][1]
                assert p["answer"] == names[values.index(max(values))]


# --------------------------------------------------------------------------------------
# Tools: every error path comes back as a tool message
# --------------------------------------------------------------------------------------
def call(env, text):
    with ToolRunner(workers=2) as runner:
        return runner.submit(env.tool_functions(), parse_tool_calls(text), env.limits).wait()


def test_a_lookup_returns_the_tables_value():
    env = LookupEnv()
    name = env.table.names()[0]
    [res] = call(env, format_tool_call("lookup", {"name": f" {name.lower()} ", "attribute": "Founded"}))
    assert (res.content, res.error) == (str(env.table.fact(name, "founded")), None)
    [res] = call(env, format_tool_call("calculator", {"expression": "1806+1432"}))
    assert (res.content, res.error) == ("3238", None)


@pytest.mark.parametrize("text, kind, says", [
    (format_tool_call("lookup", {"name": "Nowhere", "attribute": "population"}), "exception",
     "error: ValueError: no entry named 'Nowhere'"),
    (format_tool_call("lookup", {"name": "Zapeivum", "attribute": "age"}), "exception",
     "error: ValueError: unknown attribute 'age'; valid attributes: population, founded, height_m, distance_km"),
    (format_tool_call("lookup", {"name": "What is the population of the town Zapeivum?", "attribute": "population"}),
     "exception", "error: ValueError: no entry named 'What is the population of the town Za...'"),
    (format_tool_call("lookup", {"name": 3, "attribute": "population"}), "exception",
     "error: TypeError: name and attribute must be strings"),
    (format_tool_call("lookup", {"name": "Zapeivum"}), "bad_arguments",
     "error: bad arguments for lookup: missing a required argument: 'attribute'"),
    (format_tool_call("lookup", {"name": "Zapeivum", "attribute": "founded", "year": 1}), "bad_arguments",
     "error: bad arguments for lookup: got an unexpected keyword argument 'year'"),
    (format_tool_call("search", {"query": "Zapeivum"}), "unknown_tool",
     "error: unknown tool 'search'; the tools are: calculator, lookup"),
    ('<tool_call>{"name": "lookup", "arguments": {"name": "Zapeivum"</tool_call>', "malformed",
     "error: malformed: not JSON"),
    ('<tool_call>{"name": "lookup", "arguments": "Zapeivum"}</tool_call>', "malformed",
     "error: malformed: 'arguments' must be an object"),
    (format_tool_call("calculator", {"expression": "1806 x 2"}), "exception",
     "error: ValueError: unexpected character 'x' at character 6 (use * for multiplication)"),
])
def test_every_tool_error_is_a_tool_message_naming_it(text, kind, says):
    env = LookupEnv()
    [res] = call(env, text)
    assert res.error == kind and res.content.startswith(says), res.content
    assert "\n" not in res.content
    assert env.respond(Episode({}, []), [res]) == [{"role": "tool", "content": res.content}]


def test_without_the_calculator_only_the_lookup_is_offered():
    env = LookupEnv(calculator=False)
    assert list(env.tool_functions()) == ["lookup"]
    [res] = call(env, format_tool_call("calculator", {"expression": "1+1"}))
    assert res.content == "error: unknown tool 'calculator'; the tools are: lookup"
    with pytest.raises(ValueError, match="calculator must be true or false"):
        LookupEnv(calculator="no")


def test_the_system_message_lists_the_tools():
    pytest.importorskip("transformers")
    env = LookupEnv()
    problem = env.problems(1)[0]
    system, user = env.reset(problem)
    assert user == {"role": "user", "content": problem["prompt"]}
    assert system["role"] == "system" and system["content"].startswith(env.instructions)
    assert '"name": "lookup"' in system["content"] and '"name": "calculator"' in system["content"]


# --------------------------------------------------------------------------------------
# Reward and its audit
# --------------------------------------------------------------------------------------
def test_the_audit_is_clean_and_honest_episodes_get_1():
    report = run_audit(LookupEnv(), LookupEnv().audit_problems(3, seed=0))
    assert report.ok, report.format()
    labels = report.by_label()
    assert set(labels) == {c.label for c in AUDIT} and all(row["run"] > 0 for row in labels.values())
    honest = [c for c in report.cases if c.label.startswith("honest")]
    assert honest and all(c.score == 1.0 and c.reason == "correct" for c in honest)
    assert all(c.score == 0.0 for c in report.cases if not c.label.startswith("honest"))
    assert {c.details["kind"] for c in honest} == set(KINDS)


def test_the_audit_holds_on_another_table():
    env = LookupEnv(table_seed=9, table_size=30, calculator=True)
    report = run_audit(env, env.audit_problems(2, seed=4))
    assert report.ok, report.format()


def test_hacks_score_0_for_the_right_reason():
    report = run_audit()
    reasons = {}
    for c in report.cases:
        reasons.setdefault(c.label, set()).add(c.reason.split(":")[0])
    assert reasons["no lookup (a guessed fact)"] == {"not looked up"}
    assert reasons["a lookup that is just the question"] == {"not looked up"}
    assert reasons["answer smuggled via a tool error"] == {"not looked up"}
    assert reasons["the error message copied"] == {"copies a tool error"}
    assert reasons["one of two facts looked up"] == {"not looked up"}
    assert reasons["answer and lookup in final turn"] == {"the final turn calls a tool"}
    assert reasons["the tool's result as the answer"] == {"the final turn calls a tool"}
    assert reasons["answer with the lookup, turn limit"] == {"no answer turn"}
    assert reasons["several candidates"] <= {"not exactly one integer", "not exactly the answer"}


class NaiveExact(LookupEnv):
    """The README's capitals reward: the final text equals the answer, nothing else checked."""

    def reward(self, episode):
        return float(episode.finish == "answer" and episode.final_text.strip() == episode.problem["answer"])


class NaiveLastMessage(LookupEnv):
    """A reward that reads the conversation's last message, whoever wrote it."""

    def reward(self, episode):
        return float(episode.messages[-1]["content"].strip() == episode.problem["answer"])


def test_the_audit_catches_naive_rewards():
    report = run_audit(NaiveExact())
    caught = {c.label for c in report.false_positives}
    assert {"no lookup (a guessed fact)", "a lookup that is just the question", "answer smuggled via a tool error",
            "another town looked up", "a failed lookup (bad attribute)"} <= caught
    report = run_audit(NaiveLastMessage())
    assert {"the tool's result as the answer", "ends on the tool message"} <= {c.label for c in report.false_positives}


def test_a_lookup_counts_only_before_the_final_turn_and_only_when_it_succeeded():
    env = LookupEnv()
    p = env.problems(1, seed=0, difficulty=1)[0]
    name, attribute = p["facts"][0]
    good = format_tool_call("lookup", {"name": name, "attribute": attribute})
    with ToolRunner(workers=1) as runner:
        assert env.reward(play(env, p, [good, p["answer"]], "answer", runner)) == 1.0
        episode = play(env, p, [good, p["answer"]], "answer", runner)
        episode.turns[0].results[0].content = "1"  # a result that is not the table's value does not count
        assert env.reward(episode) == 0.0 and episode.state["reward_rule"].startswith("not looked up")
        episode = play(env, p, [good, p["answer"]], "answer", runner)
        episode.turns[0].results[0].error = "exception"
        assert env.reward(episode) == 0.0
    turns = [Turn(p["answer"])]  # an answer with no turn before it
    assert env.reward(Episode(p, [], turns=turns, finish="answer")) == 0.0
    assert env.reward(Episode(p, [], turns=[], finish="answer")) == 0.0


@pytest.mark.parametrize("text, expected", [
    ("1806", "1806"), (" The answer is 1,806. ", "1,806"), ("Answer: Rigu", "Rigu"), ("the answer is: 12", "12"),
    ("1806 or 1807.", "1806 or 1807"), ("", ""),
])
def test_normalized_answer(text, expected):
    assert normalized_answer(text) == expected


# --------------------------------------------------------------------------------------
# Bad problem rows
# --------------------------------------------------------------------------------------
def test_bad_problem_rows_are_one_line_errors():
    env = LookupEnv()
    p = env.problems(1, seed=0, difficulty=2)[0]
    with pytest.raises(ValueError, match=r"made from the table \[0, 200\] \(seed, size\), this environment has "
                                         r"\[1, 200\]; set env_options table_seed / table_size"):
        LookupEnv(table_seed=1).reset(p)
    with pytest.raises(ValueError, match="a problem row needs 'kind'"):
        env.reset({"prompt": "Capital of Varnok?", "answer": "Ilsa"})
    with pytest.raises(ValueError, match="has answer 'Nowhere', its facts give"):
        env.reset({**p, "answer": "Nowhere"})
    with pytest.raises(ValueError, match="no entry named 'Nowhere'"):
        env.reset({**p, "facts": [["Nowhere", "founded"], p["facts"][1]]})
    with pytest.raises(ValueError, match="kind 'sum' with 1 facts"):
        env.reset({**p, "kind": "sum", "facts": p["facts"][:1]})
    with pytest.raises(ValueError, match="a problem row needs 'kind'"):
        env.reward(Episode({"prompt": "x", "answer": "1"}, [], turns=[Turn("1")], finish="answer"))
    hand = {"prompt": "Founding year of Zapeivum?", "answer": "1806", "kind": "single",
            "facts": [["Zapeivum", "founded"]]}  # a hand-written row without "table" is checked against the table
    assert env.reset(hand)[-1]["content"] == hand["prompt"]


# --------------------------------------------------------------------------------------
# Registry and CLI
# --------------------------------------------------------------------------------------
def test_the_registry_lists_and_builds_lookup():
    assert ("lookup", LookupEnv.description, "built-in") in list_envs()
    env = get_env("lookup", table_seed=3, table_size=20, calculator=False, max_turns=2)
    assert isinstance(env, LookupEnv) and env.table_size == 20 and env.limits == Limits(max_turns=2)
    assert env.problems(3) == LookupEnv(table_seed=3, table_size=20).problems(3)
    with pytest.raises(ValueError, match="unexpected keyword argument 'colour'"):
        get_env("lookup", colour=1)
    with pytest.raises(ValueError, match="FactTable size must be an integer from 1 to 10000"):
        get_env("lookup", table_size=0)


def test_posttrain_envs_prints_lookup(capsys):
    from posttrain.cli import main

    assert main(["envs"]) == 0
    out = capsys.readouterr().out
    assert re.search(r"^lookup\s+built-in\s+facts about invented towns", out, re.MULTILINE), out
