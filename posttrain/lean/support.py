"""What the lean Llama-family paths can run: ONE support predicate and one model-type list, shared by the
rollout engine's decoder (`posttrain.lean.decode`) and the differentiable training forward
(`posttrain.lean.train`), plus the RoPE pieces both use.

`lean_support(model, seq_len, mode=...)` answers (ok, one-line reason). What both paths need: a model type
of `LEAN_MODEL_TYPES` (llama / mistral / qwen2) with a silu MLP, Llama-style RMSNorms, no q/k norms, no
logit soft-capping or scaling, RoPE with static frequencies (default, linear, llama3, yarn: `inv_freq` and
`attention_scaling` read from the module; not dynamic / longrope), a sequence no longer than a sliding
window, weights on one device (train: fp32; decode: fp32, bf16 or fp16), no sharded parameters (FSDP /
DTensor / ZeRO-3 keep only a shard outside the model's own forward) and no accelerate device-map hooks.
Then per mode:
- "decode" (the engine): fp32, bf16 or fp16 weights (half weights run natively in their dtype, see
  `posttrain.lean.decode`); not under torch.autocast, except bf16 autocast on CUDA (accelerate's bf16 mixed
  precision), where the decoder computes in bf16 on bf16 copies of the weights (`decode_autocast`: autocast
  would have run those matmuls in bf16 anyway); a `*ForCausalLM`, or a peft model with plain LoRA adapters on
  Linear layers (the decoder fuses base + deltas into its weights and honours disabled adapters).
- "train" (`sequence_logprobs`, reward / value forwards): the object passed is itself a `*ForCausalLM`
  (head="lm") or `*ForSequenceClassification` (head="score") `PreTrainedModel`, or (head="lm") a peft model with
  plain LoRA adapters without dropout on its Linear layers (the forward adds each adapter's scaling * B(A(h)), so
  gradients reach A and B; the frozen base weights are cast to bf16 once, not per forward); not DDP / FSDP /
  torch.compile-wrapped (a wrapper needs its own forward for gradient sync); plain nn.Linear (or LoRA) projections
  and nn.Embedding, no gradient checkpointing, attention_dropout 0, no module hooks, and not
  fp16 / fp8 mixed precision: under bf16 autocast (the caller's torch.autocast, or accelerate's mixed precision,
  whose patched forward it never calls: `train_autocast`) it runs its matmuls in bf16 as the HF forward would,
  with an fp32 residual stream and fp32 log-probs. `ENABLED = False` (or POSTTRAIN_LEAN_TRAIN=0) turns it off.
Anything else returns the reason, and the caller falls back to the Hugging Face forward.

RoPE as one complex multiply (both paths): the q/k rows of each head are permuted from the half-split
pairing (x_i, x_{i+D/2}) that `rotate_half` uses to interleaved pairs (`rope_pair_order`), so rotating
is `view_as_complex(q) * cis` with `rope_cis`'s factors, computed with the same expression as
`LlamaRotaryEmbedding` (`position * inv_freq`, times `attention_scaling`); q.k is unchanged by permuting
q and k alike, v is untouched.
"""
from __future__ import annotations

import os

import torch
from torch import nn

ENABLED = os.environ.get("POSTTRAIN_LEAN_TRAIN", "1").strip().lower() not in ("0", "false", "no", "off")
LEAN_MODEL_TYPES = ("llama", "mistral", "qwen2")
# Architectures users bring that fall back to the Hugging Face forward, and what the lean paths lack for them
# (README "Model support"; each row is tested on a tiny config: tests/posttrain/lean/test_model_support.py).
FALLBACK_REASONS = {
    "qwen3": "RMSNorms on q and k inside attention",
    "gemma2": "logit soft-capping, (1 + w) norms, scaled embeddings, alternating sliding windows",
    "phi3": "fused qkv and gate/up projections",
    "gpt2": "learned positions, LayerNorm, GELU, fused qkv (not a Llama-family model)",
}
MODES = ("decode", "train")


# ----------------------------------------------------------------------------- projections (plain or LoRA)
def plain_or_lora(m) -> str | None:
    """None when `m` is a plain nn.Linear or a peft LoRA Linear over one (plain LoRA, no variant such as
    DoRA); else why not."""
    if type(m) is nn.Linear:
        return None
    base = getattr(m, "base_layer", None)
    if type(base) is not nn.Linear or not hasattr(m, "lora_A") or not hasattr(m, "get_delta_weight"):
        return f"{type(m).__name__} is neither nn.Linear nor a LoRA Linear"
    if getattr(m, "fan_in_fan_out", False):
        return "LoRA with fan_in_fan_out"
    if any(getattr(m, "lora_variant", {}).get(a) is not None for a in m.active_adapters):
        return "a LoRA variant (DoRA, ...) is active"
    return None


def _lora_train(m) -> str | None:
    """None when the training forward can run `m`: a plain nn.Linear, or a plain LoRA Linear whose active adapters
    have no dropout (the lean path draws no dropout masks); else why not."""
    why = plain_or_lora(m)
    if why is None and type(m) is not nn.Linear:
        if any(type(m.lora_dropout[a]) is not nn.Identity for a in m.active_adapters if a in m.lora_dropout):
            return "LoRA dropout (the lean training path has none)"
    return why


def _plain(m) -> str | None:
    return None if type(m) is nn.Linear else f"{type(m).__name__} is not a plain nn.Linear"


def effective_weight(m) -> torch.Tensor:
    """The effective (out, in) weight: the base weight plus each active, enabled, unmerged LoRA delta."""
    if type(m) is nn.Linear:
        return m.weight.detach()
    w = m.base_layer.weight.detach()
    if not m.disable_adapters and not m.merged:
        for a in m.active_adapters:
            if a in m.lora_A:
                w = w + m.get_delta_weight(a).detach().to(w.dtype)
    return w


def linear_bias(m) -> torch.Tensor | None:
    lin = m if type(m) is nn.Linear else m.base_layer
    return None if lin.bias is None else lin.bias.detach()


# ----------------------------------------------------------------------------- RoPE
def rope_pair_order(heads: int, D: int) -> torch.Tensor:
    """(heads * D,) row order that turns each head's half-split RoPE pairs (i, i + D/2) into interleaved pairs."""
    half = torch.arange(D // 2)
    one = torch.stack([half, half + D // 2], 1).reshape(-1)  # (D,)
    return (one[None] + D * torch.arange(heads)[:, None]).reshape(-1)


def rope_cis(inv_freq: torch.Tensor, attention_scaling: float, positions: torch.Tensor) -> torch.Tensor:
    """(...) positions -> (..., D/2) complex RoPE factors attention_scaling * (cos + i sin), with
    LlamaRotaryEmbedding's expression (positions * inv_freq)."""
    freqs = positions[..., None].float() * inv_freq.float()  # (..., D/2)
    return torch.complex(freqs.cos() * attention_scaling, freqs.sin() * attention_scaling)


# ----------------------------------------------------------------------------- what neither path implements
HALF_DTYPES = (torch.bfloat16, torch.float16)
DECODE_DTYPES = (torch.float32,) + HALF_DTYPES


def decode_autocast(device) -> tuple[torch.dtype | None, str | None]:
    """The engine decoder under torch.autocast, as (compute dtype or None when autocast is off, why it cannot run
    or None). bf16 autocast on CUDA (accelerate's bf16 mixed precision): the decoder computes in bf16 on bf16
    copies of fp32 weights, as autocast would have run its matmuls (the residual stream is bf16 too, as in a
    bf16 model; fp32 where `posttrain.lean.decode` says). Any other autocast (fp16, or on CPU, where bf16
    elementwise work is slow and `rollout.dtype` chooses the precision): the caller falls back to the model's
    own forward, which follows the autocast policy. (The training forward runs under bf16 autocast:
    `train_autocast`.)"""
    kind = torch.device(device).type
    try:
        on = torch.is_autocast_enabled(kind)
    except (TypeError, RuntimeError):  # a device type autocast does not know
        on = False
    if not on:
        return None, None
    dtype = torch.get_autocast_dtype(kind)
    if kind == "cuda" and dtype == torch.bfloat16:
        return torch.bfloat16, None
    return None, f"torch.autocast to {dtype} is on for {kind} (mixed precision)"


def autocast_problem(device) -> str | None:
    """Why the engine's lean decoder cannot run under the autocast state of `device`, or None (`decode_autocast`)."""
    return decode_autocast(device)[1]


def _accelerate_mixed_precision() -> str | None:
    """The process's accelerate mixed precision ("no", "bf16", "fp16", "fp8"), or None while no Accelerator
    exists (reading AcceleratorState() before then would create one)."""
    try:
        from accelerate.state import AcceleratorState
    except ImportError:
        return None
    if not getattr(AcceleratorState, "_shared_state", None):
        return None
    return str(AcceleratorState().mixed_precision)


def train_autocast(model, device) -> tuple[torch.dtype | None, str | None]:
    """The autocast the lean training forward runs under, as (dtype or None for fp32, why it cannot run or None).

    Mixed precision reaches a model two ways, and the lean forward honours both: the caller's torch.autocast
    (on for `device`'s type), or accelerate's (Accelerator.prepare under mixed precision keeps the model's own
    forward in `_original_forward` and wraps `forward` in autocast; the lean path never calls `forward`, so it
    enters the same bf16 autocast itself). bf16 only: fp16 autocast needs loss scaling and fp8 its own kernels,
    so those fall back to the model's forward."""
    kind = torch.device(device).type
    try:
        on = torch.is_autocast_enabled(kind)
    except (TypeError, RuntimeError):  # a device type autocast does not know
        on = False
    if on:
        dtype = torch.get_autocast_dtype(kind)
        if dtype != torch.bfloat16:
            return None, f"torch.autocast to {dtype} on {kind} (the lean training forward runs bf16 autocast only)"
        return torch.bfloat16, None
    if "_original_forward" in vars(model):  # accelerate's mixed precision patched forward (autocast inside it)
        mp = _accelerate_mixed_precision()
        if mp == "bf16":
            return torch.bfloat16, None
        return None, (f"accelerate mixed precision {mp!r}: the model's autocast forward is used (the lean path "
                      "runs bf16 only)")
    return None, None


def sharded_problem(model) -> str | None:
    """Why the lean paths cannot read `model`'s weights as whole tensors, or None: FSDP (1 or 2) or tensor
    parallelism (modules wrapped in FullyShardedDataParallel, DTensor parameters) and DeepSpeed ZeRO-3
    (partitioned parameters) keep only a shard of each weight outside the model's own forward."""
    for m in model.modules():
        if "FullyShardedDataParallel" in type(m).__name__ or type(m).__name__.startswith("FSDP"):
            return f"FSDP-sharded module ({type(m).__name__})"
    try:
        from torch.distributed.tensor import DTensor
    except ImportError:  # torch built without distributed
        DTensor = ()
    for p in model.parameters():
        if isinstance(p, DTensor) or type(p).__name__ == "DTensor":
            return "DTensor (FSDP2 / tensor-parallel) parameters"
        if hasattr(p, "ds_id"):
            return "DeepSpeed ZeRO-3 partitioned parameters"
    return None


def llama_family_problem(cfg, base) -> str | None:
    """What in a Llama-family config / decoder the lean paths (decode and train) do not
    implement: another activation, logit soft-capping or scaling, RoPE without static frequencies; None if nothing."""
    if getattr(cfg, "hidden_act", None) != "silu":
        return f"hidden_act {getattr(cfg, 'hidden_act', None)!r} (the lean path implements silu)"
    for attr in ("final_logit_softcapping", "attn_logit_softcapping", "logit_scale"):
        if getattr(cfg, attr, None) not in (None, 1.0):
            return f"config.{attr} is set"
    rot = getattr(base, "rotary_emb", None)
    if rot is None or not hasattr(rot, "inv_freq"):
        return "no model.rotary_emb with inv_freq"
    rope_type = str(getattr(rot, "rope_type", "default"))
    if "dynamic" in rope_type or rope_type == "longrope":
        return f"rope_type {rope_type!r} changes with sequence length"
    return None


def lean_support(model, seq_len: int | None = None, *, mode: str = "decode", head: str = "lm") -> tuple[bool, str]:
    """Whether a lean path can replace `model`'s own forward for sequences of up to `seq_len` tokens (None:
    any length), and why (not). mode "decode": the rollout engine's `LeanLlama`; "train": the differentiable
    forward, head "lm" (`lean_forward`, logits) or "score" (`lean_hidden`, a reward / value model)."""
    if mode not in MODES or head not in ("lm", "score") or (mode == "decode" and head != "lm"):
        raise ValueError(f"lean_support: mode must be one of {MODES} and head 'lm' or 'score' (train only), "
                         f"got {mode!r}, {head!r}")
    train = mode == "train"
    outer = model  # accelerate's mixed precision patches the outermost object (`train_autocast`)
    if train and not ENABLED:
        return False, "disabled (posttrain.lean.support.ENABLED / POSTTRAIN_LEAN_TRAIN=0)"
    lora = hasattr(model, "peft_config") and hasattr(model, "get_base_model")
    if hasattr(model, "peft_config") and not lora:
        return False, "peft-wrapped model of unknown shape"
    if lora:
        if train and head != "lm":
            return False, "a peft reward / value model (the lean training path runs LoRA on causal LMs only)"
        types_ = {getattr(c, "peft_type", None) for c in model.peft_config.values()}
        if {str(t).split(".")[-1] for t in types_} != {"LORA"}:
            return False, f"peft adapters of type(s) {sorted(map(str, types_))} (the lean path fuses LoRA only)"
        model = model.get_base_model()
    if train:
        from transformers import PreTrainedModel

        kind = {"lm": "ForCausalLM", "score": "ForSequenceClassification"}[head]
        if not isinstance(model, PreTrainedModel) or not type(model).__name__.endswith(kind):
            return False, f"{type(model).__name__} is not a *{kind} PreTrainedModel (a wrapper runs its own forward)"
    cfg = getattr(model, "config", None)
    if cfg is None:
        return False, "model has no config"
    mt = getattr(cfg, "model_type", None)
    if mt not in LEAN_MODEL_TYPES:
        known = f": {FALLBACK_REASONS[mt]}" if mt in FALLBACK_REASONS else ""
        return False, f"model_type {mt!r} is not one of {LEAN_MODEL_TYPES}{known}"
    linear_problem = (_lora_train if lora else _plain) if train else plain_or_lora
    out_name = "lm_head" if head == "lm" else "score"
    base, out = getattr(model, "model", None), getattr(model, out_name, None)
    if base is None or out is None or linear_problem(out) is not None:
        return False, f"no plain {out_name} / .model"
    if train:
        if any(getattr(mod, "gradient_checkpointing", False) is True for mod in model.modules()):
            return False, "gradient checkpointing is enabled"
        if float(getattr(cfg, "attention_dropout", 0.0) or 0.0) != 0.0:
            return False, f"attention_dropout {cfg.attention_dropout} (the lean path has no dropout)"
        emb = getattr(base, "embed_tokens", None)
        if type(emb) is not nn.Embedding:
            return False, f"no plain nn.Linear {out_name} / nn.Embedding model.embed_tokens"
        if emb.max_norm is not None or emb.scale_grad_by_freq or emb.sparse:
            return False, "embedding with max_norm / scale_grad_by_freq / sparse"
        if any(p.dtype != torch.float32 for p in model.parameters()):
            return False, "not every parameter is fp32"
    elif effective_weight(out).dtype not in DECODE_DTYPES:
        return False, f"dtype {effective_weight(out).dtype} (the lean decoder runs fp32, bf16 or fp16 weights)"
    devices = {p.device for p in model.parameters()}
    if len(devices) != 1 or next(iter(devices)).type == "meta":
        return False, f"weights on several devices or on meta ({sorted(str(d) for d in devices)})"
    device = next(iter(devices))
    amp = None
    if train:
        amp, why = train_autocast(outer, device)
    else:
        why = autocast_problem(device)
    why = why or llama_family_problem(cfg, base)
    if why:
        return False, why
    window = getattr(cfg, "sliding_window", None)
    if window is not None and getattr(cfg, "use_sliding_window", True) is not False and \
            (seq_len is None or seq_len > window):
        return False, f"sequence length {seq_len} may exceed the sliding window {window}"
    for mod in model.modules():
        if hasattr(mod, "_hf_hook"):
            return False, "accelerate device-map hooks (offloaded or dispatched weights)"
        if train and (mod._forward_hooks or mod._forward_pre_hooks):
            return False, f"a forward hook on {type(mod).__name__} (the lean path would skip it)"
    why = sharded_problem(model)
    if why:
        return False, why
    for layer in base.layers[:cfg.num_hidden_layers]:
        att, mlp = getattr(layer, "self_attn", None), getattr(layer, "mlp", None)
        try:
            lins = [att.q_proj, att.k_proj, att.v_proj, att.o_proj, mlp.gate_proj, mlp.up_proj, mlp.down_proj]
        except AttributeError:
            return False, "a decoder layer without the Llama projections"
        why = next((w for w in map(linear_problem, lins) if w is not None), None)
        if why is not None:
            return False, f"a layer projection: {why} (quantised or another adapter)"
        for norm in (layer.input_layernorm, layer.post_attention_layernorm):
            if not type(norm).__name__.endswith("RMSNorm") or not hasattr(norm, "variance_epsilon"):
                return False, "a layer norm is not a Llama-style RMSNorm"
        if hasattr(att, "q_norm") or hasattr(att, "k_norm"):
            return False, "q/k norms are not implemented in the lean path"
    if not hasattr(getattr(base, "norm", None), "variance_epsilon"):
        return False, "the final norm is not a Llama-style RMSNorm"
    if train:
        return True, f"lean training forward ({mt}{', LoRA' if lora else ''}{', bf16 autocast' if amp is not None else ''})"
    half = effective_weight(out).dtype
    prec = f", {str(half).removeprefix('torch.')} weights" if half in HALF_DTYPES else ""
    if decode_autocast(device)[0] is not None:
        prec += ", bf16 autocast"
    return True, f"lean Llama-family path ({mt}{', LoRA fused' if lora else ''}{prec})"
