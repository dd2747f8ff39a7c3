"""What `palletpilot test` prints and writes: progress lines, the summary table, JUnit XML, suite.json.

- `progress_line(result, done, total)`: one line per finished run (stderr, as runs finish);
- `summary_table(suite_name, results, wall_s)`: per case the runs, how many met their expectation, the
  outcomes, the simulated time (summed over its runs) and the elapsed time (from its first run's start
  to its last run's end: runs of other cases overlap it with `--jobs`); then each run that did not,
  with every reason and the paths to its report.json and trajectory.png;
- `junit_xml(suite_name, results)`: one `<testcase>` per run (`classname` the suite and case, `name`
  `case#k`, `time` the run's elapsed time), a `<failure>` with every problem when it did not meet its
  case, and a `<system-out>` of plain `key: value` lines (outcome, times, report folder, what the family
  drew), so a CI server (GitLab, Jenkins, GitHub via an action) shows the runs;
- `suite_json(...)`: the same as JSON (`DIR/suite.json`);
- `drawn_text(drawn)`: what a family drew for a run, as one line of text.

Public API: the five functions above.
"""

from __future__ import annotations

import xml.etree.ElementTree as ET
from collections import Counter
from typing import Any

from palletpilot.executor.apps.suite_run import RunResult


def progress_line(r: RunResult, done: int, total: int) -> str:
    """`[3/12] ok   demo#0  success in 12.3 s (88 s simulated)` or `FAIL` with the first problem."""
    mark = "ok  " if r.met else "FAIL"
    what = r.outcome + (f" ({r.reason})" if r.reason and r.outcome != "success" else "")
    tail = "" if r.met else f": {r.problems[0]}"
    width = len(str(total))
    timing = f"in {r.wall_s:.1f} s ({r.simulated_s:.0f} s simulated)"
    return f"[{done:>{width}}/{total}] {mark} {r.label}  {what} {timing}{tail}"


def summary_table(suite_name: str, results: list[RunResult], wall_s: float) -> str:
    """The summary a person reads at the end of `palletpilot test`."""
    cases: dict[str, list[RunResult]] = {}
    for r in results:
        cases.setdefault(r.case, []).append(r)
    rows = [("case", "runs", "met", "outcomes", "sim s", "elapsed s")]
    for name, runs in cases.items():
        outcomes = Counter(r.outcome for r in runs)
        rows.append(
            (
                name,
                str(len(runs)),
                str(sum(r.met for r in runs)),
                ", ".join(f"{k} {v}" for k, v in sorted(outcomes.items())),
                f"{sum(r.simulated_s for r in runs):.0f}",
                f"{_elapsed(runs):.1f}",
            )
        )
    widths = [max(len(row[c]) for row in rows) for c in range(len(rows[0]))]
    lines = [f"suite: {suite_name}"]
    for k, row in enumerate(rows):
        lines.append(
            "  ".join(
                cell.ljust(w) if c in (0, 3) else cell.rjust(w)
                for c, (cell, w) in enumerate(zip(row, widths, strict=True))
            )
        )
        if k == 0:
            lines.append("  ".join("-" * w for w in widths))
    met = sum(r.met for r in results)
    sim_s = sum(r.simulated_s for r in results)
    lines.append(f"{met} of {len(results)} runs met their case in {wall_s:.1f} s ({sim_s / 60:.1f} simulated minutes)")
    lines.append("(sim s: simulated time summed over the case's runs; elapsed s: its first start to its last end)")
    failed = [r for r in results if not r.met]
    if failed:
        lines.append("")
        lines.append("not met:")
        for r in failed:
            lines.append(f"  {r.label}: {r.outcome}" + (f" ({r.reason})" if r.reason else ""))
            lines += [f"    - {p}" for p in r.problems]
            if r.drawn:
                lines.append(f"    drawn: {drawn_text(r.drawn)}")
            if r.report_dir:
                lines.append(f"    report: {r.report_dir}/report.json")
            if r.trajectory_png:
                lines.append(f"    trajectory: {r.trajectory_png}")
    return "\n".join(lines)


def junit_xml(suite_name: str, results: list[RunResult], wall_s: float) -> str:
    """JUnit XML of the runs (one testsuite, one testcase per run)."""
    failures = sum(not r.met and r.outcome != "error" for r in results)
    errors = sum(r.outcome == "error" for r in results)
    root = ET.Element(
        "testsuites", name=suite_name, tests=str(len(results)), failures=str(failures), errors=str(errors)
    )
    suite = ET.SubElement(
        root,
        "testsuite",
        name=suite_name,
        tests=str(len(results)),
        failures=str(failures),
        errors=str(errors),
        time=f"{wall_s:.2f}",
    )
    for r in results:
        case = ET.SubElement(
            suite, "testcase", classname=f"{suite_name}.{r.case}", name=r.label, time=f"{r.wall_s:.2f}"
        )
        if not r.met:
            tag = "error" if r.outcome == "error" else "failure"
            body = "\n".join([*r.problems, *([f"report: {r.report_dir}/report.json"] if r.report_dir else [])])
            ET.SubElement(case, tag, message=r.problems[0] if r.problems else r.outcome).text = body
        out = [
            f"outcome: {r.outcome}" + (f" ({r.reason})" if r.reason else ""),
            f"simulated_s: {r.simulated_s:.2f}",
            f"elapsed_s: {r.wall_s:.2f}",
        ]
        if r.report_dir:
            out.append(f"report: {r.report_dir}")
            if r.trajectory_png:
                out.append(f"trajectory: {r.trajectory_png}")
        if r.drawn:
            out.append(f"drawn: {drawn_text(r.drawn)}")
        ET.SubElement(case, "system-out").text = "\n".join(out)
    ET.indent(root)
    return '<?xml version="1.0" encoding="UTF-8"?>\n' + ET.tostring(root, encoding="unicode") + "\n"


def _elapsed(runs: list[RunResult]) -> float:
    """Seconds from the first of `runs` starting to the last one ending."""
    return max(r.started_s + r.wall_s for r in runs) - min(r.started_s for r in runs)


def _number(value: Any) -> str:
    """A drawn value as text: numbers with `:g`, lists comma-separated."""
    if isinstance(value, list):
        return "[" + ", ".join(_number(v) for v in value) + "]"
    return f"{value:g}" if isinstance(value, float) else str(value)


def drawn_text(drawn: dict[str, Any]) -> str:
    """What a family drew for a run, one line: `floor_b2 dx -0.05 dy 0.21 dyaw_deg 3.2; tilt_deg 22.4; clutter [1]`."""
    parts = []
    for key, value in drawn.items():
        if isinstance(value, dict):
            parts.append(" ".join([key, *(f"{k} {_number(v)}" for k, v in value.items())]))
        else:
            parts.append(f"{key} {_number(value)}")
    return "; ".join(parts)


def suite_json(suite_name: str, results: list[RunResult], wall_s: float, jobs: int) -> dict[str, Any]:
    """The suite's results as JSON: totals and every run."""
    sim_s = sum(r.simulated_s for r in results)
    return {
        "suite": suite_name,
        "runs": len(results),
        "met": sum(r.met for r in results),
        "wall_s": round(wall_s, 2),
        "jobs": jobs,
        "simulated_s": round(sim_s, 1),
        "wall_s_per_simulated_minute": round(sum(r.wall_s for r in results) / (sim_s / 60.0), 2) if sim_s else None,
        "results": [r.to_json() for r in results],
    }
