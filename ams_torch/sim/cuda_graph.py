"""The simulator's step captured in a CUDA graph and replayed each frame: for small scenes (a few
thousand strands) a frame is a few dozen kernel launches of microseconds each, so launching them
from Python costs more than running them; one graph replay launches them all at once.

Usage (a drop-in for ``sim.step``)::

    step = GraphedStep(sim)                  # sim on a CUDA device
    state = sim.initial_state()
    for pose in poses:
        state = step(state, pose)            # captured on the first call, replayed afterwards

How: the inputs of a frame (the state, the head pose, the collider poses, the time, a tensor
external force) are flattened; a combination of their shapes, dtypes, devices and structure (e.g.
a pose with or without velocities) that was not seen before is captured once (a few warm-up
steps on a side stream, then ``torch.cuda.graph``), into static input buffers; every call copies
its inputs into those buffers and replays. The model's tensors are read in place (an in-place
change, e.g. an optimiser step on a learnable parameter, is seen; a replaced tensor, e.g. after
``.to()``, triggers a new capture). The divergence guard runs every ``params.check_every``
frames, as in ``sim.step``.

Not captured (the call runs ``sim.step`` itself, counted in ``eager_calls``): a callable external
force (Python runs inside the step), anything that needs a gradient (grad mode on and an input or
a learnable parameter requiring grad), a simulator not on CUDA (unless a ``capture`` function is
given: the tests use an eager stand-in with the same static-buffer semantics).

Outputs: with ``clone=True`` (default) each call returns tensors of its own; with ``clone=False``
it returns the graph's static outputs, overwritten by the next call (one copy less per field; keep
only the latest state).
"""
from __future__ import annotations

from collections import OrderedDict
from typing import Callable, Optional

import torch
import torch.utils._pytree as pytree

from ams_torch.sim.stepping import step as _step
from ams_torch.sim.state import State

__all__ = ["GraphedStep", "cuda_capture", "eager_capture"]


def cuda_capture(fn: Callable[[], object], warmup: int = 2):
    """Capture ``fn`` (reading static inputs, returning a pytree of tensors) in a CUDA graph, after
    ``warmup`` runs on a side stream. Returns (replay, static outputs)."""
    side = torch.cuda.Stream()
    side.wait_stream(torch.cuda.current_stream())
    with torch.cuda.stream(side):
        for _ in range(warmup):
            fn()
    torch.cuda.current_stream().wait_stream(side)
    graph = torch.cuda.CUDAGraph()
    with torch.cuda.graph(graph):
        out = fn()
    return graph.replay, out


def eager_capture(fn: Callable[[], object], warmup: int = 2):
    """The semantics of :func:`cuda_capture` without a GPU: "replay" runs ``fn`` again and copies
    its result into the static outputs of the first run (for tests of the capture logic)."""
    for _ in range(warmup):
        fn()
    out = fn()
    leaves = [t for t in pytree.tree_leaves(out) if isinstance(t, torch.Tensor)]

    def replay():
        new = [t for t in pytree.tree_leaves(fn()) if isinstance(t, torch.Tensor)]
        for dst, src in zip(leaves, new):
            dst.copy_(src)

    return replay, out


class _Captured:
    __slots__ = ("inputs", "replay", "output")

    def __init__(self, inputs, replay, output):
        self.inputs, self.replay, self.output = inputs, replay, output


class GraphedStep:
    """``sim.step`` through CUDA graphs (module docstring).

    Args:
        sim: the :class:`~ams_torch.Simulator`.
        clone: return fresh tensors (default) or the static outputs.
        warmup: steps run before a capture (allocations, lazy initialisation).
        max_graphs: captured input layouts kept (least recently used dropped).
        capture: the capture function (default :func:`cuda_capture` on CUDA; None elsewhere: eager).
    Attributes: ``captures``, ``replays``, ``eager_calls`` (counters).
    """

    def __init__(self, sim, *, clone: bool = True, warmup: int = 2, max_graphs: int = 4,
                 capture: Optional[Callable] = None):
        self.sim = sim
        self.clone = clone
        self.warmup = int(warmup)
        self.max_graphs = int(max_graphs)
        self._capture = capture if capture is not None else (cuda_capture if sim.device.type == "cuda" else None)
        self._graphs: "OrderedDict[tuple, _Captured]" = OrderedDict()
        self.captures = self.replays = self.eager_calls = 0
        self._frames = 0

    def __call__(self, state: State, pose=None, *, collider_poses=None, external_force=None) -> State:
        """One frame, as ``sim.step(state, pose, collider_poses=..., external_force=...)``."""
        sim = self.sim
        control = sim.control(state, pose, collider_poses=collider_poses, external_force=external_force)
        if not self._graphable(state, control):
            self.eager_calls += 1
            return sim.step(state, pose, collider_poses=collider_poses, external_force=external_force)
        tree = (state, control.pose, control.collider_poses, control.time, control.external_force)
        leaves, spec = pytree.tree_flatten(tree)
        key = self._key(leaves, spec)
        entry = self._graphs.get(key)
        if entry is None:
            entry = self._new(leaves, spec, control)
            self._graphs[key] = entry
            while len(self._graphs) > self.max_graphs:
                self._graphs.popitem(last=False)
        else:
            self._graphs.move_to_end(key)
            for dst, src in zip(entry.inputs, leaves):
                if isinstance(dst, torch.Tensor):
                    dst.copy_(src)
            entry.replay()
            self.replays += 1
        out = entry.output
        if self.clone:
            out = pytree.tree_map(lambda t: t.clone() if isinstance(t, torch.Tensor) else t, out)
        self._check(out)
        return out

    # -- internals ------------------------------------------------------------------------------
    def _graphable(self, state: State, control) -> bool:
        force = control.external_force
        if self._capture is None or (force is not None and not isinstance(force, torch.Tensor)):
            return False
        if torch.is_grad_enabled():
            tensors = [t for t in pytree.tree_leaves((state, control.pose, control.collider_poses,
                                                      control.external_force)) if isinstance(t, torch.Tensor)]
            tensors += list(self.sim.parameters())
            if any(t.requires_grad for t in tensors):
                return False
        return True

    def _key(self, leaves, spec) -> tuple:
        meta = tuple((tuple(t.shape), t.dtype, t.device) if isinstance(t, torch.Tensor) else t for t in leaves)
        model = tuple(t.data_ptr() for t in list(self.sim.parameters()) + list(self.sim.buffers()))
        return (str(spec), meta, model)

    def _new(self, leaves, spec, control) -> _Captured:
        inputs = [t.clone() if isinstance(t, torch.Tensor) else t for t in leaves]
        sim = self.sim

        def run():
            state, pose, colliders, time, force = pytree.tree_unflatten(inputs, spec)
            ctrl = type(control)(pose=pose, collider_poses=colliders, time=time, external_force=force)
            return _step(sim.model, state, ctrl, sim.config)

        replay, output = self._capture(run, self.warmup)
        self.captures += 1
        if self._capture is not cuda_capture:  # the stand-in computed the output; a CUDA capture only recorded it
            return _Captured(inputs, replay, output)
        replay()  # the captured frame for these inputs
        self.replays += 1
        return _Captured(inputs, replay, output)

    def _check(self, out: State) -> None:
        every = self.sim.check_every
        if every:
            self._frames += 1
            if self._frames % every == 0:
                self.sim.check(out)
