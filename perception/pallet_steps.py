"""The steps of `perception.pallet.estimate_pallet` on one frame (forklift frame, m): the pallet pixels
(step 0 and 1: `_pallet_pixels`), the entry face (2: `_entry_face`), the pixels on and near it, its lateral
centre and underside, the refit on the solid face (3: `_face_pixels`, `_lateral_centre`, `_underside`,
`_refit_face`, with `_face_cells` and `_recessed` for the parts that are missing) and the pockets edge by
edge (4: `_pocket_edges`). `perception.pallet` runs them in order; the plane, rays and model they work on
are `perception.pallet_face`'s and `perception.pallet_model`'s.

Public API: none (the steps are `perception.pallet`'s).
"""

from __future__ import annotations

from typing import Any, NamedTuple

import numpy as np

from palletpilot.geometry import SE2, SE3
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.instances import Gate, select_instance
from palletpilot.perception.pallet_estimate import (
    PALLET_CLASSES,
    PalletEstimatorConfig,
    PalletNotFound,
)
from palletpilot.perception.pallet_face import (
    _depth_edges,
    _face_coords,
    _face_run,
    _FaceCoords,
    _fit_plane,
    _no_return_rays,
    _Plane,
    _ransac,
    _Rays,
    _rays,
    _robust_sigma,
    _roi,
)
from palletpilot.perception.pallet_model import (
    _best,
    _cost,
    _family_edges,
    _initial_underside,
    _layer_delta,
    _Model,
    _wall_delta,
)
from palletpilot.perception.pointcloud import class_mask
from palletpilot.perception.specs import PalletType


class _Pixels(NamedTuple):
    """Steps 0 and 1 of `estimate_pallet`: the frame's pixels with depth and its pallet pixels."""

    valid: np.ndarray  # H x W: depth, and not another pallet instance's pixel
    labelled: np.ndarray  # H x W: labelled pallet
    rows: np.ndarray  # the pallet pixels to fit (of the expected instance, with `expected`)
    cols: np.ndarray
    found: dict[str, Any]  # the instance separation's extras (none without `expected`)


def _pallet_pixels(
    frame: FrameBundle,
    labels: np.ndarray,
    T_cf: SE3,
    cfg: PalletEstimatorConfig,
    expected: SE2 | None,
    gate: Gate,
) -> _Pixels:
    """The pallet-labelled pixels with depth; with `expected` only those of the instance found there, inside
    `gate` around it."""
    depth = frame.depth
    valid = np.isfinite(depth) & (depth > 0)
    labelled = class_mask(labels, PALLET_CLASSES)
    rows, cols = np.nonzero(labelled & valid)
    if len(rows) < cfg.min_points:
        raise PalletNotFound("too_few_points", f"{len(rows)} pallet pixels with depth, need at least {cfg.min_points}")
    if expected is not None:  # 0. Only the expected pallet instance; other pallets' pixels are no evidence.
        jumps = _depth_edges(depth, valid, cfg)
        chosen = select_instance(frame, T_cf, labelled & valid, expected, jumps, cfg.instances, gate=gate)
        if chosen.target is None:
            raise PalletNotFound("not_where_expected", chosen.miss_message())
        valid &= ~chosen.foreign_mask
        rows, cols = np.nonzero(chosen.target_mask)
        if len(rows) < cfg.min_points:
            raise PalletNotFound("too_few_points", f"the expected pallet has {len(rows)} pixels with depth")
        found = {"instances": len(chosen.instances), "instance_distance_m": chosen.target.distance_m}
    else:
        found = {}
    return _Pixels(valid, labelled, rows, cols, found)


def _entry_face(
    rays: _Rays,
    model: _Model,
    pallet: PalletType,
    cam: np.ndarray,
    cfg: PalletEstimatorConfig,
    rng: np.random.Generator,
) -> tuple[_Plane, float, float, float, float]:
    """Step 2: the entry face among the labelled pixels, checked against the pallet type's size.

    Returns the plane, the first lateral centre `s0` and underside height `z0` (m), the inverse-depth
    noise `sigma` on the face and the half-width (m) of the first lateral search.
    """
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
    return plane, s0, z0, sigma, half_range


def _face_pixels(
    frame: FrameBundle,
    T_cf: SE3,
    valid: np.ndarray,
    labelled: np.ndarray,
    model: _Model,
    plane: _Plane,
    s0: float,
    z0: float,
    cfg: PalletEstimatorConfig,
) -> tuple[_Rays, np.ndarray]:
    """Step 3: every pixel with depth near the face (whatever its label) as a ray, and which are steady;
    and the pixels without depth that saw past the face (`_no_return_rays`: inverse depth 0, steady).

    Steady: not next to a depth discontinuity, where pixels may mix both sides (flying pixels).
    """
    R, cam = T_cf.R, T_cf.t
    depth = frame.depth
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
    past = _no_return_rays(frame, T_cf, rs, cs, z0, cfg)
    return all_rays.plus(past), np.concatenate([steady, np.ones(len(past.w), bool)])


def _lateral_centre(
    model: _Model,
    fc: _FaceCoords,
    s0: float,
    z0: float,
    sigma: float,
    half_range: float,
    footprint: float,
    round_: int,
    cfg: PalletEstimatorConfig,
) -> float:
    """Step 3: the lateral centre `s0` (m on the face) searched on the block layer, coarse then fine."""
    trunc = cfg.truncation_sigma
    band = (fc.h - z0 >= 0.3 * model.block_top) & (fc.h - z0 <= 0.9 * model.block_top)
    band &= np.abs(fc.s - s0) <= 0.5 * model.width + 0.1
    idx = np.flatnonzero(band)
    if idx.size < cfg.min_face_pixels:
        raise PalletNotFound("no_entry_face", f"only {idx.size} pixels on the block layer of the face")
    t_idx = fc.t[idx][:, None]
    spans = ((half_range, 0.003), (0.004, 0.0005)) if round_ == 0 else ((4 * footprint + 0.01, 0.002), (0.003, 0.00025))
    for span, step in spans:
        grid = s0 + np.arange(-span, span + 1e-12, step)
        delta = _wall_delta(fc.s[idx][:, None] - grid[None], t_idx, model.columns, model.block_length)
        s0, _ = _best(grid, _cost(fc, idx, delta, model.block_length, sigma, trunc))
    return s0


def _underside(
    model: _Model,
    fc: _FaceCoords,
    steady: np.ndarray,
    s0: float,
    z0: float,
    sigma: float,
    footprint: float,
    round_: int,
    cfg: PalletEstimatorConfig,
) -> float:
    """Step 3: the underside height `z0` (m) from the pockets' upper edges (unchanged with too few pixels)."""
    trunc = cfg.truncation_sigma
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
    return z0


MAX_GONE = 0.3
"""Share of the modelled face's pixels that `_recessed` may take out, the most evident cells first (a missing
board and three chipped blocks of a EUR pallet are about a fifth of it, but nearly half with the margins
around each hole: the clearest holes go out, the rest stay in rather than the fit losing most of the face)."""
RECESS_SIGMAS = 4.0
"""How many standard errors of its median a cell must lie behind the face to count as missing (some
twenty cells are tested, twice: 3 would take out a sound part of the face in about one frame in ten)."""


def _refit_face(
    model: _Model,
    fc: _FaceCoords,
    all_rays: _Rays,
    plane: _Plane,
    cam: np.ndarray,
    s0: float,
    z0: float,
    sigma: float,
    footprint: float,
    cfg: PalletEstimatorConfig,
    cargo: np.ndarray | None = None,
) -> tuple[_Plane, float, float, np.ndarray]:
    """Step 3: the plane refitted on the pixels the model puts on the solid face (parts of it that are
    missing, `_recessed`, and a load in front of it left out).

    Returns the plane, the lateral centre re-expressed on it, the inverse-depth noise and the mask of
    the pixels fitted.
    """
    trunc = cfg.truncation_sigma
    margin = cfg.face_margin_px * footprint + cfg.face_margin_m
    solid = model.solid(fc.s - s0, fc.h - z0, margin, margin)
    if cargo is not None:  # a load or stretch film in front of the face (an overhang) is not the face
        solid &= ~cargo
    res = fc.w - fc.nd / fc.D
    gone = np.zeros(len(fc.s), bool)
    # The lateral centre as a point on the face: `s` is measured along the plane's lateral axis from
    # the forklift origin, so a new plane (another yaw) needs it re-expressed, or the pallet model
    # slides sideways by D * (change of yaw) (11 cm for 1.6 deg at 4 m).
    centre = plane.point(cam, s0)
    n_solid = np.count_nonzero(solid)
    cells = _face_cells(model, fc, all_rays, s0, z0, margin)
    for round_ in range(3):
        if round_ < 2:
            # Cells found missing stay out: each is tested against the plane of the rest of the face, in
            # two passes (the second without the first's). A damaged pallet misses a few parts, never
            # most of its face: the cells go out most evident first, while at most `MAX_GONE` of it is
            # out (more would mean a poor plane, not damage).
            usable = solid & ~gone & (np.abs(res) < trunc * sigma)
            for grown in _recessed(cells, all_rays, usable, fc.D, sigma, cfg):
                more = gone.copy()
                more[grown] = True
                if np.count_nonzero(solid & more) <= MAX_GONE * n_solid:
                    gone = more
        use = solid & ~gone & (np.abs(res) < trunc * sigma)
        if use.sum() < cfg.min_face_pixels:
            raise PalletNotFound("no_entry_face", f"only {int(use.sum())} pixels on the modelled entry face")
        plane = _fit_plane(all_rays.d[use], all_rays.w[use], sigma)
        res = all_rays.w - plane.predict(all_rays.d)
        sigma = _robust_sigma(res[use], cfg.min_sigma_w)
    use = solid & ~gone & (np.abs(res) < trunc * sigma)
    plane = _fit_plane(all_rays.d[use], all_rays.w[use], sigma)
    s0 = float(plane.e @ centre)
    return plane, s0, sigma, use


class _FaceCells(NamedTuple):
    """The cells of the modelled face that `_recessed` tests, as pixel indices, and the pixels' terms of
    the plane fit's normal equations."""

    inner: list[np.ndarray]  # per cell: its pixels at least a margin inside it (tested)
    grown: list[np.ndarray]  # per cell: its pixels and those within two margins around it (taken out)
    terms: np.ndarray  # N x 5: x x, x y, y y, x w, y w of each pixel's ray (x, y) and inverse depth w


def _face_cells(model: _Model, fc: _FaceCoords, rays: _Rays, s0: float, z0: float, margin: float) -> _FaceCells:
    """Each bottom board, and each half of a block face (left and right) in its lower half, its upper half
    and whole (a chipped corner, a chipped vertical edge), at the lateral centre `s0` and underside `z0`."""
    s_rel, h_rel = fc.s - s0, fc.h - z0
    boxes = [(lo, hi, 0.0, model.bottom_top) for lo, hi in model.bottom_segments()]
    low = max(model.bottom_top, model.pocket_floor)
    z_mid = 0.5 * (low + model.block_top)
    for lo, hi in model.columns:
        y_mid = 0.5 * (lo + hi)
        for y0, y1 in ((lo, y_mid), (y_mid, hi)):
            boxes += [(y0, y1, low, z_mid), (y0, y1, z_mid, model.block_top), (y0, y1, low, model.block_top)]
    g = 2.0 * margin
    near = np.flatnonzero(
        (s_rel >= min(b[0] for b in boxes) - g)
        & (s_rel <= max(b[1] for b in boxes) + g)
        & (h_rel >= -g)
        & (h_rel <= model.block_top + g)
    )
    s_n, h_n = s_rel[near], h_rel[near]
    inner, grown = [], []
    for y0, y1, z0_, z1_ in boxes:
        m = (s_n >= y0 + margin) & (s_n <= y1 - margin) & (h_n >= z0_ + margin) & (h_n <= z1_ - margin)
        gm = (s_n >= y0 - g) & (s_n <= y1 + g) & (h_n >= z0_ - g) & (h_n <= z1_ + g)
        inner.append(near[m])
        grown.append(near[gm])
    x, y, w = rays.d[:, 0], rays.d[:, 1], rays.w
    return _FaceCells(inner, grown, np.stack([x * x, x * y, y * y, x * w, y * w], axis=1))


def _recessed(
    cells: _FaceCells, rays: _Rays, usable: np.ndarray, D: float, sigma: float, cfg: PalletEstimatorConfig
) -> list[np.ndarray]:
    """Parts of the modelled face that are not there (a damaged pallet): their rays end well behind it.
    Returns each missing cell's pixels with a margin around it (indices of `rays`), most evident first.

    The cells of the face (`_face_cells`) are tested one by one. A cell is gone where the median
    inverse-depth residual of its pixels, against the plane fitted to the `usable` pixels outside it (so
    that the missing part cannot tilt the plane towards itself), lies clearly (`RECESS_SIGMAS` standard
    errors) and at least `cfg.missing_board_depth_m` behind the face (`D` m away). Then the cell and a
    margin around it are no evidence of the face: its edges border a hole (flying pixels, rays that pass
    the missing part's edge and end on the floor behind it).
    """
    out: list[tuple[float, np.ndarray]] = []
    total = cells.terms[usable].sum(axis=0)
    depth = cfg.missing_board_depth_m
    behind = depth / (D * (D + depth))  # in inverse depth
    for inner, grown in zip(cells.inner, cells.grown, strict=True):
        n = len(inner)
        if n < 5:
            continue
        sxx, sxy, syy, sxw, syw = total - cells.terms[grown[usable[grown]]].sum(axis=0)
        det = sxx * syy - sxy * sxy
        if det <= 0.0:
            continue
        A, B = (syy * sxw - sxy * syw) / det, (sxx * syw - sxy * sxw) / det
        d = rays.d[inner]
        med = float(np.median(rays.w[inner] - (A * d[:, 0] + B * d[:, 1])))
        standard_error = 1.25 * sigma / np.sqrt(n)  # of the median
        if med < -behind and med < -RECESS_SIGMAS * standard_error:
            out.append((-med / standard_error, grown))
    return [grown for _, grown in sorted(out, key=lambda c: -c[0])]


def _pocket_edges(
    model: _Model,
    fc: _FaceCoords,
    s0: float,
    band: np.ndarray,
    sigma: float,
    footprint: float,
    cfg: PalletEstimatorConfig,
) -> list[float]:
    """Step 4: the four inner block-column edges (pallet y, m), each searched on its own.

    Right pocket (its right then left edge), then the left pocket. A family (`model.ranges`): all six
    column edges, right to left, each searched over its range (`_family_edges`).
    """
    if model.ranges is not None:
        return _family_edges(model, fc, s0, band, sigma, cfg)
    trunc = cfg.truncation_sigma
    offsets = []
    for col, side in _INNER_EDGES:
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
        offsets.append(e)
    # Build tolerance moves an edge by millimetres; further off, the face is another pallet type, unless a
    # single edge lies further into its block, as a chipped block's edge does (`_chipped_edge`).
    limit = cfg.max_edge_offset_m + footprint  # a pixel more for the quantisation at a distance
    chipped = _chipped_edge(offsets, limit)
    for k, ((col, side), e) in enumerate(zip(_INNER_EDGES, offsets, strict=True)):
        if abs(e) > limit and k != chipped:
            raise PalletNotFound(
                "pockets_inconsistent",
                f"the block edge at y = {model.columns[col, side]:+.3f} m of the {model.name} type is "
                f"{1e3 * e:+.0f} mm off (more than {1e3 * limit:.0f} mm)",
            )
    if chipped is not None:  # the chipped edge where its pocket's other edge and the type put it
        offsets[chipped] = offsets[chipped ^ 1]
    return [float(model.columns[col, side] + e) for (col, side), e in zip(_INNER_EDGES, offsets, strict=True)]


_INNER_EDGES = ((0, 1), (1, 0), (1, 1), (2, 0))
"""The four block-column edges beside the pockets, as (column, side) of `_Model.columns` (right to left):
the right pocket's right and left edge, then the left pocket's."""
_INTO_BLOCK = (-1.0, 1.0, -1.0, 1.0)
"""The sign of an offset (m, pallet y) that moves each of `_INNER_EDGES` into its block (its pocket wider)."""


def _chipped_edge(offsets: list[float], limit: float) -> int | None:
    """Which of the four edge `offsets` (m, `_INNER_EDGES` order) is a chipped block's, if one is: the only
    one more than `limit` off, and off into its block. A chunk missing at a pocket's edge leaves the pocket
    wider at the face, never narrower, and the forks enter where the other edge and the type put it. None
    when no edge, or more than one, is off (then the face is not of this type)."""
    off = [k for k, e in enumerate(offsets) if abs(e) > limit]
    if len(off) != 1 or offsets[off[0]] * _INTO_BLOCK[off[0]] <= 0.0:
        return None
    return off[0]
