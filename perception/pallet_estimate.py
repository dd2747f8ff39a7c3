"""What the pallet estimator takes and gives: its tuning, its result and its failure; fusing results.

Frames (ARCHITECTURE.md): `forklift` (origin on the floor between the fork heels, x towards the tips,
y left, z up), `pallet` (origin at the centre of the entry face on the pallet's underside, x into the
pallet, y left, z up), `world`. SI units (angles in rad; `to_json` in degrees).

Public API (re-exported by `perception.pallet`; import it from there):
- `PalletEstimatorConfig` (the tuning of `estimate_pallet`), `DEFAULT_CONFIG`, `estimator_config` (for a
  camera with or without a depth tare), `TARED_DEPTH_SCALE_SIGMA`.
- `PalletEstimate` (`T_forklift_pallet`, `T_world_pallet`, spread, pocket measurements, `to_json`),
  `PalletSpread` (1-sigma x, y and yaw).
- `PalletNotFound`: a `PerceptionError` whose `reason` is one of `NotFoundReason`.
- `fuse_estimates`: one estimate from several frames of one standpoint (inverse-variance weights).
- `FramePolicy`: how many frames a standpoint takes before its fused estimate is judged (more where
  the fused yaw is still uncertain), and when its frames doubt the pallet type (`TYPE_REFUSALS`);
  `RoundVerdict`, its decision after each round.
- `PALLET_CLASSES`: the label ids of pallet pixels.
"""

from __future__ import annotations

import dataclasses
import math
from dataclasses import dataclass, field
from typing import Any, Literal, NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from palletpilot.geometry import SE3
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import SemanticClass
from palletpilot.perception.instances import InstanceConfig

PALLET_CLASSES = (int(SemanticClass.PALLET_EMPTY), int(SemanticClass.PALLET_FULL))
"""Label ids of pallet pixels."""


NotFoundReason = Literal[
    "too_few_points", "no_entry_face", "pockets_inconsistent", "not_where_expected", "type_mismatch"
]
"""Why no pallet was found; `type_mismatch`: a pallet face wider than the pallet type's (another type)."""
TYPE_REFUSALS = frozenset({"type_mismatch", "pockets_inconsistent"})
"""The reasons that say the face is not of the pallet type (rather than not seen well enough)."""


class PalletNotFound(PerceptionError):  # noqa: N818 (the name the architecture gives it)
    """No pallet pose in the frame; `reason` is one of `NotFoundReason`, the message says why."""

    def __init__(self, reason: NotFoundReason, message: str, where: str | None = None) -> None:
        prefix = f"{where}: " if where else ""
        super().__init__(f"{prefix}pallet not found ({reason.replace('_', ' ')}): {message}")
        self.reason: NotFoundReason = reason
        self.detail = message


@dataclass(frozen=True)
class PalletEstimatorConfig:
    """Tuning of `estimate_pallet`. Distances in m, inverse depths in 1/m."""

    min_points: int = 150
    """Fewest pallet-labelled pixels with depth."""
    depth_noise_k: float = 0.0042
    """Prior depth noise: sigma(z) = k z^2, i.e. sigma of 1/z = k (D435 at 640x480: 0.08 px / (384 px * 0.05 m))."""
    min_sigma_w: float = 2e-5
    """Floor of the inverse-depth noise used in the scores (an ideal camera still has float rounding)."""
    ransac_iterations: int = 200
    ransac_max_pixels: int = 3000
    seed: int = 0
    max_yaw_deg: float = 50.0
    """Largest angle between the entry face's normal and the forklift's x axis."""
    min_face_pixels: int = 60
    min_face_width_ratio: float = 0.5
    """The plane's labelled inliers must span at least this share of the pallet width."""
    min_face_height_ratio: float = 0.5
    """... and at least this share of its height (5th to 95th percentile)."""
    lateral_search_m: float = 0.06
    vertical_search_m: float = 0.03
    edge_search_m: float = 0.02
    pocket_width_tolerance_m: float = 0.02
    pocket_centre_tolerance_m: float = 0.025
    min_pocket_open: float = 0.4
    """Share of pocket-interior pixels that must see past the face."""
    min_column_solid: float = 0.6
    """Share of block-column pixels that must lie on the face."""
    max_side_solid: float = 0.5
    """Largest share of pallet pixels just past a side of the modelled face (block layer) that may lie on
    the face plane: more, and the face is wider than the pallet type's (`type_mismatch`)."""
    no_return_range_m: float = 6.0
    """A pixel near the face without depth saw past it (a time-of-flight or stereo camera returns nothing
    where a ray meets nothing in its range: through a pocket, beside the face) when its ray stays above the
    pallet's support for this far (camera depth, m) and no pixel with depth lies within
    `no_return_margin_px` (a dropout at a depth edge is unknown, not far); 0 counts none."""
    no_return_margin_px: int = 2
    missing_board_depth_m: float = 0.015
    """A cell of the face (a bottom board, a quarter of a block face) whose pixels lie (median) this far
    behind the face is missing or chipped: left out of the face fit."""
    max_edge_offset_m: float = 0.012
    """A pocket edge this far (m) plus a pixel footprint off where the pallet type has it (build
    tolerance moves edges by millimetres) means another pallet type (`pockets_inconsistent`)."""
    truncation_sigma: float = 3.0
    rounds: int = 2
    face_margin_px: float = 0.5
    face_margin_m: float = 0.003
    """The plane is refitted on pixels at least `face_margin_px` pixel footprints plus `face_margin_m` inside the
    modelled solid face (its edges are known to a few millimetres)."""
    edge_jump_rel: float = 0.05
    """A pixel next to a depth jump of this share of its depth, or ..."""
    edge_jump_sigma: float = 5.0
    """... of this many depth-noise sigmas, is left out of the edge searches (it may be a flying pixel)."""
    side_walls: bool = False
    """Also fit side-wall pixels (pocket insides, pallet sides) with the face. Off: on the benchmark the few,
    thin wall pixels at 2.5-4 m made the yaw slightly worse (p95 0.64 vs 0.51 deg on 60 frames)."""
    min_wall_pixels: int = 30
    """Fewest side-wall pixels for the joint face-and-walls fit."""
    depth_scale_sigma: float = 0.0017
    """1-sigma of the camera's depth scale error (a fraction; measured z = true z (1 + s), the same for
    every frame of one camera): it moves the pallet along the camera's ray by s times its distance, 6 mm
    at 3.5 m. 0.0017 is +-0.3 % uniform, the simulator's D435; a camera with a depth tare
    (`perception.depth_tare`) is known to about 0.04 % (`TARED_DEPTH_SCALE_SIGMA`)."""
    depth_correlation_px: float = 1.0
    """The camera's depth-noise correlation area (pixels, at least 1): neighbouring pixels' depth errors are
    correlated over about this many pixels, so N fitted pixels carry as much as N / this independent ones and
    the own (per-frame) part of the spread, computed as if pixels were independent, is widened by its square
    root. A camera property: `palletpilot camera noise` measures it from still frames into the camera's tare
    file (`DepthTare.depth_correlation_px`). 1 (independent pixels) is the simulator's D435 unless its
    `CameraNoise.depth_correlation_px` says otherwise; real stereo and ToF depth (block matching, filtering)
    is correlated over several pixels (real ToF frames of issue 37 stated a yaw 3-5 times too small)."""
    build_tolerance_m: float = 0.005
    """A real pallet's boards and blocks are off its type's drawing: sizes by up to +- this, face positions by
    up to +- half of it (uniform; the `tolerance` family of `bench pallet`). Every frame of the pallet sees
    the same deviations, so they are stated as the spread's common part (`PalletSpread`, `_common_spread`):
    the entry face's parts tilt the face (yaw), its blocks' sides move the pocket edges (lateral)."""
    deck_yaw: bool = True
    """Refine the yaw with the top deck's board edges where the camera sees the deck (see `_deck_yaw`)."""
    deck_min_pixels: int = 150
    """Fewest unoccluded deck pixels for the deck refinement."""
    deck_min_camera_height_m: float = 0.05
    """The camera must be this far above the deck for the refinement (a grazing view tells nothing)."""
    deck_front_margin_m: float = 0.03
    """Deck pixels nearer than this to the entry face are left out (the face's top edge)."""
    deck_cargo_margin_px: int = 3
    """Pixels this close to cargo, other-object or person pixels are left out (labels may be a few pixels off)."""
    deck_yaw_search_deg: float = 1.5
    """Largest yaw change the deck may make (searched within 4 face sigmas, at most this)."""
    deck_lateral_step_m: float = 0.0005
    """Resolution of the lateral cost tables."""
    deck_sigma_scale: float = 1.4
    """The deck yaw's 1-sigma from its cost curve, times this: neighbouring pixels' depth errors are not
    independent, so the curve alone understates it (`bench pallet` frames, seeds 0 and 1, 165 and 177
    frames with the deck in view: errors over the curve's sigma had an RMS of 1.41 and 1.42; the face's
    own yaw sigma, 0.92-1.08, needs no such factor)."""
    deck_shift_max_m: float = 0.012
    """Largest sideways shift of the face centre the deck may make (searched within 3 lateral sigmas, at most this)."""
    deck_shift_steps: int = 6
    """Shifts searched on each side of the face centre's (2 n + 1 in all)."""
    instances: InstanceConfig = field(default_factory=InstanceConfig)
    """Instance separation and its gate, with `expected` (see `perception.instances`)."""


DEFAULT_CONFIG = PalletEstimatorConfig()


TARED_DEPTH_SCALE_SIGMA = 0.0004
"""`depth_scale_sigma` after a depth tare: its residual (bench calibration: p95 0.06 %)."""


def estimator_config(depth_tared: bool, depth_correlation_px: float = 1.0) -> PalletEstimatorConfig:
    """The default tuning for a camera with (`TARED_DEPTH_SCALE_SIGMA`) or without a depth tare, whose depth
    noise is correlated over `depth_correlation_px` pixels (`PalletEstimatorConfig.depth_correlation_px`)."""
    cfg = dataclasses.replace(DEFAULT_CONFIG, depth_correlation_px=max(float(depth_correlation_px), 1.0))
    return dataclasses.replace(cfg, depth_scale_sigma=TARED_DEPTH_SCALE_SIGMA) if depth_tared else cfg


@dataclass(frozen=True)
class PalletSpread:
    """1-sigma uncertainty of a pallet estimate: x, y (m, forklift frame) and yaw (rad).

    `x_common_m`, `y_common_m`, `yaw_common_rad`: the part of `x_m`, `y_m`, `yaw_rad` that every frame of
    the same pallet from the same standpoint shares, which fusing frames does not reduce: the camera's
    depth scale error (it moves the whole point cloud along the rays), the pallet's build tolerance (its
    parts are where they are in every frame) and the pixel grid's quantisation of edges (the same pixels
    see the same edges). The rest (`x_own_m`, `y_own_m`, `yaw_own_rad`) is each frame's own noise.
    """

    x_m: float
    y_m: float
    yaw_rad: float
    x_common_m: float = 0.0
    y_common_m: float = 0.0
    yaw_common_rad: float = 0.0

    @property
    def x_own_m(self) -> float:
        """The part of `x_m` that is this frame's own (without `x_common_m`)."""
        return math.sqrt(max(self.x_m**2 - self.x_common_m**2, 0.0))

    @property
    def y_own_m(self) -> float:
        """The part of `y_m` that is this frame's own (without `y_common_m`)."""
        return math.sqrt(max(self.y_m**2 - self.y_common_m**2, 0.0))

    @property
    def yaw_own_rad(self) -> float:
        """The part of `yaw_rad` that is this frame's own (without `yaw_common_rad`)."""
        return math.sqrt(max(self.yaw_rad**2 - self.yaw_common_rad**2, 0.0))

    def to_json(self) -> dict[str, float]:
        """`x_m`, `y_m` (m) and `yaw_deg`, and the common parts `x_common_m`, `y_common_m` (m), `yaw_common_deg`."""
        return {
            "x_m": round(self.x_m, 6),
            "y_m": round(self.y_m, 6),
            "yaw_deg": round(math.degrees(self.yaw_rad), 5),
            "x_common_m": round(self.x_common_m, 6),
            "y_common_m": round(self.y_common_m, 6),
            "yaw_common_deg": round(math.degrees(self.yaw_common_rad), 5),
        }


@dataclass(frozen=True)
class PalletEstimate:
    """The estimated pallet pose and how it was found.

    `T_forklift_pallet`: pallet frame (ARCHITECTURE.md) in the forklift frame at the time of the frame;
    `T_world_pallet`: the same in the world when `T_world_forklift` was given.
    `pocket_widths_m` and `pocket_centres_y_m` are measured in the pallet frame (left, right).
    """

    T_forklift_pallet: SE3
    spread: PalletSpread
    n_points: int
    n_face_points: int
    pocket_widths_m: tuple[float, float]
    pocket_centres_y_m: tuple[float, float]
    residual_rms_w: float
    T_world_pallet: SE3 | None = None
    runtime_ms: float = 0.0
    extras: dict[str, Any] = field(default_factory=dict)

    @property
    def yaw(self) -> float:
        """Yaw (rad) of the pallet's x axis in the forklift frame."""
        return self.T_forklift_pallet.to_se2().yaw

    def to_json(self) -> dict[str, Any]:
        """The `estimate-pallet --json` document (degrees and metres)."""
        t = self.T_forklift_pallet.t
        doc: dict[str, Any] = {
            "T_forklift_pallet": np.round(self.T_forklift_pallet.matrix, 9).tolist(),
            "x_m": round(float(t[0]), 6),
            "y_m": round(float(t[1]), 6),
            "z_m": round(float(t[2]), 6),
            "yaw_deg": round(math.degrees(self.yaw), 5),
            "spread": self.spread.to_json(),
            "n_points": self.n_points,
            "n_face_points": self.n_face_points,
            "pocket_widths_m": [round(v, 5) for v in self.pocket_widths_m],
            "pocket_centres_y_m": [round(v, 5) for v in self.pocket_centres_y_m],
            "runtime_ms": round(self.runtime_ms, 2),
        }
        if self.T_world_pallet is not None:
            pose = self.T_world_pallet.to_se2()
            doc["T_world_pallet"] = np.round(self.T_world_pallet.matrix, 9).tolist()
            doc["world"] = {
                "x_m": round(pose.x, 6),
                "y_m": round(pose.y, 6),
                "yaw_deg": round(math.degrees(pose.yaw), 5),
            }
        return doc


def fuse_estimates(estimates: list[PalletEstimate]) -> PalletEstimate:
    """One estimate from several frames of a standing pallet, each weighted by its spread.

    x, y (forklift frame, and the world frame where every estimate has `T_world_pallet`) and yaw are
    inverse-variance weighted means (the spreads come from each frame's fit, so a frame that sees
    less counts less); the height is the plain mean. The spread of the result is that of the
    weighted mean of the frames' own parts, 1 / sqrt(sum of 1 / sigma_own^2), with the part every frame
    shares (`x_common_m`, `y_common_m`, `yaw_common_rad`: the camera's depth scale, the pallet's build,
    the pixel grid) added back, undiminished. All estimates must be of the same pallet from the same
    standpoint (the forklift frame does not move between them).
    """
    if not estimates:
        raise ValueError("fuse_estimates: no estimates")
    if len(estimates) == 1:
        return estimates[0]

    # Precisions (1 / sigma^2) per frame of x, y (their own parts, without what all frames share) and yaw;
    # normalised, they are the weights.
    px, py, pyaw = (
        1.0 / np.maximum(np.array([getattr(e.spread, k) for e in estimates]), 1e-9) ** 2
        for k in ("x_own_m", "y_own_m", "yaw_own_rad")
    )
    wx, wy, wyaw = px / px.sum(), py / py.sum(), pyaw / pyaw.sum()

    def fuse(poses: list[SE3], wx: np.ndarray, wy: np.ndarray, wyaw: np.ndarray) -> SE3:
        t = np.array([p.t for p in poses])
        yaws = np.array([p.to_se2().yaw for p in poses])
        ref = yaws[0]
        yaw = ref + float(wyaw @ np.angle(np.exp(1j * (yaws - ref))))  # mean of the differences: no wrap-around
        xyz = (float(wx @ t[:, 0]), float(wy @ t[:, 1]), float(np.mean(t[:, 2])))
        return SE3(Rotation.from_euler("z", yaw), xyz)

    T_fp = fuse([e.T_forklift_pallet for e in estimates], wx, wy, wyaw)
    T_wp = None
    if all(e.T_world_pallet is not None for e in estimates):
        # The fused pallet carried into the world through each frame's own T_world_forklift, averaged
        # (equal weights: those differ by localization noise only).
        T_wf = [e.T_world_pallet @ e.T_forklift_pallet.inv() for e in estimates]  # type: ignore[operator]
        equal = np.full(len(estimates), 1.0 / len(estimates))
        T_wp = fuse([T @ T_fp for T in T_wf], equal, equal, equal)

    fused = [float(1.0 / math.sqrt(p.sum())) for p in (px, py, pyaw)]
    cx = float(np.mean([e.spread.x_common_m for e in estimates]))
    cy = float(np.mean([e.spread.y_common_m for e in estimates]))
    cyaw = float(np.mean([e.spread.yaw_common_rad for e in estimates]))
    spread = PalletSpread(math.hypot(fused[0], cx), math.hypot(fused[1], cy), math.hypot(fused[2], cyaw), cx, cy, cyaw)
    first = estimates[0]
    return PalletEstimate(
        T_forklift_pallet=T_fp,
        spread=spread,
        n_points=sum(e.n_points for e in estimates),
        n_face_points=sum(e.n_face_points for e in estimates),
        pocket_widths_m=tuple(np.mean([e.pocket_widths_m for e in estimates], axis=0).tolist()),
        pocket_centres_y_m=tuple(np.mean([e.pocket_centres_y_m for e in estimates], axis=0).tolist()),
        residual_rms_w=float(np.mean([e.residual_rms_w for e in estimates])),
        T_world_pallet=T_wp,
        runtime_ms=sum(e.runtime_ms for e in estimates),
        extras={**first.extras, "frames": len(estimates)},
    )


class RoundVerdict(NamedTuple):
    """`FramePolicy.after_round`: the type in doubt, the fused estimate so far, frames still to take."""

    type_in_doubt: bool
    fused: PalletEstimate | None
    more: int


@dataclass(frozen=True)
class FramePolicy:
    """How many frames of one standpoint go into the estimate that the Pickup judges.

    A single frame of a narrow loaded face 3.5-4 m away states a yaw 1-sigma of 0.4-0.75 deg (honestly:
    its errors over that sigma spread about 1), so three such frames can still be 0.9 deg off. The
    Pickup therefore takes `per_round` frames, fuses them, and while the fused yaw 1-sigma is above
    `yaw_sigma_rad` takes another round, up to `max_frames` in all; nearer or empty pallets (deck in
    view) meet the limit with the first round. Only the frames' own part of the yaw sigma
    (`PalletSpread.yaw_own_rad`) shrinks with more frames: once it is no larger than the common part
    (the pallet's build, the pixel grid), doubling the frames would cut the fused sigma by at most 13 %,
    and the estimate is judged as it is (the alignment check takes its sigma into account).
    """

    per_round: int = 3
    max_frames: int = 9
    yaw_sigma_rad: float = math.radians(0.25)

    def type_in_doubt(self, found: int, reasons: list[str]) -> bool:
        """Whether a standpoint's frames doubt the pallet type: as many or more of them refused it
        (`TYPE_REFUSALS`) as gave an estimate. Another type at 3.5-4 m (a 1200 x 800 plastic pallet told
        EUR: pockets 27.5 mm narrower, a pixel is 6-7 mm there) now and then passes in one frame of three,
        while a sound pallet of the type is refused in about one frame in thirty; the Pickup never enters
        a pallet whose type its own frames doubt."""
        refused = sum(r in TYPE_REFUSALS for r in reasons)
        return refused > 0 and refused >= found

    def after_round(self, found: list[PalletEstimate], reasons: list[str], frames_taken: int) -> RoundVerdict:
        """What a standpoint does after a round, the Pickup and `bench pallet` alike: the type in doubt
        (`type_in_doubt`) ends it first; else the fused estimate (None without one) and how many more
        frames to take before judging it (`more_frames`)."""
        if found and self.type_in_doubt(len(found), reasons):
            return RoundVerdict(True, None, 0)
        fused = fuse_estimates(found) if found else None
        return RoundVerdict(False, fused, self.more_frames(fused, frames_taken))

    def more_frames(self, fused: PalletEstimate | None, frames_taken: int) -> int:
        """Frames to take before judging (0: judge `fused` now): another round while the fused yaw is
        uncertain, more frames can still make it less so (its own part exceeds the common part) and
        `max_frames` allows; none without an estimate (nothing seen is judged at once)."""
        if fused is None or fused.spread.yaw_rad <= self.yaw_sigma_rad:
            return 0
        if fused.spread.yaw_own_rad <= fused.spread.yaw_common_rad:
            return 0
        return max(0, min(self.per_round, self.max_frames - frames_taken))
