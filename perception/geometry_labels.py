"""Labels from depth geometry: where perception's pixels come from when the segmentation model is not trusted.

The segmentation model was trained on the project's renders; on real cameras it may label little of a pallet
(issue 37). The pallet estimator and the calibration need labels only to *select* pixels (the pallet's, the
floor's, the forks'); the poses come from depth. So the selection can come from geometry alone, seeded by
what the caller already knows:

- **Pallet** (`pallet_labels`): the pixels whose points (forklift frame) stand in the pallet's height band
  above its support (the floor, or the rack beams: `support_height_m`) inside the misplacement envelope
  around where the pallet is expected (`expected`, `Envelope`). Everything the estimator does after the
  selection (the vertical entry face by RANSAC, the instance at the expected place, the pallet model, the
  pockets) is geometry already. A load standing on the pallet is found once the face is known
  (`load_mask`): points above the deck over the pallet's footprint.
- **Calibration** (`calibration_labels`): the floor as the dominant plane below the camera, the forks as the
  points standing a blade's thickness above it in pieces that reach the image's lower border (the blades
  start under the camera); no earlier calibration is needed.

`LabelsMode` (`perception.labels_mode`, re-exported here) says which source selects: `model` (the
segmentation labels alone, as before issue 37), `geometry` (depth alone; the model is not run), `fused`
(the default of every command: geometry selects, the model adds what geometry cannot tell, as hints that
must be coherent blobs so that a model giving noise changes nothing: a person in front of the pallet is
left out, a load above the pallet is cargo, and where the geometry sees no pallet, the model's pallet
pixels inside the envelope stand in). `MODES` is the one table of what each mode needs and what it is
robust to (the README quotes it).

Frames (ARCHITECTURE.md): `camera` optical (x right, y down, z forward), `forklift` (origin on the floor
between the fork heels, x towards the tips, z up), `pallet` (origin at the centre of the entry face on the
underside, x into the pallet). SI units.

Public API: `LabelsMode`, `DEFAULT_LABELS_MODE`, `MODES`, `Envelope`, `DEFAULT_ENVELOPE`, `PalletLabels`,
`pallet_labels`, `load_mask`, `calibration_labels`, `sources_note`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from palletpilot.geometry import SE2, SE3
from palletpilot.perception.errors import CalibrationError, PerceptionError
from palletpilot.perception.frames import FrameBundle, SemanticClass
from palletpilot.perception.labels_mode import DEFAULT_LABELS_MODE, MODES, LabelsMode
from palletpilot.perception.pointcloud import check_intrinsics, class_mask, depth_edges
from palletpilot.perception.specs import ForkGeometry, PalletType

__all__ = [
    "DEFAULT_ENVELOPE",
    "DEFAULT_LABELS_MODE",
    "MODES",
    "Envelope",
    "LabelsMode",
    "PalletLabels",
    "calibration_labels",
    "load_mask",
    "pallet_labels",
    "sources_note",
]


@dataclass(frozen=True)
class Envelope:
    """How far a pallet may stand from where it is expected (the Pickup's misplacement envelope)."""

    lateral_m: float = 0.40
    longitudinal_m: float = 0.40
    yaw_deg: float = 15.0


DEFAULT_ENVELOPE = Envelope()
"""The executor's envelope (`Settings.envelope_*`)."""

FLOOR_MARGIN_M = 0.015
"""Points less than this above the support are the support, or `FLOOR_SIGMAS` of their height's noise where
that is more (a stereo camera's depth error grows with the square of the depth)."""
FLOOR_SIGMAS = 3.0
DEPTH_NOISE_K = 0.0042
"""Depth noise sigma(z) = k z^2 (m; a D435 at 640 x 480, `PalletEstimatorConfig.depth_noise_k`)."""
TOP_MARGIN_M = 0.02
"""The pallet band reaches this far above the deck (a board proud of the deck, depth noise)."""
REGION_MARGIN_M = 0.10
"""The envelope's region is grown by this (the pallet's own build tolerance, depth noise at its edges)."""
AHEAD_X_M = (0.2, 6.0)
AHEAD_Y_M = 3.0
"""Without an expected pose: the region ahead of the forks (forklift x range and |y|, m)."""
HINT_OPEN_PX = 5
"""The model's hint masks are opened with a square of this size: single pixels and thin speckle are noise."""
HINT_MIN_PX = 150
"""A hint blob (person, load) needs at least this many pixels after opening."""
SEES_MIN_PX = 150
"""A source 'sees' the pallet when it selects at least this many pixels (the estimator's `min_points`)."""


@dataclass(frozen=True)
class PalletLabels:
    """The labels the estimator selects pallet pixels with, and how many pixels each source selected.

    `geometry_px`: pixels in the height band inside the envelope; `model_px`: the model's pallet pixels
    inside the envelope, in coherent blobs (`_blobs`; None without model labels; in the `model` mode all
    its pallet pixels).
    """

    labels: np.ndarray
    mode: LabelsMode
    geometry_px: int
    model_px: int | None
    points: np.ndarray | None = None  # H x W x 3 forklift-frame points (NaN without depth); None in `model`

    def to_json(self) -> dict[str, object]:
        """The sources' pixel counts for a report."""
        return {"labels": str(self.mode), "geometry_pixels": self.geometry_px, "model_pixels": self.model_px}


def _points(frame: FrameBundle, T_forklift_camera: SE3) -> tuple[np.ndarray, np.ndarray]:
    """Forklift-frame points (H x W x 3, NaN without depth) and the valid mask (H x W)."""
    check_intrinsics(frame.K, "frame K")
    depth = frame.depth
    valid = np.isfinite(depth) & (depth > 0)
    h, w = depth.shape
    K = frame.K
    v, u = np.mgrid[0:h, 0:w]
    z = np.where(valid, depth, np.nan).astype(np.float64)
    y = (v - K[1, 2]) / K[1, 1]
    x = ((u - K[0, 2]) - K[0, 1] * y) / K[0, 0]
    cam = np.stack([x * z, y * z, z], axis=-1)
    pts = cam @ T_forklift_camera.R.T + T_forklift_camera.t
    return pts, valid


def _region(pts: np.ndarray, pallet: PalletType, expected: SE2 | None, envelope: Envelope) -> np.ndarray:
    """Pixels whose point lies (in plan) where the pallet may stand: its footprint at `expected` grown by
    the envelope (a yaw turns its far corners sideways), or the area ahead of the forks without it."""
    x, y = pts[..., 0], pts[..., 1]
    if expected is None:
        return (x >= AHEAD_X_M[0]) & (x <= AHEAD_X_M[1]) & (np.abs(y) <= AHEAD_Y_M)
    c, s = math.cos(expected.yaw), math.sin(expected.yaw)
    dx, dy = x - expected.x, y - expected.y
    xp, yp = c * dx + s * dy, -s * dx + c * dy  # in the expected pallet frame
    turn = math.sin(math.radians(envelope.yaw_deg))
    lat = 0.5 * pallet.width + envelope.lateral_m + REGION_MARGIN_M
    lat_far = lat + pallet.length * turn  # a turned pallet's back corners swing out
    along = envelope.longitudinal_m + REGION_MARGIN_M + 0.5 * pallet.width * turn
    inside_x = (xp >= -along) & (xp <= pallet.length + along)
    frac = np.clip(xp / max(pallet.length, 1e-6), 0.0, 1.0)
    return inside_x & (np.abs(yp) <= lat + (lat_far - lat) * frac)


def _blobs(mask: np.ndarray) -> np.ndarray:
    """`mask` opened (speckle removed) and kept only in connected pieces of at least `HINT_MIN_PX` pixels."""
    if not mask.any():
        return mask
    k = np.ones((HINT_OPEN_PX, HINT_OPEN_PX), np.uint8)
    opened = cv2.morphologyEx(mask.astype(np.uint8), cv2.MORPH_OPEN, k)
    n, comp, stats, _ = cv2.connectedComponentsWithStats(opened, connectivity=8)
    keep = np.zeros(n, bool)
    keep[1:] = stats[1:, cv2.CC_STAT_AREA] >= HINT_MIN_PX
    return keep[comp]


def pallet_labels(
    frame: FrameBundle,
    T_forklift_camera: SE3,
    pallet: PalletType,
    mode: LabelsMode,
    *,
    expected: SE2 | None = None,
    support_height_m: float = 0.0,
    envelope: Envelope = DEFAULT_ENVELOPE,
    depth_noise_k: float = DEPTH_NOISE_K,
) -> PalletLabels:
    """The labels that select the pallet's pixels in `frame`, by `mode`.

    `T_forklift_camera`: the camera at the frame's fork height; `expected`: `T_forklift_pallet` (SE2) where
    the pallet should stand (None: anywhere ahead of the forks, less the pieces of the band that reach the
    image's lowest rows: the blades); `support_height_m`: the height (forklift
    frame, m) of what it stands on, the floor (0) or a rack's beams. `model`: the frame's own labels
    (`PerceptionError` without them). `geometry`: pallet-empty on the pixels in the band from
    `FLOOR_MARGIN_M` above the support to `TOP_MARGIN_M` above the deck inside the envelope, drivable on the
    floor, unlabeled elsewhere; the band starts higher where the depth is noisier (`FLOOR_SIGMAS` of a
    point's height noise from `depth_noise_k`). `fused`: the geometry's, less the model's person blobs,
    its load blobs above the pallet's band as cargo, pallet-full where it says a pallet is loaded; where the
    geometry sees no pallet (fewer than `SEES_MIN_PX` pixels: a wrong support height), the model's pallet
    blobs inside the envelope.
    """
    if mode == LabelsMode.MODEL:
        if frame.labels is None:
            raise PerceptionError("labels (model): the frame has no labels (segment its RGB first)")
        model_px = int(np.count_nonzero(class_mask(frame.labels, _PALLET)))
        return PalletLabels(frame.labels, mode, 0, model_px)
    pts, valid = _points(frame, T_forklift_camera)
    with np.errstate(invalid="ignore"):
        region = _region(pts, pallet, expected, envelope) & valid
        z = pts[..., 2] - support_height_m
        depth = frame.depth
        slope = np.abs(pts[..., 2] - T_forklift_camera.t[2]) / depth  # height change per metre of z-depth
        floor_margin = np.maximum(FLOOR_MARGIN_M, FLOOR_SIGMAS * depth_noise_k * depth * depth * slope)
        band = region & (z >= floor_margin) & (z <= pallet.height + TOP_MARGIN_M)
        floor = valid & (np.abs(pts[..., 2]) < FLOOR_MARGIN_M)
    if expected is None:  # the forks (raised to the pallet) are in the band too: pieces from the image's bottom
        band &= ~_lower_pieces(band & ~depth_edges(frame.depth, 0.03, no_data_is_edge=True))
    labels = np.full(frame.depth.shape, SemanticClass.UNLABELED, np.uint8)
    labels[floor] = SemanticClass.DRIVABLE
    labels[band] = SemanticClass.PALLET_EMPTY
    geometry_px = int(np.count_nonzero(band))
    model = frame.labels if mode == LabelsMode.FUSED else None
    if model is None:
        return PalletLabels(labels, mode, geometry_px, None, pts)
    model_pallet = _blobs(class_mask(model, _PALLET) & region)
    model_px = int(np.count_nonzero(model_pallet))
    if geometry_px < SEES_MIN_PX:  # geometry sees nothing where the pallet should stand: the model's view
        labels[model_pallet & ~band] = SemanticClass.PALLET_EMPTY
    full = _blobs(model == SemanticClass.PALLET_FULL)
    labels[full & (labels == SemanticClass.PALLET_EMPTY)] = SemanticClass.PALLET_FULL
    labels[_blobs((model == SemanticClass.PERSON) & valid)] = SemanticClass.PERSON
    # A load seen by the model: above the pallet's band only (the face stays the geometry's until the face is
    # found; then `load_mask` takes a loaded pallet's deck layer, where a film may hang).
    labels[_blobs((model == SemanticClass.CARGO) & valid) & ~band] = SemanticClass.CARGO
    return PalletLabels(labels, mode, geometry_px, model_px, pts)


_PALLET = (int(SemanticClass.PALLET_EMPTY), int(SemanticClass.PALLET_FULL))


LOAD_BOTTOM_M = 0.25
"""A load stands on the deck: some of its points lie within this of the deck's top (a rack beam of the
level above, a metre up, is over the footprint too, but no load)."""
LOAD_MIN_PX = 100
"""Fewest such pixels for a load on the pallet."""


def load_mask(
    points: np.ndarray,
    T_forklift_pallet: SE3,
    pallet: PalletType,
    camera: np.ndarray,
    overhang_m: float = 0.10,
) -> tuple[np.ndarray, bool]:
    """Pixels of what stands over the pallet, by geometry (points above the deck over its footprint), and
    whether a load stands on it (`LOAD_MIN_PX` of them within `LOAD_BOTTOM_M` of the deck's top). With a
    load, the face's deck layer (above the pockets, at most `overhang_m` in front of the face) joins the
    mask: a load's film or overhang may hang over it, and depth cannot tell them apart (a film 1-3 cm proud
    of the deck moved the face 1-2.5 cm in `bench pallet --families film`).

    `points`: the frame's forklift-frame points, H x W x 3, NaN without depth (`PalletLabels.points`);
    `T_forklift_pallet`: the pallet frame (on its underside) as far as the estimator knows it; the footprint
    is grown by `overhang_m` in front of the entry face and at the sides (a load may overhang).

    `camera`: the camera's forklift-frame position (m). The deck layer is told by where each pixel's ray
    crosses the entry face's plane, which depth noise does not move (`_deck_layer`), not by the noisy point:
    at 3-4 m a pixel's depth scatters by 4-7 cm, and along a ray that looks down a point measured too far
    is also too low, so a cut on the points (it was: within 5 cm behind the face, above the pockets) kept
    the deck layer's pixels that noise put far and low and dropped the others, which pushed the face fitted
    on what is left back (`bench pallet --families block_2pocket`, loaded: +4-6 mm).
    """
    valid = np.isfinite(points[..., 2])
    q = (points - T_forklift_pallet.t) @ T_forklift_pallet.R  # into the pallet frame
    with np.errstate(invalid="ignore"):
        over = (q[..., 0] >= -overhang_m) & (q[..., 0] <= pallet.length + 0.02)
        over &= np.abs(q[..., 1]) <= 0.5 * pallet.width + overhang_m
        above = (q[..., 2] > pallet.height + TOP_MARGIN_M) & (q[..., 2] < pallet.height + 3.0)
        low = q[..., 2] <= pallet.height + LOAD_BOTTOM_M
        cam = (np.asarray(camera, float) - T_forklift_pallet.t) @ T_forklift_pallet.R
        deck_front = _deck_layer(q, cam, pallet) & (q[..., 0] >= -overhang_m - DECK_LAYER_NEAR_M)
    mask = valid & over & above
    loaded = int(np.count_nonzero(mask & low)) >= LOAD_MIN_PX
    return (mask | (valid & deck_front)) if loaded else mask, loaded


DECK_LAYER_NEAR_M = 0.10
"""`load_mask`: the deck layer's pixels may lie this much more than `overhang_m` in front of the
face (depth noise: 1.5 sigma at 4 m of a D435 at 640 x 480)."""


def _deck_layer(q: np.ndarray, cam: np.ndarray, pallet: PalletType) -> np.ndarray:
    """Points `q` (pallet frame, m, H x W x 3) whose ray from the camera (`cam`, pallet frame) crosses the
    entry face's plane (x = 0) above the pockets and at most `TOP_MARGIN_M` above the deck, within the face's
    width and 2 cm, and which lie no farther than the pallet's length behind it. The crossing depends on
    the ray's direction alone, not on the measured depth."""
    with np.errstate(invalid="ignore", divide="ignore"):
        t = -cam[0] / (q[..., 0] - cam[0])  # ray parameter at x = 0 (camera at 0, the point at 1)
        y = cam[1] + t * (q[..., 1] - cam[1])
        z = cam[2] + t * (q[..., 2] - cam[2])
        out = (t > 0) & (z > pallet.pocket_height) & (z <= pallet.height + TOP_MARGIN_M)
        out &= (np.abs(y) <= 0.5 * pallet.width + 0.02) & (q[..., 0] <= pallet.length + 0.02)
    return out


def sources_note(found: PalletLabels) -> str:
    """Which source saw the pallet, for a reason: empty when both did (or the mode has only one source)."""
    if found.mode == LabelsMode.MODEL:
        return ""
    geo = found.geometry_px >= SEES_MIN_PX
    if found.model_px is None:
        return "" if geo else f" (geometry: {found.geometry_px} pixels in the pallet's height band in the envelope)"
    model = found.model_px >= SEES_MIN_PX
    if geo == model:
        return ""
    counts = f"geometry {found.geometry_px} pixels, model {found.model_px}"
    return f" (only the {'geometry' if geo else 'model'} sees a pallet where it should stand: {counts})"


# -- calibration: the floor and the forks -------------------------------------------------------------------

FORK_BAND_M = (0.012, 0.035)
"""Fork points stand this far above the floor, beyond the blade's thickness (lower, upper margins, m)."""
FORK_MIN_PX = 200
"""A piece of the fork band needs this many pixels to be a blade."""
LOWER_BORDER = 0.06
"""A blade's piece reaches into this share of the image's rows at the bottom (the blades start under the camera)."""


def _floor_plane(cam: np.ndarray, near: np.ndarray, where: str) -> tuple[np.ndarray, float]:
    """The floor in the camera frame: unit normal towards the camera and the camera's height above it.

    The largest plane among the near points (seeded RANSAC, `calibration_features._ransac_plane`) whose
    normal points up in the image (camera -y within 60 deg): the floor under a truck's camera.
    """
    from palletpilot.perception.calibration_features import _ransac_plane

    pts = cam[near]
    if len(pts) < 500:
        raise CalibrationError(f"{where}: labels (geometry): {len(pts)} points with depth near the camera")
    rng = np.random.default_rng(0)
    sample = pts if len(pts) <= 20000 else pts[rng.choice(len(pts), 20000, replace=False)]
    for _ in range(3):
        n, d = _ransac_plane(sample, 0.02)
        if n @ (-n * d) > 0:  # orient towards the camera: the camera (origin) on the positive side
            n, d = -n, -d
        if d > 0 and n[1] < -math.cos(math.radians(60.0)):
            return n, float(d)
        off = np.abs(sample @ n + d) > 0.04  # not the floor: try again without it
        sample = sample[off]
        if len(sample) < 500:
            break
    raise CalibrationError(f"{where}: labels (geometry): no floor plane below the camera")


def calibration_labels(frame: FrameBundle, forks: ForkGeometry, mode: LabelsMode, where: str = "frame") -> np.ndarray:
    """Drivable and fork labels for calibrating from `frame` (camera at lift `frame.fork_height`), by `mode`.

    `geometry`: the floor plane (drivable within 2 cm of it, nearer than 6 m), the forks (points from
    `FORK_BAND_M[0]` above the fork bottoms to their thickness plus `FORK_BAND_M[1]`, off depth jumps, in
    pieces of at least `FORK_MIN_PX` pixels that reach the image's lowest rows). `fused`: the same, and
    where geometry finds no blade, the model's fork blobs in that band. `model`: the frame's labels.
    """
    if mode == LabelsMode.MODEL:
        if frame.labels is None:
            raise CalibrationError(
                f"{where}: the frame has no labels; calibration needs the drivable and forks classes "
                "(segment the RGB first, or use the geometry labels)"
            )
        return frame.labels

    cam, valid = _points(frame, SE3())
    with np.errstate(invalid="ignore"):
        near = valid & (cam[..., 2] < 6.0)
        n, d = _floor_plane(cam, near, where)
        height = cam @ n + d  # above the floor (m), NaN without depth
        floor = near & (np.abs(height) < 0.02)
        lo = frame.fork_height + FORK_BAND_M[0]
        hi = frame.fork_height + forks.thickness + FORK_BAND_M[1]
        band = valid & (height >= lo) & (height <= hi) & ~depth_edges(frame.depth, 0.03, no_data_is_edge=True)
    blades = _lower_pieces(band)
    if mode == LabelsMode.FUSED and frame.labels is not None and np.count_nonzero(blades) < FORK_MIN_PX:
        blades = _blobs((frame.labels == SemanticClass.FORKS) & band)
    labels = np.full(frame.depth.shape, SemanticClass.UNLABELED, np.uint8)
    labels[floor] = SemanticClass.DRIVABLE
    labels[blades] = SemanticClass.FORKS
    return labels


def _lower_pieces(band: np.ndarray) -> np.ndarray:
    """The connected pieces of `band` with at least `FORK_MIN_PX` pixels that reach the lowest rows."""
    _, comp, stats, _ = cv2.connectedComponentsWithStats(band.astype(np.uint8), connectivity=8)
    h = band.shape[0]
    bottom = stats[:, cv2.CC_STAT_TOP] + stats[:, cv2.CC_STAT_HEIGHT]
    keep = (stats[:, cv2.CC_STAT_AREA] >= FORK_MIN_PX) & (bottom >= h * (1.0 - LOWER_BORDER))
    keep[0] = False
    return keep[comp]
