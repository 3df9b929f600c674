"""Hypothesis strategies of TOML tables, shared by the property tests of parsing
(``test_parsing_property.py``) and of the command line (``test_reliability_cli_property.py``):
not a test module (pytest does not collect it; test modules import it, never each other).

``toml_value``: anything a TOML value can be (booleans, integers of any size, floats with nan and
inf, strings, arrays, tables keyed by the shipped scenes' section keys or random text); ``sampler``:
a recipe's random-parameter tables; ``mutate(data, raw, values)``: one random edit of a table.
"""
import copy
import glob
import os
import tomllib

from hypothesis import strategies as st

from ams_torch.apps.scene import SCENE_DIR

SCENES = {os.path.basename(p): tomllib.load(open(p, "rb")) for p in sorted(glob.glob(os.path.join(SCENE_DIR, "*.toml")))}
SECTION_KEYS = sorted({k for s in SCENES.values() for v in s.values() if isinstance(v, dict) for k in v}
                      | {"units", "scale", "up_axis", "transform", "bind", "max_bind_distance", "rotations", "type"})

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


def table_paths(v, path=()):
    """Every (path) into nested tables and arrays (the root excluded)."""
    out = []
    if isinstance(v, dict):
        for k, x in v.items():
            out.append(path + (k,))
            out += table_paths(x, path + (k,))
    elif isinstance(v, list):
        for j, x in enumerate(v):
            out.append(path + (j,))
            out += table_paths(x, path + (j,))
    return out


def mutate(data, raw: dict, values) -> dict:
    """One random edit of a table: replace a value, delete a key, or add a key."""
    raw = copy.deepcopy(raw)
    paths = table_paths(raw)
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
