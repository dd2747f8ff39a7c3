"""`palletpilot replay RUN.mcap --report DIR`: a run's report (report.json, trajectory.png) from its recording.

Exit codes as `palletpilot run`'s: 0 written; 2 a bad recording (one line naming the file); 3 the report
could not be written. `executor.replay` says what is read back.

Public API: `add_parsers`, `cmd_replay`.
"""

from __future__ import annotations

import argparse
import json
from types import SimpleNamespace

from palletpilot.executor.apps.cli_args import out_folder
from palletpilot.executor.apps.cli_outcome import task_line


def cmd_replay(args: argparse.Namespace) -> int:
    """Regenerate the report of the recording `args.recording` into `args.report`."""
    from palletpilot.executor.adapters.mcap.replay import replay

    path = replay(args.recording, args.report)
    doc = json.loads(path.read_text())
    if args.json:
        print(json.dumps({"success": doc["success"], "tasks": [_summary(t) for t in doc["tasks"]]}, indent=2))
    else:
        for t in doc["tasks"]:  # report.json's task entries hold the task's record (estimates, ...) at top level
            fields = {k: t.get(k) for k in ("type", "node", "result", "reason")}
            print(task_line(SimpleNamespace(**fields, start_s=t["start_s"], end_s=t["end_s"], record=t)))
        print(f"mission {'succeeded' if doc['success'] else 'FAILED'} (replayed); report in {path.parent}/")
    return 0


def _summary(task: dict) -> dict:
    return {k: task[k] for k in ("type", "node", "result", "reason", "attempts")}


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register `replay` on the `palletpilot` sub-command parser."""
    p = subparsers.add_parser("replay", help="a run's report (report.json, trajectory.png) from its run.mcap")
    p.add_argument("recording", metavar="RUN.mcap", help="the recording (run.mcap of a report folder)")
    p.add_argument("--report", required=True, type=out_folder, help="folder to write report.json and trajectory.png")
    p.add_argument("--json", action="store_true", help="print the summary as JSON")
    p.set_defaults(func=cmd_replay)
