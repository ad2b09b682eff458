"""`generate`: the batched sampling loop (see `posttrain.rollout` for the contract).

Precision of the lean engine (`select_backend`): fp32 weights run fp32, or with `rollout.dtype=bfloat16` on
CPU bf16 weight copies under fp32 activations (compressed weights). bf16 / fp16 model weights run natively
in their dtype (posttrain.lean.decode, "Half precision"). On CUDA, `rollout.dtype=bfloat16` and bf16
torch.autocast (accelerate's bf16 mixed precision, `lean.support.decode_autocast`) both compute in bf16 on bf16
copies of fp32 weights (cached per model, refreshed when parameters change): autocast would have run those
matmuls in bf16 anyway, and the bf16 KV cache halves what each step reads. Other autocast (fp16, or any on
CPU) falls back to the HF forward.

The loop on CUDA (`_run_micro_batch`): with the lean decoder, the static decode step (`LeanLlama.step`: every
row of the micro-batch every step, no compaction, a replayed CUDA graph; `STATIC_DECODE`, env
POSTTRAIN_CUDA_GRAPHS=0 for eager steps) and EOS checked every `EOS_CHECK_CUDA` steps instead of every step
(a host sync each): the first EOS of each row within the window is found afterwards from the recorded
tokens, so lengths, finish reasons and log-probs equal a per-step check; generation stops at the first
check after every row has finished. With stop strings (decoded text, a host sync anyway) EOS is checked every
step. On CPU: per-step checks and compaction of finished rows, as before.
"""
from __future__ import annotations

import dataclasses
import logging
import os
import weakref
from typing import Any, Callable, NamedTuple, Sequence

import torch

from ..chat import encode_prompts, is_conversation
from ..models import model_device, unwrap_model, weights_signature
from ..runtime import tune_malloc
from ..lean.decode import LeanLlama
from ..lean.support import HALF_DTYPES, decode_autocast, effective_weight, lean_support
from .backends import HFForward
from .records import Rollout, finish_rollouts
from .sampling import Sampler, SamplingParams, find_stop, row_uniforms, stop_candidates

log = logging.getLogger(__name__)

DEFAULT_MAX_BATCH_TOKENS = 16384
BACKENDS = ("auto", "lean", "hf", "vllm")
_defaults: dict = {"backend": "auto", "vllm": {}, "dtype": "float32"}
DTYPES = {"float32": torch.float32, "bfloat16": torch.bfloat16}
# The static decode step (LeanLlama.step): None = with the lean decoder on CUDA; True forces it (CPU: eager
# steps, for tests), False never (env POSTTRAIN_STATIC_DECODE=0). Graphs: posttrain.lean.decode.CUDA_GRAPHS.
STATIC_DECODE: bool | None = None if os.environ.get("POSTTRAIN_STATIC_DECODE", "").strip().lower() not in \
    ("0", "false", "no", "off") else False
EOS_CHECK_CUDA = 16  # steps between EOS checks on CUDA (each is a host sync)
EOS_CHECK_EVERY: int | None = None  # forces the interval on any device (None: EOS_CHECK_CUDA on CUDA, else 1)


def configure(backend: str = "auto", dtype: str = "float32", **vllm_options) -> None:
    """Set the process-wide rollout backend that `generate(..., backend=None)` uses (every trainer, preference
    sampling and evaluation call it so): the CLI calls this once per command with the recipe's `rollout:` section
    (`configure(**asdict(res.rollout))`). `vllm_options`: the `vllm_*` fields of config.RolloutConfig.
    `dtype`: the lean engine's weight dtype (`rollout.dtype`: bfloat16 runs its matmuls on bf16 copies of the
    weights, see posttrain.lean.decode; auto: bfloat16 where `runtime.native_bf16()`, else float32). backend=vllm checks here, before any model loads, that vLLM is importable and a CUDA GPU is visible."""
    if backend not in BACKENDS:
        raise ValueError(f"rollout backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    if dtype == "auto":  # bf16 weights only where bf16 matmuls are native (emulated bf16 is slower than fp32)
        from ..runtime import native_bf16

        dtype = "bfloat16" if native_bf16() else "float32"
    if dtype not in DTYPES:
        raise ValueError(f"rollout dtype must be one of auto, {', '.join(DTYPES)}, got {dtype!r}")
    if backend == "vllm":
        from .vllm_backend import require_vllm

        require_vllm()
    _defaults["backend"] = backend
    _defaults["dtype"] = dtype
    _defaults["vllm"] = {k.removeprefix("vllm_"): v for k, v in vllm_options.items()}


def default_backend() -> str:
    """The backend `generate` uses when none is given (see `configure`)."""
    return _defaults["backend"]


def default_dtype() -> str:
    """The lean engine's weight dtype when `generate` is given none ("float32" or "bfloat16"; see `configure`)."""
    return _defaults["dtype"]


def context_length(model) -> int | None:
    cfg = getattr(unwrap_model(model), "config", None)
    n = getattr(cfg, "max_position_embeddings", None)
    return int(n) if n else None


class _LeanEntry(NamedTuple):
    """A model's cached lean forward and what it was built from."""

    signature: Any  # `weights_signature` of the model (tensor versions): a changed weight changes it
    lean: Any  # the LeanLlama
    layout: tuple  # (shape, dtype, device) of every parameter: equal layouts refresh in place
    mode: tuple  # (weight dtype, compute dtype)


_lean_cache: "weakref.WeakKeyDictionary[Any, _LeanEntry]" = weakref.WeakKeyDictionary()


def select_backend(model, max_len: int = 0, backend: str = "auto", dtype: str | None = None):
    """(forward object, one-line reason): "lean" when supported, else the HF forward.

    The lean path's fused weights are cached per model and rewritten when any parameter changed since
    (tensor version counters), so a training step between two calls is always seen. `dtype`: the lean
    weights' dtype (None: `configure`'s, float32 by default); the HF forward runs the model as it is."""
    if backend not in ("auto", "lean", "hf"):
        raise ValueError(f"rollout backend must be 'auto', 'lean' or 'hf', got {backend!r}")
    dtype = dtype or _defaults["dtype"]
    if dtype not in DTYPES:
        raise ValueError(f"rollout dtype must be one of {', '.join(DTYPES)}, got {dtype!r}")
    compressed = "" if dtype == "float32" else f"; rollout.dtype={dtype} applies to the lean engine only"
    if backend == "hf":
        return HFForward(model), f"HF forward (requested{compressed})"
    inner = unwrap_model(model)
    ok, why = lean_support(inner, max_len, mode="decode")
    if ok:
        wdt, cdt, note = _lean_precision(inner, dtype)
        mode = (wdt, cdt)
        sig = weights_signature(inner)
        cached = _lean_cache.get(inner)
        if cached is None or cached.signature != sig or cached.mode != mode:
            layout = tuple((p.shape, p.dtype, p.device) for p in inner.parameters())
            lean = cached.lean if cached is not None else None
            with torch.no_grad():
                if lean is not None and cached.layout == layout and cached.mode == mode:
                    lean.load(inner)  # same parameter shapes, dtypes and devices: refresh in place
                else:
                    lean = LeanLlama(inner, weight_dtype=wdt, compute_dtype=cdt)
            cached = _LeanEntry(sig, lean, layout, mode)
            _lean_cache[inner] = cached
        return cached.lean, why + note
    if backend == "lean":
        raise ValueError(f"rollout backend 'lean' cannot run this model: {why}; use backend='auto' or 'hf'")
    return HFForward(model), f"HF forward ({why}{compressed})"


def _lean_precision(inner, dtype: str) -> tuple[torch.dtype | None, torch.dtype | None, str]:
    """(weight dtype, compute dtype, note for the reason) of the lean decoder (module docstring)."""
    head = inner.get_base_model() if hasattr(inner, "peft_config") else inner
    model_dt = effective_weight(head.lm_head).dtype
    if model_dt in HALF_DTYPES:  # half weights: native, in their own dtype
        return None, None, ""
    amp, _ = decode_autocast(model_device(inner))
    if amp is not None:
        return amp, amp, f" (bf16 autocast: weights and compute {str(amp).removeprefix('torch.')})"
    if dtype != "float32" and model_device(inner).type == "cuda":
        return DTYPES[dtype], DTYPES[dtype], f" (weights and compute {dtype})"
    return (None, None, "") if dtype == "float32" else (DTYPES[dtype], None, f" (weights {dtype})")


def _tokenize(tokenizer, prompts) -> tuple[list[list[int]], list[str | None]]:
    ids: list[list[int] | None] = [None] * len(prompts)
    texts: list[str | None] = [None] * len(prompts)
    str_pos = [i for i, p in enumerate(prompts) if isinstance(p, str) or is_conversation(p)]
    if str_pos:
        if tokenizer is None:
            raise ValueError("generate: prompts are strings (or conversations) but no tokenizer was given")
        enc = encode_prompts(tokenizer, [prompts[i] for i in str_pos])  # chat template when it has one
        for i, e in zip(str_pos, enc):
            ids[i], texts[i] = list(e), prompts[i]
    for i, p in enumerate(prompts):
        if ids[i] is None:
            if isinstance(p, torch.Tensor):
                p = p.tolist()
            if not isinstance(p, (list, tuple)) or not all(isinstance(x, int) and not isinstance(x, bool) for x in p):
                raise ValueError(f"generate: prompt {i} must be a string, a conversation or a list of token ids, "
                                 f"got {type(p).__name__}")
            ids[i] = list(p)
    return ids, texts  # type: ignore[return-value]


def _eos_ids(model, tokenizer) -> list[int]:
    out = set()
    if tokenizer is not None and tokenizer.eos_token_id is not None:
        out.add(int(tokenizer.eos_token_id))
    gc = getattr(unwrap_model(model), "generation_config", None)
    e = getattr(gc, "eos_token_id", None)
    if e is not None:
        out.update(int(x) for x in (e if isinstance(e, (list, tuple)) else [e]))
    return sorted(out)


def generate(model, tokenizer, prompts: Sequence[str | Sequence[int]], sampling: SamplingParams | None = None, *,
             prompt_keys: Sequence[int] | None = None, max_batch_tokens: int = DEFAULT_MAX_BATCH_TOKENS,
             backend: str | None = None, progress: Callable[[int, int], None] | None = None,
             **overrides) -> list[Rollout]:
    """Sample `n` completions for each prompt; returns Rollouts ordered by (prompt_index, sample_index).

    prompts: strings (rendered with the tokenizer's chat template when it has one, then tokenized:
        `posttrain.chat.encode_prompts`) or lists of token ids, any lengths.
    sampling: a SamplingParams; keyword `overrides` replace its fields (`generate(m, t, ps, n=4, top_p=0.9)`).
    prompt_keys: one integer per prompt that seeds its randomness (default: its index). Pass stable ids
        (e.g. dataset indices) to get the same samples whatever else is in the call.
    max_batch_tokens: KV-cache budget; rows are split into micro-batches with
        rows * (longest prompt + max_new_tokens) <= max_batch_tokens (at least one row each).
    backend: "auto" (lean path when supported, else HF forward), "lean", "hf", or "vllm" (a vLLM engine per
        model, `posttrain.rollout.vllm_backend`; weights pushed to it whenever they changed since its last call);
        None: the process default set by `configure` ("auto" unless configured).
    progress: called as progress(rows_done, rows_total) after each decoding step of the built-in engine (a row is
        one (prompt, sample)); `loop.Progress` prints it with an ETA for long phases (evaluation, pair sampling).
    """
    backend = default_backend() if backend is None else backend
    if backend not in BACKENDS:
        raise ValueError(f"rollout backend must be one of {', '.join(BACKENDS)}, got {backend!r}")
    params = sampling or SamplingParams()
    if overrides:
        names = {f.name for f in dataclasses.fields(SamplingParams)}
        unknown = sorted(set(overrides) - names)
        if unknown:
            raise ValueError(f"generate: unknown sampling option(s) {unknown}; known: {sorted(names)}")
        params = dataclasses.replace(params, **overrides)
    if isinstance(params.stop, str):
        raise ValueError(f"sampling: stop must be a list of strings, got the string {params.stop!r}")
    params = dataclasses.replace(params, stop=tuple(params.stop)).validate()
    if not isinstance(max_batch_tokens, int) or max_batch_tokens < 1:
        raise ValueError(f"generate: max_batch_tokens must be a positive integer, got {max_batch_tokens!r}")
    if isinstance(prompts, (str, torch.Tensor)):
        raise ValueError("generate: prompts must be a list of strings or of token-id lists")
    prompts = list(prompts)
    if not prompts:
        return []
    ids, texts = _tokenize(tokenizer, prompts)

    inner = unwrap_model(model)
    vocab = int(inner.get_output_embeddings().weight.shape[0]) if hasattr(inner, "get_output_embeddings") \
        and inner.get_output_embeddings() is not None else int(inner.config.vocab_size)
    ctx = context_length(model)
    limits = []
    for i, p in enumerate(ids):
        if not p:
            raise ValueError(f"generate: prompt {i} is empty (0 tokens); give at least one token")
        if min(p) < 0 or max(p) >= vocab:
            raise ValueError(f"generate: prompt {i} has token ids outside [0, {vocab}) (vocabulary of the model)")
        if ctx is not None and len(p) >= ctx:
            raise ValueError(f"generate: prompt {i} has {len(p)} tokens but the model's context is {ctx}; "
                             f"shorten it to at most {ctx - 1} tokens")
        limits.append(params.max_new_tokens if ctx is None else min(params.max_new_tokens, ctx - len(p)))
    if prompt_keys is None:
        keys = list(range(len(ids)))
    else:
        keys = [int(k) for k in prompt_keys]
        if len(keys) != len(ids):
            raise ValueError(f"generate: prompt_keys has {len(keys)} entries for {len(ids)} prompts")

    if backend == "vllm":
        if params.stop and tokenizer is None:
            raise ValueError("generate: stop strings need a tokenizer to decode completions; pass one or drop stop=")
        from .vllm_backend import engine_for

        return engine_for(model, tokenizer, **_defaults["vllm"]).generate(model, ids, texts, params, keys, limits,
                                                                          tokenizer)
    fwd, why = select_backend(model, max(len(p) for p in ids) + params.max_new_tokens, backend)
    log.debug("rollout backend: %s", why)
    tune_malloc()
    stop_table = None
    if params.stop and tokenizer is None:
        raise ValueError("generate: stop strings need a tokenizer to decode completions; pass one or drop stop=")
    if params.stop:
        stop_table = stop_candidates(tokenizer, params.stop, vocab, fwd.device)
    sampler = Sampler(params, vocab)
    eos = [] if params.ignore_eos else _eos_ids(model, tokenizer)
    pad_id = tokenizer.pad_token_id if tokenizer is not None and tokenizer.pad_token_id is not None else 0

    batches = plan_micro_batches([len(p) for p in ids], params.n, params.max_new_tokens, max_batch_tokens)
    results: dict[tuple[int, int], tuple[list[int], list[float], list[float], str]] = {}
    model_was_training = getattr(model, "training", False)
    if isinstance(fwd, HFForward) and model_was_training:
        model.eval()
    try:
        with torch.inference_mode():
            total, done = sum(len(b) for b in batches), 0
            for rows in batches:
                # within a micro-batch (a real model's evaluation may be one long one) rows count as they finish
                on_step = None if progress is None else (lambda k, d=done: progress(min(d + k, total - 1), total))
                _run_micro_batch(fwd, rows, sampler, params, ids, limits, keys, eos, stop_table, tokenizer, pad_id,
                                 results, on_step)
                done += len(rows)
                if progress is not None:
                    progress(done, total)
    finally:
        fwd.release()
        if isinstance(fwd, HFForward) and model_was_training:
            model.train()
    return finish_rollouts(results, ids, texts, params, tokenizer)


def plan_micro_batches(lengths: list[int], n: int, max_new: int, budget: int) -> list[list[tuple[int, int]]]:
    """Rows (prompt, sample), prompts sorted by length (little padding per micro-batch), cut into
    micro-batches with rows * (longest prompt + max_new) <= budget (>= 1 row each). The samples of a
    prompt are consecutive, so they share one prefill when they land in the same micro-batch."""
    order = sorted(range(len(lengths)), key=lambda i: (lengths[i], i))
    batches: list[list[tuple[int, int]]] = []
    cur: list[tuple[int, int]] = []
    cur_p = 0
    for i in order:
        for j in range(n):
            need = max(cur_p, lengths[i]) + max_new
            if cur and (len(cur) + 1) * need > budget:
                batches.append(cur)
                cur, cur_p = [], 0
            cur.append((i, j))
            cur_p = max(cur_p, lengths[i])
    batches.append(cur)
    return batches


def prefill_inputs(rows: list[tuple[int, int]], ids: list[list[int]], pad_id: int, dev):
    """A micro-batch's prefill: its unique prompts in row order (the samples of a prompt share one prefill) and
    ids / valid / pos (U, Tp) left-padded on `dev`, positions as HF generate computes them, row_of (B,) the prompt of
    each row. Returns (prompt indices, ids, valid, pos, row_of)."""
    prompts: list[int] = []
    row_of = []
    for i, _ in rows:
        if not prompts or prompts[-1] != i:
            prompts.append(i)
        row_of.append(len(prompts) - 1)
    Tp = max(len(ids[i]) for i in prompts)
    ids_t = torch.full((len(prompts), Tp), pad_id, dtype=torch.long)  # (U, Tp) left-padded
    valid = torch.zeros((len(prompts), Tp), dtype=torch.bool)  # (U, Tp)
    for u, i in enumerate(prompts):
        ids_t[u, Tp - len(ids[i]):] = torch.tensor(ids[i], dtype=torch.long)
        valid[u, Tp - len(ids[i]):] = True
    pos = (valid.long().cumsum(-1) - 1).clamp_(min=0)  # (U, Tp)
    return prompts, ids_t.to(dev), valid.to(dev), pos.to(dev), torch.tensor(row_of, dtype=torch.long, device=dev)


def _static_step(fwd) -> bool:
    """Whether this micro-batch decodes with the static step (`STATIC_DECODE`; the HF forward has none)."""
    if not hasattr(fwd, "step"):
        return False
    return fwd.device.type == "cuda" if STATIC_DECODE is None else bool(STATIC_DECODE)


def _eos_interval(dev, stop_table) -> int:
    """Steps between EOS checks: 1 with stop strings (their check decodes text every step anyway), else
    `EOS_CHECK_EVERY`, or EOS_CHECK_CUDA on CUDA and 1 elsewhere."""
    if stop_table is not None:
        return 1
    if EOS_CHECK_EVERY is not None:
        return max(1, int(EOS_CHECK_EVERY))
    return EOS_CHECK_CUDA if torch.device(dev).type == "cuda" else 1


def _run_micro_batch(fwd, rows, sampler, params, ids, limits, keys, eos, stop_table, tokenizer, pad_id, results,
                     on_step=None):
    """Decode one micro-batch into `results`; `on_step(rows_finished)` after each decoding step (progress).

    Finishing is decided at checks, every `every` steps (`_eos_interval`): a check covers the steps
    [t0, t] since the last one, and per live row takes the first of: its first EOS in the window (from the
    recorded tokens), a stop string (every step only), its length limit -- the order a per-step check
    finds them in, so the results do not depend on `every`. Rows keep decoding until the check that
    finishes them (their extra tokens are cut off)."""
    dev = fwd.device
    prompts, ids_t, valid, pos, row_of = prefill_inputs(rows, ids, pad_id, dev)
    B = len(rows)
    Tp = ids_t.shape[1]
    row_limit = [limits[i] for i, _ in rows]
    steps = max(row_limit)
    plen_l = [len(ids[i]) for i, _ in rows]
    plen = torch.tensor(plen_l, dtype=torch.long, device=dev)  # (B,)
    static = _static_step(fwd)
    every = _eos_interval(dev, stop_table)

    if static:  # all rows every step, a replayed graph on CUDA (posttrain.lean.decode, "Static decode step")
        fwd.start(B, Tp + steps - 1, max(plen_l) + steps, static=True)
    else:
        fwd.start(B, Tp + steps - 1, max(plen_l) + steps)
    u_all = row_uniforms(params.seed, torch.tensor([keys[i] for i, _ in rows], device=dev),
                         torch.tensor([j for _, j in rows], device=dev), steps)  # (B, steps)
    out_tok = torch.full((B, steps), pad_id, dtype=torch.long, device=dev)  # (B, steps), rows in slot order
    out_lp = torch.zeros((B, steps), dtype=torch.float32, device=dev)
    out_pol = torch.zeros((B, steps), dtype=torch.float32, device=dev)
    fin_tok, fin_lp, fin_pol = out_tok.clone(), out_lp.clone(), out_pol.clone()  # (B, steps), by row
    eos_t = torch.tensor(eos, dtype=torch.long, device=dev) if len(eos) > 1 else None
    eos_1 = eos[0] if len(eos) == 1 else None

    slot_row = list(range(B))  # slot -> row of this micro-batch
    length = [0] * B
    reason = ["length"] * B
    dead: set[int] = set()  # slots that finished but are still in the active batch
    limit_steps = {}
    for r, lim in enumerate(row_limit):
        limit_steps.setdefault(lim - 1, []).append(r)  # step index at which a row hits its limit
    alive_n = B

    def retire(slots: list[int]) -> None:
        s = torch.tensor(slots, dtype=torch.long, device=dev)
        r = torch.tensor([slot_row[x] for x in slots], dtype=torch.long, device=dev)
        fin_tok[r] = out_tok[s]
        fin_lp[r] = out_lp[s]
        fin_pol[r] = out_pol[s]

    logits = fwd.prefill(ids_t, valid, pos, row_of)  # (B, V)
    next_pos = plen.clone()  # (B,) position of the token fed at the next decode step
    if static:
        st = fwd.st  # the step's input buffers: token (B, 1), positions (B,), cache column (1,)
        st.pos.copy_(plen)
        st.col.fill_(Tp)
    tok = None
    Bact = B
    t0 = 0  # first step not yet checked
    for t in range(steps):
        if t > 0:
            if static:
                logits = fwd.step()  # (B, V) fp32
                st.pos.add_(1)
                st.col.add_(1)
            else:
                logits = fwd.decode(tok, next_pos, Tp + t - 1)  # (Bact, V)
                next_pos += 1
        if logits.dtype != torch.float32:
            logits = logits.float()
        tok, lp, pol = sampler(logits, u_all[:Bact, t:t + 1])  # (Bact, 1) each
        out_tok[:Bact, t:t + 1] = tok
        out_lp[:Bact, t:t + 1] = lp
        out_pol[:Bact, t:t + 1] = pol
        if static:
            st.tok.copy_(tok)

        if t + 1 - t0 < every and t < steps - 1:  # no check this step
            if on_step is not None:
                on_step(B - alive_n)
            continue
        newly: list[tuple[int, str, int]] = []  # (slot, reason, step)
        if eos:
            win = out_tok[:Bact, t0:t + 1]  # (Bact, w)
            hit = (win == eos_1) if eos_t is None else torch.isin(win, eos_t)  # (Bact, w)
            if bool(hit.any()):
                if t == t0:
                    first = [0 if h else -1 for h in hit.view(-1).tolist()]
                else:  # first EOS step of each row in the window
                    first = torch.where(hit.any(1), hit.int().argmax(1), -1).tolist()
                for s, f in enumerate(first):
                    if f >= 0 and s not in dead and t0 + f < row_limit[slot_row[s]]:
                        newly.append((s, "eos", t0 + f))
        if stop_table is not None:  # every == 1 here: t0 == t
            cand = stop_table[tok.view(-1)]
            if bool(cand.any()):
                taken = {s for s, _, _ in newly}
                for s in cand.nonzero().view(-1).tolist():
                    if s in dead or s in taken:
                        continue
                    text = tokenizer.decode(out_tok[s, :t + 1].tolist(), skip_special_tokens=True)
                    if find_stop(text, params.stop) is not None:
                        newly.append((s, "stop", t))
        if any(tt in limit_steps for tt in range(t0, t + 1)):
            slot_of = {r: s for s, r in enumerate(slot_row[:Bact])}
            taken = {s for s, _, _ in newly}
            for tt in range(t0, t + 1):
                newly += [(slot_of[r], "length", tt) for r in limit_steps.get(tt, ()) if r in slot_of
                          and slot_of[r] not in dead and slot_of[r] not in taken]
        for s, why, tt in newly:
            dead.add(s)
            length[slot_row[s]] = tt + 1
            reason[slot_row[s]] = why
        t0 = t + 1
        alive_n = Bact - len(dead)
        if on_step is not None:
            on_step(B - alive_n)
        if alive_n == 0 or t == steps - 1:
            break
        if not static and dead and len(dead) >= max(1, Bact // 8):
            # Drop finished rows: the last live slots move into the holes (see lean.decode.LeanLlama.select).
            retire(sorted(dead))
            n_new = alive_n
            holes = [s for s in sorted(dead) if s < n_new]
            movers = [s for s in range(n_new, Bact) if s not in dead]
            order = list(range(n_new))
            for h, m in zip(holes, movers):
                order[h] = m
            fwd.select(order, Tp + t)
            if holes:
                o = torch.tensor(order, dtype=torch.long, device=dev)
                tok = tok.index_select(0, o)
                next_pos = next_pos.index_select(0, o)
                for buf in (u_all, out_tok, out_lp, out_pol):
                    buf[:n_new] = buf.index_select(0, o)
            else:
                tok, next_pos = tok[:n_new], next_pos[:n_new]
            slot_row = [slot_row[o] for o in order]
            Bact = n_new
            dead = set()
    retire(list(range(Bact)))
    for r in range(B):
        if length[r] == 0:  # still alive at the end: reached its budget
            length[r] = row_limit[r]
    tok_l, lp_l, pol_l = fin_tok.tolist(), fin_lp.tolist(), fin_pol.tolist()
    for r, key in enumerate(rows):
        k = length[r]
        results[key] = (tok_l[r][:k], lp_l[r][:k], pol_l[r][:k], reason[r])
