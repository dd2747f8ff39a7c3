"""Issue 38: one composition root, immutable settings, and a runner that nobody patches after building it.

`compose.build_runner` takes everything a run needs (the AGV's order planner and the heading the truck
stands with included); `Settings` is frozen, so a mission's own wait or a command's `--no-adapt` makes a
new one instead of changing the caller's.
"""

from __future__ import annotations

import ast
import dataclasses
from pathlib import Path
from typing import Any

import pytest
import yaml
from test_runner_failsafe import VEHICLE, FakeVehicle

from palletpilot.control.mpc import MpcFollower
from palletpilot.executor.apps import compose
from palletpilot.executor.core.behaviour import Settings
from palletpilot.executor.core.clock import SimClock
from palletpilot.executor.core.mission import load_mission
from palletpilot.executor.core.runner import Runner
from palletpilot.geometry.fileio import bundled_path
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
    assert plain.ctx.heading == plain.ctx.roadmap.node("charger").pose.yaw

    class OrderPlanner(Planner):
        pass

    roadmap = plain.ctx.roadmap
    planner = OrderPlanner(roadmap)
    runner = compose.build_runner(_parts(tmp_path, planner=planner, start_heading=1.25), compose.Outputs(), Settings())
    assert runner.ctx.planner is planner
    assert runner.ctx.heading == 1.25 and runner.ctx.at_node == "charger"


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
