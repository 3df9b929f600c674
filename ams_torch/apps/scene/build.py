"""Building a validated scene: head mesh, groom, colliders, motion, wind and the simulator."""
from __future__ import annotations

import time
from dataclasses import dataclass, field
from typing import Any, Dict, List, Optional

import numpy as np
import torch

from ams_torch.apps.motion import Motion, make_motion
from ams_torch.apps.scene.schema import make_collider, make_params
from ams_torch.sim.params import Params
from ams_torch.stages.wind import Wind

__all__ = ["BuiltScene", "build", "trim_strands"]


def _import_args(section: dict) -> dict:
    """The import keys of a [head]/[groom] section (units normalised to ``scale`` by the schema)."""
    return {k: section[k] for k in ("scale", "up_axis", "transform") if k in section}


def _head_mesh(head: dict):
    if head["mesh"] == "default":
        from ams_torch.grooms.head import default_head

        return default_head(head["subdivisions"])
    if head["mesh"] in ("sphere", "none"):
        return None
    from ams_torch.geometry.mesh import load_mesh

    return load_mesh(head["mesh"], **_import_args(head))


#: m: imported strands shorter than this are dropped (a few millimetre-long "strands" of 32
#: particles are degenerate: their segments of micrometres make every stiffness of the per-length
#: material enormous against their mass). Override with ``[groom] min_length``.
MIN_STRAND_LENGTH = 0.005


def _drop_short_strands(groom, min_length: float):
    keep = groom.lengths() >= min_length
    if keep.all():
        return groom
    out = groom.subset(np.flatnonzero(keep))
    out.metadata["dropped_short_strands"] = int((~keep).sum())
    out.metadata["min_length"] = float(min_length)
    return out


def _make_groom(scene: dict, mesh) -> tuple:
    """The scene's groom (scaled strand count): (rest positions (S, N, 3) m as numpy, the
    :class:`~ams_torch.Groom` with its root binding for presets and files, or None)."""
    g = scene["groom"]
    scale = float(scene["scale"])
    strands = max(1, int(round(g.get("strands", 1000) * scale)))
    particles = g.get("particles")
    if "preset" in g:
        from ams_torch.grooms.presets import preset

        groom = preset(g["preset"], strands=strands, particles=particles, seed=g.get("seed", 0), mesh=mesh,
                       **g.get("growth", {}))
        return groom.rest_positions.numpy(), groom
    if "file" in g:
        from ams_torch.grooms.io import read_groom

        groom = read_groom(g["file"], resample=particles or 32, **_import_args(g))
        groom = _drop_short_strands(groom, g.get("min_length", MIN_STRAND_LENGTH))
        if g.get("bind"):  # roots to their nearest triangles of the head mesh (SPEC §14)
            groom = groom.bind_to(mesh, **({"max_distance": g["max_bind_distance"]} if "max_bind_distance" in g
                                           else {}))
        if scale != 1.0:
            groom = groom.subset(np.linspace(0, groom.num_strands - 1, strands).astype(int))
        return groom.rest_positions.numpy(), groom
    n = particles or 32
    length = g.get("length", 0.25)
    if g["kind"] == "sphere":
        from ams_torch.grooms.simple import sphere_groom

        return sphere_groom(strands, n, radius=g.get("radius", scene["head"]["radius"]), length=length).numpy(), None
    if g["kind"] == "wisp":
        from ams_torch.grooms.simple import wisp

        return np.asarray(wisp(strands, n, length=length, spread=g.get("spread", 0.01))), None
    # a single horizontal strand (or several side by side, 1 cm apart), rooted at the origin
    t = np.linspace(0.0, length, n)
    rest = np.zeros((strands, n, 3))
    rest[:, :, 0] = t
    rest[:, :, 2] = (np.arange(strands) * 0.01)[:, None]
    return rest, None


@dataclass
class BuiltScene:
    """What :func:`build` makes. ``sim`` is the :class:`~ams_torch.Simulator`; ``motion`` the head
    motion; ``wind`` (or None); ``collider_motions`` one entry per collider (Motion or None);
    ``rest`` the simulated rest shape (S, N, 3) m; ``groom`` the :class:`~ams_torch.Groom` it came
    from (root binding) for preset and file grooms, else None."""

    scene: dict
    sim: Any
    motion: Motion
    wind: Optional[Wind]
    collider_motions: List[Optional[Motion]]
    head_mesh: Any
    rest: np.ndarray
    build_seconds: Dict[str, float] = field(default_factory=dict)
    groom: Any = None


def _ms_variant(params: Params, rest: np.ndarray, offset) -> tuple:
    """Duplicate the groom as plain mass-spring strands (κ_I = κ_α = 0, so no sag-free offset
    either) shifted by ``offset``; the original strands keep the AMS couplings."""
    from ams_torch.sim.params import ANGULAR_FIELD, INTEGRITY_FIELD

    s = rest.shape[0]
    both = np.concatenate([rest, rest + np.asarray(offset)[None, None]], 0)
    per = lambda v: torch.cat([torch.full((s, 1), float(v)), torch.zeros(s, 1)])  # noqa: E731
    fi, fa = INTEGRITY_FIELD[params.material], ANGULAR_FIELD[params.material]
    return params.replace(**{fi: per(getattr(params, fi)), fa: per(getattr(params, fa))}), both


def build(scene: dict, device=None, dtype=torch.float32) -> BuiltScene:
    """Build the simulator and controls of a validated scene (see :func:`load_scene`).
    Only the stages the scene names are built (no grid, no SDF otherwise)."""
    from ams_torch.stages.hair_hair import HairHair
    from ams_torch.sim.simulator import Simulator

    times = {}
    t0 = time.perf_counter()
    mesh = _head_mesh(scene["head"])
    rest, groom = _make_groom(scene, mesh)
    times["groom"] = time.perf_counter() - t0
    params = make_params(scene)
    if scene["groom"]["compare_ms"]:
        params, rest = _ms_variant(params, rest, scene["groom"]["compare_offset"])
        groom = None  # the doubled groom has no single root binding
    stages = scene["stages"]
    cols, col_motions = [], []
    if stages["collisions"]:
        from ams_torch.stages.collide import MeshCollider, SphereCollider

        if scene["head"]["collide"] and mesh is not None:
            cols.append(MeshCollider(mesh, resolution=scene["head"]["sdf_resolution"], follow_head=True))
            col_motions.append(None)
        elif scene["head"]["collide"] and scene["head"]["mesh"] == "sphere":
            cols.append(SphereCollider(radius=scene["head"]["radius"], follow_head=True))
            col_motions.append(None)
        for c in scene["colliders"]:
            cols.append(make_collider(c))
            col_motions.append(make_motion(c["motion"]) if "motion" in c else None)
    hh = HairHair(**scene.get("hair_hair", {})) if stages["hair_hair"] else None
    t1 = time.perf_counter()
    motion = make_motion(scene.get("motion"))
    sim = Simulator(rest, params, device=device, dtype=dtype, pose=motion(0.0, dtype=dtype), hair_hair=hh,
                    colliders=cols or None)  # builds (or loads) the SDFs now, not inside the first frame
    times["simulator"] = time.perf_counter() - t1
    wind = Wind(**scene["wind"]) if "wind" in scene else None
    return BuiltScene(scene, sim, motion, wind, col_motions, mesh, rest, times, groom)


def trim_strands(rest: torch.Tensor, x: torch.Tensor, v: torch.Tensor, pose, point, normal,
                 min_fraction: float = 0.2) -> tuple:
    """Cut strands where they cross a plane (digital trimming).

    rest: (S, N, 3) m head-frame rest shape; x, v: (S, N, 3) world positions (m) and velocities
    (m/s); pose: the head pose; point, normal: the plane in the head frame (the side the normal
    points to is cut off). Each strand whose current shape crosses the plane keeps the arc-length
    fraction f up to the crossing (at least ``min_fraction``); its rest shape, positions and
    velocities are resampled to the same N particles over that fraction. Returns (new rest
    (S, N, 3), new x, new v, kept fraction (S,)).
    """
    xl = pose.to_local(x)
    p = torch.as_tensor(point, dtype=x.dtype, device=x.device)
    n = torch.nn.functional.normalize(torch.as_tensor(normal, dtype=x.dtype, device=x.device), dim=0)
    side = (xl - p) @ n  # (S, N), > 0: to be cut
    seg = (xl[:, 1:] - xl[:, :-1]).norm(dim=-1)
    arc = torch.nn.functional.pad(torch.cumsum(seg, -1), (1, 0))  # (S, N)
    total = arc[:, -1].clamp(min=1e-12)
    out = side > 0
    num = x.shape[1]
    first = torch.where(out.any(-1), out.float().argmax(-1), torch.full_like(out[:, 0], num, dtype=torch.long))
    frac = torch.ones(x.shape[0], dtype=x.dtype, device=x.device)
    cut = (first > 0) & (first < num)
    i1 = first.clamp(1, num - 1)
    i0 = i1 - 1
    s0 = side.gather(1, i0[:, None])[:, 0]
    s1 = side.gather(1, i1[:, None])[:, 0]
    w = (-s0 / (s1 - s0).clamp(min=1e-12)).clamp(0, 1)  # s0 <= 0 < s1
    a0, a1 = arc.gather(1, i0[:, None])[:, 0], arc.gather(1, i1[:, None])[:, 0]
    frac = torch.where(cut, ((a0 + w * (a1 - a0)) / total).clamp(min=min_fraction, max=1.0), frac)

    def resample(y: torch.Tensor) -> torch.Tensor:
        u = arc / total[:, None]  # (S, N) parameter of each particle along the current strand
        target = torch.linspace(0, 1, num, dtype=x.dtype, device=x.device)[None] * frac[:, None]
        idx = torch.searchsorted(u.contiguous(), target.contiguous()).clamp(1, num - 1)
        ua, ub = u.gather(1, idx - 1), u.gather(1, idx)
        t = ((target - ua) / (ub - ua).clamp(min=1e-12)).clamp(0, 1)[..., None]
        ya = y.gather(1, (idx - 1)[..., None].expand(-1, -1, 3))
        yb = y.gather(1, idx[..., None].expand(-1, -1, 3))
        return ya + t * (yb - ya)

    return resample(rest), resample(x), resample(v), frac
