"""Fault injection (sim.faults): scenario entries, each fault kind, state triggers, and a real SIGKILL."""

from __future__ import annotations

import math
import os
import signal
import subprocess
import sys
import textwrap
import time
from pathlib import Path
from typing import Any

import pytest

from palletpilot.executor.ports import VehiclePort
from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.errors import PerceptionError
from palletpilot.sim import faults
from palletpilot.sim.faults import CameraError, FaultInjector
from palletpilot.sim.scenario import Scenario, SimError, load_scenario
from palletpilot.sim.simulator import CONTROL_DT, Simulator

MISSIONS = bundled_path("missions")

EXAMPLE_FAULTS = """\
faults:
  - {kind: camera_drop, at_s: 30.0, duration_s: 2.0}
  - {kind: camera_freeze, state: calibrate, after_s: 0.0, duration_s: 3.0}
  - {kind: perception_exception, state: estimate_pallet, count: 1}
  - {kind: perception_slow, at_s: 12.0, delay_s: 2.0, count: 1}
  - {kind: localization_jump, at_s: 40.0, dx: 0.5, dy: 0.0, dyaw_deg: 0.0}
  - {kind: solver_failure, at_s: 20.0, duration_s: 1.0}
  - {kind: vehicle_ignores_commands, at_s: 25.0, duration_s: 1.0}
  - {kind: kill, state: lift, after_s: 0.5, task: 1}
"""


def make_sim(faults: list[dict[str, Any]], start: str = "floor_b2_pre") -> tuple[Simulator, FaultInjector]:
    sc = Scenario.model_validate(
        {
            "map": "warehouse.yaml",
            "start": start,
            "camera": {"noise": {"depth_noise": False, "label_noise": False, "invalid_rate": 0.0}},
            "pallets": [{"node": "floor_b2"}],
            "faults": faults,
        }
    )
    sc.folder = MISSIONS
    sim = Simulator(sc)
    # Open-loop drives towards the pallet at floor_b2: the scanners would cap and stop them (not under test).
    sim.scanner.params = sim.vehicle.model_copy(update={"safety_scanner": None})
    return sim, FaultInjector(sc.faults, sim)


def tick(sim: Simulator, inj: FaultInjector, n: int = 1) -> None:
    """Advance n control ticks: step the simulator, then poll the injector at the new time."""
    for _ in range(n):
        sim.step(CONTROL_DT)
        inj.poll(sim.time)


def write_scenario(tmp_path: Path, faults_yaml: str) -> Path:
    path = tmp_path / "scenario.yaml"
    path.write_text(f"map: {MISSIONS / 'warehouse.yaml'}\nstart: charger\n{faults_yaml}")
    return path


# -- scenario files ----------------------------------------------------------------------------------
def test_existing_scenarios_load_without_faults() -> None:
    files = sorted(MISSIONS.glob("scenario_*.yaml"))
    assert files
    for path in files:
        assert load_scenario(path).faults == []


def test_example_fault_entries_load(tmp_path: Path) -> None:
    sc = load_scenario(write_scenario(tmp_path, EXAMPLE_FAULTS))
    assert [f.kind for f in sc.faults] == [
        "camera_drop",
        "camera_freeze",
        "perception_exception",
        "perception_slow",
        "localization_jump",
        "solver_failure",
        "vehicle_ignores_commands",
        "kill",
    ]
    jump = sc.faults[4]
    assert jump.kind == "localization_jump" and jump.duration_s is None  # until the end
    assert sc.faults[7].state == "lift" and sc.faults[7].after_s == 0.5 and sc.faults[7].task == 1
    # A journal stores the scenario as dumped JSON, defaults included; it must load back the same.
    again = Scenario.model_validate(sc.model_dump(mode="json"))
    assert again.faults == sc.faults


@pytest.mark.parametrize(
    ("entry", "field", "problem"),
    [
        ("{kind: camera_drop, at_s: 1.0}", "camera_drop.duration_s", "Field required"),
        ("{kind: camera_drop, at_s: .nan, duration_s: 1}", "camera_drop.at_s", "finite"),
        ("{kind: camera_freeze, at_s: -1, duration_s: 1}", "camera_freeze.at_s", "greater than or equal to 0"),
        ("{kind: solver_failure, at_s: 1, duration_s: .inf}", "solver_failure.duration_s", "finite"),
        ("{kind: camera_drop, at_s: 1, state: lift, duration_s: 1}", "camera_drop", "at_s or state (both given)"),
        ("{kind: kill}", "kill", "at_s or state (neither given)"),
        ("{kind: kill, at_s: 2, task: 0}", "kill", "task: only with a state trigger"),
        ("{kind: kill, state: lift, after_s: .inf}", "kill.after_s", "finite"),
        ("{kind: kill, state: lift, task: -1}", "kill.task", "greater than or equal to 0"),
        ("{kind: perception_slow, at_s: 1, delay_s: 0}", "perception_slow.delay_s", "greater than 0"),
        ("{kind: perception_exception, at_s: 1, count: 0}", "perception_exception.count", "greater than or equal"),
        ("{kind: localization_jump, at_s: 1, dx: .inf}", "localization_jump.dx", "finite"),
        ("{kind: localization_jump, at_s: 1, duration_s: 0}", "localization_jump.duration_s", "greater than 0"),
        (
            "{kind: vehicle_ignores_commands, at_s: 1, duration_s: 1, speed: 2}",
            "vehicle_ignores_commands.speed",
            "Extra",
        ),
        ("{kind: meteor, at_s: 1}", "faults[0]", "'meteor'"),
    ],
)
def test_bad_fault_entries_are_refused_naming_the_field(tmp_path: Path, entry: str, field: str, problem: str) -> None:
    path = write_scenario(tmp_path, f"faults:\n  - {entry}\n")
    with pytest.raises(SimError) as info:
        load_scenario(path)
    problems = info.value.problems
    assert len(problems) == 1, problems
    line = problems[0]
    assert line.startswith(f"{path}: faults[0]") and field in line and problem in line, line


# -- each kind ------------------------------------------------------------------------------------------
def test_vehicle_is_a_vehicle_port_delegating_the_rest() -> None:
    sim, inj = make_sim([{"kind": "vehicle_ignores_commands", "at_s": 0.0, "duration_s": 1.0}])
    vehicle: Any = inj.vehicle
    # The port as the simulator offers it: members the simulator lacks are missing from the wrapper too.
    assert isinstance(vehicle, VehiclePort) == isinstance(sim, VehiclePort)
    for name in ("localization_stamp", "battery_level", "emergency_stop", "snapshot"):
        assert hasattr(vehicle, name) == hasattr(sim, name), name
    assert vehicle.true_pose == sim.true_pose and vehicle.collisions is sim.collisions
    vars(sim)["tyre_pressure_bar"] = 8.5  # a simulator attribute added later is delegated
    assert vehicle.tyre_pressure_bar == 8.5
    assert vehicle.localization() == sim.localization() and vehicle.proximity_ranges() == sim.proximity_ranges()
    assert (vehicle.speed, vehicle.steering, vehicle.fork_height) == (0.0, 0.0, 0.0)
    assert vehicle.load_detected() is False and vehicle.faults() == []
    stops: list[str] = []
    vars(sim)["emergency_stop"] = lambda: stops.append("e-stop")
    inj.poll(0.0)
    vehicle.stop()  # ignored ...
    vehicle.emergency_stop()  # ... but the safety stop is not a drive command: it always gets through
    assert stops == ["e-stop"] and inj.injected[0]["kind"] == "vehicle_ignores_commands"


def test_camera_drop_raises_for_its_duration() -> None:
    sim, inj = make_sim([{"kind": "camera_drop", "at_s": 0.1, "duration_s": 0.2}])
    inj.poll(0.0)
    inj.grab()
    tick(sim, inj, 2)  # t = 0.1
    with pytest.raises(CameraError, match=r"no frame \(injected\)") as info:
        inj.grab()
    assert isinstance(info.value, PerceptionError)
    tick(sim, inj, 3)  # t = 0.25: still dropping
    with pytest.raises(CameraError):
        inj.grab()
    tick(sim, inj, 1)  # t = 0.3: over
    assert inj.grab().depth.size > 0
    assert [(r["event"], round(r["t_s"], 6)) for r in inj.injected] == [("start", 0.1), ("end", 0.3)]
    assert inj.injected[1]["hits"] == 2 and inj.pending() == []


def test_camera_freeze_repeats_the_last_frame_from_a_state_trigger() -> None:
    sim, inj = make_sim([{"kind": "camera_freeze", "state": "calibrate", "duration_s": 0.5}])
    first = inj.grab()
    inj.observe("state_start", {"task": 0, "state": "drive_to_pre_pallet"}, 0.0)
    assert inj.grab() is not first
    inj.observe("state_start", {"task": 0, "state": "calibrate"}, sim.time)
    frozen = inj.grab()
    sim.set_fork_height(0.3)  # the carriage camera moves: a live frame would differ
    tick(sim, inj, 5)
    again = inj.grab()
    assert again is frozen and again.fork_height == frozen.fork_height == 0.0
    tick(sim, inj, 5)  # 0.5 s after the state started: thawed
    live = inj.grab()
    assert live is not frozen and live.fork_height > 0.0


class FakePerception:
    """A stand-in `PerceptionService` that counts its calls."""

    def __init__(self) -> None:
        self.calls = 0
        self.model_name = "fake"

    def calibrate(self, frames: Any) -> str:
        self.calls += 1
        return "calibration"

    def estimate_pallet(
        self,
        frame: Any,
        calibration: Any,
        T_world_forklift: SE2,
        expected: Any = None,
        pallet: Any = None,
        support_height_m: float = 0.0,
    ) -> str:
        self.calls += 1
        return "estimate"

    @property
    def last_good(self) -> str:
        return "last good"


def test_perception_exception_raises_a_bug_for_count_calls() -> None:
    _, inj = make_sim([{"kind": "perception_exception", "state": "estimate_pallet", "count": 2}])
    inner = FakePerception()
    perception = inj.perception(inner)
    assert perception.calibrate([]) == "calibration"
    inj.observe("state_start", {"task": 0, "state": "estimate_pallet"}, 3.0)
    for _ in range(2):
        with pytest.raises(RuntimeError, match=r"perception crashed \(injected\)") as info:
            perception.estimate_pallet(None, None, SE2())
        assert not isinstance(info.value, PerceptionError)
    assert perception.estimate_pallet(None, None, SE2()) == "estimate"
    assert inner.calls == 2 and perception.last_good == "last good" and perception.model_name == "fake"
    assert [r["event"] for r in inj.injected] == ["start", "end"]


def test_perception_slow_reports_and_sleeps_the_delay() -> None:
    sim, inj = make_sim([{"kind": "perception_slow", "at_s": 0.05, "delay_s": 2.0, "count": 2}])
    perception = inj.perception(FakePerception())
    perception.calibrate([])
    assert perception.simulated_delay_s == 0.0
    tick(sim, inj)
    assert perception.calibrate([]) == "calibration" and perception.simulated_delay_s == 2.0
    perception.estimate_pallet(None, None, SE2())
    assert perception.simulated_delay_s == 2.0
    perception.estimate_pallet(None, None, SE2())
    assert perception.simulated_delay_s == 0.0

    sim, inj = make_sim([{"kind": "perception_slow", "at_s": 0.0, "delay_s": 0.2}])
    inj.realtime = True
    perception = inj.perception(FakePerception())
    inj.poll(0.0)
    began = time.monotonic()
    perception.calibrate([])
    assert time.monotonic() - began >= 0.2 and perception.simulated_delay_s == 0.2


def test_localization_jump_is_in_the_forklift_frame() -> None:
    sim, inj = make_sim(
        [
            {"kind": "localization_jump", "at_s": 1.0, "dx": 0.5, "dy": 0.2, "dyaw_deg": 10.0},
            {"kind": "localization_jump", "at_s": 2.0, "dy": -1.0, "duration_s": 0.5},
        ]
    )
    vehicle = inj.vehicle
    vehicle.drive(0.5, 0.3)  # turn, so the forklift frame differs from the world frame
    tick(sim, inj, 19)
    assert vehicle.localization() == sim.localization()
    tick(sim, inj)  # t = 1.0
    truth, jumped = sim.localization(), vehicle.localization()
    c, s = math.cos(truth.yaw), math.sin(truth.yaw)
    assert abs(truth.yaw) > 0.05
    assert jumped.x == pytest.approx(truth.x + 0.5 * c - 0.2 * s)
    assert jumped.y == pytest.approx(truth.y + 0.5 * s + 0.2 * c)
    assert jumped.yaw == pytest.approx(truth.yaw + math.radians(10.0))
    tick(sim, inj, 20)  # t = 2.0: both jumps, composed in order
    truth = sim.localization()
    expected = truth @ SE2(0.5, 0.2, math.radians(10.0)) @ SE2(0.0, -1.0, 0.0)
    assert vehicle.localization().distance_to(expected) == pytest.approx(0.0, abs=1e-9)
    tick(sim, inj, 10)  # t = 2.5: the second jump ended, the first stays to the end
    truth = sim.localization()
    assert vehicle.localization() == truth @ SE2(0.5, 0.2, math.radians(10.0))
    assert [(r["index"], r["event"]) for r in inj.injected] == [(0, "start"), (1, "start"), (1, "end")]


def test_solver_failure_reports_while_active() -> None:
    sim, inj = make_sim([{"kind": "solver_failure", "at_s": 0.1, "duration_s": 0.1}])
    inj.poll(0.0)
    assert inj.step_failure(0.0) is None
    tick(sim, inj, 2)
    message = inj.step_failure(sim.time)
    assert message is not None and "solver failure (injected" in message
    tick(sim, inj, 2)
    assert inj.step_failure(sim.time) is None


def test_vehicle_ignores_commands_keeps_the_last_ones() -> None:
    sim, inj = make_sim([{"kind": "vehicle_ignores_commands", "at_s": 1.0, "duration_s": 1.0}])
    vehicle = inj.vehicle
    vehicle.drive(0.5, 0.0)
    tick(sim, inj, 20)  # t = 1.0: ignoring
    moving = sim.speed
    assert moving > 0.4
    vehicle.stop()
    vehicle.set_fork_height(0.5)
    vehicle.drive(0.0, 0.3)
    tick(sim, inj, 10)
    assert sim.speed >= moving - 1e-9 and sim.fork_height == 0.0 and sim.steering == 0.0
    tick(sim, inj, 10)  # t = 2.0: commands reach the vehicle again
    vehicle.stop()
    tick(sim, inj, 40)
    assert abs(sim.speed) < 1e-3
    assert inj.injected[-1]["event"] == "end" and inj.injected[-1]["hits"] == 3


def test_state_trigger_picks_the_task_and_waits_after_s() -> None:
    _, inj = make_sim(
        [
            {"kind": "solver_failure", "state": "lift", "task": 1, "after_s": 0.5, "duration_s": 1.0},
            {"kind": "camera_drop", "state": "lift", "duration_s": 0.2},
        ]
    )
    inj.observe("state_start", {"task": 0, "state": "lift"}, 10.0)  # the first lift: only the task-free drop
    assert [r["kind"] for r in inj.injected] == ["camera_drop"]
    inj.poll(10.25)
    inj.observe("state_start", {"task": 1, "state": "lift"}, 20.0)  # fires once: no second drop
    inj.poll(20.45)
    assert inj.step_failure(20.45) is None
    inj.poll(20.5)
    assert inj.step_failure(20.5) is not None
    inj.poll(21.5)
    assert inj.step_failure(21.5) is None
    assert [(r["kind"], r["event"], r["t_s"]) for r in inj.injected] == [
        ("camera_drop", "start", 10.0),
        ("camera_drop", "end", 10.25),
        ("solver_failure", "start", 20.5),
        ("solver_failure", "end", 21.5),
    ]
    first = inj.injected[2]
    assert first["state"] == "lift" and first["task"] == 1 and first["after_s"] == 0.5


def test_kill_sends_sigkill_from_poll() -> None:
    child = textwrap.dedent(
        """
        from palletpilot.geometry.fileio import bundled_path
        from palletpilot.sim.faults import FaultInjector
        from palletpilot.sim.scenario import Scenario
        from palletpilot.sim.simulator import Simulator

        faults = [{"kind": "kill", "at_s": 0.2}]
        sc = Scenario.model_validate({"map": "warehouse.yaml", "start": "charger", "faults": faults})
        sc.folder = bundled_path("missions")
        sim = Simulator(sc)
        inj = FaultInjector(sc.faults, sim)
        for _ in range(10):
            sim.step(0.05)
            inj.poll(sim.time)
            print(f"polled {sim.time:.2f}", flush=True)
        print("survived", flush=True)
        """
    )
    result = subprocess.run([sys.executable, "-c", child], capture_output=True, text=True, timeout=60)
    assert result.returncode == -9, (result.returncode, result.stdout, result.stderr[-2000:])
    assert result.stdout.splitlines() == ["polled 0.05", "polled 0.10", "polled 0.15"]


def test_state_triggered_kill_waits_for_poll(monkeypatch: pytest.MonkeyPatch) -> None:
    sent: list[tuple[int, int]] = []
    monkeypatch.setattr(faults.os, "kill", lambda pid, sig: sent.append((pid, sig)))
    _, inj = make_sim([{"kind": "kill", "state": "lift", "after_s": 0.5}])
    inj.observe("state_start", {"task": 0, "state": "lift"}, 1.0)
    inj.poll(1.45)
    inj.observe("state_end", {"task": 0, "state": "lift"}, 1.5)
    assert sent == []
    inj.poll(1.5)
    assert sent == [(os.getpid(), signal.SIGKILL)]
    assert inj.injected == [{"kind": "kill", "t_s": 1.5, "event": "start", "index": 0, "state": "lift", "after_s": 0.5}]


def test_skip_until_resumes_without_refiring() -> None:
    sim, inj = make_sim(
        [
            {"kind": "camera_drop", "at_s": 1.0, "duration_s": 0.5},
            {"kind": "solver_failure", "at_s": 2.0, "duration_s": 2.0},
            {"kind": "localization_jump", "at_s": 2.5, "dx": 1.0},
            {"kind": "vehicle_ignores_commands", "at_s": 5.0, "duration_s": 1.0},
            {"kind": "camera_freeze", "state": "calibrate", "duration_s": 1.0},
        ]
    )
    inj.skip_until(3.0)
    inj.poll(3.0)
    inj.grab()  # the drop is over
    assert inj.step_failure(3.0) is not None  # still inside its window
    assert inj.vehicle.localization() == sim.localization() @ SE2(1.0, 0.0, 0.0)
    inj.poll(4.0)
    assert inj.step_failure(4.0) is None
    assert [(r["kind"], r["event"]) for r in inj.injected] == [("solver_failure", "end")]
    assert [f.kind for f in inj.pending()] == ["vehicle_ignores_commands", "camera_freeze"]
