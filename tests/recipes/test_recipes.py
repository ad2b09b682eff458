"""Every shipped recipe loads and resolves for each stage it configures."""
import pytest

from posttrain.cli import STAGES
from posttrain.config import list_recipes, load_recipe, resolve

RECIPES = [name for name, _ in list_recipes()]


def test_recipes_shipped():
    assert "tiny-summarize" in RECIPES


@pytest.mark.parametrize("name", RECIPES)
def test_recipe_resolves_for_its_stages(name):
    _, raw = load_recipe(name)
    stages = [s for s in raw if s in STAGES] + ["eval"]
    for stage in stages:
        cfg_cls, _ = STAGES[stage].load()
        res = resolve(name, stage, cfg_cls, [])
        assert res.recipe == name and res.stage == stage


@pytest.mark.parametrize("name", RECIPES)
def test_recipe_header(name):
    from posttrain.config import resolve_recipe

    text = resolve_recipe(name).read_text()
    assert text.startswith("# "), "a recipe starts with a one-line description"
    assert "posttrain " in text and "min" in text, "a recipe header gives the command and the expected runtime"
