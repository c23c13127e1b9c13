"""A query camera of any COLMAP model as the pinhole camera the line stage works in, with the undistortion of its
pixels, segments and images into that camera.

Straight 3D lines project to straight 2D lines only without lens distortion, so a distorted query is moved into
the pinhole camera with the same focal lengths and principal point before anything else; its pose is unchanged.
Pixels are COLMAP's (pixel centre at +0.5) on both sides.
"""
from __future__ import annotations

from dataclasses import dataclass, field
from typing import Optional

import numpy as np

from lipmap import InputError
from lipmap.scene import Camera

# models whose pixels are the pinhole camera's (no distortion parameters)
_PINHOLE_MODELS = ("PINHOLE", "SIMPLE_PINHOLE")


@dataclass
class QueryCamera:
    """A query's camera: ``pinhole`` (:class:`lipmap.scene.Camera`) and, for a model with distortion, ``colmap`` (the
    ``pycolmap.Camera`` that maps its pixels to rays and back)."""

    pinhole: Camera
    model: str = "PINHOLE"
    colmap: Optional[object] = None
    _maps: Optional[tuple] = field(default=None, repr=False)

    @property
    def distorted(self) -> bool:
        return self.colmap is not None

    def undistort_points(self, p2d: np.ndarray) -> np.ndarray:
        """:math:`(N, 2)` pixels of this camera as the pinhole camera's pixels."""
        p2d = np.asarray(p2d, dtype=np.float64).reshape(-1, 2)
        if not self.distorted or len(p2d) == 0:
            return p2d
        xn = np.asarray(self.colmap.cam_from_img(p2d), dtype=np.float64).reshape(-1, 2)
        c = self.pinhole
        return np.stack([c.fx * xn[:, 0] + c.cx, c.fy * xn[:, 1] + c.cy], 1)

    def undistort_segments(self, segments: np.ndarray) -> np.ndarray:
        """:math:`(M, 4)` or :math:`(M, 2, 2)` segments with their endpoints undistorted, in the shape given (a
        segment short against the distortion's curvature stays a segment)."""
        s = np.asarray(segments, dtype=np.float64)
        if not self.distorted or s.size == 0:
            return s
        return self.undistort_points(s.reshape(-1, 2)).reshape(s.shape)

    def undistort_image(self, image: np.ndarray) -> np.ndarray:
        """The image resampled into the pinhole camera (bilinear; outside the source: black)."""
        if not self.distorted:
            return image
        import cv2

        if self._maps is None:
            c = self.pinhole
            u, v = np.meshgrid(np.arange(c.width) + 0.5, np.arange(c.height) + 0.5)
            rays = np.stack([(u.ravel() - c.cx) / c.fx, (v.ravel() - c.cy) / c.fy, np.ones(u.size)], 1)
            src = np.asarray(self.colmap.img_from_cam(rays, check_cheirality=False), dtype=np.float64) - 0.5  # OpenCV origin
            self._maps = (src[:, 0].reshape(u.shape).astype(np.float32), src[:, 1].reshape(u.shape).astype(np.float32))
        return cv2.remap(np.asarray(image), self._maps[0], self._maps[1], cv2.INTER_LINEAR, borderMode=cv2.BORDER_CONSTANT)


def as_query_camera(camera) -> QueryCamera:
    """A :class:`QueryCamera` from a :class:`lipmap.scene.Camera`, a PoseLib/COLMAP dict (``model``, ``width``,
    ``height``, ``params``) or a ``pycolmap.Camera`` of any model."""
    if isinstance(camera, QueryCamera):
        return camera
    if isinstance(camera, Camera):
        return QueryCamera(camera)
    if isinstance(camera, dict):
        try:
            model, w, h, params = str(camera.get("model", "PINHOLE")), int(camera["width"]), int(camera["height"]), camera["params"]
        except (KeyError, TypeError, ValueError) as e:
            raise InputError(f"a camera dict needs model, width, height and params ({e})") from None
    elif all(hasattr(camera, a) for a in ("width", "height", "params", "model")):  # pycolmap.Camera
        model = getattr(camera.model, "name", str(camera.model))
        w, h, params = int(camera.width), int(camera.height), camera.params
    else:
        raise InputError(f"cannot use {type(camera).__name__} as a camera: give lipmap.scene.Camera, a dict with model, "
                         "width, height, params, or a pycolmap.Camera")
    params = [float(p) for p in np.asarray(params, dtype=np.float64).ravel()]
    if model == "PINHOLE":
        return QueryCamera(Camera(w, h, params))
    import pycolmap

    try:
        cc = pycolmap.Camera(model=model, width=w, height=h, params=params)
    except Exception as e:  # noqa: BLE001 - pycolmap raises several types for an unknown model or bad params
        raise InputError(f"camera model {model!r} with params {params}: {e}") from None
    if len(params) != len(cc.params_info.split(",")):
        raise InputError(f"camera model {model} takes {cc.params_info} ({len(cc.params_info.split(','))} params), "
                         f"got {len(params)}: {params}")
    pinhole = Camera(w, h, (cc.focal_length_x, cc.focal_length_y, cc.principal_point_x, cc.principal_point_y))
    return QueryCamera(pinhole, model, None if model in _PINHOLE_MODELS else cc)
