"""The fork blades' profile near the tips, measured in RGB-D frames of the forks (`palletpilot forks measure`).

ISO 2328 blades thin over their last 50-150 mm; a forks file that states only the nominal box makes
the calibration's tips untrustworthy (`perception.calibration`). This module measures the profile
from labelled frames of the forks over the open floor and a camera pose (a calibration, or one made
from the same frames):

- the top face: fork points inside each fork's footprint (1 cm in from its sides), binned along x
  (`BIN_M`); the median height per bin is the top face (the depth noise is symmetric, so the median
  is unbiased). The full-thickness top ends where that height first falls `DROP_M` below `thickness`;
- the sloping top: a line through the median heights of the bins beyond that; it meets the full
  thickness at the taper's start;
- the blade's end: the depth edges where the blades end against the floor (`perception.calibration`),
  each camera ray through one meeting the sloping top there (rays, not noisy depth, place the end);
  the tip thickness is the line's height at the end. A taper whose top slopes away from the camera
  faster than the camera looks down is not seen: the command says so (tilt the camera further down);
- a bottom taper (top flat to the tip): the inner side face's lowest points rise towards the tip;
  only visible with the forks raised over the floor (`fork_height` >= `RAISED_M` in the bundle).

Lengths along x are measured from the end of the full-thickness top, so an error of the camera's
forward position (a calibration made with the nominal box) cancels out.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass, field

import cv2
import numpy as np

from palletpilot.geometry import SE3
from palletpilot.perception.distortion import undistort_bundle
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle, SemanticClass
from palletpilot.perception.specs import ForkGeometry

BIN_M = 0.005
"""Bin width (m) along x."""
DROP_M = 0.003
"""The top face is below full thickness when it lies this much (m) lower."""
MIN_TAPER_M = 0.012
"""A shorter thinning (m) is a chamfer, not a taper: the profile stays a box."""
RAISED_M = 0.05
"""Frames with the forks at least this high (m) show the blades' bottom edges against the floor."""
SEARCH_M = 0.35
"""The profile is looked for this far (m) behind and ahead of the file's tips."""


class ProfileError(PerceptionError):
    """The frames do not show enough of the blades near the tips to measure their profile."""


@dataclass
class ProfileMeasurement:
    """The measured profile (m) and how it was found."""

    taper_length: float
    tip_thickness: float
    taper_side: str
    full_end_x: float  # x where the full-thickness top ends (camera frame estimate)
    end_x: float  # x of the blade's end (same estimate)
    points: int
    notes: list[str] = field(default_factory=list)

    @property
    def tapered(self) -> bool:
        """True when the blade thins towards the tip."""
        return self.taper_length > 0.0

    def to_json(self) -> dict:
        """Figures in mm for the CLI."""
        return {
            "taper_length_mm": round(self.taper_length * 1e3, 1),
            "tip_thickness_mm": round(self.tip_thickness * 1e3, 1),
            "taper_side": self.taper_side,
            "points": self.points,
            "notes": self.notes,
        }

    def apply(self, forks: ForkGeometry) -> ForkGeometry:
        """`forks` with this profile (validated: out-of-range values raise `pydantic.ValidationError`)."""
        doc = forks.model_dump()
        if self.tapered:
            doc.update(
                taper_length=round(self.taper_length, 4),
                tip_thickness=round(min(self.tip_thickness, forks.thickness), 4),
                taper_side=self.taper_side,
            )
        else:
            doc.update(taper_length=0.0, tip_thickness=None, taper_side="top")
        return ForkGeometry.model_validate(doc)


def _points(frame: FrameBundle, T: SE3, forks: ForkGeometry) -> np.ndarray:
    """Points (forklift frame at lift 0) of the pixels near the fork labels that stand above the floor."""
    if frame.labels is None:
        raise ProfileError("the frame has no labels (segment the RGB first)")
    labels = (frame.labels == SemanticClass.FORKS).astype(np.uint8)
    near = cv2.dilate(labels, np.ones((7, 7), np.uint8)) > 0
    depth = frame.depth
    valid = near & np.isfinite(depth) & (depth > 0)
    rows, cols = np.nonzero(valid)
    rays = np.column_stack([cols, rows, np.ones(len(rows))]) @ np.linalg.inv(frame.K).T
    z = depth[rows, cols]
    q = T.apply(rays * z[:, None])
    sigma = 0.0042 * z * z  # D435 stereo depth noise (m) at 640x480, along the ray
    up = np.abs((rays @ T.R.T)[:, 2]) / np.linalg.norm(rays, axis=1)
    height = q[:, 2] + frame.fork_height  # above the floor
    keep = height > 3.0 * sigma * up + 0.002
    keep &= np.abs(np.abs(q[:, 1]) - forks.centre_y) < 0.5 * forks.width + 0.006
    keep &= np.abs(q[:, 0] - forks.tip_x) < SEARCH_M
    # Depth-edge pixels (mixed, flying) are flagged: they serve for the blades' extent only.
    d = np.where(np.isfinite(depth) & (depth > 0), depth, 0.0).astype(np.float32)
    kernel = np.ones((3, 3), np.uint8)
    d_min = cv2.erode(np.where(d > 0, d, np.float32(1e6)), kernel)
    edge = (cv2.dilate(d, kernel) > d_min * 1.06)[rows, cols]
    return np.column_stack([q[keep], np.full(int(keep.sum()), frame.fork_height), edge[keep]])


def _tip_rays(frames: Sequence[FrameBundle], T: SE3, forks: ForkGeometry) -> list[np.ndarray]:
    """Camera rays through the blades' far ends (depth edges against the floor), per frame."""
    from palletpilot.perception.calibration import LIMITS
    from palletpilot.perception.calibration_features import _edge_rays, _frame_data

    return [_edge_rays(_frame_data(f, "frame", LIMITS), T, forks, forks.tip_x, SEARCH_M).tips for f in frames]


def measure_profile(frames: Sequence[FrameBundle], forks: ForkGeometry, T_forklift_camera: SE3) -> ProfileMeasurement:
    """The blade profile near the tips from frames of the forks (see the module docstring); frames with lens
    distortion are undistorted first (`perception.distortion`)."""
    if not frames:
        raise ProfileError("no frames")
    frames = [undistort_bundle(f) for f in frames]
    T = T_forklift_camera
    pts = np.vstack([_points(f, T, forks) for f in frames])
    interior = np.abs(np.abs(pts[:, 1]) - forks.centre_y) < 0.5 * forks.width - 0.01
    top = pts[interior & (pts[:, 4] == 0) & (pts[:, 2] > -0.005) & (pts[:, 2] < forks.thickness + 0.02)]
    if len(top) < 200:
        raise ProfileError(f"too few fork-top points near the tips ({len(top)}): the tips must be in view")
    edges = np.arange(forks.tip_x - SEARCH_M, forks.tip_x + SEARCH_M + BIN_M, BIN_M)
    centres = 0.5 * (edges[1:] + edges[:-1])
    idx = np.digitize(top[:, 0], edges) - 1
    counts = np.bincount(idx[(idx >= 0) & (idx < len(centres))], minlength=len(centres))
    medians = np.full(len(centres), np.nan)
    for k in np.flatnonzero(counts >= 8):
        medians[k] = float(np.median(top[idx == k, 2]))
    full = medians >= forks.thickness - DROP_M
    if not full.any():
        raise ProfileError("no part of the fork tops is at the file's full thickness: check `thickness`")
    last_full = int(np.flatnonzero(full)[-1])
    notes: list[str] = []
    # The ends against the floor far below (forks raised): a thin tip on the floor is hard to tell from it.
    raised = [f for f in frames if f.fork_height >= RAISED_M] or list(frames)
    rays = np.vstack(_tip_rays(raised, T, forks))
    if len(rays) < 8:
        raise ProfileError(f"the blades' ends are not seen against the floor ({len(rays)} edge pixels)")
    d = rays @ T.R.T
    c = T.t
    # The top face as a hinge: full thickness up to x_start, then a straight slope (least squares
    # over the bins' medians, weighted by their counts; x_start searched bin by bin).
    fit = _hinge(centres, medians, counts, forks.thickness, last_full)
    if fit is not None:
        x_start, b = fit
        a = forks.thickness - b * x_start
        # Each end ray meets the sloping top at the blade's end.
        s_hit = (a + b * c[0] - c[2]) / (d[:, 2] - b * d[:, 0])
        x_end = c[0] + s_hit * d[:, 0]
        x_end = x_end[(x_end > x_start + MIN_TAPER_M) & (x_end < x_start + 0.4)]
        if len(x_end) >= 8:
            end = float(np.median(x_end))
            # The rays meet the slope at a shallow angle: 1 mm of height error moves the end by this much.
            look = float(np.median(np.abs(d[:, 2] / np.hypot(d[:, 0], d[:, 1]))))
            spread_mm = 1.0 / max(look + b, 1e-3)
            if spread_mm > 3.0:
                notes.append(
                    f"the camera looks down at the taper only {np.degrees(np.arctan(look) - np.arctan(-b)):.0f} deg "
                    f"more steeply than it slopes: its end is uncertain by about {spread_mm:.0f} mm per mm of height "
                    "error; tilt the camera further down (or raise it) for these frames"
                )
            tip = float(np.clip(a + b * end, 0.003, forks.thickness))
            return ProfileMeasurement(end - x_start, tip, "top", x_start, end, len(pts), notes)
    # No sloping top in view: the top is flat to the end (a box or a bottom taper), or slopes away
    # from the camera faster than it looks down (then the blade goes on beyond the top's end).
    full_end = float(edges[last_full + 1])
    x_flat = c[0] + (forks.thickness - c[2]) / d[:, 2] * d[:, 0]
    end = float(np.median(x_flat))
    beyond = (pts[:, 0] > end + 0.02) & (pts[:, 0] < end + 0.2)
    if beyond.sum() > 30:
        raise ProfileError(
            "the blades go on beyond the end of their top face, whose taper slopes away from the camera: "
            "tilt the camera further down (or raise it) for these frames, or measure taper_length and "
            "tip_thickness by hand"
        )
    taper_length, tip_thickness, side = 0.0, forks.thickness, "top"
    bottom = _bottom_taper(pts, forks, end, notes)
    if bottom is not None:
        taper_length, tip_thickness = bottom
        side = "bottom"
    else:
        notes.append("no taper seen: the blades keep their full thickness to the tips")
    return ProfileMeasurement(taper_length, tip_thickness, side, full_end, end, len(pts), notes)


def _hinge(
    centres: np.ndarray, medians: np.ndarray, counts: np.ndarray, thickness: float, last_full: int
) -> tuple[float, float] | None:
    """(x_start, slope) of the top face z = thickness + slope (x - x_start) beyond x_start, or None (flat)."""
    ok = np.isfinite(medians)
    ok[: max(last_full - int(0.2 / BIN_M), 0)] = False
    x, z, w = centres[ok], medians[ok], counts[ok].astype(float)
    if len(x) < 4:
        return None
    best: tuple[float, float, float] | None = None
    for x_s in np.arange(x[0], x[-1] - MIN_TAPER_M, 0.5 * BIN_M):
        u = np.maximum(x - x_s, 0.0)
        denom = float(np.sum(w * u * u))
        if denom <= 0.0:
            continue
        b = float(np.sum(w * u * (z - thickness)) / denom)
        sse = float(np.sum(w * (z - thickness - b * u) ** 2))
        if best is None or sse < best[0]:
            best = (sse, float(x_s), b)
    if best is None or best[2] > -0.02 or np.sum(z < thickness - DROP_M) < 2:
        return None
    return best[1], best[2]


def _bottom_taper(pts: np.ndarray, forks: ForkGeometry, end: float, notes: list[str]) -> tuple[float, float] | None:
    """(taper length, tip thickness) of a bottom taper from the inner side faces of raised forks, if any."""
    inner_y = forks.centre_y - 0.5 * forks.width
    raised = pts[:, 3] >= RAISED_M
    if not raised.any():
        notes.append(f"no frame with the forks raised ({RAISED_M:g} m or more): a bottom taper cannot be seen")
        return None
    strip = raised & (np.abs(np.abs(pts[:, 1]) - inner_y) < 0.006) & (pts[:, 2] < forks.thickness - 0.002)
    s = pts[strip]
    ref = s[(s[:, 0] < end - 0.2) & (s[:, 0] > end - SEARCH_M)]
    if len(ref) < 30:
        notes.append("too little of the inner side faces seen to check for a bottom taper")
        return None
    low_ref = float(np.percentile(ref[:, 2], 10))
    rise = []
    for x0 in np.arange(end - 0.2, end, 0.01):
        b = s[(s[:, 0] >= x0) & (s[:, 0] < x0 + 0.01)]
        rise.append(float(np.percentile(b[:, 2], 10)) - low_ref if len(b) >= 10 else math.nan)
    rise_a = np.array(rise)
    xs = np.arange(end - 0.2, end, 0.01) + 0.005
    ok = np.isfinite(rise_a)
    if ok.sum() < 5 or np.nanmax(rise_a[-5:]) < 0.005:
        return None
    start_i = np.flatnonzero(ok & (rise_a > 0.003))
    start = float(xs[start_i[0]]) - 0.005 if len(start_i) else end
    A = np.column_stack([np.ones(int(ok.sum())), np.maximum(xs[ok] - start, 0.0)])
    coef, *_ = np.linalg.lstsq(A, rise_a[ok], rcond=None)
    rise_tip = float(coef[0] + coef[1] * (end - start))
    return end - start, float(np.clip(forks.thickness - rise_tip, 0.003, forks.thickness))


def forks_yaml(forks: ForkGeometry, source: str) -> str:
    """A forks file (YAML) for `forks`, with a header naming where the profile came from."""
    lines = [
        "# Fork geometry of the ego forklift (metres); see README 'File formats' -> Forks.",
        f"# Blade profile measured by `palletpilot forks measure` from {source}.",
    ]
    for key, value in forks.model_dump().items():
        if value is None:
            continue
        lines.append(f"{key}: {value:.4f}".rstrip("0").rstrip(".") if isinstance(value, float) else f"{key}: {value}")
    return "\n".join(lines) + "\n"
