"""`posttrain plot`: metric families by name, one PNG per family (split past MAX_PANELS), bad files named."""

from __future__ import annotations

import json

import pytest

from posttrain import cli, plots
from posttrain.errors import DataError


@pytest.mark.parametrize("name, family", [
    ("loss", "loss"), ("eval_loss", "loss"), ("policy/loss", "loss"), ("lr", "lr"), ("kl", "kl"),
    ("rollout/kl", "kl"), ("mismatch/max_ratio", "kl"), ("entropy", "entropy"), ("eval/accuracy", "eval"),
    ("gold/win_rate", "eval"), ("curriculum/pass_0", "curriculum"), ("reward/mean", "reward"),
    ("rollout/score", "reward"), ("completion/length", "length"), ("tokens/generated", "length"),
    ("time/step", "speed"), ("tokens_per_s", "speed"), ("grad_norm", "other")])
def test_family_of_metric_names(name, family):
    assert plots.family_of(name) == family


def _write(path, rows, tail=""):
    path.write_text("".join(json.dumps(r) + "\n" for r in rows) + tail)
    return path


def test_plot_run_writes_one_png_per_family_and_splits_big_families(tmp_path):
    rows = [{"step": s, "time": 0.1 * s, "loss": 1.0 / s, "lr": 1e-3, "kl": 0.01 * s, "note": "text is skipped",
             **{f"reward/part_{i}": float(i + s) for i in range(plots.MAX_PANELS + 2)}} for s in range(1, 41)]
    rows.append({"step": 40, "eval/accuracy": 0.5})  # logged at one step only
    _write(tmp_path / "metrics.jsonl", rows, tail='{"step": 41, "lo')  # a killed run's torn line is skipped
    written = plots.plot_run(tmp_path)
    assert sorted(p.name for p in written) == ["eval.png", "kl.png", "loss.png", "lr.png", "reward-1.png",
                                                "reward-2.png"]
    for p in written:
        assert p.parent == tmp_path / "plots" and p.read_bytes()[:8] == b"\x89PNG\r\n\x1a\n"
    assert not list((tmp_path / "plots").glob("*.tmp*"))
    _, series = plots.read_metrics(tmp_path / "metrics.jsonl")
    assert series["eval/accuracy"] == [(40, 0.5)] and len(series["loss"]) == 40 and "note" not in series


@pytest.mark.parametrize("content, words", [(None, "no metrics.jsonl"), ('{"step": 1, "loss": 1}\nnot json\n{"step": 2}\n',
                                                                         "line 2: not JSON"),
                                            ('{"loss": 1}\n', "line 1: a metrics row needs a numeric 'step'"),
                                            ('{"step": 1, "note": "x"}\n', "no numeric metrics")])
def test_bad_metrics_files_are_named(tmp_path, content, words):
    if content is not None:
        (tmp_path / "metrics.jsonl").write_text(content)
    with pytest.raises(DataError, match=words):
        plots.plot_run(tmp_path)


def test_cli_plot_writes_to_out(tmp_path, capsys):
    _write(tmp_path / "metrics.jsonl", [{"step": s, "loss": 2.0 - 0.1 * s} for s in range(1, 5)])
    assert cli.main(["plot", str(tmp_path), "--out", str(tmp_path / "figs")]) == 0
    assert (tmp_path / "figs" / "loss.png").is_file()
    assert "wrote" in capsys.readouterr().out
    assert cli.main(["plot", str(tmp_path / "missing")]) != 0
