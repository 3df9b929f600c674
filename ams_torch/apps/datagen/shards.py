"""The output folder (one run at a time, one dataset per folder) and the shards: plans, resuming,
assembly, and the local backend."""
from __future__ import annotations

import contextlib
import errno
import fcntl
import json
import os
import shutil
import socket
import sys
import time
from typing import Callable, List, Optional, Sequence

from ams_torch.apps.data.format import LOCK_FILE, SHARD_FILE, holder_text, lock_holder, read_header
from ams_torch.apps.datagen.writer import _json, write_group, atomic_write, copy_groups
from ams_torch.apps.recipe import Recipe

__all__ = ["shard_filename", "parse_shard", "output_lock", "lock_holder", "OutputError", "LOCK_FILE",
           "generate_shard", "generate", "check_sharding", "check_output", "prepare_shard", "finish_shard", "log_plan"]



class OutputError(ValueError):
    """The output folder cannot take this run: another run holds it, or it holds another dataset."""


def shard_filename(recipe: Recipe, shard: int, num_shards: int) -> str:
    """``<name>-shard-00000-of-00004.h5`` (shard 0 of 4; shards are numbered from 0)."""
    return f"{recipe.name}-shard-{shard:05d}-of-{num_shards:05d}.h5"


def parse_shard(text: str) -> tuple:
    """``"i/n"`` → (i, n): shard i of n, 0-based (0 <= i < n), with a clear error."""
    try:
        i, n = (int(p) for p in str(text).split("/"))
    except ValueError:
        raise ValueError(f"--shard must look like i/n with 0 <= i < n (e.g. 0/4 is the first of 4 shards); "
                         f"got {text!r}") from None
    if n < 1:
        raise ValueError(f"--shard {text}: the number of shards n must be >= 1")
    if not 0 <= i < n:
        raise ValueError(f"--shard {text}: shards are numbered from 0, so i must be in 0..{n - 1} "
                         f"(e.g. {n - 1}/{n} is the last of {n})")
    return i, n


def _group_done(path: str, recipe: Recipe) -> bool:
    import h5py

    try:
        with h5py.File(path, "r") as f:
            if f.attrs.get("recipe_digest") != recipe.digest:
                raise OutputError(f"{path} was written by a different recipe (recipe_digest "
                                  f"{str(f.attrs.get('recipe_digest'))[:12]}…); use a fresh --out folder")
            return bool(f.attrs.get("complete", False))
    except OSError:
        return False


def log_plan(recipe: Recipe, log: Callable[[str], None]) -> None:
    """Say how many grooms the recipe grows and how its sequences split, before simulating."""
    from ams_torch.apps.recipe.splits import describe

    log(f"{recipe.name}: {recipe.groom_note()}; {describe(recipe)}")


# -- the output folder: one run at a time, one dataset per folder ---------------------------------
def _flock(fd: int, wait: bool) -> bool:
    """flock(fd) exclusively: True when taken, False when another process holds it (``wait``:
    block until it is free)."""
    try:
        fcntl.flock(fd, fcntl.LOCK_EX | (0 if wait else fcntl.LOCK_NB))
        return True
    except OSError as err:
        if err.errno not in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES):
            raise
        return False


def _folder_fd(out: str) -> Optional[int]:
    """A descriptor of the folder itself for flock, or None where the file system cannot lock
    folders (then the lock file alone serves)."""
    try:
        fd = os.open(out, os.O_RDONLY | getattr(os, "O_DIRECTORY", 0))
    except OSError:
        return None
    try:
        fcntl.flock(fd, fcntl.LOCK_SH | fcntl.LOCK_NB)  # probe: can this file system lock a folder?
        fcntl.flock(fd, fcntl.LOCK_UN)
    except OSError as err:
        if err.errno not in (errno.EAGAIN, errno.EWOULDBLOCK, errno.EACCES):
            os.close(fd)
            return None
    return fd


@contextlib.contextmanager
def output_lock(out: str, wait: bool = False, log: Callable[[str], None] = print):
    """Hold an exclusive ``flock`` on the folder ``out`` itself and on ``out/.lock`` (created if
    needed) for the ``with`` block; the file records pid, host, start time and command. The
    folder's lock is what holds: deleting ``.lock`` under a running run does not let a second
    run in (the file's lock keeps runs of older versions out). Another holder:
    :class:`OutputError` naming it, or (``wait``) block until it is done. The kernel releases the
    locks when the process dies, so a killed run leaves no stale lock."""
    os.makedirs(out, exist_ok=True)
    path = os.path.join(out, LOCK_FILE)
    folder = _folder_fd(out)
    fd = os.open(path, os.O_RDWR | os.O_CREAT, 0o644)
    held = False
    try:
        if not all(_flock(d, False) for d in (folder, fd) if d is not None):
            try:
                holder = holder_text(json.loads(os.pread(fd, 65536, 0).decode() or "{}"))
            except ValueError:
                holder = "holder unknown"
            if holder == "holder unknown":
                holder += f" (its {LOCK_FILE} record is empty or was deleted)"
            if not wait:
                raise OutputError(f"{out} is locked by another generate run ({holder}); wait for it to finish, "
                                  f"or rerun with --wait to start when it is done") from None
            log(f"waiting for {out}: another generate run holds it ({holder})")
            for d in (folder, fd):
                if d is not None:
                    _flock(d, True)
        held = True
        info = {"pid": os.getpid(), "host": socket.gethostname(), "started": time.strftime("%Y-%m-%d %H:%M:%S"),
                "command": " ".join(sys.argv)}
        os.ftruncate(fd, 0)
        os.pwrite(fd, json.dumps(info).encode(), 0)
        yield
    finally:
        if held:
            with contextlib.suppress(OSError):
                os.ftruncate(fd, 0)
        os.close(fd)  # releases the locks
        if folder is not None:
            os.close(folder)


def check_output(recipe: Recipe, out: str, num_shards: int) -> None:
    """Refuse a folder that holds (finished or unfinished) shards of another sharding or recipe."""

    mine, others = shard_filename(recipe, 0, num_shards), []
    partial = os.path.join(out, ".partial")
    names = [n for n in os.listdir(out) if n.endswith(".h5")]
    names += [n + ".h5" for n in (os.listdir(partial) if os.path.isdir(partial) else [])]
    for name in sorted(set(names)):
        m = SHARD_FILE.match(name)
        if m is None:
            raise OutputError(f"{out} holds {name}, which is not a shard of an ams_torch dataset; use an empty --out folder")
        path = os.path.join(out, name)
        h = read_header(path) if os.path.isfile(path) else None
        if m["name"] != recipe.name or int(m["n"]) != num_shards or (h is not None and h["digest"] != recipe.digest):
            others.append((name, int(m["n"])))
    if not others:
        return
    counts = sorted({n for _, n in others})
    listed = ", ".join(n for n, _ in others[:4]) + (" ..." if len(others) > 4 else "")
    if all(n != num_shards for _, n in others):
        raise OutputError(f"{out} already holds a {'/'.join(map(str, counts))}-shard dataset ({listed}); refusing to "
                          f"write {num_shards} shard(s) ({mine} ...) into it: two shardings in one folder hold every "
                          f"sequence twice. Use another --out folder" +
                          (f", or --shards {counts[0]} to continue that one" if len(counts) == 1 else ""))
    raise OutputError(f"{out} holds shard files of another recipe ({listed}; this recipe {recipe.name!r} has "
                      f"recipe_digest {recipe.digest[:12]}…); use another --out folder")


def check_sharding(recipe: Recipe, num_shards: int, shards=None) -> List[int]:
    if isinstance(num_shards, bool) or not isinstance(num_shards, int) or num_shards < 1:
        raise ValueError(f"the number of shards must be an integer >= 1; got {num_shards!r}")
    if num_shards > recipe.num_groups:
        raise ValueError(f"{num_shards} shards for {recipe.num_groups} batch group(s): a shard would be empty; use "
                         f"at most {recipe.num_groups} shards (or more sequences / a smaller batch)")
    shards = list(range(num_shards)) if shards is None else list(shards)
    bad = [i for i in shards if not (isinstance(i, int) and 0 <= i < num_shards)]
    if bad:
        raise ValueError(f"shard(s) {bad} out of range: shards of {num_shards} are numbered 0..{num_shards - 1}")
    return shards


# -- shards ------------------------------------------------------------------------------------
def prepare_shard(recipe: Recipe, out: str, shard: int, num_shards: int) -> dict:
    """The plan of one shard: its file, work folder, groups and the groups already done (a
    killed run's temporaries removed). ``complete``: the shard file exists (same recipe)."""

    final = os.path.join(out, shard_filename(recipe, shard, num_shards))
    groups = recipe.shard_groups(shard, num_shards)
    work = os.path.join(out, ".partial", os.path.splitext(os.path.basename(final))[0])
    plan = {"final": final, "work": work, "groups": groups, "done": [], "shard": shard, "num_shards": num_shards,
            "complete": os.path.exists(final), "path_of": lambda g: os.path.join(work, f"group-{g:06d}.h5")}
    if plan["complete"]:
        h = read_header(final)
        if h is None or h["digest"] != recipe.digest:
            raise OutputError(f"{final} exists and is not a shard of this recipe (or is unreadable); "
                              f"use a fresh --out folder")
        _remove_work(work)  # left by a run killed while it removed the folder after the rename
        return plan
    for name in os.listdir(out):  # an assembly that was cut short
        if name.startswith(os.path.basename(final) + ".tmp"):
            os.remove(os.path.join(out, name))
    os.makedirs(work, exist_ok=True)
    for name in os.listdir(work):
        if ".tmp" in name:  # a write that was cut short: never kept
            os.remove(os.path.join(work, name))
    atomic_write(os.path.join(work, "shard.json"), lambda tmp: open(tmp, "w").write(_json(
        {"groups": groups, "shard": shard, "num_shards": num_shards, "recipe_digest": recipe.digest})))
    plan["done"] = [g for g in groups if os.path.exists(plan["path_of"](g)) and _group_done(plan["path_of"](g), recipe)]
    return plan


def finish_shard(recipe: Recipe, plan: dict) -> str:
    """Assemble the shard file from its groups (temporary name, then rename); remove the work folder."""
    parts = [plan["path_of"](g) for g in plan["groups"]]

    def assemble(tmp: str) -> None:
        copy_groups(recipe, parts, tmp, plan["shard"], plan["num_shards"])
        _read_back(tmp, recipe, plan)

    atomic_write(plan["final"], assemble)
    _remove_work(plan["work"])
    return plan["final"]


def _read_back(tmp: str, recipe: Recipe, plan: dict) -> None:
    """The assembled shard opens, holds exactly its groups' sequences, and its metadata is sound
    (attributes only: cheap), before it is renamed into place."""
    import h5py

    from ams_torch.apps.data.metadata import metadata_problems

    want = sorted(i for g in plan["groups"] for i in recipe.group_sequences(g))
    h = read_header(tmp)
    found = [] if h is not None and h["digest"] == recipe.digest and h["sequences"] == want else \
        [f"its header lists {None if h is None else h['sequences'][:8]}, expected sequences {want[:8]}"]
    if not found:
        with h5py.File(tmp, "r") as f:
            found = metadata_problems(f)
    if found:
        raise OSError(errno.EIO, f"{plan['final']}: the assembled shard does not read back: {found[0]}")


def _remove_work(work: str) -> None:
    """Remove a finished shard's work folder (and ``.partial`` when it is empty). A kill part-way
    leaves some of it; :func:`prepare_shard` calls this again when it finds the shard complete."""
    if os.path.isdir(work):
        shutil.rmtree(work)
    with contextlib.suppress(OSError):  # other shards may still be in progress there
        os.rmdir(os.path.dirname(work))


def generate_shard(recipe: Recipe, out: str, shard: int = 0, num_shards: int = 1, device=None,
                   progress: bool = True, log: Callable[[str], None] = print, lock: bool = True,
                   wait: bool = False) -> str:
    """Generate shard ``shard`` (0-based) of ``num_shards`` into folder ``out``, resuming a killed
    run. Returns the shard file's path; a complete shard file of this recipe is kept as it is.
    ``lock``: hold the folder's lock (see :func:`output_lock`; ``wait`` for another holder)."""
    check_sharding(recipe, num_shards, [shard])
    with output_lock(out, wait, log) if lock else contextlib.nullcontext():
        if lock:
            check_output(recipe, out, num_shards)
        plan = prepare_shard(recipe, out, shard, num_shards)
        name = os.path.basename(plan["final"])
        if plan["complete"]:
            log(f"{plan['final']}: already complete")
            return plan["final"]
        if plan["done"]:
            log(f"resuming {name}: {len(plan['done'])} of {len(plan['groups'])} batch groups already done")
        bar = None
        if progress:
            from tqdm.auto import tqdm

            bar = tqdm(total=len(plan["groups"]), initial=len(plan["done"]), unit="group",
                       desc=f"{recipe.name} shard {shard} of {num_shards} (0-based)")
        try:
            for g in plan["groups"]:
                if g not in plan["done"]:
                    ms = write_group(recipe, g, plan["path_of"](g), device)
                    if bar is not None:
                        bar.set_postfix_str(f"{ms:.0f} ms/frame for {len(recipe.group_sequences(g))} seq")
                        bar.update(1)
        finally:
            if bar is not None:
                bar.close()
        return finish_shard(recipe, plan)


def generate(recipe: Recipe, out: str, shards: Optional[Sequence[int]] = None, num_shards: int = 1, device=None,
             progress: bool = True, log: Callable[[str], None] = print, wait: bool = False) -> List[str]:
    """Generate shards ``shards`` (0-based; default all) of ``num_shards`` in this process, one
    after the other, holding the folder's lock. Returns the shard file paths."""
    shards = check_sharding(recipe, num_shards, shards)
    with output_lock(out, wait, log):
        check_output(recipe, out, num_shards)
        log_plan(recipe, log)
        return [generate_shard(recipe, out, i, num_shards, device=device, progress=progress, log=log, lock=False)
                for i in shards]
