"""Pallet pose from one RGB-D frame: labels select the pallet, depth and the pallet model decide the pose.

Frames (ARCHITECTURE.md): `camera` optical (x right, y down, z forward), `forklift` (origin on the floor
between the fork heels, x towards the tips, y left, z up), `pallet` (origin at the centre of the entry
face on the pallet's underside, x into the pallet, y left, z up). SI units throughout.

Method, in the forklift frame with the camera at `calibration.T_forklift_camera_at(frame.fork_height)`:

0. **Instance** (only with `expected`, the pose where the pallet should be): the pallet pixels are
   split into pallet instances at depth jumps (`perception.instances`); only the largest instance
   whose entry face is within a gate around `expected` is fitted, and other instances' pixels are
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
   centre is the mean of the two pocket centres. A family type (`perception.pallet_family`) has all
   six column edges searched over its ranges instead: the face, columns and pockets are measured and
   must lie within the ranges, and the measured face replaces the nominal one (`_family_face`); the
   plane is refitted on the pixels the measured face puts on the solid face (the nominal columns of
   the rounds above are centimetres off on such a pallet: `bench pallet --families block_2pocket`,
   20 standpoints, seeds 1-3: 2-sigma yaw coverage of the frames 0.90-0.97 before, 0.95-0.97 after).

5. **Deck.** Where the camera sees the top deck (an empty pallet from above), the deck boards' side
   edges, lines along the whole pallet length, refine the yaw (`_deck_yaw`): each deck pixel is
   predicted on a board or past its edge for a yaw turned about the entry-face centre, scored in
   inverse depth together with the face fit's own yaw term. That centre comes from the pockets and is
   good to a few millimetres, so each yaw takes its best sideways shift of the centre within that
   uncertainty (at a cost); the lateral position itself stays the pockets'. A load on the deck
   switches it off.

Geometry, not label boundaries, places the edges: a pixel's evidence is its depth against the model.
`fuse_estimates` combines the estimates of several frames from one standpoint (inverse-variance
weights from their spreads); the Pickup acts on three.
Spread (1-sigma): yaw and the face distance from the plane fit's covariance, the lateral centre from
the pocket edges' scatter and pixel footprint.

Public API: `estimate_pallet`, and re-exported from `perception.pallet_estimate` (import them from
here): `PalletEstimate`, `PalletSpread`, `PalletEstimatorConfig`, `DEFAULT_CONFIG`, `PalletNotFound`,
`NotFoundReason`, `fuse_estimates`, `FramePolicy`, `RoundVerdict`, `TYPE_REFUSALS`, `estimator_config`,
`TARED_DEPTH_SCALE_SIGMA`, `PALLET_CLASSES`.

This module runs the steps; the pieces live in `perception.pallet_estimate` (tuning, result, failure,
fusion), `perception.pallet_face` (pixels as rays, the face plane, its fits and the spread: steps 1
and 2), `perception.pallet_model` (the pallet model, scoring hypotheses, the pocket check: steps 3
and 4) and `perception.pallet_deck` (step 5).
"""

from __future__ import annotations

import dataclasses
import math
import time
from typing import Any, NamedTuple

import numpy as np
from scipy.spatial.transform import Rotation

from palletpilot.geometry import SE2, SE3
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.distortion import undistort_bundle
from palletpilot.perception.frames import FrameBundle, SemanticClass
from palletpilot.perception.geometry_labels import (
    DEFAULT_ENVELOPE,
    Envelope,
    LabelsMode,
    PalletLabels,
    load_mask,
    pallet_labels,
    sources_note,
)
from palletpilot.perception.instances import Gate, select_instance
from palletpilot.perception.pallet_deck import _ON_DECK_CLASSES, _deck_yaw
from palletpilot.perception.pallet_estimate import (
    DEFAULT_CONFIG,
    PALLET_CLASSES,
    TARED_DEPTH_SCALE_SIGMA,
    TYPE_REFUSALS,
    FramePolicy,
    NotFoundReason,
    PalletEstimate,
    PalletEstimatorConfig,
    PalletNotFound,
    PalletSpread,
    RoundVerdict,
    estimator_config,
    fuse_estimates,
)
from palletpilot.perception.pallet_face import (
    _depth_edges,
    _face_coords,
    _face_run,
    _FaceCoords,
    _fit_plane,
    _joint_refine,
    _no_return_rays,
    _Plane,
    _ransac,
    _Rays,
    _rays,
    _robust_sigma,
    _roi,
    _spread,
)
from palletpilot.perception.pallet_model import (
    _best,
    _check_pockets,
    _check_sides,
    _cost,
    _family_edges,
    _family_face,
    _initial_underside,
    _layer_delta,
    _Model,
    _wall_delta,
    _wall_pixels,
)
from palletpilot.perception.pointcloud import check_intrinsics, class_mask
from palletpilot.perception.specs import PalletType

__all__ = [
    "DEFAULT_CONFIG",
    "PALLET_CLASSES",
    "TARED_DEPTH_SCALE_SIGMA",
    "TYPE_REFUSALS",
    "FramePolicy",
    "NotFoundReason",
    "PalletEstimate",
    "PalletEstimatorConfig",
    "PalletNotFound",
    "PalletSpread",
    "RoundVerdict",
    "estimate_pallet",
    "estimator_config",
    "fuse_estimates",
]


def estimate_pallet(
    frame: FrameBundle,
    calibration: Calibration,
    pallet: PalletType | None = None,
    T_world_forklift: SE2 | None = None,
    config: PalletEstimatorConfig = DEFAULT_CONFIG,
    *,
    expected: SE2 | None = None,
    labels: LabelsMode = LabelsMode.MODEL,
    support_height_m: float = 0.0,
    envelope: Envelope = DEFAULT_ENVELOPE,
) -> PalletEstimate:
    """The pose of the pallet in front of the forks from one labelled RGB-D frame.

    `calibration.T_forklift_camera_at(frame.fork_height)` places the camera; the result's
    `T_forklift_pallet` is the pallet frame (origin at the centre of the entry face on the underside,
    x into the pallet) in the forklift frame, `T_world_pallet` is added when `T_world_forklift` (SE2)
    is given. With `expected` (`T_forklift_pallet` on the floor, SE2: where the pallet should be, in
    the forklift frame) only the largest pallet instance whose entry face is inside the gate of
    `envelope` around it (`InstanceConfig.gate`: the envelope plus a margin on each axis) is fitted and other pallets'
    pixels are left out (`perception.instances`);
    without it every pallet-labelled pixel counts.

    `labels` says which pixels are the pallet's (`perception.geometry_labels`): the frame's labels
    (`model`, the default here), depth alone in the pallet's height band above `support_height_m`
    (forklift frame, m: 0 on the floor, the beams' height in a rack) inside `envelope` around `expected`
    (`geometry`), or both (`fused`, the commands' default); `extras` says how many pixels each source
    selected, and a `PalletNotFound` message says when only one source saw a pallet. Raises
    `PalletNotFound` (too few points, no entry face, pockets inconsistent, not where expected) and
    `PerceptionError` when the `model` mode finds no labels in the frame.
    """
    t_start = time.perf_counter()
    pallet = pallet or PalletType.eur()
    frame = undistort_bundle(frame)  # an ideal pinhole image: every ray from K alone (`perception.distortion`)
    check_intrinsics(frame.K, "frame K")
    T_cf = calibration.T_forklift_camera_at(frame.fork_height)
    found = pallet_labels(
        frame,
        T_cf,
        pallet,
        labels,
        expected=expected,
        support_height_m=support_height_m,
        envelope=envelope,
        depth_noise_k=config.depth_noise_k,
    )
    try:
        gate = config.instances.gate(envelope.lateral_m, envelope.longitudinal_m)
        labelled = dataclasses.replace(frame, labels=found.labels)
        estimate = _estimate(labelled, T_cf, pallet, config, expected, found, gate)
    except PalletNotFound as exc:
        note = sources_note(found)
        if not note:
            raise
        raise PalletNotFound(exc.reason, f"{exc.detail}{note}") from None
    if T_world_forklift is not None:
        estimate = dataclasses.replace(estimate, T_world_pallet=T_world_forklift.to_se3() @ estimate.T_forklift_pallet)
    return dataclasses.replace(estimate, runtime_ms=(time.perf_counter() - t_start) * 1e3)


def _estimate(
    frame: FrameBundle,
    T_cf: SE3,
    pallet: PalletType,
    cfg: PalletEstimatorConfig,
    expected: SE2 | None,
    found_labels: PalletLabels,
    gate: Gate,
) -> PalletEstimate:
    """`estimate_pallet`'s steps on a frame whose labels `found_labels` chose (forklift frame, m); `gate`:
    the instance selection's (`InstanceConfig.gate`)."""
    assert frame.labels is not None  # `pallet_labels` gives labels in every mode
    model = _Model.of(pallet)
    R, cam = T_cf.R, T_cf.t
    depth = frame.depth
    # 0. and 1. The pallet pixels (of the expected instance only, with `expected`).
    valid, labelled, rows, cols, found = _pallet_pixels(frame, frame.labels, T_cf, cfg, expected, gate)
    rays = _rays(depth, frame.K, R, rows, cols, np.ones(len(rows), bool))
    rng = np.random.default_rng(cfg.seed)

    # 2. The entry face among the labelled pixels.
    plane, s0, z0, sigma, half_range = _entry_face(rays, model, pallet, cam, cfg, rng)
    if found_labels.mode != LabelsMode.MODEL:  # a load on the pallet, by geometry, now that the face is known
        origin = plane.point(cam, s0)
        rough = SE3(Rotation.from_euler("z", plane.psi), (origin[0], origin[1], z0))
        assert found_labels.points is not None  # the geometry's points, computed once by `pallet_labels`
        load, loaded = load_mask(found_labels.points, rough, pallet, cam)
        frame.labels[load] = SemanticClass.CARGO
        if loaded:  # the deck's front strip and the load's foot are not told apart by height: no deck yaw
            cfg = dataclasses.replace(cfg, deck_yaw=False)
    on_deck = class_mask(frame.labels, _ON_DECK_CLASSES)  # a load, film, or what else stands on a pallet

    trunc = cfg.truncation_sigma
    n_face = 0
    for round_ in range(cfg.rounds):
        # 3. Every pixel near the face, by geometry.
        all_rays, steady = _face_pixels(frame, T_cf, valid, labelled, model, plane, s0, z0, cfg)
        fc = _face_coords(all_rays, plane, cam)
        footprint = plane.D / float(frame.K[0, 0])  # lateral size (m) of a pixel on the face, roughly
        s0 = _lateral_centre(model, fc, s0, z0, sigma, half_range, footprint, round_, cfg)
        z0 = _underside(model, fc, steady, s0, z0, sigma, footprint, round_, cfg)
        cargo = on_deck[all_rays.rows, all_rays.cols]
        plane, s0, sigma, use = _refit_face(model, fc, all_rays, plane, cam, s0, z0, sigma, footprint, cfg, cargo)
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
    _check_sides(model, cfg, fc, all_rays.labelled, s0, z0, band, sigma, footprint)
    edges = _pocket_edges(model, fc, s0, band, sigma, footprint, cfg)
    sides = edges if len(edges) == 6 else None  # a family: all six column edges, measured
    edges = edges[1:5] if sides is not None else edges
    right_w, left_w = edges[1] - edges[0], edges[3] - edges[2]
    right_c, left_c = 0.5 * (edges[0] + edges[1]), 0.5 * (edges[2] + edges[3])
    face = model if sides is None else model.measured(sides, None)
    _check_pockets(face, cfg, fc, s0, z0, band, sigma, (left_w, right_w), (left_c, right_c), footprint)
    centre_offset = 0.5 * (left_c + right_c)  # pocket-based centre relative to the model fit
    s0 += centre_offset
    if sides is not None:  # the measured face (relative to the pockets' centre) replaces the nominal one
        model, z0, measured = _family_face(model, sides, centre_offset, z0, footprint)
        found = {**found, **measured}
        if cov3 is None:  # the face refitted on the pixels the measured face (not the nominal one) puts on it
            cargo = on_deck[all_rays.rows, all_rays.cols]
            plane, s0, sigma, use = _refit_face(model, fc, all_rays, plane, cam, s0, z0, sigma, footprint, cfg, cargo)
            n_face = int(use.sum())
    pocket_resid = np.array(
        [left_c - centre_offset - model.pocket_centres[0], right_c - centre_offset - model.pocket_centres[1]]
    )
    edge_sigma = max(float(np.sqrt(np.mean(pocket_resid**2))), footprint / math.sqrt(12.0))
    # Two pocket centres; floored at half a pixel footprint, which matches the benchmark's scatter.
    sigma_s = max(edge_sigma / math.sqrt(2.0), 0.5 * footprint)

    # 5. The top deck's board edges, where the camera sees the deck: turn the plane about the face centre
    # (the yaw is the deck's best over the centre's lateral uncertainty; the centre stays the pockets').
    deck = _deck_yaw(frame, T_cf, valid, model, plane, s0, z0, sigma, cfg, sigma_s) if cfg.deck_yaw else None
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
    # The frame's own noise, and what every frame from here shares: the camera's depth scale, the pallet's
    # build tolerance, the pixel grid (`_spread`).
    deck_yaw = None if deck is None else (deck.sigma_psi, deck.floor, model.length)
    spread = _spread(
        plane, cam, s0, sigma_s, cov3, cfg=cfg, columns=model.columns, footprint=footprint, deck_yaw=deck_yaw
    )
    res = all_rays.w - plane.predict(all_rays.d)
    estimate = PalletEstimate(
        T_forklift_pallet=T_fp,
        spread=spread,
        n_points=len(rows),
        n_face_points=n_face,
        pocket_widths_m=(float(left_w), float(right_w)),
        pocket_centres_y_m=(float(left_c - centre_offset), float(right_c - centre_offset)),
        residual_rms_w=float(sigma),
        T_world_pallet=None,
        runtime_ms=0.0,
        extras={
            "lateral_fit_m": float(s0 - centre_offset),
            "face_distance_m": D,
            "plane_residual_rms": float(np.sqrt(np.mean(res[np.abs(res) < trunc * sigma] ** 2))),
            "deck_pixels": 0 if deck is None else deck.n_pixels,
            "deck_height_m": None if deck is None else deck.deck_height,
            "deck_shift_m": None if deck is None else deck.shift,
            **found,
            **found_labels.to_json(),
        },
    )
    return estimate


# -- the steps of `estimate_pallet` ------------------------------------------------------------------


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
"""Share of the modelled face's pixels that `_recessed` may take out (a missing board and three chipped
blocks of a EUR pallet are about a fifth of it)."""
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
            # most of its face: more than `MAX_GONE` of it means a poor plane, not damage.
            usable = solid & ~gone & (np.abs(res) < trunc * sigma)
            more = gone | _recessed(cells, all_rays, usable, fc.D, sigma, cfg)
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
) -> np.ndarray:
    """Pixels of the modelled face that are not there (a damaged pallet): their rays end well behind it.

    The cells of the face (`_face_cells`) are tested one by one. A cell is gone where the median
    inverse-depth residual of its pixels, against the plane fitted to the `usable` pixels outside it (so
    that the missing part cannot tilt the plane towards itself), lies clearly (`RECESS_SIGMAS` standard
    errors) and at least `cfg.missing_board_depth_m` behind the face (`D` m away). Then the cell and a
    margin around it are no evidence of the face: its edges border a hole (flying pixels, rays that pass
    the missing part's edge and end on the floor behind it).
    """
    out = np.zeros(len(rays.w), bool)
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
        if med < -behind and med < -RECESS_SIGMAS * 1.25 * sigma / np.sqrt(n):
            out[grown] = True
    return out


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
        # Build tolerance moves an edge by millimetres; further off, the face is another pallet type.
        limit = cfg.max_edge_offset_m + footprint  # a pixel more for the quantisation at a distance
        if abs(e) > limit:
            raise PalletNotFound(
                "pockets_inconsistent",
                f"the block edge at y = {y_edge:+.3f} m of the {model.name} type is {1e3 * e:+.0f} mm off "
                f"(more than {1e3 * limit:.0f} mm)",
            )
        edges.append(y_edge + e)
    return edges
