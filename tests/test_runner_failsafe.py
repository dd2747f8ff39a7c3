"""The runner is fail-safe: any exception stops the vehicle, ends the task with a reason and the run reports.

A fake vehicle records every command, so the tests see exactly what the truck was told.
"""

from __future__ import annotations

import json
import math
from pathlib import Path
from typing import Any

import pytest
import yaml

from palletpilot.control.follower import DriveCommand, FollowerStatus
from palletpilot.control.safety import SafetyState
from palletpilot.control.vehicle import load_vehicle
from palletpilot.executor.apps.app import run_simulated
from palletpilot.executor.core.clock import SimClock, WallClock
from palletpilot.executor.core.controls import Controls
from palletpilot.executor.core.mission import load_mission
from palletpilot.executor.core.runner import Runner
from palletpilot.executor.core.watchdog import WatchdogLimits
from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import bundled_path
from palletpilot.roadmap import load_map
from palletpilot.sim.scenario import Scenario

MISSIONS = bundled_path("missions")
VEHICLE = load_vehicle(MISSIONS / "forklift.yaml")


class FakeVehicle:
    """A `VehiclePort` on a straight line: speed follows the command at the truck's limits; every command logged."""

    def __init__(self, pose: SE2, clock_now: Any = None) -> None:
        self.pose = pose
        self.v = 0.0
        self.cmd = 0.0
        self.fork = 0.0
        self.fork_cmd = 0.0
        self.t = 0.0
        self.emergency = False
        self.commands: list[tuple[float, str, float]] = []  # t, kind, value
        self.frozen_localization_at: float | None = None
        self.ignore_commands = False

    # commands
    def drive(self, speed: float, steering: float) -> None:
        self.commands.append((self.t, "drive", speed))
        if not self.ignore_commands:
            self.cmd = speed

    def stop(self) -> None:
        self.commands.append((self.t, "stop", 0.0))
        if not self.ignore_commands:
            self.cmd = 0.0

    def emergency_stop(self) -> None:
        self.commands.append((self.t, "emergency_stop", 0.0))
        self.emergency, self.cmd = True, 0.0

    def set_fork_height(self, height: float) -> None:
        self.commands.append((self.t, "fork", height))
        self.fork_cmd = height

    # readings
    def localization(self) -> SE2:
        return self.pose

    def localization_stamp(self) -> float:
        return self.t if self.frozen_localization_at is None else self.frozen_localization_at

    @property
    def speed(self) -> float:
        return self.v

    @property
    def steering(self) -> float:
        return 0.0

    @property
    def fork_height(self) -> float:
        return self.fork

    def proximity_ranges(self) -> tuple[float, float]:
        return math.inf, math.inf

    def load_detected(self) -> bool:
        return False

    def faults(self) -> list[str]:
        return []

    def safety_state(self) -> SafetyState:
        return SafetyState()

    def set_safety_field_set(self, name: str, direction: str = "forward") -> None:
        self.field_set = name

    def step(self, dt: float) -> None:
        self.t += dt
        decel = VEHICLE.emergency_decel if self.emergency else VEHICLE.max_decel
        target = 0.0 if self.emergency else self.cmd
        dv = target - self.v
        limit = (decel if abs(target) < abs(self.v) else VEHICLE.max_accel) * dt
        self.v += max(-limit, min(limit, dv))
        self.pose = self.pose @ SE2(self.v * dt, 0.0, 0.0)
        self.fork += max(-0.3 * dt, min(0.2 * dt, self.fork_cmd - self.fork))


class CrashingFollower:
    """Drives at 0.3 m/s, then raises a bug (not a ControlError) after `after` ticks."""

    def __init__(self, after: int = 40) -> None:
        self.after, self.n = after, 0
        self.log = type("Log", (), {"solve_s": []})()

    def start(self, path: Any) -> None:
        self.n = 0

    def update(self, t: float, pose: SE2, speed: float, steering: float) -> DriveCommand:
        self.n += 1
        if self.n > self.after:
            raise ZeroDivisionError("bug in the follower")
        return DriveCommand(0.3, 0.0, FollowerStatus.RUNNING)

    def stop(self) -> None:
        pass


def _runner(tmp_path: Path, vehicle: FakeVehicle, follower: Any, step: Any = None, **kw: Any) -> Runner:
    path = tmp_path / "m.yaml"
    path.write_text(
        yaml.safe_dump(
            {"name": "t", "map": str(MISSIONS / "warehouse.yaml"), "tasks": [{"type": "move", "node": "a_top"}]}
        )
    )
    mission = load_mission(path)
    roadmap = load_map(mission.map_path)
    start = "charger"
    vehicle.pose = roadmap.node(start).pose
    clock = SimClock(step or vehicle.step)

    def grab() -> Any:
        raise AssertionError("no camera in these tests")

    return Runner(mission, roadmap, vehicle, None, grab, clock, VEHICLE, None, start, follower=follower, **kw)  # type: ignore[arg-type]


def test_an_unexpected_exception_stops_the_vehicle_and_ends_the_task(tmp_path: Path) -> None:
    vehicle = FakeVehicle(SE2(0, 0, 0))
    runner = _runner(tmp_path, vehicle, CrashingFollower(after=40))
    assert runner.run() is False  # never raises
    result = runner.results[0]
    assert result.result == "failed" and result.reason == "internal_error"
    assert "ZeroDivisionError: bug in the follower" in (result.message or "")
    moving_at_failure = [c for c in vehicle.commands if c[1] == "emergency_stop"]
    assert moving_at_failure, "a moving vehicle gets the safety stop"
    after = [c for c in vehicle.commands if c[0] >= moving_at_failure[0][0]]
    assert all(kind != "drive" or value == 0.0 for _, kind, value in after), after
    assert abs(vehicle.v) < 1e-3
    stop = runner.stops[0]
    assert stop["reason"] == "internal_error" and stop["standstill_s"] is not None
    assert stop["standstill_s"] - stop["t_s"] < 1.0  # 0.3 m/s at 1.5 m/s^2


def test_stale_localization_stops_with_sensor_timeout(tmp_path: Path) -> None:
    vehicle = FakeVehicle(SE2(0, 0, 0))
    follower = CrashingFollower(after=10**6)

    def step(dt: float) -> None:
        vehicle.step(dt)
        if vehicle.t > 2.0 and vehicle.frozen_localization_at is None:
            vehicle.frozen_localization_at = vehicle.t

    limits = WatchdogLimits(localization_max_age_s=0.5)
    runner = _runner(tmp_path, vehicle, follower, step=step, watchdog_limits=limits)
    assert runner.run() is False
    result = runner.results[0]
    assert result.reason == "sensor_timeout" and "localization is stale" in (result.message or "")
    assert abs(vehicle.v) < 1e-3


def test_a_vehicle_that_ignores_its_commands_is_a_vehicle_fault(tmp_path: Path) -> None:
    vehicle = FakeVehicle(SE2(0, 0, 0))

    def step(dt: float) -> None:
        vehicle.step(dt)
        vehicle.ignore_commands = vehicle.t > 1.0
        if vehicle.ignore_commands:
            vehicle.cmd = 0.8  # runs away at 0.8 m/s while commanded 0.3

    runner = _runner(tmp_path, vehicle, CrashingFollower(after=10**6), step=step)
    assert runner.run() is False
    result = runner.results[0]
    assert result.reason == "vehicle_fault" and "does not follow its commands" in (result.message or "")
    assert any(kind == "emergency_stop" for _, kind, _ in vehicle.commands)


def test_a_localization_jump_stops_the_truck_with_a_localization_fault(tmp_path: Path) -> None:
    vehicle = FakeVehicle(SE2(0, 0, 0))
    jumped: list[float] = []
    real_localization = vehicle.localization

    def localization() -> SE2:
        pose = real_localization()
        return pose @ SE2(0.0, 0.5, 0.0) if vehicle.t > 2.0 else pose  # 0.5 m sideways from t = 2 s on

    vehicle.localization = localization  # type: ignore[method-assign]

    def step(dt: float) -> None:
        vehicle.step(dt)
        if vehicle.t > 2.0 and not jumped:
            jumped.append(vehicle.t)

    runner = _runner(tmp_path, vehicle, CrashingFollower(after=10**6), step=step)
    assert runner.run() is False
    result = runner.results[0]
    assert result.reason == "localization_fault" and "jumped 0.50 m" in (result.message or "")
    assert runner.stops[0]["t_s"] - jumped[0] < 0.11  # the next tick
    assert abs(vehicle.v) < 1e-3


def test_cancel_and_pause_through_controls(tmp_path: Path) -> None:
    vehicle = FakeVehicle(SE2(0, 0, 0))
    controls = Controls()

    def step(dt: float) -> None:
        vehicle.step(dt)
        if 0.99 < vehicle.t < 1.01:
            controls.pause()
        if 60.0 < vehicle.t < 60.06:  # a minute paused: no timeout, no "no progress"
            controls.resume()
        if 62.0 < vehicle.t < 62.06:
            controls.cancel("cancelled by SIGINT", 2)

    runner = _runner(tmp_path, vehicle, CrashingFollower(after=10**6), step=step, controls=controls)
    assert runner.run() is False
    result = runner.results[0]
    assert result.reason == "cancelled" and "SIGINT" in (result.message or "")
    paused = [c for c in vehicle.commands if 1.1 < c[0] < 59.9]
    assert paused and all(kind in ("stop", "fork") for _, kind, _ in paused)


def test_wall_clock_counts_ticks_and_overruns() -> None:
    now = [0.0]

    def monotonic() -> float:
        return now[0]

    def sleep(s: float) -> None:
        now[0] += s

    clock = WallClock(0.05, monotonic=monotonic, sleep=sleep)
    for i in range(100):
        if i == 50:
            now[0] += 0.2  # one slow tick
        clock.tick()
    stats = clock.stats()
    assert stats["ticks"] == 100 and stats["overruns"] == 1 and stats["max_overrun_streak"] == 1
    assert stats["jitter_ms"]["p50"] == 0.0 and stats["jitter_ms"]["max"] == pytest.approx(150.0)  # 0.2 s - a tick
    assert clock.now() == pytest.approx(100 * 0.05 + 0.15, abs=1e-9)  # the schedule restarted, no catch-up


def _strict(text: str) -> Any:
    def refuse(name: str) -> None:
        raise ValueError(f"non-standard JSON constant {name}")

    return json.loads(text, parse_constant=refuse)


def test_a_perception_crash_is_an_internal_error_and_reports_are_strict_json(tmp_path: Path) -> None:
    sc = Scenario.model_validate(
        {
            "map": "warehouse.yaml",
            "start": "b1",
            "seed": 4,
            "pallets": [{"node": "floor_b2"}],
            "faults": [{"kind": "perception_exception", "state": "estimate_pallet", "count": 5}],
        }
    )
    sc.folder = MISSIONS
    mission = tmp_path / "m.yaml"
    mission.write_text(
        yaml.safe_dump(
            {"name": "t", "map": str(MISSIONS / "warehouse.yaml"), "tasks": [{"type": "pickup", "node": "floor_b2"}]}
        )
    )
    r = run_simulated(mission, scenario=sc, report_dir=tmp_path / "report")
    assert not r.success
    task = r.runner.results[0]
    assert task.reason == "internal_error" and "perception crashed" in (task.message or ""), task.message
    report = _strict((tmp_path / "report" / "report.json").read_text())
    assert report["tasks"][0]["reason"] == "internal_error"
    assert report["stops"] and report["stops"][0]["standstill_s"] is not None
    for line in (tmp_path / "report" / "events.jsonl").read_text().splitlines():
        _strict(line)


def test_slow_perception_lets_the_state_timeout_fire_while_the_vehicle_stands(tmp_path: Path) -> None:
    sc = Scenario.model_validate(
        {
            "map": "warehouse.yaml",
            "start": "b1",
            "seed": 4,
            "pallets": [{"node": "floor_b2"}],
            "faults": [{"kind": "perception_slow", "state": "calibrate", "delay_s": 60.0, "count": 10}],
        }
    )
    sc.folder = MISSIONS
    mission = tmp_path / "m.yaml"
    mission.write_text(
        yaml.safe_dump(
            {"name": "t", "map": str(MISSIONS / "warehouse.yaml"), "tasks": [{"type": "pickup", "node": "floor_b2"}]}
        )
    )
    r = run_simulated(mission, scenario=sc, report_dir=tmp_path / "report")
    task = r.runner.results[0]
    assert task.reason == "timeout" and "calibrate" in (task.message or "")
    calibrate = next(s for s in task.states if s["state"] == "calibrate")
    assert calibrate["end_s"] - calibrate["start_s"] == pytest.approx(20.0, abs=0.2)
    assert abs(r.sim.speed) < 1e-3
