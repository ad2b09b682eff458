"""PPO for RLHF (Ziegler et al. 2019; Stiennon et al. 2020; Ouyang et al. 2022): policy, value model, frozen
reference and reward model, rollouts from the shared engine.

CPU:        posttrain ppo --recipe tiny-summarize        (from nothing: SFT, pairs, reward model, PPO, eval;
                                                          see the recipe header for the times)
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain ppo --recipe tiny-summarize model.path=/path/to/hf-model
            (2 CPU processes: accelerate launch --config_file recipes/launch/cpu-2proc.yaml -m posttrain ppo
            --recipe tiny-summarize run.threads=1; tested against one process in tests/posttrain/test_distributed.py)
LoRA:       posttrain ppo --recipe tiny-summarize lora.enabled=true   (see "LoRA" below)

Reads top to bottom: build the models (policy and reference from the SFT model, value model, reward);
measure the reward statistics of SFT samples (reward normalisation); then loop { rollout batch from
the engine -> score -> log-probs of policy (old), reference and values -> per-token rewards with the
KL penalty -> GAE -> ppo_epochs x minibatches of clipped policy and value updates -> KL controller ->
log -> eval (gold, win-rate vs SFT, proxy RM, KL) -> checkpoint }; save final/ (the policy, a HF
directory); print the gold score and win-rate against the SFT model.

Implementation details it follows, numbered as in Huang et al. 2022/2024 ("The N Implementation
Details of RLHF with PPO", ICLR blog track 2023; "The N+ Implementation Details of RLHF with PPO:
A Case Study on TL;DR Summarization", 2024), each a config flag where it is a choice, each flag's effect
tested in tests/posttrain/test_ppo.py (the clipped losses and GAE themselves in test_losses.py and
test_advantages.py):
 1. Reward normalisation (`reward_norm`): "init" (default) measures the reward of `reward_norm_prompts`
    SFT samples before training and rescales every later score to that mean 0 / std 1, as
    lm-human-preferences normalises its reward model on samples of the initial policy (Ziegler et al.
    2019 §2.2; Huang 2022 "reward normalization"); "batch" whitens each rollout batch's scores; "none".
 2. Reward clipping (`reward_clip`): normalised scores clipped to [-c, c] (0: off).
 3. EOS trick (`missing_eos_penalty`): a completion that never ends (finish reason "length") gets its
    score lowered by this much (after normalisation, before clipping). Huang 2024 replace the score
    by -1; we subtract, as TRL's `missing_eos_penalty` does, so the RM's ranking of such samples stays.
 4. KL as a per-token reward (`kl_estimator`, `kl_coef`): reward_t = -beta * KL_t at every completion
    token plus the score at the last one (`advantages.rewards_with_kl`; InstructGPT eq. 2). KL_t is
    Schulman's k1 (log pi - log pi_ref, default: its per-sequence sum is the KL the objective has) or
    k3 (`losses.kl_penalty`), from the rollout-time log-probs.
 5. Adaptive KL controller (`kl_control`, `kl_target`, `kl_horizon`): Ziegler et al. 2019's
    proportional controller on the mean per-sequence k1 KL of each rollout batch; "fixed" keeps kl_coef.
 6. Reward whitening (`whiten_rewards`, off): TRL's whiten_rewards, per-token rewards whitened over the
    batch (the mean is kept) before GAE.
 7. GAE (`gamma`, `lam`): gamma = 1 (Huang 2022: no discount inside a completion), lam = 0.95.
 8. Advantage whitening (`whiten_advantages`): over the completion tokens of the whole rollout batch
    (`logprobs.masked_whiten`), once, after GAE (returns come from the raw advantages).
 9. Clipped surrogate (`clip_eps`), token-mean aggregation (`losses.ppo_policy_loss`).
10. Value clipping (`value_clip`): `losses.value_loss`'s clipped form around the rollout-time values
    (0: plain squared error).
11. Value model init (`value_init`): "reward" (default) starts the value model as a copy of the reward
    model, transformer and head (lm-human-preferences; Huang 2022 "value head initialised from the
    reward model"); "policy" starts it as the SFT transformer with a new, seeded one-output head.
12. Separate policy and value networks, each with its own AdamW. Not a choice here: with two
    optimizers a value-loss coefficient would only rescale the value gradient, which Adam undoes,
    so there is `value_lr` instead of vf_coef.
13. Dropout disabled (`disable_dropout`): dropout modules and attention dropout set to 0 in policy,
    value and reference, so the log-probs of the update equal the rollout's at the first minibatch.
14. Temperature (`scale_logits_by_temperature`): rollouts sample at `temperature`, and every log-prob
    of the update (old, new, reference) divides the logits by the same temperature (Huang 2022:
    "scale the logits by the sampling temperature"), so the ratio and the KL are those of the
    distribution actually sampled. Off: log-probs of the raw (temperature-1) policy.
15. No top-k / top-p at rollout time (not a flag): sampling from the full distribution keeps the
    engine's sampling log-probs equal to the policy's, which the ratio needs.
16. Old log-probs recomputed after the rollout (not a flag) with `posttrain.logprobs` (the same
    forward as the update), not taken from the engine: the first minibatch's ratio is exactly 1.
    The engine's numbers are compared and logged (rollout/logprob_gap).
17. Entropy bonus (`entropy_coef`, 0 by default as in the RLHF implementations Huang et al. study):
    loss -= coef * mean token entropy of the policy on the rollout tokens.
18. Several epochs (`ppo_epochs`) of minibatches (`minibatch_size`), reshuffled every epoch
    (seeded by seed, iteration and epoch).
19. Learning-rate annealing (`schedule`): linear to 0 over all optimizer steps by default.

Departures: one completion per prompt per rollout (no best-of / groups); no reward-model training
during PPO; rewards come through `posttrain.scoring` (`RewardModelScorer`, or `GoldScorer` with
`reward=gold` for ablations) from the completion TEXT, re-tokenised as the reward model was trained;
the value model scores the sampled token ids. Non-finite loss or gradient stops the run naming the
step (weights are also checked before each checkpoint); the last good checkpoint stays intact.

Models in memory during training: 4 (policy, value, reference, reward model); the reference and the
reward model are frozen and in eval mode. With LoRA: 3 (see below).

Several processes (`accelerate launch`, data parallel). `rollout_batch_size` and `minibatch_size` are
GLOBAL (over all processes); minibatch_size must be a multiple of the number of processes W. What each
process does on its own, and what is global:
- Per process: process r takes positions r, r + W, ... of the iteration's global prompt batch
  (`loop.batch_indices`), generates their completions (prompt keys = dataset indices, so every
  sample is the one a single process would draw, up to float differences between batch shapes; see
  posttrain.rollout), scores them, and runs the no-grad forwards of the old policy, the reference and
  the value model on those rows. reward_norm=init measures its SFT samples sharded the same way.
- Gathered (every process then holds the whole rollout batch, in global order): rollout records, raw
  scores and those per-token tensors (small next to the forwards). Everything computed from them is
  therefore global and identical on every process: reward normalisation (init statistics, or
  "batch"), the KL penalty, reward whitening, GAE, advantage whitening over the completion tokens of
  the whole batch, the KL controller's mean KL (so the coefficient stays in step), the rollout
  metrics.
- Updates: the epoch permutation of the global batch is the same on every process (seeded by seed,
  iteration, epoch); of each global minibatch, process r takes rows r, r + W, ... Every forward that
  needs gradients goes through the accelerate-prepared (DDP) module -- the value model's per-token
  forward too (`TokenValueModel`). Each process scales its token-mean loss by its tokens / the
  minibatch's tokens x W, so DDP's gradient average is the gradient of the token mean over the whole
  minibatch, as in one process (`global_token_mean`). Logged policy/value metrics are global too
  (token means weighted the same way, ratio_max a max, explained variance from summed moments); a
  non-finite loss on any process stops every process at the same step.
- Main process only: evaluation, the SFT baseline completions, the proxy scorer, metrics.jsonl,
  final/ and eval.json; checkpoints are written once (`loop.Checkpointer`). time/* metrics are the
  main process's.

LoRA (`lora.enabled=true`; peft via `posttrain.models.maybe_lora`): the policy gets adapters; the
reference is `reference_view(policy)`, the same weights with the adapters switched off (no second copy
of the policy is loaded). The value model gets its own adapters too (task type SEQ_CLS: peft trains
its score head fully): `lora.enabled` means no full-weight training in this stage, and a fully trained
value model would need gradients and two Adam moments of a whole model (3 weight-sized copies), the
memory LoRA is there to save. The value model remains a separate set of base weights (its transformer
is the reward model's, or the SFT model's under value_init=policy, where a second adapter on the policy's
own base weights would save one more copy; not done). LoRA dropout counts as
dropout for detail 13. final/ is saved merged (a plain HF model); checkpoints hold the full state.
Models in memory: 3 sets of base weights (policy = reference, value, reward model) and adapters.
Measured (one thread): the tiny-summarize recipe with lora.enabled=true reaches a gold win-rate of 0.672
against SFT at the recipe's lr (0.685 with lr=1e-3 value_lr=1e-3, as full PPO), with 23 MiB of live
weights + Adam state instead of 41 (peak RSS 720 vs 700 MiB: on a 1.4M-parameter model the runtime
dominates and peft adds ~20 MiB); with the `base` preset (26M parameters, minibatch 4) 429 vs 899 MiB
of live tensors and peak RSS 1235 vs 1670 MiB.
"""
from __future__ import annotations

import math
import time
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Literal

import numpy as np
import torch

from posttrain import loop
from posttrain.lean import train as lean
from posttrain.lean.support import lean_support
from posttrain.advantages import AdaptiveKLController, FixedKLController, gae, rewards_with_kl
from posttrain.config import ConfigError, Resolved, save_resolved
from posttrain.logprobs import batched_logprobs, masked_mean, masked_sum, masked_whiten, sequence_logprobs
from posttrain.models import load_reward_init, position_ids_from_mask, resolve_dtype, unwrap_model
from posttrain.losses import kl_penalty, ppo_policy_loss, value_loss


@dataclass
class PPOConfig:
    reward: Literal["rm", "gold"] = "rm"
    """rm: the reward model (reward_model, else the rm stage output, built if missing); gold: the task's gold scorer."""
    reward_model: str = ""
    """Reward-model directory; empty: runs/<recipe>/rm/final (with reward=gold only the proxy curve, if it exists)."""
    max_steps: int = 40
    """PPO iterations: each is one rollout batch followed by ppo_epochs passes of minibatch updates."""
    rollout_batch_size: int = 64
    """Training prompts per iteration (one sampled completion each; global, across processes)."""
    minibatch_size: int = 16
    """Rollouts per optimizer step (each model steps once per minibatch; global, a multiple of the processes)."""
    ppo_epochs: int = 2
    """Passes over each rollout batch, minibatches reshuffled every pass."""
    lr: float = 1e-4
    """Policy learning rate (AdamW)."""
    value_lr: float = 1e-4
    """Value-model learning rate (its own AdamW; replaces a value-loss coefficient)."""
    weight_decay: float = 0.0
    """AdamW weight decay of both models (not applied to norms and embeddings)."""
    schedule: Literal["linear", "cosine", "constant"] = "linear"
    """Learning-rate schedule over all optimizer steps (max_steps * ppo_epochs * minibatches)."""
    max_grad_norm: float = 1.0
    """Gradient clipping norm of each model (0 disables)."""
    temperature: float = 1.0
    """Rollout sampling temperature (no top-k / top-p: the full distribution is sampled)."""
    scale_logits_by_temperature: bool = True
    """Divide logits by temperature for every log-prob of the update (old, new, reference); off: temperature 1."""
    max_new_tokens: int = 64
    """Rollout and evaluation generation budget."""
    gamma: float = 1.0
    """GAE discount."""
    lam: float = 0.95
    """GAE lambda."""
    clip_eps: float = 0.2
    """Policy ratio clipping range."""
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
    log_every: int = 1
    """Iterations between metric lines."""
    eval_every: int = 10
    """Iterations between evaluations (gold, win-rate vs SFT, proxy RM, KL); 0: only at the end."""
    eval_rows: int = 100
    """Held-out prompts for the periodic evaluation."""
    final_eval_rows: int = 200
    """Held-out prompts for the final comparison with the SFT model (0 skips it)."""
    save_every: int = 10
    """Iterations between checkpoints (0: only at the end)."""
    keep_checkpoints: int = 2
    """Checkpoints kept on disk (oldest deleted first)."""
    seed: int = 0
    """Seed of prompt order, rollout sampling, minibatch order and the value head init."""
    resume: bool = False
    """Continue from the newest checkpoint in the run directory."""


def check_config(cfg: PPOConfig) -> None:
    """One-line ConfigErrors for settings that cannot run, before anything loads."""
    def bad(msg: str) -> ConfigError:
        return ConfigError(f"ppo.{msg}")

    for name in ("max_steps", "rollout_batch_size", "minibatch_size", "ppo_epochs", "max_new_tokens"):
        if getattr(cfg, name) < 1:
            raise bad(f"{name} must be >= 1, got {getattr(cfg, name)}")
    if cfg.rollout_batch_size % cfg.minibatch_size:
        raise bad(f"minibatch_size={cfg.minibatch_size} must divide rollout_batch_size={cfg.rollout_batch_size}")
    if cfg.temperature <= 0 or not math.isfinite(cfg.temperature):
        raise bad(f"temperature must be > 0 (PPO samples; greedy rollouts have no ratio), got {cfg.temperature}")
    if cfg.clip_eps <= 0:
        raise bad(f"clip_eps must be > 0, got {cfg.clip_eps}")
    for name in ("value_clip", "reward_clip", "missing_eos_penalty", "entropy_coef", "kl_coef", "lr", "value_lr"):
        if getattr(cfg, name) < 0:
            raise bad(f"{name} must be >= 0, got {getattr(cfg, name)}")
    if not (0.0 <= cfg.gamma <= 1.0 and 0.0 <= cfg.lam <= 1.0):
        raise bad(f"gamma and lam must be in [0, 1], got gamma={cfg.gamma}, lam={cfg.lam}")
    if cfg.kl_control == "adaptive" and (cfg.kl_target <= 0 or cfg.kl_horizon < 1):
        raise bad(f"kl_target must be > 0 and kl_horizon >= 1 with kl_control=adaptive, got {cfg.kl_target}, "
                  f"{cfg.kl_horizon}")
    if cfg.reward_norm == "init" and cfg.reward_norm_prompts < 2:
        raise bad(f"reward_norm_prompts must be >= 2 with reward_norm=init, got {cfg.reward_norm_prompts}")


# ----------------------------------------------------------------------------- models
def disable_dropout(model) -> int:
    """Detail 13: every nn.Dropout p, attention-dropout attribute and config *dropout* field set to 0.
    Returns how many were non-zero."""
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
                                                                   dtype=resolve_dtype(dtype))
        model.config.pad_token_id = pad_id
        return model.to(device)
    return load_reward_init(sft_dir, pad_id, seed, device, dtype)


def token_values(value_model, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
    """Per-token values aligned with input_ids (the `posttrain.logprobs` convention): (B, T).

    values[:, t] = V(input_ids[:, :t]) = the head on the hidden state of token t-1, i.e. the value of
    the state in which token t is chosen; column 0 is 0. Positions count real tokens (left padding).
    A plain fp32 Llama-family value model runs `posttrain.lean.train.lean_hidden` (called inside DDP's forward
    when wrapped, see `TokenValueModel`), else its decoder's own forward.
    """
    inner = unwrap_model(value_model)
    if hasattr(inner, "get_base_model"):  # peft (LoRA): the adapters live inside the base model's layers
        inner = inner.get_base_model()
    base = getattr(inner, inner.base_model_prefix)
    dev = next(inner.parameters()).device
    input_ids, attention_mask = input_ids.to(dev), attention_mask.to(dev)
    if lean_support(inner, input_ids.shape[1], mode="train", head="score")[0]:  # same numbers, fewer ops
        hidden = lean.lean_hidden(inner, input_ids, attention_mask)  # (B, T, H)
    else:
        hidden = base(input_ids=input_ids, attention_mask=attention_mask,
                      position_ids=position_ids_from_mask(attention_mask)).last_hidden_state  # (B, T, H)
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
    from posttrain.scoring import GoldScorer, RewardModelScorer

    if reward == "gold":
        return GoldScorer(task_name)
    return RewardModelScorer(rm_dir, device=device)


# ----------------------------------------------------------------------------- pure steps of an iteration
def logprob_temperature(cfg: PPOConfig) -> float:
    """Detail 14: the temperature every log-prob of the update is computed at."""
    return cfg.temperature if cfg.scale_logits_by_temperature else 1.0


@torch.no_grad()
def shape_scores(raw: torch.Tensor, ended: torch.Tensor, cfg: PPOConfig,
                 norm: dict[str, float] | None) -> torch.Tensor:
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
                           values: torch.Tensor, completion_mask: torch.Tensor, kl_coef: float
                           ) -> dict[str, torch.Tensor]:
    """Details 4, 6, 7, 8: per-token KL penalty, rewards, GAE, whitening. All (B, T), 0 outside the mask."""
    cm = completion_mask.bool()
    zero = torch.zeros_like(logps)
    kl = torch.where(cm, kl_penalty(logps, ref_logps, cfg.kl_estimator), zero)  # (B, T)
    rewards = rewards_with_kl(scores, kl, cm, kl_coef=kl_coef)  # (B, T)
    if cfg.whiten_rewards:
        rewards = torch.where(cm, masked_whiten(rewards, cm, shift_mean=False), zero)
    adv, returns = gae(rewards, values, cm, gamma=cfg.gamma, lam=cfg.lam)  # (B, T), (B, T)
    if cfg.whiten_advantages:
        adv = torch.where(cm, masked_whiten(adv, cm), zero)
    return {"kl": kl, "rewards": rewards, "advantages": adv, "returns": returns}


def policy_loss(cfg: PPOConfig, logps: torch.Tensor, entropy: torch.Tensor, old_logps: torch.Tensor,
                advantages: torch.Tensor, completion_mask: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """Details 9 and 17: clipped surrogate minus the entropy bonus."""
    loss, m = ppo_policy_loss(logps, old_logps, advantages, completion_mask, clip_eps=cfg.clip_eps)
    ent = masked_mean(entropy, completion_mask.bool())
    if cfg.entropy_coef:
        loss = loss - cfg.entropy_coef * ent
    m["entropy"] = float(ent.detach())
    return loss, m


def critic_loss(cfg: PPOConfig, values: torch.Tensor, old_values: torch.Tensor, returns: torch.Tensor,
                completion_mask: torch.Tensor) -> tuple[torch.Tensor, dict[str, float]]:
    """Detail 10: `losses.value_loss`, clipped around the rollout-time values unless value_clip = 0."""
    return value_loss(values, old_values, returns, completion_mask, clip_range=cfg.value_clip or None)


# ----------------------------------------------------------------------------- several processes
# Process r of W holds the rows at global positions r, r + W, ... (see the module docstring).
TOKEN_MEAN_METRICS = frozenset({"clip_frac", "clip_frac_low", "clip_frac_high", "approx_kl", "ratio_mean", "entropy",
                                "value_clip_frac", "value_mean"})


def gather_rows(accelerator, items: list, positions: list[int]) -> list:
    """Every process's `items` (picklable; item i sits at global position positions[i]), in global order."""
    if accelerator.num_processes == 1:
        return list(items)
    from accelerate.utils import gather_object

    pairs = gather_object(list(zip(positions, items)))
    return [x for _, x in sorted(pairs, key=lambda t: t[0])]


def gather_row_tensor(accelerator, local: torch.Tensor, positions: list[int]) -> torch.Tensor:
    """Every process's rows (n, ...) (the same n and trailing shape everywhere) -> (W * n, ...) in global order."""
    if accelerator.num_processes == 1:
        return local
    rows = accelerator.gather(local.contiguous())  # (W * n, ...) process-major
    where = accelerator.gather(torch.as_tensor(positions, dtype=torch.long, device=local.device))  # (W * n,)
    return torch.empty_like(rows).index_copy_(0, where, rows)


def global_token_mean(accelerator, loss: torch.Tensor, metrics: dict[str, float], n_local: float,
                      n_global: float) -> tuple[torch.Tensor, dict[str, float]]:
    """A process's token-mean loss and metrics over its rows of a minibatch, rescaled by
    n_local / n_global * W: DDP's gradient average and `loop.optimizer_step`'s metric average over
    processes then give the token mean over the whole minibatch, as one process computes it.
    ratio_max becomes the max over processes. A non-finite loss on any process makes every process's
    loss NaN, so all of them stop at the same step (none waits forever in the next all-reduce).
    The identity in one process."""
    W = accelerator.num_processes
    if W == 1:
        return loss, metrics
    f = n_local * W / n_global
    out = {k: (v * f if k in TOKEN_MEAN_METRICS else v) for k, v in metrics.items()}
    mine = torch.tensor([[0.0 if bool(torch.isfinite(loss)) else 1.0, metrics.get("ratio_max", 0.0)]],
                        dtype=torch.float64, device=accelerator.device)
    every = accelerator.gather(mine)  # (W, 2)
    if "ratio_max" in metrics:
        out["ratio_max"] = float(every[:, 1].max())
    if float(every[:, 0].sum()) > 0:
        loss = loss * float("nan")
    return loss * f, out


def global_explained_variance(accelerator, values: torch.Tensor, returns: torch.Tensor,
                              completion_mask: torch.Tensor) -> float:
    """`losses.value_loss`'s explained variance, 1 - Var(R - V) / Var(R), over the completion tokens of
    every process's rows (from summed first and second moments)."""
    cm = completion_mask.bool()
    r = returns.detach()[cm].double()
    d = (returns.detach() - values.detach())[cm].double()
    t = torch.stack([torch.tensor(float(r.numel()), dtype=torch.float64), r.sum(), (r * r).sum(), d.sum(),
                     (d * d).sum()]).to(accelerator.device)
    n, sr, srr, sd, sdd = accelerator.reduce(t, reduction="sum").tolist()
    var_r, var_d = srr - sr * sr / max(n, 1.0), sdd - sd * sd / max(n, 1.0)  # both times (n - 1)
    return 1.0 - var_d / var_r if var_r > 0 else float("nan")


def _trim(mb: dict[str, torch.Tensor]) -> dict[str, torch.Tensor]:
    """Drop columns that are padding in every row of a minibatch (all tensors (b, T) sliced alike)."""
    live = mb["attention_mask"].any(0).nonzero()
    lo, hi = int(live[0]), int(live[-1]) + 1
    return {k: v[:, lo:hi] for k, v in mb.items()}


def _weights_finite(*models) -> bool:
    return all(bool(torch.isfinite(p).all()) for m in models for p in m.parameters())


# ----------------------------------------------------------------------------- train
def train(res: Resolved, ensure) -> Path:
    """PPO-for-RLHF from the SFT model; returns the final policy directory."""
    from posttrain import evaluation, tasks
    from posttrain.models import is_model_dir, load_model, load_tokenizer, maybe_lora, reference_view, save_model
    from posttrain.rollout import SamplingParams, collate_rollouts, generate
    from posttrain.scoring import RewardModelScorer

    cfg: PPOConfig = res.stage_cfg
    check_config(cfg)
    run_dir = res.stage_dir()
    task = tasks.get_task(res.task.name)
    has_gold = tasks.has_gold(task)
    if cfg.reward == "gold" and not has_gold:
        raise ConfigError(f"ppo.reward=gold needs a task with a gold metric; {res.task.name!r} has none")
    if cfg.reward_model and not is_model_dir(cfg.reward_model):
        raise ConfigError(f"ppo.reward_model {cfg.reward_model!r} is not a reward-model directory")
    train_rows = tasks.load_split(res.task, "train")
    if len(train_rows) < cfg.rollout_batch_size:
        raise ConfigError(f"ppo.rollout_batch_size={cfg.rollout_batch_size} is more than the {len(train_rows)} "
                          "training prompts (task.n_train)")
    if cfg.reward == "gold" and not all(r.get("meta") for r in train_rows):
        raise ConfigError("ppo.reward=gold needs the task's meta in every training row; task.train_file has rows "
                          "without it (use reward=rm)")
    eval_rows = [r for r in tasks.load_split(res.task, "eval") if r.get("meta")] if has_gold else []

    sft_dir = ensure("sft")
    rm_dir: Path | None = Path(cfg.reward_model) if cfg.reward_model else None
    if rm_dir is None and (cfg.reward == "rm" or cfg.value_init == "reward"):
        rm_dir = ensure("rm")
    elif rm_dir is None and is_model_dir(res.stage_dir("rm") / "final"):
        rm_dir = res.stage_dir("rm") / "final"  # reward=gold: the RM is only the proxy curve
    tokenizer = load_tokenizer(sft_dir, res.model)
    pad_id = tokenizer.pad_token_id

    accelerator = loop.setup(cfg.seed, res.run.threads)
    rank, world = accelerator.process_index, accelerator.num_processes
    if cfg.minibatch_size % world:
        raise ConfigError(f"ppo.minibatch_size={cfg.minibatch_size} must be a multiple of the number of processes "
                          f"({world}): each process takes an equal share of every minibatch")
    main = accelerator.is_main_process
    say = print if main else (lambda *a, **k: None)
    if main:
        loop.prepare_run_dir(run_dir, cfg.resume, say)
        save_resolved(res, run_dir / "config.yaml")
    accelerator.wait_for_everyone()
    dev = accelerator.device

    # Models: policy and reference are the SFT model (LoRA: one model, the reference is it with the
    # adapters off); the value model per value_init (LoRA: its own adapters); the reward.
    policy = maybe_lora(res, load_model(sft_dir, res.model.dtype, device=dev), lambda m: say(m + " (policy)"))
    reference = reference_view(policy) if res.use_lora else \
        load_model(sft_dir, res.model.dtype, device=dev).eval().requires_grad_(False)
    value_model = maybe_lora(res, build_value_model(cfg.value_init, sft_dir, rm_dir, pad_id, cfg.seed, dev,
                                                    res.model.dtype),
                             lambda m: say(m + " (value model)"), "SEQ_CLS")
    if cfg.disable_dropout:
        for m in (policy, reference, value_model):
            disable_dropout(m)
    scorer = reward_scorer(cfg.reward, res.task.name, rm_dir, dev)
    proxy = None
    if rm_dir is not None and main:
        proxy = scorer if isinstance(scorer, RewardModelScorer) else RewardModelScorer(rm_dir, device=dev)
    temp_lp = logprob_temperature(cfg)
    gen_rows = eval_rows[: max(cfg.eval_rows, cfg.final_eval_rows)]
    baseline = evaluation.complete(policy, tokenizer, [r["prompt"] for r in gen_rows],
                                   max_new_tokens=cfg.max_new_tokens) if (gen_rows and main) else []

    def score_rollouts(rows: list[dict], rollouts) -> list[float]:
        if not rows:  # a process with no share (fewer reward_norm prompts than processes)
            return []
        res_ = scorer.score([r["prompt"] for r in rows], [ro.text for ro in rollouts], [r.get("meta") for r in rows])
        return [float(x) for x in res_.rewards]

    def sample(rows: list[dict], keys: list[int], seed: int) -> list:
        if not rows:
            return []
        return generate(accelerator.unwrap_model(policy), tokenizer, [r["prompt"] for r in rows],
                        SamplingParams(temperature=cfg.temperature, max_new_tokens=cfg.max_new_tokens, seed=seed),
                        prompt_keys=keys)

    n_mb = cfg.rollout_batch_size // cfg.minibatch_size
    total_updates = cfg.max_steps * cfg.ppo_epochs * n_mb
    opt_p = loop.build_optimizer(policy, cfg.lr, cfg.weight_decay)
    opt_v = loop.build_optimizer(value_model, cfg.value_lr, cfg.weight_decay)
    sched_p = loop.build_scheduler(opt_p, 0, total_updates, cfg.schedule, 0.0)
    sched_v = loop.build_scheduler(opt_v, 0, total_updates, cfg.schedule, 0.0)
    # The value model's update forward must run through DDP: wrap it so that its forward IS the per-token value.
    policy, value_model, opt_p, opt_v = accelerator.prepare(policy, TokenValueModel(value_model), opt_p, opt_v)
    kl_ctl = (AdaptiveKLController(cfg.kl_coef, cfg.kl_target, cfg.kl_horizon) if cfg.kl_control == "adaptive"
              else FixedKLController(cfg.kl_coef))
    ckpt = loop.Checkpointer(run_dir, cfg.keep_checkpoints, accelerator)
    metrics = loop.MetricsLog(run_dir / "metrics.jsonl", cfg.max_steps, main, res.run.quiet, prefix="[ppo] ")

    start = 0
    norm: dict[str, float] | None = None
    if cfg.resume:
        last = ckpt.latest()
        if last is None:
            say(f"[ppo] resume=true but no checkpoint in {ckpt.dir}; starting from iteration 0")
        else:
            state = ckpt.load(last, policy, opt_p, sched_p)
            extra = state["extra"]
            accelerator.unwrap_model(value_model).model.load_state_dict(extra["value_model"])
            opt_v.load_state_dict(extra["value_optimizer"])
            sched_v.load_state_dict(extra["value_scheduler"])
            kl_ctl.load_state_dict(extra["kl_controller"])
            norm = extra["reward_norm"]
            start = state["step"]
            metrics.truncate_after(start)
            say(f"[ppo] resumed from {last} at iteration {start}")

    if cfg.reward_norm == "init" and norm is None:
        # Detail 1: reward statistics of SFT samples, measured once (saved in every checkpoint).
        t0 = time.time()
        k = min(cfg.reward_norm_prompts, len(train_rows))
        first = len(train_rows) - k  # the end of the split: iterations draw from all of it anyway
        mine = list(range(rank, k, world))  # this process's share; prompt keys are dataset indices
        rows = [train_rows[first + p] for p in mine]
        local = score_rollouts(rows, sample(rows, [first + p for p in mine], cfg.seed + 1_000_003))
        raw = torch.tensor(gather_rows(accelerator, local, mine), dtype=torch.float32)  # (k,) all processes'
        norm = {"mean": float(raw.mean()), "std": float(raw.std().clamp(min=1e-6)), "n": k}
        say(f"[ppo] reward normalisation from {k} SFT samples: mean {norm['mean']:.4f}, std {norm['std']:.4f} "
            f"({time.time() - t0:.1f}s)")

    def evaluate(it: int) -> None:
        if not (gen_rows and main):
            return
        pol = accelerator.unwrap_model(policy).eval()  # (with LoRA, the reference runs in the policy's mode)
        rows = gen_rows[: cfg.eval_rows]
        r = evaluation.compare_policy(res.task.name, pol, tokenizer, rows, baseline[: len(rows)],
                                      max_new_tokens=cfg.max_new_tokens, proxy=proxy)
        m = {"gold/reward": r["gold_reward"], "gold/quality": r["mean_quality"], "gold/in_band": r["frac_in_band"],
             "gold/length": r["mean_length"], "gold/win_rate": r["win_rate"]}
        if "proxy_reward" in r:
            m["proxy/reward"] = r["proxy_reward"]
        m["kl"] = evaluation.kl_to_reference(pol, reference, tokenizer, [x["prompt"] for x in rows],
                                             max_new_tokens=cfg.max_new_tokens, seed=cfg.seed + 7)
        metrics.log(it, m, console=False)
        say(f"[ppo] iteration {it} eval: " + ", ".join(f"{k} {v:.3f}" for k, v in m.items()
                                                      if k in ("gold/reward", "gold/win_rate", "proxy/reward", "kl")))

    if start == 0 and cfg.eval_every:
        evaluate(0)
    say(f"[ppo] {cfg.max_steps} iterations x {cfg.rollout_batch_size} rollouts, {cfg.ppo_epochs} epochs x {n_mb} "
        f"minibatches of {cfg.minibatch_size}; reward {cfg.reward}" + (f" ({rm_dir})" if cfg.reward == "rm" else "")
        + f", value from {cfg.value_init}, KL {cfg.kl_estimator} coef {kl_ctl.value:g} ({cfg.kl_control}), "
        f"temperature {cfg.temperature}; {world} process(es) on {dev}")

    for it in range(start, cfg.max_steps):
        done = it + 1
        t_it = time.time()
        # ---- rollout (the shared engine; prompts and samples seeded by (seed, iteration)). The batch is
        # global; this process generates, scores and runs the no-grad forwards of its share of it.
        idx = loop.batch_indices(len(train_rows), cfg.rollout_batch_size, cfg.seed, it)
        mine = list(range(rank, cfg.rollout_batch_size, world))  # positions in the global batch
        rows = [train_rows[idx[p]] for p in mine]
        local_ro = sample(rows, [idx[p] for p in mine], cfg.seed * 100_003 + it)
        t_gen = time.time() - t_it
        local_raw = score_rollouts(rows, local_ro)
        rollouts = gather_rows(accelerator, local_ro, mine)  # the whole batch, in global order
        raw = torch.tensor(gather_rows(accelerator, local_raw, mine), dtype=torch.float32)  # (B,)
        ended = torch.tensor([ro.finish_reason != "length" for ro in rollouts])  # (B,)
        scores = shape_scores(raw, ended, cfg, norm)  # (B,)
        batch = collate_rollouts(rollouts, pad_id).to(dev)
        cm = batch.completion_mask.bool()  # (B, T)

        # ---- log-probs (old policy, reference) and values at rollout time: no grad, this process's rows
        pol = accelerator.unwrap_model(policy).eval()
        sel = torch.as_tensor(mine, device=dev)
        own = {"input_ids": batch.input_ids[sel], "attention_mask": batch.attention_mask[sel],
               "completion_mask": batch.completion_mask[sel]}
        old_logps = gather_row_tensor(accelerator, batched_logprobs(pol, own, cfg.minibatch_size,
                                                                    temperature=temp_lp)[0], mine)  # (B, T)
        ref_logps = gather_row_tensor(accelerator, batched_logprobs(reference, own, cfg.minibatch_size,
                                                                    temperature=temp_lp)[0], mine)  # (B, T)
        engine_lp = batch.logprobs if cfg.scale_logits_by_temperature else batch.policy_logprobs  # (B, T)
        lp_gap = float((old_logps - engine_lp).abs().masked_fill(~cm, 0).max())
        with torch.no_grad():
            vm = accelerator.unwrap_model(value_model).eval()
            local_v = torch.cat([vm(own["input_ids"][s], own["attention_mask"][s])
                                 for s in loop.chunks(list(range(len(mine))), cfg.minibatch_size)])  # (B/W, T)
            old_values = gather_row_tensor(accelerator, local_v, mine)  # (B, T)
            old_values = torch.where(cm, old_values, torch.zeros_like(old_values))
        # From here on every process holds the same global tensors: the statistics below are global.
        seq_kl = masked_sum(old_logps - ref_logps, cm, -1)  # (B,) k1 per sequence, the controller's quantity
        adv = advantages_and_returns(cfg, scores.to(dev), old_logps, ref_logps, old_values, cm, kl_ctl.value)

        # ---- ppo_epochs x minibatches of policy and value updates (of each minibatch, process r takes
        # rows r, r + W, ...; losses scaled to the minibatch's global token mean, see global_token_mean)
        data = {"input_ids": batch.input_ids, "attention_mask": batch.attention_mask, "completion_mask": cm,
                "old_logps": old_logps, "old_values": old_values, "advantages": adv["advantages"],
                "returns": adv["returns"]}
        sums: dict[str, float] = {}
        n_updates = 0
        try:
            for epoch in range(cfg.ppo_epochs):
                perm = np.random.default_rng([cfg.seed, it, epoch]).permutation(cfg.rollout_batch_size)
                for j in range(n_mb):
                    whole = torch.as_tensor(perm[j * cfg.minibatch_size:(j + 1) * cfg.minibatch_size], device=dev)
                    n_global = float(cm[whole].sum())  # completion tokens of the global minibatch
                    mb = _trim({k: v[whole[rank::world]] for k, v in data.items()})
                    n_local = float(mb["completion_mask"].sum())

                    def p_loss(mb):
                        logps, ent = sequence_logprobs(policy, mb["input_ids"], mb["attention_mask"],
                                                       mb["completion_mask"], temperature=temp_lp,
                                                       return_entropy=True)  # (b, T), (b, T)
                        loss, m = policy_loss(cfg, logps, ent, mb["old_logps"], mb["advantages"],
                                              mb["completion_mask"])
                        return global_token_mean(accelerator, loss, m, n_local, n_global)

                    def v_loss(mb):
                        v = value_model(mb["input_ids"], mb["attention_mask"])  # (b, T), through DDP
                        loss, m = critic_loss(cfg, v, mb["old_values"], mb["returns"], mb["completion_mask"])
                        if world > 1:
                            m["explained_variance"] = global_explained_variance(accelerator, v, mb["returns"],
                                                                                mb["completion_mask"])
                        return global_token_mean(accelerator, loss, m, n_local, n_global)

                    mp = loop.optimizer_step(accelerator, policy, opt_p, sched_p, [mb], p_loss, cfg.max_grad_norm,
                                             done)
                    mv = loop.optimizer_step(accelerator, value_model, opt_v, sched_v, [mb], v_loss,
                                             cfg.max_grad_norm, done)
                    for k, v in mp.items():
                        key = "policy/" + ("loss" if k == "loss" else k)
                        sums[key] = sums.get(key, 0.0) + v
                    for k, v in mv.items():
                        key = "value/" + k
                        sums[key] = sums.get(key, 0.0) + v
                    n_updates += 1
            saving = (cfg.save_every and done % cfg.save_every == 0) or done == cfg.max_steps
            if (saving or (cfg.eval_every and done % cfg.eval_every == 0)) and not _weights_finite(policy,
                                                                                                  value_model):
                raise loop.TrainingError(f"non-finite weights after iteration {done}; stopping without saving them")
        except loop.TrainingError as e:
            last = ckpt.latest()
            where = f"last good checkpoint: {last}" if last else "no checkpoint was written yet"
            raise loop.TrainingError(f"{e} (PPO iteration {done}; {where})") from None
        mean_kl = float(seq_kl.mean())
        kl_coef_used = kl_ctl.value
        kl_ctl.update(mean_kl, cfg.rollout_batch_size)  # detail 5 (a no-op when fixed)

        if done % cfg.log_every == 0 or done == cfg.max_steps:
            lengths = cm.sum(-1).float()
            row = {"rollout/score_raw": float(raw.mean()), "rollout/score": float(scores.mean()),
                   "rollout/reward_total": float(masked_sum(adv["rewards"], cm, -1).mean()),
                   "rollout/kl": mean_kl, "rollout/kl_penalty": float(masked_sum(adv["kl"], cm, -1).mean()),
                   "kl_coef": kl_coef_used, "rollout/length": float(lengths.mean()),
                   "rollout/no_eos": float((~ended).float().mean()), "rollout/logprob_gap": lp_gap,
                   "rollout/returns": float(masked_mean(adv["returns"], cm)),
                   **{k: v / n_updates for k, v in sums.items()},
                   "time/rollout_s": t_gen, "time/iteration_s": time.time() - t_it}
            metrics.log(done, row)
        if cfg.eval_every and (done % cfg.eval_every == 0 or done == cfg.max_steps):
            evaluate(done)
        if saving:
            extra = {"value_model": {k: v.detach().cpu() for k, v in
                                     accelerator.unwrap_model(value_model).model.state_dict().items()},
                     "value_optimizer": opt_v.state_dict(), "value_scheduler": sched_v.state_dict(),
                     "kl_controller": kl_ctl.state_dict(), "reward_norm": norm}
            ckpt.save(done, policy, opt_p, sched_p, {"step": done}, extra)

    final = run_dir / "final"
    if main:
        pol = accelerator.unwrap_model(policy).eval()
        save_model(pol, tokenizer, final)
        say(f"[ppo] saved {final}")
        report: dict[str, Any] = {"model": str(final), "reference": str(sft_dir), "reward": cfg.reward,
                                  "reward_model": str(rm_dir) if rm_dir else None, "reward_norm": norm}
        note = evaluation.plot_gold_vs_proxy(list(loop.iter_jsonl(run_dir / "metrics.jsonl")),
                                             run_dir / "overoptimization.png", title=f"{res.recipe} PPO")
        say(f"[ppo] over-optimisation plot: {note}")
        if cfg.final_eval_rows and gen_rows:
            rows = gen_rows[: cfg.final_eval_rows]
            base = baseline[: len(rows)]
            sft_m = evaluation.compare_policy(res.task.name, None, tokenizer, rows, base, proxy=proxy, completions=base)
            ppo_m = evaluation.compare_policy(res.task.name, pol, tokenizer, rows, base,
                                              max_new_tokens=cfg.max_new_tokens, proxy=proxy)
            ppo_m["kl"] = evaluation.kl_to_reference(pol, reference, tokenizer, [r["prompt"] for r in rows],
                                                     max_new_tokens=cfg.max_new_tokens, seed=cfg.seed + 7)
            sft_m["kl"] = 0.0
            say(evaluation.format_comparison({"sft": sft_m, "ppo": ppo_m}, res.task.name))
            report.update(sft={k: v for k, v in sft_m.items() if not k.startswith("_")},
                          ppo={k: v for k, v in ppo_m.items() if not k.startswith("_")},
                          samples=[{"prompt": r["prompt"][-200:], "sft": b, "ppo": p}
                                   for r, b, p in zip(rows[:10], base, ppo_m["_completions"])])
            counts = (f": {ppo_m['wins']} wins, {ppo_m['ties']} ties, {ppo_m['losses']} losses"
                      if "wins" in ppo_m else "")
            say(f"[ppo] gold score (quality) {sft_m['mean_quality']:.3f} -> {ppo_m['mean_quality']:.3f}, gold reward "
                f"{sft_m['gold_reward']:.3f} -> {ppo_m['gold_reward']:.3f}, in band {sft_m['frac_in_band']:.2f} -> "
                f"{ppo_m['frac_in_band']:.2f}, KL to SFT {ppo_m['kl']:.2f} nats")
            say(f"[ppo] gold win-rate of the PPO model against the SFT model: {ppo_m['win_rate']:.3f} "
                f"({len(rows)} held-out prompts{counts}; ties count half)")
        loop.write_json(run_dir / "eval.json", report)
    accelerator.wait_for_everyone()
    return final
