"""Conversational rows (TRL's formats) in every schema: loading, the format said per source, column mapping,
storage round trips, and one clear line for each malformed conversation (posttrain.data, posttrain.preferences)."""
from __future__ import annotations

import json
from pathlib import Path

import pytest

from posttrain.data import DataError, load_rows, save_rows
from posttrain.preferences import check_pairs, check_unpaired, read_pairs


def U(text):
    return {"role": "user", "content": text}


def A(text):
    return {"role": "assistant", "content": text}


SYSTEM = {"role": "system", "content": "Be brief."}
MESSAGES = [SYSTEM, U("hi"), A("hello"), U("2+2?"), A("4")]


def _jsonl(path: Path, rows) -> Path:
    path.write_text("".join((r if isinstance(r, str) else json.dumps(r)) + "\n" for r in rows), encoding="utf-8")
    return path


# --- SFT ------------------------------------------------------------------------------------------

def test_messages_rows_load_with_prompt_completion_and_the_whole_conversation(tmp_path):
    said = []
    ds = load_rows(_jsonl(tmp_path / "c.jsonl", [{"messages": MESSAGES, "meta": {"id": 1}}] * 2), "sft",
                   say=said.append)
    row = ds[0]
    assert row["messages"] == MESSAGES and row["train_from"] == 0 and row["meta"] == {"id": 1}
    assert row["prompt"] == MESSAGES[:-1] and row["completion"] == "4"
    assert said == [f"[data] {tmp_path / 'c.jsonl'}: 2 rows, conversational (messages)"]


def test_conversational_prompt_completion_trains_only_the_completion(tmp_path):
    rows = [{"prompt": [SYSTEM, U("2+2?")], "completion": [A("4")]},
            {"prompt": [U("3+3?")], "completion": "6"},  # a text completion is the assistant's reply
            {"prompt": "4+4?", "completion": [A("8")]}]  # a text prompt is the user turn
    said = []
    ds = load_rows(_jsonl(tmp_path / "pc.jsonl", rows), "sft", say=said.append)
    assert [r["train_from"] for r in ds] == [2, 1, 1]
    assert ds[1]["messages"] == [U("3+3?"), A("6")] and ds[2]["messages"] == [U("4+4?"), A("8")]
    assert [r["completion"] for r in ds] == ["4", "6", "8"]
    assert said == [f"[data] {tmp_path / 'pc.jsonl'}: 3 rows, conversational prompt/completion"]


def test_text_rows_say_their_format_and_stay_as_they_were(tmp_path):
    said = []
    ds = load_rows(_jsonl(tmp_path / "t.jsonl", [{"prompt": "p", "completion": " c"}]), "sft", say=said.append)
    assert ds.column_names == ["prompt", "completion"] and ds[0] == {"prompt": "p", "completion": " c"}
    assert said == [f"[data] {tmp_path / 't.jsonl'}: 1 rows, text prompt/completion"]


@pytest.mark.parametrize("suffix", [".jsonl", ".parquet"])
def test_conversations_round_trip_through_save_rows(tmp_path, suffix):
    rows = [dict(r) for r in load_rows(_jsonl(tmp_path / "c.jsonl", [{"messages": MESSAGES}]), "sft")]
    back = load_rows(save_rows(rows, tmp_path / f"out{suffix}"), "sft")
    assert back[0]["messages"] == MESSAGES and back[0]["prompt"] == MESSAGES[:-1] and back[0]["completion"] == "4"


def test_a_hub_style_parquet_with_a_list_of_structs_column_loads(tmp_path):
    import pyarrow as pa
    import pyarrow.parquet as pq

    pq.write_table(pa.Table.from_pylist([{"conversations": MESSAGES}, {"conversations": MESSAGES[1:3]}]),
                   tmp_path / "train.parquet")
    ds = load_rows(tmp_path / "train.parquet", "sft", columns={"messages": "conversations"})
    assert ds[1]["messages"] == [U("hi"), A("hello")] and ds[1]["prompt"] == [U("hi")]


@pytest.mark.parametrize("row, expected", [
    ({"messages": [U("hi")]}, "field 'messages': the conversation ends with a user turn; it must end with the "
                              "assistant reply that is trained on"),
    ({"messages": [A("hello")]}, "field 'messages': a single assistant message has no prompt; start the "
                                 "conversation with a user turn"),
    ({"messages": []}, "field 'messages': an empty list of messages"),
    ({"messages": "hi"}, "field 'messages': expected a list of messages, got text"),
    ({"messages": [U("hi"), {"role": "bot", "content": "x"}]},
     "field 'messages': message 2: role 'bot' is not one of system, user, assistant, tool"),
    ({"messages": [U("hi"), {"role": "assistant"}]},
     "field 'messages': message 2 (assistant): 'content' must be text, got NoneType"),
    ({"messages": [U("hi"), A("  ")]}, "field 'messages': message 2 (assistant): empty content"),
    ({"messages": [{"role": "user", "content": [{"type": "text", "text": "hi"}]}, A("x")]},
     "field 'messages': message 1 (user): 'content' must be text, got a list of content parts (only text content "
     "is supported)"),
    ({"messages": [U("hi"), "hello"]}, "field 'messages': message 2: expected an object with 'role' and 'content', "
                                       "got str"),
    ({"messages": MESSAGES, "prompt": "p"}, "field 'messages': a row has either 'messages' or "
                                           "'prompt'/'completion', not both"),
    ({"prompt": [U("hi"), A("hello")], "completion": "x"},
     "field 'prompt': a conversational prompt must not end with an assistant turn (the model writes the next "
     "one); move the last assistant message to the completion"),
    ({"prompt": [U("hi")], "completion": [A("x"), U("more?")]},
     "field 'completion': the completion ends with a user turn; it must end with an assistant reply"),
])
def test_malformed_conversations_stop_with_file_row_and_field(tmp_path, row, expected):
    path = _jsonl(tmp_path / "bad.jsonl", [{"messages": MESSAGES}, row] if "messages" in row else
                  [{"prompt": [U("q")], "completion": "a"}, row])
    with pytest.raises(DataError) as e:
        load_rows(path, "sft")
    assert str(e.value) == f"{path}: row 2: {expected}"


def test_a_source_mixing_text_and_conversational_rows_stops(tmp_path):
    path = _jsonl(tmp_path / "mixed.jsonl", [{"prompt": "p", "completion": " c"}, "", {"messages": MESSAGES}])
    with pytest.raises(DataError) as e:
        load_rows(path, "sft")
    assert str(e.value) == (f"{path}: row 3: conversational (messages), but row 1 is text; one format per source "
                            "(convert the rows, or split the file)")


# --- column mapping -------------------------------------------------------------------------------

def test_columns_map_a_dataset_named_otherwise(tmp_path):
    path = _jsonl(tmp_path / "q.jsonl", [{"question": "1+1?", "solution": "2", "verifier": "math", "id": 3}])
    ds = load_rows(path, "verifiable", columns={"prompt": "question", "answer": "solution"})
    assert ds[0]["prompt"] == "1+1?" and ds[0]["answer"] == "2"
    with pytest.raises(DataError) as e:
        load_rows(path, "verifiable", columns={"prompt": "query"})
    assert str(e.value) == f"{path}: row 1: field 'query': missing (task.columns.prompt=query names it)"


def test_task_columns_is_a_checked_config_section():
    from posttrain.config import ConfigError, resolve
    from posttrain.trainers.sft import SFTConfig

    res = resolve("tiny-summarize", "sft", SFTConfig, ["task.columns.prompt=question", "task.columns.answer=solution"])
    assert res.task.columns.mapping() == {"prompt": "question", "answer": "solution"}
    with pytest.raises(ConfigError, match="unknown config key 'task.columns.question'"):
        resolve("tiny-summarize", "sft", SFTConfig, ["task.columns.question=prompt"])


# --- verifiable and prompt-only -------------------------------------------------------------------

def test_verifiable_rows_take_a_conversational_prompt(tmp_path):
    path = _jsonl(tmp_path / "v.jsonl", [{"prompt": [SYSTEM, U("1+1?")], "answer": "2", "verifier": "math"}])
    said = []
    ds = load_rows(path, "verifiable", say=said.append)
    assert ds[0]["prompt"] == [SYSTEM, U("1+1?")] and ds[0]["answer"] == "2"
    assert said == [f"[data] {path}: 1 rows, conversational prompt/answer/verifier"]
    assert load_rows(_jsonl(tmp_path / "p.jsonl", [{"prompt": [U("hi")]}]), "prompt")[0]["prompt"] == [U("hi")]


# --- preference pairs -----------------------------------------------------------------------------

def test_conversational_pairs_explicit_and_implicit_prompt(tmp_path):
    explicit = _jsonl(tmp_path / "e.jsonl", [{"prompt": [SYSTEM, U("2+2?")], "chosen": [A("4")],
                                              "rejected": [A("5")]}])
    implicit = _jsonl(tmp_path / "i.jsonl", [{"chosen": [SYSTEM, U("2+2?"), A("4")],
                                              "rejected": [SYSTEM, U("2+2?"), A("5")], "meta": {"k": 1}}])
    for path in (explicit, implicit):
        (row,) = read_pairs(path)
        assert row["prompt"] == [SYSTEM, U("2+2?")] and row["chosen"] == "4" and row["rejected"] == "5"
    assert read_pairs(implicit)[0]["meta"] == {"k": 1}
    ds = load_rows(implicit, "preference")
    assert ds[0]["prompt"] == [SYSTEM, U("2+2?")] and ds[0]["chosen"] == "4"
    kept, _, bad = check_pairs(read_pairs(implicit), str(implicit), "error")
    assert len(kept) == 1 and not bad.count


@pytest.mark.parametrize("row, expected", [
    ({"chosen": [U("a"), A("x")], "rejected": [U("b"), A("y")]},
     "field 'chosen': no prompt: 'chosen' and 'rejected' share no leading messages (the implicit prompt is their "
     "common prefix); add a 'prompt' field or start both with the same turns"),
    ({"chosen": [U("a"), A("x"), U("more"), A("y")], "rejected": [U("a"), A("x"), U("more"), A("z")],
      "x": 1}, None),  # a multi-turn shared prefix is the prompt
    ({"chosen": [U("a"), A("x"), U("b"), A("y")], "rejected": [U("a"), A("z")]},
     "field 'chosen': expected one assistant message, got 3 message(s) (assistant, user, assistant); a preference "
     "side is one assistant reply"),
    ({"prompt": "other", "chosen": [U("a"), A("x")], "rejected": [U("a"), A("y")]},
     "field 'prompt': differs from the turns 'chosen' and 'rejected' share (their implicit prompt); drop it or make "
     "the conversations start with it"),
    ({"prompt": [U("a")], "chosen": [A("x"), A("y")], "rejected": "z"},
     "field 'chosen': expected one assistant message, got 2 message(s) (assistant, assistant); a preference side "
     "is one assistant reply"),
    ({"prompt": [U("a")], "chosen": [U("x")], "rejected": "z"},
     "field 'chosen': expected one assistant message, got 1 message(s) (user); a preference side is one "
     "assistant reply"),
])
def test_malformed_conversational_pairs(tmp_path, row, expected):
    path = _jsonl(tmp_path / "p.jsonl", [row])
    if expected is None:
        (got,) = read_pairs(path)
        assert got["prompt"] == [U("a"), A("x"), U("more")] and (got["chosen"], got["rejected"]) == ("y", "z")
        return
    with pytest.raises(DataError) as e:
        read_pairs(path)
    assert str(e.value) == f"{path}: row 1: {expected}"
    with pytest.raises(DataError) as e:
        load_rows(path, "preference")
    assert str(e.value) == f"{path}: row 1: {expected}"


def test_pair_files_mixing_formats_stop(tmp_path):
    path = _jsonl(tmp_path / "m.jsonl", [{"prompt": "p", "chosen": "a", "rejected": "b"},
                                         {"chosen": [U("q"), A("a")], "rejected": [U("q"), A("b")]}])
    with pytest.raises(DataError) as e:
        read_pairs(path)
    assert str(e.value) == f"{path}: row 2: conversational (implicit prompt), but row 1 is text; one format per file"


def test_columns_rename_pair_files(tmp_path):
    path = _jsonl(tmp_path / "c.jsonl", [{"question": "q", "good": "a", "bad": "b"}])
    (row,) = read_pairs(path, {"prompt": "question", "chosen": "good", "rejected": "bad"})
    assert (row["prompt"], row["chosen"], row["rejected"]) == ("q", "a", "b")


def test_unpaired_conversational_rows_for_kto(tmp_path):
    from posttrain.models import train_tokenizer

    rows = [{"prompt": [U(f"q{i}")], "completion": [A(f"a{i}")], "label": i % 2 == 0} for i in range(4)]
    read = read_pairs(_jsonl(tmp_path / "u.jsonl", rows))
    assert read[1]["prompt"] == [U("q1")] and read[1]["completion"] == "a1" and read[1]["label"] is False
    tok = train_tokenizer(["q0 q1 a0 a1 q2 a2"] * 20, vocab_size=280, chat=True)
    pairs, labels, bad = check_unpaired(read, "u.jsonl", "error", tok)
    assert len(pairs) == 4 and labels == [True, False, True, False] and not bad.count
    assert tok.decode(pairs[0].prompt) == "<|user|>q0<|assistant|>"


# --- sampling from conversational prompts --------------------------------------------------------------

def test_the_rollout_engine_samples_from_conversational_prompts(tmp_path):
    from posttrain.chat import encode_prompts
    from posttrain.models import build_model, train_tokenizer
    from posttrain.problems import split_rows, tokenize_problems, check_problems
    from posttrain.rollout import generate
    from posttrain.rollout.records import table_rows

    tok = train_tokenizer(["what is one plus one two three"] * 20, vocab_size=280, chat=True)
    model = build_model("tiny", tok, seed=0)
    prompts = [[SYSTEM, U("one plus one?")], "two plus two?"]
    outs = generate(model, tok, prompts, greedy=True, max_new_tokens=4)
    assert [o.prompt_ids for o in outs] == encode_prompts(tok, prompts)
    assert outs[0].prompt == prompts[0] and tok.decode(outs[0].prompt_ids).startswith("<|system|>Be brief.<|user|>")
    assert table_rows(outs)[0]["prompt"] == "[system] Be brief.\n[user] one plus one?"

    from posttrain.config import TaskConfig

    path = _jsonl(tmp_path / "v.jsonl", [{"prompt": [U("one plus one?")], "answer": "2", "verifier": "math"}] * 2)
    rows, source = split_rows(TaskConfig(), "train", str(path))
    problems, skipped = check_problems(rows, source, "error")
    (p,) = tokenize_problems(tok, problems[:1], "train", 8, 64, print)
    assert p.prompt == [U("one plus one?")] and p.reference == "2" and skipped == []
    assert p.prompt_ids == encode_prompts(tok, [[U("one plus one?")]])[0]


def test_json_lines_rows_may_hold_unicode_line_separators(tmp_path):
    """Only \n ends a JSON Lines row: U+2028 and U+0085 inside a string are text (str.splitlines would cut there)."""
    path = tmp_path / "p.jsonl"
    path.write_text(json.dumps({"prompt": "a\u2028b", "chosen": "c\x85d", "rejected": "e"}, ensure_ascii=False) + "\n",
                    encoding="utf-8")
    (row,) = read_pairs(path)
    assert row["prompt"] == "a\u2028b" and row["chosen"] == "c\x85d"
    assert load_rows(path, "preference")[0]["prompt"] == "a\u2028b"
