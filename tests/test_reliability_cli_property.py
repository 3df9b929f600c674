"""Property tests of the command line itself (issue 28): a scene or recipe file with one random
edit (a value replaced by anything TOML can hold, a key deleted or added) makes ``simulate`` /
``generate`` exit 0, or exit 2 with exactly one ``error:`` line; never a traceback, never a signal.

Profiles: ``fast`` (default: a few examples in this process, where a traceback is an exception
escaping ``main``) and ``slow`` (many examples, each in a child process, where a signal or a
traceback on stderr is seen as such): ``HYPOTHESIS_PROFILE=slow pytest tests/test_reliability_cli_property.py``.
Every run passes ``--frames 2`` (generate: ``--sequences 2``, frames at most 4) and
``--max-memory 64M``, so an edit cannot make it long.
"""
import contextlib
import io
import json
import math
import os
import tempfile
import tomllib

from hypothesis import HealthCheck, given, settings
from hypothesis import strategies as st

from ams_torch.apps.cli import main

from toml_strategies import mutate, sampler, toml_value
from helpers import run_cli

SLOW = os.environ.get("HYPOTHESIS_PROFILE") == "slow"
PROFILE = dict(max_examples=150 if SLOW else 6, deadline=None, derandomize=not SLOW,
               suppress_health_check=[HealthCheck.too_slow, HealthCheck.data_too_large,
                                      HealthCheck.function_scoped_fixture])

SCENE = tomllib.loads("""
name = "prop"
frames = 2
substeps = 1
[head]
mesh = "sphere"
radius = 0.1
[groom]
kind = "sphere"
strands = 6
particles = 6
length = 0.1
[params]
drag = 1.5
gravity = [0.0, -9.81, 0.0]
[stages]
collisions = true
hair_hair = true
[hair_hair]
resolution = 8
pressure_iterations = 5
[motion]
type = "shake"
amplitude = 0.3
frequency = 1.0
[wind]
speed = 1.0
direction = [1.0, 0.0, 0.0]
[[colliders]]
type = "capsule"
a = [0.0, -0.3, 0.15]
b = [0.0, -0.1, 0.15]
radius = 0.02
[colliders.motion]
type = "keyframes"
times = [0.0, 0.1]
translations = [[0.0, 0.0, 0.0], [0.0, 0.0, -0.02]]
[render]
size = 1.0
""")

RECIPE = tomllib.loads("""
name = "prop"
sequences = 2
frames = 2
batch = 2
[head]
mesh = "sphere"
[groom]
kind = "sphere"
strands = { randint = [4, 8] }
particles = 6
[params]
drag = { uniform = [1.0, 2.0] }
[motion]
type = { choice = ["shake", "random"] }
[motion.random]
keys = 2
[wind]
probability = 0.5
speed = { uniform = [0.5, 2.0] }
[store]
guides = 2
[split]
train = 1.0
""")


#: numbers at and past the edges of what the scene keys accept: the edits most likely to pass
#: validation and reach the simulation
EXTREME = st.sampled_from([0, -1, 1, 2, 3, 0.5, -0.5, 1e-300, 1e-12, 1e-9, 1e-7, 1e3, 1e6, 1e9, 1e15, 1.1e15, 1e308,
                           -1e308, float("nan"), float("inf"), 64, 512, 513, 1024, 4096, 4097, 10**6, 10**7, 10**18,
                           2**63, [0.0, 0.0, 0.0], [1e15, 0.0, 0.0], [1.0, 1.0]])
VALUES = st.one_of(toml_value, EXTREME)


def to_toml(table: dict) -> str:
    """A TOML document of ``table`` (every value inline, keys quoted), as a person could write it."""
    def value(v):
        if isinstance(v, bool):
            return "true" if v else "false"
        if isinstance(v, int):
            return str(v)
        if isinstance(v, float):
            return "nan" if math.isnan(v) else ("inf" if v > 0 else "-inf") if math.isinf(v) else repr(v)
        if isinstance(v, str):
            return json.dumps(v, ensure_ascii=False)
        if isinstance(v, list):
            return "[" + ", ".join(value(x) for x in v) + "]"
        return "{" + ", ".join(f"{json.dumps(str(k), ensure_ascii=False)} = {value(x)}" for k, x in v.items()) + "}"

    return "".join(f"{json.dumps(str(k), ensure_ascii=False)} = {value(v)}\n" for k, v in table.items())


def _check(rc, out: str, err: str, what: str) -> None:
    assert rc in (0, 2), f"{what}: exit status {rc} (a signal if negative)\n{err[-3000:]}"
    assert "Traceback" not in err, f"{what}: a traceback\n{err[-3000:]}"
    errors = [line for line in err.splitlines() if line.startswith("error:")]
    assert len(errors) == (1 if rc == 2 else 0), f"{what}: exit {rc} with error lines {errors}\n{err[-2000:]}"


def _run(args: list, what: str) -> int:
    if SLOW:  # a child process: signals and tracebacks are visible as such
        p = run_cli(args, timeout=600)
        _check(p.returncode, p.stdout, p.stderr, what)
        return p.returncode
    out, err = io.StringIO(), io.StringIO()
    with contextlib.redirect_stdout(out), contextlib.redirect_stderr(err):
        rc = main(args)  # an exception escaping main is the traceback a user would see
    _check(rc, out.getvalue(), err.getvalue(), what)
    return rc


def _write(table: dict, folder: str, name: str) -> str:
    text = to_toml(table)
    path = os.path.join(folder, name)
    with open(path, "w", encoding="utf-8") as fh:
        fh.write(text)
    return path


def test_the_toml_writer_round_trips():
    for table in (SCENE, RECIPE, {"x": [1, 2.5, float("inf"), "a\"b\n", {"y z": []}], "": {}}):
        text = to_toml(table)
        back = tomllib.loads(text)
        assert json.dumps(back, sort_keys=True, default=str) == json.dumps(table, sort_keys=True, default=str)


@settings(**PROFILE)
@given(st.data())
def test_simulate_exits_0_or_2_with_one_error_line(data):
    scene = mutate(data, SCENE, VALUES)
    with tempfile.TemporaryDirectory() as tmp:
        path = _write(scene, tmp, "scene.toml")
        _run(["simulate", path, "--out", os.path.join(tmp, "out"), "--frames", "2", "--no-video", "--quiet",
              "--max-memory", "64M", "--device", "cpu"], f"simulate of\n{to_toml(scene)}")


@settings(**PROFILE)
@given(st.data())
def test_generate_exits_0_or_2_with_one_error_line_and_validates(data):
    recipe = mutate(data, RECIPE, st.one_of(VALUES, sampler))
    if isinstance(recipe.get("frames"), int) and not isinstance(recipe["frames"], bool) and recipe["frames"] > 4:
        recipe["frames"] = 4  # a long dataset is a valid request, not a fault: keep the run short
    with tempfile.TemporaryDirectory() as tmp:
        path, out = _write(recipe, tmp, "recipe.toml"), os.path.join(tmp, "out")
        what = f"generate of\n{to_toml(recipe)}"
        if _run(["generate", path, "--out", out, "--quiet", "--max-memory", "64M", "--sequences", "2"], what) == 0:
            assert _run(["validate", out, "--quiet"], what) == 0
