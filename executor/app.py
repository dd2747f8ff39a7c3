"""Running a mission in the simulated warehouse: from files to a finished, reported run.

`run_simulated(mission_path, scenario_path=None, seed=None, report_dir=None, adapt=True)` loads and
validates the mission against its map and the vehicle, builds the simulator (the scenario's, or the
default warehouse: the mission's map, the forklift at the first charging node, an empty pallet exactly
at every pickup node), runs the tasks and writes the report. Returns a `SimRun`.
"""

from __future__ import annotations

import contextlib
import math
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import TextIO

import numpy as np

from control.mpc import MpcConfig, MpcFollower
from control.vehicle import load_vehicle
from executor.mission import Mission, load_mission, validate_mission
from executor.ports import LocalPerception
from executor.report import summary, write_report
from executor.runner import Runner, SimClock
from executor.tasks import Settings
from perception.specs import node_pose_for_pallet
from roadmap import NodeType, load_map, map_vehicle_file
from sim.scenario import Scenario, SimError, load_scenario
from sim.simulator import Simulator

MISSIONS = Path(__file__).resolve().parents[1] / "missions"


@dataclass
class SimRun:
    """A finished simulated run."""

    success: bool
    runner: Runner
    sim: Simulator
    summary: dict
    report: Path | None


def default_scenario(mission: Mission) -> Scenario:
    """The default simulated warehouse for a mission: aligned empty pallets at its pickup nodes."""
    roadmap = load_map(mission.map_path)
    chargers = [n.id for n in roadmap.nodes() if n.type is NodeType.CHARGING]
    if not chargers:
        raise SimError(f"{mission.map_path}: no charging node to start the default warehouse from")
    pickups = [t.node for t in mission.tasks if t.type == "pickup"]
    sc = Scenario.model_validate(
        {
            "map": str(mission.map_path.resolve()),
            "forks": str((MISSIONS / "forks.yaml").resolve()),
            "start": chargers[0],
            "pallets": [{"node": n} for n in pickups],
        }
    )
    sc.folder = MISSIONS
    return sc


def run_simulated(
    mission_path: str | Path,
    scenario_path: str | Path | None = None,
    seed: int | None = None,
    report_dir: str | Path | None = None,
    adapt: bool = True,
    settings: Settings | None = None,
    progress: TextIO | None = None,
    scenario: Scenario | None = None,
    on_start: Callable[[Runner], None] | None = None,
) -> SimRun:
    """Validate and run a mission in the simulator; write the report when `report_dir` is given.

    `on_start(runner)` is called once the runner exists and before it runs (e.g. to pause, resume or
    cancel it from a signal handler).
    """
    mission = load_mission(mission_path)
    if scenario is None:
        scenario = load_scenario(scenario_path) if scenario_path else default_scenario(mission)
    sim = Simulator(scenario, seed=seed)
    roadmap = load_map(mission.map_path)
    vehicle_file = map_vehicle_file(mission.map_path)
    vehicle = load_vehicle(vehicle_file) if vehicle_file else sim.vehicle
    validate_mission(mission, roadmap, vehicle, scenario.start, str(mission_path))

    settings = settings or Settings()
    settings.adapt = adapt
    perception = LocalPerception(sim.forks, sim.pallet_type) if adapt else None
    clock = SimClock(sim.step)
    with contextlib.ExitStack() as stack:
        events = None
        if report_dir is not None:
            folder = Path(report_dir)
            folder.mkdir(parents=True, exist_ok=True)
            events = stack.enter_context((folder / "events.jsonl").open("w"))
        runner = Runner(
            mission,
            roadmap,
            sim,
            perception,
            sim.grab,
            clock,
            vehicle,
            sim.forks,
            scenario.start,
            settings=settings,
            # Simulated time waits for each solve: no wall-clock deadline, so the machine's load cannot
            # change a seeded run. The solve times are in the report (`solve_ms`).
            follower=MpcFollower(vehicle, MpcConfig(solve_deadline_s=None)),
            events=events,
            progress=progress,
        )
        if on_start is not None:
            on_start(runner)
        success = runner.run()
    truth = [node_pose_for_pallet(p.T_world_pallet) for p in sim.pallets]
    report = None
    if report_dir is not None:
        report = write_report(
            Path(report_dir),
            mission.name,
            success,
            runner.results,
            roadmap,
            runner.trajectory,
            runner.ctx.planned_paths,
            truth_pallets=[(p.T_world_pallet).to_se2() for p in sim.pallets],
            extra={
                "seed": sim.seed,
                "adapt": adapt,
                "simulated_s": round(clock.now(), 2),
                "solve_ms": _solve_ms(runner.ctx.follower.log.solve_s),
                "collisions": sim.collisions,
                "pallets_true": [
                    {
                        "node": p.node,
                        "x_m": round(t.x, 4),
                        "y_m": round(t.y, 4),
                        "yaw_deg": round(math.degrees(t.yaw), 3),
                        "carried": p.carried,
                    }
                    for p, t in zip(sim.pallets, truth, strict=True)
                ],
            },
        )
    return SimRun(success, runner, sim, summary(success, runner.results), report)


def _solve_ms(solve_s: list[float]) -> dict[str, float | None]:
    """Median, p99 and max controller solve time (ms, wall clock) of a run."""
    if not solve_s:
        return {"median": None, "p99": None, "max": None}
    ms = np.asarray(solve_s) * 1e3
    return {
        "median": round(float(np.median(ms)), 2),
        "p99": round(float(np.percentile(ms, 99)), 2),
        "max": round(float(ms.max()), 2),
    }
