"""Tiny Llama-family models built from nothing, a tokenizer trained locally, and any local HF model.

Nothing here downloads anything. A preset is a `transformers.LlamaConfig` with random
init; the tokenizer is a byte-level BPE trained with `tokenizers` on the task's own
corpus and wrapped as a `PreTrainedTokenizerFast` with pad and eos tokens. Both are
saved with `save_pretrained` and load back with `AutoModelForCausalLM` / `AutoTokenizer`.

CPU runs use fp32 weights. `model.dtype` (float32 | bfloat16 | float16) sets the weights dtype of every
model a stage loads with `load_model`; the half dtypes are refused without a GPU (`dtype_problem`): they
train without an fp32 master copy, and many CPUs have no bf16 matmul units (where a CPU has them, bf16
autocast over fp32 weights is the fast path; RESULTS.md). With bfloat16 the trained weights and the optimizer run
in bf16 (no fp32 master copy); for fp32 weights with bf16 compute keep float32 and launch with
`run.mixed_precision=bf16` (or `auto`). Reward-model scoring (`posttrain.scoring`) stays fp32.

A local model directory (`model.path`) is any causal LM `AutoModelForCausalLM` loads; its chat
template is applied to prompts as `posttrain.chat` describes. `model.gradient_checkpointing`
recomputes activations in the backward pass of the trained model (`maybe_lora`).

Presets (parameter counts with the default 1024-token vocabulary, tied embeddings):
- `tiny`  : d=128, 4 layers, 4 heads, MLP 512   -> ~1.2M parameters (tests, default recipes)
- `small` : d=384, 6 layers, 6 heads, MLP 1024  -> ~11M parameters (the seed's E6 asks 10-100M)
- `base`  : d=512, 8 layers, 8 heads, MLP 1408  -> ~26M parameters
"""
from __future__ import annotations

import inspect
import os
import warnings
from pathlib import Path
from typing import Iterable

import torch

from posttrain.errors import ModelError, TrainingError
from posttrain.runtime import DTYPES, dtype_problem

PAD_TOKEN = "<|pad|>"
EOS_TOKEN = "<|eos|>"
BOS_TOKEN = "<|bos|>"

PRESETS: dict[str, dict] = {
    "tiny": dict(hidden_size=128, intermediate_size=512, num_hidden_layers=4, num_attention_heads=4,
                 num_key_value_heads=4, max_position_embeddings=512),
    "small": dict(hidden_size=384, intermediate_size=1024, num_hidden_layers=6, num_attention_heads=6,
                  num_key_value_heads=6, max_position_embeddings=512),
    "base": dict(hidden_size=512, intermediate_size=1408, num_hidden_layers=8, num_attention_heads=8,
                 num_key_value_heads=8, max_position_embeddings=1024),
}




def train_tokenizer(texts: Iterable[str], vocab_size: int = 1024, model_max_length: int = 512,
                    split_digits: bool = False, chat: bool = False):
    """Train a byte-level BPE tokenizer on `texts` and wrap it as a PreTrainedTokenizerFast.

    Byte-level means any input string round-trips (no unknown token). Special tokens:
    pad (id 0), eos (id 1), bos (id 2). No BOS is added automatically: prompts are plain text
    and completions end with eos, which the trainers append.

    `split_digits`: every digit is its own token (a `Digits(individual_digits=True)` pre-tokenizer
    before the byte-level one, as Llama and DeepSeek tokenizers do), so BPE never merges "47" or
    " 85" into one token. Arithmetic tasks need it: a tiny model learns digit-by-digit column
    arithmetic from single-digit tokens, not from ~1000 opaque number tokens.

    `chat`: the role markers `<|system|>`, `<|user|>`, `<|assistant|>`, `<|tool|>` are special tokens too (ids
    3-6) and the tokenizer carries `posttrain.chat.PRESET_CHAT_TEMPLATE`, for conversational data. Without it
    the vocabulary is exactly what it was before chat templates existed.
    """
    from posttrain.chat import PRESET_CHAT_TEMPLATE, ROLE_TOKENS
    from tokenizers import Tokenizer, decoders, models, pre_tokenizers, trainers
    from transformers import PreTrainedTokenizerFast

    tok = Tokenizer(models.BPE())
    byte_level = pre_tokenizers.ByteLevel(add_prefix_space=False)
    tok.pre_tokenizer = pre_tokenizers.Sequence([pre_tokenizers.Digits(individual_digits=True), byte_level]) \
        if split_digits else byte_level
    tok.decoder = decoders.ByteLevel()
    trainer = trainers.BpeTrainer(
        vocab_size=vocab_size,
        min_frequency=2,
        special_tokens=[PAD_TOKEN, EOS_TOKEN, BOS_TOKEN, *(ROLE_TOKENS if chat else ())],
        initial_alphabet=pre_tokenizers.ByteLevel.alphabet(),
        show_progress=False,
    )
    tok.train_from_iterator(list(texts), trainer=trainer)
    wrapped = PreTrainedTokenizerFast(
        tokenizer_object=tok,
        pad_token=PAD_TOKEN,
        eos_token=EOS_TOKEN,
        bos_token=BOS_TOKEN,
        model_max_length=model_max_length,
        padding_side="left",
        clean_up_tokenization_spaces=False,
    )
    if chat:
        wrapped.chat_template = PRESET_CHAT_TEMPLATE
    return wrapped


def build_model(preset: str, tokenizer, seed: int = 0, dtype: torch.dtype = torch.float32):
    """A randomly initialised LlamaForCausalLM for `preset`, sized to `tokenizer`'s vocabulary."""
    from transformers import LlamaConfig, LlamaForCausalLM

    if preset not in PRESETS:
        raise ModelError(f"unknown model preset {preset!r}; choose one of {sorted(PRESETS)} or give a model directory")
    cfg = LlamaConfig(
        vocab_size=len(tokenizer),
        tie_word_embeddings=True,
        pad_token_id=tokenizer.pad_token_id,
        eos_token_id=tokenizer.eos_token_id,
        bos_token_id=tokenizer.bos_token_id,
        attention_bias=False,
        mlp_bias=False,
        **PRESETS[preset],
    )
    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = LlamaForCausalLM(cfg)
    return model.to(dtype)


def is_model_dir(path: str | os.PathLike) -> bool:
    p = Path(path)
    return p.is_dir() and (p / "config.json").is_file()


def load_tokenizer(path: str | os.PathLike, model_cfg=None):
    """The tokenizer of a local model directory, left-padding, pad = eos when it has no pad token.

    `model_cfg` (a ModelConfig): apply its `chat_template` / `system_prompt` (see `posttrain.chat`);
    None leaves the directory's chat template as it is (the "auto" behaviour)."""
    from transformers import AutoTokenizer

    p = Path(path)
    if not p.is_dir():
        raise ModelError(f"model path {str(p)!r} does not exist; give a local Hugging Face model directory or a preset name ({', '.join(PRESETS)})")
    tok = AutoTokenizer.from_pretrained(str(p))
    if tok.eos_token_id is None:
        raise ModelError(f"tokenizer in {str(p)!r} has no eos token; set one in its tokenizer_config.json")
    if tok.pad_token_id is None:
        # Common for real checkpoints (e.g. Llama): padding is masked anyway, so reuse eos.
        tok.pad_token = tok.eos_token
    tok.padding_side = "left"
    if model_cfg is not None:
        from posttrain import chat

        chat.configure(tok, model_cfg.chat_template, model_cfg.system_prompt, str(p))
    return tok


def resolve_dtype(dtype: str | torch.dtype | None, device: str | torch.device = "cpu") -> torch.dtype:
    """A torch dtype from a `model.dtype` name (checked by `dtype_problem`) or a torch dtype; None: fp32 on
    CPU, bf16 on an accelerator."""
    if dtype is None:
        return torch.float32 if torch.device(device).type == "cpu" else torch.bfloat16
    if isinstance(dtype, torch.dtype):
        return dtype
    if dtype not in DTYPES:
        raise ModelError(f"model.dtype {dtype!r}: choose one of {', '.join(DTYPES)}")
    problem = dtype_problem(dtype)
    if problem:
        raise ModelError(problem)
    return DTYPES[dtype]


def load_model(path: str | os.PathLike, dtype: str | torch.dtype | None = None, device: str | torch.device = "cpu"):
    """Load a causal LM from a local directory (never from a hub), its weights in `dtype` (a `model.dtype`
    name or a torch dtype; None: fp32 on CPU, bf16 on an accelerator)."""
    from transformers import AutoModelForCausalLM

    p = Path(path)
    if not is_model_dir(p):
        what = "does not exist" if not p.exists() else "has no config.json (not a Hugging Face model directory)"
        raise ModelError(f"model path {str(p)!r} {what}; give a local Hugging Face model directory or a preset name ({', '.join(PRESETS)})")
    model = AutoModelForCausalLM.from_pretrained(str(p), dtype=resolve_dtype(dtype, device), local_files_only=True)
    return model.to(device)


def maybe_lora(res, model, say=print, task_type: str = "CAUSAL_LM"):
    """The model a stage trains, as the resolved config asks: gradient checkpointing when
    `model.gradient_checkpointing`, then `apply_lora` when this stage uses LoRA (`res.use_lora`)."""
    if res.model.gradient_checkpointing:
        enable_gradient_checkpointing(model)
    if not res.use_lora:
        return model
    model = apply_lora(model, res.lora, task_type)
    trainable = sum(p.numel() for p in model.parameters() if p.requires_grad)
    say(f"[{res.stage}] LoRA r={res.lora.r} alpha={res.lora.alpha} on {', '.join(res.lora.target_modules)}: "
        f"{trainable / 1e3:.1f}k trainable of {count_parameters(model) / 1e6:.2f}M parameters")
    return model


def enable_gradient_checkpointing(model) -> None:
    """Recompute each decoder layer's activations in the backward pass instead of keeping them.

    Non-reentrant `torch.utils.checkpoint` (transformers' default), and the embedding output requires
    grad (`enable_input_require_grads`) so gradients reach LoRA adapters behind frozen layers. Only in
    training mode: the rollout engine's and the evaluations' forwards run in eval mode, unchanged."""
    if not getattr(model, "supports_gradient_checkpointing", False):
        raise ModelError(f"model.gradient_checkpointing: {type(model).__name__} does not support it; "
                         "set model.gradient_checkpointing=false")
    if hasattr(model, "activation_checkpointing_enable"):  # transformers 5: it also makes the inputs require grad
        model.activation_checkpointing_enable({"use_reentrant": False})
    else:  # older transformers (the name warns in 5)
        model.gradient_checkpointing_enable(gradient_checkpointing_kwargs={"use_reentrant": False})
        model.enable_input_require_grads()


def apply_lora(model, lora_cfg, task_type: str = "CAUSAL_LM"):
    """Wrap `model` with trainable LoRA adapters (peft); every base weight is frozen.

    The adapters start at zero (B = 0), so the wrapped model computes exactly the base model until the
    first update; with the adapters disabled (`reference_view`) it is the base model, the reference of
    DPO / PPO / GRPO, and no second copy of the weights is needed."""
    from peft import LoraConfig, get_peft_model

    target = lora_cfg.target_modules
    config = LoraConfig(r=lora_cfg.r, lora_alpha=lora_cfg.alpha, lora_dropout=lora_cfg.dropout,
                        target_modules=target[0] if target == ["all-linear"] else list(target),
                        task_type=task_type, bias="none")
    try:
        with warnings.catch_warnings():  # peft 0.21 asks transformers 5 a deprecated property; nothing to act on
            warnings.filterwarnings("ignore", message=".*is_gradient_checkpointing.*", category=FutureWarning)
            return get_peft_model(model, config)
    except ValueError as e:  # e.g. a target module name the model does not have
        raise ModelError(f"lora.target_modules {list(target)}: {e}") from None


def is_lora(model) -> bool:
    return hasattr(model, "peft_config") and hasattr(model, "disable_adapter")


class reference_view(torch.nn.Module):
    """The base model inside a LoRA-wrapped model: calls run with the adapters disabled.

    A drop-in reference for `posttrain.logprobs` (it only calls the model and reads its parameters'
    device). Shares every weight with the policy: no copy."""

    def __init__(self, peft_model):
        super().__init__()
        self.inner = peft_model

    def forward(self, *args, **kwargs):
        with self.inner.disable_adapter():
            return self.inner(*args, **kwargs)

    @property
    def config(self):
        return self.inner.config

    def get_base_model(self):  # lets posttrain.logprobs inspect the real forward's arguments
        return self.inner.get_base_model()


def tensor_bytes(obj) -> int:
    """Bytes of the tensors in a nested dict / list / tuple: what `torch.save` or safetensors writes of them."""
    if isinstance(obj, torch.Tensor):
        return obj.numel() * obj.element_size()
    if isinstance(obj, dict):
        return sum(tensor_bytes(v) for v in obj.values())
    if isinstance(obj, (list, tuple)):
        return sum(tensor_bytes(v) for v in obj)
    return 0


def out_of_disk(error: BaseException, partial: str | os.PathLike, size: int) -> bool:
    """Whether a write of about `size` bytes that raised `error`, having written `partial` (a file or directory)
    so far, failed for want of disk. torch.save raises a bare RuntimeError on a full disk and safetensors its own
    error ("os error 28"): ENOSPC, that message, or bytes written plus bytes still free short of `size`."""
    import errno
    import shutil

    if (isinstance(error, OSError) and error.errno == errno.ENOSPC) or "No space left on device" in str(error):
        return True
    partial = Path(partial)
    files = [partial] if partial.is_file() else list(partial.rglob("*")) if partial.is_dir() else []
    written = sum(f.stat().st_size for f in files if f.is_file())
    return written + shutil.disk_usage(partial.parent).free < size


def save_model(model, tokenizer, out_dir: str | os.PathLike, state_dict: dict | None = None) -> Path:
    """Save model + tokenizer as a Hugging Face directory, atomically (write to a temp dir, then rename); a disk
    that fills during the write raises a TrainingError, the temp dir removed and `out_dir` as it was.

    A LoRA-wrapped model is saved merged (base + adapters) as a plain Hugging Face model; the model
    passed in keeps its adapters (the merge is made on a copy of the weights). `state_dict`: the full weights
    to write instead of the model's own parameters, for a sharded model (FSDP / ZeRO-3), whose parameters hold only
    a shard (`loop.full_state_dict` gathers them)."""
    if state_dict is not None and is_lora(model):
        raise NotImplementedError("save_model: a sharded (FSDP / ZeRO-3) LoRA model cannot be saved merged yet; "
                                  "train LoRA without sharding (its weights are small) or full weights under FSDP")
    if is_lora(model):
        import copy

        model = copy.deepcopy(model).merge_and_unload()
    out = Path(out_dir)
    tmp = out.with_name(out.name + ".tmp")
    if tmp.exists():
        import shutil

        shutil.rmtree(tmp)
    tmp.mkdir(parents=True)
    try:
        model.save_pretrained(str(tmp), safe_serialization=True,
                              **({"state_dict": state_dict} if state_dict is not None else {}))
        tokenizer.save_pretrained(str(tmp))
    except Exception as e:
        import shutil

        full = out_of_disk(e, tmp, tensor_bytes(state_dict if state_dict is not None else model.state_dict()))
        shutil.rmtree(tmp, ignore_errors=True)
        if not full:
            raise
        raise TrainingError(f"the disk filled while saving the model to {out} (its temp dir removed"
                            f"{', the one there before kept' if out.exists() else ''}): free some space and rerun "
                            f"with resume=true, which writes it again from the last checkpoint") from e
    if out.exists():
        import shutil

        old = out.with_name(out.name + ".old")
        if old.exists():
            shutil.rmtree(old)
        out.rename(old)
        tmp.rename(out)
        shutil.rmtree(old)
    else:
        tmp.rename(out)
    return out


# run.micro_batch_tokens=0 sizes micro-batches so that their activations take about this much memory.
ACTIVATION_BUDGET_BYTES = 2 * 2**30


def activation_bytes_per_token(config) -> int:
    """Rough bytes one token's activations keep for the backward pass of a decoder-only LM in fp32: per layer
    ~10 hidden-size vectors (norms, q, attention output, projections, residuals), 3 key/value-size ones and
    4 MLP-size ones (gate, up, activation, product), plus the logits and their softmax (the HF forward's head;
    the lean path chunks it). Measured against the HF Llama forward's saved tensors: RESULTS.md, "Memory"."""
    d = config.hidden_size
    heads = config.num_attention_heads
    kv = (getattr(config, "num_key_value_heads", None) or heads) * (getattr(config, "head_dim", None) or d // heads)
    mlp = getattr(config, "intermediate_size", None) or 4 * d
    per_layer = 10 * d + 3 * kv + 4 * mlp
    return 4 * (config.num_hidden_layers * per_layer + 2 * config.vocab_size)


def token_budget(setting: int, model) -> int:
    """Padded tokens per micro-batch: `run.micro_batch_tokens` when set, else those whose activations take
    ACTIVATION_BUDGET_BYTES for `model` (at least 256)."""
    if setting:
        return int(setting)
    return max(256, ACTIVATION_BUDGET_BYTES // activation_bytes_per_token(unwrap_model(model).config))


def count_parameters(model) -> int:
    return sum(p.numel() for p in model.parameters())


def bootstrap(preset: str, corpus: Iterable[str], out_dir: str | os.PathLike, *, vocab_size: int = 1024,
              seed: int = 0, max_length: int = 512, split_digits: bool = False, chat: bool = False):
    """Build a tokenizer on `corpus` (with a chat template when `chat`) and a random `preset` model; save both to
    `out_dir`; return (model, tokenizer)."""
    tokenizer = train_tokenizer(corpus, vocab_size=vocab_size, model_max_length=max_length,
                                split_digits=split_digits, chat=chat)
    model = build_model(preset, tokenizer, seed=seed)
    save_model(model, tokenizer, out_dir)
    return model, tokenizer


# ----------------------------------------------------------------------------- model plumbing
def unwrap_model(model):
    """The HF model inside DDP / accelerate / torch.compile wrappers (peft models are returned as they are)."""
    seen = set()
    while id(model) not in seen:
        seen.add(id(model))
        if hasattr(model, "_orig_mod"):
            model = model._orig_mod
        elif isinstance(model, (torch.nn.parallel.DistributedDataParallel, torch.nn.DataParallel)) or (
            isinstance(getattr(model, "module", None), torch.nn.Module) and not hasattr(model, "config")
        ):
            model = model.module
    return model


def accepts(model, name: str) -> bool:
    """Whether the real forward inside `model`'s wrappers (DDP, peft, torch.compile) takes the argument `name`."""
    m = unwrap_model(model)
    if hasattr(m, "get_base_model"):  # peft
        m = m.get_base_model()
    try:
        return name in inspect.signature(m.forward).parameters
    except (TypeError, ValueError):
        return False


def position_ids_from_mask(attention_mask: torch.Tensor) -> torch.Tensor:
    """(B, T) 0/1 mask -> (B, T) positions counting real tokens only (pads get 0)."""
    return (attention_mask.long().cumsum(-1) - 1).clamp_(min=0)


def causal_padding_mask(valid: torch.Tensor) -> torch.Tensor:
    """(B, T) real-token mask -> (B, 1, T, T) bool attention mask: key j visible to query i when j <= i and j is
    real, and every query sees itself, so no attention row is empty. A left-padded row's leading pad queries would
    otherwise see no key at all; fully masked attention rows are where attention kernels differ (NaN outputs or
    gradients in some fused kernels). The lean forwards mask this way; a Hugging Face forward given it computes
    the real tokens' numbers of the plain 2D mask exactly (tests/posttrain/test_logprobs.py)."""
    T = valid.shape[1]
    causal = torch.ones(T, T, dtype=torch.bool, device=valid.device).tril_()
    return (causal & (valid.bool()[:, None, :] | torch.eye(T, dtype=torch.bool, device=valid.device)))[:, None]


def plain_causal_attention(model) -> bool:
    """Every layer of `model` attends causally over the whole sequence (no sliding windows, alternating layer
    types or attention chunks), so one 4D mask describes them all."""
    cfg = getattr(unwrap_model(model), "config", None)
    if cfg is None:
        return False
    if getattr(cfg, "sliding_window", None) and getattr(cfg, "use_sliding_window", True) is not False:
        return False
    if any(t != "full_attention" for t in (getattr(cfg, "layer_types", None) or ())):
        return False
    return not getattr(cfg, "attention_chunk_size", None)


def hf_attention_mask(attention_mask: torch.Tensor, model) -> torch.Tensor:
    """The mask a Hugging Face forward of `model` gets for a (B, T) 0/1 padding mask: `causal_padding_mask` when a
    row starts with padding (left padding: the rollout layout) and the model attends plainly causally
    (`plain_causal_attention`: a 4D mask given to a sliding-window model would replace its windows), else the 2D
    mask itself (which also keeps SDPA's causal fast paths). One host read of the first column."""
    if plain_causal_attention(model) and bool((attention_mask[:, 0] == 0).any()):
        return causal_padding_mask(attention_mask)
    return attention_mask


def model_device(model) -> torch.device:
    for p in model.parameters():
        return p.device
    return torch.device("cpu")


def weights_signature(model) -> tuple:
    """Changes whenever a parameter is replaced or updated in place (optimizer steps bump `_version`), or
    LoRA adapters are switched on / off, merged or swapped: how the rollout engine and the vLLM backend see
    that a model changed since they last read its weights."""
    sig = tuple((p.data_ptr(), p._version) for p in model.parameters())
    if hasattr(model, "peft_config"):
        sig += tuple((m.disable_adapters, m.merged, tuple(m.active_adapters)) for m in model.modules()
                     if hasattr(m, "lora_A"))
    return sig


def load_reference(res, policy, model_dir, device):
    """The frozen reference of DPO / PPO / GRPO: with LoRA (`res.use_lora`) the policy with its adapters
    switched off (`reference_view`, no copy of the weights), else a second copy of `model_dir` in eval mode."""
    if res.use_lora:
        return reference_view(policy)
    return load_model(model_dir, res.model.dtype, device=device).eval().requires_grad_(False)


def load_reward_init(sft_dir, pad_id: int, seed: int, device, dtype: str | torch.dtype = torch.float32):
    """The SFT transformer under a new one-output head (`AutoModelForSequenceClassification`, seeded init):
    the reward model's start, and PPO's value model under value_init=policy; weights in `dtype` (a
    `model.dtype` name or a torch dtype)."""
    from transformers import AutoModelForSequenceClassification

    with torch.random.fork_rng(devices=[]):
        torch.manual_seed(seed)
        model = AutoModelForSequenceClassification.from_pretrained(str(sft_dir), num_labels=1,
                                                                   dtype=resolve_dtype(dtype), local_files_only=True)
    model.config.pad_token_id = pad_id
    return model.to(device)
