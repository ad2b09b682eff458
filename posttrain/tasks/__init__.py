"""Seeded task generators with gold scorers (pure Python, no torch).

Every task module offers at least:
    make_examples(n, seed, split) -> list[{"prompt", "completion" | "answer", "meta"}]
    corpus(n, seed) -> list[str]                 # text for training the tokenizer
    evaluate(metas, completions) -> dict[str, float]

`TASKS` maps a recipe's `task.name` to its module; `get_task` imports it on first use.
"""
from __future__ import annotations

import importlib
from types import ModuleType

TASKS: dict[str, str] = {
    "tiny-summarize": "posttrain.tasks.summarize",
    "tiny-math": "posttrain.tasks.math",
    "tiny-countdown": "posttrain.tasks.countdown",
    "tiny-code": "posttrain.tasks.code",
}


def get_task(name: str) -> ModuleType:
    """The task module registered under `name`; a clear error lists the known names."""
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; known tasks: {', '.join(sorted(TASKS))}")
    return importlib.import_module(TASKS[name])


def _task_or_config_error(name: str) -> ModuleType:
    from posttrain.config import ConfigError

    try:
        return get_task(name)
    except ValueError as e:
        raise ConfigError(f"task.name: {e}") from None


def load_split(task_cfg, split: str) -> list[dict]:
    """The rows of `split` ("train" | "eval") for a recipe's `task:` section, validated.

    A file given as task.train_file / task.eval_file replaces the generated split; it is
    checked row by row (posttrain.data) before anything else happens.
    """
    from posttrain.data import load_rows, validate_rows

    file = task_cfg.train_file if split == "train" else task_cfg.eval_file
    if file:
        return [dict(r) for r in load_rows(file, "sft")]
    task = _task_or_config_error(task_cfg.name)
    n = task_cfg.n_train if split == "train" else task_cfg.n_eval
    rows = task.make_examples(n, task_cfg.seed, split)
    validate_rows(rows, "sft", f"task {task_cfg.name} ({split})")
    return rows


def tokenizer_corpus(task_cfg) -> list[str]:
    """Texts to train a tokenizer on: the training file's prompts and completions, or the task's corpus."""
    if task_cfg.train_file:
        rows = load_split(task_cfg, "train")
        return [r["prompt"] + r["completion"] for r in rows]
    return _task_or_config_error(task_cfg.name).corpus(task_cfg.n_train, task_cfg.seed)
