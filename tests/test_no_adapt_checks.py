"""`--no-adapt` never drives the forks into a pallet they do not fit (issue 40): without adaptation the
truck still looks with its camera (calibrate, estimate, the entry checks) and refuses, standing, a pallet
the forks would not go into as it stands. The paper's beams-only Pickup is a bench baseline that no
command driving a truck reaches."""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path

import pytest
from test_executor_missions import run, scenario

from palletpilot.executor.apps.robot import RobotError, load_inputs
from palletpilot.executor.core.behaviour import Settings
from palletpilot.executor.core.tasks import pickup_kind
from palletpilot.geometry.fileio import bundled_path

REPO = Path(__file__).resolve().parents[1]


def _states(result) -> list[str]:
    return [s["state"] for s in result.runner.results[0].states]


def test_no_adapt_refuses_a_pallet_030_m_to_the_side_standing(tmp_path: Path) -> None:
    # The paper's Pickup entered it (one beam through a pocket, one beside the pallet) and collided.
    sc = scenario("b1", [{"node": "floor_b2", "dy": 0.30}])
    r = run(tmp_path, [{"type": "pickup", "node": "floor_b2"}], sc, adapt=False)
    task = r.runner.results[0]
    assert not r.success and task.reason == "safety_check_failed", task.message
    assert "--no-adapt" in task.message and "lateral" in task.message, task.message
    assert r.sim.collisions == [] and not r.sim.pallets[0].carried
    assert abs(r.sim.speed) < 1e-3  # stopped
    states = _states(r)
    assert "calibrate" in states and "estimate_pallet" in states and "enter" not in states, states
    assert r.sim.pallets[0].T_world_pallet.to_se2().distance_to(r.sim.pallets[0].initial.to_se2()) < 1e-6


def test_no_adapt_looks_then_takes_an_aligned_pallet(tmp_path: Path) -> None:
    r = run(tmp_path, [{"type": "pickup", "node": "floor_b2"}], scenario("b1", [{"node": "floor_b2"}]), adapt=False)
    assert r.success, [t.message for t in r.runner.results]
    assert r.sim.pallets[0].carried and r.sim.collisions == []
    states = _states(r)
    for state in ("calibrate", "estimate_pallet", "check_entry", "safety_check", "enter"):
        assert state in states, states
    assert "replan" not in states


def test_only_the_bench_reaches_the_paper_baseline() -> None:
    settings = Settings(adapt=False)
    assert pickup_kind(settings) == "pickup_no_adapt"
    assert pickup_kind(dataclasses.replace(settings, paper_baseline=True)) == "pickup_paper"
    # No command that drives a truck (run, robot, agv: executor/) sets the bench's switch.
    setters = []
    for path in sorted((REPO / "executor").rglob("*.py")):
        for node in ast.walk(ast.parse(path.read_text())):
            targets = node.targets if isinstance(node, ast.Assign) else []
            keywords = node.keywords if isinstance(node, ast.Call) else []
            names = [t.attr for t in targets if isinstance(t, ast.Attribute)] + [k.arg for k in keywords]
            if "paper_baseline" in names:
                setters.append(f"{path.relative_to(REPO)}:{node.lineno}")
    assert setters == []


@pytest.mark.parametrize("adapt", [True, False])
def test_a_robot_without_a_camera_refuses_a_pickup_in_every_mode(tmp_path: Path, adapt: bool) -> None:
    robot = tmp_path / "robot.yaml"
    robot.write_text(f"forks: {bundled_path('missions', 'forks.yaml')}\ncamera: {{source: none}}\n")
    with pytest.raises(RobotError, match=r"camera\.source: none, but the mission's pickups"):
        load_inputs(bundled_path("missions", "pickup_delivery.yaml"), robot, adapt=adapt)
