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
    beyond it (the floor). The midpoint of that interval has no quantisation bias; pixels that are
    neither count as unknown and widen the interval instead of biasing it; once the tips are trusted,
    a last round counts a pixel at a depth jump (mixed, flying) as fork only on the blade's top face,
    so mixed pixels on both sides of the edge widen it alike;
  - points at depth discontinuities are left out of the surface fits, labelled points that sit on
    the wrong surface (fork labels bled onto the floor) are dropped by geometry, and a soft-L1 loss
    absorbs the rest;
  - several frames (also with raised forks, `fork_height` in the bundle) are fitted together; the
    result is always for lift height 0;
  - quality: residual RMS per kind, inlier counts, frames used. Missing features or residuals above
    limits raise `CalibrationError` with the reason. `Calibrator` keeps the last good calibration;
  - tips: `tip_trusted` false with a warning when fork pixels stand beyond the fitted tips (`_tip_check`),
    or when the forks file leaves the blade profile unknown and the camera looks down at the tips less
    steeply than a tapered top may slope, so that a taper would hide (`_tip_view_check`).
"""

from __future__ import annotations

import dataclasses
import math
import time
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Literal

import cv2
import numpy as np
from scipy.optimize import least_squares
from scipy.spatial.transform import Rotation

from palletpilot.geometry import SE3
from palletpilot.perception.calibration_features import (
    _RNG_SEED,
    _depth_tolerance,
    _edge_rays,
    _Edges,
    _fit_floor,
    _fork_distance,
    _frame_data,
    _FrameData,
    _hit_plane,
    _tip_offsets,
)
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.calibration_paper import paper_fit
from palletpilot.perception.distortion import undistort_bundle
from palletpilot.perception.errors import CalibrationError
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.geometry_labels import LabelsMode, calibration_labels
from palletpilot.perception.specs import ForkGeometry

Method = Literal["model", "paper"]
METHODS: tuple[Method, ...] = ("model", "paper")


@dataclass(frozen=True)
class Limits:
    """Thresholds of a usable calibration (m unless named otherwise)."""

    min_floor_points: int = 2000
    min_fork_points: int = 1500
    min_tip_edges: int = 8
    min_beyond_points: int = 9  # fork pixels beyond the fitted tips that make them untrusted (`_tip_check`)
    floor_rms: float = 0.010  # plus the stereo noise expected at the floor's median depth (raised forks)
    fork_rms: float = 0.008
    tip_rms: float = 0.010
    ransac_threshold: float = 0.008
    depth_edge_jump: float = 0.03  # relative depth jump in a 3x3 neighbourhood that marks a depth edge
    max_floor_depth: float = 3.0  # floor points farther than this (z-depth, m) are too noisy to use


LIMITS = Limits()
BEYOND_MIN_M, BEYOND_MAX_M = 0.02, 0.25
"""Fork pixels this far ahead of the fitted tips (m) mean that the tips cannot be trusted (`_tip_check`)."""
STEEPEST_TAPER_M = (0.05, 0.012)
"""(length, tip thickness) in m of the steepest top taper assumed when the forks file does not state the
profile: ISO 2328-like blades thin over their last 50-150 mm to a 12-25 mm tip (`_tip_view_check`)."""
GRAZING_MARGIN_DEG = 5.0
"""A sloping top face seen within this angle (deg) of grazing covers too few image rows to show beyond
the tips (`bench calibration`, taper_nominal: 8-13 pixels at 0.5-3 deg, about the noise of box blades)."""


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


def _model_fit(
    data: Sequence[_FrameData], forks: ForkGeometry, limits: Limits, where: str
) -> tuple[SE3, dict, list[str]]:
    """The `model` fit: the pose, the quality figures and warnings (`_tip_check`)."""
    rng = np.random.default_rng(_RNG_SEED)
    T0 = _initial_pose(data, forks, limits, where)

    def subsample(a: np.ndarray, n: int) -> np.ndarray:
        return a if len(a) <= n else a[rng.choice(len(a), n, replace=False)]

    floors = [subsample(fd.floor, 1500) for fd in data]
    lifts = [fd.frame.fork_height for fd in data]
    full_x = forks.taper_start_x - 0.01 if forks.tapered and forks.taper_side == "top" else forks.tip_x

    def fit_round(T: SE3, first: bool, settled: bool) -> tuple[SE3, list[np.ndarray], list[_Edges], dict]:
        """One robust fit of all six degrees of freedom to the evidence found under the estimate `T`."""
        # Evidence against the current estimate: forks near the model, tips from the depth image.
        fork_sets: list[np.ndarray] = []
        edge_sets: list[_Edges] = []
        for fd in data:
            q = T.apply(fd.forks)
            keep = _fork_distance(q, forks) < (0.03 if first else 0.01)
            keep &= q[:, 0] > forks.heel_x + forks.heel_radius + 0.01
            fork_sets.append(subsample(fd.forks[keep], 2000))
            edge_sets.append(_edge_rays(fd, T, forks, full_x, 0.3 if first else 0.03, settled))
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
                # Edge rays graze the blade's profile at the tips and meet the outer sides. The tips
                # count as one mean constraint on x, weighted by their number: the tip edge runs along
                # the pixel grid, so per-fork quantisation must not tilt the yaw (the sides set it).
                tip_x = _tip_offsets(edges.tips, Tx, forks)[0]
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
        return T, fork_sets, edge_sets, stats

    T, _, _, _ = fit_round(T0, True, False)
    T, fork_sets, edge_sets, stats = fit_round(T, False, False)
    quality, warnings = _quality(data, floors, lifts, fork_sets, edge_sets, T, forks, limits, where, stats)
    if quality.get("tip_trusted", True):
        # The tips are where the forks file says: once more with the mixed pixels at depth jumps set apart.
        try:
            T2, fork_sets2, edge_sets2, stats = fit_round(T, False, True)
            quality2, warnings2 = _quality(data, floors, lifts, fork_sets2, edge_sets2, T2, forks, limits, where, stats)
        except CalibrationError:  # too few edges left, or residuals above the limits: keep the fit as it was
            pass
        else:
            if quality2.get("tip_trusted", True):
                T, quality, warnings, edge_sets = T2, quality2, warnings2, edge_sets2
    _tip_view_check(edge_sets, T, forks, quality, warnings)
    return T, quality, warnings


def _quality(
    data: Sequence[_FrameData],
    floors: list[np.ndarray],
    lifts: list[float],
    fork_sets: list[np.ndarray],
    edge_sets: list[_Edges],
    T: SE3,
    forks: ForkGeometry,
    limits: Limits,
    where: str,
    stats: dict,
) -> tuple[dict, list[str]]:
    """The fit's quality figures and warnings; residuals above the limits raise `CalibrationError`."""
    floor_res = np.concatenate([T.apply(f)[:, 2] + lift for f, lift in zip(floors, lifts, strict=True)])
    fork_res = np.concatenate([_fork_distance(T.apply(f), forks) for f in fork_sets])
    tip_res = np.concatenate([_tip_offsets(e.tips, T, forks)[0] for e in edge_sets])

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
    warnings: list[str] = []
    quality.update(_tip_check(data, edge_sets, T, forks, limits, warnings))
    return quality, warnings


def _tip_check(
    data: Sequence[_FrameData],
    edge_sets: Sequence[_Edges],
    T: SE3,
    forks: ForkGeometry,
    limits: Limits,
    warnings: list[str],
) -> dict:
    """Does anything of the forks reach beyond the fitted tips? Then the tips cannot be trusted.

    A blade whose profile the file does not give (a taper stated as the nominal box) shows its
    full-thickness top face ending before the tip, and the camera may see nothing of the taper's top
    (it slopes away as steeply as the camera looks down); the thinner rest (its sloping top or the
    strip of its inner side face) still stands above the floor beyond where the fit put the tips.
    Counted: pixels clearly above the floor within the forks' footprint, `BEYOND_MIN_M` ..
    `BEYOND_MAX_M` ahead of the tips and at least 3 image rows off the tip edge in their column (mixed
    pixels along a tip edge lie within a row or two of it); depth-edge pixels count along the inner
    sides only (that strip is narrow; mixed pixels along the outer sides fly beyond the tips). A
    sloping top seen with the wrong tip height lands there as well: it lies lower than the file says,
    so its points map beyond the tips.
    """
    reach_all: list[np.ndarray] = []
    for fd, edges in zip(data, edge_sets, strict=True):
        if not len(edges.tips):
            continue
        uv = edges.tips @ fd.frame.K.T
        order = np.argsort(uv[:, 0])
        r0 = max(int(uv[:, 1].min()) - 80, 0)
        depth = fd.frame.depth[r0 : int(uv[:, 1].max()) + 60]
        valid = np.isfinite(depth) & (depth > 0)
        rows, cols = np.nonzero(valid)
        rows += r0
        # At least 3 rows off the tip edge in the pixel's column (mixed pixels lie within a row or two).
        off_edge = np.abs(rows - np.interp(cols, uv[order, 0], uv[order, 1])) >= 3.0
        rows, cols = rows[off_edge], cols[off_edge]
        mixed = fd.edge[rows, cols]
        rays = np.column_stack([cols, rows, np.ones(len(rows))]) @ fd.K_inv.T
        z = fd.frame.depth[rows, cols]
        q = T.apply(rays * z[:, None])
        ahead = q[:, 0] - forks.tip_x
        sel = (ahead > BEYOND_MIN_M) & (ahead < BEYOND_MAX_M)
        sel &= np.abs(np.abs(q[:, 1]) - forks.centre_y) < 0.5 * forks.width + 0.005
        # Depth-edge pixels only along the inner sides (mixed pixels along the outer sides fly beyond the tips).
        sel &= ~mixed | (np.abs(q[:, 1]) < forks.centre_y - 0.5 * forks.width + 0.006)
        # Above the floor by more than the depth noise (4 sigma of its vertical part), and not above the blade.
        d_up = np.abs((rays @ T.R.T)[:, 2]) / np.linalg.norm(rays, axis=1)
        height = q[:, 2] + fd.frame.fork_height
        sel &= (height > 1.35 * _depth_tolerance(z) * d_up + 0.002) & (q[:, 2] < forks.thickness + 0.01)
        reach_all.append(ahead[sel])
    ahead_all = np.concatenate(reach_all) if reach_all else np.zeros(0)
    n = len(ahead_all)
    out: dict = {"beyond_tip_points": n, "tip_trusted": True}
    if n < limits.min_beyond_points:
        return out
    reach = float(np.percentile(ahead_all, 90))
    out.update({"tip_trusted": False, "beyond_tip_reach_m": reach})
    warnings.append(
        f"fork tips cannot be trusted: {n} pixels of the forks stand above the floor up to about "
        f"{reach * 1e3:.0f} mm beyond where the fit put the tips. The blades' top face ends before their tips, "
        "as on a tapered blade whose profile the forks file does not give, so the camera's forward position x "
        "may be off by as much. Measure the blade profile near the tips (taper_length, tip_thickness, "
        "taper_side; `palletpilot forks measure FRAME.npz ... --forks FORKS.yaml --out NEW_FORKS.yaml` with "
        "frames at a few fork heights) and calibrate with that file"
    )
    return out


def _tip_view_deg(edge_sets: Sequence[_Edges], T: SE3) -> float | None:
    """How steeply (deg below the horizontal) the camera looks down at the fork tips; None without tip edges.

    The median over the tip edge rays of their descent along the forks, `atan(-dz / dx)` of the ray
    direction in the forklift frame (x forward, z up): a top face that slopes down to the tip more
    steeply than this faces away from the camera.
    """
    rays = [e.tips for e in edge_sets if len(e.tips)]
    if not rays:
        return None
    d = np.vstack(rays) @ T.R.T
    return float(np.degrees(np.median(np.arctan2(-d[:, 2], d[:, 0]))))


def _tip_view_check(
    edge_sets: Sequence[_Edges], T: SE3, forks: ForkGeometry, quality: dict, warnings: list[str]
) -> None:
    """Could the frames have shown a tapered top face? If not and the forks file does not say, the tips are unverified.

    A top face that slopes down to the tip more steeply than the camera looks down at it (`_tip_view_deg`)
    faces away from the camera: the full-thickness top then ends where the taper starts, exactly as a box
    tip there would, and the ray grazing that edge passes over the thinner rest onto the same floor. Only
    the narrow strip of the blades' inner side faces differs, a few pixels per fork, no more than the
    noise along a box tip (`_tip_check` counts them, but cannot rely on them). So when the file leaves the
    profile unknown (`ForkGeometry.profile_stated`) and the view at the tips is shallower than the
    steepest taper assumed (`STEEPEST_TAPER_M` on this blade thickness) plus `GRAZING_MARGIN_DEG`, the
    tips are not trusted and a warning names the angles and what to measure. Adds `tip_view_deg` (and
    `tip_view_needed_deg` when it applies) to `quality`; a fit already untrusted is left as it is.
    """
    view = _tip_view_deg(edge_sets, T)
    if view is None:
        return
    quality["tip_view_deg"] = round(view, 2)
    if forks.profile_stated or not quality.get("tip_trusted", True):
        return
    length, tip = STEEPEST_TAPER_M
    slope = math.degrees(math.atan2(max(forks.thickness - tip, 0.0), length))
    needed = slope + GRAZING_MARGIN_DEG
    quality["tip_view_needed_deg"] = round(needed, 2)
    if view >= needed:
        return
    quality["tip_trusted"] = False
    warnings.append(
        f"fork tips cannot be verified: the camera looks down at the tips at {view:.0f} deg, and the forks file "
        f"does not state the blade profile. A top face tapering to the tip more steeply than that (ISO 2328-like "
        f"blades slope up to about {slope:.0f} deg over the last {length * 1e3:.0f}-150 mm) faces away from the "
        "camera and looks like a box tip where the taper starts, so the camera's forward position x may be off by "
        "the taper's length (50-150 mm). Measure the blade profile near the tips (taper_length, tip_thickness, "
        "taper_side: with a ruler, or `palletpilot forks measure FRAME.npz ... --forks FORKS.yaml --out "
        f"NEW_FORKS.yaml` from a mount looking down at the tips at more than {needed:.0f} deg) and calibrate with "
        "that file, or, after checking that the blades are plain boxes to the tip, state `taper_length: 0` in "
        "the forks file"
    )


# -- method `paper` ---------------------------------------------------------------------------------


# -- public API ------------------------------------------------------------------------------------


def calibrate(
    frames: Sequence[FrameBundle],
    forks: ForkGeometry,
    method: Method = "model",
    limits: Limits = LIMITS,
    names: Sequence[str] | None = None,
    labels: LabelsMode = LabelsMode.MODEL,
) -> Calibration:
    """`T_forklift_camera` (lift height 0) from RGB-D frames of the forks and the floor.

    `method` is `model` (default; several frames are fitted together) or `paper` (uses the first
    frame only, as the paper does). `labels` selects the floor and fork pixels
    (`perception.geometry_labels.calibration_labels`): the frames' own labels (`model`, the default
    here), depth alone (`geometry`) or depth with the model's hints (`fused`, the commands' default).
    Raises `CalibrationError` naming the frame and the reason.
    """
    if method not in METHODS:
        raise CalibrationError(f"unknown calibration method '{method}' (known: {', '.join(METHODS)})")
    if not frames:
        raise CalibrationError("no frames to calibrate from")
    names = list(names) if names is not None else [f"frame {i}" for i in range(len(frames))]
    t0 = time.perf_counter()
    frames = [undistort_bundle(f) for f in frames]  # an ideal pinhole image: every ray from K alone
    if labels != LabelsMode.MODEL:
        frames = [
            dataclasses.replace(f, labels=calibration_labels(f, forks, labels, n))
            for f, n in zip(frames, names, strict=True)
        ]
    data = [_frame_data(f, n, limits) for f, n in zip(frames, names, strict=True)]
    where = names[0] if len(names) == 1 else f"{len(names)} frames"
    warnings: list[str] = []
    if method == "paper":
        n, d, _ = _fit_floor(data[0].floor, limits, names[0])  # floor normal (up) in camera coordinates
        T, quality = paper_fit(data[0], (n, d), forks, limits, names[0])
        used = 1
    else:
        T, quality, warnings = _model_fit(data, forks, limits, where)
        used = len(data)
    quality = {k: (round(v, 6) if isinstance(v, float) else v) for k, v in quality.items()}
    quality["frames_used"] = used
    quality["runtime_ms"] = round((time.perf_counter() - t0) * 1e3, 1)
    return Calibration(T, method, quality, tuple(warnings))


class Calibrator:
    """Calibrates on demand and keeps the last good calibration when a new one fails."""

    def __init__(
        self,
        forks: ForkGeometry,
        method: Method = "model",
        initial: Calibration | None = None,
        labels: LabelsMode = LabelsMode.MODEL,
    ) -> None:
        self.forks = forks
        self.method = method
        self.labels = labels
        self.last_good: Calibration | None = initial

    def calibrate(self, frames: Sequence[FrameBundle]) -> Calibration:
        """A new calibration; on `CalibrationError` the last good one stays in `last_good` and the error is raised."""
        result = calibrate(frames, self.forks, self.method, labels=self.labels)
        self.last_good = result
        return result
