"""On-policy distillation: the student samples, a teacher scores every token of the student's samples, and the
student minimises the per-token divergence between its next-token distribution and the teacher's.

CPU:        posttrain distill --recipe tiny-math      (from nothing: the teacher and the student's SFT model are
                                                        built first when missing; see the recipe's distill section)
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain distill --recipe tiny-math teacher=/path/to/teacher
            (2 CPU processes: accelerate launch --config_file recipes/launch/cpu-2proc.yaml -m posttrain distill
            --recipe tiny-math run.threads=1)

Reads top to bottom: `setup` (prompts, verifier, the student and the frozen teacher, both scored on held-out
problems), loop { rollout (detail 1) -> score -> one optimizer step (`update`) -> log -> eval -> checkpoint }, `finish`.

Implementation details it follows, each a config field:
 1. On-policy data (GKD: Agarwal et al. 2024, "On-Policy Distillation of Language Models: Learning from
    Self-Generated Mistakes", §3): the student's own samples at `temperature`, so it is taught in the states it
    reaches itself, not the teacher's (supervised KD's train-test mismatch); student_fraction is GKD's lambda.
 2. The per-token divergence over the whole vocabulary (loss; `distill_loss`): reverse KL (the default: GKD,
    MiniLLM, Thinking Machines), forward KL, GKD's generalised JSD (jsd_beta), or nll (the SFT baseline).
 3. On-policy: one optimizer step per batch on the token mean over its completion tokens (every process's), no
    importance ratio, no clipping (GKD; TRL's GKDTrainer).
 4. Both distributions at the same temperature, logits / temperature: the student's tempered one is the one taught.
 5. An optional reward term (reward_weight; `distill_loss`): a group-baseline policy gradient (GKD §3.2; Qwen3).
 6. Teacher and student share one tokenizer, checked before training (`check_same_tokenizer`); sizes may differ.
 7. The frozen teacher runs on each micro-batch inside the loss, sized by a token budget (`distill_budget`).
 8. Multi-turn episodes (env; `update`): the teacher scores whole trajectories, the loss covers sampled tokens only.

Deviations and limits:
- The divergence is summed per token over the student's sampled prefixes, as in GKD: its gradient treats each
  position's distribution as the target and ignores that the student's choice of earlier tokens changed which
  prefixes it is scored on (the sequence-level reverse KL's score-function term; MiniLLM keeps it with a policy
  gradient). Thinking Machines' sampled-token estimator (log S - log P of the sampled token as a per-token reward)
  is not offered: with a shared tokenizer the exact per-token divergence is cheap here.
- Full-vocabulary divergences hold both models' logits for a micro-batch: on a 150k vocabulary that limits
  micro-batches to a few hundred tokens (the budget does this; a top-k teacher is not implemented).
- The teacher runs whole on every process (no sharding of the teacher; no separate teacher server), in the run's
  precision: under run.mixed_precision=bf16 its forward runs in the student's bf16 autocast (its frozen weights
  cast to bf16 once, `posttrain.lean.train`), as TRL's under bf16=True; otherwise fp32.
- An environment's tokens are context only (neither model is taught what a tool returns); the divergence ignores
  that the student's tool calls changed them (the first point's term). Its limits, not max_new_tokens, end episodes.
"""
from __future__ import annotations

import contextlib
import functools
import random
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal

import torch

from posttrain import loop, sharding
from posttrain.advantages import group_advantages, zero_variance_groups
from posttrain.config import ConfigError, Resolved
from posttrain.logprobs import completion_logits, masked_mean, scatter_scored
from posttrain.losses import logprob_divergence, policy_loss, sampler_mismatch
from posttrain.problems import (HeldOut, Problem, Reward, build_env_reward, build_reward, load_env, load_problems,
                                preflight, sample_and_score, tokenize_problems)
from posttrain.rollout import SamplingParams
from posttrain.rollout.multiturn import episode_metrics

if TYPE_CHECKING:  # the annotations of the run object only
    from accelerate import Accelerator
    from transformers import PreTrainedTokenizerBase


@dataclass
class DistillConfig(loop.TrainingConfig):
    teacher: str = "grpo"
    """A stage of this recipe (its final/, built when missing) or a model directory / .gguf file (`teacher_dir`)."""
    teacher_model: str = ""
    """Run the teacher's stage with this model (a preset such as small, or a model directory); empty: model.path."""
    loss: Literal["reverse_kl", "forward_kl", "jsd", "nll"] = "reverse_kl"
    """Per-token loss (detail 2): reverse_kl (KL(student || teacher)), forward_kl, jsd (jsd_beta), nll."""
    jsd_beta: float = 0.5
    """beta of loss=jsd, in (0, 1): near 0 it is forward-KL-like, near 1 reverse-KL-like."""
    student_fraction: float = 1.0
    """GKD's lambda: the chance a step's samples are the student's (seeded by step), else the teacher's; 0: KD."""
    reward_weight: float = 0.0
    """Weight of a policy-gradient term on the reward (verifier or env; group advantages: group_size >= 2)."""
    verifier: str = "auto"
    """Verifier spec for the reward term and the held-out accuracy; auto: the task's; none: no verifier."""
    verifier_options: dict[str, Any] = field(default_factory=dict)
    """Keyword options of a single (not composed) verifier."""
    env: str = ""
    """A multi-turn environment ("calc", an entry point, "file.py:Name"; detail 8); empty: single completions."""
    env_options: dict[str, Any] = field(default_factory=dict)
    """Keyword options of the environment, its limits included (e.g. {max_turns: 3})."""
    verifier_workers: int = 2
    """Verifier worker processes; 0 scores in-process."""
    verifier_timeout_s: float = 0.0
    """Wall-clock limit per check in seconds; 0: the verifier's own limit."""
    on_bad_rows: Literal["error", "skip"] = "error"
    """Problems without a reference (when a verifier is used): stop naming the row, or skip them."""
    train_file: str | None = None
    """Prompt file (JSONL/JSON/Parquet rows: prompt[, answer, verifier]) replacing the task's training prompts."""
    eval_file: str | None = None
    """Held-out prompt file (same schema) replacing the task's held-out prompts."""
    prompts_per_step: int = 16
    """Prompts per step (P)."""
    group_size: int = 1
    """Samples per prompt (K); the reward term's group baseline needs K >= 2."""
    max_new_tokens: int = 64
    """Generation budget per sample."""
    temperature: float = 1.0
    """Sampling temperature (> 0); both models' logits are divided by it in the loss."""
    eval_rows: int = 100
    """Held-out problems for the periodic evaluation."""
    final_eval_rows: int = 200
    """Held-out problems for the before / after / teacher comparison (0 skips it)."""
    # loop.TrainingConfig's fields (one docstring each, there) whose default is this trainer's own:
    lr: float = 5e-5


def check_config(cfg: DistillConfig) -> None:
    """Inconsistent settings are a ConfigError before anything runs."""
    def bad(msg: str) -> ConfigError:
        return ConfigError(f"distill.{msg}")

    if not cfg.teacher:
        raise bad("teacher is empty; give a stage of this recipe (e.g. grpo) or a model directory")
    if cfg.prompts_per_step < 1 or cfg.group_size < 1 or cfg.max_new_tokens < 1 or cfg.micro_batch_size < 0:
        raise bad("prompts_per_step, group_size and max_new_tokens must be >= 1 and micro_batch_size >= 0")
    if not 0 < cfg.jsd_beta < 1:
        raise bad(f"jsd_beta must be in (0, 1), got {cfg.jsd_beta}")
    if not 0 <= cfg.student_fraction <= 1:
        raise bad(f"student_fraction must be in [0, 1], got {cfg.student_fraction}")
    if not cfg.temperature > 0:
        raise bad(f"temperature must be > 0, got {cfg.temperature}")
    if cfg.reward_weight < 0:
        raise bad(f"reward_weight must be >= 0, got {cfg.reward_weight}")
    if cfg.reward_weight > 0 and cfg.group_size < 2:
        raise bad(f"reward_weight > 0 needs group_size >= 2 (the group baseline of its advantages), got "
                  f"{cfg.group_size}")
    if cfg.reward_weight > 0 and cfg.verifier == "none" and not cfg.env:
        raise bad("reward_weight > 0 needs a verifier (verifier=none) or an environment (env)")
    if cfg.env and cfg.verifier not in ("auto", "none"):
        raise bad(f"verifier={cfg.verifier!r}: env={cfg.env!r} rewards whole episodes itself; leave verifier unset")
    if cfg.verifier_workers < 0 or cfg.verifier_timeout_s < 0:
        raise bad("verifier_workers and verifier_timeout_s must be >= 0")


# ----------------------------------------------------------------------------- train
def train(res: Resolved, ensure) -> Path:
    """On-policy distillation of the teacher into the recipe's SFT model; returns the final model directory."""
    cfg: DistillConfig = res.stage_cfg
    check_config(cfg)
    K, P = cfg.group_size, cfg.prompts_per_step
    with contextlib.ExitStack() as stack:
        run = setup(res, cfg, ensure, stack)  # prompts and verifier, teacher and student, optimizer, resume, baselines
        t_start = time.time()
        for step in range(run.start, cfg.max_steps):
            done, t_step = step + 1, time.time()
            saving = (cfg.save_every and done % cfg.save_every == 0) or done == cfg.max_steps
            evaluating = cfg.eval_every and done % cfg.eval_every == 0
            with loop.naming_checkpoint(run.ckpt):
                # ---- rollout: the student's samples (GKD's lambda: else the teacher's), process r taking
                # positions r, r + W, ... of the step's global prompt batch; score (verifier metrics and the
                # reward term), gathered: every process holds every group
                on_policy = random.Random(loop.stream_seed(cfg.seed, "distill/mix", step)).random() \
                    < cfg.student_fraction
                params = SamplingParams(n=K, max_new_tokens=cfg.max_new_tokens, temperature=cfg.temperature,
                                        seed=loop.stream_seed(cfg.seed, "distill/sample", step))
                got = sample_and_score(run.accelerator, run.student if on_policy else run.teacher, run.tokenizer,
                                       run.problems, loop.batch_indices(len(run.problems), P, cfg.seed, step),
                                       params, run.reward, step)
                t_train = time.time()
                rollouts = [r for g in got.groups for r in g.rollouts]
                rewards = torch.tensor([x for g in got.groups for x in g.rewards], dtype=torch.float32)
                # ---- update: one optimizer step on the step's token mean (micro-batches by the token budget)
                m = update(run, rollouts, rewards, with_reward=cfg.reward_weight > 0 and on_policy, done=done,
                           on_policy=on_policy)
                if saving or evaluating:
                    loop.check_weights(done, run.model)
            # ---- log
            m.update(step_metrics(rollouts, rewards, K, on_policy, run.reward))
            m.update({"time/sample": got.sample_s, "time/score": got.score_s, "time/train": time.time() - t_train,
                      "time/step": time.time() - t_step})
            run.metrics.log(done, m, console=False)
            if run.main and not res.run.quiet and (done % cfg.log_every == 0 or done == cfg.max_steps):
                print(progress_line(done, cfg.max_steps, m, time.time() - t_start, run.start), flush=True)
            # ---- eval
            if run.main and run.held_out is not None and run.held_out.n_eval and evaluating \
                    and done != cfg.max_steps:
                run.held_out.log_eval(run.student, run.tokenizer, run.metrics, done, run.say)
            # ---- checkpoint
            if saving:
                run.ckpt.save(done, run.model, run.optimizer, run.scheduler, {"step": done})
        return finish(run)


# ----------------------------------------------------------------------------- setup, update and the end of a run
@dataclass(kw_only=True)
class DistillRun:
    """What a run holds between steps (`setup`)."""

    res: Resolved
    cfg: DistillConfig
    accelerator: Accelerator
    say: Callable[[str], None]  # prints on the main process
    run_dir: Path
    main: bool
    sft_dir: Path
    teacher_dir: Path
    tokenizer: PreTrainedTokenizerBase
    model: torch.nn.Module  # the student as accelerate prepared it
    student: torch.nn.Module  # the student inside the wrapper: generation, evaluation, saving
    teacher: torch.nn.Module  # frozen
    vocab: int  # detail 6: the tokenizer's ids (padded output rows beyond it are never compared)
    budget: int  # padded tokens per micro-batch (both models' logits)
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler
    ckpt: loop.Checkpointer
    metrics: loop.MetricsLog
    problems: list[Problem]
    reward: Reward | None  # the verifier's or the environment's; None without either
    held_out: HeldOut | None  # None without a reward
    start: int  # the first step (resume)
    baseline: dict  # the student's SFT model's held-out numbers (main process)
    teacher_eval: dict  # the teacher's (main process)


def setup(res: Resolved, cfg: DistillConfig, ensure, stack: contextlib.ExitStack) -> DistillRun:
    """Prompts and the verifier first (a bad row or a broken verifier stops before any model loads; the verifier
    pool lives in `stack`), then the teacher and the SFT model (one tokenizer: checked before the run directory
    changes), the optimizer, the resumed state and the held-out numbers of the SFT model and of the teacher. The
    student is this recipe's SFT model (model.start_from=base: the model as it is)."""
    from posttrain.config import STAGE_SECTIONS
    from posttrain.models import load_model, load_tokenizer, maybe_lora
    from posttrain.verifiers.envs import ToolRunner
    from posttrain.verifiers.runner import VerifierPool

    schema = "prompt" if cfg.verifier == "none" else "verifiable"  # no verifier: a prompt file needs no answers
    verifier, train_rows, train_source, problems, eval_problems = load_problems(res, cfg, "distill", schema=schema)
    pool = stack.enter_context(VerifierPool(workers=cfg.verifier_workers, timeout_s=cfg.verifier_timeout_s or None))
    if verifier is not None:
        preflight(verifier, pool, train_rows, train_source, print, stage="distill")
    env = load_env(cfg, "distill")
    t_dir = teacher_dir(res, cfg, tuple(s for s in STAGE_SECTIONS if s not in ("eval", "distill")), ensure)
    sft_dir = ensure("sft")
    tokenizer = load_tokenizer(sft_dir, res.model)
    check_same_tokenizer(tokenizer, load_tokenizer(t_dir, res.model), t_dir)  # before the run dir changes

    accelerator, say = loop.start_run(res, cfg.seed, cfg.resume)
    run_dir, main, device = res.stage_dir(), accelerator.is_main_process, accelerator.device
    model = maybe_lora(res, load_model(sft_dir, res.model.dtype, device=device), say)
    teacher = load_model(t_dir, res.model.dtype, device=device).eval().requires_grad_(False)
    budget = distill_budget(res.run.micro_batch_tokens, model, teacher)
    problems = tokenize_problems(tokenizer, problems, "training", cfg.max_new_tokens, res.model.max_length, say,
                                 stage="distill")
    eval_problems = tokenize_problems(tokenizer, eval_problems, "held-out", cfg.max_new_tokens,
                                      res.model.max_length, say, stage="distill")
    if len(problems) < cfg.prompts_per_step:
        raise loop.TrainingError(f"only {len(problems)} training prompts fit, fewer than "
                                 f"prompts_per_step={cfg.prompts_per_step}")
    reward = build_env_reward(env, stack.enter_context(ToolRunner())) if env is not None else \
        build_reward(verifier, pool, None, device, timeout_s=cfg.verifier_timeout_s) if verifier is not None else None
    held_out = None if reward is None else HeldOut(
        eval_problems, reward, cfg.max_new_tokens, min(cfg.eval_rows, len(eval_problems)),
        min(cfg.final_eval_rows, len(eval_problems)), stage="distill",
        start="base" if res.model.start_from == "base" else "SFT")
    optimizer = loop.build_optimizer(model, cfg.lr, cfg.weight_decay)
    scheduler = loop.build_scheduler(optimizer, cfg.warmup_steps, cfg.max_steps, cfg.schedule, cfg.min_lr_ratio)
    model, optimizer = accelerator.prepare(model, optimizer)
    student = accelerator.unwrap_model(model)
    ckpt = loop.Checkpointer(run_dir, cfg.keep_checkpoints, accelerator)
    metrics = loop.open_metrics(res, cfg.max_steps, main, "[distill] ")
    start = loop.resume_run(ckpt, metrics, model, optimizer, scheduler, resume=cfg.resume, say=say,
                            tag="distill")["step"]
    baseline = held_out.sft_baseline(student, tokenizer, run_dir / "sft_eval.json", start, metrics, say) \
        if main and held_out is not None else {}
    teacher_eval = teacher_baseline(held_out, teacher, tokenizer, run_dir / "teacher_eval.json", say) \
        if main and held_out is not None else {}
    say(describe_run(cfg, t_dir, len(problems), reward, accelerator.num_processes, device, budget))
    return DistillRun(res=res, cfg=cfg, accelerator=accelerator, say=say, run_dir=run_dir, main=main, sft_dir=sft_dir,
                      teacher_dir=t_dir, tokenizer=tokenizer, model=model, student=student, teacher=teacher,
                      vocab=len(tokenizer), budget=budget, optimizer=optimizer, scheduler=scheduler, ckpt=ckpt,
                      metrics=metrics, problems=problems, reward=reward, held_out=held_out, start=start,
                      baseline=baseline, teacher_eval=teacher_eval)


def update(run: DistillRun, rollouts: list, rewards: torch.Tensor, *, with_reward: bool, done: int,
           on_policy: bool = False) -> dict[str, float]:
    """One optimizer step on the step's rollouts (every process holds all of them; process r takes rows r, r + W,
    ... in micro-batches of the token budget): the divergence, plus the reward term (`with_reward`, group
    advantages of `rewards`); its metrics. `on_policy`: the student sampled them, so its sampling log-probs
    (those of the tempered distribution it sampled) are compared with the loss's (mismatch/*).

    Several processes: `posttrain.sharding`'s convention, as GRPO: process r sampled positions r, r + W, ... of
    the step's global prompt batch, the groups were gathered (every process holds every row), and the step's rows
    are split over the processes by `sharding.micro_batches`. Evaluation, logs and final/ are the main process's.

    Detail 8, multi-turn episodes (env, env_options; `posttrain.rollout.multiturn`, as grpo.env): each sample is
    an episode in a tool-use environment. The teacher scores the whole trajectory (prompt, every sampled and every
    environment token as context); every per-token loss and metric covers the sampled tokens only (the loss mask
    is completion_mask, 0 on the environment's tokens); the reward term takes the environment's reward; held-out
    evaluation runs greedy episodes. Steps whose samples are the teacher's (student_fraction < 1) are its own
    episodes in the environment."""
    from posttrain.rollout import collate_rollouts

    cfg, device = run.cfg, run.accelerator.device
    batch = collate_rollouts(rollouts, run.tokenizer.pad_token_id).to(device)
    rows = {"input_ids": batch.input_ids, "attention_mask": batch.attention_mask, "loss_mask": batch.completion_mask}
    if with_reward:
        rows["advantages"] = group_advantages(rewards, cfg.group_size, estimator="grpo", std_scale="group").to(device)
    if on_policy:
        rows["sampler_logps"] = batch.policy_logprobs if cfg.temperature == 1.0 else batch.logprobs  # (N, T)
    world = run.accelerator.num_processes
    mbs = sharding.micro_batches(rows, torch.arange(len(rollouts), device=device), cfg.micro_batch_size,
                                 "token_mean", run.accelerator.process_index, world, run.budget)
    loss_fn = functools.partial(distill_loss, cfg, run.model, run.teacher, run.vocab, with_reward, world,
                                teacher_autocast=run.accelerator.autocast)
    return loop.optimizer_step(run.accelerator, run.model, run.optimizer, run.scheduler, mbs, loss_fn,
                               cfg.max_grad_norm, done, weights=[tokens for _, _, tokens in mbs])


def finish(run: DistillRun) -> Path:
    """final/ (every process gathers a sharded model; the main process saves), the comparison with the SFT model
    and the teacher, eval.json; returns final/."""
    from posttrain.models import save_model

    final = run.run_dir / "final"
    whole = loop.full_state_dict(run.accelerator, run.model)  # every process: gathers a sharded model (FSDP, ZeRO-3)
    if run.main:
        save_model(run.student, run.tokenizer, final, state_dict=whole)
        run.say(f"[distill] saved {final}")
        report = run.held_out.compare(run.student, run.tokenizer, run.baseline, run.metrics, run.cfg.max_steps,
                                      run.say) if run.held_out is not None else {}
        if run.teacher_eval:
            report["teacher"] = run.teacher_eval
            if "eval/accuracy" in run.teacher_eval:
                run.say(f"[distill] teacher's held-out greedy accuracy: {run.teacher_eval['eval/accuracy']:.3f}")
        loop.write_json(run.run_dir / "eval.json", {"model": str(final), "sft_model": str(run.sft_dir),
                                                    "teacher_model": str(run.teacher_dir), **report})
        run.metrics.close(report)
    run.metrics.close()
    run.accelerator.wait_for_everyone()
    return final


def teacher_dir(res: Resolved, cfg: DistillConfig, stages: tuple[str, ...], ensure) -> Path:
    """The teacher's model directory: a stage's output (built first when missing; with teacher_model, in that
    model's run tree), a .gguf file dequantized once (as model.path=FILE.gguf), or the directory given.

    distill.teacher names a stage of this recipe (sft, grpo, ...: its final/) or a model directory / .gguf file.
    distill.teacher_model (a preset such as small, or a model directory) runs that stage's chain with another
    model, in its own run tree <run.output_dir>/model-<name>/<recipe>/ (the same task, so the same tokenizer for a
    preset)."""
    from posttrain import model_files
    from posttrain.errors import ModelError
    from posttrain.models import is_model_dir

    if cfg.teacher in stages:
        return ensure(cfg.teacher, cfg.teacher_model or None)
    if cfg.teacher_model:
        raise ConfigError(f"distill.teacher_model={cfg.teacher_model!r} names the model of a teacher STAGE, but "
                          f"distill.teacher={cfg.teacher!r} is a path; give a stage ({', '.join(stages)}) or drop it")
    if model_files.is_gguf(cfg.teacher):
        return model_files.cached_import(cfg.teacher, Path(res.run.output_dir) / "models")
    if not is_model_dir(cfg.teacher):
        raise ModelError(f"distill.teacher {cfg.teacher!r} is neither a stage of this recipe ({', '.join(stages)}) "
                         "nor a Hugging Face model directory")
    return Path(cfg.teacher)


def check_same_tokenizer(student_tok, teacher_tok, teacher_path: Path) -> None:
    """Detail 6: one tokenizer for both, vocabulary and special tokens (a ModelError naming the first difference
    otherwise): the divergence compares the two next-token distributions id by id. The models' sizes may differ; a
    teacher whose output layer has more rows than the tokenizer (padded vocabularies) is compared on the
    tokenizer's ids only (`DistillRun.vocab`)."""
    from posttrain.errors import ModelError

    a, b = student_tok.get_vocab(), teacher_tok.get_vocab()
    if a != b:
        differ = sorted(set(a.items()) ^ set(b.items()), key=lambda kv: kv[1])[:3]
        raise ModelError(f"distill.teacher {str(teacher_path)!r} has another tokenizer than the student (vocabularies "
                         f"of {len(b)} and {len(a)} tokens; e.g. {differ}): on-policy distillation compares the two "
                         "next-token distributions id by id, so both models must share one tokenizer")
    for name in ("eos_token_id", "pad_token_id", "bos_token_id"):
        if getattr(student_tok, name) != getattr(teacher_tok, name):
            raise ModelError(f"distill.teacher {str(teacher_path)!r}: its tokenizer's {name} is "
                             f"{getattr(teacher_tok, name)}, the student's {getattr(student_tok, name)}")


def distill_budget(setting: int, student, teacher) -> int:
    """Detail 7: the teacher is frozen (no grad, eval mode) and runs on each micro-batch inside the loss, so neither
    its logits nor the student's exist for the whole batch at once. Padded tokens per micro-batch whose activations
    (the student's, both models' full logits, their softmaxes and the divergence's temporaries: ~8 vocabulary-size
    fp32 vectors) take ACTIVATION_BUDGET_BYTES; `setting` (run.micro_batch_tokens) overrides it."""
    from posttrain.models import ACTIVATION_BUDGET_BYTES, activation_bytes_per_token, unwrap_model

    if setting:
        return int(setting)
    cfg = unwrap_model(student).config
    per_token = activation_bytes_per_token(cfg) + 4 * 8 * max(cfg.vocab_size, unwrap_model(teacher).config.vocab_size)
    return max(64, ACTIVATION_BUDGET_BYTES // per_token)


# ----------------------------------------------------------------------------- the loss
def distill_loss(cfg: DistillConfig, model, teacher, vocab: int, with_reward: bool, world: int,
                 micro_batch: tuple[dict, float, float], teacher_autocast=contextlib.nullcontext
                 ) -> tuple[torch.Tensor, dict[str, float]]:
    """The loss of one of `sharding.micro_batches`: the token mean of the per-token loss over its completion
    tokens (plus reward_weight x the policy-gradient term), scaled to its share of the step's tokens times W (DDP
    averages gradients). Metrics: both KLs per token whatever the loss (comparable across runs), the NLL; with
    the sampler's log-probs (an on-policy step) their gap to the loss's, `losses.sampler_mismatch`.

    Detail 2 (`losses.token_divergence`): reverse KL, KL(student || teacher), the default: mode-seeking, the loss
    of on-policy distillation in GKD, MiniLLM (Gu et al. 2024) and Thinking Machines' "On-Policy Distillation"
    (2025); forward KL; GKD's generalised JSD (jsd_beta). loss=nll is the negative log-likelihood of the sampled
    tokens: with student_fraction=0 that is SFT of the student on the teacher's samples (sequence-level KD, Kim &
    Rush 2016), the baseline of the distillation-vs-SFT comparison at the same prompts, samples and steps.
    Detail 4: both models' logits / temperature when temperature != 1 (the student samples from its tempered
    distribution, so that is the one taught). Detail 5: reward_weight x a policy-gradient term with group
    advantages (GRPO's group baseline, `advantages.group_advantages`; K = group_size >= 2 samples per prompt) on
    the student's own samples, added to the divergence (GKD §3.2, "RL fine-tuning with on-policy GKD"; Qwen3's and
    Thinking Machines' distillation mix it the same way); steps whose samples are the teacher's carry no reward
    term (they are not the student's policy)."""
    mb, share, _ = micro_batch
    ids, am = mb["input_ids"], mb["attention_mask"]
    # both models' full distributions on the scored columns only: (n, V) rows, index into the (b, T-c) columns c..
    s_logits, index, c = completion_logits(model, ids, am, mb["loss_mask"], temperature=cfg.temperature)
    with torch.no_grad(), teacher_autocast():  # the run's mixed precision (the accelerator's autocast)
        t_logits, _, _ = completion_logits(teacher, ids, am, mb["loss_mask"], temperature=cfg.temperature)
    s_logits, t_logits = s_logits[..., :vocab], t_logits[..., :vocab]
    completion_mask = mb["loss_mask"][:, c:].to(s_logits.device).bool()  # (b, T-c)
    shape = tuple(completion_mask.shape)
    every = torch.ones_like(index, dtype=torch.bool)  # (n,): each row is scored
    targets = ids[:, c:].to(s_logits.device).reshape(-1).index_select(0, index)  # (n,)
    # one log_softmax per side over the vocabulary, shared by the loss, the NLL and both KL metrics
    log_s = torch.log_softmax(s_logits, -1)  # (n, V) fp32
    with torch.no_grad():
        log_p = torch.log_softmax(t_logits, -1)
    logps = scatter_scored(log_s.gather(-1, targets[:, None]).squeeze(-1), index, shape)  # (b, T-c)
    nll = torch.where(completion_mask, -logps, torch.zeros_like(logps))
    per_token = nll if cfg.loss == "nll" else scatter_scored(
        logprob_divergence(log_s, log_p, every, kind=cfg.loss, beta=cfg.jsd_beta), index, shape)  # (b, T-c)
    loss = masked_mean(per_token, completion_mask)
    m: dict[str, float] = {}
    with torch.no_grad():
        ls = log_s.detach()
        for kind in ("reverse", "forward"):
            kl = per_token.detach() if cfg.loss == f"{kind}_kl" else \
                scatter_scored(logprob_divergence(ls, log_p, every, kind=f"{kind}_kl"), index, shape)
            m[f"kl/{kind}"] = float(masked_mean(kl, completion_mask))
        m["nll"] = float(masked_mean(nll.detach(), completion_mask))
        if "sampler_logps" in mb:  # the weights that sampled: every micro-batch runs before the optimizer step
            m.update(sampler_mismatch(logps, mb["sampler_logps"][:, c:].to(logps.device), completion_mask))
    if with_reward:  # detail 5: on-policy, so the ratio is 1 and this is REINFORCE with the group baseline
        pg, _ = policy_loss("clip", logps, logps.detach(), mb["advantages"].to(logps.device), completion_mask,
                            clip_eps=0.2, aggregation="token_mean")  # ratio 1: the clip never binds
        loss = loss + cfg.reward_weight * pg
        m["pg_loss"] = float(pg.detach())
    return loss * share * world, m


# ----------------------------------------------------------------------------- log
def step_metrics(rollouts: list, rewards: torch.Tensor, K: int, on_policy: bool, reward: Reward | None
                 ) -> dict[str, float]:
    """Whose samples, their length and truncation, the completion tokens and those that carry the loss (sampled,
    not the environment's); with a reward, its mean and the fraction of groups with identical rewards; in an
    environment, its episode means (env/*: turns, tool calls, sampled and environment tokens)."""
    lengths = [len(r.completion_ids) for r in rollouts]
    m = {"samples/student": float(on_policy), "completion/length": sum(lengths) / len(lengths),
         "completion/truncated": sum(r.finish_reason == "length" for r in rollouts) / len(rollouts),
         "tokens/generated": float(sum(lengths)),
         "tokens/trained": float(sum(sum(r.completion_mask) for r in rollouts))}
    if reward is not None:
        m["reward/mean"] = float(rewards.mean())
        m["zero_var_frac"] = float(zero_variance_groups(rewards, K).float().mean()) if K > 1 else 0.0
    if reward is not None and reward.env is not None:
        m.update(episode_metrics(rollouts))
    return m


def teacher_baseline(held_out: HeldOut, teacher, tokenizer, path: Path, say) -> dict[str, float]:
    """The teacher's held_out-out numbers (once per run directory: read back on resume)."""
    import json

    if not held_out.n_final and not held_out.n_eval:
        return {}
    if path.is_file():
        return json.loads(path.read_text())
    n = held_out.n_final or held_out.n_eval
    m = held_out.summarise(held_out.evaluate(teacher, tokenizer, n), n)
    loop.write_json(path, m)
    if "eval/accuracy" in m:
        say(f"[distill] teacher, greedy, {n} held_out-out problems: accuracy {m['eval/accuracy']:.3f}")
    return m


def describe_run(cfg: DistillConfig, t_dir: Path, n: int, reward: Reward | None, world: int, device,
                 budget: int) -> str:
    loss = f"jsd (beta {cfg.jsd_beta:g})" if cfg.loss == "jsd" else cfg.loss
    env = None if reward is None else reward.env
    reward_name = "" if reward is None else f"environment {env.name}" if env is not None else \
        f"verifier {reward.verifier.name}"
    data = "the student's samples" if cfg.student_fraction == 1 else "the teacher's samples" \
        if cfg.student_fraction == 0 else f"the student's samples with probability {cfg.student_fraction:g}, else " \
                                          "the teacher's"
    return (f"[distill] teacher {t_dir}; {n} training prompts, {cfg.prompts_per_step} prompts x {cfg.group_size} "
            f"samples per step, {cfg.max_steps} steps; loss {loss} on {data}"
            + (f" + {cfg.reward_weight:g} x {reward_name} policy gradient" if cfg.reward_weight else "")
            + (f"; episodes in environment {env.name} (at most {env.limits.max_turns} turns, tools: "
               f"{', '.join(env.tool_functions()) or 'none'})" if env is not None else "")
            + f"; {world} process(es) on {device}; micro-batches <= {budget} tokens")


def progress_line(done: int, total: int, m: dict[str, float], elapsed: float, start: int) -> str:
    eta = elapsed / max(1, done - start) * (total - done)
    shown = [("loss", m["loss"]), ("kl_rev", m.get("kl/reverse")), ("kl_fwd", m.get("kl/forward")),
             ("reward", m.get("reward/mean")), ("len", m["completion/length"])]
    return (f"[distill] step {done}/{total} " + " ".join(f"{k} {v:.4g}" for k, v in shown if v is not None)
            + ("" if m["samples/student"] else " (teacher samples)")
            + f" | {m['time/step']:.2f}s (sample {m['time/sample']:.2f}, train {m['time/train']:.2f}), "
            f"{elapsed:.0f}s elapsed, eta {eta:.0f}s")
