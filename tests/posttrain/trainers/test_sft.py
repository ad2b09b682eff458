"""SFT end to end on a tiny model: it learns, resumes after a kill, and saves a loadable HF directory."""
import json
import os
import shutil
import signal
import subprocess
import sys
import time
from pathlib import Path

import pytest
import torch

from posttrain.cli import main

# A small but real configuration: ~20 s on 2 cores.
FAST = ["task.n_train=400", "task.n_eval=40", "model.max_length=160", "model.vocab_size=512",
        "batch_size=16", "log_every=5", "eval_every=0", "final_eval_rows=24", "max_new_tokens=40", "warmup_steps=5",
        "run.quiet=true"]


def _metrics(run: Path) -> list[dict]:
    return [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()]


@pytest.mark.slow
@pytest.mark.learning
def test_sft_learns_and_saves_hf_dir(tmp_path, capsys, learning):
    rc = main(["sft", "--recipe", "tiny-summarize", f"run.output_dir={tmp_path}", "max_steps=120", "lr=5e-3"] + FAST
              + learning.overrides)
    assert rc == 0
    run = tmp_path / "tiny-summarize" / "sft"
    rows = [r for r in _metrics(run) if "loss" in r]
    learning.above("loss first/last", rows[0]["loss"] / rows[-1]["loss"], 2.0, rows)
    ev = json.loads((run / "eval.json").read_text())
    # 120 steps teach the format and the length (content needs the recipe's 2400 steps)
    before, after = ev["untrained"], ev["sft"]
    learning.above("words out of band, untrained - sft", before["mean_distance"] - after["mean_distance"], 5, ev)
    learning.above("in band, sft - untrained", after["frac_in_band"] - before["frac_in_band"], 0.25, ev)
    learning.below("empty summaries", after["frac_empty"], 0.05, ev)
    assert after["frac_degenerate"] <= before["frac_degenerate"], ev
    out = capsys.readouterr().out
    assert "untrained" in out and "sft" in out
    from transformers import AutoModelForCausalLM, AutoTokenizer

    model = AutoModelForCausalLM.from_pretrained(run / "final")
    tok = AutoTokenizer.from_pretrained(run / "final")
    assert tok.eos_token_id is not None and model.config.vocab_size == len(tok)
    assert (run / "config.yaml").is_file()


@pytest.mark.slow
def test_sft_killed_midway_resumes_from_last_checkpoint(tmp_path):
    common = ["sft", "--recipe", "tiny-summarize", f"run.output_dir={tmp_path}", "max_steps=24", "save_every=6",
              "final_eval_rows=0", "run.threads=1"] + [o for o in FAST if not o.startswith("final_eval")]
    env = dict(os.environ, PYTHONUNBUFFERED="1")
    run = tmp_path / "tiny-summarize" / "sft"
    proc = subprocess.Popen([sys.executable, "-m", "posttrain", *common], env=env,
                            stdout=subprocess.PIPE, stderr=subprocess.STDOUT, text=True)
    deadline = time.time() + 300
    while time.time() < deadline and not (run / "checkpoints" / "step-000012").exists():
        time.sleep(0.05)
        assert proc.poll() is None, proc.stdout.read()
    proc.send_signal(signal.SIGKILL)
    proc.wait()
    done = {p.name for p in (run / "checkpoints").glob("step-*")}
    assert "step-000012" in done and not (run / "final").exists()

    out = subprocess.run([sys.executable, "-m", "posttrain", *common, "resume=true"], env=env,
                         capture_output=True, text=True, timeout=300)
    assert out.returncode == 0, out.stdout + out.stderr
    last = max(int(n.split("-")[1]) for n in done)
    assert f"resumed from" in out.stdout and f"at step {last}" in out.stdout
    steps = [r["step"] for r in _metrics(run) if "loss" in r]
    assert steps == sorted(set(steps)) and steps[-1] == 24  # no duplicated or missing rows
    resumed_final = {k: v.clone() for k, v in torch.load(run / "checkpoints" / "step-000024" / "state.pt",
                                                         weights_only=False)["model"].items()}

    # the same run without the kill ends with the same weights
    ref_dir = tmp_path / "ref"
    shutil.copytree(tmp_path / "tiny-summarize" / "base", ref_dir / "tiny-summarize" / "base")  # the same base model
    rc = subprocess.run([sys.executable, "-m", "posttrain", *[c.replace(str(tmp_path), str(ref_dir)) for c in common]],
                        env=env, capture_output=True, text=True, timeout=300)
    assert rc.returncode == 0, rc.stderr
    ref = torch.load(ref_dir / "tiny-summarize" / "sft" / "checkpoints" / "step-000024" / "state.pt",
                     weights_only=False)["model"]
    for k in ref:
        assert torch.allclose(ref[k], resumed_final[k], atol=1e-5), k


def test_bf16_mixed_precision_trains_fp32_weights_with_nearly_the_fp32_losses(tmp_path, capsys):
    """run.mixed_precision=bf16: autocast over fp32 weights (the lean forward under it); the losses follow the
    fp32 run's closely and final/ holds fp32 weights."""
    from posttrain.models import load_model

    losses = {}
    for mp in ("no", "bf16"):
        out = tmp_path / mp
        assert main(["sft", "--recipe", "tiny-summarize", f"run.output_dir={out}", "max_steps=4", "log_every=1",
                     "final_eval_rows=0", "run.threads=1", f"run.mixed_precision={mp}"] + FAST[:5]) == 0
        losses[mp] = [r["loss"] for r in _metrics(out / "tiny-summarize" / "sft") if "loss" in r]
    assert "[run] bf16 autocast over fp32 weights" in capsys.readouterr().out
    assert losses["bf16"] == pytest.approx(losses["no"], rel=0.02), losses  # bf16 keeps ~3 significant digits
    assert losses["bf16"] != losses["no"]  # it really ran in bf16
    assert load_model(tmp_path / "bf16" / "tiny-summarize" / "sft" / "final").dtype == torch.float32


# the CPU's bf16 probe decides `auto` only where torch sees no CUDA GPU (there the GPU's bf16 support decides)
cpu_probe_only = pytest.mark.skipif(torch.cuda.is_available(), reason="a CUDA GPU decides run.mixed_precision=auto "
                                    "by its bf16 support: no CPU probe runs (runtime.probe_decides_bf16)")


@cpu_probe_only
@pytest.mark.parametrize("ratio", [0.6, 2.0])
def test_mixed_precision_auto_says_what_the_bf16_probe_measured_and_follows_it(tmp_path, capsys, monkeypatch, ratio):
    """run.mixed_precision=auto on a CPU whose flags list AVX512-BF16: the run prints the measured bf16 / fp32
    matmul ratio and autocasts only when it clears runtime.BF16_MIN_SPEEDUP (here the probe is replaced)."""
    from posttrain import runtime

    monkeypatch.setattr(runtime, "cpu_flags", lambda: {"avx512f", "avx512_bf16"})
    monkeypatch.setattr(runtime, "_bf16_speedups", {})
    monkeypatch.setattr(runtime, "_matmul_time_ratio", lambda rows, **kw: ratio)
    assert main(["sft", "--recipe", "tiny-summarize", f"run.output_dir={tmp_path}", "max_steps=1", "final_eval_rows=0",
                 "run.threads=1", "run.mixed_precision=auto"] + FAST[:5]) == 0
    out = capsys.readouterr().out
    chosen = "bf16" if ratio > runtime.BF16_MIN_SPEEDUP else "fp32"
    assert f"run.mixed_precision=auto: bf16 matmuls measured {ratio:.2f}x fp32 here ({chosen};" in out
    assert ("[run] bf16 autocast over fp32 weights" in out) == (chosen == "bf16")


@cpu_probe_only
def test_a_resumed_auto_run_keeps_the_bf16_decision_it_started_with(tmp_path, capsys, monkeypatch):
    """The probe that decides `auto` is a timing: under another load a resumed run could measure the other side of
    the threshold and switch precision half-way. The first run records its decision (precision.json); resume=true
    keeps it whatever the probe says now; a fresh run decides afresh."""
    from posttrain import runtime

    monkeypatch.setattr(runtime, "cpu_flags", lambda: {"avx512f", "avx512_bf16"})
    monkeypatch.delenv("POSTTRAIN_BF16", raising=False)
    common = ["sft", "--recipe", "tiny-summarize", f"run.output_dir={tmp_path}", "final_eval_rows=0", "save_every=1",
              "run.threads=1", "run.mixed_precision=auto"] + FAST[:5]
    run_dir = tmp_path / "tiny-summarize" / "sft"

    def run(ratio: float, *extra: str) -> str:
        monkeypatch.setattr(runtime, "_bf16_speedups", {})
        monkeypatch.setattr(runtime, "_matmul_time_ratio", lambda rows, **kw: ratio)
        assert main(common + list(extra)) == 0
        return capsys.readouterr().out

    assert "[run] bf16 autocast over fp32 weights" in run(2.0, "max_steps=1")
    assert json.loads((run_dir / "precision.json").read_text()) == {"bf16": True, "decided_by": "probe",
                                                                     "bf16_speedup": 2.0, "threads": 1}
    out = run(0.6, "max_steps=2", "resume=true")  # the probe would now say fp32
    assert "the auto settings use bf16: the decision recorded when this run started" in out
    assert "[run] bf16 autocast over fp32 weights" in out and "resumed from" in out
    assert json.loads((run_dir / "precision.json").read_text())["bf16_speedup"] == 2.0  # the record is kept
    out = run(0.6, "max_steps=1")  # a fresh run: the probe decides
    assert "[run] bf16 autocast over fp32 weights" not in out and "(fp32; bf16 needs" in out
    assert json.loads((run_dir / "precision.json").read_text())["bf16"] is False
    assert runtime.bf16_forced() is None  # the pin ends with the command
