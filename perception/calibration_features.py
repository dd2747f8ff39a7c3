"""The calibration's evidence from each frame: floor and fork points, depth edges, and the forks' edge rays.

Package-internal (`perception.calibration` fits the camera pose to it):
- `_FrameData`, `_frame_data`: one frame's floor and fork points (camera frame), its depth-edge mask
  (mixed and flying pixels at depth jumps) and inverse intrinsics;
- `_ransac_plane`: a seeded, reproducible RANSAC plane (open3d);
- `_fit_floor`: the floor plane (RANSAC, refined) in the camera frame;
- `_fork_distance`: how far points (forklift frame) lie outside the blades' volume;
- `_Edges`, `_edge_rays`: camera-frame rays through the forks' depth edges against the floor (the tips,
  and the outer sides), found by scanning the depth image with the current pose;
- `_tip_offsets`: where tip-edge rays graze the blade's profile, relative to the tips;
- `_depth_tolerance`: a D435's depth spread at a z-depth; `_hit_plane`: rays onto a horizontal plane.

Frames: camera optical frame (x right, y down, z forward) for points and rays; forklift frame at lift
height 0 (`T`: `T_forklift_camera`) where a pose is given. Metres.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TYPE_CHECKING

import cv2
import numpy as np
import open3d as o3d

from palletpilot.geometry import SE3
from palletpilot.perception.errors import CalibrationError
from palletpilot.perception.frames import FrameBundle, SemanticClass
from palletpilot.perception.pointcloud import check_intrinsics, class_mask, deproject, depth_edges
from palletpilot.perception.specs import ForkGeometry

if TYPE_CHECKING:
    from palletpilot.perception.calibration import Limits

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
    edge = depth_edges(frame.depth, limits.depth_edge_jump, no_data_is_edge=True)
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


def _ransac_plane(points: np.ndarray, threshold: float, iterations: int = 200) -> tuple[np.ndarray, float]:
    """RANSAC plane `n . p + d = 0` through `points` (N x 3, any frame): unit normal `n` and offset `d` (m).

    Reproducible: the same points give the same plane, bit for bit. open3d's RANSAC runs its iterations on
    several threads and, with its default `probability` < 1, stops as soon as enough of them have run, so
    which samples were tried depended on thread timing (two or three different planes from one point set
    in a process). With `probability` 1 every one of the `iterations` seeded samples is tried.
    """
    pcd = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points))
    o3d.utility.random.seed(_RNG_SEED)
    (a, b, c, d), _ = pcd.segment_plane(threshold, 3, iterations, probability=1.0)
    norm = math.sqrt(a * a + b * b + c * c)
    return np.array([a, b, c]) / norm, d / norm


def _fit_floor(points: np.ndarray, limits: Limits, where: str) -> tuple[np.ndarray, float, np.ndarray]:
    """RANSAC plane, refined by least squares on its inliers: unit normal (towards the camera), offset, inliers.

    The plane is `n . p = -d` with `d` > 0 the camera's distance to the floor.
    """
    rng = np.random.default_rng(_RNG_SEED)
    sample = points if len(points) <= 20000 else points[rng.choice(len(points), 20000, replace=False)]
    n0, d0 = _ransac_plane(sample, limits.ransac_threshold)
    inl = np.abs(points @ n0 + d0) < limits.ransac_threshold  # inliers of the whole set
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
    """Distance (m) of points (forklift frame at lift 0) to the nearer fork's surfaces (the file's profile).

    The forks mirror each other about y = 0, so y folds onto one fork: |y| - centre_y. The fork is
    open towards the back (the heels are out of view and the carriage is not a fork). The top and
    bottom faces follow the blade profile (`ForkGeometry.top_z`, `bottom_z`: a taper, the heel fillet);
    a sloping face's distance is its vertical offset times the cosine of its slope.
    """
    half_w = 0.5 * forks.width
    dy = np.abs(np.abs(q[:, 1]) - forks.centre_y) - half_w  # > 0 outside the fork sideways
    top, bottom = forks.top_z(q[:, 0]), forks.bottom_z(q[:, 0])
    if forks.tapered:
        slope = (forks.thickness - forks.tip_top_z + float(forks.bottom_z(forks.tip_x))) / forks.taper_length
        in_taper = q[:, 0] > forks.taper_start_x
        cos = 1.0 / math.sqrt(1.0 + slope * slope)
        top_cos = np.where(in_taper & (forks.taper_side == "top"), cos, 1.0)
        bottom_cos = np.where(in_taper & (forks.taper_side == "bottom"), cos, 1.0)
    else:
        top_cos = bottom_cos = np.ones(len(q))
    dz = np.maximum((q[:, 2] - top) * top_cos, (bottom - q[:, 2]) * bottom_cos)  # > 0 above or below
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


def _edge_rays(
    data: _FrameData, T: SE3, forks: ForkGeometry, full_x: float, tip_window: float = 0.04, settled: bool = False
) -> _Edges:
    """Rays through the forks' depth edges against the floor, found by scanning the depth image.

    A fork ends where the camera starts to see beyond it (the floor, lower): at the tips, scanning up
    each column, and along the outer sides, scanning sideways along each row. A pixel is on the fork
    when it sees something clearly above the floor within the fork's footprint, at any height: a
    tapered tip is as good as a full-thickness one. The edge lies between the last pixel on the fork
    and the first pixel on the floor; pixels matching neither (mixed, flying, no data) in between count
    as unknown. The ray through the middle of that interval (at most 4 px) has no quantisation bias.
    Edge rays are then placed on the forks under the current estimate `T` (forklift frame at lift 0):
    tips where the ray grazes the blade's profile (`_tip_offsets`) within `tip_window` (m) of it;
    outer sides on the full-thickness top face, behind `full_x`.
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
    with np.errstate(divide="ignore", invalid="ignore"):
        s_floor = (-data.frame.fork_height - t[2]) / along_up  # z-depth of the floor along each ray
    s_floor[~(s_floor > 0)] = np.inf
    z = depth[rows, cols]
    valid = np.isfinite(z) & (z > 0)
    floor_ok = np.isfinite(s_floor)
    tol = _depth_tolerance(np.where(floor_ok, s_floor, 0.0))
    beyond = valid & floor_ok & (np.abs(z - s_floor) < tol)  # on the floor
    above = valid & ~beyond & (~floor_ok | (z < s_floor - tol))  # nearer than the floor: something on it
    q = (rays * np.where(valid, z, 0.0)[:, None]) @ R.T + t  # the pixel's own point (noisy depth)
    margin = 0.03 + 2.0 * _depth_tolerance(np.where(valid, z, 0.0)) / 3.0
    near_forks = np.abs(np.abs(q[:, 1]) - forks.centre_y) < 0.5 * forks.width + margin
    near_forks &= (q[:, 0] > forks.heel_x) & (q[:, 0] < forks.tip_x + tip_window + margin)
    near_forks &= q[:, 2] < forks.thickness + forks.heel_radius + margin
    fg = above & near_forks
    if settled:  # `T` is close: a pixel at a depth jump counts as fork only on the blade's top face
        # Stereo gives mixed depths at a depth jump, on both sides of it. One between the floor and the
        # blade is neither: it is unknown on either side alike, so the edge interval keeps its midpoint.
        # (Counting it as fork wherever it is above the floor moves the tips ~half a pixel away on
        # average, as the floor test is a narrow band and "above the floor" a wide one.)
        at_jump = data.edge[rows, cols]
        tol_h = np.abs(along_up) * tol  # the depth tolerance as height
        tol_x = np.abs(rays @ R[0]) * tol  # and along the blade
        on_top = np.abs(q[:, 2] - forks.top_z(np.clip(q[:, 0], forks.heel_x, forks.tip_x))) < tol_h
        on_top &= q[:, 0] < forks.tip_x + tip_window + tol_x
        fg &= on_top | ~at_jump
        above &= fg | ~at_jump
    # Codes: 0 unknown (also everywhere off the band), 1 on a fork, 2 floor, 3 something else above the floor.
    code = np.zeros(shape, np.int8)
    code[rows, cols] = np.where(fg, 1, np.where(beyond, 2, np.where(above, 3, 0)))
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
    half_w, margin_y = 0.5 * forks.width, 0.012
    off, y_tip = _tip_offsets(vertical, T, forks)
    tip = (np.abs(off) < tip_window) & (np.abs(np.abs(y_tip) - forks.centre_y) < half_w - margin_y)
    ps = _hit_plane(sideways, T, forks.thickness)
    outer = forks.centre_y + half_w
    side = (np.abs(np.abs(ps[:, 1]) - outer) < 0.02) & (ps[:, 0] < min(full_x, forks.tip_x - 0.03))
    side &= ps[:, 0] > forks.heel_x + forks.heel_radius
    return _Edges(vertical[tip], sideways[side], np.sign(ps[side, 1]))


def _hit_plane(rays: np.ndarray, T: SE3, z_plane: float) -> np.ndarray:
    """Points (forklift frame at lift 0) where camera rays meet the horizontal plane z = z_plane."""
    d = rays @ T.R.T
    s = (z_plane - T.t[2]) / d[:, 2]
    return T.t + d * s[:, None]


def _tip_offsets(rays: np.ndarray, T: SE3, forks: ForkGeometry) -> tuple[np.ndarray, np.ndarray]:
    """How far (m, along x) each tip edge ray passes beyond the blade's profile, and y where it touches it.

    The camera sees the blade end where a ray grazes the blade's roof: the top edge of the tip, or, on
    a blade whose top face slopes away faster than the camera looks down, the start of the taper.
    The roof is convex, so the ray touches it at one of its corners: the offset is the smallest
    `x_ray(z_v) - x_v` over the corners v (0 for a ray through the edge; > 0 passes beyond).
    """
    d = rays @ T.R.T
    c = T.t
    corners = [(forks.tip_x, forks.tip_top_z)]
    if forks.tapered and forks.taper_side == "top":
        corners.append((forks.taper_start_x, forks.thickness))
    best = np.full(len(rays), np.inf)
    y = np.zeros(len(rays))
    for x_v, z_v in corners:
        s = (z_v - c[2]) / d[:, 2]
        off = c[0] + s * d[:, 0] - x_v
        better = off < best
        best = np.where(better, off, best)
        y = np.where(better, c[1] + s * d[:, 1], y)
    return best, y
