"""Losses of preference learning and policy optimisation, as pure tensor functions.

Every function here takes tensors and returns `(loss, metrics)` (or a per-token tensor): no
model, optimizer or config inside. `loss` is a 0-dim tensor that carries the graph; `metrics`
is a dict of python floats computed without grad, ready for `loop.MetricsLog`.

Shapes: B sequences (or preference pairs), T token columns. Per-token tensors follow the
`RolloutBatch` layout (`posttrain/rollout/records.py`): `completion_mask` (B, T) selects the
completion tokens (bool or 0/1; prompt and padding columns are 0, anything may sit there).
Log-probs are those of the sampled tokens as `posttrain.logprobs` gathers them, and every
masked mean / sum comes from `posttrain.logprobs` (the single implementation).

- `dpo_loss`: DPO (sigmoid, with conservative-DPO label smoothing), IPO, SLiC hinge.
- `bradley_terry_loss`: the reward-model pairwise loss, optional margin.
- `ppo_policy_loss`: PPO clipped surrogate with DAPO clip-higher and three aggregations.
- `aggregate_token_loss`: those aggregations on their own, so that a GRPO trainer reduces its
  per-token KL term exactly like the policy term.
- `kl_penalty`: Schulman's k1 / k2 / k3 per-token estimators.
- `value_loss`: PPO clipped value loss.

Not here, on purpose: the entropy bonus (entropy comes from `posttrain.logprobs`; a trainer
subtracts `coef * masked_mean(entropy, completion_mask)`) and the SFT loss (a masked mean of
`-logprobs`).

Choices and deviations, each named again where it is used:
- Inputs outside `completion_mask` are replaced by 0 with `torch.where` (selected, not
  multiplied by the mask) before any arithmetic, so garbage (even NaN/inf) in prompt or padding
  columns never reaches a loss, a metric or a gradient.
- `ppo_policy_loss(aggregation="seq_mean_token_sum_norm")` requires `max_tokens` (the
  generation budget, e.g. `max_new_tokens`): TRL divides by B * max_completion_length; verl
  divides by the padded width T only (not by B). Neither T (= prompt + completion columns in a
  `RolloutBatch`) nor B-free scaling is the constant normaliser Dr. GRPO asks for.
- `value_loss` keeps the 1/2 factor of TRL / "N implementation details of RLHF with PPO"
  (cleanrl uses it too); its explained variance is that of the `values` passed in.
- `kl_penalty` does not clamp (verl clamps its k3, "low_var_kl", to [-10, 10]).
"""
from __future__ import annotations

from typing import Literal

import torch
import torch.nn.functional as F

from posttrain.logprobs import masked_mean, masked_sum, masked_var

Aggregation = Literal["seq_mean_token_mean", "token_mean", "seq_mean_token_sum_norm"]


# ----------------------------------------------------------------------------- preferences
def dpo_loss(
    policy_chosen_logps: torch.Tensor,
    policy_rejected_logps: torch.Tensor,
    ref_chosen_logps: torch.Tensor,
    ref_rejected_logps: torch.Tensor,
    *,
    beta: float,
    loss_type: Literal["sigmoid", "ipo", "hinge"],
    label_smoothing: float = 0.0,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Direct preference losses on per-sequence log-probs of (chosen, rejected) pairs.

    Inputs are (B,) log pi(y|x) of each completion under the policy and under the frozen
    reference. With the log-ratio difference
        h = [log pi(y_c) - log ref(y_c)] - [log pi(y_r) - log ref(y_r)]        # (B,)
    the per-pair losses are (then averaged over the B pairs):
    - "sigmoid": DPO, Rafailov et al. 2023, eq. 7: -log sigmoid(beta h); with
      `label_smoothing` = eps, conservative DPO (Mitchell 2023, "A note on DPO with noisy
      preferences"; TRL's `label_smoothing`): -(1 - eps) log sigmoid(beta h) - eps log sigmoid(-beta h),
      i.e. the labels are assumed flipped with probability eps.
    - "ipo": IPO, Azar et al. 2023 ("A General Theoretical Paradigm to Understand Learning from
      Human Preferences"), eq. 17 with tau = beta: (h - 1/(2 beta))^2. It regresses h to a
      finite target instead of pushing it to infinity. Pass LENGTH-AVERAGED log-probs for IPO
      (sum of token log-probs / number of completion tokens, for policy and reference alike):
      that is how TRL applies it (`logps / loss_mask.sum(-1)` when loss_type == "ipo"); on summed
      log-probs the target 1/(2 beta) is a per-sequence margin and the loss scales with length.
    - "hinge": SLiC-HF (Zhao et al. 2023) calibration loss in TRL's form: relu(1 - beta h),
      i.e. beta * max(0, delta - h) with margin delta = 1/beta, on reference-adjusted log-ratios.

    `label_smoothing` only exists for "sigmoid" (0 <= eps <= 0.5; 0.5 makes the loss blind to
    the label). Metrics (means over the batch, python floats): rewards/chosen and
    rewards/rejected are the implicit rewards beta (log pi - log ref), rewards/margin their
    difference, rewards/accuracy the fraction with chosen reward > rejected reward,
    logps/chosen and logps/rejected the policy log-probs as passed in.
    """
    if beta <= 0:
        raise ValueError(f"dpo_loss: beta must be > 0, got {beta}")
    if not 0.0 <= label_smoothing <= 0.5:
        raise ValueError(f"dpo_loss: label_smoothing must be in [0, 0.5], got {label_smoothing}")
    if label_smoothing and loss_type != "sigmoid":
        raise ValueError(f"dpo_loss: label_smoothing applies to loss_type='sigmoid' only, got {loss_type!r}")

    chosen_logratios = policy_chosen_logps - ref_chosen_logps  # (B,)
    rejected_logratios = policy_rejected_logps - ref_rejected_logps  # (B,)
    h = chosen_logratios - rejected_logratios  # (B,)

    if loss_type == "sigmoid":
        losses = (
            -(1.0 - label_smoothing) * F.logsigmoid(beta * h) - label_smoothing * F.logsigmoid(-beta * h)
        )  # (B,)
    elif loss_type == "ipo":
        losses = (h - 1.0 / (2.0 * beta)) ** 2  # (B,)
    elif loss_type == "hinge":
        losses = torch.relu(1.0 - beta * h)  # (B,)
    else:
        raise ValueError(f"dpo_loss: unknown loss_type {loss_type!r}; expected 'sigmoid', 'ipo' or 'hinge'")
    loss = losses.mean()

    with torch.no_grad():
        chosen_rewards = beta * chosen_logratios.detach()  # (B,)
        rejected_rewards = beta * rejected_logratios.detach()  # (B,)
        metrics = {
            "rewards/chosen": chosen_rewards.mean().item(),
            "rewards/rejected": rejected_rewards.mean().item(),
            "rewards/margin": (chosen_rewards - rejected_rewards).mean().item(),
            "rewards/accuracy": (chosen_rewards > rejected_rewards).float().mean().item(),
            "logps/chosen": policy_chosen_logps.detach().mean().item(),
            "logps/rejected": policy_rejected_logps.detach().mean().item(),
        }
    return loss, metrics


def bradley_terry_loss(
    chosen_rewards: torch.Tensor,
    rejected_rewards: torch.Tensor,
    margin: torch.Tensor | float | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """Pairwise reward-model loss: mean of -log sigmoid(r_c - r_r - margin).

    Bradley & Terry 1952 preference model as used for RLHF reward models (Christiano et al.
    2017; Ouyang et al. 2022, eq. 1). `chosen_rewards`, `rejected_rewards`: (B,) scalar rewards
    of the two completions of each pair. `margin`: optional (B,) (or scalar) required gap, the
    Llama 2 margin loss (Touvron et al. 2023, eq. 2; TRL's `margin` column); None = 0.

    Metrics: accuracy (fraction with r_c > r_r), margin (mean r_c - r_r, without the required
    margin), reward/chosen and reward/rejected (means).
    """
    diff = chosen_rewards - rejected_rewards  # (B,)
    logits = diff if margin is None else diff - margin  # (B,)
    loss = -F.logsigmoid(logits).mean()
    with torch.no_grad():
        d = diff.detach()
        metrics = {
            "accuracy": (d > 0).float().mean().item(),
            "margin": d.mean().item(),
            "reward/chosen": chosen_rewards.detach().mean().item(),
            "reward/rejected": rejected_rewards.detach().mean().item(),
        }
    return loss, metrics


# ----------------------------------------------------------------------------- policy optimisation
def aggregate_token_loss(
    per_token: torch.Tensor,
    completion_mask: torch.Tensor,
    aggregation: Aggregation,
    max_tokens: int | None = None,
) -> torch.Tensor:
    """Reduce a (B, T) per-token loss to a scalar over the completion tokens.

    - "seq_mean_token_mean": mean over each sequence's tokens, then mean over sequences,
      (1/B) sum_i (1/|o_i|) sum_t l_it: the GRPO objective (Shao et al. 2024, DeepSeekMath,
      eq. 3). Every sequence weighs the same, so a token of a long sequence weighs less.
    - "token_mean": sum over all completion tokens / their count: DAPO's token-level loss (Yu
      et al. 2025, §3.3 "Token-Level Policy Gradient Loss"). Every token weighs the same.
    - "seq_mean_token_sum_norm": sum over all completion tokens / (B * max_tokens), a
      normaliser that does not depend on lengths: Dr. GRPO (Liu et al. 2025, "Understanding
      R1-Zero-Like Training", which divides each sequence's token sum by the generation
      budget); TRL's `loss_type="dr_grpo"` uses the same B * max_completion_length. Requires
      `max_tokens` = the generation budget (max_new_tokens), constant over training.

    Under gradient accumulation these are means of the micro-batch, not of the optimizer
    batch; a trainer that wants the optimizer-batch token mean must re-weight.
    """
    completion_mask = completion_mask.bool()
    per_token = torch.where(completion_mask, per_token, torch.zeros_like(per_token))  # (B, T)
    if aggregation == "token_mean":
        return masked_mean(per_token, completion_mask)
    if aggregation == "seq_mean_token_mean":
        return masked_mean(per_token, completion_mask, dim=-1).mean()  # (B,) -> ()
    if aggregation == "seq_mean_token_sum_norm":
        if max_tokens is None or max_tokens <= 0:
            raise ValueError(
                "aggregate_token_loss: aggregation='seq_mean_token_sum_norm' needs max_tokens = the "
                f"generation budget (max_new_tokens) as a positive int, got {max_tokens!r}"
            )
        return masked_sum(per_token, completion_mask) / (per_token.shape[0] * max_tokens)
    raise ValueError(
        f"aggregate_token_loss: unknown aggregation {aggregation!r}; expected "
        "'seq_mean_token_mean', 'token_mean' or 'seq_mean_token_sum_norm'"
    )


def ppo_policy_loss(
    logps: torch.Tensor,
    old_logps: torch.Tensor,
    advantages: torch.Tensor,
    completion_mask: torch.Tensor,
    *,
    clip_eps: float,
    clip_eps_high: float | None = None,
    aggregation: Aggregation = "token_mean",
    max_tokens: int | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """PPO clipped surrogate (Schulman et al. 2017, eq. 7), per token, as a loss to minimise.

    `logps` (B, T): log pi_theta of the sampled tokens (with grad); `old_logps` (B, T): log
    pi_old of the same tokens at rollout time (no grad); `advantages`: (B, T) per token (GAE)
    or (B,) per sequence (GRPO / RLOO; broadcast over the tokens). With ratio = exp(logps -
    old_logps), the per-token loss is
        max(-A * ratio, -A * clip(ratio, 1 - clip_eps, 1 + clip_eps_high))
    (the pessimistic bound). `clip_eps_high` = None means symmetric clipping; a larger value
    is DAPO's "clip-higher" (Yu et al. 2025, eps_low = 0.2, eps_high = 0.28): it only changes
    the loss of tokens with A > 0 and ratio > 1 + clip_eps. The per-token loss is reduced by
    `aggregate_token_loss(aggregation, max_tokens)` (GRPO / DAPO / Dr. GRPO normalisers).

    GRPO's KL term and PPO's entropy bonus are separate terms the trainer adds: `kl_penalty`
    reduced with the same `aggregate_token_loss`, and the entropy from `posttrain.logprobs`.

    Metrics (over completion tokens, no grad): clip_frac (fraction where the clipped branch
    is active, i.e. strictly larger; = clip_frac_low + clip_frac_high), clip_frac_low (A < 0,
    ratio < 1 - clip_eps), clip_frac_high (A > 0, ratio > 1 + clip_eps_high), approx_kl (k3
    estimate of KL(pi_old || pi_theta) on the rollout samples: ratio - 1 - log ratio, cleanrl's
    `approx_kl`), ratio_mean, ratio_max.
    """
    if clip_eps <= 0 or (clip_eps_high is not None and clip_eps_high <= 0):
        raise ValueError(f"ppo_policy_loss: clip ranges must be > 0, got {clip_eps}, {clip_eps_high}")
    eps_low = clip_eps
    eps_high = clip_eps if clip_eps_high is None else clip_eps_high
    completion_mask = completion_mask.bool()
    if advantages.dim() == 1:
        advantages = advantages.unsqueeze(-1)  # (B,) -> (B, 1), broadcasts over T
    advantages = torch.where(completion_mask, advantages.detach(), 0.0).expand_as(logps)  # (B, T)

    log_ratio = torch.where(completion_mask, logps - old_logps.detach(), torch.zeros_like(logps))  # (B, T)
    ratio = log_ratio.exp()  # (B, T)
    unclipped = -advantages * ratio  # (B, T)
    clipped = -advantages * ratio.clamp(1.0 - eps_low, 1.0 + eps_high)  # (B, T)
    per_token = torch.maximum(unclipped, clipped)  # (B, T)
    loss = aggregate_token_loss(per_token, completion_mask, aggregation, max_tokens)

    with torch.no_grad():
        r = ratio.detach()  # (B, T)
        lr = log_ratio.detach()  # (B, T)
        clip_low = completion_mask & (advantages < 0) & (r < 1.0 - eps_low)  # (B, T)
        clip_high = completion_mask & (advantages > 0) & (r > 1.0 + eps_high)  # (B, T)
        metrics = {
            "clip_frac": masked_mean((clipped.detach() > unclipped.detach()).float(), completion_mask).item(),
            "clip_frac_low": masked_mean(clip_low.float(), completion_mask).item(),
            "clip_frac_high": masked_mean(clip_high.float(), completion_mask).item(),
            "approx_kl": masked_mean(r - 1.0 - lr, completion_mask).item(),
            "ratio_mean": masked_mean(r, completion_mask).item(),
            "ratio_max": r[completion_mask].max().item() if completion_mask.any() else float("nan"),
        }
    return loss, metrics


def kl_penalty(
    logps: torch.Tensor,
    ref_logps: torch.Tensor,
    kind: Literal["k1", "k2", "k3"],
) -> torch.Tensor:
    """Per-token estimate of KL(pi || pi_ref) from the sampled tokens: (B, T) -> (B, T).

    Schulman's estimators ("Approximating KL Divergence", 2020), with log r = ref_logps - logps
    on tokens sampled from pi:
    - "k1" = log pi - log pi_ref = -log r: unbiased, high variance, can be negative. The
      per-token penalty of the RLHF reward (Ziegler et al. 2019; InstructGPT; use it with
      `advantages.rewards_with_kl`).
    - "k2" = 1/2 (log r)^2: biased, low variance, >= 0. Used as a loss on on-policy samples its
      gradient, E_pi[(log pi - log pi_ref) grad log pi], is exactly grad KL(pi || pi_ref).
    - "k3" = r - 1 - log r = exp(ref - logps) - (ref - logps) - 1: unbiased, low variance,
      >= 0. The KL term of the GRPO loss (Shao et al. 2024, eq. 4). Note its gradient as a loss,
      E_pi[(1 - pi_ref/pi) grad log pi], is the gradient of KL(pi_ref || pi), not of KL(pi || pi_ref).

    Values outside `completion_mask` are meaningless; reduce with a masked aggregation (e.g.
    `aggregate_token_loss`) or mask them. No clamping (verl clamps its k3 to [-10, 10]).
    """
    if kind == "k1":
        return logps - ref_logps  # (B, T)
    if kind == "k2":
        return 0.5 * (logps - ref_logps) ** 2  # (B, T)
    if kind == "k3":
        log_r = ref_logps - logps  # (B, T)
        return log_r.exp() - log_r - 1.0  # (B, T)
    raise ValueError(f"kl_penalty: unknown kind {kind!r}; expected 'k1', 'k2' or 'k3'")


def value_loss(
    values: torch.Tensor,
    old_values: torch.Tensor,
    returns: torch.Tensor,
    completion_mask: torch.Tensor,
    *,
    clip_range: float | None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """PPO value loss: 1/2 masked mean of max((V - R)^2, (V_clip - R)^2).

    `values` (B, T): current value predictions (with grad); `old_values` (B, T): the values
    at rollout time; `returns` (B, T): the targets (GAE returns, no grad). V_clip =
    old_values + clip(values - old_values, -clip_range, clip_range): the clipped value loss of
    the PPO2 baselines / cleanrl / TRL / "The N implementation details of RLHF with PPO"
    (Huang et al. 2022). `clip_range=None`: plain 1/2 (V - R)^2. The mean is over completion
    tokens of the batch.

    Metrics: value_clip_frac (fraction of completion tokens where the clipped error is
    strictly larger, i.e. the clipped branch is active), explained_variance =
    1 - Var(R - V) / Var(R) over completion tokens, for the `values` passed in (cleanrl logs it
    for the rollout values, which equal these on the first minibatch of the first epoch; NaN
    when the returns are constant), value_mean.
    """
    if clip_range is not None and clip_range <= 0:
        raise ValueError(f"value_loss: clip_range must be > 0 or None, got {clip_range}")
    completion_mask = completion_mask.bool()
    zeros = torch.zeros_like(values)
    # select (not multiply) so that NaN/inf outside the mask reaches neither loss nor gradient
    values = torch.where(completion_mask, values, zeros)  # (B, T)
    returns = torch.where(completion_mask, returns.detach(), zeros)  # (B, T)
    unclipped = (values - returns) ** 2  # (B, T)
    if clip_range is None:
        per_token = unclipped  # (B, T)
        clipped = None
    else:
        old = torch.where(completion_mask, old_values.detach(), zeros)  # (B, T)
        v_clipped = old + (values - old).clamp(-clip_range, clip_range)  # (B, T)
        clipped = (v_clipped - returns) ** 2  # (B, T)
        per_token = torch.maximum(unclipped, clipped)  # (B, T)
    per_token = torch.where(completion_mask, per_token, torch.zeros_like(per_token))
    loss = 0.5 * masked_mean(per_token, completion_mask)

    with torch.no_grad():
        v = values.detach()  # (B, T)
        clip_frac = 0.0 if clipped is None else masked_mean(
            (clipped.detach() > unclipped.detach()).float(), completion_mask
        ).item()
        var_returns = masked_var(returns, completion_mask)
        var_residual = masked_var(returns - v, completion_mask)
        explained = (1.0 - var_residual / var_returns).item() if var_returns > 0 else float("nan")
        metrics = {
            "value_clip_frac": clip_frac,
            "explained_variance": explained,
            "value_mean": masked_mean(v, completion_mask).item(),
        }
    return loss, metrics
