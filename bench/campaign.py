"""`palletpilot bench campaign --runs N --executor local|ray [--jobs N] [--seed S] [--case NAME] [--scaling]`:
how many suite runs a minute an executor gets through, and how that scales with the runs at a time.

The campaign is one case of the example suite (`missions/suite/suite.yaml`, default `floor_envelope`:
misplaced floor pallets, camera mounts, people and boxes beside the route) run `--runs` times: a family
draws `--runs` scenarios from `--seed`, a plain case runs with `--runs` seeds. The runs go through what
`palletpilot test` uses: `run_case` in `--jobs` worker processes (`local`), or `suite_ray.run_on_ray` on a
local Ray instance (or `--ray-address`) with `--jobs` tasks at a time (`ray`; the inputs sent through the
object store, the reports packed back). The reports land in a temporary folder, deleted after.

Figures: `wall_s` (the campaign, from the first submission to the last result; Ray's own start apart,
`ray_start_s`), `runs_per_minute`, `run_wall_s_mean` (one run's own time), `busy_fraction` (the runs' own
time over `jobs` x `wall_s`: 1.0 is no executor overhead and no idle worker), `verdicts_sha256` (of every
run's label, outcome, met, reason, problems and simulated time: equal on both executors when the verdicts
are), `hours_for_5000_runs` at this rate; with `--scaling` the same campaign again one run at a time
(after the first, so both executors' first campaigns start with cold workers): `runs_per_minute_1_job`,
`speedup` and `efficiency` (speedup / jobs).
"""

from __future__ import annotations

import argparse
import hashlib
import json
import logging
import os
import tempfile
import time
from collections import Counter
from dataclasses import replace
from pathlib import Path
from typing import Any

from palletpilot.executor.apps.cli_args import count, seed
from palletpilot.executor.apps.suite import RunSpec, Suite, SuiteError, load_suite
from palletpilot.executor.apps.suite_ray import Executor, ray_missing, run_on_ray
from palletpilot.executor.apps.suite_run import RunResult, run_case
from palletpilot.geometry.fileio import bundled_path
from palletpilot.geometry.processes import spawn_pool

SUITE = bundled_path("missions", "suite", "suite.yaml")
DEFAULT_CASE = "floor_envelope"
VERDICT = ("label", "outcome", "met", "reason", "problems", "simulated_s")
"""What must be equal, run by run, on either executor."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument("--runs", type=count(1, 10_000), default=8)
    parser.add_argument("--executor", choices=[e.value for e in Executor], default=Executor.LOCAL.value)
    parser.add_argument("--jobs", type=count(1, 256), help="runs at a time (default: this machine's cores)")
    parser.add_argument("--seed", type=seed, default=1, help="the family's draws (a plain case: its first seed)")
    parser.add_argument("--case", default=DEFAULT_CASE, help=f"a case of the example suite (default {DEFAULT_CASE})")
    parser.add_argument("--ray-address", metavar="ADDR", help="with --executor ray: an existing cluster")
    parser.add_argument("--scaling", action="store_true", help="first the same campaign one run at a time")


def campaign_specs(case: str, runs: int, draw_seed: int) -> list[RunSpec]:
    """`runs` runs of the example suite's `case` (a family drawn from `draw_seed`, else as many seeds).
    Raises `SuiteError` naming the cases for an unknown one."""
    example = load_suite(SUITE)
    doc = example.model_dump(mode="json", exclude_unset=True)
    names = [c["name"] for c in doc["cases"]]
    if case not in names:
        raise SuiteError(f"--case: no case '{case}' in {SUITE} (cases: {', '.join(names)})")
    picked = dict(doc["cases"][names.index(case)])
    if "family" in picked:
        picked["family"] = {**picked["family"], "runs": runs, "seed": draw_seed}
    else:
        picked["seeds"] = runs
    suite = Suite.model_validate({**doc, "cases": [picked]})
    suite.folder, suite.source = example.folder, example.source
    specs = suite.runs()
    if "family" not in picked:  # seeds 1000 + k as `palletpilot test` gives them, moved by --seed
        specs = [replace(s, seed=draw_seed * 10_000 + 1000 + s.index) for s in specs]
    return specs


def _local(specs: list[RunSpec], report: Path, jobs: int) -> list[RunResult]:
    """The runs in `jobs` worker processes, as `palletpilot test --executor local` runs them."""
    if jobs == 1:
        return [run_case(spec, report) for spec in specs]
    with spawn_pool(jobs) as pool:
        return list(pool.map(run_case, specs, [report] * len(specs)))


def _campaign(
    specs: list[RunSpec], executor: Executor, jobs: int, address: str | None
) -> tuple[list[RunResult], float]:
    """Run the campaign once; its results and wall time (s)."""
    with tempfile.TemporaryDirectory(prefix="palletpilot-bench-campaign-") as tmp:
        t0 = time.perf_counter()
        if executor is Executor.RAY:
            outcome = run_on_ray(specs, Path(tmp), address, jobs, lambda r, done: None)
            results = outcome.results
        else:
            results = _local(specs, Path(tmp), jobs)
        return results, time.perf_counter() - t0


def _verdicts_sha256(results: list[RunResult]) -> str:
    rows = [{k: getattr(r, k) for k in VERDICT} for r in results]
    return hashlib.sha256(json.dumps(rows, sort_keys=True, default=str).encode()).hexdigest()


def run(args: argparse.Namespace) -> dict[str, Any]:
    """Measure and return the figures."""
    executor = Executor(args.executor)
    if executor is Executor.RAY and (missing := ray_missing()):
        raise SuiteError(missing)
    if executor is Executor.LOCAL and args.ray_address:
        raise SuiteError("--ray-address: only with --executor ray")
    jobs = args.jobs or os.cpu_count() or 1
    specs = campaign_specs(args.case, args.runs, args.seed)
    ray_start_s = None
    if executor is Executor.RAY:
        import ray

        t0 = time.perf_counter()
        try:
            ray.init(
                address=args.ray_address, include_dashboard=False, logging_level=logging.ERROR, log_to_driver=False
            )
        except Exception as exc:  # ConnectionError, ValueError for a bad address: the user's input
            raise SuiteError(f"--ray-address {args.ray_address}: cannot reach the Ray cluster: {exc}") from None
        ray_start_s = round(time.perf_counter() - t0, 2)
    try:
        results, wall = _campaign(specs, executor, jobs, args.ray_address)
        single = _campaign(specs, executor, 1, args.ray_address)[1] if args.scaling and jobs > 1 else None
    finally:
        if executor is Executor.RAY:
            ray.shutdown()
    per_minute = len(results) / wall * 60.0
    out: dict[str, Any] = {
        "case": args.case,
        "runs": len(results),
        "executor": executor.value,
        "jobs": jobs,
        "seed": args.seed,
        "ray_start_s": ray_start_s,
        "wall_s": round(wall, 2),
        "runs_per_minute": round(per_minute, 2),
        "run_wall_s_mean": round(sum(r.wall_s for r in results) / len(results), 2),
        "busy_fraction": round(sum(r.wall_s for r in results) / (jobs * wall), 3),
        "simulated_minutes": round(sum(r.simulated_s for r in results) / 60.0, 1),
        "met": sum(r.met for r in results),
        "outcomes": dict(sorted(Counter(r.outcome for r in results).items())),
        "retried": sum(r.retried for r in results),
        "verdicts_sha256": _verdicts_sha256(results),
        "hours_for_5000_runs": round(5000 / per_minute / 60.0, 2),
    }
    if single is not None:
        one = len(results) / single * 60.0
        out |= {
            "runs_per_minute_1_job": round(one, 2),
            "speedup": round(per_minute / one, 2),
            "efficiency": round(per_minute / one / jobs, 3),
        }
    return out
