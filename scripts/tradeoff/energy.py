"""The one-step energy probe: does a step of the integrator gain energy (SPEC §4)?

From a state of a scene's run, one frame step (M substeps) is taken with the head held still
and every non-conservative or once-per-frame term removed: no gravity, no drag, no
inextensibility, no collisions, no hair–hair, Hookean integrity (the non-Hookean law's energy
is not ½κd², and its plastic yield moves the ghosts), float64. The state is taken in the head's
frame: the head's pose is kept and its velocity set to zero, the hair's velocities are its
velocities relative to the head's rigid motion (pinned particles: zero). What is left is
conservative: its total energy (kinetic + spring + integrity + angular, as
``ams_torch.testing.total_energy``) can only fall or stay in an exact step, and any rise is
the frozen-direction linearisation's.
"""
from __future__ import annotations

import torch

import ams_torch as at
from ams_torch.testing import total_energy

F64 = torch.float64


class EnergyProbe:
    """Called as ``probe(k, state)`` after each frame of a run (``run_setting(probes=...)``):
    records the relative energy change of one conservative probe step from that state, with
    geometric stiffness off and on (the same state for both)."""

    def __init__(self, sim: at.Simulator):
        p = sim.params.replace(gravity=(0.0, 0.0, 0.0), drag=0.0, inextensibility=False, integrity_model="hookean",
                               check_every=0)
        rest = sim.model.rest_positions.double()
        self.sims = {gs: at.Simulator(rest, p.replace(geometric_stiffness=gs), dtype=F64, backend="native")
                     for gs in (False, True)}
        self.energy = []  # per frame: E0 of the probe state (J)
        self.gain = {False: [], True: []}  # per frame: (E1 − E0) / E0

    def __call__(self, k: int, state) -> None:
        pose = state.pose.to(dtype=F64)
        x = state.x.detach().double()
        v = state.v.detach().double() - pose.velocity_at(x)
        z = torch.zeros_like(pose.translation)
        still = pose.with_velocity(z, z.clone())
        for gs, sim in self.sims.items():
            s0 = sim.initial_state(still).replace(x=x, v=v, ghost_rest=state.ghost_rest.detach().double(),
                                                  sag_offset=state.sag_offset.detach().double())
            pinned = sim.model.pinned[..., None]
            s0 = s0.replace(v=torch.where(pinned, torch.zeros_like(v), v))
            e0 = float(total_energy(sim, s0))
            s1 = sim.step(s0, still)
            e1 = float(total_energy(sim, s1))
            if not gs:
                self.energy.append(e0)
            self.gain[gs].append((e1 - e0) / e0 if e0 > 0 else 0.0)

    def summary(self, floor: float = 1e-6) -> dict:
        """Per form (``"spec"``: geometric stiffness off, ``"geometric"``: on): the largest
        one-step relative gain over the run's frames, the share of frames that gained more than
        1e-9, and the median relative change; frames whose energy is below ``floor`` × the run's
        largest are left out (rounding dominates their ratio)."""
        if not self.energy:
            return {}
        top = max(self.energy)
        alive = [i for i, e in enumerate(self.energy) if e > floor * top]
        out = {"frames": len(alive)}
        for gs, name in ((False, "spec"), (True, "geometric")):
            g = sorted(self.gain[gs][i] for i in alive)
            out[name] = {"max_gain": max(g) if g else None,
                         "gaining_share": sum(1 for x in g if x > 1e-9) / len(g) if g else None,
                         "median_change": g[len(g) // 2] if g else None}
        return out
