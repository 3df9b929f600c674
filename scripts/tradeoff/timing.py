"""Timing on a shared machine: a window of frames per case, cases interleaved, repeated.

Each *case* is a (setting, path) of one scene: a simulator built on the path ("native" or
"torch") and the state of that setting after ``k0`` frames of the scene (from its error run),
so every case times the same window of frames ``k0 + 1 … k0 + W`` of the head motion, mid-run
(contact and hair–hair are under way there). One repeat times every case once; repeats
alternate the order of the cases (forward, backward, ...), so a burst of load from another
process hits one repeat of a case, not all. Per case: the ms/frame of each repeat (wall time
of ``Simulator.step``, one frame at a time, per stage from the step's ``timer`` hook), reported
as minimum and median.
"""
from __future__ import annotations

import contextlib
import os
import statistics
import subprocess
import time

import torch

STAGE_NAMES = ("dynamics", "hair_hair", "collisions")


class Case:
    """One timed (setting, path): ``label`` (any hashable), ``sim``, ``state`` (after ``k0``
    frames) and the ``poses`` of the window (end-of-frame head poses, the simulator's dtype)."""

    def __init__(self, label, run, sim, state, k0: int, frames: int):
        if any(m is not None for m in run.collider_motions) or (run.wind is not None and not run.wind.is_zero):
            raise ValueError("timing windows support head motion only (no moving colliders, no wind)")
        self.label, self.sim, self.state = label, sim, state
        dt = sim.params.dt
        self.poses = [run.motion((k0 + k + 1) * dt, device=sim.device, dtype=sim.dtype) for k in range(frames)]
        self.ms: list[float] = []
        self.stages: dict = {s: [] for s in STAGE_NAMES}

    def time_once(self) -> None:
        stage = {s: 0.0 for s in STAGE_NAMES}

        @contextlib.contextmanager
        def timer(name):
            t = time.perf_counter()
            yield
            stage[name] = stage.get(name, 0.0) + time.perf_counter() - t

        state, wall = self.state, 0.0
        for pose in self.poses:
            t0 = time.perf_counter()
            state = self.sim.step(state, pose, timer=timer)
            wall += time.perf_counter() - t0
        n = len(self.poses)
        self.ms.append(1e3 * wall / n)
        for s in STAGE_NAMES:
            self.stages[s].append(1e3 * stage[s] / n)

    def result(self) -> dict:
        """``ms_min``, ``ms_median`` (ms/frame over the repeats), ``ms_repeats`` and the per-stage
        medians ``stages_median`` (ms/frame)."""
        return {"ms_min": round(min(self.ms), 3), "ms_median": round(statistics.median(self.ms), 3),
                "ms_repeats": [round(x, 3) for x in self.ms],
                "stages_median": {s: round(statistics.median(v), 3) for s, v in self.stages.items() if any(v)}}


def time_cases(cases: list, repeats: int, log=print, warmup: bool = True) -> dict:
    """Time every case ``repeats`` times, interleaved (order reversed every other repeat), after
    one untimed warm-up frame each. Returns ``{label: case.result()}``."""
    if warmup:
        for c in cases:
            c.sim.step(c.state, c.poses[0])
    t0 = time.perf_counter()
    for r in range(repeats):
        for c in (cases if r % 2 == 0 else cases[::-1]):
            c.time_once()
        log(f"  timing repeat {r + 1}/{repeats} of {len(cases)} cases: {time.perf_counter() - t0:.0f} s, "
            f"load {os.getloadavg()[0]:.2f}")
    return {c.label: c.result() for c in cases}


def other_processes() -> list[str]:
    """The project's test suites and scripts running now, other than this process and its parents."""
    try:
        out = subprocess.run(["pgrep", "-af", "pytest|scripts/"], capture_output=True, text=True, check=False).stdout
    except OSError:
        return []
    mine = {os.getpid(), os.getppid()}
    rows = []
    for line in out.splitlines():
        pid, _, cmd = line.partition(" ")
        if pid.isdigit() and int(pid) not in mine and "pgrep" not in cmd:
            rows.append(line)
    return rows


def wait_until_quiet(max_minutes: float, load_limit: float = 1.5, poll_s: float = 60.0, log=print) -> dict:
    """Poll every ``poll_s`` s, for up to ``max_minutes``, until the 1-minute load average is below
    ``load_limit`` and no other test suite or script of the project runs. Returns ``quiet``
    (whether it got quiet), ``waited_s``, ``load_1min`` and ``others`` (at the end)."""
    t0 = time.perf_counter()
    while True:
        load, others = os.getloadavg()[0], other_processes()
        if load < load_limit and not others:
            return {"quiet": True, "waited_s": round(time.perf_counter() - t0), "load_1min": round(load, 2),
                    "others": []}
        if time.perf_counter() - t0 >= 60 * max_minutes:
            return {"quiet": False, "waited_s": round(time.perf_counter() - t0), "load_1min": round(load, 2),
                    "others": others}
        log(f"waiting for a quiet machine: load {load:.2f}, {len(others)} other process(es)"
            + (f" (e.g. {others[0][:100]})" if others else ""))
        time.sleep(poll_s)


def thread_setup(threads: int) -> int:
    if threads > 0:
        torch.set_num_threads(threads)
    return torch.get_num_threads()
