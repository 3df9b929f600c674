"""Guide-strand selection (SPEC §11): farthest-point sampling or k-means on the roots."""
from __future__ import annotations

import torch

from ams_torch.grooms.groom import fps_order

__all__ = ["select_guides", "fps_order"]


def select_guides(roots: torch.Tensor, count: int, method: str = "fps", seed: int = 0,
                  iterations: int = 25) -> torch.Tensor:
    """Choose ``count`` guide strands among S strands from their roots.

    Args:
        roots: (S, 3) root positions, metres.
        count: number of guides, 1 ≤ count ≤ S.
        method: ``"fps"`` (farthest-point sampling, deterministic, seed unused) or ``"kmeans"``
            (Lloyd iterations from a seeded k-means++ start; each centroid picks its nearest
            strand, duplicates replaced by the farthest remaining strands).
        seed: random seed of the k-means start.
    Returns: (count,) long tensor of distinct strand indices (FPS: in selection order;
    k-means: sorted).
    """
    roots = torch.as_tensor(roots).detach().to(torch.float64).cpu()
    if roots.dim() != 2 or roots.shape[1] != 3:
        raise ValueError(f"roots must be (S, 3), got {tuple(roots.shape)}")
    if method == "fps":
        return fps_order(roots, count)
    if method != "kmeans":
        raise ValueError(f"unknown guide selection method {method!r} (use 'fps' or 'kmeans')")
    s = roots.shape[0]
    if not 1 <= count <= s:
        raise ValueError(f"guide count {count} must be in [1, {s}] (the number of strands)")
    g = torch.Generator().manual_seed(seed)
    # k-means++ initialisation
    first = int(torch.randint(s, (1,), generator=g))
    centres = [roots[first]]
    d2 = (roots - roots[first]).square().sum(-1)
    for _ in range(1, count):
        p = d2 / d2.sum() if float(d2.sum()) > 0 else torch.full_like(d2, 1.0 / s)
        c = int(torch.multinomial(p, 1, generator=g))
        centres.append(roots[c])
        d2 = torch.minimum(d2, (roots - roots[c]).square().sum(-1))
    c = torch.stack(centres)
    for _ in range(iterations):
        assign = torch.cdist(roots, c).argmin(1)
        sums = torch.zeros_like(c).index_add_(0, assign, roots)
        counts = torch.bincount(assign, minlength=count).to(roots.dtype)
        c = torch.where(counts[:, None] > 0, sums / counts.clamp_min(1)[:, None], c)
    nearest = torch.cdist(c, roots).argmin(1)
    chosen = torch.unique(nearest)
    if chosen.numel() < count:  # fill duplicates with the strands farthest from the chosen ones
        taken = torch.zeros(s, dtype=torch.bool)
        taken[chosen] = True
        dist = torch.cdist(roots, roots[chosen]).min(1).values
        extra = []
        for _ in range(count - chosen.numel()):
            dist = torch.where(taken, torch.full_like(dist, -1.0), dist)
            nxt = int(dist.argmax())
            extra.append(nxt)
            taken[nxt] = True
            dist = torch.minimum(dist, (roots - roots[nxt]).norm(dim=-1))
        chosen = torch.cat((chosen, torch.tensor(extra, dtype=torch.long)))
    return torch.sort(chosen).values
