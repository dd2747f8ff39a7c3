"""`palletpilot bench faults`: random faults in seeded pickups and deliveries; does the truck always stop?

Each run: one misplaced pallet (floor or rack, +-0.20 m, +-8 deg) at a random pallet node of the example
map, its neighbours occupied, a person standing in the aisle beside the route's end; the forklift starts
at the aisle node before the pallet's pre-pallet node, picks the pallet up and delivers it to `drop`.
One to three faults from `sim.faults` are drawn per run (kind, trigger time or task state, parameters).
With probability `--kill-rate` a run also gets a `kill` (SIGKILL in a random task state): that run goes
through the command line in a subprocess with `--journal` and is then resumed with `--resume`.

Figures (JSON):
- `runs`, `seed`, `kill_runs`, `outcomes` (succeeded / failed missions), `faults_fired` per kind;
- `collisions`: runs in which the forklift or its load touched anything;
- `unstopped_failures`: failures after which the vehicle still moved 1 s later. In-process runs measure
  the simulator's true speed (the simulation goes on for 1 s past the run's end with no new command);
  killed-and-resumed runs use the report's own `stops` (standstill time);
- `invalid_reports`: runs whose report.json or an events.jsonl line is missing or not strict JSON;
- `reasons`: failed tasks per reason; `resumed_ok`: kill runs that resumed and finished without
  repeating a lift;
- `failure_to_standstill_s` and `fault_to_standstill_s` (p50 / p99 / max): from a failure (and from the
  last fault that took effect before it: a fault's start; a perception fault's call) to the true
  standstill (|v| < 1 mm/s). A failure more than `FAULT_WINDOW_S` (10 s) after the last fault is not
  counted as that fault's effect: `failures_without_fault` counts them.

Rack pallets stand at most `bench.missions.RACK_DEEPER_MAX_M` deeper than their node (deeper ones the
Pickup refuses by design, see the README).
"""

from __future__ import annotations

import argparse
import collections
import json
import math
import subprocess
import sys
import tempfile
from collections.abc import Callable
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from palletpilot.bench.missions import RACK_DEEPER_MAX_M, draw_pickup, example_pallet_nodes
from palletpilot.executor.apps.cli_args import count, number, seed
from palletpilot.geometry.fileio import bundled_path
from palletpilot.geometry.processes import spawn_pool
from palletpilot.sim.faults import FAULT_KINDS

MISSIONS = bundled_path("missions")
STANDSTILL_MPS = 1e-3
FAULT_WINDOW_S = 10.0  # a failure this long after the last fault took effect is not counted as its effect
MOVING_MPS = 0.01  # m/s: "still moving" 1 s after a failure
PICKUP_STATES = (
    "drive_to_pre_pallet",
    "calibrate",
    "raise_forks",
    "estimate_pallet",
    "back_off",
    "approach",
    "enter",
    "lift",
    "reverse_out",
    "return_to_roadmap",
)
DELIVERY_STATES = ("drive_to_pre_drop", "raise_forks", "enter", "lower", "reverse_out")
KINDS = tuple(k for k in FAULT_KINDS if k != "kill")  # a kill is drawn apart: its run is resumed


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument("--runs", type=count(1), default=50)
    parser.add_argument("--seed", type=seed, default=0)
    parser.add_argument("--jobs", type=count(1, 256), default=1, help="worker processes")
    parser.add_argument(
        "--kill-rate", type=number(0.0, 1.0), default=0.15, help="share of runs that are also killed (-9)"
    )


def _fault(rng: np.random.Generator) -> dict[str, Any]:
    """One random fault: a kind, a trigger (a simulated time or a task state) and its parameters."""
    kind = str(rng.choice(KINDS))
    if rng.random() < 0.5:
        trigger: dict[str, Any] = {"at_s": round(float(rng.uniform(1.0, 110.0)), 2)}
    else:
        task = int(rng.integers(2))
        states = PICKUP_STATES if task == 0 else DELIVERY_STATES
        trigger = {"state": str(rng.choice(states)), "task": task, "after_s": round(float(rng.uniform(0, 2)), 2)}
    draw: dict[str, Callable[[], dict[str, Any]]] = {
        "camera_drop": lambda: {"duration_s": round(float(rng.uniform(0.2, 3.0)), 2)},
        "camera_freeze": lambda: {"duration_s": round(float(rng.uniform(0.2, 3.0)), 2)},
        "perception_exception": lambda: {"count": 1},
        "perception_slow": lambda: {"delay_s": 2.0, "count": 1},
        "localization_jump": lambda: _jump(rng),
        "solver_failure": lambda: {"duration_s": round(float(rng.uniform(0.1, 1.5)), 2)},
        "vehicle_ignores_commands": lambda: {"duration_s": 1.0},
    }
    return {"kind": kind, **trigger, **draw[kind]()}


def _jump(rng: np.random.Generator) -> dict[str, Any]:
    """A 0.5 m localization jump in a random direction (forklift frame), for a while or for good."""
    angle = float(rng.uniform(-np.pi, np.pi))
    doc = {"dx": round(0.5 * math.cos(angle), 3), "dy": round(0.5 * math.sin(angle), 3)}
    return doc if rng.random() < 0.5 else {**doc, "duration_s": round(float(rng.uniform(0.2, 2.0)), 2)}


def _scenarios(runs: int, seed: int, kill_rate: float) -> list[dict[str, Any]]:
    roadmap, pallets = example_pallet_nodes(exclude=("drop",))
    rng = np.random.default_rng(seed)
    out = []
    for i in range(runs):
        node, rack, before = draw_pickup(roadmap, pallets, rng)
        others = [n for n in pallets if n != node and rng.random() < 0.4]
        faults = [_fault(rng) for _ in range(int(rng.integers(1, 4)))]
        kill = None
        if rng.random() < kill_rate:
            task = int(rng.integers(2))
            state = str(rng.choice(PICKUP_STATES if task == 0 else DELIVERY_STATES))
            kill = {"kind": "kill", "state": state, "task": task, "after_s": round(float(rng.uniform(0, 1.5)), 2)}
            faults.append(kill)
        scenario = {
            "map": "warehouse.yaml",
            "forks": "forks.yaml",
            "start": before,
            "seed": int(rng.integers(2**31)),
            "camera": {
                "mount": {"tilt_deg": float(rng.uniform(19.0, 25.0)), "pan_deg": float(rng.uniform(-1, 1))},
                "perturbation": {"xyz_sigma": 0.002, "angle_sigma_deg": 0.2},
            },
            "noise": {"localization_xy_sigma": 0.005, "localization_yaw_sigma_deg": 0.1, "slip_sigma": 0.005},
            "pallets": [
                {
                    "node": node,
                    "dx": float(rng.uniform(-0.2, min(0.2, RACK_DEEPER_MAX_M) if rack else 0.2)),
                    "dy": float(rng.uniform(-0.2, 0.2)),
                    "dyaw_deg": float(rng.uniform(-8.0, 8.0)),
                    "loaded": bool(rng.random() < 0.5),
                },
                *({"node": n, "loaded": True} for n in others),
            ],
            "faults": faults,
        }
        out.append({"index": i, "node": node, "kill": kill, "scenario": scenario})
    return out


def _mission(folder: Path, node: str) -> Path:
    path = folder / "mission.yaml"
    tasks = [{"type": "pickup", "node": node}, {"type": "delivery", "node": "drop"}]
    path.write_text(yaml.safe_dump({"name": "faults", "map": str(MISSIONS / "warehouse.yaml"), "tasks": tasks}))
    return path


def _reject(name: str) -> None:
    raise ValueError(f"not strict JSON: {name}")


def _read_report(folder: Path) -> tuple[dict[str, Any] | None, list[dict[str, Any]]]:
    """report.json and the events, parsed as strict JSON; (None, []) when either is missing or invalid."""
    try:
        doc = json.loads((folder / "report.json").read_text(), parse_constant=_reject)
        events = [json.loads(line, parse_constant=_reject) for line in (folder / "events.jsonl").open()]
    except (OSError, ValueError):
        return None, []
    if not isinstance(doc, dict) or not {"success", "tasks", "stops", "collisions"} <= set(doc):
        return None, []
    return doc, events


def _last_fault_before(doc: dict[str, Any], t: float) -> float | None:
    """When the last fault before `t` (s) took effect: its start, or for the call-counted perception faults
    (armed at their trigger, biting at the next perception call) the call that used them up."""
    times = []
    for f in doc.get("faults_injected", []):
        counted = f["kind"] in ("perception_exception", "perception_slow")
        if f["event"] == ("end" if counted else "start") and f["t_s"] <= t + 1e-6:
            times.append(f["t_s"])
    return max(times) if times else None


def _in_process(spec: dict[str, Any], folder: Path) -> dict[str, Any]:
    """Run without a kill: measure the true speed every tick, and 1 s past the end with no new command."""
    from palletpilot.executor.apps.app import run_simulated
    from palletpilot.sim.scenario import Scenario

    sc = Scenario.model_validate(spec["scenario"])
    sc.folder = MISSIONS
    trace: list[tuple[float, float]] = []  # (t, |v|): the simulator's speed is the truck's true speed

    def record(runner: Any) -> None:
        tick = runner.clock.tick

        def traced() -> None:
            tick()
            trace.append((runner.clock.now(), abs(runner.vehicle.speed)))

        runner.clock.tick = traced

    run = run_simulated(_mission(folder, spec["node"]), scenario=sc, report_dir=folder / "report", on_start=record)
    sim = run.sim
    t_end = trace[-1][0] if trace else 0.0
    last_stop = max((s["t_s"] for s in run.runner.stops), default=t_end)
    t = t_end
    while t < last_stop + 1.0 + 1e-9:  # the truck goes on existing after the run; no new command comes
        sim.step()
        t += 0.05
        trace.append((t, abs(sim.speed)))
    doc, events = _read_report(folder / "report")
    stops = []
    for stop in run.runner.stops:
        after = [(tt, v) for tt, v in trace if tt >= stop["t_s"] - 1e-9]
        standstill = next((tt for tt, v in after if v < STANDSTILL_MPS), None)
        one_s_later = next((v for tt, v in after if tt >= stop["t_s"] + 1.0 - 1e-9), 0.0)
        stops.append({**stop, "true_standstill_s": standstill, "moving_1s_later": one_s_later > MOVING_MPS})
    return _outcome(spec, doc, events, stops, len(sim.collisions) > 0, resumed=None)


def _killed(spec: dict[str, Any], folder: Path) -> dict[str, Any]:
    """Run with a kill through the command line (subprocess, --journal), then resume it (--resume)."""
    scenario = dict(spec["scenario"], map=str(MISSIONS / "warehouse.yaml"), forks=str(MISSIONS / "forks.yaml"))
    (folder / "scenario.yaml").write_text(yaml.safe_dump(scenario))
    journal, report = folder / "run.journal", folder / "report"
    cmd = [sys.executable, "-m", "palletpilot.cli", "run", "--quiet"]
    first = subprocess.run(
        [
            *cmd,
            str(_mission(folder, spec["node"])),
            "--scenario",
            str(folder / "scenario.yaml"),
            "--journal",
            str(journal),
            "--report",
            str(report),
        ],
        capture_output=True,
        text=True,
    )
    killed = first.returncode == -9
    second = subprocess.run([*cmd, "--resume", str(journal)], capture_output=True, text=True) if killed else first
    doc, events = _read_report(report)
    stops = []
    for stop in doc["stops"] if doc else []:
        standstill = stop.get("standstill_s")
        stops.append(
            {
                **stop,
                "true_standstill_s": standstill,
                "moving_1s_later": standstill is None or standstill - stop["t_s"] > 1.0,
            }
        )
    lifts = sum(1 for e in events if e["event"] == "state_end" and e["state"] == "lift" and e["outcome"] == "done")
    finished = second.returncode in (0, 1) and any(e["event"] == "mission_end" for e in events)
    resumed = {"killed": killed, "finished": finished, "lifts": lifts, "exit": second.returncode}
    collided = bool(doc and doc["collisions"])
    return _outcome(spec, doc, events, stops, collided, resumed=resumed)


def _outcome(
    spec: dict[str, Any],
    doc: dict[str, Any] | None,
    events: list[dict[str, Any]],
    stops: list[dict[str, Any]],
    collided: bool,
    resumed: dict[str, Any] | None,
) -> dict[str, Any]:
    fired = [f["kind"] for f in (doc or {}).get("faults_injected", []) if f["event"] == "start"]
    if resumed is not None and resumed["killed"]:
        fired.append("kill")
    return {
        "index": spec["index"],
        "valid_report": doc is not None,
        "success": bool(doc and doc["success"]),
        "reasons": [t["reason"] for t in (doc or {}).get("tasks", []) if t["result"] != "succeeded"],
        "fired": fired,
        "collided": collided,
        "stops": [
            {
                "reason": s["reason"],
                "moving_1s_later": s["moving_1s_later"],
                "failure_to_standstill_s": None
                if s["true_standstill_s"] is None
                else s["true_standstill_s"] - s["t_s"],
                "fault_to_standstill_s": _fault_delay(doc, s),
            }
            for s in stops
        ],
        "resumed": resumed,
    }


def _fault_delay(doc: dict[str, Any] | None, stop: dict[str, Any]) -> float | None:
    """Fault to standstill (s) for a failure within `FAULT_WINDOW_S` of the last fault; else None."""
    if doc is None or stop["true_standstill_s"] is None:
        return None
    start = _last_fault_before(doc, stop["t_s"])
    if start is None or stop["t_s"] - start > FAULT_WINDOW_S:
        return None
    return stop["true_standstill_s"] - start


def _one(spec: dict[str, Any]) -> dict[str, Any]:
    with tempfile.TemporaryDirectory() as tmp:
        return (_killed if spec["kill"] else _in_process)(spec, Path(tmp))


def _percentiles(values: list[float]) -> dict[str, float | None]:
    if not values:
        return {"p50": None, "p99": None, "max": None, "n": 0}
    a = np.asarray(values)
    return {
        "p50": round(float(np.percentile(a, 50)), 3),
        "p99": round(float(np.percentile(a, 99)), 3),
        "max": round(float(a.max()), 3),
        "n": len(values),
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Run every seeded faulty mission and return the figures."""
    specs = _scenarios(args.runs, args.seed, args.kill_rate)
    if args.jobs > 1:
        with spawn_pool(args.jobs) as pool:
            outcomes = list(pool.map(_one, specs))
    else:
        outcomes = [_one(s) for s in specs]
    stops = [s for o in outcomes for s in o["stops"]]
    kills = [o for o in outcomes if o["resumed"] is not None]
    return {
        "runs": len(outcomes),
        "seed": args.seed,
        "kill_runs": len(kills),
        "outcomes": {
            "succeeded": sum(o["success"] for o in outcomes),
            "failed": sum(not o["success"] for o in outcomes),
        },
        "faults_fired": dict(collections.Counter(k for o in outcomes for k in o["fired"])),
        "collisions": sum(o["collided"] for o in outcomes),
        "failures": len(stops),
        "unstopped_failures": sum(s["moving_1s_later"] for s in stops),
        "invalid_reports": sum(not o["valid_report"] for o in outcomes),
        "reasons": dict(collections.Counter(r for o in outcomes for r in o["reasons"])),
        "resumed_ok": sum(
            bool(o["resumed"]["killed"] and o["resumed"]["finished"] and o["resumed"]["lifts"] <= 1) for o in kills
        ),
        "kills_fired": sum(bool(o["resumed"]["killed"]) for o in kills),
        "failure_to_standstill_s": _percentiles(
            [s["failure_to_standstill_s"] for s in stops if s["failure_to_standstill_s"] is not None]
        ),
        "failures_without_fault": sum(1 for s in stops if s["fault_to_standstill_s"] is None),
        "fault_to_standstill_s": _percentiles(
            [s["fault_to_standstill_s"] for s in stops if s["fault_to_standstill_s"] is not None]
        ),
        "problem_runs": [
            o["index"]
            for o in outcomes
            if o["collided"] or not o["valid_report"] or any(s["moving_1s_later"] for s in o["stops"])
        ][:20],
    }
