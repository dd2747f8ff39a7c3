"""`palletpilot bench missions`: seeded pickups of misplaced pallets, adaptive against the paper's original.

Each run: one pallet of a family of `--families`, drawn per run: `floor` and `rack` (a floor or rack
pallet node of the example map) and `narrow` (a slot of rack row N, beams at 1.8 m, in the narrow aisle
of `missions/narrow_aisle.yaml`: `NARROW_AISLE_WIDTH_M` from rack to rack, racks `NARROW_RACK_DEPTH_M`
deep, with pallets in the slots either side), empty or loaded, misplaced uniformly within the envelope
(`ENVELOPE_M` lateral and longitudinal, `ENVELOPE_DEG`, on floor and rack slots alike: a rack pallet
pushed deeper than the forks can carry is refused, `no_feasible_approach`, and counted as an engagement
shortfall), D435 noise with label noise, a random camera mount (tilt 18-26 deg, pan +-2, roll +-1.5)
with a random per-run perturbation, localization noise; the forklift starts at the aisle node before
the pallet's pre-pallet node and runs a single pickup. The same scenarios are run in each mode
(`--modes`): `adaptive` (the adaptive Pickup as on a truck: perception selects its pixels by each of
`--labels`: `fused`, the default, depth geometry with the shipped ONNX model's hints on the simulator's
RGB; `geometry`, depth alone; `model`, the ONNX model alone; one row each, `adaptive` for fused alone,
else `adaptive:LABELS`), `adaptive_truth` (the model mode fed the simulator's labels, label noise on),
`no_adapt` (`run --no-adapt`: no re-plan, the camera's checks refuse a pallet the forks do not fit as it
stands) and `paper` (the paper's original Pickup: no camera, only the proximity safety check; a baseline
that no truck runs, `Settings.paper_baseline`). Success: the pallet is on the forks and nothing
collided. A rack pallet is judged beforehand from the simulator's truth by the engagement rule
(`executor.core.engagement.rack_engagement`, `_rack_verdict`): `take` (the forks reach its minimum
engagement with `VERDICT_BAND_M` to spare for the estimate's error), `refuse` (they cannot, even with a
perfect estimate) or `either`. A run's outcome is *correct* when a `take` run succeeds, a `refuse` run is
refused for its engagement without contact, and an `either` run does one of the two; `success_rate` counts
successes over all runs, `take_success_rate` over the runs that can be taken. Per mode also: the success
rate per family, the verdicts, the manoeuvres planned (`manoeuvres`: re-plans that needed forward and
reverse moves, and the runs with one), the engagement shortfalls (`engagement`: pallets taken with the
forks held back at the rack, and pallets refused for it) and the incorrect runs with their messages.
"""

from __future__ import annotations

import argparse
import collections
import tempfile
import time
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np
import yaml

from palletpilot.executor.apps.cli_args import count, names, seed
from palletpilot.geometry.fileio import bundled_path
from palletpilot.geometry.processes import spawn_pool

if TYPE_CHECKING:
    from palletpilot.roadmap import Roadmap

MISSIONS = bundled_path("missions")
MODES = ("adaptive", "adaptive_truth", "no_adapt", "paper")
FAMILIES = ("floor", "rack", "narrow")
"""`--families`: floor and rack slots of the example map, and the narrow aisle's rack row N."""
ENVELOPE_M = 0.40
ENVELOPE_DEG = 15.0
"""Misplacements are drawn within +-`ENVELOPE_M` (m, lateral and longitudinal) and +-`ENVELOPE_DEG`."""
NARROW_MAP = "narrow_aisle.yaml"
NARROW_AISLE_WIDTH_M = 4.6
NARROW_RACK_DEPTH_M = 1.1
"""The narrow aisle (`missions/narrow_aisle.yaml`): rack to rack (m), and the simulator's rack depth (m)."""
LABELS = ("fused", "geometry", "model")
"""`--labels` of the adaptive mode (`perception.labels_mode`)."""
INCORRECT_KEYS = ("index", "family", "node", "verdict", "reason", "message")
"""What the figures say of each incorrect run."""
VERDICT_BAND_M = 0.03
"""A rack pallet within this much (m) of the engagement limit may be taken or refused (`_rack_verdict`):
about the pallet estimate's error at the envelope's edge (`Settings.envelope_tolerance`)."""
RACK_DEEPER_MAX_M = 0.13
"""A rack pallet stands at most this much deeper than its node in `bench faults` (its figures stay
comparable). The Pickup takes deeper ones while the forks carry the pallet type's minimum engagement
(`executor.core.engagement`: about 0.39 m deeper for an EUR pallet with the example forks) and refuses the
rest (`no_feasible_approach`) rather than touch the rack."""


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
    parser.add_argument(
        "--families", type=names(FAMILIES), default=list(FAMILIES), help="comma-separated: floor, rack, narrow"
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


def _scenarios(runs: int, seed: int, families: list[str]) -> list[dict]:
    """`runs` seeded pickups, each of a family drawn from `families` (see the module docstring)."""
    from palletpilot.roadmap import NodeType

    roadmap, pallets = example_pallet_nodes()
    by_family = {
        "floor": [n for n in pallets if roadmap.node(n).height == 0.0],
        "rack": [n for n in pallets if roadmap.node(n).height > 0.0],
    }
    narrow = load_narrow_aisle()
    by_family["narrow"] = sorted(
        n.id for n in narrow.nodes() if n.id.startswith("rack_n") and n.type is NodeType.PALLET
    )
    rng = np.random.default_rng(seed)
    out = []
    for i in range(runs):
        family = str(rng.choice(families))
        world = narrow if family == "narrow" else roadmap
        node = str(rng.choice(by_family[family]))
        before = start_node(world, node)
        target = {
            "node": node,
            "dx": float(rng.uniform(-ENVELOPE_M, ENVELOPE_M)),
            "dy": float(rng.uniform(-ENVELOPE_M, ENVELOPE_M)),
            "dyaw_deg": float(rng.uniform(-ENVELOPE_DEG, ENVELOPE_DEG)),
            "loaded": bool(rng.random() < 0.5),
        }
        neighbours = _neighbours(by_family["narrow"], node, rng) if family == "narrow" else []
        out.append(
            {
                "index": i,
                "family": family,
                "verdict": _rack_verdict(world, NARROW_MAP if family == "narrow" else "warehouse.yaml", node, target),
                "map": NARROW_MAP if family == "narrow" else "warehouse.yaml",
                "node": node,
                "start": before,
                "scenario": {
                    "map": NARROW_MAP if family == "narrow" else "warehouse.yaml",
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
                    "pallets": [target, *neighbours],
                },
            }
        )
    return out


def _rack_verdict(world: Roadmap, map_name: str, node: str, target: dict) -> str:
    """What a pickup of the pallet `target` (at `node` of `world`, the map file `map_name` of the missions
    folder, misplaced by its dx, dy in m and dyaw_deg in the node's frame) must do,
    from the truth: `take`, `refuse` (a rack pallet deeper than the forks can carry) or `either` (within
    `VERDICT_BAND_M` of that limit); floor pallets are always `take`."""
    import math

    from palletpilot.control.vehicle import load_vehicle
    from palletpilot.executor.core.behaviour import Settings
    from palletpilot.executor.core.engagement import geometry_tolerances, rack_engagement
    from palletpilot.geometry import SE2
    from palletpilot.perception.specs import ENTRY_GAP_M, load_forks, pallet_type
    from palletpilot.roadmap.mapfile import map_vehicle_file

    if world.node(node).height <= 0.0:
        return "take"
    st = Settings()
    forks, pallet = load_forks(MISSIONS / "forks.yaml"), pallet_type("eur")
    vehicle = load_vehicle(map_vehicle_file(MISSIONS / map_name) or MISSIONS / "forklift.yaml")
    tol = geometry_tolerances(forks, pallet, st)
    gap = SE2(ENTRY_GAP_M, 0.0, 0.0)
    rel = gap @ SE2(target["dx"], target["dy"], math.radians(target["dyaw_deg"])) @ gap.inv()  # serving node
    held = rack_engagement(vehicle.body, tol, pallet, st.rack_overrun, rel)
    if held is None or held.enough(st.longitudinal_margin + VERDICT_BAND_M):
        return "take"
    return "refuse" if not held.enough(0.0) else "either"


def load_narrow_aisle() -> Roadmap:
    """The narrow aisle's map (`missions/narrow_aisle.yaml`)."""
    from palletpilot.roadmap import load_map

    return load_map(MISSIONS / NARROW_MAP)


def _neighbours(slots: list[str], node: str, rng: np.random.Generator) -> list[dict]:
    """Pallets in the slots either side of `node` in the narrow aisle's row (at their nodes)."""
    k = slots.index(node)
    return [{"node": slots[j], "loaded": bool(rng.random() < 0.5)} for j in (k - 1, k + 1) if 0 <= j < len(slots)]


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
            yaml.safe_dump({"map": str(MISSIONS / spec["map"]), "tasks": [{"type": "pickup", "node": spec["node"]}]})
        )
        t0 = time.perf_counter()
        run = run_simulated(mission, scenario=sc, adapt=adapt, labels=labels, settings=settings)  # type: ignore[arg-type]
        wall = time.perf_counter() - t0
    task = run.runner.results[0]
    lifted = bool(run.sim.pallets and run.sim.pallets[0].carried)
    success = task.result == "succeeded" and lifted and not run.sim.collisions
    reason = None if success else str(task.reason or ("collision" if run.sim.collisions else "pallet_not_lifted"))
    engagement = task.record.get("engagement", [])
    refused = any(not e["enough"] for e in engagement) and reason == "no_feasible_approach" and not run.sim.collisions
    verdict = spec["verdict"]
    return {
        "index": spec["index"],
        "mode": mode,
        "family": spec["family"],
        "verdict": verdict,
        "correct": success if verdict == "take" else (refused if verdict == "refuse" else success or refused),
        "message": None if success else (task.message or "")[:400],
        "node": spec["node"],
        "manoeuvres": sum("manoeuvre" in t for t in task.record.get("temporary_nodes", [])),
        "held_back": any(e["enough"] for e in engagement),
        "refused_engagement": refused,
        "contacts": len(run.sim.collisions),
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
    families = list(getattr(args, "families", FAMILIES))
    specs = _scenarios(args.runs, args.seed, families)
    modes = [m for mode in args.modes for m in _rows(mode, list(args.labels))]
    jobs = [(s, m) for m in modes for s in specs]
    if args.jobs > 1:
        with spawn_pool(args.jobs) as pool:
            outcomes = list(pool.map(_one, jobs))
    else:
        outcomes = [_one(j) for j in jobs]
    result: dict = {
        "runs": args.runs,
        "seed": args.seed,
        "envelope": f"+-{ENVELOPE_M:.2f} m lateral and longitudinal, +-{ENVELOPE_DEG:.0f} deg, floor and rack",
        "families": dict(collections.Counter(s["family"] for s in specs)),
    }
    if "narrow" in families:
        result["narrow_aisle"] = (
            f"{NARROW_MAP}: {NARROW_AISLE_WIDTH_M:.1f} m from rack to rack, racks {NARROW_RACK_DEPTH_M:.1f} m deep"
        )
    for mode in modes:
        result[mode] = _figures([o for o in outcomes if o["mode"] == mode], families)
    return result


def _figures(mine: list[dict], families: list[str]) -> dict:
    """One mode's figures over its outcomes."""
    ok = [o for o in mine if o["success"]]
    takeable = [o for o in mine if o["verdict"] == "take"]
    per_family = {}
    for family in families:
        runs = [o for o in mine if o["family"] == family]
        if runs:
            per_family[family] = round(sum(o["success"] for o in runs) / len(runs), 4)
    return {
        "success_rate": round(len(ok) / len(mine), 4),
        "take_success_rate": round(sum(o["success"] for o in takeable) / len(takeable), 4) if takeable else None,
        "correct_outcome_rate": round(sum(o["correct"] for o in mine) / len(mine), 4),
        "verdicts": dict(collections.Counter(o["verdict"] for o in mine)),
        "by_family": per_family,
        "manoeuvres": {
            "planned": sum(o["manoeuvres"] for o in mine),
            "runs": sum(o["manoeuvres"] > 0 for o in mine),
            "runs_succeeded": sum(o["manoeuvres"] > 0 and o["success"] for o in mine),
        },
        "engagement": {
            "held_back": sum(o["held_back"] for o in mine),
            "refused": sum(o["refused_engagement"] for o in mine),
        },
        "contacts": sum(o["contacts"] for o in mine),
        "mean_replans": round(float(np.mean([o["replans"] for o in mine])), 3),
        "mean_task_s": round(float(np.mean([o["task_s"] for o in mine])), 2),
        "mean_wall_s": round(float(np.mean([o["wall_s"] for o in mine])), 2),
        "failures": dict(collections.Counter(str(o["reason"]) for o in mine if not o["success"])),
        "failed_runs": [o["index"] for o in mine if not o["success"]][:20],
        "incorrect_runs": [{k: o[k] for k in INCORRECT_KEYS} for o in mine if not o["correct"]][:20],
    }
