"""Hair–hair interaction on a background grid that moves rigidly with the head (SPEC §6).

The paper's §3.2 (after McAdams et al. 2009, but with a grid attached to the head): once per
frame, after inextensibility, the particles' mass and momentum are rasterised to an Eulerian
grid, the grid velocity is corrected so that hair does not pile up beyond a target density,
and the result goes back to the particles with a FLIP/PIC blend (the PIC share smooths
velocities between neighbouring strands: hair–hair friction). Optional "detailed collisions"
then push apart particles of different strands that come closer than a radius.

Modules: :mod:`.config` (settings :class:`HairHair`, fixed data :class:`HairHairGrid`),
:mod:`.transfer` (frames, P2G, G2P, density on the dense grid), :mod:`.pressure` (volume
preservation, with its derivation), :mod:`.sparse` (the same grid on the blocks the hair
occupies: the stage's torch path), :mod:`.detailed` (particle repulsion), :mod:`.native` (the
grid part as registered ops with native CPU/CUDA kernels), :mod:`.stage`
(:func:`hair_hair_stage`, :func:`make_stage`).

Choices (written down here because the paper leaves them open):

* **Frame.** Everything happens in the head frame. Velocities are taken relative to the grid's
  rigid motion, ``v_rel = Rᵀ (v − V − ω × (x − T))``, so a groom moving rigidly with the head
  has zero grid velocity and comes back unchanged (no damping of rigid motion). The change
  computed on the grid is rotated back to the world and added to the incoming velocity.
* **Grid.** A cube of ``R³`` cubic cells (edge ``h``) around the groom's reach in the head frame:
  the box of the roots ± the longest strand's arc length (and the rest positions), its largest
  side enlarged by ``bounds_padding``. Staggered (MAC) layout: velocity component ``c`` lives on
  the faces normal to axis ``c`` (``(R+1)·R·R`` per component); the pressure potential and the
  density at cell centres. Transfers are trilinear (weights from each particle to the 8 nearest
  samples of each face grid), one stencil per particle and face grid shared by mass and
  momentum, no Python loop over particles. Particles outside the grid keep their velocity
  (their missing weight falls back to their own velocity).
* **Storage that follows the hair.** The dense R³ grid of :mod:`.transfer` / :mod:`.pressure` is
  the definition; the stage stores and visits only the 4³-cell blocks the hair occupies
  (:mod:`.sparse`): a pool of ``HairHairGrid.capacity`` blocks per scene (``HairHair.max_blocks``,
  by default 4 × the rest groom's), so R = 128 costs about what R = 64 does instead of 8×.
  Capacities are static shapes; a frame whose hair needs more is flagged on the device
  (``State.overflow_frame``) and ``Simulator.check`` raises ``GridOverflow``. In float64 the
  values are the dense grid's (tests compare them).
* **Density.** A cell's mass is the mean over the three axes of the average of its two face
  masses (a smoothed cell-centred rasterisation); density = mass / h³ in kg/m³.
* **Volume preservation** (unilateral, as Narain et al. 2010 do for granular media), conserving
  momentum: a potential ``φ ≥ 0`` at cell centres and ``Δu_f = −(∇φ)_f / ρ_f`` on faces with the
  face density ``ρ_f = M_f / h³``, so the particles' momentum changes by
  ``Σ_f M_f Δu_f = −h³ Σ_f (∇φ)_f = 0`` when φ lives only on cells whose six faces all have
  mass (φ = 0 elsewhere and outside the grid). The constraint ``∇·Δu ≥ b`` with
  ``b = volume_stiffness (1 − ρ₀/ρ)/Δt`` (and ``b ≥ −∇·u`` above the target) becomes
  ``Σ_f (φ_c − φ_nb)/ρ_f ≥ h² b``, solved by projected weighted Jacobi. Derivation and details:
  :mod:`.pressure`.
* **FLIP/PIC.** Per particle, ``v_flip = v + I(Δu)`` and ``v_pic = I(u + Δu)`` (``I`` trilinear
  interpolation), blended ``flip · v_flip + (1 − flip) · v_pic``.
* **Positions.** The stage replaces the frame's end velocity ``v`` by ``v'`` and moves the
  positions consistently with the backward-Euler position update ``x = xⁿ + Δt v``:
  ``x' = x + Δt (v' − v)``. (Detailed collisions move positions and velocities by separate
  amounts, so that resolving an overlap does not inject a separating velocity.)
* **Detailed collisions** (``detailed_collisions=True``): a sort-based spatial hash in the head
  frame, in torch, after the grid part (see :mod:`.detailed`).
* **Batching.** Leading dims ``...`` of ``x`` are flattened into ``B`` scenes, each with its own
  copy of the grid.
* **Backends.** The torch functions are the definition (and the only differentiable path);
  the native kernels (:mod:`.native`) do the same arithmetic without grad. The stage has no
  host synchronisation and static shapes (``torch.compile(fullgraph=True)``, CUDA graphs).

Nothing is allocated unless a scene enables hair–hair: :func:`build_hair_hair` returns ``None``
for a ``None`` config and :func:`hair_hair_stage` with ``grid=None`` returns its inputs.
Per-frame grid buffers (the block pool) are temporaries of the stage.
"""
from ams_torch.stages.hair_hair.config import HairHair, HairHairGrid, build_hair_hair
from ams_torch.stages.hair_hair.stage import hair_hair_stage, make_stage
from ams_torch.stages.hair_hair.transfer import grid_density

__all__ = ["HairHair", "HairHairGrid", "build_hair_hair", "hair_hair_stage", "grid_density", "make_stage"]
