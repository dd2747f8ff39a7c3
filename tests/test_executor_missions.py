"""Simulated missions end to end: the adaptive pickup, failures that end cleanly, invalid missions."""

import csv
import json
from pathlib import Path

import pytest
import yaml

from palletpilot.cli import main
from palletpilot.control.vehicle import load_vehicle
from palletpilot.executor.apps.app import run_simulated
from palletpilot.executor.core.mission import MissionError
from palletpilot.geometry.fileio import bundled_path
from palletpilot.sim.scenario import Scenario
from palletpilot.testing import assert_checks, assert_failed, assert_succeeded

MISSIONS = bundled_path("missions")


def mission_file(tmp_path: Path, tasks: list[dict], name: str = "test") -> Path:
    path = tmp_path / "mission.yaml"
    path.write_text(yaml.safe_dump({"name": name, "map": str(MISSIONS / "warehouse.yaml"), "tasks": tasks}))
    return path


def scenario(start: str, pallets: list[dict], seed: int = 3, noise: bool = True, tilt_deg: float = 22.0) -> Scenario:
    camera = {
        "mount": {"tilt_deg": tilt_deg, "pan_deg": 0.8, "roll_deg": -0.5},
        "perturbation": {"xyz_sigma": 0.002, "angle_sigma_deg": 0.2},
    }
    if not noise:
        camera["noise"] = {"depth_noise": False, "label_noise": False, "rgb_sigma": 0.0, "lighting_variation": False}
    sc = Scenario.model_validate(
        {
            "map": "warehouse.yaml",
            "start": start,
            "seed": seed,
            "camera": camera,
            "noise": {"localization_xy_sigma": 0.003, "localization_yaw_sigma_deg": 0.05},
            "pallets": pallets,
        }
    )
    sc.folder = MISSIONS
    return sc


def run(tmp_path, tasks, sc, **kw):
    return run_simulated(mission_file(tmp_path, tasks), scenario=sc, report_dir=tmp_path / "report", **kw)


def test_aligned_pallet_is_picked_without_replanning(tmp_path, monkeypatch):
    # Every controller solve seems to take 0.5 s of wall clock (a badly loaded machine): simulated time
    # waits for it, so the seeded run must not change (a real-time deadline would fail it).
    ticks = iter(range(10**9))
    monkeypatch.setattr("palletpilot.control.mpc.timed", lambda: 0.5 * next(ticks))
    r = run(tmp_path, [{"type": "pickup", "node": "floor_b2"}], scenario("b1", [{"node": "floor_b2"}]))
    task = r.summary["tasks"][0]
    assert r.success and task["result"] == "succeeded" and task["attempts"] == 1
    assert r.sim.pallets[0].carried and r.sim.collisions == []
    report = json.loads((tmp_path / "report" / "report.json").read_text())
    assert report["solve_ms"]["median"] == report["solve_ms"]["max"] == 500.0
    assert "temporary_nodes" not in report["tasks"][0]
    assert (tmp_path / "report" / "trajectory.png").stat().st_size > 10_000
    assert (tmp_path / "report" / "events.jsonl").read_text().count("state_start") >= 8


def test_misplaced_pallet_is_picked_after_replanning(tmp_path, run_mission):
    sc = scenario("b1", [{"node": "floor_b2", "dx": 0.12, "dy": -0.2, "dyaw_deg": 6.0}])
    r = run_mission(mission_file(tmp_path, [{"type": "pickup", "node": "floor_b2"}]), sc)
    assert_succeeded(r)
    assert_checks(r, max_replans=3)  # no contact, travel height, nothing else moved
    task = r.summary["tasks"][0]
    assert task["attempts"] >= 2  # estimated off, re-planned, estimated aligned
    assert r.sim.pallets[0].carried
    assert not any(n.temporary for n in r.runner.ctx.roadmap.nodes())  # temporary nodes removed
    report = json.loads(Path(r.report).read_text())["tasks"][0]
    assert report["estimates"][0]["aligned"] is False and report["estimates"][-1]["aligned"] is True
    assert report["temporary_nodes"][0]["pallet"] == "floor_b2~1"


def test_a_mount_too_steep_for_a_far_load_is_reported_and_the_pickup_still_works(tmp_path):
    sc = scenario("b1", [{"node": "floor_b2", "dy": 0.1, "dyaw_deg": 4.0}], tilt_deg=25.0)
    r = run(tmp_path, [{"type": "pickup", "node": "floor_b2"}], sc)
    assert r.success and r.sim.pallets[0].carried
    events = [json.loads(line) for line in (tmp_path / "report" / "events.jsonl").read_text().splitlines()]
    warnings = [e for e in events if e["event"] == "camera_mount_warning"]
    assert warnings and all(w["problems"][0].startswith("a load is in the image only") for w in warnings)
    assert not any("entry face" in p for w in warnings for p in w["problems"])  # the face stays in view


def test_missing_pallet_fails_cleanly(tmp_path, run_mission):
    r = run_mission(mission_file(tmp_path, [{"type": "pickup", "node": "floor_b2"}]), scenario("b1", []))
    assert_failed(r, "pallet_not_found")
    assert_checks(r)
    assert abs(r.sim.speed) < 1e-3


def test_pallet_too_far_off_fails_cleanly(tmp_path):
    # Seen and estimated, but 0.6 m to the side and turned 45 deg: outside the envelope of the node, so
    # not the mission's pallet; nothing is re-planned towards it.
    sc = scenario("b1", [{"node": "floor_b2", "dx": 0.3, "dy": -0.6, "dyaw_deg": -45.0}])
    r = run(tmp_path, [{"type": "pickup", "node": "floor_b2"}], sc)
    task = r.summary["tasks"][0]
    assert not r.success and task["reason"] == "pallet_not_found", task
    message = r.runner.results[0].message or ""
    # Perception fits only the pallet where it is expected (or the envelope check refuses the estimate).
    assert "from where it was expected" in message or "not the mission's pallet" in message
    assert abs(r.sim.speed) < 1e-3 and r.sim.collisions == [] and not r.sim.pallets[0].carried
    assert not any(n.temporary for n in r.runner.ctx.roadmap.nodes())
    assert "replan" not in [s["state"] for s in r.runner.results[0].states]


def test_rack_pickup_at_height(tmp_path, run_mission):
    sc = scenario("a1", [{"node": "rack_a2", "dx": -0.03, "dy": 0.1, "dyaw_deg": -3.0, "loaded": True}])
    r = run_mission(mission_file(tmp_path, [{"type": "pickup", "node": "rack_a2"}]), sc)
    assert_succeeded(r)
    assert_checks(r)  # among them: loaded and faster than creep speed, the forks at travel height
    pallet = r.sim.pallets[0]
    assert pallet.carried and pallet.T_world_pallet.t[2] < 0.5  # lifted off the 1.0 m beam, carried low
    # Above travel height the truck only creeps; it drives the roadmap with the load at travel height.
    mast, creep = r.sim.vehicle.mast, r.sim.vehicle.creep_speed
    rows = list(csv.DictReader((Path(r.report).parent / "trajectory.csv").open()))
    raised = [r for r in rows if float(r["fork_height_m"]) > mast.travel_height_loaded + 0.05]
    assert raised and max(abs(float(r["speed_mps"])) for r in raised) <= creep + 0.02
    assert abs(float(rows[-1]["fork_height_m"]) - mast.travel_height_loaded) < 0.005


@pytest.mark.parametrize(("deeper_m", "engagement", "picked"), [(0.12, None, True), (0.25, 0.9, False)])
def test_a_pallet_deep_in_a_rack_is_entered_only_as_far_as_the_mast_allows(tmp_path, deeper_m, engagement, picked):
    # The rack's front beam stands 0.22 m past the node's heels before the mast (0.12 m behind the heels)
    # meets it: the truck goes at most Settings.rack_overrun (0.10 m) past the node. 0.25 m deeper, the tips
    # reach about 950 mm into the pallet: enough for the default two thirds (tests/test_fork_engagement.py),
    # not for a pallet type that asks for 0.9 of its 1200 mm.
    sc = scenario("a1", [{"node": "rack_a2", "dx": deeper_m, "dy": 0.05, "loaded": True}])
    task = {"type": "pickup", "node": "rack_a2"}
    if engagement is not None:  # an EUR pallet whose warehouse asks for more of its depth on the forks
        (tmp_path / "strict.yaml").write_text(f"min_fork_engagement: {engagement}\n")
        task["pallet_type"] = str(tmp_path / "strict.yaml")
    poses = []

    def record_true_poses(runner):
        tick = runner.clock.tick

        def traced():
            tick()
            poses.append(runner.ctx.vehicle.true_pose)

        runner.clock.tick = traced

    r = run(tmp_path, [task], sc, on_start=record_true_poses)
    assert r.sim.collisions == []
    assert r.success is picked and r.sim.pallets[0].carried is picked, r.runner.results[0].message
    node = r.runner.ctx.roadmap.node("rack_a2").pose
    deepest = max((node.inv() @ pose).x for pose in poses)
    assert deepest < 0.10 + 0.03  # the heels' true position, never more than the overrun (+ tracking)
    if not picked:
        result = r.runner.results[0]
        assert result.reason == "no_feasible_approach" and "deeper in the rack" in (result.message or "")
        # what it could reach, and what the pallet needs (0.9 of 1200 mm)
        assert "could then reach 9" in result.message and "it needs 1080 mm" in result.message, result.message


def test_pickup_then_delivery(tmp_path):
    sc = scenario("b1", [{"node": "floor_b2", "dy": 0.1, "dyaw_deg": -4.0}])
    tasks = [{"type": "pickup", "node": "floor_b2"}, {"type": "delivery", "node": "drop"}]
    r = run(tmp_path, tasks, sc)
    assert r.success, [t.message for t in r.runner.results]
    pallet = r.sim.pallets[0]
    drop = r.runner.ctx.roadmap.node("drop").pose
    assert not pallet.carried and pallet.T_world_pallet.t[2] == 0.0
    assert pallet.T_world_pallet.to_se2().distance_to(drop) < 0.2  # set down at the drop node
    assert r.runner.ctx.memory.at_node == "drop_pre"
    assert abs(r.sim.fork_height - r.sim.vehicle.mast.travel_height_empty) < 0.005  # empty forks back down
    # The report and every event line are strict JSON (RFC 8259): no NaN / Infinity (beam ranges are null).
    for text in [(tmp_path / "report" / "report.json").read_text(), *open(tmp_path / "report" / "events.jsonl")]:
        json.loads(text, parse_constant=_reject)


def _reject(name: str) -> None:
    raise ValueError(f"not strict JSON: {name}")


def test_no_adapt_baseline_refuses_a_misplaced_pallet(tmp_path):
    sc = scenario("b1", [{"node": "floor_b2", "dy": 0.15, "dyaw_deg": 5.0}])
    r = run(tmp_path, [{"type": "pickup", "node": "floor_b2"}], sc, adapt=False)
    task = r.summary["tasks"][0]
    assert not r.success and task["reason"] in {"safety_check_failed", "collision"}
    assert abs(r.sim.speed) < 1e-3


def test_the_load_is_followed_through_the_mission(tmp_path):
    from palletpilot.executor.core.mission import load_mission, validate_mission
    from palletpilot.roadmap import load_map

    path = mission_file(
        tmp_path,
        [
            {"type": "pickup", "node": "floor_b2"},
            {"type": "pickup", "node": "floor_b3"},
            {"type": "delivery", "node": "drop"},
            {"type": "delivery", "node": "drop"},
        ],
    )
    mission = load_mission(path)
    vehicle = load_vehicle(MISSIONS / "forklift.yaml")
    with pytest.raises(MissionError) as info:
        validate_mission(mission, load_map(mission.map_path), vehicle, "charger", str(path))
    problems = info.value.problems
    assert len(problems) == 2, problems
    assert "tasks[1] (pickup): a pickup while the forks still carry the load from tasks[0]" in problems[0]
    assert "tasks[3] (delivery): a delivery with empty forks" in problems[1]
    starts_loaded = mission.model_copy(update={"loaded_at_start": True, "tasks": mission.tasks[2:3]})
    validate_mission(starts_loaded, load_map(mission.map_path), vehicle, "charger", str(path))


@pytest.mark.parametrize(
    "task, message",
    [
        ({"type": "pickup", "node": "nowhere"}, "unknown node 'nowhere'"),
        ({"type": "pickup", "node": "b2"}, "node 'b2' is a waypoint node, a pickup needs a pallet node"),
        ({"type": "charge", "node": "drop", "minutes": 1}, "a charge needs a charging node"),
        ({"type": "delivery", "node": "drop", "height": 3.5}, "height 3.50 m is outside the mast's range"),
        ({"type": "move", "node": "island"}, "node 'island' cannot be reached"),
        ({"type": "pickup"}, "tasks[0].pickup.node: Field required"),
        ({"type": "delivery", "node": "drop"}, "a delivery with empty forks"),
        ({"type": "pickup", "node": "rack_a1", "height": 1.9}, "height 1.90 m is outside the mast's range"),
        ({"type": "move", "node": "b1"}, "is not the mission's map"),
    ],
)
def test_invalid_missions_are_rejected(tmp_path, capsys, task, message):
    doc = yaml.safe_load((MISSIONS / "warehouse.yaml").read_text())
    doc["nodes"].append({"id": "island", "type": "waypoint", "x": 50, "y": 50})
    (tmp_path / "warehouse.yaml").write_text(yaml.safe_dump(doc))
    (tmp_path / "forklift.yaml").write_text((MISSIONS / "forklift.yaml").read_text())
    path = tmp_path / "m.yaml"
    path.write_text(yaml.safe_dump({"map": "warehouse.yaml", "tasks": [task]}))
    sc = scenario("b1", [])
    with pytest.raises(MissionError) as info:
        run_simulated(path, scenario=sc)
    assert any(message in line for line in info.value.problems), info.value.problems
    assert main(["run", str(path), "--scenario", str(MISSIONS / "scenario_floor.yaml")]) == 2
    err = capsys.readouterr().err
    assert message in err and "Traceback" not in err


def test_cancel_stops_the_vehicle(tmp_path):
    from palletpilot.executor.apps.app import default_scenario
    from palletpilot.executor.core.mission import load_mission

    path = mission_file(tmp_path, [{"type": "move", "node": "a_top"}])
    sc = default_scenario(load_mission(path))

    def cancel_after_5_s(runner):
        # Cancel once the forklift has started to move: hook the simulated clock.
        clock_tick = runner.clock.tick

        def tick():
            clock_tick()
            if runner.clock.now() > 5.0:
                runner.cancel()

        runner.clock.tick = tick

    r = run_simulated(path, scenario=sc, on_start=cancel_after_5_s)
    assert not r.success and r.summary["tasks"][0]["reason"] == "cancelled"
    assert r.runner.clock.now() < 10.0
    assert abs(r.sim.speed) < 1e-3


def test_pause_holds_the_vehicle_still(tmp_path):
    from palletpilot.executor.apps.app import default_scenario
    from palletpilot.executor.core.mission import load_mission

    path = mission_file(tmp_path, [{"type": "move", "node": "a_top"}])
    sc = default_scenario(load_mission(path))
    poses = []

    def pause_between_5_and_15_s(runner):
        clock_tick = runner.clock.tick

        def tick():
            clock_tick()
            t = runner.clock.now()
            if 5.0 < t < 15.0:
                runner.pause()
            elif t >= 15.0:
                runner.resume()
            if 8.0 < t < 15.0:
                poses.append(runner.ctx.vehicle.true_pose)

        runner.clock.tick = tick

    r = run_simulated(path, scenario=sc, on_start=pause_between_5_and_15_s)
    assert r.success
    assert poses and all(p.isclose(poses[0], atol=1e-6) for p in poses)  # stood still while paused


def test_a_report_that_cannot_be_written_is_exit_3_with_one_line(tmp_path, capsys, monkeypatch):
    import errno
    import os

    path = mission_file(tmp_path, [{"type": "move", "node": "b1"}])
    report = tmp_path / "report"
    report.mkdir()
    (report / "report.json").write_text("{}")
    real_fsync = os.fsync

    def full_disk_for_reports(fd: int) -> None:
        if os.readlink(f"/proc/self/fd/{fd}").split("/")[-1].startswith(".report.json"):
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC))
        real_fsync(fd)

    monkeypatch.setattr(os, "fsync", full_disk_for_reports)
    code = main(["run", str(path), "--report", str(report), "--quiet"])
    err = capsys.readouterr().err
    assert code == 3, err  # the mission succeeded; its report did not land
    lines = [line for line in err.splitlines() if line]
    assert len(lines) == 1 and "report.json" in lines[0] and "No space left on device" in lines[0]
    assert not (report / "report.json").exists()  # the older run's report is gone, never shown as this one's
    assert (report / "trajectory.png").exists() and (report / "events.jsonl").exists()


def test_mission_diagram(tmp_path):
    out = tmp_path / "pickup.mmd"
    assert main(["mission", "diagram", "pickup", "--out", str(out)]) == 0
    text = out.read_text()
    assert "stateDiagram-v2" in text and "estimate_pallet --> lower_forks: misaligned" in text
    assert "[*] --> drive_to_pre_pallet" in text and "succeeded --> [*]" in text
    assert "succeeded --> failed" not in text and "failed --> failed" not in text  # final states stay final
    assert "calibrate --> failed: fail" in text and "[*]" not in text.split("stateDiagram-v2")[0]
    assert main(["mission", "diagram", "dance"]) == 2
    png = tmp_path / "pickup.png"
    assert main(["mission", "diagram", "pickup", "--out", str(png)]) == 2 and not png.exists()  # no text in a .png


def test_a_delivery_whose_forks_feel_no_load_never_moves(tmp_path):
    # The mission says the truck starts loaded; the load sensor says otherwise: refuse, stand still.
    path = tmp_path / "mission.yaml"
    doc = {
        "map": str(MISSIONS / "warehouse.yaml"),
        "loaded_at_start": True,
        "tasks": [{"type": "delivery", "node": "drop"}],
    }
    path.write_text(yaml.safe_dump(doc))
    r = run_simulated(path, scenario=scenario("c_e", []), report_dir=tmp_path / "report")
    result = r.runner.results[0]
    assert not r.success and result.reason == "no_load" and "load sensor" in (result.message or "")
    assert r.sim.forklift.odometer < 1e-6


def test_charging_until_a_level_uses_the_simulated_battery(tmp_path):
    sc = scenario("charger", []).model_copy(update={"battery_level": 0.80})
    sc.folder = MISSIONS
    r = run(tmp_path, [{"type": "charge", "node": "charger", "until_level": 0.85}], sc)
    assert r.success, r.runner.results[0].message
    assert r.sim.battery_level is not None and r.sim.battery_level >= 0.85
    rate = r.sim.vehicle.battery.charge_per_min
    assert r.sim.time == pytest.approx(60.0 * 0.05 / rate, rel=0.05)  # 5 % at the vehicle file's rate


def test_driving_and_lifting_drain_the_battery(tmp_path):
    sc = scenario("b1", [{"node": "floor_b2"}]).model_copy(update={"battery_level": 0.5})
    sc.folder = MISSIONS
    r = run(tmp_path, [{"type": "pickup", "node": "floor_b2"}], sc)
    assert r.success
    battery = r.sim.vehicle.battery
    floor = 0.5 - r.sim.forklift.odometer / 1000.0 * battery.drain_per_km
    assert r.sim.battery_level < floor + 1e-9  # distance drained it, lifting a little more


def test_until_level_needs_a_battery_model(tmp_path):
    from palletpilot.executor.core.mission import load_mission, validate_mission
    from palletpilot.roadmap import load_map

    path = mission_file(tmp_path, [{"type": "charge", "node": "charger", "until_level": 0.9}])
    mission = load_mission(path)
    vehicle = load_vehicle(MISSIONS / "forklift.yaml").model_copy(update={"battery": None})
    with pytest.raises(MissionError) as info:
        validate_mission(mission, load_map(mission.map_path), vehicle, "charger", str(path))
    assert "until_level needs a battery model" in info.value.problems[0]
