"""Preference pairs: ranking and pairing rules, determinism per seed, batching independence, user files, bad rows."""
import json
import random

import pytest
import torch

from posttrain import preferences
from posttrain.cli import main
from posttrain.data import DataError
from posttrain.data import collate_pairs
from posttrain.preferences import check_pairs, form_pairs, read_pairs, sample_pairs
from posttrain.tasks import summarize


@pytest.fixture(scope="module")
def tiny(tiny_lm):
    """(model, tokenizer) of a random tiny model with a tokenizer trained on the task."""
    from posttrain.models import load_model, load_tokenizer

    lm = tiny_lm("tiny-summarize", max_length=160)
    return load_model(lm), load_tokenizer(lm)


def test_form_pairs_best_vs_worst_skips_ties_and_adds_random_lower():
    rng = random.Random(0)
    assert form_pairs([(0, 0.5), (-3, 1.0), (0, 0.9), (-3, 1.0)], 1, rng) == [(2, 1)]  # worst: lowest index on ties
    assert form_pairs([(0, 0.5)] * 4, 3, rng) == []  # all tie: no preference
    assert form_pairs([1.0], 1, rng) == []
    keys = [3, 1, 1, 0, 2, 3]
    pairs = form_pairs(keys, 10, random.Random(1))
    assert pairs[:2] == [(0, 3), (0, 4)]  # best = lowest index among the two 3s; worst; runner-up (key 2)
    assert {r for _, r in pairs} == {1, 2, 3, 4}  # every strictly lower sample, never the tied best (5)
    assert form_pairs(keys, 2, random.Random(1)) == [(0, 3), (0, 4)]
    assert all(keys[c] > keys[r] for c, r in pairs) and len(set(pairs)) == len(pairs)
    assert form_pairs(keys, 3, random.Random(7)) == form_pairs(keys, 3, random.Random(7))
    with pytest.raises(ValueError):
        form_pairs(keys, 0, rng)


def test_sample_pairs_deterministic_ordered_by_gold_and_independent_of_batching(tiny):
    model, tok = tiny
    rows = summarize.make_examples(6, 0, "train")
    label = preferences.gold_labeler("tiny-summarize")
    kw = dict(samples_per_prompt=4, pairs_per_prompt=2, temperature=1.0, max_new_tokens=24)
    a, stats = sample_pairs(model, tok, rows, label, prompt_keys=range(6), seed=3, **kw)
    b, _ = sample_pairs(model, tok, rows, label, prompt_keys=range(6), seed=3, **kw)
    assert a == b and a and stats["samples"] == 24
    c, _ = sample_pairs(model, tok, rows, label, prompt_keys=range(6), seed=4, **kw)
    assert [r["chosen"] for r in c] != [r["chosen"] for r in a]
    for r in a:
        meta = r["meta"]
        kc, kr = summarize.gold_key(meta, r["chosen"]), summarize.gold_key(meta, r["rejected"])
        assert kc > kr
        assert list(kc) == meta["pair"]["chosen_key"] and list(kr) == meta["pair"]["rejected_key"]
        assert meta["band"] == rows[meta["pair"]["prompt_index"]]["meta"]["band"]  # the task meta travels along
    # the same prompt keys give the same pairs whatever else is in the call
    tail, _ = sample_pairs(model, tok, rows[3:], label, prompt_keys=[3, 4, 5], seed=3, **kw)
    assert tail == [r for r in a if r["meta"]["pair"]["prompt_index"] >= 3]


def _write_jsonl(path, rows):
    path.write_text("".join(json.dumps(r) + "\n" for r in rows))
    return path


def _pairs(n, seed=0):
    rows = summarize.make_examples(n, seed, "train")
    return [{"prompt": r["prompt"], "chosen": " " + r["meta"]["concise_summary"], "rejected": r["completion"] + " And more.",
             "meta": {"i": i}} for i, r in enumerate(rows)]


def test_read_and_check_pairs_name_file_and_row(tmp_path, tiny):
    _, tok = tiny
    rows = _pairs(6)
    rows[1]["rejected"] = rows[1]["chosen"] + "  "  # identical after stripping
    rows[3]["chosen"] = "   "  # empty
    rows[4]["rejected"] = " word" * 300  # too long for 256 tokens
    f = _write_jsonl(tmp_path / "p.jsonl", rows)
    got = read_pairs(f)
    assert [r["_row"] for r in got] == [1, 2, 3, 4, 5, 6]
    with pytest.raises(DataError, match=r"p\.jsonl: row 2: field 'rejected': identical"):
        check_pairs(got, str(f), "error", tok, 256)
    kept, pairs, bad = check_pairs(got, str(f), "skip", tok, 256)
    assert [r["_row"] for r in kept] == [1, 3, 6] and len(pairs) == 3
    assert bad.rows == {"identical pair": [2], "empty": [4], "too long": [5]}
    assert "skipped 3 bad rows" in bad.summary() and "row 5" in bad.summary()
    assert pairs[0].chosen[-1] == tok.eos_token_id and pairs[0].prompt == tok(rows[0]["prompt"])["input_ids"]
    with pytest.raises(DataError, match=r"p\.jsonl: row 5: prompt \+ completion is \d+ tokens, longer than model.max_length=256"):
        check_pairs([got[4]], str(f), "error", tok, 256)

    (tmp_path / "bad.jsonl").write_text('{"prompt": "a", "chosen": "b"}\n')
    with pytest.raises(DataError, match=r"bad\.jsonl: row 1: field 'rejected': missing"):
        read_pairs(tmp_path / "bad.jsonl")
    (tmp_path / "bad2.jsonl").write_text('{"prompt": "a", "chosen": "b", "rejected": "c"}\n{oops\n')
    with pytest.raises(DataError, match=r"bad2\.jsonl: row 2: malformed JSON"):
        read_pairs(tmp_path / "bad2.jsonl")
    with pytest.raises(DataError, match="no such preference file"):
        read_pairs(tmp_path / "missing.jsonl")


def test_collate_pairs_puts_chosen_then_rejected():
    from posttrain.data import TokenizedPair

    pairs = [TokenizedPair([5, 6], [7, 1], [8, 9, 1], 1), TokenizedPair([5], [7, 7, 7, 1], [9, 1], 2)]
    b = collate_pairs(pairs, 0)
    assert b["input_ids"].shape == (4, 5)
    assert b["input_ids"][0].tolist() == [5, 6, 7, 1, 0] and b["input_ids"][3].tolist() == [5, 9, 1, 0, 0]
    assert b["completion_mask"][2].tolist() == [False, False, True, True, True]
    assert b["attention_mask"].sum(-1).tolist() == [4, 5, 5, 3]


@pytest.mark.parametrize("share_prompt", [True, False])
def test_reference_logps_keep_the_pairs_order_when_grouped_by_length(tiny, share_prompt):
    """Long and short pairs interleaved, two pairs per micro-batch: grouped by length they are computed as pairs
    (0, 2) and (1, 3), and every entry is the pair's own, as one pair at a time gives it."""
    from posttrain.data import TokenizedPair
    from posttrain.preferences import pair_groups, reference_logps

    model, tok = tiny
    rng = random.Random(0)
    pairs = []
    for i in range(4):
        n = 40 if i % 2 == 0 else 4
        pairs.append(TokenizedPair([rng.randrange(5, 200) for _ in range(n)], [rng.randrange(5, 200), 1],
                                   [rng.randrange(5, 200) for _ in range(3)] + [1], i))
    assert pair_groups(pairs, 2, 0, share_prompt) == [[0, 2], [1, 3]]
    grouped = reference_logps(model, pairs, tok.pad_token_id, 2, share_prompt)
    one = reference_logps(model, pairs, tok.pad_token_id, 1, share_prompt)
    for k in ("chosen", "rejected", "chosen_tokens", "rejected_tokens"):
        torch.testing.assert_close(grouped[k], one[k], atol=1e-4, rtol=1e-5)
    assert grouped["chosen_tokens"].tolist() == [2.0] * 4


@pytest.mark.parametrize("fmt", ["jsonl", "parquet"])
def test_prefs_stage_with_user_file(tmp_path, fmt, capsys):
    from posttrain.data import save_rows

    rows = _pairs(20)
    rows[5]["rejected"] = rows[5]["chosen"]
    src = save_rows(rows, tmp_path / f"prefs.{fmt}")
    args = ["prefs", "--recipe", "tiny-summarize", f"run.output_dir={tmp_path / 'runs'}", f"train_file={src}",
            "run.threads=1"]
    assert main(args) == 2
    assert f"{src}: row 6: field 'rejected': identical to 'chosen'" in capsys.readouterr().err
    assert main(args + ["on_bad_rows=skip", "eval_fraction=0.2"]) == 0
    assert "skipped 1 bad row" in capsys.readouterr().out
    final = tmp_path / "runs" / "tiny-summarize" / "prefs" / "final"
    train, ev = preferences.read_stage_pairs(final)
    assert len(train) == 15 and len(ev) == 4  # 19 good rows, 20% held out (seeded)
    assert {r["meta"]["i"] for r in train + ev} == set(range(20)) - {5}
    # the same again with a separate eval file
    ev_file = _write_jsonl(tmp_path / "ev.jsonl", _pairs(3, seed=1))
    assert main(args + ["on_bad_rows=skip", f"eval_file={ev_file}"]) == 0
    train, ev = preferences.read_stage_pairs(final)
    assert len(train) == 19 and len(ev) == 3
