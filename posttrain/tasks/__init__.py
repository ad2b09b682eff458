"""Seeded task generators with gold scorers (pure Python, no torch).

A task is a module that provides what `Task` states (`get_task` checks every name, so a task written
against this protocol fails at once, naming what it lacks): a seeded generator of rows, a tokenizer
corpus, a held-out evaluation, and the gold signals it has, each either a function or None, so the
trainers ask `task.gold_quality is not None` (see `has_gold`), never `hasattr`.

`TASKS` maps a recipe's `task.name` to its module; `get_task` imports it on first use.
"""
from __future__ import annotations

import importlib
from types import ModuleType
from typing import Any, Callable, Literal, Mapping, Protocol, Sequence


class Task(Protocol):
    """What a task module provides. Optional capabilities are None when the task has no such signal."""

    NAME: str  # the recipe's task.name
    VERIFIER: str | None  # registry spec of the verifier of its answers (GRPO's verifier=auto); None: none
    GOLD_METRICS: Mapping[str, str]  # logged name -> key of `evaluate`'s dict (DPO / PPO log gold/<name>)

    def make_examples(self, n: int, seed: int, split: Literal["train", "eval"]) -> list[dict[str, Any]]:
        """Rows {"prompt", "completion" and/or "answer", "meta"}; a pure function of (n, seed, split)."""

    def corpus(self, n: int, seed: int) -> list[str]:
        """Texts to train the task's tokenizer on."""

    def evaluate(self, metas: Sequence[dict], completions: Sequence[str]) -> dict[str, float]:
        """Held-out metrics of completions (the keys GOLD_METRICS names among them)."""

    gold_quality: Callable[[dict, str], float] | None  # scalar gold score (GoldScorer, PPO reward=gold)
    gold_breakdown: Callable[[dict, str], dict] | None  # its terms (GoldScorer's length-aware reward)
    gold_key: Callable[[dict, str], Any] | None  # gold preference as a sort key (preference pairs, DPO labels)
    gold_prefer: Callable[[dict, str, str], int] | None  # +1 / 0 / -1 (wins / ties / losses counts)
    win_rate: Callable[[Sequence[dict], Sequence[str], Sequence[str]], float] | None  # ties count half


TASK_MEMBERS = ("NAME", "VERIFIER", "GOLD_METRICS", "make_examples", "corpus", "evaluate", "gold_quality",
                "gold_breakdown", "gold_key", "gold_prefer", "win_rate")


def check_task(module: ModuleType) -> Task:
    """`module` as a `Task`; a TypeError naming every member of the protocol it lacks."""
    missing = [m for m in TASK_MEMBERS if not hasattr(module, m)]
    if missing:
        raise TypeError(f"task module {module.__name__} lacks {', '.join(missing)} of posttrain.tasks.Task "
                        "(set an optional signal to None when the task has none)")
    return module  # type: ignore[return-value]


def has_gold(task: Task) -> bool:
    """The task has a gold score of a completion (gold metrics, win-rates, PPO's reward=gold)."""
    return task.gold_quality is not None or task.gold_breakdown is not None


def has_gold_preference(task: Task) -> bool:
    """The task ranks completions by a gold preference (preference pairs labelled by it, DPO's gold metrics)."""
    return task.gold_key is not None

TASKS: dict[str, str] = {
    "tiny-summarize": "posttrain.tasks.summarize",
    "tiny-math": "posttrain.tasks.math",
    "tiny-countdown": "posttrain.tasks.countdown",
    "tiny-code": "posttrain.tasks.code",
    "word-math": "posttrain.tasks.wordmath",
    "tiny-calc": "posttrain.tasks.calc",
    "tiny-calc-direct": "posttrain.tasks.calc_direct",
    "word-calc": "posttrain.tasks.wordcalc",
}


def get_task(name: str) -> Task:
    """The task module registered under `name`, or `gym:DATASET` (a reasoning-gym dataset, posttrain.tasks.gym);
    a clear error lists the known names."""
    if name.startswith("gym:"):
        from posttrain.tasks import gym

        try:
            return check_task(gym.task(name[len("gym:"):]))  # type: ignore[arg-type]
        except ImportError as e:  # the optional extra is not installed
            raise ValueError(str(e)) from None
    if name not in TASKS:
        raise ValueError(f"unknown task {name!r}; known tasks: {', '.join(sorted(TASKS))}, or gym:DATASET "
                         "(a reasoning-gym dataset, pip install \"posttrain[gym]\")")
    return check_task(importlib.import_module(TASKS[name]))


def _task_or_config_error(name: str) -> Task:
    from posttrain.errors import ConfigError

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
        return [dict(r) for r in load_rows(file, "sft", columns(task_cfg), say=print,
                                           split="train" if split == "train" else "test")]
    task = _task_or_config_error(task_cfg.name)
    n = task_cfg.n_train if split == "train" else task_cfg.n_eval
    rows = task.make_examples(n, task_cfg.seed, split, **difficulty_kwargs(task, task_cfg),
                              **option_kwargs(task, task_cfg))
    validate_rows(rows, "sft", f"task {task_cfg.name} ({split})")
    return rows


def difficulty_kwargs(task: Task, task_cfg) -> dict[str, int]:
    """{"difficulty": level} for a task with levels (a module-level DIFFICULTIES tuple; `task.difficulty`
    0 is its default), {} for one without; a ConfigError for a level it does not have."""
    from posttrain.errors import ConfigError

    level = getattr(task_cfg, "difficulty", 0)
    levels = getattr(task, "DIFFICULTIES", None)
    if levels is None:
        if level:
            raise ConfigError(f"task.difficulty: task {task.NAME!r} has no difficulty levels; leave task.difficulty at 0")
        return {}
    if level == 0:
        return {}
    if level not in levels:
        raise ConfigError(f"task.difficulty: task {task.NAME!r} has levels {', '.join(map(str, levels))} "
                          f"(0: its default), got {level}")
    return {"difficulty": level}


def option_kwargs(task: Task, task_cfg) -> dict[str, Any]:
    """`task.options` as keyword arguments of the task's make_examples, checked against the task's OPTIONS
    ({name: description}); a ConfigError names an option the task does not have."""
    from posttrain.errors import ConfigError

    options = dict(getattr(task_cfg, "options", None) or {})
    known = getattr(task, "OPTIONS", None) or {}
    for name in options:
        if name not in known:
            have = f"its options: {', '.join(sorted(known))}" if known else "it has none"
            raise ConfigError(f"task.options.{name}: task {task.NAME!r} has no option {name!r} ({have})")
    return options


def columns(task_cfg) -> dict[str, str]:
    """`task.columns` as {posttrain's field: the data's column} (posttrain.data.load_rows)."""
    cols = getattr(task_cfg, "columns", None)
    return cols.mapping() if cols is not None else {}


def tokenizer_corpus(task_cfg, rows: list[dict] | None = None) -> list[str]:
    """Texts to train a tokenizer on: the training file's prompts and completions (every message of a
    conversation; `rows`: that file's rows when already loaded), or the task's corpus."""
    if task_cfg.train_file:
        rows = load_split(task_cfg, "train") if rows is None else rows
        return ["\n".join(m["content"] for m in r["messages"]) if "messages" in r else r["prompt"] + r["completion"]
                for r in rows]
    return _task_or_config_error(task_cfg.name).corpus(task_cfg.n_train, task_cfg.seed)


def is_conversational(rows: list[dict] | None) -> bool:
    """The training file's rows (`load_split`; None: no file) are conversations (a preset built for them gets a
    chat template)."""
    return bool(rows) and "messages" in rows[0]
