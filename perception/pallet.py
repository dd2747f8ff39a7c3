"""Pallet pose from one RGB-D frame: labels select the pallet, depth and the pallet model decide the pose.

Frames (ARCHITECTURE.md): `camera` optical (x right, y down, z forward), `forklift` (origin on the floor
between the fork heels, x towards the tips, y left, z up), `pallet` (origin at the centre of the entry
face on the pallet's underside, x into the pallet, y left, z up). SI units throughout.

Method, in the forklift frame with the camera at `calibration.T_forklift_camera_at(frame.fork_height)`:

0. **Instance** (only with `expected`, the pose where the pallet should be): the pallet pixels are
   split into pallet instances at depth jumps (`perception.instances`); only the instance whose
   entry face is nearest to `expected`, within a gate, is fitted, and other instances' pixels are
   left out of every step below (else `PalletNotFound("not_where_expected")`).
1. **Pixels.** Pixels labelled pallet-empty (7) or pallet-full (8) with depth. Each pixel is a ray
   `p(z) = t + d z` (`d` the forklift-frame direction of the pixel for unit camera z-depth) and a
   measured inverse depth `w = 1 / z`. A stereo camera's error is in disparity, i.e. in `w`, with a
   constant standard deviation, so every fit below works on `w`.
2. **Entry face.** The face is a vertical plane `cos(psi) x + sin(psi) y = rho`. On it the inverse
   depth is *linear* in the ray: `w = A d_x + B d_y` with `(A, B) = (cos psi, sin psi) / D` and `D`
   the camera's distance to the plane. RANSAC over pixel pairs (a truncated quadratic score, the
   normal within `max_yaw_deg` of the forklift's x axis) finds it among the labelled pixels (the deck
   top, side faces and flying pixels are outliers), iteratively re-weighted least squares refines it.
3. **The pallet model.** Every pixel near the face (whatever its label: labels are up to a few pixels
   off) is intersected with the plane, giving its lateral position `s` and height `h` on the face, and
   its ray slopes behind the plane. From the pallet type's boards and blocks the model predicts, for
   a hypothesised lateral centre and underside height, how far behind the face each ray ends: 0 on
   the solid face, on a block's side wall (the inside of a pocket seen at an angle, which depth
   alone cannot tell from the face at 4 m), on the cross-board or deck top, or far (the pocket).
   A truncated chi-square of the inverse-depth residuals scores the hypothesis. The lateral centre
   is searched on the block layer, the underside height on the pockets' upper edges (an occluding
   edge when the camera looks down), then the plane is refitted on the pixels the model puts on the
   solid face, away from its edges. Two rounds. Pixels next to a depth jump (which a D435 may fill
   with "flying" in-between depths) count as unknown in the edge searches, so they widen the
   interval an edge may lie in instead of biasing it. (`side_walls` optionally adds the wall pixels
   to the plane fit; off by default, see `PalletEstimatorConfig`.)
4. **Pockets.** Each inner block-column edge is searched on its own: the two gaps give the pocket
   widths and centres, which must match the pallet type (else `PalletNotFound`), and the lateral
   centre is the mean of the two pocket centres.

5. **Deck.** Where the camera sees the top deck (an empty pallet from above), the deck boards' side
   edges, lines along the whole pallet length, refine the yaw (`_deck_yaw`): each deck pixel is
   predicted on a board or past its edge for a yaw turned about the entry-face centre, scored in
   inverse depth together with the face fit's own yaw term. A load on the deck switches it off.

Geometry, not label boundaries, places the edges: a pixel's evidence is its depth against the model.
`fuse_estimates` combines the estimates of several frames from one standpoint (inverse-variance
weights from their spreads); the Pickup acts on three.
Spread (1-sigma): yaw and the face distance from the plane fit's covariance, the lateral centre from
the pocket edges' scatter and pixel footprint.
"""

from __future__ import annotations

import math
import time
from dataclasses import dataclass, field
from typing import Any, Literal

import numpy as np
from scipy.spatial.transform import Rotation

from palletpilot.geometry import SE2, SE3
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle, SemanticClass
from palletpilot.perception.instances import InstanceConfig, select_instance
from palletpilot.perception.pointcloud import check_intrinsics, class_mask
from palletpilot.perception.specs import PalletType

PALLET_CLASSES = (int(SemanticClass.PALLET_EMPTY), int(SemanticClass.PALLET_FULL))
"""Label ids of pallet pixels."""

_ON_DECK_CLASSES = (int(SemanticClass.CARGO), int(SemanticClass.OTHER_OBJECT), int(SemanticClass.PERSON))
"""Classes that may stand on a pallet's deck and hide it."""

NotFoundReason = Literal["too_few_points", "no_entry_face", "pockets_inconsistent", "not_where_expected"]


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
    pocket_width_tolerance_m: float = 0.025
    pocket_centre_tolerance_m: float = 0.025
    min_pocket_open: float = 0.4
    """Share of pocket-interior pixels that must see past the face."""
    min_column_solid: float = 0.6
    """Share of block-column pixels that must lie on the face."""
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
    instances: InstanceConfig = field(default_factory=InstanceConfig)
    """Instance separation and its gate, with `expected` (see `perception.instances`)."""


DEFAULT_CONFIG = PalletEstimatorConfig()


@dataclass(frozen=True)
class PalletSpread:
    """1-sigma uncertainty of a pallet estimate: x, y (m, forklift frame) and yaw (rad)."""

    x_m: float
    y_m: float
    yaw_rad: float

    def to_json(self) -> dict[str, float]:
        """`x_m`, `y_m` (m) and `yaw_deg`."""
        return {"x_m": round(self.x_m, 6), "y_m": round(self.y_m, 6), "yaw_deg": round(math.degrees(self.yaw_rad), 5)}


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


# -- the pallet model ------------------------------------------------------------------------------


@dataclass(frozen=True)
class _Model:
    """The entry side of a pallet type, in pallet-frame y (lateral) and z (height above the underside)."""

    width: float
    length: float
    height: float
    columns: np.ndarray  # (3, 2) block column (y_lo, y_hi), right to left
    block_top: float  # top of the block layer = pocket height
    cross_top: float  # top of the cross boards
    top_boards_thickness: float
    block_length: float
    top_boards: np.ndarray  # (B, 2) deck boards (y_lo, y_hi)
    pocket_width: float
    pocket_centres: np.ndarray  # (2,) (left, right)

    @classmethod
    def of(cls, p: PalletType) -> _Model:
        cols = np.array(p.column_bounds_y(), dtype=float)
        boards = np.array(sorted((part.lo[1], part.hi[1]) for part in p.parts() if part.kind == "top_board"))
        return cls(
            width=p.width,
            length=p.length,
            height=p.height,
            columns=cols,
            block_top=p.pocket_height,
            cross_top=p.pocket_height + p.cross_board_thickness,
            top_boards_thickness=p.top_board_thickness,
            block_length=p.block_length,
            top_boards=boards,
            pocket_width=p.pocket_width,
            pocket_centres=np.array(p.pocket_centres_y),
        )

    def solid(self, s: np.ndarray, h: np.ndarray, margin_s: np.ndarray | float, margin_h: float) -> np.ndarray:
        """Points (s, h) of the entry face at least the margins inside its solid parts."""
        out = np.zeros(np.broadcast(s, h).shape, bool)
        full = (np.abs(s) <= 0.5 * self.width - margin_s) & (h >= self.block_top + margin_h)
        out |= full & (h <= self.cross_top - margin_h)
        for lo, hi in self.top_boards:  # a deck board's front sits on the cross board's
            out |= (
                (s >= lo + margin_s)
                & (s <= hi - margin_s)
                & (h >= self.block_top + margin_h)
                & (h <= self.height - margin_h)
            )
        for lo, hi in self.columns:
            out |= (s >= lo + margin_s) & (s <= hi - margin_s) & (h >= margin_h) & (h <= self.height - margin_h)
        return out


def _wall_delta(s: np.ndarray, t: np.ndarray, intervals: np.ndarray, wall: float) -> np.ndarray:
    """Depth behind the face (m) where rays end on solid intervals of one layer, else inf.

    `s` (N, M): lateral position of each ray on the face plane relative to the pallet centre for M
    hypotheses; `t` (N, 1): lateral change per metre behind the face; `intervals` (K, 2) or
    (M, K, 2): solid (y_lo, y_hi) at the face, with side walls `wall` deep behind it.
    """
    iv = intervals if intervals.ndim == 3 else intervals[None]
    delta = np.full(np.broadcast_shapes(np.shape(s), np.shape(t), (iv.shape[0],)), np.inf)
    with np.errstate(divide="ignore", invalid="ignore"):
        inv_t = 1.0 / t
        for k in range(iv.shape[1]):
            lo, hi = iv[:, k, 0], iv[:, k, 1]
            for c in (lo, hi):  # a ray beside the interval moving towards it meets the wall at y = c
                d = (c - s) * inv_t
                d[(d <= 0) | (d > wall)] = np.inf
                np.minimum(delta, d, out=delta)
            delta[(s >= lo) & (s <= hi)] = 0.0
    return delta


def _wall_hits(s: np.ndarray, t: np.ndarray, intervals: np.ndarray, wall: float) -> tuple[np.ndarray, np.ndarray]:
    """`_wall_delta` and the lateral position (pallet y) of the side wall each ray ends on (NaN: none)."""
    delta = np.full(s.shape, np.inf)
    where = np.full(s.shape, np.nan)
    iv = intervals if intervals.ndim == 3 else intervals[None]
    with np.errstate(divide="ignore", invalid="ignore"):
        for k in range(iv.shape[1]):
            lo, hi = iv[:, k, 0], iv[:, k, 1]
            inside = (s >= lo) & (s <= hi)
            delta[inside] = 0.0
            # A ray left of the interval moving right meets its left wall (y = hi), and vice versa.
            for d, c in (((s - hi) / -t, hi), ((lo - s) / t, lo)):
                better = (d > 0) & (d <= wall) & (d < delta)
                delta = np.where(better, d, delta)
                where = np.where(better, np.broadcast_to(c, s.shape), where)
    return delta, where


@dataclass
class _Rays:
    """Pixels as rays in the forklift frame: direction `d` (N, 3) per unit camera depth, inverse depth `w`."""

    rows: np.ndarray
    cols: np.ndarray
    d: np.ndarray
    w: np.ndarray
    labelled: np.ndarray

    def subset(self, keep: np.ndarray) -> _Rays:
        return _Rays(self.rows[keep], self.cols[keep], self.d[keep], self.w[keep], self.labelled[keep])


def _rays(
    depth: np.ndarray, K: np.ndarray, R: np.ndarray, rows: np.ndarray, cols: np.ndarray, lab: np.ndarray
) -> _Rays:
    z = depth[rows, cols].astype(np.float64)
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    yc = (rows - cy) / fy
    xc = ((cols - cx) - skew * yc) / fx
    # Element-wise, not a BLAS product: right after Open3D's ray casting, a threaded BLAS call on two
    # cores oversubscribes them badly (see sim.camera).
    d = xc[:, None] * R[:, 0] + yc[:, None] * R[:, 1] + R[:, 2]
    return _Rays(rows, cols, d, 1.0 / z, lab)


@dataclass(frozen=True)
class _Plane:
    """Vertical plane in the forklift frame: w = A d_x + B d_y for rays from camera position `t`."""

    A: float
    B: float
    cov: np.ndarray  # (2, 2) covariance of (A, B)

    @property
    def psi(self) -> float:
        return math.atan2(self.B, self.A)

    @property
    def D(self) -> float:
        return 1.0 / math.hypot(self.A, self.B)

    @property
    def n(self) -> np.ndarray:
        return np.array([math.cos(self.psi), math.sin(self.psi), 0.0])

    @property
    def e(self) -> np.ndarray:
        """Lateral unit vector along the face (pallet y)."""
        return np.array([-math.sin(self.psi), math.cos(self.psi), 0.0])

    def predict(self, d: np.ndarray) -> np.ndarray:
        return self.A * d[:, 0] + self.B * d[:, 1]

    def point(self, cam: np.ndarray, s: float) -> np.ndarray:
        """The point (forklift frame, z = 0) on the plane at lateral coordinate `s`, for the camera at `cam`."""
        return self.n * (float(self.n @ cam) + self.D) + s * self.e


@dataclass
class _FaceCoords:
    """Rays expressed on the face plane: lateral `s`, height `h`, slopes behind it, inverse depths."""

    s: np.ndarray  # lateral coordinate (m) of the ray's intersection with the plane (pallet y + s0)
    h: np.ndarray  # height (m, forklift z) of that intersection
    t: np.ndarray  # lateral change per metre behind the face
    v: np.ndarray  # height change per metre behind the face (negative: looking down)
    nd: np.ndarray  # n . d: w on the face = nd / D
    w: np.ndarray
    D: float


def _face_coords(rays: _Rays, plane: _Plane, cam: np.ndarray) -> _FaceCoords:
    n, e = plane.n, plane.e
    d = rays.d
    nd = d[:, 0] * n[0] + d[:, 1] * n[1]
    with np.errstate(divide="ignore", invalid="ignore"):
        z_pl = plane.D / nd
        p = cam + rays.d * z_pl[:, None]
        s = p[:, 0] * e[0] + p[:, 1] * e[1]
        return _FaceCoords(s, p[:, 2], (d[:, 0] * e[0] + d[:, 1] * e[1]) / nd, d[:, 2] / nd, nd, rays.w, plane.D)


def _fit_plane(d: np.ndarray, w: np.ndarray, sigma: float) -> _Plane:
    X = d[:, :2]
    x, y = X[:, 0], X[:, 1]
    sxy = float(np.dot(x, y))
    XtX = np.array([[float(np.dot(x, x)), sxy], [sxy, float(np.dot(y, y))]])
    A, B = np.linalg.solve(XtX, [float(np.dot(x, w)), float(np.dot(y, w))])
    return _Plane(float(A), float(B), sigma * sigma * np.linalg.inv(XtX))


def _robust_sigma(r: np.ndarray, floor: float) -> float:
    if r.size == 0:
        return floor
    return max(float(1.4826 * np.median(np.abs(r - np.median(r)))), floor)


# -- scoring hypotheses ----------------------------------------------------------------------------


def _cost(
    fc: _FaceCoords, idx: np.ndarray, delta: np.ndarray, far_from: float, sigma: float, trunc: float
) -> np.ndarray:
    """Truncated chi-square (M,) of inverse-depth residuals for predicted depths `delta` (N, M) behind the face.

    Where the model predicts nothing within `far_from` of the face, only a measurement nearer than
    that counts against it.
    """
    nd = fc.nd[idx][:, None]
    w = fc.w[idx][:, None]
    hit = np.isfinite(delta)
    with np.errstate(invalid="ignore"):
        r_hit = (w - nd / (fc.D + np.where(hit, delta, 0.0))) / sigma
    r_far = np.maximum(w - nd / (fc.D + far_from), 0.0) / sigma
    r = np.where(hit, r_hit, r_far)
    return np.minimum(r * r, trunc * trunc).sum(axis=0)


def _best(grid: np.ndarray, cost: np.ndarray) -> tuple[float, float]:
    """Centre of the grid values whose cost is within 1 of the minimum (a ~1-sigma interval) and its half-width."""
    near = grid[cost <= cost.min() + 1.0]
    return float(0.5 * (near.min() + near.max())), float(0.5 * (near.max() - near.min()))


def _layer_delta(
    model: _Model, s_rel: np.ndarray, h_rel: np.ndarray, t: np.ndarray, v: np.ndarray, cols: np.ndarray
) -> np.ndarray:
    """Model depth behind the face (m, inf = far) for rays at (s_rel, h_rel) on the face plane.

    Covers the block layer (columns and their side walls), the cross board (full width) and the top
    board layer (deck boards with full-length side walls; between boards the ray may end on the cross
    board's top). Rays above the pallet end on the deck top when they meet a deck board.
    """
    delta = np.full(np.broadcast(s_rel, h_rel).shape, np.inf)
    block = h_rel < model.block_top
    if block.any():
        delta = np.where(block, _wall_delta(s_rel, t, cols, model.block_length), delta)
    cross = (h_rel >= model.block_top) & (h_rel < model.cross_top)
    if cross.any():
        d = _wall_delta(s_rel, t, np.array([[-0.5 * model.width, 0.5 * model.width]]), model.block_length)
        delta = np.where(cross, d, delta)
    top = h_rel >= model.cross_top
    if top.any():
        with np.errstate(divide="ignore", invalid="ignore"):
            d_boards = _wall_delta(s_rel, t, model.top_boards, model.length)
            in_gap_or_above = h_rel > model.cross_top
            d_cross = np.where(v < 0, (h_rel - model.cross_top) / -v, np.inf)
            d_cross = np.where(in_gap_or_above & (d_cross <= model.block_length), d_cross, np.inf)
            above = h_rel > model.height
            d_deck = np.where(v < 0, (h_rel - model.height) / -v, np.inf)
            s_hit = s_rel + t * d_deck
            on_board = np.zeros(np.broadcast(s_hit, h_rel).shape, bool)
            for lo, hi in model.top_boards:
                on_board |= (s_hit >= lo) & (s_hit <= hi)
            d_deck = np.where(above & on_board & (d_deck <= model.length), d_deck, np.inf)
            d_top = np.where(above, np.minimum(d_deck, d_cross), np.minimum(d_boards, d_cross))
        delta = np.where(top, d_top, delta)
    return delta


def _wall_pixels(
    model: _Model, fc: _FaceCoords, s0: float, z0: float, footprint: float
) -> tuple[np.ndarray, np.ndarray]:
    """Pixels the model puts on a side wall (pallet y = const), away from the wall's ends: mask and wall y."""
    s_rel, h_rel = fc.s - s0, fc.h - z0
    t = fc.t
    m = 0.5 * footprint + 0.003
    wall_y = np.full(len(s_rel), np.nan)
    layers = (
        ((m, model.block_top - m), model.columns, model.block_length),
        (
            (model.block_top + m, model.cross_top - m),
            np.array([[-0.5 * model.width, 0.5 * model.width]]),
            model.block_length,
        ),
        ((model.cross_top + m, model.height - m), model.top_boards, model.length),
    )
    with np.errstate(divide="ignore", invalid="ignore"):
        along = footprint / np.abs(t)  # a pixel's extent along a wall (m)
        for (h_lo, h_hi), intervals, wall in layers:
            sel = np.flatnonzero((h_rel >= h_lo) & (h_rel <= h_hi))
            if sel.size == 0:
                continue
            d, c = _wall_hits(s_rel[sel], t[sel], intervals, wall)
            ok = np.isfinite(d) & (d > 0.5 * along[sel]) & (d < wall - along[sel])
            # Where a deck gap or the layer's floor would end the ray first, it is no wall pixel.
            h_end = h_rel[sel] + fc.v[sel] * d
            ok &= h_end >= h_lo - m
            wall_y[sel[ok]] = c[ok]
    return np.isfinite(wall_y), wall_y


def _joint_refine(
    rays: _Rays,
    face: np.ndarray,
    wall: np.ndarray,
    wall_y: np.ndarray,
    plane: _Plane,
    s0: float,
    cam: np.ndarray,
    sigma: float,
    trunc: float,
) -> tuple[_Plane, float, np.ndarray, int]:
    """Gauss-Newton on (psi, D, s0): face pixels at w = n.d / D, side-wall pixels at w = e.d / (s0 + y - e.cam).

    Side walls (the pallet's sides, the insides of the pockets) run perpendicular to the face and
    seen at a slant pin the yaw far better than the face alone. Returns the plane, s0, the 3 x 3
    covariance of (psi, D, s0) and the number of wall pixels used.
    """
    d_face, w_face = rays.d[face], rays.w[face]
    d_wall, w_wall, y_wall = rays.d[wall], rays.w[wall], wall_y[wall]

    def predict(p: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        psi, D, s = p
        n = np.array([math.cos(psi), math.sin(psi)])
        e = np.array([-math.sin(psi), math.cos(psi)])
        with np.errstate(divide="ignore", invalid="ignore"):
            return d_face[:, :2] @ n / D, d_wall[:, :2] @ e / (s + y_wall - e @ cam[:2])

    p = np.array([plane.psi, plane.D, s0])
    keep_f = np.ones(len(w_face), bool)
    keep_w = np.ones(len(w_wall), bool)
    cov = np.diag([plane.cov[0, 0], 0.0, 0.0])
    for _ in range(4):
        f0, g0 = predict(p)
        rf, rw = w_face - f0, w_wall - g0
        keep_f = np.abs(rf) < trunc * sigma
        keep_w = np.isfinite(rw) & (np.abs(rw) < trunc * sigma)
        J = []
        for k, h in enumerate((1e-6, 1e-6, 1e-6)):
            dp = np.zeros(3)
            dp[k] = h
            f1, g1 = predict(p + dp)
            J.append(np.concatenate([(f1 - f0)[keep_f], (g1 - g0)[keep_w]]) / h)
        Jm = np.column_stack(J)
        r = np.concatenate([rf[keep_f], rw[keep_w]])
        JtJ = Jm.T @ Jm
        if np.linalg.cond(JtJ) > 1e14:
            break
        step = np.linalg.solve(JtJ, Jm.T @ r)
        p = p + step
        cov = sigma * sigma * np.linalg.inv(JtJ)
        if np.all(np.abs(step) < (1e-7, 1e-7, 1e-7)):
            break
    psi, D, s = p
    A, B = math.cos(psi) / D, math.sin(psi) / D
    return _Plane(A, B, plane.cov), float(s), cov, int(keep_w.sum())


# -- the estimator ---------------------------------------------------------------------------------


def _ransac(rays: _Rays, cfg: PalletEstimatorConfig, rng: np.random.Generator) -> tuple[_Plane, np.ndarray]:
    """Vertical plane with the best truncated-quadratic score, refined; returns it and the inlier mask."""
    n = len(rays.w)
    pick = rng.choice(n, min(n, cfg.ransac_max_pixels), replace=False) if n > cfg.ransac_max_pixels else np.arange(n)
    X, w = rays.d[pick, :2], rays.w[pick]
    i = rng.integers(0, len(pick), cfg.ransac_iterations)
    j = rng.integers(0, len(pick), cfg.ransac_iterations)
    a, b = X[i], X[j]
    det = a[:, 0] * b[:, 1] - a[:, 1] * b[:, 0]
    ok = np.abs(det) > 1e-4
    with np.errstate(divide="ignore", invalid="ignore"):
        A = (w[i] * b[:, 1] - w[j] * a[:, 1]) / det
        B = (a[:, 0] * w[j] - b[:, 0] * w[i]) / det
    ok &= np.abs(np.arctan2(B, A)) <= math.radians(cfg.max_yaw_deg)
    ok &= np.isfinite(A) & np.isfinite(B)
    if not ok.any():
        raise PalletNotFound("no_entry_face", "no vertical plane facing the forklift among the pallet pixels")
    A, B = A[ok], B[ok]
    thr = cfg.truncation_sigma * cfg.depth_noise_k
    r = w[:, None] - (X[:, :1] * A[None] + X[:, 1:] * B[None])
    score = np.minimum(r * r, thr * thr).sum(axis=0)
    k = int(np.argmin(score))
    plane = _Plane(float(A[k]), float(B[k]), np.zeros((2, 2)))
    inl = np.zeros(n, bool)
    for _ in range(10):  # shrink the band towards 3 sigma at most by half per step, refitting each time
        res = rays.w - plane.predict(rays.d)
        sigma = _robust_sigma(res[np.abs(res) < thr], cfg.min_sigma_w)
        thr = min(max(cfg.truncation_sigma * sigma, 0.5 * thr), thr)
        inl = np.abs(res) < thr
        if inl.sum() < 3:
            break
        plane = _fit_plane(rays.d[inl], rays.w[inl], 1.0)
    return plane, np.abs(rays.w - plane.predict(rays.d)) < thr


def _face_run(s: np.ndarray, max_gap: float) -> tuple[float, float]:
    """Lateral extent (lo, hi) of the largest run of face inliers (1 cm bins; gaps up to `max_gap` m, a
    pocket's width, are bridged: the cross boards above the pockets may be few pixels or eroded labels)."""
    lo, hi = float(s.min()), float(s.max())
    bins = np.arange(lo, hi + 0.02, 0.01)
    counts, _ = np.histogram(s, bins)
    occupied = counts >= max(2, int(0.05 * np.median(counts[counts > 0])))
    best, best_n, start = (0, 0), -1, None
    gap, end = 0, 0
    max_bins = math.ceil(max_gap / 0.01)
    for k, occ in enumerate([*occupied.tolist(), *([False] * (max_bins + 1))]):
        if occ:
            if start is None:
                start = k
            gap, end = 0, k
        elif start is not None:
            gap += 1
            if gap > max_bins:
                n = int(counts[start : end + 1].sum())
                if n > best_n:
                    best, best_n = (start, end), n
                start, gap = None, 0
    in_run = (s >= bins[best[0]]) & (s <= bins[best[1] + 1])
    return float(np.percentile(s[in_run], 1)), float(np.percentile(s[in_run], 99))


def _depth_edges(depth: np.ndarray, valid: np.ndarray, cfg: PalletEstimatorConfig) -> np.ndarray:
    """Pixels whose 3 x 3 neighbourhood spans a depth jump larger than noise explains (both sides of an edge)."""
    import cv2

    kernel = np.ones((3, 3), np.uint8)
    d = np.where(valid, depth, 0.0).astype(np.float32)
    d_max = cv2.dilate(d, kernel)
    d_min = cv2.erode(np.where(valid, d, np.float32(1e6)), kernel)
    rel = np.maximum(cfg.edge_jump_rel, cfg.edge_jump_sigma * cfg.depth_noise_k * d)
    return d_max > d_min * (1.0 + rel)


def _initial_underside(model: _Model, h: np.ndarray) -> float:
    """Underside height (m) whose face profile (solid width per height) best explains the inliers' heights."""
    step = 0.004
    lo, hi = float(np.percentile(h, 1)) - 0.06, float(np.percentile(h, 99)) + 0.06
    edges = np.arange(lo, hi + step, step)
    counts, _ = np.histogram(h, edges)
    centres = 0.5 * (edges[:-1] + edges[1:])
    best, best_ss = lo, np.inf
    for z0 in np.arange(lo, hi - model.height + 1e-9, 0.002):
        hr = centres - z0
        width = np.where((hr >= 0) & (hr < model.block_top), np.sum(np.diff(model.columns, axis=1)), 0.0)
        width = np.where((hr >= model.block_top) & (hr < model.cross_top), model.width, width)
        top = float(np.sum(np.diff(model.top_boards, axis=1)))
        width = np.where((hr >= model.cross_top) & (hr <= model.height), top, width)
        denom = float(width @ width)
        if denom <= 0:
            continue
        a = float(counts @ width) / denom
        ss = float(np.sum((counts - a * width) ** 2))
        if ss < best_ss:
            best, best_ss = float(z0), ss
    return best


def _roi(
    frame: FrameBundle,
    T_cf: SE3,
    plane: _Plane,
    cam: np.ndarray,
    s_range: tuple[float, float],
    h_range: tuple[float, float],
) -> tuple[slice, slice]:
    """Image rows and columns covering a rectangle on the face plane."""
    corners = np.array([plane.point(cam, s) + np.array([0, 0, h]) for s in s_range for h in h_range])
    if np.any(T_cf.inv().apply(corners)[:, 2] <= 0.05):
        raise PalletNotFound("no_entry_face", "the entry face would lie behind the camera")
    return _image_box(frame, T_cf, corners)


def _image_box(frame: FrameBundle, T_cf: SE3, corners: np.ndarray) -> tuple[slice, slice]:
    """Image rows and columns (clipped to the image) covering forklift-frame points, a few pixels wider.

    Points behind the camera are clipped to 5 cm in front of it (the box then reaches the image border).
    """
    pc = T_cf.inv().apply(corners)
    pc[:, 2] = np.maximum(pc[:, 2], 0.05)
    uv = pc[:, :2] / pc[:, 2:] * np.diag(frame.K)[:2] + frame.K[:2, 2]
    u0, v0 = np.floor(uv.min(axis=0)).astype(int) - 3
    u1, v1 = np.ceil(uv.max(axis=0)).astype(int) + 4
    return slice(max(v0, 0), max(min(v1, frame.height), 0)), slice(max(u0, 0), max(min(u1, frame.width), 0))


@dataclass(frozen=True)
class _DeckYaw:
    """Result of `_deck_yaw`: the yaw (rad) and its 1-sigma (rad), the deck pixels used, the deck height (m)."""

    psi: float
    sigma_psi: float
    n_pixels: int
    deck_height: float


def _deck_yaw(
    frame: FrameBundle,
    T_cf: SE3,
    valid: np.ndarray,
    model: _Model,
    plane: _Plane,
    s0: float,
    z0: float,
    sigma: float,
    cfg: PalletEstimatorConfig,
) -> _DeckYaw | None:
    """Yaw from the top deck's board edges, fused with the entry face's yaw; None where too little deck is seen.

    The deck boards run along the pallet's x axis for its whole length, so their side edges are long
    lines that turn with the pallet. A camera above the deck sees a board's top at the deck height
    (measured here from the deck pixels themselves), while past a board's edge a ray ends on the
    board's side wall or at least a board's thickness lower. For a yaw hypothesis (the pallet turned
    about the centre of its entry face, which the face and pockets fix) each deck pixel's inverse
    depth is predicted that way and scored by a truncated chi-square, plus the face fit's own term
    ((psi - psi_face) / sigma_face)^2. Occluders (a load on the deck: labelled cargo, or nearer than
    the deck) and pixels next to depth jumps are left out; label boundaries never place an edge.

    Each pixel's cost is tabulated against the lateral offset of its deck point (a turn by t moves a
    point x behind the face sideways by about -x t), so a hypothesis costs one lookup per pixel.
    The 1-sigma is the half-width of the yaws within 1 of the minimum cost, at least the turn that
    moves the deck's far end by a pixel's quantisation (footprint / sqrt(12)).
    """
    R, cam = T_cf.R, T_cf.t
    deck_h = z0 + model.height
    if cam[2] < deck_h + cfg.deck_min_camera_height_m or frame.labels is None:
        return None
    centre = plane.point(cam, s0)
    centre[2] = deck_h
    margin = 0.1
    corners = np.array(
        [
            centre + x * plane.n + y * plane.e
            for x in (cfg.deck_front_margin_m, model.length + margin)
            for y in (-0.5 * model.width - margin, 0.5 * model.width + margin)
        ]
    )
    rs, cs = _image_box(frame, T_cf, corners)
    if rs.stop - rs.start < 2 or cs.stop - cs.start < 2:
        return None
    sub_valid = valid[rs, cs]
    rr, cc = np.nonzero(sub_valid & ~_depth_edges(frame.depth[rs, cs], sub_valid, cfg))
    # A load on the deck hides it: pixels of what may stand on a pallet (and a margin around them for
    # label offsets) are left out; its lowest rows would otherwise pass for deck.
    cargo = class_mask(frame.labels[rs, cs], _ON_DECK_CLASSES)
    if cargo.any():
        import cv2

        k = 2 * cfg.deck_cargo_margin_px + 1
        cargo = cv2.dilate(cargo.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
        keep = ~cargo[rr, cc]
        rr, cc = rr[keep], cc[keep]
    rays = _rays(frame.depth, frame.K, R, rr + rs.start, cc + cs.start, np.ones(len(rr), bool))
    rays = rays.subset(rays.d[:, 2] < -1e-6)  # rays that go down
    z_deck = (deck_h - cam[2]) / rays.d[:, 2]  # camera z-depth where each ray meets the deck plane
    q = cam[:2] + rays.d[:, :2] * z_deck[:, None] - centre[:2]
    x_p, y_p = q @ plane.n[:2], q @ plane.e[:2]
    trunc = cfg.truncation_sigma
    use = (x_p >= cfg.deck_front_margin_m) & (x_p <= model.length + margin)
    use &= np.abs(y_p) <= 0.5 * model.width + margin
    use &= rays.w < 1.0 / z_deck + trunc * sigma  # nearer than the deck: something on or in front of it
    idx = np.flatnonzero(use)
    if idx.size < cfg.deck_min_pixels:
        return None
    # The deck's height from its own pixels: at a grazing view a millimetre of height moves the deck
    # points sideways by about a millimetre (their lateral over vertical ray slope), so the underside
    # found from the pocket edges (good to ~2 mm) is not enough. Weighted mean of the heights near the
    # deck, where a pixel's height sigma is |d_z| z^2 sigma_w.
    d_all, w_all = rays.d[idx], rays.w[idx]
    h_meas = cam[2] + d_all[:, 2] / w_all
    sigma_h = np.abs(d_all[:, 2]) * sigma / (w_all * w_all)
    band = 0.5 * model.top_boards_thickness
    for _ in range(3):
        on = np.abs(h_meas - deck_h) < np.clip(2.5 * sigma_h, 0.004, band)  # the first guess may be mm off
        if on.sum() < cfg.deck_min_pixels // 2:
            return None
        wt = 1.0 / np.maximum(sigma_h[on], 1e-5) ** 2
        deck_h = float(np.sum(wt * h_meas[on]) / np.sum(wt))
    d, w = d_all, w_all
    z_deck = (deck_h - cam[2]) / d[:, 2]
    q = cam[:2] + d[:, :2] * z_deck[:, None] - centre[:2]
    thick = model.top_boards_thickness
    w_low = 1.0 / ((deck_h - thick - cam[2]) / d[:, 2])  # a board's thickness below the deck
    sigma_face = math.sqrt(max(_yaw_variance(plane), 1e-12))
    psi_face = plane.psi
    span = min(4.0 * sigma_face, math.radians(cfg.deck_yaw_search_deg))
    step = cfg.deck_lateral_step_m
    reach = model.length * span + 2 * step  # largest lateral offset a hypothesis gives a pixel
    offsets = np.arange(-reach, reach + 0.5 * step, step)

    def table(psi_b: float) -> tuple[np.ndarray, np.ndarray]:
        """Pixel x in the pallet frame at yaw `psi_b`, and each pixel's cost per lateral offset (N, K).

        Only pixels whose cost changes with the offset are kept (far from every edge all yaws score alike).
        """
        n2 = np.array([math.cos(psi_b), math.sin(psi_b)])
        e2 = np.array([-n2[1], n2[0]])
        xh, yh = q @ n2, q @ e2
        slope_y = (d[:, :2] @ e2) / -d[:, 2]  # lateral change per metre of descent below the deck
        slope_x = (d[:, :2] @ n2) / -d[:, 2]
        descent = _wall_delta(yh[:, None] + offsets[None], slope_y[:, None], model.top_boards, thick)
        x_end = xh[:, None] + slope_x[:, None] * np.where(np.isfinite(descent), descent, 0.0)
        descent = np.where((x_end >= 0.0) & (x_end <= model.length), descent, np.inf)
        hit = np.isfinite(descent)
        w_hit = 1.0 / (z_deck[:, None] + np.where(hit, descent, 0.0) / -d[:, 2:3])
        r = np.where(hit, w[:, None] - w_hit, np.maximum(w - w_low, 0.0)[:, None]) / sigma
        cost = np.minimum(r * r, trunc * trunc)
        informative = np.ptp(cost, axis=1) > 1e-9
        return xh[informative], cost[informative]

    def total(dpsi: np.ndarray, dpsi_b: float, xh: np.ndarray, cost: np.ndarray) -> np.ndarray:
        u = -xh[:, None] * (dpsi[None] - dpsi_b)
        k = np.clip(np.rint((u + reach) / step).astype(int), 0, len(offsets) - 1)
        return cost[np.arange(len(xh))[:, None], k].sum(axis=0) + (dpsi / sigma_face) ** 2

    # Coarse search on the table at the face's yaw, then a fine one on a table rebuilt at that answer
    # (the rays' slopes in the pallet frame turn with the yaw).
    dpsi = 0.0
    for half in (span, 0.15 * span):
        xh, cost = table(psi_face + dpsi)
        grid = dpsi + np.linspace(-half, half, 41)
        tot = total(grid, dpsi, xh, cost)
        dpsi = float(grid[int(np.argmin(tot))])
    near_min = grid[tot <= tot.min() + 1.0]
    footprint_far = float(np.max(z_deck)) / float(frame.K[0, 0])
    sig = max(0.5 * float(np.ptp(near_min)), footprint_far / math.sqrt(12.0) / model.length)
    return _DeckYaw(psi_face + dpsi, min(sig, sigma_face), int(idx.size), deck_h)


def estimate_pallet(
    frame: FrameBundle,
    calibration: Calibration,
    pallet: PalletType | None = None,
    T_world_forklift: SE2 | None = None,
    config: PalletEstimatorConfig = DEFAULT_CONFIG,
    *,
    expected: SE2 | None = None,
) -> PalletEstimate:
    """The pose of the pallet in front of the forks from one labelled RGB-D frame.

    `calibration.T_forklift_camera_at(frame.fork_height)` places the camera; the result's
    `T_forklift_pallet` is the pallet frame (origin at the centre of the entry face on the underside,
    x into the pallet) in the forklift frame, `T_world_pallet` is added when `T_world_forklift` (SE2)
    is given. With `expected` (`T_forklift_pallet` on the floor, SE2: where the pallet should be, in
    the forklift frame) only the pallet instance whose entry face is nearest to it, within
    `config.instances.gate_m`, is fitted and other pallets' pixels are left out (`perception.instances`);
    without it every pallet-labelled pixel counts. Raises `PalletNotFound` (too few points, no entry
    face, pockets inconsistent, not where expected) and `PerceptionError` when the frame has no labels.
    """
    t_start = time.perf_counter()
    pallet = pallet or PalletType.eur()
    cfg = config
    model = _Model.of(pallet)
    if frame.labels is None:
        raise PerceptionError("estimate_pallet: the frame has no labels (segment its RGB first)")
    check_intrinsics(frame.K, "frame K")
    T_cf = calibration.T_forklift_camera_at(frame.fork_height)
    R, cam = T_cf.R, T_cf.t
    depth = frame.depth
    valid = np.isfinite(depth) & (depth > 0)
    labelled = class_mask(frame.labels, PALLET_CLASSES)
    rows, cols = np.nonzero(labelled & valid)
    if len(rows) < cfg.min_points:
        raise PalletNotFound("too_few_points", f"{len(rows)} pallet pixels with depth, need at least {cfg.min_points}")
    if expected is not None:  # 0. Only the expected pallet instance; other pallets' pixels are no evidence.
        jumps = _depth_edges(depth, valid, cfg)
        chosen = select_instance(frame, T_cf, labelled & valid, expected, jumps, cfg.instances)
        if chosen.target is None:
            raise PalletNotFound("not_where_expected", chosen.miss_message())
        valid &= ~chosen.foreign_mask
        rows, cols = np.nonzero(chosen.target_mask)
        if len(rows) < cfg.min_points:
            raise PalletNotFound("too_few_points", f"the expected pallet has {len(rows)} pixels with depth")
        found = {"instances": len(chosen.instances), "instance_distance_m": chosen.target.distance_m}
    else:
        found = {}
    rays = _rays(depth, frame.K, R, rows, cols, np.ones(len(rows), bool))
    rng = np.random.default_rng(cfg.seed)

    # 2. The entry face among the labelled pixels.
    plane, inl = _ransac(rays, cfg, rng)
    if inl.sum() < cfg.min_face_pixels:
        raise PalletNotFound(
            "no_entry_face", f"only {int(inl.sum())} pallet pixels on a vertical plane facing the forklift"
        )
    fc = _face_coords(rays.subset(inl), plane, cam)
    run_lo, run_hi = _face_run(fc.s, model.pocket_width + 0.03)
    if run_hi - run_lo < cfg.min_face_width_ratio * model.width:
        raise PalletNotFound(
            "no_entry_face",
            f"the vertical face is {1e3 * (run_hi - run_lo):.0f} mm wide, a {pallet.name} face is "
            f"{1e3 * model.width:.0f} mm",
        )
    in_run = (fc.s >= run_lo) & (fc.s <= run_hi)
    tall = float(np.percentile(fc.h[in_run], 95) - np.percentile(fc.h[in_run], 5))
    if tall < cfg.min_face_height_ratio * model.height:
        raise PalletNotFound(
            "no_entry_face",
            f"the vertical plane's pallet pixels span {1e3 * tall:.0f} mm in height, a {pallet.name} face "
            f"{1e3 * model.height:.0f} mm (a horizontal surface cut by a plane?)",
        )
    s0 = 0.5 * (run_lo + run_hi)
    z0 = _initial_underside(model, fc.h[in_run])
    sigma = _robust_sigma(fc.w[in_run] - fc.nd[in_run] / fc.D, cfg.min_sigma_w)
    half_range = max(cfg.lateral_search_m, 0.5 * abs((run_hi - run_lo) - model.width) + 0.02)

    trunc = cfg.truncation_sigma
    n_face = 0
    for round_ in range(cfg.rounds):
        # 3. Every pixel near the face, by geometry.
        rs, cs = _roi(
            frame,
            T_cf,
            plane,
            cam,
            (s0 - 0.5 * model.width - 0.3, s0 + 0.5 * model.width + 0.3),
            (z0 - 0.03, z0 + model.height + 0.03),
        )
        sub_valid = valid[rs, cs]
        rr, cc = np.nonzero(sub_valid)
        # Pixels at depth discontinuities may mix both sides (flying pixels): unknown, not evidence.
        steady = ~_depth_edges(depth[rs, cs], sub_valid, cfg)[rr, cc]
        rr, cc = rr + rs.start, cc + cs.start
        all_rays = _rays(depth, frame.K, R, rr, cc, labelled[rr, cc])
        fc = _face_coords(all_rays, plane, cam)
        footprint = plane.D / float(frame.K[0, 0])  # lateral size (m) of a pixel on the face, roughly

        # Lateral centre on the block layer.
        band = (fc.h - z0 >= 0.3 * model.block_top) & (fc.h - z0 <= 0.9 * model.block_top)
        band &= np.abs(fc.s - s0) <= 0.5 * model.width + 0.1
        idx = np.flatnonzero(band)
        if idx.size < cfg.min_face_pixels:
            raise PalletNotFound("no_entry_face", f"only {idx.size} pixels on the block layer of the face")
        t_idx = fc.t[idx][:, None]
        spans = (
            ((half_range, 0.003), (0.004, 0.0005)) if round_ == 0 else ((4 * footprint + 0.01, 0.002), (0.003, 0.00025))
        )
        for span, step in spans:
            grid = s0 + np.arange(-span, span + 1e-12, step)
            delta = _wall_delta(fc.s[idx][:, None] - grid[None], t_idx, model.columns, model.block_length)
            s0, _ = _best(grid, _cost(fc, idx, delta, model.block_length, sigma, trunc))

        # Underside height from the pockets' upper edges.
        pk = steady.copy()
        pocket_any = np.zeros(len(fc.s), bool)
        for c in model.pocket_centres:
            pocket_any |= np.abs(fc.s - s0 - c) <= 0.5 * model.pocket_width - 0.01
        pk &= pocket_any
        hr = fc.h - z0
        pk &= (hr >= model.block_top - 0.05) & (hr <= model.block_top + 0.02)
        idx = np.flatnonzero(pk)
        if idx.size >= cfg.min_face_pixels // 2:
            vspan = cfg.vertical_search_m if round_ == 0 else 3 * footprint
            vgrid = z0 + np.arange(-vspan, vspan + 1e-12, 0.001 if round_ == 0 else 0.0002)
            h_rel = fc.h[idx][:, None] - vgrid[None]
            s_rel = fc.s[idx][:, None] - s0
            delta = _layer_delta(model, s_rel, h_rel, fc.t[idx][:, None], fc.v[idx][:, None], model.columns)
            vcost = _cost(fc, idx, delta, model.block_length, sigma, trunc)
            z0, _ = _best(vgrid, vcost)

        # Refit the plane on pixels the model puts on the solid face.
        margin = cfg.face_margin_px * footprint + cfg.face_margin_m
        on_face = model.solid(fc.s - s0, fc.h - z0, margin, margin)
        res = fc.w - fc.nd / fc.D
        # The lateral centre as a point on the face: `s` is measured along the plane's lateral axis from
        # the forklift origin, so a new plane (another yaw) needs it re-expressed, or the pallet model
        # slides sideways by D * (change of yaw) (11 cm for 1.6 deg at 4 m).
        centre = plane.point(cam, s0)
        for _ in range(3):
            use = on_face & (np.abs(res) < trunc * sigma)
            if use.sum() < cfg.min_face_pixels:
                raise PalletNotFound("no_entry_face", f"only {int(use.sum())} pixels on the modelled entry face")
            plane = _fit_plane(all_rays.d[use], all_rays.w[use], sigma)
            res = all_rays.w - plane.predict(all_rays.d)
            sigma = _robust_sigma(res[use], cfg.min_sigma_w)
        plane = _fit_plane(all_rays.d[use], all_rays.w[use], sigma)
        s0 = float(plane.e @ centre)
        n_face = int(use.sum())
        # Optionally side walls seen at a slant: one fit of face and walls together.
        n_wall = 0
        if cfg.side_walls:
            fc = _face_coords(all_rays, plane, cam)
            wall, wall_y = _wall_pixels(model, fc, s0, z0, footprint)
            n_wall = int(wall.sum())
        if cfg.side_walls and n_wall >= cfg.min_wall_pixels:
            plane, s0, cov3, n_wall = _joint_refine(all_rays, use, wall, wall_y, plane, s0, cam, sigma, trunc)
        else:
            cov3 = None
        if abs(plane.psi) > math.radians(cfg.max_yaw_deg):
            raise PalletNotFound(
                "no_entry_face", f"the face turns {math.degrees(plane.psi):.1f} deg away from the forks"
            )

    # 4. The pockets, edge by edge.
    fc = _face_coords(all_rays, plane, cam)
    footprint = plane.D / float(frame.K[0, 0])
    hr = fc.h - z0
    band = (hr >= 0.3 * model.block_top) & (hr <= 0.9 * model.block_top) & steady
    edges = []
    inner = [(0, 1), (1, 0), (1, 1), (2, 0)]  # (column, side): right pocket then left pocket
    for col, side in inner:
        y_edge = model.columns[col, side]
        idx = np.flatnonzero(band & (np.abs(fc.s - s0 - y_edge) <= cfg.edge_search_m + 0.12))
        if idx.size < 10:
            raise PalletNotFound("pockets_inconsistent", f"no pixels near the block edge at y = {y_edge:+.3f} m")
        s_rel = fc.s[idx][:, None] - s0
        e = 0.0
        for span, step in ((cfg.edge_search_m, 0.002), (0.0025, 0.00025)):
            egrid = e + np.arange(-span, span + 1e-12, step)
            cols_h = np.broadcast_to(model.columns, (len(egrid), 3, 2)).copy()
            cols_h[:, col, side] += egrid
            delta = _wall_delta(s_rel, fc.t[idx][:, None], cols_h, model.block_length)
            e, _ = _best(egrid, _cost(fc, idx, delta, model.block_length, sigma, trunc))
        edges.append(y_edge + e)
    right_w, left_w = edges[1] - edges[0], edges[3] - edges[2]
    right_c, left_c = 0.5 * (edges[0] + edges[1]), 0.5 * (edges[2] + edges[3])
    _check_pockets(model, cfg, fc, s0, z0, band, sigma, (left_w, right_w), (left_c, right_c))
    centre_offset = 0.5 * (left_c + right_c)  # pocket-based centre relative to the model fit
    s0 += centre_offset
    pocket_resid = np.array(
        [left_c - centre_offset - model.pocket_centres[0], right_c - centre_offset - model.pocket_centres[1]]
    )
    edge_sigma = max(float(np.sqrt(np.mean(pocket_resid**2))), footprint / math.sqrt(12.0))
    # Two pocket centres; floored at half a pixel footprint, which matches the benchmark's scatter.
    sigma_s = max(edge_sigma / math.sqrt(2.0), 0.5 * footprint)

    # 5. The top deck's board edges, where the camera sees the deck: turn the plane about the face centre.
    deck = _deck_yaw(frame, T_cf, valid, model, plane, s0, z0, sigma, cfg) if cfg.deck_yaw else None
    if deck is not None:
        centre = plane.point(cam, s0)
        n_new = np.array([math.cos(deck.psi), math.sin(deck.psi), 0.0])
        D_new = float(n_new @ (centre - cam))
        plane = _Plane(n_new[0] / D_new, n_new[1] / D_new, plane.cov)
        s0 = float(plane.e @ centre)

    # Pose and spread.
    psi, D = plane.psi, plane.D
    origin = plane.point(cam, s0)
    T_fp = SE3(Rotation.from_euler("z", psi), (origin[0], origin[1], z0))
    sx, sy, syaw = _spread(plane, cam, s0, sigma_s, cov3)
    if deck is not None:
        syaw = deck.sigma_psi
    res = all_rays.w - plane.predict(all_rays.d)
    estimate = PalletEstimate(
        T_forklift_pallet=T_fp,
        spread=PalletSpread(sx, sy, syaw),
        n_points=len(rows),
        n_face_points=n_face,
        pocket_widths_m=(float(left_w), float(right_w)),
        pocket_centres_y_m=(float(left_c - centre_offset), float(right_c - centre_offset)),
        residual_rms_w=float(sigma),
        T_world_pallet=None if T_world_forklift is None else T_world_forklift.to_se3() @ T_fp,
        runtime_ms=(time.perf_counter() - t_start) * 1e3,
        extras={
            "lateral_fit_m": float(s0 - centre_offset),
            "face_distance_m": D,
            "plane_residual_rms": float(np.sqrt(np.mean(res[np.abs(res) < trunc * sigma] ** 2))),
            "deck_pixels": 0 if deck is None else deck.n_pixels,
            "deck_height_m": None if deck is None else deck.deck_height,
            **found,
        },
    )
    return estimate


def _check_pockets(
    model: _Model,
    cfg: PalletEstimatorConfig,
    fc: _FaceCoords,
    s0: float,
    z0: float,
    band: np.ndarray,
    sigma: float,
    widths: tuple[float, float],
    centres: tuple[float, float],
) -> None:
    """Raise `PalletNotFound("pockets_inconsistent")` unless the gaps in the face match the pallet type."""
    s_rel = fc.s - s0
    # Occupancy: the middle of each pocket must see past the face, the middle of each column must be on it.
    res = fc.w - fc.nd / fc.D
    on_face = np.abs(res) < cfg.truncation_sigma * sigma
    # Rays the model sends into the pocket (not onto a block's side wall, seen at a slant).
    into_pocket = ~np.isfinite(_wall_delta(s_rel, fc.t, model.columns, model.block_length))
    for name, c in (("left", model.pocket_centres[0]), ("right", model.pocket_centres[1])):
        m = band & into_pocket & (np.abs(s_rel - c) <= 0.25 * model.pocket_width)
        if m.sum() >= 5:
            open_share = 1.0 - float(on_face[m].mean())
            if open_share < cfg.min_pocket_open:
                raise PalletNotFound(
                    "pockets_inconsistent",
                    f"the {name} pocket is closed: only {100 * open_share:.0f} % of its pixels see past the entry face",
                )
    for lo, hi in model.columns:
        m = band & (np.abs(s_rel - 0.5 * (lo + hi)) <= 0.25 * (hi - lo))
        if m.sum() >= 5 and float(on_face[m].mean()) < cfg.min_column_solid:
            raise PalletNotFound(
                "pockets_inconsistent",
                f"the block column at y = {0.5 * (lo + hi):+.3f} m is missing: "
                f"{100 * float(on_face[m].mean()):.0f} % on the face",
            )
    for name, w in (("left", widths[0]), ("right", widths[1])):
        if abs(w - model.pocket_width) > cfg.pocket_width_tolerance_m:
            raise PalletNotFound(
                "pockets_inconsistent",
                f"the {name} pocket is {1e3 * w:.0f} mm wide, the pallet type's are {1e3 * model.pocket_width:.1f} mm",
            )
    spacing = centres[0] - centres[1]
    expected = model.pocket_centres[0] - model.pocket_centres[1]
    if abs(spacing - expected) > cfg.pocket_centre_tolerance_m:
        raise PalletNotFound(
            "pockets_inconsistent",
            f"the pocket centres are {1e3 * spacing:.0f} mm apart, the pallet type's {1e3 * expected:.1f} mm",
        )


def _spread(
    plane: _Plane, cam: np.ndarray, s0: float, sigma_s: float, cov3: np.ndarray | None
) -> tuple[float, float, float]:
    """1-sigma of the pallet origin's x, y (m, forklift frame) and yaw (rad).

    Along the face normal: the plane fit's inverse-depth uncertainty at the origin's ray; along the
    face: `sigma_s` from the pocket edges (the edges fix a point on the face whatever the yaw); yaw:
    the plane fit's covariance (`cov3`, of psi, D and s0, when the joint fit ran).
    """
    n, e = plane.n, plane.e
    origin = plane.point(cam, s0)
    u = (origin - cam) / float(np.linalg.norm(origin - cam))  # unit ray to the origin
    lam = float(np.linalg.norm(origin - cam))  # 1 / lam = A u_x + B u_y on the plane
    sigma_lam = lam * lam * math.sqrt(max(float(u[:2] @ plane.cov @ u[:2]), 0.0))
    sigma_n = float(n @ u) * sigma_lam
    cov_xy = sigma_n**2 * np.outer(n[:2], n[:2]) + sigma_s**2 * np.outer(e[:2], e[:2])
    var_yaw = float(cov3[0, 0]) if cov3 is not None else _yaw_variance(plane)
    return math.sqrt(cov_xy[0, 0]), math.sqrt(cov_xy[1, 1]), math.sqrt(max(var_yaw, 0.0))


def _yaw_variance(plane: _Plane) -> float:
    """Variance (rad^2) of the plane's yaw from the covariance of (A, B)."""
    A, B = plane.A, plane.B
    r2 = A * A + B * B
    grad = np.array([-B / r2, A / r2])  # d psi / d (A, B)
    return float(grad @ plane.cov @ grad)


def fuse_estimates(estimates: list[PalletEstimate]) -> PalletEstimate:
    """One estimate from several frames of a standing pallet, each weighted by its spread.

    x, y (forklift frame, and the world frame where every estimate has `T_world_pallet`) and yaw are
    inverse-variance weighted means (the spreads come from each frame's fit, so a frame that sees
    less counts less); the height is the plain mean. The spread of the result is that of the
    weighted mean, 1 / sqrt(sum of 1 / sigma^2). All estimates must be of the same pallet from the
    same standpoint (the forklift frame does not move between them).
    """
    if not estimates:
        raise ValueError("fuse_estimates: no estimates")
    if len(estimates) == 1:
        return estimates[0]

    # Precisions (1 / sigma^2) per frame of x, y and yaw; normalised, they are the weights.
    px, py, pyaw = (
        1.0 / np.maximum(np.array([getattr(e.spread, k) for e in estimates]), 1e-9) ** 2
        for k in ("x_m", "y_m", "yaw_rad")
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

    spread = PalletSpread(*(float(1.0 / math.sqrt(p.sum())) for p in (px, py, pyaw)))
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
