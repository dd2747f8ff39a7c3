"""Depth scale tare: measure a depth camera's scale error against a flat target at a known distance.

A stereo depth camera's depth is `f B / disparity`; a small error in its stereo calibration scales every
depth by the same factor `1 + s` (measured z = true z (1 + s); a D435 is typically within a few tenths
of a percent). The error is a property of the camera, not of its mount, and nothing a camera sees of
the forks and the floor reveals it: a scaled scene looks the same, only bigger. The camera calibration
would put the camera `s` times the fork-tip distance too far back (about 4 mm at 0.3 % and 1.3 m).
So it is measured once, the way Intel's tare calibration does it: the camera looks at a flat wall
whose distance from the camera's depth origin is measured with a laser distance meter.

`measure_depth_tare(frames, distance_m)`: in the central part of each frame (`roi`, a share of the
width and height) every valid depth pixel is one equation `1 / z = a x' + b y' + c`, with `x', y'` the
pixel's normalised image coordinates (exact) and `1 / z` proportional to the disparity (whose noise is
the same everywhere: the statistically right quantity to fit). A plane `n . p = d` seen by the camera
satisfies exactly that with `(a, b, c) = n / d`, so the plane's distance from the camera is
`1 / |(a, b, c)|`; a robust loop drops pixels off the plane (more than 4 robust sigmas of disparity).
`s = plane distance / measured distance - 1`. It refuses (`CalibrationError`, one line) a target that
does not fill the region, is not flat, is turned more than `max_wall_angle_deg` from the optical axis,
or gives an error beyond `max_scale_error` (a wrong distance, not a camera).

`DepthTare` records the result; `correct_depth(frame, tare)` removes the error from a frame (depth
divided by `1 + s`). The tare file (`save_tare` / `load_tare`, JSON, written atomically):

    {"depth_scale_error": 0.0021, "distance_m": 1.5, "plane_distance_m": 1.50315,
     "residual_disparity_rms": ..., "points": 76800, "frames": 3, "wall_angle_deg": 1.2,
     "depth_correlation_px": 6.3}

`depth_correlation_px` (optional, default 1) is not part of the tare: `palletpilot camera noise` measures it
from still frames (`perception.depth_noise`) and writes it into the same file, the camera's file.

Public API: `DepthTare`, `TareLimits`, `measure_depth_tare`, `correct_depth`, `save_tare`, `load_tare`.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import numpy as np
from pydantic import Field

from palletpilot.geometry.fileio import FileModel, parse_json, read_text, validate_model, write_json
from palletpilot.perception.distortion import undistort_bundle
from palletpilot.perception.errors import CalibrationError, PerceptionError
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.pointcloud import check_intrinsics

MAX_TARE_BYTES = 64 * 1024


@dataclass(frozen=True)
class TareLimits:
    """What a usable tare measurement must meet."""

    roi: float = 0.5
    """Share of the image width and height, centred, that must all be wall."""
    min_valid_share: float = 0.8
    """Share of the region's pixels that must have depth and lie on the plane."""
    max_wall_angle_deg: float = 20.0
    """Angle between the optical axis and the wall's normal."""
    max_scale_error: float = 0.03
    """Larger errors mean a wrong distance or a wrong target, not a camera (D400: well under 1 %)."""
    max_residual_rms_m: float = 0.02
    """RMS distance of the region's points from the plane, at 1 m (a flat target); it scales with the
    square of the distance, as stereo depth noise does."""
    min_distance_m: float = 0.5
    max_distance_m: float = 4.0


@dataclass(frozen=True)
class DepthTare:
    """A camera's measured depth scale error: measured z = true z (1 + `depth_scale_error`)."""

    depth_scale_error: float
    distance_m: float
    """The distance the user measured: depth origin to the wall, perpendicular (m)."""
    plane_distance_m: float
    """The wall's distance from the camera as the depth data put it (m)."""
    residual_rms_m: float
    """RMS distance of the used points from the fitted plane (m)."""
    points: int
    frames: int
    wall_angle_deg: float
    depth_correlation_px: float = 1.0
    """The depth noise's correlation area (pixels; `palletpilot camera noise`, `perception.depth_noise`): the
    pallet estimate's spread takes it (`PalletEstimatorConfig.depth_correlation_px`); 1 until measured."""

    @property
    def correction(self) -> float:
        """The factor that turns the camera's depth into true depth: 1 / (1 + s)."""
        return 1.0 / (1.0 + self.depth_scale_error)

    def to_json(self) -> dict[str, Any]:
        """The tare file's content."""
        return dataclasses.asdict(self)


class _TareFile(FileModel):
    """The schema of a tare file (module docstring)."""

    depth_scale_error: float = Field(ge=-0.05, le=0.05, description="measured z = true z (1 + s)")
    distance_m: float = Field(gt=0.0, le=20.0)
    plane_distance_m: float = Field(gt=0.0, le=20.0)
    residual_rms_m: float = Field(ge=0.0, le=1.0)
    points: int = Field(ge=0)
    frames: int = Field(ge=1)
    wall_angle_deg: float = Field(ge=0.0, le=90.0)
    depth_correlation_px: float = Field(1.0, ge=1.0, le=400.0, description="depth noise correlation area (px)")


def _region_rays(frame: FrameBundle, roi: float) -> tuple[np.ndarray, np.ndarray]:
    """(normalised image coordinates x', y', 1 as N x 3; z as N, 0 where no depth) of the central region."""
    h, w = frame.depth.shape
    r0, r1 = round(h * (1 - roi) / 2), round(h * (1 + roi) / 2)
    c0, c1 = round(w * (1 - roi) / 2), round(w * (1 + roi) / 2)
    rows, cols = np.mgrid[r0:r1, c0:c1]
    K = frame.K
    yn = (rows - K[1, 2]) / K[1, 1]
    xn = ((cols - K[0, 2]) - K[0, 1] * yn) / K[0, 0]
    rays = np.column_stack([xn.ravel(), yn.ravel(), np.ones(xn.size)])
    z = frame.depth[r0:r1, c0:c1].astype(np.float64).ravel()
    return rays, np.where(np.isfinite(z), z, 0.0)


def _fit_inverse_depth(rays: np.ndarray, inv_z: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Robust least squares of `inv_z = rays @ q`: (q, inlier mask); drops > 4 robust sigmas, 10 rounds."""
    keep = np.ones(len(inv_z), bool)
    q = np.zeros(3)
    for _ in range(10):
        q, *_ = np.linalg.lstsq(rays[keep], inv_z[keep], rcond=None)
        r = inv_z - rays @ q
        sigma = 1.4826 * float(np.median(np.abs(r[keep]))) + 1e-12
        new = np.abs(r) < 4.0 * sigma
        if np.array_equal(new, keep):
            break
        keep = new
    return q, keep


def measure_depth_tare(frames: Sequence[FrameBundle], distance_m: float, limits: TareLimits | None = None) -> DepthTare:
    """The camera's depth scale error from frames of a flat wall at `distance_m` (m, from the depth origin).

    The frames are in the camera's optical frame; the wall must fill the central `limits.roi` of each.
    Raises `CalibrationError` (one line) when the frames do not allow a trustworthy measurement.
    """
    limits = limits or TareLimits()
    if not frames:
        raise CalibrationError("depth tare: no frames")
    if not (limits.min_distance_m <= distance_m <= limits.max_distance_m):
        raise CalibrationError(
            f"depth tare: distance {distance_m:g} m outside {limits.min_distance_m:g}-{limits.max_distance_m:g} m"
        )
    all_rays, all_inv = [], []
    total = 0
    for i, frame in enumerate(frames):
        frame = undistort_bundle(frame)  # rays from K alone (`perception.distortion`)
        check_intrinsics(frame.K, f"frame {i}: K")
        rays, z = _region_rays(frame, limits.roi)
        total += len(z)
        ok = z > 0
        all_rays.append(rays[ok])
        all_inv.append(1.0 / z[ok])
    rays, inv_z = np.concatenate(all_rays), np.concatenate(all_inv)
    if len(inv_z) < limits.min_valid_share * total:
        raise CalibrationError(
            f"depth tare: only {len(inv_z) / max(total, 1):.0%} of the central region has depth "
            f"(at least {limits.min_valid_share:.0%}: the wall must fill the middle {limits.roi:.0%} of the image)"
        )
    q, keep = _fit_inverse_depth(rays, inv_z)
    used = int(np.count_nonzero(keep))
    if used < limits.min_valid_share * total:
        raise CalibrationError(
            f"depth tare: only {used / total:.0%} of the central region lies on one plane "
            f"(at least {limits.min_valid_share:.0%}: a flat wall, nothing in front of it)"
        )
    norm = float(np.linalg.norm(q))
    if not math.isfinite(norm) or norm <= 0.0:
        raise CalibrationError("depth tare: no plane fits the depth data")
    n = q / norm  # unit normal (towards the wall) in the camera frame
    plane_distance = 1.0 / norm
    angle = math.degrees(math.acos(min(1.0, abs(float(n[2])))))
    if angle > limits.max_wall_angle_deg:
        raise CalibrationError(
            f"depth tare: the wall is turned {angle:.1f} deg from the optical axis "
            f"(at most {limits.max_wall_angle_deg:g} deg: face it squarely)"
        )
    points = rays[keep] * (1.0 / inv_z[keep])[:, None]
    residual = float(np.sqrt(np.mean((points @ n - plane_distance) ** 2)))
    allowed = limits.max_residual_rms_m * max(1.0, plane_distance) ** 2
    if residual > allowed:
        raise CalibrationError(
            f"depth tare: the target is not flat (points {residual * 1e3:.1f} mm RMS off the plane, "
            f"at most {allowed * 1e3:.0f} mm at {plane_distance:.2f} m)"
        )
    s = plane_distance / distance_m - 1.0
    if abs(s) > limits.max_scale_error:
        raise CalibrationError(
            f"depth tare: the depth puts the wall at {plane_distance:.4f} m, {s:+.2%} off the measured "
            f"{distance_m:.4f} m (more than {limits.max_scale_error:.0%}: check the distance and the target)"
        )
    return DepthTare(
        depth_scale_error=float(s),
        distance_m=float(distance_m),
        plane_distance_m=plane_distance,
        residual_rms_m=residual,
        points=used,
        frames=len(frames),
        wall_angle_deg=angle,
    )


def correct_depth(frame: FrameBundle, tare: DepthTare | None) -> FrameBundle:
    """`frame` with the tare's depth scale error removed (depth / (1 + s)); the same frame without a tare."""
    if tare is None or tare.depth_scale_error == 0.0:
        return frame
    depth = (frame.depth * np.float32(tare.correction)).astype(frame.depth.dtype, copy=False)
    return dataclasses.replace(frame, depth=depth)


def save_tare(path: str | Path, tare: DepthTare) -> Path:
    """Write a tare file (JSON), atomically."""
    return write_json(path, tare.to_json())


def load_tare(path: str | Path) -> DepthTare:
    """Read and check a tare file; problems raise `PerceptionError`, one line naming the file and field."""
    path = Path(path)
    doc = parse_json(read_text(path, PerceptionError, MAX_TARE_BYTES), str(path), PerceptionError)
    model = validate_model(doc, _TareFile, str(path), PerceptionError)
    return DepthTare(**model.model_dump())
