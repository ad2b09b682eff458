"""Advantages, returns, RLHF rewards and KL controllers, as pure tensor functions.

Nothing here sees a model, an optimizer or a config; everything runs without grad (rewards,
advantages and returns are constants of the policy update). Shapes: B sequences, T token
columns in the `RolloutBatch` layout (`posttrain/rollout/records.py`), `completion_mask`
(B, T) selecting completion tokens; N = number of completions, K = group size.

- `gae`: Generalized Advantage Estimation per token (PPO).
- `rewards_with_kl`: the per-token RLHF reward (score at the last token, -kl_coef * KL at every token).
- `turn_rewards_with_kl`: the same for multi-turn trajectories, plus each turn's own reward at its last sampled
  token (environment tokens carry no reward and, in `gae`, are no time step).
- `group_advantages`: critic-free per-sequence advantages (GRPO, RLOO, REINFORCE++).
- `zero_variance_groups`: groups whose completions all got the same reward (no signal).
- `track_pass_rates`, `curriculum_weights`: a pass-rate curriculum for verifier-reward RL (which problems
  to sample next: those whose groups are likely to carry signal).
- `FixedKLController`, `AdaptiveKLController`: the KL coefficient of PPO-for-RLHF.

Whitening GAE advantages over the batch (TRL's PPO does it; cleanrl per minibatch) is
`posttrain.logprobs.masked_whiten`; it is not repeated here.

Choices and deviations, each named again where it is used:
- `gae` skips masked columns (it treats the completion tokens of a row as consecutive steps):
  the prompt columns on the left and padding on the right are never read, and the value after
  the last completion token is 0, so bootstrapping stops at the end of each sequence. A hole
  inside a completion (e.g. masked tool output) is stepped over as verl does, not treated as
  an episode end. For a multi-turn trajectory (sampled turns with environment tokens between them,
  `posttrain.rollout.multiturn`) this makes the value bootstrapped after a turn's last sampled token
  the value at the next turn's first sampled token: environment tokens are neither actions nor
  time steps, as in verl's multi-turn GAE (observation tokens skipped) and OpenRLHF's agent
  rollouts (action mask).
- `turn_rewards_with_kl` finds a trajectory's turns as the maximal runs of its completion mask
  (an environment reply is never empty, so two turns never touch); a turn's reward lands on its
  last sampled token and the final score on the trajectory's last one, so the last turn's reward
  and the final score add.
- `group_advantages` uses the unbiased (N-1) standard deviation, as `torch.std`, TRL and verl
  do; `eps` is added to the std, not to the variance.
- REINFORCE++ is implemented at the sequence level (scalar outcome rewards, KL in the loss);
  see `group_advantages` for how to get OpenRLHF's token-weighted variant.
- `curriculum_weights` weighs a problem by the probability that a group of K samples from it is
  informative, 1 - p^K - (1 - p)^K for its tracked pass rate p (binary rewards), rather than by a
  hand-set band of pass rates: it is the chance that dynamic sampling would keep the group.
"""
from __future__ import annotations

from typing import Literal

import torch


# ----------------------------------------------------------------------------- PPO: per-token
@torch.no_grad()
def gae(
    rewards: torch.Tensor,
    values: torch.Tensor,
    completion_mask: torch.Tensor,
    *,
    gamma: float,
    lam: float,
) -> tuple[torch.Tensor, torch.Tensor]:
    """Generalized Advantage Estimation (Schulman et al. 2016) per completion token.

    `rewards` (B, T): per-token rewards (e.g. from `rewards_with_kl`); `values` (B, T): V(s_t)
    at rollout time. Over the completion tokens t_1 < ... < t_n of a row:
        delta_t = r_t + gamma * V(next) - V(t),      V(next) = 0 after the last token
        A_t     = delta_t + gamma * lam * A(next),   A(next) = 0 after the last token
        R_t     = A_t + V(t)                         (the value target)
    Masked columns are skipped, never read (anything, even NaN, may sit there) and get 0 in
    both outputs. Vectorised over the batch; the only loop is over the T columns, backwards.

    Returns `(advantages, returns)`, both (B, T), without grad. With gamma = lam = 1,
    A_t = (sum of rewards from t to the end) - V(t).
    """
    completion_mask = completion_mask.bool()
    B, T = rewards.shape
    zero = torch.zeros((), dtype=values.dtype, device=values.device)
    advantages = torch.zeros_like(values)  # (B, T)
    next_value = torch.zeros(B, dtype=values.dtype, device=values.device)  # (B,)  V after t
    next_adv = torch.zeros(B, dtype=values.dtype, device=values.device)  # (B,)  A after t
    for t in reversed(range(T)):
        valid = completion_mask[:, t]  # (B,)
        r_t = torch.where(valid, rewards[:, t], zero)  # (B,)
        v_t = torch.where(valid, values[:, t], zero)  # (B,)
        delta = r_t + gamma * next_value - v_t  # (B,)
        adv_t = delta + gamma * lam * next_adv  # (B,)
        advantages[:, t] = torch.where(valid, adv_t, zero)
        # a masked column passes the recursion through unchanged (skipped)
        next_adv = torch.where(valid, adv_t, next_adv)
        next_value = torch.where(valid, v_t, next_value)
    returns = torch.where(completion_mask, advantages + values, zero)  # (B, T)
    return advantages, returns


@torch.no_grad()
def rewards_with_kl(
    score: torch.Tensor,
    kl_per_token: torch.Tensor,
    completion_mask: torch.Tensor,
    *,
    kl_coef: float,
) -> torch.Tensor:
    """The per-token RLHF reward: -kl_coef * KL_t at every completion token, + score at the last.

    Ziegler et al. 2019 / InstructGPT (Ouyang et al. 2022, eq. 2) / "The N implementation
    details of RLHF with PPO" (Huang et al. 2022): the reward model's scalar `score` (B,) is
    given to the last completion token of each row (its eos, or its last token when
    truncated) and the KL penalty `kl_per_token` (B, T) (usually `losses.kl_penalty(..., "k1")`
    of the rollout log-probs against the reference) is paid at every completion token.
    Returns (B, T) rewards, 0 outside `completion_mask`, without grad. `kl_coef` comes from a
    KL controller's `.value`. A row with no completion token has nowhere to put its score and
    raises.
    """
    completion_mask = completion_mask.bool()
    B, T = completion_mask.shape
    if not completion_mask.any(dim=-1).all():
        rows = (~completion_mask.any(dim=-1)).nonzero().flatten().tolist()
        raise ValueError(f"rewards_with_kl: rows {rows} have no completion token to receive their score")
    kl = kl_per_token.detach()
    rewards = torch.where(completion_mask, -kl_coef * kl, torch.zeros_like(kl))  # (B, T)
    # index of the last True per row: first True of the flipped row, counted from the end
    last = T - 1 - completion_mask.flip(-1).to(torch.int8).argmax(dim=-1)  # (B,)
    rows = torch.arange(B, device=rewards.device)
    rewards[rows, last] += score.detach().to(rewards.dtype)
    return rewards


@torch.no_grad()
def turn_rewards_with_kl(
    score: torch.Tensor,
    kl_per_token: torch.Tensor,
    completion_mask: torch.Tensor,
    turn_rewards: torch.Tensor,
    *,
    kl_coef: float,
) -> torch.Tensor:
    """The per-token reward of multi-turn trajectories: `rewards_with_kl` plus each turn's reward.

    A trajectory's completion columns are turn 1's sampled tokens, the environment's tokens (tool
    results, the next assistant header), turn 2's sampled tokens, ... (`posttrain.rollout.multiturn`);
    `completion_mask` (B, T) is 1 on the sampled tokens only, and the turns of a row are its maximal
    runs of ones, in column order. `turn_rewards` (B, K) holds the reward of each row's turn k
    (0 where the environment gives none: a reward of 0 and no reward are the same thing here). Per row:
        r_t = -kl_coef * KL_t          at every sampled token (environment tokens get nothing: no action)
            + turn_rewards[k]          at the last sampled token of turn k
            + score                    at the last sampled token of the trajectory
    `score` (B,) is the final (outcome) reward. The KL term and the score are InstructGPT's (Ouyang
    et al. 2022, eq. 2; see `rewards_with_kl`); crediting a turn-level reward to the end of its turn
    and letting GAE carry it back follows multi-turn PPO with turn-level rewards (Zeng et al. 2025,
    "Reinforcing Multi-Turn Reasoning in LLM Agents via Turn-Level Reward Design", arXiv:2505.11821).
    Pass the result to `gae` with the same mask: it steps over the environment columns, so turn k's
    last token bootstraps from the value at turn k+1's first token.

    Returns (B, T) rewards, 0 outside `completion_mask`, without grad. A nonzero reward for a turn
    that a row does not have (K larger than its number of runs) raises, naming the rows; so does a
    row with no sampled token (`rewards_with_kl`).
    """
    completion_mask = completion_mask.bool()
    B, T = completion_mask.shape
    if turn_rewards.dim() != 2 or turn_rewards.shape[0] != B:
        raise ValueError(f"turn_rewards_with_kl: turn_rewards must be (B={B}, K), got {tuple(turn_rewards.shape)}")
    rewards = rewards_with_kl(score, kl_per_token, completion_mask, kl_coef=kl_coef)  # (B, T)
    K = turn_rewards.shape[1]
    if K == 0:
        return rewards
    after = torch.cat([completion_mask[:, 1:], torch.zeros_like(completion_mask[:, :1])], dim=1)  # (B, T)
    ends = completion_mask & ~after  # (B, T): the last sampled token of each turn
    n_turns = ends.sum(dim=-1)  # (B,)
    turn_rewards = turn_rewards.detach().to(rewards.dtype)
    missing = (turn_rewards != 0) & (torch.arange(K, device=ends.device)[None, :] >= n_turns[:, None])  # (B, K)
    if missing.any():
        rows = missing.any(dim=-1).nonzero().flatten().tolist()
        raise ValueError(f"turn_rewards_with_kl: rows {rows} have rewards for more turns than they have runs of "
                         "sampled tokens")
    turn = (ends.long().cumsum(dim=-1) - 1).clamp(0, K - 1)  # (B, T): the turn whose end a column is
    at_end = ends & (ends.long().cumsum(dim=-1) <= K)  # (B, T): ends of turns that have a column in turn_rewards
    return rewards + torch.where(at_end, turn_rewards.gather(1, turn), torch.zeros_like(rewards))


# ----------------------------------------------------------------------------- critic-free: per-sequence
@torch.no_grad()
def group_advantages(
    rewards: torch.Tensor,
    group_size: int,
    *,
    estimator: Literal["grpo", "rloo", "reinforce_pp"],
    std_scale: Literal["group", "batch", "none"],
    eps: float = 1e-6,
) -> torch.Tensor:
    """Per-completion advantages from scalar rewards, without a critic: (N,) -> (N,).

    `rewards` (N,) holds N / K groups of K = `group_size` completions of the same prompt,
    CONTIGUOUS: rewards[g*K:(g+1)*K] is group g (the order the rollout engine returns for
    `n` samples per prompt). N must be a multiple of K.

    The baseline (`estimator`):
    - "grpo": the group mean: A_i = r_i - mean_group(r) (Shao et al. 2024, DeepSeekMath §4.1.2).
    - "rloo": leave-one-out: A_i = r_i - mean_{j != i in group} r_j = K/(K-1) (r_i - mean_group)
      (Kool et al. 2019, "Buy 4 REINFORCE samples, get a baseline for free!"; Ahmadian et al.
      2024, "Back to Basics"). Needs K >= 2.
    - "reinforce_pp": REINFORCE++ (Hu et al. 2025, arXiv:2501.03262), global batch
      normalisation. K = 1 (the paper's REINFORCE++): A = (r - mean_batch(r)) / std_batch(r).
      K > 1 ("REINFORCE++ w/ baseline"): A~ = r - mean_group(r), then
      A = (A~ - mean_batch(A~)) / std_batch(A~) (the batch mean of A~ is 0 with full groups).
      The normalisation is part of the estimator, so `std_scale` must be "batch". This is the
      sequence-level version for outcome rewards with the KL in the loss; OpenRLHF normalises
      over tokens instead (a token-weighted mean and std) and, with KL in the reward, over
      per-token returns. For that variant call `group_advantages(..., estimator="grpo",
      std_scale="none")`, broadcast to (B, T) and apply `posttrain.logprobs.masked_whiten`.

    The divisor (`std_scale`, for "grpo" and "rloo"):
    - "group": std of the raw rewards within the group (GRPO as published; TRL's
      `scale_rewards="group"`). Needs K >= 2.
    - "batch": std of the raw rewards over the whole batch (TRL's `scale_rewards="batch"`;
      "group mean, batch std" of Liu et al. 2025, "Tricks or Traps?").
    - "none": no division. With "grpo" this is Dr. GRPO's mean-centred advantage (Liu et al.
      2025, "Understanding R1-Zero-Like Training"); with "rloo" it is RLOO as published.
    `eps` is added to the std, so a zero-variance group (or batch) gets advantage 0, not NaN.
    """
    if rewards.dim() != 1:
        raise ValueError(f"group_advantages: rewards must be 1-D (N,), got shape {tuple(rewards.shape)}")
    n, k = rewards.numel(), group_size
    if k < 1 or n % k:
        raise ValueError(f"group_advantages: {n} rewards do not split into groups of group_size={k}")
    if estimator not in ("grpo", "rloo", "reinforce_pp"):
        raise ValueError(f"group_advantages: unknown estimator {estimator!r}; expected 'grpo', 'rloo' or 'reinforce_pp'")
    if std_scale not in ("group", "batch", "none"):
        raise ValueError(f"group_advantages: unknown std_scale {std_scale!r}; expected 'group', 'batch' or 'none'")
    if estimator == "reinforce_pp" and std_scale != "batch":
        raise ValueError(
            "group_advantages: estimator='reinforce_pp' normalises by the batch std by definition "
            f"(Hu et al. 2025); set std_scale='batch', got {std_scale!r}"
        )
    if estimator in ("grpo", "rloo") and k < 2:
        raise ValueError(f"group_advantages: estimator={estimator!r} needs group_size >= 2, got {k}")

    grouped = rewards.view(n // k, k)  # (G, K)
    group_mean = grouped.mean(dim=1, keepdim=True)  # (G, 1)

    if estimator == "reinforce_pp":
        centred = rewards if k == 1 else (grouped - group_mean).flatten()  # (N,)
        centred = centred - centred.mean()  # (N,)
        std = centred.std() if n > 1 else torch.zeros((), dtype=rewards.dtype, device=rewards.device)
        return centred / (std + eps)  # (N,)

    if estimator == "grpo":
        adv = grouped - group_mean  # (G, K)
    else:  # rloo
        loo_mean = (grouped.sum(dim=1, keepdim=True) - grouped) / (k - 1)  # (G, K)
        adv = grouped - loo_mean  # (G, K)

    if std_scale == "group":
        adv = adv / (grouped.std(dim=1, keepdim=True) + eps)  # (G, K)
    elif std_scale == "batch":
        adv = adv / (rewards.std() + eps)  # (G, K)
    return adv.flatten()  # (N,)


@torch.no_grad()
def zero_variance_groups(rewards: torch.Tensor, group_size: int) -> torch.Tensor:
    """(N,) rewards in contiguous groups of K -> (N/K,) bool, True where all K rewards are equal.

    Such groups carry no learning signal under a group baseline (their advantages are 0);
    DAPO's dynamic sampling (Yu et al. 2025, §3.2) filters them out and refills the batch.
    Equality is exact (verifier rewards are usually exact 0/1 values).
    """
    if rewards.dim() != 1 or group_size < 1 or rewards.numel() % group_size:
        raise ValueError(
            f"zero_variance_groups: {tuple(rewards.shape)} rewards do not split into groups of group_size={group_size}"
        )
    grouped = rewards.view(-1, group_size)  # (G, K)
    return grouped.max(dim=1).values == grouped.min(dim=1).values  # (G,)


# ----------------------------------------------------------------------------- KL coefficient
# ----------------------------------------------------------------------------- curriculum
@torch.no_grad()
def track_pass_rates(rates: torch.Tensor, seen: torch.Tensor, idx: torch.Tensor, group_pass: torch.Tensor,
                     decay: float) -> tuple[torch.Tensor, torch.Tensor]:
    """Each problem's recent pass rate: an exponential moving average over the groups sampled from it.

    `rates` (N,) and `seen` (N,) bool: the table over the whole problem pool; `idx` (G,): the problems of
    this step's groups; `group_pass` (G,): the fraction of each group's K completions that passed. A
    problem seen for the first time takes its group's pass rate; after that r <- decay r + (1 - decay)
    pass (decay in [0, 1): 0 keeps only the latest group). A problem drawn twice in one step is updated
    in order. Returns new tensors (the inputs are not modified).
    """
    if not 0.0 <= decay < 1.0:
        raise ValueError(f"track_pass_rates: decay must be in [0, 1), got {decay}")
    rates, seen = rates.clone(), seen.clone()
    for i, p in zip(idx.tolist(), group_pass.tolist()):
        rates[i] = decay * rates[i] + (1.0 - decay) * p if seen[i] else p
        seen[i] = True
    return rates, seen


@torch.no_grad()
def curriculum_weights(rates: torch.Tensor, seen: torch.Tensor, group_size: int, *, floor: float) -> torch.Tensor:
    """Sampling weights (N,) of the problems for the next groups, from their tracked pass rates.

    A group of K binary rewards carries signal unless all K agree, which happens with probability
    p^K + (1 - p)^K; the weight is the complement, 1 - p^K - (1 - p)^K (so problems that are always solved
    or always failed are down-weighted), never below `floor` (0 < floor <= 1: every problem stays
    reachable and a pass-rate estimate from few groups can be revised). Unseen problems weigh 1, the
    most any problem can (as much as one of pass rate 1/2 at large K). Curriculum sampling in the spirit
    of DAPO's dynamic sampling and of balanced online difficulty filtering (Bae et al. 2025, "Online
    Difficulty Filtering for Reasoning Oriented Reinforcement Learning"), which keep prompts of
    intermediate pass rate; here as weights, not a filter.
    """
    if not 0.0 < floor <= 1.0:
        raise ValueError(f"curriculum_weights: floor must be in (0, 1], got {floor}")
    if group_size < 1:
        raise ValueError(f"curriculum_weights: group_size must be >= 1, got {group_size}")
    informative = 1.0 - rates.pow(group_size) - (1.0 - rates).pow(group_size)  # (N,)
    return torch.where(seen, informative.clamp(min=floor), torch.ones_like(rates))


class FixedKLController:
    """A constant KL coefficient (Ziegler et al. 2019, the non-adaptive setting)."""

    def __init__(self, kl_coef: float):
        self.value = float(kl_coef)

    def update(self, current_kl: float, n_steps: int) -> None:
        """No-op; same signature as `AdaptiveKLController.update`."""

    def state_dict(self) -> dict[str, float]:
        return {"value": self.value}

    def load_state_dict(self, state: dict[str, float]) -> None:
        self.value = float(state["value"])


class AdaptiveKLController:
    """Log-space proportional controller of the KL coefficient (Ziegler et al. 2019, §2.2).

        e     = clip(current_kl / target - 1, -0.2, 0.2)
        beta <- beta * (1 + e * n_steps / horizon)

    The paper writes beta <- beta (1 + K_beta e); its lm-human-preferences code (and TRL) use
    K_beta = n_steps / horizon, which is what this implements. The coefficient grows when the
    measured KL is above `target` and shrinks when below, by at most 20% per `horizon` steps.
    `n_steps` and `horizon` count the same unit: in that code `n_steps` is the number of
    rollouts (samples) since the last update and `horizon` = 10000 of them. `current_kl` is the
    mean per-SEQUENCE KL (k1 summed over completion tokens, averaged over rows), the quantity
    `target` is set in (TRL's default target is 6 nats). `state_dict` / `load_state_dict` let
    a checkpoint resume it.
    """

    def __init__(self, init_kl_coef: float, target: float, horizon: int):
        if target <= 0 or horizon <= 0:
            raise ValueError(f"AdaptiveKLController: target and horizon must be > 0, got {target}, {horizon}")
        self.value = float(init_kl_coef)
        self.target = float(target)
        self.horizon = int(horizon)

    def update(self, current_kl: float, n_steps: int) -> None:
        error = min(max(float(current_kl) / self.target - 1.0, -0.2), 0.2)
        self.value *= 1.0 + error * n_steps / self.horizon

    def state_dict(self) -> dict[str, float]:
        return {"value": self.value}

    def load_state_dict(self, state: dict[str, float]) -> None:
        self.value = float(state["value"])
