"""`palletpilot bench sim`: rendering time and how much faster than real time the simulator drives.

- `render_ms_median`: one 640x480 frame (depth + labels + RGB, D435 noise on) from a standing forklift
  at a pre-pallet node, the way the pickup uses the camera. `render_moving_ms_median`: the same while
  the forklift moves between frames (the ray-casting scene is rebuilt for the moved forks).
- `sim_realtime_factor`: simulated seconds per wall-clock second when driving at the 20 Hz control rate
  (localization read, drive command, step with pallet contact checks) without rendering.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from palletpilot.executor.apps.cli_args import count, number, seed
from palletpilot.geometry.fileio import bundled_path
from palletpilot.sim.scenario import load_scenario
from palletpilot.sim.simulator import CONTROL_DT, Simulator

SCENARIO = bundled_path("missions") / "scenario_floor.yaml"


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument("--frames", type=count(1), default=60)
    parser.add_argument("--sim-seconds", type=number(0.05, 36000.0, "s"), default=120.0)
    parser.add_argument("--width", type=int, default=640, choices=(640, 848))
    parser.add_argument("--seed", type=seed, default=0)


def run(args: argparse.Namespace) -> dict:
    """Measure and return the figures."""
    sc = load_scenario(SCENARIO)
    sc.camera.width = args.width
    sim = Simulator(sc, seed=args.seed)
    sim.grab()  # warm-up: builds the scene and ray caches
    standing = []
    for _ in range(args.frames):
        t0 = time.perf_counter()
        sim.grab()
        standing.append((time.perf_counter() - t0) * 1e3)
    moving = []
    for _ in range(max(10, args.frames // 3)):
        sim.drive(-0.3, 0.0)
        sim.step()
        t0 = time.perf_counter()
        sim.grab()
        moving.append((time.perf_counter() - t0) * 1e3)

    drive = Simulator(load_scenario(SCENARIO), seed=args.seed, start="b_bot")
    steps = round(args.sim_seconds / CONTROL_DT)
    t0 = time.perf_counter()
    for k in range(steps):
        drive.localization()
        drive.drive(1.0, 0.3 * math.sin(0.2 * k * CONTROL_DT))
        drive.step(CONTROL_DT)
    wall = time.perf_counter() - t0
    return {
        "width": args.width,
        "height": 480,
        "frames": len(standing),
        "render_ms_median": round(float(np.median(standing)), 2),
        "render_ms_p90": round(float(np.percentile(standing, 90)), 2),
        "render_moving_ms_median": round(float(np.median(moving)), 2),
        "sim_seconds": args.sim_seconds,
        "sim_wall_s": round(wall, 3),
        "sim_realtime_factor": round(args.sim_seconds / wall, 1),
        "seed": args.seed,
    }
