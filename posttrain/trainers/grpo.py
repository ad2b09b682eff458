"""GRPO: group-relative policy optimisation with verifier (and/or reward-model) rewards.

CPU:        posttrain grpo --recipe tiny-countdown        (from nothing: base model, SFT, GRPO; see the recipe)
            posttrain grpo --recipe tiny-code
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain grpo --recipe tiny-countdown model.path=/path/to/hf-model
            (2 CPU processes: accelerate launch --config_file recipes/launch/cpu-2proc.yaml -m posttrain grpo
            --recipe tiny-countdown run.threads=1; tested against one process in tests/posttrain/test_distributed.py)

Reads top to bottom: `setup` (problems and reward before any model loads, the SFT model as the policy, a frozen
reference only when beta > 0, its held-out greedy baseline), loop { rollout: P prompts x K samples in ONE `generate`
call -> score in the verifier pool -> group advantages -> mu passes x minibatches of clipped-ratio updates -> log ->
eval -> checkpoint }, `finish` (final/; held-out greedy accuracy against the SFT model's).

Implementation details it follows, each a config field:
 1. Group baseline (GRPO: Shao et al. 2024, DeepSeekMath §4.1; DeepSeek-R1): K samples per prompt, the group mean
    as baseline and the group std as scale (`advantages.group_advantages`, estimator grpo, std_scale group).
 2. PPO's clipped ratio per token (`losses.ppo_policy_loss`, clip_eps) against pi_old, the policy that sampled;
    mu passes over one batch of rollouts (GRPO's mu; TRL's num_iterations), `minibatches` updates each.
 3. KL to the reference with the k3 estimator, added to the loss, not the reward (GRPO eq. 4; `losses.kl_penalty`).
 4. Per-sequence token mean (GRPO eq. 3; aggregation seq_mean_token_mean).
 5. Clip-higher (DAPO: Yu et al. 2025, §3.1; clip_eps_high, 0.28 over 0.2).
 6. Dynamic sampling (DAPO §3.2; zero_variance=resample; `rollout_rounds`): equal-reward groups are dropped and
    more prompts sampled to refill the batch (at most max_resample_rounds more rounds).
 7. Token-level loss (DAPO §3.3; aggregation token_mean, the default) and beta = 0 (no reference model at all).
 8. Overlong filtering (DAPO §3.4; mask_truncated): completions cut at max_new_tokens carry no loss.
 9. Dr. GRPO (Liu et al. 2025, "Understanding R1-Zero-Like Training"): no std division (std_scale none) and a
    constant normaliser (aggregation seq_mean_token_sum_norm: token sums / (rows x max_new_tokens)).
10. RLOO (Ahmadian et al. 2024) and REINFORCE++ (Hu et al. 2025) as other critic-free baselines (estimator).
11. pi_old from the rollout engine (old_logprobs=rollout: no extra forward; TRL, verl), or recomputed by one
    batched no-grad forward of the trainer (`loss_rows`). The default, auto, recomputes wherever the sampler's
    numerics are not the trainer's (bf16 rollout weights, bf16 autocast, half weights, vLLM; `sampler_is_trainer`)
    and takes the engine's where they are (fp32: equal within 1e-6). With bf16 on both sides and the engine's pi_old,
    smol-math's GRPO collapsed in 2 seeds of 3 (held-out 0.21 -> 0.015 and 0.255, against 0.625 and 0.58 in fp32):
    the ratio pi_trainer / pi_sampler of the one update is not 1, and clipping it drops the gradient of 1-6% of the
    tokens by their rounding, not their advantage (RESULTS.md, "Is E7 real's drift bf16?").
12. The policy-loss family (policy_loss, `losses.policy_loss`; `grpo_loss`): PPO's clipped token ratio (clip);
    GSPO (Zheng et al. 2025): one clipped ratio per sequence, the geometric mean of its token ratios (gspo), and
    GSPO-token (gspo_token); CISPO (MiniMax-M1, 2025): the clipped importance weight, stop-gradient, times the
    log-prob, so no token's gradient is dropped (cispo).
13. Rollout correction (rollout_correction, `losses.rollout_correction`; `apply_rollout_correction`): truncated
    importance weights pi_old / pi_sampler (tis: Yao et al. 2025) or dropped tokens (mask: IcePop), and the
    sampler-trainer gap logged (mismatch/*) whenever it can be measured.
14. Pass-rate curriculum (prompt_sampling=pass_rate; `Curriculum`): problems drawn by the chance that a group of K
    is informative given each one's tracked pass rate.
15. Multi-turn episodes (env, env_options; `posttrain.rollout.multiturn`; `posttrain envs` lists them): each sample
    is an episode (turns, tool calls, tool results) rewarded by the environment; the loss covers sampled tokens only.

Named methods as settings (other fields at their defaults; the loss family and the aggregations are orthogonal,
except where `check_config` says otherwise):

    method        policy_loss  aggregation              std_scale  other settings
    GRPO          clip         seq_mean_token_mean      group      beta 0.04 (DeepSeekMath)
    DAPO          clip         token_mean               group      clip_eps_high 0.28, zero_variance resample,
                                                                   mask_truncated true (beta 0, the default)
    Dr. GRPO      clip         seq_mean_token_sum_norm  none
    GSPO          gspo         seq_mean_token_mean      group      clip_eps 3e-4, clip_eps_high 4e-4, minibatches 4
    GSPO-token    gspo_token   any                      group      as GSPO; per-token advantages allowed
    CISPO         cispo        token_mean               group      clip_eps 1 (no lower bound), clip_eps_high
    + TIS         any          any                      any        rollout_correction tis, rollout_correction_cap 2
    + IcePop      any          any                      any        rollout_correction mask (sequence level for gspo)

Rewards come through `posttrain.scoring` only (a verifier spec such as "0.9*countdown + 0.1*format", a reward model,
or both weighted; checks in a verifier pool, several processes: `rollout_rounds`). One step (the unit of max_steps,
logs, eval and checkpoints) is one batch of rollouts; everything random is a function of (seed, step), so resume=true
continues exactly; non-finite numbers stop the run (`update`). eval/accuracy is the greedy pass rate of the FIRST
term of a composition ("0.9*math + 0.1*format"). Degenerate steps are explained in the log (`degenerate_message`).

Deviations and limits:
- The loss uses logits / temperature when temperature != 1 (TRL, verl); the policy being trained is then the
  tempered one. top_p < 1 samples from a truncated distribution but ratios and KL use the full one (TRL does too).
- zero_variance=skip (the default) drops degenerate groups from the loss without refilling (DAPO's filter without
  its resampling): cheaper, and with beta = 0 the gradient direction is unchanged; with beta > 0 those rows' KL term
  is dropped too. "keep" trains on them as GRPO as published does.
- The k3 KL term's gradient is that of KL(pi_ref || pi), not KL(pi || pi_ref) (see `losses.kl_penalty`); GRPO as
  published has the same property.
- Sequence-level rollout correction uses the geometric mean of the token ratios, not their product (see `losses`);
  CISPO's loss value is the clipped-weight surrogate -A w, its gradient the paper's.
- CISPO's published cap (eps_high) is not stated here as a default: clip_eps_high keeps its meaning, the upper clip
  range, for every policy loss, and recipes set it.
"""
from __future__ import annotations

import collections
import contextlib
import functools
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal

import torch

from posttrain import loop, sharding
from posttrain.advantages import curriculum_weights, group_advantages, track_pass_rates, zero_variance_groups
from posttrain.config import ConfigError, Resolved
from posttrain.logprobs import masked_mean, sequence_logprobs
from posttrain.losses import aggregate_token_loss, kl_penalty, policy_loss, rollout_correction, sampler_mismatch
from posttrain.problems import (HeldOut, Problem, Reward, build_env_reward, build_reward, load_env, load_problems,
                                preflight, sample_and_score, tokenize_problems)
from posttrain.rollout.multiturn import episode_metrics

if TYPE_CHECKING:  # the annotations of the run object only
    from accelerate import Accelerator
    from transformers import PreTrainedTokenizerBase


@dataclass
class GRPOConfig(loop.TrainingConfig):
    verifier: str = "auto"
    """Reward verifier spec ("countdown", "0.9*math + 0.1*format", "file.py:name"); auto: the task's; none: RM only."""
    env: str = ""
    """A multi-turn environment ("calc", an entry point, "file.py:Name"; detail 15); empty: `verifier` scores."""
    env_options: dict[str, Any] = field(default_factory=dict)
    """Keyword options of the environment, its limits included (e.g. {max_turns: 3, tool_timeout_s: 2})."""
    verifier_options: dict[str, Any] = field(default_factory=dict)
    """Keyword options of a single (not composed) verifier, e.g. {partial_credit: true} for code."""
    verifier_weight: float = 1.0
    """Weight of the verifier reward when a reward model is also used."""
    reward_model: str = "none"
    """Reward model: none, train (run `rm` first) or a path to a sequence-classification model directory."""
    reward_model_weight: float = 1.0
    """Weight of the reward-model score when a verifier is also used."""
    verifier_workers: int = 2
    """Verifier worker processes (checks run in parallel, each under a hard time limit); 0 scores in-process."""
    verifier_timeout_s: float = 0.0
    """Wall-clock limit per check in seconds; 0: the verifier's own limit."""
    on_verifier_error: Literal["zero", "stop"] = "zero"
    """A check that raises: zero scores that completion 0 and reports it; stop ends the run (checkpoint intact)."""
    on_bad_rows: Literal["error", "skip"] = "error"
    """Problems without a reference: stop naming the row, or skip them with a count."""
    train_file: str | None = None
    """Problem file (JSONL/JSON/Parquet rows: prompt, answer, verifier) replacing the task's training prompts."""
    eval_file: str | None = None
    """Held-out problem file (same schema) replacing the task's held-out prompts."""
    prompts_per_step: int = 8
    """Prompts per step (P); each gets group_size samples."""
    group_size: int = 8
    """Completions per prompt (K), the group of the group baseline."""
    max_new_tokens: int = 64
    """Generation budget per completion (also Dr. GRPO's constant normaliser)."""
    temperature: float = 1.0
    """Sampling temperature (> 0); the loss uses the same temperature."""
    top_p: float = 1.0
    """Nucleus sampling mass (1: off)."""
    estimator: Literal["grpo", "rloo", "reinforce_pp"] = "grpo"
    """Advantage baseline: grpo (group mean), rloo (leave-one-out), reinforce_pp (REINFORCE++, batch-normalised)."""
    std_scale: Literal["group", "batch", "none"] = "group"
    """Advantage divisor: group std (GRPO), batch std, none (Dr. GRPO); reinforce_pp needs batch."""
    policy_loss: Literal["clip", "gspo", "gspo_token", "cispo"] = "clip"
    """Policy loss (detail 12; the table): clip (PPO's token ratio), gspo, gspo_token (GSPO), cispo (CISPO)."""
    clip_eps: float = 0.2
    """Clip range of the ratio (lower side, and upper side unless clip_eps_high is set); GSPO used 3e-4."""
    clip_eps_high: float | None = None
    """Upper clip range (DAPO clip-higher, e.g. 0.28); null: clip_eps (symmetric)."""
    beta: float = 0.0
    """KL-to-reference coefficient; 0 loads no reference model (DAPO, Dr. GRPO); DeepSeekMath used 0.04."""
    kl_estimator: Literal["k1", "k2", "k3"] = "k3"
    """Per-token KL estimator in the loss (GRPO: k3)."""
    aggregation: Literal["seq_mean_token_mean", "token_mean", "seq_mean_token_sum_norm"] = "token_mean"
    """Loss normaliser: per-sequence token mean (GRPO), global token mean (DAPO), constant (Dr. GRPO)."""
    mu: int = 1
    """Optimisation passes over each batch of rollouts (GRPO's mu), against the sampling policy's log-probs."""
    minibatches: int = 1
    """Optimizer updates per pass (the batch is split into this many minibatches)."""
    old_logprobs: Literal["auto", "rollout", "recompute"] = "auto"
    """pi_old (detail 11): the engine's log-probs, a no-grad recompute by the trainer (some settings recompute
    regardless), or auto: recompute where the sampler's numerics are not the trainer's (bf16, vLLM)."""
    rollout_correction: Literal["none", "tis", "mask"] = "none"
    """Correct for a sampler that is not the trainer (detail 13): tis (weights min(w, cap)) or mask (IcePop)."""
    rollout_correction_level: Literal["token", "sequence"] = "token"
    """Weights per token, or per sequence (the geometric mean of its token ratios; gspo needs this)."""
    rollout_correction_cap: float = 2.0
    """C of rollout_correction (> 1)."""
    mask_truncated: bool = False
    """Give completions cut at max_new_tokens no loss (DAPO overlong filtering); they still count in their group."""
    zero_variance: Literal["keep", "skip", "resample"] = "skip"
    """Groups with identical rewards: keep them, skip them, or resample more prompts to refill (DAPO)."""
    max_resample_rounds: int = 2
    """Extra sampling rounds per step at most when zero_variance=resample."""
    prompt_sampling: Literal["uniform", "pass_rate"] = "uniform"
    """Which problems a step samples: uniform (seeded epochs) or pass_rate (detail 14; needs a verifier)."""
    curriculum_floor: float = 0.05
    """pass_rate: the smallest sampling weight (always-solved and never-solved problems keep this much)."""
    curriculum_decay: float = 0.5
    """pass_rate: EMA decay of each problem's pass rate (0: only its latest group)."""
    eval_rows: int = 100
    """Held-out problems for the periodic evaluation."""
    final_eval_rows: int = 200
    """Held-out problems for the SFT vs GRPO comparison (before and after training; 0 skips it)."""
    save_rollouts_every: int = 0
    """Steps between saving scored rollouts to rollouts/step-NNNNNN.jsonl (`posttrain rollouts DIR`); 0: never."""


def check_config(cfg: GRPOConfig) -> None:
    """Inconsistent settings are a ConfigError before anything runs."""
    def bad(msg: str) -> ConfigError:
        return ConfigError(f"grpo.{msg}")

    if cfg.prompts_per_step < 1 or cfg.group_size < 1:
        raise bad(f"prompts_per_step and group_size must be >= 1, got {cfg.prompts_per_step}, {cfg.group_size}")
    if cfg.estimator in ("grpo", "rloo") and cfg.group_size < 2:
        raise bad(f"group_size must be >= 2 for estimator={cfg.estimator} (a group baseline needs two samples)")
    if cfg.estimator == "reinforce_pp" and cfg.std_scale != "batch":
        raise bad(f"estimator=reinforce_pp normalises by the batch std by definition; set std_scale=batch "
                  f"(got {cfg.std_scale})")
    if cfg.std_scale == "group" and cfg.group_size < 2:
        raise bad("std_scale=group needs group_size >= 2")
    if cfg.clip_eps <= 0 or (cfg.clip_eps_high is not None and cfg.clip_eps_high <= 0):
        raise bad(f"clip_eps and clip_eps_high must be > 0, got {cfg.clip_eps}, {cfg.clip_eps_high}")
    if cfg.beta < 0:
        raise bad(f"beta must be >= 0, got {cfg.beta}")
    if not cfg.temperature > 0 or not 0 < cfg.top_p <= 1:
        raise bad(f"temperature must be > 0 (greedy groups have no variance) and top_p in (0, 1], got "
                  f"{cfg.temperature}, {cfg.top_p}")
    if cfg.mu < 1 or cfg.minibatches < 1 or cfg.micro_batch_size < 0 or cfg.max_new_tokens < 1:
        raise bad("mu, minibatches and max_new_tokens must be >= 1 and micro_batch_size >= 0")
    if cfg.minibatches > cfg.prompts_per_step * cfg.group_size:
        raise bad(f"minibatches={cfg.minibatches} exceeds the {cfg.prompts_per_step * cfg.group_size} rows of a step")
    if cfg.verifier_workers < 0 or cfg.verifier_timeout_s < 0 or cfg.max_resample_rounds < 0:
        raise bad("verifier_workers, verifier_timeout_s and max_resample_rounds must be >= 0")
    if cfg.policy_loss in ("gspo",) and cfg.aggregation != "seq_mean_token_mean":
        raise bad(f"policy_loss=gspo is a mean over sequences (GSPO eq. 5): set aggregation=seq_mean_token_mean "
                  f"(got {cfg.aggregation}), or use policy_loss=gspo_token for a token-level aggregation")
    if cfg.policy_loss == "gspo" and cfg.rollout_correction != "none" and cfg.rollout_correction_level != "sequence":
        raise bad("policy_loss=gspo has one ratio per sequence, so its rollout correction must be per sequence too: "
                  "set rollout_correction_level=sequence (or use policy_loss=gspo_token)")
    if cfg.prompt_sampling == "pass_rate" and cfg.verifier == "none":
        raise bad("prompt_sampling=pass_rate tracks each problem's pass rate, which needs a verifier (verifier=none)")
    if not 0 < cfg.curriculum_floor <= 1 or not 0 <= cfg.curriculum_decay < 1:
        raise bad(f"curriculum_floor must be in (0, 1] and curriculum_decay in [0, 1), got {cfg.curriculum_floor}, "
                  f"{cfg.curriculum_decay}")
    if not cfg.rollout_correction_cap > 1:
        raise bad(f"rollout_correction_cap must be > 1, got {cfg.rollout_correction_cap}")
    if cfg.verifier == "none" and cfg.reward_model == "none" and not cfg.env:
        raise bad("verifier=none and reward_model=none: there is no reward; set one of them")
    if cfg.env and (cfg.reward_model != "none" or cfg.verifier not in ("auto", "none")):
        raise bad(f"env={cfg.env!r} rewards whole episodes itself: leave verifier (auto) and reward_model (none) unset")


# ----------------------------------------------------------------------------- train
def train(res: Resolved, ensure) -> Path:
    """GRPO on the recipe's task from the SFT model; returns the final model directory."""
    cfg: GRPOConfig = res.stage_cfg
    check_config(cfg)
    with contextlib.ExitStack() as stack:
        run = setup(res, cfg, ensure, stack)  # problems and reward, models, optimizer, resume, the SFT baseline
        t_start = time.time()
        for step in range(run.start, cfg.max_steps):
            done, t_step = step + 1, time.time()
            saving = (cfg.save_every and done % cfg.save_every == 0) or done == cfg.max_steps
            evaluating = cfg.eval_every and done % cfg.eval_every == 0
            with loop.naming_checkpoint(run.ckpt):
                # ---- rollout and score, in rounds (DAPO dynamic sampling: more rounds until P informative groups)
                step_batch, scored, timing = rollout_rounds(run, step)
                m = _row_metrics(step_batch, cfg.group_size, run.reward.verifier_parts)
                if run.reward.env is not None:  # turns, tool calls and their errors, environment tokens
                    m.update(episode_metrics(step_batch.rollouts))
                if run.curriculum is not None:  # every process holds every group: the same table everywhere
                    run.curriculum.update(cfg, [run.index_of[p.key] for p in step_batch.problems],
                                          passed_flags(step_batch, run.reward))
                    m.update(run.curriculum.metrics())
                # ---- advantages of the kept groups; pi_old (when recomputed) and reference log-probs, no grad
                t0 = time.time()
                rows = loss_rows(cfg, step_batch, run.accelerator, run.tokenizer.pad_token_id,
                                 run.policy if run.recompute_old else None, run.ref_model, run.budget)
                m.update(apply_rollout_correction(cfg, rows))  # pi_old recomputed: the sampler's gap, the correction
                # ---- update: mu passes x minibatches of clipped-ratio steps
                m.update(update(cfg, run.accelerator, run.model, run.optimizer, run.scheduler, rows, step, run.budget,
                                sampler_old=not run.recompute_old))
                timing["train"] = time.time() - t0
                if saving or evaluating:
                    loop.check_weights(done, run.model)
            # ---- log: metrics.jsonl every step, problems in words, a console line every log_every steps
            m["verifier/scored"] = float(scored)  # distinct completions scored (duplicates reuse a score)
            m.update({f"time/{k}": v for k, v in timing.items()})
            m["time/step"] = time.time() - t_step
            log_step(run, done, m, step_batch, timing, time.time() - t_start)
            # ---- eval
            if run.main and run.held_out.n_eval and evaluating and done != cfg.max_steps:
                run.held_out.log_eval(run.policy, run.tokenizer, run.metrics, done, run.say)
            # ---- checkpoint (with the curriculum's table)
            if saving:
                run.ckpt.save(done, run.model, run.optimizer, run.scheduler, {"step": done},
                              None if run.curriculum is None else {"curriculum": run.curriculum.state()})
        return finish(run)


# ----------------------------------------------------------------------------- setup and the end of a run
@dataclass(kw_only=True)
class GRPORun:
    """What a run holds between steps (`setup`)."""

    res: Resolved
    cfg: GRPOConfig
    accelerator: Accelerator
    say: Callable[[str], None]  # prints on the main process
    run_dir: Path
    main: bool
    sft_dir: Path
    tokenizer: PreTrainedTokenizerBase
    model: torch.nn.Module  # as accelerate prepared it
    policy: torch.nn.Module  # the model inside the wrapper: generation, evaluation, saving
    ref_model: torch.nn.Module | None  # None when beta = 0
    budget: int  # padded tokens per micro-batch (memory)
    recompute_old: bool  # pi_old recomputed by the trainer (not the sampler's log-probs)
    optimizer: torch.optim.Optimizer
    scheduler: torch.optim.lr_scheduler.LRScheduler
    ckpt: loop.Checkpointer
    metrics: loop.MetricsLog
    problems: list[Problem]
    index_of: dict[int, int]  # a group's problem key -> its position in `problems`
    reward: Reward
    held_out: HeldOut
    curriculum: Curriculum | None
    rounds: int  # sampling rounds per step at most
    start: int  # the first step (resume)
    baseline: dict  # the SFT model's held-out numbers (main process)


def setup(res: Resolved, cfg: GRPOConfig, ensure, stack: contextlib.ExitStack) -> GRPORun:
    """Problems and the reward first (a bad row or a broken verifier stops before any model loads; the verifier
    pool lives in `stack`), then the earlier stages, the models, the optimizer, the resumed state and the SFT
    model's held-out numbers."""
    from posttrain.models import is_model_dir, load_model, load_reference, load_tokenizer, maybe_lora, token_budget
    from posttrain.rollout import default_backend
    from posttrain.verifiers.envs import ToolRunner
    from posttrain.verifiers.runner import VerifierPool

    P = cfg.prompts_per_step
    verifier, train_rows, train_source, problems, eval_problems = load_problems(res, cfg, "grpo")
    if cfg.reward_model not in ("none", "train") and not is_model_dir(cfg.reward_model):
        raise ConfigError(f"grpo.reward_model {cfg.reward_model!r} is not a model directory; give none, train or "
                          "the path of a reward model (posttrain rm output)")
    pool = stack.enter_context(VerifierPool(workers=cfg.verifier_workers, timeout_s=cfg.verifier_timeout_s or None))
    if verifier is not None:
        preflight(verifier, pool, train_rows, train_source, print)
    env = load_env(cfg, "grpo")
    rm_dir = ensure("rm") if cfg.reward_model == "train" else \
        (Path(cfg.reward_model) if cfg.reward_model != "none" else None)
    sft_dir = ensure("sft")

    accelerator, say = loop.start_run(res, cfg.seed, cfg.resume)
    run_dir, main, device = res.stage_dir(), accelerator.is_main_process, accelerator.device
    tokenizer = load_tokenizer(sft_dir, res.model)
    model = maybe_lora(res, load_model(sft_dir, res.model.dtype, device=device), say)  # LoRA: adapters start at 0
    budget = token_budget(res.run.micro_batch_tokens, model)  # padded tokens per micro-batch (memory)
    # beta = 0: no reference model at all; LoRA: the policy with its adapters off (no copy of the weights)
    ref_model = load_reference(res, model, sft_dir, device) if cfg.beta > 0 else None
    problems = tokenize_problems(tokenizer, problems, "training", cfg.max_new_tokens, res.model.max_length, say)
    eval_problems = tokenize_problems(tokenizer, eval_problems, "held-out", cfg.max_new_tokens,
                                      res.model.max_length, say)
    if len(problems) < P:
        raise loop.TrainingError(f"only {len(problems)} training prompts fit, fewer than prompts_per_step={P}")
    reward = build_env_reward(env, stack.enter_context(ToolRunner())) if env is not None else \
        build_reward(verifier, pool, rm_dir, device, timeout_s=cfg.verifier_timeout_s, on_error=cfg.on_verifier_error,
                     verifier_weight=cfg.verifier_weight, reward_model_weight=cfg.reward_model_weight)
    held_out = HeldOut(eval_problems, reward, cfg.max_new_tokens, min(cfg.eval_rows, len(eval_problems)),
                       min(cfg.final_eval_rows, len(eval_problems)),
                       start="base" if res.model.start_from == "base" else "SFT")
    # pi_old recomputed: asked for, or auto where the sampler is not the trainer, rollout correction (it weighs
    # pi_old against the sampler), a truncated sampler (top-p) at temperature != 1, or vLLM rollouts
    recompute_old = cfg.old_logprobs == "recompute" or cfg.rollout_correction != "none" \
        or (cfg.old_logprobs == "auto" and not sampler_is_trainer(accelerator, model)) \
        or (cfg.temperature != 1.0 and cfg.top_p < 1.0) or default_backend() == "vllm"
    optimizer = loop.build_optimizer(model, cfg.lr, cfg.weight_decay)
    scheduler = loop.build_scheduler(optimizer, cfg.warmup_steps, cfg.max_steps * cfg.mu * cfg.minibatches,
                                     cfg.schedule, cfg.min_lr_ratio)  # it counts optimizer updates
    model, optimizer = accelerator.prepare(model, optimizer)
    policy = accelerator.unwrap_model(model)
    ckpt = loop.Checkpointer(run_dir, cfg.keep_checkpoints, accelerator)
    metrics = loop.open_metrics(res, cfg.max_steps, main, "[grpo] ")
    state = loop.resume_run(ckpt, metrics, model, optimizer, scheduler, resume=cfg.resume, say=say, tag="grpo")
    start, saved = state["step"], state["extra"].get("curriculum")
    curriculum = None if cfg.prompt_sampling == "uniform" else Curriculum.fresh(len(problems)) if saved is None \
        else Curriculum(torch.tensor(saved["rates"]), torch.tensor(saved["seen"], dtype=torch.bool))
    baseline = held_out.sft_baseline(policy, tokenizer, run_dir / "sft_eval.json", start, metrics, say) if main else {}
    say(describe_run(cfg, reward, len(problems), rm_dir, recompute_old, accelerator.num_processes, device, budget))
    rounds = 1 + (cfg.max_resample_rounds if cfg.zero_variance == "resample" else 0)
    return GRPORun(res=res, cfg=cfg, accelerator=accelerator, say=say, run_dir=run_dir, main=main, sft_dir=sft_dir,
                   tokenizer=tokenizer, model=model, policy=policy, ref_model=ref_model, budget=budget,
                   recompute_old=recompute_old, optimizer=optimizer, scheduler=scheduler, ckpt=ckpt, metrics=metrics,
                   problems=problems, index_of={p.key: i for i, p in enumerate(problems)}, reward=reward,
                   held_out=held_out, curriculum=curriculum, rounds=rounds, start=start, baseline=baseline)


def finish(run: GRPORun) -> Path:
    """final/ (every process gathers a sharded model; the main process saves), the comparison with the SFT model
    and eval.json; returns final/."""
    from posttrain.models import save_model

    final = run.run_dir / "final"
    whole = loop.full_state_dict(run.accelerator, run.model)  # every process: gathers a sharded model (FSDP, ZeRO-3)
    if run.main:
        save_model(run.policy, run.tokenizer, final, state_dict=whole)
        run.say(f"[grpo] saved {final}")
        report = run.held_out.compare(run.policy, run.tokenizer, run.baseline, run.metrics, run.cfg.max_steps, run.say)
        loop.write_json(run.run_dir / "eval.json", {"model": str(final), "sft": str(run.sft_dir), **report})
        run.metrics.close(report)
    run.metrics.close()
    run.accelerator.wait_for_everyone()
    return final


# ----------------------------------------------------------------------------- rollout and score
def round_order_seed(seed: int, rnd: int) -> int:
    """The seed of `loop.batch_indices` for sampling round `rnd` of a step: the run's data order for the first,
    a stream of its own for each resampling round (zero_variance=resample)."""
    return seed if rnd == 0 else loop.stream_seed(seed, "grpo/resample-batch", rnd)


@dataclass
class Curriculum:
    """Detail 14: the pass-rate table over the training problems and the weighted draw of a round's prompts.

    Pass-rate curriculum (prompt_sampling=pass_rate, `advantages.track_pass_rates` / `curriculum_weights`): each
    problem's recent pass rate is tracked (an EMA over its groups) and the next prompts are drawn without
    replacement with weight 1 - p^K - (1 - p)^K, the chance that a group of K is informative, floored so none
    starves; unseen problems weigh 1. An option beside dynamic sampling (both can run); the pass-rate histogram
    of the pool is logged (curriculum/*) and the table is part of the checkpoint."""

    rates: torch.Tensor  # (N,) tracked pass rate per problem
    seen: torch.Tensor  # (N,) bool: sampled at least once

    @classmethod
    def fresh(cls, n: int) -> Curriculum:
        return cls(torch.zeros(n), torch.zeros(n, dtype=torch.bool))

    def pick(self, cfg: GRPOConfig, n: int, seed: int, exclude: list[int]) -> list[int]:
        """`n` problem indices, drawn without replacement by weight (`seed`: the round's stream, a function of
        (seed, step, round): resumable); the problems already drawn this step (`exclude`) are left out."""
        w = curriculum_weights(self.rates, self.seen, cfg.group_size, floor=cfg.curriculum_floor)
        w[torch.as_tensor(exclude, dtype=torch.long)] = 0.0
        gen = torch.Generator().manual_seed(seed)
        return torch.multinomial(w, min(n, int((w > 0).sum())), replacement=False, generator=gen).tolist()

    def update(self, cfg: GRPOConfig, index: list[int], passed: list[bool]) -> None:
        """Fold a step's groups (problem indices, K pass flags each, contiguous) into the table."""
        K = cfg.group_size
        rate = torch.tensor([sum(passed[g * K:(g + 1) * K]) / K for g in range(len(index))])
        self.rates, self.seen = track_pass_rates(self.rates, self.seen, torch.tensor(index, dtype=torch.long), rate,
                                                 cfg.curriculum_decay)

    def state(self) -> dict[str, list]:
        """The table as the checkpoint keeps it."""
        return {"rates": self.rates.tolist(), "seen": self.seen.tolist()}

    def metrics(self) -> dict[str, float]:
        """The pool's pass-rate histogram: fractions of all problems unseen, and of the seen ones never solved,
        below 1/2, at least 1/2 (not always) and always solved."""
        n, r = len(self.rates), self.rates[self.seen]
        k = max(1, len(r))
        return {"curriculum/unseen": 1.0 - len(r) / n, "curriculum/pass_0": float((r == 0).sum()) / k,
                "curriculum/pass_lt_half": float(((r > 0) & (r < 0.5)).sum()) / k,
                "curriculum/pass_ge_half": float(((r >= 0.5) & (r < 1)).sum()) / k,
                "curriculum/pass_1": float((r == 1).sum()) / k}


@dataclass
class StepBatch:
    """The scored rollouts of one step (all rounds), and which groups go into the loss."""

    rollouts: list  # list[Rollout], groups of K contiguous
    problems: list[Problem]  # one per group
    rewards: torch.Tensor  # (N,)
    parts: dict[str, list[float]]
    reasons: list[str]
    first_round_groups: int  # groups sampled in the first round (the zero-variance statistics use them)
    rounds: int

    @classmethod
    def of(cls, groups: list[Group], first_round_groups: int, rounds: int) -> StepBatch:
        parts: dict[str, list[float]] = collections.defaultdict(list)
        for g in groups:
            for k, v in g.parts.items():
                parts[k] += v
        return cls([r for g in groups for r in g.rollouts], [g.problem for g in groups],
                   torch.tensor([x for g in groups for x in g.rewards], dtype=torch.float32), dict(parts),
                   [x for g in groups for x in g.reasons], first_round_groups, rounds)


def rollout_rounds(run: GRPORun, step: int) -> tuple[StepBatch, int, dict[str, float]]:
    """The step's rollouts, in rounds: each round's global prompt batch (the data order, or the curriculum's draw),
    K samples per prompt, scored in the verifier pool and gathered (`problems.sample_and_score`: every process
    holds every group); with zero_variance=resample, more rounds until P groups are informative (DAPO dynamic
    sampling). Returns the step's batch, the distinct completions scored and this process's sample / score time.

    Checks run in a `posttrain.verifiers.runner.VerifierPool` under a hard time limit: a hung or crashing check
    scores 0 and the step goes on; one that raises scores 0 with its reason (on_verifier_error=zero) or stops the
    run (stop); a step where every check raised stops the run. Identical completions of a prompt are scored once
    (a sandboxed check is costly). Several processes (`posttrain.sharding`'s convention): process r samples and
    scores positions r, r + W, ... of each round's global prompt batch (a group never spans processes); the
    scored groups are gathered after every round, so every decision and statistic (resampling, advantages,
    metrics) is global; each minibatch is split over the processes by `sharding.micro_batches` (`update`).
    Evaluation, logs and final/ are the main process's."""
    from posttrain.rollout import SamplingParams

    cfg, K, P = run.cfg, run.cfg.group_size, run.cfg.prompts_per_step
    groups, scored, first_round, drawn = [], 0, 0, []
    timing: dict[str, float] = collections.defaultdict(float)
    for rnd in range(run.rounds):
        idx = loop.batch_indices(len(run.problems), P, round_order_seed(cfg.seed, rnd), step) \
            if run.curriculum is None else \
            run.curriculum.pick(cfg, P, loop.stream_seed(cfg.seed, "grpo/curriculum", step, rnd), drawn)
        drawn += idx
        params = SamplingParams(n=K, max_new_tokens=cfg.max_new_tokens, temperature=cfg.temperature, top_p=cfg.top_p,
                                seed=loop.stream_seed(cfg.seed, "grpo/sample", step, rnd))
        got = sample_and_score(run.accelerator, run.policy, run.tokenizer, run.problems, idx, params, run.reward, step)
        timing["sample"] += got.sample_s
        timing["score"] += got.score_s
        groups, scored, first_round = groups + got.groups, scored + got.scored, first_round or len(got.groups)
        step_batch = StepBatch.of(groups, first_round, rnd + 1)
        if int((~zero_variance_groups(step_batch.rewards, K)).sum()) >= P:  # informative groups
            break
    return step_batch, scored, timing


# ----------------------------------------------------------------------------- advantages and update
def sampler_is_trainer(accelerator, model) -> bool:
    """Whether the rollout engine computes the trainer's own log-probs (old_logprobs=auto takes them, detail 11):
    fp32 weights sampled by the built-in engine in fp32, trained without autocast. bf16 rollout weights, bf16 /
    fp16 autocast, half model weights or vLLM each give another distribution (mismatch/kl 0.002-0.01 on smol-math
    in bf16, against ~4e-9 in fp32)."""
    from posttrain.rollout import default_backend, default_dtype

    weights = {p.dtype for p in model.parameters()}
    return (default_backend() != "vllm" and default_dtype() == "float32" and accelerator.mixed_precision == "no"
            and weights == {torch.float32})


def loss_rows(cfg: GRPOConfig, step_batch: StepBatch, accelerator, pad_id: int, old_model, ref_model,
              budget: int = 0) -> dict[str, torch.Tensor] | None:
    """The rows of the loss: the kept groups' tokens, loss mask and group advantages, pi_old (the engine's, or
    recomputed by `old_model`) and the reference log-probs (beta > 0); None when no group is kept. The no-grad
    log-probs are computed in shards (micro-batches of at most `budget` padded tokens) and gathered: every
    process holds every row.

    Detail 11: pi_old from the rollout engine (old_logprobs=rollout: no extra forward) is the raw log-probs at
    temperature 1, else those of softmax(logits / T), the distribution the loss uses (TRL, verl). With top_p < 1,
    old_logprobs=recompute, rollout_correction or vLLM rollouts (`posttrain.rollout.vllm_backend`): one batched
    no-grad forward of the trainer, and the sampler's log-probs are compared with it on every row."""
    from posttrain.rollout import collate_rollouts

    K = cfg.group_size
    zv = zero_variance_groups(step_batch.rewards, K)  # (G,)
    keep = torch.ones_like(zv) if cfg.zero_variance == "keep" else ~zv  # (G,)
    if cfg.zero_variance == "resample":
        keep &= torch.cumsum(keep.long(), 0) <= cfg.prompts_per_step  # refill up to P groups, no more
    rows_idx = [g * K + j for g in keep.nonzero().flatten().tolist() for j in range(K)]
    if not rows_idx:
        return None
    adv = group_advantages(step_batch.rewards[rows_idx], K, estimator=cfg.estimator, std_scale=cfg.std_scale)  # (n,)
    batch = collate_rollouts([step_batch.rollouts[i] for i in rows_idx], pad_id).to(accelerator.device)
    loss_mask = batch.completion_mask.clone()  # (n, T)
    if cfg.mask_truncated:  # DAPO overlong filtering: truncated completions carry no loss
        loss_mask[torch.tensor([step_batch.rollouts[i].finish_reason == "length" for i in rows_idx],
                               device=loss_mask.device)] = 0
    # pi_old from the engine: raw log-probs at temperature 1, or (temperature != 1, no top-p) the log-probs
    # of the distribution it sampled, softmax(logits / T), which is the one the loss uses; else recomputed.
    sampler_logps = batch.policy_logprobs if cfg.temperature == 1.0 else batch.logprobs  # (n, T)
    rows = {"input_ids": batch.input_ids, "attention_mask": batch.attention_mask, "loss_mask": loss_mask,
            "advantages": adv.to(accelerator.device), "old_logps": sampler_logps}
    micro = cfg.micro_batch_size or len(rows_idx)
    if old_model is not None:  # the trainer's pi_old; the sampler's stay for `apply_rollout_correction`
        rows["old_logps"] = sharding.sharded_logprobs(accelerator, old_model, batch, micro, cfg.temperature, budget)
        rows["sampler_logps"] = sampler_logps
    if ref_model is not None:
        rows["ref_logps"] = sharding.sharded_logprobs(accelerator, ref_model, batch, micro, cfg.temperature, budget)
    return rows


def apply_rollout_correction(cfg: GRPOConfig, rows: dict[str, torch.Tensor] | None) -> dict[str, float]:
    """Where pi_old was recomputed by the trainer, the sampler's log-probs are a second opinion: the gap between
    the two over every row (`losses.sampler_mismatch`: mismatch/kl, mismatch/max_ratio, mismatch/min_ratio) and,
    with rollout_correction, the importance weights `rows["is_weights"]` and the loss mask without the tokens
    it drops (`losses.rollout_correction`); their metrics. The rows change in place.

    Detail 13: the sampler (bf16 rollout weights, vLLM) is not the trainer, so pi_old is recomputed by the trainer
    and each token's loss is weighted by w = pi_old / pi_sampler truncated at C (tis: Yao et al. 2025) or dropped
    when w leaves [1/C, C] (mask: IcePop), per token or per sequence. Every step where the sampler's log-probs can
    be compared with the trainer's logs the gap (mismatch/kl = KL(sampler || trainer), k3; mismatch/max_ratio,
    mismatch/min_ratio): ~0 with the built-in fp32 engine, which samples with the trainer's own forward, by
    construction (tested below 1e-6)."""
    sampler = None if rows is None else rows.pop("sampler_logps", None)
    if sampler is None:
        return {}
    m = sampler_mismatch(rows["old_logps"], sampler, rows["loss_mask"])
    weights, keep, cm = rollout_correction(rows["old_logps"], sampler, rows["loss_mask"], kind=cfg.rollout_correction,
                                           level=cfg.rollout_correction_level, cap=cfg.rollout_correction_cap)
    rows["loss_mask"] = keep.to(rows["loss_mask"].dtype)
    if weights is not None:
        rows["is_weights"] = weights
    return {**m, **cm}


def grpo_loss(cfg: GRPOConfig, model, mb: dict[str, torch.Tensor], scale: float,
              with_entropy: bool, mismatch: bool = False) -> tuple[torch.Tensor, dict[str, float]]:
    """The GRPO loss of one micro-batch (policy term + beta * KL term, same aggregation), times `scale`.
    `mismatch`: also the sampler-trainer gap `losses.sampler_mismatch` (old_logps are the sampler's and the weights
    are the ones it sampled with: the first minibatch of the first pass).

    Detail 12: on-policy (mu = 1, minibatches = 1, pi_old the sampler) every ratio is 1 and, with aggregation
    seq_mean_token_mean, all four policy losses give the same gradient (tested); they differ in the later updates
    of a batch (mu > 1 or minibatches > 1) and under a mismatched sampler."""
    loss_mask = mb["loss_mask"]
    logps, entropy = sequence_logprobs(model, mb["input_ids"], mb["attention_mask"], loss_mask,
                                       temperature=cfg.temperature, return_entropy=with_entropy,
                                       entropy_grad=False)  # (b, T); the entropy is a metric here
    loss, m = policy_loss(cfg.policy_loss, logps, mb["old_logps"], mb["advantages"], loss_mask, clip_eps=cfg.clip_eps,
                          clip_eps_high=cfg.clip_eps_high, aggregation=cfg.aggregation, max_tokens=cfg.max_new_tokens,
                          weights=mb.get("is_weights"))
    m = {"policy_loss": float(loss.detach()), **m}
    if cfg.beta > 0:
        kl = kl_penalty(logps, mb["ref_logps"], cfg.kl_estimator)  # (b, T)
        kl_loss = aggregate_token_loss(kl, loss_mask, cfg.aggregation, cfg.max_new_tokens)
        loss = loss + cfg.beta * kl_loss
        m["kl"] = float(masked_mean(kl.detach(), loss_mask.bool()))
    if with_entropy:
        m["entropy"] = float(masked_mean(entropy.detach(), loss_mask.bool()))
    if mismatch:
        m.update(sampler_mismatch(logps, mb["old_logps"], loss_mask))
    return loss * scale, m


def micro_batch_loss(cfg: GRPOConfig, model, world: int, with_entropy: bool, mismatch: bool,
                     micro_batch: tuple[dict, float, float]) -> tuple[torch.Tensor, dict[str, float]]:
    """`grpo_loss` of one of `sharding.micro_batches`, scaled to its loss share times W (DDP averages gradients).
    `loop.optimizer_step` weighs the token-mean metrics by the loss-token shares; the policy loss is reported as
    this micro-batch's part of the minibatch's aggregation (`policy_loss_sum`: summed over micro-batches and
    processes, it is the minibatch's policy loss)."""
    mb, share, _ = micro_batch
    loss, m = grpo_loss(cfg, model, mb, share * world, with_entropy, mismatch)
    m["policy_loss_sum"] = m.pop("policy_loss") * share
    return loss, m  # a non-finite loss on any process stops every process (loop.optimizer_step)


def update(cfg: GRPOConfig, accelerator, model, optimizer, scheduler, rows: dict[str, torch.Tensor] | None,
           step: int, budget: int = 0, sampler_old: bool = True) -> dict[str, float]:
    """mu passes x minibatches optimizer updates over `rows`; the update metrics. `sampler_old`: pi_old is the
    sampler's log-probs (not recomputed), so the first minibatch also measures `mismatch/kl`.

    Every process holds the same rows, so the row order of each pass (seeded by step and pass) and the
    minibatches are the same everywhere; `sharding.micro_batches` gives process r rows r, r + W, ... of each.
    Non-finite loss, gradient or weights stop the run naming the step and the last good checkpoint (intact;
    `loop.optimizer_step`, and `loop.check_weights` in the loop)."""
    if rows is None:
        return {"loss": 0.0, "rows/trained": 0.0, "updates": 0.0}
    usable = (rows["loss_mask"].sum(-1) > 0).nonzero().flatten().cpu()  # rows with at least one loss token
    upd: dict[str, list[float]] = collections.defaultdict(list)
    for epoch in range(cfg.mu if len(usable) else 0):
        gen = torch.Generator().manual_seed(loop.stream_seed(cfg.seed, "grpo/minibatch", step, epoch))
        order = usable[torch.randperm(len(usable), generator=gen)]
        for i, mb_idx in enumerate(torch.tensor_split(order, min(cfg.minibatches, len(usable)))):
            mbs = sharding.micro_batches(rows, mb_idx.to(accelerator.device), cfg.micro_batch_size, cfg.aggregation,
                                         accelerator.process_index, accelerator.num_processes, budget)
            loss_fn = functools.partial(micro_batch_loss, cfg, model, accelerator.num_processes, epoch == 0,
                                        sampler_old and epoch == 0 and i == 0)
            out = loop.optimizer_step(accelerator, model, optimizer, scheduler, mbs, loss_fn, cfg.max_grad_norm,
                                      step + 1, weights=[tokens for _, _, tokens in mbs])
            for k, v in out.items():
                upd[k].append(v)
    pick = {"max": max, "min": min, "": lambda v: sum(v) / len(v)}
    m = {k.removesuffix("_sum"): pick[loop.metric_extreme(k)](v) for k, v in upd.items()}
    m.update({"rows/trained": float(len(usable)), "updates": float(len(upd.get("loss", [])))})
    m.setdefault("loss", 0.0)
    return m


# ----------------------------------------------------------------------------- log
def log_step(run: GRPORun, done: int, m: dict[str, float], step_batch: StepBatch, timing: dict[str, float],
             elapsed: float) -> None:
    """metrics.jsonl every step, the step's problems in words, a console line every log_every steps, the scored
    rollouts every save_rollouts_every steps."""
    cfg = run.cfg
    run.metrics.log(done, m, console=False)
    for note in step_notes(done, m, step_batch, cfg.group_size, run.reward):
        run.say(note)
    if run.main and not run.res.run.quiet and (done % cfg.log_every == 0 or done == cfg.max_steps):
        print(progress_line(done, cfg.max_steps, m, timing, elapsed, run.start), flush=True)
    if run.main and cfg.save_rollouts_every and done % cfg.save_rollouts_every == 0:
        table = save_scored_rollouts(cfg, step_batch, run.run_dir, done)
        run.metrics.log_table("rollouts", table, done)


def describe_run(cfg: GRPOConfig, reward: Reward, n_problems: int, rm_dir: Path | None, recompute_old: bool,
                 world: int, device, budget: int = 0) -> str:
    from posttrain.rollout import default_backend

    desc = " + ".join(x for x in (
        (f"{cfg.verifier_weight:g} * " if reward.rm_scorer is not None else "") + f"verifier {reward.verifier.name}"
        if reward.verifier is not None else "",
        f"{cfg.reward_model_weight:g} * reward model {rm_dir}" if reward.rm_scorer is not None else "",
        f"environment {reward.env.name} (episodes of at most {reward.env.limits.max_turns} turns, tools: "
        f"{', '.join(reward.env.tool_functions()) or 'none'})" if reward.env is not None else "") if x)
    return (f"[grpo] {n_problems} training problems, {cfg.prompts_per_step} prompts x {cfg.group_size} samples per "
            f"step, {cfg.max_steps} steps ({cfg.mu} pass(es) x {cfg.minibatches} update(s) each); reward: {desc}; "
            f"{cfg.estimator} advantages ({cfg.std_scale} std), {cfg.policy_loss} policy loss, {cfg.aggregation}, "
            + (f"rollout correction {cfg.rollout_correction} ({cfg.rollout_correction_level}, cap "
               f"{cfg.rollout_correction_cap:g}), " if cfg.rollout_correction != "none" else "")
            + f"beta {cfg.beta}, zero-variance "
            f"groups: {cfg.zero_variance}; rollouts: {default_backend()} backend"
            + (" (pi_old recomputed)" if recompute_old else "") + f"; {world} process(es) on {device}"
            + (f"; micro-batches <= {budget} tokens" if budget else ""))


def _row_metrics(step_batch: StepBatch, K: int, verifier_parts: set[str]) -> dict[str, float]:
    """Reward, pass rates, zero-variance fraction, length and truncation of the first round's rows."""
    n = step_batch.first_round_groups * K
    r = step_batch.rewards[:n]
    zv = zero_variance_groups(r, K)
    lengths = [len(x.completion_ids) for x in step_batch.rollouts[:n]]
    m: dict[str, float] = {
        "reward/mean": float(r.mean()), "reward/std": float(r.std()) if n > 1 else 0.0,
        "zero_var_frac": float(zv.float().mean()),
        "completion/length": sum(lengths) / n, "completion/max_length": float(max(lengths)),
        "completion/truncated": sum(x.finish_reason == "length" for x in step_batch.rollouts[:n]) / n,
    }
    for name, values in step_batch.parts.items():
        v = values[:n]
        m[f"reward/{name}"] = sum(v) / n
        if name in verifier_parts:
            m[f"pass/{name}"] = sum(x >= 1.0 for x in v) / n
    reasons = step_batch.reasons[:n]
    m["tokens/generated"] = float(sum(len(x.completion_ids) for x in step_batch.rollouts))  # every round's
    m["verifier/timeouts"] = float(sum("timeout" in x for x in reasons))
    m["verifier/crashes"] = float(sum("crashed" in x for x in reasons))
    m["verifier/errors"] = float(sum("verifier error" in x for x in reasons))
    if step_batch.rounds > 1:
        m["resample/rounds"] = float(step_batch.rounds)
        m["zero_var_frac/all_rounds"] = float(zero_variance_groups(step_batch.rewards, K).float().mean())
    return m


def degenerate_message(step: int, step_batch: StepBatch, K: int, passed: list[bool] | None) -> str | None:
    """Words for a step where every group got identical rewards (the loss is ~0: nothing to learn).

    `passed`: per completion, whether the correctness verifier passed it (None: no verifier)."""
    zv = zero_variance_groups(step_batch.rewards, K)
    if not bool(zv.all()):
        return None
    values = sorted({round(float(x), 4) for x in step_batch.rewards})
    common = collections.Counter(x for x in step_batch.reasons if x).most_common(1)
    if passed is not None and not any(passed):
        why = ("no completion is correct: the problems are too hard for the policy now, or the verifier rejects "
               "its format")
    elif passed is not None and all(passed):
        why = "every completion is correct: these problems are too easy to teach anything"
    else:
        why = "within each group all rewards are equal"
    reason = f"; most common reason: {common[0][0]!r} ({common[0][1]}x)" if common else ""
    return (f"[grpo] step {step}: all {len(zv)} groups have zero reward variance (rewards {values[:4]}): the "
            f"advantages are 0, so the policy-gradient loss is ~0 and this step teaches nothing - {why}{reason}")


def passed_flags(step_batch: StepBatch, reward: Reward) -> list[bool] | None:
    """Per completion of `step_batch`, whether the correctness verifier passed it: the first term of a composition,
    else the whole verdict; None without a verifier."""
    if reward.verifier is None:
        return None
    parts = step_batch.parts
    src = parts.get(reward.prefix + reward.correctness) if reward.correctness else parts.get("verifier")
    return [x >= 1.0 for x in (src if src is not None else step_batch.rewards.tolist())]


def step_notes(done: int, m: dict[str, float], step_batch: StepBatch, K: int, reward: Reward) -> list[str]:
    """What a user asks when a run misbehaves, in words: verifier errors, timeouts and crashes, no signal."""
    notes = []
    if m["verifier/errors"]:
        i = next(j for j, x in enumerate(step_batch.reasons) if "verifier error" in x)
        notes.append(f"[grpo] step {done}: the verifier raised on {int(m['verifier/errors'])} of "
                     f"{len(step_batch.reasons)} "
                     f"completions, scored 0 (e.g. training problem row {step_batch.problems[i // K].key + 1}: "
                     f"{step_batch.reasons[i]})")
    if m["verifier/timeouts"] or m["verifier/crashes"]:
        notes.append(f"[grpo] step {done}: {int(m['verifier/timeouts'])} verifier timeouts and "
                     f"{int(m['verifier/crashes'])} crashes, scored 0 (the step went on)")
    degenerate = degenerate_message(done, step_batch, K, passed_flags(step_batch, reward))
    return notes + ([degenerate] if degenerate else [])


def progress_line(done: int, total: int, m: dict[str, float], timing: dict[str, float], elapsed: float,
                  start: int) -> str:
    eta = elapsed / max(1, done - start) * (total - done)
    shown = [("reward", m["reward/mean"]), ("zero_var", m["zero_var_frac"]), ("loss", m["loss"]),
             ("clip", m.get("clip_frac")), ("kl", m.get("kl")), ("entropy", m.get("entropy")),
             ("mismatch", m.get("mismatch/kl")), ("len", m["completion/length"]), ("trunc", m["completion/truncated"])]
    return (f"[grpo] step {done}/{total} " + " ".join(f"{k} {v:.4g}" for k, v in shown if v is not None)
            + f" | {m['time/step']:.2f}s (sample {timing['sample']:.2f}, score {timing['score']:.2f}, "
            f"train {timing['train']:.2f}), {elapsed:.0f}s elapsed, eta {eta:.0f}s")


def save_scored_rollouts(cfg: GRPOConfig, step_batch: StepBatch, run_dir: Path, step: int) -> list[dict]:
    """The step's rollouts (every round) with what a reader asks of each: the prompt, the reward and each
    reward part, the verifier's reason, the group advantage, whether its group was degenerate (`posttrain
    rollouts RUN_DIR` prints them). Returns them as table rows (for the trackers that show tables)."""
    from posttrain.rollout.records import save_step_rollouts

    K = cfg.group_size
    adv = group_advantages(step_batch.rewards, K, estimator=cfg.estimator, std_scale=cfg.std_scale).tolist()
    degenerate = zero_variance_groups(step_batch.rewards, K).tolist()
    for i, (r, reward, reason) in enumerate(zip(step_batch.rollouts, step_batch.rewards.tolist(), step_batch.reasons)):
        r.reward = reward
        r.prompt = step_batch.problems[i // K].prompt
        r.extras.update(reason=reason, advantage=adv[i], zero_variance_group=bool(degenerate[i // K]),
                        parts={k: v[i] for k, v in step_batch.parts.items()})
    return save_step_rollouts(step_batch.rollouts, run_dir, step)
