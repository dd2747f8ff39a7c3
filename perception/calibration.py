"""Camera calibration from the forks and the floor: `T_forklift_camera` from RGB-D frames.

Two methods, both on labelled frames (class ids of ARCHITECTURE.md; the camera frame is optical):

`paper`: section 3.2 of the reference paper, kept as the baseline to compare against.
  - tilt (the paper's "roll"): angle between the camera's -y axis and the RANSAC floor normal;
  - pan (the paper's "pitch"): `atan((VP_x - c_x) / f_x)` from the vanishing point of the fork edges;
  - rotation about the optical axis (the paper's "yaw"): zero, as set with a bubble level;
  - lateral position: midway between RANSAC planes on the inner fork sides (P2, P3); height: the
    camera's distance to the floor plane; forward: the distance to the plane through the farthest fork
    points (P5, the tips) minus `tip_x`.

`model` (the default) does better where the paper reports trouble (a 20-30 mm forward bias from
weak tip features, height deviations, an assumed zero roll):
  - full 3-DOF rotation: floor normal (RANSAC, refined) plus the forks' direction, no bubble level;
  - then one robust least-squares fit of all six degrees of freedom to three kinds of evidence:
    floor points lie on the floor, fork points lie on the surfaces of the known fork model (two
    boxes: tops, inner and outer sides), and the tip edges lie at `tip_x`;
  - the tips come from geometry, not from label boundaries: scanning the depth image along each
    fork, a tip edge sits between the last pixel on the fork-top plane and the first pixel that sees
    beyond it (the floor). The midpoint of that interval has no quantisation bias; pixels at depth
    edges (mixed, flying) count as unknown and widen the interval instead of biasing it;
  - points at depth discontinuities are left out of the surface fits, labelled points that sit on
    the wrong surface (fork labels bled onto the floor) are dropped by geometry, and a soft-L1 loss
    absorbs the rest;
  - several frames (also with raised forks, `fork_height` in the bundle) are fitted together; the
    result is always for lift height 0;
  - quality: residual RMS per kind, inlier counts, frames used. Missing features or residuals above
    limits raise `CalibrationError` with the reason. `Calibrator` keeps the last good calibration.
"""

from __future__ import annotations

import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
import open3d as o3d
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from palletpilot.geometry import SE3
from palletpilot.perception.calibration_io import R_LEVEL, Calibration
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle, SemanticClass
from palletpilot.perception.pointcloud import check_intrinsics, class_mask, deproject
from palletpilot.perception.specs import ForkGeometry

Method = Literal["model", "paper"]
METHODS: tuple[Method, ...] = ("model", "paper")


class CalibrationError(PerceptionError):
    """The frames do not allow a calibration; the message says which feature is missing or how far off."""


@dataclass(frozen=True)
class Limits:
    """Thresholds of a usable calibration (m unless named otherwise)."""

    min_floor_points: int = 2000
    min_fork_points: int = 1500
    min_tip_edges: int = 8
    floor_rms: float = 0.010  # plus the stereo noise expected at the floor's median depth (raised forks)
    fork_rms: float = 0.008
    tip_rms: float = 0.010
    ransac_threshold: float = 0.008
    depth_edge_jump: float = 0.03  # relative depth jump in a 3x3 neighbourhood that marks a depth edge
    max_floor_depth: float = 3.0  # floor points farther than this (z-depth, m) are too noisy to use


LIMITS = Limits()
_RNG_SEED = 0  # RANSAC and subsampling are seeded: same frames, same result


# -- per-frame evidence ---------------------------------------------------------------------------


@dataclass
class _FrameData:
    """What one frame contributes, in the camera frame."""

    frame: FrameBundle
    floor: np.ndarray  # (N, 3) drivable points off depth edges
    forks: np.ndarray  # (M, 3) fork points off depth edges
    fork_pixels: np.ndarray  # (M, 2) rows, cols of those
    edge: np.ndarray  # bool image: depth discontinuities (mixed / flying pixels)
    K_inv: np.ndarray


def _depth_edges(depth: np.ndarray, jump: float) -> np.ndarray:
    """Pixels whose 3x3 neighbourhood spans a relative depth jump above `jump` (or touches no-data)."""
    d = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    d_max = cv2.dilate(d, kernel)
    d_min = cv2.erode(np.where(d > 0, d, np.float32(1e6)), kernel)
    return (d_max > d_min * (1.0 + jump)) | (d == 0)


def _frame_data(frame: FrameBundle, where: str, limits: Limits) -> _FrameData:
    check_intrinsics(frame.K, f"{where}: K")
    if frame.labels is None:
        raise CalibrationError(
            f"{where}: the frame has no labels; calibration needs the drivable and forks classes "
            "(segment the RGB first)"
        )
    valid = np.isfinite(frame.depth) & (frame.depth > 0)
    if not valid.any():
        raise CalibrationError(f"{where}: no valid depth in the frame")
    edge = _depth_edges(frame.depth, limits.depth_edge_jump)
    # Near floor only: stereo depth noise grows with z^2 (about 0.1 m at 5 m for a D435).
    near = frame.depth < limits.max_floor_depth
    floor = deproject(frame.depth, frame.K, class_mask(frame.labels, [SemanticClass.DRIVABLE]) & ~edge & near)
    forks = deproject(frame.depth, frame.K, class_mask(frame.labels, [SemanticClass.FORKS]) & ~edge)
    if len(floor) < limits.min_floor_points:
        raise CalibrationError(
            f"{where}: no floor: {len(floor)} drivable pixels with depth (need {limits.min_floor_points})"
        )
    if len(forks) < limits.min_fork_points:
        raise CalibrationError(
            f"{where}: no forks: {len(forks)} fork pixels with depth (need {limits.min_fork_points})"
        )
    return _FrameData(
        frame,
        floor.points,
        forks.points,
        np.column_stack([forks.rows, forks.cols]),
        edge,
        np.linalg.inv(frame.K),
    )


def _fit_floor(points: np.ndarray, limits: Limits, where: str) -> tuple[np.ndarray, float, np.ndarray]:
    """RANSAC plane, refined by least squares on its inliers: unit normal (towards the camera), offset, inliers.

    The plane is `n . p = -d` with `d` > 0 the camera's distance to the floor.
    """
    rng = np.random.default_rng(_RNG_SEED)
    sample = points if len(points) <= 20000 else points[rng.choice(len(points), 20000, replace=False)]
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(sample))
    o3d.utility.random.seed(_RNG_SEED)
    (a, b, c, d0), _ = pcd.segment_plane(limits.ransac_threshold, 3, 200)
    inl = np.abs(points @ np.array([a, b, c]) + d0) < limits.ransac_threshold  # inliers of the whole set
    if inl.sum() < limits.min_floor_points:
        raise CalibrationError(f"{where}: no floor plane: {inl.sum()} points on one plane")
    p = points[inl]
    p = p if len(p) <= 50000 else p[rng.choice(len(p), 50000, replace=False)]
    centre = p.mean(axis=0)
    _, _, vt = np.linalg.svd(p - centre, full_matrices=False)
    n = vt[2]
    if n @ centre > 0:  # normal towards the camera (the camera is above the floor)
        n = -n
    d = float(-(n @ centre))
    return n, d, inl


# -- the fork model -------------------------------------------------------------------------------


def _fork_distance(q: np.ndarray, forks: ForkGeometry) -> np.ndarray:
    """Distance (m) of points (forklift frame at lift 0) to the nearer fork's surfaces.

    The forks mirror each other about y = 0, so y folds onto one fork: |y| - centre_y. The fork is
    open towards the back (the heels are out of view and the carriage is not a fork).
    """
    half_w = 0.5 * forks.width
    dy = np.abs(np.abs(q[:, 1]) - forks.centre_y) - half_w  # > 0 outside the fork sideways
    dz = np.abs(q[:, 2] - 0.5 * forks.thickness) - 0.5 * forks.thickness
    dx = q[:, 0] - forks.tip_x
    outside = np.sqrt(np.maximum(dx, 0.0) ** 2 + np.maximum(dy, 0.0) ** 2 + np.maximum(dz, 0.0) ** 2)
    inside = -np.maximum(np.maximum(dx, dy), dz)  # distance to the nearest face from within
    return np.where(outside > 0.0, outside, inside)


# -- fork edges from the depth image --------------------------------------------------------------


def _depth_tolerance(z: np.ndarray) -> np.ndarray:
    """How far (m) a stereo depth reading may stray from the truth at z-depth z (m): ~3 sigma of a D435."""
    return 0.004 + 0.012 * z * z


@dataclass(frozen=True)
class _Edges:
    """Camera-frame rays through fork edges: the tips, and the outer sides (with the fork's side sign)."""

    tips: np.ndarray  # (N, 3)
    sides: np.ndarray  # (M, 3)
    side_sign: np.ndarray  # (M,) +1 left fork (y > 0), -1 right fork


def _edge_rays(data: _FrameData, T: SE3, forks: ForkGeometry, tip_window: float = 0.04) -> _Edges:
    """Rays through the forks' depth edges against the floor, found by scanning the depth image.

    A fork's top face ends where the camera starts to see beyond it (the floor, 5 cm lower): at the
    tips, scanning up each column, and along the outer sides, scanning sideways along each row. The
    edge lies between the last pixel on the fork-top plane and the first pixel seeing beyond it;
    pixels matching neither surface (mixed, flying, no data) in between count as unknown. The ray through the middle of
    that interval (at most 4 px) has no quantisation bias. Each edge point is then classified by where
    it lies on the forks under the current estimate `T` (forklift frame at lift 0); tips are looked
    for within `tip_window` (m) of `tip_x`.
    """
    depth = data.frame.depth
    shape = depth.shape
    assert data.frame.labels is not None  # `_frame_data` rejects frames without labels
    # Every edge lies near the border of the fork labels (off by a few pixels at most): classify
    # only a band of +-7 px around it.
    labels = (data.frame.labels == SemanticClass.FORKS).astype(np.uint8)
    kernel = np.ones((15, 15), np.uint8)
    band = cv2.dilate(labels, kernel) != cv2.erode(labels, kernel)
    rows, cols = np.nonzero(band)
    R, t = T.R, T.t
    rays = np.column_stack([cols, rows, np.ones(len(rows))]) @ data.K_inv.T
    along_up = rays @ R[2]  # forklift z component of each ray

    def plane_depth(z_plane: float) -> np.ndarray:
        """z-depth where each ray meets the horizontal plane z_F = z_plane (inf: never)."""
        with np.errstate(divide="ignore", invalid="ignore"):
            s_ = (z_plane - t[2]) / along_up
        s_[~(s_ > 0)] = np.inf
        return s_

    s_top = plane_depth(forks.thickness)
    s_floor = plane_depth(-data.frame.fork_height)
    z = depth[rows, cols]
    valid = np.isfinite(z) & (z > 0)
    # Each pixel against both surfaces: fork top, floor, or neither (mixed, flying, no data).
    top_ok = np.isfinite(s_top)
    on_top = valid & top_ok & (np.abs(z - s_top) < _depth_tolerance(np.where(top_ok, s_top, 0.0)))
    floor_ok = np.isfinite(s_floor)
    beyond = valid & floor_ok & ~on_top & (np.abs(z - s_floor) < _depth_tolerance(np.where(floor_ok, s_floor, 0.0)))
    q = (rays * np.where(top_ok, s_top, 0.0)[:, None]) @ R.T + t
    near_forks = (np.abs(np.abs(q[:, 1]) - forks.centre_y) < 0.5 * forks.width + 0.03) & (q[:, 0] > forks.heel_x)
    near_forks &= q[:, 0] < forks.tip_x + tip_window + 0.01
    fg = on_top & near_forks
    # Codes: 0 unknown (also everywhere off the band), 1 fork top near the forks, 2 floor, 3 other top.
    code = np.zeros(shape, np.int8)
    code[rows, cols] = np.where(fg, 1, np.where(beyond, 2, np.where(on_top, 3, 0)))
    fr, fc = rows[fg], cols[fg]

    def scan(dr: int, dc: int) -> np.ndarray:
        """Rays at edges from fg pixels to floor pixels 1-4 steps away along (dr, dc), unknown between."""
        out = []
        for gap in (1, 2, 3, 4):
            r2, c2 = fr + dr * gap, fc + dc * gap
            ok = (r2 >= 0) & (r2 < shape[0]) & (c2 >= 0) & (c2 < shape[1])
            ok[ok] = code[r2[ok], c2[ok]] == 2
            for k in range(1, gap):
                ok[ok] = code[fr[ok] + dr * k, fc[ok] + dc * k] == 0
            mid_r = fr[ok] + 0.5 * dr * gap
            mid_c = fc[ok] + 0.5 * dc * gap
            out.append(np.column_stack([mid_c, mid_r, np.ones(len(mid_r))]) @ data.K_inv.T)
        return np.vstack(out)

    vertical = scan(-1, 0)  # up the columns: away from the forklift
    sideways = np.vstack([scan(0, -1), scan(0, 1)])
    half_w, margin = 0.5 * forks.width, 0.012
    pv = _hit_plane(vertical, T, forks.thickness)
    tip = (np.abs(pv[:, 0] - forks.tip_x) < tip_window) & (np.abs(np.abs(pv[:, 1]) - forks.centre_y) < half_w - margin)
    ps = _hit_plane(sideways, T, forks.thickness)
    outer = forks.centre_y + half_w
    side = (np.abs(np.abs(ps[:, 1]) - outer) < 0.02) & (ps[:, 0] < forks.tip_x - 0.03)
    return _Edges(vertical[tip], sideways[side], np.sign(ps[side, 1]))


def _hit_plane(rays: np.ndarray, T: SE3, z_plane: float) -> np.ndarray:
    """Points (forklift frame at lift 0) where camera rays meet the horizontal plane z = z_plane."""
    d = rays @ T.R.T
    s = (z_plane - T.t[2]) / d[:, 2]
    return T.t + d * s[:, None]


# -- method `model` ---------------------------------------------------------------------------------


def _initial_pose(data: Sequence[_FrameData], forks: ForkGeometry, limits: Limits, where: str) -> SE3:
    """Rotation from the floor normal and the forks' direction; translation from floor distance and fork extent."""
    first = data[0]
    n, d, _ = _fit_floor(first.floor, limits, where)
    up = n  # forklift z in camera coordinates
    # The two forks: the two largest connected regions of fork pixels in the image.
    mask = np.zeros(first.frame.depth.shape, np.uint8)
    mask[first.fork_pixels[:, 0], first.fork_pixels[:, 1]] = 1
    _, comp, stats, _ = cv2.connectedComponentsWithStats(mask, connectivity=8)
    largest = np.argsort(stats[1:, cv2.CC_STAT_AREA])[::-1][:2] + 1
    component = comp[first.fork_pixels[:, 0], first.fork_pixels[:, 1]]
    # Fork points clearly above the floor (labels bleed onto the floor at the fork edges).
    height = first.forks @ up + d - first.frame.fork_height  # above the fork bottoms' plane at lift 0
    above = (height > 0.25 * forks.thickness) & (height < 2.0 * forks.thickness)
    groups = [first.forks[above & (component == c)] for c in largest]
    if len(groups) < 2 or min(len(g) for g in groups) < limits.min_fork_points // 4:
        raise CalibrationError(f"{where}: no forks: the fork pixels do not form two forks")
    groups = [g - np.outer(g @ up, up) for g in groups]  # onto the floor plane

    def principal_axis(p: np.ndarray) -> np.ndarray:
        """Long axis of one fork's points: each fork is a long, narrow strip."""
        _, _, vt = np.linalg.svd(p - p.mean(axis=0), full_matrices=False)
        axis = vt[0] - (vt[0] @ up) * up
        axis /= np.linalg.norm(axis)
        return axis if axis[2] > 0 else -axis  # the forks point away from the camera

    x_axis = principal_axis(groups[0]) + principal_axis(groups[1])
    x_axis /= np.linalg.norm(x_axis)
    y_axis = np.cross(up, x_axis)
    R_FC = np.vstack([x_axis, y_axis, up])  # rows: forklift axes in camera coordinates
    q = np.vstack(groups) @ R_FC.T
    centres = [np.median(g @ y_axis) for g in groups]  # each fork's centre line
    t = np.array(
        [
            forks.tip_x - np.percentile(q[:, 0], 99.0),  # rough: the tip edges refine it
            -0.5 * (centres[0] + centres[1]),
            d - first.frame.fork_height,
        ]
    )
    return SE3(Rotation.from_matrix(R_FC), t)


def _model_fit(data: Sequence[_FrameData], forks: ForkGeometry, limits: Limits, where: str) -> tuple[SE3, dict]:
    rng = np.random.default_rng(_RNG_SEED)
    T0 = _initial_pose(data, forks, limits, where)

    def subsample(a: np.ndarray, n: int) -> np.ndarray:
        return a if len(a) <= n else a[rng.choice(len(a), n, replace=False)]

    floors = [subsample(fd.floor, 1500) for fd in data]
    lifts = [fd.frame.fork_height for fd in data]
    T = T0
    stats: dict = {}
    for round_ in range(2):
        # Evidence against the current estimate: forks near the model, tips from the depth image.
        fork_sets, edge_sets = [], []
        for fd in data:
            q = T.apply(fd.forks)
            keep = _fork_distance(q, forks) < (0.03 if round_ == 0 else 0.01)
            fork_sets.append(subsample(fd.forks[keep], 2000))
            edge_sets.append(_edge_rays(fd, T, forks, tip_window=0.15 if round_ == 0 else 0.03))
        n_tips = sum(len(e.tips) for e in edge_sets)
        n_sides = sum(len(e.sides) for e in edge_sets)
        if n_tips < limits.min_tip_edges:
            raise CalibrationError(
                f"{where}: fork tips not found: {n_tips} tip edge pixels (need {limits.min_tip_edges})"
            )

        def residuals(x: np.ndarray, fork_sets: list = fork_sets, edge_sets: list = edge_sets) -> np.ndarray:
            Tx = SE3(Rotation.from_rotvec(x[:3]), x[3:])
            res = []
            for floor, fork_pts, edges, lift in zip(floors, fork_sets, edge_sets, lifts, strict=True):
                res.append(Tx.apply(floor)[:, 2] + lift)  # the floor is at z = -lift below the carriage
                res.append(_fork_distance(Tx.apply(fork_pts), forks))
                # Edge rays meet the fork-top plane at the tips (x = tip_x) and the outer sides. The tips
                # count as one mean constraint on x, weighted by their number: the tip edge runs along
                # the pixel grid, so per-fork quantisation must not tilt the yaw (the sides set it).
                tip_x = _hit_plane(edges.tips, Tx, forks.thickness)[:, 0] - forks.tip_x
                res.append(np.atleast_1d(math.sqrt(len(tip_x)) * tip_x.mean()) if len(tip_x) else np.zeros(0))
                side_y = _hit_plane(edges.sides, Tx, forks.thickness)[:, 1]
                res.append(edges.side_sign * side_y - (forks.centre_y + 0.5 * forks.width))
            return np.concatenate(res)

        x0 = np.concatenate([T.rotation.as_rotvec(), T.t])
        sol = least_squares(residuals, x0, loss="soft_l1", f_scale=0.004, x_scale=[0.01] * 3 + [0.01] * 3)
        T = SE3(Rotation.from_rotvec(sol.x[:3]), sol.x[3:])
        stats = {
            "fork_points": sum(len(f) for f in fork_sets),
            "tip_edges": n_tips,
            "side_edges": n_sides,
            "evaluations": int(sol.nfev),
        }

    floor_res = np.concatenate([T.apply(f)[:, 2] + lift for f, lift in zip(floors, lifts, strict=True)])
    fork_res = np.concatenate([_fork_distance(T.apply(f), forks) for f in fork_sets])
    tip_res = np.concatenate([_hit_plane(e.tips, T, forks.thickness)[:, 0] - forks.tip_x for e in edge_sets])

    def robust_rms(r: np.ndarray) -> float:
        inl = np.abs(r) < 0.02
        return float(np.sqrt(np.mean(r[inl] ** 2))) if inl.any() else math.inf

    floor_depth = float(np.median(np.concatenate([f[:, 2] for f in floors])))
    floor_limit = limits.floor_rms + 2.0 * float(_depth_tolerance(np.array(floor_depth))) / 3.0
    quality = {
        "floor_rms_m": robust_rms(floor_res),
        "fork_rms_m": robust_rms(fork_res),
        "tip_rms_m": robust_rms(tip_res),
        "floor_inlier_ratio": float(np.mean(np.abs(floor_res) < 0.02)),
        "fork_inlier_ratio": float(np.mean(np.abs(fork_res) < 0.02)),
        "floor_points": int(sum(len(f) for f in floors)),
        **stats,
    }
    checks = (("floor_rms_m", floor_limit), ("fork_rms_m", limits.fork_rms), ("tip_rms_m", limits.tip_rms))
    for key, limit in checks:
        if not quality[key] <= limit:
            raise CalibrationError(
                f"{where}: {key} {quality[key] * 1e3:.1f} mm is above the limit {limit * 1e3:.1f} mm"
            )
    return T, quality


# -- method `paper` ---------------------------------------------------------------------------------


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


def _ransac_plane(points: np.ndarray, threshold: float) -> tuple[np.ndarray, float]:
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    o3d.utility.random.seed(_RNG_SEED)
    (a, b, c, d), _ = pcd.segment_plane(threshold, 3, 200)
    n = np.array([a, b, c])
    return n / np.linalg.norm(n), d / np.linalg.norm(n)


def _paper_fit(fd: _FrameData, forks: ForkGeometry, limits: Limits, where: str) -> tuple[SE3, dict]:
    n, d, _ = _fit_floor(fd.floor, limits, where)  # n: floor normal (up) in camera coordinates
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


# -- public API ------------------------------------------------------------------------------------


def calibrate(
    frames: Sequence[FrameBundle],
    forks: ForkGeometry,
    method: Method = "model",
    limits: Limits = LIMITS,
    names: Sequence[str] | None = None,
) -> Calibration:
    """`T_forklift_camera` (lift height 0) from labelled RGB-D frames of the forks and the floor.

    `method` is `model` (default; several frames are fitted together) or `paper` (uses the first
    frame only, as the paper does). Raises `CalibrationError` naming the frame and the reason.
    """
    if method not in METHODS:
        raise CalibrationError(f"unknown calibration method '{method}' (known: {', '.join(METHODS)})")
    if not frames:
        raise CalibrationError("no frames to calibrate from")
    names = list(names) if names is not None else [f"frame {i}" for i in range(len(frames))]
    t0 = time.perf_counter()
    data = [_frame_data(f, n, limits) for f, n in zip(frames, names, strict=True)]
    where = names[0] if len(names) == 1 else f"{len(names)} frames"
    if method == "paper":
        T, quality = _paper_fit(data[0], forks, limits, names[0])
        used = 1
    else:
        T, quality = _model_fit(data, forks, limits, where)
        used = len(data)
    quality = {k: (round(v, 6) if isinstance(v, float) else v) for k, v in quality.items()}
    quality["frames_used"] = used
    quality["runtime_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
    return Calibration(T, method, quality)


class Calibrator:
    """Calibrates on demand and keeps the last good calibration when a new one fails."""

    def __init__(self, forks: ForkGeometry, method: Method = "model", initial: Calibration | None = None) -> None:
        self.forks = forks
        self.method = method
        self.last_good: Calibration | None = initial

    def calibrate(self, frames: Sequence[FrameBundle]) -> Calibration:
        """A new calibration; on `CalibrationError` the last good one stays in `last_good` and the error is raised."""
        result = calibrate(frames, self.forks, self.method)
        self.last_good = result
        return result
