"""Two CPU processes through `accelerate launch` (gloo) give the loss curve of one process at the same
global batch: the data is sharded by rank (loop.batch_indices), gradients are averaged by DDP, the
token mean is taken over the global batch, and the logged loss is reduced over processes. Every run here is on
the CPU, also on a GPU machine (CUDA_VISIBLE_DEVICES="" in the runs' environment: two processes on one GPU would
share a device, and the one-process run would not be the same computation)."""
from __future__ import annotations

import json
import os
import subprocess
import sys
from pathlib import Path

import pytest

from posttrain.runtime import probe_decides_bf16

ARGS = ["--recipe", "tiny-summarize", "run.threads=1", "max_steps=6", "batch_size=8", "log_every=1", "eval_every=0",
        "num_samples=0", "final_eval_rows=0", "save_every=0", "task.n_train=200", "task.n_eval=20", "lr=3e-3",
        "warmup_steps=2"]


def _run(cmd: list[str], cwd: Path) -> str:
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", "CUDA_VISIBLE_DEVICES": ""}  # CPU runs
    r = subprocess.run(cmd, cwd=cwd, env=env, capture_output=True, text=True, timeout=600)
    assert r.returncode == 0, f"{' '.join(cmd)} failed:\n{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
    return r.stdout


# `python -m accelerate.commands.launch ...` for two CPU processes, and the one- and two-process runs of a command
TWO_PROCESSES = ["-m", "accelerate.commands.launch", "--multi_gpu", "--num_processes", "2", "--num_machines", "1",
                 "--mixed_precision", "no", "--dynamo_backend", "no"]
LAUNCHES = (("one", []), ("two", TWO_PROCESSES))
ENVS_FILE = Path(__file__).resolve().parent / "envs_for_tests.py"


def _env_runs(tmp_path: Path, tiny_lm, stage: str, args: list[str], key: str) -> tuple[list[dict], list[dict]]:
    """The metrics rows holding `key` of `posttrain <stage> *args` on tiny-calc episodes, run as 1 and as 2
    processes, both from one random chat 'SFT model' whose eos is likely enough that some turns end early
    (envs_for_tests.eos_pulled_copy)."""
    import importlib.util
    import shutil

    spec = importlib.util.spec_from_file_location("envs_for_tests", ENVS_FILE)
    envs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(envs)
    sft = envs.eos_pulled_copy(tiny_lm("tiny-calc", vocab_size=320, max_length=256, split_digits=True, chat=True),
                               tmp_path / "sft")
    runs = {}
    for name, launch in LAUNCHES:
        out = tmp_path / name
        shutil.copytree(sft, out / "tiny-calc" / "sft" / "final")
        text = _run([sys.executable, *launch, "-m", "posttrain", stage, *args, f"run.output_dir={out}"], tmp_path)
        assert f"{1 if name == 'one' else 2} process(es)" in text
        rows = [json.loads(l) for l in (out / "tiny-calc" / stage / "metrics.jsonl").read_text().splitlines()]
        runs[name] = [r for r in rows if key in r]
    return runs["one"], runs["two"]


def _losses(run_dir: Path) -> list[float]:
    rows = [json.loads(l) for l in (run_dir / "metrics.jsonl").read_text().splitlines()]
    return [r["loss"] for r in rows if "loss" in r]


def _assert_same_weights(w1: dict, w2: dict, start: dict, rel: float = 1e-3) -> None:
    """The final weights of two runs that differ only by float summation order: the norm of their difference is
    a small fraction of how far training moved them. Not a per-element bound: Adam divides each gradient by its
    own root mean square, so an element whose gradient is at the level of the summation noise moves by up to
    the learning rate in either direction (a CI run saw one element 1.05e-4 apart with lr 1e-3
    while the rest agreed to 3e-5); the norm carries such elements at their weight."""
    assert sorted(w1) == sorted(w2) and set(w1) <= set(start)
    diff = sum(float((w1[k] - w2[k]).double().pow(2).sum()) for k in w1) ** 0.5
    moved = sum(float((w1[k] - start[k]).double().pow(2).sum()) for k in w1) ** 0.5
    worst = max(float((w1[k] - w2[k]).abs().max()) for k in w1)
    assert moved > 0 and diff <= rel * moved, f"|w1 - w2| = {diff:.3g} vs moved {moved:.3g} (max element {worst:.3g})"


@pytest.mark.slow
def test_two_processes_match_one_process_loss_curve(tmp_path):
    out = tmp_path / "runs"
    one = _run([sys.executable, "-m", "posttrain", "sft", *ARGS, f"run.output_dir={out}"], tmp_path)
    assert "1 process(es)" in one
    two = _run([sys.executable, *TWO_PROCESSES, "-m", "posttrain", "sft", *ARGS, f"run.output_dir={out}"], tmp_path)
    assert "2 process(es)" in two, two[-2000:]
    single = _losses(out / "tiny-summarize" / "sft.prev")
    double = _losses(out / "tiny-summarize" / "sft")
    assert len(single) == len(double) == 6
    # Same global batch, same data, same init: equal up to float summation order (gloo all-reduce,
    # two half-batch forwards). Stated tolerance: 1e-4 relative.
    for a, b in zip(single, double):
        assert abs(a - b) <= 1e-4 * abs(a), (single, double)
    assert single[-1] < single[0]  # it trained


@pytest.mark.slow
def test_dpo_recipe_chain_runs_under_two_processes(tmp_path):
    """The README's command: `accelerate launch --config_file recipes/launch/cpu-2proc.yaml -m posttrain dpo
    --recipe tiny-summarize ...` builds base (process 0; the other waits), SFT, pairs (sampled by shards),
    the reward model and DPO with two processes, and writes each stage's output once. With
    run.mixed_precision=auto, where a probe decides (a CPU that lists bf16 units), process 0's bf16 probe decides for both
    (loop.share_bf16_probe: a broadcast over the real process group)."""
    out = tmp_path / "runs"
    config = Path(__file__).resolve().parents[2] / "recipes" / "launch" / "cpu-2proc.yaml"
    text = _run([sys.executable, "-m", "accelerate.commands.launch", "--config_file", str(config),
                 "-m", "posttrain", "dpo", "--recipe", "tiny-summarize", f"run.output_dir={out}", "run.threads=1",
                 "run.mixed_precision=auto",
                 "sft.max_steps=20", "sft.eval_every=0", "sft.final_eval_rows=0", "sft.num_samples=0",
                 "task.n_train=300", "prefs.n_prompts=32", "prefs.n_eval_prompts=16", "rm.max_steps=3",
                 "max_steps=4", "online=false", "eval_every=0", "final_eval_rows=8", "batch_size=8"], tmp_path)
    assert "2 process(es)" in text
    assert "gold win-rate of the DPO model against the SFT model" in text
    if probe_decides_bf16():
        assert "run.mixed_precision=auto: bf16 matmuls measured" in text, text[-2000:]
    for stage in ("sft", "rm", "dpo"):
        assert (out / "tiny-summarize" / stage / "final" / "config.json").is_file()
    assert (out / "tiny-summarize" / "prefs" / "final" / "train.jsonl").is_file()


PPO_ARGS = ["--recipe", "tiny-summarize", "run.threads=1", "reward=rm", "value_init=reward", "rollout_batch_size=8",
            "minibatch_size=4", "ppo_epochs=2", "max_steps=3", "max_new_tokens=8", "reward_norm=init",
            "reward_norm_prompts=6", "kl_control=adaptive", "kl_target=0.01", "kl_horizon=16", "eval_every=0",
            "final_eval_rows=4", "save_every=3", "lr=1e-3", "value_lr=1e-3", "task.n_train=64", "task.n_eval=16"]


@pytest.mark.slow
def test_ppo_two_processes_match_one_process(tmp_path, tiny_lm, tiny_rm):
    """PPO under 2 processes == 1 process at the same global rollout batch and seed. Rollouts are sharded by
    prompt key (counter-based sampling), so they are the same samples: lengths, EOS counts and clip counts
    equal exactly. Reward normalisation (init), the adaptive KL coefficient, advantage whitening and the
    losses are global; they differ only by float summation order (half-batch forwards, gloo all-reduce of
    the gradients) and how Adam carries that through 12 updates. Measured: <= 3e-5 relative on every
    logged number; the final weights' difference 1.4e-5 of their movement from SFT in norm (largest element
    2.1e-5). Stated tolerance: 1e-4 relative (+1e-6 absolute), 1e-3 of the movement on the weights."""
    import shutil

    from safetensors.torch import load_file

    world = {"sft": tiny_lm("tiny-summarize"), "rm": tiny_rm("tiny-summarize")}  # the world of trainers/test_ppo.py
    runs = {}
    for name, launch in LAUNCHES:
        out = tmp_path / name
        (out / "tiny-summarize" / "sft").mkdir(parents=True)
        shutil.copytree(world["sft"], out / "tiny-summarize" / "sft" / "final")  # never runs SFT
        cmd = [sys.executable, *launch, "-m", "posttrain", "ppo", *PPO_ARGS, f"reward_model={world['rm']}",
               f"run.output_dir={out}"]
        text = _run(cmd, tmp_path)
        assert f"{1 if name == 'one' else 2} process(es)" in text
        assert text.count("gold win-rate of the PPO model against the SFT model") == 1  # the main process's eval
        run = out / "tiny-summarize" / "ppo"
        assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["step-000003"]  # written once, atomic
        runs[name] = ([json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()],
                      load_file(run / "final" / "model.safetensors"))
    (one, w1), (two, w2) = runs["one"], runs["two"]
    start = load_file(world["sft"] / "model.safetensors")
    assert [r["step"] for r in one] == [r["step"] for r in two] == [1, 2, 3]
    for a, b in zip(one, two):
        for k in ("rollout/length", "rollout/no_eos", "policy/lr"):  # the same samples
            assert a[k] == b[k], (k, a[k], b[k])
        for k in ("policy/clip_frac", "value/value_clip_frac"):  # the same counts (one token would be >= 1/64)
            assert a[k] == pytest.approx(b[k], rel=1e-6, abs=1e-9), (k, a[k], b[k])
        for k in ("rollout/score_raw", "rollout/score", "rollout/kl", "kl_coef", "rollout/returns", "policy/loss",
                  "policy/approx_kl", "policy/entropy", "policy/ratio_max", "policy/grad_norm", "value/loss",
                  "value/explained_variance", "value/value_mean", "value/grad_norm"):
            assert a[k] == pytest.approx(b[k], rel=1e-4, abs=1e-6), (k, a[k], b[k])
    assert one[-1]["kl_coef"] != one[0]["kl_coef"]  # the adaptive controller moved, in step on both processes
    _assert_same_weights(w1, w2, start)


COIN = '''import zlib


def coin(completion, reference):
    """A deterministic 0/1 reward of the text: about a fifth of the groups of 4 get equal rewards."""
    return 1.0 if zlib.crc32(completion.encode()) % 3 == 0 else 0.0
'''


@pytest.mark.slow
def test_grpo_two_processes_match_one_process(tmp_path, tiny_lm):
    """GRPO under 2 processes == 1 process at the same global batch and seed. P = 3 prompts (split 2 + 1), each
    group of K = 4 whole on one process; then gathered, so dynamic sampling's resample decision, the
    zero-variance filter, REINFORCE++'s batch normalisation and the metrics are global; the reference log-probs
    are computed in shards and gathered; each minibatch (2 per pass, 2 passes) is split over the processes with
    DAPO's token mean over the whole minibatch; micro_batch_size=2 leaves one process a zero-weight padding
    micro-batch. Same samples, rewards, lengths and resample rounds exactly; losses, KL, clip fractions,
    entropy and gradient norms differ only by float summation order. Measured: <= 1e-6 relative on every
    logged number; the final weights' difference 2.7e-5 of their movement in norm (largest element 3e-5 to
    1.05e-4 across machines). Stated tolerance: 1e-4 relative (+1e-6 absolute), 1e-3 of the movement on the
    weights. (The code before this test: half the rows per step, local batch
    statistics; its curves differ at the first step.)"""
    import shutil

    from safetensors.torch import load_file

    sft = tiny_lm("tiny-countdown", vocab_size=256, max_length=128, split_digits=True)
    (tmp_path / "coin.py").write_text(COIN)
    args = ["--recipe", "tiny-countdown", "run.threads=1", f"verifier={tmp_path / 'coin.py'}:coin",
            "verifier_workers=0", "prompts_per_step=3", "group_size=4", "max_new_tokens=12", "max_steps=3",
            "estimator=reinforce_pp", "std_scale=batch", "aggregation=token_mean", "beta=0.04", "mu=2",
            "minibatches=2", "micro_batch_size=2", "zero_variance=resample", "max_resample_rounds=2", "lr=1e-3",
            "eval_every=0", "eval_rows=4", "final_eval_rows=4", "save_every=3", "task.n_train=64", "task.n_eval=16"]
    runs = {}
    for name, launch in LAUNCHES:
        out = tmp_path / name
        shutil.copytree(sft, out / "tiny-countdown" / "sft" / "final")  # never runs SFT
        text = _run([sys.executable, *launch, "-m", "posttrain", "grpo", *args, f"run.output_dir={out}"], tmp_path)
        assert f"{1 if name == 'one' else 2} process(es)" in text
        assert text.count("[grpo] SFT model, greedy") == text.count("held-out greedy accuracy") == 1  # main only
        run = out / "tiny-countdown" / "grpo"
        assert sorted(p.name for p in (run / "checkpoints").iterdir()) == ["step-000003"]  # written once, atomic
        rows = [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()]
        runs[name] = ([r for r in rows if "reward/mean" in r], load_file(run / "final" / "model.safetensors"))
    (one, w1), (two, w2) = runs["one"], runs["two"]
    start = load_file(sft / "model.safetensors")
    assert [r["step"] for r in one] == [r["step"] for r in two] == [1, 2, 3]
    assert any(r.get("resample/rounds", 1) > 1 for r in one) and all(r["rows/trained"] > 0 for r in one)
    for a, b in zip(one, two):
        for k in ("reward/mean", "reward/std", "zero_var_frac", "completion/length", "completion/truncated",
                  "rows/trained", "updates", "verifier/scored", "lr"):  # the same samples, scores and batches
            assert a[k] == b[k], (k, a[k], b[k])
        assert a.get("resample/rounds") == b.get("resample/rounds")
        for k in ("loss", "policy_loss", "kl", "approx_kl", "clip_frac", "ratio_mean", "ratio_max", "entropy",
                  "grad_norm"):
            assert a[k] == pytest.approx(b[k], rel=1e-4, abs=1e-6), (k, a[k], b[k])
    _assert_same_weights(w1, w2, start)


@pytest.mark.slow
def test_grpo_in_an_environment_two_processes_match_one_process(tmp_path, tiny_lm):
    """Multi-turn episodes (grpo.env) under 2 processes == 1 process: each process runs its groups' episodes (a row's
    episode depends only on its key and sample index), then the groups are gathered; the same rewards, turns and
    environment tokens exactly, the losses within float summation order."""
    args = ["--recipe", "tiny-calc", "run.threads=1", f"env={ENVS_FILE}:Turns", "prompts_per_step=2", "group_size=4",
            "max_steps=2", "zero_variance=keep", "lr=1e-3", "eval_every=0", "eval_rows=4", "final_eval_rows=4",
            "save_every=0", "task.n_train=32", "task.n_eval=8"]
    one, two = _env_runs(tmp_path, tiny_lm, "grpo", args, "reward/mean")
    assert [r["step"] for r in one] == [r["step"] for r in two] == [1, 2]
    for a, b in zip(one, two):
        for k in ("reward/mean", "env/turns", "env/tool_calls", "env/env_tokens", "env/sampled_tokens"):
            assert a[k] == b[k], (k, a[k], b[k])
        for k in ("loss", "grad_norm"):
            assert a[k] == pytest.approx(b[k], rel=1e-4, abs=1e-6), (k, a[k], b[k])


@pytest.mark.slow
def test_ppo_in_an_environment_two_processes_match_one_process(tmp_path, tiny_lm):
    """PPO on multi-turn episodes (ppo.env, detail 20) under 2 processes == 1 process: each process runs its rows'
    episodes (a row's episode depends only on its key and the iteration's seed), then the rollouts are gathered;
    the same rewards, turns and environment tokens exactly; the losses, KL and gradient norms within float
    summation order (stated tolerance 1e-4 relative, as the single-turn PPO test's)."""
    args = ["--recipe", "tiny-calc", "run.threads=1", f"env={ENVS_FILE}:Turns", "reward=env", "value_init=policy",
            "reward_norm=none", "rollout_batch_size=8", "minibatch_size=4", "ppo_epochs=1", "max_steps=2",
            "lr=1e-3", "value_lr=1e-3", "eval_every=0", "eval_rows=0", "final_eval_rows=0", "save_every=0",
            "task.n_train=32", "task.n_eval=8"]
    one, two = _env_runs(tmp_path, tiny_lm, "ppo", args, "rollout/score_raw")
    assert [r["step"] for r in one] == [r["step"] for r in two] == [1, 2]
    assert any(r["env/env_tokens"] > 0 for r in one)
    for a, b in zip(one, two):
        for k in ("rollout/score_raw", "rollout/length", "env/turns", "env/tool_calls", "env/env_tokens",
                  "env/sampled_tokens"):
            assert a[k] == b[k], (k, a[k], b[k])
        for k in ("rollout/kl", "rollout/returns", "policy/loss", "policy/grad_norm", "value/loss", "value/grad_norm"):
            assert a[k] == pytest.approx(b[k], rel=1e-4, abs=1e-6), (k, a[k], b[k])


@pytest.mark.slow
def test_distill_two_processes_match_one_process(tmp_path, tiny_lm):
    """On-policy distillation under 2 processes == 1 process at the same global batch and seed: P = 3 prompts
    (split 2 + 1) x K = 2 samples, the groups gathered, the step's token mean split over the processes by
    `sharding.micro_batches` (micro_batch_size=1: one process gets a zero-weight padding micro-batch), a small
    teacher of the same tokenizer on every process. Same samples exactly; losses, KLs and gradient norms differ
    only by float summation order (stated tolerance 1e-4 relative); the final weights' difference 7.6e-6 of
    their movement in norm (stated tolerance 1e-3)."""
    import shutil

    from safetensors.torch import load_file

    from posttrain.models import build_model, load_tokenizer, save_model

    sft = tiny_lm("tiny-countdown", vocab_size=256, max_length=128, split_digits=True)
    teacher = save_model(build_model("small", load_tokenizer(sft), seed=7), load_tokenizer(sft), tmp_path / "teacher")
    args = ["--recipe", "tiny-countdown", "run.threads=1", f"teacher={teacher}", "verifier_workers=0",
            "prompts_per_step=3", "group_size=2", "max_new_tokens=12", "max_steps=3", "micro_batch_size=1", "lr=1e-3",
            "eval_every=0", "eval_rows=4", "final_eval_rows=4", "save_every=3", "task.n_train=64", "task.n_eval=16"]
    runs = {}
    for name, launch in LAUNCHES:
        out = tmp_path / name
        shutil.copytree(sft, out / "tiny-countdown" / "sft" / "final")  # never runs SFT
        text = _run([sys.executable, *launch, "-m", "posttrain", "distill", *args, f"run.output_dir={out}"], tmp_path)
        assert f"{1 if name == 'one' else 2} process(es)" in text
        assert text.count("[distill] held-out greedy accuracy on") == 1  # the main process's only
        run = out / "tiny-countdown" / "distill"
        rows = [json.loads(l) for l in (run / "metrics.jsonl").read_text().splitlines()]
        runs[name] = ([r for r in rows if "kl/reverse" in r], load_file(run / "final" / "model.safetensors"))
    (one, w1), (two, w2) = runs["one"], runs["two"]
    start = load_file(sft / "model.safetensors")
    assert [r["step"] for r in one] == [r["step"] for r in two] == [1, 2, 3]
    for a, b in zip(one, two):
        for k in ("completion/length", "completion/truncated", "tokens/generated", "reward/mean", "lr"):
            assert a[k] == b[k], (k, a[k], b[k])  # the same samples and scores
        for k in ("loss", "kl/reverse", "kl/forward", "nll", "grad_norm"):
            assert a[k] == pytest.approx(b[k], rel=1e-4, abs=1e-6), (k, a[k], b[k])
    _assert_same_weights(w1, w2, start)
