"""`generate` under faults (issue 28, items 3, 4, 12): a full disk (a file size limit in a child),
a kill -9 while the finished shard's work folder is removed, the lock file deleted under a
running run."""
import os
import signal
import subprocess
import sys
import textwrap
import time

import pytest

from ams_torch.apps.cli import main
from ams_torch.apps.data import validate
from ams_torch.apps.datagen import OutputError, generate
from ams_torch.apps.recipe import load_recipe

from helpers import REPO as ROOT, one_error, run_cli

MINI = """
name = "mini"
sequences = 2
frames = 3
batch = 2
[head]
mesh = "sphere"
[groom]
kind = "sphere"
strands = 10
particles = 6
[motion]
type = "nod"
[split]
train = 1.0
"""


@pytest.fixture
def recipe(tmp_path):
    path = tmp_path / "mini.toml"
    path.write_text(MINI)
    return path


def test_generate_on_a_full_disk_fails_clean_and_resumes_bit_for_bit(recipe, tmp_path):
    """Item 3: generate into a full disk printed 134 tracebacks from h5py's deallocation and
    died of SIGSEGV; now exit 2 with one line naming the file, and the next run (with room)
    finishes the same bytes as a run that never failed."""
    out, ref = tmp_path / "out", tmp_path / "ref"
    p = run_cli(["generate", recipe, "--out", out, "--quiet"], fsize=6 << 10)
    line = one_error(p)
    assert "group-000000.h5" in line and "File too large" in line, line
    assert not [n for _, _, names in os.walk(out) for n in names if ".tmp" in n]
    assert main(["generate", str(recipe), "--out", str(out), "--quiet"]) == 0
    assert main(["generate", str(recipe), "--out", str(ref), "--quiet"]) == 0
    name = "mini-shard-00000-of-00001.h5"
    assert (out / name).read_bytes() == (ref / name).read_bytes()
    assert validate(str(out)).ok


def test_a_kill_while_the_work_folder_is_removed_is_cleaned_by_the_next_run(recipe, tmp_path, capsys):
    """Item 4: a kill during finish_shard's rmtree (after the shard's rename) left
    ``.partial/<stem>/``; generate said "already complete" and never removed it, validate exited
    1 for good. Now validate notes it (exit 0) and the next generate removes it."""
    out = tmp_path / "out"
    script = textwrap.dedent(f"""
        import os, signal, shutil
        from ams_torch.apps.datagen import shards
        def dying(path, *a, **k):
            os.remove(os.path.join(path, sorted(os.listdir(path))[0]))
            os.kill(os.getpid(), signal.SIGKILL)
        shards.shutil.rmtree = dying
        from ams_torch.apps.cli import main
        main(["generate", {str(recipe)!r}, "--out", {str(out)!r}, "--quiet"])
    """)
    p = run_cli(None, script=script)
    work = out / ".partial" / "mini-shard-00000-of-00001"
    assert p.returncode == -signal.SIGKILL and work.is_dir() and (out / "mini-shard-00000-of-00001.h5").exists()
    capsys.readouterr()
    assert main(["validate", str(out), "--quiet"]) == 0
    assert "leftover work folder of the finished shard" in capsys.readouterr().out
    assert main(["generate", str(recipe), "--out", str(out), "--quiet"]) == 0
    assert "already complete" in capsys.readouterr().out
    assert not (out / ".partial").exists()
    report = validate(str(out))
    assert report.ok and not report.notes


def test_deleting_the_lock_file_does_not_let_a_second_run_in(recipe, tmp_path):
    """Item 12: the ``.lock`` could be deleted under a running generate, after which a second run
    took a new lock file and both wrote the folder. The folder itself is locked now."""
    out = tmp_path / "out"
    started, go = tmp_path / "started", tmp_path / "go"
    script = textwrap.dedent(f"""
        import os, time
        from ams_torch.apps.datagen import shards
        write = shards.write_group
        def waiting(*a, **k):
            open({str(started)!r}, "w").close()
            while not os.path.exists({str(go)!r}):
                time.sleep(0.05)
            return write(*a, **k)
        shards.write_group = waiting
        from ams_torch.apps.cli import main
        raise SystemExit(main(["generate", {str(recipe)!r}, "--out", {str(out)!r}, "--quiet"]))
    """)
    env = dict(os.environ, PYTHONPATH=str(ROOT))
    child = subprocess.Popen([sys.executable, "-c", script], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE,
                             text=True)
    try:
        deadline = time.time() + 120
        while not started.exists():
            assert child.poll() is None and time.time() < deadline, child.communicate()
            time.sleep(0.05)
        os.remove(out / ".lock")
        with pytest.raises(OutputError, match="locked by another generate run"):
            generate(load_recipe(str(recipe)), str(out), progress=False, log=lambda s: None)
    finally:
        go.touch()
        stdout, stderr = child.communicate(timeout=120)
    assert child.returncode == 0, stderr
    assert validate(str(out)).ok


def test_a_shard_that_does_not_read_back_is_not_renamed(recipe, tmp_path, monkeypatch):
    """The assembled shard is read back (its sequences, its metadata) before the rename: a bad
    one is never put in place, the finished groups stay for the next run."""
    import h5py

    from ams_torch.apps.datagen import shards

    copy = shards.copy_groups

    def bad_copy(*args):
        copy(*args)
        with h5py.File(args[2], "r+") as f:
            f["seq_000000"].attrs["frames"] = 1000

    monkeypatch.setattr(shards, "copy_groups", bad_copy)
    out = tmp_path / "out"
    with pytest.raises(OSError, match="the assembled shard does not read back: seq_000000: attribute 'frames'"):
        generate(load_recipe(str(recipe)), str(out), progress=False, log=lambda s: None)
    assert not (out / "mini-shard-00000-of-00001.h5").exists()
    assert (out / ".partial" / "mini-shard-00000-of-00001" / "group-000000.h5").exists()
    monkeypatch.setattr(shards, "copy_groups", copy)
    generate(load_recipe(str(recipe)), str(out), progress=False, log=lambda s: None)
    assert validate(str(out)).ok
