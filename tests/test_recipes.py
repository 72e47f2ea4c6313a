"""Recipe schema: shipped recipes validate; wrong fields name their path."""

from pathlib import Path

import pytest
import yaml

from tiledsm.errors import RecipeError
from tiledsm.pipelines import load_recipe
from tiledsm.recipes import dump_resolved

RECIPES = Path(__file__).resolve().parents[1] / "recipes"


@pytest.mark.parametrize("name", sorted(str(p.relative_to(RECIPES)) for p in RECIPES.rglob("*.yaml")))
def test_shipped_recipes_validate(name):
    """Examples (recipes/) and seed-reproduction experiments (recipes/experiments/)."""
    recipe = load_recipe(RECIPES / name)
    assert recipe.pipeline


@pytest.mark.realdata
def test_experiments_reach_the_shared_data_beside_the_repository(shared_data):
    """The experiments sit one folder deeper than the examples: their relative
    paths still reach ../shared/data."""
    from tiledsm.sr.train import config_from_yaml

    shared_data("s2p_pair")
    shared_data("sr_train")
    s2p = load_recipe(RECIPES / "experiments" / "sr_dsm_s2p.yaml")
    for path in (*s2p.input.images, s2p.input.reference):
        assert Path(path).is_file(), path
    for name in ("train_srmd.yaml", "train_vdsr.yaml", "train_srcnn_residual.yaml"):
        config = config_from_yaml(RECIPES / "experiments" / name)
        assert config.data_dirs and all(Path(d).is_dir() for d in config.data_dirs), name


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


def test_recipes_load_without_the_matching_kernels():
    """Reading and checking a recipe imports neither numba nor OpenCV: a
    command's option and recipe errors come before the kernels load."""
    import subprocess
    import sys

    code = ("import sys, tiledsm.recipes as r; r.MatchSpec(params={'window': 7});"
            "print(sorted(m for m in ('numba', 'cv2', 'tiledsm.match.sgvll') if m in sys.modules))")
    done = subprocess.run([sys.executable, "-c", code], capture_output=True, text=True, check=True)
    assert done.stdout.strip() == "[]"


def test_unknown_kernel_named_with_the_registered_ones():
    """The ``kernel`` validator loads the registry when a kernel is named."""
    from pydantic import ValidationError

    from tiledsm.match.params import SGVLLParams

    with pytest.raises(ValidationError, match="unknown matching kernel 'fastest'; known: cuda, fast, reference"):
        SGVLLParams(kernel="fastest")
    assert SGVLLParams(kernel="reference").kernel == "reference"


def test_misspelled_matching_parameter_named_with_the_valid_ones(tmp_path):
    """Issue 13: a misspelled matching parameter is one recipe error naming
    it and listing the valid names (not a TypeError deep in the run)."""
    from tiledsm.match.sgvll import SGVLLParams

    p = tmp_path / "r.yaml"
    p.write_text("pipeline: dsm\ninput: {synth: {size: 128}}\nmatch: {params: {windw: 5}}\n")
    with pytest.raises(RecipeError) as e:
        load_recipe(p)
    msg = str(e.value)
    assert "match.params" in msg and "'windw'" in msg
    assert all(name in msg for name in SGVLLParams.model_fields)
    p.write_text("pipeline: dsm\ninput: {synth: {size: 128}}\nmatch: {params: {window: five}}\n")
    with pytest.raises(RecipeError, match="window: Input should be a valid integer"):
        load_recipe(p)


def test_resolved_recipe_echoes_every_matching_parameter(tmp_path):
    """The resolved recipe shows every matching parameter with the value
    used (defaults filled in, given ones kept), and reads back the same."""
    from tiledsm.dsm import DSMParams
    from tiledsm.match.sgvll import SGVLLParams

    p = tmp_path / "r.yaml"
    p.write_text("pipeline: dsm\ninput: {synth: {size: 128}}\nmatch: {params: {window: 7, P2: 3}}\n")
    recipe = load_recipe(p)
    expected = SGVLLParams().model_copy(update={"window": 7, "P2": 3.0}).model_dump()
    assert recipe.match.params.model_dump() == expected
    dump_resolved(recipe, tmp_path / "resolved.yaml")
    echoed = yaml.safe_load((tmp_path / "resolved.yaml").read_text())["match"]["params"]
    assert echoed == expected
    assert DSMParams.of_recipe(recipe.grid, recipe.match).match == SGVLLParams(**expected)
    assert load_recipe(tmp_path / "resolved.yaml") == recipe
