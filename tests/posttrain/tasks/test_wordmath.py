"""word-math: the generator's guarantees (levels, splits, references), its scoring and its config knob."""
import re

import pytest

from posttrain.tasks import wordmath as W


def _all(split, difficulty, n=400, seed=0):
    return W.make_examples(n, seed=seed, split=split, difficulty=difficulty)


def test_deterministic_and_prefix_stable():
    a = W.make_examples(50, seed=3, split="train", difficulty=2)
    assert a == W.make_examples(50, seed=3, split="train", difficulty=2)
    assert a[:10] == W.make_examples(10, seed=3, split="train", difficulty=2)
    assert a != W.make_examples(50, seed=4, split="train", difficulty=2)
    assert W.make_examples(0, seed=3, split="eval") == []


@pytest.mark.parametrize("bad, match", [({"split": "test"}, "split"), ({"n": -1}, "n must be"),
                                        ({"n": 1.5}, "n must be"), ({"difficulty": 6}, "difficulty must be one of")])
def test_bad_arguments_name_the_problem(bad, match):
    kwargs = {"n": 1, "seed": 0, "split": "train", "difficulty": 1, **bad}
    with pytest.raises(ValueError, match=match):
        W.make_examples(**kwargs)


@pytest.mark.parametrize("difficulty", W.DIFFICULTIES)
def test_reference_is_the_running_total_and_the_worked_solution_scores(difficulty):
    for split in ("train", "eval"):
        for row in _all(split, difficulty, n=150):
            ops = [tuple(o) for o in row["meta"]["ops"]]
            assert row["answer"] == row["meta"]["answer"] == str(W.apply(ops))
            assert int(row["answer"]) >= 0
            assert row["meta"]["n_steps"] == len(ops) - 1 in W.LEVELS[difficulty].steps
            assert row["verifier"] == "math" and row["completion"].startswith(" ")
            assert W.gold_quality(row["meta"], row["completion"]) == 1.0
            for op, n in ops:  # every number of the problem is written in its prompt
                assert re.search(rf"\b{n}\b", row["prompt"]), (n, row["prompt"])


def test_operations_follow_the_level_table():
    for d, level in W.LEVELS.items():
        for split, which in (("train", 0), ("eval", 1)):
            lo, hi = level.add[which]
            flo, fhi = level.factor[which]
            for row in _all(split, d, n=300):
                for op, n in row["meta"]["ops"][1:]:
                    if op in "+-":
                        assert lo <= n <= hi
                    else:
                        assert flo <= n <= fhi
                    if op == "/":  # an exact share, only as the last step
                        assert row["meta"]["ops"][-1] == [op, n]


def test_held_out_reaches_past_the_training_ranges():
    hi = W.LEVELS[1].add[0][1]
    eval_ops = [n for r in _all("eval", 1, n=300) for op, n in r["meta"]["ops"][1:] if op in "+-"]
    assert max(eval_ops) > hi and all(n <= W.LEVELS[1].add[1][1] for n in eval_ops)


@pytest.mark.parametrize("difficulty", W.DIFFICULTIES)
def test_splits_share_no_operation_tuple(difficulty):
    key = lambda r: tuple(tuple(o) for o in r["meta"]["ops"])  # noqa: E731
    train = {key(r) for r in _all("train", difficulty, n=600)}
    held = {key(r) for r in _all("eval", difficulty, n=300)}
    assert not train & held


def test_held_out_phrasings_names_and_items_never_occur_in_training():
    train_prompts = [r["prompt"] for d in W.DIFFICULTIES for r in _all("train", d, n=500)]
    eval_rows = [r for d in W.DIFFICULTIES for r in _all("eval", d, n=500)]
    held_name, held_item = W.NAMES[-1][0], W.ITEMS[-1]
    assert not any(held_name in p or held_item in p for p in train_prompts)
    assert any(held_name in r["prompt"] for r in eval_rows) and any(held_item in r["prompt"] for r in eval_rows)
    # the held-out-only phrasing of each clause kind: its fixed words never appear in a training prompt
    held_words = ["owns", "fills", "wins", "to a friend", "packs them", "end up"]
    for words in held_words:
        assert not any(words in p for p in train_prompts), words


def test_evaluate_scores_and_breaks_down():
    rows = _all("eval", 2, n=40)
    metas = [r["meta"] for r in rows]
    right = W.evaluate(metas, [r["completion"] for r in rows])
    assert right["accuracy"] == 1.0 and right["frac_explicit_answer"] == 1.0 and right["n"] == 40
    assert {"accuracy_1_steps", "accuracy_2_steps"} <= set(right)
    wrong = W.evaluate(metas, [" I do not know."] * 40)
    assert wrong["accuracy"] == 0.0 and wrong["frac_no_answer"] == 1.0
    with pytest.raises(ValueError, match="equal lengths"):
        W.evaluate(metas, ["x"])
    with pytest.raises(ValueError, match="row 1: meta has no 'answer'"):
        W.evaluate([{}], ["1"])


def test_the_models_own_answer_forms_are_read():
    meta = {"answer": "12"}
    assert W.gold_quality(meta, "Mia has 5 + 7 = 12 pencils.\n#### 12\nThe answer is: 12") == 1.0
    assert W.gold_quality(meta, "So she has 5 + 7 = 12 pencils.") == 1.0  # the last number
    # the failure mode the recipe's RL has to remove: the right sum, then more writing with a wrong last number
    assert W.gold_quality(meta, "5 + 7 = 12 pencils.\nShe now has 12 - 5 = 7 pencils.") == 0.0


def test_behaviour_counts_by_hand():
    texts = ["5 + 7 = 12\nLet me check: 5 + 7 = 12. #### 12",
             "Wait, actually 3 x 4 = 12, not 11.",
             "#### 9"]
    b = W.behaviour_counts(texts)
    assert W.recomputations(texts[0]) == 1 and W.recomputations(texts[1]) == 0
    assert b["frac_verification"] == pytest.approx(1 / 3) and b["mean_verification"] == pytest.approx(2 / 3)  # check, let me check
    assert b["frac_self_correction"] == pytest.approx(1 / 3) and b["mean_self_correction"] == pytest.approx(2 / 3)
    assert b["frac_recomputation"] == pytest.approx(1 / 3)
    assert W.behaviour_counts(["checking the list"])["frac_verification"] == 0.0  # whole words only


def test_task_difficulty_config_knob():
    from posttrain.config import ConfigError, TaskConfig
    from posttrain.tasks import load_split

    rows = load_split(TaskConfig(name="word-math", n_eval=20, difficulty=3), "eval")
    assert {r["meta"]["difficulty"] for r in rows} == {3}
    assert {r["meta"]["difficulty"] for r in load_split(TaskConfig(name="word-math", n_eval=5), "eval")} == \
        {W.DEFAULT_DIFFICULTY}
    with pytest.raises(ConfigError, match="task.difficulty: task 'word-math' has levels 1, 2, 3"):
        load_split(TaskConfig(name="word-math", n_eval=5, difficulty=7), "eval")
    with pytest.raises(ConfigError, match="task.difficulty: task 'tiny-math' has no difficulty levels"):
        load_split(TaskConfig(name="tiny-math", n_eval=5, difficulty=1), "eval")


def test_corpus_covers_every_level_and_split():
    texts = W.corpus(60, seed=0)
    assert len(texts) == 60 and all("####" in t for t in texts)
