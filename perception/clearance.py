"""Is a volume in front of the forks free? Depth points inside an upright box, and how much of it was seen.

Before the forks enter a pallet (the entry volume between the fork tips and the entry face) and before
a load goes into a drop slot (the slot's volume), the camera must show no person and no object there.
`check_volume` takes one depth frame, puts every valid pixel into the forklift frame with the
calibration (the camera rides on the carriage: `Calibration.T_forklift_camera_at(frame.fork_height)`)
and counts the points inside (pixels next to a depth jump, where a stereo camera puts "flying" depths
between an edge and the background, are skipped) a `Volume` (an upright box in the forklift frame: origin on the floor
between the fork heels, x towards the tips, y left, z up; metres). Geometry only: no labels are needed,
so it works with or without a segmenter.

It also reports `seen`: the share of sample points spread through the volume's lower part that the camera could
see, i.e. that lie in the image where a depth was measured, and not in front of them from outside
the volume (the truck's own load hides a drop slot from a carriage camera, or leaves no valid depth
at all). A check with little seen is no check: the caller must use another sensor or refuse.

Public API: `Volume`, `VolumeCheck`, `check_volume`.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.distortion import undistort_bundle
from palletpilot.perception.frames import FrameBundle

MIN_POINTS = 150
"""Depth points inside a volume that make it occupied: a person or a box at a few metres gives thousands,
flying pixels and depth noise a handful."""

EDGE_JUMP = 0.05
"""A depth jump over this share of a pixel's depth within 5x5 px marks an edge (its pixels are skipped)."""

_OCCLUSION_M = 0.10  # a measured depth this much nearer than a sample point hides it


@dataclass(frozen=True)
class Volume:
    """An upright box in the forklift frame (m): x from `x0` to `x1`, y from `y0` to `y1`, z from `z0`
    to `z1` above the floor."""

    x0: float
    x1: float
    y0: float
    y1: float
    z0: float
    z1: float

    def contains(self, p: np.ndarray) -> np.ndarray:
        """Which of the points `p` (N, 3; forklift frame) lie inside."""
        return (
            (p[:, 0] >= self.x0)
            & (p[:, 0] <= self.x1)
            & (p[:, 1] >= self.y0)
            & (p[:, 1] <= self.y1)
            & (p[:, 2] >= self.z0)
            & (p[:, 2] <= self.z1)
        )

    def samples(self, step_m: float = 0.05) -> np.ndarray:
        """Points (N, 3) spread through the volume's lower part on a grid of about `step_m`, at its floor
        and 0.3 m above it (where anything standing in it shows)."""
        xs = np.linspace(self.x0, self.x1, max(2, int((self.x1 - self.x0) / step_m) + 1))
        ys = np.linspace(self.y0, self.y1, max(2, int((self.y1 - self.y0) / step_m) + 1))
        zs = np.array([self.z0 + 0.01, min(self.z1, self.z0 + 0.3)])
        return np.stack(np.meshgrid(xs, ys, zs, indexing="ij"), axis=-1).reshape(-1, 3)

    def to_json(self) -> dict[str, list[float]]:
        """`{x_m: [x0, x1], y_m: [...], z_m: [...]}`."""
        r = lambda a, b: [round(a, 3), round(b, 3)]  # noqa: E731
        return {"x_m": r(self.x0, self.x1), "y_m": r(self.y0, self.y1), "z_m": r(self.z0, self.z1)}


@dataclass(frozen=True)
class VolumeCheck:
    """What the camera saw of a volume: `points` inside it, the `nearest_x_m` of them (forklift frame;
    None when none), and the share of the volume `seen` (0..1)."""

    points: int
    nearest_x_m: float | None
    seen: float

    @property
    def occupied(self) -> bool:
        """Enough points inside to be a person or an object."""
        return self.points >= MIN_POINTS

    def to_json(self) -> dict[str, object]:
        """Plain JSON for events."""
        nearest = None if self.nearest_x_m is None else round(self.nearest_x_m, 3)
        return {"points": self.points, "nearest_x_m": nearest, "seen": round(self.seen, 3)}


def _depth_edges(depth: np.ndarray, valid: np.ndarray) -> np.ndarray:
    """Pixels next to a depth jump (over `EDGE_JUMP` of their depth within 5x5 px): a stereo camera's
    "flying" pixels there lie between the near edge and the background, in the middle of nowhere."""
    d = np.where(valid, depth, 0.0).astype(np.float32)
    kernel = np.ones((5, 5), np.uint8)
    near = cv2.erode(np.where(valid, d, np.float32(1e6)), kernel)
    far = cv2.dilate(d, kernel)
    return (far - near) > EDGE_JUMP * d


def check_volume(frame: FrameBundle, calibration: Calibration, volume: Volume) -> VolumeCheck:
    """Count the frame's depth points inside `volume` and measure how much of it the camera saw (a frame
    with lens distortion is undistorted first: `perception.distortion`)."""
    frame = undistort_bundle(frame)
    T_fc = calibration.T_forklift_camera_at(frame.fork_height)
    R, t = T_fc.rotation.as_matrix(), np.asarray(T_fc.t, dtype=float)
    depth = frame.depth
    K = frame.K
    valid = np.isfinite(depth) & (depth > 0.0)
    rows, cols = np.nonzero(valid & ~_depth_edges(depth, valid))
    z = depth[rows, cols].astype(np.float64)
    yc = (rows - K[1, 2]) / K[1, 1]
    xc = ((cols - K[0, 2]) - K[0, 1] * yc) / K[0, 0]
    # Element-wise (no BLAS product): see `perception.pallet_face._rays`.
    points = z[:, None] * (xc[:, None] * R[:, 0] + yc[:, None] * R[:, 1] + R[:, 2]) + t
    inside = volume.contains(points)
    count = int(inside.sum())
    nearest = float(points[inside, 0].min()) if count else None

    # Visibility: project samples of the volume; a sample is hidden when the pixel measures a point in
    # front of it that is itself outside the volume.
    s = volume.samples()
    cam = (s - t) @ R  # camera frame (R's columns are the camera axes in the forklift frame)
    h, w = depth.shape
    front = cam[:, 2] > 0.05
    u = np.full(len(s), -1, dtype=int)
    v = np.full(len(s), -1, dtype=int)
    u[front] = np.round(K[0, 0] * cam[front, 0] / cam[front, 2] + K[0, 1] * cam[front, 1] / cam[front, 2] + K[0, 2])
    v[front] = np.round(K[1, 1] * cam[front, 1] / cam[front, 2] + K[1, 2])
    in_image = front & (u >= 0) & (u < w) & (v >= 0) & (v < h)
    seen = np.zeros(len(s), dtype=bool)
    idx = np.flatnonzero(in_image)
    d = depth[v[idx], u[idx]].astype(np.float64)
    measured = np.isfinite(d) & (d > 0.0)
    nearer = measured & (d < cam[idx, 2] - _OCCLUSION_M)
    if nearer.any():
        ray = (cam[idx[nearer]] / cam[idx[nearer], 2:3]) * d[nearer, None]  # the measured point (camera frame)
        hit = ray @ R.T + t
        hidden = ~volume.contains(hit)
        blocked = np.zeros(len(idx), dtype=bool)
        blocked[np.flatnonzero(nearer)[hidden]] = True
    else:
        blocked = np.zeros(len(idx), dtype=bool)
    seen[idx] = measured & ~blocked  # no depth there (too near, as a load right before the lens): unseen
    return VolumeCheck(count, nearest, float(seen.mean()) if len(s) else 0.0)
