"""`palletpilot bench recording`: what recording a run costs: the demo mission's `run.mcap` size and the
recorder's time per control tick.

Runs the demo (`missions/pickup_delivery.yaml` in `missions/scenario_demo.yaml`, `--seed`) in simulated
time with its report (and so `run.mcap`, `executor.recording`), then reads the file: `mcap_size_mb`,
`channels` (topic -> message count, from the MCAP summary), and the recorder's own timing, written into
the file as the metadata record `recording_cost`: `ticks`, `tick_cost_ms_mean`, `tick_cost_ms_p99`,
`tick_cost_ms_max` (wall-clock time spent in the recorder per control tick: its tick, the events and
camera frames of that tick). Goals (issue #21): `mcap_size_mb` <= 50, `tick_cost_ms_mean` <= 1.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from pathlib import Path
from typing import Any

from mcap.reader import make_reader

from palletpilot.executor.apps.cli_args import seed
from palletpilot.geometry.fileio import bundled_path

MISSIONS = bundled_path("missions")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """`--seed`, `--mission`, `--scenario`, `--keep DIR`."""
    parser.add_argument("--seed", type=seed, default=7, help="the simulator's seed (default 7)")
    parser.add_argument("--mission", default=str(MISSIONS / "pickup_delivery.yaml"), help="mission (default: demo)")
    parser.add_argument("--scenario", default=str(MISSIONS / "scenario_demo.yaml"), help="scenario (default: demo)")
    parser.add_argument("--keep", metavar="DIR", help="write the report (and run.mcap) here instead of a temp folder")


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Run the mission with the recorder; the figures of the module docstring."""
    from palletpilot.executor.apps.app import run_simulated

    with tempfile.TemporaryDirectory() as tmp:
        folder = Path(args.keep) if args.keep else Path(tmp)
        t0 = time.perf_counter()
        result = run_simulated(args.mission, args.scenario, seed=args.seed, report_dir=folder)
        wall_s = time.perf_counter() - t0
        path = folder / "run.mcap"
        with path.open("rb") as f:
            reader = make_reader(f)
            summary = reader.get_summary()
            assert summary is not None and summary.statistics is not None
            stats = summary.statistics
            channels = {summary.channels[cid].topic: n for cid, n in sorted(stats.channel_message_counts.items())}
            cost = next(m.metadata for m in reader.iter_metadata() if m.name == "recording_cost")
        return {
            "mission": Path(args.mission).name,
            "scenario": Path(args.scenario).name,
            "seed": args.seed,
            "success": result.success,
            "write_errors": result.write_errors,
            "mcap_size_mb": round(path.stat().st_size / 1e6, 2),
            "ticks": int(cost["ticks"]),
            "tick_cost_ms_mean": float(cost["mean_ms"]),
            "tick_cost_ms_p99": float(cost["p99_ms"]),
            "tick_cost_ms_max": float(cost["max_ms"]),
            "messages": int(stats.message_count),
            "channels": dict(sorted(channels.items())),
            "run_wall_s": round(wall_s, 1),
            "goals": {"mcap_size_mb": 50.0, "tick_cost_ms_mean": 1.0},
        }
