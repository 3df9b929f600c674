"""Property-based tests of scene and recipe parsing: random and mutated tables either parse to a
valid result or raise SceneError/RecipeError naming the file and a key, never another exception.

Profiles: ``fast`` (default, few examples, keeps this file under ~20 s) and ``slow`` (many more):
``HYPOTHESIS_PROFILE=slow pytest tests/test_parsing_property.py``.
"""
import glob
import os
import re
import tomllib

from pathlib import Path

import pytest
from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ams_torch.apps.recipe import RecipeError, parse_recipe
from ams_torch.apps.scene import SCENE_DIR, SceneError, make_params, parse_scene
from ams_torch.apps.scene.schema import TOP
from toml_strategies import SCENES, mutate, sampler, toml_value

settings.register_profile("fast", max_examples=30, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.register_profile("slow", max_examples=1500, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "fast"))

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
RECIPES = {os.path.basename(p): tomllib.load(open(p, "rb")) for p in sorted(glob.glob(os.path.join(ROOT, "datasets", "*.toml")))}
NAMES_A_KEY = re.compile(r"\[[^\]]+\]|\b(name|description|frames|dt|substeps|scale|sequences|batch|seed|dtype)\b")

def _check_scene(raw) -> None:
    try:
        scene = parse_scene(raw, where="scene.toml", base=SCENE_DIR)
    except SceneError as err:
        msg = str(err)
        assert msg.startswith("scene.toml: ") and NAMES_A_KEY.search(msg), msg
        return
    make_params(scene)  # a valid result is a usable one ...
    assert parse_scene(scene, where="again", base=SCENE_DIR) == scene  # ... and validation is idempotent


def _check_recipe(raw) -> None:
    try:
        recipe = parse_recipe(raw, where="recipe.toml", base=os.path.join(ROOT, "datasets"))
    except RecipeError as err:
        msg = str(err)
        assert msg.startswith("recipe.toml: ") and NAMES_A_KEY.search(msg), msg
        return
    recipe.group_scene(recipe.num_groups - 1)
    recipe.sequence_spec(recipe.num_sequences - 1)
    assert len(recipe.group_splits()) == recipe.num_groups


@given(st.dictionaries(st.one_of(st.sampled_from(sorted(TOP)), st.text(max_size=6)), toml_value, max_size=5))
def test_random_scene_tables(raw):
    _check_scene(raw)


@given(st.data(), st.sampled_from(sorted(SCENES)))
def test_mutated_shipped_scenes(data, name):
    _check_scene(mutate(data, SCENES[name], toml_value))


@given(st.data(), st.sampled_from(sorted(RECIPES)))
def test_mutated_recipes(data, name):
    raw = {**RECIPES[name], "sequences": 2, "frames": 3}
    _check_recipe(mutate(data, raw, st.one_of(toml_value, sampler)))


@given(st.dictionaries(st.one_of(st.sampled_from(["sequences", "frames", "batch", "seed", "groom", "params", "motion",
                                                  "wind", "store", "split", "head"]), st.text(max_size=5)),
                       st.one_of(toml_value, sampler), max_size=6))
def test_random_recipe_tables(raw):
    _check_recipe(raw)


@pytest.mark.parametrize("name", sorted(SCENES))
def test_shipped_scenes_are_valid_and_idempotent(name):
    shared = Path(__file__).resolve().parents[2] / "shared" / "assets"
    if "shared/assets" in (Path(SCENE_DIR) / name).read_text() and not shared.is_dir():
        pytest.skip(f"{name} reads real assets from ../shared/assets, which is not here")
    scene = parse_scene(SCENES[name], where=name, base=SCENE_DIR)
    assert parse_scene(scene, where=name, base=SCENE_DIR) == scene
