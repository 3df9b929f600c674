"""Settings (:class:`HairHair`) and fixed data (:class:`HairHairGrid`) of the hair–hair stage."""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional

import torch

from ams_torch.stages.hair_hair.sparse import (BLOCK_CELLS, active_cells, block_layout, blocks_per_axis, p2g_sparse,
                                              pool_density)
from ams_torch.stages.hair_hair.transfer import scene_frame

__all__ = ["HairHair", "HairHairGrid", "build_hair_hair"]

MIN_AUTO_BLOCKS = 64  # the smallest automatic capacity (blocks per scene)
MIN_AUTO_ACTIVE = 4096  # the smallest automatic active-cell capacity (cells per scene)


def _check_int(name: str, value, minimum: int) -> None:
    if isinstance(value, bool) or not isinstance(value, int) or value < minimum:
        raise ValueError(f"HairHair.{name} must be an integer ≥ {minimum}; got {value!r}")


def _check_real(name: str, value, lo: float, hi: float = math.inf, lo_open: bool = False) -> None:
    ok = isinstance(value, (int, float)) and not isinstance(value, bool) and math.isfinite(value)
    ok = ok and (value > lo if lo_open else value >= lo) and value <= hi
    if not ok:
        lo_s = f"> {lo}" if lo_open else f"≥ {lo}"
        hi_s = "" if hi == math.inf else f" and ≤ {hi}"
        raise ValueError(f"HairHair.{name} must be a finite number {lo_s}{hi_s}; got {value!r}")


@dataclass(frozen=True)
class HairHair:
    """Configuration of the hair–hair stage (SPEC §6). SI units; all fields validated.

    Fields:
        resolution: cells per axis R of the cubic grid (R³ cells). Paper: 128; authors' code: 64.
        flip: FLIP share in [0, 1]; the PIC share ``1 − flip`` smooths velocities between
            neighbouring strands and acts as hair–hair friction. Default 0.95 (authors: 0.8).
        pressure_iterations: projected weighted-Jacobi sweeps of the volume-preservation solve
            (0 switches it off). Default 50 (as the authors' code).
        jacobi_omega: Jacobi relaxation weight in (0, 1]. Default 0.6 (as the authors' code).
        target_density: ρ₀, kg/m³: cells denser than this are pushed apart. ``None`` (default)
            derives it from the rest groom: ``target_density_margin ×`` the peak rest density
            on the grid, so the groom at rest is never pushed.
        target_density_margin: multiplier (> 0) used when ``target_density`` is None. Default 1.1.
        volume_stiffness: share in [0, 1] of a cell's density excess removed per frame.
            Default 1.0.
        bounds_padding: relative enlargement (≥ 0) of the grid's side over the groom's reach
            (roots ± the longest strand). Default 0.3 (the authors enlarge their box by 30 %).
        detailed_collisions: run the particle–particle repulsion after the grid. Default False.
        collision_radius: m, distance below which particles of different strands repel (and
            the spatial-hash cell size). Default 2e-3.
        collision_stiffness: share in [0, 1] of a pair's overlap removed per frame. Default 0.5.
        collision_max_per_cell: particles examined per neighbouring hash cell (≥ 1). Default 8.
        max_blocks: blocks of 4³ cells each scene's grid holds (≥ 1; a static capacity, see
            :mod:`.sparse`: storage and work follow the hair, not the R³ box). ``None`` (default):
            ``block_margin ×`` the blocks the rest groom occupies (at least 64), at most the whole
            grid. A frame whose hair occupies more blocks is flagged on the device and
            ``Simulator.check`` raises :class:`~ams_torch.sim.stepping.GridOverflow`.
        block_margin: multiplier (≥ 1) used when ``max_blocks`` or ``max_active_cells`` is None.
            Default 4.
        max_active_cells: cells per scene that can carry the pressure (all six faces massive) the
            torch path's sweeps hold (≥ 1; a static capacity: its sweeps cost this, not the
            pool). ``None`` (default): ``block_margin ×`` the active cells of the rest groom, at
            least 4,096, at most the pool's cells. More is flagged on both paths like the blocks.
    """

    resolution: int = 128
    flip: float = 0.95
    pressure_iterations: int = 50
    jacobi_omega: float = 0.6
    target_density: Optional[float] = None
    target_density_margin: float = 1.1
    volume_stiffness: float = 1.0
    bounds_padding: float = 0.3
    detailed_collisions: bool = False
    collision_radius: float = 2e-3
    collision_stiffness: float = 0.5
    collision_max_per_cell: int = 8
    max_blocks: Optional[int] = None
    block_margin: float = 4.0
    max_active_cells: Optional[int] = None

    def __post_init__(self):
        _check_int("resolution", self.resolution, 2)
        _check_real("flip", self.flip, 0.0, 1.0)
        _check_int("pressure_iterations", self.pressure_iterations, 0)
        _check_real("jacobi_omega", self.jacobi_omega, 0.0, 1.0, lo_open=True)
        if self.target_density is not None:
            _check_real("target_density", self.target_density, 0.0, lo_open=True)
        _check_real("target_density_margin", self.target_density_margin, 0.0, lo_open=True)
        _check_real("volume_stiffness", self.volume_stiffness, 0.0, 1.0)
        _check_real("bounds_padding", self.bounds_padding, 0.0)
        if not isinstance(self.detailed_collisions, bool):
            raise ValueError(f"HairHair.detailed_collisions must be a bool; got {self.detailed_collisions!r}")
        _check_real("collision_radius", self.collision_radius, 0.0, lo_open=True)
        _check_real("collision_stiffness", self.collision_stiffness, 0.0, 1.0)
        _check_int("collision_max_per_cell", self.collision_max_per_cell, 1)
        if self.max_blocks is not None:
            _check_int("max_blocks", self.max_blocks, 1)
        _check_real("block_margin", self.block_margin, 1.0)
        if self.max_active_cells is not None:
            _check_int("max_active_cells", self.max_active_cells, 1)

    def build(self, rest_positions, particle_mass, device=None, dtype=None) -> "HairHairGrid":
        """Fit the grid to the rest groom and allocate its fixed data.

        Args:
            rest_positions: (S, N, 3) metres, rest groom in the head frame (array or tensor).
            particle_mass: kg, a number or a tensor broadcastable to (S, N), positive.
            device, dtype: of the grid's tensors (default: those of ``rest_positions``, float32
                for non-tensors).
        Returns:
            a :class:`HairHairGrid`.
        """
        if dtype is None:
            dtype = rest_positions.dtype if isinstance(rest_positions, torch.Tensor) else torch.float32
        rest = torch.as_tensor(rest_positions, device=device, dtype=dtype)
        if rest.dim() != 3 or rest.shape[-1] != 3 or rest.shape[0] < 1 or rest.shape[1] < 2:
            raise ValueError(f"rest_positions must have shape (S, N, 3) with S ≥ 1, N ≥ 2; got {tuple(rest.shape)}")
        if not bool(torch.isfinite(rest).all()):
            raise ValueError("rest_positions contain non-finite values")
        s, n = rest.shape[:2]
        mass = torch.as_tensor(particle_mass, device=rest.device, dtype=dtype)
        try:
            mass = mass.expand(s, n)
        except RuntimeError:
            raise ValueError(f"particle_mass of shape {tuple(mass.shape)} does not broadcast to (S, N) = ({s}, {n})")
        if not bool((mass > 0).all()) or not bool(torch.isfinite(mass).all()):
            raise ValueError("particle_mass must be positive and finite")
        reach = (rest[:, 1:] - rest[:, :-1]).norm(dim=-1).sum(-1).max()
        roots = rest[:, 0]
        flat = rest.reshape(-1, 3)
        lo = torch.minimum(roots.amin(0) - reach, flat.amin(0))
        hi = torch.maximum(roots.amax(0) + reach, flat.amax(0))
        side = float((hi - lo).max()) * (1.0 + self.bounds_padding)
        side = max(side, 1e-6)
        h = side / self.resolution
        origin = (lo + hi) / 2 - side / 2
        whole = blocks_per_axis(self.resolution) ** 3
        # the rest groom on a pool that just holds it: its blocks, peak density and active cells
        head = rest.reshape(1, -1, 3)
        occupied = int(block_layout(head, origin, h, self.resolution, whole)[2])
        frame = scene_frame(None, (), 1, dtype, rest.device)
        pool = p2g_sparse(head, torch.zeros_like(head), mass.reshape(1, -1), frame, origin, h, self.resolution,
                          max(1, occupied))
        if self.max_blocks is not None:
            capacity = min(self.max_blocks, whole)
        else:
            capacity = min(whole, max(MIN_AUTO_BLOCKS, math.ceil(self.block_margin * occupied)))
        grid = HairHairGrid(self, h, origin, torch.ones((), device=rest.device, dtype=dtype), s, n, capacity)
        if self.target_density is not None:
            target = torch.as_tensor(self.target_density, device=rest.device, dtype=dtype)
        else:  # the peak of grid_density(rest), read from the pool (no R³ array)
            target = pool_density(*pool[:3], h, self.resolution).max() * self.target_density_margin
        grid.target_density = target.detach().clone()
        cells = capacity * BLOCK_CELLS
        if self.max_active_cells is not None:
            grid.active_capacity = min(self.max_active_cells, cells)
        else:
            active = int(active_cells(*pool[:3], grid.target_density, h, self.resolution))
            grid.active_capacity = min(cells, max(MIN_AUTO_ACTIVE, math.ceil(self.block_margin * active)))
        return grid


class HairHairGrid(torch.nn.Module):
    """Fixed data of the hair–hair grid (built by :meth:`HairHair.build`; no batch dims).

    A ``torch.nn.Module`` so that a simulator can register it: ``.to()``, ``.double()`` and
    ``state_dict()`` act on its tensors (buffers); everything else is plain Python data.

    Buffers:
        origin: (3,) metres, the grid's lower corner in the head frame.
        target_density: () kg/m³, ρ₀.
    Attributes:
        config: the :class:`HairHair` it was built from.
        resolution: R, cells per axis.
        cell_size: h, metres (cubic cells).
        num_strands, num_particles: S and N of the groom it was fitted to.
        capacity: K, blocks of 4³ cells per scene (``config.max_blocks``, or what the build
            derived from the rest groom; default here: the whole grid).
        active_capacity: active cells per scene the torch path's sweeps hold
            (``config.max_active_cells`` or derived; default here: every pool cell).
        hash_size: cells per axis of the detailed-collision hash (cell size = collision radius).
    """

    def __init__(self, config: HairHair, cell_size: float, origin: torch.Tensor, target_density: torch.Tensor,
                 num_strands: int, num_particles: int, capacity: Optional[int] = None):
        super().__init__()
        if not isinstance(config, HairHair):
            raise ValueError(f"config must be a HairHair; got {type(config).__name__}")
        if origin.shape != (3,) or target_density.shape != ():
            raise ValueError(f"origin must have shape (3,) and target_density shape (); got "
                             f"{tuple(origin.shape)} and {tuple(target_density.shape)}")
        self.config = config
        self.resolution = config.resolution
        self.cell_size = float(cell_size)
        self.num_strands = int(num_strands)
        self.num_particles = int(num_particles)
        whole = blocks_per_axis(self.resolution) ** 3
        self.capacity = whole if capacity is None else int(capacity)
        if not 1 <= self.capacity <= whole:
            raise ValueError(f"capacity must be in [1, {whole}] blocks for resolution {self.resolution}; "
                             f"got {capacity!r}")
        self.active_capacity = self.capacity * BLOCK_CELLS
        self.hash_size = int(math.ceil(self.cell_size * self.resolution / config.collision_radius)) + 3
        self.register_buffer("origin", origin)
        self.register_buffer("target_density", target_density)

    @property
    def blocks_per_axis(self) -> int:
        """nb = R // 4 + 1: blocks of 4³ cells per axis (the whole grid is nb³ blocks)."""
        return blocks_per_axis(self.resolution)

    @property
    def extent(self) -> float:
        """Side of the cubic grid, metres."""
        return self.cell_size * self.resolution

    def extra_repr(self) -> str:
        return (f"resolution={self.resolution}, cell_size={self.cell_size:.4g} m, strands={self.num_strands}, "
                f"particles={self.num_particles}, capacity={self.capacity} blocks, {self.active_capacity} active cells")


def build_hair_hair(config: Optional[HairHair], rest_positions, particle_mass, device=None,
                    dtype=None) -> Optional[HairHairGrid]:
    """``config.build(...)``, or ``None`` (nothing allocated, nothing run) when ``config`` is None.

    Args as :meth:`HairHair.build`: rest_positions (S, N, 3) m in the head frame, particle_mass kg
    broadcastable to (S, N).
    """
    if config is None:
        return None
    if not isinstance(config, HairHair):
        raise ValueError(f"hair_hair must be a HairHair config or None; got {type(config).__name__}")
    return config.build(rest_positions, particle_mass, device=device, dtype=dtype)
