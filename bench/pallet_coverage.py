"""Does a pallet estimate's stated spread cover its error? Helpers of `bench pallet --families` (issue 37).

Frames (ARCHITECTURE.md): the spread (`perception.pallet.PalletSpread`) states 1-sigma x, y (m) in the
`forklift` frame and yaw (rad), so the errors it is judged against are taken in the forklift frame too:
lateral = y, longitudinal = x of `T_estimated.t - T_true.t`, yaw the difference of the yaws.

- `forklift_errors`: those three errors of one estimate.
- `coverage`: per axis, the share of errors within `COVERAGE_SIGMAS` stated sigmas (`coverage_2sigma`),
  the median of |error| / sigma and the mean stated sigma (mm or deg: a spread that covers by being
  needlessly wide shows there).
- `crop_frame`, `crop_box`, `crop_check`: an independent check of the spread that needs no ground truth:
  the estimate of a frame and that of its own 4:3 crop around the pallet (cutting `CROP_CUT` of the
  pallet's width off one side; K's principal point shifted) should disagree by no more than their
  stated sigmas allow.
"""

from __future__ import annotations

import dataclasses
import math
from collections.abc import Sequence
from typing import Any

import numpy as np

from palletpilot.geometry import SE3
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.pallet import PALLET_CLASSES, PalletEstimate, PalletNotFound, estimate_pallet
from palletpilot.perception.specs import PalletType

COVERAGE_SIGMAS = 2.0
"""An error is covered when it is within this many of its estimate's stated 1-sigmas."""
AXES = ("lateral", "longitudinal", "yaw")
CROP_CUT = 0.1
"""The crop cuts this share of the pallet's width in the image off its right side: a crop that keeps every
pixel the estimator uses gives the same estimate, which checks nothing (on the real 1280 x 720 frames of
issue 37 a 4:3 crop cut into the near pallet)."""
CROP_MARGIN_PX = 8
"""The crop keeps the principal point at least this far inside (a frame's K must have it in the image)."""


def forklift_errors(T_true: SE3, T_est: SE3) -> tuple[float, float, float]:
    """Lateral (y, m), longitudinal (x, m) and yaw (rad) error of an estimate in the forklift frame."""
    d = T_est.t - T_true.t
    dyaw = T_est.to_se2().yaw - T_true.to_se2().yaw
    return float(d[1]), float(d[0]), math.atan2(math.sin(dyaw), math.cos(dyaw))


def stated_sigmas(est: PalletEstimate) -> tuple[float, float, float]:
    """The estimate's stated 1-sigma lateral (y, m), longitudinal (x, m) and yaw (rad)."""
    sp = est.spread
    return sp.y_m, sp.x_m, sp.yaw_rad


def coverage(errors: Sequence[Sequence[float]], sigmas: Sequence[Sequence[float]]) -> dict[str, Any]:
    """Per axis (`AXES`): `coverage_2sigma`, the share of |error| <= `COVERAGE_SIGMAS` sigma,
    `median_error_over_sigma` and `mean_sigma` (the mean stated 1-sigma, mm for lateral and longitudinal,
    deg for yaw); None without errors. `errors` and `sigmas` are (lateral m, longitudinal m, yaw rad) per
    estimate, in the same order."""
    out: dict[str, Any] = {}
    e = np.abs(np.asarray(errors, float).reshape(-1, 3))
    s = np.maximum(np.asarray(sigmas, float).reshape(-1, 3), 1e-12)
    for k, axis in enumerate(AXES):
        if len(e) == 0:
            out[axis] = {"coverage_2sigma": None, "median_error_over_sigma": None, "mean_sigma": None}
            continue
        z = e[:, k] / s[:, k]
        unit = 180.0 / math.pi if axis == "yaw" else 1e3
        out[axis] = {
            "coverage_2sigma": round(float(np.mean(z <= COVERAGE_SIGMAS)), 4),
            "median_error_over_sigma": round(float(np.median(z)), 3),
            "mean_sigma": round(float(np.mean(s[:, k])) * unit, 4),
        }
    return out


def worst_coverage(cov: dict[str, Any]) -> float | None:
    """The smallest `coverage_2sigma` over the axes of a `coverage` result (None without any)."""
    values = [v["coverage_2sigma"] for v in cov.values() if v["coverage_2sigma"] is not None]
    return min(values) if values else None


def crop_frame(frame: FrameBundle, rows: slice, cols: slice) -> FrameBundle:
    """`frame` cut to `rows` x `cols`: depth, labels and RGB cropped, K's principal point shifted."""
    K = frame.K.copy()
    K[0, 2] -= cols.start
    K[1, 2] -= rows.start
    return dataclasses.replace(
        frame,
        depth=np.ascontiguousarray(frame.depth[rows, cols]),
        K=K,
        labels=None if frame.labels is None else np.ascontiguousarray(frame.labels[rows, cols]),
        rgb=None if frame.rgb is None else np.ascontiguousarray(frame.rgb[rows, cols]),
        truth={},
    )


def crop_box(frame: FrameBundle, cut: float = CROP_CUT) -> tuple[slice, slice]:
    """Rows and columns of a 4:3 crop of `frame` that cuts `cut` of the width of the pallet-labelled pixels'
    box off its side farther from the principal point and keeps the rest of the box and the principal
    point (`CROP_MARGIN_PX` inside), as far as the frame allows: wider than that where the box's rows and
    the principal point need the height."""
    h, w = frame.height, frame.width
    labels = frame.labels if frame.labels is not None else np.zeros((h, w), np.uint8)
    rr, cc = np.nonzero(np.isin(labels, PALLET_CLASSES))
    if not rr.size:
        return slice(0, h), slice(0, w)
    cx, cy = float(frame.K[0, 2]), float(frame.K[1, 2])
    m = CROP_MARGIN_PX
    r0, r1 = max(min(int(rr.min()), math.floor(cy) - m), 0), min(max(int(rr.max()) + 1, math.ceil(cy) + m), h)
    a, b = int(cc.min()), int(cc.max()) + 1
    need = math.ceil(4 / 3 * (r1 - r0))  # the width a 4:3 crop of those rows has
    if 0.5 * (a + b) >= cx:  # cut the right side, widen to the left
        c1 = round(b - cut * (b - a))
        c0 = max(min(a, math.floor(cx) - m, c1 - need), 0)
    else:
        c0 = round(a + cut * (b - a))
        c1 = min(max(b, math.ceil(cx) + m, c0 + need), w)
    ch = min(max(round(0.75 * (c1 - c0)), r1 - r0), h)
    top = int(np.clip(round(0.5 * (r0 + r1 - ch)), 0, h - ch))
    return slice(top, top + ch), slice(c0, c1)


def crop_check(
    frame: FrameBundle,
    calibration: Calibration,
    pallet: PalletType,
    full: PalletEstimate,
    box: tuple[slice, slice] | None = None,
    **estimate: Any,
) -> tuple[tuple[float, float, float], tuple[float, float, float]] | None:
    """The disagreement (lateral, longitudinal m, yaw rad; forklift frame) between `full`, the estimate of
    `frame`, and that of its crop (`box`, default `crop_box(frame)`), and the larger of the two stated
    sigmas per axis; None where the crop gives no estimate. `estimate`: more arguments of `estimate_pallet`
    (the labels mode, where the pallet should stand), as `full` was estimated."""
    try:
        cropped = estimate_pallet(crop_frame(frame, *(box or crop_box(frame))), calibration, pallet, **estimate)
    except PalletNotFound:
        return None
    diff = forklift_errors(full.T_forklift_pallet, cropped.T_forklift_pallet)
    sig = tuple(max(a, b) for a, b in zip(stated_sigmas(full), stated_sigmas(cropped), strict=True))
    return diff, (sig[0], sig[1], sig[2])


class Honesty:
    """What `bench pallet --families` collects per family to judge the stated spreads: per frame (the
    first round of each standpoint), per fused estimate and per crop check, errors and stated sigmas."""

    def __init__(self) -> None:
        self.frame_errors: list[tuple[float, float, float]] = []
        self.frame_sigmas: list[tuple[float, float, float]] = []
        self.fused_errors: list[tuple[float, float, float]] = []
        self.fused_sigmas: list[tuple[float, float, float]] = []
        self.crop_diffs: list[tuple[float, float, float]] = []
        self.crop_sigmas: list[tuple[float, float, float]] = []
        self.crop_misses = 0

    def add_frame(self, T_true: SE3, est: PalletEstimate) -> None:
        """A single frame's estimate (`T_true`: the true `T_forklift_pallet`)."""
        self.frame_errors.append(forklift_errors(T_true, est.T_forklift_pallet))
        self.frame_sigmas.append(stated_sigmas(est))

    def add_fused(self, T_true: SE3, est: PalletEstimate) -> None:
        """A standpoint's fused estimate."""
        self.fused_errors.append(forklift_errors(T_true, est.T_forklift_pallet))
        self.fused_sigmas.append(stated_sigmas(est))

    def add_crop(
        self,
        frame: FrameBundle,
        calibration: Calibration,
        pallet: PalletType,
        est: PalletEstimate,
        box: tuple[slice, slice] | None = None,
        **estimate: Any,
    ) -> None:
        """The crop check (`crop_check`) of a frame and its estimate."""
        got = crop_check(frame, calibration, pallet, est, box, **estimate)
        if got is None:
            self.crop_misses += 1
            return
        self.crop_diffs.append(got[0])
        self.crop_sigmas.append(got[1])

    def result(self) -> dict[str, Any]:
        """`per_frame`, `per_estimate` and `crop` coverages (`coverage`; for the crop the disagreement over
        the larger stated sigma, and the p95 disagreement in mm and deg), and `worst`: the smallest
        `coverage_2sigma` of the frames and fused estimates over the axes."""
        per_frame = coverage(self.frame_errors, self.frame_sigmas)
        per_estimate = coverage(self.fused_errors, self.fused_sigmas)
        d = np.abs(np.asarray(self.crop_diffs, float).reshape(-1, 3))
        crop: dict[str, Any] = {
            "checks": len(self.crop_diffs),
            "crop_not_found": self.crop_misses,
            **coverage(self.crop_diffs, self.crop_sigmas),
            "disagreement_p95": {
                "lateral_mm": round(float(np.percentile(d[:, 0], 95)) * 1e3, 2) if len(d) else None,
                "longitudinal_mm": round(float(np.percentile(d[:, 1], 95)) * 1e3, 2) if len(d) else None,
                "yaw_deg": round(math.degrees(float(np.percentile(d[:, 2], 95))), 3) if len(d) else None,
            },
        }
        worst = [w for w in (worst_coverage(per_frame), worst_coverage(per_estimate)) if w is not None]
        return {
            "per_frame": per_frame,
            "per_estimate": per_estimate,
            "crop": crop,
            "worst": min(worst) if worst else None,
        }
