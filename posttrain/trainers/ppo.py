"""PPO for RLHF (Ziegler et al. 2019; Stiennon et al. 2020; Ouyang et al. 2022) on the shared rollout engine.

CPU:        posttrain ppo --recipe tiny-summarize   (from nothing: SFT, pairs, reward model, PPO, eval; see the recipe)
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain ppo --recipe tiny-summarize model.path=/path/to/hf-model
            (2 CPU processes: accelerate launch --config_file recipes/launch/cpu-2proc.yaml -m posttrain ppo
            --recipe tiny-summarize run.threads=1; tested against one process in tests/posttrain/test_distributed.py)
LoRA:       posttrain ppo --recipe tiny-summarize lora.enabled=true
Tools:      posttrain ppo --recipe tiny-calc env=calc reward=env value_init=policy   (multi-turn episodes, detail 20)

Implementation details, numbered as in Huang et al. ("The N Implementation Details of RLHF with PPO", 2022; "The N+
Implementation Details of RLHF with PPO: A Case Study on TL;DR Summarization", 2024); each flag's effect is tested in
tests/posttrain/trainers/test_ppo.py (the losses and GAE themselves in test_losses.py and test_advantages.py):
 1. Reward normalisation (`reward_norm`): "init" to mean 0 / std 1 of `reward_norm_prompts` SFT samples measured
    before training (lm-human-preferences, Ziegler et al. 2019 §2.2); "batch": each batch whitened; "none".
 2. Reward clipping (`reward_clip`): normalised scores clipped to [-c, c] (0: off).
 3. EOS trick (`missing_eos_penalty`): subtracted from the score of a completion that never ends (TRL's; Huang
    2024 set it to -1 instead).
 4. KL as a per-token reward (`kl_estimator`, `kl_coef`; InstructGPT eq. 2): -beta * KL_t (Schulman's k1 or k3)
    at every completion token, plus the score at the last one (`advantages.rewards_with_kl`).
 5. Adaptive KL controller (`kl_control`, `kl_target`, `kl_horizon`): Ziegler et al. 2019's, on the mean k1 KL.
 6. Reward whitening (`whiten_rewards`, off): TRL's, per-token rewards whitened over the batch, mean kept.
 7. GAE (`gamma`, `lam`): gamma = 1 (Huang 2022: no discount inside a completion), lam = 0.95.
 8. Advantage whitening (`whiten_advantages`): over the batch's completion tokens, after GAE (`masked_whiten`).
 9. Clipped surrogate (`clip_eps`), token-mean aggregation (`losses.ppo_policy_loss`); `policy_loss` swaps in the
    token-level members of GRPO's family (`losses.policy_loss`): cispo (CISPO's clipped stop-gradient weight)
    or gspo_token (GSPO-token; sequence-level gspo needs one advantage per sequence and GAE gives one per token).
10. Value clipping (`value_clip`): around the rollout-time values (`losses.value_loss`; 0: plain squared error).
11. Value model init (`value_init`): "reward" copies the reward model (lm-human-preferences; Huang 2022); "policy"
    is the SFT transformer under a new, seeded head.
12. Separate policy and value networks with their own AdamW (not a flag): `value_lr`, no vf_coef (Adam undoes it).
13. Dropout disabled (`disable_dropout`; LoRA dropout too) in policy, value and reference (Huang 2022).
14. Logits divided by the sampling temperature (`scale_logits_by_temperature`; Huang 2022) in every update log-prob.
15. No top-k / top-p at rollout time (not a flag): the engine's log-probs stay the policy's.
16. Old log-probs recomputed after the rollout (not a flag): the first ratio is exactly 1. The sampler's own log-probs
    are compared with them: rollout/logprob_gap (max abs), mismatch/kl (KL(sampler || trainer), k3; > 0 with
    rollout.dtype=bfloat16 or run.mixed_precision=bf16), mismatch/max_ratio and min_ratio; `rollout_correction`
    (tis / mask, `losses.rollout_correction`) weighs or drops the policy loss's tokens by pi_old / pi_sampler, as
    GRPO's detail 13 (the value loss keeps every token).
17. Entropy bonus (`entropy_coef`): 0 by default, as in the RLHF implementations Huang et al. study.
18. Several epochs (`ppo_epochs`) of minibatches (`minibatch_size`), reshuffled every epoch (seeded).
19. Learning-rate annealing (`schedule`): linear to 0 over all optimizer steps by default.
20. Multi-turn episodes (`env`, `env_options`, reward=env; tests/posttrain/trainers/test_ppo_env.py): a rollout is
    an episode in a tool-use environment, sampled by the driver GRPO and distillation use too
    (`problems.sample_and_score` over `rollout.multiturn.generate_episodes`; `problems.load_env`): turn 1's sampled
    tokens, the environment's tokens (tool results, the next assistant header), turn 2's sampled tokens, ...; the
    score (details 1-3) is the environment's final reward. Sampled tokens are the actions and the only time
    steps: the KL penalty, the per-token rewards (`advantages.turn_rewards_with_kl`: each turn's reward, when the
    environment gives one, at that turn's last sampled token, the score at the episode's last one), GAE (`gae`
    steps over environment tokens, so a turn's last token bootstraps from the value at the next turn's first
    sampled token; verl and OpenRLHF treat environment tokens so), advantage whitening, the policy and entropy
    terms and the value loss all cover sampled tokens only. Environment tokens are context: the old, reference
    and updated log-probs and the values are computed over the whole trajectory, and the values at environment
    tokens are neither read nor trained. Held-out evaluation is greedy episodes (`problems.HeldOut`: eval/reward,
    eval/accuracy, eval/env/*) against the SFT model's, and every iteration logs env/* (turns, tool calls, errors,
    tokens). Rule: reward=env if and only if env is set; value_init=policy (there is no reward model to copy) and
    no reward_model. Not supported: per-turn rewards are not shaped (details 1-3 shape the final score only: with
    reward_norm on, a turn's reward and the normalised score are on different scales); `max_new_tokens` does not
    apply (the environment's limits do); no win-rate, gold or proxy curve (the environment's reward is the
    measure); turns are not time steps of their own (no turn-level value or discount: gamma counts tokens).

`save_rollouts_every` writes an iteration's samples with their raw and shaped scores, KL penalty and mean advantage
to rollouts/step-NNNNNN.jsonl (`posttrain rollouts RUN_DIR`), and sends them as a table to trackers that show tables.

Departures: one completion per prompt (no groups); no reward-model training during PPO; rewards come through
`posttrain.scoring` (`RewardModelScorer`, or `GoldScorer` with reward=gold) from the completion TEXT, re-tokenised
as the reward model was trained, while the value model reads the sampled ids. A non-finite loss, gradient or weight
stops the run naming the iteration; the last good checkpoint stays. In memory: policy, value, frozen reference, RM.

Several processes follow posttrain/sharding.py: `rollout_batch_size` and `minibatch_size` are global (minibatch_size
a multiple of the processes), everything computed from the gathered batch is global, `sharding.token_share` gives
DDP the whole minibatch's gradient (also when `run.micro_batch_tokens` splits a minibatch into micro-batches);
the main process evaluates and writes metrics.jsonl, final/ and eval.json.

LoRA (`models.maybe_lora`): policy and value model (SEQ_CLS: its head trains fully) get adapters; the reference is
the policy with them off (`models.reference_view`): 3 sets of base weights. final/ is saved merged. See RESULTS.md.
In an environment (detail 20) every process runs its rows' episodes (a row's episode depends only on its prompt
key and the iteration's seed) and the rollouts are gathered as above; the tool calls run in one `ToolRunner`.
"""
from __future__ import annotations

import contextlib
import math
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Callable, Literal

import numpy as np
import torch

from posttrain import evaluation, loop, models, sharding, tasks
from posttrain.advantages import AdaptiveKLController, FixedKLController, gae, rewards_with_kl, turn_rewards_with_kl
from posttrain.config import ConfigError, Resolved
from posttrain.data import row_spans, token_groups
from posttrain.lean import train as lean
from posttrain.lean.support import lean_support
from posttrain.logprobs import masked_mean, masked_sum, masked_whiten, sequence_logprobs
from posttrain import losses
from posttrain.losses import kl_penalty, rollout_correction, sampler_mismatch, value_loss
from posttrain.problems import HeldOut, Problem, build_env_reward, env_problem, load_env, sample_and_score
from posttrain.rollout import SamplingParams, collate_rollouts, generate
from posttrain.rollout.multiturn import episode_metrics
from posttrain.scoring import GoldScorer, RewardModelScorer

if TYPE_CHECKING:  # annotations only
    from accelerate import Accelerator
    from transformers import PreTrainedTokenizerBase

    from posttrain.verifiers.envs import Environment, ToolRunner


@dataclass
class PPOConfig(loop.TrainingBase):
    reward: Literal["rm", "gold", "env"] = "rm"
    """rm: the reward model (reward_model, else the rm stage output, built if missing); gold: the task's gold scorer;
    env: the final reward of `env`'s episodes (set with env, and only with it)."""
    env: str = ""
    """A multi-turn environment with tools ("calc", an entry point, or "file.py:Name"; `posttrain envs` lists them),
    with reward=env and value_init=policy: each rollout is an episode (detail 20); per-turn rewards are credited to
    their turns; the losses cover sampled tokens only. Empty: single completions."""
    env_options: dict[str, Any] = field(default_factory=dict)
    """Keyword options of the environment, its limits included (e.g. {max_turns: 3, tool_timeout_s: 2})."""
    reward_model: str = ""
    """Reward-model directory; empty: runs/<recipe>/rm/final (with reward=gold only the proxy curve, if it exists)."""
    rollout_batch_size: int = 64
    """Training prompts per iteration (one sampled completion each; global, across processes)."""
    minibatch_size: int = 16
    """Rollouts per optimizer step (each model steps once per minibatch; global, a multiple of the processes);
    forward in micro-batches of at most `run.micro_batch_tokens` padded tokens (auto: ~2 GiB of activations)."""
    ppo_epochs: int = 2
    """Passes over each rollout batch, minibatches reshuffled every pass."""
    value_lr: float = 1e-4
    """Value-model learning rate (its own AdamW; replaces a value-loss coefficient)."""
    temperature: float = 1.0
    """Rollout sampling temperature (no top-k / top-p: the full distribution is sampled)."""
    scale_logits_by_temperature: bool = True
    """Divide logits by temperature for every log-prob of the update (old, new, reference); off: temperature 1."""
    max_new_tokens: int = 64
    """Rollout and evaluation generation budget (not with env: the environment's limits apply)."""
    gamma: float = 1.0
    """GAE discount."""
    lam: float = 0.95
    """GAE lambda."""
    clip_eps: float = 0.2
    """Policy ratio clipping range."""
    policy_loss: Literal["clip", "gspo_token", "cispo"] = "clip"
    """clip (PPO's surrogate), cispo (CISPO), gspo_token (GSPO-token); sequence-level gspo is GRPO's only (it needs
    one advantage per sequence, and GAE gives one per token)."""
    rollout_correction: Literal["none", "tis", "mask"] = "none"
    """Sampler-trainer correction of the policy loss: tis (weights min(w, cap)), mask (drop w outside [1/cap, cap])."""
    rollout_correction_level: Literal["token", "sequence"] = "token"
    """Per token, or per sequence (geometric mean of its token ratios)."""
    rollout_correction_cap: float = 2.0
    """C of rollout_correction (> 1)."""
    value_clip: float = 0.2
    """Value clipping range around the rollout-time values (0: unclipped squared error)."""
    entropy_coef: float = 0.0
    """Entropy bonus: loss -= entropy_coef * mean token entropy of the policy."""
    kl_estimator: Literal["k1", "k3"] = "k1"
    """Per-token KL penalty estimator (Schulman): k1 = log pi - log pi_ref, k3 = r - 1 - log r."""
    kl_coef: float = 0.05
    """KL penalty coefficient (the starting value under kl_control=adaptive)."""
    kl_control: Literal["fixed", "adaptive"] = "fixed"
    """fixed kl_coef, or Ziegler et al.'s adaptive controller toward kl_target."""
    kl_target: float = 6.0
    """Adaptive controller: target mean per-sequence KL (nats)."""
    kl_horizon: int = 10000
    """Adaptive controller: horizon in samples (coefficient moves by at most 20% per horizon)."""
    reward_norm: Literal["init", "batch", "none"] = "init"
    """init: scale scores to mean 0 / std 1 of SFT samples measured before training; batch: whiten each batch; none."""
    reward_norm_prompts: int = 128
    """reward_norm=init: training prompts sampled from the SFT model to measure the reward statistics."""
    reward_clip: float = 5.0
    """Clip shaped scores to [-reward_clip, reward_clip] (0: off)."""
    missing_eos_penalty: float = 1.0
    """Subtracted from the (normalised) score of a completion that hit max_new_tokens without ending (0: off)."""
    whiten_rewards: bool = False
    """Whiten the per-token rewards (mean kept) over the batch before GAE (TRL's whiten_rewards)."""
    whiten_advantages: bool = True
    """Whiten GAE advantages over the completion tokens of the rollout batch."""
    value_init: Literal["reward", "policy"] = "reward"
    """Start the value model from the reward model (transformer and head) or from the SFT model with a new head."""
    disable_dropout: bool = True
    """Set every dropout probability (incl. attention dropout) of policy, value and reference to 0."""
    eval_rows: int = 100
    """Held-out prompts for the periodic evaluation."""
    final_eval_rows: int = 200
    """Held-out prompts for the final comparison with the SFT model (0 skips it)."""
    save_rollouts_every: int = 0
    """Iterations between saving the iteration's scored rollouts to rollouts/step-NNNNNN.jsonl (0: never); read them
    with `posttrain rollouts RUN_DIR`."""
    # loop.TrainingBase's fields (one docstring each, there) whose default is this trainer's own:
    max_steps: int = 40
    schedule: Literal["cosine", "linear", "constant"] = "linear"
    eval_every: int = 10
    save_every: int = 10


def check_config(cfg: PPOConfig) -> None:
    """One-line ConfigErrors for settings that cannot run, before anything loads (`check_processes`: once the
    number of processes is known)."""
    for name in ("max_steps", "rollout_batch_size", "minibatch_size", "ppo_epochs", "max_new_tokens"):
        if getattr(cfg, name) < 1:
            raise ConfigError(f"ppo.{name} must be >= 1, got {getattr(cfg, name)}")
    if cfg.rollout_batch_size % cfg.minibatch_size:
        raise ConfigError(f"ppo.minibatch_size={cfg.minibatch_size} must divide "
                          f"rollout_batch_size={cfg.rollout_batch_size}")
    if cfg.temperature <= 0 or not math.isfinite(cfg.temperature):
        raise ConfigError(f"ppo.temperature must be > 0 (PPO samples; greedy rollouts have no ratio), "
                          f"got {cfg.temperature}")
    if cfg.clip_eps <= 0:
        raise ConfigError(f"ppo.clip_eps must be > 0, got {cfg.clip_eps}")
    if not cfg.rollout_correction_cap > 1:
        raise ConfigError(f"ppo.rollout_correction_cap must be > 1, got {cfg.rollout_correction_cap}")
    for name in ("value_clip", "reward_clip", "missing_eos_penalty", "entropy_coef", "kl_coef", "lr", "value_lr"):
        if getattr(cfg, name) < 0:
            raise ConfigError(f"ppo.{name} must be >= 0, got {getattr(cfg, name)}")
    if not (0.0 <= cfg.gamma <= 1.0 and 0.0 <= cfg.lam <= 1.0):
        raise ConfigError(f"ppo.gamma and lam must be in [0, 1], got gamma={cfg.gamma}, lam={cfg.lam}")
    if cfg.kl_control == "adaptive" and (cfg.kl_target <= 0 or cfg.kl_horizon < 1):
        raise ConfigError(f"ppo.kl_target must be > 0 and kl_horizon >= 1 with kl_control=adaptive, got "
                          f"{cfg.kl_target}, {cfg.kl_horizon}")
    if cfg.reward_norm == "init" and cfg.reward_norm_prompts < 2:
        raise ConfigError(f"ppo.reward_norm_prompts must be >= 2 with reward_norm=init, got {cfg.reward_norm_prompts}")
    # detail 20: reward=env if and only if env is set; nothing of a reward model with it
    if cfg.env and cfg.reward != "env":
        raise ConfigError(f"ppo.env={cfg.env!r} rewards whole episodes itself: set ppo.reward=env "
                          f"(reward={cfg.reward} would be ignored)")
    if cfg.reward == "env" and not cfg.env:
        raise ConfigError("ppo.reward=env needs ppo.env, the environment whose episodes are rewarded (e.g. env=calc)")
    if cfg.env and cfg.reward_model:
        raise ConfigError(f"ppo.reward_model is unused in an environment (env={cfg.env!r} rewards the episodes and "
                          "the value model starts from the policy): leave it unset")
    if cfg.env and cfg.value_init == "reward":
        raise ConfigError("ppo.value_init=reward copies a reward model, and a run in an environment (ppo.env) has "
                          "none: set ppo.value_init=policy")


def check_processes(cfg: PPOConfig, world: int) -> None:
    """A ConfigError when the minibatch cannot be shared equally by `world` processes."""
    if cfg.minibatch_size % world:
        raise ConfigError(f"ppo.minibatch_size={cfg.minibatch_size} must be a multiple of the number of processes "
                          f"({world}): each process takes an equal share of every minibatch")


# ----------------------------------------------------------------------------- train
def train(res: Resolved, ensure) -> Path:
    """PPO-for-RLHF from the SFT model; returns the final policy directory."""
    cfg: PPOConfig = res.stage_cfg
    check_config(cfg)
    with contextlib.ExitStack() as stack:  # an environment's ToolRunner (detail 20)
        run = setup(res, cfg, ensure, stack)  # inputs, models, optimizers, resume, reward statistics, SFT baseline
        for it in range(run.start, cfg.max_steps):
            done, t_it = it + 1, time.time()
            # ---- rollout (the shared engine, or episodes in the environment; prompts and samples seeded by (seed,
            # iteration)) and score: the batch is global, each process samples and scores its share, then every
            # process holds all of it
            idx = loop.batch_indices(len(run.train_rows), cfg.rollout_batch_size, cfg.seed, it)
            rollouts, raw, t = rollout_and_score(run.accelerator, run.nets, cfg, run.train_rows, idx,
                                                 sample_seed(cfg.seed, it))
            # ---- log-probs (old policy, reference) and values at rollout time, KL-penalised per-token rewards (with
            # the turns' rewards), GAE, whitening (global: every process holds the same tensors)
            batch = rollout_batch(run, rollouts, raw)
            # ---- ppo_epochs x minibatches of policy and value updates
            saving = (cfg.save_every and done % cfg.save_every == 0) or done == cfg.max_steps
            with loop.naming_checkpoint(run.ckpt, f"PPO iteration {done}"):
                update_metrics = update(run, batch, it)
                if saving or (cfg.eval_every and done % cfg.eval_every == 0):
                    loop.check_weights(done, run.nets.policy, run.nets.value, unit="iteration")
            # ---- rollout inspection: the iteration's samples with their scores, KL penalties and advantages
            if run.main and cfg.save_rollouts_every and done % cfg.save_rollouts_every == 0:
                table = save_scored_rollouts(rollouts, raw, batch.scores, batch.adv, batch.completion_mask,
                                             run.kl_ctl.value, run.run_dir, done, batch.turn_rewards)
                run.metrics.log_table("rollouts", table, done)
            # ---- KL controller (detail 5; a no-op when fixed)
            mean_kl, kl_coef_used = float(batch.seq_kl.mean()), run.kl_ctl.value
            run.kl_ctl.update(mean_kl, cfg.rollout_batch_size)
            # ---- log (in an environment: its turns, tool calls and errors, detail 20)
            if done % cfg.log_every == 0 or done == cfg.max_steps:
                run.metrics.log(done, {**iteration_metrics(batch, raw, mean_kl, kl_coef_used), **update_metrics,
                                       **(episode_metrics(rollouts) if run.nets.env is not None else {}),
                                       "time/rollout_s": t["sample"], "time/score_s": t["score"],
                                       "time/iteration_s": time.time() - t_it})
            # ---- eval
            if cfg.eval_every and (done % cfg.eval_every == 0 or done == cfg.max_steps):
                evaluate(done, res.task.name, run.accelerator, run.nets, run.held_out, run.baseline, cfg,
                         run.metrics, run.say, run.episodes)
            # ---- checkpoint (the value model's side, the KL controller and the reward statistics as extra)
            if saving:
                save_checkpoint(run, done)
        return finish(run)


# ----------------------------------------------------------------------------- setup and the end of a run
def sample_seed(seed: int, it: int) -> int:
    """The sampling stream of iteration `it`, kept at its value from before `loop.stream_seed` (as PPO's epoch
    shuffles, detail 18): the learning tests' bounds were measured on these samples (docs/results-archive.md,
    "Test margins"), and under a renamed stream test_ppo_learns_a_hand_made_reward falls below its bound at seeds
    0 and 3. Rename it (loop.stream_seed(seed, "ppo/sample", it)) together with a new measurement of those margins."""
    return seed * 100_003 + it



@dataclass(kw_only=True)
class PPORun:
    """What a run holds between iterations (`setup`)."""

    res: Resolved
    cfg: PPOConfig
    accelerator: Accelerator
    say: Callable[[str], None]  # prints on the main process
    run_dir: Path
    main: bool
    sft_dir: Path
    rm_dir: Path | None
    nets: PPOModels
    budget: int  # padded tokens per micro-batch (memory)
    train_rows: list[dict]
    held_out: list[dict]  # held-out rows with gold meta (main process; none in an environment)
    baseline: list[str]  # the SFT model's completions of them
    episodes: HeldOut | None  # in an environment: greedy held-out episodes (main process), else None
    episodes_baseline: dict  # the SFT model's numbers on them (`HeldOut.sft_baseline`)
    opt_p: torch.optim.Optimizer  # the policy's optimizer and scheduler
    sched_p: torch.optim.lr_scheduler.LRScheduler
    opt_v: torch.optim.Optimizer  # the value model's
    sched_v: torch.optim.lr_scheduler.LRScheduler
    kl_ctl: FixedKLController | AdaptiveKLController
    ckpt: loop.Checkpointer
    metrics: loop.MetricsLog
    norm: dict[str, float] | None  # detail 1's reward statistics (reward_norm=init)
    start: int  # the first iteration (resume)


def setup(res: Resolved, cfg: PPOConfig, ensure, stack: contextlib.ExitStack) -> PPORun:
    """The inputs (checked before the run directory changes), the models, their optimizers and schedules, the
    resumed state (PPO's own part of the checkpoint restored here), the reward statistics and the SFT model's
    held-out completions (in an environment: its held-out episodes; the ToolRunner lives in `stack`)."""
    from posttrain.verifiers.envs import ToolRunner

    train_rows, eval_rows, sft_dir, rm_dir, env = load_inputs(res, cfg, ensure)
    accelerator, say = loop.start_run(res, cfg.seed, cfg.resume, check=lambda acc: check_processes(cfg, acc.num_processes))
    world, main, dev = accelerator.num_processes, accelerator.is_main_process, accelerator.device
    nets = build_models(res, cfg, sft_dir, rm_dir, dev, say, main)
    if env is not None:  # detail 20
        nets.env, nets.runner = env, stack.enter_context(ToolRunner())
    budget = models.token_budget(res.run.micro_batch_tokens, nets.policy)  # padded tokens per micro-batch (memory)
    held_out = eval_rows[: max(cfg.eval_rows, cfg.final_eval_rows)] if main and env is None else []
    baseline = evaluation.complete(nets.policy, nets.tokenizer, [r["prompt"] for r in held_out],
                                   max_new_tokens=cfg.max_new_tokens) if held_out else []  # the SFT model's
    n_mb = cfg.rollout_batch_size // cfg.minibatch_size
    opt_p = loop.build_optimizer(nets.policy, cfg.lr, cfg.weight_decay)
    opt_v = loop.build_optimizer(nets.value, cfg.value_lr, cfg.weight_decay)
    sched_p = loop.build_scheduler(opt_p, 0, cfg.max_steps * cfg.ppo_epochs * n_mb, cfg.schedule, 0.0)  # detail 19
    sched_v = loop.build_scheduler(opt_v, 0, cfg.max_steps * cfg.ppo_epochs * n_mb, cfg.schedule, 0.0)
    # The value model's update forward must run through DDP: wrap it so that its forward IS the per-token value.
    nets.policy, nets.value, opt_p, opt_v = accelerator.prepare(nets.policy, TokenValueModel(nets.value), opt_p, opt_v)
    kl_ctl = (AdaptiveKLController(cfg.kl_coef, cfg.kl_target, cfg.kl_horizon) if cfg.kl_control == "adaptive"
              else FixedKLController(cfg.kl_coef))
    ckpt = loop.Checkpointer(res.stage_dir(), cfg.keep_checkpoints, accelerator)
    metrics = loop.open_metrics(res, cfg.max_steps, main, "[ppo] ")
    state = loop.resume_run(ckpt, metrics, nets.policy, opt_p, sched_p, resume=cfg.resume, say=say, tag="ppo",
                            unit="iteration")
    norm = (extra := state["extra"]).get("reward_norm")  # resumed: PPO's own part of the checkpoint, restored below
    if extra:
        accelerator.unwrap_model(nets.value).model.load_state_dict(extra["value_model"])
        opt_v.load_state_dict(extra["value_optimizer"])
        sched_v.load_state_dict(extra["value_scheduler"])
        kl_ctl.load_state_dict(extra["kl_controller"])
    if cfg.reward_norm == "init" and norm is None:
        norm = measure_reward_norm(accelerator, nets, cfg, train_rows, say)
    episodes = episodes_baseline = None
    if env is not None and main:  # detail 20: greedy held-out episodes, the SFT model's read back on resume
        problems = [Problem(e["prompt"], e["answer"], i, env_problem=e) for i, e in enumerate(eval_rows)]
        episodes = HeldOut(problems, build_env_reward(env, nets.runner), cfg.max_new_tokens,
                           min(cfg.eval_rows, len(problems)), min(cfg.final_eval_rows, len(problems)), stage="ppo")
        episodes_baseline = episodes.sft_baseline(accelerator.unwrap_model(nets.policy), nets.tokenizer,
                                                  res.stage_dir() / "sft_eval.json", state["step"], metrics, say)
    if state["step"] == 0 and cfg.eval_every and env is None:
        evaluate(0, res.task.name, accelerator, nets, held_out, baseline, cfg, metrics, say)
    what = {"rm": f" ({rm_dir})", "env": "" if env is None else f" ({env.name}: episodes of at most "
            f"{env.limits.max_turns} turns, {env.limits.max_total_tokens} tokens)"}.get(cfg.reward, "")
    say(f"[ppo] {cfg.max_steps} iterations x {cfg.rollout_batch_size} rollouts, {cfg.ppo_epochs} epochs x {n_mb} "
        f"minibatches of {cfg.minibatch_size}; reward {cfg.reward}{what}, value from {cfg.value_init}, KL "
        f"{cfg.kl_estimator} coef {kl_ctl.value:g} ({cfg.kl_control}), temperature {cfg.temperature}; {world} "
        f"process(es) on {dev}")
    return PPORun(res=res, cfg=cfg, accelerator=accelerator, say=say, run_dir=res.stage_dir(), main=main,
                  sft_dir=sft_dir, rm_dir=rm_dir, nets=nets, budget=budget, train_rows=train_rows, held_out=held_out,
                  baseline=baseline, episodes=episodes, episodes_baseline=episodes_baseline or {}, opt_p=opt_p,
                  sched_p=sched_p, opt_v=opt_v, sched_v=sched_v, kl_ctl=kl_ctl, ckpt=ckpt, metrics=metrics, norm=norm,
                  start=state["step"])


def save_checkpoint(run: PPORun, done: int) -> None:
    """The policy's checkpoint with PPO's own part as extra: the value model, its optimizer and schedule, the KL
    controller and the reward statistics."""
    value_model = run.accelerator.unwrap_model(run.nets.value).model
    value_state = {k: v.detach().cpu() for k, v in value_model.state_dict().items()}
    run.ckpt.save(done, run.nets.policy, run.opt_p, run.sched_p, {"step": done}, {
        "value_model": value_state, "value_optimizer": run.opt_v.state_dict(),
        "value_scheduler": run.sched_v.state_dict(), "kl_controller": run.kl_ctl.state_dict(), "reward_norm": run.norm})


def finish(run: PPORun) -> Path:
    """final/ (the policy, a HF directory), the over-optimisation plot, the comparison with the SFT model (in an
    environment: held-out greedy episodes, no plot)."""
    cfg, res, run_dir = run.cfg, run.res, run.run_dir
    final = run_dir / "final"
    whole = loop.full_state_dict(run.accelerator, run.nets.policy)  # every process: gathers a sharded model
    if run.main:
        pol = run.accelerator.unwrap_model(run.nets.policy).eval()
        models.save_model(pol, run.nets.tokenizer, final, state_dict=whole)
        run.say(f"[ppo] saved {final}")
        report: dict[str, Any] = {"model": str(final), "reference": str(run.sft_dir), "reward": cfg.reward,
                                  "reward_model": str(run.rm_dir) if run.rm_dir else None, "reward_norm": run.norm}
        if run.episodes is not None:  # detail 20: the environment's reward on greedy held-out episodes
            report.update(env=cfg.env, **run.episodes.compare(pol, run.nets.tokenizer, run.episodes_baseline,
                                                              run.metrics, cfg.max_steps, run.say))
        else:
            note = evaluation.plot_gold_vs_proxy(list(loop.iter_jsonl(run_dir / "metrics.jsonl")),
                                                 run_dir / "overoptimization.png", title=f"{res.recipe} PPO")
            run.say(f"[ppo] over-optimisation plot: {note}")
        if cfg.final_eval_rows and run.held_out:
            report.update(evaluation.compare_with_sft(
                "ppo", res.task.name, pol, run.nets.reference, run.nets.tokenizer, run.held_out[: cfg.final_eval_rows],
                run.baseline, max_new_tokens=cfg.max_new_tokens, proxy=run.nets.proxy,
                seed=loop.stream_seed(cfg.seed, "eval/sample"), say=run.say))
        loop.write_json(run_dir / "eval.json", report)
        run.metrics.close(report)
    run.metrics.close()
    run.accelerator.wait_for_everyone()
    return final


# ----------------------------------------------------------------------------- an iteration's batch and updates
@dataclass
class RolloutBatch:
    """An iteration's rollouts as the updates read them (every tensor global: every process holds all rows)."""

    data: dict[str, torch.Tensor]  # the update's (B, T) tensors: ids, masks, old log-probs and values, advantages
    completion_mask: torch.Tensor  # (B, T) bool
    ended: torch.Tensor  # (B,) bool: the completion ended with EOS
    scores: torch.Tensor  # (B,) shaped scores (details 1-3)
    adv: dict[str, torch.Tensor]  # `advantages_and_returns`: kl, rewards, advantages, returns, (B, T) each
    seq_kl: torch.Tensor  # (B,) k1 per sequence, the KL controller's quantity
    logprob_gap: float  # max |trainer - sampler| log-prob over completion tokens
    mismatch: dict[str, float]  # `losses.sampler_mismatch` and `losses.rollout_correction`'s metrics
    turn_rewards: torch.Tensor | None = None  # (B, K) in an environment: each episode's per-turn rewards (detail 20)


def rollout_batch(run: PPORun, rollouts: list, raw: torch.Tensor) -> RolloutBatch:
    """Scores shaped (details 1-3); log-probs of the old policy and the reference and the values at rollout time
    (no grad; each process its rows, gathered; in an environment over the whole trajectories); the sampler
    compared with the trainer and the rollout correction (detail 16); KL-penalised per-token rewards (with the
    turns' rewards, detail 20), GAE and whitening (details 4-8), over the sampled tokens."""
    cfg, accelerator, nets, dev, budget = run.cfg, run.accelerator, run.nets, run.accelerator.device, run.budget
    temp_lp = logprob_temperature(cfg)
    turns = episode_turn_rewards(rollouts, nets.env.name) if nets.env is not None else None  # (B, K)
    ended = torch.tensor([ro.finish_reason != "length" for ro in rollouts])  # (B,)
    scores = shape_scores(raw, ended, cfg, run.norm)  # (B,) details 1-3
    batch = collate_rollouts(rollouts, nets.tokenizer.pad_token_id).to(dev)
    cm = batch.completion_mask.bool()  # (B, T)
    pol = accelerator.unwrap_model(nets.policy).eval()
    old_logps = sharding.sharded_logprobs(accelerator, pol, batch, cfg.minibatch_size, temp_lp, budget)  # (B, T)
    ref_logps = sharding.sharded_logprobs(accelerator, nets.reference, batch, cfg.minibatch_size, temp_lp,
                                          budget)  # (B, T)
    old_values = rollout_values(accelerator, nets.value, batch, cfg.minibatch_size, budget)  # (B, T)
    engine_lp = batch.logprobs if cfg.scale_logits_by_temperature else batch.policy_logprobs  # (B, T)
    lp_gap = float((old_logps - engine_lp).abs().masked_fill(~cm, 0).max())
    mismatch = sampler_mismatch(old_logps, engine_lp, cm)  # KL(sampler || trainer), ratio extremes
    is_w, policy_mask, corr = rollout_correction(old_logps, engine_lp, cm, kind=cfg.rollout_correction,
                                                 level=cfg.rollout_correction_level, cap=cfg.rollout_correction_cap)
    seq_kl = masked_sum(old_logps - ref_logps, cm, -1)  # (B,) k1 per sequence, the controller's quantity
    adv = advantages_and_returns(cfg, scores.to(dev), old_logps, ref_logps, old_values, cm, run.kl_ctl.value,
                                 None if turns is None else turns.to(dev))
    data = dict(input_ids=batch.input_ids, attention_mask=batch.attention_mask, completion_mask=cm,  # (B, T) each
                policy_mask=policy_mask, old_logps=old_logps, old_values=old_values, advantages=adv["advantages"],
                returns=adv["returns"], **({} if is_w is None else {"is_weights": is_w}))
    return RolloutBatch(data, cm, ended, scores, adv, seq_kl, lp_gap, {**mismatch, **corr}, turns)


def episode_turn_rewards(rollouts: list, env_name: str) -> torch.Tensor:
    """Detail 20: the per-turn rewards (B, K) of episode rollouts, K their most turns (0 where a turn has no reward
    or a row fewer turns), in the order `advantages.turn_rewards_with_kl` reads them: the runs of sampled tokens
    of each row's completion mask. Each row's layout (turn k's sampled tokens, then its environment tokens) is
    checked against the episode's token counts first; a non-finite reward (final or per turn) is one TrainingError
    line naming the environment."""
    turns = [r.extras["episode"]["turns"] for r in rollouts]
    out = torch.zeros(len(rollouts), max(len(ts) for ts in turns))  # (B, K)
    for i, (r, ts) in enumerate(zip(rollouts, turns)):
        layout = [m for t in ts for m in [1] * t["sampled_tokens"] + [0] * t["env_tokens"]]
        if layout != [int(m) for m in r.completion_mask] or any(t["env_tokens"] < 1 for t in ts[:-1]) \
                or any(t["sampled_tokens"] < 1 for t in ts):  # the multi-turn engine's contract: our bug
            raise RuntimeError(f"episode rollout {i}: completion_mask does not match its turns' token counts "
                               f"{[(t['sampled_tokens'], t['env_tokens']) for t in ts]}")
        for k, t in enumerate(ts):
            if t["reward"] is not None:
                out[i, k] = float(t["reward"])
    for what, x in (("reward", [float(r.reward) for r in rollouts]), ("turn_reward", out.flatten().tolist())):
        if not all(math.isfinite(v) for v in x):
            raise loop.TrainingError(f"environment {env_name!r}: {what} returned a non-finite value "
                                     f"({next(v for v in x if not math.isfinite(v))}); fix the environment (nothing "
                                     "of this iteration was trained)")
    return out


def update(run: PPORun, batch: RolloutBatch, it: int) -> dict[str, float]:
    """ppo_epochs x minibatches of policy and value updates (of each minibatch, process r takes rows r, r + W, ...,
    in micro-batches of at most `budget` tokens; losses scaled to their share of the minibatch's global token
    mean, see sharding.token_share); the update metrics, averaged over the updates."""
    cfg, accelerator, nets, dev = run.cfg, run.accelerator, run.nets, run.accelerator.device
    data, cm, policy_mask = batch.data, batch.completion_mask, batch.data["policy_mask"]
    n_mb, done = cfg.rollout_batch_size // cfg.minibatch_size, it + 1
    sums: dict[str, float] = {}
    for epoch in range(cfg.ppo_epochs):
        perm = np.random.default_rng([cfg.seed, it, epoch]).permutation(cfg.rollout_batch_size)  # detail 18
        for j in range(n_mb):
            whole = torch.as_tensor(perm[j * cfg.minibatch_size:(j + 1) * cfg.minibatch_size], device=dev)
            mbs, n_all = minibatch_parts(data, whole, accelerator, run.budget), float(cm[whole].sum())
            w = [float(b["completion_mask"].sum()) / n_all for b in mbs]  # shares of the minibatch's tokens
            n_pol = max(1.0, float(policy_mask[whole].sum()))  # the policy loss's tokens (rollout correction)
            mp = loop.optimizer_step(accelerator, nets.policy, run.opt_p, run.sched_p, mbs,
                                     lambda b: policy_update_loss(accelerator, nets.policy, cfg, b,
                                                                  float(b["policy_mask"].sum()), n_pol),
                                     cfg.max_grad_norm, done,
                                     weights=[float(b["policy_mask"].sum()) / n_pol for b in mbs])
            mv = loop.optimizer_step(accelerator, nets.value, run.opt_v, run.sched_v, mbs,
                                     lambda b: value_update_loss(accelerator, nets.value, cfg, b,
                                                                 float(b["completion_mask"].sum()), n_all),
                                     cfg.max_grad_norm, done, weights=w)
            got = {"policy/" + k: v for k, v in mp.items()} | {"value/" + k: v for k, v in mv.items()}
            sums = {k: sums.get(k, 0.0) + v for k, v in got.items()}
    return {k: v / (cfg.ppo_epochs * n_mb) for k, v in sums.items()}


def iteration_metrics(batch: RolloutBatch, raw: torch.Tensor, mean_kl: float, kl_coef: float) -> dict[str, float]:
    """The rollout side of an iteration's metrics: scores, rewards, KL, lengths, the sampler-trainer gap."""
    cm, adv = batch.completion_mask, batch.adv
    return {"rollout/score_raw": float(raw.mean()), "rollout/score": float(batch.scores.mean()),
            "rollout/reward_total": float(masked_sum(adv["rewards"], cm, -1).mean()),
            "rollout/kl": mean_kl, "rollout/kl_penalty": float(masked_sum(adv["kl"], cm, -1).mean()),
            "kl_coef": kl_coef, "rollout/length": float(cm.sum(-1).float().mean()),
            "rollout/no_eos": float((~batch.ended).float().mean()), "rollout/logprob_gap": batch.logprob_gap,
            **batch.mismatch, "rollout/returns": float(masked_mean(adv["returns"], cm)),
            **({} if batch.turn_rewards is None else  # detail 20: the turns' rewards summed, per episode
               {"rollout/turn_rewards": float(batch.turn_rewards.sum(-1).mean())})}


# ----------------------------------------------------------------------------- models
def disable_dropout(model) -> int:
    """Detail 13: every nn.Dropout p, attention-dropout attribute and config *dropout* field set to 0; how many were."""
    changed = 0
    for module in model.modules():
        if isinstance(module, torch.nn.Dropout) and module.p:
            module.p, changed = 0.0, changed + 1
        if isinstance(getattr(module, "attention_dropout", None), float) and module.attention_dropout:
            module.attention_dropout, changed = 0.0, changed + 1
    config = getattr(model, "config", None)
    if config is not None:
        for key, value in list(vars(config).items()):
            if "dropout" in key and isinstance(value, float) and value:
                setattr(config, key, 0.0)
    return changed


def build_value_model(value_init: str, sft_dir: Path, rm_dir: Path | None, pad_id: int, seed: int, device,
                      dtype: str | torch.dtype = torch.float32):
    """Detail 11: the value model, a sequence-classification model whose head is read at every token."""
    from transformers import AutoModelForSequenceClassification

    if value_init == "reward":
        if rm_dir is None:
            raise ConfigError("ppo.value_init=reward needs a reward model; set ppo.reward_model or value_init=policy")
        model = AutoModelForSequenceClassification.from_pretrained(str(rm_dir), local_files_only=True,
                                                                   dtype=models.resolve_dtype(dtype))
        model.config.pad_token_id = pad_id
        return model.to(device)
    return models.load_reward_init(sft_dir, pad_id, seed, device, dtype)


def token_values(value_model, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
    """Per-token values (B, T) aligned with input_ids (the `posttrain.logprobs` convention): values[:, t] =
    V(input_ids[:, :t]), the head on token t-1's hidden state (the state in which token t is chosen); column 0 is 0.
    Positions count real tokens (left padding). A plain fp32 Llama-family model runs `lean.lean_hidden`."""
    inner = models.unwrap_model(value_model)
    if hasattr(inner, "get_base_model"):  # peft (LoRA): the adapters live inside the base model's layers
        inner = inner.get_base_model()
    dev = next(inner.parameters()).device
    input_ids, attention_mask = input_ids.to(dev), attention_mask.to(dev)
    if lean_support(inner, input_ids.shape[1], mode="train", head="score")[0]:  # same numbers, fewer ops
        hidden = lean.lean_hidden(inner, input_ids, attention_mask)  # (B, T, H)
    else:
        hidden = getattr(inner, inner.base_model_prefix)(  # a 4D mask for left padding: no empty attention row
            input_ids=input_ids, attention_mask=models.hf_attention_mask(attention_mask, inner),
            position_ids=models.position_ids_from_mask(attention_mask)).last_hidden_state  # (B, T, H)
    v = inner.score(hidden).squeeze(-1).float()  # (B, T): value after token j
    return torch.cat([torch.zeros_like(v[:, :1]), v[:, :-1]], dim=1)  # (B, T)


class TokenValueModel(torch.nn.Module):
    """The value model as a module whose forward returns `token_values` (B, T). accelerate wraps THIS in
    DDP, so the update's value forward goes through DDP's __call__ (which is what syncs gradients)."""

    def __init__(self, model):
        super().__init__()
        self.model = model

    def forward(self, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
        return token_values(self.model, input_ids, attention_mask)  # (B, T)


def reward_scorer(reward: str, task_name: str, rm_dir: Path | None, device):
    """The training reward through `posttrain.scoring` (tests replace this function with a hand-made scorer)."""
    return GoldScorer(task_name) if reward == "gold" else RewardModelScorer(rm_dir, device=device)


# ----------------------------------------------------------------------------- pure steps of an iteration
def logprob_temperature(cfg: PPOConfig) -> float:
    """Detail 14: the temperature every log-prob of the update is computed at."""
    return cfg.temperature if cfg.scale_logits_by_temperature else 1.0


@torch.no_grad()
def shape_scores(raw: torch.Tensor, ended: torch.Tensor, cfg: PPOConfig, norm: dict[str, float] | None) -> torch.Tensor:
    """Details 1-3: raw scores (B,) -> normalised (init stats or batch), minus the missing-EOS penalty
    where `ended` (B,) is False, clipped."""
    s = raw.float()
    if cfg.reward_norm == "init":
        s = (s - norm["mean"]) / norm["std"]
    elif cfg.reward_norm == "batch":
        s = (s - s.mean()) / (s.std() + 1e-8) if s.numel() > 1 else s - s.mean()
    s = s - cfg.missing_eos_penalty * (~ended.bool()).float()
    if cfg.reward_clip > 0:
        s = s.clamp(-cfg.reward_clip, cfg.reward_clip)
    return s


@torch.no_grad()
def advantages_and_returns(cfg: PPOConfig, scores: torch.Tensor, logps: torch.Tensor, ref_logps: torch.Tensor,
                           values: torch.Tensor, completion_mask: torch.Tensor, kl_coef: float,
                           turn_rewards: torch.Tensor | None = None) -> dict[str, torch.Tensor]:
    """Details 4, 6, 7, 8: per-token KL penalty, rewards, GAE, whitening. All (B, T), 0 outside the mask. Detail 20:
    `completion_mask` selects the sampled tokens of multi-turn trajectories (environment tokens are skipped by GAE
    and whitening) and `turn_rewards` (B, K) adds each turn's reward at its last sampled token."""
    cm = completion_mask.bool()
    zero = torch.zeros_like(logps)
    kl = torch.where(cm, kl_penalty(logps, ref_logps, cfg.kl_estimator), zero)  # (B, T)
    rewards = rewards_with_kl(scores, kl, cm, kl_coef=kl_coef) if turn_rewards is None else \
        turn_rewards_with_kl(scores, kl, cm, turn_rewards, kl_coef=kl_coef)  # (B, T)
    if cfg.whiten_rewards:
        rewards = torch.where(cm, masked_whiten(rewards, cm, shift_mean=False), zero)
    adv, returns = gae(rewards, values, cm, gamma=cfg.gamma, lam=cfg.lam)  # (B, T), (B, T)
    if cfg.whiten_advantages:
        adv = torch.where(cm, masked_whiten(adv, cm), zero)
    return {"kl": kl, "rewards": rewards, "advantages": adv, "returns": returns}


def actor_loss(cfg: PPOConfig, logps: torch.Tensor, entropy: torch.Tensor, old_logps: torch.Tensor,
                advantages: torch.Tensor, completion_mask: torch.Tensor, policy_mask: torch.Tensor | None = None,
                weights: torch.Tensor | None = None) -> tuple[torch.Tensor, dict[str, float]]:
    """Details 9, 16 and 17: the policy loss (clipped surrogate by default) over `policy_mask` (the completion tokens
    the rollout correction keeps; default all) with its importance `weights`, minus the entropy bonus."""
    loss, m = losses.policy_loss(cfg.policy_loss, logps, old_logps, advantages,
                                 completion_mask if policy_mask is None else policy_mask, clip_eps=cfg.clip_eps,
                                 weights=weights)
    ent = masked_mean(entropy, completion_mask.bool())
    if cfg.entropy_coef:
        loss = loss - cfg.entropy_coef * ent
    m["entropy"] = float(ent.detach())
    return loss, m


def critic_loss(cfg: PPOConfig, values: torch.Tensor, old_values: torch.Tensor, returns: torch.Tensor,
                completion_mask: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """Detail 10: `losses.value_loss`, clipped around the rollout-time values unless value_clip = 0."""
    return value_loss(values, old_values, returns, completion_mask, clip_range=cfg.value_clip or None)

# ----------------------------------------------------------------------------- the pieces train() calls
@dataclass
class PPOModels:
    """The models of a run (policy and value model as accelerate prepared them) and its reward scorers."""
    policy: Any
    value: Any  # a TokenValueModel once prepared
    reference: Any
    tokenizer: Any
    scorer: Any  # the training reward (None in an environment: it rewards the episodes)
    proxy: Any  # the reward model as the evaluation's proxy scorer (main process), or None
    env: Environment | None = None  # the environment (detail 20), or None
    runner: ToolRunner | None = None


def load_inputs(res: Resolved, cfg: PPOConfig, ensure) -> tuple[list[dict], list[dict], Path, Path | None, Any]:
    """Training prompts, held-out rows with gold meta (none without a gold metric), the SFT and the reward model (built
    when reward=rm or value_init=reward needs it, else only the proxy curve if it exists), the environment (None
    without one; with one, both splits' rows as its problems and no reward model); one-line ConfigErrors."""
    if cfg.env:  # detail 20
        env = load_env(cfg, "ppo")
        train_rows = [env_problem(r) for r in tasks.load_split(res.task, "train")]
        if len(train_rows) < cfg.rollout_batch_size:
            raise ConfigError(f"ppo.rollout_batch_size={cfg.rollout_batch_size} is more than the {len(train_rows)} "
                              "training problems (task.n_train)")
        eval_rows = [env_problem(r) for r in tasks.load_split(res.task, "eval")][: max(cfg.eval_rows,
                                                                                         cfg.final_eval_rows)]
        return train_rows, eval_rows, ensure("sft"), None, env
    task = tasks.get_task(res.task.name)
    if cfg.reward == "gold" and not tasks.has_gold(task):
        raise ConfigError(f"ppo.reward=gold needs a task with a gold metric; {res.task.name!r} has none")
    if cfg.reward_model and not models.is_model_dir(cfg.reward_model):
        raise ConfigError(f"ppo.reward_model {cfg.reward_model!r} is not a reward-model directory")
    train_rows = tasks.load_split(res.task, "train")
    if len(train_rows) < cfg.rollout_batch_size:
        raise ConfigError(f"ppo.rollout_batch_size={cfg.rollout_batch_size} is more than the {len(train_rows)} "
                          "training prompts (task.n_train)")
    if cfg.reward == "gold" and not all(r.get("meta") for r in train_rows):
        raise ConfigError("ppo.reward=gold needs the task's meta in every training row; task.train_file has rows "
                          "without it (use reward=rm)")
    eval_rows = [r for r in tasks.load_split(res.task, "eval") if r.get("meta")] if tasks.has_gold(task) else []
    sft_dir = ensure("sft")
    rm_dir: Path | None = Path(cfg.reward_model) if cfg.reward_model else None
    if rm_dir is None and (cfg.reward == "rm" or cfg.value_init == "reward"):
        rm_dir = ensure("rm")
    elif rm_dir is None and models.is_model_dir(res.stage_dir("rm") / "final"):
        rm_dir = res.stage_dir("rm") / "final"
    return train_rows, eval_rows, sft_dir, rm_dir, None


def build_models(res: Resolved, cfg: PPOConfig, sft_dir: Path, rm_dir: Path | None, dev, say, main: bool) -> PPOModels:
    """Policy and reference from the SFT model (`models.load_reference`), the value model per value_init (LoRA: each
    its own adapters), dropout off (detail 13), the reward and the proxy scorer."""
    tokenizer = models.load_tokenizer(sft_dir, res.model)
    policy = models.maybe_lora(res, models.load_model(sft_dir, res.model.dtype, dev), lambda s: say(s + " (policy)"))
    reference = models.load_reference(res, policy, sft_dir, dev)
    value = build_value_model(cfg.value_init, sft_dir, rm_dir, tokenizer.pad_token_id, cfg.seed, dev, res.model.dtype)
    value = models.maybe_lora(res, value, lambda s: say(s + " (value model)"), "SEQ_CLS")
    for model in (policy, reference, value) if cfg.disable_dropout else ():
        disable_dropout(model)
    scorer = reward_scorer(cfg.reward, res.task.name, rm_dir, dev) if cfg.reward != "env" else None
    proxy = None if rm_dir is None or not main else (  # the RM's scores of evaluation completions
        scorer if isinstance(scorer, RewardModelScorer) else RewardModelScorer(rm_dir, device=dev))
    return PPOModels(policy, value, reference, tokenizer, scorer, proxy)


def rollout_and_score(accelerator, nets: PPOModels, cfg: PPOConfig, train_rows: list[dict], keys: list[int],
                      seed: int) -> tuple[list, torch.Tensor, dict[str, float]]:
    """The global batch train_rows[keys]: each process samples (prompt keys = dataset indices: the samples one process
    draws) and scores its positions, all gathered in global order. Returns (rollouts, raw scores (B,), {"sample":
    s, "score": s} of this process)."""
    params = SamplingParams(temperature=cfg.temperature, max_new_tokens=cfg.max_new_tokens, seed=seed)
    policy = accelerator.unwrap_model(nets.policy)
    if nets.env is not None:  # detail 20: episodes through the trainers' one multi-turn driver, its final reward
        problems = [Problem(train_rows[k]["prompt"], train_rows[k]["answer"], k, env_problem=train_rows[k])
                    for k in keys]  # the key (dataset index) seeds the episode, as below
        got = sample_and_score(accelerator, policy, nets.tokenizer, problems, list(range(len(keys))), params,
                               build_env_reward(nets.env, nets.runner), 0)
        return ([g.rollouts[0] for g in got.groups], torch.tensor([float(g.rewards[0]) for g in got.groups]),
                {"sample": got.sample_s, "score": got.score_s})
    where = sharding.positions(len(keys), accelerator.process_index, accelerator.num_processes)
    rows, t0 = [train_rows[keys[p]] for p in where], time.time()  # rows: none for a process with no share
    local = generate(policy, nets.tokenizer, [r["prompt"] for r in rows], params,
                     prompt_keys=[keys[p] for p in where]) if rows else []
    t1 = time.time()
    raw = [float(x) for x in nets.scorer.score([r["prompt"] for r in rows], [ro.text for ro in local],
                                            [r.get("meta") for r in rows]).rewards] if rows else []
    return (sharding.gather_rows(accelerator, local, where), torch.tensor(sharding.gather_rows(accelerator, raw, where),
            dtype=torch.float32), {"sample": t1 - t0, "score": time.time() - t1})


def save_scored_rollouts(rollouts: list, raw: torch.Tensor, scores: torch.Tensor, adv: dict, cm: torch.Tensor,
                         kl_coef: float, run_dir: Path, step: int, turn_rewards: torch.Tensor | None = None
                         ) -> list[dict]:
    """The iteration's rollouts with what a reader asks of each (`posttrain rollouts RUN_DIR` prints them): the
    reward it was trained on (the per-token rewards summed: shaped score, plus the turns' rewards in an environment,
    minus the KL penalty), its parts (raw score, shaped score, the sequence's KL (kl_estimator) and kl_coef times
    it, `turns`: the sum of its per-turn rewards) and its mean advantage over completion (sampled) tokens. Episodes
    keep extras["episode"] (the turns). Returns them as table rows (trackers)."""
    from posttrain.rollout.records import save_step_rollouts

    advantage = masked_mean(adv["advantages"], cm, -1).tolist()  # (B,)
    total, kl = masked_sum(adv["rewards"], cm, -1).tolist(), masked_sum(adv["kl"], cm, -1).tolist()  # (B,)
    turns = turn_rewards.sum(-1).tolist() if turn_rewards is not None else None  # (B,)
    for i, r in enumerate(rollouts):
        r.reward = total[i]
        r.extras.update(advantage=advantage[i], parts={"score_raw": float(raw[i]), "score": float(scores[i]),
                                                       "kl": kl[i], "kl_penalty": kl_coef * kl[i],
                                                       **({} if turns is None else {"turns": turns[i]})})
    return save_step_rollouts(rollouts, run_dir, step)


def measure_reward_norm(accelerator, nets: PPOModels, cfg: PPOConfig, train_rows: list[dict], say) -> dict[str, float]:
    """Detail 1: reward statistics of SFT samples of the split's last reward_norm_prompts prompts (checkpointed)."""
    t0, k = time.time(), min(cfg.reward_norm_prompts, len(train_rows))
    _, raw, _ = rollout_and_score(accelerator, nets, cfg, train_rows, list(range(len(train_rows) - k, len(train_rows))),
                                  loop.stream_seed(cfg.seed, "ppo/reward-norm"))  # (k,)
    norm = {"mean": float(raw.mean()), "std": float(raw.std().clamp(min=1e-6)), "n": k}
    say(f"[ppo] reward normalisation from {k} SFT samples: mean {norm['mean']:.4f}, std {norm['std']:.4f} "
        f"({time.time() - t0:.1f}s)")
    return norm


@torch.no_grad()
def rollout_values(accelerator, value, batch, micro: int, budget: int = 0) -> torch.Tensor:
    """The value model's per-token values (B, T) of every row at rollout time, 0 outside the completion: each process
    its rows r, r + W, ... in micro-batches (at most `micro` rows and `budget` padded tokens), gathered (as
    `sharding.sharded_logprobs`)."""
    where = sharding.positions(batch.input_ids.shape[0], accelerator.process_index, accelerator.num_processes)
    vm, ids, am = accelerator.unwrap_model(value).eval(), batch.input_ids[where], batch.attention_mask[where]
    local = None  # (B/W, T) on the value model's device
    for g in token_groups(row_spans(am), micro, budget, by_length=True):
        v = vm(ids[g], am[g])
        local = v.new_zeros(ids.shape) if local is None else local
        local[g] = v
    values = sharding.gather_row_tensor(accelerator, local, where)  # (B, T)
    return torch.where(batch.completion_mask.bool(), values, torch.zeros_like(values))


def minibatch_parts(data: dict, whole: torch.Tensor, accelerator, budget: int) -> list[dict]:
    """This process's rows r, r + W, ... of the minibatch `whole`, in micro-batches of at most `budget` padded
    tokens, all-padding columns trimmed."""
    mine = whole[accelerator.process_index::accelerator.num_processes]
    groups = token_groups(row_spans(data["attention_mask"][mine]), 0, budget, by_length=True)
    return [sharding.trim_columns({k: v[mine[torch.as_tensor(g, device=mine.device)]] for k, v in data.items()})
            for g in groups]


def policy_update_loss(accelerator, policy, cfg: PPOConfig, mb: dict, n_local: float, n_global: float):
    """Details 9, 14, 17 on this process's rows of a minibatch, scaled to the global minibatch's token mean."""
    logps, ent = sequence_logprobs(policy, mb["input_ids"], mb["attention_mask"], mb["completion_mask"],
                                   temperature=logprob_temperature(cfg), return_entropy=True)  # (b, T), (b, T)
    loss, m = actor_loss(cfg, logps, ent, mb["old_logps"], mb["advantages"], mb["completion_mask"], mb["policy_mask"],
                          mb.get("is_weights"))
    return sharding.token_share(accelerator, loss, n_local, n_global), m


def value_update_loss(accelerator, value, cfg: PPOConfig, mb: dict, n_local: float, n_global: float):
    """Detail 10 on this process's rows of a minibatch (the forward through DDP), scaled like the policy's."""
    v = value(mb["input_ids"], mb["attention_mask"])  # (b, T)
    loss, m = critic_loss(cfg, v, mb["old_values"], mb["returns"], mb["completion_mask"])
    if accelerator.num_processes > 1:
        m["explained_variance"] = sharding.global_explained_variance(accelerator, v, mb["returns"], mb["completion_mask"])
    return sharding.token_share(accelerator, loss, n_local, n_global), m


def evaluate(it: int, task_name: str, accelerator, nets: PPOModels, rows: list[dict], baseline: list[str],
             cfg: PPOConfig, metrics, say, episodes: HeldOut | None = None) -> None:
    """`evaluation.policy_eval` against the SFT model's completions `baseline`, logged at `it` (main process); in an
    environment (detail 20) greedy `episodes` (the last iteration's are `finish`'s comparison with the SFT model)."""
    if episodes is not None and episodes.n_eval and it != cfg.max_steps:
        episodes.log_eval(accelerator.unwrap_model(nets.policy), nets.tokenizer, metrics, it, say)
    if rows:
        pol = accelerator.unwrap_model(nets.policy).eval()  # (with LoRA, the reference runs in the policy's mode)
        e = evaluation.policy_eval(task_name, pol, nets.reference, nets.tokenizer, rows[: cfg.eval_rows], baseline,
                                   max_new_tokens=cfg.max_new_tokens, proxy=nets.proxy,
                                   seed=loop.stream_seed(cfg.seed, "eval/sample"))
        metrics.log(it, e, console=False)
        say(f"[ppo] iteration {it} eval: " + ", ".join(f"{k} {v:.3f}" for k, v in e.items()
                                                      if k in ("gold/reward", "gold/win_rate", "proxy/reward", "kl")))
