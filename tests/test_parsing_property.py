"""Property-based tests of scene and recipe parsing: random and mutated tables either parse to a
valid result or raise SceneError/RecipeError naming the file and a key, never another exception.

Profiles: ``fast`` (default, few examples, keeps this file under ~20 s) and ``slow`` (many more):
``HYPOTHESIS_PROFILE=slow pytest tests/test_parsing_property.py``.
"""
import copy
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

settings.register_profile("fast", max_examples=30, deadline=None, derandomize=True,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.register_profile("slow", max_examples=1500, deadline=None,
                          suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large])
settings.load_profile(os.environ.get("HYPOTHESIS_PROFILE", "fast"))

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
SCENES = {os.path.basename(p): tomllib.load(open(p, "rb")) for p in sorted(glob.glob(os.path.join(SCENE_DIR, "*.toml")))}
RECIPES = {os.path.basename(p): tomllib.load(open(p, "rb")) for p in sorted(glob.glob(os.path.join(ROOT, "datasets", "*.toml")))}
SECTION_KEYS = sorted({k for s in SCENES.values() for v in s.values() if isinstance(v, dict) for k in v}
                      | {"units", "scale", "up_axis", "transform", "bind", "max_bind_distance", "rotations", "type"})
NAMES_A_KEY = re.compile(r"\[[^\]]+\]|\b(name|description|frames|dt|substeps|scale|sequences|batch|seed|dtype)\b")

# TOML values: booleans, integers (any size), floats (nan and inf included), strings, arrays, tables
leaf = st.one_of(st.booleans(), st.integers(), st.integers(-3, 300), st.floats(allow_nan=True, allow_infinity=True),
                 st.floats(-2.0, 2.0), st.text(max_size=6), st.sampled_from(["default", "sphere", "shake", "cm", "z",
                                                                              "keyframes", "choice", "uniform"]))
toml_value = st.recursive(leaf, lambda inner: st.one_of(
    st.lists(inner, max_size=4), st.dictionaries(st.one_of(st.sampled_from(SECTION_KEYS), st.text(max_size=5)), inner,
                                                 max_size=4)), max_leaves=10)
sampler = st.one_of(
    st.fixed_dictionaries({"uniform": st.lists(st.one_of(st.floats(-3, 3), leaf), min_size=0, max_size=3)}),
    st.fixed_dictionaries({"log_uniform": st.lists(st.one_of(st.floats(-1, 3), leaf), max_size=3)}),
    st.fixed_dictionaries({"randint": st.lists(st.one_of(st.integers(-5, 400), st.integers()), max_size=3)}),
    st.fixed_dictionaries({"choice": st.lists(toml_value, max_size=4)}))


def _paths(v, path=()):
    """Every (path) into nested tables and arrays (the root excluded)."""
    out = []
    if isinstance(v, dict):
        for k, x in v.items():
            out.append(path + (k,))
            out += _paths(x, path + (k,))
    elif isinstance(v, list):
        for j, x in enumerate(v):
            out.append(path + (j,))
            out += _paths(x, path + (j,))
    return out


def _mutate(data, raw: dict, values) -> dict:
    """One random edit of a table: replace a value, delete a key, or add a key."""
    raw = copy.deepcopy(raw)
    paths = _paths(raw)
    path = data.draw(st.sampled_from(paths)) if paths else ()
    parent = raw
    for p in path[:-1]:
        parent = parent[p]
    op = data.draw(st.sampled_from(["replace", "replace", "delete", "add"]))
    if op == "replace" and path:
        parent[path[-1]] = data.draw(values)
    elif op == "delete" and path:
        del parent[path[-1]]
    else:
        target = parent[path[-1]] if path and isinstance(parent[path[-1]], dict) else raw
        target[data.draw(st.one_of(st.sampled_from(SECTION_KEYS), st.text(max_size=5)))] = data.draw(values)
    return raw


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
    _check_scene(_mutate(data, SCENES[name], toml_value))


@given(st.data(), st.sampled_from(sorted(RECIPES)))
def test_mutated_recipes(data, name):
    raw = {**RECIPES[name], "sequences": 2, "frames": 3}
    _check_recipe(_mutate(data, raw, st.one_of(toml_value, sampler)))


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
