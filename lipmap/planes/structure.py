"""Structure changes of the plane set: pruning and splitting, and the index map that carries per-plane state."""
from __future__ import annotations

from dataclasses import dataclass
from typing import Optional

import torch

from .primitives import Planes


@dataclass
class PlaneIndexMap:
    """How a restructured plane set relates to the previous one.

    Attributes:
        parent: :math:`(K_{new},)` int64, the old index each new plane comes from (a split plane's
            children share their parent). Per-plane state follows as ``state_new = state_old[parent]``.
        n_old: K_old.
    """

    parent: torch.Tensor
    n_old: int
    n_pruned: int = 0
    n_split: int = 0
    n_unseen: int = 0  # of n_pruned: valid and large enough, but seen by no view
    child: Optional[torch.Tensor] = None  # (K_new,) bool: made by a split (None: no split)

    def old_to_new(self) -> torch.Tensor:
        """:math:`(K_{old}, 4)` int64: the new indices of each old plane (-1 padded; all -1 = pruned)."""
        out = torch.full((self.n_old, 4), -1, dtype=torch.long, device=self.parent.device)
        order = torch.argsort(self.parent, stable=True)
        p = self.parent[order]
        first = torch.searchsorted(p, p)  # index of the first child of the same parent
        out[p, torch.arange(len(p), device=p.device) - first] = order
        return out


def prune_and_split(
    planes: Planes,
    seen: Optional[torch.Tensor] = None,  # (K,) bool
    radii_grad: Optional[torch.Tensor] = None,  # (K, 2) mean |grad| of the x radii and of the y radii
    min_radius: float = 1.25e-3,
    split_threshold: Optional[float] = 0.2,
    split_into_four: bool = True,
    max_planes: int = 20000,
) -> tuple[Planes, PlaneIndexMap]:
    """Remove degenerate, tiny and unseen planes; split planes with large radius gradients.

    Removed: non-finite parameters, zero quaternions, any radius <= ``min_radius`` (radii are
    read unclamped, so zero and negative radii go too), and ``~seen`` when ``seen`` is given.
    Split (when ``split_threshold`` is set and ``radii_grad`` given): an axis whose mean |grad|
    >= threshold is cut in two halves (children half as long along it, centred on each half); with
    both axes over it and ``split_into_four``, into four. The highest-gradient planes go first if
    ``max_planes`` would be exceeded. Returns detached planes (re-centred) and the index map.
    """
    K = len(planes)
    dev = planes.device
    with torch.no_grad():
        keep = planes.valid_mask() & (torch.nan_to_num(planes.radii, nan=-1.0).min(1).values > min_radius)
        n_unseen = 0
        if seen is not None:
            n_unseen = int((keep & ~seen.to(dev)).sum())
            keep &= seen.to(dev)
        base = planes.detach()[keep].recentered()
        parent = keep.nonzero().squeeze(1)
        n_pruned = int(K - keep.sum())
        n_split = 0
        child = None
        if split_threshold is not None and radii_grad is not None and len(base) > 0:
            g = torch.nan_to_num(radii_grad.to(dev)[keep])
            sx, sy = g[:, 0] >= split_threshold, g[:, 1] >= split_threshold
            if not split_into_four:  # only the larger axis
                sx, sy = sx & (g[:, 0] >= g[:, 1]), sy & (g[:, 1] > g[:, 0])
            extra = sx.long() + sy.long() + (sx & sy).long()  # children - 1
            budget = max_planes - len(base)
            if int(extra.sum()) > budget:
                order = torch.argsort(g.max(1).values, descending=True)
                allowed = torch.zeros_like(sx)
                allowed[order[torch.cumsum(extra[order], 0) <= max(budget, 0)]] = True
                sx, sy = sx & allowed, sy & allowed
            split = sx | sy
            n_split = int(split.sum())
            if n_split:
                R = base.rotation()
                X, Y = R[..., 0], R[..., 1]
                rx, ry = base.radii[:, 0], base.radii[:, 2]
                # offsets along (X, Y) in units of the current radii, per child
                cx = torch.where(sx, 0.5, 0.0)
                cy = torch.where(sy, 0.5, 0.0)
                children = []
                parents_new = []
                idx = split.nonzero().squeeze(1)
                for ox, oy in ((1, 1), (1, -1), (-1, 1), (-1, -1)):
                    # (ox, oy) children exist when the axis with a -1 is split (or it's the first)
                    m = split.clone()
                    if ox < 0:
                        m &= sx
                    if oy < 0:
                        m &= sy
                    i = m[idx].nonzero().squeeze(1)
                    j = idx[i]
                    c = base.center[j] + (ox * cx[j] * rx[j])[:, None] * X[j] + (oy * cy[j] * ry[j])[:, None] * Y[j]
                    nrx = torch.where(sx[j], 0.5 * rx[j], rx[j])
                    nry = torch.where(sy[j], 0.5 * ry[j], ry[j])
                    children.append(Planes(c, base.quat[j], torch.stack([nrx, nrx, nry, nry], 1)))
                    parents_new.append(parent[j])
                stay = ~split
                base = Planes.cat([base[stay]] + children)
                parent = torch.cat([parent[stay]] + parents_new)
                child = torch.arange(len(parent), device=parent.device) >= int(stay.sum())
    return base, PlaneIndexMap(parent, K, n_pruned, n_split, n_unseen, child)
