"""Recipe schema: shipped recipes validate; wrong fields name their path."""

from pathlib import Path

import pytest
import yaml

from tiledsm.errors import RecipeError
from tiledsm.recipes import dump_resolved, load_recipe

RECIPES = Path(__file__).resolve().parents[1] / "recipes"


@pytest.mark.parametrize("name", sorted(p.name for p in RECIPES.glob("*.yaml")))
def test_shipped_recipes_validate(name):
    recipe = load_recipe(RECIPES / name)
    assert recipe.pipeline


def test_unknown_field_named(tmp_path):
    p = tmp_path / "r.yaml"
    p.write_text("pipeline: dsm\ninput: {synth: {size: 128, sise: 3}}\n")
    with pytest.raises(RecipeError) as e:
        load_recipe(p)
    assert "input.synth.sise" in str(e.value) and str(p) in str(e.value)


def test_bad_value_named(tmp_path):
    p = tmp_path / "r.yaml"
    p.write_text("pipeline: dsm\ninput: {synth: {gsd: -1}}\ngrid: {chunk: 8}\n")
    with pytest.raises(RecipeError) as e:
        load_recipe(p)
    msg = str(e.value)
    assert "input.synth.gsd" in msg and "grid.chunk" in msg


def test_exactly_one_input_source(tmp_path):
    p = tmp_path / "r.yaml"
    p.write_text("pipeline: dsm\ninput: {}\n")
    with pytest.raises(RecipeError, match="exactly one of"):
        load_recipe(p)


def test_unknown_pipeline_and_bad_yaml(tmp_path):
    p = tmp_path / "r.yaml"
    p.write_text("pipeline: nope\n")
    with pytest.raises(RecipeError, match="pipeline: expected one of"):
        load_recipe(p)
    p.write_text("pipeline: [dsm\n")
    with pytest.raises(RecipeError, match="not valid YAML"):
        load_recipe(p)
    with pytest.raises(RecipeError, match="cannot read recipe"):
        load_recipe(tmp_path / "missing.yaml")


def test_relative_paths_resolved_and_round_trip(tmp_path):
    p = tmp_path / "r.yaml"
    p.write_text("pipeline: dsm\ninput: {images: [a.tif, b.tif], reference: ref.tif}\n")
    recipe = load_recipe(p)
    assert recipe.input.images == [str(tmp_path / "a.tif"), str(tmp_path / "b.tif")]
    out = tmp_path / "resolved.yaml"
    dump_resolved(recipe, out)
    again = load_recipe(out)
    assert again == recipe
    assert yaml.safe_load(out.read_text())["grid"]["chunk"] == 512
