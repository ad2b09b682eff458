"""The gym verifier: reasoning-gym's scorers behind the verifier interface, offline (verifiers/gym.py)."""
from __future__ import annotations

import json

import pytest

pytest.importorskip("reasoning_gym")

from posttrain.verifiers.registry import get_verifier  # noqa: E402
from posttrain.verifiers.runner import VerifierPool  # noqa: E402

DATASETS = ["basic_arithmetic", "chain_sum", "leg_counting", "spell_backward", "knights_knaves", "countdown"]


def _ref(name: str, i: int = 0, seed: int = 3) -> dict:
    import reasoning_gym

    e = reasoning_gym.create_dataset(name, size=i + 1, seed=seed)[i]
    return {"dataset": name, "entry": json.loads(json.dumps({k: e[k] for k in ("question", "answer", "metadata")},
                                                            default=str))}


@pytest.mark.parametrize("name", DATASETS)
def test_the_datasets_answer_in_the_last_tag_scores_one_and_a_wrong_one_less(name):
    v = get_verifier("gym")
    ref = _ref(name)
    gold = ref["entry"]["answer"]
    right = v.check(f"thinking <answer>wrong</answer> then <answer>{gold}</answer>", ref)
    assert right.score == 1.0 and right.reason == "correct" and right.details["dataset"] == name
    wrong = v.check("<answer>zzz qqq</answer>", ref)
    assert wrong.score < 1.0
    assert v.check(f"the answer is {gold}", ref).to_dict() == {"score": 0.0, "reason": "no <answer> tag",
                                                               "details": {"dataset": name}}


def test_options_and_malformed_references():
    ref = _ref("basic_arithmetic")
    spell = _ref("spell_backward")
    almost = f"<answer>{spell['entry']['answer'][:-1]}</answer>"  # one letter short
    assert 0 < get_verifier("gym").check(almost, spell).score < 1  # reasoning-gym's partial credit
    assert get_verifier("gym").check(almost, spell).reason == "partial credit"
    assert get_verifier("gym", partial=False).check(almost, spell).score == 0.0
    assert get_verifier("gym", tag="").check(f"  {ref['entry']['answer']} ", ref).score == 1.0
    with pytest.raises(ValueError, match="tag must be"):
        get_verifier("gym", tag="a b")
    v = get_verifier("gym")
    with pytest.raises(ValueError, match="gym reference must be"):
        v.check("<answer>1</answer>", {"answer": "1"})
    with pytest.raises(ValueError, match="reasoning-gym does not have"):
        v.check("<answer>1</answer>", {"dataset": "no_such_dataset", "entry": {"answer": "1"}})


def test_the_runner_scores_gym_references_in_its_worker_pool():
    refs = [_ref("chain_sum", i) for i in range(4)]
    completions = [f"<answer>{r['entry']['answer']}</answer>" for r in refs[:2]] + ["<answer>x</answer>", "none"]
    with VerifierPool(workers=1) as pool:
        verdicts = pool.score(get_verifier("gym"), completions, refs)
    assert [v.score for v in verdicts] == [1.0, 1.0, 0.0, 0.0]


def test_audit_problems_and_adversarial_cases():
    v = get_verifier("gym")
    problems = v.audit_problems(6, seed=1)
    assert len(problems) == 6
    for p in problems:
        assert v.check(p.gold, p.reference).score == 1.0
        for label, completion, expected in v.adversarial_cases(p):
            assert v.check(completion, p.reference).score == expected, label
