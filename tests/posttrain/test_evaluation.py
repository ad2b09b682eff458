"""posttrain.evaluation: task-free reference metrics for a user's rows without the task's meta (hand-computed)."""
import pytest

from posttrain.evaluation import reference_metrics


def test_reference_metrics_by_hand():
    refs = ["the red fox eats berries", "four", "a b", "x"]
    outs = ["The red fox eats", "four", "", "y y"]
    m = reference_metrics(refs, outs)
    # F1: row 1 p=4/4 r=4/5 -> 8/9; row 2: 1; row 3: empty -> 0; row 4: no overlap -> 0
    assert m["word_f1"] == pytest.approx((8 / 9 + 1 + 0 + 0) / 4)
    assert m["exact_match"] == 0.25  # "four" only (case and spacing matter for exact match)
    assert m["mean_length"] == (4 + 1 + 0 + 2) / 4 and m["frac_empty"] == 0.25


def test_repeated_words_count_once_per_reference_occurrence():
    m = reference_metrics(["a a b"], ["a a a"])
    # common = min(2, 3) = 2: precision 2/3, recall 2/3
    assert m["word_f1"] == pytest.approx(2 / 3)


def test_evaluate_model_uses_reference_metrics_for_rows_without_meta():
    from posttrain.evaluation import evaluate_model

    rows = [{"prompt": "p", "completion": "four"}, {"prompt": "q", "completion": "five six", "meta": None}]
    out = evaluate_model("tiny-summarize", None, None, rows, completions=["four", "five"])
    assert out["exact_match"] == 0.5 and out["word_f1"] == pytest.approx((1 + 2 / 3) / 2) and out["n"] == 2
