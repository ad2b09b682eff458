"""GRPO: group-relative policy optimisation with verifier (and/or reward-model) rewards.

CPU:        posttrain grpo --recipe tiny-countdown        (from nothing: base model, SFT, GRPO; see the recipe)
            posttrain grpo --recipe tiny-code
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain grpo --recipe tiny-countdown model.path=/path/to/hf-model
            (2 CPU processes: accelerate launch --config_file recipes/launch/cpu-2proc.yaml -m posttrain grpo
            --recipe tiny-countdown run.threads=1; tested against one process in tests/posttrain/test_distributed.py)

Reads top to bottom: resolve the reward (verifier spec, reward model) and check every problem has a
reference, run the verifier on a few worked solutions (a broken verifier stops here, before any
model loads), load the SFT model (the policy; a frozen copy as reference only when beta > 0), score
the SFT model's greedy answers on held-out problems, then loop { P prompts x K samples in ONE
`generate` call -> score in the verifier worker pool -> group advantages -> drop / resample
zero-variance groups -> mu passes of clipped-ratio updates over the batch -> log -> eval ->
checkpoint }; save final/ and compare held-out greedy accuracy with the SFT model.

What it follows, where:
- GRPO (Shao et al. 2024, DeepSeekMath §4.1; DeepSeek-R1): K samples per prompt, the group mean as
  baseline and the group std as scale (`advantages.group_advantages`, estimator "grpo", std_scale
  "group"), PPO's clipped ratio per token (`losses.ppo_policy_loss`), KL to the reference with the
  k3 estimator added to the loss, not the reward (`losses.kl_penalty`, eq. 4), per-sequence token
  mean (aggregation "seq_mean_token_mean", eq. 3), mu passes over one batch of rollouts with the
  log-probs of the policy that sampled them as pi_old (GRPO's mu; TRL's num_iterations).
- DAPO (Yu et al. 2025): clip-higher (`clip_eps_high`, §3.1: 0.28 over 0.2), dynamic sampling
  (`zero_variance=resample`, §3.2: groups whose rewards are all equal are dropped and more prompts
  are sampled to refill the batch), token-level loss (aggregation "token_mean", §3.3), overlong
  filtering (`mask_truncated`, §3.4: completions cut at max_new_tokens carry no loss), beta = 0.
- Dr. GRPO (Liu et al. 2025, "Understanding R1-Zero-Like Training"): no std division
  (std_scale "none") and a constant normaliser (aggregation "seq_mean_token_sum_norm": token sums /
  (rows x max_new_tokens)), removing GRPO's length and difficulty biases.
- RLOO (Ahmadian et al. 2024) and REINFORCE++ (Hu et al. 2025) as other critic-free baselines
  (`estimator`); see `advantages.group_advantages` for their exact form.

Plumbing:
- Rewards come through `posttrain.scoring` only: a `VerifierScorer` (any registry spec, e.g.
  "0.9*countdown + 0.1*format", weights normalised by their sum), a `RewardModelScorer`, or both
  in a `WeightedScorer` (verifier_weight, reward_model_weight). Verifier checks run in a
  `verifiers.runner.VerifierPool` of `verifier_workers` processes, in parallel, each under a hard
  wall-clock limit: a hung or crashing check scores 0 ("timeout", "crashed: ...") and the step goes
  on. A check that raises (a verifier bug or a malformed reference) scores 0 with reason "verifier
  error: ..." under on_verifier_error=zero (the default) and the step's log line says how many, on
  which problem; on_verifier_error=stop stops the run instead (the last good checkpoint is intact).
  A step where EVERY check raised stops the run in either mode: that reward carries no signal.
  Identical completions of the same prompt within a step are scored once (verifiers are deterministic
  by contract, reward models are): a confident policy samples many duplicates and a sandboxed code
  check costs ~50 ms; `verifier/scored` logs how many distinct completions were checked.
- Before anything loads: an unknown verifier name is a config error; a problem without a reference
  stops with its row (on_bad_rows=error) or is skipped with a count (skip); the verifier runs on the
  worked solutions of the first training rows, and one that raises there stops with the row (one
  that scores the worked solution below 1 is reported, not fatal).
- Old log-probs: `old_logprobs=rollout` takes pi_old from the engine, so no extra forward is spent:
  `Rollout.policy_logprobs` (raw temperature-1 log-probs of the sampled tokens, equal to a recompute
  within 1e-4) at temperature 1; at another temperature the loss uses logits / temperature (as TRL and
  verl do) and pi_old is `Rollout.logprobs`, the log-probs of the distribution the engine sampled,
  which is that same softmax(logits / T) when top_p = 1. With top_p < 1 (a truncated sampler),
  `old_logprobs=recompute`, or rollout.backend=vllm (vLLM's log-probs come from its own forward; see
  `posttrain.rollout.vllm_backend`) they come from one batched no-grad forward.
- One optimisation "step" (the unit of max_steps, logging, eval and checkpoints) = one batch of
  rollouts = mu passes x `minibatches` optimizer updates (the LR schedule counts updates). Each pass
  shuffles the rows (seeded by step and pass); gradient accumulation over `micro_batch_size` rows
  re-weights each micro-batch so the update is that of the whole minibatch's aggregation.
- Everything random is a function of (seed, step): the prompts of a step (`loop.batch_indices`),
  the samples (the engine's counter-based RNG, seeded by step and round, keyed by problem index) and
  the row shuffles; so resume=true continues exactly.
- Non-finite loss, gradient or weights stop the run naming the step and the last good checkpoint,
  which stays intact (as the DPO trainer does).
- Diagnostics per step (metrics.jsonl; a short console line every log_every steps): reward mean /
  std, reward and pass rate of each verifier part, zero-variance group fraction (of the first round,
  before resampling), clip fraction, approx KL to pi_old, KL to the reference (beta > 0), entropy,
  completion length, truncation rate, verifier timeouts / crashes / errors, time per phase. When
  every group is degenerate the log says so in words (no learning signal this step, and why).
- Eval every eval_every steps: greedy completions of eval_rows held-out problems scored by the
  verifier (not the reward model): eval/accuracy = pass rate of the correctness part (the FIRST term
  of a composition: put it first, "0.9*math + 0.1*format"), eval/pass/<part>, eval/reward, lengths.

Deviations and limits:
- The loss uses logits / temperature when temperature != 1 (TRL, verl); the policy being trained is
  then the tempered one. top_p < 1 samples from a truncated distribution but ratios and KL use the
  full one (TRL does the same).
- zero_variance=skip (the default) drops degenerate groups from the loss without refilling (DAPO's
  filter without its resampling): cheaper, and with beta = 0 the gradient direction is unchanged;
  with beta > 0 those rows' KL term is dropped too. "keep" trains on them as GRPO as published does.
- The k3 KL term's gradient is that of KL(pi_ref || pi), not KL(pi || pi_ref) (see
  `losses.kl_penalty`); GRPO as published has the same property.

Several processes (`accelerate launch`, data parallel). prompts_per_step is GLOBAL. Per process: process r
takes positions r, r + W, ... of each round's global prompt batch (`loop.batch_indices`), samples all K
completions of each of its prompts in one `generate` call (a group never spans processes; prompt keys are
problem indices, so the samples are those one process draws, up to float differences between batch shapes)
and scores them in its own verifier pool. Gathered: the scored groups, in global order, after every round,
so every process holds the whole step batch and everything computed from it is global and identical
everywhere: whether to resample (dynamic sampling stops when P informative groups exist over all
processes), the zero-variance filter, the advantages (group statistics, std_scale=batch and REINFORCE++'s
batch normalisation over the whole batch), the pass order and minibatches, the logged reward / pass /
zero-variance / length metrics. The no-grad log-probs (reference; pi_old when recomputed) are computed on
rows r, r + W, ... and gathered. Updates: of each minibatch, process r trains rows r, r + W, ..., its loss
scaled to its share of the minibatch's aggregation (token_mean: loss tokens / the whole minibatch's; the
sequence aggregations: rows / rows) times W, so DDP's gradient average is the one-process gradient (DAPO's
token mean over the global minibatch); logged update metrics are the global minibatch's token means
(ratio_max a max). A process short of rows in a minibatch runs a zero-weight copy of a real row so that
every process makes the same all-reduces, and a non-finite loss on any process stops every process at the
same step. Main process only: evaluation (SFT baseline, periodic, final), metrics.jsonl, saved rollouts,
final/ and eval.json; checkpoints are written once (`loop.Checkpointer`); time/* are the main process's.
Measured against one process in tests/posttrain/test_distributed.py (same samples, rewards and lengths
exactly; losses and update metrics within float summation order).
"""
from __future__ import annotations

import collections
import time
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import torch

from posttrain import loop
from posttrain.advantages import group_advantages, zero_variance_groups
from posttrain.config import ConfigError, Resolved, save_resolved
from posttrain.logprobs import batched_logprobs, masked_mean, sequence_logprobs
from posttrain.losses import aggregate_token_loss, kl_penalty, ppo_policy_loss

PREFLIGHT_ROWS = 8  # worked solutions scored before training (a broken verifier stops there)


@dataclass
class GRPOConfig:
    verifier: str = "auto"
    """Reward verifier spec ("countdown", "0.9*math + 0.1*format", "file.py:name"); auto: the task's; none: RM only."""
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
    clip_eps: float = 0.2
    """PPO clip range of the ratio (lower side, and upper side unless clip_eps_high is set)."""
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
    micro_batch_size: int = 0
    """Rows per forward pass (gradient accumulation); 0: a whole minibatch at once."""
    old_logprobs: Literal["rollout", "recompute"] = "rollout"
    """pi_old: the rollout engine's log-probs (no extra forward) or a no-grad recompute."""
    mask_truncated: bool = False
    """Give completions cut at max_new_tokens no loss (DAPO overlong filtering); they still count in their group."""
    zero_variance: Literal["keep", "skip", "resample"] = "skip"
    """Groups with identical rewards: keep them, skip them, or resample more prompts to refill (DAPO)."""
    max_resample_rounds: int = 2
    """Extra sampling rounds per step at most when zero_variance=resample."""
    lr: float = 1e-4
    """Peak learning rate (AdamW)."""
    weight_decay: float = 0.0
    """AdamW weight decay (not applied to norms and embeddings)."""
    warmup_steps: int = 0
    """Linear warmup, in optimizer updates."""
    schedule: Literal["cosine", "linear", "constant"] = "constant"
    """Learning-rate schedule after warmup."""
    min_lr_ratio: float = 0.0
    """Final learning rate as a fraction of the peak (cosine / linear)."""
    max_grad_norm: float = 1.0
    """Gradient clipping norm (0 disables)."""
    max_steps: int = 100
    """Steps; each is one batch of rollouts (mu x minibatches optimizer updates)."""
    log_every: int = 1
    """Steps between console lines (metrics.jsonl gets every step)."""
    eval_every: int = 20
    """Steps between held-out greedy evaluations; 0: only before and after training."""
    eval_rows: int = 100
    """Held-out problems for the periodic evaluation."""
    final_eval_rows: int = 200
    """Held-out problems for the SFT vs GRPO comparison (before and after training; 0 skips it)."""
    save_every: int = 50
    """Steps between checkpoints (0: only at the end)."""
    keep_checkpoints: int = 2
    """Checkpoints kept on disk (oldest deleted first)."""
    save_rollouts_every: int = 0
    """Steps between saving a step's scored rollouts to rollouts/step-NNNNNN.jsonl (0: never)."""
    seed: int = 0
    """Seed of prompt order, sampling and row shuffles."""
    resume: bool = False
    """Continue from the newest checkpoint in the run directory."""


# ----------------------------------------------------------------------------- problems and reward
@dataclass
class Problem:
    """One prompt with its verifier reference; `key` (its row index) seeds its samples."""

    prompt: str
    reference: Any
    key: int
    prompt_ids: list[int] = field(default_factory=list)


def _present(value: Any) -> bool:
    if isinstance(value, str):
        return bool(value.strip())
    if isinstance(value, (dict, list)):
        return bool(value)
    return value is not None


def row_reference(row: dict[str, Any]) -> Any:
    """The verifier reference of a row: `answer`, else meta.answer / meta.reference; None when missing or empty."""
    meta = row.get("meta") if isinstance(row.get("meta"), dict) else {}
    for value in (row.get("answer"), meta.get("answer"), meta.get("reference")):
        if _present(value):
            return value
    return None


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
    if cfg.verifier == "none" and cfg.reward_model == "none":
        raise bad("verifier=none and reward_model=none: there is no reward; set one of them")


def build_verifier(cfg: GRPOConfig, task, rows: list[dict[str, Any]]):
    """The Verifier instance of `cfg.verifier` (auto: the rows' `verifier` field, else the task's VERIFIER), or None."""
    from verifiers.registry import get_verifier

    spec = cfg.verifier.strip()
    if spec == "none":
        return None
    if spec == "auto":
        named = sorted({str(r["verifier"]) for r in rows if r.get("verifier")})
        if len(named) > 1:
            raise ConfigError(f"grpo.verifier=auto: the problems name several verifiers ({', '.join(named)}); "
                              "set grpo.verifier to one spec (e.g. logic dispatches on the reference's family)")
        spec = named[0] if named else (task.VERIFIER or "")
        if not spec:
            raise ConfigError(f"grpo.verifier=auto but task {task.NAME!r} names no verifier "
                              "(VERIFIER); set grpo.verifier, e.g. grpo.verifier=math")
    try:
        return get_verifier(spec, **cfg.verifier_options)
    except (ValueError, ImportError, TypeError) as e:
        raise ConfigError(f"grpo.verifier: {e}") from None


def check_problems(rows: list[dict[str, Any]], source: str, on_bad: str) -> tuple[list[Problem], list[int]]:
    """Problems of `rows` (1-based row numbers in errors); rows without a reference stop or are skipped."""
    problems, skipped = [], []
    for i, row in enumerate(rows):
        ref = row_reference(row)
        if ref is None:
            if on_bad == "error":
                raise ConfigError(f"{source}: row {i + 1}: no reference answer for the verifier (an 'answer' field, "
                                  "or meta.answer / meta.reference); fix the row or set grpo.on_bad_rows=skip")
            skipped.append(i + 1)
            continue
        problems.append(Problem(row["prompt"], ref, i))
    return problems, skipped


def preflight(verifier, pool, rows: list[dict[str, Any]], source: str, say) -> None:
    """Score the worked solutions of the first rows: a verifier that raises stops here, with the row."""
    from verifiers.runner import VerifierError

    rows = [r for r in rows[:PREFLIGHT_ROWS] if isinstance(r.get("completion"), str) and row_reference(r) is not None]
    if not rows:
        return
    try:
        verdicts = pool.score(verifier, [r["completion"] for r in rows], [row_reference(r) for r in rows])
    except VerifierError as e:
        where = f"the worked solution of {source} row {e.index + 1}" if e.index is not None else "loading"
        raise ConfigError(f"grpo.verifier {verifier.name!r} raised {e.exc_type} on {where}: {e.message} "
                          "(a bug in the verifier or a malformed reference; nothing was trained)") from None
    low = [(i, v) for i, v in enumerate(verdicts) if v.score < 1.0]
    if low:
        i, v = low[0]
        say(f"[grpo] note: the verifier scores {len(low)} of {len(rows)} worked solutions below 1 (e.g. {source} "
            f"row {i + 1}: {v.score:.2f}, {v.reason!r}); check that the verifier matches the task's answer format")


# ----------------------------------------------------------------------------- rollouts of one step
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


def _row_metrics(sb: StepBatch, K: int, verifier_parts: set[str]) -> dict[str, float]:
    """Reward, pass rates, zero-variance fraction, length and truncation of the first round's rows."""
    n = sb.first_round_groups * K
    r = sb.rewards[:n]
    zv = zero_variance_groups(r, K)
    lengths = [len(x.completion_ids) for x in sb.rollouts[:n]]
    m: dict[str, float] = {
        "reward/mean": float(r.mean()), "reward/std": float(r.std()) if n > 1 else 0.0,
        "zero_var_frac": float(zv.float().mean()),
        "completion/length": sum(lengths) / n, "completion/max_length": float(max(lengths)),
        "completion/truncated": sum(x.finish_reason == "length" for x in sb.rollouts[:n]) / n,
    }
    for name, values in sb.parts.items():
        v = values[:n]
        m[f"reward/{name}"] = sum(v) / n
        if name in verifier_parts:
            m[f"pass/{name}"] = sum(x >= 1.0 for x in v) / n
    reasons = sb.reasons[:n]
    m["verifier/timeouts"] = float(sum("timeout" in x for x in reasons))
    m["verifier/crashes"] = float(sum("crashed" in x for x in reasons))
    m["verifier/errors"] = float(sum("verifier error" in x for x in reasons))
    if sb.rounds > 1:
        m["resample/rounds"] = float(sb.rounds)
        m["zero_var_frac/all_rounds"] = float(zero_variance_groups(sb.rewards, K).float().mean())
    return m


def degenerate_message(step: int, sb: StepBatch, K: int, passed: list[bool] | None) -> str | None:
    """Words for a step where every group got identical rewards (the loss is ~0: nothing to learn).

    `passed`: per completion, whether the correctness verifier passed it (None: no verifier)."""
    zv = zero_variance_groups(sb.rewards, K)
    if not bool(zv.all()):
        return None
    values = sorted({round(float(x), 4) for x in sb.rewards})
    common = collections.Counter(x for x in sb.reasons if x).most_common(1)
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


# ----------------------------------------------------------------------------- loss
def grpo_loss(cfg: GRPOConfig, model, mb: dict[str, torch.Tensor], scale: float,
              with_entropy: bool) -> tuple[torch.Tensor, dict[str, float]]:
    """The GRPO loss of one micro-batch (policy term + beta * KL term, same aggregation), times `scale`."""
    loss_mask = mb["loss_mask"]
    logps, entropy = sequence_logprobs(model, mb["input_ids"], mb["attention_mask"], loss_mask,
                                       temperature=cfg.temperature, return_entropy=with_entropy,
                                       entropy_grad=False)  # (b, T); the entropy is a metric here
    loss, m = ppo_policy_loss(logps, mb["old_logps"], mb["advantages"], loss_mask, clip_eps=cfg.clip_eps,
                              clip_eps_high=cfg.clip_eps_high, aggregation=cfg.aggregation,
                              max_tokens=cfg.max_new_tokens)
    m = {"policy_loss": float(loss.detach()), **m}
    if cfg.beta > 0:
        kl = kl_penalty(logps, mb["ref_logps"], cfg.kl_estimator)  # (b, T)
        kl_loss = aggregate_token_loss(kl, loss_mask, cfg.aggregation, cfg.max_new_tokens)
        loss = loss + cfg.beta * kl_loss
        m["kl"] = float(masked_mean(kl.detach(), loss_mask.bool()))
    if with_entropy:
        m["entropy"] = float(masked_mean(entropy.detach(), loss_mask.bool()))
    return loss * scale, m


def _micro_batches(rows: dict[str, torch.Tensor], idx: torch.Tensor, micro: int, aggregation: str,
                   rank: int = 0, world: int = 1) -> list[tuple[dict[str, torch.Tensor], float, float]]:
    """This process's micro-batches of the minibatch `idx` (process r takes rows r, r + W, ... of it), all-padding
    columns trimmed, each with (its share of the minibatch loss, its share of the minibatch's loss tokens).

    Shares are fractions of the WHOLE minibatch (all processes): token_mean weighs by loss tokens, the other
    aggregations by rows, so the shares of all micro-batches of all processes sum to 1 and the accumulated (and,
    under DDP, averaged x W) gradient is the whole minibatch's aggregation. micro = 0: one micro-batch per
    process. Every process returns the same number of micro-batches (a process short of rows gets copies of
    a real row with share 0), so the DDP all-reduces of the last one line up on every process."""
    total_rows = len(idx)
    total_tokens = float(rows["loss_mask"][idx].sum())
    mine = idx[rank::world]
    largest = -(-total_rows // world)  # rows of the largest share
    micro = micro or largest
    out = []
    for i in range(-(-largest // micro)):
        sel = mine[i * micro:(i + 1) * micro]
        real = len(sel) > 0
        if not real:
            sel = idx[:1]
        am = rows["attention_mask"][sel]
        live = am.any(0).nonzero()
        lo, hi = int(live[0]), int(live[-1]) + 1
        mb = {k: (v[sel][:, lo:hi] if v.dim() == 2 else v[sel]) for k, v in rows.items()}
        tokens = float(mb["loss_mask"].sum()) / total_tokens if real else 0.0
        share = tokens if aggregation == "token_mean" else (len(sel) / total_rows if real else 0.0)
        out.append((mb, share, tokens))
    return out


def _weights_finite(model) -> bool:
    return all(bool(torch.isfinite(p).all()) for p in model.parameters())


# ----------------------------------------------------------------------------- train
def train(res: Resolved, ensure) -> Path:
    """GRPO on the recipe's task from the SFT model; returns the final model directory."""
    from posttrain import tasks
    from posttrain.data import load_rows
    from posttrain.models import is_model_dir
    from verifiers.runner import VerifierPool

    cfg: GRPOConfig = res.stage_cfg
    check_config(cfg)
    say_all = print

    # Problems and the reward first: a bad row or a broken verifier stops before any model loads.
    try:
        task = tasks.get_task(res.task.name)
    except ValueError as e:
        raise ConfigError(f"task.name: {e}") from None

    def split_rows(split: str, file: str | None) -> tuple[list[dict], str]:
        if file:
            return [dict(r) for r in load_rows(file, "verifiable")], file
        return tasks.load_split(res.task, split), f"task {res.task.name} ({split})"

    train_rows, train_source = split_rows("train", cfg.train_file)
    eval_rows, eval_source = split_rows("eval", cfg.eval_file)
    eval_rows = eval_rows[: max(cfg.eval_rows, cfg.final_eval_rows)]
    verifier = build_verifier(cfg, task, train_rows)
    if verifier is not None:
        problems, skipped = check_problems(train_rows, train_source, cfg.on_bad_rows)
        eval_problems, eval_skipped = check_problems(eval_rows, eval_source, cfg.on_bad_rows)
        for n, what, rows in ((skipped, train_source, train_rows), (eval_skipped, eval_source, eval_rows)):
            if n:
                say_all(f"[grpo] skipped {len(n)} of {len(rows)} problems of {what} without a reference answer "
                        f"(rows {', '.join(map(str, n[:10]))}{', ...' if len(n) > 10 else ''})")
    else:  # reward model only: no references needed
        problems = [Problem(r["prompt"], None, i) for i, r in enumerate(train_rows)]
        eval_problems = [Problem(r["prompt"], None, i) for i, r in enumerate(eval_rows)]
    if len(problems) < cfg.prompts_per_step:
        raise ConfigError(f"{train_source}: {len(problems)} usable problems, fewer than grpo.prompts_per_step="
                          f"{cfg.prompts_per_step}")
    if cfg.reward_model not in ("none", "train") and not is_model_dir(cfg.reward_model):
        raise ConfigError(f"grpo.reward_model {cfg.reward_model!r} is not a model directory; give none, train or "
                          "the path of a reward model (posttrain rm output)")
    pool = VerifierPool(workers=cfg.verifier_workers, timeout_s=cfg.verifier_timeout_s or None)
    try:
        if verifier is not None:
            preflight(verifier, pool, train_rows, train_source, say_all)
        rm_dir = ensure("rm") if cfg.reward_model == "train" else \
            (Path(cfg.reward_model) if cfg.reward_model != "none" else None)
        sft_dir = ensure("sft")
        return _train(res, cfg, verifier, pool, problems, eval_problems, rm_dir, sft_dir)
    finally:
        pool.close()


def _train(res: Resolved, cfg: GRPOConfig, verifier, pool, problems: list[Problem], eval_problems: list[Problem],
           rm_dir: Path | None, sft_dir: Path) -> Path:
    import json

    from posttrain.chat import encode_prompts
    from posttrain.models import load_model, load_tokenizer, maybe_lora, reference_view, save_model
    from posttrain.rollout import SamplingParams, collate_rollouts, default_backend, generate, save_rollouts
    from posttrain.scoring import RewardModelScorer, VerifierScorer, WeightedScorer
    from verifiers.runner import VerifierError

    run_dir = res.stage_dir()
    accelerator = loop.setup(cfg.seed, res.run.threads)
    main = accelerator.is_main_process
    say = print if main else (lambda *a, **k: None)
    if main:
        loop.prepare_run_dir(run_dir, cfg.resume, say)
        save_resolved(res, run_dir / "config.yaml")
    accelerator.wait_for_everyone()

    tokenizer = load_tokenizer(sft_dir, res.model)
    model = maybe_lora(res, load_model(sft_dir, res.model.dtype, device=accelerator.device), say)  # LoRA: adapters start at 0
    # beta = 0: no reference model at all; LoRA: the policy with its adapters off (no copy of the weights)
    ref_model = None
    if cfg.beta > 0:
        ref_model = reference_view(model) if res.use_lora else \
            load_model(sft_dir, res.model.dtype, device=accelerator.device).eval().requires_grad_(False)

    # Prompts tokenized once (the engine takes ids); prompt + max_new_tokens > max_length: dropped with a count.
    def tokenize(ps: list[Problem], what: str) -> list[Problem]:
        ids = encode_prompts(tokenizer, [p.prompt for p in ps])  # chat template when it has one
        kept = []
        for p, x in zip(ps, ids):
            if len(x) + cfg.max_new_tokens <= res.model.max_length:
                p.prompt_ids = list(x)
                kept.append(p)
        if len(kept) < len(ps):
            say(f"[grpo] dropped {len(ps) - len(kept)}/{len(ps)} {what} prompts longer than model.max_length="
                f"{res.model.max_length} - max_new_tokens={cfg.max_new_tokens}")
        return kept

    problems, eval_problems = tokenize(problems, "training"), tokenize(eval_problems, "held-out")
    if len(problems) < cfg.prompts_per_step:
        raise loop.TrainingError(f"only {len(problems)} training prompts fit, fewer than prompts_per_step="
                                 f"{cfg.prompts_per_step}")

    # The reward, through one scoring interface whatever makes it.
    timeout = cfg.verifier_timeout_s or None
    vscorer = eval_scorer = None
    if verifier is not None:
        vscorer = VerifierScorer(verifier, pool=pool, timeout_s=timeout, name="verifier",
                                 on_error="zero" if cfg.on_verifier_error == "zero" else "raise")
        eval_scorer = VerifierScorer(verifier, pool=pool, timeout_s=timeout, name="verifier", on_error="zero")
    rm_scorer = RewardModelScorer(rm_dir, device=accelerator.device, name="rm") if rm_dir is not None else None
    if vscorer is not None and rm_scorer is not None:
        scorer = WeightedScorer([(vscorer, cfg.verifier_weight), (rm_scorer, cfg.reward_model_weight)])
    else:
        scorer = vscorer if vscorer is not None else rm_scorer
    part_labels = [label for label, _, _ in getattr(verifier, "parts", [])]
    prefix = "verifier/" if rm_scorer is not None else ""  # a WeightedScorer prefixes its scorers' parts
    verifier_parts = ({"verifier"} | {prefix + p for p in part_labels}) if verifier is not None else set()
    correctness = part_labels[0] if part_labels else None  # the first term of a composition

    K, P = cfg.group_size, cfg.prompts_per_step
    rank, world = accelerator.process_index, accelerator.num_processes
    # pi_old recomputed: asked for, a truncated sampler (top-p) at temperature != 1, or vLLM rollouts (their
    # log-probs come from vLLM's forward, not the training one; see posttrain.rollout.vllm_backend).
    recompute_old = cfg.old_logprobs == "recompute" or (cfg.temperature != 1.0 and cfg.top_p < 1.0) \
        or default_backend() == "vllm"
    optimizer = loop.build_optimizer(model, cfg.lr, cfg.weight_decay)
    scheduler = loop.build_scheduler(optimizer, cfg.warmup_steps, cfg.max_steps * cfg.mu * cfg.minibatches,
                                     cfg.schedule, cfg.min_lr_ratio)
    model, optimizer = accelerator.prepare(model, optimizer)
    ckpt = loop.Checkpointer(run_dir, cfg.keep_checkpoints, accelerator)
    metrics = loop.MetricsLog(run_dir / "metrics.jsonl", cfg.max_steps, main, res.run.quiet, prefix="[grpo] ")

    start = 0
    if cfg.resume:
        last = ckpt.latest()
        if last is None:
            say(f"[grpo] resume=true but no checkpoint in {ckpt.dir}; starting from step 0")
        else:
            start = ckpt.load(last, model, optimizer, scheduler)["step"]
            metrics.truncate_after(start)
            say(f"[grpo] resumed from {last} at step {start}")

    def policy():
        return accelerator.unwrap_model(model)

    # ------------------------------------------------------------------ held-out evaluation
    def evaluate(ps: list[Problem]) -> dict[str, Any]:
        """Greedy completions of held-out problems, scored by the verifier (and the reward model)."""
        rollouts = generate(policy(), tokenizer, [p.prompt_ids for p in ps],
                            SamplingParams(n=1, max_new_tokens=cfg.max_new_tokens, greedy=True),
                            prompt_keys=[p.key for p in ps])
        texts, prompts = [r.text for r in rollouts], [p.prompt for p in ps]
        ev: dict[str, Any] = {"texts": texts, "lengths": [len(r.completion_ids) for r in rollouts],
                              "truncated": [r.finish_reason == "length" for r in rollouts]}
        if eval_scorer is not None:
            sr = eval_scorer.score(prompts, texts, [p.reference for p in ps])
            ev.update(reward=sr.rewards, parts=sr.parts, reasons=sr.reasons)
        if rm_scorer is not None:
            ev["rm"] = rm_scorer.score(prompts, texts).rewards
        return ev

    def summarise(ev: dict[str, Any], n: int) -> dict[str, float]:
        """eval/* metrics of the first n rows of an `evaluate` result."""
        n = min(n, len(ev["texts"]))
        if n == 0:
            return {}
        m = {"eval/length": sum(ev["lengths"][:n]) / n, "eval/truncated": sum(ev["truncated"][:n]) / n}
        if "reward" in ev:
            m["eval/reward"] = sum(ev["reward"][:n]) / n
            m["eval/pass"] = sum(x >= 1.0 for x in ev["reward"][:n]) / n
            for label, values in ev["parts"].items():
                if label != "verifier":
                    m[f"eval/pass/{label}"] = sum(x >= 1.0 for x in values[:n]) / n
            src = ev["parts"][correctness] if correctness else ev["reward"]
            m["eval/accuracy"] = sum(x >= 1.0 for x in src[:n]) / n
        if "rm" in ev:
            m["eval/rm"] = sum(ev["rm"][:n]) / n
        return m

    n_final = min(cfg.final_eval_rows, len(eval_problems))
    n_eval = min(cfg.eval_rows, len(eval_problems))
    baseline_file = run_dir / "sft_eval.json"  # the SFT model's numbers, kept for a resumed run
    baseline: dict[str, Any] = {}
    if main and (n_final or n_eval):
        if start > 0 and baseline_file.is_file():
            baseline = json.loads(baseline_file.read_text())
        elif start == 0:
            t0 = time.time()
            ev = evaluate(eval_problems[: max(n_final, n_eval)])
            baseline = {"metrics": summarise(ev, n_final or n_eval), "eval_metrics": summarise(ev, n_eval),
                        "samples": [{"prompt": p.prompt, "completion": t}
                                    for p, t in zip(eval_problems[:10], ev["texts"])]}
            loop.write_json(baseline_file, baseline)
            if n_eval:
                metrics.log(0, baseline["eval_metrics"], console=False)
            key = "eval/accuracy" if "eval/accuracy" in baseline["metrics"] else "eval/rm"
            say(f"[grpo] SFT model, greedy, {n_final or n_eval} held-out problems: {key.removeprefix('eval/')} "
                f"{baseline['metrics'][key]:.3f} ({time.time() - t0:.1f}s)")

    # ------------------------------------------------------------------ one step's rollouts
    timing: dict[str, float] = collections.defaultdict(float)

    def sample_groups(step: int, rnd: int, ps: list[Problem]) -> tuple[list[tuple], str | None, int]:
        """This process's prompts x K samples in one generate call, scored: ([(problem, K rollouts, K rewards,
        K reasons, {part: K values})], the message of a verifier error under on_verifier_error=stop, number of
        distinct completions scored)."""
        if not ps:  # more processes than prompts: this one has none this round
            return [], None, 0
        params = SamplingParams(n=K, max_new_tokens=cfg.max_new_tokens, temperature=cfg.temperature,
                                top_p=cfg.top_p, seed=cfg.seed * 1_000_003 + step * 31 + rnd)
        t0 = time.time()
        out = generate(policy(), tokenizer, [p.prompt_ids for p in ps], params, prompt_keys=[p.key for p in ps])
        texts = [r.text for r in out]
        t1 = time.time()
        # Identical completions of the same prompt are scored once (verifiers and reward models are
        # deterministic): a confident policy samples many duplicates, and a sandbox check costs ~50 ms.
        first: dict[tuple[int, str], int] = {}
        slot = [first.setdefault((ps[i // K].key, t), len(first)) for i, t in enumerate(texts)]
        uniq = list(first)  # (problem key, text) in first-seen order
        by_key = {p.key: p for p in ps}
        try:
            su = scorer.score([by_key[k].prompt for k, _ in uniq], [t for _, t in uniq],
                              [by_key[k].reference for k, _ in uniq] if vscorer is not None else None)
        except VerifierError as e:  # on_verifier_error=stop: reported after the gather, by every process
            row = uniq[e.index][0] + 1 if e.index is not None and rm_scorer is None else "?"
            return [], (f"verifier {verifier.name!r} raised {e.exc_type} at step {step + 1} on a completion of "
                        f"training problem row {row}: {e.message} (on_verifier_error=stop)"), 0
        timing["sample"] += t1 - t0
        timing["score"] += time.time() - t1
        groups = []
        for g, p in enumerate(ps):
            sl = [slot[g * K + j] for j in range(K)]
            groups.append((p, out[g * K:(g + 1) * K], [su.rewards[i] for i in sl], [su.reasons[i] for i in sl],
                           {k: [v[i] for i in sl] for k, v in su.parts.items()}))
        return groups, None, len(uniq)

    def sample_and_score(step: int) -> StepBatch:
        """The step's P prompts x K samples, scored; resampled rounds when zero_variance=resample.

        Each process samples and scores its share of every round's prompts (positions r, r + W, ... of the
        global batch; prompt keys are problem indices, so they are the samples one process would draw), then
        the groups are gathered: every process holds the whole step batch in global order, and every decision
        and statistic taken from it (resampling, zero-variance filter, advantages, metrics) is global."""
        rollouts, groups, rewards, reasons = [], [], [], []
        parts: dict[str, list[float]] = collections.defaultdict(list)
        informative, first_round, scored = 0, 0, 0
        rounds = 1 + (cfg.max_resample_rounds if cfg.zero_variance == "resample" else 0)
        for rnd in range(rounds):
            idx = loop.batch_indices(len(problems), P, cfg.seed + 7919 * rnd, step)  # the global batch
            mine = list(range(rank, P, world))  # this process's positions in it
            local, error, n_scored = sample_groups(step, rnd, [problems[idx[i]] for i in mine])
            shards = [(list(zip(mine, local)), error, n_scored)]
            if world > 1:
                from accelerate.utils import gather_object

                shards = gather_object(shards)  # one entry per process
            errors = [e for _, e, _ in shards if e]
            if errors:
                raise loop.TrainingError(errors[0])
            scored += sum(n for _, _, n in shards)
            round_groups = [g for _, g in sorted((x for sh, _, _ in shards for x in sh), key=lambda t: t[0])]
            round_reasons = [x for g in round_groups for x in g[3]]
            if vscorer is not None and all("verifier error:" in x for x in round_reasons):
                raise loop.TrainingError(f"verifier {verifier.name!r} raised on every completion of step {step + 1} "
                                         f"({round_reasons[0]}); the reward is broken")
            for p, outs, rs, why, pv in round_groups:
                rollouts += outs
                groups.append(p)
                rewards += rs
                reasons += why
                for k, v in pv.items():
                    parts[k] += v
            first_round = first_round or len(round_groups)
            informative += int((~zero_variance_groups(torch.tensor([r for g in round_groups for r in g[2]]),
                                                      K)).sum())
            if informative >= P:
                break
        timing["scored"] += scored
        return StepBatch(rollouts, groups, torch.tensor(rewards, dtype=torch.float32), dict(parts), reasons,
                         first_round, rnd + 1)

    def sharded_logprobs(m, batch, micro: int) -> torch.Tensor:
        """No-grad log-probs (B, T) of every row of `batch` under `m`: each process computes rows r, r + W, ...,
        then they are gathered (every process needs all rows: its minibatch rows change with every pass)."""
        if world == 1:
            return batched_logprobs(m, batch, micro, temperature=cfg.temperature)[0]
        B, T = batch.input_ids.shape
        own = torch.arange(rank, B, world, device=batch.input_ids.device)
        share = -(-B // world)  # rows of the largest share; the others are padded to it for the gather
        local = torch.zeros(share, T, dtype=torch.float32, device=batch.input_ids.device)
        if len(own):
            rows_ = {"input_ids": batch.input_ids[own], "attention_mask": batch.attention_mask[own],
                     "completion_mask": batch.completion_mask[own]}
            local[:len(own)] = batched_logprobs(m, rows_, micro, temperature=cfg.temperature)[0]
        every = accelerator.gather(local)  # (W * share, T), process-major
        out = torch.empty(B, T, dtype=torch.float32, device=every.device)
        for p in range(world):
            n = len(range(p, B, world))
            out[p::world] = every[p * share:p * share + n]
        return out

    def update(step: int, sb: StepBatch) -> dict[str, float]:
        """Advantages of the kept groups, then mu passes x minibatches optimizer updates; the update metrics.

        The step batch is the same on every process, so the advantages, the row order of each pass and the
        minibatches are too; of each minibatch, process r trains rows r, r + W, ..., with its loss scaled to
        its share of the whole minibatch's aggregation (token_mean: its loss tokens / the minibatch's) times W,
        so DDP's gradient average is the whole minibatch's gradient, as in one process."""
        zv = zero_variance_groups(sb.rewards, K)  # (G,)
        keep = torch.ones_like(zv) if cfg.zero_variance == "keep" else ~zv  # (G,)
        if cfg.zero_variance == "resample":
            keep &= torch.cumsum(keep.long(), 0) <= P  # refill up to P groups, no more
        rows_idx = [g * K + j for g in keep.nonzero().flatten().tolist() for j in range(K)]
        if not rows_idx:
            return {"loss": 0.0, "rows/trained": 0.0, "updates": 0.0}
        rewards = sb.rewards[rows_idx]  # (n,)
        adv = group_advantages(rewards, K, estimator=cfg.estimator, std_scale=cfg.std_scale)  # (n,)
        batch = collate_rollouts([sb.rollouts[i] for i in rows_idx], tokenizer.pad_token_id).to(accelerator.device)
        loss_mask = batch.completion_mask.clone()  # (n, T)
        if cfg.mask_truncated:  # DAPO overlong filtering: truncated completions carry no loss
            loss_mask[torch.tensor([sb.rollouts[i].finish_reason == "length" for i in rows_idx],
                                   device=loss_mask.device)] = 0
        # pi_old from the engine: raw log-probs at temperature 1, or (temperature != 1, no top-p) the log-probs
        # of the distribution it sampled, softmax(logits / T), which is the one the loss uses; else recompute.
        rows = {"input_ids": batch.input_ids, "attention_mask": batch.attention_mask, "loss_mask": loss_mask,
                "advantages": adv.to(accelerator.device),
                "old_logps": batch.policy_logprobs if cfg.temperature == 1.0 else batch.logprobs}
        micro = cfg.micro_batch_size or len(rows_idx)
        if recompute_old:
            rows["old_logps"] = sharded_logprobs(policy(), batch, micro)
        if ref_model is not None:
            rows["ref_logps"] = sharded_logprobs(ref_model, batch, micro)
        usable = (loss_mask.sum(-1) > 0).nonzero().flatten().cpu()  # rows with at least one loss token
        upd: dict[str, list[float]] = collections.defaultdict(list)
        for epoch in range(cfg.mu if len(usable) else 0):
            gen = torch.Generator().manual_seed(cfg.seed * 1_000_003 + step * 101 + epoch)
            order = usable[torch.randperm(len(usable), generator=gen)]
            for mb_idx in torch.tensor_split(order, min(cfg.minibatches, len(usable))):
                mbs = _micro_batches(rows, mb_idx.to(accelerator.device), cfg.micro_batch_size, cfg.aggregation,
                                     rank, world)

                def loss_fn(x, first=epoch == 0, n=len(mbs)):
                    mb, share, tokens = x
                    loss, m = grpo_loss(cfg, model, mb, share * world, first)
                    # loop.optimizer_step averages metrics over micro-batches and processes: weighted so that
                    # average is the whole minibatch's (token means by loss tokens, policy_loss by loss share).
                    w = n * world
                    m = {k: (v if k == "ratio_max" else v * w * (share if k == "policy_loss" else tokens))
                         for k, v in m.items()}
                    if tokens == 0.0:
                        m["ratio_max"] = float("-inf")  # a padding micro-batch: no rows of this process
                    return loss, m  # a non-finite loss on any process stops every process (loop.optimizer_step)

                out = loop.optimizer_step(accelerator, model, optimizer, scheduler, mbs, loss_fn, cfg.max_grad_norm,
                                          step + 1)
                for k, v in out.items():
                    upd[k].append(v)
        m = {k: (max(v) if k == "ratio_max" else sum(v) / len(v)) for k, v in upd.items()}
        m.update({"rows/trained": float(len(usable)), "updates": float(len(upd.get("loss", [])))})
        m.setdefault("loss", 0.0)
        return m

    # ------------------------------------------------------------------ loop
    reward_desc = " + ".join(x for x in (
        (f"{cfg.verifier_weight:g} * " if rm_scorer is not None else "") + f"verifier {verifier.name}"
        if verifier is not None else "",
        f"{cfg.reward_model_weight:g} * reward model {rm_dir}" if rm_scorer is not None else "") if x)
    say(f"[grpo] {len(problems)} training problems, {P} prompts x {K} samples per step, {cfg.max_steps} steps "
        f"({cfg.mu} pass(es) x {cfg.minibatches} update(s) each); reward: {reward_desc}; {cfg.estimator} advantages "
        f"({cfg.std_scale} std), {cfg.aggregation}, beta {cfg.beta}, zero-variance groups: {cfg.zero_variance}; "
        f"rollouts: {default_backend()} backend" + (" (pi_old recomputed)" if recompute_old else "")
        + f"; {world} process(es) on {accelerator.device}")
    t_start = time.time()
    for step in range(start, cfg.max_steps):
        done = step + 1
        timing.clear()
        t_step = time.time()
        try:
            sb = sample_and_score(step)
            m = _row_metrics(sb, K, verifier_parts)
            t0 = time.time()
            m.update(update(step, sb))
            timing["train"] = time.time() - t0
            saving = (cfg.save_every and done % cfg.save_every == 0) or done == cfg.max_steps
            evaluating = cfg.eval_every and done % cfg.eval_every == 0
            if (saving or evaluating) and not _weights_finite(model):
                raise loop.TrainingError(f"non-finite weights after step {done}; stopping without saving them")
        except loop.TrainingError as e:
            last = ckpt.latest()
            where = f"last good checkpoint: {last}" if last else "no checkpoint was written yet"
            raise loop.TrainingError(f"{e} ({where})") from None
        m["verifier/scored"] = timing.pop("scored", 0.0)  # distinct completions scored (duplicates reuse a score)
        m.update({f"time/{k}": v for k, v in timing.items()})
        m["time/step"] = time.time() - t_step
        metrics.log(done, m, console=False)

        # what a user asks when a run misbehaves, in words
        if m["verifier/errors"]:
            i = next(j for j, x in enumerate(sb.reasons) if "verifier error" in x)
            say(f"[grpo] step {done}: the verifier raised on {int(m['verifier/errors'])} of {len(sb.reasons)} "
                f"completions, scored 0 (e.g. training problem row {sb.problems[i // K].key + 1}: {sb.reasons[i]})")
        if m["verifier/timeouts"] or m["verifier/crashes"]:
            say(f"[grpo] step {done}: {int(m['verifier/timeouts'])} verifier timeouts and "
                f"{int(m['verifier/crashes'])} crashes, scored 0 (the step went on)")
        passed = None
        if verifier is not None:  # the correctness part (first term of a composition), else the whole verdict
            src = sb.parts.get(prefix + correctness) if correctness else sb.parts.get("verifier")
            passed = [x >= 1.0 for x in (src if src is not None else sb.rewards.tolist())]
        note = degenerate_message(done, sb, K, passed)
        if note:
            say(note)
        if main and not res.run.quiet and (done % cfg.log_every == 0 or done == cfg.max_steps):
            elapsed = time.time() - t_start
            eta = elapsed / max(1, done - start) * (cfg.max_steps - done)
            shown = [("reward", m["reward/mean"]), ("zero_var", m["zero_var_frac"]), ("loss", m["loss"]),
                     ("clip", m.get("clip_frac")), ("kl", m.get("kl")), ("entropy", m.get("entropy")),
                     ("len", m["completion/length"]), ("trunc", m["completion/truncated"])]
            print(f"[grpo] step {done}/{cfg.max_steps} " + " ".join(f"{k} {v:.4g}" for k, v in shown if v is not None)
                  + f" | {m['time/step']:.2f}s (sample {timing['sample']:.2f}, score {timing['score']:.2f}, "
                  f"train {timing['train']:.2f}), {elapsed:.0f}s elapsed, eta {eta:.0f}s", flush=True)
        if main and cfg.save_rollouts_every and done % cfg.save_rollouts_every == 0:
            for r, reward, reason in zip(sb.rollouts, sb.rewards.tolist(), sb.reasons):
                r.reward = reward
                r.extras["reason"] = reason
            save_rollouts(sb.rollouts, run_dir / "rollouts" / f"step-{done:06d}.jsonl")
        if main and n_eval and cfg.eval_every and done % cfg.eval_every == 0 and done != cfg.max_steps:
            em = summarise(evaluate(eval_problems[:n_eval]), n_eval)
            metrics.log(done, em, console=False)
            say(f"[grpo] step {done} eval, {n_eval} held-out problems: "
                + ", ".join(f"{k.removeprefix('eval/')} {v:.3f}" for k, v in em.items()))
        if (cfg.save_every and done % cfg.save_every == 0) or done == cfg.max_steps:
            ckpt.save(done, model, optimizer, scheduler, {"step": done})

    final = run_dir / "final"
    if main:
        save_model(policy(), tokenizer, final)
        say(f"[grpo] saved {final}")
        report: dict[str, Any] = {"model": str(final), "sft": str(sft_dir)}
        if n_final or n_eval:
            n = n_final or n_eval
            ev = evaluate(eval_problems[: max(n, n_eval)])
            after = summarise(ev, n)
            if n_eval:
                metrics.log(cfg.max_steps, summarise(ev, n_eval), console=False)
            before = baseline.get("metrics", {})
            report.update(rows=n, sft=before, grpo=after,
                          samples=[{"prompt": p.prompt, "completion": t}
                                   for p, t in zip(eval_problems[:10], ev["texts"])])
            key = "eval/accuracy" if "eval/accuracy" in after else "eval/rm"
            was = f"SFT {before[key]:.3f} -> " if key in before else ""
            say(f"[grpo] held-out greedy {key.removeprefix('eval/')} on {n} problems: {was}GRPO {after[key]:.3f}")
        loop.write_json(run_dir / "eval.json", report)
    accelerator.wait_for_everyone()
    return final
