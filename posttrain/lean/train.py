"""A lean, differentiable forward for Llama-family causal LMs: the training-side twin of the rollout
engine's `posttrain.lean.decode.LeanLlama`, used by `posttrain.logprobs.sequence_logprobs` for the policy
update (under autograd) and for reference / old-policy log-probs (under no-grad), by
`logprobs.packed_logprobs` (DPO's shared-prompt rows), and, through `lean_hidden`, by the reward and value
models' forwards (`scoring.reward_forward`, PPO's `token_values`).

CPU: `python -c "import posttrain.lean.train"` (exercised by tests/posttrain/lean/test_lean_train.py).
Multi-GPU: a DDP / FSDP wrapper is never run here (it needs its own forward for gradient sync):
`sequence_logprobs` then calls the model's own forward. A peft LoRA model (no dropout) is run here: each
projection adds its adapters' scaling * B(A(h)) (`_proj`), the frozen base cast to bf16 once under autocast.

What it computes: the same numbers as `model(input_ids=, attention_mask=, position_ids=).logits` (in fp32, equal
within fp32 rounding, tested: logits 1e-5 absolute, gradients of every parameter), for left-, right- or
un-padded (B, T) batches with a 0/1 attention mask and explicit position_ids. It reads the live
parameters on every call (nothing is cached), so gradients reach each parameter as in the HF module and
the optimizer may change them freely between calls. What it runs: `lean_support(model, T, mode="train")`
(`posttrain.lean.support`); anything else falls back to the HF forward.

Why: at the `tiny` preset (d=128) the HF module-per-op structure costs as much as the matmuls (RoPE's
cos/sin broadcasts and rotate_half, the mask rebuilt by `create_causal_mask`, the loss's (B, T, V)
zero-fill + scatter in the backward). Implementation details, each measured alone and kept only when
faster (figures in docs/results-archive.md, "Lean forwards"):
- RoPE as one complex multiply (`support.rope_pair_order` / `rope_cis`): the q/k weight rows (and
  biases) are permuted to interleaved pairs by an `index_select` on the parameters every call
  (differentiable), the (N, D/2) factors computed once per call.
- RMSNorm weights folded into the weight of each following projection (`W * w`, differentiable) when a call
  has more tokens than those projections have rows (`_normed`): one activation-sized multiply fewer per norm;
  with fewer tokens (a real model's short batches) the weight multiplies the activations, as in HF, since
  weight-sized products (and their backward) then cost more than the activations' (measured on SmolLM2).
- Attention: `F.scaled_dot_product_attention` with `is_causal` when nothing is padded, else one boolean
  (B, 1, T, T) mask built once per call (pad queries see themselves, so no softmax row is empty). GQA
  through `enable_gqa`. Under bf16 autocast on a CPU with at most EXPLICIT_ATTENTION_MAX_KEYS keys: explicit
  matmuls with an fp32 softmax instead (`_sdpa`), as the CPU kernel is 2-3x slower in bf16 at those lengths.
- RMSNorm as one autograd Function (`_RMSNorm`) with a written-out backward, its output cast to bf16 once under
  autocast for every projection that reads it (autograd's own: ~10 activation-sized passes and one cast per
  projection, forward and backward): a real-size RM step 3.5% faster, DPO 2.4% (RESULTS.md, "Two passes fewer").
- q/k/v and gate/up NOT fused into one matmul (slower on CPU at these sizes; the split's backward is a cat).
- Logits only for the columns the caller needs (`positions`; `logprobs.sequence_logprobs` and
  `logprobs.completion_logits` pass only the scored ones), and `token_logprobs_fused`: log p(target)
  and the entropy from one softmax pass, with a backward that is one multiply plus a scatter; the
  entropy's own gradient (PPO's entropy bonus) is -p * (x - E_p[x]). The temperature is folded into the
  final norm weight, so no (B, T, V) division.
- Shared prompts (`lean_forward_shared`, chosen by `sequence_logprobs` when it leaves at most
  `SHARE_PREFIX_BELOW` of the tokens): rows whose columns before the first scored one are identical
  (GRPO's K completions of a prompt) run that prefix once; each row's completion tokens attend to the
  gathered prefix keys/values plus their own, so gradients from every row reach the shared computation.
- Mixed precision (`run.mixed_precision=bf16`): under bf16 autocast, the caller's or the one accelerate's
  prepared model would enter in its patched `forward` (entered here, since that forward is never called:
  `support.train_autocast`), every projection and the attention run in bf16 as the HF forward's would; the
  residual stream, the norms (their outputs cast to bf16) and RoPE stay fp32, the head's matmul is bf16 with
  its softmax, log-probs and gradients fp32 (the chunked head casts explicitly, forward and backward). fp16
  autocast falls back. On SmolLM2 with native bf16 a GRPO-like forward + backward is faster than lean fp32 and
  than the HF forward under the same autocast (measured: docs/results-archive.md, "Lean forwards" and
  "Figures once kept in code comments").
- Not kept: a vector_norm/hypot RMSNorm (as `LeanLlama`; barely faster, more rounding), explicit-matmul
  attention in fp32 (no faster than the kernel; its backward keeps the (B, H, T, T) probabilities), a flip-based
  rotate_half.

Switch: `posttrain.lean.support.ENABLED = False`, or POSTTRAIN_LEAN_TRAIN=0 in the environment, makes
`sequence_logprobs` and the reward / value forwards always use the model's own forward.
"""
from __future__ import annotations

import functools
import weakref

import torch
import torch.nn.functional as F
from torch import nn

from ..models import causal_padding_mask, position_ids_from_mask
from .support import rope_cis, rope_pair_order, train_autocast

_PERMS: dict = {}


def _perm(heads: int, D: int, device) -> torch.Tensor:
    """Row order that turns each head's half-split RoPE pairs (i, i + D/2) into interleaved pairs."""
    key = (heads, D, str(device))
    if key not in _PERMS:
        _PERMS[key] = rope_pair_order(heads, D).to(device)
    return _PERMS[key]


def _model_precision(fn):
    """Run `fn(model, ...)` under the bf16 autocast the model's mixed precision asks for (`train_autocast`):
    accelerate's autocast lives in the model's patched `forward`, which the lean path never calls, so it is
    entered here; a caller's own torch.autocast is already on. Without mixed precision: fp32, unchanged."""
    @functools.wraps(fn)
    def run(model, *args, **kwargs):
        inner = model.get_base_model() if hasattr(model, "get_base_model") else model  # a peft LoRA model's own
        device = inner.model.embed_tokens.weight.device
        dtype, _ = train_autocast(model, device)  # accelerate patches the outermost object's forward
        if dtype is None or torch.is_autocast_enabled(device.type):
            return fn(inner, *args, **kwargs)
        with torch.autocast(device.type, dtype=dtype):
            return fn(inner, *args, **kwargs)
    return run


def _autocast_dtype(device) -> torch.dtype | None:
    """The dtype torch.autocast computes matmuls in on `device` now, or None when it is off."""
    kind = torch.device(device).type
    return torch.get_autocast_dtype(kind) if torch.is_autocast_enabled(kind) else None


def _rms(x: torch.Tensor, eps: float) -> torch.Tensor:
    """RMSNorm without its weight (folded into the next matrix): x * rsqrt(mean(x^2) + eps), as HF computes it."""
    return x * torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + eps)


class _RMSNorm(torch.autograd.Function):
    """y = x * rsqrt(mean(x^2) + eps) * g (g optional), as HF's LlamaRMSNorm computes it, returned in `dtype`
    (bf16 under bf16 autocast: cast once here for every projection that reads it, not once per projection,
    forward and backward). The backward is written out, gx = r * (a - h * mean(a * h)) with h = x * r and
    a = gy * g, gg = sum over rows of gy * h: 4 activation-sized passes against autograd's ~10 through pow,
    mean, rsqrt and the two products (and the upcast of each projection's input gradient)."""

    @staticmethod
    def forward(ctx, x, g, eps, dtype):
        r = torch.rsqrt(x.pow(2).mean(-1, keepdim=True) + eps)  # (N, 1)
        h = x * r
        y = h if g is None else h * g
        ctx.save_for_backward(h, r, g)
        return y if dtype is None or y.dtype == dtype else y.to(dtype)

    @staticmethod
    def backward(ctx, gy):
        h, r, g = ctx.saved_tensors
        gy = gy.to(h.dtype)
        a = gy if g is None else gy * g
        gg = (gy * h).sum(0) if g is not None and ctx.needs_input_grad[1] else None
        gx = torch.addcmul(a, h, (a * h).mean(-1, keepdim=True), value=-1).mul_(r) if ctx.needs_input_grad[0] \
            else None
        return gx, gg, None, None


def _normed(x: torch.Tensor, norm, projections: tuple) -> tuple[torch.Tensor, torch.Tensor | None]:
    """RMSNorm `norm` of x (N, d) for the `projections` that read it: its weight g multiplies either the
    activations (x_normed * g, N x d products, as HF does) or, when there are more tokens than the projections have
    rows and they are plain nn.Linear, each following weight (W * g: one activation-sized multiply fewer, forward
    and backward). Returns (the projections' input, g to fold into their weights or None): see `_proj`. Under
    bf16 autocast the input is bf16 (`_RMSNorm`); the residual stream x stays fp32."""
    g, eps, dtype = norm.weight, norm.variance_epsilon, _autocast_dtype(x.device)
    if x.shape[0] > sum(m.weight.shape[0] for m in projections) and all(type(m) is nn.Linear for m in projections):
        return _RMSNorm.apply(x, None, eps, dtype), g
    return _RMSNorm.apply(x, g, eps, dtype), None


# bf16 copies of frozen weights (a LoRA model's base), made once and reused while the weight is unchanged: autocast
# would cast every one of them again in each forward. id(weight) -> (a weak reference to it, {(dtype, permuted):
# (version, copy)}); the entry goes when the weight does, and the version counter makes a fresh copy after an
# in-place change (a checkpoint load).
_FROZEN_CASTS: dict[int, tuple] = {}


def _frozen_cast(w: torch.Tensor, dtype: torch.dtype, perm: torch.Tensor | None) -> torch.Tensor:
    """`w` (rows permuted by `perm`) in `dtype`, cached while w keeps its version."""
    k = id(w)
    entry = _FROZEN_CASTS.get(k)
    if entry is None or entry[0]() is not w:
        entry = _FROZEN_CASTS[k] = (weakref.ref(w, lambda _, k=k: _FROZEN_CASTS.pop(k, None)), {})
    copies = entry[1]
    key = (dtype, perm is not None)
    hit = copies.get(key)
    if hit is None or hit[0] != w._version:
        with torch.no_grad():
            t = w if perm is None else w.index_select(0, perm)
            hit = copies[key] = (w._version, t.to(dtype))
    return hit[1]


def _proj(m, h: torch.Tensor, g: torch.Tensor | None = None, perm: torch.Tensor | None = None) -> torch.Tensor:
    """A projection of h (N, in): a plain nn.Linear, or a peft LoRA Linear (base + each active adapter's
    scaling * B(A(h)), no dropout: `lean_support`), with `g` (a norm weight, plain Linear only) folded into the
    weight and the output rows permuted by `perm` (RoPE's pair order for q / k). A frozen base weight under bf16
    autocast is read from `_frozen_cast` (cast once, not in every forward)."""
    base = m if type(m) is nn.Linear else m.base_layer
    w, b = base.weight, base.bias
    dtype = _autocast_dtype(h.device)
    if g is None and not w.requires_grad and dtype is not None:
        w = _frozen_cast(w, dtype, perm)
    else:
        w = w if g is None else w * g
        w = w if perm is None else w.index_select(0, perm)
    if b is not None and perm is not None:
        b = b.index_select(0, perm)
    y = F.linear(h, w, b)
    if base is m or m.disable_adapters or m.merged:
        return y
    for a in m.active_adapters:
        if a not in m.lora_A:
            continue
        lb = m.lora_B[a]
        wb = lb.weight if perm is None else lb.weight.index_select(0, perm)
        bb = lb.bias if lb.bias is None or perm is None else lb.bias.index_select(0, perm)
        y = y + F.linear(F.linear(h, m.lora_A[a].weight), wb, bb) * m.scaling[a]
    return y


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
    return rope_cis(rot.inv_freq, float(getattr(rot, "attention_scaling", 1.0)), position_ids)[..., None, :]


def _allowed(valid: torch.Tensor) -> torch.Tensor | None:
    """(B, T) real-token mask -> (B, 1, T, T) bool: key j visible to query i when j <= i and j is real; pad
    queries also see themselves (no empty softmax row). None when nothing is padded (use is_causal)."""
    if bool(valid.all()):
        return None
    return causal_padding_mask(valid)


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
        h, g = _normed(x, layer.input_layernorm, (a.q_proj, a.k_proj, a.v_proj))
        q = _proj(a.q_proj, h, g, perm_q)  # (N, H*D), pairs interleaved
        k = _proj(a.k_proj, h, g, perm_k)  # (N, Hkv*D)
        v = _proj(a.v_proj, h, g)  # (N, Hkv*D)
        # RoPE in fp32 (bf16 under autocast: there is no complex bf16); the attention casts back
        q = torch.view_as_real(torch.view_as_complex(q.float().view(N, H, D // 2, 2)) * cis).view(N, H, D)
        k = torch.view_as_real(torch.view_as_complex(k.float().view(N, Hkv, D // 2, 2)) * cis).view(N, Hkv, D)
        x = x + _proj(a.o_proj, attend(q, k, v.view(N, Hkv, D)))
        h, g = _normed(x, layer.post_attention_layernorm, (m.gate_proj, m.up_proj))
        gate = _proj(m.gate_proj, h, g)  # (N, I)
        up = _proj(m.up_proj, h, g)
        x = x + _proj(m.down_proj, F.silu(gate) * up)
    return x


@_model_precision
def lean_logits(model, x: torch.Tensor, temperature: float = 1.0) -> torch.Tensor:
    """Final norm and lm_head: (..., d) last-layer outputs (e.g. `lean_packed_hidden`'s) -> (..., V) logits /
    temperature (folded into the norm weight); bf16 under bf16 autocast, as the HF head's."""
    base = model.model
    gf = base.norm.weight if temperature == 1.0 else base.norm.weight / temperature
    head = model.lm_head
    hb = head.bias if head.bias is None or temperature == 1.0 else head.bias / temperature
    return F.linear(_rms(x, base.norm.variance_epsilon) * gf, head.weight, hb)


# Keys per query up to which bf16 attention on a CPU runs as explicit matmuls (`_sdpa`) instead of
# F.scaled_dot_product_attention, whose CPU flash kernel in bf16 is 2-3x slower forward + backward at these
# lengths (SmolLM2 shapes, Zen 4: docs/results-archive.md, "Training at the matrix units' speed"); past it the
# kernel wins.
EXPLICIT_ATTENTION_MAX_KEYS = 256


def _sdpa(model, q, k, v, allowed):
    """q (B, H, Tq, D), k/v (B, Hkv, Tk, D), allowed (B, 1, Tq, Tk) bool or None (causal) -> (B, H, Tq, D).

    Under bf16 autocast on a CPU with at most EXPLICIT_ATTENTION_MAX_KEYS keys: explicit matmuls, each kv head's
    G = H / Hkv query heads stacked into one (G*Tq, D) matrix (no repeated k / v), the scores masked with an
    additive -inf bias and soft-maxed in fp32, as the HF eager attention does; else the fused kernel."""
    H, Hkv, D, scale = _dims(model)
    B, _, Tq, _ = q.shape
    Tk = k.shape[2]
    if (q.device.type != "cpu" or Tk > EXPLICIT_ATTENTION_MAX_KEYS
            or _autocast_dtype(q.device) != torch.bfloat16):
        return F.scaled_dot_product_attention(q, k, v, attn_mask=allowed, is_causal=allowed is None, scale=scale,
                                              enable_gqa=Hkv != H)
    G = H // Hkv
    if allowed is None:  # causal: query i (the last Tq of Tk columns) sees keys <= Tk - Tq + i
        allowed = torch.ones(Tq, Tk, dtype=torch.bool, device=q.device).tril_(Tk - Tq)
    else:
        allowed = allowed[:, :, None]  # (B, 1, 1, Tq, Tk): the same for every head
    bias = torch.zeros(allowed.shape, device=q.device).masked_fill_(~allowed, float("-inf"))
    s = (q.reshape(B, Hkv, G * Tq, D) @ k.transpose(-1, -2)).view(B, Hkv, G, Tq, Tk)  # bf16
    p = torch.softmax(s.float() * scale + bias, -1).view(B, Hkv, G * Tq, Tk)  # fp32
    return (p @ v).view(B, H, Tq, D)  # bf16 (autocast casts p)


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


@_model_precision
def lean_forward(model, input_ids: torch.Tensor, attention_mask: torch.Tensor, position_ids: torch.Tensor,
                 logits_to_keep: int = 0, *, positions: slice | None = None,
                 temperature: float = 1.0) -> torch.Tensor:
    """Logits (B, K, V) fp32 of a supported model (see `lean_support(model, T, mode="train")`), differentiable.

    input_ids, attention_mask (0/1), position_ids: (B, T). Columns kept: the last `logits_to_keep`
    (0: all), as HF's argument does, or `positions` (a slice of columns) when given. `temperature`
    divides the logits (folded into the final norm weight)."""
    x = _rows_forward(model, input_ids, attention_mask, position_ids)
    if positions is not None:
        x = x[:, positions]
    elif logits_to_keep:
        x = x[:, -logits_to_keep:]
    return lean_logits(model, x, temperature).float()  # (B, K, V)


@_model_precision
def lean_last_layer(model, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
    """The last decoder layer's outputs (B, T, d) BEFORE the final norm (`lean_logits` / `lean_token_logprobs`
    apply norm and head), positions from the mask; differentiable."""
    return _rows_forward(model, input_ids, attention_mask, position_ids_from_mask(attention_mask))


@_model_precision
def lean_hidden(model, input_ids: torch.Tensor, attention_mask: torch.Tensor,
                position_ids: torch.Tensor | None = None) -> torch.Tensor:
    """The decoder's last hidden states (B, T, d) after the final norm: what `model.model(...).last_hidden_state`
    returns, for a supported `*ForSequenceClassification` (`lean_support(model, T, mode="train", head="score")`) or
    `*ForCausalLM`; differentiable. position_ids default to cumsum(attention_mask) - 1 (clamped at 0)."""
    if position_ids is None:
        position_ids = position_ids_from_mask(attention_mask)
    return final_norm(model, _rows_forward(model, input_ids, attention_mask, position_ids))  # (B, T, d)


def final_norm(model, x: torch.Tensor) -> torch.Tensor:
    """The decoder's final RMSNorm of last-layer outputs x (..., d), e.g. chosen columns of `lean_packed_hidden`'s:
    the last hidden states a head reads."""
    norm = model.model.norm
    return _rms(x, norm.variance_epsilon) * norm.weight


@_model_precision
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


@_model_precision
def lean_forward_shared(model, input_ids: torch.Tensor, attention_mask: torch.Tensor, c: int,
                        first: torch.Tensor, row_of: torch.Tensor, temperature: float = 1.0) -> torch.Tensor:
    """Logits (B, T-c, V) of `lean_hidden_shared` (final norm and lm_head applied)."""
    return lean_logits(model, lean_hidden_shared(model, input_ids, attention_mask, c, first, row_of),
                       temperature).float()


@_model_precision
def lean_hidden_shared(model, input_ids: torch.Tensor, attention_mask: torch.Tensor, c: int,
                       first: torch.Tensor, row_of: torch.Tensor) -> torch.Tensor:
    """The last layer's outputs (B, T-c, d) for columns c-1 .. T-2 (those whose logits predict columns c ..),
    as `lean_forward(..., positions=slice(c - 1, T - 1))` before its head, computed with each distinct prefix (columns < c) run
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
    return torch.cat([last[:, None], x[Np:].view(B, S, -1)[:, :S - 1]], 1)  # (B, S, d): columns c-1 .. T-2


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


def _mm(a: torch.Tensor, b: torch.Tensor, dtype: torch.dtype) -> torch.Tensor:
    """a @ b computed in `dtype`, returned fp32: the chunked head's matmuls under mixed precision, explicit so
    that forward and backward run the same precision whatever autocast state the backward sees."""
    return (a.to(dtype) @ b.to(dtype)).float()


def _head(h: torch.Tensor, weight: torch.Tensor, bias: torch.Tensor | None, dtype: torch.dtype | None):
    """(n, d) -> (n, V) fp32 logits h @ W.T + b, the matmul in `dtype` (None: fp32); weight already in dtype."""
    if dtype is None:
        return F.linear(h, weight, bias)
    x = _mm(h, weight.t(), dtype)
    return x if bias is None else x.add_(bias)


class _ChunkedHeadLogprob(torch.autograd.Function):
    """log p(target) (and the entropy) of logits = h @ W.T + b, `chunk` rows at a time. Saves h, W and the
    (N,) logsumexp, never an (N, V) tensor: the backward recomputes each chunk's logits. Peak memory
    O(chunk * V) instead of O(N * V), for one extra head matmul per chunk. `dtype`: the matmuls' precision
    (bf16 under bf16 autocast, as the HF head's; None: fp32); softmax, log-probs and gradients are fp32."""

    @staticmethod
    def forward(ctx, h, weight, bias, targets, chunk: int, want_entropy: bool, entropy_grad: bool,
                dtype: torch.dtype | None = None):
        N = h.shape[0]
        logp, lse = h.new_empty(N), h.new_empty(N)
        ent = h.new_empty(N) if want_entropy else None
        wd = weight if dtype is None else weight.to(dtype)  # cast once per call
        for s in range(0, N, chunk):
            x = _head(h[s:s + chunk], wd, bias, dtype)  # (n, V) fp32
            lse[s:s + chunk] = torch.logsumexp(x, -1)
            logp[s:s + chunk] = x.gather(-1, targets[s:s + chunk, None]).squeeze(-1) - lse[s:s + chunk]
            if want_entropy:  # H = lse - sum_v p_v * logit_v
                ent[s:s + chunk] = lse[s:s + chunk] - (torch.sub(x, lse[s:s + chunk, None]).exp_() * x).sum(-1)
        if want_entropy and not entropy_grad:
            ctx.mark_non_differentiable(ent)
        ctx.chunk, ctx.entropy_grad, ctx.dtype = chunk, want_entropy and entropy_grad, dtype
        ctx.save_for_backward(h, weight, bias, targets, lse)
        return logp, ent

    @staticmethod
    def backward(ctx, g, g_ent):
        h, weight, bias, targets, lse = ctx.saved_tensors
        chunk, dtype = ctx.chunk, ctx.dtype
        wd = weight if dtype is None else weight.to(dtype)
        gh = torch.empty_like(h) if ctx.needs_input_grad[0] else None
        gw = torch.zeros_like(weight) if ctx.needs_input_grad[1] else None
        gb = torch.zeros_like(bias) if bias is not None and ctx.needs_input_grad[2] else None
        for s in range(0, h.shape[0], chunk):
            hc = h[s:s + chunk]
            x = _head(hc, wd, bias, dtype)  # (n, V) fp32
            p = torch.sub(x, lse[s:s + chunk, None]).exp_()
            gc = g[s:s + chunk]
            grad = p * gc.neg()[:, None]
            grad.scatter_add_(-1, targets[s:s + chunk, None], gc[:, None])
            if ctx.entropy_grad and g_ent is not None:  # dH/dx = -p * (x - E_p[x])
                mean = (p * x).sum(-1, keepdim=True)
                grad.sub_(x.sub_(mean).mul_(p).mul_(g_ent[s:s + chunk, None]))
            if gh is not None:
                gh[s:s + chunk] = grad @ weight if dtype is None else _mm(grad, wd, dtype)
            if gw is not None:
                if dtype is None:
                    gw.addmm_(grad.t(), hc)
                else:
                    gw += _mm(grad.t(), hc, dtype)
            if gb is not None:
                gb += grad.sum(0)
        return gh, gw, gb, None, None, None, None, None


# The (N, V) logits of one call are computed in row chunks (`_ChunkedHeadLogprob`) once they would exceed
# this many elements (64 MiB in fp32): a 49k-vocabulary model's GRPO batch otherwise materialises GBs of
# logits (and its softmax, saved for the backward). Below it the one-pass fused path runs (the presets'
# batches are far below: their numbers do not change).
HEAD_CHUNK_ELEMENTS = 1 << 24


@_model_precision
def lean_token_logprobs(model, x: torch.Tensor, targets: torch.Tensor, temperature: float = 1.0,
                        return_entropy: bool = False, entropy_grad: bool = False,
                        chunk_elements: int | None = None):
    """Last-layer outputs x (..., d) and targets (...) -> (log p(target) (...), entropy (...) | None) under the
    final norm and lm_head at `temperature`: `lean_logits` + `token_logprobs_fused` while the logits are at most
    `chunk_elements` (None: HEAD_CHUNK_ELEMENTS), else the same numbers (fp32 rounding) in row chunks that never
    hold all logits."""
    if chunk_elements is None:
        chunk_elements = HEAD_CHUNK_ELEMENTS
    head = model.lm_head
    V = head.weight.shape[0]
    shape = targets.shape
    N = targets.numel()
    if N * V <= chunk_elements:
        return token_logprobs_fused(lean_logits(model, x, temperature).float(), targets, return_entropy,
                                    entropy_grad)
    base = model.model
    gf = base.norm.weight if temperature == 1.0 else base.norm.weight / temperature
    hb = head.bias if head.bias is None or temperature == 1.0 else head.bias / temperature
    h = (_rms(x, base.norm.variance_epsilon) * gf).reshape(N, -1)
    chunk = max(1, chunk_elements // V)
    dtype = _autocast_dtype(h.device)  # the matmuls' precision; the Function casts explicitly (`_mm`)
    with torch.autocast(h.device.type, enabled=False):
        logp, ent = _ChunkedHeadLogprob.apply(h.float(), head.weight, hb, targets.reshape(-1), chunk,
                                              return_entropy, entropy_grad, dtype)
    return logp.view(shape), (ent.view(shape) if ent is not None else None)


def token_logprobs_fused(logits: torch.Tensor, targets: torch.Tensor, return_entropy: bool = False,
                         entropy_grad: bool = False):
    """`logprobs.token_logprobs` (temperature 1) with a cheaper backward (see module docstring).
    logits (..., V), targets (...) -> (log p(target) (...), entropy (...) | None); the entropy carries
    a gradient only with entropy_grad."""
    shape = targets.shape
    logp, ent = _TargetLogprob.apply(logits.reshape(-1, logits.shape[-1]), targets.reshape(-1), return_entropy,
                                     entropy_grad)
    return logp.view(shape), (ent.view(shape) if ent is not None else None)
