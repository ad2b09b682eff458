"""The GRPO recipes' task modules (tiny-countdown, tiny-code): seeded, prefix-stable, disjoint splits, worked
solutions the verifier passes, a gold evaluation that tells right from wrong, registered for recipes."""
import pytest

from posttrain import tasks
from posttrain.data import validate_rows
from posttrain.tasks import code, countdown
from posttrain.verifiers.registry import get_verifier

MODULES = {"tiny-countdown": countdown, "tiny-code": code}


@pytest.mark.parametrize("name", list(MODULES))
def test_registered_with_a_default_verifier(name):
    mod = tasks.get_task(name)
    assert mod is MODULES[name]
    get_verifier(mod.VERIFIER)  # resolves


@pytest.mark.parametrize("name", list(MODULES))
def test_deterministic_prefix_stable_and_valid(name):
    mod = MODULES[name]
    for split in ("train", "eval"):
        rows = mod.make_examples(60, 3, split)
        assert rows == mod.make_examples(60, 3, split)
        assert rows[:25] == mod.make_examples(25, 3, split)
        assert rows != mod.make_examples(60, 4, split)
        validate_rows(rows, "sft", name)
        for r in rows:
            assert r["answer"] and r["meta"]["reference"] == r["answer"] and r["meta"]["task"] == name
    with pytest.raises(ValueError, match="split must be"):
        mod.make_examples(3, 0, "test")


@pytest.mark.parametrize("name", list(MODULES))
def test_worked_solutions_pass_the_verifier_and_evaluate_tells_right_from_wrong(name):
    mod = MODULES[name]
    v = get_verifier(mod.VERIFIER)
    rows = mod.make_examples(24, 0, "train") + mod.make_examples(8, 0, "eval")
    assert all(v.check(r["completion"], r["answer"]).score == 1.0 for r in rows)
    metas = [r["meta"] for r in rows]
    assert mod.evaluate(metas, [r["completion"] for r in rows])["accuracy"] == 1.0
    shifted = [r["completion"] for r in rows[1:] + rows[:1]]  # each row answered with another row's solution
    assert mod.evaluate(metas, shifted)["accuracy"] <= 0.1
    assert mod.evaluate(metas, [""] * len(rows))["accuracy"] == 0.0
    assert len(mod.corpus(40, 0)) == 50 and all(isinstance(t, str) and t for t in mod.corpus(40, 0))


def test_countdown_splits_are_disjoint_problem_sets():
    def key(r):
        return tuple(sorted(r["answer"]["numbers"])), r["answer"]["target"]

    train = countdown.make_examples(500, 0, "train")
    held = countdown.make_examples(100, 0, "eval")
    assert len({key(r) for r in train}) == len(train)  # distinct problems
    assert not {key(r) for r in train} & {key(r) for r in held}
    assert {r["meta"]["gold"].split()[1] for r in train} == {"+", "-", "*", "/"}
    for r in train + held:
        target = r["answer"]["target"]
        assert 10 <= target <= countdown.MAX_TARGET and target not in r["answer"]["numbers"]
        assert max(r["answer"]["numbers"]) <= 50


def test_code_splits_are_disjoint_problem_sets_and_tests_discriminate():
    def ids(rows):
        return {(r["meta"]["template"], tuple(r["meta"]["constants"]), r["meta"]["phrasing"]) for r in rows}

    train, held = ids(code.make_examples(700, 0, "train")), ids(code.make_examples(200, 0, "eval"))
    assert len(train) > 500 and len(held) > 100 and not train & held
    rows = code.make_examples(40, 1, "train")
    v = get_verifier("code", partial_credit=True)
    for r in rows:  # the identity function fails at least one assert of every problem
        name = r["answer"]["entry_point"]
        param = r["completion"].split("(")[1].split(")")[0]
        assert v.check(f"def {name}({param}):\n    return {param}\n", r["answer"]).score < 1.0, r["prompt"]
