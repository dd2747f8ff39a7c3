"""The pallet's yaw from the top deck's board edges, where the camera sees the deck from above.

Step 5 of `perception.pallet.estimate_pallet`. Frames: `forklift` and camera optical; a yaw
hypothesis turns the pallet about the centre of its entry face (which the face and pockets fix).

Package-internal API (used by `perception.pallet`): `_deck_yaw` (the yaw fused with the entry face's,
its 1-sigma, the deck pixels and the deck height as a `_DeckYaw`, or None where too little deck is
seen), `_deck_pixels` (the deck's unoccluded rays and its height measured from them).
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import NamedTuple

import numpy as np

from palletpilot.geometry import SE3
from palletpilot.perception.frames import FrameBundle, SemanticClass
from palletpilot.perception.pallet_estimate import PalletEstimatorConfig
from palletpilot.perception.pallet_face import _depth_edges, _image_box, _Plane, _rays, _yaw_variance
from palletpilot.perception.pallet_model import _Model, _wall_delta
from palletpilot.perception.pointcloud import class_mask

_ON_DECK_CLASSES = (int(SemanticClass.CARGO), int(SemanticClass.OTHER_OBJECT), int(SemanticClass.PERSON))
"""Classes that may stand on a pallet's deck and hide it."""


@dataclass(frozen=True)
class _DeckYaw:
    """Result of `_deck_yaw`: the yaw (rad) and its 1-sigma (rad), the deck pixels used, the deck height (m),
    and the sideways shift (m, along the face's lateral unit vector `_Plane.e`) of the face centre that
    the best yaw took; `floor` (rad): the part of the 1-sigma that the pixel grid sets (the deck's far
    end quantised to a pixel), the same in every frame from the standpoint."""

    psi: float
    sigma_psi: float
    n_pixels: int
    deck_height: float
    shift: float = 0.0
    floor: float = 0.0


class _DeckPixels(NamedTuple):
    """The deck as `_deck_pixels` sees it: its rays (forklift frame), their inverse depths and its height."""

    d: np.ndarray  # (N, 3) ray directions per unit camera z-depth
    w: np.ndarray  # (N,) measured inverse depths (1/m)
    height: float  # the deck's height (m, forklift z) measured from its pixels
    centre: np.ndarray  # the entry face's centre at the first deck height guess (forklift frame)


def _deck_pixels(
    frame: FrameBundle,
    T_cf: SE3,
    valid: np.ndarray,
    model: _Model,
    plane: _Plane,
    s0: float,
    z0: float,
    sigma: float,
    cfg: PalletEstimatorConfig,
) -> _DeckPixels | None:
    """The unoccluded deck pixels seen from above and the deck height from them; None where too few.

    Occluders (a load on the deck: labelled cargo, or nearer than the deck) and pixels next to depth
    jumps are left out.
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
    return _DeckPixels(d_all, w_all, deck_h, centre)


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
    sigma_s: float = 0.0,
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

    The face centre the pallet turns about comes from the pockets and is only good to `sigma_s` (m,
    1-sigma, lateral): a centre a few millimetres off would otherwise be made up for by a turn (at
    0.8 m deck length, 8 mm is 0.6 deg). So a hypothesis also shifts the pallet sideways by `u`,
    within 3 `sigma_s` (at most `deck_shift_max_m`), at the cost (u / sigma_s)^2; the yaw's cost is the
    least over the shifts (a profile likelihood). The best hypothesis's shift is reported (`shift`) but
    not applied: the deck's board edges place the pallet sideways less reliably than they turn it
    (noise-free views at 15 deg have them a few mm off where the pockets are sub-millimetre).

    Each pixel's cost is tabulated against the lateral offset of its deck point (a turn by t moves a
    point x behind the face sideways by about -x t, a shift by u by -u), so a hypothesis costs one
    lookup per pixel. The 1-sigma is the half-width of the yaws within 1 of the minimum cost, at least
    the turn that moves the deck's far end by a pixel's quantisation (footprint / sqrt(12)).
    """
    deck = _deck_pixels(frame, T_cf, valid, model, plane, s0, z0, sigma, cfg)
    if deck is None:
        return None
    cam = T_cf.t
    d, w, deck_h, centre = deck
    trunc = cfg.truncation_sigma
    z_deck = (deck_h - cam[2]) / d[:, 2]
    q = cam[:2] + d[:, :2] * z_deck[:, None] - centre[:2]
    thick = model.top_boards_thickness
    w_low = 1.0 / ((deck_h - thick - cam[2]) / d[:, 2])  # a board's thickness below the deck
    sigma_face = math.sqrt(max(_yaw_variance(plane), 1e-12))
    psi_face = plane.psi
    span = min(4.0 * sigma_face, math.radians(cfg.deck_yaw_search_deg))
    step = cfg.deck_lateral_step_m
    shift_max = min(3.0 * sigma_s, cfg.deck_shift_max_m)
    # Whole table steps: a pure shift then looks up its pixels' costs exactly.
    n_shift = min(cfg.deck_shift_steps, int(shift_max / step))
    shifts = step * np.round(np.linspace(-shift_max, shift_max, 2 * n_shift + 1) / step)
    reach = model.length * span + shift_max + 2 * step  # largest lateral offset a hypothesis gives a pixel
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

    def total(dpsi: np.ndarray, dpsi_b: float, xh: np.ndarray, cost: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Cost per yaw of `dpsi` (least over the shifts) and the shift (m) that gives it."""
        u = -xh[:, None, None] * (dpsi[None, :, None] - dpsi_b) - shifts[None, None, :]
        k = np.clip(np.rint((u + reach) / step).astype(int), 0, len(offsets) - 1)
        tot = np.take_along_axis(cost, k.reshape(len(xh), -1), axis=1).sum(axis=0).reshape(len(dpsi), len(shifts))
        tot = tot + (dpsi[:, None] / sigma_face) ** 2
        if sigma_s > 0.0:
            tot = tot + (shifts[None, :] / sigma_s) ** 2
        best = np.argmin(tot, axis=1)
        return tot[np.arange(len(dpsi)), best], shifts[best]

    # Coarse search on the table at the face's yaw, then a fine one on a table rebuilt at that answer
    # (the rays' slopes in the pallet frame turn with the yaw).
    dpsi, shift = 0.0, 0.0
    for half in (span, 0.15 * span):
        xh, cost = table(psi_face + dpsi)
        grid = dpsi + np.linspace(-half, half, 41)
        tot, best_shift = total(grid, dpsi, xh, cost)
        i = int(np.argmin(tot))
        dpsi, shift = float(grid[i]), float(best_shift[i])
    near_min = grid[tot <= tot.min() + 1.0]
    footprint_far = float(np.max(z_deck)) / float(frame.K[0, 0])
    floor = footprint_far / math.sqrt(12.0) / model.length
    sig = cfg.deck_sigma_scale * max(0.5 * float(np.ptp(near_min)), floor)
    return _DeckYaw(psi_face + dpsi, min(sig, sigma_face), len(w), deck_h, shift, min(floor, sigma_face))
