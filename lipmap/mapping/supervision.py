"""The line term of the joint line-plane optimization (paper Sec. 3.3), as a callback for the plane loop.

Each training iteration samples pixels from the 1-pixel regions of the view's detected lines (one per
line by default, as the reference code does), finds the first plane each pixel's ray hits and the edge
that explains the line (no gradient), and returns the line loss of those edges (with gradient).
"""
from __future__ import annotations

import functools
from dataclasses import dataclass
from typing import Optional

import numpy as np
import torch

from ..frames import DEFAULT_CAPACITY, LRU
from ..planes.primitives import TRANSMITTANCE_EPS
from .assign import best_edges, first_hit, first_hit_in_render, line_regions, pixel_rays_world
from .depth_lookup import depth_window, nearest_depth_residual_torch
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
        exclusive_pixels: a pixel in several lines' regions belongs to the nearest line only (the reference's
            attraction field); False: to each.
        seed: sampling seed (combined with the iteration, so a resumed run samples the same pixels).
    """

    def __init__(self, lines_by_view: dict, weight: float = 0.1, pixels_per_line: int = 1, use_group: bool = False,
                 group_weight: float = 10.0, seed: int = 0,
                 endpoint_weight: float = 0.5, robust_scale: float = 0.0, max_assign_frac: float = 0.1,
                 euc_inside_only: bool = False, depth_gate: float = 0.0, hard_first_hit: bool = False,
                 exclusive_pixels: bool = False):
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
        self.exclusive_pixels = exclusive_pixels
        self._geometry = LRU(self._make_view_geometry, DEFAULT_CAPACITY)  # bounded: scenes have thousands of views
        self._last = None
        # rows of the edge choice and the loss: the kept pairs only (reads the mask: a host sync) or every candidate
        # row with its mask (none); None: compacted on a CPU, masked on a GPU. The same loss up to float rounding
        self.compact_rows: Optional[bool] = None

    def regions(self, view, camera):
        """Region pixels :math:`(P, 2)` (col, row) and their line :math:`(P,)` of ``view``'s lines on the grid of
        ``camera`` (the training resolution): the full-resolution segments are scaled to it first, x and y each by
        its own factor (exact in COLMAP's pixel convention)."""
        return self._make_regions(view.name, view.camera.width, view.camera.height, camera.width, camera.height)

    def _make_regions(self, name, full_w, full_h, width, height):
        return line_regions(self.lines[name] * _axis_scale(full_w, full_h, width, height), width, height,
                            exclusive=self.exclusive_pixels)

    def _make_view_geometry(self, key):
        # what stays put for a view at one training resolution, on the training device: its lines, the region
        # pixels' lines, world rays (first hits) and 3x3 depth windows (the gate; the centre is the pixel)
        name, full_w, full_h, width, height, camera, cam_from_world, device = key
        pix, li = self._make_regions(*key[:5])
        T = np.frombuffer(cam_from_world, dtype=np.float64).reshape(4, 4).copy()
        o, d = pixel_rays_world(pix, T, camera)
        dev = torch.device(device)
        lines_s = self.lines[name] * _axis_scale(full_w, full_h, width, height)
        return _ViewGeometry(
            li=torch.as_tensor(li, dtype=torch.long, device=dev),
            lines=torch.as_tensor(lines_s, dtype=torch.float64, device=dev),
            origin=torch.as_tensor(o[0] if len(o) else np.zeros(3), dtype=torch.float32, device=dev),
            dirs=torch.as_tensor(d, dtype=torch.float32, device=dev),
            window=torch.as_tensor(depth_window(pix[:, 1], pix[:, 0], (height, width)), dtype=torch.int32, device=dev),
            T=torch.as_tensor(T, dtype=torch.float64, device=dev), width=width, camera=camera)

    def settings(self) -> dict:
        """What shapes the loss, for the planes' artifact stamp."""
        return {"weight": self.weight, "pixels_per_line": self.pixels_per_line, "use_group": self.use_group,
                "group_weight": self.group_weight, "seed": self.seed, "endpoint_weight": self.endpoint_weight,
                "robust_scale": self.robust_scale, "max_assign_frac": self.max_assign_frac,
                "euc_inside_only": self.euc_inside_only, "depth_gate": self.depth_gate,
                "hard_first_hit": self.hard_first_hit,
                # only when on: the stamps of the planes made before the switch existed stay valid
                **({"exclusive_pixels": True} if self.exclusive_pixels else {})}

    @property
    def last(self) -> dict:
        """The last call's assignments: ``n_assign``, ``loss`` and the assigned ``planes`` (numpy); read from the
        device only when asked for."""
        if self._last is None:
            return {}
        ok, plane, loss = self._last
        return {"n_assign": int(ok.sum()), "loss": float(loss), "planes": plane[ok].cpu().numpy()}

    def __call__(self, view, planes, iteration: int, render=None, target=None):
        """Line loss of ``view`` at the training resolution: that of ``target`` (the view's
        :class:`~lipmap.planes.targets.ViewTarget`, whose camera ``render`` was made with and whose sensor depth the
        gate reads); the view's own camera without one.

        Everything per iteration runs on the planes' device; on a GPU on fixed-size rows with masks, so that nothing
        waits for the device (on a CPU the rows are compacted to the pairs kept, which costs nothing there)."""
        camera = view.camera if target is None else target.camera
        if render is not None and tuple(render.hits.shape[:2]) != (camera.height, camera.width):
            raise ValueError(f"{view.name}: the render is {tuple(render.hits.shape[:2])} pixels, the training camera "
                             f"{(camera.height, camera.width)}: pass the view's training target with its render")
        self._last = None
        lines = self.lines.get(view.name)
        corners = planes.corners()
        zero = corners.sum() * 0
        if lines is None or len(lines) == 0 or len(planes) == 0:
            return zero
        if target is not None and self.depth_gate > 0 and tuple(target.depth.shape) != (camera.height, camera.width):
            raise ValueError(f"{view.name}: the sensor depth is {tuple(target.depth.shape)}, the training grid "
                             f"{(camera.height, camera.width)}")
        g = self._geometry((view.name, view.camera.width, view.camera.height, camera.width, camera.height, camera,
                            np.asarray(view.cam_from_world, dtype=np.float64).tobytes(), str(corners.device)))
        if len(g.li) == 0:
            return zero
        if self.pixels_per_line == 0:
            # every region pixel; each (line, first-hit plane) pair once
            k_all = self._first_hits(g, corners, render)
            ok_pix = self._depth_ok(g, None, k_all, corners, target)
            rows, keep = _first_of_each_pair(g.li, k_all, len(planes), ok_pix)
            li, plane = g.li[rows], k_all[rows]
        else:
            rng = np.random.default_rng([self.seed, iteration])
            # sample k pixels per line: random keys, then the first k of each line after sorting (on the host: the
            # region's line ids are constants of the view, no device data is read)
            li_np = g.li_host
            order = np.lexsort((rng.random(len(li_np)), li_np))
            li_sorted = li_np[order]
            rank = np.arange(len(li_sorted)) - np.searchsorted(li_sorted, li_sorted)
            take = torch.as_tensor(order[rank < self.pixels_per_line], dtype=torch.long, device=corners.device)
            plane = first_hit(corners, g.origin.to(corners.dtype).expand(len(take), 3).contiguous(),
                              g.dirs[take].to(corners.dtype))
            ok_pix = self._depth_ok(g, take, plane, corners, target)
            keep = plane >= 0 if ok_pix is None else (plane >= 0) & (ok_pix != 0)
            li = g.li[take]
        if self.compact_rows if self.compact_rows is not None else corners.device.type == "cpu":
            # a CPU reads the mask for free: the rows shrink to the kept pairs (~1 in 6 of the region pixels), where
            # a GPU keeps every row and its mask rather than wait for the count
            sel = keep.nonzero().squeeze(1)
            li, plane, keep = li[sel], plane[sel], keep[sel]
        plane_c = plane.clamp(min=0)
        det = g.lines[li]
        edge, _, dist, _ = best_edges(corners.detach().to(torch.float64), plane_c, det, g.T, camera)
        ok = keep & torch.isfinite(dist)
        if self.max_assign_frac > 0:  # an edge hopelessly far is another surface's: skip the assignment
            ok = ok & (dist < self.max_assign_frac * max(camera.width, camera.height))
        s = float(_axis_scale(view.camera.width, view.camera.height, camera.width, camera.height)[0])
        # s: training pixels per full-resolution pixel (x and y differ by the rounding of one row)
        loss = line_loss(corners, plane_c, edge, det.to(corners.dtype), li, g.T.to(corners.dtype), camera,
                         use_group=self.use_group, group_weight=self.group_weight,
                         endpoint_weight=self.endpoint_weight, robust_scale=self.robust_scale * s,
                         euc_inside_only=self.euc_inside_only, mask=ok)
        self._last = (ok, plane, loss.detach())
        # distances are in training-resolution pixels; express them in full-resolution pixels so the
        # balance with the plane loss does not change with the training scale
        return self.weight * loss / s

    def _first_hits(self, g, corners, render):
        """The first plane (-1: none) each region pixel's ray meets: :math:`(P,)` long, on the planes' device."""
        flat = g.pixel
        if render is not None and not self.hard_first_hit:
            return render.hits.reshape(-1, render.hits.shape[-1])[flat, 0].to(corners.device)
        d = g.dirs.to(corners.dtype)
        o = g.origin.to(corners.dtype).expand(len(d), 3).contiguous()
        if render is None or render.hit_rule != "nearest":  # only the nearest-hit rule's lists hold the first hit
            return first_hit(corners, o, d)
        cand = render.hits.reshape(-1, render.hits.shape[-1])[flat].to(corners.device)
        # a list is whole unless it is full or the transmittance behind it ran out
        alpha = render.alpha.detach().reshape(-1)[flat].to(corners.device)
        return first_hit_in_render(corners, cand, o, d, (cand[:, -1] < 0) & (alpha < 1 - TRANSMITTANCE_EPS))

    def _depth_ok(self, g, take, plane, corners, target):
        """Per region pixel (those indexed by ``take``; all with None): 1 where the plane ``plane`` it meets first
        lies within ``depth_gate`` of the sensor depth at one of the 3x3 pixels around it (an edge lies on a depth
        step, and a 1-pixel region straddles it), 0 where it does not, -1 where there is no sensor depth there (or
        no plane); None when the gate is off. :math:`(P,)` int8 on the planes' device."""
        if not self.depth_gate > 0 or target is None:
            return None
        window = g.window if take is None else g.window[take]
        ray = g.ray_cam(window[:, 4])
        # each pixel's plane's normal and offset in the camera frame, then the depth of its ray's hit (float64)
        c = corners.detach()[plane.clamp(min=0)].to(torch.float64)  # (P, 4, 3)
        R, t = g.T[:3, :3], g.T[:3, 3]
        c_cam = c @ R.T + t
        n = torch.linalg.cross(c_cam[:, 1] - c_cam[:, 0], c_cam[:, 3] - c_cam[:, 0])
        z = (n * c_cam[:, 0]).sum(1) / (n * ray).sum(1)  # ray at z = 1: the hit's parameter is its depth
        best = nearest_depth_residual_torch(target.depth.to(corners.device), z, window)
        out = torch.where(best <= self.depth_gate, 1, 0).to(torch.int8)
        return torch.where((plane >= 0) & torch.isfinite(best), out, torch.full_like(out, -1))


@dataclass
class _ViewGeometry:
    """A view's line-term constants at one training resolution (see ``LineSupervision._make_view_geometry``); about
    60 bytes per region pixel, held for up to ``DEFAULT_CAPACITY`` views."""

    li: torch.Tensor  # (P,) long, each region pixel's line
    lines: torch.Tensor  # (N, 4) float64, the lines at the training resolution
    origin: torch.Tensor  # (3,) float32 the camera centre (every ray's origin)
    dirs: torch.Tensor  # (P, 3) float32 unit world ray directions
    window: torch.Tensor  # (P, 9) int32, flat indices of the 3x3 pixels around each (the pixel itself at 4)
    T: torch.Tensor  # (4, 4) float64 cam_from_world
    width: int
    camera: object

    @property
    def pixel(self) -> torch.Tensor:
        """(P,) long flat index of each region pixel."""
        return self.window[:, 4].long()

    def ray_cam(self, flat: torch.Tensor) -> torch.Tensor:
        """(P, 3) float64 camera rays at z = 1 through the pixels ``flat`` (:func:`pixel_rays_camera`'s arithmetic)."""
        col, row = (flat % self.width).double(), torch.div(flat, self.width, rounding_mode="floor").double()
        cam = self.camera
        x, y = (col + 0.5 - cam.cx) / cam.fx, (row + 0.5 - cam.cy) / cam.fy
        return torch.stack([x, y, torch.ones_like(x)], -1)

    @functools.cached_property
    def li_host(self) -> np.ndarray:
        return self.li.cpu().numpy()


def _first_of_each_pair(li: torch.Tensor, plane: torch.Tensor, n_planes: int, ok_pix: Optional[torch.Tensor]):
    """Each (line, plane) pair of the region pixels once, on the device with fixed-size rows.

    Returns ``rows`` :math:`(P,)`, the pixels in (line, plane) order, and ``keep`` :math:`(P,)` bool: True at the
    first pixel of each pair whose plane is not -1 and, with ``ok_pix`` (the depth gate), where one of the pair's
    pixels agrees with the sensor depth or none has sensor depth.
    """
    key = li * (n_planes + 1) + (plane + 1)  # one integer per (line, plane)
    skey, rows = torch.sort(key, stable=True)
    first = torch.ones_like(skey, dtype=torch.bool)
    first[1:] = skey[1:] != skey[:-1]
    keep = first & (plane[rows] >= 0)
    if ok_pix is not None:
        gid = torch.cumsum(first, 0) - 1  # the pair of each sorted pixel
        okp = ok_pix[rows]
        agree = torch.zeros(len(rows), dtype=torch.int32, device=li.device).scatter_reduce(
            0, gid, (okp == 1).to(torch.int32), "amax")
        known = torch.zeros_like(agree).scatter_reduce(0, gid, (okp >= 0).to(torch.int32), "amax")
        keep &= (agree[gid] > 0) | (known[gid] == 0)
    return rows, keep


def _axis_scale(full_w: int, full_h: int, width: int, height: int) -> np.ndarray:
    """(4,) factors that take segments (x1, y1, x2, y2) from a full_w x full_h image to a width x height one."""
    sx, sy = width / full_w, height / full_h
    return np.array([sx, sy, sx, sy])
