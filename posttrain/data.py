"""Loading, validating and saving the row schemas posttrain trains on.

    from posttrain.data import load_rows
    ds = load_rows("data/train.jsonl", "sft")          # a datasets.Dataset, every row checked

Schemas (full text with examples in data/README.md):
- ``sft``:        ``prompt: str``, ``completion: str``, optional ``meta``.
- ``preference``: ``prompt: str``, ``chosen: str``, ``rejected: str``, optional ``meta``.
- ``verifiable``: ``prompt: str``, ``answer: str | JSON object``, ``verifier: str``, optional ``meta``.
- ``prompt``:     ``prompt: str``, optional ``meta`` (prompts to sample from, e.g. ``distill.train_file``).
- ``unpaired``:   ``prompt``, ``completion``, and a boolean ``label`` (KTO; read by posttrain.preferences).
Text fields must be strings with at least one non-space character; ``answer`` is non-empty
text or a non-empty JSON object (numbers must be written as text: ``"42"``); ``meta`` is a
JSON object or null. Other fields are ignored and dropped.

Conversational rows (TRL's formats; data/README.md): a prompt may be a list of messages, an SFT row may
be a ``messages`` conversation or have conversational prompt/completion, a preference row may have
conversational sides or the implicit-prompt form. `normalize_row` brings each into posttrain's form (a
conversational SFT row keeps ``messages`` and ``train_from`` for the assistant-only loss of
`tokenize_completions`); every row of a source must have the format of its first row, and `load_rows`
says that format. ``columns`` ({our field: their column}, ``task.columns``) renames a source's columns.

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
import re
import tempfile
from dataclasses import dataclass
from pathlib import Path
from typing import Any, Iterable, Iterator, Literal, Sequence

import datasets
import torch

from posttrain.chat import ROLES, encode_conversation, encode_prompts, is_conversation, messages_problem
from posttrain.errors import DataError

Schema = Literal["sft", "preference", "verifiable", "prompt", "unpaired"]

TEXT_FIELDS: dict[str, tuple[str, ...]] = {
    "sft": ("prompt", "completion"),
    "preference": ("prompt", "chosen", "rejected"),
    "verifiable": ("prompt", "answer", "verifier"),  # answer: text or a JSON object
    "prompt": ("prompt",),  # prompts only (on-policy distillation without a verifier)
    "unpaired": ("prompt", "completion"),  # + a boolean label (KTO; posttrain.preferences reads these files)
}
JSON_FIELDS = ("answer", "meta")  # stored as f"{name}_json" text columns
CONVERSATION_FIELDS = ("prompt", "messages")  # conversations, stored as f"{name}_json" text columns too
SFT_CONVERSATION = ("messages", "train_from")  # what a conversational SFT row carries besides prompt/completion
STORED_JSON = JSON_FIELDS + CONVERSATION_FIELDS
COLUMN_NAMES = ("prompt", "completion", "chosen", "rejected", "answer", "messages", "label", "verifier", "meta")
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
    """(field or None, problem) for the first thing wrong with `row` (in posttrain's form: see `normalize_row`),
    or None if it is valid."""
    if not isinstance(row, dict):
        return None, f"expected a JSON object, got {_json_type(row)}"
    for field in TEXT_FIELDS[schema]:
        if field not in row:
            return field, "missing"
        value = row[field]
        if field == "prompt" and isinstance(value, list):
            problem = _prompt_problem(value)
            if problem:
                return field, problem
            continue
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


# --- conversations ------------------------------------------------------------------------------

class _Bad(Exception):
    """A row problem found while bringing a row into posttrain's form: (field, what)."""

    def __init__(self, field: str | None, what: str):
        super().__init__(field, what)
        self.field, self.what = field, what


def _prompt_problem(messages: list) -> str | None:
    problem = messages_problem(messages)
    if problem:
        return problem
    if messages[-1]["role"] == "assistant":
        return ("a conversational prompt must not end with an assistant turn (the model writes the next one); "
                "move the last assistant message to the completion")
    return None


def _conversation(row: dict, field: str, *, prompt: bool = False) -> list[dict] | str:
    """`row[field]` as text (unchanged) or a checked list of messages; _Bad when it is neither."""
    value = row[field]
    if isinstance(value, str):
        return value
    problem = _prompt_problem(value) if prompt else messages_problem(value)
    if problem:
        raise _Bad(field, problem)
    return [dict(m) for m in value]


def _reply(value: list[dict] | str, field: str) -> str:
    """A completion side as text: text itself, or a conversation of exactly one assistant message."""
    if isinstance(value, str):
        return value
    if len(value) != 1 or value[0]["role"] != "assistant":
        roles = ", ".join(m["role"] for m in value)
        raise _Bad(field, f"expected one assistant message, got {len(value)} message(s) ({roles}); a preference side "
                          "is one assistant reply")
    return value[0]["content"]


def _as_user(prompt: list[dict] | str) -> list[dict]:
    return [{"role": "user", "content": prompt}] if isinstance(prompt, str) else prompt


def _rename(row: dict, columns: dict[str, str]) -> dict:
    """`row` with its columns renamed to posttrain's names (`task.columns`: {our name: their name})."""
    row = dict(row)
    for ours, theirs in columns.items():
        if theirs == ours:
            continue
        if theirs not in row:
            if ours in row:
                continue  # the row already uses our name
            raise _Bad(theirs, f"missing (task.columns.{ours}={theirs} names it)")
        row[ours] = row.pop(theirs)
    return row


def normalize_row(row: Any, schema: Schema, columns: dict[str, str] | None = None) -> tuple[Any, str]:
    """(`row` in posttrain's form, the name of its format); raises _Bad(field, problem).

    Text rows pass unchanged. Conversational rows (TRL's formats) become:
    - sft `messages` (a whole conversation ending with an assistant turn; every assistant turn trained) and
      conversational sft `prompt` / `completion` (the completion's assistant turns trained): `messages` (the
      whole conversation), `train_from` (index of the first trained message), `prompt` (the messages before
      the last assistant turn) and `completion` (that turn's text: what generation is compared against).
    - preference `prompt` / `chosen` / `rejected` with conversational sides: each side the text of its one
      assistant message; the implicit-prompt form (no `prompt`; `chosen` and `rejected` whole conversations)
      gets their shared leading messages as its prompt.
    - any `prompt` that is a list of messages stays one (`posttrain.chat` renders it).
    """
    if not isinstance(row, dict):
        return row, "text"
    if columns:
        row = _rename(row, columns)
    if schema == "sft" and "messages" in row:
        ours = isinstance(row.get("train_from"), int) and not isinstance(row["train_from"], bool)
        if ("prompt" in row or "completion" in row) and not ours:
            raise _Bad("messages", "a row has either 'messages' or 'prompt'/'completion', not both")
        messages = _conversation(row, "messages")
        if isinstance(messages, str):
            raise _Bad("messages", "expected a list of messages, got text")
        if messages[-1]["role"] != "assistant":
            raise _Bad("messages", f"the conversation ends with a {messages[-1]['role']} turn; it must end with the "
                                   "assistant reply that is trained on")
        if len(messages) < 2:
            raise _Bad("messages", "a single assistant message has no prompt; start the conversation with a user turn")
        train_from = row["train_from"] if ours else 0  # a row saved in posttrain's form keeps its trained turns
        if not 0 <= train_from < len(messages):
            raise _Bad("train_from", f"{train_from} is not the index of a message (0-{len(messages) - 1})")
        rest = {k: v for k, v in row.items() if k not in ("messages", "prompt", "completion", "train_from")}
        return {**rest, "prompt": messages[:-1], "completion": messages[-1]["content"], "messages": messages,
                "train_from": train_from}, "conversational (messages)" if train_from == 0 else "conversational"
    if schema == "preference" and all(isinstance(row.get(f), list) for f in ("chosen", "rejected")) and (
            "prompt" not in row or any(m.get("role") != "assistant" for m in row["chosen"][:1] if isinstance(m, dict))):
        # the implicit prompt (TRL), also when a `prompt` repeats it (HuggingFaceH4/ultrafeedback_binarized)
        chosen, rejected = _conversation(row, "chosen"), _conversation(row, "rejected")
        shared = 0
        while shared < min(len(chosen), len(rejected)) and chosen[shared] == rejected[shared]:
            shared += 1
        if shared == 0:
            raise _Bad("chosen", "no prompt: 'chosen' and 'rejected' share no leading messages (the implicit prompt is "
                                 "their common prefix); add a 'prompt' field or start both with the same turns")
        prompt = chosen[:shared]
        if prompt[-1]["role"] == "assistant":
            raise _Bad("chosen", "the messages 'chosen' and 'rejected' share end with an assistant turn; the "
                                 "implicit prompt must end with a user turn")
        given = row.get("prompt")
        if given is not None and given != prompt and not (isinstance(given, str) and given == prompt[-1]["content"]):
            raise _Bad("prompt", "differs from the turns 'chosen' and 'rejected' share (their implicit prompt); drop "
                                 "it or make the conversations start with it")
        return {**row, "prompt": prompt, "chosen": _reply(chosen[shared:] or [], "chosen"),
                "rejected": _reply(rejected[shared:] or [], "rejected")}, "conversational (implicit prompt)"
    fields = TEXT_FIELDS[schema]
    present = [f for f in fields if f in row and f in ("prompt", "completion", "chosen", "rejected")]
    if not any(isinstance(row[f], list) for f in present):
        return row, "text"
    out = dict(row)
    for f in present:
        if not isinstance(row[f], (str, list)):
            continue  # _row_problem names the wrong type
        out[f] = _conversation(row, f, prompt=f == "prompt")
    if schema == "sft" and "completion" in present and "prompt" in present:
        completion = out["completion"]
        completion = [{"role": "assistant", "content": completion}] if isinstance(completion, str) else completion
        if completion[-1]["role"] != "assistant":
            raise _Bad("completion", f"the completion ends with a {completion[-1]['role']} turn; it must end with an "
                                     "assistant reply")
        messages = _as_user(out["prompt"]) + completion
        out.update(prompt=messages[:-1], completion=messages[-1]["content"], messages=messages,
                   train_from=len(messages) - len(completion))
    elif schema in ("preference", "unpaired"):
        for f in ("chosen", "rejected", "completion"):
            if f in present:
                out[f] = _reply(out[f], f)
    return out, "conversational"


def normalized_row(row: Any, schema: Schema, source: str, number: int,
                   columns: dict[str, str] | None = None) -> tuple[Any, str]:
    """`normalize_row` with its problems as DataErrors naming `source` and row `number`."""
    try:
        return normalize_row(row, schema, columns)
    except _Bad as e:
        raise _error(source, number, (e.field, e.what)) from None


class _Checker:
    """Brings each row of one source into posttrain's form and checks it (DataError with source, row and field);
    every row of a source must have the format of its first row."""

    def __init__(self, schema: Schema, columns: dict[str, str] | None = None):
        self.schema, self.columns = schema, columns or {}
        self.format: str | None = None
        self.first: int = 0

    def __call__(self, row: Any, source: str, number: int) -> dict:
        row, fmt = normalized_row(row, self.schema, source, number, self.columns)
        problem = _row_problem(row, self.schema)
        if problem:
            raise _error(source, number, problem)
        if self.format is None:
            self.format, self.first = fmt, number
        elif fmt != self.format:
            raise DataError(f"{source}: row {number}: {fmt}, but row {self.first} is {self.format}; one format per "
                            "source (convert the rows, or split the file)")
        return row


def _error(source: str, row_number: int, problem: tuple[str | None, str]) -> DataError:
    field, what = problem
    where = f"{source}: row {row_number}: "
    return DataError(where + (f"field '{field}': {what}" if field else what))


def validate_rows(rows: Iterable[dict], schema: Schema, source_name: str = "<rows>") -> None:
    """Raise DataError on the first invalid row (rows numbered from 1 by position)."""
    _check_schema(schema)
    check = _Checker(schema)
    for number, row in enumerate(rows, start=1):
        check(row, source_name, number)


# --- reading ------------------------------------------------------------------------------

def _decode_stored(row: dict, source: str, number: int) -> dict:
    """Turn `answer_json`/`meta_json`/`prompt_json`/`messages_json` text columns (our storage layout) back into
    values."""
    for name in STORED_JSON:
        stored = f"{name}_json"
        if stored in row:
            text = row.pop(stored)
            try:
                row[name] = json.loads(text) if text is not None else None
            except (TypeError, json.JSONDecodeError) as e:
                raise DataError(f"{source}: row {number}: field '{stored}': malformed JSON ({e})") from None
    return row


def _read_jsonl(path: Path, check: _Checker) -> Iterator[dict]:
    try:
        with path.open(encoding="utf-8") as f:
            for number, line in enumerate(f, start=1):
                if not line.strip():
                    continue
                try:
                    row = json.loads(line.rstrip("\r\n"))  # so an error's column stays on this line
                except json.JSONDecodeError as e:
                    raise DataError(f"{path}: row {number}: malformed JSON: {e.msg} (column {e.colno})") from None
                yield check(row, str(path), number)
    except UnicodeDecodeError as e:
        raise DataError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None


def _read_json(path: Path, check: _Checker) -> Iterator[dict]:
    try:
        data = json.loads(path.read_text(encoding="utf-8"))
    except json.JSONDecodeError as e:
        if e.msg == "Extra data":  # several JSON values: JSON Lines under a .json name
            yield from _read_jsonl(path, check)
            return
        raise DataError(f"{path}: malformed JSON: {e.msg} (line {e.lineno}, column {e.colno})") from None
    except UnicodeDecodeError as e:
        raise DataError(f"{path}: not UTF-8 text ({e.reason} at byte {e.start})") from None
    if isinstance(data, dict):  # a single object on one line is one JSON Lines row
        data = [data]
    if not isinstance(data, list):
        raise DataError(f"{path}: expected a JSON array of row objects (or JSON Lines), got {_json_type(data)}")
    for number, row in enumerate(data, start=1):
        yield check(row, str(path), number)


def _read_table_rows(rows: list[dict], source: str, check: _Checker) -> Iterator[dict]:
    for number, row in enumerate(rows, start=1):
        yield check(_decode_stored(dict(row), source, number), source, number)


def _read_parquet(path: Path, check: _Checker) -> Iterator[dict]:
    import pyarrow as pa
    import pyarrow.parquet as pq

    try:
        table = pq.read_table(path)
    except (pa.ArrowInvalid, OSError) as e:
        raise DataError(f"{path}: not a readable parquet file ({e})") from None
    yield from _read_table_rows(table.to_pylist(), str(path), check)


def _read_saved(path: Path, check: _Checker) -> Iterator[dict]:
    loaded = datasets.load_from_disk(str(path))
    if isinstance(loaded, datasets.DatasetDict):
        splits = list(loaded)
        if len(splits) != 1:
            raise DataError(f"{path}: a DatasetDict with splits {', '.join(splits)}; "
                            f"point at one split directory, e.g. {path / splits[0]}")
        path, loaded = path / splits[0], loaded[splits[0]]
    yield from _read_table_rows(loaded.with_format(None).to_list(), str(path), check)


def _read_file(path: Path, check: _Checker) -> Iterator[dict]:
    suffix = path.suffix.lower()
    if suffix == ".jsonl":
        return _read_jsonl(path, check)
    if suffix == ".json":
        return _read_json(path, check)
    if suffix == ".parquet":
        return _read_parquet(path, check)
    raise DataError(f"{path}: unsupported file type {path.suffix or '(no extension)'!r}; "
                    f"supported: {', '.join(LOAD_EXTENSIONS)}, or a dataset directory")


def _read_rows(path: Path, check: _Checker) -> list[dict]:
    if path.is_dir():
        if (path / "dataset_dict.json").exists() or (path / "state.json").exists():
            rows = list(_read_saved(path, check))
        else:
            files = sorted(p for p in path.iterdir() if p.is_file() and p.suffix.lower() in LOAD_EXTENSIONS)
            if not files:
                raise DataError(f"{path}: directory holds no {', '.join(LOAD_EXTENSIONS)} files "
                                "and is not a save_to_disk dataset")
            rows = [row for f in files for row in _read_file(f, check)]
    else:
        rows = list(_read_file(path, check))
    if not rows:
        raise DataError(f"{path}: no rows")
    return rows


# --- hub datasets -----------------------------------------------------------------------------------

HUB_OPTIONS = ("split", "subset", "revision")
_HUB_NAME = re.compile(r"[A-Za-z0-9][\w.-]*/[\w.-]+")


@dataclass(frozen=True)
class HubSource:
    """A Hugging Face hub dataset named as a source: `org/name`, or `org/name,split=S,subset=C,revision=R`."""

    name: str
    split: str
    subset: str | None = None
    revision: str | None = None


def hub_source(source: str | Path, default_split: str = "train") -> HubSource | None:
    """The hub dataset `source` names, or None when it is a local path (an existing file or directory, or a
    name that is not `org/name`). `default_split`: the split when none is given (train files: "train",
    eval files: "test")."""
    text = str(source)
    if Path(text).exists():
        return None
    name, *options = text.split(",")
    if not _HUB_NAME.fullmatch(name) or Path(name).suffix.lower() in LOAD_EXTENSIONS:
        return None
    given: dict[str, str] = {}
    for option in options:
        key, sep, value = option.partition("=")
        if not sep or key not in HUB_OPTIONS or not value:
            raise DataError(f"{text}: option {option!r} of a hub dataset: expected split=NAME, subset=NAME or "
                            "revision=REF (e.g. trl-lib/Capybara,split=test)")
        given[key] = value
    return HubSource(name, given.get("split", default_split), given.get("subset"), given.get("revision"))


def hub_rows(hub: HubSource, source: str) -> list[dict]:
    """The rows of a hub dataset's split through `datasets.load_dataset`: from the Hub when it can be reached,
    else (HF_HUB_OFFLINE=1 / HF_DATASETS_OFFLINE=1, or no network) from the local Hugging Face datasets cache;
    one DataError line when it is in neither."""
    import logging

    level = logging.getLogger("datasets").level
    logging.getLogger("datasets").setLevel(logging.ERROR)  # "Using the latest cached version ...": said below
    try:
        ds = datasets.load_dataset(hub.name, hub.subset, split=hub.split, revision=hub.revision)
    except (ConnectionError, FileNotFoundError) as e:
        from datasets import config

        offline = " (offline mode is on: HF_HUB_OFFLINE / HF_DATASETS_OFFLINE)" if config.HF_HUB_OFFLINE else ""
        raise DataError(f"{source}: no such local file or directory, and the Hugging Face hub dataset {hub.name!r} is "
                        f"neither in the local datasets cache ({config.HF_DATASETS_CACHE}) nor reachable{offline}; "
                        "load it once with network access, or give a local file") from None
    except Exception as e:  # noqa: BLE001 - unknown split / subset, a gated or missing repo: the library says which
        raise DataError(f"{source}: hub dataset {hub.name!r}: {' '.join(str(e).split())}") from None
    finally:
        logging.getLogger("datasets").setLevel(level)
    return ds.to_list()


def read_raw(source: str | Path, schema: Schema, columns: dict[str, str] | None = None,
             split: str = "train") -> tuple[list[dict], str, str]:
    """The rows of a file, directory or hub dataset in posttrain's form, each checked; their format
    (`normalize_row`); and where they came from (the hub split when it is one)."""
    check = _Checker(schema, columns)
    hub = hub_source(source, split)
    if hub is not None:
        rows = list(_read_table_rows(hub_rows(hub, str(source)), str(source), check))
        if not rows:
            raise DataError(f"{source}: no rows in split {hub.split!r}")
        where = f"{hub.name} (hub, split {hub.split}{f', subset {hub.subset}' if hub.subset else ''})"
        return rows, check.format or "text", where
    path = Path(source)
    if not path.exists():
        raise DataError(f"{path}: no such file or directory")
    return _read_rows(path, check), check.format or "text", str(path)


# --- the Dataset ------------------------------------------------------------------------------

def _storage_rows(rows: Sequence[dict], fields: Sequence[str]) -> list[dict]:
    """Rows as stored in Arrow: `fields` as they are, answer/meta (when any row has them) and conversations
    (a prompt or `messages` that is a list of messages) as JSON text."""
    json_fields = [name for name in JSON_FIELDS if any(name in row for row in rows)]
    json_fields += [name for name in CONVERSATION_FIELDS if name in fields and name not in json_fields
                    and any(isinstance(row.get(name), list) for row in rows)]
    return [
        {**{f: row.get(f) for f in fields if f not in json_fields},
         **{f"{name}_json": json.dumps(row.get(name), ensure_ascii=False) for name in json_fields}}
        for row in rows
    ]


def _decode_batch(batch: dict[str, list]) -> dict[str, list]:
    """Dataset transform: `answer_json`/`meta_json`/... text columns back to `answer`/`meta`/... values."""
    out = {}
    for key, values in batch.items():
        if key.endswith("_json") and key[: -len("_json")] in STORED_JSON:
            out[key[: -len("_json")]] = [json.loads(v) for v in values]
        else:
            out[key] = values
    return out


def to_dataset(rows: Sequence[dict], schema: Schema) -> datasets.Dataset:
    """Validated rows -> an in-memory Dataset with the schema's fields (+ meta when present; + messages and
    train_from for conversational SFT rows)."""
    fields = list(TEXT_FIELDS[schema]) + [f for f in SFT_CONVERSATION if any(f in row for row in rows)]
    storage = _storage_rows(rows, fields)
    ds = datasets.Dataset.from_list(storage)
    if any(c.endswith("_json") for c in ds.column_names):
        ds = ds.with_transform(_decode_batch)
    return ds


def load_rows(source: str | Path, schema: Schema, columns: dict[str, str] | None = None,
              say=None, split: str = "train") -> datasets.Dataset:
    """Load and validate every row of `source` (see the module docstring for formats; `org/name[,options]`: a
    hub dataset, `hub_source`). `columns`: {our field: the source's column} for sources named otherwise
    (`task.columns`). `say`: told the source's format. `split`: a hub dataset's split when it names none."""
    _check_schema(schema)
    rows, fmt, where = read_raw(source, schema, columns, split)
    if say is not None:
        say(f"[data] {where}: {len(rows)} rows, {fmt} {'/'.join(TEXT_FIELDS[schema])}"
            if fmt in ("text", "conversational") else f"[data] {where}: {len(rows)} rows, {fmt}")
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
def tokenize_completions(rows: list[dict], tokenizer, max_length: int) -> tuple[list[tuple], int]:
    """SFT rows -> token items and the number of rows dropped because they exceed `max_length`.

    A text row {"prompt", "completion"} gives (prompt_ids, completion_ids + eos). A conversational row (its
    `messages`, `normalize_row`) gives (prompt_ids, completion_ids, trained): the last assistant turn is the
    completion, and `trained` lists the (start, end) token spans of earlier assistant turns that the loss
    covers too (`posttrain.chat.encode_conversation`)."""
    plain = [i for i, r in enumerate(rows) if "messages" not in r]
    items: list[tuple | None] = [None] * len(rows)
    # Prompts rendered (chat template) and tokenized exactly as the rollout engine does (posttrain.chat).
    prompts = encode_prompts(tokenizer, [rows[i]["prompt"] for i in plain])
    comps = tokenizer([rows[i]["completion"] for i in plain], add_special_tokens=False)["input_ids"] if plain else []
    for i, p, c in zip(plain, prompts, comps):
        items[i] = (p, c + [tokenizer.eos_token_id])
    for i, r in enumerate(rows):
        if items[i] is None:
            p, c, trained = encode_conversation(tokenizer, r["messages"], r.get("train_from", 0))
            items[i] = (p, c, trained) if trained else (p, c)
    out = [x for x in items if len(x[0]) + len(x[1]) <= max_length]
    return out, len(rows) - len(out)


def collate_completions(items: list[tuple], pad_id: int) -> dict[str, torch.Tensor]:
    """Right-padded batch of `tokenize_completions` items ((prompt, completion) or (prompt, completion,
    trained)): input_ids, attention_mask, completion_mask (completion tokens and the trained spans), all (B, T)."""
    T = max(len(x[0]) + len(x[1]) for x in items)
    B = len(items)
    input_ids = torch.full((B, T), pad_id, dtype=torch.long)
    attention_mask = torch.zeros((B, T), dtype=torch.long)
    completion_mask = torch.zeros((B, T), dtype=torch.bool)
    for i, (p, c, *trained) in enumerate(items):
        n = len(p) + len(c)
        input_ids[i, :n] = torch.tensor(p + c)
        attention_mask[i, :n] = 1
        completion_mask[i, len(p):n] = True
        for a, b in (trained[0] if trained else ()):
            completion_mask[i, a:b] = True
    return {"input_ids": input_ids, "attention_mask": attention_mask, "completion_mask": completion_mask}


# ----------------------------------------------------------------------------- preference pairs as tokens
@dataclass
class TokenizedPair:
    """Token ids of one pair: prompt (with the tokenizer's special tokens), each completion (+ eos)."""

    prompt: list[int]
    chosen: list[int]
    rejected: list[int]
    row: int  # 1-based row number in its source



def collate_pairs(pairs: Sequence[TokenizedPair], pad_id: int, share_prompt: bool = False) -> dict[str, torch.Tensor]:
    """One right-padded batch holding the chosen rows first, then the rejected rows: (2B, T) tensors.

    input_ids, attention_mask, completion_mask (the completion tokens incl. eos). Chosen and
    rejected go through the model in ONE forward pass (concatenated along the batch, as TRL's
    `concatenated_forward`); row i and row B + i are the two sides of pair i.
    share_prompt=True: the packed layout of `collate_shared_prompt` instead (the prompt once per pair).
    """
    if share_prompt:
        return collate_shared_prompt(pairs, pad_id)
    # two right-padded rows per pair, (2B, T): prompt + chosen, then prompt + rejected
    return collate_completions([(p.prompt, p.chosen) for p in pairs] + [(p.prompt, p.rejected) for p in pairs], pad_id)



def collate_shared_prompt(pairs: Sequence[TokenizedPair], pad_id: int) -> dict[str, torch.Tensor]:
    """One row per pair: prompt, chosen, rejected, right-padded (B, T), for `logprobs.packed_logprobs`.

    The rejected tokens attend to the prompt and to themselves, never to the chosen tokens, and their
    positions continue from the prompt as if chosen were absent; so each side's log-probs equal those of
    its own (prompt + completion) row, while the prompt is computed once per pair instead of twice
    (prefix sharing). Keys: input_ids, position_ids (B, T); allowed (B, T, T) bool (query, key);
    pred_index / targets / target_mask (B, Lc + Lr): chosen tokens in columns [:Lc], rejected in [Lc:],
    each with the column whose logits predict it (the last prompt column predicts the first token of
    both sides); chosen_cols = Lc. Pad columns attend only to themselves (their outputs are never read).
    """
    B = len(pairs)
    T = max(len(p.prompt) + len(p.chosen) + len(p.rejected) for p in pairs)
    Lc = max(len(p.chosen) for p in pairs)
    L = Lc + max(len(p.rejected) for p in pairs)
    input_ids = torch.full((B, T), pad_id, dtype=torch.long)  # (B, T)
    position_ids = torch.zeros((B, T), dtype=torch.long)  # (B, T)
    allowed = torch.eye(T, dtype=torch.bool).repeat(B, 1, 1)  # (B, T, T)
    causal = torch.ones(T, T, dtype=torch.bool).tril()  # (T, T)
    pred_index = torch.zeros((B, L), dtype=torch.long)  # (B, Lc + Lr)
    targets = torch.zeros((B, L), dtype=torch.long)  # (B, Lc + Lr)
    target_mask = torch.zeros((B, L), dtype=torch.bool)  # (B, Lc + Lr)
    for b, p in enumerate(pairs):
        P, C, R = len(p.prompt), len(p.chosen), len(p.rejected)
        n = P + C + R
        input_ids[b, :n] = torch.tensor(p.prompt + p.chosen + p.rejected)
        position_ids[b, :P + C] = torch.arange(P + C)
        position_ids[b, P + C:n] = torch.arange(P, P + R)
        allowed[b, :n, :n] = causal[:n, :n]
        allowed[b, P + C:n, P:P + C] = False  # rejected never sees chosen
        pred_index[b, :C] = torch.arange(P - 1, P + C - 1)
        pred_index[b, Lc] = P - 1
        pred_index[b, Lc + 1:Lc + R] = torch.arange(P + C, n - 1)
        targets[b, :C] = torch.tensor(p.chosen)
        targets[b, Lc:Lc + R] = torch.tensor(p.rejected)
        target_mask[b, :C] = True
        target_mask[b, Lc:Lc + R] = True
    return {"input_ids": input_ids, "position_ids": position_ids, "allowed": allowed, "pred_index": pred_index,
            "targets": targets, "target_mask": target_mask, "chosen_cols": torch.tensor(Lc)}


def to_device(batch: dict[str, Any], device) -> dict[str, Any]:
    """A collated batch with its tensors on `device` (the model's): the one place per step where a batch built on
    the host moves, so everything computed from it (masks, weights, log-probs) lives beside the model. Non-tensor
    values pass through; tensors already there are not copied."""
    return {k: v.to(device, non_blocking=True) if isinstance(v, torch.Tensor) else v for k, v in batch.items()}


def token_groups(spans: Sequence[tuple[int, int]], max_rows: int = 0, max_tokens: int = 0,
                 rows_per_item: int = 1, by_length: bool = False) -> list[list[int]]:
    """Groups of item indices for micro-batches: each group's padded size, rows x (its widest column span: max
    end - min start, the columns a trimmed batch keeps), stays within `max_tokens`, and it has at most
    `max_rows` items (0: no limit on either). An item (`rows_per_item` rows: 2 for a preference pair) wider
    than the budget forms a group alone. spans: (start, end) columns of each item's tokens (unpadded lists:
    (0, length)).

    Groups are runs of consecutive items, or with `by_length` runs of the items ordered by width (then start),
    so that short rows are padded to short rows and a step needs fewer, less padded micro-batches. Unlike
    transformers' `group_by_length`, which orders the whole dataset by length, this regroups the rows of one
    step only: the step's gradient is the same sum. Each group lists its indices in ascending order and groups
    come in the order of their first index, so a single group is the items as they were."""
    if by_length:
        order = sorted(range(len(spans)), key=lambda i: (spans[i][1] - spans[i][0], spans[i][0]))
        runs = token_groups([spans[i] for i in order], max_rows, max_tokens, rows_per_item)
        return sorted((sorted(order[j] for j in g) for g in runs), key=lambda g: g[0])
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
