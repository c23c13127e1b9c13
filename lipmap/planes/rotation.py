"""The reference's rotation parameters: a normal quaternion (w, x, y) and an in-plane quaternion (w, z).

The reference code (PlanarSplatting's model) optimizes a plane's rotation as two quaternions, each its own
parameter: q_n = (w, x, y, 0), which turns the z axis onto the plane's normal, and q_z = (w, 0, 0, z), a turn about
the normal; each is normalised when used, never in place, and the rotation is q_n * q_z. Here the two are one (K, 5)
leaf, (w_n, x_n, y_n, w_z, z_z): Adam is elementwise and the reference gives both groups the same learning rate and
betas, so one tensor steps as the two groups do. The renderer and everything after it take the composed (K, 4)
quaternion (:func:`composed`), so the kernels are the same for both parametrisations.
"""
from __future__ import annotations

import torch

WIDTH = 5  # the last dimension of the two-quaternion parameter


def _mult(a: torch.Tensor, b: torch.Tensor) -> torch.Tensor:
    """Hamilton product of wxyz quaternions (..., 4)."""
    aw, ax, ay, az = a.unbind(-1)
    bw, bx, by, bz = b.unbind(-1)
    return torch.stack([aw * bw - ax * bx - ay * by - az * bz,
                        aw * bx + ax * bw + ay * bz - az * by,
                        aw * by - ax * bz + ay * bw + az * bx,
                        aw * bz + ax * by - ay * bx + az * bw], -1)


def composed(rot: torch.Tensor) -> torch.Tensor:
    """(K, 5) two-quaternion parameters -> (K, 4) unit wxyz quaternion q_n * q_z (differentiable); a (K, 4)
    quaternion is returned as it is."""
    if rot.shape[-1] != WIDTH:
        return rot
    zero = torch.zeros_like(rot[..., :1])
    qn = torch.nn.functional.normalize(torch.cat([rot[..., :3], zero], -1), dim=-1)
    qz = torch.nn.functional.normalize(torch.cat([rot[..., 3:4], zero, zero, rot[..., 4:5]], -1), dim=-1)
    return torch.nn.functional.normalize(_mult(qn, qz), dim=-1)


def split(quat: torch.Tensor) -> torch.Tensor:
    """(K, 4) wxyz quaternions -> (K, 5) two-quaternion parameters of the same rotations (swing-twist about z: the
    twist is q's (w, z) normalised, the swing q * conj(twist), whose z part is 0). Where q turns z by 180 degrees
    (w = z = 0) the twist is taken as none."""
    q = torch.nn.functional.normalize(quat, dim=-1)
    w, z = q[..., 0], q[..., 3]
    n = torch.sqrt(w * w + z * z)
    ok = n > 1e-9
    tw = torch.where(ok, w / n.clamp(min=1e-12), torch.ones_like(w))
    tz = torch.where(ok, z / n.clamp(min=1e-12), torch.zeros_like(z))
    conj = torch.stack([tw, torch.zeros_like(tw), torch.zeros_like(tw), -tz], -1)
    swing = _mult(q, conj)
    return torch.stack([swing[..., 0], swing[..., 1], swing[..., 2], tw, tz], -1)
