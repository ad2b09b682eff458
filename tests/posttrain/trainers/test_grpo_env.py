"""GRPO in a multi-turn environment (grpo.env): episodes train end to end, only sampled tokens carry loss, the
trainer's log-probs equal the sampler's on multi-turn trajectories, the policy learns the environment's reward,
LoRA and resume work, saved rollouts keep the turns, and bad settings are one-line errors."""
import json
import re
import shutil
from pathlib import Path

import pytest
import torch

from posttrain.cli import main

ENVS = Path(__file__).resolve().parent.parent / "envs_for_tests.py"


# chat_sft: tests/posttrain/trainers/conftest.py


def _args(sft_model, out: Path, *extra: str) -> list[str]:
    sft = out / "tiny-calc" / "sft" / "final"
    if not sft.exists():
        sft.parent.mkdir(parents=True, exist_ok=True)
        shutil.copytree(sft_model, sft)
    return ["grpo", "--recipe", "tiny-calc", f"run.output_dir={out}", f"env={ENVS}:Turns", "prompts_per_step=4",
            "group_size=4", "max_steps=2", "eval_every=0", "eval_rows=8", "final_eval_rows=8", "save_every=0",
            "lr=1e-3", "task.n_train=64", "task.n_eval=16", "run.quiet=true", "run.threads=1", *extra]


def _steps(out: Path) -> list[dict]:
    rows = [json.loads(x) for x in (out / "tiny-calc" / "grpo" / "metrics.jsonl").read_text().splitlines()]
    return [r for r in rows if "reward/mean" in r]


def test_episodes_train_end_to_end_with_the_trainers_log_probs_equal_to_the_samplers(chat_sft, tmp_path, capsys):
    out = tmp_path / "run"
    assert main(_args(chat_sft, out, "old_logprobs=recompute", "zero_variance=keep", "save_rollouts_every=1")) == 0
    steps = _steps(out)
    assert [s["step"] for s in steps] == [1, 2]
    for s in steps:
        assert s["env/turns"] >= 1 and s["env/tool_calls"] > 0 and s["env/env_tokens"] > 0
        assert s["mismatch/kl"] == pytest.approx(0.0, abs=1e-6)  # pi_old recomputed on the whole trajectories
        assert s["mismatch/max_ratio"] == pytest.approx(1.0, abs=1e-4)
    saved = sorted((out / "tiny-calc" / "grpo" / "rollouts").glob("*.jsonl"))
    assert saved
    from posttrain.rollout import load_rollouts

    rs = load_rollouts(saved[0])
    multi = [r for r in rs if len(r.extras["episode"]["turns"]) > 1]
    assert multi and all(0 in r.completion_mask for r in multi)  # environment tokens, masked out of the loss
    assert all(len(r.completion_ids) == len(r.completion_mask) for r in rs)
    capsys.readouterr()
    assert main(["rollouts", str(out / "tiny-calc" / "grpo"), "--step", "2"]) == 0  # the turns, readably
    shown = capsys.readouterr().out
    assert "episode:" in shown and "[assistant 1]" in shown and "[tool] add(a=" in shown
    report = json.loads((out / "tiny-calc" / "grpo" / "eval.json").read_text())
    assert "eval/env/turns" in report["grpo"] and "<|tool|>" in report["samples"][0]["completion"] \
        or report["grpo"]["eval/env/turns"] == 1.0  # a sample shows the tool turn when the episode had one


@pytest.mark.learning
def test_grpo_learns_the_environments_reward(chat_sft, tmp_path, learning):
    """Turns: reward 1 for two or more turns, i.e. for ending a turn at eos within 12 tokens; a random model does so
    rarely. Margin over seeds and thread counts: scripts/test_margins.py (docs/results-archive.md, "Test margins")."""
    out = tmp_path / "learn"
    assert main(_args(chat_sft, out, "max_steps=10", "prompts_per_step=8", "group_size=8", "lr=1e-3",
                      "log_every=1", *learning.overrides)) == 0
    r = [s["reward/mean"] for s in _steps(out)]
    assert len(r) == 10
    # step 1's samples come from the model before any update; the policy learns within a few steps
    # (each seed's random model starts elsewhere, so the bound is on the share of the room to 1 that was closed)
    learning.above("Turns reward, share of (1 - step 1) gained by the last 5 steps",
                   (sum(r[-5:]) / 5 - r[0]) / max(1 - r[0], 1e-9), 0.5, r)


def test_lora_and_resume_in_an_environment(chat_sft, tmp_path):
    from safetensors.torch import load_file

    full, cut = tmp_path / "full", tmp_path / "cut"
    common = ("max_steps=3", "lora.enabled=true", "zero_variance=keep")
    assert main(_args(chat_sft, full, *common)) == 0
    assert main(_args(chat_sft, cut, *common[1:], "max_steps=2", "save_every=2")) == 0
    assert main(_args(chat_sft, cut, *common, "resume=true")) == 0
    a = load_file(full / "tiny-calc" / "grpo" / "final" / "model.safetensors")
    b = load_file(cut / "tiny-calc" / "grpo" / "final" / "model.safetensors")
    assert all(torch.allclose(a[k], b[k], atol=1e-5) for k in a)
    assert [s["reward/mean"] for s in _steps(full)] == pytest.approx([s["reward/mean"] for s in _steps(cut)])


def test_bad_environment_settings_are_one_line_errors(chat_sft, tmp_path, capsys):
    assert main(_args(chat_sft, tmp_path / "a", "env=nope")) == 2
    assert "grpo.env: unknown environment 'nope'; available: calc" in capsys.readouterr().err
    assert main(_args(chat_sft, tmp_path / "b", "env=calc", "reward_model=train")) == 2
    assert "rewards whole episodes itself" in capsys.readouterr().err
    assert main(_args(chat_sft, tmp_path / "c", "env=calc", "env_options={max_turns: 0}")) == 2
    assert "Limits.max_turns must be a positive integer" in capsys.readouterr().err
    assert main(_args(chat_sft, tmp_path / "d", "env=calc-words", "env_options={partial_credit: 1.5}")) == 2
    assert "grpo.env: calc-words partial_credit must be in [0, 1), got 1.5" in capsys.readouterr().err


def test_posttrain_envs_lists_the_built_ins(capsys):
    assert main(["envs"]) == 0
    out = capsys.readouterr().out
    for name in ("calc", "lookup"):
        assert re.search(rf"^{name}\s+built-in", out, re.M), out
    assert "file.py:Name" in out


def test_the_readmes_environment_trains_without_touching_the_package(chat_sft, tmp_path):
    """README.md's 'Your own environment, in one file' example, as written there, trains with posttrain grpo."""
    readme = (Path(__file__).resolve().parents[3] / "README.md").read_text()
    block = readme[readme.index("```python\n# capitals.py"):]
    code = block[len("```python\n"):block.index("\n```")]
    assert len(code.splitlines()) <= 35
    (tmp_path / "capitals.py").write_text(code)
    rows = [{"prompt": f"Capital of {c}?", "answer": a} for c, a in
            {"Varnok": "Ilsa", "Zelpha": "Orun", "Quillo": "Metz"}.items()] * 4
    data = tmp_path / "capitals.jsonl"
    data.write_text("".join(json.dumps(r) + "\n" for r in rows))
    out = tmp_path / "run"
    args = [a for a in _args(chat_sft, out) if not a.startswith("env=")]
    assert main(args + [f"env={tmp_path / 'capitals.py'}:Capitals", f"grpo.train_file={data}",
                        f"grpo.eval_file={data}"]) == 0
    steps = _steps(out)
    assert len(steps) == 2 and all("env/turns" in s for s in steps)
