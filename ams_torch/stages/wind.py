"""Wind: a spatially and temporally varying air velocity field and its force on the hair.

The air velocity (m/s, world frame) at points x (..., 3) m and time t s is

    u(x, t) = speed · d̂ · (1 + gust · g(t)) + turbulence · c(x, t)

with d̂ the base direction, g(t) ∈ [−1, 1] a smooth gust signal (two incommensurate
sinusoids at ``gust_frequency`` Hz) and c(x, t) a divergence-free curl-noise field of unit
scale (the curl of a random sum of Fourier modes of wavelength ``noise_scale`` m, drifting at
``noise_frequency`` Hz).

Force law (SPEC §4 external force): the model's drag already applies −γ m v (``Params.drag``
γ in 1/s, ``particle_mass`` m in kg), i.e. drag against still air. Wind adds
``f = c · u(x, t)`` newtons per particle with c = γ m kg/s by default, so the total air force
is the drag law ``c (u − v)`` against the moving air. Zero wind adds exactly zero force, so
it equals no wind bit for bit. Use with ``Simulator.step(state, pose, external_force=wind.bind(sim))``.
"""
from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Optional, Tuple

import torch

__all__ = ["Wind", "wind_force"]


def wind_force(air_velocity: torch.Tensor, coefficient) -> torch.Tensor:
    """The wind's force ``c · u`` (N): air_velocity (..., S, N, 3) m/s; coefficient c kg/s,
    a float or a tensor broadcastable to (..., S, N) (per-particle γ m)."""
    c = torch.as_tensor(coefficient, dtype=air_velocity.dtype, device=air_velocity.device)
    return (c[..., None] if c.dim() > 0 else c) * air_velocity


@dataclass
class Wind:
    """An air velocity field (see the module docstring). SI units.

    Fields:
        direction: base direction (3,), normalised; default +x.
        speed: base speed, m/s (>= 0).
        gust: relative gust amplitude (>= 0): the base speed varies by ± gust·speed.
        gust_frequency: Hz.
        turbulence: curl-noise amplitude, m/s (>= 0).
        noise_scale: wavelength of the noise modes, m (> 0).
        noise_frequency: drift rate of the noise phases, Hz.
        modes: number of Fourier modes of the noise.
        seed: random seed of the noise modes.
        coefficient: c in kg/s per particle; None = γ m from the simulator's parameters.
    """

    direction: Tuple[float, float, float] = (1.0, 0.0, 0.0)
    speed: float = 0.0
    gust: float = 0.0
    gust_frequency: float = 0.5
    turbulence: float = 0.0
    noise_scale: float = 0.2
    noise_frequency: float = 0.3
    modes: int = 8
    seed: int = 0
    coefficient: Optional[float] = None

    def __post_init__(self) -> None:
        d = [float(v) for v in self.direction]
        n = math.sqrt(sum(v * v for v in d))
        if len(d) != 3 or not n > 0:
            raise ValueError(f"wind.direction must be a non-zero 3-vector; got {self.direction}")
        self.direction = tuple(v / n for v in d)
        for name in ("speed", "gust", "turbulence"):
            if not float(getattr(self, name)) >= 0:
                raise ValueError(f"wind.{name} must be >= 0; got {getattr(self, name)}")
        if not self.noise_scale > 0:
            raise ValueError(f"wind.noise_scale must be positive (m); got {self.noise_scale}")
        if self.modes < 1:
            raise ValueError(f"wind.modes must be >= 1; got {self.modes}")
        if self.coefficient is not None and not self.coefficient >= 0:
            raise ValueError(f"wind.coefficient must be >= 0 (kg/s); got {self.coefficient}")
        g = torch.Generator().manual_seed(int(self.seed))
        k = torch.randn(self.modes, 3, generator=g, dtype=torch.float64)
        self._k = k / k.norm(dim=-1, keepdim=True) * (2 * math.pi / self.noise_scale)  # (K, 3) 1/m
        a = torch.randn(self.modes, 3, generator=g, dtype=torch.float64)
        a = a - (a * self._k).sum(-1, keepdim=True) * self._k / (self._k * self._k).sum(-1, keepdim=True)
        # curl of a sin(k·x + θ) is cos(k·x + θ) (k × a); normalise so the field has O(1) amplitude
        kxa = torch.cross(self._k, a, dim=-1)
        self._kxa = kxa / (kxa.norm(dim=-1, keepdim=True) * math.sqrt(self.modes / 2))
        self._phase = torch.rand(self.modes, generator=g, dtype=torch.float64) * 2 * math.pi
        self._rate = (0.5 + torch.rand(self.modes, generator=g, dtype=torch.float64)) * 2 * math.pi \
            * self.noise_frequency

    @property
    def is_zero(self) -> bool:
        return float(self.speed) == 0.0 and float(self.turbulence) == 0.0

    def gust_signal(self, t):
        """g(t) ∈ [−1, 1], dimensionless; t in seconds, a number or a tensor (then a tensor)."""
        w = 2 * math.pi * self.gust_frequency
        sin = torch.sin if isinstance(t, torch.Tensor) else math.sin
        return (sin(w * t) + 0.5 * sin(2.3 * w * t + 1.3)) / 1.5

    def velocity(self, x: torch.Tensor, t) -> torch.Tensor:
        """Air velocity u(x, t), (..., 3) m/s, at world points x (..., 3) m and time t s (a number
        or a 0-d tensor)."""
        base = torch.as_tensor(self.direction, dtype=x.dtype, device=x.device) \
            * (float(self.speed) * (1.0 + float(self.gust) * self.gust_signal(t)))
        u = base.expand_as(x)
        if float(self.turbulence) != 0.0:
            k = self._k.to(x)
            arg = x @ k.T + (self._phase + self._rate * t).to(x)  # (..., K)
            u = u + float(self.turbulence) * (torch.cos(arg) @ self._kxa.to(x))
        return u

    def bind(self, sim):
        """The external-force callable ``f(x, v, t) -> (..., S, N, 3)`` N for ``sim`` (a
        :class:`~ams_torch.Simulator`), with c = ``coefficient`` or γ m of ``sim``'s model (read
        at every call, so learnable drag and mass are seen as they are)."""

        def force(x: torch.Tensor, v: torch.Tensor, t) -> torch.Tensor:
            if self.is_zero:
                return torch.zeros_like(x)
            c = self.coefficient if self.coefficient is not None else sim.drag_coefficient()  # (S, N) kg/s
            return wind_force(self.velocity(x, t), c)

        return force
