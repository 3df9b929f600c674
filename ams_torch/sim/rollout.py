"""Rollouts: many frames of the pure step, with gradients through all of them at O(frames / k) memory.

``rollout(sim, state, controls, checkpoint_every=k)`` runs one frame per control and returns the
states (or what ``observe`` takes of each, or what ``reduce`` folds them into). Without
checkpointing (k = 0) autograd keeps every frame's graph: memory grows with frames × the
operations of a frame (854 MiB for 92 frames of a 12-strand groom in ``docs/identification.md``).
With ``checkpoint_every=k`` the frames run in segments of k, each one node of a hand-written
segment recompute (:class:`_Segment`): its forward runs without autograd and keeps only the
segment's input state; its backward runs the segment again with autograd on and back-propagates
through it, one segment at a time. Memory: one state per segment plus one segment's graph during
the backward, O(frames / k + k) (k ≈ √frames is the least); time: one extra forward. With
``checkpoint_frames=True`` the recomputed segment is itself a chain of one-frame nodes, so its
backward holds one state per frame and a single frame's graph (two levels; one more forward).

Unlike ``torch.utils.checkpoint`` the segment lists its differentiable inputs itself: the state,
the simulator's parameters and grad-carrying buffers (learnable fields, their parametrisations,
a collider's friction given as a tensor), and the tensors of the segment's controls (head and
collider poses, external forces). So ``loss.backward()`` and ``torch.autograd.grad(loss, inputs)``
both work, and no autograd graph is held between the passes (the non-reentrant checkpoint drops
saved tensors but keeps every frame's graph nodes). A tensor that only a callable external force
``f(x, v, t)`` captures is not seen: give such forces as tensors when they must receive gradients
through a checkpointed rollout.

The forward of a segment runs without autograd, where a simulator built with ``backend="auto"``
takes the native kernels, and its recomputation the path a frame with gradients takes; in float64
both are the same trajectory to rounding. Build the simulator with ``backend="torch"`` when the two
passes must be the same arithmetic bit for bit.
"""
from __future__ import annotations

from typing import Any, Callable, List, NamedTuple, Optional, Sequence, Union

import torch
import torch.utils._pytree as pytree

from ams_torch.geometry.pose import Pose
from ams_torch.sim.state import Control, State
from ams_torch.sim.stepping import step as _step

__all__ = ["rollout", "Rollout", "frame_controls"]

#: One frame's control: None (the head stays), a Pose (the head at the end of the frame), a
#: :class:`Control`, a dict with keys among ``pose``, ``collider_poses``, ``external_force``, or a
#: tuple ``(pose, collider_poses, external_force)``.
FrameControl = Any
Controls = Union[Sequence[FrameControl], Callable[[int], FrameControl]]


class Rollout(NamedTuple):
    """What :func:`rollout` returns.

    final: the State after the last frame. outputs: one entry per frame, ``observe(state)`` when
    ``observe`` was given, else the State itself (None when only ``reduce`` was given). value: the
    reducer's result (None without ``reduce``)."""

    final: State
    outputs: Optional[list]
    value: Any


def frame_controls(item: FrameControl) -> tuple:
    """(pose, collider_poses, external_force) of one frame's control (see :data:`FrameControl`)."""
    if item is None or isinstance(item, Pose):
        return item, None, None
    if isinstance(item, Control):
        return item.pose, (list(item.collider_poses) or None), item.external_force
    if isinstance(item, dict):
        unknown = set(item) - {"pose", "collider_poses", "external_force"}
        if unknown:
            raise ValueError(f"a frame's control dict takes pose, collider_poses, external_force; got {sorted(unknown)}")
        return item.get("pose"), item.get("collider_poses"), item.get("external_force")
    if isinstance(item, tuple) and len(item) == 3:
        return item
    raise ValueError(f"a frame's control must be None, a Pose, a Control, a dict or a (pose, collider_poses, "
                     f"external_force) tuple; got {type(item).__name__}")


def _grad_tensors(obj) -> list:
    """The tensors in a pytree-ish control (poses, lists, dicts) that require grad."""
    leaves = pytree.tree_leaves(obj, is_leaf=lambda t: isinstance(t, torch.Tensor))
    return [t for t in leaves if isinstance(t, torch.Tensor) and t.requires_grad]


def _unique(tensors: list) -> list:
    seen, out = set(), []
    for t in tensors:
        if id(t) not in seen:
            seen.add(id(t))
            out.append(t)
    return out


class _Segment(torch.autograd.Function):
    """A segment of frames as one autograd node that recomputes itself in the backward pass.

    forward(run, n_state, foreign, *inputs): foreign: ids of tensors the segment may return but did
    not create (copied on the way out); inputs[:n_state] are the flattened (state, accumulator) of the
    segment's start, inputs[n_state:] the segment's other differentiable inputs (parameters,
    control tensors), which ``run`` reads itself. ``run(state_leaves)`` returns the segment's flat
    outputs. Only the state leaves are saved."""

    @staticmethod
    def forward(ctx, run, n_state, foreign, *inputs):
        ctx.run, ctx.n_state = run, n_state
        ctx.externals = inputs[n_state:]
        ctx.save_for_backward(*inputs[:n_state])
        outs = run(list(inputs[:n_state]))
        # autograd gives the output tensors themselves this node as their grad_fn: an output that
        # the segment did not create (an input, a control's pose carried into the state, a model
        # buffer) or a view is returned as a copy, so no tensor outside the segment is rewired
        ids = {id(t) for t in inputs} | foreign
        outs = [o.clone() if id(o) in ids or o._base is not None else o for o in outs]
        ctx.mark_non_differentiable(*[o for o in outs if not o.is_floating_point()])
        return tuple(outs)

    @staticmethod
    def backward(ctx, *grads):
        saved = ctx.saved_tensors
        leaves = [t.detach().requires_grad_(t.requires_grad) if t.is_floating_point() else t for t in saved]
        with torch.enable_grad():
            outs = ctx.run(list(leaves))
        pairs = [(o, g) for o, g in zip(outs, grads) if g is not None and o.requires_grad]
        wrt = [t for t in list(leaves) + list(ctx.externals) if t.requires_grad]
        got = iter(torch.autograd.grad([o for o, _ in pairs], wrt, [g for _, g in pairs], allow_unused=True)
                   if pairs and wrt else [None] * len(wrt))
        out = [next(got) if t.requires_grad else None for t in list(leaves) + list(ctx.externals)]
        return (None, None, None, *out)


def _differentiable_parameters(sim) -> list:
    """The simulator's parameters and buffers that require grad (learnable fields, their
    parametrisations' raw values, grad-carrying Params tensors, a collider's friction tensor)."""
    return _unique([p for p in sim.parameters() if p.requires_grad] + [b for b in sim.buffers() if b.requires_grad])


def rollout(sim, state: State, controls: Controls, *, frames: Optional[int] = None, checkpoint_every: int = 0,
            checkpoint_frames: bool = False, observe: Optional[Callable[[State], Any]] = None,
            reduce: Optional[Callable[[Any, int, State], Any]] = None, initial: Any = None,
            check: bool = True) -> Rollout:
    """Run ``frames`` frames of ``sim`` from ``state``, one per control.

    Args:
        sim: a :class:`~ams_torch.Simulator` (its model, config and input checks).
        state: the State to start from (e.g. ``sim.initial_state()``, possibly with grad-carrying x, v).
        controls: a sequence with one :data:`FrameControl` per frame (a Pose, a dict, a Control, ...),
            or a callable ``frame index → FrameControl`` (then ``frames`` is required).
        frames: how many frames (default: ``len(controls)``).
        checkpoint_every: k ≥ 1 runs the frames in segments of k that are recomputed in the backward
            pass (memory O(frames / k + k) instead of O(frames)); 0 keeps every frame's graph.
        checkpoint_frames: with ``checkpoint_every``, the backward pass's recompute of a segment
            checkpoints each of its frames too (a second level): while a segment is differentiated
            it keeps one state per frame instead of every frame's graph (the saved inputs of the
            frame's native ops: about 3 states' worth per frame), at the cost of one more forward
            per frame. Memory: (frames / k + k) states plus one frame's graph.
        observe: ``state → tensor(s)`` taken after every frame (e.g. positions at material points);
            the results are ``outputs``. Default: the States themselves are the outputs (unless
            ``reduce`` is given).
        reduce: ``(accumulator, frame index, state) → accumulator`` after every frame, from
            ``initial`` (tensors, or pytrees of tensors, and numbers); its result is ``value``
            (e.g. a loss summed over frames without keeping the frames' positions).
        check: read the divergence flag once at the end (:meth:`Simulator.check`; one host sync).
    Returns:
        :class:`Rollout` (final, outputs, value).
    """
    if callable(controls) and not isinstance(controls, Sequence):
        if frames is None:
            raise ValueError("rollout: give frames= with a callable controls")
        get = controls
    else:
        controls = list(controls)
        frames = len(controls) if frames is None else int(frames)
        if frames > len(controls):
            raise ValueError(f"rollout: {frames} frames but {len(controls)} controls")
        get = controls.__getitem__
    if checkpoint_every < 0 or int(checkpoint_every) != checkpoint_every:
        raise ValueError(f"checkpoint_every must be an integer ≥ 0; got {checkpoint_every!r}")
    keep_states = observe is None and reduce is None
    acc = initial
    outputs: Optional[list] = None if (observe is None and reduce is not None) else []
    k = int(checkpoint_every) or frames
    params = _differentiable_parameters(sim) if torch.is_grad_enabled() and checkpoint_every else []
    for start in range(0, frames, k):
        items = [frame_controls(get(i)) for i in range(start, min(start + k, frames))]
        run = _segment_runner(sim, items, start, observe, reduce, keep_states,
                              params if checkpoint_frames and checkpoint_every else None)
        flat_in, spec = pytree.tree_flatten((state, acc))
        tensor_in = [t for t in flat_in if isinstance(t, torch.Tensor)]
        externals = _unique(params + _grad_tensors(items))
        differentiable = any(t.requires_grad for t in tensor_in) or externals
        if not checkpoint_every or not torch.is_grad_enabled() or not differentiable:
            state, outs, acc = run(state, acc)
        else:
            foreign = {id(t) for t in pytree.tree_leaves(items) + list(sim.parameters()) + list(sim.buffers())
                       if isinstance(t, torch.Tensor)}
            state, outs, acc = _checkpointed(run, flat_in, spec, externals, foreign)
        if outputs is not None:
            outputs.extend(outs)
    if check:
        sim.check(state)
    return Rollout(final=state, outputs=outputs, value=acc)


def _segment_runner(sim, items: List[tuple], start: int, observe, reduce, keep_states: bool,
                    frame_nodes: Optional[list] = None):
    """run(state, acc) → (state, [per-frame outputs], acc) for the frames ``start …`` of ``items``.
    ``frame_nodes``: the differentiable parameters, given when each frame of a recomputation (grad
    mode on: the backward pass of a checkpointed segment) is itself a checkpointed node."""

    def run(state, acc):
        if frame_nodes is not None and torch.is_grad_enabled() and len(items) > 1:
            outs = []
            for i, item in enumerate(items):
                one = _segment_runner(sim, [item], start + i, observe, reduce, keep_states)
                flat_in, spec = pytree.tree_flatten((state, acc))
                foreign = {id(t) for t in pytree.tree_leaves([item]) + list(sim.parameters()) + list(sim.buffers())
                           if isinstance(t, torch.Tensor)}
                state, o, acc = _checkpointed(one, flat_in, spec, _unique(frame_nodes + _grad_tensors([item])),
                                              foreign)
                outs.extend(o)
            return state, outs, acc
        outs = []
        for i, (pose, collider_poses, external_force) in enumerate(items):
            control = sim.control(state, pose, collider_poses=collider_poses, external_force=external_force)
            state = _step(sim.model, state, control, sim.config, stages=sim.stages)
            if observe is not None:
                outs.append(observe(state))
            elif keep_states:
                outs.append(state)
            if reduce is not None:
                acc = reduce(acc, start + i, state)
        return state, outs, acc

    return run


def _checkpointed(run, flat_in: list, spec, externals: list, foreign: set) -> tuple:
    """run(state, acc) as one :class:`_Segment` node: (state, outs, acc) with their tensors its outputs."""
    positions = [i for i, t in enumerate(flat_in) if isinstance(t, torch.Tensor)]
    box = {}

    def flat_run(tensors: list) -> list:
        leaves = list(flat_in)
        for i, t in zip(positions, tensors):
            leaves[i] = t
        state, acc = pytree.tree_unflatten(leaves, spec)
        result = run(state, acc)
        out_leaves, out_spec = pytree.tree_flatten(result)
        tensor_out = [t for t in out_leaves if isinstance(t, torch.Tensor)]
        box.setdefault("spec", out_spec)
        # the non-tensor leaves only: the tensors become this node's outputs, and a reference to them
        # from its own `run` closure would be a cycle through the autograd graph that Python's
        # collector cannot see (every segment's outputs and graph would stay alive)
        box.setdefault("leaves", [None if isinstance(t, torch.Tensor) else t for t in out_leaves])
        box.setdefault("tensor_slots", [i for i, t in enumerate(out_leaves) if isinstance(t, torch.Tensor)])
        # one output per distinct tensor (a state returned as the final state and as an output)
        unique = _unique(tensor_out)
        box.setdefault("index", [next(j for j, u in enumerate(unique) if u is t) for t in tensor_out])
        return unique

    tensors = [flat_in[i] for i in positions]
    outs = _Segment.apply(flat_run, len(tensors), foreign, *tensors, *externals)
    leaves = list(box["leaves"])
    for slot, j in zip(box["tensor_slots"], box["index"]):
        leaves[slot] = outs[j]
    return pytree.tree_unflatten(leaves, box["spec"])
