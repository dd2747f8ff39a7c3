"""Exit codes of every `palletpilot` command, and how `run` and `robot` end: the summary they print
and the exit code of a mission's outcome.

Public API: `EXIT_OK`, `EXIT_FAILED`, `EXIT_BAD_INPUT`, `EXIT_WRITE_FAILED`, `EXIT_INTERNAL`,
`mission_outcome`, `task_line`.
"""

from __future__ import annotations

import itertools
import json
import math
import sys
from pathlib import Path
from typing import Any

from palletpilot.executor.core.controls import Controls
from palletpilot.executor.ports import vocabulary
from palletpilot.executor.ports.vocabulary import Outcome

EXIT_OK = vocabulary.EXIT_OK
EXIT_FAILED = vocabulary.EXIT_FAILED
"""The mission (or the command's task) failed; the vehicle stands."""
EXIT_BAD_INPUT = 2
"""Bad input: one line per problem on stderr, nothing done."""
EXIT_WRITE_FAILED = 3
"""The work succeeded but an output could not be written."""
EXIT_INTERNAL = 70
"""A bug (EX_SOFTWARE): the traceback goes to a log file, one line to stderr."""


def task_line(task: Any) -> str:
    """One finished task as a shift lead reads it (a `TaskResult`): type, node, outcome and reason, how long it
    took; for a Pickup how far off its node the pallet was found first (lateral, along, yaw), the re-plans and
    the estimates, and the manoeuvres (their segments) when a re-plan needed one."""
    why = f" ({task.reason})" if task.reason else ""
    line = f"{task.type:9s} {task.node or '':14s} {task.result}{why} in {task.end_s - task.start_s:.1f} s"
    estimates = task.record.get("estimates", [])
    if estimates:
        first = estimates[0]
        replans = task.record.get("temporary_nodes", [])
        line += (
            f": pallet found {abs(first['lateral_mm']):.0f} mm sideways, {abs(first['longitudinal_mm']):.0f} mm along, "
            f"{abs(first['yaw_deg']):.1f} deg off its node; {len(replans)} re-plan(s), {len(estimates)} estimate(s)"
        )
        moves = [r["manoeuvre"]["segments"] for r in replans if "manoeuvre" in r]
        if moves:  # a re-plan no single curve reached: forward and reverse moves
            line += f", {len(moves)} manoeuvre(s) of {'+'.join(map(str, moves))} segments"
    return line


def _totals(trajectory: list[tuple[float, float, float, float]]) -> str:
    """` in T s, D m driven` of a run's localization trajectory (t, x, y, yaw), or nothing without one."""
    if len(trajectory) < 2:
        return ""
    distance = sum(math.hypot(b[1] - a[1], b[2] - a[2]) for a, b in itertools.pairwise(trajectory))
    return f" in {trajectory[-1][0] - trajectory[0][0]:.1f} s, {distance:.1f} m driven"


def mission_outcome(result: Any, report: Path | None, as_json: bool, controls: Controls, vehicle: str) -> int:
    """Print a finished mission's summary on stdout (`as_json`: the report's summary as JSON, else one
    line per task and the outcome), write errors and the failed task on stderr, and return the exit
    code: 0 success, 3 success with an output not written, 128 + signal when a signal cancelled it,
    else the failed task's reason's (`executor.vocabulary.REASONS`: 1). `result`: a `RunResult` of
    `executor.app` or `executor.ros.robot` (`summary`, `success`, `write_errors`, `runner.results`);
    `report`: its report folder; `vehicle`: the word for what was stopped ("vehicle", "truck")."""
    if as_json:
        print(json.dumps(result.summary, indent=2))
    else:
        for task in result.runner.results:
            print(task_line(task))
        where = f"; report in {report}/" if report is not None else ""
        print(f"mission {'succeeded' if result.success else 'FAILED'}{_totals(result.runner.trajectory)}{where}")
    for line in result.write_errors:
        print(f"error: {line}", file=sys.stderr)
    if result.success:
        return EXIT_WRITE_FAILED if result.write_errors else EXIT_OK
    failed = next((t for t in result.runner.results if t.result != Outcome.SUCCEEDED), None)
    if failed is not None:
        why = f"{failed.reason}: {failed.message}"
        number = f"{failed.index + 1} of {len(result.runner.mission.tasks)}"  # from 1, as the progress line counts
        print(f"mission failed: task {number} ({failed.type}): {why}; {vehicle} stopped", file=sys.stderr)
    if controls.cancel_signal is not None:
        return 128 + controls.cancel_signal
    meta = None if failed is None or failed.reason is None else vocabulary.info(failed.reason)
    return EXIT_FAILED if meta is None else meta.exit_code
