"""Sizes that cannot fit and absurd values are refused when a scene or recipe is read, naming the
key (issue 28, items 8 and 11): before, they failed late as tracebacks (std::bad_alloc from the
frame kernel, a render after the whole simulation), ran for minutes, or diverged with "try more
substeps"."""
import copy

import pytest

from ams_torch.apps.cli import main
from ams_torch.apps.recipe import RecipeError, parse_recipe
from ams_torch.apps.recipe.core import check_recipe_memory
from ams_torch.apps.scene import SceneError, parse_scene
from ams_torch.apps.scene import limits
from ams_torch.apps.scene.limits import MemoryLimitError, check_memory, estimate_memory, parse_size

BASE = {"frames": 2, "head": {"mesh": "default", "subdivisions": 2, "sdf_resolution": 32},
        "groom": {"preset": "straight", "strands": 50, "particles": 8},
        "stages": {"collisions": True, "hair_hair": True}, "hair_hair": {"resolution": 16}}


def _with(path: str, value) -> dict:
    scene = copy.deepcopy(BASE)
    *sections, key = path.split(".")
    d = scene
    for s in sections:
        d = d.setdefault(s, {})
    d[key] = value
    return scene


#: (key path, value, what the error names): the measured cases of the issue, then its absurd values
REFUSED = [
    ("groom.strands", 10**9, "[groom].strands"), ("scale", 1e9, "scale"), ("groom.particles", 10**9, "[groom].particles"),
    ("groom.particles", 10**8, "[groom].particles"), ("hair_hair.resolution", 4096, "[hair_hair].resolution"),
    ("hair_hair.collision_max_per_cell", 10**9, "[hair_hair].collision_max_per_cell"),
    ("substeps", 10**9, "substeps"), ("params.substeps", 10**9, "[params].substeps"),
    ("hair_hair.bounds_padding", 1e308, "[hair_hair].bounds_padding"), ("render.size", 1e308, "[render].size"),
    ("params.collision_inextensibility", 10**9, "[params].collision_inextensibility"),
    ("head.sdf_resolution", 1024, "[head].sdf_resolution"), ("hair_hair.pressure_iterations", 10**9,
                                                              "[hair_hair].pressure_iterations"),
    ("groom.growth.steps", 10**9, "[groom.growth].steps"), ("groom.growth.step", 1e-9, "[groom.growth].step"),
    # item 11: values that diverged with "try more substeps"
    ("dt", 1e-300, "dt"), ("params.dt", 1e-300, "[params].dt"), ("params.gravity", [0.0, -1e308, 0.0], "[params].gravity"),
    ("params.gravity", [0.0, -1e6, 0.0], "[params].gravity"), ("params.stretch_rigidity", 1e308, "[params].stretch_rigidity"),
    ("params.drag", 1e300, "[params].drag"), ("wind.speed", 1e308, "[wind].speed"), ("wind.speed", 1e5, "[wind].speed"),
    ("head.radius", 1e308, "[head].radius"), ("groom.length", 1e308, "[groom].length"),
]


@pytest.mark.parametrize("path,value,key", REFUSED, ids=[f"{p}={v}" for p, v, _ in REFUSED])
def test_sizes_and_absurd_values_are_refused_naming_the_key(path, value, key):
    with pytest.raises(SceneError) as err:
        parse_scene(_with(path, value), where="s.toml")
    assert str(err.value).startswith(f"s.toml: {key}") and "more substeps" not in str(err.value), \
        str(err.value)


def test_colliders_and_their_motions_are_bounded_too():
    scene = _with("colliders", [{"type": "sphere", "radius": 1e308}])
    with pytest.raises(SceneError, match=r"\[colliders\[0\]\]\.radius"):
        parse_scene(scene, where="s.toml")
    scene = _with("colliders", [{"type": "sphere", "motion": {"type": "spin", "rate": 1e9}}])
    with pytest.raises(SceneError, match=r"\[colliders\[0\]\.motion\]\.rate = 1000000000\.0 is outside"):
        parse_scene(scene, where="s.toml")


def test_recipes_refuse_the_same_values_at_any_sampler_option():
    recipe = {"name": "r", "sequences": 2, "frames": 2, "head": {"mesh": "sphere"},
              "groom": {"kind": "sphere", "strands": 10, "particles": {"choice": [8, 10**8]}}}
    with pytest.raises(RecipeError, match=r"\[groom\]\.particles = 100000000 \(choice option 2 of 2\)"):
        parse_recipe(recipe, where="r.toml")
    recipe["groom"]["particles"] = 8
    recipe["params"] = {"dt": {"uniform": [1e-300, 0.01]}}
    with pytest.raises(RecipeError, match=r"\[params\]\.dt"):
        parse_recipe(recipe, where="r.toml")


def test_memory_is_estimated_from_the_sizes_and_refused_naming_the_largest_part(monkeypatch):
    scene = parse_scene(_with("hair_hair.resolution", 1000))
    parts = estimate_memory(scene)
    assert parts["hair_hair"][0] == 1000 ** 3 * limits.GRID_CELL_BYTES and "[hair_hair].resolution" in parts["hair_hair"][1]
    assert estimate_memory(scene, itemsize=8)["particles"][0] == 2 * parts["particles"][0]
    assert estimate_memory(scene, batch=4)["particles"][0] == 4 * parts["particles"][0]
    with pytest.raises(MemoryLimitError, match=r"the largest part is the 1000³ hair–hair grid \(\[hair_hair\]\.resolution\)"):
        check_memory(scene, limit=parse_size("8G"), where="s.toml")
    monkeypatch.setattr(limits, "available_memory", lambda device=None: parse_size("1G"))  # a small machine
    with pytest.raises(MemoryLimitError, match="available on this machine"):
        check_memory(scene)
    small = parse_scene(BASE)
    assert check_memory(small) < parse_size("1G")
    grown = parse_scene(_with("groom.growth", {"length": 10.0, "step": 1e-4}))  # 1e5 growth steps per strand
    assert estimate_memory(grown)["growth"][0] == 50 * 100001 * limits.GROWTH_POINT_BYTES
    assert parse_size("512M") == 512 * 2**20 and parse_size("2e9") == 2 * 10**9 and parse_size("1.5GB") == 1.5e9
    for bad in ("lots", "-1G", "0", "8X"):
        with pytest.raises(ValueError, match="--max-memory"):
            parse_size(bad)


def test_cli_refuses_before_allocating(tmp_path, capsys):
    scene = tmp_path / "s.toml"
    scene.write_text('frames = 2\n[groom]\npreset = "straight"\nstrands = 2000000\nparticles = 32\n')
    assert main(["simulate", str(scene), "--out", str(tmp_path / "o"), "--max-memory", "4G", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert err.startswith(f"error: {scene}: the run needs about") and "[groom].strands × [groom].particles" in err \
        and "--max-memory" in err and err.count("\n") == 1
    assert not (tmp_path / "o").exists()
    recipe = tmp_path / "r.toml"
    recipe.write_text('sequences = 4\nframes = 2\nbatch = 4\n[head]\nmesh = "sphere"\n[groom]\nkind = "sphere"\n'
                      'strands = { randint = [10, 300000] }\nparticles = 32\n')
    assert main(["generate", str(recipe), "--out", str(tmp_path / "d"), "--max-memory", "8G", "--quiet"]) == 2
    err = capsys.readouterr().err
    assert "the run needs about" in err and "× batch 4" in err and err.count("\n") == 1
    with pytest.raises(MemoryLimitError):
        from ams_torch.apps.recipe import load_recipe

        check_recipe_memory(load_recipe(str(recipe)), limit=parse_size("8G"))


@pytest.mark.parametrize("error", [MemoryError(), RuntimeError("DefaultCPUAllocator: can't allocate memory: you tried "
                                                               "to allocate 68719476736 bytes"),
                                   RuntimeError("CUDA out of memory. Tried to allocate 20.00 GiB")])
def test_running_out_of_memory_anyway_is_one_error_line(tmp_path, capsys, monkeypatch, error):
    """An estimate can be short: memory that runs out is still one line (exit 2), with the
    frames done kept; another RuntimeError stays a traceback (a bug)."""
    from ams_torch.sim.simulator import Simulator

    scene = tmp_path / "s.toml"
    scene.write_text('frames = 3\n[head]\nmesh = "none"\n[groom]\nkind = "strand"\nstrands = 2\nparticles = 6\n')
    step, calls = Simulator.step, []

    def running_out(self, *a, **k):
        calls.append(1)
        if len(calls) == 2:
            raise error
        return step(self, *a, **k)

    monkeypatch.setattr(Simulator, "step", running_out)
    assert main(["simulate", str(scene), "--out", str(tmp_path / "o"), "--quiet", "--no-video"]) == 2
    said = capsys.readouterr()
    assert said.err.startswith("error: out of memory") and said.err.count("\n") == 1
    assert "sequence.partial.h5" in said.out
    calls.clear()
    monkeypatch.setattr(Simulator, "step", lambda self, *a, **k: (_ for _ in ()).throw(RuntimeError("a bug")))
    with pytest.raises(RuntimeError, match="a bug"):
        main(["simulate", str(scene), "--out", str(tmp_path / "o2"), "--quiet", "--no-video"])


@pytest.mark.slow
def test_the_estimates_per_unit_costs_bound_the_measured_ones():
    """scripts/memory_costs.py at small sizes: each measured peak cost (bytes per particle on both
    paths, per SDF sample, per grid cell built) is below the constant the estimate uses."""
    from helpers import load_script

    mc = load_script("memory_costs")
    # sizes whose difference is tens of MB, well above the noise of a process's peak RSS
    assert mc.cost("particles", (200, 1600), "torch") <= limits.PARTICLE_BYTES
    assert mc.cost("particles", (200, 1600), "native") <= limits.PARTICLE_BYTES
    assert mc.cost("sdf", (32, 80)) <= limits.SDF_SAMPLE_BYTES
    assert mc.cost("grid", (32, 96)) <= limits.GRID_CELL_BYTES
