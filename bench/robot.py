"""`palletpilot bench robot`: on-robot execution over ROS 2 against the stand-in truck, on loopback DDS.

Two processes, as on a truck: `palletpilot sim serve SCENARIO --ros` (the simulator as the truck, on the
wall clock, with the truck controller's 0.2 s command timeout) and `palletpilot robot MISSION` (the
executor) over Cyclone DDS bound to the loopback interface in a domain of its own
(`executor.ros.dds.loopback_env`). The mission: a pickup of a loaded pallet at `floor_b2` (misplaced by
`--misplace-m` sideways and `--misplace-deg`) and its delivery back, from `floor_b2_pre`; the calibration
file is the installed mount. Then the same mission and scenario run in the simulator
(`executor.app.run_simulated`, the same seed) for the outcome to compare.

Figures: `control_tick_jitter_ms` (the robot's control tick period minus its nominal 50 ms: the wall
clock's own statistics), `command_latency_ms` (a drive command's header stamp to the stand-in receiving
it, on the one machine's clock) and `command_latency_split_ms` (the same split at the robot's DDS write,
from the sample's source timestamp: `stamp_to_dds_write` is the robot process's part, `dds_write_to_receipt`
the transport's and the stand-in's), `localization_age_ms` (the age of the localization fix each time the
executor reads it), each with median, p99, max; `ticks`, `success_robot`, `success_sim`,
`same_outcome` (the same task results), and the goals (jitter p99 <= 5 ms, latency p99 <= 10 ms, same
outcome), and under `stand_in` its ticks, commands, camera frames and their render time (ms, in the
stand-in's camera child process, `executor.ros.standin_camera`). The machine's other load shows in the
figures; the whole benchmark takes about 100 s.

Public API: `add_arguments`, `run`, `start_stand_in` (also the ROS 2 integration test's).
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import signal
import subprocess
import sys
import tempfile
import threading
from pathlib import Path
from typing import Any

from palletpilot.executor.apps.cli_args import number, seed

JITTER_GOAL_MS = 5.0
LATENCY_GOAL_MS = 10.0
READY_TIMEOUT_S = 60.0
RUN_TIMEOUT_S = 600.0


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument("--seed", type=seed, default=7, help="the scenario's seed (both runs)")
    parser.add_argument("--misplace-m", type=number(0.0, 0.3, "m"), default=0.1, help="pallet off its node sideways")
    parser.add_argument("--misplace-deg", type=number(0.0, 10.0, "deg"), default=4.0, help="pallet turned")


def _files(folder: Path, args: argparse.Namespace) -> tuple[Path, Path, Path]:
    """The scenario, the mission and the installed calibration, written into `folder`."""
    from palletpilot.geometry.fileio import bundled_path
    from palletpilot.perception.calibration_io import Calibration, save_calibration
    from palletpilot.sim.scenario import load_scenario
    from palletpilot.sim.simulator import Simulator

    missions = bundled_path("missions")
    scenario = folder / "scenario.yaml"
    scenario.write_text(
        f"map: {missions / 'warehouse.yaml'}\nforks: {missions / 'forks.yaml'}\nseed: {args.seed}\n"
        "start: floor_b2_pre\n"
        "camera:\n  mount: {x: -0.10, y: 0.0, z: 0.45, tilt_deg: 22, pan_deg: 0.0, roll_deg: 0.0}\n"
        f"pallets: [{{node: floor_b2, loaded: true, dy: {args.misplace_m}, dyaw_deg: {args.misplace_deg}}}]\n"
    )
    mission = folder / "mission.yaml"
    mission.write_text(
        f"name: bench_robot\nmap: {missions / 'warehouse.yaml'}\ntasks:\n"
        "  - {type: pickup, node: floor_b2}\n  - {type: delivery, node: floor_b2}\n"
    )
    calibration = folder / "calibration.json"  # the mount as installed (`palletpilot calibrate --out`)
    save_calibration(calibration, Calibration(Simulator(load_scenario(scenario)).T_forklift_camera_true, "model"))
    return scenario, mission, calibration


def start_stand_in(env: dict[str, str], scenario: Path, log: Path, robot: Path | None = None) -> subprocess.Popen[str]:
    """`palletpilot sim serve SCENARIO --ros [--robot ROBOT]` (stderr to `log`), returned once it printed its
    ready line (its stdout is drained from then on); `RuntimeError` (killed) when it does not come up."""
    cmd = [sys.executable, "-m", "palletpilot.cli", "sim", "serve", str(scenario), "--ros"]
    cmd += [] if robot is None else ["--robot", str(robot)]
    proc = subprocess.Popen(cmd, env=env, stdout=subprocess.PIPE, stderr=log.open("w"), text=True)
    lines: queue.Queue[str] = queue.Queue()

    def read() -> None:
        assert proc.stdout is not None
        for line in proc.stdout:
            lines.put(line)

    threading.Thread(target=read, daemon=True).start()
    try:
        line = lines.get(timeout=READY_TIMEOUT_S)
    except queue.Empty:
        proc.kill()
        raise RuntimeError(f"sim serve did not come up: {log.read_text()[-2000:]}") from None
    if not line.startswith("stand-in truck ready:"):
        proc.kill()
        raise RuntimeError(f"sim serve: {line.strip()}")
    return proc


def _stand_in_stats(proc: subprocess.Popen[str], log: Path) -> dict[str, Any]:
    """Stop the stand-in (SIGINT) and read the statistics it prints on stderr as it exits."""
    proc.send_signal(signal.SIGINT)
    try:
        proc.wait(timeout=30)
    except subprocess.TimeoutExpired:
        proc.kill()
        proc.wait()
    for line in reversed(log.read_text().splitlines()):
        if line.startswith('{"stand_in"'):
            return dict(json.loads(line)["stand_in"])
    raise RuntimeError(f"sim serve printed no statistics: {log.read_text()[-500:]}")


def run(args: argparse.Namespace) -> dict:
    """Run the mission on the stand-in truck and in the simulator; the figures as a dict."""
    from palletpilot.executor.adapters.ros.dds import loopback_env
    from palletpilot.executor.apps.app import run_simulated
    from palletpilot.geometry.fileio import bundled_path

    with tempfile.TemporaryDirectory(prefix="palletpilot-bench-robot-") as tmp:
        folder = Path(tmp)
        scenario, mission, calibration = _files(folder, args)
        env = {**os.environ, **loopback_env(folder), "PYTHONUNBUFFERED": "1"}
        serve_log = folder / "serve.log"
        standin = start_stand_in(env, scenario, serve_log)
        report = folder / "report"
        cmd = [sys.executable, "-m", "palletpilot.cli", "robot", str(mission), "--calibration", str(calibration)]
        cmd += ["--robot", str(bundled_path("missions", "robot.yaml")), "--report", str(report)]
        cmd += ["--wait", "20", "--json", "--quiet"]
        try:
            robot = subprocess.run(
                cmd,
                env=env,
                capture_output=True,
                text=True,
                timeout=RUN_TIMEOUT_S,
            )
        finally:
            stats = _stand_in_stats(standin, serve_log)
        if robot.returncode not in (0, 1):
            raise RuntimeError(f"palletpilot robot exited {robot.returncode}: {robot.stderr.strip()[-500:]}")
        doc = json.loads((report / "report.json").read_text())
        sim = run_simulated(mission, scenario, seed=args.seed)
    robot_tasks = [(t["type"], t["result"], t.get("reason")) for t in doc["tasks"]]
    sim_tasks = [(t["type"], t["result"], t.get("reason")) for t in sim.summary["tasks"]]
    jitter, latency = doc["clock"]["jitter_ms"], stats["command_latency_ms"]
    return {
        "seed": args.seed,
        "mission": "pickup floor_b2 (misplaced), delivery floor_b2",
        "ticks": doc["clock"]["ticks"],
        "control_tick_jitter_ms": jitter,
        "command_latency_ms": latency,
        "command_latency_split_ms": stats.get("command_latency_split_ms"),
        "localization_age_ms": doc["localization_age_ms"],
        "stand_in": {k: v for k, v in stats.items() if not k.startswith("command_latency")},
        "success_robot": bool(doc["success"]),
        "success_sim": bool(sim.success),
        "tasks_robot": robot_tasks,
        "tasks_sim": sim_tasks,
        "same_outcome": robot_tasks == sim_tasks,
        "goals": {
            "jitter_p99_ms": {"goal": JITTER_GOAL_MS, "met": (jitter.get("p99") or 0.0) <= JITTER_GOAL_MS},
            "latency_p99_ms": {"goal": LATENCY_GOAL_MS, "met": (latency.get("p99") or 0.0) <= LATENCY_GOAL_MS},
            "same_outcome": robot_tasks == sim_tasks,
        },
    }
