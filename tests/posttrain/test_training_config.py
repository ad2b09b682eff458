"""The training-config block (`loop.TrainingBase` / `loop.TrainingConfig`): defined once, and every stage's keys,
types and defaults exactly what they were (tests/posttrain/stage_fields.json, taken from the configs before the
block existed: a recipe, a YAML key and `posttrain STAGE --help` mean what they meant).

A key added, removed or given a new default on purpose: regenerate the JSON (the snippet in
`test_stage_keys_types_and_defaults_are_kept`'s message) in the same commit, and say so in its message.
"""
from __future__ import annotations

import ast
import inspect
import json
import textwrap
from dataclasses import fields
from pathlib import Path

import pytest

from posttrain import loop
from posttrain.cli import STAGES
from posttrain.config import describe_fields, field_docs

GOLDEN = Path(__file__).with_name("stage_fields.json")
TRAINERS = ("sft", "rm", "dpo", "grpo", "distill", "ppo")
BASE = [f.name for f in fields(loop.TrainingBase)]
FULL = [f.name for f in fields(loop.TrainingConfig)]


def stage_cls(stage: str) -> type:
    return STAGES[stage].load()[0]


@pytest.mark.parametrize("stage", sorted(json.loads(GOLDEN.read_text())))
def test_stage_keys_types_and_defaults_are_kept(stage):
    want = {tuple(r) for r in json.loads(GOLDEN.read_text())[stage]}
    got = {r[:3] for r in describe_fields(stage_cls(stage))}
    assert got == want, (
        f"`posttrain {stage} --help` keys changed: only now {sorted(got - want)}, gone {sorted(want - got)}. On "
        f"purpose? Regenerate {GOLDEN.name}: json of {{stage: sorted([key, type, default] of describe_fields)}}")


def test_the_block_has_its_sizes():
    assert len(BASE) == 11 and len(FULL) == 14
    assert set(FULL) - set(BASE) == {"micro_batch_size", "warmup_steps", "min_lr_ratio"}


@pytest.mark.parametrize("stage", TRAINERS)
def test_each_trainer_takes_the_block_and_documents_none_of_it(stage):
    cls = stage_cls(stage)
    base = loop.TrainingBase if stage == "ppo" else loop.TrainingConfig
    assert issubclass(cls, base), f"{cls.__name__} must inherit loop.{base.__name__}"
    names = {f.name for f in fields(cls)}
    assert set(BASE) <= names
    assert (set(FULL) <= names) == (stage != "ppo")  # PPO fixes warmup, min lr and row micro-batches itself
    # a field of the block re-declared in the trainer (its own default) carries no docstring of its own
    body = ast.parse(textwrap.dedent(inspect.getsource(cls))).body[0].body
    for a, b in zip(body, body[1:] + [None]):
        if isinstance(a, ast.AnnAssign) and a.target.id in FULL:
            documented = isinstance(b, ast.Expr) and isinstance(b.value, ast.Constant)
            assert not documented, f"{cls.__name__}.{a.target.id}: its one docstring is loop.{base.__name__}'s"
    docs = field_docs(cls)
    base_docs = field_docs(loop.TrainingConfig)
    for name in BASE:
        assert docs[name] == base_docs[name] and docs[name], name


def test_help_lists_the_trainers_own_fields_first():
    rows = [r[0] for r in describe_fields(stage_cls("grpo"))]
    own = [r for r in rows if r not in FULL]
    assert rows[:len(own)] == own and rows[len(own):] == FULL
    assert rows[0] == "verifier"
    sft = [r[0] for r in describe_fields(stage_cls("sft"))]
    assert sft[0] == "batch_size" and sft[-len(FULL):] == FULL


@pytest.mark.parametrize("stage", TRAINERS)
def test_the_run_object_is_built_by_keyword_with_real_types(stage):
    """Each trainer's `setup()` returns a keyword-only dataclass (no 25-argument positional call to misorder) whose
    fields say what they hold (no `Any`)."""
    import importlib

    module = importlib.import_module(STAGES[stage].load()[0].__module__)
    runs = [obj for name, obj in vars(module).items()
            if name.endswith("Run") and isinstance(obj, type) and obj.__module__ == module.__name__]
    assert len(runs) == 1, f"{module.__name__}: one run object expected, found {[r.__name__ for r in runs]}"
    assert callable(getattr(module, "setup", None)) and callable(getattr(module, "finish", None)), module.__name__
    for f in fields(runs[0]):
        assert f.kw_only, f"{runs[0].__name__}.{f.name} can be passed by position"
        assert "Any" not in str(f.type), f"{runs[0].__name__}.{f.name} is typed {f.type}"
