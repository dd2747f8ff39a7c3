"""Lens distortion: a frame bundle with distortion coefficients as the same frame from an ideal pinhole camera.

A real lens bends rays: a pixel of a camera with distortion coefficients `dist` (OpenCV's model and order,
`perception.frames`) does not look along `K^-1 [u, v, 1]`. Every deprojection in perception uses K alone
(`perception.pointcloud`, the pallet face's rays, the calibration's features, the clearance check), so a
frame with coefficients is first resampled into the image an ideal pinhole camera with the same K would
have taken (`undistort_bundle`); everything downstream stays as it is. All in the camera's optical frame
(x right, y down, z out of the lens).

- For each pixel of the ideal image, `cv2.initUndistortRectifyMap` gives the distorted image's pixel that
  looks along the same ray (the forward lens model, closed form). The maps depend only on (K, dist, image
  size) and are computed once and kept (`MAP_CACHE_SIZE` cameras).
- Depth and labels are taken from the nearest distorted pixel, never interpolated: a depth between a
  pallet's edge and the wall behind it is a point in the air, a label between two classes is no class.
  Depth stays valid: it is z-depth along the optical axis, which the same K and the same optical frame
  keep (a pixel's point is `z * K^-1 [u, v, 1]` in the ideal image). No data stays no data (0 or NaN);
  an ideal pixel that no distorted pixel sees (outside the image, or beyond where the lens model folds
  back) gets no depth (0) and label 255 (unlabeled). Nearest-neighbour sampling moves a depth by at most
  half a pixel: on the floor seen at a grazing angle that is a few millimetres at 2 m.
- The colour image is interpolated bilinearly (black where depth and labels have no pixel).
- Truth arrays (`*_true`) are left as they are: perception never reads them.

Public API: `undistort_bundle`, `undistort_maps` (the cached maps), `distort_points` (the forward lens model
on normalised image points), `fit_brown_conrady` (OpenCV's 5 coefficients nearest to any forward model, for
camera sources whose own model is another), `MAP_CACHE_SIZE`.
"""

from __future__ import annotations

import dataclasses
import math
import threading
from collections import OrderedDict
from typing import NamedTuple

import cv2
import numpy as np

from palletpilot.perception.bundle_contract import SemanticClass, _fold_radius
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle

__all__ = [
    "MAP_CACHE_SIZE",
    "UndistortMaps",
    "distort_points",
    "fit_brown_conrady",
    "undistort_bundle",
    "undistort_maps",
]

MAP_CACHE_SIZE = 8
"""How many (K, dist, image size) maps are kept: 640 x 480 maps take 3.7 MB each."""


class UndistortMaps(NamedTuple):
    """Where each pixel of the ideal H x W image looks in the distorted one.

    `map_x`, `map_y`: float32 H x W, the distorted image's column and row (-1 where no pixel sees it);
    `flat_index`: int32 H*W, the flat index of the nearest distorted pixel (0 where none); `outside`: bool
    H*W, the ideal pixels no distorted pixel sees.
    """

    map_x: np.ndarray
    map_y: np.ndarray
    flat_index: np.ndarray
    outside: np.ndarray


_cache: OrderedDict[bytes, UndistortMaps] = OrderedDict()
_cache_lock = threading.Lock()


def undistort_maps(K: np.ndarray, dist: np.ndarray, shape: tuple[int, int]) -> UndistortMaps:
    """The maps of an H x W (`shape`) image with intrinsics K and coefficients `dist` (cached; read-only)."""
    K = np.ascontiguousarray(K, dtype=np.float64)
    dist = np.ascontiguousarray(dist, dtype=np.float64)
    key = K.tobytes() + dist.tobytes() + np.array(shape, dtype=np.int64).tobytes()
    with _cache_lock:
        maps = _cache.get(key)
        if maps is not None:
            _cache.move_to_end(key)
            return maps
    maps = _build_maps(K, dist, shape)
    with _cache_lock:
        _cache[key] = maps
        while len(_cache) > MAP_CACHE_SIZE:
            _cache.popitem(last=False)
    return maps


def _build_maps(K: np.ndarray, dist: np.ndarray, shape: tuple[int, int]) -> UndistortMaps:
    h, w = shape
    map_x, map_y = cv2.initUndistortRectifyMap(K, dist, None, K, (w, h), cv2.CV_32FC1)
    # Ideal pixels beyond the radius where the radial model folds back would be mapped back into the
    # image (a second ray on one pixel): they see nothing.
    rows, cols = np.mgrid[0:h, 0:w]
    yn = (rows - K[1, 2]) / K[1, 1]
    xn = ((cols - K[0, 2]) - K[0, 1] * yn) / K[0, 0]
    r = np.hypot(xn, yn)
    fold, _, _ = _fold_radius(dist, float(r.max()))
    beyond = (r >= fold) if math.isfinite(fold) else np.zeros((h, w), dtype=bool)
    beyond |= ~(np.isfinite(map_x) & np.isfinite(map_y))
    map_x[beyond] = -1.0
    map_y[beyond] = -1.0
    u = np.floor(map_x + 0.5)
    v = np.floor(map_y + 0.5)
    outside = beyond | (u < 0) | (u > w - 1) | (v < 0) | (v > h - 1)
    index = np.where(outside, 0, v * w + u).astype(np.int32).ravel()
    for a in (map_x, map_y, index, outside):
        a.flags.writeable = False
    return UndistortMaps(map_x, map_y, index, outside.ravel())


def _nearest(image: np.ndarray, maps: UndistortMaps, fill: float) -> np.ndarray:
    """`image` (H x W) sampled at the nearest distorted pixel of each ideal pixel; `fill` where none."""
    out = image.reshape(-1)[maps.flat_index]
    out[maps.outside] = fill
    return out.reshape(image.shape)


def undistort_bundle(frame: FrameBundle) -> FrameBundle:
    """`frame` as an ideal pinhole camera with the same K would have taken it (module docstring), `dist`
    cleared; `frame` itself when it has no distortion (no coefficients, or all zero)."""
    if not frame.distorted:
        return frame
    assert frame.dist is not None  # distorted
    maps = undistort_maps(frame.K, frame.dist, frame.depth.shape)
    depth = _nearest(frame.depth, maps, 0.0)
    labels = None if frame.labels is None else _nearest(frame.labels, maps, SemanticClass.UNLABELED)
    rgb = None
    if frame.rgb is not None:
        rgb = cv2.remap(
            np.ascontiguousarray(frame.rgb),
            maps.map_x,
            maps.map_y,
            cv2.INTER_LINEAR,
            borderMode=cv2.BORDER_CONSTANT,
            borderValue=(0, 0, 0),
        )
        rgb.reshape(-1, 3)[maps.outside] = 0  # what the depth and labels have no pixel for is black too
    return dataclasses.replace(frame, depth=depth, labels=labels, rgb=rgb, dist=None)


def distort_points(xy: np.ndarray, dist: np.ndarray) -> np.ndarray:
    """The forward lens model: ideal normalised image points (N x 2, `x / z`, `y / z` in the optical
    frame) to distorted normalised points (N x 2), for any of OpenCV's models (4..14 coefficients)."""
    xy = np.asarray(xy, dtype=np.float64).reshape(-1, 2)
    pts = np.column_stack([xy, np.ones(len(xy))])
    out, _ = cv2.projectPoints(pts, np.zeros(3), np.zeros(3), np.eye(3), np.asarray(dist, dtype=np.float64))
    return np.asarray(out, dtype=np.float64).reshape(-1, 2)


def fit_brown_conrady(ideal: np.ndarray, distorted: np.ndarray) -> tuple[np.ndarray, float]:
    """OpenCV's 5 coefficients (k1, k2, p1, p2, k3) whose forward model maps the ideal normalised points
    (N x 2) nearest (least squares) to the `distorted` ones (N x 2), and the largest miss (normalised units).

    The model is linear in its coefficients: `xd - x = k1 x r^2 + k2 x r^4 + k3 x r^6 + 2 p1 x y +
    p2 (r^2 + 2 x^2)`, and likewise for y.
    """
    ideal = np.asarray(ideal, dtype=np.float64).reshape(-1, 2)
    distorted = np.asarray(distorted, dtype=np.float64).reshape(-1, 2)
    if len(ideal) != len(distorted) or len(ideal) < 5:
        raise PerceptionError(f"fit_brown_conrady: need as many ideal as distorted points (>= 5), got {len(ideal)}")
    x, y = ideal[:, 0], ideal[:, 1]
    r2 = x * x + y * y
    ax = np.column_stack([x * r2, x * r2**2, 2 * x * y, r2 + 2 * x * x, x * r2**3])
    ay = np.column_stack([y * r2, y * r2**2, r2 + 2 * y * y, 2 * x * y, y * r2**3])
    a = np.vstack([ax, ay])
    b = np.concatenate([distorted[:, 0] - x, distorted[:, 1] - y])
    coeffs, *_ = np.linalg.lstsq(a, b, rcond=None)
    miss = a @ coeffs - b
    worst = float(np.max(np.hypot(miss[: len(x)], miss[len(x) :]))) if len(x) else 0.0
    return coeffs, worst
