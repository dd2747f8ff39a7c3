"""Re-planning from further back along the route, and `return_on_failure` to a parking node (issue 15).

Simulated missions on small maps written into tmp_path: a straight aisle eastwards whose nodes stand
close before the pre-pallet node (so the curve to a misplaced pallet's new pre-pallet node only fits from
further back), and the example warehouse with two park nodes.
"""

import dataclasses
import itertools
import json
import shutil
from pathlib import Path
from typing import Any

import pytest
import yaml

from palletpilot.executor.adapters.stores.journal import Journal
from palletpilot.executor.apps.app import run_simulated
from palletpilot.executor.core.behaviour import TemporaryNodes
from palletpilot.executor.core.pickup import add_temporary_nodes
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.errors import PerceptionError
from palletpilot.roadmap import NodeType, RoadmapError, load_map
from palletpilot.sim.scenario import Scenario

MISSIONS = bundled_path("missions")

# The pallet stands 0.3 m to the left of its node, turned 5 deg to the right: the new pre-pallet node
# lies ~0.52 m to the side, heading -5 deg, which no curve reaches within 1.2 m (radius >= 0.78 m).
MISPLACED = {"node": "slot", "dy": 0.3, "dyaw_deg": -5.0}


def _files(tmp_path: Path) -> None:
    for name in ("forklift.yaml", "forks.yaml"):
        shutil.copy(MISSIONS / name, tmp_path / name)


def aisle_map(tmp_path: Path, behind_pre: list[float], park: bool = False) -> Path:
    """A straight aisle heading east (forks leading), ending at pre-pallet node `pre` (x = 8) and pallet
    node `slot` 2.5 m beyond it. Waypoints `n1`, `n2`, ... stand `behind_pre` metres before `pre`
    (nearest first), `s` (the start) at x = 0; each joined forward and, in reverse, back. With `park`, a
    park node on an arc to the left of `n2`."""
    _files(tmp_path)
    chain = ["pre", *(f"n{i + 1}" for i in range(len(behind_pre))), "s"]
    xs = [8.0, *(8.0 - d for d in behind_pre), 0.0]
    nodes: list[dict[str, Any]] = [{"id": "pre", "type": "pre_pallet", "x": 8.0, "y": 0.0, "yaw_deg": 0}]
    nodes += [
        {"id": n, "type": "waypoint", "x": x, "y": 0.0, "yaw_deg": 0} for n, x in zip(chain[1:], xs[1:], strict=True)
    ]
    nodes.append({"id": "slot", "type": "pallet", "x": 10.5, "y": 0.0, "yaw_deg": 0, "pre_pallet": "pre"})
    edges: list[dict[str, Any]] = []
    for near, far in itertools.pairwise(chain):
        edges += [{"from": far, "to": near}, {"from": near, "to": far, "direction": "reverse", "speed_limit": 0.5}]
    edges += [
        {"from": "pre", "to": "slot", "speed_limit": 0.3},
        {"from": "slot", "to": "pre", "direction": "reverse", "speed_limit": 0.3},
    ]
    if park:
        x2 = 8.0 - behind_pre[1]
        nodes.append({"id": "park", "type": "park", "x": x2 + 2.5, "y": 2.5, "yaw_deg": 90})
        edges += [
            {"from": "n2", "to": "park", "curve": "arc", "speed_limit": 0.6},
            {"from": "park", "to": "n2", "curve": "arc", "direction": "reverse", "speed_limit": 0.5},
        ]
    path = tmp_path / "aisle.yaml"
    path.write_text(yaml.safe_dump({"name": "aisle", "vehicle": "forklift.yaml", "nodes": nodes, "edges": edges}))
    return path


def warehouse_with_parking(tmp_path: Path) -> Path:
    """The example warehouse plus two park nodes: `park_near`, off b_top, 8 m from floor_b2_pre as the
    crow flies but ~16 m by the one-way loop, and `park_far`, off b_bot, 6 m away but ~70 m by the loop."""
    _files(tmp_path)
    doc = yaml.safe_load((MISSIONS / "warehouse.yaml").read_text())
    doc["parking_types"] = ["park"]
    doc["nodes"] += [
        {"id": "park_near", "type": "park", "x": 22.5, "y": 19.5, "yaw_deg": 0},
        {"id": "park_far", "type": "park", "x": 22.5, "y": 5.5, "yaw_deg": 0},
    ]
    for spur, park in (("b_top", "park_near"), ("b_bot", "park_far")):
        doc["edges"] += [
            {"from": spur, "to": park, "curve": "arc", "speed_limit": 0.6},
            {"from": park, "to": spur, "curve": "arc", "direction": "reverse", "speed_limit": 0.5},
        ]
    path = tmp_path / "warehouse.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def run(
    tmp_path: Path,
    map_path: Path,
    start: str,
    pallets: list[dict],
    tasks: list[dict],
    on_start: Any = None,
    **mission: Any,
) -> Any:
    sc = Scenario.model_validate(
        {
            "map": map_path.name,
            "start": start,
            "seed": 5,
            "camera": {"mount": {"tilt_deg": 22.0}},
            "noise": {"localization_xy_sigma": 0.002, "localization_yaw_sigma_deg": 0.03},
            "pallets": pallets,
        }
    )
    sc.folder = tmp_path
    path = tmp_path / "mission.yaml"
    path.write_text(yaml.safe_dump({"name": "t", "map": map_path.name, "tasks": tasks, **mission}))
    report, journal = tmp_path / "report", tmp_path / "run.db"
    return run_simulated(path, scenario=sc, report_dir=report, journal=journal, on_start=on_start)


def events(tmp_path: Path) -> list[dict[str, Any]]:
    return [json.loads(line) for line in (tmp_path / "report" / "events.jsonl").read_text().splitlines()]


def report_task(tmp_path: Path) -> dict[str, Any]:
    return json.loads((tmp_path / "report" / "report.json").read_text())["tasks"][0]


# -- re-planning further back --------------------------------------------------------------------


def test_replan_joins_the_new_node_further_back_when_the_nearest_gives_no_curve(tmp_path):
    map_path = aisle_map(tmp_path, [0.6, 4.0])
    r = run(tmp_path, map_path, "s", [MISPLACED], [{"type": "pickup", "node": "slot"}])
    result = r.runner.results[0]
    assert r.success, result.message
    assert r.sim.pallets[0].carried and r.sim.collisions == []
    task = report_task(tmp_path)
    first = task["temporary_nodes"][0]
    assert first["joined_to"] == "n2" and first["nodes_tried"] == 2 and first["backs_along"] == ["n1", "n2"]
    assert "n2->pre~1" in first["edges"] and "pre~1->n2" in first["edges"]
    log = events(tmp_path)
    assert [e["node"] for e in log if e["event"] == "approach_infeasible"][:1] == ["n1"]
    # The truck backed from n1 to n2 before the new curve, and left the temporary nodes through n2.
    routes = [e["nodes"] for e in log if e["event"] == "route"]
    assert ["n1", "n2", "pre~1"] in routes
    last = task["temporary_nodes"][-1]
    assert task["states"][-1]["state"] == "return_to_roadmap" and r.runner.ctx.memory.at_node == last["joined_to"]
    assert [last["pre_pallet"], last["joined_to"]] == routes[-1]
    assert not any(n.temporary for n in r.runner.ctx.roadmap.nodes())
    # The journal holds what rebuilds the same temporary graph on a resume.
    with Journal.open(tmp_path / "run.db") as book:
        saved = next(cp["ctx"] for cp in book.checkpoints() if cp.get("state") == "approach")
    assert saved["route_to_pre"] == ["s", "n2", "n1", "pre"]
    spec = TemporaryNodes.from_json(saved["temporary"][0])
    assert spec.before == "n2" and spec.via == ("n1", "n2")
    ctx = dataclasses.replace(r.runner.ctx, log=lambda *a, **k: None)
    ctx.memory.task, ctx.memory.temporary = r.runner.mission.tasks[0], []
    with ctx.roadmap.overlay() as ov:
        ctx.memory.overlay = ov
        rebuilt = add_temporary_nodes(ctx, spec)
        assert [e.name for e in rebuilt] == first["edges"]
        assert ov.node_ids == ["pre~1", "slot~1"]


def test_no_feasible_approach_names_how_many_nodes_were_tried(tmp_path):
    # n1..n3 all stand too close to the new pre-pallet node; `s` (8 m back) would do, but lies beyond
    # the bound (Settings.replan_back_nodes = 3). A rack slot beside the aisle (`side`, its rack's front
    # 1.0 m left of the aisle) leaves the truck no room at the new pre-pallet pose, so no manoeuvre either.
    map_path = aisle_map(tmp_path, [0.6, 0.8, 1.0])
    doc = yaml.safe_load(map_path.read_text())
    doc["nodes"] += [
        {"id": "side_pre", "type": "pre_pallet", "x": 8.0, "y": -1.48, "yaw_deg": 90},
        {"id": "side", "type": "pallet", "x": 8.0, "y": 1.02, "yaw_deg": 90, "pre_pallet": "side_pre", "height": 1.0},
    ]
    doc["edges"] += [{"from": "side_pre", "to": "side"}, {"from": "side", "to": "side_pre", "direction": "reverse"}]
    map_path.write_text(yaml.safe_dump(doc))
    r = run(tmp_path, map_path, "s", [MISPLACED], [{"type": "pickup", "node": "slot"}])
    result = r.runner.results[0]
    assert not r.success and result.reason == "no_feasible_approach"
    message = result.message or ""
    assert "tried 3 nodes back along the route (at most 3)" in message
    assert all(f"from '{n}'" in message for n in ("n1", "n2", "n3"))
    assert "from 's'" not in message
    assert "a manoeuvre from 'n1'" in message and "the rack at 'side'" in message
    assert abs(r.sim.speed) < 1e-3 and r.sim.collisions == [] and not r.sim.pallets[0].carried


def test_a_manoeuvre_takes_the_pallet_when_no_node_back_gives_a_curve(tmp_path):
    # As above without the rack: the truck backs up and drives forward into the new pre-pallet node.
    map_path = aisle_map(tmp_path, [0.6, 0.8, 1.0])
    r = run(tmp_path, map_path, "s", [MISPLACED], [{"type": "pickup", "node": "slot"}])
    assert r.success and r.sim.pallets[0].carried and r.sim.collisions == []
    planned = [e for e in events(tmp_path) if e["event"] == "manoeuvre_planned"]
    assert planned and planned[0]["node"] == "n1" and "reverse" in planned[0]["directions"]
    assert report_task(tmp_path)["temporary_nodes"][0]["nodes_tried"] == 4
    assert r.runner.ctx.memory.at_node == "n1" and not any(n.temporary for n in r.runner.ctx.roadmap.nodes())


# -- return_on_failure ---------------------------------------------------------------------------


def test_a_failed_pickup_returns_to_the_nearest_park_node_by_route(tmp_path):
    map_path = warehouse_with_parking(tmp_path)
    r = run(tmp_path, map_path, "b1", [], [{"type": "pickup", "node": "floor_b2"}], return_on_failure=True)
    result = r.runner.results[0]
    assert not r.success and result.reason == "pallet_not_found"
    assert r.runner.ctx.memory.at_node == "park_near"  # nearer by route than park_far, though further away
    park = r.runner.ctx.roadmap.node("park_near").pose
    assert r.sim.true_pose.distance_to(park) < 0.15 and abs(r.sim.speed) < 1e-3 and r.sim.collisions == []
    fork = r.sim.fork_height
    assert abs(fork - r.sim.vehicle.mast.travel_height_empty) < 0.005  # lowered before leaving
    record = report_task(tmp_path)["return_on_failure"]
    assert record["parking_node"] == "park_near" and record["parked"] is True and record["reason"] is None
    names = [e["event"] for e in events(tmp_path)]
    assert names.index("returning_on_failure") < names.index("parked") < names.index("task_end")


def test_a_failure_on_a_temporary_node_backs_out_through_the_temporary_edges_to_park(tmp_path):
    # The misplaced pallet is re-planned to (pre~1 joined to n2); seen from pre~1 it is "not found".
    def blind_from_temporary_nodes(runner):
        perception, ctx = runner.ctx.perception, runner.ctx
        real = perception.estimate_pallet

        def estimate(frame, calibration, pose, expected=None, pallet=None, **kw):
            if ctx.roadmap.node(ctx.memory.pre_node).temporary:
                raise PerceptionError("test: nothing seen from the temporary node")
            return real(frame, calibration, pose, expected, pallet, **kw)

        perception.estimate_pallet = estimate

    map_path = aisle_map(tmp_path, [0.6, 4.0], park=True)
    tasks = [{"type": "pickup", "node": "slot", "return_on_failure": True}]
    r = run(tmp_path, map_path, "s", [MISPLACED], tasks, on_start=blind_from_temporary_nodes)
    assert r.runner.results[0].reason == "pallet_not_found"
    (going,) = [e for e in events(tmp_path) if e["event"] == "returning_on_failure"]
    assert going["from_node"] == "pre~1" and going["route"] == ["pre~1", "n2", "park"]
    assert r.runner.ctx.memory.at_node == "park" and abs(r.sim.speed) < 1e-3 and r.sim.collisions == []
    assert r.sim.true_pose.distance_to(r.runner.ctx.roadmap.node("park").pose) < 0.15
    assert report_task(tmp_path)["return_on_failure"]["parking_node"] == "park"
    assert not any(n.temporary for n in r.runner.ctx.roadmap.nodes())


@pytest.mark.parametrize(
    ("mission", "task"),
    [({}, {}), ({"return_on_failure": False}, {}), ({"return_on_failure": True}, {"return_on_failure": False})],
    ids=["default", "mission-false", "task-overrides-mission"],
)
def test_without_return_on_failure_the_truck_stays_where_the_task_failed(tmp_path, mission, task):
    map_path = warehouse_with_parking(tmp_path)
    r = run(tmp_path, map_path, "b1", [], [{"type": "pickup", "node": "floor_b2", **task}], **mission)
    assert r.runner.results[0].reason == "pallet_not_found"
    assert r.runner.ctx.memory.at_node == "floor_b2_pre" and abs(r.sim.speed) < 1e-3
    assert "return_on_failure" not in report_task(tmp_path)
    assert not {"returning_on_failure", "parked", "return_failed"} & {e["event"] for e in events(tmp_path)}


def test_no_parking_node_keeps_the_truck_stopped_and_says_why(tmp_path):
    _files(tmp_path)
    map_path = tmp_path / "warehouse.yaml"
    shutil.copy(MISSIONS / "warehouse.yaml", map_path)  # no park node
    r = run(tmp_path, map_path, "b1", [], [{"type": "pickup", "node": "floor_b2", "return_on_failure": True}])
    assert r.runner.results[0].reason == "pallet_not_found" and r.runner.ctx.memory.at_node == "floor_b2_pre"
    (failed,) = [e for e in events(tmp_path) if e["event"] == "return_failed"]
    assert "no node of a parking type (park)" in failed["reason"]
    assert report_task(tmp_path)["return_on_failure"]["parked"] is False


def test_a_cancelled_task_never_returns(tmp_path):
    map_path = warehouse_with_parking(tmp_path)

    def cancel_after_3_s(runner):
        tick = runner.clock.tick

        def traced():
            tick()
            if runner.clock.now() > 3.0:
                runner.cancel()

        runner.clock.tick = traced

    sc = Scenario.model_validate({"map": map_path.name, "start": "b1"})
    sc.folder = tmp_path
    path = tmp_path / "mission.yaml"
    doc = {"map": map_path.name, "return_on_failure": True, "tasks": [{"type": "move", "node": "b_top"}]}
    path.write_text(yaml.safe_dump(doc))
    r = run_simulated(path, scenario=sc, report_dir=tmp_path / "report", on_start=cancel_after_3_s)
    assert r.runner.results[0].reason == "cancelled" and abs(r.sim.speed) < 1e-3
    (failed,) = [e for e in events(tmp_path) if e["event"] == "return_failed"]
    assert "stays stopped" in failed["reason"]
    assert "returning_on_failure" not in {e["event"] for e in events(tmp_path)}


# -- the map's parking types ---------------------------------------------------------------------


def test_parking_types_are_optional_in_the_map_and_never_slots(tmp_path):
    _files(tmp_path)
    doc = yaml.safe_load((MISSIONS / "warehouse.yaml").read_text())
    assert load_map(MISSIONS / "warehouse.yaml").parking_types == {NodeType.PARK}  # existing maps: default
    doc["parking_types"] = ["park", "charging"]
    (tmp_path / "a.yaml").write_text(yaml.safe_dump(doc))
    roadmap = load_map(tmp_path / "a.yaml")
    assert roadmap.parking_types == {NodeType.PARK, NodeType.CHARGING}
    assert [n.id for n in roadmap.parking_nodes()] == ["charger"]
    doc["parking_types"] = ["pre_pallet"]
    (tmp_path / "b.yaml").write_text(yaml.safe_dump(doc))
    with pytest.raises(RoadmapError) as info:
        load_map(tmp_path / "b.yaml")
    assert any("parking_types: pre_pallet nodes are slots or their approaches" in p for p in info.value.problems)
