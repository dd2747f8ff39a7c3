"""Lens distortion in frame bundles: the `dist` field (contract, .npz, wire), `undistort_bundle`, its callers.

The synthetic plane: a floor 1 m below a camera pitched 20 deg down, rendered exactly through a lens with
known coefficients (each distorted pixel's ray from OpenCV's iterative inverse, 100 rounds), so the only
error left after undistortion is the nearest-neighbour resampling.
"""

from __future__ import annotations

import dataclasses
import json
import sys
from pathlib import Path

import cv2
import numpy as np
import pytest

from palletpilot.perception import wire
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.clearance import Volume, check_volume
from palletpilot.perception.distortion import (
    distort_points,
    fit_brown_conrady,
    undistort_bundle,
    undistort_maps,
)
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import DIST_LENGTHS, FrameBundle, load_bundle, save_bundle
from palletpilot.perception.pointcloud import deproject

H, W = 480, 640
K = np.array([[380.0, 0.0, 322.3], [0.0, 380.0, 241.7], [0.0, 0.0, 1.0]])
LENS = np.array([-0.12, 0.03, 0.0008, -0.0005, -0.004])  # a wide colour lens: barrel, slight decentering
PITCH = np.radians(20.0)
FLOOR_N = np.array([0.0, np.cos(PITCH), np.sin(PITCH)])  # the floor's normal (down) in the camera frame
FLOOR_D = 1.0  # m: points p of the floor have FLOOR_N . p = FLOOR_D
EXACT = (cv2.TERM_CRITERIA_COUNT | cv2.TERM_CRITERIA_EPS, 100, 1e-12)


def ideal_pixels(K: np.ndarray, dist: np.ndarray, shape: tuple[int, int]) -> np.ndarray:
    """For every pixel of the distorted image, the ideal pixel (same K) on the same ray: H x W x 2."""
    h, w = shape
    rows, cols = np.mgrid[0:h, 0:w]
    pix = np.column_stack([cols.ravel(), rows.ravel()]).astype(np.float64).reshape(-1, 1, 2)
    return cv2.undistortPoints(pix, K, dist, None, None, K, EXACT).reshape(h, w, 2)


def floor_depth(dist: np.ndarray) -> np.ndarray:
    """The floor's z-depth (m) in each pixel of an image taken through `dist`; 0 above the horizon or past 20 m."""
    ideal = ideal_pixels(K, dist, (H, W)).reshape(-1, 2)
    rays = np.column_stack([(ideal - K[:2, 2]) / np.diag(K)[:2], np.ones(len(ideal))])
    with np.errstate(divide="ignore"):
        z = FLOOR_D / (rays @ FLOOR_N)
    z[~np.isfinite(z) | (z <= 0) | (z > 20.0)] = 0.0
    return z.reshape(H, W).astype(np.float32)


def distort_image(image: np.ndarray, K: np.ndarray, dist: np.ndarray, fill: float, nearest: bool) -> np.ndarray:
    """An ideal image as the camera with `dist` (same K) would have taken it (resampled)."""
    ideal = ideal_pixels(K, dist, image.shape[:2]).astype(np.float32)
    mode = cv2.INTER_NEAREST if nearest else cv2.INTER_LINEAR
    return cv2.remap(image, ideal[..., 0], ideal[..., 1], mode, borderMode=cv2.BORDER_CONSTANT, borderValue=fill)


def plane_errors_mm(frame: FrameBundle, near_m: float = 3.0) -> np.ndarray:
    """|distance| (mm) of the deprojected points nearer than `near_m` from the floor plane."""
    points = deproject(frame.depth, frame.K).points
    points = points[points[:, 2] < near_m]
    return np.abs(points @ FLOOR_N - FLOOR_D) * 1e3


# -- the field: contract, .npz, wire ---------------------------------------------------------------


@pytest.mark.parametrize("n", DIST_LENGTHS)
def test_every_coefficient_count_is_saved_and_loaded_exactly(tmp_path: Path, n: int) -> None:
    dist = np.zeros(n)
    dist[:5] = LENS[:n] if n < 5 else LENS
    frame = FrameBundle(np.ones((H, W), np.float32), K, dist=dist)
    back = load_bundle(save_bundle(tmp_path / "f.npz", frame))
    assert back.dist is not None and back.dist.dtype == np.float64 and np.array_equal(back.dist, dist)
    assert back.distorted
    plain = load_bundle(save_bundle(tmp_path / "g.npz", FrameBundle(np.ones((H, W), np.float32), K)))
    assert plain.dist is None and not plain.distorted
    with np.load(tmp_path / "g.npz") as data:
        assert "dist" not in data.files  # a bundle without distortion is written as before


@pytest.mark.parametrize(
    ("dist", "words"),
    [
        (np.array([0.1, 0.0, 0.0]), "dist: must be a float64 vector of 4, 5, 8, 12 or 14"),
        (np.zeros(5, dtype=np.float32), "got shape (5,) dtype float32"),
        (np.zeros((1, 5)), "got shape (1, 5)"),
        ([0.1, 0.0, 0.0, 0.0], "dist: expected a numpy array, got list"),
        (np.array([np.nan, 0.0, 0.0, 0.0, 0.0]), "dist: has non-finite coefficients"),
        (np.array([0.1, 0.0, 0.5, 0.0, 0.0]), "dist: p1, p2 up to 0.5: beyond 0.1"),
        (np.array([5e3, 0.0, 0.0, 0.0, 0.0]), "dist: k1..k6 up to 5000"),
        (np.array([-3.0, 0.0, 0.0, 0.0, 0.0]), "dist: the lens model folds back"),  # k1 in the wrong units
        (np.array([0.0, 0.0, 0.0, 0.0, -2.0]), "dist: the lens model folds back"),
        (np.array([1.0, 0.0, 0.0, 0.0, 0.0, 8.0, 0.0, 0.0]), "brings no ray within 6 x"),  # r / 8 far out
    ],
)
def test_implausible_coefficients_are_one_line(dist: object, words: str) -> None:
    with pytest.raises(PerceptionError) as err:
        FrameBundle(np.ones((H, W), np.float32), K, dist=dist)  # type: ignore[arg-type]
    assert len(err.value.problems) == 1 and words in str(err.value), str(err.value)
    assert str(err.value).startswith("FrameBundle: dist: ")


def test_real_lenses_pass_the_contract() -> None:
    depth = np.ones((H, W), np.float32)
    FrameBundle(depth, K, dist=LENS)
    # An OAK-D's rational model (14 coefficients, numerator and denominator nearly cancel).
    oak = np.array([-4.6, 14.5, 0.0004, -0.0003, 13.4, -4.7, 14.6, 13.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0])
    FrameBundle(depth, K, dist=oak)
    FrameBundle(depth, K, dist=np.array([0.12, -0.25, 0.001, 0.0, 0.1]))  # pincushion


def test_a_bad_dist_in_a_file_names_the_file_and_is_refused_before_reading(tmp_path: Path) -> None:
    path = tmp_path / "bad.npz"
    np.savez(path, depth=np.ones((H, W), np.float32), K=K, dist=np.zeros(6))
    with pytest.raises(PerceptionError, match=r"bad.npz: dist: must be a float64 vector of 4, 5, 8, 12 or 14"):
        load_bundle(path)
    np.savez(path, depth=np.ones((H, W), np.float32), K=K, dist=np.array([0.0, 0.0, 0.9, 0.0]))
    with pytest.raises(PerceptionError, match=r"bad.npz: dist: p1, p2 up to 0.9"):
        load_bundle(path)


def test_wire_carries_dist_and_old_messages_still_decode() -> None:
    depth = floor_depth(LENS)
    frame = FrameBundle(depth, K, dist=LENS, stamp_s=3.0)
    back = wire.decode_frame(wire.encode_frame(frame))
    assert back.dist is not None and np.array_equal(back.dist, LENS) and np.array_equal(back.depth, depth)
    params, frames = wire.decode_request(wire.encode_request({"x": 1}, [frame]))
    assert params == {"x": 1}
    assert frames[0].dist is not None and np.array_equal(frames[0].dist, LENS)
    plain = dataclasses.replace(frame, dist=None)
    payload = bytes(wire.encode_frame(plain))
    assert b'"dist"' not in payload  # the layout of a frame without distortion is unchanged
    assert wire.decode_frame(payload).dist is None
    raw = bytes(wire.encode_frame(frame))
    n = int.from_bytes(raw[16:20], "little")  # the meta's length (header: magic, 4 bytes, H, W, length)
    meta = json.loads(raw[20 : 20 + n])
    meta["dist"][0] = "x"
    text = json.dumps(meta).encode()
    bad = raw[:16] + len(text).to_bytes(4, "little") + text + raw[20 + n :]
    with pytest.raises(PerceptionError, match=r"frame meta: dist: expected a finite number"):
        wire.decode_frame(bad)


# -- undistortion ----------------------------------------------------------------------------------


def test_no_coefficients_is_the_same_frame() -> None:
    depth = np.ones((H, W), np.float32)
    frame = FrameBundle(depth, K)
    assert undistort_bundle(frame) is frame
    zeros = FrameBundle(depth, K, dist=np.zeros(8))
    assert undistort_bundle(zeros) is zeros


def test_undistorted_plane_is_flat_and_k_alone_bends_it() -> None:
    frame = FrameBundle(floor_depth(LENS), K, dist=LENS)
    ideal = undistort_bundle(frame)
    assert ideal.dist is None and ideal.K is frame.K and ideal.depth.dtype == np.float32
    err = plane_errors_mm(ideal)
    bent = plane_errors_mm(dataclasses.replace(frame, dist=None))
    assert len(err) > 100_000
    assert np.percentile(err, 95) < 3.0 and err.max() < 5.0, np.percentile(err, [50, 95, 100])
    assert np.percentile(bent, 95) > 30.0, np.percentile(bent, [50, 95, 100])
    # The ideal image agrees with a floor rendered without a lens (where both see it).
    truth = floor_depth(np.zeros(5))
    both = (ideal.depth > 0) & (truth > 0) & (truth < 3.0)
    assert np.percentile(np.abs(ideal.depth[both] - truth[both]) / truth[both], 95) < 0.005


def test_depth_and_labels_are_never_interpolated_and_no_data_stays_no_data() -> None:
    depth = np.full((H, W), 3.0, np.float32)
    depth[150:330, 200:420] = 1.2  # a box in front of a wall
    depth[200:220, 100:140] = np.nan  # no reading
    depth[400:, :] = 0.0
    labels = np.full((H, W), 1, np.uint8)
    labels[150:330, 200:420] = 7
    rgb = np.zeros((H, W, 3), np.uint8)
    rgb[..., 1] = 200
    pincushion = np.array([0.1, -0.02, 0.0005, 0.0003, 0.0])  # the ideal image's corners: outside the camera's
    frame = FrameBundle(depth, K, labels, rgb, dist=pincushion)
    out = undistort_bundle(frame)
    values = set(np.unique(out.depth[np.isfinite(out.depth)]).tolist())
    assert values <= {0.0, 1.2000000476837158, 3.0}, values  # only source depths (or no data): no mixed edge
    assert np.isnan(out.depth).any() and (out.depth == 0).any()
    assert set(np.unique(out.labels).tolist()) <= {1, 7, 255}
    maps = undistort_maps(K, pincushion, (H, W))
    outside = maps.outside.reshape(H, W)
    assert outside.any() and np.all(out.depth[outside] == 0) and np.all(out.labels[outside] == 255)
    inner = cv2.erode((~outside).astype(np.uint8), np.ones((3, 3), np.uint8)) > 0  # bilinear: the rim blends
    assert out.rgb is not None and out.rgb.dtype == np.uint8 and np.all(out.rgb[inner][:, 1] >= 199)
    assert np.all(out.rgb[outside] == 0)
    assert undistort_maps(K, pincushion.copy(), (H, W)) is maps  # cached per (K, dist, size)


def test_a_lens_model_that_folds_beyond_the_image_leaves_those_ideal_pixels_empty() -> None:
    # r (1 + 10 r^2) / (1 + 10 r^4) grows to 1.2 (past the distorted image's corner, 0.8) and turns back at
    # r = 0.7: the ideal image's corners (0.8) lie beyond the fold, where a second ray would map into the image.
    dist = np.array([10.0, 0.0, 0.0, 0.0, 0.0, 0.0, 10.0, 0.0])
    k_narrow = np.array([[500.0, 0.0, 319.5], [0.0, 500.0, 239.5], [0.0, 0.0, 1.0]])
    frame = FrameBundle(np.ones((H, W), np.float32), k_narrow, dist=dist)
    out = undistort_bundle(frame)
    assert out.depth[0, 0] == 0 and out.depth[H - 1, W - 1] == 0 and out.depth[H // 2, W // 2] == 1.0


def test_distort_points_and_fit_recover_coefficients() -> None:
    rng = np.random.default_rng(0)
    xy = rng.uniform(-0.9, 0.9, (500, 2))
    coeffs, miss = fit_brown_conrady(xy, distort_points(xy, LENS))
    assert np.allclose(coeffs, LENS, atol=1e-9) and miss < 1e-9
    with pytest.raises(PerceptionError, match="need as many ideal as distorted points"):
        fit_brown_conrady(xy[:3], xy[:3])


# -- where perception takes a frame ----------------------------------------------------------------


@pytest.fixture(scope="module")
def sim_frame_and_truth():
    sys.path.insert(0, str(Path(__file__).parent))
    from test_perception_calibration import render

    return render()


def _distorted(frame: FrameBundle, dist: np.ndarray) -> FrameBundle:
    return FrameBundle(
        distort_image(frame.depth, frame.K, dist, 0.0, nearest=True),
        frame.K,
        distort_image(frame.labels, frame.K, dist, 255, nearest=True),
        distort_image(frame.rgb, frame.K, dist, 0, nearest=False),
        frame.fork_height,
        dist=dist,
    )


def test_calibration_undistorts_each_frame(sim_frame_and_truth) -> None:
    from test_perception_calibration import FORKS, errors

    from palletpilot.perception.calibration import calibrate

    frame, truth = sim_frame_and_truth
    lensed = _distorted(frame, LENS)
    dt, da = errors(calibrate([lensed], FORKS).T_forklift_camera, truth)
    assert np.all(np.abs(dt) < 1.5) and np.all(np.abs(da) < 0.02), (dt, da)
    dt_k, da_k = errors(calibrate([dataclasses.replace(lensed, dist=None)], FORKS).T_forklift_camera, truth)
    assert np.max(np.abs(dt_k)) > 4.0 and np.max(np.abs(da_k)) > 0.2, (dt_k, da_k)  # K alone: what a lens does


def test_volume_check_and_labels_take_the_undistorted_frame(sim_frame_and_truth) -> None:
    from palletpilot.perception.segmentation import GroundTruthSegmenter, ensure_labels

    frame, truth = sim_frame_and_truth
    lensed = _distorted(frame, LENS)
    calibration = Calibration(truth, "model", {}, ())
    volume = Volume(1.2, 3.0, -0.6, 0.6, 0.0, 1.5)
    assert check_volume(lensed, calibration, volume) == check_volume(undistort_bundle(lensed), calibration, volume)
    seen = []
    segmenter = GroundTruthSegmenter(lambda: seen.append(1) or np.zeros((H, W), np.uint8))
    labelled = ensure_labels(dataclasses.replace(lensed, labels=None), segmenter)
    assert labelled.dist is None and seen == [1] and labelled.labels is not None
    assert ensure_labels(lensed, segmenter).dist is None  # labelled already: undistorted all the same


# -- RealSense: the colour stream's own lens model -------------------------------------------------


def _intrinsics(rs, model: str, coeffs: list[float]):
    intr = rs.intrinsics()
    intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy = W, H, 610.0, 609.0, 318.2, 243.9
    intr.model, intr.coeffs = getattr(rs.distortion, model), coeffs
    return intr


def test_realsense_models_become_opencv_coefficients() -> None:
    rs = pytest.importorskip("pyrealsense2")
    from palletpilot.perception.realsense import opencv_distortion

    assert opencv_distortion(rs, _intrinsics(rs, "none", [0.1] * 5), "cam") is None
    assert opencv_distortion(rs, _intrinsics(rs, "inverse_brown_conrady", [0.0] * 5), "cam") is None
    bc = [0.08, -0.2, 0.001, -0.0007, 0.09]
    got = opencv_distortion(rs, _intrinsics(rs, "brown_conrady", bc), "cam")
    assert got is not None and np.allclose(got, bc, atol=1e-7)
    d455 = [-0.0556, 0.0655, -0.00086, 0.00047, -0.0207]  # a D455 colour stream's inverse Brown-Conrady
    for model in ("inverse_brown_conrady", "modified_brown_conrady"):
        intr = _intrinsics(rs, model, d455)
        dist = opencv_distortion(rs, intr, "cam")
        assert dist is not None
        xy = np.array([[u, v] for u in np.linspace(-0.55, 0.55, 9) for v in np.linspace(-0.42, 0.42, 7)])
        sdk = np.array([rs.rs2_project_point_to_pixel(intr, [x, y, 1.0]) for x, y in xy])
        ours = distort_points(xy, dist) * [610.0, 609.0] + [318.2, 243.9]
        assert np.max(np.abs(sdk - ours)) < 0.01  # the same projection rs.align used


def test_realsense_models_perception_cannot_express_are_refused() -> None:
    rs = pytest.importorskip("pyrealsense2")
    from palletpilot.perception.realsense import opencv_distortion

    with pytest.raises(PerceptionError, match=r"cam: colour lens model kannala_brandt4 \(a fisheye model\)"):
        opencv_distortion(rs, _intrinsics(rs, "kannala_brandt4", [0.1, 0.0, 0.0, 0.0, 0.0]), "cam")
    with pytest.raises(PerceptionError, match=r"fitted to librealsense's projection miss it by"):
        opencv_distortion(rs, _intrinsics(rs, "inverse_brown_conrady", [0.1, -0.05, 0.01, -0.02, 0.03]), "cam")


def test_ros_camera_info_distortion_models() -> None:
    from palletpilot.executor.adapters.ros.camera import _distortion

    assert _distortion("plumb_bob", [0.0] * 5, "info") is None  # all zero: an ideal pinhole
    d = _distortion("plumb_bob", [-0.05, 0.06, 0.0, 0.0, -0.02], "info")
    assert d is not None and d.dtype == np.float64 and len(d) == 5
    assert _distortion("rational_polynomial", [0.1] * 8, "info") is not None
    with pytest.raises(PerceptionError, match="equidistant"):
        _distortion("equidistant", [0.1, 0.0, 0.0, 0.0], "info")
