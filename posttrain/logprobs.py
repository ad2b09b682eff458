"""Per-token log-probs of given tokens under a model, entropy, and masked reductions: the single
implementation every trainer uses (policy under autograd, reference / old policy under no-grad).

CPU: `python -c "import posttrain.logprobs"` (pure functions; exercised by tests/posttrain/test_logprobs.py).
Multi-GPU: called inside each accelerate process on its own batch; nothing here communicates.

Alignment (the one convention):
    logps[:, t] = log p(input_ids[:, t] | input_ids[:, :t])     (B, T), 0 where completion_mask is 0
so every per-token tensor lines up with `input_ids` (the `RolloutBatch` layout of `posttrain.rollout`).
Column 0 never has a log-prob (nothing precedes it).

Positions. The model is called as `model(input_ids=, attention_mask=, position_ids=)` with
position_ids = cumsum(attention_mask) - 1 (clamped at 0), the same as HF `generate` and the rollout
engine use. Left-padded, right-padded and unpadded batches therefore give the same numbers per row.
Passing no position_ids would be wrong for left padding: Llama-family models then count positions
from column 0, padding included. Wrappers (accelerate/DDP, peft, torch.compile) work: we only read
`.logits` from the output. A left-padded batch gets a 4D mask in which every pad query sees itself
(`models.hf_attention_mask`): no attention row is empty, as on the lean path; the real tokens' numbers are those of
the 2D mask. (Fully masked rows are where fused attention kernels differ; PPO with bf16 weights on an H200 met a
non-finite gradient that this may be, unverified: docs/results-archive.md, "The GPU path".)

Lean path. For a plain fp32 Llama / Mistral / Qwen2 `*ForCausalLM`, or one under peft LoRA adapters (not wrapped
by DDP / torch.compile, no gradient checkpointing, no dropout; fp32 or under bf16 autocast) `sequence_logprobs` runs
`posttrain.lean.lean_forward` instead of the model's forward, and a fused log-prob with a cheaper
backward: the same numbers within fp32 rounding, faster for a tiny-model update step
(docs/results-archive.md, "Lean forwards"). Turn it
off with `posttrain.lean.ENABLED = False` or POSTTRAIN_LEAN_TRAIN=0. Rows that share their prompt
(GRPO's K completions per prompt) run that prompt once on this path (`lean.lean_forward_shared`), and the
vocabulary-wide head runs on the scored columns only (`_scored_head`).

Memory. Logits are requested only from the first completion column on (`logits_to_keep`, when the
model accepts it), and log-probs are gathered logit minus logsumexp: no (B, T, V) log_softmax copy is
made. Under autograd the logits themselves are kept for the backward pass (as for any loss on them).
"""
from __future__ import annotations

from typing import Any, Mapping

import torch

from posttrain.data import row_spans, to_device, token_groups
from posttrain.lean import train as lean
from posttrain.lean.support import lean_support
from posttrain.models import accepts, hf_attention_mask, model_device, position_ids_from_mask

# ------------------------------------------------------------------ log-probs

# The lean path runs each distinct prompt once (`lean.lean_forward_shared`) when that leaves at most this
# fraction of the batch's tokens: below ~0.9 the saved tokens outweigh the extra attention calls (tiny preset).
SHARE_PREFIX_BELOW = 0.9


def token_logprobs(logits: torch.Tensor, targets: torch.Tensor, temperature: float = 1.0,
                   return_entropy: bool = False, entropy_grad: bool = True):
    """logits (..., V), targets (...) -> (log p(target) (...), entropy (...) | None), no log_softmax copy.

    entropy_grad=False: the entropy is a metric only, computed outside autograd (no softmax kept for backward)."""
    if temperature != 1.0:
        logits = logits / temperature
    lse = torch.logsumexp(logits, dim=-1)  # (...)
    logp = logits.gather(-1, targets.unsqueeze(-1)).squeeze(-1) - lse  # (...)
    entropy = None
    if return_entropy:
        # H = lse - sum_v p_v * logit_v
        with torch.set_grad_enabled(entropy_grad and torch.is_grad_enabled()):
            x, z = (logits, lse) if entropy_grad else (logits.detach(), lse.detach())
            entropy = z - (torch.softmax(x, -1) * x).sum(-1)
    return logp, entropy


def sequence_logprobs(model, input_ids: torch.Tensor, attention_mask: torch.Tensor,
                      completion_mask: torch.Tensor | None = None, *, temperature: float = 1.0,
                      return_entropy: bool = False, entropy_grad: bool = True):
    """Log-probs of `input_ids` under `model`, aligned with input_ids (see module docstring).

    input_ids (B, T) long; attention_mask (B, T) 0/1; completion_mask (B, T) 0/1 selects the tokens to
    score (default: every real token that has a real token before it).
    Returns (logps (B, T), entropy (B, T) | None), both 0 where completion_mask is 0; differentiable
    when called under autograd. `temperature` divides the logits first (use the sampling temperature
    to get the sampler's distribution; PPO/GRPO ratios use 1.0). entropy_grad=False: the entropy is a
    metric only (no gradient, cheaper backward), as in GRPO; PPO's entropy bonus needs True.
    """
    if input_ids.dim() != 2 or input_ids.shape != attention_mask.shape:
        raise ValueError(f"sequence_logprobs: input_ids {tuple(input_ids.shape)} and attention_mask "
                         f"{tuple(attention_mask.shape)} must both be (B, T)")
    B, T = input_ids.shape
    dev = model_device(model)
    input_ids, attention_mask = input_ids.to(dev), attention_mask.to(dev)
    if completion_mask is None:
        completion_mask = torch.zeros_like(attention_mask)
        completion_mask[:, 1:] = attention_mask[:, 1:] * attention_mask[:, :-1]
    else:
        if completion_mask.shape != input_ids.shape:
            raise ValueError(f"sequence_logprobs: completion_mask {tuple(completion_mask.shape)} must match "
                             f"input_ids {tuple(input_ids.shape)}")
        completion_mask = completion_mask.to(dev)
    completion_mask = completion_mask.clone()
    completion_mask[:, 0] = 0
    cols = completion_mask.any(0).nonzero()
    dtype = torch.float32
    if T < 2 or cols.numel() == 0:
        zeros = torch.zeros(B, T, device=dev, dtype=dtype)
        return zeros, (zeros.clone() if return_entropy else None)
    c = int(cols[0])  # first scored column; logits needed from position c-1 on
    if lean_support(model, T, mode="train")[0]:
        # Same numbers as the branch below (fp32 rounding), fewer ops: see posttrain/lean.py.
        first, row_of = lean.shared_prefix_rows(input_ids, attention_mask, c)
        if len(first) * c + B * (T - c) <= SHARE_PREFIX_BELOW * B * T:  # e.g. GRPO's K completions per prompt
            x = lean.lean_hidden_shared(model, input_ids, attention_mask, c, first, row_of)  # (B, T-c, d)
        else:
            x = lean.lean_last_layer(model, input_ids, attention_mask)[:, c - 1:T - 1]  # (B, T-c, d)
        # the head: one fused pass, or row chunks when the (B, T-c, V) logits would be large (real vocabularies);
        # only on the scored columns (padding and the longer prompts' columns skipped)
        logp, ent = _scored_head(model, x, input_ids[:, c:], completion_mask[:, c:], temperature, return_entropy,
                                 entropy_grad)  # (B, T-c)
        return _place(logp, ent, completion_mask, c)
    kw: dict[str, Any] = {}
    if accepts(model, "position_ids"):
        kw["position_ids"] = position_ids_from_mask(attention_mask)
    keep_kw = accepts(model, "logits_to_keep") and c > 1
    if keep_kw:
        kw["logits_to_keep"] = T - c + 1
    mask = hf_attention_mask(attention_mask, model)  # left padding: 4D, no empty attention row
    logits = model(input_ids=input_ids, attention_mask=mask, **kw).logits  # (B, T or T-c+1, V)
    logits = logits[:, -(T - c + 1):-1]  # (B, T-c, V) predicts columns c .. T-1
    logp, ent = token_logprobs(logits.float(), input_ids[:, c:], temperature, return_entropy, entropy_grad)  # (B, T-c)
    return _place(logp, ent, completion_mask, c)


def completion_logits(model, input_ids: torch.Tensor, attention_mask: torch.Tensor, completion_mask: torch.Tensor,
                      *, temperature: float = 1.0) -> tuple[torch.Tensor, torch.Tensor, int]:
    """The full next-token distributions where `completion_mask` scores, and only there: (logits (n, V) fp32,
    index (n,), c). c is the first column the mask selects; row i of logits is the distribution, divided by
    `temperature`, of the token at flat position index[i] of the (B, T-c) columns c.. (row index // (T-c), column
    c + index % (T-c)) given the tokens before it (the same alignment as `sequence_logprobs`), in row-major order
    of the mask's nonzero entries. Differentiable under autograd. `scatter_scored` puts per-token values back.

    For losses on whole distributions (on-policy distillation's `losses.token_divergence`); memory is n x V
    floats, so callers bound B x T by a token budget per micro-batch. The lean path when it applies: its head then
    runs on the n scored columns only (padding and unscored columns never reach the vocabulary-wide matmul)."""
    B, T = input_ids.shape
    dev = model_device(model)
    input_ids, attention_mask, completion_mask = input_ids.to(dev), attention_mask.to(dev), completion_mask.to(dev)
    cols = completion_mask[:, 1:].any(0).nonzero()
    if T < 2 or cols.numel() == 0:
        raise ValueError("completion_logits: completion_mask selects no column after the first")
    c = int(cols[0]) + 1
    index = completion_mask[:, c:].reshape(-1).nonzero().squeeze(1)  # (n,)
    if lean_support(model, T, mode="train")[0]:
        x = lean.lean_last_layer(model, input_ids, attention_mask)[:, c - 1:T - 1]  # (B, T-c, d)
        x = x.reshape(B * (T - c), -1).index_select(0, index)  # (n, d)
        return lean.lean_logits(model, x, temperature).float(), index, c
    kw: dict[str, Any] = {"position_ids": position_ids_from_mask(attention_mask)} if accepts(model, "position_ids") \
        else {}
    if accepts(model, "logits_to_keep") and c > 1:
        kw["logits_to_keep"] = T - c + 1
    mask = hf_attention_mask(attention_mask, model)  # left padding: 4D, no empty attention row
    logits = model(input_ids=input_ids, attention_mask=mask, **kw).logits  # (B, T or T-c+1, V)
    logits = logits[:, -(T - c + 1):-1]  # (B, T-c, V), a strided view
    logits = logits[index // (T - c), index % (T - c)].float()  # (n, V): gathers the rows, no (B, T-c, V) copy
    return (logits if temperature == 1.0 else logits / temperature), index, c


def scatter_scored(values: torch.Tensor, index: torch.Tensor, shape: tuple[int, int]) -> torch.Tensor:
    """Per-token values (n,) of `completion_logits`'s rows -> (B, T-c) `shape`, zeros at the unscored columns;
    differentiable."""
    return values.new_zeros(shape[0] * shape[1]).index_copy(0, index, values).view(shape)


def _scored_head(model, x: torch.Tensor, targets: torch.Tensor, scored: torch.Tensor, temperature: float,
                 return_entropy: bool, entropy_grad: bool):
    """`lean.lean_token_logprobs` of last-layer outputs x (B, S, d) for targets (B, S), run only on the rows where
    `scored` (B, S) is nonzero: (logp (B, S), entropy (B, S) | None), 0 elsewhere. A real vocabulary's head costs
    per row about a quarter of the decoder (SmolLM2: 49k x 576 against 30 layers of 576 wide), and a batch's
    unscored columns (padding after short completions, the prompt tails of rows with longer prompts) are often a
    third or more of its columns; fewer rows also keep more batches under the chunked head's threshold
    (no recomputed logits in the backward). The numbers per row are unchanged."""
    B, S = targets.shape
    keep = scored.reshape(-1).bool()
    if bool(keep.all()):
        return lean.lean_token_logprobs(model, x, targets, temperature, return_entropy, entropy_grad)
    idx = keep.nonzero().squeeze(1)
    lp, en = lean.lean_token_logprobs(model, x.reshape(B * S, -1).index_select(0, idx),
                                      targets.reshape(-1).index_select(0, idx), temperature, return_entropy,
                                      entropy_grad)
    return scatter_scored(lp, idx, (B, S)), (scatter_scored(en, idx, (B, S)) if en is not None else None)


def _place(logp: torch.Tensor, ent: torch.Tensor | None, completion_mask: torch.Tensor, c: int):
    """(B, T-c) per-token values for columns c.. -> (B, T) aligned with input_ids, 0 outside completion_mask."""
    m = completion_mask[:, c:].to(logp.dtype)
    pad = torch.zeros(logp.shape[0], c, device=logp.device, dtype=logp.dtype)
    logps = torch.cat([pad, logp * m], 1)  # (B, T)
    entropy = torch.cat([pad, ent * m], 1) if ent is not None else None  # (B, T)
    return logps, entropy


def packed_logprobs(model, input_ids: torch.Tensor, position_ids: torch.Tensor, allowed: torch.Tensor,
                    pred_index: torch.Tensor, targets: torch.Tensor, target_mask: torch.Tensor) -> torch.Tensor:
    """Log-probs of `targets` for rows that pack several continuations of one prompt (prefix sharing).

    input_ids, position_ids (B, T); allowed (B, T, T) bool, allowed[b, q, k]: query column q may attend
    to key column k (a 4D mask: each continuation sees the prompt and itself, never a sibling);
    pred_index (B, L): the column whose logits predict targets[:, j]; target_mask (B, L) 0/1.
    Returns (B, L) log p(targets), 0 where target_mask is 0; differentiable under autograd.
    The numbers equal `sequence_logprobs` on each (prompt + continuation) row alone (tested); the prompt
    runs through the model once instead of once per continuation. Needs a model that takes a 4D
    attention mask and explicit position_ids (HF Llama-family models do). A plain fp32 Llama-family model
    runs the lean forward (`lean.lean_packed_hidden`) instead, as `sequence_logprobs` does.
    """
    B, T = input_ids.shape
    if position_ids.shape != (B, T) or allowed.shape != (B, T, T):
        raise ValueError(f"packed_logprobs: position_ids {tuple(position_ids.shape)} must be (B, T) and allowed "
                         f"{tuple(allowed.shape)} (B, T, T) for input_ids {tuple(input_ids.shape)}")
    if pred_index.shape != targets.shape or targets.shape != target_mask.shape:
        raise ValueError("packed_logprobs: pred_index, targets and target_mask must have the same (B, L) shape")
    dev = model_device(model)
    m = target_mask.to(dev).bool()
    pred_index, targets = pred_index.to(dev), targets.to(dev)
    if not bool(m.any()):
        return torch.zeros(targets.shape, device=dev, dtype=torch.float32)
    if lean_support(model, T, mode="train")[0]:  # same numbers within fp32 rounding, fewer ops
        x = lean.lean_packed_hidden(model, input_ids.to(dev), position_ids.to(dev), allowed.to(dev))  # (B, T, d)
        idx = pred_index.masked_fill(~m, 0)  # (B, L)
        picked = x.gather(1, idx[..., None].expand(-1, -1, x.shape[-1]))  # (B, L, d)
        logp, _ = lean.lean_token_logprobs(model, picked, targets.masked_fill(~m, 0))  # (B, L)
        return logp * m.to(logp.dtype)
    lo = int(pred_index[m].min())  # first column whose logits are needed
    kw: dict[str, Any] = {}
    if accepts(model, "logits_to_keep") and lo > 0:
        kw["logits_to_keep"] = T - lo
    else:
        lo = 0
    logits = model(input_ids=input_ids.to(dev), attention_mask=allowed.to(dev)[:, None],
                   position_ids=position_ids.to(dev), **kw).logits  # (B, T - lo, V)
    logits = logits[:, -(T - lo):]
    idx = (pred_index - lo).clamp(min=0).masked_fill(~m, 0)  # (B, L)
    picked = logits.gather(1, idx[..., None].expand(-1, -1, logits.shape[-1]))  # (B, L, V)
    logp, _ = token_logprobs(picked.float(), targets.masked_fill(~m, 0))  # (B, L)
    return logp * m.to(logp.dtype)


@torch.no_grad()
def batched_logprobs(model, batch: Any, micro_batch_size: int = 16, *, temperature: float = 1.0,
                     return_entropy: bool = False, max_tokens: int = 0):
    """`sequence_logprobs` without grad over a RolloutBatch (or a mapping with input_ids, attention_mask,
    completion_mask) in micro-batches of at most `micro_batch_size` rows and `max_tokens` padded tokens (0: no
    token limit), rows of like length together; all-padding columns of each micro-batch are trimmed first.
    Returns (logps (B, T), entropy (B, T) | None) on the batch's device."""
    get = (lambda k: batch[k]) if isinstance(batch, Mapping) else (lambda k: getattr(batch, k))
    input_ids, attention_mask = get("input_ids"), get("attention_mask")
    try:
        completion_mask = get("completion_mask")
    except (KeyError, AttributeError):
        completion_mask = None
    if micro_batch_size < 1:
        raise ValueError(f"batched_logprobs: micro_batch_size must be >= 1, got {micro_batch_size}")
    B, T = input_ids.shape
    out = torch.zeros(B, T, dtype=torch.float32, device=input_ids.device)
    ent_out = torch.zeros_like(out) if return_entropy else None
    for group in token_groups(row_spans(attention_mask), micro_batch_size, max_tokens, by_length=True):
        run = group[-1] - group[0] + 1 == len(group)  # consecutive rows: a view, not a copy
        sl = slice(group[0], group[-1] + 1) if run else torch.as_tensor(group, device=input_ids.device)
        am = attention_mask[sl]
        live = am.any(0).nonzero()
        if live.numel() == 0:
            continue
        lo, hi = int(live[0]), int(live[-1]) + 1
        cm = None if completion_mask is None else completion_mask[sl, lo:hi]
        lp, en = sequence_logprobs(model, input_ids[sl, lo:hi], am[:, lo:hi], cm, temperature=temperature,
                                   return_entropy=return_entropy)
        out[sl, lo:hi] = lp.to(out.device)
        if return_entropy:
            ent_out[sl, lo:hi] = en.to(out.device)
    return out, ent_out


# ------------------------------------------------------------------ masked reductions


def masked_sum(x: torch.Tensor, mask: torch.Tensor, dim: int | None = None) -> torch.Tensor:
    """Sum of x where mask is 1 (over `dim`, or everything)."""
    mask = mask.to(x.dtype)
    return (x * mask).sum() if dim is None else (x * mask).sum(dim)


def masked_mean(x: torch.Tensor, mask: torch.Tensor, dim: int | None = None) -> torch.Tensor:
    """Mean of x where mask is 1; 0 where the mask is empty (never NaN)."""
    mask = mask.to(x.dtype)
    total = mask.sum() if dim is None else mask.sum(dim)
    return masked_sum(x, mask, dim) / total.clamp(min=1.0)


def masked_var(x: torch.Tensor, mask: torch.Tensor, unbiased: bool = True) -> torch.Tensor:
    """Variance of x over all positions where mask is 1 (Bessel-corrected when unbiased and n > 1)."""
    mask = mask.to(x.dtype)
    mean = masked_mean(x, mask)
    var = masked_mean((x - mean) ** 2, mask)
    if unbiased:
        n = mask.sum()
        var = var * (n / (n - 1)) if n > 1 else var
    return var


def masked_whiten(x: torch.Tensor, mask: torch.Tensor, shift_mean: bool = True, eps: float = 1e-8) -> torch.Tensor:
    """(x - mean) / sqrt(var + eps) over the masked positions (TRL's `masked_whiten`: unbiased variance;
    with shift_mean=False the mean is added back). Positions outside the mask are returned as computed."""
    mean, var = masked_mean(x, mask), masked_var(x, mask)
    whitened = (x - mean) * torch.rsqrt(var + eps)
    return whitened if shift_mean else whitened + mean


# ------------------------------------------------------------------ SFT's weighted NLL
def token_weights(batch: dict[str, torch.Tensor], prompt_loss_weight: float) -> torch.Tensor:
    """(B, T) loss weight per token: 1 on completion tokens, `prompt_loss_weight` on prompt tokens after the first."""
    weights = batch["completion_mask"].float()
    if prompt_loss_weight > 0:
        prompt = batch["attention_mask"].bool() & ~batch["completion_mask"]
        prompt[:, 0] = False  # the first token has nothing to be predicted from
        weights = weights + prompt_loss_weight * prompt.float()
    return weights


def nll_sum(model, batch: dict[str, torch.Tensor], prompt_loss_weight: float = 0.0) -> tuple[torch.Tensor, torch.Tensor]:
    """SFT's loss: the `token_weights`-weighted summed negative log-likelihood of a batch (input_ids, attention_mask,
    completion_mask), and the total weight (= completion tokens when the prompt weight is 0), both 0-dim tensors on
    the model's device (no host sync here); the loss is differentiable. A batch still on the host is moved first."""
    batch = to_device(batch, model_device(model))
    weights = token_weights(batch, prompt_loss_weight)  # (B, T)
    logps, _ = sequence_logprobs(model, batch["input_ids"], batch["attention_mask"], weights > 0)
    return -(logps * weights).sum(), weights.sum()
