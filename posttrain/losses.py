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
- `simpo_loss`: SimPO, the reference-free length-normalised margin loss.
- `orpo_loss`: ORPO, the SFT loss plus an odds-ratio term, reference-free.
- `kto_loss`: KTO, unpaired desirable / undesirable completions against a batch KL reference point.
- `bradley_terry_loss`: the reward-model pairwise loss, optional margin.
- `ppo_policy_loss`: PPO clipped surrogate with DAPO clip-higher and three aggregations.
- `gspo_policy_loss`: GSPO's sequence-level clipped ratio, and its token-level variant GSPO-token.
- `cispo_policy_loss`: CISPO's clipped, stop-gradient importance weight times the log-prob.
- `policy_loss`: the one entry the trainers call, selecting among the three by a `PolicyLoss` name.
- `rollout_correction`: truncated (TIS) or masked (IcePop-style) importance weights between the
  sampler and the trainer; `sampler_mismatch`: the gap between them as metrics.
- `aggregate_token_loss`: those aggregations on their own, so that a GRPO trainer reduces its
  per-token KL term exactly like the policy term.
- `token_divergence`: on-policy distillation's per-token reverse / forward KL or GKD's generalised JSD
  between the student's and the teacher's full next-token distributions.
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
- `cispo_policy_loss` writes CISPO's term as -A sg(w) exp(log pi - sg(log pi)) rather than the
  paper's -A sg(w) log pi: the gradient is the same (-A w grad log pi), and the value is the
  clipped-weight surrogate -A w, comparable with PPO's, instead of a number that moves with log pi.
- `rollout_correction(level="sequence")` uses the geometric mean of the token ratios (verl's
  "geometric" level), not their product: the product, the exact sequence weight, spans orders of
  magnitude that grow with length, so one cap C would truncate or drop nearly every long sequence.
"""
from __future__ import annotations

import math
from typing import Literal

import torch
import torch.nn.functional as F

from posttrain.logprobs import masked_mean, masked_sum, masked_var

Aggregation = Literal["seq_mean_token_mean", "token_mean", "seq_mean_token_sum_norm"]
Divergence = Literal["reverse_kl", "forward_kl", "jsd"]
PolicyLoss = Literal["clip", "gspo", "gspo_token", "cispo"]
Correction = Literal["none", "tis", "mask"]
CorrectionLevel = Literal["token", "sequence"]


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


def simpo_loss(
    policy_chosen_logps: torch.Tensor,
    policy_rejected_logps: torch.Tensor,
    chosen_tokens: torch.Tensor,
    rejected_tokens: torch.Tensor,
    *,
    beta: float,
    gamma: float,
) -> tuple[torch.Tensor, dict[str, float]]:
    """SimPO (Meng et al. 2024, "SimPO: Simple Preference Optimization with a Reference-Free Reward", eq. 6).

    The implicit reward is the length-normalised log-likelihood r(y) = (beta / |y|) log pi(y): no reference
    model. Per pair, -log sigmoid(r(y_c) - r(y_r) - gamma) with the target reward margin gamma >= 0; mean
    over the B pairs. Inputs: (B,) summed log-probs of each side and (B,) their token counts (clamped to
    >= 1). The paper's ranges: beta 2-10, gamma 0.3-1.6 (TRL's CPOTrainer writes gamma as
    simpo_gamma and divides by beta inside the sigmoid's argument, which is the same loss).

    Metrics: rewards/chosen, rewards/rejected (means of r), rewards/margin, rewards/accuracy (r_c > r_r),
    logps/chosen, logps/rejected (the per-token means (1/|y|) log pi, without beta).
    """
    if beta <= 0 or gamma < 0:
        raise ValueError(f"simpo_loss: beta must be > 0 and gamma >= 0, got {beta}, {gamma}")
    avg_c = policy_chosen_logps / chosen_tokens.clamp(min=1)  # (B,)
    avg_r = policy_rejected_logps / rejected_tokens.clamp(min=1)  # (B,)
    rc, rr = beta * avg_c, beta * avg_r  # (B,), (B,)
    loss = -F.logsigmoid(rc - rr - gamma).mean()
    with torch.no_grad():
        metrics = {
            "rewards/chosen": rc.detach().mean().item(), "rewards/rejected": rr.detach().mean().item(),
            "rewards/margin": (rc - rr).detach().mean().item(),
            "rewards/accuracy": (rc.detach() > rr.detach()).float().mean().item(),
            "logps/chosen": avg_c.detach().mean().item(), "logps/rejected": avg_r.detach().mean().item(),
        }
    return loss, metrics


def orpo_loss(
    policy_chosen_logps: torch.Tensor,
    policy_rejected_logps: torch.Tensor,
    chosen_tokens: torch.Tensor,
    rejected_tokens: torch.Tensor,
    *,
    lam: float,
) -> tuple[torch.Tensor, dict[str, float]]:
    """ORPO (Hong et al. 2024, "ORPO: Monolithic Preference Optimization without Reference Model", eq. 6-7).

    With the per-token mean log-likelihood l(y) = (1/|y|) log pi(y) and odds(y) = P / (1 - P) for
    P = exp(l(y)) (the paper's length-normalised likelihood), the odds-ratio term is
        L_OR = -log sigmoid( log odds(y_c) - log odds(y_r) ),
    log odds(y) = l(y) - log(1 - exp(l(y))), and the loss is L_SFT + lam * L_OR, where L_SFT is the
    chosen side's per-token NLL, -l(y_c), averaged over pairs: one stage, no reference model. The paper
    uses lam 0.1-0.2 (TRL's ORPOConfig calls it beta). Inputs as `simpo_loss`. log(1 - exp(l)) is computed
    as log(-expm1(l)), finite for every l < 0 (l = 0, a certain completion, gives -inf odds: clamped to
    l <= -1e-6 here).

    Metrics: nll (L_SFT), log_odds_ratio (mean of log odds(y_c) - log odds(y_r)), rewards/accuracy
    (fraction with log odds(y_c) > log odds(y_r)), rewards/margin (mean of lam times the log-odds ratio,
    TRL's reward margin), logps/chosen and logps/rejected (means of l).
    """
    if lam < 0:
        raise ValueError(f"orpo_loss: lam must be >= 0, got {lam}")
    avg_c = (policy_chosen_logps / chosen_tokens.clamp(min=1)).clamp(max=-1e-6)  # (B,)
    avg_r = (policy_rejected_logps / rejected_tokens.clamp(min=1)).clamp(max=-1e-6)  # (B,)
    log_odds = (avg_c - torch.log(-torch.expm1(avg_c))) - (avg_r - torch.log(-torch.expm1(avg_r)))  # (B,)
    odds_term = -F.logsigmoid(log_odds).mean()
    nll = -avg_c.mean()
    loss = nll + lam * odds_term
    with torch.no_grad():
        lo = log_odds.detach()
        metrics = {
            "nll": nll.detach().item(), "odds_ratio_loss": odds_term.detach().item(),
            "log_odds_ratio": lo.mean().item(), "rewards/accuracy": (lo > 0).float().mean().item(),
            "rewards/margin": (lam * lo).mean().item(),
            "logps/chosen": avg_c.detach().mean().item(), "logps/rejected": avg_r.detach().mean().item(),
        }
    return loss, metrics


def kto_loss(
    policy_logps: torch.Tensor,
    reference_logps: torch.Tensor,
    desirable: torch.Tensor,
    kl_policy_logps: torch.Tensor,
    kl_reference_logps: torch.Tensor,
    *,
    beta: float,
    desirable_weight: float = 1.0,
    undesirable_weight: float = 1.0,
) -> tuple[torch.Tensor, dict[str, float]]:
    """KTO (Ethayarajh et al. 2024, "KTO: Model Alignment as Prospect Theoretic Optimization", eq. 7-8):
    unpaired completions, each labelled desirable or undesirable, no pairs.

    r(x, y) = log pi(y|x) - log pi_ref(y|x) (summed over the completion's tokens, (B,) inputs), and the
    reference point z0 = max(0, mean_j [log pi(y'_j|x_j) - log pi_ref(y'_j|x_j)]), a batch estimate of
    KL(pi || pi_ref) from completions y'_j that do NOT belong to their prompt x_j (`kl_*_logps`, (B',)
    summed log-probs: the paper and TRL pair each prompt with another row's completion); z0 carries no
    gradient. Per row the loss is
        desirable:    w_D (1 - sigmoid(beta (r - z0)))
        undesirable:  w_U (1 - sigmoid(beta (z0 - r)))
    averaged over the B rows (the paper's lambda_y - v(x, y)). The paper sets w_D n_D / (w_U n_U) in
    [1, 4/3] when the classes are unbalanced. `desirable` is (B,) bool.

    Metrics: kl (z0), rewards/chosen and rewards/rejected (mean beta r of desirable / undesirable rows, NaN
    when the batch has none), rewards/margin (their difference), rewards/accuracy (fraction of rows on the
    right side of z0: r > z0 if desirable, r < z0 if not), logps/chosen, logps/rejected.
    """
    if beta <= 0 or desirable_weight < 0 or undesirable_weight < 0:
        raise ValueError(f"kto_loss: beta must be > 0 and the weights >= 0, got {beta}, {desirable_weight}, "
                         f"{undesirable_weight}")
    desirable = desirable.bool()
    z0 = (kl_policy_logps - kl_reference_logps).mean().clamp(min=0).detach()  # ()
    r = policy_logps - reference_logps  # (B,)
    value = torch.where(desirable, torch.sigmoid(beta * (r - z0)), torch.sigmoid(beta * (z0 - r)))  # (B,)
    weight = torch.where(desirable, torch.full_like(r, desirable_weight), torch.full_like(r, undesirable_weight))
    loss = (weight * (1 - value)).mean()
    with torch.no_grad():
        rd = (beta * r).detach()

        def mean_of(x: torch.Tensor, sel: torch.Tensor) -> float:
            return x[sel].mean().item() if sel.any() else float("nan")

        chosen, rejected = mean_of(rd, desirable), mean_of(rd, ~desirable)
        metrics = {
            "kl": z0.item(), "rewards/chosen": chosen, "rewards/rejected": rejected,
            "rewards/margin": chosen - rejected,
            "rewards/accuracy": torch.where(desirable, r > z0, r < z0).float().mean().item(),
            "logps/chosen": mean_of(policy_logps.detach(), desirable),
            "logps/rejected": mean_of(policy_logps.detach(), ~desirable),
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
    weights: torch.Tensor | None = None,
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
    `weights` (B, T), optional and never differentiated: per-token factors of the loss, the
    importance weights of `rollout_correction` (TIS: verl multiplies its policy loss the same way).

    GRPO's KL term and PPO's entropy bonus are separate terms the trainer adds: `kl_penalty`
    reduced with the same `aggregate_token_loss`, and the entropy from `posttrain.logprobs`.

    Metrics (over completion tokens, no grad): clip_frac (fraction where the clipped branch
    is active, i.e. strictly larger; = clip_frac_low + clip_frac_high), clip_frac_low (A < 0,
    ratio < 1 - clip_eps), clip_frac_high (A > 0, ratio > 1 + clip_eps_high), approx_kl (k3
    estimate of KL(pi_old || pi_theta) on the rollout samples: ratio - 1 - log ratio, cleanrl's
    `approx_kl`), ratio_mean, ratio_max.
    """
    eps_low, eps_high, completion_mask, advantages, log_ratio = _ratio_inputs(
        logps, old_logps, advantages, completion_mask, clip_eps, clip_eps_high, "ppo_policy_loss")
    ratio = log_ratio.exp()  # (B, T)
    unclipped = -advantages * ratio  # (B, T)
    clipped = -advantages * ratio.clamp(1.0 - eps_low, 1.0 + eps_high)  # (B, T)
    per_token = torch.maximum(unclipped, clipped)  # (B, T)
    loss = aggregate_token_loss(_weighted(per_token, weights, completion_mask), completion_mask, aggregation,
                                max_tokens)
    return loss, _ratio_metrics(ratio, log_ratio, advantages, completion_mask, eps_low, eps_high,
                                clipped_branch=clipped.detach() > unclipped.detach())


def _weighted(per_token: torch.Tensor, weights: torch.Tensor | None, mask: torch.Tensor) -> torch.Tensor:
    """per_token * weights (detached; selected inside the mask, so garbage outside it stays out)."""
    if weights is None:
        return per_token
    return per_token * torch.where(mask, weights.detach(), torch.ones_like(per_token))


def _ratio_metrics(ratio: torch.Tensor, log_ratio: torch.Tensor, advantages: torch.Tensor, mask: torch.Tensor,
                   eps_low: float, eps_high: float, clipped_branch: torch.Tensor) -> dict[str, float]:
    """The clip and ratio statistics of a (B, T) ratio over the masked tokens (see `ppo_policy_loss`)."""
    with torch.no_grad():
        r, lr = ratio.detach(), log_ratio.detach()  # (B, T)
        clip_low = mask & (advantages < 0) & (r < 1.0 - eps_low)  # (B, T)
        clip_high = mask & (advantages > 0) & (r > 1.0 + eps_high)  # (B, T)
        return {
            "clip_frac": masked_mean(clipped_branch.float(), mask).item(),
            "clip_frac_low": masked_mean(clip_low.float(), mask).item(),
            "clip_frac_high": masked_mean(clip_high.float(), mask).item(),
            "approx_kl": masked_mean(r - 1.0 - lr, mask).item(),
            "ratio_mean": masked_mean(r, mask).item(),
            "ratio_max": r[mask].max().item() if mask.any() else float("nan"),
        }


def _ratio_inputs(logps, old_logps, advantages, completion_mask, clip_eps, clip_eps_high, who: str):
    """Shared argument handling of the policy losses: the clip range, a bool mask, (B, T) advantages selected
    inside the mask and the masked log-ratio log pi - log pi_old."""
    if clip_eps <= 0 or (clip_eps_high is not None and clip_eps_high <= 0):
        raise ValueError(f"{who}: clip ranges must be > 0, got {clip_eps}, {clip_eps_high}")
    eps_high = clip_eps if clip_eps_high is None else clip_eps_high
    completion_mask = completion_mask.bool()
    if advantages.dim() == 1:
        advantages = advantages.unsqueeze(-1)  # (B,) -> (B, 1), broadcasts over T
    advantages = torch.where(completion_mask, advantages.detach(), 0.0).expand_as(logps)  # (B, T)
    log_ratio = torch.where(completion_mask, logps - old_logps.detach(), torch.zeros_like(logps))  # (B, T)
    return clip_eps, eps_high, completion_mask, advantages, log_ratio


def gspo_policy_loss(
    logps: torch.Tensor,
    old_logps: torch.Tensor,
    advantages: torch.Tensor,
    completion_mask: torch.Tensor,
    *,
    clip_eps: float,
    clip_eps_high: float | None = None,
    token_level: bool = False,
    aggregation: Aggregation = "seq_mean_token_mean",
    max_tokens: int | None = None,
    weights: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """GSPO (Zheng et al. 2025, "Group Sequence Policy Optimization"): one importance ratio per sequence.

    The sequence ratio is the geometric mean of the token ratios (GSPO eq. 7),
        s_i = exp( (1/|o_i|) sum_t [log pi_theta(o_it) - log pi_old(o_it)] ),
    clipped per sequence: loss_i = max(-A_i s_i, -A_i clip(s_i, 1 - clip_eps, 1 + clip_eps_high)), and
    the loss is the mean over sequences (GSPO eq. 5). The paper's ranges are far narrower than PPO's
    (3e-4 / 4e-4, §5.1), because s_i averages the log-ratios. `advantages` must be (B,) (one per
    sequence); `aggregation` must stay "seq_mean_token_mean" and `weights`, if given, must be constant
    along each sequence (a sequence-level importance weight): both follow from the loss being per sequence.

    `token_level=True` is GSPO-token (GSPO eq. 13): s_it = sg(s_i) * pi_theta(o_it) / sg(pi_theta(o_it)),
    equal to s_i in value but differentiated per token, so (B, T) advantages (PPO's GAE) are allowed;
    the per-token clipped term is reduced by `aggregate_token_loss(aggregation)` and `weights` (B, T)
    multiply it. With one advantage per sequence and the per-sequence token mean, GSPO-token's loss and
    gradient equal GSPO's (GSPO §4.3; tested).

    Metrics: as `ppo_policy_loss`'s, over sequences for GSPO (clip_frac: fraction of sequences whose
    clipped branch is active; ratio_mean / ratio_max: of s_i) and over tokens for GSPO-token; approx_kl
    is the token-level k3 estimate of KL(pi_old || pi_theta) in both.
    """
    eps_low, eps_high, mask, adv, log_ratio = _ratio_inputs(logps, old_logps, advantages, completion_mask,
                                                           clip_eps, clip_eps_high, "gspo_policy_loss")
    seq_log_ratio = masked_mean(log_ratio, mask, dim=-1)  # (B,)
    with torch.no_grad():
        token_kl = masked_mean(log_ratio.exp() - 1.0 - log_ratio, mask).item()
    if token_level:
        log_s = seq_log_ratio.detach().unsqueeze(-1) + logps - logps.detach()  # (B, T)
        s = torch.where(mask, log_s, torch.zeros_like(log_s)).exp()  # (B, T)
        unclipped = -adv * s  # (B, T)
        clipped = -adv * s.clamp(1.0 - eps_low, 1.0 + eps_high)  # (B, T)
        per_token = torch.maximum(unclipped, clipped)  # (B, T)
        loss = aggregate_token_loss(_weighted(per_token, weights, mask), mask, aggregation, max_tokens)
        m = _ratio_metrics(s, log_s, adv, mask, eps_low, eps_high, clipped.detach() > unclipped.detach())
        return loss, {**m, "approx_kl": token_kl}
    if advantages.dim() != 1:
        raise ValueError("gspo_policy_loss: sequence-level GSPO needs one advantage per sequence, shape (B,); "
                         f"got {tuple(advantages.shape)} (use token_level=True for per-token advantages)")
    if aggregation != "seq_mean_token_mean":
        raise ValueError("gspo_policy_loss: sequence-level GSPO is a mean over sequences; aggregation must be "
                         f"'seq_mean_token_mean', got {aggregation!r}")
    has_tokens = mask.any(-1)  # (B,)
    a = advantages.detach()  # (B,)
    s = seq_log_ratio.exp()  # (B,)
    unclipped = -a * s  # (B,)
    clipped = -a * s.clamp(1.0 - eps_low, 1.0 + eps_high)  # (B,)
    per_seq = torch.where(has_tokens, torch.maximum(unclipped, clipped), torch.zeros_like(s))  # (B,)
    if weights is not None:
        wt = weights.detach()
        w = wt.masked_fill(~mask, float("-inf")).amax(-1)  # (B,) the sequence's weight
        spread = w - wt.masked_fill(~mask, float("inf")).amin(-1)  # (B,) 0 when constant along the sequence
        if bool((has_tokens & (spread > 1e-6 * w.abs().clamp(min=1.0))).any()):
            raise ValueError("gspo_policy_loss: sequence-level GSPO takes one weight per sequence; `weights` vary "
                             "along a sequence (use sequence-level rollout correction, or token_level=True)")
        per_seq = per_seq * torch.where(has_tokens, w, torch.ones_like(w))
    loss = per_seq.mean()
    seq_mask = has_tokens.unsqueeze(-1)  # (B, 1): the metrics over sequences
    m = _ratio_metrics(s.unsqueeze(-1), seq_log_ratio.unsqueeze(-1), a.unsqueeze(-1), seq_mask, eps_low, eps_high,
                       (clipped.detach() > unclipped.detach()).unsqueeze(-1))
    return loss, {**m, "approx_kl": token_kl}


def cispo_policy_loss(
    logps: torch.Tensor,
    old_logps: torch.Tensor,
    advantages: torch.Tensor,
    completion_mask: torch.Tensor,
    *,
    clip_eps: float,
    clip_eps_high: float | None = None,
    aggregation: Aggregation = "token_mean",
    max_tokens: int | None = None,
    weights: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """CISPO (MiniMax-M1, Chen et al. 2025, eq. 4): clip the importance weight, not the update.

    With r = pi_theta / pi_old per token and w = sg(clip(r, 1 - clip_eps, 1 + clip_eps_high)), the
    gradient is -A w grad log pi_theta on EVERY completion token: PPO's clip zeroes the gradient of a
    token whose ratio left the range (often the rare "fork" tokens, MiniMax-M1 §3.1), CISPO only caps
    its weight. The per-token term is written -A w exp(log pi - sg(log pi)) (value -A w, the paper's
    gradient; see the module notes) and reduced by `aggregate_token_loss(aggregation)` (the paper
    uses the token mean). MiniMax-M1 sets no lower bound on w: clip_eps >= 1 does that here.
    `weights` (B, T): the rollout-correction factors, as in `ppo_policy_loss`.

    Metrics: clip_frac (fraction of tokens whose weight was capped, either side; = clip_frac_low +
    clip_frac_high, here regardless of the advantage's sign), approx_kl, ratio_mean, ratio_max.
    """
    eps_low, eps_high, mask, adv, log_ratio = _ratio_inputs(logps, old_logps, advantages, completion_mask,
                                                           clip_eps, clip_eps_high, "cispo_policy_loss")
    ratio = log_ratio.exp()  # (B, T)
    w = ratio.detach().clamp(max(0.0, 1.0 - eps_low), 1.0 + eps_high)  # (B, T), stop-gradient
    surrogate = torch.where(mask, logps - logps.detach(), torch.zeros_like(logps)).exp()  # value 1, grad of log pi
    per_token = -adv * w * surrogate  # (B, T)
    loss = aggregate_token_loss(_weighted(per_token, weights, mask), mask, aggregation, max_tokens)
    with torch.no_grad():
        r = ratio.detach()
        low, high = mask & (r < 1.0 - eps_low), mask & (r > 1.0 + eps_high)  # (B, T)
        m = _ratio_metrics(ratio, log_ratio, adv, mask, eps_low, eps_high, low | high)
        m.update({"clip_frac_low": masked_mean(low.float(), mask).item(),
                  "clip_frac_high": masked_mean(high.float(), mask).item()})
    return loss, m


def policy_loss(
    kind: PolicyLoss,
    logps: torch.Tensor,
    old_logps: torch.Tensor,
    advantages: torch.Tensor,
    completion_mask: torch.Tensor,
    *,
    clip_eps: float,
    clip_eps_high: float | None = None,
    aggregation: Aggregation = "token_mean",
    max_tokens: int | None = None,
    weights: torch.Tensor | None = None,
) -> tuple[torch.Tensor, dict[str, float]]:
    """The policy loss a trainer asks for by name: "clip" (`ppo_policy_loss`: PPO / GRPO / DAPO / Dr.
    GRPO), "gspo" and "gspo_token" (`gspo_policy_loss`), "cispo" (`cispo_policy_loss`); same arguments."""
    kw = dict(clip_eps=clip_eps, clip_eps_high=clip_eps_high, aggregation=aggregation, max_tokens=max_tokens,
              weights=weights)
    if kind == "clip":
        return ppo_policy_loss(logps, old_logps, advantages, completion_mask, **kw)
    if kind in ("gspo", "gspo_token"):
        return gspo_policy_loss(logps, old_logps, advantages, completion_mask, token_level=kind == "gspo_token", **kw)
    if kind == "cispo":
        return cispo_policy_loss(logps, old_logps, advantages, completion_mask, **kw)
    raise ValueError(f"policy_loss: unknown kind {kind!r}; expected 'clip', 'gspo', 'gspo_token' or 'cispo'")


# ----------------------------------------------------------------------------- rollout correction
def sampler_mismatch(train_logps: torch.Tensor, sampler_logps: torch.Tensor,
                     completion_mask: torch.Tensor) -> dict[str, float]:
    """How far the sampler's log-probs are from the trainer's on the sampled tokens (no grad).

    `train_logps` (B, T): the trainer's log pi of the sampled tokens with the weights that sampled;
    `sampler_logps` (B, T): the sampler's own. With log w = train - sampler on tokens drawn from the
    sampler: mismatch/kl is the k3 estimate of KL(sampler || trainer), mean of w - 1 - log w (>= 0);
    mismatch/max_ratio and mismatch/min_ratio are the extremes of w = pi_train / pi_sampler.
    """
    mask = completion_mask.bool()
    with torch.no_grad():
        log_w = torch.where(mask, train_logps.detach() - sampler_logps.detach(), torch.zeros_like(train_logps))
        w = log_w.exp()
        any_ = bool(mask.any())
        return {"mismatch/kl": masked_mean(w - 1.0 - log_w, mask).item(),
                "mismatch/max_ratio": w[mask].max().item() if any_ else float("nan"),
                "mismatch/min_ratio": w[mask].min().item() if any_ else float("nan")}


def rollout_correction(
    train_logps: torch.Tensor,
    sampler_logps: torch.Tensor,
    completion_mask: torch.Tensor,
    *,
    kind: Correction,
    level: CorrectionLevel = "token",
    cap: float = 2.0,
) -> tuple[torch.Tensor | None, torch.Tensor, dict[str, float]]:
    """Importance weights for a sampler that is not the trainer's forward: (weights, loss mask, metrics).

    When the samples come from pi_sampler (vLLM, bf16 weights, stale weights) but the loss's pi_old is
    the trainer's own forward at rollout time, the policy gradient is off by w = pi_old / pi_sampler
    per token. `train_logps` (B, T) are pi_old's log-probs, `sampler_logps` (B, T) the sampler's, both
    fixed per rollout batch (no grad). log w = train - sampler per token; at `level="sequence"` every
    token of a sequence gets the geometric mean of its token ratios (see the module notes).
    - "tis": truncated importance sampling (Yao et al. 2025, "Your Efficient RL Framework Secretly
      Brings You Off-Policy RL Training"): weights min(w, cap), the mask unchanged.
    - "mask": masked importance sampling (IcePop, Ling Team 2025, "Every Step Evolves"): tokens (or
      whole sequences) with w outside [1/cap, cap] leave the loss mask; the others keep weight w.
    - "none": weights None and the mask as given.
    The trainer multiplies its per-token policy loss by `weights` (the `weights` argument of the policy
    losses) and uses the returned mask as its loss mask, so dropped tokens leave the normalisers too.

    Metrics: correction/weight_mean and correction/max_weight (mean and largest applied weight over the kept
    tokens: <= cap by construction), correction/truncated
    (fraction of tokens whose weight was capped: tis) and correction/masked (fraction dropped: mask).
    """
    if cap <= 1.0:
        raise ValueError(f"rollout_correction: cap must be > 1, got {cap}")
    mask = completion_mask.bool()
    if kind == "none":
        return None, mask, {}
    if kind not in ("tis", "mask"):
        raise ValueError(f"rollout_correction: unknown kind {kind!r}; expected 'none', 'tis' or 'mask'")
    if level not in ("token", "sequence"):
        raise ValueError(f"rollout_correction: unknown level {level!r}; expected 'token' or 'sequence'")
    with torch.no_grad():
        log_w = torch.where(mask, train_logps.detach() - sampler_logps.detach(), torch.zeros_like(train_logps))
        if level == "sequence":
            log_w = masked_mean(log_w, mask, dim=-1).unsqueeze(-1).expand_as(log_w)  # (B, T)
        w = log_w.exp()  # (B, T)
        if kind == "tis":
            weights, keep = w.clamp(max=cap), mask
            metrics = {"correction/truncated": masked_mean((w > cap).float(), mask).item()}
        else:
            inside = (log_w >= -math.log(cap)) & (log_w <= math.log(cap))  # (B, T)
            weights, keep = w, mask & inside
            metrics = {"correction/masked": masked_mean((~inside).float(), mask).item()}
        weights = torch.where(keep, weights, torch.ones_like(weights))
        metrics["correction/weight_mean"] = masked_mean(weights, keep).item()
        metrics["correction/max_weight"] = weights[keep].max().item() if keep.any() else float("nan")
    return weights, keep, metrics


# ----------------------------------------------------------------------------- distillation
def token_divergence(
    student_logits: torch.Tensor,
    teacher_logits: torch.Tensor,
    mask: torch.Tensor,
    *,
    kind: Divergence = "reverse_kl",
    beta: float = 0.5,
) -> torch.Tensor:
    """Per-token divergence between the student's and the teacher's next-token distributions over the whole
    vocabulary: (..., V) logits of both at the same positions, a (...) mask -> (...) values, 0 outside it.

    With S = softmax(student_logits) and P = softmax(teacher_logits) at each position:
    - "reverse_kl": KL(S || P) = sum_v S (log S - log P), mode-seeking; the per-token loss of on-policy
      distillation (Agarwal et al. 2024, GKD, with the student's own samples; Gu et al. 2024, MiniLLM).
    - "forward_kl": KL(P || S) = sum_v P (log P - log S), mean-seeking (the classic distillation loss,
      Hinton et al. 2015, evaluated here on the student's samples).
    - "jsd": GKD's generalised Jensen-Shannon divergence (Agarwal et al. 2024, eq. 1),
        JSD(beta) = beta KL(P || M) + (1 - beta) KL(S || M),  M = beta P + (1 - beta) S,  beta in (0, 1);
      it tends to beta x forward KL as beta -> 0 and to (1 - beta) x reverse KL as beta -> 1 (TRL's
      GKDTrainer names the two ends beta 0 and 1 and special-cases them; here they are the other two kinds).
    Differentiable in both arguments (pass the teacher's logits detached); computed in fp32 from
    log_softmax, so each value is >= 0 up to rounding. Temperature: divide the logits before the call.
    """
    if student_logits.shape != teacher_logits.shape or student_logits.shape[:-1] != mask.shape:
        raise ValueError(f"token_divergence: student {tuple(student_logits.shape)}, teacher "
                         f"{tuple(teacher_logits.shape)} and mask {tuple(mask.shape)} must agree (..., V) / (...)")
    return logprob_divergence(masked_log_softmax(student_logits, mask), masked_log_softmax(teacher_logits, mask),
                              mask, kind=kind, beta=beta)


def masked_log_softmax(logits: torch.Tensor, mask: torch.Tensor) -> torch.Tensor:
    """fp32 log_softmax of (..., V) logits where the (...) mask is set, of zeros elsewhere (uniform, finite): garbage
    logits outside the mask are selected away (not multiplied), so they reach neither a value nor a gradient."""
    keep = mask.bool()[..., None]
    return F.log_softmax(torch.where(keep, logits.float(), torch.zeros((), device=logits.device)), -1)


def logprob_divergence(log_s: torch.Tensor, log_p: torch.Tensor, mask: torch.Tensor, *,
                       kind: Divergence = "reverse_kl", beta: float = 0.5) -> torch.Tensor:
    """`token_divergence` from the two sides' log-probabilities over the vocabulary (`masked_log_softmax` of their
    logits), for a caller that needs those log-probs for more than one quantity (on-policy distillation's loss, its
    NLL and both KL metrics from one log_softmax per side)."""
    if kind not in ("reverse_kl", "forward_kl", "jsd"):
        raise ValueError(f"token_divergence: unknown kind {kind!r}; expected 'reverse_kl', 'forward_kl' or 'jsd'")
    if kind == "jsd" and not 0 < beta < 1:
        raise ValueError(f"token_divergence: jsd needs 0 < beta < 1, got {beta}")
    mask = mask.bool()
    if kind == "reverse_kl":
        per_token = (log_s.exp() * (log_s - log_p)).sum(-1)  # (...)
    elif kind == "forward_kl":
        per_token = (log_p.exp() * (log_p - log_s)).sum(-1)  # (...)
    else:
        log_m = torch.logaddexp(log_p + math.log(beta), log_s + math.log(1 - beta))  # (..., V)
        per_token = beta * (log_p.exp() * (log_p - log_m)).sum(-1) \
            + (1 - beta) * (log_s.exp() * (log_s - log_m)).sum(-1)  # (...)
    return torch.where(mask, per_token, torch.zeros_like(per_token))


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
