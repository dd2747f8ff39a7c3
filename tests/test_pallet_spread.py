"""The pallet estimate's stated spread (issue 37, "honest uncertainty"): the parts every frame shares, how
fusing and the frame policy treat them, the alignment check that takes them into account, and the
bench's coverage and crop checks."""

import dataclasses
import math

import numpy as np
import pytest

from palletpilot.bench.pallet import FrameSpec, render, standpoint
from palletpilot.bench.pallet_coverage import Honesty, coverage, crop_box, crop_check, crop_frame, forklift_errors
from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.alignment import AlignmentTolerances, check_alignment
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.pallet import (
    DEFAULT_CONFIG,
    FramePolicy,
    PalletSpread,
    estimate_pallet,
    fuse_estimates,
)
from palletpilot.perception.pallet_face import _face_lever
from palletpilot.perception.pallet_model import _Model
from palletpilot.perception.specs import PalletType, load_forks, pallet_pose_at_node

MISSIONS = bundled_path("missions")
PART = DEFAULT_CONFIG.build_tolerance_m / (2 * math.sqrt(3))  # one face part's 1-sigma off the drawing


def _calibration(frame) -> Calibration:
    return Calibration(SE3.from_matrix(frame.truth["T_forklift_camera_true"]), "true")


def test_a_loaded_face_states_the_build_tolerance_as_a_common_yaw():
    """No deck in view: the face's yaw shares the tilt its parts' build tolerance gives (part / lever of the
    block columns, 0.17 deg for a EUR face), which no number of frames removes."""
    spec = FrameSpec("floor_b2", loaded=True, dx=0.0, dy=0.05, dyaw_deg=3.0, ahead=2.5, seed=2)
    frames = standpoint(spec)(3)
    cal = _calibration(frames[0])
    ests = [estimate_pallet(f, cal) for f in frames]
    lever = math.sqrt(2) * 0.35  # EUR block columns at y = -0.35, 0, +0.35 m
    assert _face_lever(_Model.of(PalletType.eur()).columns) == pytest.approx(lever)
    assert ests[0].extras["deck_pixels"] == 0
    assert ests[0].spread.yaw_common_rad == pytest.approx(PART / lever, rel=0.02)
    assert math.degrees(ests[0].spread.yaw_common_rad) == pytest.approx(0.17, abs=0.01)
    fused = fuse_estimates(ests)
    own = 1 / math.sqrt(sum(1 / e.spread.yaw_own_rad**2 for e in ests))
    assert fused.spread.yaw_common_rad == pytest.approx(ests[0].spread.yaw_common_rad)
    assert fused.spread.yaw_rad == pytest.approx(math.hypot(own, fused.spread.yaw_common_rad))
    assert fused.spread.yaw_rad > ests[0].spread.yaw_common_rad
    # The lateral common part: half a part (four block-side edges) and the pixel grid's quantisation.
    footprint = ests[0].extras["face_distance_m"] / frames[0].K[0, 0]
    along_face = math.hypot(0.5 * PART, footprint / math.sqrt(12)) * math.cos(ests[0].yaw)
    assert along_face < ests[0].spread.y_common_m < ests[0].spread.y_m


def test_an_exact_pallet_states_no_build_tolerance():
    spec = FrameSpec("floor_b2", loaded=True, dx=0.0, dy=0.05, dyaw_deg=3.0, ahead=2.5, seed=2)
    frame, _ = render(spec)
    exact = dataclasses.replace(DEFAULT_CONFIG, build_tolerance_m=0.0)
    est = estimate_pallet(frame, _calibration(frame), config=exact)
    assert est.spread.yaw_common_rad == 0.0
    assert est.spread.yaw_rad == pytest.approx(est.spread.yaw_own_rad)
    assert estimate_pallet(frame, _calibration(frame)).spread.yaw_rad > est.spread.yaw_rad


def test_no_more_frames_once_the_common_part_dominates():
    spec = FrameSpec("floor_b2", loaded=True, dx=0.0, dy=0.05, dyaw_deg=3.0, ahead=2.5, seed=2)
    frame, _ = render(spec)
    est = estimate_pallet(frame, _calibration(frame))
    policy = FramePolicy(per_round=3, max_frames=9, yaw_sigma_rad=math.radians(0.25))

    def stating(own_deg: float, common_deg: float):
        total = math.radians(math.hypot(own_deg, common_deg))
        sp = dataclasses.replace(est.spread, yaw_rad=total, yaw_common_rad=math.radians(common_deg))
        return dataclasses.replace(est, spread=sp)

    assert policy.more_frames(stating(0.3, 0.2), 3) == 3  # frames still cut it
    assert policy.more_frames(stating(0.2, 0.3), 3) == 0  # more frames cannot bring it under 0.25 deg
    assert policy.more_frames(stating(0.1, 0.2), 3) == 0  # known well enough


def test_the_crop_of_a_frame_gives_the_same_pixels_and_rays():
    spec = FrameSpec("floor_b2", loaded=False, dx=0.0, dy=0.0, dyaw_deg=0.0, ahead=1.4, seed=1)
    frame, _ = render(spec)
    rows, cols = slice(40, 440), slice(50, 583)
    crop = crop_frame(frame, rows, cols)
    assert crop.depth.shape == (400, 533) and crop.labels is not None and crop.labels.shape == (400, 533)
    assert crop.K[0, 2] == pytest.approx(frame.K[0, 2] - 50) and crop.K[1, 2] == pytest.approx(frame.K[1, 2] - 40)
    # Every pixel the estimator uses is kept: the same estimate.
    cal = _calibration(frame)
    a, b = estimate_pallet(frame, cal), estimate_pallet(crop, cal)
    assert np.allclose(forklift_errors(a.T_forklift_pallet, b.T_forklift_pallet), 0.0, atol=1e-9)


def test_a_frame_and_its_cut_crop_agree_within_the_stated_sigmas():
    """The crop check: a 4:3 crop that cuts a tenth of the pallet off one side changes the pixels the
    estimate rests on; the two estimates must agree within two stated sigmas (they share the frame's noise)."""
    spec = FrameSpec("rack_b1", loaded=False, dx=0.0, dy=0.1, dyaw_deg=5.0, ahead=3.0, seed=4)
    frame, _ = render(spec)
    rows, cols = crop_box(frame)
    assert cols.stop - cols.start < frame.width and rows.stop - rows.start == round(0.75 * (cols.stop - cols.start))
    cal = _calibration(frame)
    est = estimate_pallet(frame, cal)
    got = crop_check(frame, cal, PalletType.eur(), est)
    assert got is not None
    diff, sigmas = got
    assert any(abs(d) > 0 for d in diff)  # the crop did change what the estimate saw
    assert all(abs(d) <= 2 * s for d, s in zip(diff, sigmas, strict=True)), (diff, sigmas)


def test_coverage_counts_errors_within_two_sigma():
    errs = [(0.001, 0.0, 0.0), (0.003, 0.0, 0.0), (-0.005, 0.0, 0.02)]
    sig = [(0.001, 0.001, 0.01)] * 3
    cov = coverage(errs, sig)
    assert cov["lateral"]["coverage_2sigma"] == pytest.approx(1 / 3, abs=1e-4)
    assert cov["lateral"]["median_error_over_sigma"] == pytest.approx(3.0)
    assert cov["longitudinal"]["coverage_2sigma"] == 1.0
    assert cov["yaw"]["coverage_2sigma"] == 1.0  # 2 sigma exactly is within
    assert cov["lateral"]["mean_sigma"] == pytest.approx(1.0)  # mm
    assert cov["yaw"]["mean_sigma"] == pytest.approx(math.degrees(0.01), abs=1e-4)  # deg
    assert coverage([], [])["yaw"]["coverage_2sigma"] is None
    honesty = Honesty()
    assert honesty.result()["worst"] is None and honesty.result()["crop"]["checks"] == 0


# -- alignment with the estimate's uncertainty -------------------------------------------------------


@dataclasses.dataclass
class Node:
    pose: SE2
    height: float = 0.0


@pytest.fixture
def tolerances() -> AlignmentTolerances:
    return AlignmentTolerances.from_geometry(load_forks(MISSIONS / "forks.yaml"), PalletType.eur())


def test_an_uncertain_estimate_is_not_aligned(tolerances):
    """15 mm off with 23.75 mm allowed: aligned when the estimate is sure, not when 2 sigma of it reach
    past the tolerance (the yaw's sigma counts at the fork tips, 1.1 m into the pallet)."""
    node = Node(SE2(24.0, 10.5, 0.0))
    T_world_pallet = pallet_pose_at_node(node.pose, node.height) @ SE2(0.0, 0.015, 0.0).to_se3()
    sure = PalletSpread(0.003, 0.002, math.radians(0.05))
    unsure = PalletSpread(0.003, 0.002, math.radians(0.25))
    assert check_alignment(T_world_pallet, node, tolerances).aligned
    ok = check_alignment(T_world_pallet, node, tolerances, sure)
    assert ok.aligned
    assert ok.uncertainty[0] == pytest.approx(2 * math.hypot(0.002, 1.10 * math.radians(0.05)))
    bad = check_alignment(T_world_pallet, node, tolerances, unsure)
    assert not bad.aligned and bad.corrected_node_pose is not None
    assert any("2 sigma of the estimate's" in p for p in bad.problems)
    assert bad.to_json()["uncertainty"]["lateral_mm"] == pytest.approx(2e3 * math.hypot(0.002, 1.1 * 0.004363), 0.01)


def test_the_uncertainty_counts_on_the_longitudinal_and_the_yaw(tolerances):
    node = Node(SE2(0.0, 0.0, 0.0))
    near = pallet_pose_at_node(node.pose, 0.0) @ SE2(-0.035, 0.0, 0.0).to_se3()  # 40 mm allowed
    assert check_alignment(near, node, tolerances).aligned
    result = check_alignment(near, node, tolerances, PalletSpread(0.004, 0.001, 0.001))
    assert not result.aligned and any("nearer" in p for p in result.problems)
    turned = pallet_pose_at_node(node.pose, 0.0) @ SE2(0.0, 0.0, math.radians(1.0)).to_se3()  # 1.24 deg allowed
    assert check_alignment(turned, node, tolerances).aligned
    result = check_alignment(turned, node, tolerances, PalletSpread(0.0005, 0.0005, math.radians(0.2)))
    assert not result.aligned and any(p.startswith("yaw") for p in result.problems)
