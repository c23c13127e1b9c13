"""Planar primitives (LiP-Map paper Sec. 3.1, after PlanarSplatting): rectangles with 4 radii.

A plane is a centre ``p`` (3), a rotation quaternion ``q`` (wxyz, 4; not necessarily unit: it is
normalised in use) and radii ``r = (x+, x-, y+, y-)`` (4). With ``R = R(q)``:
X axis = R [1,0,0], Y axis = R [0,1,0], normal = R [0,0,1]. The rectangle spans [-x-, x+] along X
and [-y-, y+] along Y around the centre. Radii are clamped to [R_MIN, R_MAX] wherever they are used.

Vertex order (the paper's v1..v4) and edges e1..e4 = (v1,v2), (v2,v3), (v3,v4), (v4,v1):
v1 = p + x+ X + y+ Y,  v2 = p + x+ X - y- Y,  v3 = p - x- X - y- Y,  v4 = p - x- X + y+ Y.
"""
from __future__ import annotations

from dataclasses import dataclass

import numpy as np
import torch

from ..errors import InputError

# Shared by both renderer backends, the optimizer and the tests.
R_MIN = 1e-3  # radii clamp (reference-code fact)
R_MAX = 0.5
WEIGHT_EPS = 1e-4  # intersections with splat weight <= this are dropped (paper, appendix A)
TRANSMITTANCE_EPS = 1e-4  # compositing stops once transmittance falls below this
MAX_HITS = 5  # M nearest intersections composited per ray (paper: M = 5)
NEAR = 1e-2  # metres; intersections closer than this to the camera are ignored
# 2 sigmoid(z) = WEIGHT_EPS  <=>  z = -log((2 - WEIGHT_EPS) / WEIGHT_EPS); the splat footprint of a
# plane therefore extends SPLAT_MARGIN / lambda beyond its rectangle.
SPLAT_MARGIN = float(np.log((2.0 - WEIGHT_EPS) / WEIGHT_EPS))


def quat_to_rotmat(q: torch.Tensor) -> torch.Tensor:
    """Quaternions wxyz :math:`(..., 4)` (normalised here) -> rotation matrices :math:`(..., 3, 3)`.

    The torch twin of :func:`lipmap.poses.qvec_wxyz_to_R` (numpy, one quaternion); differentiable.
    """
    w, x, y, z = q.unbind(-1)
    # summed left to right and rooted in float64, as the Warp renderer's per-plane setup does: torch's float32 sqrt
    # is not correctly rounded on every CPU, and the two backends must see bit-identical planes. Clamped before the
    # root: finite gradients at 0.
    norm = (w * w + x * x + y * y + z * z).clamp(min=1e-24).double().sqrt().to(q.dtype)
    w, x, y, z = w / norm, x / norm, y / norm, z / norm
    return torch.stack(
        [
            1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y),
            2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x),
            2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y),
        ],
        dim=-1,
    ).reshape(*q.shape[:-1], 3, 3)


def rotation_from_normals(normals: np.ndarray, frame: np.ndarray | None = None) -> np.ndarray:
    """Rotations (K, 3, 3) whose third column is the unit normal, with a deterministic in-plane X axis.

    X is the axis of ``frame`` (rows; default the world axes) least aligned with the normal, made
    orthogonal to it (Gram-Schmidt); ties go to the lowest axis index, so the same normal always gives
    the same frame. Y = normal x X. With the scene's Manhattan frame the rectangles' edges start
    parallel to the walls' and furniture's edges, which is where the detected lines are.
    """
    n = np.asarray(normals, dtype=np.float64).reshape(-1, 3)
    n = n / np.maximum(np.linalg.norm(n, axis=1, keepdims=True), 1e-12)
    F = np.eye(3) if frame is None else np.asarray(frame, dtype=np.float64).reshape(3, 3)
    e = F[np.argmin(np.abs(n @ F.T), axis=1)]
    x = e - (e * n).sum(1, keepdims=True) * n
    x /= np.maximum(np.linalg.norm(x, axis=1, keepdims=True), 1e-12)
    y = np.cross(n, x)
    return np.stack([x, y, n], axis=2)


def rotmat_to_quat(R: np.ndarray) -> np.ndarray:
    """Rotations (K, 3, 3) -> unit quaternions wxyz (K, 4) with w >= 0 (batched :func:`lipmap.poses.R_to_qvec_wxyz`)."""
    from scipy.spatial.transform import Rotation

    from ..poses import xyzw_to_wxyz

    R = np.asarray(R, dtype=np.float64).reshape(-1, 3, 3)
    if len(R) == 0:
        return np.zeros((0, 4))
    q = xyzw_to_wxyz(Rotation.from_matrix(R).as_quat())
    return np.where(q[:, :1] < 0, -q, q)


@dataclass
class Planes:
    """K rectangular planes as torch tensors (any device; float32 unless built otherwise).

    Attributes:
        center: :math:`(K, 3)` world-frame centres (metres).
        quat: :math:`(K, 4)` rotations, wxyz (normalised in use).
        radii: :math:`(K, 4)` (x+, x-, y+, y-) in metres (clamped to [R_MIN, R_MAX] in use).
    """

    center: torch.Tensor
    quat: torch.Tensor
    radii: torch.Tensor

    def __post_init__(self):
        for name, dims in (("center", 3), ("quat", 4), ("radii", 4)):
            t = getattr(self, name)
            if not isinstance(t, torch.Tensor):
                t = torch.as_tensor(np.asarray(t), dtype=torch.float32)
                setattr(self, name, t)
            if t.ndim != 2 or t.shape[1] != dims:
                raise InputError(f"Planes.{name} must have shape (K, {dims}), got {tuple(t.shape)}")
        if not (len(self.center) == len(self.quat) == len(self.radii)):
            raise InputError(
                f"Planes fields disagree on K: center {len(self.center)}, quat {len(self.quat)}, radii {len(self.radii)}"
            )

    # ---- construction ---------------------------------------------------------------------
    @classmethod
    def from_normals(cls, centers, normals, radii, dtype=torch.float32, device=None, frame=None) -> "Planes":
        """Planes at ``centers`` (K, 3) facing ``normals`` (K, 3); ``radii`` (K,) or (K, 4); in-plane
        axes from ``frame`` (see :func:`rotation_from_normals`)."""
        centers = np.asarray(centers, dtype=np.float64).reshape(-1, 3)
        radii = np.asarray(radii, dtype=np.float64)
        if radii.ndim == 1:
            radii = np.repeat(radii[:, None], 4, axis=1)
        quat = rotmat_to_quat(rotation_from_normals(normals, frame))
        kw = dict(dtype=dtype, device=device)
        return cls(torch.as_tensor(centers, **kw), torch.as_tensor(quat, **kw), torch.as_tensor(radii, **kw))

    @classmethod
    def empty(cls, dtype=torch.float32, device=None) -> "Planes":
        kw = dict(dtype=dtype, device=device)
        return cls(torch.zeros(0, 3, **kw), torch.zeros(0, 4, **kw), torch.zeros(0, 4, **kw))

    # ---- basic container ops ----------------------------------------------------------------
    def __len__(self) -> int:
        return int(self.center.shape[0])

    @property
    def device(self) -> torch.device:
        return self.center.device

    @property
    def dtype(self) -> torch.dtype:
        return self.center.dtype

    def to(self, device=None, dtype=None) -> "Planes":
        return Planes(*(t.to(device=device, dtype=dtype) for t in (self.center, self.quat, self.radii)))

    def detach(self) -> "Planes":
        return Planes(self.center.detach().clone(), self.quat.detach().clone(), self.radii.detach().clone())

    def __getitem__(self, idx) -> "Planes":
        """Subset by index tensor, bool mask or slice (a copy for tensors; keeps autograd history)."""
        return Planes(self.center[idx], self.quat[idx], self.radii[idx])

    @staticmethod
    def cat(planes: list) -> "Planes":
        return Planes(*(torch.cat([getattr(p, f) for p in planes]) for f in ("center", "quat", "radii")))

    def tensors(self) -> list:
        return [self.center, self.quat, self.radii]

    def requires_grad_(self, flag: bool = True) -> "Planes":
        for t in self.tensors():
            t.requires_grad_(flag)
        return self

    # ---- derived geometry (differentiable) --------------------------------------------------
    def rotation(self) -> torch.Tensor:
        """:math:`(K, 3, 3)` world-frame rotations; columns = X axis, Y axis, normal."""
        return quat_to_rotmat(self.quat)

    @property
    def normal(self) -> torch.Tensor:
        """:math:`(K, 3)` unit normals R z."""
        return self.rotation()[..., 2]

    @property
    def x_axis(self) -> torch.Tensor:
        return self.rotation()[..., 0]

    @property
    def y_axis(self) -> torch.Tensor:
        return self.rotation()[..., 1]

    def radii_clamped(self) -> torch.Tensor:
        """:math:`(K, 4)` radii clamped to [R_MIN, R_MAX] (gradient zero outside the range)."""
        return self.radii.clamp(R_MIN, R_MAX)

    def corners(self) -> torch.Tensor:
        """:math:`(K, 4, 3)` vertices v1..v4 in the paper's order (see the module docstring)."""
        R = self.rotation()
        X, Y = R[..., 0], R[..., 1]
        xp, xm, yp, ym = self.radii_clamped().unbind(-1)
        sx = torch.stack([xp, xp, -xm, -xm], dim=1)[..., None]  # (K, 4, 1)
        sy = torch.stack([yp, -ym, -ym, yp], dim=1)[..., None]
        return self.center[:, None] + sx * X[:, None] + sy * Y[:, None]

    def edges(self) -> torch.Tensor:
        """:math:`(K, 4, 2, 3)` edges e1..e4 = (v1,v2), (v2,v3), (v3,v4), (v4,v1)."""
        v = self.corners()
        return torch.stack([v, v.roll(-1, dims=1)], dim=2)

    # ---- maintenance ------------------------------------------------------------------------
    def recentered(self) -> "Planes":
        """Same rectangles with x+ = x- and y+ = y- (the centre moves to the rectangle's middle).

        Uses the clamped radii, so the result is what the renderer draws. No autograd history.
        """
        with torch.no_grad():
            R = self.rotation()
            xp, xm, yp, ym = self.radii_clamped().unbind(-1)
            center = self.center + (0.5 * (xp - xm))[:, None] * R[..., 0] + (0.5 * (yp - ym))[:, None] * R[..., 1]
            rx, ry = 0.5 * (xp + xm), 0.5 * (yp + ym)
            radii = torch.stack([rx, rx, ry, ry], dim=1)
        return Planes(center, self.quat.detach().clone(), radii)

    def valid_mask(self) -> torch.Tensor:
        """:math:`(K,)` bool: finite parameters, a usable quaternion and radii above R_MIN."""
        with torch.no_grad():
            finite = torch.isfinite(self.center).all(1) & torch.isfinite(self.quat).all(1) & torch.isfinite(self.radii).all(1)
            qn = torch.nan_to_num(self.quat).norm(dim=1)
            return finite & (qn > 1e-6) & (torch.nan_to_num(self.radii, nan=-1.0).min(dim=1).values > R_MIN)

    def sanitized(self) -> tuple["Planes", torch.Tensor]:
        """(planes without degenerate entries, kept mask (K,)).

        Degenerate = non-finite centre/quaternion/radii, a zero quaternion, or a radius <= R_MIN
        (zero or negative radii included): such a plane has no area and cannot recover.
        """
        keep = self.valid_mask()
        return self.detach()[keep], keep

    # ---- numpy views --------------------------------------------------------------------------
    def numpy(self) -> dict:
        return {k: getattr(self, k).detach().cpu().numpy() for k in ("center", "quat", "radii")}


def triangle_mesh(planes: Planes) -> tuple[np.ndarray, np.ndarray]:
    """Planar mesh: vertices (4K, 3) = the corners v1..v4 of each plane, faces (2K, 3).

    Two triangles per plane (v1, v2, v3) and (v1, v3, v4), wound so their normal is the plane's.
    """
    with torch.no_grad():
        V = planes.corners().detach().cpu().double().numpy().reshape(-1, 3)
    k = np.arange(len(planes))[:, None] * 4
    # (v1, v4, v3) runs +x+y -> -x+y -> -x-y: counter-clockwise seen from +Z, so the face normal
    # is the plane normal; (v1, v3, v2) likewise.
    faces = np.concatenate([k + np.array([0, 3, 2]), k + np.array([0, 2, 1])], axis=1).reshape(-1, 3)
    return V, faces
