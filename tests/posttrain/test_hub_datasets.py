"""Hugging Face hub datasets by name (`task.train_file=org/name[,split=...,subset=...,revision=...]`), offline from
the local datasets cache, with no network: the cache is populated inside the test exactly as an earlier online
`datasets.load_dataset("org/name")` leaves it (`<HF_DATASETS_CACHE>/org___name/<subset>/0.0.0/<hash>/`)."""
from __future__ import annotations

import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest

from posttrain.data import DataError, HubSource, hub_source, load_rows


def U(text):
    return {"role": "user", "content": text}


def A(text):
    return {"role": "assistant", "content": text}


CHATS = [{"messages": [U(f"document {i}: the red fox eats berries"), A(f"fox {i} eats berries")], "source": "x"}
         for i in range(40)]
PAIRS = [{"prompt": f"q{i}", "chosen": [U(f"q{i}"), A("good")], "rejected": [U(f"q{i}"), A("bad")],
          "score_chosen": 9.0, "score_rejected": 2.0} for i in range(6)]


def cache_hub_dataset(cache: Path, repo: str, splits: dict[str, list[dict]], subset: str = "default") -> None:
    """Write `splits` into the datasets cache under `cache` in the layout of a dataset once loaded from the hub."""
    import pyarrow as pa
    import pyarrow.parquet as pq
    from datasets.packaged_modules.parquet.parquet import Parquet

    org, name = repo.split("/")
    src = cache.parent / f"src-{org}-{name}-{subset}"
    src.mkdir(parents=True, exist_ok=True)
    files = {}
    for split, rows in splits.items():
        pq.write_table(pa.Table.from_pylist(rows), src / f"{split}.parquet")
        files[split] = [str(src / f"{split}.parquet")]
    builder = Parquet(cache_dir=str(cache), dataset_name=name, config_name=subset, config_id=subset,
                      data_files=files, hash="0123456789abcdef")
    builder.download_and_prepare()
    target = cache / f"{org}___{name}"
    target.mkdir(exist_ok=True)
    shutil.move(str(cache / name / subset), str(target / subset))
    shutil.rmtree(cache / name)


@pytest.fixture
def offline_cache(tmp_path, monkeypatch):
    """An offline datasets cache holding someorg/chats (train, test), someorg/levels (subsets easy and hard) and
    someorg/pairs."""
    import datasets.config
    import huggingface_hub.constants

    cache = tmp_path / "hf-datasets"
    cache_hub_dataset(cache, "someorg/chats", {"train": CHATS, "test": CHATS[:8]})
    cache_hub_dataset(cache, "someorg/levels", {"train": CHATS[:3]}, subset="easy")
    cache_hub_dataset(cache, "someorg/levels", {"train": CHATS[:5]}, subset="hard")
    cache_hub_dataset(cache, "someorg/pairs", {"train": PAIRS})
    monkeypatch.setattr(datasets.config, "HF_DATASETS_CACHE", cache)
    monkeypatch.setattr(datasets.config, "HF_HUB_OFFLINE", True)
    monkeypatch.setattr(huggingface_hub.constants, "HF_HUB_OFFLINE", True)
    monkeypatch.chdir(tmp_path)
    return cache


def test_hub_names_and_options_parse(tmp_path, monkeypatch):
    monkeypatch.chdir(tmp_path)
    assert hub_source("trl-lib/Capybara") == HubSource("trl-lib/Capybara", "train")
    assert hub_source("trl-lib/Capybara", "test") == HubSource("trl-lib/Capybara", "test")
    assert hub_source("org/name,split=validation,subset=main,revision=abc123") == \
        HubSource("org/name", "validation", "main", "abc123")
    for local in ("data/train.jsonl", "a/b/c", "train.parquet", "name", "data/chat/x.json"):
        assert hub_source(local) is None, local
    (tmp_path / "org").mkdir()
    (tmp_path / "org" / "name").mkdir()
    assert hub_source("org/name") is None  # an existing local directory wins
    with pytest.raises(DataError, match=r"option 'splt=test' of a hub dataset: expected split=NAME"):
        hub_source("other/name,splt=test")


def test_a_cached_hub_dataset_loads_offline_and_says_where_it_came_from(offline_cache):
    said = []
    ds = load_rows("someorg/chats", "sft", say=said.append)
    assert len(ds) == 40 and ds[3]["messages"] == CHATS[3]["messages"] and ds[3]["completion"] == "fox 3 eats berries"
    assert said == ["[data] someorg/chats (hub, split train): 40 rows, conversational (messages)"]
    assert len(load_rows("someorg/chats", "sft", split="test")) == 8  # an eval file's default split
    assert len(load_rows("someorg/chats,split=test", "sft")) == 8
    assert len(load_rows("someorg/levels,subset=easy", "sft")) == 3
    assert len(load_rows("someorg/levels,subset=hard", "sft")) == 5
    with pytest.raises(DataError, match=r"someorg/levels: hub dataset 'someorg/levels': There are multiple "):
        load_rows("someorg/levels", "sft")  # offline, datasets needs the subset of a dataset with several


def test_eval_files_default_to_the_test_split(offline_cache):
    from posttrain import tasks
    from posttrain.config import TaskConfig

    cfg = TaskConfig(train_file="someorg/chats", eval_file="someorg/chats")
    assert len(tasks.load_split(cfg, "train")) == 40 and len(tasks.load_split(cfg, "eval")) == 8


def test_hub_preference_pairs_with_extra_columns(offline_cache):
    from posttrain.preferences import read_pairs

    rows = read_pairs("someorg/pairs")
    # HuggingFaceH4/ultrafeedback_binarized's shape: a text prompt repeated as the first turn of both whole
    # conversations; the shared turns are the prompt
    assert len(rows) == 6 and rows[0]["prompt"] == [U("q0")] and rows[0]["chosen"] == "good"
    assert rows[5]["_row"] == 6


def test_hub_problems_are_named_in_one_line(offline_cache):
    with pytest.raises(DataError) as e:
        load_rows("someorg/missing", "sft")
    msg = str(e.value)
    assert "\n" not in msg and msg.startswith("someorg/missing: no such local file or directory, and the Hugging Face "
                                              "hub dataset 'someorg/missing' is neither in the local datasets cache")
    assert "offline mode is on" in msg and "give a local file" in msg
    with pytest.raises(DataError) as e:
        load_rows("someorg/chats,split=validation", "sft")
    assert "\n" not in str(e.value) and str(e.value).startswith("someorg/chats,split=validation: hub dataset "
                                                                "'someorg/chats': ")
    assert "validation" in str(e.value)
    with pytest.raises(DataError, match=r"someorg/chats: row 1: field 'question': missing \(task.columns.prompt"):
        load_rows("someorg/chats", "verifiable", columns={"prompt": "question"})


@pytest.mark.slow
def test_posttrain_sft_trains_on_a_hub_dataset_offline(tmp_path):
    """The CLI as a user runs it offline: HF_HUB_OFFLINE=1 and the datasets cache as an earlier download left it."""
    cache = tmp_path / "hf-datasets"
    cache_hub_dataset(cache, "someorg/chats", {"train": CHATS, "test": CHATS[:8]})
    env = dict(os.environ, HF_HUB_OFFLINE="1", HF_DATASETS_OFFLINE="1", HF_DATASETS_CACHE=str(cache))
    cmd = [sys.executable, "-m", "posttrain", "sft", "--recipe", "tiny-summarize", f"run.output_dir={tmp_path / 'runs'}",
           "task.train_file=someorg/chats", "task.eval_file=someorg/chats", "max_steps=3", "batch_size=8",
           "warmup_steps=1", "log_every=1", "eval_every=0", "final_eval_rows=4", "max_new_tokens=8",
           "model.vocab_size=300", "run.threads=1"]
    out = subprocess.run(cmd, env=env, capture_output=True, text=True, timeout=600)
    assert out.returncode == 0, out.stdout[-3000:] + out.stderr[-3000:]
    assert "[data] someorg/chats (hub, split train): 40 rows, conversational (messages)" in out.stdout
    assert "[data] someorg/chats (hub, split test): 8 rows" in out.stdout
    assert (tmp_path / "runs" / "tiny-summarize" / "sft" / "final" / "model.safetensors").is_file()
    missing = subprocess.run(cmd[:-9] + ["task.train_file=someorg/nothing"], env=env, capture_output=True, text=True,
                             timeout=300)
    assert missing.returncode != 0
    err = (missing.stdout + missing.stderr).strip().splitlines()[-1]
    assert "someorg/nothing: no such local file or directory, and the Hugging Face hub dataset" in err
