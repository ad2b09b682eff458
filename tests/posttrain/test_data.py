"""posttrain.data: loading from each source kind, one-line errors, save/load round trips."""
from __future__ import annotations

import json
from pathlib import Path

import datasets
import pytest

from posttrain.data import DataError, clean_preference_rows, load_rows, save_rows, to_dataset, validate_rows

SFT = [
    {"prompt": "Document: A.\nSummary:", "completion": " A."},
    {"prompt": "Document: B.\nSummary:", "completion": " B.", "meta": {"band": [1, 3], "facts": [{"keys": ["b"]}]}},
]
VERIFIABLE = [
    {"prompt": "1+1?", "answer": "2", "verifier": "math"},
    {"prompt": "Write f.", "answer": {"tests": ["assert f() == 1"]}, "verifier": "code", "meta": {"id": 7}},
    {"prompt": "Write g.", "answer": {"tests": ["assert g() == 2"], "entry": "g"}, "verifier": "code"},
]


def write_jsonl(path: Path, lines: list[str]) -> Path:
    path.write_text("".join(line + "\n" for line in lines), encoding="utf-8")
    return path


def message(excinfo) -> str:
    return str(excinfo.value)


# --- loading ------------------------------------------------------------------------------

def test_jsonl_loads_and_keeps_values(tmp_path):
    path = save_rows(VERIFIABLE, tmp_path / "v.jsonl")
    ds = load_rows(path, "verifiable")
    assert isinstance(ds, datasets.Dataset) and len(ds) == 3
    # Text and object answers in one file come back exactly, without merged keys.
    assert [row["answer"] for row in ds] == [r["answer"] for r in VERIFIABLE]
    assert [row["meta"] for row in ds] == [None, {"id": 7}, None]
    assert ds[1]["verifier"] == "code"
    assert ds.shuffle(seed=0).select([0])[0]["answer"] in [r["answer"] for r in VERIFIABLE]


def test_jsonl_without_meta_is_a_plain_dataset(tmp_path):
    path = write_jsonl(tmp_path / "s.jsonl", [json.dumps({"prompt": "p", "completion": " c", "extra": 1}), ""])
    ds = load_rows(path, "sft")
    assert ds.column_names == ["prompt", "completion"]  # extra field dropped, blank line skipped
    assert ds.to_list() == [{"prompt": "p", "completion": " c"}]


def test_json_array_loads(tmp_path):
    path = tmp_path / "p.json"
    path.write_text(json.dumps([{"prompt": "p", "chosen": " a", "rejected": " b"}]))
    assert load_rows(path, "preference")[0] == {"prompt": "p", "chosen": " a", "rejected": " b"}


def test_parquet_round_trip(tmp_path):
    path = save_rows(VERIFIABLE, tmp_path / "v.parquet")
    ds = load_rows(path, "verifiable")
    assert [dict(row) for row in ds] == [{**r, "meta": r.get("meta")} for r in VERIFIABLE]


def test_jsonl_round_trip_sft(tmp_path):
    ds = load_rows(save_rows(SFT, tmp_path / "s.jsonl"), "sft")
    assert [row["meta"] for row in ds] == [None, SFT[1]["meta"]]
    assert [row["completion"] for row in ds] == [" A.", " B."]


def test_saved_dataset_directory_loads(tmp_path):
    plain = datasets.Dataset.from_list([{"prompt": "p", "completion": " c", "meta": {"k": 1}}])
    plain.save_to_disk(str(tmp_path / "plain"))
    assert load_rows(tmp_path / "plain", "sft")[0] == {"prompt": "p", "completion": " c", "meta": {"k": 1}}

    # Our own layout (answer/meta as JSON text columns) survives save_to_disk; the decoding
    # transform is a function, which save_to_disk refuses, so it is dropped first.
    ours = to_dataset(VERIFIABLE, "verifiable")
    ours.with_format(None).save_to_disk(str(tmp_path / "ours"))
    assert [row["answer"] for row in load_rows(tmp_path / "ours", "verifiable")] == [r["answer"] for r in VERIFIABLE]

    datasets.DatasetDict({"train": plain}).save_to_disk(str(tmp_path / "dd"))
    assert len(load_rows(tmp_path / "dd", "sft")) == 1
    datasets.DatasetDict({"train": plain, "test": plain}).save_to_disk(str(tmp_path / "dd2"))
    with pytest.raises(DataError, match=r"dd2: a DatasetDict with splits train, test; point at one split"):
        load_rows(tmp_path / "dd2", "sft")


def test_directory_of_files_loads_in_name_order(tmp_path):
    save_rows(SFT[:1], tmp_path / "a.jsonl")
    save_rows(SFT[1:], tmp_path / "b.parquet")
    (tmp_path / "notes.txt").write_text("ignored")
    ds = load_rows(tmp_path, "sft")
    assert [row["completion"] for row in ds] == [" A.", " B."]


def test_bad_row_in_a_directory_names_its_file(tmp_path):
    save_rows(SFT, tmp_path / "a.jsonl")
    write_jsonl(tmp_path / "b.jsonl", [json.dumps({"prompt": "p", "completion": " c"}), json.dumps({"prompt": "p"})])
    with pytest.raises(DataError) as e:
        load_rows(tmp_path, "sft")
    assert message(e) == f"{tmp_path / 'b.jsonl'}: row 2: field 'completion': missing"


# --- one-line errors ------------------------------------------------------------------------

GOOD = json.dumps({"prompt": "p", "completion": " c"})


@pytest.mark.parametrize(
    "bad_line, expected",
    [
        ('{"prompt": "p"}', "row 3: field 'completion': missing"),
        ('{"prompt": "p", "completion": 5}', "row 3: field 'completion': expected text, got number"),
        ('{"prompt": "p", "completion": null}', "row 3: field 'completion': expected text, got null"),
        ('{"prompt": "p", "completion": "  "}', "row 3: field 'completion': empty text"),
        ('{"prompt": "", "completion": " c"}', "row 3: field 'prompt': empty text"),
        ('{"prompt": "p", "completion": " c", "meta": [1]}', "row 3: field 'meta': expected a JSON object or null, got list"),
        ('{"prompt": "p", "completion": " c"', "row 3: malformed JSON: Expecting ',' delimiter (column 35)"),
        ('["p", " c"]', "row 3: expected a JSON object, got list"),
    ],
)
def test_bad_sft_row_gives_one_line_with_file_row_field(tmp_path, bad_line, expected):
    # Line 2 is blank: numbers are file line numbers, so the bad row is reported on line 3.
    path = write_jsonl(tmp_path / "train.jsonl", [GOOD, "", bad_line, GOOD])
    with pytest.raises(DataError) as e:
        load_rows(path, "sft")
    assert message(e) == f"{path}: {expected}"
    assert "\n" not in message(e)


@pytest.mark.parametrize(
    "row, expected",
    [
        ({"prompt": "p", "chosen": " a"}, "field 'rejected': missing"),
        ({"prompt": "p", "chosen": "", "rejected": " b"}, "field 'chosen': empty text"),
        ({"prompt": "p", "chosen": ["a"], "rejected": " b"}, "field 'chosen': message 1: expected an object with 'role' and 'content', got str"),
    ],
)
def test_bad_preference_row(tmp_path, row, expected):
    path = write_jsonl(tmp_path / "pairs.jsonl", [json.dumps(row)])
    with pytest.raises(DataError) as e:
        load_rows(path, "preference")
    assert message(e) == f"{path}: row 1: {expected}"


@pytest.mark.parametrize(
    "row, expected",
    [
        ({"prompt": "p", "answer": 42, "verifier": "math"},
         "field 'answer': expected text or a JSON object, got number (write numbers as text, e.g. \"42\")"),
        ({"prompt": "p", "answer": {}, "verifier": "code"}, "field 'answer': empty JSON object"),
        ({"prompt": "p", "answer": " ", "verifier": "math"}, "field 'answer': empty text"),
        ({"prompt": "p", "answer": "2"}, "field 'verifier': missing"),
    ],
)
def test_bad_verifiable_row(tmp_path, row, expected):
    path = write_jsonl(tmp_path / "v.jsonl", [json.dumps(row)])
    with pytest.raises(DataError) as e:
        load_rows(path, "verifiable")
    assert message(e) == f"{path}: row 1: {expected}"


def test_bad_row_in_parquet_and_json_array_uses_position(tmp_path):
    rows = [{"prompt": "p", "completion": " c"}, {"prompt": "p", "completion": ""}]
    save_rows(rows, tmp_path / "s.parquet")
    with pytest.raises(DataError) as e:
        load_rows(tmp_path / "s.parquet", "sft")
    assert message(e) == f"{tmp_path / 's.parquet'}: row 2: field 'completion': empty text"
    (tmp_path / "s.json").write_text(json.dumps(rows))
    with pytest.raises(DataError) as e:
        load_rows(tmp_path / "s.json", "sft")
    assert message(e) == f"{tmp_path / 's.json'}: row 2: field 'completion': empty text"


def test_missing_file_unknown_extension_and_empty_file(tmp_path):
    with pytest.raises(DataError) as e:
        load_rows(tmp_path / "nope.jsonl", "sft")
    assert message(e) == f"{tmp_path / 'nope.jsonl'}: no such file or directory"

    (tmp_path / "rows.csv").write_text("prompt,completion\n")
    with pytest.raises(DataError) as e:
        load_rows(tmp_path / "rows.csv", "sft")
    assert message(e) == (f"{tmp_path / 'rows.csv'}: unsupported file type '.csv'; "
                          "supported: .jsonl, .json, .parquet, or a dataset directory")

    write_jsonl(tmp_path / "empty.jsonl", [""])
    with pytest.raises(DataError, match=r"empty\.jsonl: no rows$"):
        load_rows(tmp_path / "empty.jsonl", "sft")

    with pytest.raises(ValueError, match="unknown schema 'dpo'"):
        load_rows(tmp_path / "empty.jsonl", "dpo")  # type: ignore[arg-type]


def test_validate_rows_in_memory():
    validate_rows(SFT, "sft")
    with pytest.raises(DataError) as e:
        validate_rows([SFT[0], {"prompt": "p", "completion": 3}], "sft", source_name="tiny-summarize")
    assert message(e) == "tiny-summarize: row 2: field 'completion': expected text, got number"


# --- saving ----------------------------------------------------------------------------------

def test_save_is_atomic_and_rejects_unknown_extension(tmp_path):
    path = save_rows(SFT, tmp_path / "sub" / "s.jsonl")
    assert [json.loads(line) for line in path.read_text().splitlines()] == SFT
    assert sorted(p.name for p in path.parent.iterdir()) == ["s.jsonl"]  # no temp file left
    with pytest.raises(DataError, match=r"s\.csv: cannot save as '\.csv'; supported: \.jsonl, \.parquet"):
        save_rows(SFT, tmp_path / "s.csv")

    class Unserialisable:
        pass

    with pytest.raises(TypeError):
        save_rows([{"prompt": "p", "completion": Unserialisable()}], tmp_path / "sub" / "s.jsonl")
    assert [json.loads(line) for line in path.read_text().splitlines()] == SFT  # old file intact
    assert sorted(p.name for p in path.parent.iterdir()) == ["s.jsonl"]


# --- preference cleaning -----------------------------------------------------------------------

PAIRS = [
    {"prompt": "p", "chosen": " a", "rejected": " b"},
    {"prompt": "p", "chosen": " same", "rejected": "same "},
    {"prompt": "q", "chosen": " c", "rejected": " d"},
]


def test_clean_preference_rows_error_or_skip(tmp_path):
    with pytest.raises(DataError) as e:
        clean_preference_rows(PAIRS, "error", source_name="pairs.jsonl")
    assert message(e) == ("pairs.jsonl: row 2: field 'rejected': identical to 'chosen' "
                          "(set on_bad='skip' to drop such pairs)")
    rows, skipped = clean_preference_rows(PAIRS, "skip")
    assert skipped == 1 and rows == [PAIRS[0], PAIRS[2]]

    ds = load_rows(save_rows(PAIRS, tmp_path / "pairs.jsonl"), "preference")
    cleaned, skipped = clean_preference_rows(ds, "skip")
    assert isinstance(cleaned, datasets.Dataset) and skipped == 1
    assert [row["chosen"] for row in cleaned] == [" a", " c"]


def test_clean_preference_rows_always_stops_on_empty():
    bad = PAIRS[:1] + [{"prompt": "p", "chosen": " a", "rejected": ""}]
    with pytest.raises(DataError, match=r"row 2: field 'rejected': empty text"):
        clean_preference_rows(bad, "skip")


# ----------------------------------------------------------------------------- micro-batches by tokens
def test_token_groups_bound_rows_and_padded_tokens():
    from posttrain.data import token_groups

    spans = [(0, 4), (0, 4), (0, 10), (0, 2), (0, 2), (0, 2)]
    assert token_groups(spans) == [[0, 1, 2, 3, 4, 5]]  # no limits: one group
    assert token_groups(spans, max_rows=4) == [[0, 1, 2, 3], [4, 5]]
    # 3 rows of width 10 = 30 > 24: the third item starts a group; 2+2+2 after it fit under 10-wide padding?
    assert token_groups(spans, max_tokens=24) == [[0, 1], [2, 3], [4, 5]]  # (2 x 4), (2 x 10), (2 x 2)
    assert token_groups([(0, 50), (0, 3)], max_tokens=20) == [[0], [1]]  # wider than the budget: alone
    assert token_groups([(5, 9), (0, 9), (7, 9)], max_tokens=27) == [[0, 1, 2]]  # width = max end - min start
    assert token_groups([(0, 6)] * 4, max_tokens=24, rows_per_item=2) == [[0, 1], [2, 3]]  # pairs: 2 rows each
    assert token_groups([]) == []


def test_token_groups_by_length_pad_short_rows_to_short_rows():
    from posttrain.data import token_groups

    def padded(spans, groups):
        return sum(len(g) * (max(spans[i][1] for i in g) - min(spans[i][0] for i in g)) for g in groups)

    spans = [(0, 10), (0, 2), (0, 9), (0, 3), (0, 10), (0, 2)]  # long and short rows interleaved
    assert token_groups(spans, max_rows=2) == [[0, 1], [2, 3], [4, 5]]  # 2 x 10 + 2 x 9 + 2 x 10 = 58 tokens
    by_len = token_groups(spans, max_rows=2, by_length=True)
    assert by_len == [[0, 4], [1, 5], [2, 3]]  # widths 2, 2 | 3, 9 | 10, 10: ascending within, by first index
    assert padded(spans, by_len) == 4 + 18 + 20 < 58
    assert token_groups(spans, max_tokens=24, by_length=True) == [[0, 2], [1, 3, 5], [4]]  # 2 x 10, 3 x 3, 1 x 10
    assert padded(spans, token_groups(spans, max_tokens=24, by_length=True)) == 39  # consecutive: 58, as above
    # one group is the items in their order (no limits, or everything fits), so a step without a split is as it was
    assert token_groups(spans, by_length=True) == token_groups(spans) == [[0, 1, 2, 3, 4, 5]]
    # left-padded rows: the width is end - start; every index once, every group within the budget
    left = [(8 - w, 8) for w in (7, 1, 6, 2, 8, 1, 5)]
    groups = token_groups(left, max_tokens=12, by_length=True)
    assert sorted(i for g in groups for i in g) == list(range(len(left)))
    assert all(len(g) == 1 or padded(left, [g]) <= 12 for g in groups)
    assert padded(left, groups) < padded(left, token_groups(left, max_tokens=12))
    assert token_groups([], by_length=True) == []


def test_row_spans_of_a_padded_batch():
    import torch

    from posttrain.data import row_spans

    am = torch.tensor([[0, 0, 1, 1, 1], [1, 1, 1, 0, 0], [0, 0, 0, 0, 0], [1, 1, 1, 1, 1]])
    assert row_spans(am) == [(2, 5), (0, 3), (0, 0), (0, 5)]


def test_token_budget_is_the_setting_or_two_gib_of_activations():
    from transformers import LlamaConfig

    from posttrain.models import PRESETS, activation_bytes_per_token, token_budget

    class M:
        def __init__(self, **kw):
            self.config = LlamaConfig(**kw)

    tiny = M(vocab_size=1024, **PRESETS["tiny"])
    assert token_budget(500, tiny) == 500
    # the tiny preset: every shipped recipe's micro-batch (e.g. GRPO's 64 rows x ~300 tokens) fits, so
    # their numbers do not change; a 135M model with a 49k vocabulary: ~1.1k tokens
    assert token_budget(0, tiny) >= 64 * 300
    smol = M(vocab_size=49152, hidden_size=576, intermediate_size=1536, num_hidden_layers=30,
             num_attention_heads=9, num_key_value_heads=3)
    assert 900 <= token_budget(0, smol) <= 1400
    assert activation_bytes_per_token(smol.config) * token_budget(0, smol) <= 2 * 2**30
