from dataclasses import dataclass
from typing import Literal

import pytest

from posttrain.config import ConfigError, coerce, describe_fields, parse_overrides, resolve
from posttrain.trainers.sft import SFTConfig


def test_defaults_recipe_overrides_precedence(tmp_path):
    recipe = tmp_path / "r.yaml"
    recipe.write_text("task:\n  n_train: 100\nsft:\n  lr: 0.01\n  max_steps: 7\n")
    res = resolve(str(recipe), "sft", SFTConfig, ["max_steps=9", "task.seed=3", "model.path=small", "sft.batch_size=4"])
    assert res.recipe == "r"
    assert res.stage_cfg.lr == 0.01            # recipe over default
    assert res.stage_cfg.max_steps == 9        # command line over recipe
    assert res.stage_cfg.batch_size == 4       # dotted stage key
    assert res.stage_cfg.warmup_steps == SFTConfig().warmup_steps  # default kept
    assert res.task.n_train == 100 and res.task.seed == 3
    assert res.model.path == "small"


def test_model_sugar_and_scientific_float(tmp_path):
    recipe = tmp_path / "r.yaml"
    recipe.write_text("sft: {}\n")
    res = resolve(str(recipe), "sft", SFTConfig, ["model=/some/dir", "lr=1e-3"])
    assert res.model.path == "/some/dir"
    assert res.stage_cfg.lr == pytest.approx(1e-3)


def _sft(tmp_path, recipe_text: str, *overrides: str):
    """Resolve the sft stage of a recipe file holding `recipe_text`, with `overrides`."""
    recipe = tmp_path / "r.yaml"
    recipe.write_text(recipe_text)
    return resolve(str(recipe), "sft", SFTConfig, list(overrides))


@pytest.mark.parametrize("recipe_text, overrides, message", [
    pytest.param("sft:\n  learning_rate: 0.1\n", [], r"unknown config key 'sft.learning_rate'; valid keys in sft: lr, ",
                 id="unknown-key-in-recipe"),
    pytest.param("sft: {}\n", ["bogus=1"], r"unknown config key 'bogus' for stage 'sft'; valid keys: .*lr",
                 id="unknown-override"),
    pytest.param("sft: {}\n", ["model.colour=red"], r"unknown config key 'model.colour'", id="unknown-shared-key"),
    pytest.param("sfx:\n  lr: 1\n", [], "unknown recipe section 'sfx'", id="unknown-section"),
    pytest.param("sft: [1, 2\n", [], "not valid YAML", id="bad-yaml"),
    pytest.param("sft:\n  max_steps: ten\n", [], r"config key 'sft.max_steps': expected int, got 'ten'", id="int"),
    pytest.param("sft: {}\n", ["schedule=wavy"], r"'sft.schedule': 'wavy' is not one of 'cosine', 'linear', 'constant'",
                 id="literal"),
    pytest.param("sft: {}\n", ["resume=maybe"], r"expected bool", id="bool"),
    pytest.param("sft: {}\n", ["resume"], "key=value", id="override-without-value"),
])
def test_bad_config_names_the_key(tmp_path, recipe_text, overrides, message):
    """Unknown keys and sections, bad YAML and wrong types: one ConfigError naming the key (and the valid ones)."""
    with pytest.raises(ConfigError, match=message):
        _sft(tmp_path, recipe_text, *overrides)


def test_unknown_recipe_lists_shipped():
    with pytest.raises(ConfigError, match=r"unknown recipe 'nope'; shipped recipes: .*tiny-summarize"):
        resolve("nope", "sft", SFTConfig, [])


def test_coerce_rules():
    assert coerce(3, float, "k") == 3.0 and isinstance(coerce(3, float, "k"), float)
    with pytest.raises(ConfigError):
        coerce(True, int, "k")  # bools are not ints in a config
    assert coerce(None, int | None, "k") is None
    assert coerce(["a", "b"], list[str], "k") == ["a", "b"]
    with pytest.raises(ConfigError, match=r"k\[1\]"):
        coerce(["a", 2], list[str], "k")
    assert coerce("x", Literal["x", "y"], "k") == "x"


def test_parse_overrides_yaml_values():
    assert parse_overrides(["a=1", "b=true", "c=hello", "d=[1, 2]", "e=", "f=null"]) == [
        ("a", 1), ("b", True), ("c", "hello"), ("d", [1, 2]), ("e", ""), ("f", None)]


def test_describe_fields_has_docs():
    rows = {r[0]: r for r in describe_fields(SFTConfig)}
    assert "Peak learning rate" in rows["lr"][3]
    assert rows["schedule"][1].startswith("one of")


def test_other_stage_overrides_configure_prerequisites(tmp_path):
    from posttrain.config import check_stage_sections

    recipe = tmp_path / "r.yaml"
    recipe.write_text("sft:\n  lr: 0.01\n")
    res = resolve(str(recipe), "eval", _EvalLike, ["sft.max_steps=5"])
    sft = res.for_stage("sft", SFTConfig)
    assert sft.stage_cfg.max_steps == 5 and sft.stage_cfg.lr == 0.01  # override merged into the recipe section
    check_stage_sections(res, {"sft": SFTConfig})
    bad = resolve(str(recipe), "eval", _EvalLike, ["sft.max_stepz=5"])
    with pytest.raises(ConfigError, match=r"unknown config key 'sft.max_stepz'"):
        check_stage_sections(bad, {"sft": SFTConfig})


@dataclass
class _EvalLike:
    rows: int = 1
    """rows"""
