"""Loading, validating and saving the row schemas posttrain trains on.

    from posttrain.data import load_rows
    ds = load_rows("data/train.jsonl", "sft")          # a datasets.Dataset, every row checked

Schemas (full text with examples in data/README.md):
- ``sft``:        ``prompt: str``, ``completion: str``, optional ``meta``.
- ``preference``: ``prompt: str``, ``chosen: str``, ``rejected: str``, optional ``meta``.
- ``verifiable``: ``prompt: str``, ``answer: str | JSON object``, ``verifier: str``, optional ``meta``.
- ``prompt``:     ``prompt: str``, optional ``meta`` (prompts to sample from, e.g. ``distill.train_file``).
Text fields must be strings with at least one non-space character; ``answer`` is non-empty
text or a non-empty JSON object (numbers must be written as text: ``"42"``); ``meta`` is a
JSON object or null. Other fields are ignored and dropped.

Sources: a ``.jsonl`` file, a ``.json`` file (an array of objects, or JSON Lines), a
``.parquet`` file, or a local directory: either ``Dataset.save_to_disk`` output (a
``DatasetDict`` with exactly one split is accepted too) or a directory of
``.jsonl``/``.json``/``.parquet`` files, read in name order.

Errors are one line, ``DataError("<file>: row <N>: field '<name>': <problem>")``, raised
at the first bad row. N is 1-based everywhere: for JSONL (and ``.json`` holding JSON Lines)
it is the line number in the file, blank lines included; for a JSON array, a parquet file
or a saved dataset it is the row's position.

How a file is read, and why it departs from ``datasets.load_dataset``:
- Files are read with the ``json`` module line by line (JSONL) or ``pyarrow`` (parquet,
  the engine ``datasets`` uses), each row is validated where its line number is known,
  and the ``datasets.Dataset`` is built in memory with ``Dataset.from_list``. The
  ``datasets`` JSON loader reports malformed lines without a line number, fails on a
  column mixing text and objects, and writes a cache under ~/.cache; this way has none
  of those.
- Arrow stores one type per column. ``answer`` (text in one row, an object in the next)
  and ``meta`` (free-form objects) do not fit, and merging objects with different keys
  would silently add ``None`` keys. So these two fields are stored as JSON text in the
  columns ``answer_json`` / ``meta_json``, and the returned dataset carries a transform
  (``Dataset.with_transform``) that decodes them on access: ``ds[0]["answer"]``,
  ``ds[0]["meta"]``, iteration, ``select``, ``shuffle`` and ``map`` all see the original
  values. ``ds.column_names`` and ``to_list()/to_pandas()`` show the stored JSON text.
  ``save_rows(..., "x.parquet")`` and ``ds.with_format(None).save_to_disk(...)`` keep that
  layout and ``load_rows`` reads it back (``save_to_disk`` refuses a dataset carrying a
  transform, hence ``with_format(None)``). Datasets without answer/meta are plain, with
  no transform.
"""
from __future__ import annotations

import json
import os
import tempfile
from pathlib import Path
from typing import Any, Iterable, Iterator, Literal, Sequence

import datasets
import torch

from posttrain.chat import encode_prompts
from posttrain.errors import DataError  # noqa: F401  (raised here; importable from here as before)

Schema = Literal["sft", "preference", "verifiable", "prompt"]

TEXT_FIELDS: dict[str, tuple[str, ...]] = {
    "sft": ("prompt", "completion"),
    "preference": ("prompt", "chosen", "rejected"),
    "verifiable": ("prompt", "answer", "verifier"),  # answer: text or a JSON object
    "prompt": ("prompt",),  # prompts only (on-policy distillation without a verifier)
}
JSON_FIELDS = ("answer", "meta")  # stored as f"{name}_json" text columns
LOAD_EXTENSIONS = (".jsonl", ".json", ".parquet")
SAVE_EXTENSIONS = (".jsonl", ".parquet")



def _check_schema(schema: str) -> None:
    if schema not in TEXT_FIELDS:
        raise ValueError(f"unknown schema {schema!r}; expected one of: {', '.join(TEXT_FIELDS)}")


def _json_type(value: Any) -> str:
    if value is None:
        return "null"
    if isinstance(value, bool):
        return "boolean"
    if isinstance(value, (int, float)):
        return "number"
    if isinstance(value, str):
        return "text"
    if isinstance(value, (list, tuple)):
        return "list"
    if isinstance(value, dict):
        return "object"
    return type(value).__name__


def _row_problem(row: Any, schema: Schema) -> tuple[str | None, str] | None:
    """(field or None, problem) for the first thing wrong with `row`, or None if it is valid."""
    if not isinstance(row, dict):
        return None, f"expected a JSON object, got {_json_type(row)}"
    for field in TEXT_FIELDS[schema]:
        if field not in row:
            return field, "missing"
        value = row[field]
        if field == "answer":
            if isinstance(value, dict):
                if not value:
                    return field, "empty JSON object"
                continue
            if not isinstance(value, str):
                return field, (f"expected text or a JSON object, got {_json_type(value)}"
                               " (write numbers as text, e.g. \"42\")")
        elif not isinstance(value, str):
            return field, f"expected text, got {_json_type(value)}"
        if not value.strip():
            return field, "empty text"
    meta = row.get("meta")
    if meta is not None and not isinstance(meta, dict):
        return "meta", f"expected a JSON object or null, got {_json_type(meta)}"
    return None


def _error(source: str, row_number: int, problem: tuple[str | None, str]) -> DataError:
    field, what = problem
    where = f"{source}: row {row_number}: "
    return DataError(where + (f"field '{field}': {what}" if field else what))


def validate_rows(rows: Iterable[dict], schema: Schema, source_name: str = "<rows>") -> None:
    """Raise DataError on the first invalid row (rows numbered from 1 by position)."""
    _check_schema(schema)
    for number, row in enumerate(rows, start=1):
        problem = _row_problem(row, schema)
        if problem:
            raise _error(source_name, number, problem)


# --- reading ------------------------------------------------------------------------------

def _decode_stored(row: dict, source: str, number: int) -> dict:
    """Turn `answer_json`/`meta_json` text columns (our storage layout) back into values."""
    for name in JSON_FIELDS:
        stored = f"{name}_json"
        if stored in row:
            text = row.pop(stored)
            try:
                row[name] = json.loads(text) if text is not None else None
            except (TypeError, json.JSONDecodeError) as e:
                raise DataError(f"{source}: row {number}: field '{stored}': malformed JSON ({e})") from None
    return row


def _read_jsonl(path: Path, schema: Schema) -> Iterator[dict]:
    try:
        with path.open(encoding="utf-8") as f:
            for number, line in enumerate(f, start=1):
                if not line.strip():
                    continue
                try:
                    row = json.loads(line.rstrip("\r\n"))  # so an error's column stays on this line
                except json.JSONDecodeError as e:
                    raise DataError(f"{path}: row {number}: malformed JSON: {e.msg} (column {e.colno})") from None
                problem = _row_problem(row, schema)
                if problem:
                    raise _error(str(path), number, problem)
                yield row
    except UnicodeDecodeError as e:
        raise DataError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None


def _read_json(path: Path, schema: Schema) -> Iterator[dict]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        if e.msg == "Extra data":  # several JSON values: JSON Lines under a .json name
            yield from _read_jsonl(path, schema)
            return
        raise DataError(f"{path}: malformed JSON: {e.msg} (line {e.lineno}, column {e.colno})") from None
    except UnicodeDecodeError as e:
        raise DataError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    if isinstance(data, dict):  # a single object on one line is one JSON Lines row
        data = [data]
    if not isinstance(data, list):
        raise DataError(f"{path}: expected a JSON array of row objects (or JSON Lines), got {_json_type(data)}")
    for number, row in enumerate(data, start=1):
        problem = _row_problem(row, schema)
        if problem:
            raise _error(str(path), number, problem)
        yield row


def _read_table_rows(rows: list[dict], source: str, schema: Schema) -> Iterator[dict]:
    for number, row in enumerate(rows, start=1):
        row = _decode_stored(dict(row), source, number)
        problem = _row_problem(row, schema)
        if problem:
            raise _error(source, number, problem)
        yield row


def _read_parquet(path: Path, schema: Schema) -> Iterator[dict]:
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as e:
        raise DataError(f"{path}: not a readable parquet file ({e})") from None
    yield from _read_table_rows(table.to_pylist(), str(path), schema)


def _read_saved(path: Path, schema: Schema) -> Iterator[dict]:
    loaded = datasets.load_from_disk(str(path))
    if isinstance(loaded, datasets.DatasetDict):
        splits = list(loaded)
        if len(splits) != 1:
            raise DataError(f"{path}: a DatasetDict with splits {', '.join(splits)}; "
                            f"point at one split directory, e.g. {path / splits[0]}")
        path, loaded = path / splits[0], loaded[splits[0]]
    yield from _read_table_rows(loaded.with_format(None).to_list(), str(path), schema)


def _read_file(path: Path, schema: Schema) -> Iterator[dict]:
    suffix = path.suffix.lower()
    if suffix == ".jsonl":
        return _read_jsonl(path, schema)
    if suffix == ".json":
        return _read_json(path, schema)
    if suffix == ".parquet":
        return _read_parquet(path, schema)
    raise DataError(f"{path}: unsupported file type {path.suffix or '(no extension)'!r}; "
                    f"supported: {', '.join(LOAD_EXTENSIONS)}, or a dataset directory")


def _read_rows(path: Path, schema: Schema) -> list[dict]:
    if path.is_dir():
        if (path / "dataset_dict.json").exists() or (path / "state.json").exists():
            rows = list(_read_saved(path, schema))
        else:
            files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in LOAD_EXTENSIONS)
            if not files:
                raise DataError(f"{path}: directory holds no {', '.join(LOAD_EXTENSIONS)} files "
                                "and is not a save_to_disk dataset")
            rows = [row for f in files for row in _read_file(f, schema)]
    else:
        rows = list(_read_file(path, schema))
    if not rows:
        raise DataError(f"{path}: no rows")
    return rows


# --- the Dataset ------------------------------------------------------------------------------

def _storage_rows(rows: Sequence[dict], fields: Sequence[str]) -> list[dict]:
    """Rows as stored in Arrow: `fields` as they are, answer/meta (when any row has them) as JSON text."""
    json_fields = [name for name in JSON_FIELDS if any(name in row for row in rows)]
    return [
        {**{f: row.get(f) for f in fields if f not in JSON_FIELDS},
         **{f"{name}_json": json.dumps(row.get(name), ensure_ascii=False) for name in json_fields}}
        for row in rows
    ]


def _decode_batch(batch: dict[str, list]) -> dict[str, list]:
    """Dataset transform: `answer_json`/`meta_json` text columns back to `answer`/`meta` values."""
    out = {}
    for key, values in batch.items():
        if key.endswith("_json") and key[: -len("_json")] in JSON_FIELDS:
            out[key[: -len("_json")]] = [json.loads(v) for v in values]
        else:
            out[key] = values
    return out


def to_dataset(rows: Sequence[dict], schema: Schema) -> datasets.Dataset:
    """Validated rows -> an in-memory Dataset with the schema's fields (+ meta when present)."""
    storage = _storage_rows(rows, TEXT_FIELDS[schema])
    ds = datasets.Dataset.from_list(storage)
    if any(c.endswith("_json") for c in ds.column_names):
        ds = ds.with_transform(_decode_batch)
    return ds


def load_rows(source: str | Path, schema: Schema) -> datasets.Dataset:
    """Load and validate every row of `source` (see the module docstring for formats)."""
    _check_schema(schema)
    path = Path(source)
    if not path.exists():
        raise DataError(f"{path}: no such file or directory")
    rows = _read_rows(path, schema)
    return to_dataset(rows, schema)


# --- writing ----------------------------------------------------------------------------------

def save_rows(rows: Sequence[dict], path: str | Path) -> Path:
    """Write rows atomically (temporary file + rename): JSON Lines for .jsonl, parquet for .parquet.

    Parquet stores `answer`/`meta` as JSON text columns (`answer_json`/`meta_json`), which
    `load_rows` decodes; JSONL keeps them as JSON values.
    """
    path = Path(path)
    suffix = path.suffix.lower()
    if suffix not in SAVE_EXTENSIONS:
        raise DataError(f"{path}: cannot save as {path.suffix or '(no extension)'!r}; "
                        f"supported: {', '.join(SAVE_EXTENSIONS)}")
    if not rows:
        raise ValueError(f"save_rows({path}): no rows to save")
    path.parent.mkdir(parents=True, exist_ok=True)
    fd, tmp_name = tempfile.mkstemp(dir=path.parent, prefix=f".{path.name}.", suffix=".tmp")
    try:
        if suffix == ".jsonl":
            with os.fdopen(fd, "w", encoding="utf-8") as f:
                for row in rows:
                    f.write(json.dumps(row, ensure_ascii=False) + "\n")
                f.flush()
                os.fsync(f.fileno())
        else:
            os.close(fd)
            import pyarrow as pa
            import pyarrow.parquet as pq

            fields = list(dict.fromkeys(k for row in rows for k in row))
            pq.write_table(pa.Table.from_pylist(_storage_rows(rows, fields)), tmp_name)
        os.replace(tmp_name, path)
    except BaseException:
        Path(tmp_name).unlink(missing_ok=True)
        raise
    return path


# --- preference pairs ---------------------------------------------------------------------------

def clean_preference_rows(
    rows: Sequence[dict] | datasets.Dataset,
    on_bad: Literal["error", "skip"] = "error",
    source_name: str = "<rows>",
) -> tuple[list[dict] | datasets.Dataset, int]:
    """Handle pairs whose `chosen` equals `rejected` (compared after stripping whitespace).

    on_bad="error": DataError at the first such row. on_bad="skip": drop them and return
    how many were dropped. Rows that break the preference schema (a missing or empty
    `chosen`/`rejected`, ...) always raise. Rows are numbered from 1 by position. A Dataset
    comes back as a Dataset (`select`, transform kept), a list as a list.
    """
    if on_bad not in ("error", "skip"):
        raise ValueError(f"on_bad must be 'error' or 'skip', got {on_bad!r}")
    keep: list[int] = []
    for index, row in enumerate(rows):
        problem = _row_problem(row, "preference")
        if problem:
            raise _error(source_name, index + 1, problem)
        if row["chosen"].strip() == row["rejected"].strip():
            if on_bad == "error":
                raise DataError(f"{source_name}: row {index + 1}: field 'rejected': identical to 'chosen' "
                                "(set on_bad='skip' to drop such pairs)")
            continue
        keep.append(index)
    n_skipped = len(rows) - len(keep)
    if isinstance(rows, datasets.Dataset):
        return (rows.select(keep) if n_skipped else rows), n_skipped
    return [rows[i] for i in keep], n_skipped


# ----------------------------------------------------------------------------- SFT rows as tokens
def tokenize_completions(rows: list[dict], tokenizer, max_length: int) -> tuple[list[tuple[list[int], list[int]]], int]:
    """SFT rows {"prompt", "completion"} -> [(prompt_ids, completion_ids + eos)] and the number of rows dropped
    because prompt + completion exceeds `max_length`."""
    # Prompts rendered (chat template) and tokenized exactly as the rollout engine does (posttrain.chat).
    prompts = encode_prompts(tokenizer, [r["prompt"] for r in rows])
    comps = tokenizer([r["completion"] for r in rows], add_special_tokens=False)["input_ids"]
    out, dropped = [], 0
    for p, c in zip(prompts, comps):
        c = c + [tokenizer.eos_token_id]
        if len(p) + len(c) > max_length:
            dropped += 1
            continue
        out.append((p, c))
    return out, dropped


def collate_completions(pairs: list[tuple[list[int], list[int]]], pad_id: int) -> dict[str, torch.Tensor]:
    """Right-padded batch of `tokenize_completions` pairs: input_ids, attention_mask, completion_mask, all (B, T)."""
    T = max(len(p) + len(c) for p, c in pairs)
    B = len(pairs)
    input_ids = torch.full((B, T), pad_id, dtype=torch.long)
    attention_mask = torch.zeros((B, T), dtype=torch.long)
    completion_mask = torch.zeros((B, T), dtype=torch.bool)
    for i, (p, c) in enumerate(pairs):
        n = len(p) + len(c)
        input_ids[i, :n] = torch.tensor(p + c)
        attention_mask[i, :n] = 1
        completion_mask[i, len(p):n] = True
    return {"input_ids": input_ids, "attention_mask": attention_mask, "completion_mask": completion_mask}


def token_groups(spans: Sequence[tuple[int, int]], max_rows: int = 0, max_tokens: int = 0,
                 rows_per_item: int = 1) -> list[list[int]]:
    """Consecutive groups of item indices for micro-batches: each group's padded size, rows x (its widest
    column span: max end - min start, the columns a trimmed batch keeps), stays within `max_tokens`, and it
    has at most `max_rows` items (0: no limit on either). An item (`rows_per_item` rows: 2 for a preference
    pair) wider than the budget forms a group alone. spans: (start, end) columns of each item's tokens
    (unpadded lists: (0, length))."""
    groups: list[list[int]] = []
    cur: list[int] = []
    lo = hi = 0
    for i, (a, b) in enumerate(spans):
        nlo, nhi = (min(lo, a), max(hi, b)) if cur else (a, b)
        full = (max_rows and len(cur) >= max_rows) or \
            (max_tokens and (len(cur) + 1) * rows_per_item * (nhi - nlo) > max_tokens)
        if cur and full:
            groups.append(cur)
            cur, nlo, nhi = [], a, b
        cur.append(i)
        lo, hi = nlo, nhi
    if cur:
        groups.append(cur)
    return groups


def row_spans(attention_mask: torch.Tensor) -> list[tuple[int, int]]:
    """(first, last + 1) real column of each row of a (B, T) 0/1 mask, (0, 0) for an all-padding row: the
    `token_groups` spans of a padded batch."""
    real = attention_mask.bool()
    cols = torch.arange(real.shape[1], device=real.device)
    first = torch.where(real, cols, real.shape[1]).min(1).values
    last = torch.where(real, cols, -1).max(1).values + 1
    return [(int(a), int(b)) if b > 0 else (0, 0) for a, b in zip(first.tolist(), last.tolist())]
