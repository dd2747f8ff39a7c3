"""Before the forks go in: the camera (and beams) must see the pallet's entry volume and the drop slot free."""

import json
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from palletpilot.executor.apps.app import run_simulated
from palletpilot.executor.core.behaviour import Settings
from palletpilot.geometry import SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.clearance import Volume, check_volume
from palletpilot.sim.scenario import Scenario
from palletpilot.sim.simulator import Simulator

MISSIONS = bundled_path("missions")
DROP_SPOT = {"x": 15.5, "y": -4.05, "yaw_deg": -90.0}  # where a pallet delivered to `drop` stands


def _scenario(start: str, pallets: list[dict], clutter: list[dict] | None = None) -> Scenario:
    sc = Scenario.model_validate(
        {
            "map": "warehouse.yaml",
            "start": start,
            "seed": 5,
            "camera": {"mount": {"tilt_deg": 22.0}},
            "pallets": pallets,
            "clutter": clutter or [],
        }
    )
    sc.folder = MISSIONS
    return sc


def _run(tmp_path: Path, tasks: list[dict], sc: Scenario):
    path = tmp_path / "mission.yaml"
    path.write_text(yaml.safe_dump({"name": "t", "map": str(MISSIONS / "warehouse.yaml"), "tasks": tasks}))
    settings = Settings(blocked_wait_s=5.0)
    return run_simulated(path, scenario=sc, report_dir=tmp_path / "report", settings=settings)


def _events(tmp_path: Path) -> list[dict]:
    return [json.loads(x) for x in (tmp_path / "report" / "events.jsonl").read_text().splitlines()]


def _truth_calibration(sim: Simulator) -> Calibration:
    return Calibration(T_forklift_camera=sim.T_forklift_camera_true, method="truth")


def test_check_volume_counts_a_box_in_the_volume_and_nothing_on_an_empty_floor():
    box = {"kind": "box", "x": 22.5 + 2.0, "y": 11.5, "yaw_deg": 10, "size": [0.6, 0.4, 0.5]}
    volume = Volume(1.25, 2.6, -0.45, 0.45, 0.05, 1.2)  # ahead of the tips at floor_b2_pre
    for clutter, occupied in (([], False), ([box], True)):
        sim = Simulator(_scenario("floor_b2_pre", [], clutter))
        frame = sim.grab()
        look = check_volume(frame, _truth_calibration(sim), volume)
        assert look.occupied is occupied, look
        assert look.seen > 0.9
        if occupied:
            assert look.nearest_x_m == pytest.approx(2.0 - 0.3, abs=0.1)


def test_a_load_on_the_forks_hides_the_slot_from_the_carriage_camera():
    sim = Simulator(_scenario("floor_b2_pre", [{"node": "floor_b2", "loaded": True}]))
    pallet = sim.pallets[0]
    pallet.carried, pallet.T_forks_pallet = True, SE3.from_translation(0.05, 0.0, 0.05 - 0.1)
    sim._update_pallets()
    sim._static_changed()
    look = check_volume(sim.grab(), _truth_calibration(sim), Volume(1.3, 3.8, -0.45, 0.45, 0.03, 1.2))
    assert look.seen < 0.2  # the executor then relies on the fork-tip beams


def test_a_box_in_front_of_the_pallet_holds_the_pickup_then_fails_path_blocked_untouched(tmp_path):
    box = {"kind": "box", "x": 24.4, "y": 11.55, "yaw_deg": 0, "size": [0.4, 0.4, 0.4]}  # 0.6 m before the face
    r = _run(
        tmp_path, [{"type": "pickup", "node": "floor_b2"}], _scenario("floor_b2_pre", [{"node": "floor_b2"}], [box])
    )
    result = r.runner.results[0]
    assert not r.success and result.reason == "path_blocked", result.message
    assert "entry volume" in (result.message or "")
    assert not r.sim.collisions and abs(r.sim.speed) < 1e-3
    assert not r.sim.pallets[0].lifted
    assert any(e["event"] == "entry_blocked" for e in _events(tmp_path))


def test_an_occupied_drop_slot_fails_slot_occupied_and_nothing_is_touched(tmp_path):
    occupant = {**DROP_SPOT, "loaded": True}
    sc = _scenario("floor_b2_pre", [{"node": "floor_b2", "loaded": True}, occupant])
    r = _run(tmp_path, [{"type": "pickup", "node": "floor_b2"}, {"type": "delivery", "node": "drop"}], sc)
    pickup, delivery = r.runner.results
    assert pickup.result == "succeeded"
    assert delivery.reason == "slot_occupied", delivery.message
    assert not r.sim.collisions
    other = r.sim.pallets[1]
    assert not other.lifted
    moved = other.initial.inv() @ other.T_world_pallet
    assert np.linalg.norm(moved.t) < 1e-9
    assert r.sim.load_detected()  # the load is still on the forks, the truck stands before the slot
    doc = json.loads((tmp_path / "report" / "report.json").read_text())
    assert doc["tasks"][1]["reason"] == "slot_occupied"


def test_a_free_drop_slot_is_checked_and_the_load_delivered(tmp_path):
    sc = _scenario("floor_b2_pre", [{"node": "floor_b2", "loaded": True}])
    r = _run(tmp_path, [{"type": "pickup", "node": "floor_b2"}, {"type": "delivery", "node": "drop"}], sc)
    assert r.success, [x.message for x in r.runner.results]
    checks = [e for e in _events(tmp_path) if e["event"] == "entry_check" and e["what"] == "the drop slot"]
    assert checks and checks[-1]["free"] is True
    placed = r.sim.pallets[0].T_world_pallet.to_se2()
    assert math.hypot(placed.x - DROP_SPOT["x"], placed.y - DROP_SPOT["y"]) < 0.1
