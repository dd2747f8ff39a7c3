"""Depth images to point clouds (camera optical frame: x right, y down, z out of the lens; metres).

Vectorised pinhole deprojection with K: a pixel (u, v) with z-depth z is the point
`z * K^-1 [u, v, 1]`. Pixels without depth (0, NaN, inf) are dropped. Labels, being aligned with the
depth image (as RealSense `rs.align` gives it), select per-class clouds. `depth_edges` marks the pixels
at a depth jump (both sides of an object's silhouette), where a depth camera's values mix near and far.
"""

from __future__ import annotations

from collections.abc import Iterable
from dataclasses import dataclass

import numpy as np

from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle


def check_intrinsics(K: np.ndarray, where: str = "K") -> None:
    """Raise `PerceptionError` unless K is a finite 3x3 pinhole matrix with positive focal lengths."""
    K = np.asarray(K)
    if K.shape != (3, 3) or not np.all(np.isfinite(K)):
        raise PerceptionError(f"{where}: intrinsics must be a finite 3x3 matrix, got shape {K.shape}")
    if K[0, 0] <= 0 or K[1, 1] <= 0 or not np.allclose(K[2], [0.0, 0.0, 1.0]) or K[1, 0] != 0:
        raise PerceptionError(f"{where}: malformed intrinsics (need fx, fy > 0 and last row [0, 0, 1]): {K.tolist()}")


def depth_edges(
    depth: np.ndarray, rel_jump: float | np.ndarray, valid: np.ndarray | None = None, no_data_is_edge: bool = False
) -> np.ndarray:
    """Pixels (H, W) bool whose 3 x 3 neighbourhood spans a relative depth jump: its farthest valid depth
    exceeds its nearest by more than `rel_jump` (a share of the nearest; a scalar or per pixel (H, W)).

    `valid` (H, W): the pixels with depth (default: finite and above 0). With `no_data_is_edge`, pixels
    without depth count as edges too (the calibration keeps its floor and fork points away from holes).
    """
    import cv2

    if valid is None:
        valid = np.isfinite(depth) & (depth > 0)
    kernel = np.ones((3, 3), np.uint8)
    d = np.where(valid, depth, 0.0).astype(np.float32)
    d_max = cv2.dilate(d, kernel)
    d_min = cv2.erode(np.where(valid, d, np.float32(1e6)), kernel)
    edge = d_max > d_min * (1.0 + rel_jump)
    return edge | ~valid if no_data_is_edge else edge


@dataclass(frozen=True)
class PointCloud:
    """Points (N x 3, camera frame, m) with the image row and column each came from."""

    points: np.ndarray
    rows: np.ndarray
    cols: np.ndarray

    def __len__(self) -> int:
        return len(self.points)


def deproject(depth: np.ndarray, K: np.ndarray, mask: np.ndarray | None = None) -> PointCloud:
    """Points of every valid depth pixel (where `mask`, if given, is true), in the camera frame."""
    check_intrinsics(K)
    valid = np.isfinite(depth) & (depth > 0)
    if mask is not None:
        valid &= mask
    rows, cols = np.nonzero(valid)
    z = depth[rows, cols].astype(np.float64)
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    y = (rows - cy) / fy * z
    x = ((cols - cx) - skew * (rows - cy) / fy) / fx * z
    return PointCloud(np.column_stack([x, y, z]), rows, cols)


def class_mask(labels: np.ndarray, classes: Iterable[int]) -> np.ndarray:
    """Boolean image: pixels whose label is one of `classes`."""
    lut = np.zeros(256, bool)
    lut[list(classes)] = True
    return lut[labels]


def class_cloud(bundle: FrameBundle, classes: Iterable[int], where: str = "frame") -> PointCloud:
    """Points of the pixels labelled with any of `classes` (needs labels in the bundle)."""
    if bundle.labels is None:
        raise PerceptionError(f"{where}: the frame has no labels (segment its RGB first)")
    return deproject(bundle.depth, bundle.K, class_mask(bundle.labels, classes))
