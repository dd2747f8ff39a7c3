"""Mission reports: `report.json`, `trajectory.png`, `events.jsonl` (and `trajectory.csv`, see
`executor.trajectory_log`; `run.mcap`, the run's recording, see `executor.recording`) in a report folder.

`report.json`: the mission, `success`, and per task its type, node, result, reason, attempts, start and
end time (simulated s), its states with their times and outcomes, the calibrations, the pallet
estimates against the node, the temporary nodes, and (in the simulator) the true pallet poses.
`trajectory.png`: the map, the planned paths, the driven trajectory (localization), the true and the
estimated pallet poses.

Both are written atomically (`geometry.fileio.write_atomic`), the PNG first and report.json last, so a
report.json on disk always belongs to a run that finished writing. JSON is strict (RFC 8259): numbers
that are not finite (a beam that sees nothing: infinite range) are written as `null`.
"""

from __future__ import annotations

import io
import math
from pathlib import Path
from typing import Any

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np

from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import write_atomic, write_json
from palletpilot.perception.specs import PalletType
from palletpilot.roadmap import Roadmap
from palletpilot.roadmap.draw import draw_roadmap

REPORT_FILES = ("report.json", "trajectory.png", "events.jsonl", "trajectory.csv", "run.mcap", "run-resumed.mcap")
"""The files a run writes into its report folder (a new run removes them first)."""


def summary(success: bool, results: list) -> dict[str, Any]:
    """The `--json` summary: `success` and `tasks` (type, node, result, reason, attempts)."""
    return {"success": success, "tasks": [r.summary() for r in results]}


def write_report(
    folder: Path,
    mission_name: str,
    success: bool,
    results: list,
    roadmap: Roadmap,
    trajectory: list[tuple[float, float, float, float]],
    planned_paths: list[list[tuple[float, float]]],
    truth_pallets: list[SE2] | None = None,
    extra: dict[str, Any] | None = None,
    obstacles: list[tuple[str, str, np.ndarray]] | None = None,
) -> Path:
    """Write `trajectory.png`, then `report.json` into `folder`, atomically; returns the JSON path.

    Raises `OutputError` (one line) when a file cannot be written; an older file stays as it was.
    """
    doc = {
        "mission": mission_name,
        "success": success,
        **(extra or {}),
        "tasks": [
            {
                **r.summary(),
                "message": r.message,
                "start_s": round(r.start_s, 3),
                "end_s": round(r.end_s, 3),
                "duration_s": round(r.end_s - r.start_s, 3),
                "states": r.states,
                **r.record,
            }
            for r in results
        ],
    }
    png = _plot(mission_name, success, results, roadmap, trajectory, planned_paths, truth_pallets, obstacles or [])
    write_atomic(folder / "trajectory.png", png)
    return write_json(folder / "report.json", doc)


_OBSTACLE_COLOURS = {"rack": "#4a5a8a", "person": "#e41a1c", "box": "#8c6d31"}


def _pallet_outline(pose: SE2, pallet: PalletType) -> np.ndarray:
    corners = np.array([[0, -0.5], [1, -0.5], [1, 0.5], [0, 0.5], [0, -0.5]]) * [pallet.length, pallet.width]
    return pose.apply(corners)


def _plot(
    name: str,
    success: bool,
    results: list,
    roadmap: Roadmap,
    trajectory: list[tuple[float, float, float, float]],
    planned: list[list[tuple[float, float]]],
    truth: list[SE2] | None,
    obstacles: list[tuple[str, str, np.ndarray]],
) -> bytes:
    """The trajectory plot as PNG bytes: map, racks and clutter, planned and driven paths, pallets."""
    fig, ax = plt.subplots(figsize=(11, 9), dpi=110)
    draw_roadmap(roadmap, ax, labels=True)
    labelled: set[str] = set()
    for kind, _id, corners in obstacles:
        colour = _OBSTACLE_COLOURS.get(kind, "#7f7f7f")
        label = None if kind in labelled else kind
        labelled.add(kind)
        ax.fill(corners[:, 0], corners[:, 1], color=colour, alpha=0.55, lw=0, label=label)
    for i, path in enumerate(planned):
        xy = np.array(path)
        ax.plot(xy[:, 0], xy[:, 1], "-", color="#1f77b4", lw=1.2, alpha=0.6, label="planned" if i == 0 else None)
    if trajectory:
        tr = np.array(trajectory)
        ax.plot(tr[:, 1], tr[:, 2], "-", color="#d62728", lw=1.6, label="driven")
    pallet = PalletType.eur()
    for i, pose in enumerate(truth or []):
        xy = _pallet_outline(pose, pallet)
        ax.plot(xy[:, 0], xy[:, 1], "-", color="#2ca02c", lw=1.5, label="pallet (true)" if i == 0 else None)
    first = True
    for r in results:
        for est in r.record.get("estimates", []):
            w = est["T_world_pallet"]
            xy = _pallet_outline(SE2(w["x_m"], w["y_m"], math.radians(w["yaw_deg"])), pallet)
            ax.plot(xy[:, 0], xy[:, 1], "--", color="#ff7f0e", lw=1.2, label="pallet (estimated)" if first else None)
            first = False
    ax.legend(loc="upper right", fontsize=8)
    verdict = "succeeded" if success else "failed: " + ", ".join(f"{r.type} {r.reason}" for r in results if r.reason)
    ax.set_title(f"{name}: {verdict}", fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def ms_stats(durations_s: list[float]) -> dict[str, float | None]:
    """Median, p99 and max (ms) of durations in seconds, as report.json states them (None without any)."""
    if not durations_s:
        return {"median": None, "p99": None, "max": None}
    ms = np.asarray(durations_s) * 1e3
    return {
        "median": round(float(np.median(ms)), 2),
        "p99": round(float(np.percentile(ms, 99)), 2),
        "max": round(float(ms.max()), 2),
    }
