"""`palletpilot test SUITE.yaml [--jobs N] [--executor local|ray] [--ray-address ADDR] [--junit FILE]
[--report DIR] [--only NAME,...] [--json]`.

Runs every case of a mission test suite (`executor.suite`) in the simulator, `--jobs` worker processes
at a time (each run is deterministic for its seed, whatever the order), prints a line per finished run
on stderr, then the summary table (each run that did not meet its case with its reasons and the paths
to its report and trajectory image); `--junit FILE` writes JUnit XML, `--report DIR` (default
`out/test/<suite file's stem>`) keeps every run's report folder (`DIR/<case>/<k>/`), `DIR/suite.json`
and the campaign report (`DIR/campaign.json`, `DIR/campaign/<family>.png`: `executor.apps.suite_campaign`);
the last lines say where they landed.
`--executor ray` runs each run as a Ray task instead (`executor.apps.suite_ray`: a local Ray instance, or the
cluster at `--ray-address`; `--jobs` then caps the runs at a time, default the cluster's CPUs); Ctrl-C
there cancels the cluster's tasks, writes the summary and JUnit of the runs that finished, exit 130.

Exit codes: 0 every run met its case, 1 some did not, 2 a bad suite file or option (one line per
problem), 3 an output that could not be written.
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from concurrent.futures import as_completed
from pathlib import Path

from palletpilot.executor.apps.cli_args import count, out_file, out_folder
from palletpilot.executor.apps.suite import RunSpec, SuiteError, load_suite
from palletpilot.executor.apps.suite_campaign import write_campaign
from palletpilot.executor.apps.suite_inputs import gather_inputs
from palletpilot.executor.apps.suite_ray import Executor, ray_missing, run_on_ray
from palletpilot.executor.apps.suite_report import junit_xml, progress_line, suite_json, summary_table
from palletpilot.executor.apps.suite_run import RunResult, run_case
from palletpilot.geometry.fileio import write_atomic, write_json
from palletpilot.geometry.processes import spawn_pool

DEFAULT_REPORT_ROOT = Path("out") / "test"
"""Where `palletpilot test` keeps the runs' reports without --report (`out/` is ignored by git)."""


def _run_all(specs: list[RunSpec], report: Path, jobs: int) -> list[RunResult]:
    """Every run, `jobs` processes at a time; results in the suite's order, progress as they finish."""
    results: dict[int, RunResult] = {}
    total = len(specs)
    if jobs <= 1:
        for k, spec in enumerate(specs):
            results[k] = run_case(spec, report)
            print(progress_line(results[k], k + 1, total), file=sys.stderr, flush=True)
    else:
        with spawn_pool(jobs) as pool:
            futures = {pool.submit(run_case, spec, report): k for k, spec in enumerate(specs)}
            for done, fut in enumerate(as_completed(futures), start=1):
                k = futures[fut]
                results[k] = fut.result()
                print(progress_line(results[k], done, total), file=sys.stderr, flush=True)
    return [results[k] for k in range(total)]


def cmd_test(args: argparse.Namespace) -> int:
    """Load the suite, run its cases, report; exit 0 only when every run met its case."""
    suite = load_suite(args.suite)
    only = [n for n in (args.only or "").split(",") if n]
    unknown = [n for n in only if n not in {c.name for c in suite.cases}]
    if unknown:
        known = ", ".join(c.name for c in suite.cases)
        raise SuiteError(f"--only: no case named {', '.join(unknown)} in {args.suite} (cases: {known})")
    executor = Executor(args.executor)
    if executor is Executor.RAY and (missing := ray_missing()):
        raise SuiteError(missing)
    if executor is Executor.LOCAL and args.ray_address:
        raise SuiteError("--ray-address: only with --executor ray")
    specs = suite.runs(only)
    report = Path(args.report or DEFAULT_REPORT_ROOT / Path(args.suite).stem).resolve()
    report.mkdir(parents=True, exist_ok=True)
    at_a_time = str(args.jobs or (1 if executor is Executor.LOCAL else "the cluster's CPUs"))
    cases = len({s.case for s in specs})
    print(
        f"{suite.name}: {len(specs)} runs of {cases} cases, {at_a_time} at a time ({executor.value})",
        file=sys.stderr,
    )
    t0 = time.perf_counter()
    interrupted, jobs = False, args.jobs or 1
    if executor is Executor.RAY:

        def progress(r: RunResult, done: int) -> None:
            print(progress_line(r, done, len(specs)), file=sys.stderr, flush=True)

        inputs = gather_inputs(specs, Path(args.suite))
        outcome = run_on_ray(specs, report, args.ray_address, args.jobs, progress, inputs)
        results, interrupted, jobs = outcome.results, outcome.interrupted, outcome.jobs
    else:
        results = _run_all(specs, report, jobs)
    wall_s = time.perf_counter() - t0
    doc = suite_json(suite.name, results, wall_s, jobs)
    write_json(report / "suite.json", doc)
    write_campaign(report, suite, results)
    if args.junit:
        write_atomic(args.junit, junit_xml(suite.name, results, wall_s))
    print(json.dumps(doc, indent=2) if args.json else summary_table(suite.name, results, wall_s))
    where = sys.stderr if args.json else sys.stdout  # --json: stdout holds the JSON alone
    print(f"reports: {report}/ (suite.json, campaign.json, CASE/K/report.json)", file=where)
    if args.junit:
        print(f"JUnit: {Path(args.junit).resolve()}", file=where)
    if interrupted:
        done = f"{len(results)} of {len(specs)} runs finished"
        print(f"interrupted: {done}, the cluster's tasks cancelled", file=sys.stderr)
        return 130
    return 0 if all(r.met for r in results) else 1


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register `test` on the `palletpilot` sub-command parser."""
    p = subparsers.add_parser("test", help="run a mission test suite (SUITE.yaml) in the simulator")
    p.add_argument("suite", metavar="SUITE.yaml", help="the suite file (cases, expectations, checks)")
    p.add_argument(
        "--jobs", type=count(1, 256), help="runs at a time (local: worker processes, default 1; ray: default all CPUs)"
    )
    p.add_argument(
        "--executor",
        choices=[e.value for e in Executor],
        default=Executor.LOCAL.value,
        help="local worker processes (default) or Ray tasks (pip install 'palletpilot[cluster]')",
    )
    p.add_argument("--ray-address", metavar="ADDR", help="with --executor ray: ray://HOST:10001, auto or HOST:PORT")
    p.add_argument("--junit", type=out_file(".xml"), metavar="FILE.xml", help="write JUnit XML")
    p.add_argument("--report", type=out_folder, metavar="DIR", help="report folder (default out/test/SUITE)")
    p.add_argument("--only", metavar="NAME[,NAME]", help="run only these cases")
    p.add_argument("--json", action="store_true", help="print the results as JSON instead of the table")
    p.set_defaults(func=cmd_test)
