"""One run of a suite case in the simulator, and the checks every run must pass.

`run_case(spec, report_root)` runs a `suite.RunSpec` (in whatever process calls it) and returns a
`RunResult`: the outcome (`success`, `failure` with the first failed task's reason, `rejected` before
anything moved, or `error` for an internal error), whether it met the case's expectation, and every
check that did not hold, each one line. `check_run(...)` applies the checks to a finished run's report
folder (report.json, trajectory.csv), so the pytest helpers (`palletpilot.testing`) use the same code.

Checks (`suite.Checks`), all in the world frame of the map, metres and degrees as named:
- `no_contact`: report.json `collisions` is empty (the simulator stops the truck at the first contact);
- `travel_height`: every trajectory row with a load and |speed| above the vehicle's creep speed has the
  forks at most `driving.TRAVEL_HEIGHT_TOLERANCE` above `travel_height_loaded`;
- `only_target_moved`: every pallet that no pickup of the mission names ends where it started (1 cm, 1 deg);
- `max_task_s`, `max_replans`: per task, its duration and its `replan` states;
- `delivered_within_m`, `delivered_yaw_deg`: a pallet delivered by a succeeded delivery stands at its drop
  node's pallet pose (`perception.specs.pallet_pose_at_node`) within these.

Public API: `RunResult`, `run_case`, `check_run`.
"""

from __future__ import annotations

import csv
import json
import math
import time
from dataclasses import asdict, dataclass, field
from pathlib import Path
from typing import Any

from palletpilot.control.vehicle import VehicleParams
from palletpilot.executor.apps.suite import Checks, RunSpec
from palletpilot.executor.core.driving import TRAVEL_HEIGHT_TOLERANCE
from palletpilot.executor.core.mission import Mission
from palletpilot.geometry import PalletpilotError
from palletpilot.perception.specs import pallet_pose_at_node
from palletpilot.roadmap import Roadmap

MOVED_M = 0.01
MOVED_DEG = 1.0
"""A pallet this far (m, or deg) from where it started has been moved."""


@dataclass
class RunResult:
    """What one run of a case gave and whether it met the case's expectation."""

    label: str
    case: str
    index: int
    outcome: str  # success | failure | rejected | error
    met: bool
    reason: str | None = None  # the first failed task's reason, or the refusal's first line
    problems: list[str] = field(default_factory=list)  # why the run did not meet its case (one line each)
    simulated_s: float = 0.0
    wall_s: float = 0.0  # this run's own elapsed time (s)
    started_s: float = 0.0  # when it started (Unix time, s: comparable across the worker processes)
    report_dir: str | None = None
    drawn: dict[str, Any] = field(default_factory=dict)
    retried: bool = False  # its worker died (node lost, out of memory) and it ran again (`--executor ray`)

    def to_json(self) -> dict[str, Any]:
        """The result as plain JSON types."""
        return asdict(self)

    @property
    def trajectory_png(self) -> str | None:
        """The run's trajectory image, when it was drawn."""
        if self.report_dir is None:
            return None
        png = Path(self.report_dir) / "trajectory.png"
        return str(png) if png.is_file() else None


def run_case(spec: RunSpec, report_root: Path) -> RunResult:
    """Run `spec` in the simulator with its report under `report_root/<case>/<index>/`; never raises."""
    from palletpilot.executor.apps.app import run_simulated
    from palletpilot.sim.scenario import Scenario, SimError

    folder = report_root / spec.case / str(spec.index)
    res = RunResult(spec.label, spec.case, spec.index, "error", False, report_dir=str(folder), drawn=spec.drawn)
    t0 = time.perf_counter()
    res.started_s = round(time.time(), 3)
    try:
        scenario = None
        if spec.scenario_doc is not None:
            try:
                scenario = Scenario.model_validate(spec.scenario_doc)
            except ValueError as exc:
                raise SimError(f"{spec.label}: drawn scenario: {str(exc).splitlines()[0]}") from None
            scenario.folder = spec.scenario_folder or Path(".")
            scenario.source = f"{spec.label} (drawn)"
        run = run_simulated(spec.mission, spec.scenario_path, spec.seed, folder, scenario=scenario)
    except PalletpilotError as exc:
        res.outcome, res.reason = "rejected", exc.problems[0]
        res.report_dir = None
    except Exception as exc:  # a bug: reported as this run's error, the suite goes on
        res.reason = f"internal error: {type(exc).__name__}: {exc}"
    else:
        failed = next((t for t in run.summary["tasks"] if t["result"] != "succeeded"), None)
        res.outcome = "success" if run.success else "failure"
        res.reason = None if failed is None else failed["reason"]
        res.simulated_s = round(float(run.sim.time), 2)
        res.problems += check_run(
            folder, run.runner.mission, run.sim.roadmap, run.runner.ctx.params, Checks(**spec.checks)
        )
    res.wall_s = round(time.perf_counter() - t0, 2)
    res.problems[:0] = _expectation(spec, res)
    res.met = res.outcome != "error" and not res.problems
    return res


def _expectation(spec: RunSpec, res: RunResult) -> list[str]:
    """Why the outcome is not the one expected ([] when it is)."""
    if res.outcome == "error":
        return [res.reason or "internal error"]
    if res.outcome != spec.expect:
        why = f" ({res.reason})" if res.reason else ""
        return [f"expected {spec.expect}, got {res.outcome}{why}"]
    if spec.expect == "failure" and spec.reasons and res.reason not in spec.reasons:
        return [f"expected a failure with {' or '.join(spec.reasons)}, got {res.reason}"]
    if spec.expect == "rejected" and spec.message and spec.message not in (res.reason or ""):
        return [f"expected a refusal saying '{spec.message}', got: {res.reason}"]
    return []


def check_run(folder: Path, mission: Mission, roadmap: Roadmap, vehicle: VehicleParams, checks: Checks) -> list[str]:
    """Every check of `checks` on the run whose report is in `folder`; one line per violation."""
    report = json.loads((folder / "report.json").read_text())
    problems: list[str] = []
    if checks.no_contact:
        for c in report.get("collisions", []):
            problems.append(f"contact: {json.dumps(c, sort_keys=True)}")
    if checks.travel_height:
        problems += _travel_height(folder / "trajectory.csv", vehicle)
    targets = {t.node for t in mission.tasks if t.type == "pickup"}
    pallets = {p["id"]: p for p in report.get("pallets", [])}
    if checks.only_target_moved:
        for pid, p in pallets.items():
            if pid not in targets and _moved(p["initial"], p["final"]):
                problems.append(f"pallet {pid} moved, but no pickup names it: {p['initial']} -> {p['final']}")
    for i, task in enumerate(report.get("tasks", [])):
        label = f"tasks[{i}] ({task['type']} {task.get('node') or ''})".replace(" )", ")")
        if checks.max_task_s is not None and task["duration_s"] > checks.max_task_s:
            problems.append(f"{label}: took {task['duration_s']:.1f} s (limit {checks.max_task_s:g} s)")
        replans = sum(s["state"] == "replan" for s in task.get("states", []))
        if checks.max_replans is not None and replans > checks.max_replans:
            problems.append(f"{label}: {replans} re-plans (limit {checks.max_replans})")
    problems += _deliveries(report, mission, roadmap, pallets, checks)
    return problems


def _travel_height(csv_path: Path, vehicle: VehicleParams) -> list[str]:
    """Rows driving loaded faster than creep speed with the forks above travel height (first one only)."""
    limit = vehicle.mast.travel_height_loaded + TRAVEL_HEIGHT_TOLERANCE
    fast = vehicle.creep_speed + 0.02  # the speed tracker may overshoot a little
    with csv_path.open() as f:
        for row in csv.DictReader(f):
            if row["loaded"] == "1" and abs(float(row["speed_mps"])) > fast and float(row["fork_height_m"]) > limit:
                return [
                    f"at t = {float(row['t_s']):.2f} s the truck drove loaded at {float(row['speed_mps']):.2f} m/s "
                    f"with the forks at {float(row['fork_height_m']):.3f} m (travel height "
                    f"{vehicle.mast.travel_height_loaded:.3f} m)"
                ]
    return []


def _moved(a: dict[str, float], b: dict[str, float]) -> bool:
    dyaw = abs((b["yaw_deg"] - a["yaw_deg"] + 180.0) % 360.0 - 180.0)
    return math.hypot(b["x_m"] - a["x_m"], b["y_m"] - a["y_m"]) > MOVED_M or dyaw > MOVED_DEG


def _deliveries(
    report: dict[str, Any], mission: Mission, roadmap: Roadmap, pallets: dict[str, Any], checks: Checks
) -> list[str]:
    """Delivered pallets off their drop node's pallet pose by more than the checks allow."""
    if checks.delivered_within_m is None and checks.delivered_yaw_deg is None:
        return []
    problems, carried = [], None
    for i, (task, rec) in enumerate(zip(mission.tasks, report.get("tasks", []), strict=False)):
        if task.type == "pickup" and rec["result"] == "succeeded":
            carried = task.node
        if task.type != "delivery" or rec["result"] != "succeeded" or carried not in pallets:
            continue
        node = roadmap.node(task.node)
        want = pallet_pose_at_node(node.pose, node.height).to_se2()
        got = pallets[carried]["final"]
        off_m = math.hypot(got["x_m"] - want.x, got["y_m"] - want.y)
        off_deg = abs((got["yaw_deg"] - math.degrees(want.yaw) + 180.0) % 360.0 - 180.0)
        if checks.delivered_within_m is not None and off_m > checks.delivered_within_m:
            problems.append(
                f"tasks[{i}] (delivery {task.node}): pallet {carried} stands {1e3 * off_m:.1f} mm from the drop "
                f"node's pallet pose (limit {1e3 * checks.delivered_within_m:.1f} mm)"
            )
        if checks.delivered_yaw_deg is not None and off_deg > checks.delivered_yaw_deg:
            problems.append(
                f"tasks[{i}] (delivery {task.node}): pallet {carried} is turned {off_deg:.1f} deg from the drop "
                f"node (limit {checks.delivered_yaw_deg:g} deg)"
            )
        carried = None
    return problems
