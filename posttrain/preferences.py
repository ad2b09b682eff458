"""Preference pairs: sample from the SFT model, rank with the task's gold preference, keep (chosen, rejected).

CPU:        posttrain prefs --recipe tiny-summarize     (~30 s on 2 cores once the SFT model exists)
Multi-GPU:  accelerate launch --num_processes 8 -m posttrain prefs --recipe tiny-summarize
            (each process samples its shard of the prompts; prompt_keys make the samples independent
            of the sharding, and the main process gathers and writes the files)

The stage writes `runs/<recipe>/prefs/final/` as its last act (a temp dir renamed, so it is
complete once it exists), holding two preference files (schema `preference` of posttrain.data):

    final/train.jsonl   pairs from the task's training prompts
    final/eval.jsonl    pairs from held-out prompts (reward-model eval, DPO held-out accuracy)

Each row is {"prompt", "chosen", "rejected", "meta"}; `meta` is the task's meta of the prompt
(so the gold scorer can score either side) plus `meta["pair"]` = {prompt_index, chosen_sample,
rejected_sample, chosen_key, rejected_key, strategy}. Load one file, not the directory
(`posttrain.data.load_rows` would read both files of a directory).

How pairs are made (`form_pairs`, the same code for offline data and online DPO):
1. `samples_per_prompt` completions per prompt from the rollout engine at `temperature` (seeded,
   prompt_keys = dataset indices, so the samples do not depend on batching or sharding).
2. Each completion gets a key, larger is better: the task's `gold_key` (tiny-summarize: length
   band first, then quality rounded to 0.01) or, for online DPO with an RM labeler, the RM score.
3. Best vs worst: chosen = the highest key, rejected = the lowest (the lowest sample index among
   equal keys, so it is deterministic). A prompt whose samples all tie gives no pair (skipped
   and counted: a tie carries no preference). Empty completions (eos first) are left out of
   the ranking (the preference schema has no empty side) and counted.
4. `pairs_per_prompt` >= 2 adds best vs the runner-up (the best sample with a strictly lower
   key: a hard negative), and >= 3 best vs random other samples with a strictly lower key
   (seeded, without replacement). Best vs worst is mostly a length contrast (the worst sample
   rambles on); the runner-up is typically in the band too, so that pair carries the quality
   distinction (an invented name, a missing fact). Trained on best-vs-worst alone the tiny
   model learns "stop early" and overshoots to too-short summaries.
Samples cut at max_new_tokens (finish "length") stay in: they are typically the worst and make
good rejected examples; as text they are re-tokenized with an eos at the end, as any text pair is.

User files. `prefs.train_file` (and optionally `prefs.eval_file`) replace generation: JSONL,
JSON or Parquet with prompt/chosen/rejected (+ optional meta). Without an eval file, a seeded
`eval_fraction` of the train rows is held out. Bad rows (chosen == rejected, an empty side)
stop the stage or are skipped with a count, per `on_bad_rows`; rows too long for the model are
found where the tokenizer is known (the DPO / RM trainers, same flag there). `dpo.train_file` /
`rm.train_file` read a file directly without this stage.
"""
from __future__ import annotations

import json
import random
import shutil
from collections import Counter
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Callable, Literal, Sequence

import torch

from posttrain import loop
from posttrain.chat import encode_prompts, is_conversation, prompt_key, prompt_text
from posttrain.logprobs import masked_sum, packed_logprobs, sequence_logprobs
from posttrain.data import (DataError, TokenizedPair, collate_pairs, hub_rows, hub_source, normalized_row,
                            token_groups)

PAIR_FIELDS = ("prompt", "chosen", "rejected")
UNPAIRED_FIELDS = ("prompt", "completion", "label")  # TRL's unpaired preference format (KTO)


@dataclass
class PrefsConfig:
    train_file: str | None = None
    """A preference file (JSONL/JSON/Parquet: prompt, chosen, rejected) used instead of sampling pairs."""
    eval_file: str | None = None
    """A held-out preference file; without one (and with train_file) eval_fraction of train_file is held out."""
    eval_fraction: float = 0.05
    """Fraction of train_file held out for eval when no eval_file is given."""
    n_prompts: int = 1000
    """Training prompts to sample for (the first n of the task's training split)."""
    n_eval_prompts: int = 100
    """Held-out prompts to sample eval pairs for (the first n of the task's eval split)."""
    samples_per_prompt: int = 8
    """Completions sampled per prompt (K); pairs are formed among them."""
    pairs_per_prompt: int = 2
    """Pairs per prompt: best vs worst, then best vs the runner-up (hard negative), then best vs random lower."""
    temperature: float = 1.0
    """Sampling temperature."""
    top_p: float = 1.0
    """Nucleus sampling mass (1: off)."""
    max_new_tokens: int = 64
    """Generation budget per completion."""
    on_bad_rows: Literal["error", "skip"] = "error"
    """User files: stop at the first bad row (chosen == rejected, empty side) or skip them with a count."""
    seed: int = 0
    """Seed of sampling and of the choice of extra pairs."""


# ----------------------------------------------------------------------------- forming pairs
def form_pairs(keys: Sequence[Any], pairs_per_prompt: int, rng: random.Random) -> list[tuple[int, int]]:
    """(chosen, rejected) sample indices for one prompt's samples, ranked by `keys` (larger is better).

    Pair 1: best vs worst. Pair 2: best vs the runner-up, the best sample with a strictly lower key
    (a hard negative). Further pairs: best vs random others with a strictly lower key. Among equal
    keys the lowest index is taken; no pair when all tie; no pair is repeated.
    """
    if pairs_per_prompt < 1:
        raise ValueError(f"pairs_per_prompt must be >= 1, got {pairs_per_prompt}")
    if len(keys) < 2:
        return []
    best = max(range(len(keys)), key=lambda i: (keys[i], -i))
    worst = min(range(len(keys)), key=lambda i: (keys[i], i))
    if not keys[best] > keys[worst]:
        return []
    pairs = [(best, worst)]
    lower = [i for i in range(len(keys)) if keys[i] < keys[best] and i != worst]
    if pairs_per_prompt >= 2 and lower:
        runner_up = max(lower, key=lambda i: (keys[i], -i))
        pairs.append((best, runner_up))
        lower.remove(runner_up)
    extra = min(pairs_per_prompt - len(pairs), len(lower))
    if extra > 0:
        pairs += [(best, j) for j in rng.sample(lower, extra)]
    return pairs


def gold_labeler(task_name: str) -> Callable[[list[dict], list[list[str]]], list[list[Any]]]:
    """Keys from the task's gold preference: `task.gold_key(meta, text)` per sample."""
    from posttrain import tasks

    task = tasks.get_task(task_name)
    if not tasks.has_gold_preference(task):
        raise ValueError(f"task {task_name!r} has no gold preference (gold_key); give a preference file "
                         "(prefs.train_file) or use a reward-model labeler")

    def label(rows: list[dict], texts: list[list[str]]) -> list[list[Any]]:
        return [[task.gold_key(r["meta"], t) for t in ts] for r, ts in zip(rows, texts)]

    return label


def scorer_labeler(scorer) -> Callable[[list[dict], list[list[str]]], list[list[Any]]]:
    """Keys from a `posttrain.scoring` scorer (e.g. a reward model): its reward per sample."""

    def label(rows: list[dict], texts: list[list[str]]) -> list[list[Any]]:
        prompts = [r["prompt"] for r, ts in zip(rows, texts) for _ in ts]
        refs = [r.get("meta") for r, ts in zip(rows, texts) for _ in ts]
        rewards = scorer.score(prompts, [t for ts in texts for t in ts], refs).rewards
        out, i = [], 0
        for ts in texts:
            out.append(rewards[i:i + len(ts)])
            i += len(ts)
        return out

    return label


def sample_pairs(model, tokenizer, rows: list[dict], labeler, *, prompt_keys: Sequence[int], samples_per_prompt: int,
                 pairs_per_prompt: int, temperature: float, top_p: float = 1.0, max_new_tokens: int = 64,
                 seed: int = 0, strategy: str = "gold", rollouts_out: list | None = None
                 ) -> tuple[list[dict], dict[str, Any]]:
    """Sample K completions per row, rank them with `labeler`, form pairs (see the module docstring).

    `rows` carry "prompt" (and "meta" for the gold labeler); `prompt_keys` are stable ids (dataset
    indices) that seed each prompt's samples and extra-pair choice. Returns (pair rows, stats).
    `rollouts_out`: given a list, every sample is appended to it as a Rollout with its key (the reward when the
    key is a number, its parts when it is a tuple) and its role in the pairs (chosen, rejected, both, unused,
    or empty), for `posttrain rollouts`.
    """
    from posttrain.loop import Progress
    from posttrain.rollout import SamplingParams, generate

    if samples_per_prompt < 2:
        raise ValueError(f"samples_per_prompt must be >= 2 to form pairs, got {samples_per_prompt}")
    params = SamplingParams(n=samples_per_prompt, temperature=temperature, top_p=top_p,
                            max_new_tokens=max_new_tokens, seed=seed)
    rollouts = generate(model, tokenizer, [r["prompt"] for r in rows], params, prompt_keys=list(prompt_keys),
                        progress=Progress("[prefs] sampling"))
    K = samples_per_prompt
    texts = [[ro.text for ro in rollouts[i * K:(i + 1) * K]] for i in range(len(rows))]
    keys = labeler(rows, texts)
    out: list[dict] = []
    tied = 0
    empty = 0
    for n, (row, key_i, ts, pkey) in enumerate(zip(rows, keys, texts, prompt_keys)):
        rng = random.Random(f"pairs:{seed}:{pkey}")
        # empty completions (eos first) are left out: the preference schema has no empty side
        ok = [i for i, t in enumerate(ts) if t.strip()]
        empty += len(ts) - len(ok)
        pairs = [(ok[c], ok[r]) for c, r in form_pairs([key_i[i] for i in ok], pairs_per_prompt, rng)]
        tied += not pairs
        if rollouts_out is not None:
            rollouts_out.extend(_labelled(rollouts[n * K:(n + 1) * K], key_i, pairs, ok))
        for c, r in pairs:
            meta = dict(row.get("meta") or {})
            meta["pair"] = {"prompt_index": int(pkey), "chosen_sample": c, "rejected_sample": r,
                            "chosen_key": _jsonable(key_i[c]), "rejected_key": _jsonable(key_i[r]),
                            "strategy": strategy}
            out.append({"prompt": row["prompt"], "chosen": ts[c], "rejected": ts[r], "meta": meta})
    stats = {"prompts": len(rows), "samples": len(rollouts), "pairs": len(out), "prompts_all_tied": tied,
             "empty_samples": empty, "finish_length": sum(ro.finish_reason == "length" for ro in rollouts)}
    return out, stats


def _labelled(samples: list, keys: Sequence[Any], pairs: list[tuple[int, int]], ok: list[int]) -> list:
    """One prompt's samples annotated for `posttrain rollouts`: reward (a numeric key), parts (a tuple key's terms),
    reason (its role in the pairs)."""
    chosen, rejected = {c for c, _ in pairs}, {r for _, r in pairs}
    for j, ro in enumerate(samples):
        key = _jsonable(keys[j])
        role = ("empty" if j not in ok else "both" if j in chosen and j in rejected else "chosen" if j in chosen
                else "rejected" if j in rejected else "unused")
        ro.reward = float(key) if isinstance(key, (int, float)) else None
        ro.extras.update(reason=f"pair role: {role}", key=key,
                         parts={f"key[{i}]": float(k) for i, k in enumerate(key)} if isinstance(key, list) else {})
    return list(samples)


def _jsonable(key: Any) -> Any:
    if isinstance(key, tuple):
        return [_jsonable(k) for k in key]
    if isinstance(key, torch.Tensor):
        return key.item()
    return key


# ----------------------------------------------------------------------------- reading and checking files
def _read_pair_file(p: Path) -> list[tuple[int, Any]]:
    """(row number, raw row) of a local preference file."""
    if not p.is_file():
        raise DataError(f"{p}: no such preference file (give a .jsonl, .json or .parquet file)")
    suffix = p.suffix.lower()
    raw: list[tuple[int, Any]] = []
    if suffix in (".jsonl", ".json"):
        text = p.read_text(encoding="utf-8")
        try:
            data = json.loads(text)
            raw = list(enumerate(data if isinstance(data, list) else [data], start=1))
        except json.JSONDecodeError:
            for number, line in enumerate(text.split("\n"), start=1):  # not splitlines: \u2028 is text
                if not line.strip():
                    continue
                try:
                    raw.append((number, json.loads(line)))
                except json.JSONDecodeError as e:
                    raise DataError(f"{p}: row {number}: malformed JSON: {e.msg} (column {e.colno})") from None
    elif suffix == ".parquet":
        import pyarrow.parquet as pq

        try:
            table = pq.read_table(p)
        except Exception as e:  # noqa: BLE001 - any arrow failure is a bad file
            raise DataError(f"{p}: not a readable parquet file ({e})") from None
        raw = list(enumerate(table.to_pylist(), start=1))
    else:
        raise DataError(f"{p}: unsupported preference file type {p.suffix or '(no extension)'!r}; "
                        "use .jsonl, .json or .parquet")
    return raw


def read_pairs(path: str | Path, columns: dict[str, str] | None = None, split: str = "train") -> list[dict]:
    """Rows of a preference file (.jsonl / .json / .parquet), each with its 1-based row number in `_row`.

    Structure is checked here (a JSON object with text prompt/chosen/rejected, meta an object or
    null): a malformed file always raises DataError naming the file and row. Content problems
    (empty side, chosen == rejected, too long) are `check_pairs`' business, under `on_bad_rows`.
    Conversational rows (TRL's formats: a prompt of messages, sides of one assistant message, or the
    implicit-prompt form) are brought into posttrain's form by `posttrain.data.normalize_row`; `columns`
    renames a file's columns (`task.columns`). One format per file. `org/name[,split=...]` reads a Hugging Face
    hub dataset (`posttrain.data.hub_source`; `split` when it names none).
    """
    hub = hub_source(path, split)
    p = Path(path)
    if hub is not None:
        raw = list(enumerate(hub_rows(hub, str(path)), start=1))
        if not raw:
            raise DataError(f"{path}: no rows in split {hub.split!r}")
    else:
        raw = _read_pair_file(p)
    rows = []
    columns = columns or {}
    label = columns.get("label", "label")
    unpaired = isinstance(raw[0][1], dict) and label in raw[0][1] if raw else False  # the first row decides
    first_format = None
    for number, row in raw:
        if not isinstance(row, dict):
            raise DataError(f"{p}: row {number}: expected a JSON object with prompt, chosen, rejected")
        for name in ("meta", "prompt"):  # parquet written by posttrain.data.save_rows
            if f"{name}_json" in row and name not in row:
                row = dict(row, **{name: json.loads(row.pop(f"{name}_json") or "null")})
        row, fmt = normalized_row(row, "unpaired" if unpaired else "preference", str(p), number, columns)
        if first_format is None:
            first_format = (fmt, number)
        elif fmt != first_format[0]:
            raise DataError(f"{p}: row {number}: {fmt}, but row {first_format[1]} is {first_format[0]}; one format "
                            "per file")
        if unpaired:
            rows.append(_unpaired_row(p, number, row))
            continue
        if "label" in row:
            raise DataError(f"{p}: row {number}: field 'label': an unpaired row (prompt, completion, label) in a "
                            "file of pairs (its first row has prompt, chosen, rejected); one format per file")
        for f in PAIR_FIELDS:
            if f not in row:
                raise DataError(f"{p}: row {number}: field '{f}': missing")
            if not isinstance(row[f], str) and not (f == "prompt" and is_conversation(row[f])):
                raise DataError(f"{p}: row {number}: field '{f}': expected text, got {type(row[f]).__name__}")
        if row.get("meta") is not None and not isinstance(row["meta"], dict):
            raise DataError(f"{p}: row {number}: field 'meta': expected a JSON object or null")
        rows.append({"prompt": row["prompt"], "chosen": row["chosen"], "rejected": row["rejected"],
                     "meta": row.get("meta"), "_row": number})
    if not rows:
        raise DataError(f"{p}: no rows")
    return rows


def _unpaired_row(p: Path, number: int, row: dict) -> dict:
    """One row of TRL's unpaired preference format: prompt, completion, label (true: desirable)."""
    for f in UNPAIRED_FIELDS:
        if f not in row:
            raise DataError(f"{p}: row {number}: field '{f}': missing (an unpaired file's rows have prompt, "
                            "completion, label)")
    for f in ("prompt", "completion"):
        if not isinstance(row[f], str) and not (f == "prompt" and is_conversation(row[f])):
            raise DataError(f"{p}: row {number}: field '{f}': expected text, got {type(row[f]).__name__}")
    if not isinstance(row["label"], bool):
        raise DataError(f"{p}: row {number}: field 'label': expected true or false, got {row['label']!r}")
    if row.get("meta") is not None and not isinstance(row["meta"], dict):
        raise DataError(f"{p}: row {number}: field 'meta': expected a JSON object or null")
    return {"prompt": row["prompt"], "completion": row["completion"], "label": row["label"], "meta": row.get("meta"),
            "_row": number}


def is_unpaired(rows: list[dict]) -> bool:
    """Rows read from an unpaired file (prompt, completion, label) rather than pairs."""
    return bool(rows) and "label" in rows[0]


def unpair(rows: list[dict]) -> list[dict]:
    """Pairs as unpaired rows: each pair gives its chosen side as desirable and its rejected side as undesirable
    (TRL's unpair_preference_dataset); unpaired rows pass through. Row numbers stay those of the source."""
    if is_unpaired(rows):
        return list(rows)
    return [{"prompt": r["prompt"], "completion": r[side], "label": side == "chosen", "meta": r.get("meta"),
             "_row": r["_row"]} for r in rows for side in ("chosen", "rejected")]


def check_unpaired(rows: list[dict], source: str, on_bad: Literal["error", "skip"], tokenizer,
                   max_length: int | None = None) -> tuple[list[TokenizedPair], list[bool], BadRows]:
    """KTO's rows: unpaired (prompt, completion, label) rows (pairs are `unpair`ed first), checked and tokenized as
    TokenizedPairs whose `chosen` is the row's completion and whose `rejected` is its KL partner: the completion of
    the next row (cyclically) with ANOTHER prompt, under this row's prompt. Those mismatched (x, y') give KTO's
    reference point z0 = KL(pi || pi_ref), estimated from completions that are not answers to their prompt.
    Returns (rows as pairs, their labels, BadRows). Bad: an empty prompt or completion; too long (either
    completion); fewer than two distinct prompts (no KL partner)."""
    rows = unpair(rows)
    bad = BadRows(source)
    hint = " (set on_bad_rows=skip to drop such rows)"
    ok = []
    for row in rows:
        empty = [f for f in UNPAIRED_FIELDS[:2] if not prompt_text(row[f]).strip()]
        if empty:
            if on_bad == "error":
                raise DataError(f"{source}: row {row['_row']}: field '{empty[0]}': empty text{hint}")
            bad.add("empty", row["_row"])
        else:
            ok.append(row)
    distinct = len({prompt_key(r["prompt"]) for r in ok})
    if distinct < 2:
        raise DataError(f"{source}: KTO needs at least two distinct prompts (its KL reference point pairs each prompt "
                        f"with another prompt's completion); got {distinct}")
    n = len(ok)
    partner = []
    for i, r in enumerate(ok):
        j = next(k % n for k in range(i + 1, i + n) if ok[k % n]["prompt"] != r["prompt"])
        partner.append(j)
    eos = [tokenizer.eos_token_id]
    prompts = encode_prompts(tokenizer, [r["prompt"] for r in ok])
    completions = tokenizer([r["completion"] for r in ok], add_special_tokens=False)["input_ids"]
    pairs, labels = [], []
    for i, row in enumerate(ok):
        c, k = completions[i], completions[partner[i]]
        length = len(prompts[i]) + max(len(c), len(k)) + 1
        if max_length is not None and length > max_length:
            if on_bad == "error":
                raise DataError(f"{source}: row {row['_row']}: prompt + completion (or its KL partner) is {length} "
                                f"tokens, longer than model.max_length={max_length}{hint}")
            bad.add("too long", row["_row"])
            continue
        pairs.append(TokenizedPair(prompts[i], c + eos, k + eos, row["_row"]))
        labels.append(bool(row["label"]))
    return pairs, labels, bad


@dataclass
class BadRows:
    """Rows dropped by `check_pairs` (on_bad_rows="skip"): reason -> row numbers."""

    source: str
    rows: dict[str, list[int]] = field(default_factory=dict)

    @property
    def count(self) -> int:
        return sum(len(v) for v in self.rows.values())

    def add(self, reason: str, row: int) -> None:
        self.rows.setdefault(reason, []).append(row)

    def summary(self) -> str:
        parts = [f"{len(v)} {k} (row{'s' if len(v) > 1 else ''} {', '.join(map(str, v[:5]))}"
                 f"{', ...' if len(v) > 5 else ''})" for k, v in self.rows.items()]
        return f"skipped {self.count} bad row{'s' if self.count != 1 else ''} of {self.source}: " + "; ".join(parts)


def check_pairs(rows: list[dict], source: str, on_bad: Literal["error", "skip"], tokenizer=None,
                max_length: int | None = None, append_eos: bool = True
                ) -> tuple[list[dict], list[TokenizedPair], BadRows]:
    """Drop or refuse bad pairs; tokenize the good ones when a tokenizer is given.

    Bad: an empty (whitespace-only) prompt, chosen or rejected; chosen == rejected (after
    stripping); prompt + completion (+ eos) longer than `max_length` tokens, for either side.
    on_bad="error": DataError naming the source, the row and the problem, at the first bad row.
    on_bad="skip": the bad rows are dropped and reported in the returned `BadRows`.
    Returns (kept rows, their tokenized pairs ([] without a tokenizer), BadRows).
    """
    if on_bad not in ("error", "skip"):
        raise ValueError(f"on_bad must be 'error' or 'skip', got {on_bad!r}")
    if is_unpaired(rows):
        raise DataError(f"{source}: its rows are unpaired (prompt, completion, label): only dpo.loss_type=kto trains on "
                        "them; this stage needs pairs (prompt, chosen, rejected)")
    bad = BadRows(source)
    hint = " (set on_bad_rows=skip to drop such rows)"

    def reject(row: dict, reason: str, detail: str) -> None:
        if on_bad == "error":
            raise DataError(f"{source}: row {row['_row']}: {detail}{hint}")
        bad.add(reason, row["_row"])

    ok: list[dict] = []
    for row in rows:
        empty = [f for f in PAIR_FIELDS if not prompt_text(row[f]).strip()]
        if empty:
            reject(row, "empty", f"field '{empty[0]}': empty text")
        elif row["chosen"].strip() == row["rejected"].strip():
            reject(row, "identical pair", "field 'rejected': identical to 'chosen'")
        else:
            ok.append(row)
    if tokenizer is None:
        return ok, [], bad
    eos = [tokenizer.eos_token_id] if append_eos else []
    prompts = encode_prompts(tokenizer, [r["prompt"] for r in ok])  # chat template, as everywhere (posttrain.chat)
    chosen = tokenizer([r["chosen"] for r in ok], add_special_tokens=False)["input_ids"]
    rejected = tokenizer([r["rejected"] for r in ok], add_special_tokens=False)["input_ids"]
    kept, pairs = [], []
    for row, p, c, r in zip(ok, prompts, chosen, rejected):
        n = len(p) + max(len(c), len(r)) + len(eos)
        if max_length is not None and n > max_length:
            reject(row, "too long", f"prompt + completion is {n} tokens, longer than model.max_length={max_length}")
            continue
        kept.append(row)
        pairs.append(TokenizedPair(p, c + eos, r + eos, row["_row"]))
    return kept, pairs, bad


def load_pairs(train_file: str, eval_file: str | None, on_bad: Literal["error", "skip"] | None, *,
               eval_fraction: float = 0.05, seed: int = 0, say: Callable[[str], None] = print,
               tag: str = "[prefs]", columns: dict[str, str] | None = None) -> tuple[list[dict], list[dict]]:
    """(train rows, eval rows) from user files.

    `on_bad`: check the rows here (no tokenizer, so not their length) with that policy; None
    leaves all checks to the caller (trainers run `check_pairs` with their tokenizer, so one
    report covers every kind of bad row). Without an eval file a seeded `eval_fraction` of the
    train rows is held out (at least one row); rows keep their row numbers in `_row`. `columns`: `task.columns`.
    """
    train = read_pairs(train_file, columns)
    if on_bad is not None:
        train, _, bad = check_pairs(train, str(train_file), on_bad)
        if bad.count:
            say(f"{tag} {bad.summary()}")
    if eval_file:
        ev = read_pairs(eval_file, columns, split="test")
        if on_bad is not None:
            ev, _, bad = check_pairs(ev, str(eval_file), on_bad)
            if bad.count:
                say(f"{tag} {bad.summary()}")
        return train, ev
    if not 0.0 < eval_fraction < 1.0:
        return train, []
    order = list(range(len(train)))
    random.Random(f"eval-split:{seed}").shuffle(order)
    n_eval = max(1, int(round(eval_fraction * len(train)))) if len(train) > 1 else 0
    held = set(order[:n_eval])
    return [r for i, r in enumerate(train) if i not in held], [r for i, r in enumerate(train) if i in held]


def read_stage_pairs(prefs_dir: Path) -> tuple[list[dict], list[dict]]:
    """(train rows, eval rows) from a prefs stage output directory (eval may be empty)."""
    prefs_dir = Path(prefs_dir)
    train = read_pairs(prefs_dir / "train.jsonl")
    ev = read_pairs(prefs_dir / "eval.jsonl") if (prefs_dir / "eval.jsonl").is_file() else []
    return train, ev


def training_pairs(ensure, train_file: str | None, eval_file: str | None, *, seed: int = 0,
                   columns: dict[str, str] | None = None) -> tuple[list[dict], list[dict], str, str]:
    """(train rows, eval rows, train source, eval source) for a trainer, unchecked (the trainer runs
    `check_pairs` with its tokenizer): a user file, or the prefs stage output (built if missing)."""
    if train_file:
        train, ev = load_pairs(train_file, eval_file, None, seed=seed, columns=columns)
        return train, ev, str(train_file), str(eval_file or train_file)
    prefs_dir = Path(ensure("prefs"))
    train, ev = read_stage_pairs(prefs_dir)
    if eval_file:
        ev = read_pairs(eval_file, columns, split="test")
    return train, ev, str(prefs_dir / "train.jsonl"), str(eval_file or prefs_dir / "eval.jsonl")


def strip_private(rows: list[dict]) -> list[dict]:
    return [{k: v for k, v in r.items() if not k.startswith("_")} for r in rows]


# ----------------------------------------------------------------------------- batches
# ----------------------------------------------------------------------------- the stage
def train(res, ensure) -> Path:
    """The prefs stage: write `final/{train,eval}.jsonl` (see the module docstring); returns final/."""
    from posttrain import tasks
    from posttrain.config import save_resolved
    from posttrain.data import save_rows
    from posttrain.models import load_model, load_tokenizer

    cfg: PrefsConfig = res.stage_cfg
    run_dir = res.stage_dir()
    if cfg.train_file:
        train_rows, eval_rows = load_pairs(cfg.train_file, cfg.eval_file, cfg.on_bad_rows,
                                           eval_fraction=cfg.eval_fraction, seed=cfg.seed,
                                           columns=res.task.columns.mapping())
        stats: dict[str, Any] = {"source": "file", "train_file": cfg.train_file, "eval_file": cfg.eval_file}
        accelerator = loop.setup(cfg.seed, res.run.threads)
        say = loop.main_printer(accelerator)
        say(f"[prefs] {len(train_rows)} training and {len(eval_rows)} held-out pairs from {cfg.train_file}")
    else:
        prompts = tasks.load_split(res.task, "train")[: cfg.n_prompts]
        eval_prompts = tasks.load_split(res.task, "eval")[: cfg.n_eval_prompts]
        labeler = gold_labeler(res.task.name)  # before any model loads: a task without gold fails here
        sft_dir = ensure("sft")
        accelerator = loop.setup(cfg.seed, res.run.threads)
        say = loop.main_printer(accelerator)
        tokenizer = load_tokenizer(sft_dir, res.model)
        model = load_model(sft_dir, res.model.dtype, device=accelerator.device)
        say(f"[prefs] sampling {cfg.samples_per_prompt} completions for {len(prompts)} training and "
            f"{len(eval_prompts)} held-out prompts from {sft_dir} (temperature {cfg.temperature})")
        common = dict(samples_per_prompt=cfg.samples_per_prompt, pairs_per_prompt=cfg.pairs_per_prompt,
                      temperature=cfg.temperature, top_p=cfg.top_p, max_new_tokens=cfg.max_new_tokens,
                      seed=cfg.seed)

        def sharded(rows: list[dict], key_offset: int) -> tuple[list[dict], dict[str, int]]:
            # each process samples its shard; prompt keys (dataset indices) make samples independent of it
            idx = list(range(len(rows)))[accelerator.process_index::accelerator.num_processes]
            out, st = sample_pairs(model, tokenizer, [rows[i] for i in idx], labeler,
                                   prompt_keys=[key_offset + i for i in idx], **common)
            if accelerator.num_processes > 1:
                from accelerate.utils import gather_object

                out = sorted(gather_object(out), key=lambda r: r["meta"]["pair"]["prompt_index"])
                sts = gather_object([st])
                st = {k: sum(s[k] for s in sts) for k in st}
            return out, st

        train_rows, s_train = sharded(prompts, 0)
        # held-out prompts get their own key range so they never share random streams with training prompts
        eval_rows, s_eval = sharded(eval_prompts, 10**9)
        stats = {"source": "sampled", "model": str(sft_dir), "train": s_train, "eval": s_eval}
        say(f"[prefs] {s_train['pairs']} training pairs ({s_train['prompts_all_tied']} prompts skipped: all "
            f"samples tied), {s_eval['pairs']} held-out pairs")
        if not train_rows:
            raise DataError(f"prefs: no pairs: every prompt's {cfg.samples_per_prompt} samples tied under the gold "
                            "preference; raise samples_per_prompt or temperature")
    final = run_dir / "final"
    if not accelerator.is_main_process:
        accelerator.wait_for_everyone()
        return final
    loop.prepare_run_dir(run_dir, False, say)
    save_resolved(res, run_dir / "config.yaml")
    tmp = run_dir / "final.tmp"
    shutil.rmtree(tmp, ignore_errors=True)
    save_rows(strip_private(train_rows), tmp / "train.jsonl")
    if eval_rows:
        save_rows(strip_private(eval_rows), tmp / "eval.jsonl")
    stats["chosen_keys"] = _key_histogram(train_rows, "chosen_key")
    stats["rejected_keys"] = _key_histogram(train_rows, "rejected_key")
    loop.write_json(run_dir / "stats.json", stats)
    if final.exists():
        shutil.rmtree(final)
    tmp.rename(final)  # atomic: final/ exists whole or not at all
    say(f"[prefs] wrote {final}/train.jsonl ({len(train_rows)} pairs) and eval.jsonl ({len(eval_rows)} pairs)")
    accelerator.wait_for_everyone()
    return final


def _key_histogram(rows: list[dict], which: str) -> dict[str, int]:
    c = Counter(json.dumps(((r.get("meta") or {}).get("pair") or {}).get(which)) for r in rows)
    return dict(c.most_common(10))


# ----------------------------------------------------------------------------- log-probs of pairs
def pair_logps(model, batch: dict[str, torch.Tensor]) -> tuple[torch.Tensor, torch.Tensor]:
    """Summed completion log-probs (2B,) and completion token counts (2B,) of a `collate_pairs` batch, chosen
    first then rejected, in either layout (two rows per pair, or one shared-prompt row: `collate_shared_prompt`), in
    ONE forward; differentiable under autograd (DPO's policy term, and its reference)."""
    if "allowed" in batch:  # shared prompt: one row per pair, prompt + chosen + rejected
        lp = packed_logprobs(model, batch["input_ids"], batch["position_ids"], batch["allowed"],
                             batch["pred_index"], batch["targets"], batch["target_mask"])  # (B, Lc + Lr)
        Lc = int(batch["chosen_cols"])
        cm = batch["target_mask"].to(lp.device, lp.dtype)
        return (torch.cat([lp[:, :Lc].sum(-1), lp[:, Lc:].sum(-1)]),
                torch.cat([cm[:, :Lc].sum(-1), cm[:, Lc:].sum(-1)]))  # (2B,), (2B,)
    logps, _ = sequence_logprobs(model, batch["input_ids"], batch["attention_mask"], batch["completion_mask"])  # (2B, T)
    cm = batch["completion_mask"].to(logps.device)
    return masked_sum(logps, cm, -1), cm.sum(-1).to(logps.dtype)  # (2B,), (2B,)


def by_side(s: torch.Tensor, n: torch.Tensor, B: int) -> dict[str, torch.Tensor]:
    """`pair_logps`' (2B,) sums and token counts as {"chosen", "rejected", "chosen_tokens", "rejected_tokens"} (B,)."""
    return {"chosen": s[:B], "rejected": s[B:], "chosen_tokens": n[:B], "rejected_tokens": n[B:]}


def pair_groups(pairs: Sequence[TokenizedPair], max_rows: int, max_tokens: int = 0,
                share_prompt: bool = False) -> list[list[int]]:
    """Indices of `pairs` in micro-batches of at most `max_rows` pairs and `max_tokens` padded tokens as
    `collate_pairs` lays them out: two rows per pair (prompt + the longer side), or one shared-prompt row
    (prompt + chosen + rejected); grouped by length (`data.token_groups`)."""
    if share_prompt:
        return token_groups([(0, len(p.prompt) + len(p.chosen) + len(p.rejected)) for p in pairs], max_rows,
                            max_tokens, by_length=True)
    return token_groups([(0, len(p.prompt) + max(len(p.chosen), len(p.rejected))) for p in pairs], max_rows,
                        max_tokens, rows_per_item=2, by_length=True)


@torch.no_grad()
def reference_logps(model, pairs: list[TokenizedPair], pad_id: int, micro_batch_size: int,
                    share_prompt: bool = True, max_tokens: int = 0) -> dict[str, torch.Tensor]:
    """The no-grad `pair_logps` of every pair, by side: {"chosen", "rejected", "chosen_tokens", "rejected_tokens"},
    (N,) tensors on CPU, one entry per pair (DPO's precomputed reference); micro-batches of at most
    `micro_batch_size` pairs and `max_tokens` padded tokens (`pair_groups`)."""
    was_training = model.training
    model.eval()
    groups = pair_groups(pairs, micro_batch_size, max_tokens, share_prompt)
    parts = [by_side(*pair_logps(model, collate_pairs([pairs[i] for i in g], pad_id, share_prompt)), len(g))
             for g in groups]
    model.train(was_training)
    where = torch.tensor([i for g in groups for i in g], dtype=torch.long)  # the pairs' positions, group by group
    out = {}
    for k in ("chosen", "rejected", "chosen_tokens", "rejected_tokens"):
        got = torch.cat([p[k].cpu() for p in parts]) if parts else torch.zeros(0)
        out[k] = torch.empty_like(got).index_copy_(0, where, got) if parts else got
    return out
