"""Sensor depth at projected pixels: which depth-map pixel a camera pixel falls in (at any depth-map resolution),
and the smallest disagreement over its 3x3 neighbours (at a depth step one side agrees with a point on the step's
edge). Shared by the line term's depth gate (the planes) and the depth check of extracted lines."""
from __future__ import annotations

import numpy as np


def depth_pixels(uv: np.ndarray, z: np.ndarray, camera, depth_shape) -> tuple:
    """(row, col, inside) of projections ``uv`` (camera pixels) in a depth map of ``depth_shape``,
    which may have another resolution than the camera (indices scale, the map is not resampled)."""
    H, W = depth_shape
    sx, sy = W / camera.width, H / camera.height
    col = np.floor(uv[:, 0] * sx).astype(int)
    row = np.floor(uv[:, 1] * sy).astype(int)
    inside = (z > 0) & (col >= 0) & (col < W) & (row >= 0) & (row < H)
    return np.clip(row, 0, H - 1), np.clip(col, 0, W - 1), inside


def depth_window(row: np.ndarray, col: np.ndarray, shape) -> np.ndarray:
    """Flat indices :math:`(N, 9)` of the 3x3 pixels around (row, col) in a map of ``shape`` (H, W), clamped at
    the border: build once for pixels that stay put (a line's region), gather from each depth map."""
    H, W = shape
    return np.stack([np.clip(row + dy, 0, H - 1) * W + np.clip(col + dx, 0, W - 1)
                     for dy in (-1, 0, 1) for dx in (-1, 0, 1)], 1)


def nearest_depth_residual(depth: np.ndarray, row: np.ndarray, col: np.ndarray, z: np.ndarray,
                           window: np.ndarray | None = None) -> np.ndarray:
    """Smallest |z - depth| over the 3x3 pixels around (row, col) of a depth map (0 = invalid); inf where none of
    them has depth. At a depth step one side agrees with a point on the step's edge. ``window``: the pixels'
    :func:`depth_window`, when the caller keeps it (``row``/``col`` are then unused)."""
    if window is None:
        window = depth_window(row, col, depth.shape)
    d = depth.reshape(-1)[window]
    res = np.where(d > 0, np.abs(d - np.asarray(z)[:, None]), np.inf)
    return res.min(1) if len(res) else np.full(0, np.inf)


def nearest_depth_residual_torch(depth, z, window):
    """:func:`nearest_depth_residual` on tensors (the line term's device twin): ``depth`` :math:`(H, W)`, ``z``
    :math:`(N,)`, ``window`` :math:`(N, 9)` long. Compared in ``z``'s dtype."""
    import torch

    d = depth.reshape(-1)[window].to(z.dtype)
    res = torch.where(d > 0, (d - z[:, None]).abs(), torch.full_like(d, float("inf")))
    return res.amin(1) if len(res) else torch.full((0,), float("inf"), dtype=z.dtype, device=z.device)
