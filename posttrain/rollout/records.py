"""The rollout record: one `Rollout` per sample, `RolloutBatch` padded tensors for trainers, disk I/O.

Layout of a `RolloutBatch` (what `collate_rollouts` builds and what `posttrain.logprobs` expects):

    input_ids       (B, T)  [pad .. pad | prompt | completion | pad .. pad]
                            prompts left-padded to the longest prompt P, completions
                            right-padded to the longest completion C, T = P + C
    attention_mask  (B, T)  1 on prompt and completion tokens
    completion_mask (B, T)  1 on completion tokens (times each Rollout's own completion_mask)
    logprobs        (B, T)  sampling log-probs at completion positions, 0 elsewhere
    policy_logprobs (B, T)  raw policy log-probs (temperature 1, unfiltered) at completion positions

Every per-token tensor is aligned with `input_ids`: column t holds the value for token
`input_ids[:, t]`. The completion of every row starts at column P.

Which log-probs are which:
- `logprobs`: log-prob of the sampled token under the distribution the engine actually sampled
  from (temperature, top-k, top-p applied and renormalised). 0.0 for greedy decoding (a point
  mass). Use these for importance weights against the *sampler* (e.g. off-policy corrections).
- `policy_logprobs`: log-softmax of the model's raw logits (temperature 1, no filtering) at the
  sampled token, i.e. log pi_old(token). PPO / GRPO ratios use these, recomputed or not:
  `posttrain.logprobs.sequence_logprobs(model, ...)` returns the same numbers (within 1e-4).

Saved files (`save_rollouts`): one row per Rollout, JSONL (`.jsonl` / `.json`, written with the
json module so floats round-trip exactly) or Parquet (`.parquet`, written with `datasets`); both are
read back with `datasets` (`load_rollouts`, or `datasets.load_dataset("json"/"parquet", ...)`).
`extras` is stored as a JSON string column (`extras_json`) so rows with different extras keys share
one schema.
"""
from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass, field, fields
from pathlib import Path
from typing import Any, Sequence

import torch

from ..chat import prompt_text
from .sampling import find_stop

FINISH_REASONS = ("eos", "stop", "length")


@dataclass
class Rollout:
    """One sampled completion of one prompt, plus room for its reward and verifier details."""

    prompt_ids: list[int]
    completion_ids: list[int]  # ends with the EOS token when finish_reason == "eos"
    logprobs: list[float]  # sampling log-probs, one per completion token (see module docstring)
    policy_logprobs: list[float]  # raw temperature-1 policy log-probs, one per completion token
    finish_reason: str  # "eos" | "stop" | "length"
    text: str  # decoded completion (special tokens skipped; stop string excluded unless include_stop)
    prompt_index: int  # position of the prompt in the generate() call
    sample_index: int  # 0 .. n-1 among the samples of that prompt
    prompt: "str | list[dict] | None" = None  # the prompt when given as text or a conversation (posttrain.chat)
    completion_mask: list[int] = field(default_factory=list)  # 1 per completion token; trainers may zero some
    reward: float | None = None
    extras: dict[str, Any] = field(default_factory=dict)  # verifier details etc.; JSON-serialisable

    def __post_init__(self) -> None:
        if not self.completion_mask:
            self.completion_mask = [1] * len(self.completion_ids)
        n = len(self.completion_ids)
        if not (len(self.logprobs) == len(self.policy_logprobs) == len(self.completion_mask) == n):
            raise ValueError(
                f"Rollout(prompt_index={self.prompt_index}, sample_index={self.sample_index}): completion_ids, "
                f"logprobs, policy_logprobs and completion_mask must have the same length, got "
                f"{n}, {len(self.logprobs)}, {len(self.policy_logprobs)}, {len(self.completion_mask)}"
            )
        if self.finish_reason not in FINISH_REASONS:
            raise ValueError(f"Rollout.finish_reason must be one of {FINISH_REASONS}, got {self.finish_reason!r}")

    def to_dict(self) -> dict[str, Any]:
        d = asdict(self)
        d["extras_json"] = json.dumps(d.pop("extras"), sort_keys=True)
        return d

    @classmethod
    def from_dict(cls, d: dict[str, Any]) -> "Rollout":
        d = dict(d)
        extras = json.loads(d.pop("extras_json", None) or "{}")
        names = {f.name for f in fields(cls)}
        kwargs = {k: v for k, v in d.items() if k in names}
        kwargs["extras"] = extras
        for k in ("prompt_ids", "completion_ids", "completion_mask"):
            kwargs[k] = [int(x) for x in kwargs.get(k) or []]
        for k in ("logprobs", "policy_logprobs"):
            kwargs[k] = [float(x) for x in kwargs.get(k) or []]
        if kwargs.get("reward") is not None:
            kwargs["reward"] = float(kwargs["reward"])
        return cls(**kwargs)


@dataclass
class RolloutBatch:
    """Padded tensors for a list of Rollouts (layout in the module docstring)."""

    input_ids: torch.Tensor  # (B, T) long
    attention_mask: torch.Tensor  # (B, T) long
    completion_mask: torch.Tensor  # (B, T) float
    logprobs: torch.Tensor  # (B, T) float, sampling log-probs
    policy_logprobs: torch.Tensor  # (B, T) float, raw policy log-probs ("old" log-probs for PPO/GRPO)
    prompt_length: int  # P: completions start at column P
    rewards: torch.Tensor | None  # (B,) float, when every rollout has a reward
    prompt_index: torch.Tensor  # (B,) long
    sample_index: torch.Tensor  # (B,) long

    def __len__(self) -> int:
        return self.input_ids.shape[0]

    @property
    def completion_ids(self) -> torch.Tensor:
        return self.input_ids[:, self.prompt_length:]  # (B, C)

    def to(self, device: str | torch.device) -> "RolloutBatch":
        moved = {f.name: getattr(self, f.name) for f in fields(self)}
        for k, v in moved.items():
            if isinstance(v, torch.Tensor):
                moved[k] = v.to(device)
        return RolloutBatch(**moved)

    def select(self, index: torch.Tensor | slice | Sequence[int]) -> "RolloutBatch":
        """Rows `index` (a minibatch), keeping the layout."""
        if not isinstance(index, (slice, torch.Tensor)):
            index = torch.as_tensor(list(index), dtype=torch.long)
        out = {f.name: getattr(self, f.name) for f in fields(self)}
        for k, v in out.items():
            if isinstance(v, torch.Tensor):
                out[k] = v[index]
        return RolloutBatch(**out)


def collate_rollouts(rollouts: Sequence[Rollout], pad_token_id: int = 0) -> RolloutBatch:
    """Pad a list of Rollouts into a RolloutBatch: prompts left-padded, completions right-padded."""
    if not rollouts:
        raise ValueError("collate_rollouts: got an empty list of rollouts")
    B = len(rollouts)
    P = max(len(r.prompt_ids) for r in rollouts)
    C = max(len(r.completion_ids) for r in rollouts)
    T = P + C
    input_ids = torch.full((B, T), pad_token_id, dtype=torch.long)  # (B, T)
    attention_mask = torch.zeros((B, T), dtype=torch.long)  # (B, T)
    completion_mask = torch.zeros((B, T), dtype=torch.float32)  # (B, T)
    logprobs = torch.zeros((B, T), dtype=torch.float32)  # (B, T)
    policy_logprobs = torch.zeros((B, T), dtype=torch.float32)  # (B, T)
    for i, r in enumerate(rollouts):
        p, c = len(r.prompt_ids), len(r.completion_ids)
        input_ids[i, P - p:P] = torch.as_tensor(r.prompt_ids, dtype=torch.long)
        attention_mask[i, P - p:P + c] = 1
        if c:
            input_ids[i, P:P + c] = torch.as_tensor(r.completion_ids, dtype=torch.long)
            completion_mask[i, P:P + c] = torch.as_tensor(r.completion_mask, dtype=torch.float32)
            logprobs[i, P:P + c] = torch.as_tensor(r.logprobs, dtype=torch.float32)
            policy_logprobs[i, P:P + c] = torch.as_tensor(r.policy_logprobs, dtype=torch.float32)
    rewards = None
    if all(r.reward is not None for r in rollouts):
        rewards = torch.tensor([float(r.reward) for r in rollouts], dtype=torch.float32)  # (B,)
    return RolloutBatch(
        input_ids=input_ids,
        attention_mask=attention_mask,
        completion_mask=completion_mask,
        logprobs=logprobs,
        policy_logprobs=policy_logprobs,
        prompt_length=P,
        rewards=rewards,
        prompt_index=torch.tensor([r.prompt_index for r in rollouts], dtype=torch.long),
        sample_index=torch.tensor([r.sample_index for r in rollouts], dtype=torch.long),
    )


def _format(path: Path) -> str:
    suffix = path.suffix.lower()
    if suffix in (".jsonl", ".json"):
        return "json"
    if suffix == ".parquet":
        return "parquet"
    raise ValueError(f"rollout file {str(path)!r}: unknown format {suffix!r}; use a .jsonl or .parquet path")


def save_rollouts(rollouts: Sequence[Rollout], path: str | os.PathLike) -> Path:
    """Write rollouts to `path` (.jsonl or .parquet) through `datasets`; returns the path."""
    from datasets import Dataset

    p = Path(path)
    fmt = _format(p)
    p.parent.mkdir(parents=True, exist_ok=True)
    rows = [r.to_dict() for r in rollouts]
    if not rows:
        raise ValueError(f"save_rollouts({str(p)!r}): nothing to save (empty list)")
    tmp = p.with_name(p.name + ".tmp")
    if fmt == "json":
        # The json module writes floats exactly (repr); pandas' to_json would round them to 10 digits.
        with open(tmp, "w", encoding="utf-8") as f:
            for row in rows:
                f.write(json.dumps(row, ensure_ascii=False) + "\n")
    else:
        Dataset.from_list(rows).to_parquet(str(tmp))
    os.replace(tmp, p)
    return p


def save_step_rollouts(rollouts: Sequence[Rollout], run_dir: str | os.PathLike, step: int) -> list[dict[str, Any]]:
    """One step's scored rollouts as `<run_dir>/rollouts/step-NNNNNN.jsonl` (what `posttrain rollouts RUN_DIR`
    prints; GRPO, PPO and online DPO save them every `save_rollouts_every` steps); returns their `table_rows`."""
    save_rollouts(rollouts, Path(run_dir) / "rollouts" / f"step-{step:06d}.jsonl")
    return table_rows(rollouts)


def table_rows(rollouts: Sequence[Rollout]) -> list[dict[str, Any]]:
    """The rollouts as flat rows for a tracker's table: what a reader scans (no token ids or log-probs)."""
    rows = []
    for r in rollouts:
        ex = r.extras or {}
        rows.append({"prompt": prompt_text(r.prompt) if r.prompt else r.prompt, "completion": r.text, "reward": r.reward, "advantage": ex.get("advantage"),
                     "reason": ex.get("reason"), "parts": json.dumps(ex.get("parts", {}), sort_keys=True),
                     "length": len(r.completion_ids), "finish_reason": r.finish_reason,
                     "prompt_index": r.prompt_index, "sample_index": r.sample_index})
    return rows


def load_rollouts(path: str | os.PathLike) -> list[Rollout]:
    """Read rollouts written by `save_rollouts` (.jsonl or .parquet)."""
    from datasets import Dataset

    p = Path(path)
    fmt = _format(p)
    if not p.is_file():
        raise ValueError(f"rollout file {str(p)!r} does not exist")
    if fmt == "json":
        ds = Dataset.from_json(str(p), keep_in_memory=True)
    else:
        ds = Dataset.from_parquet(str(p), keep_in_memory=True)
    return [Rollout.from_dict(row) for row in ds]


def finish_rollouts(results, ids, texts, params, tokenizer) -> list[Rollout]:
    """Rollout records from a sampler's raw results {(prompt index, sample index): (token ids, log-probs,
    policy log-probs, finish reason)}, ordered by key: texts decoded, cut at the first stop string of
    `params` (a `SamplingParams`), finish reason "stop" then. Every backend (built-in, vLLM) ends here."""
    keys = sorted(results)
    decode = (lambda seqs: tokenizer.batch_decode(seqs, skip_special_tokens=True)) if tokenizer is not None \
        else (lambda seqs: [""] * len(seqs))
    full = decode([results[k][0] for k in keys])
    out = []
    for key, text in zip(keys, full):
        toks, lp, pol, why = results[key]
        if params.stop:
            hit = find_stop(text, params.stop)
            if hit is not None:
                # Shortest token prefix whose text already contains a stop string.
                lo, hi = 1, len(toks)
                while lo < hi:
                    mid = (lo + hi) // 2
                    if find_stop(tokenizer.decode(toks[:mid], skip_special_tokens=True), params.stop) is not None:
                        hi = mid
                    else:
                        lo = mid + 1
                toks, lp, pol, why = toks[:lo], lp[:lo], pol[:lo], "stop"
                text = tokenizer.decode(toks, skip_special_tokens=True)
                at, s = find_stop(text, params.stop)
                text = text[:at + len(s)] if params.include_stop else text[:at]
        i, j = key
        out.append(Rollout(prompt_ids=list(ids[i]), completion_ids=toks, logprobs=lp, policy_logprobs=pol,
                           finish_reason=why, text=text, prompt_index=i, sample_index=j, prompt=texts[i]))
    return out
