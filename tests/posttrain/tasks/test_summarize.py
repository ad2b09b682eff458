"""tiny-summarize: generation, splits, the gold scorer on hand-computed cases, the preference."""
from __future__ import annotations

import ast
import json
import re
from collections import Counter

import pytest

from posttrain.tasks import get_task
from posttrain.tasks import summarize as S

DOC = "Milo is a red fox. Milo eats berries. Some nuts grow near there."
META = {
    "facts": [{"name": "identity", "keys": ["milo", "red", "fox"]}, {"name": "food", "keys": ["berries"]}],
    "doc_words": sorted(set(re.findall(r"[a-z0-9]+", DOC.lower()))),
    "band": [4, 8],
}


def document_of(example) -> str:
    prompt = example["prompt"]
    assert prompt.startswith("Document: ") and prompt.endswith("\nSummary:")
    return prompt[len("Document: "):-len("\nSummary:")]


@pytest.fixture(scope="module")
def train():
    return S.make_examples(600, seed=0, split="train")


@pytest.fixture(scope="module")
def eval_set():
    return S.make_examples(600, seed=0, split="eval")


# --- generation --------------------------------------------------------------------------

def test_deterministic_and_prefix_stable():
    a = S.make_examples(40, seed=3, split="train")
    assert a == S.make_examples(40, seed=3, split="train")
    assert a[:10] == S.make_examples(10, seed=3, split="train")
    assert a != S.make_examples(40, seed=4, split="train")
    assert S.make_examples(0, seed=3, split="eval") == []
    with pytest.raises(ValueError, match="split must be 'train' or 'eval'"):
        S.make_examples(1, seed=0, split="test")  # type: ignore[arg-type]


def test_splits_are_disjoint(train, eval_set):
    subjects = {split: {tuple(ex["meta"]["subject"]) for ex in exs} for split, exs in
                (("train", train), ("eval", eval_set))}
    assert not subjects["train"] & subjects["eval"]
    assert not {ex["prompt"] for ex in train} & {ex["prompt"] for ex in eval_set}
    # a different seed of the other split cannot reach the held-out subjects either
    assert not {tuple(ex["meta"]["subject"]) for ex in S.make_examples(300, seed=9, split="train")} & subjects["eval"]


def test_example_format(train):
    for ex in train:
        assert set(ex) == {"prompt", "completion", "meta"}
        assert json.loads(json.dumps(ex)) == ex
        n_sentences = document_of(ex).count(". ") + 1
        assert 3 <= n_sentences <= 6
        assert 2 <= len(ex["meta"]["facts"]) <= 4
        assert ex["completion"].startswith(" ") and not ex["completion"].startswith("  ")
        assert ex["completion"].endswith(".")
        lo, hi = ex["meta"]["band"]
        assert (lo, hi) == (ex["meta"]["concise_length"] - 2, ex["meta"]["concise_length"] + 2) and lo >= 4
    assert Counter(ex["meta"]["kind"] for ex in train).keys() == {"animal", "news"}


def test_small_vocabulary_and_corpus_covers_eval(eval_set):
    corpus = S.corpus(200, seed=0)
    corpus_words = {w for text in corpus for w in re.findall(r"[a-z0-9]+", text.lower())}
    eval_words = {w for ex in eval_set for w in re.findall(r"[a-z0-9]+", (ex["prompt"] + ex["completion"]).lower())}
    assert eval_words <= corpus_words
    assert len(corpus_words) < 400


# --- references ----------------------------------------------------------------------------

def test_reference_styles_score_as_documented(train):
    styles = Counter(ex["meta"]["style"] for ex in train)
    for style, weight in S.STYLE_WEIGHTS.items():
        assert abs(styles[style] / len(train) - weight) < 0.06
    for ex in train:
        meta, b = ex["meta"], S.gold_breakdown(ex["meta"], ex["completion"])
        assert not b["invented"] and not b["degenerate"] and not b["empty"]
        k = len(meta["facts"])
        if meta["style"] == "concise":
            assert b["quality"] == 1.0 and b["in_band"]
            assert ex["completion"] == " " + meta["concise_summary"]
        elif meta["style"] == "verbose":
            assert b["quality"] == 1.0 and b["length"] > meta["band"][1]
        else:
            assert b["coverage"] == pytest.approx((k - 1) / k)
            assert b["quality"] == pytest.approx(0.7 * (k - 1) / k + 0.3)
            assert b["length"] <= meta["band"][1]


def test_references_straddle_the_band(train):
    stats = S.evaluate([ex["meta"] for ex in train], [ex["completion"] for ex in train])
    assert 0.3 < stats["frac_in_band"] < 0.6
    assert stats["frac_too_long"] > 0.35 and stats["frac_too_short"] > 0.05
    # an ideal policy (the concise summary every time) beats the references often
    ideal = [" " + ex["meta"]["concise_summary"] for ex in train]
    assert S.win_rate([ex["meta"] for ex in train], ideal, [ex["completion"] for ex in train]) > 0.8


# --- the gold scorer on hand-computed cases ----------------------------------------------------

@pytest.mark.parametrize(
    "summary, quality",
    [
        ("Milo the red fox eats berries.", 1.0),                   # complete, in band
        ("Milo is a red fox.", 0.7 * 0.5 + 0.3),                   # misses food: 0.65
        ("Milo the red fox eats nuts.", 0.65),                     # wrong food, but nuts are in the document
        ("Milo the red fox eats apples.", 0.5 * 0.65),             # 'apples' invented: x0.5
        ("Milo the red fox eats berries and plums and corn.", 0.0),  # two invented words: x0
        ("milo the red fox eats berries", 0.7),                    # no capital, no period
        ("Milo the red fox eats berries. Milo the red fox eats berries.", 0.25),  # repeated 4-gram: x1/4
        ("Milo milo milo eats berries.", 0.25 * 0.65),             # word 3 times in a row
        ("", 0.0),
        ("  . ", 0.0),
    ],
)
def test_gold_quality_hand_computed(summary, quality):
    assert S.gold_quality(META, summary) == pytest.approx(quality)


def test_gold_breakdown_terms():
    b = S.gold_breakdown(META, " Milo the red fox eats apples.")
    assert b["covered"] == ["identity"] and b["missing"] == ["food"] and b["invented"] == ["apples"]
    assert b["faithfulness"] == 0.5 and b["ends_with_period"] and b["capitalised"] and not b["degenerate"]
    assert (b["length"], b["distance"], b["in_band"]) == (6, 0, True)
    assert json.loads(json.dumps(b)) == b
    empty = S.gold_breakdown(META, "")
    assert empty["empty"] and empty["distance"] == 4 and not empty["in_band"]


# --- the preference -----------------------------------------------------------------------------

IN_BAND_COMPLETE = "Milo the red fox eats berries."            # 6 words, d=0, q=1
IN_BAND_TERSE = "Milo is a red fox."                            # 5 words, d=0, q=0.65
LONG_COMPLETE = "Milo the red fox eats berries. Some nuts grow near there."  # 11 words, d=3, q=1
VERY_LONG = LONG_COMPLETE + " Milo is a red fox."               # 16 words, d=8


@pytest.mark.parametrize(
    "a, b, expected",
    [
        (IN_BAND_TERSE, LONG_COMPLETE, +1),         # length first: in band beats better quality out of band
        (LONG_COMPLETE, VERY_LONG, +1),             # both out: smaller distance wins
        (IN_BAND_COMPLETE, IN_BAND_TERSE, +1),      # equal distance: quality breaks the tie
        ("Milo berries.", "Milo eats.", +1),        # both d=2: 0.65 beats 0.3
        (IN_BAND_COMPLETE, "Milo, the red fox, eats berries.", 0),  # same words: tie
        (IN_BAND_COMPLETE, IN_BAND_COMPLETE + " ", 0),
    ],
)
def test_gold_prefer_hand_built(a, b, expected):
    assert S.gold_prefer(META, a, b) == expected
    assert S.gold_prefer(META, b, a) == -expected
    ka, kb = S.gold_key(META, a), S.gold_key(META, b)
    assert (ka > kb) - (ka < kb) == expected


def test_gold_key_values():
    assert S.gold_key(META, IN_BAND_TERSE) == (0, 0.65)
    assert S.gold_key(META, LONG_COMPLETE) == (-3, 1.0)
    assert S.gold_key(META, "") == (-4, 0.0)


def test_reward_hacks_lose(eval_set):
    for ex in eval_set[:200]:
        meta = ex["meta"]
        lo, hi = meta["band"]
        good = " " + meta["concise_summary"]
        # garbage of the right length made only of document words, with the facts' key words removed
        keys = {k for f in meta["facts"] for k in f["keys"]}
        filler = [w for w in meta["doc_words"] if w not in keys]
        garbage = " " + " ".join(filler[:lo]).capitalize() + "."
        assert S.gold_breakdown(meta, garbage)["in_band"]
        assert S.gold_prefer(meta, good, garbage) == +1
        for bad in ["", " .", good + good, " " + " ".join([meta["concise_summary"].split()[0]] * lo) + "."]:
            b = S.gold_breakdown(meta, bad)
            assert not (b["in_band"] and b["quality"] >= 0.5), bad
            assert S.gold_prefer(meta, good, bad) == +1


def test_win_rate_counts_ties_half():
    metas = [META] * 4
    candidates = [IN_BAND_COMPLETE, IN_BAND_TERSE, IN_BAND_COMPLETE, IN_BAND_TERSE]
    baselines = [LONG_COMPLETE, IN_BAND_COMPLETE, IN_BAND_COMPLETE, VERY_LONG]
    assert S.win_rate(metas, candidates, baselines) == pytest.approx((1 + 0 + 0.5 + 1) / 4)
    with pytest.raises(ValueError, match="equal lengths"):
        S.win_rate(metas, candidates, baselines[:3])
    with pytest.raises(ValueError, match="zero examples"):
        S.win_rate([], [], [])


def test_evaluate_hand_built():
    stats = S.evaluate([META] * 4, [IN_BAND_COMPLETE, IN_BAND_TERSE, LONG_COMPLETE, ""])
    assert stats["n"] == 4
    assert stats["mean_quality"] == pytest.approx((1 + 0.65 + 1 + 0) / 4)
    assert stats["mean_length"] == pytest.approx((6 + 5 + 11 + 0) / 4)
    assert stats["frac_in_band"] == 0.5 and stats["frac_too_long"] == 0.25 and stats["frac_too_short"] == 0.25
    assert stats["frac_empty"] == 0.25 and stats["frac_complete"] == 0.5
    assert stats["mean_distance"] == pytest.approx((0 + 0 + 3 + 4) / 4)


# --- the module -----------------------------------------------------------------------------------

def test_task_table_and_no_torch():
    assert get_task("tiny-summarize") is S
    with pytest.raises(ValueError, match="unknown task 'nope'; known tasks: .*tiny-summarize"):
        get_task("nope")
    tree = ast.parse(open(S.__file__).read())
    imported = {alias.name.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.Import) for alias in node.names}
    imported |= {node.module.split(".")[0] for node in ast.walk(tree) if isinstance(node, ast.ImportFrom) and node.module}
    assert "torch" not in imported and "posttrain" not in imported
    assert not (S.GLUE & S.VALUE_WORDS)
