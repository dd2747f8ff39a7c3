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
from palletpilot.roadmap.draw import NODE_STYLE, draw_roadmap

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
    truth_initial: list[SE2] | None = None,
) -> Path:
    """Write `trajectory.png`, then `report.json` into `folder`, atomically; returns the JSON path.

    `truth_pallets`: the pallets' true poses at the end (world, entry face's centre); `truth_initial`: the same
    pallets' at the start (the plot tells them apart where a pallet moved).
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
    truth = (truth_pallets or [], truth_initial or [])
    png = _plot(mission_name, success, results, roadmap, trajectory, planned_paths, truth, obstacles or [])
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
    truth: tuple[list[SE2], list[SE2]],
    obstacles: list[tuple[str, str, np.ndarray]],
) -> bytes:
    """The trajectory plot as PNG bytes: map (a legend for its node symbols), racks and clutter, the driven path
    under the planned one, the pallets' true poses at the start and the end (`truth`: end, start) and the
    estimates."""
    fig, ax = plt.subplots(figsize=(13, 9), dpi=110)
    draw_roadmap(roadmap, ax, labels=True)
    labelled: set[str] = set()
    for kind, _id, corners in obstacles:
        colour = _OBSTACLE_COLOURS.get(kind, "#7f7f7f")
        label = None if kind in labelled else kind
        labelled.add(kind)
        ax.fill(corners[:, 0], corners[:, 1], color=colour, alpha=0.55, lw=0, label=label)
    if trajectory:
        tr = np.array(trajectory)
        ax.plot(tr[:, 1], tr[:, 2], "-", color="#d62728", lw=2.4, alpha=0.55, label="driven", zorder=5)
    for i, path in enumerate(planned):  # over the driven path, thin and dashed, so both show
        xy = np.array(path)
        ax.plot(xy[:, 0], xy[:, 1], "--", color="#1f4fb4", lw=1.1, label="planned" if i == 0 else None, zorder=6)
    _plot_pallets(ax, results, *truth)
    _node_legend(ax, roadmap)
    ax.legend(loc="upper left", bbox_to_anchor=(1.01, 1.0), fontsize=8)  # beside the map, never over it
    verdict = "succeeded" if success else "failed: " + ", ".join(f"{r.type} {r.reason}" for r in results if r.reason)
    ax.set_title(f"{name}: {verdict}", fontsize=10)
    fig.tight_layout()
    buf = io.BytesIO()
    fig.savefig(buf, format="png")
    plt.close(fig)
    return buf.getvalue()


def _plot_pallets(ax: Any, results: list, final: list[SE2], initial: list[SE2]) -> None:
    """The pallets' true outlines, at the start (dotted, where a pallet moved) and at the end, and the estimates."""
    pallet = PalletType.eur()
    moved = [(a, b) for a, b in zip(initial, final, strict=False) if _moved(a, b)]
    end_label = "pallet at the end (true)" if moved or not initial else "pallet (true)"
    for i, pose in enumerate(final):
        xy = _pallet_outline(pose, pallet)
        ax.plot(xy[:, 0], xy[:, 1], "-", color="#2ca02c", lw=1.5, label=end_label if i == 0 else None, zorder=7)
    for i, (start, _) in enumerate(moved):
        xy = _pallet_outline(start, pallet)
        label = "pallet at the start (true)" if i == 0 else None
        ax.plot(xy[:, 0], xy[:, 1], ":", color="#2ca02c", lw=2.2, label=label, zorder=8)
    first = True
    for r in results:
        for est in r.record.get("estimates", []):
            w = est["T_world_pallet"]
            xy = _pallet_outline(SE2(w["x_m"], w["y_m"], math.radians(w["yaw_deg"])), pallet)
            ax.plot(xy[:, 0], xy[:, 1], "--", color="#ff7f0e", lw=1.2, label="pallet (estimated)" if first else None)
            first = False


def _moved(a: SE2, b: SE2) -> bool:
    """Did a pallet move between poses a and b (over 1 cm or 0.01 rad)?"""
    return math.hypot(a.x - b.x, a.y - b.y) > 0.01 or abs(a.yaw - b.yaw) > 0.01


def _node_legend(ax: Any, roadmap: Roadmap) -> None:
    """Legend entries (no data) for the node symbols of the types the map has."""
    present = {node.type for node in roadmap.nodes()}
    for kind, (marker, colour) in NODE_STYLE.items():
        if kind in present:
            ax.plot([], [], marker, color=colour, ls="", label=f"{kind.value} node")


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
