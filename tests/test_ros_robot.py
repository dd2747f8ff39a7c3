"""On-robot execution end to end over ROS 2, without ROS: `palletpilot sim serve --ros` plays the truck in one
process, `palletpilot robot` drives it from another, over Cyclone DDS bound to the loopback interface in a
random domain per test (`executor.ros.dds.loopback_env`), so parallel runs never meet.

1. A short pickup and delivery succeeds (perception in the robot process, on the stand-in's camera topics).
2. The robot process is killed with SIGKILL while the truck drives at speed: the stand-in's command timeout
   (0.2 s) brakes it. From the stand-in's published odometry: the brake starts within 0.3 s of the kill and
   the truck stands within 0.3 s plus the braking time at the emergency deceleration.
"""

from __future__ import annotations

import contextlib
import json
import os
import signal
import subprocess
import sys
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import pytest

pytest.importorskip("cyclonedds")

from palletpilot.bench.robot import start_stand_in
from palletpilot.control.vehicle import load_vehicle
from palletpilot.executor.adapters.ros import messages as m
from palletpilot.executor.adapters.ros.dds import DdsTransport, loopback_env
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.calibration_io import Calibration, save_calibration
from palletpilot.sim.scenario import load_scenario
from palletpilot.sim.simulator import Simulator

ROBOT = bundled_path("missions", "robot.yaml")
MAP = bundled_path("missions", "warehouse.yaml")
FORKS = bundled_path("missions", "forks.yaml")
KILL_BRAKE_LIMIT_S = 0.3


def _scenario(folder: Path, start: str, pallets: str = "") -> Path:
    path = folder / f"scenario_{start}.yaml"
    path.write_text(
        f"map: {MAP}\nforks: {FORKS}\nseed: 7\nstart: {start}\n"
        "camera:\n  mount: {x: -0.10, y: 0.0, z: 0.45, tilt_deg: 22, pan_deg: 0.0, roll_deg: 0.0}\n"
        "noise: {localization_xy_sigma: 0.002, localization_yaw_sigma_deg: 0.05}\n"
        f"pallets: [{pallets}]\n"
    )
    return path


def _mission(folder: Path, name: str, tasks: str) -> Path:
    path = folder / f"{name}.yaml"
    path.write_text(f"name: {name}\nmap: {MAP}\ntasks:\n{tasks}")
    return path


def _palletpilot(env: dict[str, str], *args: str, log: Path | None = None) -> subprocess.Popen[str]:
    """`palletpilot ARGS` in a subprocess; stderr to `log` when given (else a pipe)."""
    cmd = [sys.executable, "-m", "palletpilot.cli", *args]
    err = log.open("w") if log is not None else subprocess.PIPE
    return subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=err, text=True)


@pytest.fixture()
def dds_env(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> dict[str, str]:
    """Loopback-only DDS in a random domain, for this process and its children."""
    env = loopback_env(tmp_path)
    for key, value in env.items():
        monkeypatch.setenv(key, value)
    return {**os.environ, **env, "PYTHONUNBUFFERED": "1"}


@contextlib.contextmanager
def stand_in(env: dict[str, str], scenario: Path, log: Path) -> Iterator[subprocess.Popen[str]]:
    """`palletpilot sim serve SCENARIO --ros` until the block ends; then SIGINT, and it must exit 0."""
    proc = start_stand_in(env, scenario, log, ROBOT)
    try:
        yield proc
    finally:
        if proc.poll() is None:
            proc.send_signal(signal.SIGINT)
        try:
            proc.wait(timeout=20)
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    assert proc.returncode == 0, log.read_text()[-2000:]


def test_pickup_and_delivery_over_ros2(tmp_path: Path, dds_env: dict[str, str]) -> None:
    scenario = _scenario(tmp_path, "floor_b2_pre", "{node: floor_b2, loaded: true}")
    mission = _mission(
        tmp_path, "short_pickup_delivery", "  - {type: pickup, node: floor_b2}\n  - {type: delivery, node: floor_b2}\n"
    )
    calibration = tmp_path / "calibration.json"  # the mount as installed (`palletpilot calibrate --out`)
    save_calibration(calibration, Calibration(Simulator(load_scenario(scenario)).T_forklift_camera_true, "model"))
    report, journal = tmp_path / "report", tmp_path / "run.db"
    with stand_in(dds_env, scenario, tmp_path / "serve.log"):
        robot = _palletpilot(
            dds_env,
            "robot", str(mission), "--robot", str(ROBOT), "--calibration", str(calibration),
            "--report", str(report), "--journal", str(journal), "--wait", "20", "--json",
        )  # fmt: skip
        try:
            out, err = robot.communicate(timeout=170)
        except subprocess.TimeoutExpired:
            robot.kill()
            out, err = robot.communicate()
        assert robot.returncode == 0, err[-3000:]
        result = json.loads(out)
        assert result["success"] is True
        assert [(t["type"], t["result"]) for t in result["tasks"]] == [
            ("pickup", "succeeded"),
            ("delivery", "succeeded"),
        ]
        doc = json.loads((report / "report.json").read_text())
        assert doc["robot"] == "truck" and doc["start"] == "floor_b2_pre"
        assert doc["clock"]["clock"] == "wall" and doc["clock"]["ticks"] > 100
        assert doc["drive_commands_sent"] >= doc["clock"]["ticks"]  # one per tick at least: the truck never timed out
        assert journal.is_file()
        # the run's recording, from the truck's own readings: replay gives the same tasks and the same clock
        from palletpilot.executor.adapters.mcap.replay import replay

        replayed = json.loads(replay(report / "run.mcap", tmp_path / "replayed").read_text())
        assert [t["result"] for t in replayed["tasks"]] == ["succeeded", "succeeded"]
        assert replayed["robot"] == "truck" and replayed["clock"]["ticks"] == doc["clock"]["ticks"]
    log = (tmp_path / "serve.log").read_text().splitlines()
    stats = json.loads(next(line for line in reversed(log) if line.startswith('{"stand_in"')))["stand_in"]
    assert stats["frames"] > 0 and stats["camera_error"] is None  # the camera child rendered and published


def test_robot_killed_mid_drive_truck_brakes(tmp_path: Path, dds_env: dict[str, str]) -> None:
    scenario = _scenario(tmp_path, "b1")
    mission = _mission(tmp_path, "aisle_b", "  - {type: move, node: b_top}\n")
    decel = load_vehicle(bundled_path("missions", "forklift.yaml")).emergency_decel
    odometry: list[tuple[float, float]] = []  # (header stamp s since the epoch, speed m/s)
    lock = threading.Lock()

    def on_odom(msg: m.Odometry, _received_s: float) -> None:
        with lock:
            odometry.append((m.seconds(msg.header.stamp), msg.twist.twist.linear.x))

    with DdsTransport() as bus:
        bus.subscribe("/odom", m.Odometry, callback=on_odom)
        with stand_in(dds_env, scenario, tmp_path / "serve.log"):
            journal = tmp_path / "run.db"
            robot = _palletpilot(
                dds_env,
                "robot",
                str(mission),
                "--robot",
                str(ROBOT),
                "--wait",
                "20",
                "--quiet",
                "--journal",
                str(journal),
            )
            t_end = time.monotonic() + 90.0
            while time.monotonic() < t_end and robot.poll() is None:
                with lock:
                    fast = bool(odometry) and odometry[-1][1] > 0.6
                if fast:
                    break
                time.sleep(0.02)
            assert robot.poll() is None, f"robot ended before driving fast: {robot.communicate()[1][-3000:]}"
            assert fast, "the truck never reached 0.6 m/s"
            time.sleep(0.5)  # steady speed
            robot.send_signal(signal.SIGKILL)
            t_kill = time.time()
            robot.communicate(timeout=20)
            assert robot.returncode == -signal.SIGKILL
            time.sleep(1.0 + 1.5 / decel)
            with lock:
                samples = list(odometry)
    # started again on the killed run's journal: refused in one line before it connects to anything
    again = _palletpilot(dds_env, "robot", str(mission), "--robot", str(ROBOT), "--journal", str(journal))
    _, err = again.communicate(timeout=120)
    assert again.returncode == 2 and "holds an unfinished run" in err and "Traceback" not in err, err[-2000:]
    assert len(err.strip().splitlines()) == 1
    before = [v for t, v in samples if t <= t_kill]
    after = [(t, v) for t, v in samples if t > t_kill]
    v_kill = before[-1]
    assert v_kill > 0.6
    braking = next(t for t, v in after if v < v_kill - 0.01)
    standing = next(t for t, v in after if abs(v) < 1e-3)
    print(
        f"\nSIGKILL at {v_kill:.2f} m/s: brake after {braking - t_kill:.3f} s, "
        f"standing after {standing - t_kill:.3f} s (braking time {v_kill / decel:.3f} s)"
    )
    assert braking - t_kill <= KILL_BRAKE_LIMIT_S
    assert standing - t_kill <= KILL_BRAKE_LIMIT_S + v_kill / decel + 0.06  # + one odometry period


def test_robot_refuses_a_silent_truck(tmp_path: Path, dds_env: dict[str, str]) -> None:
    """Nobody publishes: one line per silent topic, no tf, no camera; exit 2 before anything moves."""
    mission = _mission(tmp_path, "aisle_b", "  - {type: move, node: b_top}\n")
    robot = _palletpilot(dds_env, "robot", str(mission), "--robot", str(ROBOT), "--wait", "0.5")
    out, err = robot.communicate(timeout=120)
    assert robot.returncode == 2, err
    lines = err.strip().splitlines()
    assert any("localization.tf: /tf: no transform map -> base_link" in line for line in lines)
    assert any("topics.odometry: /odom: never heard (limit 0.3 s)" in line for line in lines)
    assert any("camera: /camera/camera/color/image_raw: never heard" in line for line in lines)
    assert all(line.startswith(f"{ROBOT}: ") for line in lines) and "Traceback" not in err
    assert not out
