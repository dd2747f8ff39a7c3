"""Pallet instances in one labelled RGB-D frame, and the one where the mission expects its pallet.

Segmentation labels say *pallet* (empty or full), not *which* pallet: in a staging lane the target
stands 0.2 m from its neighbours (EUR pallets 0.8 m wide, 1.0 m centre to centre) and every one of
their pixels carries the same labels. This module splits the pallet pixels into instances and picks
the one standing where the pallet is expected; `perception.pallet.estimate_pallet(..., expected=...)`
fits only that instance and keeps every other instance's pixels out of its fit.

Frames (ARCHITECTURE.md): `camera` optical (x right, y down, z forward); `forklift` (origin on the
floor between the fork heels, x towards the tips, y left, z up); `pallet` (origin at the centre of
the entry face on the underside, x into the pallet, y left). The expected pose is
`T_forklift_pallet` as an SE2 on the floor. SI units.

Method:

1. **Pieces.** Pallet-labelled pixels with depth, minus the pixels next to a depth jump (`edges`,
   from the caller), are split into 8-connected components of the image (OpenCV). Two pallets side
   by side are not connected: between them the camera sees the floor (not labelled pallet) or, past
   one pallet's edge, the other one's side face well behind it, a depth jump whose pixels on both
   sides are left out (flying pixels sit on such jumps and go with them). In the image, depth noise
   cannot bridge the gap as it would in a point cloud, where at 4 m a D435's depth sigma (7 cm
   along the ray) is larger than the gap of a misplaced pallet to its neighbour (5 cm).
2. **Instances.** Pieces of at least `min_pixels` pixels. Smaller ones (the back of a pocket seen
   through it, label noise, a pallet cut by the image border) belong to no instance and stay as they
   are (evidence like any unlabelled pixel).
3. **Entry-face centre** of each instance, in the forklift frame: its points put in the expected
   pallet's axes, the front is the near end along x (`front_percentile`), the lateral centre the
   middle (`side_percentile` to its complement) of the points within `front_band_m` of the front.
   A rough point (centimetres), it only decides which instance is meant.
4. **Selection.** Of the instances whose entry-face centre is inside the gate around the expected
   pallet origin, the largest (a short pallet's deck scraps can stand nearer to it than its front);
   the gate is `InstanceConfig.gate` (the misplacement envelope plus a margin on each axis, across never
   as far as a lane neighbour's near edge). With none inside, none, and `InstanceSelection.miss_message`
   says how far the nearest pallet seen is from where it was expected.

Limits: pallets whose faces touch with no depth jump between them (no gap, one plane) are one
piece; a pallet cut in two by an occluder in front of it gives two pieces, of which only one is fitted.

Public API:
- `InstanceConfig`: the tuning (distances in m, pixel counts).
- `PalletInstance`: one instance: pixel mask, pixel count, entry-face centre (forklift frame) and
  its distance to the expected pose.
- `InstanceSelection`: every instance (nearest first), the selected one or None, the pixel masks
  for the fit (`target_mask`, `foreign_mask`), `miss_message()`.
- `find_instances(frame, T_forklift_camera, mask, expected, edges, config)`: the instances.
- `select_instance(frame, T_forklift_camera, mask, expected, edges, config)`: the instances and the
  one expected.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from palletpilot.geometry import SE2, SE3
from palletpilot.perception.frames import FrameBundle


@dataclass(frozen=True)
class InstanceConfig:
    """Tuning of the instance separation and selection (distances in m)."""

    min_pixels: int = 100
    """Fewest pixels of a piece to count as a pallet instance (a loaded EUR face at 4 m has ~1300)."""
    gate_margin_m: float = 0.15
    """The gate (`gate`) is the envelope plus this on each axis: the rough entry-face centre of a pallet
    turned 15 deg is off by up to ~0.12 m on each (its near corner leads the face by 0.4 sin 15 = 0.10 m and
    the front band's centre leans towards it; `tests/test_right_pallet.py` sees 0.52 m along and across at
    the +-0.40 m corner) ..."""
    gate_lateral_max_m: float = 0.58
    """... but never more than this across: a lane neighbour (1.0 m centre to centre, 0.8 m wide) has its
    near edge 0.6 m from the expected centre line, so any piece of it seen (cut by the image border, its
    rough centre can be 0.74 m away) stays out when the slot is empty."""
    front_percentile: float = 2.0
    """Percentile of the points along the expected x axis taken as the instance's front."""
    front_band_m: float = 0.15
    """Points within this of the front give the lateral centre (the entry face of a pallet turned 15 deg)."""
    side_percentile: float = 2.0
    """Percentile of those points' lateral positions taken as each side (and its complement)."""
    support_percentile: float = 1.0
    """Percentile of a piece's heights taken as the surface it stands on (floor or beams) ..."""
    support_band_m: float = 0.03
    """... and the band above it left out of the pieces: labels grown onto the floor join a pallet's foot
    to its neighbour's across the floor seen between them (heights at 4 m have a sigma of ~8 mm)."""
    merge_band_px: int = 8
    """Pieces at most this many pixels apart in a row, with only pallet pixels between, may join ..."""
    merge_jump_rel: float = 0.05
    """... if the median relative depth difference across is at most this (a deck gap: ~0; a neighbour
    seen past the pallet's edge 5 cm away: 9 % or more) ..."""
    merge_min_pairs: int = 5
    """... over at least this many pixel pairs."""
    assign_radius_m: float = 0.05
    """Pixels outside the pieces (support band, depth jumps, scraps) join the instance with a point this near."""
    foreign_margin_px: int = 2
    """Other instances' pixel masks are grown by this many pixels (label noise) to keep them out of the fit."""

    def gate(self, lateral_m: float, longitudinal_m: float) -> Gate:
        """The selection gate for a pallet expected within +-`lateral_m` and +-`longitudinal_m` (m) of its
        node: the envelope plus `gate_margin_m` on each axis, across at most `gate_lateral_max_m`."""
        if lateral_m < 0.0 or longitudinal_m < 0.0:
            raise ValueError(f"envelope {lateral_m} m x {longitudinal_m} m: must not be negative")
        lateral = min(lateral_m + self.gate_margin_m, self.gate_lateral_max_m)
        return Gate(longitudinal_m + self.gate_margin_m, lateral)


@dataclass(frozen=True)
class Gate:
    """How far an instance's rough entry-face centre may stand from the expected pallet origin, along the
    expected pallet's x axis (`longitudinal_m`) and across it (`lateral_m`), in m."""

    longitudinal_m: float
    lateral_m: float

    def admits(self, offset: tuple[float, float]) -> bool:
        """Whether `offset` (along, across the expected pallet's axes; m) is inside the gate."""
        return abs(offset[0]) <= self.longitudinal_m and abs(offset[1]) <= self.lateral_m

    def __str__(self) -> str:
        return f"+-{self.longitudinal_m:.2f} m along, +-{self.lateral_m:.2f} m across"


@dataclass(frozen=True)
class PalletInstance:
    """One pallet seen in the frame.

    `mask` (H, W): its pixels (pallet-labelled, with depth, away from depth jumps); `entry_centre`:
    forklift-frame (x, y) in m of its rough entry-face centre on the floor; `distance_m`: from there
    to the expected pallet origin; `offset`: the same along and across the expected pallet's axes (m).
    """

    mask: np.ndarray
    n_pixels: int
    entry_centre: np.ndarray
    distance_m: float
    offset: tuple[float, float]


@dataclass(frozen=True)
class InstanceSelection:
    """The instances of a frame and the one expected.

    `instances`: nearest to `expected` first; `target`: the largest inside `gate`, else None.
    `target_mask` (H, W): the pixels to fit (the target's, with the pallet-labelled pixels next to
    it on depth jumps; empty without a target); `foreign_mask` (H, W): the other instances' pixels,
    grown by the margin, never the target's: left out of the fit altogether.
    """

    expected: SE2
    instances: tuple[PalletInstance, ...]
    target: PalletInstance | None
    gate: Gate
    target_mask: np.ndarray
    foreign_mask: np.ndarray

    @property
    def nearest(self) -> PalletInstance | None:
        """The instance nearest to the expected pose, if any."""
        return self.instances[0] if self.instances else None

    def miss_message(self) -> str:
        """Why no instance was selected: how far the nearest pallet seen is from where it was expected."""
        where = f"x {self.expected.x:.2f} m, y {self.expected.y:+.2f} m in the forklift frame"
        nearest = self.nearest
        if nearest is None:
            return f"no pallet instance seen at all; one was expected at {where}"
        x, y = (float(v) for v in nearest.entry_centre)
        others = f" ({len(self.instances)} pallets seen)" if len(self.instances) > 1 else ""
        return (
            f"the nearest pallet seen is {nearest.distance_m:.2f} m from where it was expected "
            f"({where}; its entry face at x {x:.2f} m, y {y:+.2f} m; gate {self.gate}){others}"
        )


def _points(frame: FrameBundle, T_forklift_camera: SE3, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Forklift-frame points (N, 3) of pixels with depth."""
    K = frame.K
    z = frame.depth[rows, cols].astype(np.float64)
    yc = (rows - K[1, 2]) / K[1, 1]
    xc = ((cols - K[0, 2]) - K[0, 1] * yc) / K[0, 0]
    R, t = T_forklift_camera.R, T_forklift_camera.t
    # Element-wise, not a BLAS product (see perception.pallet_face._rays: threaded BLAS after Open3D ray casting).
    return t + (xc * z)[:, None] * R[:, 0] + (yc * z)[:, None] * R[:, 1] + z[:, None] * R[:, 2]


def _entry_centre(points: np.ndarray, expected: SE2, cfg: InstanceConfig) -> np.ndarray:
    """Rough entry-face centre (forklift x, y) of an instance's points, in the expected pallet's axes."""
    c, s = math.cos(expected.yaw), math.sin(expected.yaw)
    dx, dy = points[:, 0] - expected.x, points[:, 1] - expected.y
    along, lateral = c * dx + s * dy, -s * dx + c * dy
    front = float(np.percentile(along, cfg.front_percentile))
    band = lateral[along <= front + cfg.front_band_m]
    lo, hi = np.percentile(band, (cfg.side_percentile, 100.0 - cfg.side_percentile))
    mid = 0.5 * float(lo + hi)
    return np.array([expected.x + c * front - s * mid, expected.y + s * front + c * mid])


def _merge_pieces(comp: np.ndarray, n: int, depth: np.ndarray, cfg: InstanceConfig) -> np.ndarray:
    """Group ids (n,) of the image components `comp` (0: none): pieces of one pallet joined across thin breaks.

    Two pieces join where, in one image row, pixels of theirs at most `merge_band_px` apart see
    depths within `merge_jump_rel` of each other (median over their pairs, at least `merge_min_pairs`)
    and every pixel between them lies within that band too (or has no depth): the same surface
    broken by label noise or a few stray edge pixels (a far pallet's face above the pockets is 3
    pixels tall). Across the floor between two pallets or a deck gap the camera sees farther; a
    neighbour seen past the pallet's edge is much deeper (a 5 cm gap: 9 % or more).
    """
    rows = np.flatnonzero((comp > 0).any(axis=1))
    if rows.size == 0:
        return np.arange(n)
    sub = comp[rows[0] : rows[-1] + 1]
    z = depth[rows[0] : rows[-1] + 1].astype(np.float32)
    has = np.isfinite(z) & (z > 0)
    z_hi = np.where(has, z, np.float32(0.0))  # no depth: never the largest ...
    z_lo = np.where(has, z, np.float32(np.inf))  # ... nor the smallest between two pixels
    t = cfg.merge_jump_rel
    keys, rel = [], []
    for step in range(2, cfg.merge_band_px + 1):  # horizontal neighbours are one component already
        a, b = sub[:, :-step], sub[:, step:]
        m = (a > 0) & (b > 0) & (a != b)
        if not m.any():
            continue
        kernel = np.ones((1, step - 1), np.uint8)  # anchored left: column c + 1 holds the pixels strictly between
        anchor = (0, 0)
        between_hi = cv2.dilate(z_hi, kernel, anchor=anchor, borderType=cv2.BORDER_REPLICATE)[:, 1 : 1 - step]
        between_lo = cv2.erode(z_lo, kernel, anchor=anchor, borderType=cv2.BORDER_REPLICATE)[:, 1 : 1 - step]
        za, zb = z[:, :-step], z[:, step:]
        near, far = np.minimum(za, zb), np.maximum(za, zb)
        m &= (between_hi <= far * (1 + t)) & (between_lo >= near / (1 + t))
        if not m.any():
            continue
        ia, ib = a[m].astype(np.int64), b[m].astype(np.int64)
        keys.append(np.minimum(ia, ib) * n + np.maximum(ia, ib))
        rel.append((far[m] - near[m]) / near[m])
    if not keys:
        return np.arange(n)
    key, r = np.concatenate(keys), np.concatenate(rel)
    order = np.argsort(key, kind="stable")
    key, r = key[order], r[order]
    uniq, first, count = np.unique(key, return_index=True, return_counts=True)
    join = [
        int(k)
        for k, f, c in zip(uniq, first, count, strict=True)
        if c >= cfg.merge_min_pairs and float(np.median(r[f : f + c])) <= t
    ]
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    j = np.array(join, np.int64)
    graph = coo_matrix((np.ones(len(j)), (j // n, j % n)), shape=(n, n))
    _, group = connected_components(graph, directed=False)
    return np.asarray(group)


def _pieces(mask: np.ndarray, depth: np.ndarray, cfg: InstanceConfig) -> tuple[np.ndarray, np.ndarray]:
    """Image components of `mask` joined by `_merge_pieces`: group id per pixel of `mask` (H, W; -1: none) and
    the pixel count per group."""
    n, comp = cv2.connectedComponents(mask.astype(np.uint8), connectivity=8)
    group = _merge_pieces(comp, n, depth, cfg)
    group[0] = -1  # background (its own component in the graph: it was never joined)
    ids = np.where(mask, group[comp], -1)
    counts = np.bincount(ids[ids >= 0], minlength=int(group.max()) + 1)
    return ids, counts


def find_instances(
    frame: FrameBundle,
    T_forklift_camera: SE3,
    mask: np.ndarray,
    expected: SE2,
    edges: np.ndarray | None = None,
    config: InstanceConfig | None = None,
) -> list[PalletInstance]:
    """The pallet instances among the pixels of `mask` (H, W: pallet-labelled with depth), nearest to `expected` first.

    `T_forklift_camera`: the camera at the frame's fork height; `expected`: `T_forklift_pallet` (SE2)
    where the pallet should be, whose axes measure the entry-face centres and whose origin the
    distances; `edges` (H, W): pixels next to a depth jump, left out of the pieces (None: none).
    """
    cfg = config or InstanceConfig()
    depth = frame.depth
    m_rows, m_cols = np.nonzero(mask)
    pts = _points(frame, T_forklift_camera, m_rows, m_cols)
    # Pass 1: connected pallet pixels (neighbours, too, may be joined here); each group's support (its
    # lowest points, floor or beams) and the band above it go.
    ids, counts = _pieces(mask, depth, cfg)
    at = ids[m_rows, m_cols]
    low = np.zeros(len(m_rows), bool)
    for k in np.flatnonzero(counts >= cfg.min_pixels):
        sel = at == k
        z = pts[sel, 2]
        low[sel] = z < np.percentile(z, cfg.support_percentile) + cfg.support_band_m
    # Pass 2: the pieces away from depth jumps and the support, joined across thin bands, are the instances.
    cand = np.zeros(mask.shape, bool)
    cand[m_rows[~low], m_cols[~low]] = True
    if edges is not None:
        cand &= ~edges
    ids, counts = _pieces(cand, depth, cfg)
    big = np.flatnonzero(counts >= cfg.min_pixels)
    if big.size == 0:
        return []
    which = np.full(len(counts), -1)
    which[big] = np.arange(len(big))
    at = ids[m_rows, m_cols]
    owner = np.where(at >= 0, which[np.maximum(at, 0)], -1)  # instance of each pixel of `mask`, -1: none
    core = owner >= 0
    # The rest of `mask` (support band, depth jumps, scraps) goes with the instance nearest in space,
    # if one is within `assign_radius_m`.
    rest = np.flatnonzero(~core)
    if rest.size:
        from scipy.spatial import cKDTree

        inst = np.flatnonzero(core)
        dist, near = cKDTree(pts[inst]).query(pts[rest], distance_upper_bound=cfg.assign_radius_m)
        ok = np.isfinite(dist)
        owner[rest[ok]] = owner[inst[near[ok]]]
    found = []
    for i in range(len(big)):
        centre = _entry_centre(pts[core & (owner == i)], expected, cfg)
        own = owner == i
        inst_mask = np.zeros(mask.shape, bool)
        inst_mask[m_rows[own], m_cols[own]] = True
        dx, dy = centre[0] - expected.x, centre[1] - expected.y
        c, s = math.cos(expected.yaw), math.sin(expected.yaw)
        offset = (float(c * dx + s * dy), float(-s * dx + c * dy))
        found.append(PalletInstance(inst_mask, int(own.sum()), centre, math.hypot(dx, dy), offset))
    return sorted(found, key=lambda inst: inst.distance_m)


def select_instance(
    frame: FrameBundle,
    T_forklift_camera: SE3,
    mask: np.ndarray,
    expected: SE2,
    edges: np.ndarray | None = None,
    config: InstanceConfig | None = None,
    *,
    gate: Gate,
) -> InstanceSelection:
    """The instances of `find_instances` and the largest of those inside `gate` around `expected` (forklift
    frame; `InstanceConfig.gate` of the misplacement envelope), none if none is.

    The largest, not the nearest: a pallet standing short has scraps of its own deck (split off by the
    depth jumps of the board gaps) nearer to the expected entry face than its own front; a neighbour stays
    outside the gate.

    `target_mask` holds the selected instance's pixels and the pixels of `mask` next to them (on the
    depth jumps at its edges), minus `foreign_mask`: the other instances' pixels grown by
    `foreign_margin_px` (never over the target's own).
    """
    cfg = config or InstanceConfig()
    instances = find_instances(frame, T_forklift_camera, mask, expected, edges, cfg)
    inside = [inst for inst in instances if gate.admits(inst.offset)]
    target = max(inside, key=lambda inst: inst.n_pixels) if inside else None
    foreign = np.zeros(mask.shape, bool)
    for inst in instances:
        if inst is not target:
            foreign |= inst.mask
    if cfg.foreign_margin_px > 0 and foreign.any():
        k = 2 * cfg.foreign_margin_px + 1
        foreign = cv2.dilate(foreign.astype(np.uint8), np.ones((k, k), np.uint8)).astype(bool)
    if target is None:
        target_mask = np.zeros(mask.shape, bool)
    else:
        foreign &= ~target.mask
        target_mask = target.mask
    return InstanceSelection(expected, tuple(instances), target, gate, target_mask, foreign)
