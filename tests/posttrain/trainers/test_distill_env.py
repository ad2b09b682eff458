"""On-policy distillation in a multi-turn environment (distill.env): the student samples episodes, the teacher scores
whole trajectories, every per-token loss covers the sampled tokens only (a hand check against completion_mask), the
loss's log-probs equal the sampler's on multi-turn trajectories, the student moves toward the teacher, the teacher
plays its own episodes under student_fraction=0, LoRA and resume work, two processes match one, and bad settings
are one-line errors."""
import importlib.util
import json
import shutil
from pathlib import Path

import pytest
import torch

from posttrain.cli import main

ENVS = Path(__file__).resolve().parent.parent / "envs_for_tests.py"


def _envs():
    spec = importlib.util.spec_from_file_location("envs_for_tests", ENVS)
    envs = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(envs)
    return envs


@pytest.fixture(scope="module")
def student(tiny_lm, tmp_path_factory):
    """A random tiny chat model on tiny-calc text whose eos is likely enough that some turns end early (so episodes
    have several turns and environment tokens): the 'SFT model' the stage starts from (as in test_grpo_env)."""
    src = tiny_lm("tiny-calc", vocab_size=320, max_length=256, split_digits=True, chat=True)
    return _envs().eos_pulled_copy(src, tmp_path_factory.mktemp("chat-student") / "model")


@pytest.fixture(scope="module")
def teacher(student, tmp_path_factory):
    """Another random init of the same shape and chat tokenizer, its final norm x 6: peaked next-token distributions
    far from the student's (test_distill's sharp teacher)."""
    from posttrain.models import build_model, load_tokenizer, save_model

    tok = load_tokenizer(student)
    model = build_model("tiny", tok, seed=123)
    with torch.no_grad():
        model.model.norm.weight.mul_(6.0)
    return save_model(model, tok, tmp_path_factory.mktemp("chat-teacher") / "model")


def _args(student: Path, out: Path, teacher: Path, *extra: str) -> list[str]:
    sft = out / "tiny-calc" / "sft" / "final"
    if not sft.exists():
        sft.parent.mkdir(parents=True, exist_ok=True)
        shutil.copytree(student, sft)  # the stage finds its "SFT model" and never runs SFT
    return ["distill", "--recipe", "tiny-calc", f"run.output_dir={out}", f"teacher={teacher}", f"env={ENVS}:Turns",
            "prompts_per_step=4", "group_size=2", "max_steps=2", "eval_every=0", "eval_rows=4", "final_eval_rows=4",
            "save_every=0", "lr=1e-3", "task.n_train=32", "task.n_eval=8", "run.quiet=true", "run.threads=1", *extra]


def _steps(out: Path) -> list[dict]:
    rows = [json.loads(x) for x in (out / "tiny-calc" / "distill" / "metrics.jsonl").read_text().splitlines()]
    return [r for r in rows if "kl/reverse" in r]


def test_episodes_distill_end_to_end_on_sampled_tokens_with_the_samplers_log_probs(student, teacher, tmp_path):
    """Two on-policy steps in the Turns environment with the environment's reward term: the loss tokens are the
    sampled ones (tokens/trained = the episodes' sampled tokens; the rest are the environment's), the loss's
    log-probs of them equal the sampler's (fp32 engine), the held-out comparison runs greedy episodes of the SFT
    model, the student and the teacher."""
    out = tmp_path / "run"
    assert main(_args(student, out, teacher, "reward_weight=0.5")) == 0
    steps = _steps(out)
    assert [s["step"] for s in steps] == [1, 2]
    n = 4 * 2
    assert sum(s["env/env_tokens"] for s in steps) > 0 and max(s["env/turns"] for s in steps) > 1
    for s in steps:
        assert s["samples/student"] == 1.0 and "pg_loss" in s and "reward/mean" in s
        assert s["tokens/trained"] == pytest.approx(s["env/sampled_tokens"] * n)
        assert s["tokens/generated"] - s["tokens/trained"] == pytest.approx(s["env/env_tokens"] * n)
        assert s["mismatch/kl"] == pytest.approx(0.0, abs=1e-6)  # the loss's student log-probs are the sampler's
        assert s["mismatch/max_ratio"] == pytest.approx(1.0, abs=1e-4)
        assert s["mismatch/min_ratio"] == pytest.approx(1.0, abs=1e-4)
    report = json.loads((out / "tiny-calc" / "distill" / "eval.json").read_text())
    for who in ("sft", "distill", "teacher"):
        assert "eval/env/turns" in report[who] and "eval/accuracy" in report[who], who


def test_every_loss_covers_the_sampled_tokens_only_by_hand(student, teacher):
    """`distill_loss` on a batch of episodes against a hand computation: each row's whole trajectory (prompt,
    sampled and environment tokens) through both models unpadded, the per-token loss at each position whose
    Rollout.completion_mask is 1, one mean over them. Counting the environment tokens too gives another value:
    the mask is what selects them out."""
    from posttrain.models import load_model, load_tokenizer
    from posttrain.rollout import SamplingParams, collate_rollouts
    from posttrain.rollout.multiturn import generate_episodes
    from posttrain.trainers.distill import DistillConfig, distill_loss

    envs = _envs()
    tok, s_model, t_model = load_tokenizer(student), load_model(student), load_model(teacher).eval()
    env = envs.Turns()
    problems = [{"prompt": f"What is {a} * {b}?", "answer": str(a * b)} for a, b in ((12, 34), (56, 78), (9, 87))]
    rollouts = generate_episodes(s_model, tok, env, problems, SamplingParams(n=2, temperature=1.0, seed=3))
    assert any(0 in r.completion_mask[r.completion_mask.index(1):] for r in rollouts)  # environment tokens inside
    batch = collate_rollouts(rollouts, tok.pad_token_id)
    rows = {"input_ids": batch.input_ids, "attention_mask": batch.attention_mask,
            "loss_mask": batch.completion_mask, "sampler_logps": batch.policy_logprobs}
    for loss, T in (("reverse_kl", 1.0), ("forward_kl", 1.0), ("jsd", 1.0), ("nll", 1.0), ("reverse_kl", 0.7)):
        cfg = DistillConfig(loss=loss, temperature=T, jsd_beta=0.3)
        with torch.no_grad():
            value, m = distill_loss(cfg, s_model, t_model, len(tok), False, 1, (rows, 1.0, 1.0))
        sampled, every = [], []
        for r in rollouts:
            ids = torch.tensor([r.prompt_ids + r.completion_ids])
            with torch.no_grad():
                ls = torch.log_softmax(s_model(input_ids=ids).logits[0].float() / T, -1)  # (L, V)
                lt = torch.log_softmax(t_model(input_ids=ids).logits[0].float() / T, -1)  # (L, V)
            for j, (token, sampled_token) in enumerate(zip(r.completion_ids, r.completion_mask)):
                s, t = ls[len(r.prompt_ids) + j - 1], lt[len(r.prompt_ids) + j - 1]  # the distribution of token j
                if loss == "reverse_kl":
                    x = (s.exp() * (s - t)).sum()
                elif loss == "forward_kl":
                    x = (t.exp() * (t - s)).sum()
                elif loss == "jsd":  # GKD eq. 1: 0.3 KL(P || M) + 0.7 KL(S || M), M = 0.3 P + 0.7 S
                    mix = torch.logaddexp(t + torch.log(torch.tensor(0.3)), s + torch.log(torch.tensor(0.7)))
                    x = 0.3 * (t.exp() * (t - mix)).sum() + 0.7 * (s.exp() * (s - mix)).sum()
                else:
                    x = -s[token]
                every.append(float(x))
                if sampled_token:
                    sampled.append(float(x))
        hand = sum(sampled) / len(sampled)
        assert float(value) == pytest.approx(hand, rel=1e-4, abs=1e-6), loss
        assert abs(sum(every) / len(every) - hand) > 1e-3 * hand, loss  # the environment tokens would change it
        if T == 1.0:  # the sampler's log-probs (temperature 1) are the loss's own
            assert m["mismatch/kl"] == pytest.approx(0.0, abs=1e-6)
            assert m["mismatch/max_ratio"] == pytest.approx(1.0, abs=1e-4)
        if loss in ("reverse_kl", "forward_kl") and T == 1.0:  # the metric of the loss's own kind is the loss
            assert m[f"kl/{loss.split('_')[0]}"] == pytest.approx(float(value), rel=1e-6)
    # the teacher runs in the run's precision (the accelerator's autocast): bf16 moves its logits by bf16 rounding
    cfg = DistillConfig(loss="reverse_kl")
    with torch.no_grad():
        v32, _ = distill_loss(cfg, s_model, t_model, len(tok), False, 1, (rows, 1.0, 1.0))
        v16, _ = distill_loss(cfg, s_model, t_model, len(tok), False, 1, (rows, 1.0, 1.0),
                              teacher_autocast=lambda: torch.autocast("cpu", dtype=torch.bfloat16))
    assert float(v16) != float(v32) and float(v16) == pytest.approx(float(v32), rel=0.1, abs=0.02)


@pytest.mark.learning
def test_the_students_reverse_kl_to_the_teacher_falls_in_episodes(student, teacher, tmp_path, learning):
    """The sharp teacher rarely ends a turn; the student's episodes start with tool turns. Bound 1.3 on the first 3
    / last 3 steps' reverse KL: measured 1.56-1.91 (median 1.70) over seeds 0-5 x 1 and 2 threads (the same value
    at both thread counts; `scripts/test_margins.py --seeds 0 1 2 3 4 5 -k reverse_kl_to_the_teacher_falls`, on
    the tree after edabc40): the worst value is 1.2x the bound."""
    out = tmp_path / "learn"
    assert main(_args(student, out, teacher, "max_steps=12", "final_eval_rows=0", "eval_rows=0",
                      *learning.overrides)) == 0
    steps = _steps(out)
    kl = [s["kl/reverse"] for s in steps]
    assert len(kl) == 12 and all(k > 0 for k in kl)
    assert steps[0]["env/env_tokens"] > 0  # the student's first episodes have tool turns
    learning.above("reverse KL on sampled tokens, first 3 / last 3 steps", (sum(kl[:3]) / 3) / (sum(kl[-3:]) / 3),
                   1.3, kl)


def test_the_teacher_plays_its_own_episodes_under_student_fraction_zero(student, teacher, tmp_path):
    out = tmp_path / "seqkd"
    assert main(_args(student, out, teacher, "student_fraction=0", "loss=nll", "final_eval_rows=0",
                      "eval_rows=0")) == 0
    for s in _steps(out):
        assert s["samples/student"] == 0.0 and "env/turns" in s and "mismatch/kl" not in s  # not the student's
        assert s["loss"] == pytest.approx(s["nll"], rel=1e-5)
        assert s["tokens/trained"] == pytest.approx(s["env/sampled_tokens"] * 8)


def test_lora_and_resume_in_an_environment(student, teacher, tmp_path):
    from safetensors.torch import load_file

    full, cut = tmp_path / "full", tmp_path / "cut"
    common = ("max_steps=3", "lora.enabled=true", "lora.r=4", "final_eval_rows=0", "eval_rows=0")
    assert main(_args(student, full, teacher, *common)) == 0
    assert main(_args(student, cut, teacher, *common[1:], "max_steps=2", "save_every=2")) == 0
    assert main(_args(student, cut, teacher, *common, "resume=true")) == 0
    a = load_file(full / "tiny-calc" / "distill" / "final" / "model.safetensors")
    b = load_file(cut / "tiny-calc" / "distill" / "final" / "model.safetensors")
    assert sorted(a) == sorted(b) and all(torch.allclose(a[k], b[k], atol=1e-5) for k in a)
    assert [s["step"] for s in _steps(cut)] == [1, 2, 3]
    assert [s["kl/reverse"] for s in _steps(full)] == pytest.approx([s["kl/reverse"] for s in _steps(cut)])
    assert [s["env/env_tokens"] for s in _steps(full)] == [s["env/env_tokens"] for s in _steps(cut)]


@pytest.mark.parametrize("extra, message", [
    (["env=nope"], "distill.env: unknown environment 'nope'; available: calc"),
    (["env=calc", "verifier=math"], "distill.verifier='math': env='calc' rewards whole episodes itself"),
    (["env=calc", "env_options={max_turns: 0}"], "Limits.max_turns must be a positive integer"),
    (["reward_weight=1", "group_size=1"], "distill.reward_weight > 0 needs group_size >= 2"),
])
def test_bad_environment_settings_are_one_line_errors(student, teacher, tmp_path, capsys, extra, message):
    assert main(_args(student, tmp_path / "bad", teacher, *extra)) == 2
    err = capsys.readouterr().err
    assert message in err and len(err.strip().splitlines()) == 1, err
    assert not (tmp_path / "bad" / "tiny-calc" / "distill").exists()  # stopped before the run directory changed


@pytest.mark.slow
def test_distill_in_an_environment_two_processes_match_one_process(student, teacher, tmp_path):
    """Episodes under 2 processes == 1 process (each process plays its groups' episodes; a row's episode depends on
    its key and sample index only), then the step's token mean split over the processes: the same episodes
    exactly, losses and KLs within float summation order (as test_distributed's distill and GRPO-env tests)."""
    import os
    import subprocess
    import sys

    args = ["--recipe", "tiny-calc", "run.threads=1", f"teacher={teacher}", f"env={ENVS}:Turns", "prompts_per_step=3",
            "group_size=2", "max_steps=2", "micro_batch_size=1", "lr=1e-3", "eval_every=0", "eval_rows=2",
            "final_eval_rows=2", "save_every=0", "task.n_train=32", "task.n_eval=8"]
    env = {**os.environ, "OMP_NUM_THREADS": "1", "PYTHONUNBUFFERED": "1", "CUDA_VISIBLE_DEVICES": ""}
    runs = {}
    for name, launch in (("one", []), ("two", ["-m", "accelerate.commands.launch", "--multi_gpu", "--num_processes",
                                              "2", "--num_machines", "1", "--mixed_precision", "no",
                                              "--dynamo_backend", "no"])):
        out = tmp_path / name
        shutil.copytree(student, out / "tiny-calc" / "sft" / "final")
        cmd = [sys.executable, *launch, "-m", "posttrain", "distill", *args, f"run.output_dir={out}"]
        r = subprocess.run(cmd, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=600)
        assert r.returncode == 0, f"{r.stdout[-3000:]}\n{r.stderr[-3000:]}"
        assert f"{1 if name == 'one' else 2} process(es)" in r.stdout
        runs[name] = _steps(out)
    one, two = runs["one"], runs["two"]
    assert [s["step"] for s in one] == [s["step"] for s in two] == [1, 2]
    for a, b in zip(one, two):
        for k in ("reward/mean", "env/turns", "env/env_tokens", "tokens/generated", "tokens/trained"):
            assert a[k] == b[k], (k, a[k], b[k])
        for k in ("loss", "kl/reverse", "kl/forward", "nll", "grad_norm"):
            assert a[k] == pytest.approx(b[k], rel=1e-4, abs=1e-6), (k, a[k], b[k])
