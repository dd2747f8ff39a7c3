"""`palletpilot replay RUN.mcap --report DIR`: a run's report (report.json, trajectory.png) from its recording.

Exit codes as `palletpilot run`'s: 0 written; 2 a bad recording (one line naming the file); 3 the report
could not be written. `executor.replay` says what is read back.

Public API: `add_parsers`, `cmd_replay`.
"""

from __future__ import annotations

import argparse
import json

from palletpilot.executor.apps.cli_args import out_folder


def cmd_replay(args: argparse.Namespace) -> int:
    """Regenerate the report of the recording `args.recording` into `args.report`."""
    from palletpilot.executor.adapters.mcap.replay import replay

    path = replay(args.recording, args.report)
    doc = json.loads(path.read_text())
    if args.json:
        print(json.dumps({"success": doc["success"], "tasks": [_summary(t) for t in doc["tasks"]]}, indent=2))
    else:
        for t in doc["tasks"]:
            why = f" ({t['reason']})" if t["reason"] else ""
            print(f"{t['type']:9s} {t['node'] or '':14s} {t['result']}{why}, {t['attempts']} estimate(s)")
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
