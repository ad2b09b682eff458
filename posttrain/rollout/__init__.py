"""The rollout engine: the only text generator in posttrain (PPO, GRPO, preference pairs, best-of-K, SFT
samples and evaluation all sample through `generate`).

CPU: `python -c "from posttrain.rollout import generate"`; speed: `python scripts/bench.py --only generate`.
Multi-GPU: each accelerate process calls `generate` on its own shard of prompts (pass dataset indices
as `prompt_keys` so samples do not depend on the sharding).

    from posttrain.rollout import generate, collate_rollouts, save_rollouts
    rollouts = generate(model, tokenizer, ["2+2=", "Summarize: ..."], n=4, max_new_tokens=64,
                        temperature=1.0, top_p=0.95, stop=["\\n\\n"], seed=step)
    for r in rollouts:
        r.reward = score(r.text)
    batch = collate_rollouts(rollouts, tokenizer.pad_token_id)   # padded tensors for the loss
    save_rollouts(rollouts, "runs/x/grpo/rollouts/step_0001.jsonl")

Contract
- Finishing. A row ends at EOS (finish_reason "eos"; the EOS token is the last completion token, mask 1,
  and is not in `text`), at a stop string ("stop"; `completion_ids` end with the token that completed the
  stop string, `text` is cut right before the stop string, or right after it with `include_stop=True`),
  or after max_new_tokens ("length"). `ignore_eos=True` disables EOS (benchmarks).
- Context. A prompt with >= context tokens (config.max_position_embeddings) is a ValueError. When
  prompt + max_new_tokens exceeds the context, that row's budget is clipped to fit (finish "length").
- Errors. Empty prompt, token ids outside the vocabulary, n < 1, max_new_tokens < 1, temperature < 0,
  top_k < 0, top_p outside (0, 1], a stop given as a bare string: one-line ValueError.
- Log-probs. `Rollout.logprobs`: under the distribution actually sampled (temperature, top-k, top-p,
  renormalised; 0 for greedy). `Rollout.policy_logprobs`: raw model log-softmax at temperature 1, what
  PPO/GRPO ratios need; equal (1e-4) to `posttrain.logprobs.sequence_logprobs` on the same tokens.
- Determinism. Every random draw is u = hash(seed, prompt key, sample index, step) (counter-based, per
  row; `sampling.row_uniforms`). Guaranteed: same model, inputs, params and seed -> identical rollouts
  (same machine and torch build). The samples of a (prompt key, sample index) do not depend on which
  other prompts are in the call, their order, `n`'s other samples, `max_batch_tokens` or when other
  rows finish -- up to floating-point differences in logits between batch shapes (~1e-6), which change
  a token only when u falls within that distance of a boundary of the cumulative distribution.
  Greedy decoding has the same caveat for near-ties of the top two logits.
- Memory. Rows are split into micro-batches with rows * (longest prompt + max_new_tokens) <=
  max_batch_tokens (default 16384 tokens); the KV cache of a micro-batch is that many token slots
  x layers x 2 x kv_heads x head_dim x dtype bytes (tiny: 4 KiB per slot; small: 18 KiB).
- Speed path. `select_backend` picks the lean Llama-family forward (`posttrain.lean.decode.LeanLlama`: fused and
  pre-transposed weights with norms and the softmax scale folded in, RoPE as one complex multiply,
  preallocated KV cache written in place, explicit GEMV attention; see its docstring) when the model
  supports it (llama / mistral / qwen2 types, fp32, bf16 or fp16 weights, plain nn.Linear or LoRA), else the
  model's own forward with its own cache (other architectures, other peft adapters, quantised layers). The reason
  is returned by `select_backend` and logged at DEBUG. On the CPU both paths drop finished rows from the active
  batch once >= 1/8 of it has finished (the lean path moves live rows into the holes: a compaction
  copies only as many cache rows as finished), and the loop checks for EOS after every step (one host sync).
  On CUDA the lean path runs a static-shape decode step (every row of the micro-batch, attention over the whole
  preallocated cache under a key mask) captured once in a CUDA graph and replayed, and EOS is checked every
  `EOS_CHECK_CUDA` steps from the recorded tokens (the same lengths, reasons and log-probs as a per-step check);
  `posttrain.lean.decode` and `engine` say how and which switches turn it off. Prompts are sorted by length before
  micro-batching and, on the lean path, prefilled in length buckets. The per-token loop runs under
  `torch.inference_mode` in eval mode (no dropout) and does per step: one forward, one sampler call
  (softmax, cumsum, searchsorted), three buffer writes (and a host sync for stop candidates when stop strings
  are set). Fused weights are cached per model and rebuilt when any
  parameter's version counter moved, so an optimizer step between calls is always seen (torch's fused
  AdamW writes weights without bumping the counters: `loop.build_optimizer` bumps them after each step with
  `torch.autograd.graph.increment_version`; do the same in a loop of your own with a fused optimizer). Not
  thread-safe: one `generate` at a time per model. `tune_malloc` sets glibc's malloc to keep freed memory
  once per process (see there). Measured speed: `scripts/bench.py`.
- Multi-turn. `posttrain.rollout.multiturn.generate_episodes(model, tokenizer, env, problems, ...)` samples
  episodes of an environment with tools (posttrain.verifiers.envs) through the same forwards and sampler: one
  Rollout per episode whose completion holds every turn's sampled tokens (mask 1) and the environment's tokens
  (mask 0, exactly the chat template's suffix for its messages), each row's KV cache kept across turns, tool calls
  running in threads while the other rows decode. Its contract is in that module's docstring.
- Backends. `generate(..., backend=None)` uses the process default that `configure` sets (the CLI sets it
  from the recipe's `rollout:` section; "auto" otherwise). backend="vllm" (GPU, optional, import-guarded:
  importing posttrain never imports vllm) samples through `vllm_backend.VLLMEngine`, which returns the same
  records and pushes the policy's weights into vLLM whenever they changed since its last call (so after
  every policy update); its log-probs, determinism and limits are in that module's docstring. Untested here.
"""
from ..lean.decode import LeanLlama
from ..lean.support import lean_support
from ..runtime import tune_malloc
from .engine import (BACKENDS, DEFAULT_MAX_BATCH_TOKENS, configure, context_length, default_backend, default_dtype,
                     generate, select_backend)
from .records import Rollout, RolloutBatch, collate_rollouts, load_rollouts, save_rollouts
from .sampling import SamplingParams, row_uniforms

__all__ = [
    "BACKENDS",
    "DEFAULT_MAX_BATCH_TOKENS",
    "LeanLlama",
    "Rollout",
    "RolloutBatch",
    "SamplingParams",
    "collate_rollouts",
    "configure",
    "context_length",
    "default_backend",
    "default_dtype",
    "generate",
    "lean_support",
    "load_rollouts",
    "row_uniforms",
    "save_rollouts",
    "select_backend",
    "tune_malloc",
]
