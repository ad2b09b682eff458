"""run.report_to: every metric of metrics.jsonl reaches TensorBoard, wandb (offline), trackio and MLflow, read back
with each tracker's own files; unknown and uninstalled trackers are one-line config errors; a resumed run's
TensorBoard curve has no duplicated tail. A tracker whose package is not installed (e.g. on a GPU machine with only
torch and the core packages) skips its tests, naming the package; the end-to-end run reports to those installed."""

from __future__ import annotations

import importlib.machinery
import importlib.util
import json
import os
import sqlite3
import struct
import subprocess
import sys
from pathlib import Path

import pytest

from posttrain import trackers
from posttrain.config import resolve
from posttrain.errors import ConfigError
from posttrain.trainers.sft import SFTConfig

REPO = Path(__file__).resolve().parents[2]


def _missing(*names: str) -> list[str]:
    """The trackers among `names` whose package is not installed here."""
    return [n for n in names if importlib.util.find_spec(trackers.KNOWN[n][0]) is None]


def needs(*names: str):
    """Skip unless the trackers' packages are installed (the reason names each missing one and its pip command)."""
    missing = _missing(*names)
    return pytest.mark.skipif(bool(missing), reason="not installed: " + "; ".join(
        f"{n} ({trackers.KNOWN[n][1]})" for n in missing))


INSTALLED = [n for n in trackers.KNOWN if not _missing(n)]


# ----------------------------------------------------------------------------- parsing and errors
def test_parse_report_to_accepts_none_one_several_and_lists(monkeypatch):
    monkeypatch.setattr(trackers.importlib.util, "find_spec", lambda name: importlib.machinery.ModuleSpec(name, None))
    assert trackers.parse_report_to("none") == []  # (every tracker "installed": the parsing, whatever is here)
    assert trackers.parse_report_to("") == []
    assert trackers.parse_report_to([]) == []
    assert trackers.parse_report_to("tensorboard") == ["tensorboard"]
    assert trackers.parse_report_to("tensorboard, wandb,tensorboard") == ["tensorboard", "wandb"]
    assert trackers.parse_report_to(["wandb", "mlflow"]) == ["wandb", "mlflow"]


@pytest.mark.parametrize("value, words", [("neptune", ["unknown tracker 'neptune'", "tensorboard", "wandb"]),
                                          ("none,wandb", ["'none' cannot be combined"]),
                                          (3, ["expected tracker names"])])
def test_bad_report_to_is_one_line_config_error(value, words):
    with pytest.raises(ConfigError) as e:
        trackers.parse_report_to(value)
    text = str(e.value)
    assert "run.report_to" in text and "\n" not in text
    for w in words:
        assert w in text


def test_uninstalled_tracker_names_the_pip_command(monkeypatch):
    # every other tracker "installed", whatever this machine has: the error is about wandb alone
    monkeypatch.setattr(trackers.importlib.util, "find_spec",
                        lambda name: None if name == "wandb" else importlib.machinery.ModuleSpec(name, None))
    with pytest.raises(ConfigError, match=r"wandb is not installed \(pip install \"posttrain\[wandb\]\"\)"):
        trackers.parse_report_to("tensorboard,wandb")


@needs("tensorboard", "wandb")
def test_config_resolves_report_to_to_a_list_and_refuses_unknown_names():
    res = resolve("tiny-summarize", "sft", SFTConfig, ["run.report_to=tensorboard,wandb"])
    assert res.run.report_to == ["tensorboard", "wandb"]
    assert resolve("tiny-summarize", "sft", SFTConfig, []).run.report_to == []
    with pytest.raises(ConfigError, match="unknown tracker 'comet'"):
        resolve("tiny-summarize", "sft", SFTConfig, ["run.report_to=comet"])


def test_flat_config_joins_keys_and_keeps_scalars():
    flat = trackers.flat_config({"sft": {"lr": 1e-3, "stages": ["a"], "x": None}, "recipe": "r"})
    assert flat == {"sft.lr": 1e-3, "sft.stages": '["a"]', "sft.x": "null", "recipe": "r"}
    assert trackers.flat_config({"a": {"b": 1}}, "final/", sep="/") == {"final/a/b": 1}


# ----------------------------------------------------------------------------- readers of each tracker's files
def tensorboard_scalars(logdir: Path) -> dict[str, dict[int, float]]:
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(logdir), size_guidance={"scalars": 0})
    acc.Reload()
    return {tag: {e.step: e.value for e in acc.Scalars(tag)} for tag in acc.Tags()["scalars"]}


def wandb_records(run_file: Path) -> list:
    """The records of an offline run's .wandb file (a LevelDB-style log of protobuf records: 7-byte file header, then
    32 KiB blocks of chunks with a 7-byte header: crc32, length, type 1 full / 2 first / 3 middle / 4 last)."""
    from wandb.proto import wandb_internal_pb2 as pb

    data, out, pos, pending = run_file.read_bytes(), [], 7, b""
    while pos + 7 <= len(data):
        left = 32768 - pos % 32768
        if left < 7:
            pos += left
            continue
        _crc, length, kind = struct.unpack("<IHB", data[pos:pos + 7])
        pos += 7
        if kind == 0 and length == 0:
            break
        chunk, pos = data[pos:pos + length], pos + length
        if kind in (1, 4):
            record = pb.Record()
            record.ParseFromString(pending + chunk if kind == 4 else chunk)
            out.append(record)
            pending = b""
        else:
            pending = chunk if kind == 2 else pending + chunk
    return out


# ----------------------------------------------------------------------------- end to end through the CLI
@pytest.fixture(scope="module")
def tracked_sft(tmp_path_factory):
    """One tiny SFT run reporting to all four trackers (those installed), in its own process and HOME, with no
    network."""
    if not INSTALLED:
        pytest.skip("no tracker package is installed (tensorboard, wandb, trackio, mlflow)")
    root = tmp_path_factory.mktemp("tracked")
    path = os.pathsep.join([str(REPO)] + [p for p in os.environ.get("PYTHONPATH", "").split(os.pathsep) if p])
    env = {**os.environ, "HOME": str(root / "home"), "WANDB_MODE": "offline", "WANDB_CACHE_DIR": str(root / "wandb-cache"),
           "WANDB_CONFIG_DIR": str(root / "wandb-config"), "TRACKIO_DIR": str(root / "trackio"),
           "MLFLOW_DISABLE_TELEMETRY": "true", "HF_HUB_OFFLINE": "1", "PYTHONPATH": path,
           # the CUDA driver keeps a JIT cache in ~/.nv for every CUDA process (seen on an H200): not the run's doing
           "CUDA_CACHE_DISABLE": "1"}
    env.pop("MLFLOW_TRACKING_URI", None)
    (root / "home").mkdir()
    cmd = [sys.executable, "-m", "posttrain", "sft", "--recipe", "tiny-summarize", "max_steps=6", "log_every=2",
           "eval_every=3", "final_eval_rows=4", "num_samples=0", "run.threads=1", f"run.output_dir={root / 'runs'}",
           f"run.report_to={','.join(INSTALLED)}"]
    proc = subprocess.run(cmd, cwd=root, env=env, capture_output=True, text=True, timeout=600)
    assert proc.returncode == 0, proc.stdout[-3000:] + proc.stderr[-3000:]
    run_dir = root / "runs" / "tiny-summarize" / "sft"
    rows = [json.loads(line) for line in (run_dir / "metrics.jsonl").read_text().splitlines()]
    expected = {(r["step"], k): v for r in rows for k, v in r.items() if k not in ("step", "time")}
    return root, run_dir, expected, proc


def _assert_same(got: dict[tuple[int, str], float], expected: dict[tuple[int, str], float], tracker: str):
    missing = sorted(set(expected) - set(got))
    assert not missing, f"{tracker} lacks {missing[:5]}"
    for key, v in expected.items():
        assert got[key] == pytest.approx(v, rel=1e-6), (tracker, key)


@needs("tensorboard")
def test_tensorboard_event_files_hold_every_metric_and_the_config(tracked_sft):
    _, run_dir, expected, _ = tracked_sft
    logdir = run_dir / "tensorboard" / "tiny-summarize-sft"
    scalars = tensorboard_scalars(logdir)
    _assert_same({(s, tag): v for tag, by_step in scalars.items() for s, v in by_step.items()}, expected, "tensorboard")
    assert [s for s in scalars["loss"]] == [2, 4, 6]
    assert any(tag.startswith("final/sft/") for tag in scalars), "the final evaluation reaches the tracker"
    hparams = list(logdir.glob("*/hparams.yml"))
    assert len(hparams) == 1 and "sft.lr" in hparams[0].read_text()


@needs("wandb")
def test_wandb_offline_run_holds_every_metric_and_the_config(tracked_sft):
    _, run_dir, expected, _ = tracked_sft
    run_files = list((run_dir / "wandb").glob("offline-run-*/run-*.wandb"))
    assert len(run_files) == 1
    records = wandb_records(run_files[0])
    got = {}
    for r in records:
        if r.WhichOneof("record_type") == "history":
            items = {i.key or "/".join(i.nested_key): json.loads(i.value_json) for i in r.history.item}
            got.update({(int(items["_step"]), k): v for k, v in items.items() if not k.startswith("_")})
    _assert_same(got, expected, "wandb")
    config_keys = {u.key for r in records if r.WhichOneof("record_type") == "config" for u in r.config.update}
    assert {"sft.lr", "model.path", "recipe"} <= config_keys
    run = next(r.run for r in records if r.WhichOneof("record_type") == "run")
    assert run.project == "posttrain-tiny-summarize" and run.display_name == "tiny-summarize-sft"
    assert run.run_id == (run_dir / "wandb-run-id").read_text().strip()  # a resumed stage continues this run


@needs("trackio")
def test_trackio_store_holds_every_metric(tracked_sft):
    root, _, expected, _ = tracked_sft
    db = sqlite3.connect(root / "trackio" / "posttrain-tiny-summarize.db")
    got = {}
    for step, blob, name in db.execute("select step, metrics, run_name from metrics"):
        assert name == "tiny-summarize-sft"
        got.update({(step, k): v for k, v in json.loads(blob).items()})
    _assert_same(got, expected, "trackio")


@needs("mlflow")
def test_mlflow_store_holds_every_metric_and_the_params(tracked_sft):
    from mlflow.tracking import MlflowClient

    _, run_dir, expected, _ = tracked_sft
    client = MlflowClient(tracking_uri=f"sqlite:///{run_dir / 'mlflow.db'}")
    exp = client.get_experiment_by_name("posttrain-tiny-summarize")
    (run,) = client.search_runs([exp.experiment_id])
    assert run.info.run_name == "tiny-summarize-sft" and run.data.params["sft.lr"] == "0.003"
    got = {}
    for key in {k for _, k in expected}:
        got.update({(m.step, key): m.value for m in client.get_metric_history(run.info.run_id, key)})
    _assert_same(got, expected, "mlflow")


def test_trackers_write_only_where_told(tracked_sft):
    root, _, _, _ = tracked_sft
    stores = {"trackio": ["trackio"], "wandb": ["wandb-cache"]}  # the trackers' own stores outside the run tree
    expected = sorted(["home", "runs"] + [d for n in INSTALLED for d in stores.get(n, [])])
    assert sorted(p.name for p in root.iterdir()) == expected, \
        "nothing in the working directory beyond the run tree and the trackers' own stores"
    assert not any((root / "home").rglob("*")), list((root / "home").rglob("*"))


# ----------------------------------------------------------------------------- resume
@needs("tensorboard")
def test_resumed_run_purges_the_tensorboard_tail(tmp_path):
    """A run resumed from step 2 redoes steps 3-4: the event files hold the redone values once, as metrics.jsonl."""
    first = trackers.Trackers(["tensorboard"], tmp_path, "r", "sft", {"sft": {"lr": 1.0}})
    for step in range(1, 5):
        first.log({"loss": float(step)}, step)
    first.finish()
    again = trackers.Trackers(["tensorboard"], tmp_path, "r", "sft", {"sft": {"lr": 1.0}})
    again.resume_step = 2
    for step in (3, 4):
        again.log({"loss": 10.0 + step, "note": "text stays out"}, step)
    again.finish()
    from tensorboard.backend.event_processing.event_accumulator import EventAccumulator

    acc = EventAccumulator(str(tmp_path / "tensorboard" / "r-sft"), size_guidance={"scalars": 0})
    acc.Reload()
    assert [(e.step, e.value) for e in acc.Scalars("loss")] == [(1, 1.0), (2, 2.0), (3, 13.0), (4, 14.0)]


def test_tables_go_to_trackers_that_take_them_with_cells_as_scalars(tmp_path):
    class TableTracker:
        def __init__(self):
            self.calls = []

        def log_table(self, name, columns, data, step):
            self.calls.append((name, columns, data, step))

    class ScalarTracker:  # no log_table: skipped
        pass

    t = trackers.Trackers([], tmp_path, "r", "grpo", {})
    table, scalar = TableTracker(), ScalarTracker()
    t.open = [table, scalar]
    t.log_table("rollouts", [{"prompt": "p", "reward": 1.0, "parts": {"format": 1}, "reason": None}], 5)
    t.log_table("rollouts", [], 6)  # nothing to show: no call
    assert table.calls == [("rollouts", ["prompt", "reward", "parts", "reason"], [["p", 1.0, '{"format": 1}', None]], 5)]


def test_rollout_table_rows_carry_what_a_reader_scans():
    from posttrain.rollout.records import Rollout, table_rows

    r = Rollout(prompt_ids=[1, 2], completion_ids=[3, 4, 5], logprobs=[0.0] * 3, policy_logprobs=[0.0] * 3,
                finish_reason="eos", text="42", prompt_index=0, sample_index=1, prompt="6*7=", reward=1.0,
                extras={"advantage": 0.5, "reason": "correct", "parts": {"correct": 1.0}})
    (row,) = table_rows([r])
    assert row == {"prompt": "6*7=", "completion": "42", "reward": 1.0, "advantage": 0.5, "reason": "correct",
                   "parts": '{"correct": 1.0}', "length": 3, "finish_reason": "eos", "prompt_index": 0,
                   "sample_index": 1}
