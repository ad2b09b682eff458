"""One interface for rewards: `scorer.score(prompts, completions, references) -> ScoreResult`.

CPU: `python -c "from posttrain.scoring import GoldScorer"`; exercised by tests/posttrain/test_scoring.py.
Multi-GPU: each accelerate process scores its own rollouts; nothing here communicates.

PPO, GRPO, online DPO and evaluation get rewards only through this interface, whatever makes them:

    scorer = WeightedScorer([(RewardModelScorer("runs/tiny-summarize/rm/final"), 1.0),
                             (VerifierScorer("format", pool=pool), 0.1)])
    result = scorer.score(prompts, completions, references)
    result.rewards        # list[float], one per completion
    result.parts          # {"rm": [...], "format": [...]}: each component, unweighted
    result.reasons        # list[str]: why a component scored low ("timeout", "invented: bob"), "" if nothing to say

- `RewardModelScorer`: a sequence-classification reward model (`posttrain rm` output, or any HF
  `AutoModelForSequenceClassification` directory with one label). Batched, no grad, in eval mode;
  the reward is read at the last token of the LEFT-padded sequence prompt + completion (+ eos),
  the same token the RM trainer pools at (`reward_forward`).
- `VerifierScorer`: a verifier spec ("math", "0.9*math+0.1*format", a `{name: weight}` mapping, a
  `Verifier`) run through `posttrain.verifiers.runner.VerifierPool`: every check has a hard wall-clock limit;
  a hung or crashing check scores 0 with reason "timeout" / "crashed: ..." and the call returns.
  A verifier that raises (its own bug) propagates as `VerifierError`; with `on_error="zero"` that
  completion scores 0 with reason "verifier error: <type>: <message>" and the others are scored
  (a training loop keeps going and reports it; the default "raise" stops).
- `GoldScorer`: the task's gold metric, references are the task's `meta` dicts. tiny-summarize:
  reward = quality - length_weight * distance from the length band (see the class).
- `WeightedScorer`: sum of w_i * reward_i; parts and reasons of every component, prefixed by name.
"""
from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Mapping, Protocol, Sequence

import torch


@dataclass
class ScoreResult:
    """Rewards of a batch of completions, with each component and a reason per completion."""

    rewards: list[float]
    parts: dict[str, list[float]] = field(default_factory=dict)
    reasons: list[str] = field(default_factory=list)

    def __post_init__(self) -> None:
        if not self.reasons:
            self.reasons = [""] * len(self.rewards)
        for name, values in self.parts.items():
            if len(values) != len(self.rewards):
                raise ValueError(f"ScoreResult part {name!r} has {len(values)} values for {len(self.rewards)} rewards")

    def mean(self) -> float:
        return sum(self.rewards) / max(1, len(self.rewards))


class Scorer(Protocol):
    name: str

    def score(self, prompts: Sequence[str], completions: Sequence[str],
              references: Sequence[Any] | None = None) -> ScoreResult: ...


def _check_lengths(prompts, completions, references) -> None:
    if len(prompts) != len(completions) or (references is not None and len(references) != len(completions)):
        raise ValueError(f"score: got {len(prompts)} prompts, {len(completions)} completions and "
                         f"{'no' if references is None else len(references)} references; they must match")


# ----------------------------------------------------------------------------- reward model
def reward_forward(model, input_ids: torch.Tensor, attention_mask: torch.Tensor) -> torch.Tensor:
    """(B,) rewards of a sequence-classification model on LEFT-padded rows: the score at the last column.

    Pooling. HF's `LlamaForSequenceClassification` (transformers 5: `GenericForSequenceClassification`)
    pools at the rightmost token that is not `config.pad_token_id`, which with left padding is the
    last column, as long as the last token is not the pad id. Our tokenizers pad with their own
    <|pad|>, so the HF pooling and the last column agree; when a tokenizer pads with eos (common for
    real checkpoints) the trainers leave the eos off (`append_eos=False`) so they still agree and a
    model saved here scores the same under a plain `AutoModelForSequenceClassification` call.
    Positions: position_ids = cumsum(attention_mask) - 1, as `posttrain.logprobs` uses.
    A plain fp32 Llama-family model (not wrapped) runs `posttrain.lean.lean_hidden` instead of its own
    forward: the same rewards within fp32 rounding (tested), fewer ops.
    """
    from posttrain.lean.support import lean_support
    from posttrain.models import position_ids_from_mask

    if not bool(attention_mask[:, -1].all()):
        raise ValueError("reward_forward needs LEFT-padded rows (every row's last column a real token)")
    from posttrain.lean import train as lean

    if lean_support(model, input_ids.shape[1], mode="train", head="score")[0]:
        # Same numbers within fp32 rounding, fewer ops (posttrain/lean/train.py): the score of the last column.
        hidden = lean.lean_hidden(model, input_ids, attention_mask)[:, -1]  # (B, d)
        return torch.nn.functional.linear(hidden, model.score.weight, model.score.bias)[:, 0].float()  # (B,)
    out = model(input_ids=input_ids, attention_mask=attention_mask,
                position_ids=position_ids_from_mask(attention_mask))
    return out.logits[:, 0].float()  # (B,)


def left_pad(seqs: Sequence[Sequence[int]], pad_id: int) -> tuple[torch.Tensor, torch.Tensor]:
    """Left-padded (input_ids (B, T), attention_mask (B, T)) of token-id lists."""
    T = max(len(s) for s in seqs)
    input_ids = torch.full((len(seqs), T), pad_id, dtype=torch.long)  # (B, T)
    attention_mask = torch.zeros((len(seqs), T), dtype=torch.long)  # (B, T)
    for i, s in enumerate(seqs):
        if s:
            input_ids[i, T - len(s):] = torch.as_tensor(list(s), dtype=torch.long)
            attention_mask[i, T - len(s):] = 1
    return input_ids, attention_mask


def pair_rewards(model, pairs, pad_id: int) -> torch.Tensor:
    """(2B,) rewards of `data.TokenizedPair`s (prompt + chosen, prompt + rejected): chosen rows first, then
    rejected, in ONE forward (the reward model's Bradley-Terry step; differentiable).

    On the lean path (a plain Llama-family reward model, `lean_support(..., head="score")`) each pair is ONE row,
    prompt + chosen + rejected, under the 4D mask of DPO's prefix sharing (`data.collate_shared_prompt`:
    rejected never sees chosen, its positions continue from the prompt), so the prompt runs once per pair, and the
    rewards are the head's output at each side's last token: the same numbers as two left-padded rows within fp32
    rounding (tested). Otherwise two left-padded rows per pair through `reward_forward`."""
    from posttrain.lean.support import lean_support
    from posttrain.models import model_device

    dev = model_device(model)
    longest = max(len(p.prompt) + len(p.chosen) + len(p.rejected) for p in pairs)
    if lean_support(model, longest, mode="train", head="score")[0]:
        return _shared_prompt_rewards(model, pairs, pad_id, dev)
    seqs = [p.prompt + p.chosen for p in pairs] + [p.prompt + p.rejected for p in pairs]
    input_ids, attention_mask = left_pad(seqs, pad_id)  # (2B, T), (2B, T)
    return reward_forward(model, input_ids.to(dev), attention_mask.to(dev))  # (2B,)


def _shared_prompt_rewards(model, pairs, pad_id: int, dev) -> torch.Tensor:
    """`pair_rewards` on the lean path: one packed row per pair (prompt once), the score at each side's last token."""
    from posttrain.lean import train as lean
    from posttrain.data import collate_shared_prompt

    b = collate_shared_prompt(pairs, pad_id)
    x = lean.lean_packed_hidden(model, b["input_ids"].to(dev), b["position_ids"].to(dev), b["allowed"].to(dev))
    ends = torch.tensor([[len(p.prompt) + len(p.chosen) - 1, len(p.prompt) + len(p.chosen) + len(p.rejected) - 1]
                         for p in pairs], device=dev)  # (B, 2): the last chosen and the last rejected column
    h = lean.final_norm(model, x.gather(1, ends[..., None].expand(-1, -1, x.shape[-1])))  # (B, 2, d)
    r = torch.nn.functional.linear(h, model.score.weight, model.score.bias)[..., 0].float()  # (B, 2)
    return torch.cat([r[:, 0], r[:, 1]])  # (2B,) chosen, then rejected


def load_reward_model(model_dir: str | Path, device: str | torch.device = "cpu"):
    """(model, tokenizer) of a reward-model directory, pad id set in the model config."""
    from transformers import AutoModelForSequenceClassification

    from posttrain.models import ModelError, is_model_dir, load_tokenizer

    if not is_model_dir(model_dir):
        raise ModelError(f"reward model {str(model_dir)!r} is not a Hugging Face model directory "
                         "(train one with `posttrain rm --recipe NAME`)")
    tokenizer = load_tokenizer(model_dir)
    model = AutoModelForSequenceClassification.from_pretrained(str(model_dir), local_files_only=True,
                                                               dtype=torch.float32)
    if model.config.num_labels != 1:
        raise ModelError(f"reward model {str(model_dir)!r} has {model.config.num_labels} labels; expected 1")
    model.config.pad_token_id = tokenizer.pad_token_id
    return model.to(device).eval(), tokenizer


def rm_appends_eos(tokenizer) -> bool:
    """Whether reward-model inputs end with eos: yes, unless the tokenizer pads with eos (see `reward_forward`)."""
    return tokenizer.eos_token_id != tokenizer.pad_token_id


def rm_token_ids(tokenizer, prompts: Sequence[str], completions: Sequence[str]) -> list[list[int]]:
    """prompt (rendered, `posttrain.chat`) + completion (+ eos, `rm_appends_eos`), as the RM trainer builds them."""
    from posttrain.chat import encode_prompts

    p = encode_prompts(tokenizer, prompts)  # the chat template when the tokenizer has one (posttrain.chat)
    c = tokenizer(list(completions), add_special_tokens=False)["input_ids"]
    eos = [tokenizer.eos_token_id] if rm_appends_eos(tokenizer) else []
    return [a + b + eos for a, b in zip(p, c)]


class RewardModelScorer:
    """Rewards from a sequence-classification reward model (batched, no grad, left-pad aware)."""

    def __init__(self, model_dir: str | Path | None = None, *, model=None, tokenizer=None, batch_size: int = 32,
                 device: str | torch.device = "cpu", name: str = "rm"):
        if model is None:
            if model_dir is None:
                raise ValueError("RewardModelScorer needs model_dir or (model, tokenizer)")
            model, tokenizer = load_reward_model(model_dir, device)
        elif tokenizer is None:
            raise ValueError("RewardModelScorer(model=...) needs tokenizer= too")
        self.model, self.tokenizer = model, tokenizer
        self.batch_size = batch_size
        self.name = name

    @torch.no_grad()
    def score(self, prompts, completions, references=None) -> ScoreResult:
        _check_lengths(prompts, completions, references)
        from posttrain.models import model_device

        seqs = rm_token_ids(self.tokenizer, prompts, completions)
        # sort by length so each micro-batch pads little; scatter back in order
        order = sorted(range(len(seqs)), key=lambda i: len(seqs[i]))
        rewards = [0.0] * len(seqs)
        was_training = self.model.training
        self.model.eval()
        dev = model_device(self.model)
        for i in range(0, len(order), self.batch_size):
            idx = order[i:i + self.batch_size]
            ids, am = left_pad([seqs[j] for j in idx], self.tokenizer.pad_token_id)
            r = reward_forward(self.model, ids.to(dev), am.to(dev))  # (b,)
            for j, v in zip(idx, r.tolist()):
                rewards[j] = v
        self.model.train(was_training)
        return ScoreResult(rewards, {self.name: list(rewards)})


# ----------------------------------------------------------------------------- verifiers
class VerifierScorer:
    """Rewards from posttrain.verifiers under hard time limits (`posttrain.verifiers.runner.VerifierPool`).

    `spec`: a registry spec ("math", "0.9*math+0.1*format", "file.py:name"), a `{spec: weight}`
    mapping (a weighted composition), or a `Verifier`. `pool`: a VerifierPool to reuse across calls
    (a training loop keeps one); without one the scorer makes its own and `close()` stops it.
    `timeout_s`: per-check limit (None: the pool's, else the verifier's own). References are the
    verifier references (e.g. the answer), one per completion. Parts: each part of a composition
    (a check that timed out or crashed scores 0 in every part), else the verifier's name.
    """

    def __init__(self, spec: Any, pool=None, *, timeout_s: float | None = None, workers: int | None = None,
                 name: str | None = None, on_error: str = "raise"):
        from posttrain.verifiers.combine import WeightedVerifier
        from posttrain.verifiers.registry import get_verifier
        from posttrain.verifiers.runner import VerifierPool

        if isinstance(spec, Mapping):
            self.verifier = WeightedVerifier([(get_verifier(k) if isinstance(k, str) else k, float(w))
                                              for k, w in spec.items()])
        else:
            self.verifier = get_verifier(spec)
        self._own_pool = pool is None
        self.pool = pool if pool is not None else VerifierPool(workers=workers, timeout_s=timeout_s)
        self.timeout_s = timeout_s
        self.name = name or self.verifier.name or "verifier"
        self._part_names = [label for label, _, _ in getattr(self.verifier, "parts", [])]
        if on_error not in ("raise", "zero"):
            raise ValueError(f"VerifierScorer on_error must be 'raise' or 'zero', got {on_error!r}")
        self.on_error = on_error

    def _verdicts(self, completions: list[str], refs: list[Any]) -> list:
        """The pool's verdicts; with on_error="zero" an item whose check raised scores 0 and the rest are scored."""
        if self.on_error == "raise":
            return self.pool.score(self.verifier, completions, refs, timeout_s=self.timeout_s)
        from posttrain.verifiers.base import Verdict
        from posttrain.verifiers.runner import VerifierError

        out: list[Any] = [None] * len(completions)
        todo = list(range(len(completions)))
        while todo:  # each raising item is taken out and the remaining ones are scored again
            try:
                got = self.pool.score(self.verifier, [completions[i] for i in todo], [refs[i] for i in todo],
                                      timeout_s=self.timeout_s)
            except VerifierError as e:
                if e.index is None:  # the verifier cannot even load: nothing per-item about it
                    raise
                bad = todo.pop(e.index)
                out[bad] = Verdict(0.0, f"verifier error: {e.exc_type}: {e.message[:300]}",
                                   {"verifier_error": e.exc_type})
                continue
            for i, v in zip(todo, got):
                out[i] = v
            todo = []
        return out

    def score(self, prompts, completions, references=None) -> ScoreResult:
        _check_lengths(prompts, completions, references)
        refs = list(references) if references is not None else [None] * len(completions)
        verdicts = self._verdicts(list(completions), refs)
        rewards = [float(v.score) for v in verdicts]
        if self._part_names:
            parts = {label: [float(v.details.get("parts", {}).get(label, {}).get("score", 0.0)) for v in verdicts]
                     for label in self._part_names}
        else:
            parts = {self.name: list(rewards)}
        return ScoreResult(rewards, parts, [v.reason for v in verdicts])

    def close(self) -> None:
        if self._own_pool:
            self.pool.close()


# ----------------------------------------------------------------------------- gold
class GoldScorer:
    """The task's gold metric as a reward; `references` are the task's `meta` dicts.

    tiny-summarize: reward = quality - length_weight * d, with quality in [0, 1] and d the distance
    in words from the length band (`gold_breakdown`). With length_weight > 1 the scalar orders
    summaries like the gold preference (length first, then quality): one word closer to the band
    always outweighs any quality difference. Parts: quality, distance. Reasons: invented words,
    missing facts. A task without `gold_breakdown` uses `gold_quality` alone.
    """

    def __init__(self, task_name: str, length_weight: float = 2.0, name: str = "gold"):
        from posttrain import tasks

        self.task = tasks.get_task(task_name)
        if not tasks.has_gold(self.task):
            raise ValueError(f"task {task_name!r} has no gold metric")
        self.length_weight = length_weight
        self.name = name

    def score(self, prompts, completions, references=None) -> ScoreResult:
        _check_lengths(prompts, completions, references)
        if references is None:
            raise ValueError("GoldScorer.score needs references: the task's meta of each prompt")
        if self.task.gold_breakdown is None:
            q = [float(self.task.gold_quality(m, c)) for m, c in zip(references, completions)]
            return ScoreResult(list(q), {"quality": q})
        rows = [self.task.gold_breakdown(m, c) for m, c in zip(references, completions)]
        quality = [float(r["quality"]) for r in rows]
        distance = [float(r["distance"]) for r in rows]
        rewards = [q - self.length_weight * d for q, d in zip(quality, distance)]
        reasons = []
        for r in rows:
            why = []
            if r["distance"]:
                why.append(f"{r['length']} words, band {r['band'][0]}-{r['band'][1]}")
            if r["invented"]:
                why.append("invented: " + " ".join(r["invented"][:5]))
            if r["missing"]:
                why.append("missing: " + " ".join(r["missing"]))
            reasons.append("; ".join(why))
        return ScoreResult(rewards, {"quality": quality, "distance": distance}, reasons)


# ----------------------------------------------------------------------------- combination
class WeightedScorer:
    """sum_i w_i * reward_i over scorers; parts "name" (each scorer's reward) and "name/part"."""

    def __init__(self, scorers: Sequence[tuple[Any, float]], name: str = "weighted"):
        if not scorers:
            raise ValueError("WeightedScorer needs at least one (scorer, weight)")
        for s, w in scorers:
            if not hasattr(s, "score") or isinstance(w, bool) or not isinstance(w, (int, float)) or not math.isfinite(w):
                raise ValueError(f"WeightedScorer parts are (scorer, finite weight) pairs, got ({s!r}, {w!r})")
        names = [getattr(s, "name", type(s).__name__) for s, _ in scorers]
        if len(set(names)) != len(names):
            raise ValueError(f"WeightedScorer: scorer names must differ, got {names} (pass name= to the scorers)")
        self.scorers = [(s, float(w)) for s, w in scorers]
        self.name = name

    def score(self, prompts, completions, references=None) -> ScoreResult:
        """`references`: one list for every scorer, or a mapping {scorer name: references} when they differ."""
        by_name = references if isinstance(references, Mapping) else None
        if by_name is None:
            _check_lengths(prompts, completions, references)
        total = [0.0] * len(completions)
        parts: dict[str, list[float]] = {}
        reasons: list[list[str]] = [[] for _ in completions]
        for scorer, w in self.scorers:
            refs = by_name.get(scorer.name) if by_name is not None else references
            res = scorer.score(prompts, completions, refs)
            parts[scorer.name] = list(res.rewards)
            for k, v in res.parts.items():
                if k != scorer.name:
                    parts[f"{scorer.name}/{k}"] = list(v)
            for i, (r, why) in enumerate(zip(res.rewards, res.reasons)):
                total[i] += w * r
                if why:
                    reasons[i].append(f"{scorer.name}: {why}")
        return ScoreResult(total, parts, ["; ".join(r) for r in reasons])
