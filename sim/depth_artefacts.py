"""Depth artefacts of an active-stereo camera (D435) that `sim.camera.RaycastRenderer` adds to exact depth.

- Stereo shadow (`stereo_shadow`): the depth is computed from two IR imagers; it is referenced to the
  left imager and the right imager sits `baseline_m` to its +x (image right). A point that the right
  imager cannot see, because something nearer lies on the ray from the right imager's centre to it,
  has no disparity and so no depth. This is the no-depth band on the image-left side of every
  foreground object, `f B (1/z_near - 1/z_far)` pixels wide. The rendered (aligned) camera stands in
  for the left imager; the right imager's field of view is taken to cover the rendered one (the D435's
  depth imagers see far wider than the colour stream that depth is aligned to).
- Depth scale error (`depth_scale`): every depth value times `1 + s`, with `s` fixed per camera
  (a calibration error of the stereo pair), drawn uniformly in `[-e, +e]`.

Frames and units: camera optical frame (x right, y down, z forward), z-depth in metres, pixels as in
`sim.camera` (pixel centres at integer (u, v)).
"""

from __future__ import annotations

import hashlib

import numpy as np
import open3d as o3d

from palletpilot.geometry import SE3

SHADOW_TOL_REL = 0.01
SHADOW_TOL_M = 0.002
"""A surface within `SHADOW_TOL_REL * z + SHADOW_TOL_M` of a point (along the right imager's ray) does not
shadow it: the point's own surface, and surfaces the stereo matcher could not tell apart from it."""


def shadow_candidates(
    z: np.ndarray,
    hit: np.ndarray,
    fx_px: float,
    baseline_m: float,
    width: int,
    scratch: tuple[np.ndarray, np.ndarray],
) -> np.ndarray:
    """Flat indices of the hit pixels that something may hide from the right imager (a superset).

    `z` (N,) float32 exact z-depth (m, inf where missed), `hit` (N,) bool, N = height * width in row
    order; `fx_px` the rendered camera's focal length (px). Rows are epipolar lines (the baseline runs
    along camera x), and the right imager sees pixel u at column u_r = u - fx B / z. Anything on the
    right imager's ray to a point that the left view shows is nearer and lies to the right of the point
    in the same row; a point hidden in the left view has a nearer one in front of it, also to the right.
    So pixel u can only be shadowed if a pixel u' > u has u'_r <= u_r (the stereo ordering constraint):
    a reverse running maximum of -u_r per row. `scratch` is two (N,) float32 work arrays.
    """
    g, run = (a.reshape(-1, width) for a in scratch)
    with np.errstate(divide="ignore"):
        np.divide(np.float32(fx_px * baseline_m), z.reshape(-1, width), out=g)  # disparity (px), 0 where missed
    g -= np.arange(width, dtype=np.float32)  # -u_r
    np.maximum.accumulate(g[:, ::-1], axis=1, out=run[:, ::-1])  # run[:, u] = max over u' >= u
    behind = np.zeros(g.shape, bool)
    np.greater(run[:, 1:], g[:, :-1], out=behind[:, :-1])
    behind &= hit.reshape(-1, width)
    return np.flatnonzero(behind)


def stereo_shadow(
    scene: o3d.t.geometry.RaycastingScene,
    T_world_camera: SE3,
    world_directions: np.ndarray,
    z: np.ndarray,
    candidates: np.ndarray,
    baseline_m: float,
) -> np.ndarray:
    """The candidates (flat pixel indices) that the right imager cannot see: a subset of `candidates`.

    Each candidate's point (world frame) is `C + z d`, with C the camera centre and d its pixel's ray
    (`world_directions` (N, 1, 3) float32, z component 1 in the camera frame); the right imager's centre
    is `C + baseline_m * x_camera`. One occlusion ray per candidate from there to the point, ending
    `SHADOW_TOL_REL * z + SHADOW_TOL_M` short of it, tested against the scene: exact for thin occluders
    too (which the ordering constraint alone over-shadows).
    """
    if candidates.size == 0:
        return candidates
    zc = z[candidates]
    right = (T_world_camera.R[:, 0] * baseline_m).astype(np.float32)  # right imager centre - C (world)
    rays = np.empty((candidates.size, 6), np.float32)
    rays[:, :3] = (T_world_camera.t + T_world_camera.R[:, 0] * baseline_m).astype(np.float32)
    np.multiply(world_directions[candidates, 0, :], zc[:, None], out=rays[:, 3:])
    rays[:, 3:] -= right  # right imager centre -> point
    rays[:, 3:] *= (1.0 - np.float32(SHADOW_TOL_REL) - np.float32(SHADOW_TOL_M) / zc)[:, None]
    hidden = scene.test_occlusions(o3d.core.Tensor.from_numpy(rays), tfar=1.0).numpy()
    return candidates[hidden]


def depth_scale(rng: np.random.Generator, max_error: float) -> float:
    """The camera's depth scale error s in [-max_error, +max_error] (measured z = true z (1 + s)).

    Fixed per camera: drawn uniformly from the identity of the camera's generator `rng` (PCG64's
    stream increment, fixed at seeding and kept by `bit_generator.state` snapshots; otherwise its
    seed sequence), not from its advancing state. So every frame of one camera has the same s, the
    same seed gives the same s, and drawing it does not move the noise stream. A generator with
    neither (a seedless bit generator) pays one draw from its stream, per frame.
    """
    if max_error <= 0.0:
        return 0.0
    state = rng.bit_generator.state
    inner = state.get("state")
    seed_seq = getattr(rng.bit_generator, "seed_seq", None)
    if isinstance(inner, dict) and ("inc" in inner or "key" in inner):  # PCG64 / PCG64DXSM, Philox
        key = repr((state["bit_generator"], inner.get("inc"), inner.get("key")))
    elif isinstance(seed_seq, np.random.SeedSequence):
        key = repr((state["bit_generator"], seed_seq.entropy, seed_seq.spawn_key, seed_seq.pool_size))
    else:
        return float(rng.uniform(-max_error, max_error))
    digest = hashlib.blake2b(f"depth_scale_error:{key}".encode(), digest_size=8).digest()
    unit = (int.from_bytes(digest, "little") >> 11) * 2.0**-53  # uniform in [0, 1)
    return float(max_error * (2.0 * unit - 1.0))
