"""Procedural surface textures for the synthetic rooms, and their trilinear lookup.

A texture is an RGB image laid on one planar surface in metric (u, v) coordinates: texel (col, row)
covers u in [col, col + 1) / res, v in [row, row + 1) / res, with ``res`` texels per metre. Because the
texture lives on the surface, every view sees the same pattern at the same 3D point (multi-view
consistent), which is what SIFT matching and triangulation on the rendered images need.

Every generator draws from the ``numpy.random.Generator`` it is given and from OpenCV drawing
primitives, so a seed fixes the texture bit for bit.
"""
from __future__ import annotations

from dataclasses import dataclass, field

import cv2
import numpy as np


@dataclass(frozen=True)
class Material:
    """How a surface looks. ``kind`` "plain" is one uniform colour (no texture: only its edges help).

    ``color``/``color2`` are RGB in [0, 1]; ``params`` holds kind-specific knobs (tile size, contrast, ...).
    """

    kind: str
    color: tuple
    color2: tuple = (0.0, 0.0, 0.0)
    params: dict = field(default_factory=dict)

    @property
    def plain(self) -> bool:
        return self.kind == "plain"


def _value_noise(h: int, w: int, size_m: tuple, freq: float, rng: np.random.Generator) -> np.ndarray:
    """Smooth random field (h, w) in ~[0, 1] with about ``freq`` lattice cells per metre."""
    gw = max(2, int(np.ceil(size_m[0] * freq)) + 2)
    gh = max(2, int(np.ceil(size_m[1] * freq)) + 2)
    grid = rng.random((gh, gw), dtype=np.float32)
    return cv2.resize(grid, (w, h), interpolation=cv2.INTER_CUBIC)


def fbm(h: int, w: int, size_m: tuple, res: float, rng: np.random.Generator, f0: float = 1.5,
        persistence: float = 0.7, finest_texels: float = 3.0) -> np.ndarray:
    """Multi-octave value noise (h, w), zero mean and unit standard deviation.

    Octaves double in frequency from ``f0`` cells/m until a cell is ``finest_texels`` texels wide, so the
    pattern has blobs at every scale a camera between 0.5 m and 5 m resolves (what a DoG detector needs).
    """
    out = np.zeros((h, w), np.float32)
    f, amp = f0, 1.0
    while f <= res / finest_texels:
        out += amp * (_value_noise(h, w, size_m, f, rng) - 0.5)
        f *= 2.0
        amp *= persistence
    std = float(out.std())
    return (out - out.mean()) / (std if std > 1e-6 else 1.0)


def _lerp(c1, c2, t: np.ndarray) -> np.ndarray:
    c1, c2 = np.asarray(c1, np.float32), np.asarray(c2, np.float32)
    return c1 + (c2 - c1) * t[..., None]


def _spots(t: np.ndarray, res: float, size_m: tuple, rng: np.random.Generator, per_m2: float, r_m: tuple,
           amp: float) -> np.ndarray:
    """Scatter soft discs of random lightness on the field ``t`` (sponge paint, pores, knots)."""
    t = np.ascontiguousarray(t)
    n = int(per_m2 * size_m[0] * size_m[1])
    h, w = t.shape
    xs, ys = rng.uniform(0, w, n) * 16, rng.uniform(0, h, n) * 16
    rs = rng.uniform(r_m[0], r_m[1], n) * res * 16
    vals = rng.uniform(-amp, amp, n)
    spots = np.zeros_like(t)
    for x, y, r, val in zip(xs.astype(int), ys.astype(int), np.maximum(rs, 8).astype(int), vals):
        cv2.circle(spots, (int(x), int(y)), int(r), float(val), -1, cv2.LINE_AA, 4)
    return t + cv2.GaussianBlur(spots, (0, 0), 0.6)


def _plaster(h, w, size_m, res, mat, rng):
    """Sponge-painted plaster: rough multi-scale noise plus soft spots of lighter and darker paint."""
    n = fbm(h, w, size_m, res, rng, f0=1.0, persistence=mat.params.get("persistence", 0.85))
    t = 0.5 + mat.params.get("contrast", 0.18) * n
    t = _spots(t, res, size_m, rng, mat.params.get("spots_per_m2", 700.0), (0.008, 0.04), 0.45)
    hue = fbm(h, w, size_m, res, rng, f0=0.7, persistence=0.5)
    img = _lerp(mat.color2, mat.color, np.clip(t, 0, 1))
    return img * (1.0 + 0.04 * hue[..., None])


def _wood(h, w, size_m, res, mat, rng, v0: float = 0.0):
    """Grain lines run along u; their spacing is warped by low-frequency noise like real growth rings."""
    vv = (np.arange(h, dtype=np.float32)[:, None] + 0.5) / res + v0
    warp = fbm(h, w, size_m, res, rng, f0=1.0, persistence=0.5, finest_texels=12.0)
    grain_f = mat.params.get("grain_per_m", 40.0)
    phase = 2 * np.pi * (vv * grain_f + 1.2 * warp)
    g = 0.5 + 0.5 * np.sin(phase)
    g = g ** 3  # thin dark latewood lines on a light background
    fine = fbm(h, w, size_m, res, rng, f0=4.0, persistence=0.9)
    t = 0.5 * g + 0.16 * fine + 0.2
    # knots and pores: the blobs a DoG detector finds on real wood
    t = _spots(t, res, size_m, rng, 500.0, (0.005, 0.025), 0.35)
    return _lerp(mat.color, mat.color2, np.clip(t, 0, 1))


def _planks(h, w, size_m, res, mat, rng):
    """Floor boards: wood strips along u with seams between boards and staggered end joints."""
    pw = mat.params.get("plank_width", 0.15)
    img = _wood(h, w, size_m, res, mat, rng)
    rows = (np.arange(h) + 0.5) / res
    plank = np.floor(rows / pw).astype(int)
    n_planks = int(plank.max()) + 1
    tint = 1.0 + 0.12 * rng.standard_normal(n_planks).astype(np.float32)
    img *= tint[plank][:, None, None]
    seam = int(max(1, round(0.004 * res)))
    seam_rows = (rows % pw) < seam / res
    img[seam_rows] *= 0.45
    length = mat.params.get("plank_length", 1.2)
    for p in range(n_planks):
        r0, r1 = np.searchsorted(rows, [p * pw, (p + 1) * pw])
        start = rng.uniform(0, length)
        for u in np.arange(start, size_m[0], length):
            c = int(u * res)
            img[r0:r1, max(c - seam // 2, 0):c + seam - seam // 2 + 1] *= 0.45
    return img


def _tiles(h, w, size_m, res, mat, rng):
    ts = mat.params.get("tile", 0.3)
    grout = mat.params.get("grout", 0.006)
    uu = (np.arange(w) + 0.5) / res
    vv = (np.arange(h) + 0.5) / res
    iu, iv = np.floor(uu / ts).astype(int), np.floor(vv / ts).astype(int)
    nu, nv = iu.max() + 1, iv.max() + 1
    jitter = 1.0 + (0.1 * rng.standard_normal((nv, nu, 1)) + 0.03 * rng.standard_normal((nv, nu, 3))).astype(np.float32)
    checker = mat.params.get("checker", False)
    base = np.asarray(mat.color, np.float32)
    tile_col = base * jitter
    if checker:
        alt = np.asarray(mat.params.get("alt", mat.color), np.float32)
        odd = ((np.arange(nv)[:, None] + np.arange(nu)[None]) % 2).astype(bool)
        tile_col[odd] = alt * jitter[odd]
    img = tile_col[iv[:, None], iu[None, :]]
    n = fbm(h, w, size_m, res, rng, f0=3.0, persistence=0.85)
    n = _spots(n, res, size_m, rng, mat.params.get("spots_per_m2", 300.0), (0.005, 0.02), 2.0)
    img = img * (1.0 + mat.params.get("contrast", 0.1) * n[..., None])
    line_u = (uu % ts) < grout
    line_v = (vv % ts) < grout
    img[:, line_u] = mat.color2
    img[line_v, :] = mat.color2
    return img


def _speckle(h, w, size_m, res, mat, rng):
    """Terrazzo / granite: noisy base with many small chips of a few colours."""
    img = _plaster(h, w, size_m, res, Material("noise", mat.color, mat.color2, {"contrast": 0.12}), rng)
    img = np.ascontiguousarray(img)
    area = size_m[0] * size_m[1]
    n_chips = int(mat.params.get("chips_per_m2", 400) * area)
    palette = rng.uniform(0.05, 0.95, size=(4, 1)) + rng.uniform(-0.12, 0.12, size=(4, 3))
    xs = rng.uniform(0, w, n_chips)
    ys = rng.uniform(0, h, n_chips)
    rad = rng.uniform(0.003, 0.012, n_chips) * res
    cols = palette[rng.integers(0, 4, n_chips)]
    for x, y, r, c in zip(xs, ys, rad, cols):
        cv2.circle(img, (int(x * 16), int(y * 16)), max(int(r * 16), 8), tuple(float(v) for v in c), -1,
                   cv2.LINE_AA, 4)
    return img


def _poster(h, w, size_m, res, mat, rng):
    """A picture: a background plus random rectangles, discs, ellipses, strokes and glyphs (corners, blobs)."""
    bg = np.asarray(mat.color, np.float32)
    img = np.ascontiguousarray(np.broadcast_to(bg, (h, w, 3)).copy())
    img *= (1.0 + 0.08 * fbm(h, w, size_m, res, rng, f0=2.0)[..., None])
    img = np.clip(np.round(img * 255), 0, 255).astype(np.uint8)  # cv2.putText draws on 8-bit images only
    n_shapes = int(mat.params.get("shapes_per_m2", 60) * size_m[0] * size_m[1]) + 6
    sh = 4  # sub-pixel bits for cv2 anti-aliased drawing
    for _ in range(n_shapes):
        c = tuple(float(v) for v in rng.uniform(0.0, 255.0, 3))
        kind = rng.integers(0, 5)
        x, y = rng.uniform(0, w), rng.uniform(0, h)
        s = rng.uniform(0.02, 0.25) * res
        p = lambda a, b: (int(a * 2 ** sh), int(b * 2 ** sh))  # noqa: E731
        if kind == 0:
            cv2.rectangle(img, p(x, y), p(x + s, y + s * rng.uniform(0.3, 1.5)), c, -1, cv2.LINE_AA, sh)
        elif kind == 1:
            cv2.circle(img, p(x, y), int(s / 2 * 2 ** sh), c, -1, cv2.LINE_AA, sh)
        elif kind == 2:
            cv2.ellipse(img, p(x, y), p(s / 2, s / 4 * rng.uniform(0.5, 2)), float(rng.uniform(0, 180)), 0, 360, c,
                        -1, cv2.LINE_AA, sh)
        elif kind == 3:
            pts = np.stack([rng.uniform(0, w, 4), rng.uniform(0, h, 4)], -1) * 2 ** sh
            thick = max(1, int(rng.uniform(0.004, 0.015) * res))
            cv2.polylines(img, [pts.astype(np.int32)], False, c, thick, cv2.LINE_AA, sh)
        else:
            text = "".join(chr(int(v)) for v in rng.integers(65, 91, int(rng.integers(2, 6))))
            scale = max(0.3, s / 40.0)
            cv2.putText(img, text, (int(x), int(y)), cv2.FONT_HERSHEY_SIMPLEX, scale, c,
                        max(1, int(scale * 2)), cv2.LINE_AA)
    return img.astype(np.float32) / 255.0


_GENERATORS = {
    "noise": _plaster,
    "wood": _wood,
    "planks": _planks,
    "tiles": _tiles,
    "speckle": _speckle,
    "poster": _poster,
}

TEXTURE_KINDS = tuple(_GENERATORS)


def make_texture(mat: Material, size_m: tuple, res: float, rng: np.random.Generator) -> list[np.ndarray]:
    """Mip pyramid (list of uint8 (h_l, w_l, 3)) of ``mat`` on a surface of ``size_m`` = (su, sv) metres."""
    w = max(2, int(np.ceil(size_m[0] * res)))
    h = max(2, int(np.ceil(size_m[1] * res)))
    img = _GENERATORS[mat.kind](h, w, size_m, res, mat, rng)
    level = np.clip(np.round(img * 255.0), 0, 255).astype(np.uint8)
    levels = [level]
    while min(level.shape[:2]) >= 8 and len(levels) < 5:
        level = cv2.pyrDown(level)
        levels.append(level)
    return levels


class TextureAtlas:
    """All surfaces' mip pyramids in one flat texel buffer, sampled without a loop over surfaces.

    ``table[s, l]`` = (offset, width, height) of level ``l`` of surface ``s``; surfaces with fewer
    levels repeat their coarsest one, plain surfaces (no texture) have no rows in the buffer.
    """

    def __init__(self, pyramids: list, res: float):
        self.res = float(res)
        n_levels = max([len(p) for p in pyramids if p is not None], default=1)
        self.table = np.zeros((len(pyramids), n_levels, 3), np.int64)
        chunks, offset = [], 0
        for s, pyr in enumerate(pyramids):
            if pyr is None:
                continue
            for lev in range(n_levels):
                img = pyr[min(lev, len(pyr) - 1)]
                if lev < len(pyr):
                    chunks.append(img.reshape(-1, 3))
                    self.table[s, lev] = (offset, img.shape[1], img.shape[0])
                    offset += img.shape[0] * img.shape[1]
                else:
                    self.table[s, lev] = self.table[s, len(pyr) - 1]
        self.n_levels_of = np.array([len(p) if p is not None else 1 for p in pyramids])
        self.texels = np.concatenate(chunks) if chunks else np.zeros((1, 3), np.uint8)

    def _bilinear(self, sid: np.ndarray, lev: np.ndarray, u: np.ndarray, v: np.ndarray) -> np.ndarray:
        off, w, h = self.table[sid, lev].T
        scale = (self.res / np.exp2(lev)).astype(np.float32)
        # level-l texel (c, r) has its centre at ((c + 0.5), (r + 0.5)) * 2**l / res; edges clamp
        x = np.clip(u * scale - 0.5, 0, w - 1).astype(np.float32)
        y = np.clip(v * scale - 0.5, 0, h - 1).astype(np.float32)
        x0 = np.minimum(x.astype(np.int64), np.maximum(w - 2, 0))
        y0 = np.minimum(y.astype(np.int64), np.maximum(h - 2, 0))
        fx = (x - x0)[:, None]
        fy = (y - y0)[:, None]
        dx = np.minimum(x0 + 1, w - 1) - x0
        dy = (np.minimum(y0 + 1, h - 1) - y0) * w
        i00 = off + y0 * w + x0
        t = self.texels
        a, b, c, d = (np.take(t, i, axis=0).astype(np.float32) for i in (i00, i00 + dx, i00 + dy, i00 + dy + dx))
        top = a + (b - a) * fx
        return top + (c + (d - c) * fx - top) * fy

    def sample(self, sid: np.ndarray, u: np.ndarray, v: np.ndarray, lod: np.ndarray) -> np.ndarray:
        """Trilinear RGB (N, 3) in [0, 1] of textured surfaces ``sid`` (N,) at metric (u, v) (N,).

        ``lod`` (N,) is log2 of the sample footprint in level-0 texels; blending two mip levels keeps
        distant textures from aliasing (aliasing would make the same point look different per view).
        """
        top = self.n_levels_of[sid] - 1
        lod = np.clip(lod, 0, top)
        l0 = np.minimum(np.floor(lod).astype(np.int64), top)
        l1 = np.minimum(l0 + 1, top)
        frac = (lod - l0).astype(np.float32)[:, None]
        a = self._bilinear(sid, l0, u, v)
        b = self._bilinear(sid, l1, u, v)
        return (a + (b - a) * frac) / 255.0
