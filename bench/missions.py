"""`palletpilot bench missions`: seeded pickups of misplaced pallets, adaptive against the paper's original.

Each run: one pallet at a random pallet node of the example map (floor or rack, empty or loaded),
misplaced uniformly by +-0.30 m lateral, +-0.30 m longitudinal (in a rack at most 0.13 m deeper:
`RACK_DEEPER_MAX_M`) and +-10 deg, D435 noise with label
noise, a random camera mount (tilt 18-26 deg, pan +-2, roll +-1.5) with a random per-run perturbation,
localization noise; the forklift starts at the aisle node before the pallet's pre-pallet node and runs
a single pickup. The same scenarios are run in each mode (`--modes`): `adaptive` (the adaptive Pickup as
on a truck: perception selects its pixels by each of `--labels`: `fused`, the default, depth geometry
with the shipped ONNX model's hints on the simulator's RGB; `geometry`, depth alone; `model`, the ONNX
model alone; one row each, `adaptive` for fused alone, else `adaptive:LABELS`), `adaptive_truth` (the
model mode fed the simulator's labels, label noise on), `no_adapt` (`run --no-adapt`: no re-plan, the
camera's checks refuse a pallet the forks do not fit as it stands) and `paper` (the paper's original
Pickup: no camera, only the proximity safety check; a baseline that no truck runs,
`Settings.paper_baseline`). Success: the pallet is on the forks and nothing collided.
"""

from __future__ import annotations

import argparse
import collections
import tempfile
import time
from concurrent.futures import ProcessPoolExecutor
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from palletpilot.executor.apps.cli_args import count, names, seed
from palletpilot.geometry.fileio import bundled_path

if TYPE_CHECKING:
    from palletpilot.roadmap import Roadmap

MISSIONS = bundled_path("missions")
MODES = ("adaptive", "adaptive_truth", "no_adapt", "paper")
LABELS = ("fused", "geometry", "model")
"""`--labels` of the adaptive mode (`perception.labels_mode`)."""
RACK_DEEPER_MAX_M = 0.13
"""A rack pallet stands at most this much deeper than its node: the range the bench has always drawn, so
its figures stay comparable. The Pickup takes deeper ones while the forks carry the pallet type's minimum
engagement (`executor.core.engagement`: about 0.39 m for an EUR pallet with the example forks) and refuses
the rest (`no_feasible_approach`) rather than touch the rack."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument("--runs", type=count(1), default=100)
    parser.add_argument("--seed", type=seed, default=0)
    parser.add_argument("--jobs", type=count(1, 256), default=1, help="worker processes")
    parser.add_argument(
        "--modes",
        type=names(MODES),
        default=list(MODES),
        help="comma-separated: adaptive, adaptive_truth, no_adapt, paper",
    )
    parser.add_argument(
        "--labels", type=names(LABELS), default=["fused"], help="the adaptive mode's labels: fused, geometry, model"
    )


def example_pallet_nodes(exclude: tuple[str, ...] = ()) -> tuple[Roadmap, list[str]]:
    """The example map (`missions/warehouse.yaml`) and its pallet node ids, sorted, less `exclude`."""
    from palletpilot.roadmap import NodeType, load_map

    roadmap = load_map(MISSIONS / "warehouse.yaml")
    return roadmap, sorted(n.id for n in roadmap.nodes() if n.type is NodeType.PALLET and n.id not in exclude)


def draw_pickup(roadmap: Roadmap, pallets: list[str], rng: np.random.Generator) -> tuple[str, bool, str]:
    """Draw a pallet node from `pallets`: (its id, whether it is in a rack, the aisle node before its
    pre-pallet node, where a run starts)."""
    node = str(rng.choice(pallets))
    return node, roadmap.node(node).height > 0.0, start_node(roadmap, node)


def start_node(roadmap: Roadmap, node: str) -> str:
    """The aisle node before pallet node `node`'s pre-pallet node: where a benchmark's truck starts."""
    pre = roadmap.pre_pallet_of(node)
    return next(u for u in roadmap.graph.predecessors(pre) if u != node)


def _scenarios(runs: int, seed: int) -> list[dict]:
    roadmap, pallets = example_pallet_nodes()
    rng = np.random.default_rng(seed)
    out = []
    for i in range(runs):
        node, rack, before = draw_pickup(roadmap, pallets, rng)
        out.append(
            {
                "index": i,
                "node": node,
                "start": before,
                "scenario": {
                    "map": "warehouse.yaml",
                    "start": before,
                    "seed": int(rng.integers(2**31)),
                    "camera": {
                        "mount": {
                            "x": -0.10,
                            "y": float(rng.uniform(-0.02, 0.02)),
                            "z": float(rng.uniform(0.40, 0.50)),
                            "tilt_deg": float(rng.uniform(18.0, 26.0)),
                            "pan_deg": float(rng.uniform(-2.0, 2.0)),
                            "roll_deg": float(rng.uniform(-1.5, 1.5)),
                        },
                        "perturbation": {"xyz_sigma": 0.003, "angle_sigma_deg": 0.3},
                        "noise": {"label_noise": True},
                    },
                    "noise": {"localization_xy_sigma": 0.005, "localization_yaw_sigma_deg": 0.1, "slip_sigma": 0.005},
                    "pallets": [
                        {
                            "node": node,
                            "dx": float(rng.uniform(-0.30, RACK_DEEPER_MAX_M if rack else 0.30)),
                            "dy": float(rng.uniform(-0.30, 0.30)),
                            "dyaw_deg": float(rng.uniform(-10.0, 10.0)),
                            "loaded": bool(rng.random() < 0.5),
                        }
                    ],
                },
            }
        )
    return out


def _one(job: tuple[dict, str]) -> dict:
    """Run one scenario in one mode; returns the outcome (in a worker process)."""
    from palletpilot.executor.apps.app import run_simulated
    from palletpilot.executor.core.behaviour import Settings
    from palletpilot.sim.scenario import Scenario

    spec, mode = job
    adapt = mode not in ("no_adapt", "paper")
    settings = Settings(paper_baseline=mode == "paper")
    labels = "truth" if mode == "adaptive_truth" else mode.partition(":")[2] or "fused"
    sc = Scenario.model_validate(spec["scenario"])
    sc.folder = MISSIONS
    with tempfile.TemporaryDirectory() as tmp:
        mission = Path(tmp) / "m.yaml"
        mission.write_text(
            yaml.safe_dump(
                {"map": str(MISSIONS / "warehouse.yaml"), "tasks": [{"type": "pickup", "node": spec["node"]}]}
            )
        )
        t0 = time.perf_counter()
        run = run_simulated(mission, scenario=sc, adapt=adapt, labels=labels, settings=settings)  # type: ignore[arg-type]
        wall = time.perf_counter() - t0
    task = run.runner.results[0]
    lifted = bool(run.sim.pallets and run.sim.pallets[0].carried)
    success = task.result == "succeeded" and lifted and not run.sim.collisions
    reason = None if success else (task.reason or ("collision" if run.sim.collisions else "pallet_not_lifted"))
    return {
        "index": spec["index"],
        "mode": mode,
        "node": spec["node"],
        "success": success,
        "reason": reason,
        "replans": max(task.attempts - 1, 0),
        "task_s": task.end_s - task.start_s,
        "wall_s": wall,
    }


def _rows(mode: str, labels: list[str]) -> list[str]:
    """The result rows of a mode: one per labels kind for the adaptive mode (`adaptive` for fused alone)."""
    if mode != "adaptive":
        return [mode]
    return ["adaptive"] if labels == ["fused"] else [f"adaptive:{label}" for label in labels]


def run(args: argparse.Namespace) -> dict:
    """Run every scenario in each mode and return the figures."""
    specs = _scenarios(args.runs, args.seed)
    modes = [m for mode in args.modes for m in _rows(mode, list(args.labels))]
    jobs = [(s, m) for m in modes for s in specs]
    if args.jobs > 1:
        with ProcessPoolExecutor(args.jobs) as pool:
            outcomes = list(pool.map(_one, jobs))
    else:
        outcomes = [_one(j) for j in jobs]
    result: dict = {"runs": args.runs, "seed": args.seed}
    for mode in modes:
        mine = [o for o in outcomes if o["mode"] == mode]
        ok = [o for o in mine if o["success"]]
        result[mode] = {
            "success_rate": round(len(ok) / len(mine), 4),
            "mean_replans": round(float(np.mean([o["replans"] for o in mine])), 3),
            "mean_task_s": round(float(np.mean([o["task_s"] for o in mine])), 2),
            "mean_wall_s": round(float(np.mean([o["wall_s"] for o in mine])), 2),
            "failures": dict(collections.Counter(o["reason"] for o in mine if not o["success"])),
            "failed_runs": [o["index"] for o in mine if not o["success"]][:20],
        }
    return result
