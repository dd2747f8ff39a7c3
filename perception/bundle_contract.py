"""The frame bundle's data contract: its class ids, keys and limits, and the checks of every field.

Public API:
- `SemanticClass`: the ten class ids of the paper (255 = unlabeled).
- `BUNDLE_KEYS`, `TRUTH_SUFFIX`: the keys a bundle holds (truth keys end in `_true`).
- Limits: `MAX_IMAGE_SIDE`, `MAX_TRUTH_ELEMENTS`, `MAX_DEPTH_M`, `FOCAL_RANGE`, `PIXEL_ASPECT_RANGE`,
  `MAX_SKEW`, `FORK_HEIGHT_RANGE_M`, `FORK_HEIGHT_TOLERANCE_M`, `DIST_LENGTHS`, `MAX_RADIAL_COEFF`,
  `MAX_TANGENTIAL_COEFF`, `MAX_PRISM_COEFF`, `MAX_TILT_RAD`.
- Package-internal (`perception.frames`, `perception.bundle_archive`, `perception.distortion`):
  `_check_bundle` (every field of a bundle, in memory; one `_check_*` step per field), `_k_problems`,
  `_fork_height_problem`, `_image_shape_ok`, `_error` (one `PerceptionError` for many problem lines),
  `_radial_factor` and `_fold_radius` (the lens model's radial part).

`perception.frames` re-exports the public names; import them from there.

Frames: arrays in the camera's optical frame (x right, y down, z forward; `perception.frames`).

Every bundle is checked, however it was made (`FrameBundle.__post_init__`): dtypes and shapes, at
most `MAX_IMAGE_SIDE` pixels a side, all images of one size; depth finite metres (0 or NaN: no
reading) up to `MAX_DEPTH_M`, never negative or infinite; a pinhole K with positive focal lengths
plausible for the image (`FOCAL_RANGE`: fx 0.1 .. 20 times the width, fy likewise the height, nearly
square pixels), small skew and the principal point inside the image; known class ids only; a finite
fork height within `FORK_HEIGHT_RANGE_M`; optional lens distortion `dist` (OpenCV order, `DIST_LENGTHS`
coefficients, each finite and within its limit) whose radial mapping keeps growing out to the image's
farthest corner (a model that folds back inside the image maps two rays to one pixel: coefficients in
the wrong order or units, or not a lens of this image). Every problem is one line, `WHERE: KEY: problem` (`WHERE`
the file's path, or `FrameBundle` for a bundle built in memory), and every problem is reported
(`PerceptionError.problems`).

The fork height: perception cannot know the vehicle (it may not import `control`), so a bundle's
`fork_height` is checked against the generic `FORK_HEIGHT_RANGE_M` (no mast lifts its forks below the
floor or above 20 m); a caller that knows the truck passes its mast's range (`mast_range_m` of
`load_bundle` / `load_bundles`, e.g. `palletpilot estimate-pallet --vehicle V.yaml`).
"""

from __future__ import annotations

import math
from collections.abc import Mapping
from enum import IntEnum

import numpy as np

from palletpilot.perception.errors import PerceptionError


class SemanticClass(IntEnum):
    """The ten semantic classes of the paper, ids fixed, plus 255 for unlabeled pixels."""

    DRIVABLE = 0
    VERTICAL = 1
    OTHER_OBJECT = 2
    OTHER_FORKLIFT = 3
    OTHER_VEHICLE = 4
    FORKS = 5
    CARGO = 6
    PALLET_EMPTY = 7
    PALLET_FULL = 8
    PERSON = 9
    UNLABELED = 255


BUNDLE_KEYS = ("depth", "K", "labels", "rgb", "fork_height", "dist")
"""Keys a bundle file may hold besides truth keys (which end in `TRUTH_SUFFIX`)."""
TRUTH_SUFFIX = "_true"
_VALID_LABELS = np.array([int(c) for c in SemanticClass], dtype=np.uint8)
_MAX_CLASS_ID = int(SemanticClass.PERSON)

MAX_IMAGE_SIDE = 4096
"""The largest image side (px) of a bundle: a D435 streams at most 1920 x 1080."""
MAX_TRUTH_ELEMENTS = 4 * MAX_IMAGE_SIDE**2
"""The most elements of one truth array (image-sized truth such as `labels_true` fits)."""
MAX_DEPTH_M = 100.0
"""The farthest depth reading (m) taken as metres: a D435 sees about 10 m; millimetres (x 1000) stand out."""
FOCAL_RANGE = (0.1, 20.0)
"""fx within this many image widths, fy within this many image heights (fields of view about 3..157 deg)."""
PIXEL_ASPECT_RANGE = (0.5, 2.0)
"""fy / fx: a camera's pixels are nearly square."""
MAX_SKEW = 0.01
"""The largest skew K[0, 1] as a fraction of fx (about 0.6 deg between the pixel axes)."""
FORK_HEIGHT_RANGE_M = (0.0, 20.0)
"""The lift heights (m, fork bottoms above the floor) any mast reaches; a vehicle's own is narrower."""
FORK_HEIGHT_TOLERANCE_M = 0.02
"""A lift height reading may stray this far (m) outside a range (sensor noise at the floor)."""
DIST_LENGTHS = (4, 5, 8, 12, 14)
"""Lens distortion coefficient counts (OpenCV order): k1 k2 p1 p2 (4), + k3 (5, ROS `plumb_bob`), + k4 k5 k6
(8, ROS `rational_polynomial`), + s1 s2 s3 s4 thin prism (12), + tau_x tau_y sensor tilt (14, an OAK's)."""
MAX_RADIAL_COEFF = 1000.0
"""The largest |k1..k6|: rational models of wide lenses reach tens (their numerator and denominator nearly
cancel); what matters more is checked from the image (`_fold_radius`)."""
MAX_TANGENTIAL_COEFF = 0.1
"""The largest |p1|, |p2|: decentering of a real lens is about 0.001 (0.1 is a lens tilted by degrees)."""
MAX_PRISM_COEFF = 1.0
"""The largest |s1..s4| (thin prism terms, normalised image units)."""
MAX_TILT_RAD = 0.2
"""The largest |tau_x|, |tau_y| (rad): the sensor's tilt behind the lens, about 11 deg."""
_REACH = 6.0  # a lens model must bring a ray at most this many times the corner's radius to the image corner


def _error(problems: list[str], summary: str = "") -> PerceptionError:
    """One `PerceptionError` for several problem lines: its message is the first (with how many more)."""
    more = len(problems) - 1
    first = f"{summary}: {problems[0]}" if summary else problems[0]
    return PerceptionError(first + (f" (and {more} more problem{'s' if more > 1 else ''})" if more else ""), problems)


def _image_shape_ok(shape: tuple[int, ...]) -> bool:
    """True for (H, W) with 1 <= H, W <= MAX_IMAGE_SIDE."""
    return len(shape) == 2 and all(1 <= n <= MAX_IMAGE_SIDE for n in shape)


def _fork_height_problem(value: float, mast_range_m: tuple[float, float] | None) -> str | None:
    """Why a lift height (m) is not plausible, or None."""
    if not math.isfinite(value):
        return f"must be a finite number (m), got {value!r}"
    lo, hi = mast_range_m if mast_range_m is not None else FORK_HEIGHT_RANGE_M
    what = "the mast's range" if mast_range_m is not None else "any mast's range"
    if not lo - FORK_HEIGHT_TOLERANCE_M <= value <= hi + FORK_HEIGHT_TOLERANCE_M:
        return f"{value:.4g} m is outside {what} {lo:g}..{hi:g} m (lift height of the fork bottoms)"
    return None


def _radial_factor(dist: np.ndarray, r2: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """The radial part of an OpenCV lens model at squared ideal radii `r2` (normalised image units):
    (numerator 1 + k1 r2 + k2 r2^2 + k3 r2^3, denominator 1 + k4 r2 + k5 r2^2 + k6 r2^3)."""
    k = np.zeros(6)
    k[:2] = dist[:2]
    if len(dist) > 4:
        k[2] = dist[4]
    if len(dist) >= 8:
        k[3:6] = dist[5:8]
    num = 1.0 + r2 * (k[0] + r2 * (k[1] + r2 * k[2]))
    den = 1.0 + r2 * (k[3] + r2 * (k[4] + r2 * k[5]))
    return num, den


def _fold_radius(dist: np.ndarray, r_max: float, samples: int = 2000) -> tuple[float, np.ndarray, np.ndarray]:
    """Where the radial mapping r -> r * num / den stops growing (ideal normalised radius; inf when it grows
    on all of 0..`r_max`), with the sampled radii and their distorted radii (for callers that need more)."""
    r = np.linspace(0.0, r_max, samples)
    num, den = _radial_factor(dist, r * r)
    with np.errstate(divide="ignore", invalid="ignore"):
        rd = r * num / den
    bad = ~((den > 0) & (num > 0) & np.isfinite(rd))
    bad[1:] |= np.diff(rd) <= 0
    first = int(np.argmax(bad)) if bad.any() else -1
    return (float(r[max(first - 1, 0)]) if first >= 0 else math.inf), r, rd


def _k_problems(k: np.ndarray, shape: tuple[int, int] | None) -> list[str]:
    """Why a finite float64 3 x 3 K is not a plausible pinhole matrix for an H x W image (`shape`)."""
    fx, s, cx = (float(v) for v in k[0])
    fy, cy = float(k[1, 1]), float(k[1, 2])
    if not (fx > 0 and fy > 0) or not np.array_equal(k[2], [0.0, 0.0, 1.0]) or k[1, 0] != 0:
        return [f"is not a pinhole matrix [[fx, s, cx], [0, fy, cy], [0, 0, 1]] with fx, fy > 0: {k.tolist()}"]
    if shape is None:
        return []
    h, w = shape
    lo, hi = FOCAL_RANGE
    span = f"{lo:g}..{hi:g} x the"
    out = []
    if not lo * w <= fx <= hi * w:
        out.append(f"fx {fx:.6g} px is implausible for a {w} px wide image ({lo * w:g}..{hi * w:g} px: {span} width)")
    if not lo * h <= fy <= hi * h:
        out.append(f"fy {fy:.6g} px is implausible for a {h} px high image ({lo * h:g}..{hi * h:g} px: {span} height)")
    a_lo, a_hi = PIXEL_ASPECT_RANGE
    if not a_lo <= fy / fx <= a_hi:
        out.append(f"fy / fx = {fy / fx:.4g}: pixels that far from square are implausible ({a_lo:g}..{a_hi:g})")
    if abs(s) > MAX_SKEW * fx:
        out.append(f"skew K[0, 1] = {s:.6g} px is too large (at most {MAX_SKEW:g} fx = {MAX_SKEW * fx:.4g} px)")
    if not -0.5 <= cx <= w - 0.5:
        out.append(f"principal point cx {cx:.6g} px lies outside the {w} px wide image (-0.5..{w - 0.5:g})")
    if not -0.5 <= cy <= h - 0.5:
        out.append(f"principal point cy {cy:.6g} px lies outside the {h} px high image (-0.5..{h - 0.5:g})")
    return out


class _Report:
    """The problem lines of one bundle being checked: `WHERE: KEY: problem` each."""

    def __init__(self, where: str) -> None:
        self.where = where
        self.problems: list[str] = []

    def bad(self, key: str, problem: str) -> None:
        self.problems.append(f"{self.where}: {key}: {problem}")

    def array(self, key: str, value: object) -> np.ndarray | None:
        if not isinstance(value, np.ndarray):
            self.bad(key, f"expected a numpy array, got {type(value).__name__}")
            return None
        return value


def _check_bundle(
    depth: object,
    K: object,
    labels: object,
    rgb: object,
    fork_height: object,
    truth: Mapping[str, object],
    where: str,
    mast_range_m: tuple[float, float] | None = None,
    dist: object = None,
) -> None:
    """Raise `PerceptionError` with one line (`where: key: problem`) per entry that breaks the contract."""
    report = _Report(where)
    shape = _check_depth(report, depth)
    k_ok = _check_k(report, K, shape)
    _check_images(report, labels, rgb, shape)
    _check_fork_height(report, fork_height, mast_range_m)
    _check_truth(report, truth)
    if dist is not None:
        _check_dist(report, dist, K if k_ok and shape is not None else None, shape)
    if report.problems:
        raise _error(report.problems)


def _check_depth(report: _Report, depth: object) -> tuple[int, int] | None:
    """Check the depth image; return its (H, W) when its dtype and shape are right (else None)."""
    shape: tuple[int, int] | None = None
    d = report.array("depth", depth)
    if d is not None:
        if d.dtype != np.float32:
            report.bad("depth", f"dtype must be float32 (metres), got {d.dtype}")
        elif not _image_shape_ok(d.shape):
            report.bad("depth", f"shape must be (H, W) with 1..{MAX_IMAGE_SIDE} px a side, got {d.shape}")
        else:
            shape = (int(d.shape[0]), int(d.shape[1]))
            lo = float(np.fmin.reduce(d, axis=None))  # NaN (no data) is skipped; all NaN gives NaN
            hi = float(np.fmax.reduce(d, axis=None))
            if math.isinf(lo) or math.isinf(hi):
                report.bad("depth", "contains inf (use 0 or NaN for no data)")
            elif lo < 0:
                report.bad("depth", f"contains negative depths (min {lo:.4g} m; use 0 or NaN for no data)")
            elif hi > MAX_DEPTH_M:
                report.bad(
                    "depth",
                    f"readings up to {hi:.4g} m, beyond {MAX_DEPTH_M:g} m: depth must be in metres "
                    "(millimetres divided by 1000)",
                )
    return shape


def _check_k(report: _Report, K: object, shape: tuple[int, int] | None) -> bool:
    """Check K, against the image size `shape` when known; whether it passed."""
    before = len(report.problems)
    k = report.array("K", K)
    if k is not None:
        if k.dtype != np.float64:
            report.bad("K", f"dtype must be float64, got {k.dtype}")
        elif k.shape != (3, 3):
            report.bad("K", f"shape must be (3, 3), got {k.shape}")
        elif not np.all(np.isfinite(k)):
            report.bad("K", "has non-finite entries (NaN or inf)")
        else:
            for problem in _k_problems(k, shape):
                report.bad("K", problem)
    return k is not None and len(report.problems) == before


def _check_dist(report: _Report, dist: object, K: object, shape: tuple[int, int] | None) -> None:
    """Check the lens distortion coefficients; with a good K and the image size, also that the lens model
    keeps growing out to the image's farthest corner (else two rays land on one pixel)."""
    d = report.array("dist", dist)
    if d is None:
        return
    lengths = ", ".join(map(str, DIST_LENGTHS[:-1])) + f" or {DIST_LENGTHS[-1]}"
    if d.dtype != np.float64 or d.ndim != 1 or len(d) not in DIST_LENGTHS:
        report.bad(
            "dist",
            f"must be a float64 vector of {lengths} OpenCV coefficients (k1, k2, p1, p2[, k3[, k4, k5, k6"
            f"[, s1, s2, s3, s4[, tau_x, tau_y]]]]), got shape {d.shape} dtype {d.dtype}",
        )
        return
    if not np.all(np.isfinite(d)):
        report.bad("dist", f"has non-finite coefficients (NaN or inf): {d.tolist()}")
        return
    groups = (
        ("k1..k6", [0, 1, 4, 5, 6, 7], MAX_RADIAL_COEFF),
        ("p1, p2", [2, 3], MAX_TANGENTIAL_COEFF),
        ("s1..s4", [8, 9, 10, 11], MAX_PRISM_COEFF),
        ("tau_x, tau_y (rad)", [12, 13], MAX_TILT_RAD),
    )
    for name, idx, limit in groups:
        values = d[[i for i in idx if i < len(d)]]
        if values.size and float(np.max(np.abs(values))) > limit:
            report.bad("dist", f"{name} up to {float(np.max(np.abs(values))):.4g}: beyond {limit:g} for a real lens")
            return
    if isinstance(K, np.ndarray) and shape is not None:
        problem = _lens_problem(d, K, shape)
        if problem:
            report.bad("dist", problem)


def _lens_problem(d: np.ndarray, K: np.ndarray, shape: tuple[int, int]) -> str | None:
    """Why a lens model cannot describe an H x W image with intrinsics K (its radial part), or None."""
    h, w = shape
    corners = np.array([[-0.5, -0.5, 1.0], [w - 0.5, -0.5, 1.0], [-0.5, h - 0.5, 1.0], [w - 0.5, h - 0.5, 1.0]])
    xy = (corners @ np.linalg.inv(K).T)[:, :2]
    corner = float(np.max(np.hypot(xy[:, 0], xy[:, 1])))  # the farthest corner's distorted radius
    fold, r, rd = _fold_radius(d, _REACH * corner)
    reached = np.flatnonzero(rd >= corner)
    if reached.size and r[reached[0]] <= fold:
        return None
    px = float(K[0, 0])
    if math.isfinite(fold):
        return (
            f"the lens model folds back {fold * px:.0f} px from the principal point, before it reaches the image's "
            f"farthest corner ({corner * px:.0f} px): two rays would land on one pixel (coefficients in the wrong "
            "order or units, or not this image's lens?)"
        )
    return (
        f"the lens model brings no ray within {_REACH:g} x the corner's radius to the image's farthest corner: "
        "far stronger than a pinhole lens bends (a fisheye model, or wrong coefficients?)"
    )


def _check_images(report: _Report, labels: object, rgb: object, shape: tuple[int, int] | None) -> None:
    """Check the optional labels and rgb images, against the depth image's size `shape` when known."""
    if labels is not None:
        lab = report.array("labels", labels)
        if lab is not None:
            if lab.dtype != np.uint8:
                report.bad("labels", f"dtype must be uint8 (class ids), got {lab.dtype}")
            elif shape is not None and lab.shape != shape:
                report.bad("labels", f"shape {lab.shape} does not match depth {shape}")
            elif shape is None and not _image_shape_ok(lab.shape):
                report.bad("labels", f"shape must be (H, W) with 1..{MAX_IMAGE_SIDE} px a side, got {lab.shape}")
            elif _unknown_ids(lab):
                present = np.flatnonzero(np.bincount(lab.ravel(), minlength=256))
                unknown = np.setdiff1d(present, _VALID_LABELS)
                if unknown.size:
                    report.bad("labels", f"unknown class ids {unknown[:5].tolist()} (valid: 0..9 and 255)")

    if rgb is not None:
        im = report.array("rgb", rgb)
        if im is not None:
            if im.dtype != np.uint8:
                report.bad("rgb", f"dtype must be uint8, got {im.dtype}")
            elif shape is not None and im.shape != (*shape, 3):
                report.bad("rgb", f"shape must be {(*shape, 3)} to match depth, got {im.shape}")
            elif shape is None and (im.ndim != 3 or im.shape[2] != 3 or not _image_shape_ok(im.shape[:2])):
                report.bad("rgb", f"shape must be (H, W, 3) with 1..{MAX_IMAGE_SIDE} px a side, got {im.shape}")


def _unknown_ids(labels: np.ndarray) -> bool:
    """Whether a uint8 label image holds ids besides 0..9 and 255 (about 0.05 ms for 640 x 480; a bincount
    takes 0.5 ms, which a perception service would pay for every frame it receives)."""
    if not labels.size or int(labels.max()) <= _MAX_CLASS_ID:
        return False
    return bool(np.any((labels > _MAX_CLASS_ID) & (labels != SemanticClass.UNLABELED)))


def _check_fork_height(report: _Report, fork_height: object, mast_range_m: tuple[float, float] | None) -> None:
    """Check the fork height: a finite number within the mast's range (or any mast's)."""
    height: float | None = None
    if isinstance(fork_height, np.ndarray):
        if fork_height.shape != () or fork_height.dtype.kind not in "fiu":
            report.bad(
                "fork_height", f"must be a scalar number, got shape {fork_height.shape} dtype {fork_height.dtype}"
            )
        else:
            height = float(fork_height)
    elif isinstance(fork_height, (int, float)) and not isinstance(fork_height, bool):
        height = float(fork_height)
    else:
        report.bad("fork_height", f"must be a finite number (m), got {fork_height!r}")
    if height is not None:
        height_problem = _fork_height_problem(height, mast_range_m)
        if height_problem:
            report.bad("fork_height", height_problem)


def _check_truth(report: _Report, truth: Mapping[str, object]) -> None:
    """Check the truth arrays: keys ending in `TRUTH_SUFFIX`, numeric, not too large, transforms 4 x 4."""
    for key, value in truth.items():
        if not key.endswith(TRUTH_SUFFIX):
            report.bad(key, f"truth keys must end in '{TRUTH_SUFFIX}'")
            continue
        arr = report.array(key, value)
        if arr is None:
            continue
        if arr.dtype.kind not in "fiub":
            report.bad(key, f"truth arrays must be numeric, got dtype {arr.dtype}")
        elif arr.size > MAX_TRUTH_ELEMENTS:
            report.bad(key, f"{arr.size} elements, more than a truth array may hold ({MAX_TRUTH_ELEMENTS})")
        elif key.startswith("T_") and (arr.shape != (4, 4) or not np.all(np.isfinite(arr))):
            report.bad(key, f"a transform must be a finite 4 x 4 matrix, got shape {arr.shape}")
