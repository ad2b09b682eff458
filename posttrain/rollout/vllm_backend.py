"""Optional vLLM generation backend (GPU): `rollout.backend=vllm` makes every `generate` call of every stage
sample through a vLLM engine instead of the built-in one. Same `Rollout` records, same call.

CPU:        not available (vLLM needs a CUDA GPU); the built-in engine is the default everywhere.
GPU:        pip install vllm
            posttrain grpo --recipe tiny-countdown model.path=/path/to/hf-model rollout.backend=vllm \\
                rollout.vllm_gpu_memory_utilization=0.3
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain grpo ... rollout.backend=vllm  (one engine per process,
            each on its own GPU, TP = 1; see "Several processes")

UNTESTED ON A REAL vLLM. This machine has no GPU and vLLM is not installed. What tests/posttrain/rollout/test_backends.py
checks, with a stand-in `vllm` module of a few lines, is OUR side: the mapping of SamplingParams, the
conversion of vLLM's RequestOutput / CompletionOutput into Rollout records, the weight export (LoRA merged,
names as in the Hugging Face checkpoint), that a push happens after every policy update, that GRPO then
recomputes pi_old, and the error when vLLM is missing. Whether the vLLM calls below behave as their
documentation says on a given vLLM version has not been run by us.

Targeted vLLM API: the V1 engine (vLLM >= 0.10, the only engine from 0.11 on), offline `vllm.LLM`:
- `LLM(model=DIR, tokenizer=DIR, dtype=..., gpu_memory_utilization=..., enforce_eager=..., seed=0)`, built once
  per policy model object (`engine_for`; a WeakKeyDictionary, as the lean forward's cache) from the directory
  the model was loaded from (`config._name_or_path`), else from a temporary save of its config and tokenizer.
- `LLM.generate([{"prompt_token_ids": ids}, ...], [vllm.SamplingParams per prompt], use_tqdm=False)`: token-id
  prompts (a `TokensPrompt` is that dict), one SamplingParams per prompt because each prompt's max_tokens is
  clipped to the context as the built-in engine does.
- Weight sync: `LLM.collective_rpc(fn, args=(weights,))` runs `fn(worker, weights)` in every worker, and `fn`
  calls `worker.model_runner.model.load_weights(weights)` (the model's own loader: it takes Hugging Face names
  and does the fusing of q/k/v and gate/up itself), then `LLM.reset_prefix_cache()` (cached KV blocks of the
  old weights would otherwise be reused). We set VLLM_ENABLE_V1_MULTIPROCESSING=0 before building the engine
  so the engine core and its single worker run in this process: the tensors are passed by reference, never
  pickled. Older V0 engines (< 0.8) exposed the same model as
  `llm.llm_engine.model_executor.driver_worker.model_runner.model` (no collective_rpc); not supported here.
  Newer vLLM (the "weight transfer" API, `WeightTransferConfig(backend="ipc")` for a colocated trainer) is the
  upstream-recommended path where it exists; it is not used here (its protocol changed between releases).

When weights are pushed ("sync"). `generate(..., backend="vllm")` compares the policy's weights signature
(data pointer and version counter of every parameter, plus LoRA adapter state; `engine._weights_signature`,
the same test that rebuilds the lean forward's fused weights) with the one of the last push, and pushes before
sampling when it moved. An optimizer step bumps every updated parameter's version, so the first rollout after
each policy update samples the new policy: one place for every trainer (GRPO, PPO, online DPO, preference
sampling, evaluation), one push per step however many optimizer updates the step made, none when nothing
changed (evaluation right after sampling). The first call always pushes (a resumed run's weights are not the
directory's). LoRA: the adapters are merged into the exported weights (W + scale * B @ A, computed without
touching the training model's base weights); vLLM's own LoRA support is not used.

Limits and departures from the built-in engine (`posttrain.rollout` contract):
- Log-probs. vLLM V1 returns, with SamplingParams(logprobs=0), the log-prob of each sampled token under its
  RAW logits (logprobs_mode "raw_logprobs", before temperature / top-k / top-p), computed by vLLM's forward
  (its kernels, dtype and batch shapes). Both `Rollout.policy_logprobs` and `Rollout.logprobs` hold that number
  (0.0 in `logprobs` for greedy, as the contract says); at temperature != 1 or with top-k / top-p, `logprobs` is
  therefore NOT the sampling distribution's. Neither equals the training forward's log-probs, so trainers must
  recompute pi_old: GRPO does when rollout.backend=vllm (old_logprobs=rollout is overridden, the log line says
  so); PPO always recomputes (its detail 16) and logs the gap as rollout/logprob_gap. `evaluation.kl_to_reference`
  uses `policy_logprobs` as log pi: under vLLM that KL estimate carries vLLM's numerical error.
- Determinism. The built-in engine's guarantees (same seed -> same samples, a (prompt key, sample) pair's
  sample independent of the other prompts in the call) do NOT hold: we pass one vLLM seed per request,
  hash(seed, prompt key), so a prompt's samples come from its own generator, but vLLM's batch composition,
  scheduling and kernels change logits between calls. Resume is then not bit-exact either.
- Finish reasons. vLLM "length" -> "length"; "stop" with stop_reason None or a token id (EOS / a stop token)
  -> "eos"; "stop" with a string stop_reason -> "stop"; anything else ("abort") is an error. Texts are decoded
  by OUR tokenizer and cut at the first stop string exactly as the built-in engine does (`engine._finish`),
  so `text` and `completion_ids` follow the same contract; EOS tokens are kept in completion_ids as vLLM returns
  them.
- Memory. vLLM holds its own copy of the weights and a KV cache of vllm_gpu_memory_utilization x the GPU; one
  engine per distinct model object that generates (the eval stage's model and reference: two engines). Nothing
  frees an engine's GPU memory before the process ends.
- Several processes (accelerate / torchrun): each process builds its own engine on its own GPU with
  distributed_executor_backend="external_launcher" (vLLM joins the launcher's process group instead of
  starting its own, TP = 1) and samples its own shard of prompts, as with the built-in engine.
- Not supported: tensor parallelism inside one process's engine, quantised policies, multi-LoRA serving.
"""
from __future__ import annotations

import os
import tempfile
import weakref
from pathlib import Path
from typing import Any, Sequence

import torch

from ..errors import ConfigError
from ..models import unwrap_model, weights_signature
from .records import Rollout, finish_rollouts
from .sampling import SamplingParams

_MISSING = ("rollout.backend=vllm: vLLM is not installed; pip install vllm (it needs an NVIDIA GPU with CUDA), "
            "or use rollout.backend=auto (the built-in engine, CPU or GPU)")
_NO_GPU = ("rollout.backend=vllm needs a CUDA GPU (torch.cuda.is_available() is False); use rollout.backend=auto "
           "(the built-in engine) on this machine")

_engines: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _has_cuda() -> bool:
    return torch.cuda.is_available()


def require_vllm():
    """The `vllm` module, or a one-line ConfigError: not installed (pip install vllm; needs a GPU), or no GPU."""
    try:
        import vllm
    except ImportError:
        raise ConfigError(_MISSING) from None
    if not _has_cuda():
        raise ConfigError(_NO_GPU)
    return vllm


def engine_for(model, tokenizer, **options) -> "VLLMEngine":
    """The vLLM engine of `model` (built on first use, then cached for the model object's lifetime)."""
    inner = unwrap_model(model)
    eng = _engines.get(inner)
    if eng is None:
        eng = VLLMEngine(inner, tokenizer, **options)
        _engines[inner] = eng
    return eng


def request_seed(seed: int, key: int) -> int:
    """vLLM's per-request seed of prompt `key`: a 31-bit mix of (seed, key) (one stream per prompt, up to hash
    collisions), so a prompt's seed does not depend on the other prompts of the call."""
    from .sampling import mix32

    x = mix32(torch.tensor([seed & 0xFFFFFFFF], dtype=torch.int64)) ^ (key & 0xFFFFFFFF)
    return int(mix32(x).item()) & 0x7FFFFFFF


def export_weights(model) -> list[tuple[str, torch.Tensor]]:
    """(Hugging Face name, tensor) of every weight of `model` as a plain checkpoint would hold it: a peft model's
    adapters merged into their base weights (W + scale * B @ A; the model itself is not modified), DDP wrappers
    removed. Tensors stay on the model's device; tied weights appear under each of their names."""
    inner = unwrap_model(model)
    if not (hasattr(inner, "peft_config") and hasattr(inner, "get_base_model")):
        return [(k, v.detach()) for k, v in inner.state_dict().items()]
    base = inner.get_base_model()
    deltas: dict[str, torch.Tensor] = {}
    with torch.no_grad():
        for name, mod in base.named_modules():
            if not hasattr(mod, "lora_A") or getattr(mod, "merged", False) or getattr(mod, "disable_adapters", False):
                continue
            for adapter in getattr(mod, "active_adapters", []):
                if adapter in mod.lora_A:
                    d = mod.get_delta_weight(adapter)
                    deltas[f"{name}.weight"] = deltas[f"{name}.weight"] + d if f"{name}.weight" in deltas else d
    out = []
    for key, value in base.state_dict().items():
        if "lora_" in key:
            continue
        name = key.replace(".base_layer.", ".")
        value = value.detach()
        if name in deltas:
            value = value + deltas[name].to(value.dtype)
        out.append((name, value))
    return out


def _load_into_worker(worker, weights) -> None:
    """Runs inside a vLLM worker (LLM.collective_rpc passes the worker first): the model's own weight loader."""
    runner = worker.model_runner
    model = runner.get_model() if hasattr(runner, "get_model") else runner.model
    model.load_weights(weights=weights)


def _model_dir(inner, tokenizer) -> tuple[str, str, tempfile.TemporaryDirectory | None]:
    """(model dir, tokenizer dir, temp dir to keep alive) for vLLM to read the architecture and tokenizer from:
    the directory the model was loaded from when there is one, else a temporary save of the model (base model
    of a peft model) and tokenizer. The weights vLLM loads from it are replaced by the first push anyway."""
    src = str(getattr(getattr(inner, "config", None), "_name_or_path", "") or "")
    has_model = bool(src) and (Path(src) / "config.json").is_file()
    has_tok = has_model and any((Path(src) / f).is_file() for f in ("tokenizer.json", "tokenizer_config.json"))
    if has_model and (has_tok or tokenizer is None):
        return src, src, None
    tmp = tempfile.TemporaryDirectory(prefix="posttrain-vllm-")
    if not has_model:
        base = inner.get_base_model() if hasattr(inner, "get_base_model") else inner
        base.save_pretrained(tmp.name, safe_serialization=True)
    if tokenizer is not None:
        tokenizer.save_pretrained(tmp.name)
    return (src if has_model else tmp.name), tmp.name, tmp


class VLLMEngine:
    """A `vllm.LLM` holding a copy of one policy, behind the rollout contract (see the module docstring)."""

    def __init__(self, model, tokenizer, *, gpu_memory_utilization: float = 0.3, dtype: str = "auto",
                 enforce_eager: bool = False):
        vllm = require_vllm()
        self.vllm = vllm
        inner = unwrap_model(model)
        path, tok_path, self._tmp = _model_dir(inner, tokenizer)
        os.environ.setdefault("VLLM_ENABLE_V1_MULTIPROCESSING", "0")  # engine core in-process: no weight pickling
        kwargs: dict[str, Any] = dict(model=path, tokenizer=tok_path, dtype=dtype, seed=0,
                                      gpu_memory_utilization=gpu_memory_utilization, enforce_eager=enforce_eager)
        if torch.distributed.is_available() and torch.distributed.is_initialized() \
                and torch.distributed.get_world_size() > 1:
            kwargs["distributed_executor_backend"] = "external_launcher"  # join accelerate's / torchrun's group
        self.llm = vllm.LLM(**kwargs)
        self.synced: tuple | None = None  # weights signature of the last push
        self.pushes = 0

    # ------------------------------------------------------------------ weights
    def sync_weights(self, model) -> None:
        """Push `model`'s current weights into the engine (all of them, LoRA merged) and drop its prefix cache."""
        inner = unwrap_model(model)
        with torch.no_grad():
            weights = export_weights(inner)
            self.llm.collective_rpc(_load_into_worker, args=(weights,))
        self.llm.reset_prefix_cache()
        self.synced = weights_signature(inner)
        self.pushes += 1

    def sync_if_changed(self, model) -> bool:
        """Push when the weights changed since the last push (always on the first call); True if it pushed."""
        if self.synced is not None and weights_signature(unwrap_model(model)) == self.synced:
            return False
        self.sync_weights(model)
        return True

    # ------------------------------------------------------------------ sampling
    def sampling_params(self, params: SamplingParams, key: int, max_tokens: int):
        """vLLM SamplingParams of one prompt (its key seeds its own generator)."""
        return self.vllm.SamplingParams(
            n=params.n, temperature=0.0 if params.is_greedy else float(params.temperature),
            top_k=params.top_k if params.top_k > 0 else -1, top_p=float(params.top_p), max_tokens=int(max_tokens),
            stop=list(params.stop) or None, include_stop_str_in_output=params.include_stop,
            ignore_eos=params.ignore_eos, seed=request_seed(params.seed, key), logprobs=0,
            skip_special_tokens=True)

    def generate(self, model, ids: Sequence[list[int]], texts: Sequence[str | None], params: SamplingParams,
                 keys: Sequence[int], limits: Sequence[int], tokenizer=None) -> list[Rollout]:
        """Rollouts of validated token-id prompts (`engine.generate` validated them and clipped `limits` to the
        context), ordered by (prompt index, sample index). Pushes the weights first if they changed."""
        self.sync_if_changed(model)
        requests = [{"prompt_token_ids": list(p)} for p in ids]
        sps = [self.sampling_params(params, k, lim) for k, lim in zip(keys, limits)]
        outputs = self.llm.generate(requests, sps, use_tqdm=False)
        if len(outputs) != len(ids):
            raise RuntimeError(f"vLLM returned {len(outputs)} outputs for {len(ids)} prompts")
        results: dict[tuple[int, int], tuple[list[int], list[float], list[float], str]] = {}
        for i, req in enumerate(outputs):
            comps = sorted(req.outputs, key=lambda c: c.index)
            if len(comps) != params.n:
                raise RuntimeError(f"vLLM returned {len(comps)} completions for prompt {i}, expected n={params.n}")
            for j, c in enumerate(comps):
                toks = [int(t) for t in c.token_ids]
                raw = completion_logprobs(c, toks, i, j)
                results[(i, j)] = (toks, [0.0] * len(toks) if params.is_greedy else raw, raw,
                                   finish_reason(c, i, j))
        return finish_rollouts(results, ids, texts, params, tokenizer)


def completion_logprobs(c, toks: list[int], i: int, j: int) -> list[float]:
    """Log-prob of each sampled token from a CompletionOutput's `logprobs` (per position: token id -> Logprob)."""
    steps = c.logprobs
    if steps is None or len(steps) != len(toks):
        raise RuntimeError(f"vLLM returned no per-token log-probs for prompt {i} sample {j} "
                           f"({'none' if steps is None else len(steps)} for {len(toks)} tokens); "
                           "SamplingParams(logprobs=0) asks for them")
    out = []
    for t, (tok, step) in enumerate(zip(toks, steps)):
        entry = step.get(tok) if hasattr(step, "get") else None
        if entry is None:
            raise RuntimeError(f"vLLM's log-probs of prompt {i} sample {j} lack the sampled token {tok} at step {t}")
        out.append(float(getattr(entry, "logprob", entry)))
    return out


def finish_reason(c, i: int, j: int) -> str:
    """Our finish reason of a vLLM CompletionOutput (see the module docstring)."""
    if c.finish_reason == "length":
        return "length"
    if c.finish_reason == "stop":
        return "stop" if isinstance(c.stop_reason, str) else "eos"
    raise RuntimeError(f"vLLM finished prompt {i} sample {j} with reason {c.finish_reason!r} "
                       f"(stop_reason {c.stop_reason!r}); expected 'stop' or 'length'")
