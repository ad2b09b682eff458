"""A lean, differentiable forward for Llama-family causal LMs: the training-side twin of the rollout
engine's `LeanLlama`, used by `posttrain.logprobs.sequence_logprobs` for the policy update (under
autograd) and for reference / old-policy log-probs (under no-grad), by `logprobs.packed_logprobs` (DPO's
shared-prompt rows), and, through `lean_hidden`, by the reward and value models' forwards.

CPU: `python -c "import posttrain.lean_train"` (exercised by tests/posttrain/test_lean_train.py).
Multi-GPU: a DDP / FSDP / peft wrapper is never run here (it needs its own forward for gradient sync or
adapters): `sequence_logprobs` then calls the model's own forward.

What it computes: the same numbers as `model(input_ids=, attention_mask=, position_ids=).logits`
(equal within fp32 rounding, tested: logits 1e-5 absolute, gradients of every parameter), for left-,
right- or un-padded (B, T) batches with a 0/1 attention mask and explicit position_ids. It reads the
live parameters on every call (nothing is cached), so gradients reach each parameter as in the HF
module and the optimizer may change them freely between calls.

Supported (`lean_train_support`): the object passed is itself a `*ForCausalLM` (or, with head="score",
`*ForSequenceClassification`) `PreTrainedModel` of model type llama / mistral / qwen2 (not
DDP/FSDP/peft/torch.compile-wrapped, no sharded parameters), fp32 weights on one
device, plain nn.Linear projections (biases anywhere, as qwen2's q/k/v), Llama-style RMSNorm, silu
MLP, RoPE with static frequencies (default, linear, llama3, yarn: `inv_freq` and `attention_scaling`
read from the module; not dynamic / longrope), MHA or GQA, tied or untied embeddings,
attention_dropout 0, no gradient checkpointing, no module hooks, no q/k norms or logit soft-capping,
and a sequence no longer than a sliding window. Anything else returns the reason and the caller
falls back to the HF forward.

Why: at the `tiny` preset (d=128) the HF module-per-op structure costs as much as the matmuls: RoPE
alone is ~10 elementwise ops per layer (cos/sin broadcast muls, rotate_half's slice+neg+cat and their
backward), the mask is rebuilt through `create_causal_mask`, and the loss on the logits adds a
zero-fill, a scatter and an add of a (B, T, V) tensor to the backward. Implementation details
(each measured alone on the tiny preset, kept only when faster):
- RoPE as one complex multiply: the q/k weight rows (and biases) of each head are permuted from the
  half-split pairing (x_i, x_{i+Dh/2}) that `rotate_half` uses to interleaved pairs by an
  `index_select` on the parameters every call (differentiable, 16K floats per matrix), so
  rotating is `view_as_complex(q) * cis`; q.k is unchanged by permuting q and k alike, v untouched.
  The (B, T, Dh/2) cos/sin table is computed once per call with the same expression as
  `LlamaRotaryEmbedding` (`position_ids * inv_freq`, times `attention_scaling`).
- RMSNorm weights are folded into the weight of each following projection (`W * w`, differentiable):
  a norm is x * rsqrt(mean(x^2) + eps), one activation-sized multiply fewer per norm.
- Attention: `F.scaled_dot_product_attention` with `is_causal` when there is no padding, else one
  boolean (B, 1, T, T) mask built once per call (padding queries see themselves, so no softmax row is
  empty: their outputs are finite and never reach a real token). GQA through `enable_gqa`.
- q/k/v and gate/up are NOT fused into one matmul: measured slower on CPU at these sizes (a
  (1440,128)x(128,1024) mm took 1.35x the time of two (128,512) ones, and the split's backward is a cat).
- Logits only for the columns the caller needs (`positions`), and `token_logprobs_fused`: log p(target)
  and the entropy from one softmax pass, with a backward that is one multiply plus a scatter (autograd's
  logsumexp + gather + slice backward is ~8 passes over (B, T, V)); the entropy's own gradient (PPO's
  entropy bonus) is -p * (x - E_p[x]). The temperature is folded into the final norm weight, so no
  (B, T, V) division.
- Shared prompts (`lean_forward_shared`, chosen by `logprobs.sequence_logprobs` when it leaves at most
  `SHARE_PREFIX_BELOW` of the tokens): rows whose columns before the first scored one are identical (GRPO's
  K completions of a prompt) run that prefix once; each row's completion tokens attend to the gathered
  prefix keys/values plus their own, so gradients from every row reach the shared computation. Tokens are
  kept as one flat (N, d) matrix through the projections and MLP, so sharing adds no matmul calls, only a
  second attention call per layer. GRPO-like update (16 rows = 2 prompts x 8, 26 prompt + 64 completion
  columns, 2 threads): 66.5 -> 56.6 ms (`tests/posttrain/test_lean_train.py` checks logits and gradients).
- Reward and value models (`*ForSequenceClassification`, `lean_train_support(..., head="score")`):
  `lean_hidden` gives the decoder's normed last hidden states; `scoring.reward_forward` (reward-model training
  and scoring) and `trainers.ppo.token_values` apply the model's `score` layer to them. RM / value step of
  32 rows x 118 columns on `tiny`, 1 thread: 313 -> 288 ms.
- Never on sharded weights (`rollout.backends.sharded_problem`): FSDP / DTensor / DeepSpeed ZeRO-3
  parameters hold a shard outside the model's own forward, so both lean paths refuse them.
- Not tried / not kept: a vector_norm/hypot RMSNorm (as `LeanLlama`) measured ~1% per norm faster in
  isolation, not worth the extra rounding; explicit-matmul attention was slower than SDPA here (its
  backward keeps the (B, H, T, T) probabilities); a flip-based rotate_half was slower than the complex
  multiply.

Speed (tiny preset, vocab 1024, `sequence_logprobs` + backward + fused AdamW step, GRPO-like batches
with left-padded prompts and right-padded completions, 1 thread, medians of 7 alternating runs, a
shared 2-core machine): (16, 90) 140 -> 121 ms (0.86x); (8, 256) 217 -> 196 ms (0.90x). Of that, the
lean forward/backward of the decoder is ~6% (RoPE and norm ops, the mask) and the fused log-prob
backward plus computing only the needed logit columns ~8%.

Switch: `posttrain.lean_train.ENABLED = False`, or the environment variable POSTTRAIN_LEAN_TRAIN=0,
makes `sequence_logprobs` always use the model's own forward (for debugging or comparison).
"""
from __future__ import annotations

import os

import torch
import torch.nn.functional as F
from torch import nn

from .logprobs import position_ids_from_mask
from .rollout.backends import autocast_problem, llama_family_problem, sharded_problem

ENABLED = os.environ.get("POSTTRAIN_LEAN_TRAIN", "1").strip().lower() not in ("0", "false", "no", "off")
LEAN_MODEL_TYPES = ("llama", "mistral", "qwen2")

_PERMS: dict = {}


def lean_train_support(model, seq_len: int | None = None, head: str = "lm") -> tuple[bool, str]:
    """Whether the lean forward can replace `model`'s own forward (for sequences of `seq_len` tokens), and why
    (not). head="lm": a `*ForCausalLM` for `lean_forward` (logits); head="score": a `*ForSequenceClassification`
    (reward / value model) for `lean_hidden` (its decoder's last hidden states, then its `score` layer)."""
    if not ENABLED:
        return False, "disabled (posttrain.lean_train.ENABLED / POSTTRAIN_LEAN_TRAIN=0)"
    from transformers import PreTrainedModel

    kind = {"lm": "ForCausalLM", "score": "ForSequenceClassification"}[head]
    if not isinstance(model, PreTrainedModel) or not type(model).__name__.endswith(kind):
        return False, f"{type(model).__name__} is not a *{kind} PreTrainedModel (a wrapper runs its own forward)"
    if hasattr(model, "peft_config") or hasattr(model, "get_base_model"):
        return False, "peft model"
    cfg = model.config
    mt = getattr(cfg, "model_type", None)
    if mt not in LEAN_MODEL_TYPES:
        return False, f"model_type {mt!r} is not one of {LEAN_MODEL_TYPES}"
    if any(getattr(mod, "gradient_checkpointing", False) is True for mod in model.modules()):
        return False, "gradient checkpointing is enabled"
    if float(getattr(cfg, "attention_dropout", 0.0) or 0.0) != 0.0:
        return False, f"attention_dropout {cfg.attention_dropout} (the lean path has no dropout)"
    window = getattr(cfg, "sliding_window", None)
    if window is not None and getattr(cfg, "use_sliding_window", True) is not False and \
            (seq_len is None or seq_len > window):
        return False, f"sequence length {seq_len} may exceed the sliding window {window}"
    base, out = getattr(model, "model", None), getattr(model, "lm_head" if head == "lm" else "score", None)
    if base is None or type(out) is not nn.Linear or type(getattr(base, "embed_tokens", None)) is not nn.Embedding:
        return False, f"no plain nn.Linear {'lm_head' if head == 'lm' else 'score'} / nn.Embedding model.embed_tokens"
    emb = base.embed_tokens
    if emb.max_norm is not None or emb.scale_grad_by_freq or emb.sparse:
        return False, "embedding with max_norm / scale_grad_by_freq / sparse"
    params = list(model.parameters())
    if any(p.dtype != torch.float32 for p in params):
        return False, "not every parameter is fp32"
    devices = {p.device for p in params}
    if len(devices) != 1 or next(iter(devices)).type == "meta":
        return False, f"weights on several devices or on meta ({sorted(str(d) for d in devices)})"
    why = autocast_problem(next(iter(devices)))
    if why:
        return False, why
    if "_original_forward" in vars(model):  # accelerate's mixed precision patched forward (autocast inside it)
        return False, "accelerate mixed precision: the model's autocast forward is used"
    why = llama_family_problem(cfg, base)
    if why:
        return False, why
    why = sharded_problem(model)
    if why:
        return False, why
    for mod in model.modules():
        if mod._forward_hooks or mod._forward_pre_hooks or hasattr(mod, "_hf_hook"):
            return False, f"a forward hook on {type(mod).__name__} (the lean path would skip it)"
    for layer in base.layers[:cfg.num_hidden_layers]:
        att, mlp = getattr(layer, "self_attn", None), getattr(layer, "mlp", None)
        try:
            lins = [att.q_proj, att.k_proj, att.v_proj, att.o_proj, mlp.gate_proj, mlp.up_proj, mlp.down_proj]
        except AttributeError:
            return False, "a decoder layer without the Llama projections"
        if any(type(m) is not nn.Linear for m in lins):
            return False, "a layer projection is not a plain nn.Linear (quantised or an adapter)"
        for norm in (layer.input_layernorm, layer.post_attention_layernorm):
            if not type(norm).__name__.endswith("RMSNorm") or not hasattr(norm, "variance_epsilon"):
                return False, "a layer norm is not a Llama-style RMSNorm"
        if hasattr(att, "q_norm") or hasattr(att, "k_norm"):
            return False, "q/k norms are not implemented in the lean path"
    if not hasattr(base.norm, "variance_epsilon"):
        return False, "the final norm is not a Llama-style RMSNorm"
    return True, f"lean training forward ({mt})"


def _perm(heads: int, D: int, device) -> torch.Tensor:
    """Row order that turns each head's half-split RoPE pairs (i, i + D/2) into interleaved pairs."""
    key = (heads, D, str(device))
    if key not in _PERMS:
        half = torch.arange(D // 2)
        one = torch.stack([half, half + D // 2], 1).reshape(-1)  # (D,)
        _PERMS[key] = (one[None] + D * torch.arange(heads)[:, None]).reshape(-1).to(device)
    return _PERMS[key]


def _rms(x: torch.Tensor, eps: float) -> torch.Tensor:
    """RMSNorm without its weight (folded into the next matrix): x * rsqrt(mean(x^2) + eps), as HF computes it."""
    return x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + eps)


def _dims(model):
    cfg = model.config
    H = cfg.num_attention_heads
    Hkv = getattr(cfg, "num_key_value_heads", None) or H
    att0 = model.model.layers[0].self_attn
    D = getattr(att0, "head_dim", None) or cfg.hidden_size // H
    return H, Hkv, D, float(getattr(att0, "scaling", D ** -0.5))


def _cis(model, position_ids: torch.Tensor) -> torch.Tensor:
    """(...) positions -> (..., 1, D/2) complex RoPE factors, as LlamaRotaryEmbedding computes them."""
    rot = model.model.rotary_emb
    freqs = position_ids[..., None].float() * rot.inv_freq.float()  # (..., D/2), LlamaRotaryEmbedding's expression
    sc = float(getattr(rot, "attention_scaling", 1.0))
    return torch.complex(freqs.cos() * sc, freqs.sin() * sc)[..., None, :]


def _allowed(valid: torch.Tensor) -> torch.Tensor | None:
    """(B, T) real-token mask -> (B, 1, T, T) bool: key j visible to query i when j <= i and j is real; pad
    queries also see themselves (no empty softmax row). None when nothing is padded (use is_causal)."""
    if bool(valid.all()):
        return None
    T = valid.shape[1]
    causal = torch.ones(T, T, dtype=torch.bool, device=valid.device).tril_()
    return (causal & (valid[:, None, :] | torch.eye(T, dtype=torch.bool, device=valid.device)))[:, None]


def _decoder(model, x: torch.Tensor, cis: torch.Tensor, attend) -> torch.Tensor:
    """The decoder layers on a flat token matrix. x (N, d) embeddings, cis (N, 1, D/2) RoPE factors,
    attend(q (N, H, D) roped, k (N, Hkv, D) roped, v (N, Hkv, D)) -> (N, H*D) attention outputs (the caller
    decides which tokens see which). Returns the last layer's output (N, d), before the final norm."""
    cfg = model.config
    H, Hkv, D, _ = _dims(model)
    N = x.shape[0]
    perm_q, perm_k = _perm(H, D, x.device), _perm(Hkv, D, x.device)
    for layer in model.model.layers[:cfg.num_hidden_layers]:
        a, m = layer.self_attn, layer.mlp
        g1 = layer.input_layernorm.weight
        h = _rms(x, layer.input_layernorm.variance_epsilon)  # (N, d)
        bq, bk = a.q_proj.bias, a.k_proj.bias
        q = F.linear(h, (a.q_proj.weight * g1).index_select(0, perm_q),
                     None if bq is None else bq.index_select(0, perm_q))  # (N, H*D), pairs interleaved
        k = F.linear(h, (a.k_proj.weight * g1).index_select(0, perm_k),
                     None if bk is None else bk.index_select(0, perm_k))  # (N, Hkv*D)
        v = F.linear(h, a.v_proj.weight * g1, a.v_proj.bias)  # (N, Hkv*D)
        q = torch.view_as_real(torch.view_as_complex(q.view(N, H, D // 2, 2)) * cis).view(N, H, D)
        k = torch.view_as_real(torch.view_as_complex(k.view(N, Hkv, D // 2, 2)) * cis).view(N, Hkv, D)
        x = x + F.linear(attend(q, k, v.view(N, Hkv, D)), a.o_proj.weight, a.o_proj.bias)
        g2 = layer.post_attention_layernorm.weight
        h = _rms(x, layer.post_attention_layernorm.variance_epsilon)
        gate = F.linear(h, m.gate_proj.weight * g2, m.gate_proj.bias)  # (N, I)
        up = F.linear(h, m.up_proj.weight * g2, m.up_proj.bias)
        x = x + F.linear(F.silu(gate) * up, m.down_proj.weight, m.down_proj.bias)
    return x


def lean_logits(model, x: torch.Tensor, temperature: float = 1.0) -> torch.Tensor:
    """Final norm and lm_head: (..., d) last-layer outputs (e.g. `lean_packed_hidden`'s) -> (..., V) logits /
    temperature (folded into the norm weight)."""
    base = model.model
    gf = base.norm.weight if temperature == 1.0 else base.norm.weight / temperature
    head = model.lm_head
    hb = head.bias if head.bias is None or temperature == 1.0 else head.bias / temperature
    return F.linear(_rms(x, base.norm.variance_epsilon) * gf, head.weight, hb)


def _sdpa(model, q, k, v, allowed):
    """q (B, H, Tq, D), k/v (B, Hkv, Tk, D), allowed (B, 1, Tq, Tk) bool or None (causal) -> (B, H, Tq, D)."""
    H, Hkv, _, scale = _dims(model)
    return F.scaled_dot_product_attention(q, k, v, attn_mask=allowed, is_causal=allowed is None, scale=scale,
                                          enable_gqa=Hkv != H)


def _rows_forward(model, input_ids: torch.Tensor, attention_mask: torch.Tensor | None,
                  position_ids: torch.Tensor, allowed: torch.Tensor | None = None) -> torch.Tensor:
    """(B, T) rows, each attending within itself -> the last layer's output (B, T, d), before the final norm.
    Who sees whom: causal over the real tokens of attention_mask, or `allowed` (B, 1, T, T) bool when given."""
    B, T = input_ids.shape
    H, Hkv, D, _ = _dims(model)
    if allowed is None:
        allowed = _allowed(attention_mask.bool())

    def attend(q, k, v):  # (B*T, ., D) -> (B*T, H*D)
        o = _sdpa(model, q.view(B, T, H, D).transpose(1, 2), k.view(B, T, Hkv, D).transpose(1, 2),
                  v.view(B, T, Hkv, D).transpose(1, 2), allowed)  # (B, H, T, D)
        return o.transpose(1, 2).reshape(B * T, H * D)

    emb = model.model.embed_tokens
    x = F.embedding(input_ids.reshape(-1), emb.weight, emb.padding_idx)  # (B*T, d)
    return _decoder(model, x, _cis(model, position_ids.reshape(-1)), attend).view(B, T, -1)


def lean_forward(model, input_ids: torch.Tensor, attention_mask: torch.Tensor, position_ids: torch.Tensor,
                 logits_to_keep: int = 0, *, positions: slice | None = None,
                 temperature: float = 1.0) -> torch.Tensor:
    """Logits (B, K, V) fp32 of a supported model (see `lean_train_support`), differentiable.

    input_ids, attention_mask (0/1), position_ids: (B, T). Columns kept: the last `logits_to_keep`
    (0: all), as HF's argument does, or `positions` (a slice of columns) when given. `temperature`
    divides the logits (folded into the final norm weight)."""
    x = _rows_forward(model, input_ids, attention_mask, position_ids)
    if positions is not None:
        x = x[:, positions]
    elif logits_to_keep:
        x = x[:, -logits_to_keep:]
    return lean_logits(model, x, temperature)  # (B, K, V)


def lean_hidden(model, input_ids: torch.Tensor, attention_mask: torch.Tensor,
                position_ids: torch.Tensor | None = None) -> torch.Tensor:
    """The decoder's last hidden states (B, T, d) after the final norm: what `model.model(...).last_hidden_state`
    returns, for a supported `*ForSequenceClassification` (`lean_train_support(model, T, head="score")`) or
    `*ForCausalLM`; differentiable. position_ids default to cumsum(attention_mask) - 1 (clamped at 0)."""
    if position_ids is None:
        position_ids = position_ids_from_mask(attention_mask)
    x = _rows_forward(model, input_ids, attention_mask, position_ids)
    norm = model.model.norm
    return _rms(x, norm.variance_epsilon) * norm.weight  # (B, T, d)


def lean_packed_hidden(model, input_ids: torch.Tensor, position_ids: torch.Tensor,
                       allowed: torch.Tensor) -> torch.Tensor:
    """`logprobs.packed_logprobs`'s forward (rows packing several continuations of one prompt, a 4D mask):
    input_ids, position_ids (B, T), allowed (B, T, T) bool (query, key) -> last layer output (B, T, d) before
    the final norm (`lean_logits` turns chosen columns of it into logits)."""
    return _rows_forward(model, input_ids, None, position_ids, allowed[:, None])


def shared_prefix_rows(input_ids: torch.Tensor, attention_mask: torch.Tensor, c: int):
    """Rows whose first `c` columns (tokens and mask) are identical, e.g. the K completions of one prompt in a
    GRPO group: (first row of each distinct prefix (U,), prefix of each row (B,)) with U <= B."""
    key = torch.where(attention_mask[:, :c].bool(), input_ids[:, :c], -1)  # (B, c)
    uniq, row_of = torch.unique(key, dim=0, return_inverse=True)
    first = torch.full((uniq.shape[0],), input_ids.shape[0], dtype=torch.long, device=input_ids.device)
    first.scatter_reduce_(0, row_of, torch.arange(len(row_of), device=row_of.device), "amin")
    return first, row_of


def lean_forward_shared(model, input_ids: torch.Tensor, attention_mask: torch.Tensor, c: int,
                        first: torch.Tensor, row_of: torch.Tensor, temperature: float = 1.0) -> torch.Tensor:
    """`lean_forward(..., positions=slice(c - 1, T - 1))` computed with each distinct prefix (columns < c) run
    once: rows `first` carry the U distinct prefixes, row_of (B,) maps each row to its prefix
    (`shared_prefix_rows`). The prefix tokens attend among themselves; each row's suffix tokens attend to
    its prefix's keys and values (gathered, so gradients reach the shared computation from every row) and
    causally to their own. Same numbers as the unshared forward within fp32 rounding (tested)."""
    B, T = input_ids.shape
    U, S = first.shape[0], T - c
    H, Hkv, D, _ = _dims(model)
    valid = attention_mask.bool()
    pos = position_ids_from_mask(attention_mask)  # (B, T)
    valid_p = valid[first, :c]  # (U, c)
    allowed_p = _allowed(valid_p)
    # Suffix query i (column c+i) sees prefix key j when real, suffix key j <= i when real or j == i.
    causal = torch.ones(S, S, dtype=torch.bool, device=valid.device).tril_()
    own = causal & (valid[:, None, c:] | torch.eye(S, dtype=torch.bool, device=valid.device))  # (B, S, S)
    allowed_s = torch.cat([valid_p[row_of][:, None, :].expand(B, S, c), own], 2)[:, None]  # (B, 1, S, T)
    Np = U * c

    def prefix(t, heads):  # rows [0, Np) of (N, heads, D) -> (U, heads, c, D)
        return t[:Np].view(U, c, heads, D).transpose(1, 2)

    def suffix(t, heads):  # rows [Np, N) -> (B, heads, S, D)
        return t[Np:].view(B, S, heads, D).transpose(1, 2)

    def attend(q, k, v):
        kp, vp = prefix(k, Hkv), prefix(v, Hkv)  # (U, Hkv, c, D)
        op = _sdpa(model, prefix(q, H), kp, vp, allowed_p)  # (U, H, c, D)
        ks = torch.cat([kp.index_select(0, row_of), suffix(k, Hkv)], 2)  # (B, Hkv, T, D)
        vs = torch.cat([vp.index_select(0, row_of), suffix(v, Hkv)], 2)
        os_ = _sdpa(model, suffix(q, H), ks, vs, allowed_s)  # (B, H, S, D)
        return torch.cat([op.transpose(1, 2).reshape(Np, H * D), os_.transpose(1, 2).reshape(B * S, H * D)], 0)

    ids = torch.cat([input_ids[first, :c].reshape(-1), input_ids[:, c:].reshape(-1)])  # (Np + B*S,)
    positions = torch.cat([pos[first, :c].reshape(-1), pos[:, c:].reshape(-1)])
    emb = model.model.embed_tokens
    x = _decoder(model, F.embedding(ids, emb.weight, emb.padding_idx), _cis(model, positions), attend)
    last = x[:Np].view(U, c, -1)[:, -1].index_select(0, row_of)  # (B, d): column c-1 of each row
    x = torch.cat([last[:, None], x[Np:].view(B, S, -1)[:, :S - 1]], 1)  # (B, S, d): columns c-1 .. T-2
    return lean_logits(model, x, temperature)  # (B, T-c, V)


class _TargetLogprob(torch.autograd.Function):
    """log p(target) and the entropy from logits (N, V) with one softmax pass.
    Backward: -p * g plus g at the target; with entropy_grad also -g_H * p * (x - E_p[x])."""

    @staticmethod
    def forward(ctx, logits, targets, want_entropy: bool, entropy_grad: bool):
        mx = logits.amax(-1, keepdim=True)  # (N, 1)
        p = torch.sub(logits, mx).exp_()  # (N, V) unnormalised
        s = p.sum(-1, keepdim=True)
        lse = s.log().add_(mx)  # (N, 1)
        p.div_(s)
        logp = logits.gather(-1, targets[:, None]).sub_(lse).squeeze(-1)  # (N,)
        ent = None
        if want_entropy:  # H = lse - sum_v p_v * logit_v
            ent = lse.squeeze(-1) - (p * logits).sum(-1)  # (N,)
            if not entropy_grad:
                ctx.mark_non_differentiable(ent)
        ctx.entropy_grad = want_entropy and entropy_grad
        ctx.save_for_backward(p, targets, *((logits,) if ctx.entropy_grad else ()))
        return logp, ent

    @staticmethod
    def backward(ctx, g, g_ent):
        p, targets = ctx.saved_tensors[:2]
        grad = p * g.neg()[:, None]  # (N, V)
        grad.scatter_add_(-1, targets[:, None], g[:, None])
        if ctx.entropy_grad and g_ent is not None:
            logits = ctx.saved_tensors[2]
            mean = (p * logits).sum(-1, keepdim=True)  # E_p[x] (N, 1)
            grad.sub_(torch.sub(logits, mean).mul_(p).mul_(g_ent[:, None]))
        return grad, None, None, None


def token_logprobs_fused(logits: torch.Tensor, targets: torch.Tensor, return_entropy: bool = False,
                         entropy_grad: bool = False):
    """`logprobs.token_logprobs` (temperature 1) with a cheaper backward (see module docstring).
    logits (..., V), targets (...) -> (log p(target) (...), entropy (...) | None); the entropy carries
    a gradient only with entropy_grad."""
    shape = targets.shape
    logp, ent = _TargetLogprob.apply(logits.reshape(-1, logits.shape[-1]), targets.reshape(-1), return_entropy,
                                     entropy_grad)
    return logp.view(shape), (ent.view(shape) if ent is not None else None)
