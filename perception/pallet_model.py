"""The pallet model of the entry side: where each ray ends behind the face for a pallet type, and scoring it.

Frames: on the entry-face plane (`perception.pallet_face`), a ray's lateral position `s` and height
`h` relative to a hypothesised pallet centre and underside (pallet y and z, m), its slopes behind the
face, and depths behind the face (m along the pallet's x; inf: the ray ends far, in a pocket).

Package-internal API (used by `perception.pallet`, `perception.pallet_deck`):
- `_Model` (`_Model.of(PalletType)`: block columns, cross board, deck boards and pockets of the entry
  side; `solid`: points on the face's solid parts).
- Predicted depth behind the face: `_wall_delta`, `_wall_hits` (one layer of solid intervals with side
  walls), `_layer_delta` (block layer, cross board and deck), `_wall_pixels` (pixels on side walls).
- Scoring hypotheses: `_cost` (truncated chi-square of inverse-depth residuals), `_best` (centre and
  half-width of the ~1-sigma interval of a grid), `_initial_underside` (the underside height from the
  face's profile).
- `_check_pockets`: `PalletNotFound("pockets_inconsistent")` unless the face's gaps match the type.
"""

from __future__ import annotations

import dataclasses
from dataclasses import dataclass

import numpy as np

from palletpilot.perception.pallet_estimate import PalletEstimatorConfig, PalletNotFound
from palletpilot.perception.pallet_face import _FaceCoords
from palletpilot.perception.specs import PalletType

FAMILY_DIMENSIONS = ("width", "block_columns", "pocket_width", "pocket_height")
"""The dimensions a family's ranges may set (`perception.pallet_family.FamilyRanges`)."""


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
    name: str = "EUR/EPAL"
    pocket_floor: float = 0.0  # top of a perimeter bottom board across the pockets (0: open to the floor)
    bottom_top: float = 0.0  # top of the bottom boards (0: legs)
    runners: bool = True  # bottom boards under the block columns (else across the rows, or none)
    ranges: dict[str, tuple[float, float]] | None = None  # a family's (lowest, highest) per dimension; None: exact

    @classmethod
    def of(cls, p: PalletType) -> _Model:
        cols = np.array(p.column_bounds_y(), dtype=float)
        boards = np.array(sorted(p.face_deck_bounds_y))
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
            name=p.name,
            pocket_floor=p.pocket_floor,
            bottom_top=p.bottom_board_thickness,
            runners=p.bottom_boards == "runners",
            ranges=None if p.family is None else {k: p.bounds(k) for k in FAMILY_DIMENSIONS},
        )

    def measured(self, edges: list[float], pocket_height: float | None) -> _Model:
        """This model with the block columns at the six measured `edges` (pallet y, m, right to left) and, when
        given, the pocket height (the layers above move with it)."""
        cols = np.array(edges, dtype=float).reshape(3, 2)
        rise = 0.0 if pocket_height is None else pocket_height - self.block_top
        widths = (cols[1, 0] - cols[0, 1], cols[2, 0] - cols[1, 1])
        return dataclasses.replace(
            self,
            columns=cols,
            width=float(cols[2, 1] - cols[0, 0]),
            block_top=self.block_top + rise,
            cross_top=self.cross_top + rise,
            height=self.height + rise,
            pocket_width=float(0.5 * (widths[0] + widths[1])),
            pocket_centres=np.array([0.5 * (cols[1, 1] + cols[2, 0]), 0.5 * (cols[0, 1] + cols[1, 0])]),
        )

    def bottom_segments(self) -> list[tuple[float, float]]:
        """(y_lo, y_hi) (m) of the bottom boards on the entry face: under each column, or the whole width."""
        if self.bottom_top <= 0.0:
            return []
        if self.runners:
            return [(float(lo), float(hi)) for lo, hi in self.columns]
        return [(-0.5 * self.width, 0.5 * self.width)]

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
        if self.pocket_floor > 0.0:  # a perimeter bottom board across the entry
            out |= (np.abs(s) <= 0.5 * self.width - margin_s) & (h >= margin_h) & (h <= self.pocket_floor - margin_h)
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
    if model.pocket_floor > 0.0:  # a perimeter bottom board across the entry, full width
        low = h_rel < model.pocket_floor
        if low.any():
            full = np.array([[-0.5 * model.width, 0.5 * model.width]])
            delta = np.where(low, _wall_delta(s_rel, t, full, model.block_length), delta)
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
        if model.pocket_floor > 0.0:
            width = np.where((hr >= 0) & (hr < model.pocket_floor), model.width, width)
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
    footprint_m: float = 0.0,
) -> None:
    """Raise `PalletNotFound("pockets_inconsistent")` unless the gaps in the face match the pallet type.

    For a family `model` is the measured face (`_Model.measured`): its pockets must be open, its columns
    solid, and its dimensions within the family's ranges (`_check_family`, to a pixel `footprint_m`)."""
    s_rel = fc.s - s0
    # Occupancy: the middle of each pocket must see past the face, the middle of each column must be on it.
    res = fc.w - fc.nd / fc.D
    # On the face within the noise, or within the build tolerance (in inverse depth) where the noise is
    # smaller than that (a near, low-noise camera: a part built 2 mm proud is still on the face).
    on_face = np.abs(res) < max(cfg.truncation_sigma * sigma, cfg.build_tolerance_m / fc.D**2)
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
                f"the block column at y = {0.5 * (lo + hi):+.3f} m of the {model.name} type is missing: "
                f"{100 * float(on_face[m].mean()):.0f} % on the face",
            )
    if model.ranges is not None:  # a family: the measured face (`_Model.measured`) within the ranges
        _check_family(model, widths, footprint_m)
        return
    for name, w in (("left", widths[0]), ("right", widths[1])):
        if abs(w - model.pocket_width) > cfg.pocket_width_tolerance_m:
            raise PalletNotFound(
                "pockets_inconsistent",
                f"the {name} pocket is {1e3 * w:.0f} mm wide, the {model.name} type's are "
                f"{1e3 * model.pocket_width:.1f} mm",
            )
    spacing = centres[0] - centres[1]
    expected = model.pocket_centres[0] - model.pocket_centres[1]
    if abs(spacing - expected) > cfg.pocket_centre_tolerance_m:
        raise PalletNotFound(
            "pockets_inconsistent",
            f"the pocket centres are {1e3 * spacing:.0f} mm apart, the {model.name} type's {1e3 * expected:.1f} mm",
        )


def _check_sides(
    model: _Model,
    cfg: PalletEstimatorConfig,
    fc: _FaceCoords,
    labelled: np.ndarray,
    s0: float,
    z0: float,
    band: np.ndarray,
    sigma: float,
    footprint: float,
) -> None:
    """Raise `PalletNotFound("type_mismatch")` where the pallet's face continues past a side of the type's face.

    Pallet-labelled pixels of the block layer just past each side (beyond label noise), whose rays the
    model sends past the pallet (not onto its side walls), must mostly see past the face plane.
    """
    s_rel = fc.s - s0
    res = fc.w - fc.nd / fc.D
    on_face = np.abs(res) < cfg.truncation_sigma * sigma
    past = ~np.isfinite(_wall_delta(s_rel, fc.t, model.columns, model.block_length))
    margin = max(0.015, 3.0 * footprint)
    width = model.width if model.ranges is None else model.ranges["width"][1]  # a family: its widest face
    for name, sign in (("left", 1.0), ("right", -1.0)):
        out = sign * s_rel - 0.5 * width
        m = band & labelled & past & (out >= margin) & (out <= margin + 0.06)
        if m.sum() >= 10 and float(on_face[m].mean()) > cfg.max_side_solid:
            raise PalletNotFound(
                "type_mismatch",
                f"the entry face continues past the {name} side of the {model.name} type's face "
                f"({1e3 * width:.0f} mm wide): {100 * float(on_face[m].mean()):.0f} % of the pallet pixels "
                "beyond it lie on the face",
            )


# -- a family: the face measured within its ranges -------------------------------------------------------

FAMILY_SEARCH_SLACK_M = 0.02
"""Each family edge is searched this far (m) beyond where its ranges put it: the lateral centre it is
searched from came from the nominal columns (a few millimetres off on an asymmetric face)."""


FAMILY_TOLERANCE_M = 0.006
"""A measured width may lie this far (m) plus a pixel footprint outside its family's range."""


def _family_edge_ranges(model: _Model) -> list[tuple[float, float]]:
    """Where (pallet y, m, right to left) each of the six block-column edges of a family may lie: the outer
    sides from the face width, the inner edges from the column widths."""
    assert model.ranges is not None
    (w_lo, w_hi), (c_lo, c_hi) = model.ranges["width"], model.ranges["block_columns"]
    return [
        (-0.5 * w_hi, -0.5 * w_lo),
        (-0.5 * w_hi + c_lo, -0.5 * w_lo + c_hi),
        (-0.5 * c_hi, -0.5 * c_lo),
        (0.5 * c_lo, 0.5 * c_hi),
        (0.5 * w_lo - c_hi, 0.5 * w_hi - c_lo),
        (0.5 * w_lo, 0.5 * w_hi),
    ]


def _family_edges(
    model: _Model, fc: _FaceCoords, s0: float, band: np.ndarray, sigma: float, cfg: PalletEstimatorConfig
) -> list[float]:
    """Step 4 for a family: the six block-column edges (pallet y relative to `s0`, m, right to left), each
    searched over its range (`_family_edge_ranges`, 2 mm then 0.25 mm steps), then once more within 6 mm
    of the first answers with the other edges where they were found. Raises
    `PalletNotFound("pockets_inconsistent")` where an edge has no pixels near it."""
    trunc = cfg.truncation_sigma
    cols = model.columns.copy()
    for rnd in range(2):
        for k, (lo, hi) in enumerate(_family_edge_ranges(model)):
            col, side = divmod(k, 2)
            if rnd == 0:
                lo, hi = lo - FAMILY_SEARCH_SLACK_M, hi + FAMILY_SEARCH_SLACK_M
            else:
                lo, hi = cols[col, side] - 0.006, cols[col, side] + 0.006
            idx = np.flatnonzero(band & (fc.s - s0 >= lo - 0.05) & (fc.s - s0 <= hi + 0.05))
            if idx.size < 10:
                raise PalletNotFound(
                    "pockets_inconsistent", f"no pixels near the block edge at y = {0.5 * (lo + hi):+.3f} m"
                )
            s_rel, t = fc.s[idx][:, None] - s0, fc.t[idx][:, None]
            grids = [np.arange(lo, hi + 1e-12, 0.002 if rnd == 0 else 0.00025)]
            for g in range(2 if rnd == 0 else 1):
                if g == 1:
                    grids.append(cols[col, side] + np.arange(-0.0025, 0.0025 + 1e-12, 0.00025))
                cols_h = np.broadcast_to(cols, (len(grids[g]), 3, 2)).copy()
                cols_h[:, col, side] = grids[g]
                cost = _cost(
                    fc, idx, _wall_delta(s_rel, t, cols_h, model.block_length), model.block_length, sigma, trunc
                )
                cost[cols_h[:, col, 1] <= cols_h[:, col, 0] + 0.01] = np.inf  # a column turned inside out
                cols[col, side], _ = _best(grids[g], cost)
    return [float(v) for v in cols.reshape(-1)]


def _check_family(model: _Model, widths: tuple[float, float], footprint: float) -> None:
    """Raise `PalletNotFound("pockets_inconsistent")` where the measured face (`model`, from
    `_Model.measured`) lies outside its family's ranges by more than a pixel `footprint` (m) and
    `FAMILY_TOLERANCE_M` (a single frame places an edge to about a pixel; now and then 10 mm off at 2 m)."""
    assert model.ranges is not None
    tol = footprint + FAMILY_TOLERANCE_M
    checks = [("face", "width", model.width)]
    checks += [
        (f"{n} block column", "block_columns", float(hi - lo))
        for n, (lo, hi) in zip(("right", "middle", "left"), model.columns, strict=True)
    ]
    checks += [(f"{n} pocket", "pocket_width", w) for n, w in zip(("left", "right"), widths, strict=True)]
    for what, key, value in checks:
        lo, hi = model.ranges[key]
        if not lo - tol <= value <= hi + tol:
            raise PalletNotFound(
                "pockets_inconsistent",
                f"the {what} is {1e3 * value:.0f} mm wide, the {model.name} family's are "
                f"{1e3 * lo:.0f}-{1e3 * hi:.0f} mm",
            )


def _family_face(
    model: _Model, sides: list[float], centre_offset: float, z0: float, footprint: float, support_m: float = 0.0
) -> tuple[_Model, float, dict[str, object]]:
    """A family's measured face: the model at the six measured column edges `sides` (pallet y relative
    to the model fit's centre; the pallet's centre is `centre_offset` from it), the underside height `z0`
    (m, forklift frame) and what was measured, for the estimate's extras.

    The pocket top (`z0` plus the nominal pocket height: where step 3 found the pockets' upper edges) is
    measured; the pocket height needs the floor under the pallet. A pallet whose nominal underside lies
    within the family's pocket-height spread (and 2 cm) of the truck's floor (forklift z = 0) stands on
    it: the pocket height is the pocket top's height, the underside is the floor, and the height must
    lie within the range. Elsewhere (a rack beam: the support's height `support_m` the caller gives is not
    the floor's, however low the beam) the pocket height is not measured (None: the Pickup then takes the
    family's lowest; a beam's height in the map is not known to the millimetre the fork tops need).
    """
    assert model.ranges is not None
    top = z0 + model.block_top
    lo, hi = model.ranges["pocket_height"]
    on_floor = abs(support_m) < 1e-3 and abs(z0) <= max(hi - model.block_top, model.block_top - lo) + 0.02
    height = top if on_floor else None
    if height is not None:
        tol = footprint + 0.005
        if not lo - tol <= height <= hi + tol:
            raise PalletNotFound(
                "pockets_inconsistent",
                f"the pockets are {1e3 * height:.0f} mm high, the {model.name} family's are "
                f"{1e3 * lo:.0f}-{1e3 * hi:.0f} mm",
            )
        z0 = 0.0
    face = model.measured([v - centre_offset for v in sides], height)
    cols = face.columns
    measured: dict[str, object] = {
        "family": model.name,
        "face_width_m": round(face.width, 5),
        "block_columns_m": [round(float(b - a), 5) for a, b in cols],
        "column_edges_y_m": [round(float(v), 5) for v in cols.reshape(-1)],
        "pocket_height_m": None if height is None else round(height, 5),
        "pocket_top_z_m": round(top, 5),
    }
    return face, z0, measured
