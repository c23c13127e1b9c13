"""The line term of the joint line-plane optimization (paper Sec. 3.3), as a callback for the plane loop.

Each training iteration samples pixels from the 1-pixel regions of the view's detected lines (one per
line by default, as the reference code does), finds the first plane each pixel's ray hits and the edge
that explains the line (no gradient), and returns the line loss of those edges (with gradient).
"""
from __future__ import annotations

import numpy as np
import torch

from ..frames import DEFAULT_CAPACITY, LRU
from ..planes.primitives import TRANSMITTANCE_EPS
from .assign import (best_edges, first_hit, first_hit_in_render, line_regions, pixel_rays_camera,
                     pixel_rays_world)
from .depth_lookup import depth_window, nearest_depth_residual
from .losses import line_loss


class LineSupervision:
    """``extra_loss(view, planes, iteration, render, target) -> weight * line loss`` for :func:`optimize_planes`.

    Args:
        lines_by_view: {view name: (N, 4) detected segments at the view's FULL resolution}.
        weight: the paper's alpha_L (0.1).
        pixels_per_line: region pixels sampled per line per iteration (>= 2 for the group loss; the reference: 1);
            0 = every region pixel, each (line, first-hit plane) pair once.
        endpoint_weight: weight of D_euc in the line loss (see :func:`lipmap.mapping.losses.line_loss`).
        use_group: add the paper's group loss (off in the reference code).
        robust_scale: full-resolution pixels; > 0 makes each assignment's loss robust
            (:func:`lipmap.mapping.losses.robust_px`), 0 = the paper's plain distances.
        max_assign_frac: assignments whose best edge is farther than this fraction of the image size are
            skipped (another surface's edge); 0 = none skipped (reference code).
        euc_inside_only: D_euc as the reference codes it: the mean over the projected endpoints inside the image,
            the endpoints paired on the unmasked distances (:func:`lipmap.mapping.losses.line_loss`).
        depth_gate: m; a pixel's first-hit plane is supervised only where it lies this close to the sensor depth
            (0: off, the paper).
        hard_first_hit: with every region pixel, the first plane is the first rectangle the pixel's ray meets (the
            paper's Sec. 3.2, the reference code, the sampled pixels and the extraction); False: the render's
            nearest composited plane, which can be a neighbour's splat fall-off just past its edge.
        seed: sampling seed (combined with the iteration, so a resumed run samples the same pixels).
    """

    def __init__(self, lines_by_view: dict, weight: float = 0.1, pixels_per_line: int = 1, use_group: bool = False,
                 group_weight: float = 10.0, seed: int = 0,
                 endpoint_weight: float = 0.5, robust_scale: float = 0.0, max_assign_frac: float = 0.1,
                 euc_inside_only: bool = False, depth_gate: float = 0.0, hard_first_hit: bool = False):
        self.lines = {k: np.asarray(v, dtype=np.float64).reshape(-1, 4) for k, v in lines_by_view.items()}
        self.weight = weight
        self.pixels_per_line = max(0, pixels_per_line if not use_group else max(2, pixels_per_line))
        self.use_group = use_group
        self.group_weight = group_weight
        self.seed = seed
        self.endpoint_weight = endpoint_weight
        self.robust_scale = robust_scale
        self.max_assign_frac = max_assign_frac
        self.euc_inside_only = euc_inside_only
        self.depth_gate = depth_gate
        self.hard_first_hit = hard_first_hit
        self._regions = LRU(self._make_regions, DEFAULT_CAPACITY)  # bounded: scenes have thousands of views
        self._gate_geometry = LRU(self._make_gate_geometry, DEFAULT_CAPACITY)
        self.last = {}

    def regions(self, view, camera):
        """Region pixels :math:`(P, 2)` (col, row) and their line :math:`(P,)` of ``view``'s lines on the grid of
        ``camera`` (the training resolution): the full-resolution segments are scaled to it first, x and y each by
        its own factor (exact in COLMAP's pixel convention)."""
        return self._regions((view.name, view.camera.width, view.camera.height, camera.width, camera.height))

    def _make_regions(self, key):
        name, full_w, full_h, width, height = key
        return line_regions(self.lines[name] * _axis_scale(full_w, full_h, width, height), width, height)

    def _make_gate_geometry(self, key):
        # the gate's per-pixel constants: each region pixel's ray at z = 1 and its 3x3 depth window
        name, full_w, full_h, width, height, camera = key
        pix, _ = self._regions(key[:5])
        return pixel_rays_camera(pix, camera), depth_window(pix[:, 1], pix[:, 0], (height, width))

    def settings(self) -> dict:
        """What shapes the loss, for the planes' artifact stamp."""
        return {"weight": self.weight, "pixels_per_line": self.pixels_per_line, "use_group": self.use_group,
                "group_weight": self.group_weight, "seed": self.seed, "endpoint_weight": self.endpoint_weight,
                "robust_scale": self.robust_scale, "max_assign_frac": self.max_assign_frac,
                "euc_inside_only": self.euc_inside_only, "depth_gate": self.depth_gate,
                "hard_first_hit": self.hard_first_hit}

    def __call__(self, view, planes, iteration: int, render=None, target=None):
        """Line loss of ``view`` at the training resolution: that of ``target`` (the view's
        :class:`~lipmap.planes.optimize.ViewTarget`, whose camera ``render`` was made with and whose sensor depth the
        gate reads); the view's own camera without one."""
        camera = view.camera if target is None else target.camera
        if render is not None and tuple(render.hits.shape[:2]) != (camera.height, camera.width):
            raise ValueError(f"{view.name}: the render is {tuple(render.hits.shape[:2])} pixels, the training camera "
                             f"{(camera.height, camera.width)}: pass the view's training target with its render")
        lines = self.lines.get(view.name)
        corners = planes.corners()
        zero = corners.sum() * 0
        if lines is None or len(lines) == 0 or len(planes) == 0:
            return zero
        scale = _axis_scale(view.camera.width, view.camera.height, camera.width, camera.height)
        lines_s = lines * scale  # exact in COLMAP's pixel convention
        pix, li = self.regions(view, camera)
        if len(pix) == 0:
            return zero
        if self.pixels_per_line == 0:
            # every region pixel; each (line, first-hit plane) pair once
            k_all = self._first_hits(pix, corners, view, camera, render)
            # (line, plane) pairs through one integer key: np.unique over rows is ~5x slower, same order
            n_k = len(planes) + 1
            keys, inv = np.unique(li.astype(np.int64) * n_k + (k_all + 1), return_inverse=True)
            pairs = np.stack([keys // n_k, keys % n_k - 1], 1)
            keep = pairs[:, 1] >= 0
            ok_pix = self._depth_ok(None, k_all, corners, view, camera, target)
            if ok_pix is not None:  # a pair stays when one of its pixels agrees, or none has sensor depth
                agree, known = np.zeros(len(pairs), bool), np.zeros(len(pairs), bool)
                np.logical_or.at(agree, inv.ravel(), ok_pix == 1)
                np.logical_or.at(known, inv.ravel(), ok_pix >= 0)
                keep &= agree | ~known
            pairs = pairs[keep]
            li = pairs[:, 0]
            k = torch.as_tensor(pairs[:, 1])
        else:
            rng = np.random.default_rng([self.seed, iteration])
            # sample k pixels per line: random keys, then the first k of each line after sorting
            order = np.lexsort((rng.random(len(li)), li))
            li_sorted = li[order]
            rank = np.arange(len(li_sorted)) - np.searchsorted(li_sorted, li_sorted)
            take = order[rank < self.pixels_per_line]
            pix, li = pix[take], li[take]
            o, d = pixel_rays_world(pix, view.cam_from_world, camera)
            k = first_hit(corners, torch.as_tensor(o, dtype=corners.dtype, device=corners.device),
                          torch.as_tensor(d, dtype=corners.dtype, device=corners.device))
            ok_pix = self._depth_ok(take, k.cpu().numpy(), corners, view, camera, target)
            if ok_pix is not None:
                k = torch.where(torch.as_tensor(ok_pix != 0, device=k.device), k, torch.full_like(k, -1))
        hit = (k >= 0).cpu().numpy()
        if not hit.any():
            return zero
        plane = k.cpu().numpy()[hit]
        li = li[hit]
        edge, ang, dist, _ = best_edges(corners.detach().cpu().numpy().astype(np.float64), plane, lines_s[li],
                                        view.cam_from_world, camera)
        ok = np.isfinite(dist)
        if self.max_assign_frac > 0:  # an edge hopelessly far is another surface's: skip the assignment
            ok &= dist < self.max_assign_frac * max(camera.width, camera.height)
        if not ok.any():
            return zero
        s = scale[0]  # training pixels per full-resolution pixel (x and y differ by the rounding of one row)
        loss = line_loss(corners, plane[ok], edge[ok], lines_s[li[ok]], li[ok], view.cam_from_world, camera,
                         use_group=self.use_group, group_weight=self.group_weight,
                         endpoint_weight=self.endpoint_weight, robust_scale=self.robust_scale * s,
                         euc_inside_only=self.euc_inside_only)
        self.last = {"n_assign": int(ok.sum()), "loss": float(loss.detach()), "planes": plane[ok]}
        # distances are in training-resolution pixels; express them in full-resolution pixels so the
        # balance with the plane loss does not change with the training scale
        return self.weight * loss / s

    def _first_hits(self, pix, corners, view, camera, render):
        """The first plane (-1: none) each region pixel's ray meets: :math:`(P,)` int64 numpy."""
        rows, cols = torch.as_tensor(pix[:, 1]), torch.as_tensor(pix[:, 0])
        if render is not None and not self.hard_first_hit:
            return render.hits[rows, cols, 0].cpu().numpy()
        o, d = pixel_rays_world(pix, view.cam_from_world, camera)
        o = torch.as_tensor(o, dtype=corners.dtype, device=corners.device)
        d = torch.as_tensor(d, dtype=corners.dtype, device=corners.device)
        if render is None:
            return first_hit(corners, o, d).cpu().numpy()
        cand = render.hits[rows, cols].to(corners.device)
        # a list is whole unless it is full or the transmittance behind it ran out
        complete = (cand[:, -1] < 0) & (render.alpha.detach()[rows, cols].to(corners.device) < 1 - TRANSMITTANCE_EPS)
        return first_hit_in_render(corners, cand, o, d, complete).cpu().numpy()

    def _depth_ok(self, take, plane, corners, view, camera, target):
        """Per region pixel (those indexed by ``take``; all with None): 1 where the plane ``plane`` it meets first
        lies within ``depth_gate`` of the sensor depth at one of the 3x3 pixels around it (an edge lies on a depth
        step, and a 1-pixel region straddles it), 0 where it does not, -1 where there is no sensor depth there (or
        no plane); None when the gate is off."""
        if not self.depth_gate > 0 or target is None:
            return None
        depth = target.depth.cpu().numpy()
        if depth.shape != (camera.height, camera.width):
            raise ValueError(f"{view.name}: the sensor depth is {depth.shape}, the training grid {(camera.height, camera.width)}")
        ray, window = self._gate_geometry((view.name, view.camera.width, view.camera.height, camera.width,
                                           camera.height, camera))
        if take is not None:
            ray, window = ray[take], window[take]
        out = np.full(len(plane), -1, dtype=np.int8)
        m = plane >= 0
        if not m.any():
            return out
        # each plane's normal and offset once, in the camera frame; then the depth of every ray's hit
        u, inv = np.unique(plane[m], return_inverse=True)
        c = corners.detach()[torch.as_tensor(u)].cpu().numpy().astype(np.float64)  # (U, 4, 3)
        R, t = view.cam_from_world[:3, :3], view.cam_from_world[:3, 3]
        c_cam = c @ R.T + t
        n = np.cross(c_cam[:, 1] - c_cam[:, 0], c_cam[:, 3] - c_cam[:, 0])
        offset = (n * c_cam[:, 0]).sum(1)
        with np.errstate(divide="ignore", invalid="ignore"):
            z = offset[inv] / (n[inv] * ray[m]).sum(1)  # ray at z = 1: the hit's parameter is its depth
        best = nearest_depth_residual(depth, None, None, z, window=window[m])
        out[m] = np.where(np.isfinite(best), best <= self.depth_gate, -1)
        return out


def _axis_scale(full_w: int, full_h: int, width: int, height: int) -> np.ndarray:
    """(4,) factors that take segments (x1, y1, x2, y2) from a full_w x full_h image to a width x height one."""
    sx, sy = width / full_w, height / full_h
    return np.array([sx, sy, sx, sy])
