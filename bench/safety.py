"""`palletpilot bench safety`: seeded warehouse situations where the truck must not touch anything.

Families (runs split evenly; each run drawn from its own seed on the example map, `missions/`):

- `person_on_route`: a person stands on an aisle the truck drives -> `path_blocked`;
- `person_crossing`: a person walks back and forth across the aisle (0.5-1.2 m/s) -> success;
- `person_or_box_before_pallet`: a person or a box stands between the pre-pallet node and the pallet,
  in the fork corridor -> `path_blocked`;
- `box_in_aisle`: a box on the aisle -> `path_blocked`;
- `neighbours`: the target on the floor with pallets 1.0 m centre to centre on either side, misplaced
  up to 0.15 m / 5 deg (never into a neighbour) -> success;
- `empty_slot`: the same lane with the target slot empty -> `pallet_not_found`;
- `occupied_drop`: pickup, then a delivery to a drop slot where a pallet stands -> `slot_occupied`;
- `three_level_putaway`: pickup from the floor, delivery to the floor or a rack level at 1.0 or 1.8 m
  -> success, the pallet set down at the node;
- `loaded_travel`: pickup of a loaded pallet (floor or rack, misplaced) and a delivery to the drop
  -> success.

Per family and overall: `runs`, `collisions` (runs with any contact), `wrong_pallet` (runs where a
pallet other than the mission's was lifted or moved by more than 1 cm), `correct_outcome_rate` (every
task ended as expected, no contact, no wrong pallet, a delivered pallet within 0.10 m / 3 deg of its
node), `max_fork_height_while_travelling_m` (the truck's fork height while it drove roadmap edges:
the driving states, not the pallet and slot entries and exits) against `travel_height_limit_m` (the
vehicle file's loaded travel height + 5 cm), and `travel_height_violations` (runs above the travel
height that applied, loaded or empty, + 5 cm). A blocked path holds a task `BLOCKED_WAIT_S` here (the
mission key `blocked_wait_s`), not the default 30 s.
"""

from __future__ import annotations

import argparse
import csv
import json
import math
import shutil
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np
import yaml

from palletpilot.bench.missions import start_node
from palletpilot.executor.apps.cli_args import count, names, seed
from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import bundled_path
from palletpilot.geometry.processes import spawn_pool
from palletpilot.perception.specs import PalletType, pallet_pose_at_node

MISSIONS = bundled_path("missions")
BLOCKED_WAIT_S = 10.0
"""s a blocked path holds a task in this benchmark before `path_blocked` / `slot_occupied`."""

FAMILIES = (
    "person_on_route",
    "person_crossing",
    "person_or_box_before_pallet",
    "box_in_aisle",
    "neighbours",
    "empty_slot",
    "occupied_drop",
    "three_level_putaway",
    "loaded_travel",
)
DRIVING_STATES = frozenset(
    {"drive_to_pre_pallet", "drive_to_pre_drop", "drive", "back_off", "approach", "return_to_roadmap"}
)
"""States that drive roadmap edges (the entries into and exits from pallets and slots are not among them)."""

# Straight aisle stretches of the example map: (start node, goal node, x of the aisle, y range to use).
AISLES = (("b1", "b_top", 20.0, (8.0, 15.0)), ("a_top", "a_bot", 6.0, (5.0, 14.0)))
FLOOR_NODES = ("floor_a1", "floor_a2", "floor_a3", "floor_b1", "floor_b2", "floor_b3")
RACK_NODES = ("rack_a1", "rack_a2", "rack_a3", "rack_b1", "rack_b2", "rack_b3")
DROP_SPOT = pallet_pose_at_node(SE2(15.5, -4.0, math.radians(-90.0)), 0.0).to_se2()  # `drop` in warehouse.yaml


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument("--runs", type=count(1), default=90)
    parser.add_argument("--seed", type=seed, default=0)
    parser.add_argument("--jobs", type=count(1, 256), default=1, help="worker processes")
    parser.add_argument("--families", type=names(FAMILIES), default=list(FAMILIES), help="comma-separated subset")


# -- scenarios ------------------------------------------------------------------------------------


def _node_pose(node: str) -> SE2:
    from palletpilot.roadmap import load_map

    return load_map(MISSIONS / "warehouse.yaml").node(node).pose


def _before(node: str) -> str:
    """The aisle node before a pallet's pre-pallet node (where the truck starts)."""
    from palletpilot.roadmap import load_map

    return start_node(load_map(MISSIONS / "warehouse.yaml"), node)


def _free(pose: SE2, loaded: bool) -> dict[str, Any]:
    return {"x": pose.x, "y": pose.y, "yaw_deg": math.degrees(pose.yaw), "loaded": loaded}


def _lane_placement(rng: np.random.Generator) -> tuple[float, float, float]:
    """A target misplacement (dx, dy, dyaw_deg) up to 0.15 m / 5 deg that stays 2 cm clear of neighbours
    1.0 m to either side (0.6 m from the node's centre line to their near sides)."""
    pt = PalletType.eur()
    while True:
        dx, dy, dyaw = rng.uniform(-0.05, 0.05), rng.uniform(-0.15, 0.15), rng.uniform(-5.0, 5.0)
        pose = SE2(dx, dy, math.radians(dyaw))
        corners = [pose.apply([x, y]) for x in (0.0, pt.length) for y in (-0.5 * pt.width, 0.5 * pt.width)]
        if max(abs(c[1]) for c in corners) <= 0.58:
            return float(dx), float(dy), float(dyaw)


def _spec(family: str, index: int, rng: np.random.Generator) -> dict[str, Any]:
    """One run: its mission tasks, scenario document, expected task outcomes and the target pallet id."""
    sc: dict[str, Any] = {
        "map": "warehouse.yaml",
        "seed": int(rng.integers(2**31)),
        "camera": {
            "mount": {"tilt_deg": float(rng.uniform(20.0, 24.0)), "pan_deg": float(rng.uniform(-1.0, 1.0))},
            "perturbation": {"xyz_sigma": 0.002, "angle_sigma_deg": 0.2},
        },
        "noise": {"localization_xy_sigma": 0.005, "localization_yaw_sigma_deg": 0.1, "slip_sigma": 0.005},
        "pallets": [],
        "clutter": [],
    }
    spec: dict[str, Any] = {"family": family, "index": index, "scenario": sc, "target": None, "levels": None}
    loaded = bool(rng.random() < 0.5)
    if family in ("person_on_route", "box_in_aisle", "person_crossing"):
        start, goal, x, (y0, y1) = AISLES[int(rng.integers(len(AISLES)))]
        y = float(rng.uniform(y0, y1))
        sc["start"] = start
        spec["tasks"] = [{"type": "move", "node": goal}]
        if family == "person_on_route":
            sc["clutter"] = [
                {"kind": "person", "x": x + rng.uniform(-0.3, 0.3), "y": y, "yaw_deg": rng.uniform(0, 360)}
            ]
            spec["expected"] = ["path_blocked"]
        elif family == "box_in_aisle":
            size = [float(rng.uniform(0.3, 0.8)), float(rng.uniform(0.3, 0.6)), float(rng.uniform(0.3, 0.8))]
            box = {"kind": "box", "x": x + rng.uniform(-0.3, 0.3), "y": y, "yaw_deg": rng.uniform(0, 90), "size": size}
            sc["clutter"] = [box]
            spec["expected"] = ["path_blocked"]
        else:
            side = 1.0 if rng.random() < 0.5 else -1.0
            sc["clutter"] = [
                {
                    "kind": "person",
                    "x": x - 3.0 * side,
                    "y": y,
                    "path": [[x + 3.0 * side, y]],
                    "speed": float(rng.uniform(0.5, 1.2)),
                    "repeat": True,
                }
            ]
            spec["expected"] = ["succeeded"]
        return spec
    node = str(rng.choice(FLOOR_NODES))
    sc["start"] = _before(node)
    nominal = pallet_pose_at_node(_node_pose(node), 0.0).to_se2()
    if family == "person_or_box_before_pallet":
        sc["pallets"] = [{"node": node, "loaded": loaded}]
        spot = nominal @ SE2(-float(rng.uniform(0.35, 0.9)), float(rng.uniform(-0.2, 0.2)), 0.0)
        if rng.random() < 0.5:
            thing: dict[str, Any] = {"kind": "person", "x": spot.x, "y": spot.y, "yaw_deg": rng.uniform(0, 360)}
        else:
            size = [float(rng.uniform(0.3, 0.5)), float(rng.uniform(0.3, 0.5)), float(rng.uniform(0.3, 0.6))]
            thing = {"kind": "box", "x": spot.x, "y": spot.y, "yaw_deg": rng.uniform(0, 90), "size": size}
        sc["clutter"] = [thing]
        spec.update(tasks=[{"type": "pickup", "node": node}], expected=["path_blocked"], target=node)
        return spec
    if family in ("neighbours", "empty_slot"):
        lane = [_free(nominal @ SE2(0.0, side, 0.0), bool(rng.random() < 0.5)) for side in (-1.0, 1.0)]
        if family == "neighbours":
            dx, dy, dyaw = _lane_placement(rng)
            lane.append({"node": node, "dx": dx, "dy": dy, "dyaw_deg": dyaw, "loaded": loaded})
        sc["pallets"] = lane
        expected = ["succeeded"] if family == "neighbours" else ["pallet_not_found"]
        spec.update(tasks=[{"type": "pickup", "node": node}], expected=expected, target=node)
        return spec
    placement = {
        "node": node,
        "dx": float(rng.uniform(-0.1, 0.1)),
        "dy": float(rng.uniform(-0.1, 0.1)),
        "dyaw_deg": float(rng.uniform(-4, 4)),
    }
    if family == "occupied_drop":
        occupant = DROP_SPOT @ SE2(float(rng.uniform(-0.1, 0.1)), float(rng.uniform(-0.1, 0.1)), 0.0)
        sc["pallets"] = [{**placement, "loaded": loaded}, _free(occupant, bool(rng.random() < 0.5))]
        tasks = [{"type": "pickup", "node": node}, {"type": "delivery", "node": "drop"}]
        spec.update(tasks=tasks, expected=["succeeded", "slot_occupied"], target=node)
        return spec
    if family == "three_level_putaway":
        level = float(rng.choice([0.0, 1.0, 1.8]))
        if level == 0.0:
            goal = str(rng.choice([n for n in FLOOR_NODES if n != node]))
        else:
            goal = str(rng.choice(RACK_NODES))
        sc["pallets"] = [{**placement, "loaded": loaded}]
        tasks = [{"type": "pickup", "node": node}, {"type": "delivery", "node": goal}]
        spec.update(tasks=tasks, expected=["succeeded", "succeeded"], target=node, levels=level, goal=goal)
        return spec
    # loaded_travel: a loaded pallet from the floor or a rack, misplaced within the Pickup's envelope
    node = str(rng.choice(FLOOR_NODES + RACK_NODES))
    sc["start"] = _before(node)
    rack = node.startswith("rack")
    sc["pallets"] = [
        {
            "node": node,
            "dx": float(rng.uniform(-0.2, 0.1 if rack else 0.2)),
            "dy": float(rng.uniform(-0.2, 0.2)),
            "dyaw_deg": float(rng.uniform(-6, 6)),
            "loaded": True,
        }
    ]
    tasks = [{"type": "pickup", "node": node}, {"type": "delivery", "node": "drop"}]
    spec.update(tasks=tasks, expected=["succeeded", "succeeded"], target=node, goal="drop")
    return spec


def _specs(runs: int, seed: int, families: list[str]) -> list[dict[str, Any]]:
    rng = np.random.default_rng(seed)
    seeds = rng.integers(2**31, size=runs)
    return [
        _spec(families[i % len(families)], i, np.random.default_rng(int(seeds[i]))) | {"seed": int(seeds[i])}
        for i in range(runs)
    ]


# -- one run ----------------------------------------------------------------------------------------


def _world(folder: Path, level: float | None) -> Path:
    """The example files in `folder`; with a rack `level` (m), the map's racks at that height."""
    for name in ("warehouse.yaml", "forklift.yaml", "forks.yaml"):
        shutil.copy(MISSIONS / name, folder / name)
    if level is not None and level > 0.0:
        doc = yaml.safe_load((folder / "warehouse.yaml").read_text())
        for n in doc["nodes"]:
            if n["id"].startswith("rack_") and n["type"] == "pallet":
                n["height"] = level
        (folder / "warehouse.yaml").write_text(yaml.safe_dump(doc, sort_keys=False))
    return folder / "warehouse.yaml"


def _travel_heights(folder: Path, params: Any) -> tuple[float, bool]:
    """The highest fork height (m) while driving roadmap edges, and whether it ever exceeded the travel
    height that applied (loaded or empty) by more than 5 cm."""
    windows, open_at = [], None
    for line in (folder / "events.jsonl").open():
        e = json.loads(line)
        if e.get("event") == "state_start" and e.get("state") in DRIVING_STATES:
            open_at = e["t"]
        elif e.get("event") == "state_end" and e.get("state") in DRIVING_STATES and open_at is not None:
            windows.append((open_at, e["t"]))
            open_at = None
    mast = params.mast
    highest, over = 0.0, False
    with (folder / "trajectory.csv").open() as f:
        for row in csv.DictReader(f):
            t = float(row["t_s"])
            if not any(a <= t <= b for a, b in windows):
                continue
            h = float(row["fork_height_m"])
            limit = (mast.travel_height_loaded if row["loaded"] == "1" else mast.travel_height_empty) + 0.05
            highest, over = max(highest, h), over or h > limit + 1e-9
    return highest, over


def _placed_at(sim: Any, pallet_id: str, goal: str) -> bool:
    """The pallet stands within 0.10 m, 3 deg and 2 cm of height of its delivery node's pallet pose."""
    node = sim.roadmap.node(goal)
    want = pallet_pose_at_node(node.pose, node.height)
    p = next(p for p in sim.pallets if p.id == pallet_id)
    off = want.inv() @ p.T_world_pallet
    return (
        math.hypot(off.t[0], off.t[1]) < 0.10
        and abs(math.degrees(off.to_se2().yaw)) < 3.0
        and abs(p.T_world_pallet.t[2] - node.height) < 0.02
        and not p.carried
    )


def _one(spec: dict[str, Any]) -> dict[str, Any]:
    """Run one situation (in a worker process) and judge it."""
    from palletpilot.executor.apps.app import run_simulated
    from palletpilot.sim.scenario import Scenario

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(tmp)
        map_path = _world(folder, spec.get("levels"))
        sc = Scenario.model_validate(spec["scenario"])
        sc.folder = folder
        mission = folder / "mission.yaml"
        doc = {"name": spec["family"], "map": str(map_path), "blocked_wait_s": BLOCKED_WAIT_S, "tasks": spec["tasks"]}
        mission.write_text(yaml.safe_dump(doc))
        t0 = time.perf_counter()
        run = run_simulated(mission, scenario=sc, report_dir=folder / "report")
        wall = time.perf_counter() - t0
        highest, over = _travel_heights(folder / "report", run.sim.vehicle)
    sim = run.sim
    outcomes: list[str] = [r.result if r.result == "succeeded" else (r.reason or r.result) for r in run.runner.results]
    outcomes += ["not_run"] * (len(spec["tasks"]) - len(outcomes))
    wrong = [
        p.id
        for p in sim.pallets
        if p.id != spec["target"] and (p.lifted or np.linalg.norm((p.initial.inv() @ p.T_world_pallet).t) > 0.01)  # type: ignore[union-attr]
    ]
    placed = True
    if spec.get("goal") and outcomes == spec["expected"] == ["succeeded", "succeeded"]:
        placed = _placed_at(sim, spec["target"], spec["goal"])
    correct = outcomes == spec["expected"] and not sim.collisions and not wrong and placed and not over
    last = run.runner.results[-1] if run.runner.results else None
    return {
        "family": spec["family"],
        "index": spec["index"],
        "seed": spec["seed"],
        "expected": spec["expected"],
        "outcomes": outcomes,
        "correct": correct,
        "collision": [f"{c['kind']} '{c['id']}'" for c in sim.collisions],
        "wrong_pallet": wrong,
        "placed": placed,
        "max_travel_fork_height_m": round(highest, 4),
        "travel_height_violation": over,
        "message": None if last is None or last.result == "succeeded" else last.message,
        "wall_s": round(wall, 2),
    }


# -- figures ---------------------------------------------------------------------------------------


def _figures(outcomes: list[dict[str, Any]]) -> dict[str, Any]:
    n = len(outcomes)
    return {
        "runs": n,
        "collisions": sum(bool(o["collision"]) for o in outcomes),
        "wrong_pallet": sum(bool(o["wrong_pallet"]) for o in outcomes),
        "correct_outcome_rate": round(sum(o["correct"] for o in outcomes) / n, 4) if n else None,
        "max_fork_height_while_travelling_m": max((o["max_travel_fork_height_m"] for o in outcomes), default=None),
        "travel_height_violations": sum(o["travel_height_violation"] for o in outcomes),
    }


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Run every situation and return the figures per family and overall."""
    from palletpilot.control.vehicle import load_vehicle

    families = list(args.families)
    specs = _specs(args.runs, args.seed, families)
    t0 = time.perf_counter()
    if args.jobs > 1:
        with spawn_pool(args.jobs) as pool:
            outcomes = list(pool.map(_one, specs))
    else:
        outcomes = [_one(s) for s in specs]
    mast = load_vehicle(MISSIONS / "forklift.yaml").mast
    result: dict[str, Any] = {
        "runs": args.runs,
        "seed": args.seed,
        "blocked_wait_s": BLOCKED_WAIT_S,
        "travel_height_limit_m": round(mast.travel_height_loaded + 0.05, 3),
        "overall": _figures(outcomes),
        "families": {f: _figures([o for o in outcomes if o["family"] == f]) for f in families},
        "incorrect_runs": [
            {
                k: o[k]
                for k in ("family", "index", "seed", "expected", "outcomes", "collision", "wrong_pallet", "message")
            }
            for o in outcomes
            if not o["correct"]
        ][:30],
        "wall_s": round(time.perf_counter() - t0, 1),
    }
    return result
