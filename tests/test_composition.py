"""Issue 38: one composition root, immutable settings, and a runner that nobody patches after building it.

`compose.build_runner` takes everything a run needs (the AGV's order planner and the heading the truck
stands with included); `Settings` is frozen, so a mission's own wait or a command's `--no-adapt` makes a
new one instead of changing the caller's.
"""

from __future__ import annotations

import ast
import dataclasses
import json
from pathlib import Path
from typing import Any

import pytest
import yaml
from test_runner_failsafe import VEHICLE, FakeVehicle

from palletpilot.control.mpc import MpcFollower
from palletpilot.executor.adapters.mcap.recording import Recorder
from palletpilot.executor.apps import compose
from palletpilot.executor.core.behaviour import (
    JOURNALLED,
    NOT_JOURNALLED,
    Context,
    Settings,
    TaskMemory,
    TemporaryNodes,
)
from palletpilot.executor.core.clock import SimClock
from palletpilot.executor.core.mission import MoveTask, PickupTask, WaitTask, load_mission
from palletpilot.executor.core.runner import Runner
from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.specs import load_forks
from palletpilot.roadmap import Planner, load_map

ROOT = Path(__file__).resolve().parent.parent
MISSIONS = bundled_path("missions")


def _mission(tmp_path: Path, **extra: Any) -> Path:
    path = tmp_path / "m.yaml"
    doc = {"name": "t", "map": str(MISSIONS / "warehouse.yaml"), "tasks": [{"type": "move", "node": "a_top"}], **extra}
    path.write_text(yaml.safe_dump(doc))
    return path


def _parts(tmp_path: Path, **kw: Any) -> compose.Parts:
    mission = load_mission(_mission(tmp_path))
    roadmap = load_map(mission.map_path)
    vehicle = FakeVehicle(roadmap.node("charger").pose)

    def grab() -> Any:
        raise AssertionError("no camera here")

    return compose.Parts(
        mission,
        roadmap,
        vehicle,  # type: ignore[arg-type]
        None,
        grab,
        SimClock(vehicle.step),
        VEHICLE,
        load_forks(MISSIONS / "forks.yaml"),
        "charger",
        MpcFollower(VEHICLE),
        **kw,
    )


def test_settings_are_frozen() -> None:
    settings = Settings()
    with pytest.raises(dataclasses.FrozenInstanceError):
        settings.adapt = False  # type: ignore[misc]
    assert dataclasses.replace(settings, adapt=False).adapt is False and settings.adapt is True


def test_a_missions_own_wait_leaves_the_callers_settings_alone(tmp_path: Path) -> None:
    mission = load_mission(_mission(tmp_path, blocked_wait_s=4.0))
    roadmap = load_map(mission.map_path)
    vehicle = FakeVehicle(roadmap.node("charger").pose)
    settings = Settings()
    runner = Runner(mission, roadmap, vehicle, None, lambda: None, SimClock(0.05), VEHICLE, None, "charger", settings)  # type: ignore[arg-type]
    assert runner.settings.blocked_wait_s == 4.0 and runner.ctx.settings is runner.settings
    assert settings.blocked_wait_s == Settings.blocked_wait_s == 30.0


def test_build_runner_takes_the_planner_and_the_start_heading(tmp_path: Path) -> None:
    plain = compose.build_runner(_parts(tmp_path), compose.Outputs(), Settings())
    assert type(plain.ctx.planner) is Planner
    assert plain.ctx.memory.heading == plain.ctx.roadmap.node("charger").pose.yaw

    class OrderPlanner(Planner):
        pass

    roadmap = plain.ctx.roadmap
    planner = OrderPlanner(roadmap)
    runner = compose.build_runner(_parts(tmp_path, planner=planner, start_heading=1.25), compose.Outputs(), Settings())
    assert runner.ctx.planner is planner
    assert runner.ctx.memory.heading == 1.25 and runner.ctx.memory.at_node == "charger"


def test_no_composition_root_patches_a_runner_after_building_it() -> None:
    """Nothing outside the core assigns into a runner's context (`x.ctx.y = ...`) or its attributes."""
    patched = []
    for path in sorted((ROOT / "executor").rglob("*.py")):
        if "core" in path.relative_to(ROOT / "executor").parts:
            continue
        for node in ast.walk(ast.parse(path.read_text())):
            targets = node.targets if isinstance(node, ast.Assign) else []
            targets += [node.target] if isinstance(node, (ast.AugAssign, ast.AnnAssign)) else []
            for target in targets:
                text = ast.unparse(target)
                if ".ctx." in text or text.startswith("runner."):
                    patched.append(f"{path.relative_to(ROOT)}:{node.lineno}: {text}")
    assert patched == []


def test_every_memory_field_is_journalled_or_says_why_not() -> None:
    names = [f.name for f in dataclasses.fields(TaskMemory)]
    assert sorted(names) == sorted([*JOURNALLED, *NOT_JOURNALLED]), "a new TaskMemory field: journal it or say why not"
    assert not set(JOURNALLED) & set(NOT_JOURNALLED)
    assert list(TaskMemory("a", 0.5).to_json()) == list(JOURNALLED)
    deps = {f.name for f in dataclasses.fields(Context)} - {"memory"}
    assert not deps & set(names), "a field is either injected or remembered, not both"


def test_the_memory_a_checkpoint_stores_restores_the_same_memory() -> None:
    cal = Calibration(SE3.from_translation(0.5, 0.0, 1.2), "model", {"fit_rms_m": 0.004})
    temporary = TemporaryNodes(1, "slot~1", "pre~1", SE2(3.0, 1.0, 0.1), SE2(2.0, 1.0, 0.1), "n2", 0.1, ("n1", "n2"))
    task = PickupTask(type="pickup", node="slot")
    memory = TaskMemory("pre~1", 0.25, task=task, attempts=2, pallet_node="slot", pre_node="pre", node_before="n2")
    memory.route_to_pre, memory.calibration, memory.temporary = ["s", "n2", "pre"], cal, [temporary]
    memory.estimated_pallet = SE3.from_translation(3.1, 1.0, 0.0)
    doc = json.loads(json.dumps(memory.to_json()))  # what the journal writes and reads back
    again = TaskMemory("elsewhere", 0.0, task=task)
    again.restore_position(doc)
    assert again.restore_task(doc) == [temporary] and again.temporary == []  # the caller adds them back
    assert again.to_json() | {"temporary": doc["temporary"]} == doc
    assert again.calibration is not None and again.calibration.method == "model"
    assert (again.at_node, again.heading, again.attempts, again.node_before) == ("pre~1", 0.25, 2, "n2")


def test_a_new_task_forgets_the_last_ones_scratch_but_not_where_the_truck_stands() -> None:
    memory = TaskMemory("pre", 1.0, attempts=3, route_to_pre=["a", "pre"], node_before="a", pallet_node="slot")
    memory.temporary = [TemporaryNodes(1, "s~1", "p~1", SE2(0, 0, 0), SE2(1, 0, 0), "a", 0.0)]
    move = MoveTask(type="move", node="drop")
    memory.start_task(move)
    assert (memory.task, memory.attempts, memory.temporary, memory.route_to_pre) == (move, 0, [], [])
    assert (memory.at_node, memory.heading, memory.node_before) == ("pre", 1.0, "a")
    assert memory.node_task() is move
    with pytest.raises(TypeError, match="handles no load"):
        memory.load_task()
    with pytest.raises(TypeError, match="is no WaitTask"):
        memory.task_of(WaitTask)


def test_the_injected_dependencies_are_frozen(tmp_path: Path) -> None:
    runner = compose.build_runner(_parts(tmp_path), compose.Outputs(), Settings())
    with pytest.raises(dataclasses.FrozenInstanceError):
        runner.ctx.planner = Planner(runner.ctx.roadmap)  # type: ignore[misc]


def test_a_recorder_follows_only_a_runner_built_with_its_observer(tmp_path: Path) -> None:
    recorder = Recorder(tmp_path / "run.mcap", port=None, wall=False)
    try:
        parts = _parts(tmp_path)
        bare = Runner(
            parts.mission,
            parts.roadmap,
            recorder.wrap_vehicle(parts.vehicle),
            None,
            parts.grab,
            parts.clock,
            VEHICLE,
            parts.forks,
            "charger",
        )
        with pytest.raises(ValueError, match="among its observers"):
            recorder.attach(bare)
        assert recorder.on_event not in bare.listeners  # nothing subscribed into it afterwards
        runner = compose.build_runner(_parts(tmp_path), compose.Outputs(recorder=recorder), Settings())
        assert runner.listeners[-1] == recorder.on_event and recorder.runner is runner
    finally:
        recorder.close()
