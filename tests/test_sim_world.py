"""The simulated warehouse: scenarios, proximity beams, pickup physics, collisions, frames."""

import math

import numpy as np
import pytest

from palletpilot.cli import main
from palletpilot.geometry import SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.frames import load_bundle
from palletpilot.perception.specs import pallet_pose_at_node
from palletpilot.sim.scenario import Scenario, SimError, load_scenario
from palletpilot.sim.simulator import Simulator

MISSIONS = bundled_path("missions")


def scenario(dy: float = 0.0, dyaw_deg: float = 0.0, node: str = "floor_b2", loaded: bool = False) -> Scenario:
    sc = Scenario.model_validate(
        {
            "map": "warehouse.yaml",
            "start": f"{node}_pre",
            "camera": {
                "noise": {
                    "depth_noise": False,
                    "label_noise": False,
                    "rgb_sigma": 0.0,
                    "lighting_variation": False,
                    "invalid_rate": 0.0,
                }
            },
            "pallets": [{"node": node, "dy": dy, "dyaw_deg": dyaw_deg, "loaded": loaded}],
        }
    )
    sc.folder = MISSIONS
    return sc


def entering(sim: Simulator) -> Simulator:
    """The scanners' narrow field set, as the executor selects it to enter a pallet on the floor."""
    sim.set_safety_field_set("narrow")
    return sim


def without_scanners(sim: Simulator) -> Simulator:
    """A truck without safety scanners: nothing but the contacts stops it (the physics under test)."""
    sim.scanner.params = sim.vehicle.model_copy(update={"safety_scanner": None})
    return sim


def set_forks(sim: Simulator, height: float) -> None:
    sim.set_fork_height(height)
    for _ in range(400):
        sim.step()
        if abs(sim.fork_height - height) < 1e-9:
            return
    raise AssertionError("forks did not reach their height")


def drive_straight(sim: Simulator, distance: float, speed: float = 0.3) -> None:
    """Open loop: drive straight (negative distance: reverse) and brake to a stop."""
    start = sim.true_pose
    sign = 1.0 if distance > 0 else -1.0
    braking = speed * speed / (2 * sim.vehicle.max_decel)
    sim.drive(sign * speed, 0.0)
    for _ in range(2000):
        sim.step()
        if sim.true_pose.distance_to(start) >= abs(distance) - braking or sim.collisions:
            break
    sim.stop()
    while not sim.forklift.stopped:
        sim.step()


def pallet_height(sim: Simulator, node: str) -> float:
    return sim.roadmap.node(node).height


def test_aligned_pallet_beams_clear_then_lift_carry_and_set_down():
    sim = entering(Simulator(scenario()))
    set_forks(sim, 0.025)  # fork bottoms 25 mm up: the 50 mm blades sit mid-pocket (pocket 100 mm)
    face = 2.5 + 0.05 - sim.forks.tip_x  # pre-pallet to pallet node 2.5 m, entry gap 5 cm
    left, right = sim.proximity_ranges()
    assert left > face + sim.pallet_type.length and right > face + sim.pallet_type.length
    drive_straight(sim, 2.46)
    assert sim.collisions == []
    pallet = sim.pallets[0]
    before = pallet.T_world_pallet
    set_forks(sim, 0.15)
    assert pallet.carried
    assert pallet.T_world_pallet.t[2] == pytest.approx(0.15 + sim.forks.thickness - sim.pallet_type.pocket_height)
    drive_straight(sim, -2.0)  # reverse out with the load
    moved = before.inv() @ pallet.T_world_pallet
    assert moved.t[0] == pytest.approx(-2.0, abs=0.05) and abs(moved.t[1]) < 1e-6
    set_forks(sim, 0.0)  # set it down on the floor
    assert not pallet.carried and pallet.T_world_pallet.t[2] == 0.0
    assert sim.collisions == []


def test_beams_on_blocks_stop_at_the_entry_face():
    sim = Simulator(scenario(dy=0.13))  # both fork centre lines now point at block columns
    set_forks(sim, 0.025)
    face = 2.5 + 0.05 - sim.forks.tip_x
    assert sim.proximity_ranges() == pytest.approx((face, face), abs=1e-3)


def test_a_misaligned_entry_is_a_collision():
    # 8 cm off: the thin beams on the fork centre lines still pass the (shifted) pockets, which are
    # 113 mm wide on either side of them, but the forks have only 33.75 mm of clearance.
    sim = entering(Simulator(scenario(dy=0.08)))
    set_forks(sim, 0.025)
    face = 2.5 + 0.05 - sim.forks.tip_x
    assert min(sim.proximity_ranges()) > face + sim.pallet_type.length
    drive_straight(sim, 2.46)
    assert len(sim.collisions) == 1
    hit = sim.collisions[0]
    assert hit["kind"] == "pallet" and hit["id"] == "floor_b2" and hit["part"].endswith("fork")
    assert "fork hit block_" in hit["message"] and "'floor_b2'" in hit["message"]
    assert sim.forklift.stopped
    sim.drive(0.5, 0.0)  # a blocked forklift does not move on
    pose = sim.true_pose
    for _ in range(20):
        sim.step()
    assert sim.true_pose.isclose(pose, atol=1e-9)


def test_forks_too_low_hit_nothing_in_the_pocket_but_too_high_hit_the_deck():
    sim = entering(Simulator(scenario()))
    set_forks(sim, 0.08)  # blade top 0.13 m: above the 0.100 m pocket, into the cross boards
    drive_straight(sim, 2.46)
    assert sim.collisions and "cross_board" in sim.collisions[0]["message"]


def test_rack_pallet_lifts_off_the_beams():
    sim = Simulator(scenario(node="rack_a2", loaded=True))  # rack pallets stand above the scan plane
    h = pallet_height(sim, "rack_a2")
    pallet = sim.pallets[0]
    assert pallet.T_world_pallet.t[2] == pytest.approx(h)
    set_forks(sim, h + 0.025)
    drive_straight(sim, 2.46)
    assert sim.collisions == []
    set_forks(sim, h + 0.15)
    assert pallet.carried
    set_forks(sim, h + 0.02)  # lowering again puts it back on the beams, not on the floor
    assert not pallet.carried and pallet.T_world_pallet.t[2] == pytest.approx(h)


def test_frame_truth_matches_the_scenario():
    sim = Simulator(scenario(dy=-0.1, dyaw_deg=5.0))
    frame = sim.grab()
    T_fp = SE3.from_matrix(frame.truth["T_forklift_pallet_true"])
    node = sim.roadmap.node("floor_b2")
    expected = (
        sim.T_world_forklift3.inv()
        @ pallet_pose_at_node(node.pose, 0.0)
        @ SE3.from_xyz_rpy((0.0, -0.1, 0.0), (0.0, 0.0, math.radians(5.0)))
    )
    assert T_fp.isclose(expected, atol=1e-9, atol_rot=1e-9)
    assert np.allclose(frame.truth["T_forklift_camera_true"], sim.scenario.camera.mount.T_forklift_camera().matrix)
    # The pallet's pixels: pallet-empty label where its entry face projects.
    K = frame.K
    face_centre_top = (sim.T_world_camera_true().inv() @ sim.pallets[0].T_world_pallet).apply([0.0, 0.0, 0.13])
    u, v = (K @ face_centre_top / face_centre_top[2])[:2]
    assert frame.labels[round(v), round(u)] == 7


def test_same_seed_same_run_and_mount_perturbation():
    sc = load_scenario(MISSIONS / "scenario_floor.yaml")
    a, b = Simulator(sc), Simulator(sc)
    assert a.T_forklift_camera_true.isclose(b.T_forklift_camera_true)
    assert not a.T_forklift_camera_true.isclose(sc.camera.mount.T_forklift_camera(), atol=1e-5)
    assert np.array_equal(a.grab().depth, b.grab().depth, equal_nan=True)
    assert not Simulator(sc, seed=8).T_forklift_camera_true.isclose(a.T_forklift_camera_true, atol=1e-6)


def test_bad_scenarios_are_clear(tmp_path):
    bad = tmp_path / "s.yaml"
    bad.write_text("map: warehouse.yaml\nstart: charger\ncamera: {width: 1000}\n")
    with pytest.raises(SimError, match=r"camera\.width"):
        load_scenario(bad)
    sc = scenario()
    sc.pallets[0].node = "charger"
    with pytest.raises(SimError, match=r"pallets\[0\].node: 'charger' is a charging node, not a pallet node"):
        Simulator(sc)


def test_cli_sim_render_writes_a_bundle(tmp_path, capsys):
    out = tmp_path / "f.npz"
    assert (
        main(["sim", "render", str(MISSIONS / "scenario_rack.yaml"), "--out", str(out), "--fork-height", "1.03"]) == 0
    )
    frame = load_bundle(out)
    assert frame.fork_height == pytest.approx(1.03) and frame.depth.shape == (480, 640)
    assert {"T_forklift_camera_true", "T_forklift_pallet_true"} <= set(frame.truth)
    assert (frame.labels == 8).sum() > 1000  # the loaded pallet is in view (pallet-full)
    assert main(["sim", "render", str(tmp_path / "none.yaml"), "--out", str(out)]) == 2
    assert "cannot read" in capsys.readouterr().err


def clutter_scenario(clutter: list[dict]) -> Scenario:
    sc = Scenario.model_validate({"map": "warehouse.yaml", "start": "floor_b2_pre", "clutter": clutter})
    sc.folder = MISSIONS
    return sc


def test_forks_driving_into_a_person_are_a_contact_that_stops_the_truck():
    # floor_b2_pre stands at (22.5, 11.5) facing +x; the fork tips end 1.15 m ahead.
    sim = without_scanners(Simulator(clutter_scenario([{"kind": "person", "x": 24.5, "y": 11.5, "yaw_deg": 180}])))
    set_forks(sim, 0.1)
    drive_straight(sim, 2.0)
    (hit,) = sim.collisions
    assert hit["kind"] == "person" and hit["id"] == "clutter[0]" and hit["part"] in ("left fork", "right fork")
    assert sim.speed == 0.0
    tips_x = sim.true_pose.x + sim.forks.tip_x
    assert 24.5 - 0.14 < tips_x < 24.5 - 0.12 + 0.03  # stopped at the person's legs, not through them
    sim.drive(0.5, 0.0)  # a truck that touched something stays stopped
    for _ in range(20):
        sim.step()
    assert sim.speed == 0.0 and sim.faults() == [f"collision: {hit['message']}"]


def test_the_body_reversing_into_a_box_is_a_contact():
    box = {"kind": "box", "x": 20.2, "y": 11.5, "yaw_deg": 30, "size": [0.6, 0.4, 0.5]}
    sim = without_scanners(Simulator(clutter_scenario([box])))
    drive_straight(sim, -1.5)
    (hit,) = sim.collisions
    assert (hit["kind"], hit["id"], hit["part"]) == ("box", "clutter[0]", "body")


def test_nothing_touches_when_the_truck_passes_beside_or_above():
    from palletpilot.geometry import SE2
    from palletpilot.sim.contacts import Solid, first_contact

    fork = Solid("left fork", "truck", SE2(0.0, 0.0, 0.3), (0.6, 0.05), (1.0, 1.05))
    beam_below = Solid("rack", "r beam 0", SE2(0.2, 0.0, 0.0), (0.03, 1.3), (0.88, 1.0))
    beside = Solid("person", "p", SE2(0.0, 0.6, 1.0), (0.13, 0.31), (0.0, 1.75))
    assert first_contact([fork], [beam_below, beside]) is None
    turned_into = Solid("person", "p", SE2(0.4, 0.25, 1.0), (0.13, 0.31), (0.0, 1.75))  # on the fork's line
    contact = first_contact([fork], [beam_below, turned_into])
    assert contact is not None and contact.solid.id == "p" and contact.part == "left fork"


def test_a_person_walking_across_the_standing_forks_waits_and_never_touches_them():
    # The truck stands at floor_b2_pre (22.5, 11.5) facing +x, fork tips at x = 23.65; a person's path
    # crosses 0.4 m inside the tips, from y = 14 to y = 9 at 1 m/s. People give way to a forklift: the
    # walker stops short of the truck and of its protective field, and walks on once the truck has gone.
    walker = {"kind": "person", "x": 23.25, "y": 14.0, "path": [[23.25, 9.0]], "speed": 1.0}
    sim = Simulator(clutter_scenario([{"kind": "box", "x": 30.0, "y": 30.0}, walker]))
    for _ in range(200):
        sim.step()
    assert sim.collisions == []
    ((_, waiting),) = sim._walker_poses()
    assert 11.5 + 0.55 + 0.31 < waiting.y < 13.0  # stopped beside the truck, outside the fields
    drive_straight(sim, -3.0)  # the truck backs away
    for _ in range(200):
        sim.step()
    ((_, gone),) = sim._walker_poses()
    assert sim.collisions == [] and gone.y == pytest.approx(9.0)


def test_a_walking_person_goes_back_and_forth_along_the_path():
    sc = clutter_scenario([{"kind": "person", "x": 0.0, "y": 0.0, "path": [[4.0, 0.0], [4.0, 2.0]], "repeat": True}])
    person = sc.clutter[0]
    assert person.pose_at(0.0) == pytest.approx((0.0, 0.0, 0.0))
    assert person.pose_at(5.0) == pytest.approx((4.0, 1.0, math.pi / 2))
    assert person.pose_at(7.0)[:2] == pytest.approx((4.0, 1.0))  # on the way back (6 m out, 1 back)
    assert person.pose_at(7.0)[2] == pytest.approx(-math.pi / 2)
    assert person.pose_at(12.0)[:2] == pytest.approx((0.0, 0.0))
    once = sc.clutter[0].model_copy(update={"repeat": False})
    assert once.pose_at(100.0)[:2] == pytest.approx((4.0, 2.0))  # then stands at the end


def test_a_free_standing_pallet_is_solid_and_reported_by_its_index():
    sc = Scenario.model_validate(
        {"map": "warehouse.yaml", "start": "floor_b2_pre", "pallets": [{"x": 20.0, "y": 11.5, "yaw_deg": 90}]}
    )
    sc.folder = MISSIONS
    sim = without_scanners(Simulator(sc))
    drive_straight(sim, -1.5)
    (hit,) = sim.collisions
    assert (hit["kind"], hit["id"], hit["part"]) == ("pallet", "pallets[0]", "body")
    (record,) = sim.pallet_records()
    assert record["id"] == "pallets[0]" and record["node"] is None and record["initial"]["x_m"] == 20.0


@pytest.mark.parametrize(
    ("entry", "problem"),
    [
        ("{node: floor_b2, x: 1.0, y: 2.0}", "either node"),
        ("{x: 1.0}", "needs both x and y"),
        ("{x: 1.0, y: 2.0, dx: 0.1}", "only with node"),
    ],
)
def test_bad_pallet_placements_are_one_line(tmp_path, entry, problem):
    path = tmp_path / "s.yaml"
    path.write_text(f"map: {MISSIONS / 'warehouse.yaml'}\nstart: charger\npallets:\n  - {entry}\n")
    with pytest.raises(SimError) as info:
        load_scenario(path)
    (line,) = info.value.problems
    assert line.startswith(f"{path}: pallets[0]") and problem in line
