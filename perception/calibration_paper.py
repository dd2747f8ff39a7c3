"""The paper's calibration method (section 3.2 of the reference paper), kept as the baseline.

`paper_fit(frame_data, forks, limits, where)` -> (`T_forklift_camera` at lift height 0, quality):
tilt from the RANSAC floor normal, pan from the vanishing point of the fork edges, zero rotation about
the optical axis (a bubble level), the lateral position midway between RANSAC planes on the inner fork
sides, the height from the floor plane, and the forward position from the farthest fork points (the
tips) minus `tip_x`. Frames: camera optical (x right, y down, z forward), forklift (ARCHITECTURE.md).
`perception.calibration.calibrate(..., method="paper")` calls it with the per-frame evidence
(`_FrameData`) and the RANSAC floor plane it shares with the `model` method.
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import cv2
import numpy as np
import open3d as o3d
from scipy.spatial.transform import Rotation

from palletpilot.geometry import SE3
from palletpilot.perception.calibration_features import _RNG_SEED, _ransac_plane
from palletpilot.perception.calibration_io import R_LEVEL
from palletpilot.perception.errors import CalibrationError
from palletpilot.perception.specs import ForkGeometry

if TYPE_CHECKING:
    from palletpilot.perception.calibration import Limits
    from palletpilot.perception.calibration_features import _FrameData


def _vanishing_point(fd: _FrameData) -> np.ndarray:
    """Least-squares intersection (pixels) of the lines fitted to the left and right edges of both forks."""
    mask: np.ndarray = np.zeros(fd.frame.depth.shape, np.uint8)
    mask[fd.fork_pixels[:, 0], fd.fork_pixels[:, 1]] = 1
    _, comp, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    order = np.argsort(stats[1:, cv2.CC_STAT_AREA])[::-1][:2] + 1
    lines = []
    h, w = mask.shape
    for c in order:
        rows, cols = np.nonzero(comp == c)
        left, right = np.full(h, w), np.full(h, -1)
        np.minimum.at(left, rows, cols)
        np.maximum.at(right, rows, cols)
        for edge in (left, right):
            r = np.flatnonzero((edge >= 0) & (edge < w))
            pts = np.column_stack([edge[r], r]).astype(np.float32)
            if len(pts) >= 10:
                vx, vy, x0, y0 = cv2.fitLine(pts, cv2.DIST_HUBER, 0, 0.01, 0.01).ravel()
                lines.append((np.array([vx, vy]), np.array([x0, y0])))
    if len(lines) < 2:
        raise CalibrationError("paper method: fork edges not found for the vanishing point")
    # Each line: normal . p = normal . p0; solve in least squares.
    A = np.array([[-d[1], d[0]] for d, _ in lines])
    b = np.array([(-d[1]) * p[0] + d[0] * p[1] for d, p in lines])
    vp, *_ = np.linalg.lstsq(A, b, rcond=None)
    return vp


def paper_fit(
    fd: _FrameData, floor: tuple[np.ndarray, float], forks: ForkGeometry, limits: Limits, where: str
) -> tuple[SE3, dict]:
    """The paper's `T_forklift_camera` from one frame's evidence and its floor plane (unit normal up, in
    camera coordinates, and distance, m), with the quality figures of the method."""
    n, d = floor
    # Tilt: angle between the camera's -y axis and the floor normal (eq. in 3.2.1).
    tilt = math.acos(float(np.clip(n @ np.array([0.0, -1.0, 0.0]), -1.0, 1.0)))
    vp = _vanishing_point(fd)
    K = fd.frame.K
    pan = math.atan((vp[0] - K[0, 2]) / K[0, 0])  # eq. 5
    # R_C'C = X_tilt Y_pan Z_0 in the level camera frame C' (optical axes, levelled), signs as in
    # `camera_mount_pose`: tilting down is -tilt about x, panning left is -pan about y.
    R_levelcam_cam = Rotation.from_euler("x", -tilt) * Rotation.from_euler("y", -pan)
    pts = R_levelcam_cam.apply(fd.forks)  # fork points in C': x right, y down, z forward, level
    height = d
    above = pts[(height - fd.frame.fork_height - pts[:, 1] > 0.25 * forks.thickness)]
    if len(above) < limits.min_fork_points // 2:
        raise CalibrationError(f"{where}: paper method: too few fork points above the floor")
    # P2, P3: the inner sides of the left and right fork, vertical faces (normal along C' x) that
    # face the middle. Normals from the local neighbourhood, then a RANSAC plane per fork.
    rng = np.random.default_rng(_RNG_SEED)
    sample = above if len(above) <= 30000 else above[rng.choice(len(above), 30000, replace=False)]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sample))
    pcd.estimate_normals(o3d.geometry.KDTreeSearchParamKNN(20))
    normals = np.asarray(pcd.normals)
    vertical = np.abs(normals[:, 0]) > 0.9
    middle = np.median(sample[:, 0])
    p2 = sample[vertical & (sample[:, 0] < middle)]
    p3 = sample[vertical & (sample[:, 0] >= middle)]
    if len(p2) < 30 or len(p3) < 30:
        raise CalibrationError(f"{where}: paper method: inner fork sides not found ({len(p2)}, {len(p3)} points)")
    n2, d2 = _ransac_plane(p2, 0.004)
    n3, d3 = _ransac_plane(p3, 0.004)
    x_p2 = -d2 / n2[0]  # where each plane crosses the C' x axis
    x_p3 = -d3 / n3[0]
    x_F = 0.5 * (x_p2 + x_p3)  # eq. 8-9: the origin lies midway between the inner sides
    y_F = height - fd.frame.fork_height  # eq. 10: distance to the floor plane, at lift height 0
    tip = np.percentile(pts[:, 2], 99.8)  # P5 through the farthest fork points (the tips), eq. 11-12
    z_F = tip - forks.tip_x
    t_levelcam_F = np.array([x_F, y_F, z_F])  # origin of F in C'
    T_F_levelcam = SE3(Rotation.from_matrix(R_LEVEL), -R_LEVEL @ t_levelcam_F)  # eq. 13
    T = T_F_levelcam @ SE3(R_levelcam_cam)
    quality = {"vanishing_point_px": np.round(vp, 2).tolist(), "inner_side_points": [len(p2), len(p3)]}
    return T, quality
