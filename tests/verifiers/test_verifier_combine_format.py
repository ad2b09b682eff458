"""Weighted composition, the format verifier and the length penalty (hand-computed scores)."""
import math

import pytest

from posttrain.verifiers import VerifierPool, WeightedVerifier, combine, get_verifier, score_batch
from posttrain.verifiers.base import Verdict, Verifier
from posttrain.verifiers.format import FormatVerifier, LengthVerifier


class Fixed(Verifier):
    def __init__(self, name, score):
        self.name, self.score = name, score

    def check(self, completion, reference):
        return Verdict(self.score, f"fixed {self.score}", {"ref": reference})


def test_weighted_mean_and_details():
    v = combine((Fixed("a", 1.0), 0.9), (Fixed("b", 0.0), 0.1))
    out = v.check("x", "r")
    assert out.score == pytest.approx(0.9)
    assert out.reason == "a: fixed 1.0; b: fixed 0.0"
    assert out.details == {"parts": {
        "a": {"weight": 0.9, "score": 1.0, "reason": "fixed 1.0", "details": {"ref": "r"}},
        "b": {"weight": 0.1, "score": 0.0, "reason": "fixed 0.0", "details": {"ref": "r"}},
    }}
    assert combine((Fixed("a", 0.5), 3), (Fixed("b", 0.25), 1)).check("x", None).score == pytest.approx((1.5 + 0.25) / 4)


def test_all_parts_passing_is_exactly_one_and_a_failed_part_never_passes():
    parts = [(Fixed("a", 1.0), 0.7), (Fixed("b", 1.0), 0.2), (Fixed("c", 1.0), 0.1)]
    assert math.fsum([0.7, 0.2, 0.1]) == 1.0 and 0.7 + 0.2 + 0.1 != 1.0  # why we special-case it
    assert WeightedVerifier(parts).check("x", None).passed
    failing = WeightedVerifier([(Fixed("a", 1.0), 1.0), (Fixed("b", 0.0), 0.0)]).check("x", None)
    assert not failing.passed and failing.score < 1.0


def test_composition_validation_and_naming():
    with pytest.raises(ValueError):
        WeightedVerifier([])
    with pytest.raises(ValueError, match="must be a finite number >= 0"):
        combine((Fixed("a", 1), -1))
    with pytest.raises(ValueError, match="must not all be zero"):
        combine((Fixed("a", 1), 0))
    v = combine(Fixed("a", 1), Fixed("a", 0))
    assert [label for label, _, _ in v.parts] == ["a", "a#2"]
    assert v.name == "1*a+1*a#2"
    assert combine("math", "format").timeout_s == get_verifier("math").timeout_s + get_verifier("format").timeout_s


def test_math_plus_format_correctness_weighting():
    reward = combine((get_verifier("math"), 0.9), (FormatVerifier(tags="answer"), 0.1))
    assert reward.check("<answer>42</answer>", "42").score == 1.0
    assert reward.check("The answer is 42.", "42").score == pytest.approx(0.9)
    assert reward.check("<answer>41</answer>", "42").score == pytest.approx(0.1)
    assert reward.check("nothing", "42").score == 0.0
    assert not reward.in_process  # math needs a worker process
    with VerifierPool(workers=1, timeout_s=10) as pool:
        out = pool.score(reward, ["<answer>42</answer>", "The answer is 42."], ["42", "42"])
    assert [o.score for o in out] == pytest.approx([1.0, 0.9])
    assert out[1].details["parts"]["format"]["reason"] == "missing <answer> tag"


def test_nested_composition():
    inner = combine((Fixed("a", 1.0), 1), (Fixed("b", 0.0), 1))
    outer = combine((inner, 1), (Fixed("c", 1.0), 1))
    assert outer.check("x", None).score == pytest.approx(0.75)


@pytest.mark.parametrize("completion,score,reason", [
    pytest.param(r"so \boxed{4}", 1.0, "ok", id="boxed"),
    pytest.param("<answer>4</answer>", 1.0, "ok", id="tag"),
    pytest.param(r"\boxed{}", 0.0, "no \\boxed{} or <answer> tag", id="empty-box"),
    pytest.param("<answer> </answer>", 0.0, "no \\boxed{} or <answer> tag", id="empty-tag"),
    pytest.param("4", 0.0, "no \\boxed{} or <answer> tag", id="bare"),
])
def test_format_default(completion, score, reason):
    v = FormatVerifier().check(completion, None)
    assert (v.score, v.reason) == (score, reason)


@pytest.mark.parametrize("completion,reason", [
    pytest.param("<think>hm</think><answer>4</answer>", "ok", id="good"),
    pytest.param("<answer>4</answer>", "missing <think> tag", id="missing"),
    pytest.param("<think>hm</think><answer>4</answer><answer>5</answer>", "repeated <answer> tag", id="repeated"),
    pytest.param("<answer>4</answer><think>hm</think>", "tags out of order: <answer> must come after the previous tag", id="order"),
    pytest.param("<think></think><answer>4</answer>", "empty <think> tag", id="empty"),
    pytest.param("<think>hm<answer>4</answer></think>", "tags out of order: <answer> must come after the previous tag", id="nested"),
])
def test_format_tags(completion, reason):
    v = FormatVerifier(tags=("think", "answer")).check(completion, None)
    assert v.reason == reason and v.score == (1.0 if reason == "ok" else 0.0)


def test_format_pattern_boxed_and_partial():
    v = FormatVerifier(pattern=r"Answer: \d+", boxed=True, partial=True)
    assert v.check(r"Answer: 12 \boxed{12}", None).score == 1.0
    half = v.check("Answer: 12", None)
    assert (half.score, half.reason) == (0.5, "no non-empty \\boxed{}")
    assert half.details == {"checks": {"boxed": False, "pattern": True}}
    full = FormatVerifier(pattern=r"\d+", full_match=True)
    assert full.check(" 12 \n", None).score == 1.0 and full.check("12 apples", None).score == 0.0
    with pytest.raises(ValueError, match="invalid regex"):
        FormatVerifier(pattern="(")
    with pytest.raises(ValueError, match="bad tag name"):
        FormatVerifier(tags="<answer>")


def test_format_is_picklable_and_fast_on_huge_input():
    import pickle

    v = pickle.loads(pickle.dumps(FormatVerifier(pattern=r"\d")))
    assert v.check("a1", None).score == 1.0
    assert FormatVerifier().check("<answer>" * 200_000, None).score == 0.0


@pytest.mark.parametrize("n,score", [(0, 1.0), (100, 1.0), (101, 0.98), (150, 0.0), (125, 0.5), (1000, 0.0)])
def test_length_linear_decay(n, score):
    v = LengthVerifier(max_chars=100, window=50)
    assert v.check("x" * n, None).score == pytest.approx(score)


def test_length_default_window_and_tokens():
    assert LengthVerifier(max_chars=10).check("x" * 15, None).score == pytest.approx(0.5)
    over = LengthVerifier(max_chars=10).check("x" * 15, None)
    assert over.reason == "over budget" and over.details == {"length": 15, "budget": 10, "window": 10, "unit": "chars", "over_by": 5}
    toks = LengthVerifier(max_tokens=4)
    assert toks.measure("Hello, world! 42") == 5
    assert toks.check("Hello, world! 42", None).score == pytest.approx(0.75)
    custom = LengthVerifier(max_tokens=2, tokenizer=str.split)
    assert custom.check("a b c", None).score == pytest.approx(0.5)
    with pytest.raises(ValueError):
        LengthVerifier(max_chars=1, max_tokens=1)
    with pytest.raises(ValueError):
        LengthVerifier(max_chars=0)


def test_format_and_length_run_in_process_through_the_runner():
    reward = combine(("format", 0.5), (LengthVerifier(max_chars=20), 0.5))
    assert reward.in_process
    out = score_batch(reward, [r"\boxed{1}", "x" * 40], [None, None])
    assert [o.score for o in out] == pytest.approx([1.0, 0.0])
