"""The entry face as a vertical plane fitted in inverse depth: pixels as rays, the plane, its fits and spread.

Frames (ARCHITECTURE.md): `camera` optical (x right, y down, z forward), `forklift` (origin on the
floor between the fork heels, x towards the tips, y left, z up). A pixel is a ray `p(z) = t + d z` in
the forklift frame (`d` its direction for unit camera z-depth, `t` the camera position) with the
measured inverse depth `w = 1 / z`. On a vertical plane `cos(psi) x + sin(psi) y = rho` the inverse
depth is linear in the ray: `w = A d_x + B d_y` with `(A, B) = (cos psi, sin psi) / D`, `D` the
camera's distance to the plane. On the plane, `s` is the lateral coordinate (along `e`, pallet y) and
`h` the height (forklift z).

Package-internal API (used by `perception.pallet`, `perception.pallet_model`, `perception.pallet_deck`):
- `_Rays` / `_rays` (pixels as rays), `_Plane` (psi, D, normal `n`, lateral `e`, `predict`, `point`),
  `_FaceCoords` / `_face_coords` (rays on the plane: `s`, `h`, their slopes behind it).
- Fits: `_ransac` (RANSAC over pixel pairs, then re-weighted least squares), `_fit_plane` (least
  squares), `_joint_refine` (Gauss-Newton on face and side-wall pixels), `_robust_sigma` (MAD).
- Spread: `_yaw_variance` (of the plane's yaw), `_spread` (1-sigma of the pallet origin and yaw from
  the frame's own noise), `_common_spread` (the part every frame shares), `_face_lever`.
- Image support: `_face_run` (lateral extent of the face inliers), `_depth_edges` (pixels at depth
  jumps), `_roi` / `_image_box` (image rows and columns covering forklift-frame points).
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from palletpilot.geometry import SE3
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.pallet_estimate import PalletEstimatorConfig, PalletNotFound, PalletSpread
from palletpilot.perception.pointcloud import depth_edges


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

    def plus(self, more: _Rays) -> _Rays:
        """These rays and `more`."""
        return _Rays(
            np.concatenate([self.rows, more.rows]),
            np.concatenate([self.cols, more.cols]),
            np.concatenate([self.d, more.d]),
            np.concatenate([self.w, more.w]),
            np.concatenate([self.labelled, more.labelled]),
        )


def _directions(K: np.ndarray, R: np.ndarray, rows: np.ndarray, cols: np.ndarray) -> np.ndarray:
    """Forklift-frame ray directions (N, 3) per unit camera depth of pixels (camera rotation `R`)."""
    fx, fy, cx, cy, skew = K[0, 0], K[1, 1], K[0, 2], K[1, 2], K[0, 1]
    yc = (rows - cy) / fy
    xc = ((cols - cx) - skew * yc) / fx
    # Element-wise, not a BLAS product: right after Open3D's ray casting, a threaded BLAS call on two
    # cores oversubscribes them badly (see sim.camera).
    return xc[:, None] * R[:, 0] + yc[:, None] * R[:, 1] + R[:, 2]


def _no_return_rays(
    frame: FrameBundle, T_cf: SE3, rs: slice, cs: slice, support_z: float, cfg: PalletEstimatorConfig
) -> _Rays:
    """Pixels of the region `rs` x `cs` without depth that saw past the face, as rays of inverse depth 0
    (`PalletEstimatorConfig.no_return_range_m`): no pixel with depth within `no_return_margin_px`, and
    the ray above `support_z` (forklift frame, m) for `no_return_range_m` of camera depth. In the model's
    scores a ray of inverse depth 0 contradicts the solid face and agrees with a pocket or the open side."""
    import cv2

    empty = np.zeros(0, np.int64)
    if cfg.no_return_range_m <= 0.0:
        return _Rays(empty, empty, np.zeros((0, 3)), np.zeros(0), np.zeros(0, bool))
    sub = frame.depth[rs, cs]
    none = ~(np.isfinite(sub) & (sub > 0))
    k = 2 * cfg.no_return_margin_px + 1
    kernel = np.ones((k, k), np.uint8)
    none = cv2.erode(none.astype(np.uint8), kernel, borderType=cv2.BORDER_CONSTANT, borderValue=0) > 0
    rr, cc = np.nonzero(none)
    rr, cc = rr + rs.start, cc + cs.start
    d = _directions(frame.K, T_cf.R, rr, cc)
    with np.errstate(divide="ignore", invalid="ignore"):
        reach = np.where(d[:, 2] < 0.0, (support_z - T_cf.t[2]) / d[:, 2], np.inf)  # depth where it meets the support
    far = reach > cfg.no_return_range_m
    n = int(far.sum())
    return _Rays(rr[far], cc[far], d[far], np.zeros(n), np.zeros(n, bool))


def _rays(
    depth: np.ndarray, K: np.ndarray, R: np.ndarray, rows: np.ndarray, cols: np.ndarray, lab: np.ndarray
) -> _Rays:
    z = depth[rows, cols].astype(np.float64)
    return _Rays(rows, cols, _directions(K, R, rows, cols), 1.0 / z, lab)


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


def _yaw_variance(plane: _Plane) -> float:
    """Variance (rad^2) of the plane's yaw from the covariance of (A, B)."""
    A, B = plane.A, plane.B
    r2 = A * A + B * B
    grad = np.array([-B / r2, A / r2])  # d psi / d (A, B)
    return float(grad @ plane.cov @ grad)


def _spread(
    plane: _Plane,
    cam: np.ndarray,
    s0: float,
    sigma_s: float,
    cov3: np.ndarray | None,
    *,
    cfg: PalletEstimatorConfig,
    columns: np.ndarray,
    footprint: float,
    deck_yaw: tuple[float, float, float] | None = None,
) -> PalletSpread:
    """1-sigma of the pallet origin's x, y (m, forklift frame) and yaw (rad): this frame's own noise plus
    what every frame from the standpoint shares (`PalletSpread`'s common parts).

    Own: along the face normal, the plane fit's inverse-depth uncertainty at the origin's ray; along the
    face, `sigma_s` from the pocket edges (the edges fix a point on the face whatever the yaw); yaw, the
    plane fit's covariance (`cov3`, of psi, D and s0, when the joint fit ran), or the deck's
    (`deck_yaw`: its 1-sigma, the part of it the pixel grid sets, and the deck's length in m).

    Common (errors the per-pixel noise model cannot see): each face part (block, board) is off the drawing
    by `part` = `cfg.build_tolerance_m` / (2 sqrt 3) (uniform within +- half the tolerance), so the face
    plane, fitted over some four parts, is off by part / 2 along its normal and turned by part /
    `_face_lever(columns)`; the pocket centre, the mean of four block-side edges, is off sideways by part /
    2 and by its edges' quantisation, footprint / sqrt(12) (`footprint`: a pixel's width on the face, m; the
    four edges lie on one pixel grid, so their quantisation errors do not average out: on `bench pallet
    --families tolerance`, seed 0, the three frames of a standpoint at 2.5 m agreed to 1 mm and were 4-5 mm
    off together). A deck yaw's board edges, straight to `part` at either end, turn by sqrt(2) part /
    length; its pixel-grid part is common too (and taken out of the own part). The depth scale error moves
    the origin along its ray (`_common_spread`).

    The own parts from the fits (plane, deck) assume independent pixels; they are widened by the square
    root of the camera's correlation area, `cfg.depth_correlation_px` (the pocket edges' scatter is measured).
    """
    n, e = plane.n, plane.e
    origin = plane.point(cam, s0)
    u = (origin - cam) / float(np.linalg.norm(origin - cam))  # unit ray to the origin
    lam = float(np.linalg.norm(origin - cam))  # 1 / lam = A u_x + B u_y on the plane
    n_corr = max(cfg.depth_correlation_px, 1.0)  # the fits' covariances assume independent pixels
    sigma_lam = lam * lam * math.sqrt(max(n_corr * float(u[:2] @ plane.cov @ u[:2]), 0.0))
    sigma_n = float(n @ u) * sigma_lam
    cov_xy = sigma_n**2 * np.outer(n[:2], n[:2]) + sigma_s**2 * np.outer(e[:2], e[:2])
    var_yaw = n_corr * (float(cov3[0, 0]) if cov3 is not None else _yaw_variance(plane))
    sx, sy, syaw = math.sqrt(cov_xy[0, 0]), math.sqrt(cov_xy[1, 1]), math.sqrt(max(var_yaw, 0.0))
    part = cfg.build_tolerance_m / (2.0 * math.sqrt(3.0))
    cyaw = part / max(_face_lever(columns), 1e-3)
    if deck_yaw is not None:
        sigma_deck, floor, length = deck_yaw
        syaw = math.sqrt(n_corr * max(sigma_deck**2 - floor**2, 0.0))
        cyaw = math.hypot(math.sqrt(2.0) * part / length, floor)
    cx, cy = _common_spread(
        plane, cam, origin, 0.5 * part, math.hypot(0.5 * part, footprint / math.sqrt(12.0)), cfg.depth_scale_sigma
    )
    return PalletSpread(math.hypot(sx, cx), math.hypot(sy, cy), math.hypot(syaw, cyaw), cx, cy, cyaw)


def _face_lever(columns: np.ndarray) -> float:
    """Root of the summed squared lateral distances (m) of the block columns' centres from their mean: a
    face part's offset `d` along the normal turns the face by about d / lever."""
    centres = np.asarray(columns, float).mean(axis=1)
    return float(np.sqrt(np.sum((centres - centres.mean()) ** 2)))


def _common_spread(
    plane: _Plane, cam: np.ndarray, origin: np.ndarray, sigma_n: float, sigma_e: float, depth_scale_sigma: float
) -> tuple[float, float]:
    """1-sigma x, y (m, forklift frame) of the part of the pallet origin's error that every frame from the
    standpoint shares: `sigma_n` along the face normal and `sigma_e` along the face (the pallet's build,
    the pixel grid), and the camera's depth scale error, which moves the origin along its ray by
    `depth_scale_sigma` times the ray's length."""
    n, e = plane.n[:2], plane.e[:2]
    ray = (origin - cam)[:2]
    cov = sigma_n**2 * np.outer(n, n) + sigma_e**2 * np.outer(e, e) + depth_scale_sigma**2 * np.outer(ray, ray)
    return math.sqrt(cov[0, 0]), math.sqrt(cov[1, 1])


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
    """Pixels whose 3 x 3 neighbourhood spans a depth jump larger than noise explains (both sides of an edge):
    `pointcloud.depth_edges` with the jump the larger of `cfg.edge_jump_rel` and the depth noise's share."""
    d = np.where(valid, depth, 0.0)
    return depth_edges(depth, np.maximum(cfg.edge_jump_rel, cfg.edge_jump_sigma * cfg.depth_noise_k * d), valid)


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
