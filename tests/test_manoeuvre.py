"""Manoeuvres (issue 40): forward and reverse moves to a corrected pre-pallet node no single curve reaches.

The planner on its own (`roadmap.manoeuvre`): moves join up, turn no tighter than the vehicle, keep the
truck's outline clear of the obstacles, survive the journal; then the issue's case in the simulator: a
loaded rack pallet at 1.8 m in the narrow aisle (`missions/narrow_aisle.yaml`), 0.30 m to the side,
0.20 m short and turned -10 deg, which no single curve from the aisle reaches.
"""

import dataclasses
import json
import math
import shutil
from pathlib import Path
from typing import Any

import numpy as np
import pytest
import yaml

from palletpilot.bench.missions import NARROW_AISLE_WIDTH_M, NARROW_RACK_DEPTH_M
from palletpilot.executor.adapters.stores.journal import Journal
from palletpilot.executor.apps.app import run_simulated
from palletpilot.executor.core.behaviour import TemporaryNodes
from palletpilot.executor.core.pickup import add_temporary_nodes
from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import bundled_path
from palletpilot.roadmap import Direction, RoadmapError, connect, load_map
from palletpilot.roadmap.manoeuvre import (
    Footprint,
    Manoeuvre,
    Obstacle,
    arc_then_line,
    footprint_hits,
    plan_manoeuvre,
)
from palletpilot.sim.scenario import Scenario

MISSIONS = bundled_path("missions")
K_MAX = 1 / 0.78  # the example forklift's curvature limit (1/m)
TRUCK = Footprint(-2.1, 1.25, 0.55)
# An aisle along x at y = 0: a rack row's front 2.7 m to the left, another's back 1.8 m to the right.
AISLE = [
    Obstacle.box("the north rack", SE2(), -20.0, 20.0, 2.7, 3.8),
    Obstacle.box("the south rack", SE2(), -20.0, 20.0, -2.9, -1.8),
]
# Where the new pre-pallet node of the issue's case lies, seen from the aisle node (x, y in m, yaw in deg).
GOAL = SE2(0.45, 1.02, math.radians(79.9))


def _check_drivable(m: Manoeuvre, start: SE2, goal: SE2) -> None:
    assert m.segments[0].start_pose.isclose(start, atol=1e-6, atol_yaw=1e-6)
    for a, b in zip(m.segments, m.segments[1:], strict=False):
        assert a.end_pose.isclose(b.start_pose, atol=1e-6, atol_yaw=1e-6)  # moves join, heading and all
    end = m.segments[-1].end_pose
    assert end.distance_to(goal) < 1e-6 and abs(math.remainder(end.yaw - goal.yaw, 2 * math.pi)) < 1e-3
    assert m.segments[-1].direction is Direction.FORWARD
    assert max(s.curve.max_abs_curvature() for s in m.segments) <= K_MAX * (1 + 1e-6)
    for s in m.segments:
        assert footprint_hits(s.poses(), TRUCK, AISLE, 0.09) is None


def test_no_single_curve_reaches_the_issues_pre_pallet_pose_but_a_manoeuvre_does():
    with pytest.raises(RoadmapError, match="needs a radius"):
        connect(SE2(), GOAL, K_MAX)
    m = plan_manoeuvre(SE2(), GOAL, K_MAX, TRUCK, AISLE)
    _check_drivable(m, SE2(), GOAL)
    assert m.reversals >= 1 and m.segments[0].direction is Direction.REVERSE
    assert len(m.segments) <= 4 and m.length < 6.0


def test_a_manoeuvre_survives_its_json_exactly():
    m = plan_manoeuvre(SE2(), GOAL, K_MAX, TRUCK, AISLE)
    back = Manoeuvre.from_json(json.loads(json.dumps(m.to_json())))
    assert [s.direction for s in back.segments] == [s.direction for s in m.segments]
    for a, b in zip(m.segments, back.segments, strict=True):
        np.testing.assert_allclose(a.poses(), b.poses(), atol=1e-12)


def test_no_manoeuvre_says_what_it_tried():
    # The right-hand rack 0.35 m nearer: the truck's tail cannot swing round any more.
    tight = [AISLE[0], Obstacle.box("the south rack", SE2(), -20.0, 20.0, -2.9, -1.45)]
    with pytest.raises(RoadmapError) as err:
        plan_manoeuvre(SE2(), GOAL, K_MAX, TRUCK, tight)
    message = str(err.value)
    assert "no manoeuvre of up to 2 moves" in message and "the south rack" in message
    assert "forward curves were tried" in message
    # ... and a goal the truck cannot stand at is refused before any search.
    with pytest.raises(RoadmapError, match=r"at the new pre-pallet pose would come within 0\.10 m of the north"):
        plan_manoeuvre(SE2(), SE2(1.0, 2.3, 0.0), K_MAX, TRUCK, AISLE)


def test_footprint_hits_only_what_it_overlaps():
    box = [Obstacle.box("a box", SE2(3.0, 0.0, 0.0), 0.0, 1.0, -0.5, 0.5)]
    assert footprint_hits(np.array([[0.0, 0.0, 0.0]]), TRUCK, box, 0.0) is None  # tips 1.25, box from 3.0
    assert footprint_hits(np.array([[1.8, 0.0, 0.0]]), TRUCK, box, 0.0) is not None
    assert footprint_hits(np.array([[0.0, 0.0, math.pi / 2]]), TRUCK, box, 0.0) is None  # turned away
    assert footprint_hits(np.array([[1.7, 0.0, 0.0]]), TRUCK, box, 0.1) is not None  # within the clearance


def test_arc_then_line_turns_once_and_runs_straight_in():
    start, goal = SE2(), SE2(1.5, 2.5, math.pi / 2)
    tail = arc_then_line(start, goal, K_MAX)
    assert tail is not None and [s.curve.kind for s in tail] == ["arc", "line"]
    assert tail[-1].end_pose.distance_to(goal) < 1e-9 and tail[0].end_pose.isclose(tail[1].start_pose, 1e-9, 1e-9)
    assert arc_then_line(start, SE2(0.5, 0.5, math.pi / 2), K_MAX) is None  # tighter than the truck turns
    assert arc_then_line(start, SE2(1.0, -1.0, math.pi / 2), K_MAX) is None  # it would have to turn the other way


def test_the_reversing_field_keeps_clear_of_what_cuts_the_scan_plane_only():
    truck = dataclasses.replace(TRUCK, field_m=0.3)  # the field reaches 0.3 m behind the body's rear (-2.1)
    behind = SE2(-2.3, 0.0, 0.0)  # something 0.2 m behind the truck
    floor = [Obstacle.box("a pallet on the floor", behind, -1.0, 0.0, -0.5, 0.5)]
    beams = [Obstacle.box("a pallet on the beams", behind, -1.0, 0.0, -0.5, 0.5, in_scan_plane=False)]
    here = np.array([[0.0, 0.0, 0.0]])
    assert footprint_hits(here, truck, floor, 0.0) is not None  # in the field: reversing would stop the truck
    assert footprint_hits(here, truck, beams, 0.0) is None  # above the scan plane: the field does not see it
    assert footprint_hits(np.array([[-0.3, 0.0, 0.0]]), truck, beams, 0.0) is not None  # the body still hits it


def test_a_goal_with_no_room_to_swing_in_is_backed_into():
    """A pre-pallet pose turned 90 deg across a 4.5 m aisle, 0.6 m off its middle: swinging in, the truck's
    tail would sweep through the rack behind it, so it stops further in and backs straight into the goal;
    the loaded truck leaves along that line, so the line keeps the loaded outline clear of the pallet's rack."""
    loaded, empty = Footprint(-1.85, 1.25, 0.55, 0.19), Footprint(-1.85, 1.15, 0.55, 0.19)
    goal = SE2(0.8, 0.62, math.radians(90.4))
    obstacles = [
        Obstacle.box("the pallet's rack", SE2(), -1.4, 1.4, 2.68, 3.88, approach_only=True),
        Obstacle.box("the racks beside it", SE2(), 1.4, 20.0, 2.68, 3.88),
        Obstacle.box("the racks before it", SE2(), -20.0, -1.4, 2.68, 3.88),
        Obstacle.box("the rack behind", SE2(), -20.0, 20.0, -3.0, -1.82),
        Obstacle.box("the pallet to pick", SE2(), 0.4, 1.25, 2.31, 3.7, approach_only=True, picked=True),
    ]
    m = plan_manoeuvre(SE2(), goal, K_MAX, loaded, obstacles, empty=empty)
    last = m.segments[-1]
    assert last.direction is Direction.REVERSE and last.curve.kind == "line"
    assert last.end_pose.isclose(goal, atol=1e-6, atol_yaw=1e-6)
    assert 0.2 < last.curve.length < 0.45
    for a, b in zip(m.segments, m.segments[1:], strict=False):
        assert a.end_pose.isclose(b.start_pose, atol=1e-6, atol_yaw=1e-6)
    assert max(s.curve.max_abs_curvature() for s in m.segments) <= K_MAX * (1 + 1e-6)
    kept = [o for o in obstacles if not o.approach_only]
    for s in m.segments:
        poses = s.poses()
        assert footprint_hits(poses, loaded, kept, 0.1) is None
        assert footprint_hits(poses, empty, [o for o in obstacles if o.approach_only], 0.1) is None
    assert footprint_hits(last.poses(), loaded, obstacles[:1], 0.1) is None  # leaving loaded, towards the rack


# -- the issue's case in the simulator ----------------------------------------------------------------


def _narrow_aisle_run(tmp_path: Path, pallets: list[dict[str, Any]]) -> Any:
    for name in ("forklift.yaml", "forks.yaml", "narrow_aisle.yaml"):
        shutil.copy(MISSIONS / name, tmp_path / name)
    sc = Scenario.model_validate(
        {
            "map": "narrow_aisle.yaml",
            "start": "aA1",
            "seed": 5,
            "camera": {"mount": {"tilt_deg": 22.0}},
            "noise": {"localization_xy_sigma": 0.002, "localization_yaw_sigma_deg": 0.03},
            "pallets": pallets,
        }
    )
    sc.folder = tmp_path
    mission = tmp_path / "mission.yaml"
    tasks = [{"type": "pickup", "node": "rack_n2"}]
    mission.write_text(yaml.safe_dump({"name": "narrow", "map": "narrow_aisle.yaml", "tasks": tasks}))
    return run_simulated(mission, scenario=sc, report_dir=tmp_path / "report", journal=tmp_path / "run.db")


def test_the_narrow_aisle_pallet_is_picked_after_a_manoeuvre(tmp_path):
    pallets = [
        {"node": "rack_n2", "dx": -0.20, "dy": 0.30, "dyaw_deg": -10.0, "loaded": True},
        {"node": "rack_n1", "loaded": True},  # neighbours in the racks either side, and behind the aisle
        {"node": "rack_n3", "loaded": True},
        {"node": "rack_s2", "loaded": True},
    ]
    r = _narrow_aisle_run(tmp_path, pallets)
    result = r.runner.results[0]
    assert r.success, result.message
    assert r.sim.pallets[0].carried and r.sim.collisions == []
    assert not any(p.lifted for p in r.sim.pallets[1:])
    log = [json.loads(line) for line in (tmp_path / "report" / "events.jsonl").read_text().splitlines()]
    # No single curve from the aisle node (the aisle is one-way: no node further back) ...
    assert [e["node"] for e in log if e["event"] == "approach_infeasible"] == ["aA2"]
    # ... so a manoeuvre: reverse, then forward into the new pre-pallet node.
    planned = [e for e in log if e["event"] == "manoeuvre_planned"]
    assert len(planned) == 1 and planned[0]["segments"] >= 2 and planned[0]["directions"][0] == "reverse"
    task = json.loads((tmp_path / "report" / "report.json").read_text())["tasks"][0]
    record = task["temporary_nodes"][0]
    assert record["curve"] == "manoeuvre" and record["manoeuvre"]["segments"] == planned[0]["segments"]
    routes = [e["nodes"] for e in log if e["event"] == "route"]
    waypoints = [f"rack_n2_pre~1.m{i}" for i in range(1, planned[0]["segments"])]
    assert ["aA2", *waypoints, "rack_n2_pre~1"] in routes  # the approach drives the manoeuvre ...
    assert routes[-1] == ["rack_n2_pre~1", *reversed(waypoints), "aA2"]  # ... and the way out drives it back
    assert r.runner.ctx.memory.at_node == "aA2" and not any(n.temporary for n in r.runner.ctx.roadmap.nodes())
    # The journal holds what rebuilds the same temporary graph on a resume.
    with Journal.open(tmp_path / "run.db") as book:
        saved = next(cp["ctx"] for cp in book.checkpoints() if cp.get("state") == "approach")
    spec = TemporaryNodes.from_json(saved["temporary"][0])
    assert spec.manoeuvre is not None and len(spec.manoeuvre.segments) == planned[0]["segments"]
    ctx = dataclasses.replace(r.runner.ctx, log=lambda *a, **k: None)
    ctx.memory.task, ctx.memory.temporary = r.runner.mission.tasks[0], []
    with ctx.roadmap.overlay() as ov:
        ctx.memory.overlay = ov
        assert [e.name for e in add_temporary_nodes(ctx, spec)] == record["edges"]


def test_the_narrow_aisle_map_is_as_its_header_and_the_bench_say():
    roadmap = load_map(MISSIONS / "narrow_aisle.yaml")
    north, south = roadmap.node("rack_n2"), roadmap.node("rack_s2")
    # the rack's front stands 0.10 m beyond its node (`sim.simulator`), a 1.1 m rack behind row S's front
    aisle = (north.pose.y + 0.10) - (south.pose.y + 0.10 + NARROW_RACK_DEPTH_M)
    assert aisle == pytest.approx(NARROW_AISLE_WIDTH_M)  # as `bench missions` states it
    assert north.height == 1.8 and roadmap.edge("aA2", "rack_n2_pre").curve.kind == "arc"
    assert not roadmap.graph.has_edge("aA2", "aA1")  # one-way: no node back along the aisle
