"""Every shipped recipe sets only values that differ from the dataclass defaults.

The README and every recipe header promise it: a recipe is the list of choices that make the task work,
so a key set to its default is noise that hides the real choices (and goes stale when a default moves).
For each recipe (`recipes/*.yaml`; `recipes/launch/` holds accelerate configs, not recipes), each section
and each key it sets, the YAML value -- coerced to the field's type with `posttrain.config.coerce`, as
loading a recipe does (so `3.0e-3` and `0.003`, ints for floats, lists and mappings compare by value) --
must differ from that field's default. Shared sections come from `posttrain.config.SHARED_SECTIONS`, stage
sections from the CLI's stage table (`posttrain.cli.STAGES`), so trainers can move without breaking this.
"""
from __future__ import annotations

import dataclasses
import typing
from pathlib import Path

import pytest
import yaml

from posttrain.cli import STAGES
from posttrain.config import SHARED_SECTIONS, coerce, recipes_dir

RECIPE_FILES = sorted(recipes_dir().glob("*.yaml"))  # not recursive: recipes/launch/ is left out


def _section_class(section: str) -> type:
    if section in SHARED_SECTIONS:
        return SHARED_SECTIONS[section]
    if section in STAGES:
        cfg_cls, _ = STAGES[section].load()
        return cfg_cls
    raise AssertionError(f"unknown recipe section {section!r}; shared: {sorted(SHARED_SECTIONS)}, "
                         f"stages: {sorted(STAGES)}")


def _default(f: dataclasses.Field) -> typing.Any:
    if f.default is not dataclasses.MISSING:
        return f.default
    if f.default_factory is not dataclasses.MISSING:  # type: ignore[misc]
        return f.default_factory()  # type: ignore[misc]
    raise AssertionError(f"field {f.name!r} has no default")


def _defaults_set(cls: type, values: dict, where: str) -> list[str]:
    """`where.key = value` for every key of `values` whose value equals the default of `cls`'s field."""
    assert isinstance(values, dict), f"{where} must be a mapping, got {values!r}"
    hints = typing.get_type_hints(cls)
    fields = {f.name: f for f in dataclasses.fields(cls)}
    found = []
    for key, value in values.items():
        full = f"{where}.{key}"
        assert key in fields, f"{full}: {cls.__name__} has no field {key!r}"
        tp = hints[key]
        default = _default(fields[key])
        if dataclasses.is_dataclass(tp):  # a nested section: compare its keys one by one
            found += _defaults_set(tp, value, full)
            continue
        if coerce(value, tp, full) == default:
            found.append(f"{full} = {value!r} (the default of {cls.__name__}.{key})")
    return found


def test_recipes_found():
    names = [p.stem for p in RECIPE_FILES]
    assert "tiny-summarize" in names, names


@pytest.mark.parametrize("path", RECIPE_FILES, ids=lambda p: p.stem)
def test_recipe_sets_only_non_defaults(path: Path):
    raw = yaml.safe_load(path.read_text()) or {}
    found = []
    for section, values in raw.items():
        if section == "description" or values is None:  # a top-level string, or an empty section: nothing set
            continue
        found += _defaults_set(_section_class(section), values, section)
    if found:
        pytest.fail(f"recipe {path.stem} (recipes/{path.name}) sets keys to their dataclass defaults; remove them:\n  "
                    + "\n  ".join(found), pytrace=False)
