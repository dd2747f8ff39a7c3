"""Pallet pose estimation (perception.pallet) and the alignment check (perception.alignment)."""

import dataclasses
import math

import numpy as np
import pytest

from palletpilot.bench.pallet import FrameSpec, render
from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception import pallet as pallet_module
from palletpilot.perception.alignment import AlignmentTolerances, check_alignment
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.frames import FrameBundle, SemanticClass
from palletpilot.perception.pallet import PalletNotFound, estimate_pallet, fuse_estimates
from palletpilot.perception.specs import PalletType, load_forks, node_pose_for_pallet, pallet_pose_at_node
from palletpilot.sim.camera import CameraModel, RaycastRenderer, camera_mount_pose
from palletpilot.sim.world import LabeledMesh, floor_mesh, object_box_mesh

MISSIONS = bundled_path("missions")


def true_calibration(frame: FrameBundle) -> Calibration:
    return Calibration(SE3.from_matrix(frame.truth["T_forklift_camera_true"]), "true")


def errors(frame: FrameBundle, T_forklift_pallet: SE3) -> tuple[float, float, float, float]:
    """(lateral, longitudinal, height) in m and yaw in rad of the estimate in the true pallet frame."""
    err = SE3.from_matrix(frame.truth["T_forklift_pallet_true"]).inv() @ T_forklift_pallet
    e2 = err.to_se2()
    return e2.y, e2.x, float(err.t[2]), e2.yaw


@pytest.mark.parametrize(
    "spec",
    [
        FrameSpec("floor_b2", loaded=False, dx=0.0, dy=0.0, dyaw_deg=0.0, ahead=1.4, seed=1),
        FrameSpec("floor_a1", loaded=True, dx=-0.02, dy=0.3, dyaw_deg=12.0, ahead=1.8, seed=3),
        FrameSpec("rack_a2", loaded=True, dx=0.03, dy=-0.2, dyaw_deg=-10.0, ahead=2.5, seed=2),
        FrameSpec("rack_b1", loaded=False, dx=0.0, dy=0.1, dyaw_deg=5.0, ahead=3.0, seed=4),
        FrameSpec("floor_b3", loaded=False, dx=0.0, dy=-0.35, dyaw_deg=-15.0, ahead=1.2, seed=5),
    ],
    ids=["floor-straight", "floor-loaded-turned", "rack-loaded-turned", "rack-far", "floor-extreme"],
)
def test_noise_free_frames_are_sub_millimetre(spec):
    frame, _ = render(spec, noise=False)
    # No depth scale error, and a pallet built exactly to its drawing (no build tolerance in the spread).
    exact_depth = dataclasses.replace(pallet_module.DEFAULT_CONFIG, depth_scale_sigma=0.0, build_tolerance_m=0.0)
    est = estimate_pallet(frame, true_calibration(frame), config=exact_depth)
    lateral, longitudinal, height, yaw = errors(frame, est.T_forklift_pallet)
    assert abs(lateral) < 1e-3 and abs(longitudinal) < 1e-3
    assert abs(math.degrees(yaw)) < 0.05
    assert abs(height) < 2e-3  # the underside comes from pixel-quantised pocket edges: ~1/4 pixel
    pallet = PalletType.eur()
    assert est.pocket_widths_m == pytest.approx((pallet.pocket_width,) * 2, abs=4e-3)
    # The lateral spread is floored at half a pixel footprint (3.5 mm at 4.2 m) with the pixel grid's common
    # part, the rest comes from the fit.
    assert est.spread.x_m < 1e-3 and est.spread.y_m < 4e-3 and est.spread.yaw_rad < math.radians(0.05)


def test_noisy_frame_is_within_the_goals_and_gives_the_world_pose():
    spec = FrameSpec("rack_b2", loaded=True, dx=0.02, dy=0.15, dyaw_deg=7.0, ahead=2.0, seed=11)
    frame, _ = render(spec)  # D435 depth noise, flying pixels, 2 px label noise, perturbed mount
    T_world_forklift = SE2(16.0 + 3.0, 10.5, math.pi)
    est = estimate_pallet(frame, true_calibration(frame), T_world_forklift=T_world_forklift)
    lateral, longitudinal, height, yaw = errors(frame, est.T_forklift_pallet)
    assert abs(lateral) < 0.010 and abs(longitudinal) < 0.015 and abs(math.degrees(yaw)) < 0.5
    assert abs(height) < 0.010
    assert est.T_world_pallet is not None
    assert est.T_world_pallet.isclose(T_world_forklift.to_se3() @ est.T_forklift_pallet, atol=1e-12, atol_rot=1e-12)
    doc = est.to_json()
    assert set(doc) >= {"T_forklift_pallet", "x_m", "y_m", "z_m", "yaw_deg", "spread", "T_world_pallet"}


def test_a_far_turned_rack_pallet_keeps_its_lateral_centre():
    """A pallet turned 14 deg at 4 m: the first plane's yaw is 1.6 deg off, and the refined plane must carry
    the lateral centre over (it once slid 11 cm sideways, giving 29 mm lateral and 1.8 deg yaw errors)."""
    spec = FrameSpec("rack_b3", loaded=False, dx=-0.0485, dy=0.2545, dyaw_deg=14.436, ahead=2.923, seed=1991627721)
    frame, _ = render(spec)
    est = estimate_pallet(frame, true_calibration(frame))
    lateral, longitudinal, _, yaw = errors(frame, est.T_forklift_pallet)
    assert abs(lateral) < 0.010 and abs(longitudinal) < 0.015 and abs(math.degrees(yaw)) < 0.7


@pytest.mark.parametrize("ahead", [1.5, 2.9])
def test_the_deck_edges_turn_a_wrong_face_yaw_back(ahead):
    """Noise-free empty pallet: a face plane 0.5 deg off with a loose (1 deg) yaw sigma is turned back to
    the true yaw by the deck's board edges alone, and the deck height comes from the deck pixels."""
    spec = FrameSpec("floor_b1", loaded=False, dx=0.0, dy=-0.03, dyaw_deg=-13.6, ahead=ahead, seed=1)
    frame, _ = render(spec, noise=False)
    T_fc = true_calibration(frame).T_forklift_camera_at(frame.fork_height)
    T_true = SE3.from_matrix(frame.truth["T_forklift_pallet_true"])
    psi_true = T_true.to_se2().yaw
    psi = psi_true + math.radians(0.5)
    n = np.array([math.cos(psi), math.sin(psi), 0.0])
    e = np.array([-n[1], n[0], 0.0])
    D = float(n @ (T_true.t - T_fc.t))
    r2 = 1.0 / D**2
    # cov of (A, B) such that the yaw sigma is 1 deg: var(psi) = grad . cov . grad with |grad| = D.
    cov = np.outer(e[:2], e[:2]) * math.radians(1.0) ** 2 * r2
    plane = pallet_module._Plane(n[0] / D, n[1] / D, cov)
    model = pallet_module._Model.of(PalletType.eur())
    deck = pallet_module._deck_yaw(
        frame,
        T_fc,
        frame.depth > 0,
        model,
        plane,
        float(e @ T_true.t),
        float(T_true.t[2]) + 0.002,
        1e-4,
        pallet_module.DEFAULT_CONFIG,
    )
    assert deck is not None and deck.n_pixels > 300
    assert abs(math.degrees(deck.psi - psi_true)) < 0.03
    assert deck.deck_height == pytest.approx(T_true.t[2] + PalletType.eur().height, abs=3e-4)


def test_a_load_hides_the_deck():
    spec = FrameSpec("floor_b2", loaded=True, dx=0.0, dy=0.1, dyaw_deg=5.0, ahead=2.0, seed=7)
    frame, _ = render(spec, noise=False)
    est = estimate_pallet(frame, true_calibration(frame))
    assert est.extras["deck_pixels"] == 0
    _, _, _, yaw = errors(frame, est.T_forklift_pallet)
    assert abs(math.degrees(yaw)) < 0.05


def test_fused_estimates_weigh_each_frame_by_its_spread():
    spec = FrameSpec("floor_a2", loaded=True, dx=0.0, dy=0.1, dyaw_deg=4.0, ahead=2.6, seed=21)
    T_world_forklift = SE2(3.0, 1.0, 0.3)
    frame, _ = render(spec)
    est = estimate_pallet(frame, true_calibration(frame), T_world_forklift=T_world_forklift)
    # A second "frame" of the same pallet 0.2 deg further turned but four times less sure of its yaw (its own
    # part: the part every frame shares, `yaw_common_rad`, is the same pallet's).
    turned = est.T_forklift_pallet @ SE3.from_xyz_rpy((0.0, 0.0, 0.0), (0.0, 0.0, math.radians(0.2)))
    own, common = est.spread.yaw_own_rad, est.spread.yaw_common_rad
    assert common > 0.0
    other = dataclasses.replace(
        est,
        T_forklift_pallet=turned,
        T_world_pallet=T_world_forklift.to_se3() @ turned,
        spread=dataclasses.replace(est.spread, yaw_rad=math.hypot(4 * own, common)),
    )
    fused = fuse_estimates([est, other])
    turn = math.degrees(fused.T_forklift_pallet.to_se2().yaw - est.T_forklift_pallet.to_se2().yaw)
    assert turn == pytest.approx(0.2 / 17, abs=1e-6)  # weights 16 : 1
    assert fused.spread.yaw_rad == pytest.approx(math.hypot(own / math.sqrt(1 + 1 / 16), common))
    assert fused.T_world_pallet is not None
    assert fused.T_world_pallet.isclose(T_world_forklift.to_se3() @ fused.T_forklift_pallet, atol=1e-9, atol_rot=1e-9)
    assert fuse_estimates([est]) is est
    with pytest.raises(ValueError):
        fuse_estimates([])


def test_too_few_points():
    frame, _ = render(FrameSpec("floor_b2", False, 0.0, 0.0, 0.0, 1.4, 1), noise=False)
    labels = frame.labels.copy()
    pallet = np.isin(labels, (7, 8))
    keep = np.flatnonzero(pallet.ravel())[:50]
    labels[pallet] = SemanticClass.DRIVABLE
    labels.ravel()[keep] = SemanticClass.PALLET_EMPTY
    with pytest.raises(PalletNotFound) as info:
        estimate_pallet(dataclasses.replace(frame, labels=labels), true_calibration(frame))
    assert info.value.reason == "too_few_points" and "50 pallet pixels" in str(info.value)


def test_no_entry_face_when_only_the_floor_is_labelled_pallet():
    frame, _ = render(FrameSpec("floor_b2", False, 0.0, 0.0, 0.0, 1.4, 1), noise=False)
    labels = np.where(frame.labels == SemanticClass.DRIVABLE, SemanticClass.PALLET_EMPTY, SemanticClass.VERTICAL)
    labels = labels.astype(np.uint8)
    labels[: frame.height // 2] = SemanticClass.VERTICAL  # floor far ahead only, no pallet
    with pytest.raises(PalletNotFound) as info:
        estimate_pallet(dataclasses.replace(frame, labels=labels), true_calibration(frame))
    assert info.value.reason == "no_entry_face"


def test_no_entry_face_when_only_a_sliver_is_seen():
    frame, _ = render(FrameSpec("floor_b2", False, 0.0, 0.0, 0.0, 1.4, 1), noise=False)
    labels = frame.labels.copy()
    cols = np.flatnonzero(np.isin(labels, (7, 8)).any(axis=0))
    labels[:, cols[0] + (cols[-1] - cols[0]) // 4 :] = SemanticClass.VERTICAL  # a quarter of the face
    with pytest.raises(PalletNotFound) as info:
        estimate_pallet(dataclasses.replace(frame, labels=labels), true_calibration(frame))
    assert info.value.reason == "no_entry_face"


def test_a_box_labelled_as_pallet_has_inconsistent_pockets():
    # A solid 1.2 x 0.8 x 0.144 m box where a pallet would be, every box pixel labelled pallet-empty.
    T_world_forklift = SE2(0.0, 0.0, 0.0)
    T_forklift_camera = camera_mount_pose((-0.10, 0.0, 0.475), math.radians(22.0))
    box = object_box_mesh(SE2(2.55 + 0.6, 0.0, 0.0), (1.2, 0.8, 0.144))
    world = LabeledMesh.merge([floor_mesh(-2.0, -4.0, 8.0, 4.0), box])
    camera = CameraModel.d435()
    frame = RaycastRenderer(world).render(T_world_forklift.to_se3() @ T_forklift_camera, camera, fork_height=0.025)
    labels = np.where(frame.labels == SemanticClass.OTHER_OBJECT, SemanticClass.PALLET_EMPTY, frame.labels)
    frame = dataclasses.replace(frame, labels=labels.astype(np.uint8))
    calibration = Calibration(SE3.from_translation(0.0, 0.0, -0.025) @ T_forklift_camera, "true")
    with pytest.raises(PalletNotFound) as info:
        estimate_pallet(frame, calibration)
    assert info.value.reason == "pockets_inconsistent"


def test_labels_are_required():
    frame, _ = render(FrameSpec("floor_b2", False, 0.0, 0.0, 0.0, 1.4, 1), noise=False)
    with pytest.raises(Exception, match="no labels"):
        estimate_pallet(dataclasses.replace(frame, labels=None), true_calibration(frame))


# -- alignment ---------------------------------------------------------------------------------------


@dataclasses.dataclass
class Node:
    pose: SE2
    height: float = 0.0


@pytest.fixture
def tolerances() -> AlignmentTolerances:
    return AlignmentTolerances.from_geometry(load_forks(MISSIONS / "forks.yaml"), PalletType.eur())


def test_tolerances_follow_the_geometry(tolerances):
    assert tolerances.lateral_m == pytest.approx(0.03375 - 0.010)  # (227.5 - 160) / 2 mm minus the margin
    assert tolerances.longitudinal_near_m == pytest.approx(0.04)
    assert tolerances.longitudinal_far_m == pytest.approx(1.15 - 0.05 - 1.055 - 0.010)
    assert math.degrees(tolerances.yaw_rad) == pytest.approx(math.degrees(math.asin(0.02375 / 1.10)))


def test_aligned_pallet(tolerances):
    node = Node(SE2(24.0, 10.5, 0.0))
    T_world_pallet = pallet_pose_at_node(node.pose, node.height) @ SE2(0.01, -0.008, math.radians(0.4)).to_se3()
    result = check_alignment(T_world_pallet, node, tolerances)
    assert result.aligned and result.corrected_node_pose is None and result.problems == ()
    assert result.lateral_m == pytest.approx(-0.008) and result.longitudinal_m == pytest.approx(0.01)
    assert math.degrees(result.yaw_rad) == pytest.approx(0.4)


@pytest.mark.parametrize(
    ("offset", "problem"),
    [
        (SE2(0.0, 0.05, 0.0), "lateral"),
        (SE2(0.0, 0.015, math.radians(0.8)), "lateral"),  # the yaw sweeps the tips past the pocket
        (SE2(-0.06, 0.0, 0.0), "nearer"),
        (SE2(0.08, 0.0, 0.0), "farther"),
        (SE2(0.0, 0.0, math.radians(3.0)), "yaw"),
    ],
)
def test_misaligned_pallet_gets_a_corrected_node(tolerances, offset, problem):
    node = Node(SE2(10.0, 9.5, 0.0), height=1.0)
    T_world_pallet = pallet_pose_at_node(node.pose, node.height) @ offset.to_se3()
    result = check_alignment(T_world_pallet, node, tolerances)
    assert not result.aligned
    assert any(problem in p for p in result.problems)
    corrected = result.corrected_node_pose
    assert corrected is not None and corrected.isclose(node_pose_for_pallet(T_world_pallet))
    # A pallet node there expects exactly this pallet (on the floor plan; the height stays the node's).
    expected = pallet_pose_at_node(corrected, node.height)
    assert expected.to_se2().isclose(T_world_pallet.to_se2(), atol=1e-9, atol_yaw=1e-9)


def test_alignment_from_an_estimate(tolerances):
    # The simulator's pallet is misplaced by 10 cm: the estimate says so and the corrected node serves it.
    spec = FrameSpec("floor_b2", loaded=False, dx=0.0, dy=0.10, dyaw_deg=3.0, ahead=1.4, seed=1)
    frame, _ = render(spec, noise=False)
    node_pose = SE2(24.0, 10.5, 0.0)
    T_world_forklift = node_pose @ SE2(-(1.15 + 1.4 - 0.05), 0.0, 0.0)
    est = estimate_pallet(frame, true_calibration(frame), T_world_forklift=T_world_forklift)
    result = check_alignment(est.T_world_pallet, Node(node_pose), tolerances)
    assert not result.aligned
    assert result.lateral_m == pytest.approx(0.10, abs=1e-3)
    assert math.degrees(result.yaw_rad) == pytest.approx(3.0, abs=0.05)
    true_pallet = pallet_pose_at_node(node_pose, 0.0) @ SE2(0.0, 0.10, math.radians(3.0)).to_se3()
    true_node = node_pose_for_pallet(true_pallet)
    assert result.corrected_node_pose.isclose(true_node, atol=1e-3, atol_yaw=math.radians(0.05))
    aligned = check_alignment(pallet_pose_at_node(true_node, 0.0), Node(result.corrected_node_pose), tolerances)
    assert aligned.aligned
