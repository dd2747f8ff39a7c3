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
and 4), `perception.pallet_steps` (steps 0 to 4 on a frame) and `perception.pallet_deck` (step 5).
"""

from __future__ import annotations

import dataclasses
import math
import time

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
from palletpilot.perception.instances import Gate
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
    _face_coords,
    _joint_refine,
    _Plane,
    _rays,
    _spread,
)
from palletpilot.perception.pallet_model import (
    _check_pockets,
    _check_sides,
    _family_face,
    _Model,
    _wall_pixels,
)
from palletpilot.perception.pallet_steps import (
    _entry_face,
    _face_pixels,
    _lateral_centre,
    _pallet_pixels,
    _pocket_edges,
    _refit_face,
    _underside,
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
        estimate = _estimate(labelled, T_cf, pallet, config, expected, found, gate, support_height_m)
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
    support_height_m: float = 0.0,
) -> PalletEstimate:
    """`estimate_pallet`'s steps on a frame whose labels `found_labels` chose (forklift frame, m); `gate`:
    the instance selection's (`InstanceConfig.gate`); `support_height_m`: what the pallet stands on, as the
    caller says (0: the floor)."""
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
        model, z0, measured = _family_face(model, sides, centre_offset, z0, footprint, support_height_m)
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
