"""Sampling parameters, counter-based per-row randomness, the per-step sampler, stop strings.

Randomness. Row (prompt key i, sample j) at decode step t draws one uniform
u = hash(seed, i, j, t) in [0, 1) (a 32-bit integer mixer evaluated with int64 tensor ops, all
steps of a micro-batch at once) and takes the token whose cumulative probability interval
contains u (inverse-CDF sampling over the filtered distribution, vocabulary order for plain
sampling, descending-probability order under top-k / top-p). A row's randomness therefore never
depends on its batch neighbours, the micro-batch split, or the order of prompts; see
`posttrain.rollout` for what is guaranteed. Inverse-CDF needs one uniform per row and step where
Gumbel-max needs one per vocabulary entry, and shares the sort / cumsum that top-p needs anyway.

`Sampler.__call__` reads no value on the host (no `.item()`, no data-dependent shapes: argmax, softmax, cumsum,
searchsorted, topk / sort, gather): on CUDA the engine's decode loop launches it after each graph replay without
waiting for the GPU.
"""
from __future__ import annotations

import math
import weakref
from dataclasses import dataclass

import torch

_M32 = 0xFFFFFFFF


@dataclass(frozen=True)
class SamplingParams:
    """How to sample. Every field has a CPU-friendly default; `generate(..., **overrides)` replaces fields."""

    n: int = 1  # samples per prompt
    max_new_tokens: int = 64  # completion budget per sample (clipped to the model's context, see generate)
    temperature: float = 1.0  # 0 means greedy
    top_k: int = 0  # keep the k most likely tokens; 0 = off
    top_p: float = 1.0  # nucleus: keep the smallest prefix with mass >= top_p; 1 = off
    greedy: bool = False  # argmax decoding (same as temperature=0)
    stop: tuple[str, ...] = ()  # stop strings; finish_reason "stop"
    include_stop: bool = False  # keep the stop string at the end of `text` (it is always in completion_ids)
    ignore_eos: bool = False  # keep sampling after EOS (benchmarks); EOS never ends a row then
    seed: int = 0  # with (prompt key, sample index, step) determines every random draw

    def validate(self) -> "SamplingParams":
        def bad(msg: str) -> ValueError:
            return ValueError(f"sampling: {msg}")

        if not isinstance(self.n, int) or isinstance(self.n, bool) or self.n < 1:
            raise bad(f"n must be an integer >= 1, got {self.n!r}")
        if not isinstance(self.max_new_tokens, int) or isinstance(self.max_new_tokens, bool) or self.max_new_tokens < 1:
            raise bad(f"max_new_tokens must be an integer >= 1, got {self.max_new_tokens!r}")
        t = self.temperature
        if not isinstance(t, (int, float)) or isinstance(t, bool) or math.isnan(t) or math.isinf(t) or t < 0:
            raise bad(f"temperature must be a finite number >= 0 (0 = greedy), got {t!r}")
        if not isinstance(self.top_k, int) or isinstance(self.top_k, bool) or self.top_k < 0:
            raise bad(f"top_k must be an integer >= 0 (0 = off), got {self.top_k!r}")
        p = self.top_p
        if not isinstance(p, (int, float)) or isinstance(p, bool) or math.isnan(p) or not 0.0 < p <= 1.0:
            raise bad(f"top_p must be in (0, 1] (1 = off), got {p!r}")
        if isinstance(self.stop, str) or not all(isinstance(s, str) and s for s in self.stop):
            raise bad(f"stop must be a list of non-empty strings, got {self.stop!r}")
        if not isinstance(self.seed, int) or isinstance(self.seed, bool):
            raise bad(f"seed must be an integer, got {self.seed!r}")
        return self

    @property
    def is_greedy(self) -> bool:
        return self.greedy or self.temperature == 0


def mix32(x: torch.Tensor) -> torch.Tensor:
    """A 32-bit integer finalizer (xorshift-multiply, after Wellons' `lowbias32`) on int64 tensors.

    Inputs and outputs are in [0, 2**32). Multipliers are < 2**31 so products stay below 2**63
    (no signed overflow in int64).
    """
    x = x ^ (x >> 16)
    x = (x * 0x7FEB352D) & _M32
    x = x ^ (x >> 15)
    x = (x * 0x2C1B3C6D) & _M32
    x = x ^ (x >> 16)
    x = (x * 0x297A2D39) & _M32
    return x ^ (x >> 15)


def row_uniforms(seed: int, keys: torch.Tensor, samples: torch.Tensor, steps: int) -> torch.Tensor:
    """Uniforms in [0, 1) for each row and step: (R,) keys, (R,) sample indices -> (R, steps) float32.

    u[r, t] = hash(seed, keys[r], samples[r], t) with 23 random bits (u * total < total exactly in
    fp32, so the inverse-CDF never lands past the last kept token).
    """
    dev = keys.device
    keys = keys.to(torch.int64)
    h = torch.full_like(keys, 0)
    for word in (seed & _M32, (seed >> 32) & _M32):
        h = mix32(h ^ word)
    for part in (keys & _M32, (keys >> 32) & _M32, samples.to(torch.int64) & _M32):
        h = mix32((h + 0x9E3779B9) & _M32 ^ part)
    t = torch.arange(steps, device=dev, dtype=torch.int64)
    x = mix32((h[:, None] + 0x9E3779B9) & _M32 ^ t[None, :])  # (R, steps)
    return (x >> 9).to(torch.float32) * (1.0 / (1 << 23))


class Sampler:
    """Turns next-token logits (B, V) and one uniform per row into (token, sampling logp, policy logp)."""

    def __init__(self, params: SamplingParams, vocab_size: int):
        self.greedy = params.is_greedy
        self.top_k = min(params.top_k, vocab_size) if params.top_k > 0 else 0
        self.top_p = float(params.top_p)
        self.temperature = float(params.temperature)
        # Plain sampling: temperature 1, no filter -> sampling log-prob == policy log-prob.
        self.plain = not self.greedy and self.top_k == 0 and self.top_p >= 1.0 and self.temperature == 1.0

    def __call__(self, logits: torch.Tensor, u: torch.Tensor):
        """logits (B, V) float, u (B, 1) -> token (B, 1) long, logp (B, 1), policy_logp (B, 1)."""
        if self.greedy:
            tok = logits.argmax(-1, keepdim=True)  # (B, 1)
            policy = logits.gather(1, tok) - logits.logsumexp(-1, keepdim=True)  # (B, 1)
            return tok, torch.zeros_like(policy), policy
        if self.plain:
            probs = torch.softmax(logits, -1)  # (B, V)
            cdf = probs.cumsum(-1)  # (B, V)
            tok = torch.searchsorted(cdf, u * cdf[:, -1:], right=True)  # (B, 1)
            policy = probs.gather(1, tok).log()  # (B, 1)
            return tok, policy, policy
        if self.top_k:
            vals, idx = logits.topk(self.top_k, -1)  # (B, K) sorted descending
        elif self.top_p < 1.0:
            vals, idx = logits.sort(-1, descending=True)  # (B, V)
        else:
            vals, idx = logits, None
        if self.temperature != 1.0:
            vals = vals / self.temperature
        probs = torch.softmax(vals, -1)  # (B, K)
        cdf = probs.cumsum(-1)  # (B, K)
        if self.top_p < 1.0:
            # Keep a token while the mass strictly before it is < top_p (always keeps the first).
            probs = probs.masked_fill((cdf - probs) >= self.top_p, 0.0)
            cdf = probs.cumsum(-1)
        total = cdf[:, -1:]  # (B, 1)
        choice = torch.searchsorted(cdf, u * total, right=True)  # (B, 1)
        logp = (probs.gather(1, choice) / total).log()  # (B, 1)
        tok = idx.gather(1, choice) if idx is not None else choice  # (B, 1)
        policy = logits.gather(1, tok) - logits.logsumexp(-1, keepdim=True)  # (B, 1)
        return tok, logp, policy


# --------------------------------------------------------------------------- stop strings

_candidate_cache: "weakref.WeakKeyDictionary" = weakref.WeakKeyDictionary()


def _decode_each(tokenizer, vocab_size: int) -> list[str]:
    n = min(vocab_size, len(tokenizer))
    texts = tokenizer.batch_decode([[i] for i in range(n)], skip_special_tokens=False)
    return texts + [""] * (vocab_size - n)


def stop_candidates(tokenizer, stops: tuple[str, ...], vocab_size: int, device) -> torch.Tensor:
    """(V,) bool: tokens that may complete a stop string (a cheap in-loop prefilter).

    A token is a candidate when its own decoded text contains the last character of a stop
    string, is empty, or holds a partial UTF-8 sequence. A stop string ending in whitespace makes
    every token a candidate (SentencePiece-style tokenizers hide leading spaces when decoding one
    token). The prefilter only decides *when* a row is checked; the final text pass is exact.
    """
    try:
        per_tok = _candidate_cache.setdefault(tokenizer, {})
    except TypeError:  # not weak-referenceable
        per_tok = {}
    key = (stops, vocab_size)
    if key not in per_tok:
        lasts = {s[-1] for s in stops}
        if any(c.isspace() for c in lasts):
            table = [True] * vocab_size
        else:
            texts = _decode_each(tokenizer, vocab_size)
            table = [(not t) or ("\ufffd" in t) or any(c in t for c in lasts) for t in texts]
        per_tok[key] = torch.tensor(table, dtype=torch.bool)
    return per_tok[key].to(device)


def find_stop(text: str, stops: tuple[str, ...]) -> tuple[int, str] | None:
    """Earliest (position, stop string) in `text`, or None."""
    best = None
    for s in stops:
        i = text.find(s)
        if i >= 0 and (best is None or i < best[0] or (i == best[0] and len(s) > len(best[1]))):
            best = (i, s)
    return best
