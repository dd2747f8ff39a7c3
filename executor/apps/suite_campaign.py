"""The campaign report of `palletpilot test`: what a suite's families covered, and where to look first.

`campaign_json(suite, results)` gives, per family (a case with `family:`), every parameter it drew
against the outcome: the span the suite allows, the values drawn, and the span cut into bins (five equal
bins for a continuous value, one per whole number for a count) with the runs, those that met their case
and the outcomes in each, so an empty or failing corner of the envelope shows; then the runs that did not
meet their case and the slowest runs, each with its report.json, run.mcap and trajectory.png paths.
`write_campaign(report, suite, results)` writes it as `REPORT/campaign.json` and one plot per family
(`REPORT/campaign/<case>.png`: each parameter's drawn values against the outcome, met or not, over the
allowed span), atomically, beside suite.json.

Parameters (names in the JSON; units as named): `<node>.dx`, `<node>.dy` (m, in the pallet node's frame)
and `<node>.dyaw_deg` per drawn pallet; `tilt_deg`, `pan_deg`, `roll_deg` of the camera mount;
`clutter.count` (items added) and `clutter.<kind>` (of them, how many of each kind: `clutter.person` are
the people).

Public API: `Unit`, `campaign_json`, `write_campaign`, `SLOWEST`, `MAX_LISTED`, `BINS`.
"""

from __future__ import annotations

import io
from collections import Counter
from collections.abc import Callable
from dataclasses import dataclass
from enum import Enum
from functools import partial
from pathlib import Path
from typing import Any

from palletpilot.executor.apps.suite import Family, Suite
from palletpilot.executor.apps.suite_run import RunResult
from palletpilot.geometry.fileio import write_atomic, write_json

BINS = 5
"""Equal bins a continuous parameter's span is cut into."""
SLOWEST = 10
"""The slowest runs listed."""
MAX_LISTED = 100
"""The failing runs listed at most (`failing_total` counts them all)."""
OUTCOMES = ("success", "failure", "rejected", "error")


class Unit(str, Enum):
    """A drawn parameter's unit."""

    M = "m"
    DEG = "deg"
    COUNT = "count"


@dataclass(frozen=True)
class Parameter:
    """One drawn parameter of a family: its name, unit, allowed span and how to read it from `drawn`."""

    name: str
    unit: Unit
    span: tuple[float, float]
    read: Callable[[dict[str, Any]], float | None]

    def bins(self) -> list[tuple[float, float]]:
        """The span cut into bins: whole numbers for a count, else `BINS` equal ones (one for a point)."""
        lo, hi = self.span
        if self.unit is Unit.COUNT:
            return [(float(k), float(k)) for k in range(int(lo), int(hi) + 1)]
        if hi <= lo:
            return [(lo, hi)]
        step = (hi - lo) / BINS
        return [(lo + k * step, hi if k == BINS - 1 else lo + (k + 1) * step) for k in range(BINS)]


def _parameters(fam: Family, drawn: list[dict[str, Any]]) -> list[Parameter]:
    """The parameters `fam` draws (pallet nodes as the runs drew them)."""
    out: list[Parameter] = []
    if fam.pallets is not None:
        nodes = sorted({k for d in drawn for k, v in d.items() if isinstance(v, dict)})
        for node in nodes:
            for key, unit in (("dx", Unit.M), ("dy", Unit.M), ("dyaw_deg", Unit.DEG)):
                span = getattr(fam.pallets, key)
                out.append(Parameter(f"{node}.{key}", unit, span, partial(_pallet_value, node, key)))
    if fam.mount is not None:
        for key in ("tilt_deg", "pan_deg", "roll_deg"):
            span = getattr(fam.mount, key)
            if span is not None:
                out.append(Parameter(key, Unit.DEG, span, partial(_value, key)))
    if fam.clutter is not None:
        choose = fam.clutter.choose
        lo, hi = fam.clutter.count
        out.append(Parameter("clutter.count", Unit.COUNT, (lo, hi), partial(_count, choose, None)))
        for kind in sorted({str(item.get("kind")) for item in choose}):
            most = min(hi, sum(str(item.get("kind")) == kind for item in choose))
            out.append(Parameter(f"clutter.{kind}", Unit.COUNT, (0, most), partial(_count, choose, kind)))
    return out


def _value(key: str, drawn: dict[str, Any]) -> float | None:
    """A mount angle a run drew (None: not drawn)."""
    value = drawn.get(key)
    return None if value is None else float(value)


def _pallet_value(node: str, key: str, drawn: dict[str, Any]) -> float | None:
    """A pallet's misplacement a run drew at `node` (None: not drawn)."""
    value = drawn.get(node, {}).get(key)
    return None if value is None else float(value)


def _count(choose: list[dict[str, Any]], kind: str | None, drawn: dict[str, Any]) -> float | None:
    """How many clutter items a run drew (of `kind`, when given); None when it drew none of the list."""
    picked = drawn.get("clutter")
    if picked is None:
        return None
    return float(sum(kind is None or str(choose[i].get("kind")) == kind for i in picked))


def _in_bin(value: float, k: int, bins: list[tuple[float, float]], unit: Unit) -> bool:
    lo, hi = bins[k]
    if unit is Unit.COUNT:
        return value == lo
    return lo <= value < hi or (k == len(bins) - 1 and lo <= value <= hi)


def _coverage(p: Parameter, runs: list[RunResult]) -> dict[str, Any]:
    """One parameter's span, drawn values and bins (runs, met, outcomes in each)."""
    values = [(p.read(r.drawn), r) for r in runs]
    seen = [(float(v), r) for v, r in values if v is not None]
    bins = p.bins()
    rows: list[dict[str, Any]] = []
    for k, (lo, hi) in enumerate(bins):
        inside = [r for v, r in seen if _in_bin(v, k, bins, p.unit)]
        rows.append(
            {
                "low": round(lo, 6),
                "high": round(hi, 6),
                "runs": len(inside),
                "met": sum(r.met for r in inside),
                "outcomes": dict(sorted(Counter(r.outcome for r in inside).items())),
            }
        )
    covered = sum(row["runs"] > 0 for row in rows)
    return {
        "unit": p.unit.value,
        "span": [p.span[0], p.span[1]],
        "drawn_min": min((v for v, _ in seen), default=None),
        "drawn_max": max((v for v, _ in seen), default=None),
        "bins": rows,
        "bins_covered": covered,
        "coverage": round(covered / len(rows), 3),
    }


def _paths(r: RunResult) -> dict[str, str | None]:
    """A run's report.json, run.mcap and trajectory.png, where they exist."""
    if r.report_dir is None:
        return {"report": None, "mcap": None, "trajectory": None}
    folder = Path(r.report_dir)
    found = {k: folder / name for k, name in (("report", "report.json"), ("mcap", "run.mcap"))}
    return {**{k: str(p) if p.is_file() else None for k, p in found.items()}, "trajectory": r.trajectory_png}


def _listed(r: RunResult) -> dict[str, Any]:
    return {
        "label": r.label,
        "case": r.case,
        "outcome": r.outcome,
        "met": r.met,
        "reason": r.reason,
        "problems": r.problems,
        "wall_s": r.wall_s,
        "simulated_s": r.simulated_s,
        "retried": r.retried,
        "drawn": r.drawn,
        **_paths(r),
    }


def _family(name: str, fam: Family, runs: list[RunResult]) -> dict[str, Any]:
    """A family's runs, outcomes, each parameter's coverage, every run's drawn values and its plot's path."""
    params = _parameters(fam, [r.drawn for r in runs])
    return {
        "runs": len(runs),
        "met": sum(r.met for r in runs),
        "outcomes": dict(sorted(Counter(r.outcome for r in runs).items())),
        "seed": fam.seed,
        "parameters": {p.name: _coverage(p, runs) for p in params},
        "drawn": [
            {"label": r.label, "outcome": r.outcome, "met": r.met, "values": {p.name: p.read(r.drawn) for p in params}}
            for r in runs
        ],
        "plot": f"campaign/{name}.png" if params else None,  # none for a family that only draws seeds
    }


def campaign_json(suite: Suite, results: list[RunResult]) -> dict[str, Any]:
    """The campaign report of `results` (runs of `suite`): families' coverage, failing and slowest runs."""
    by_case: dict[str, list[RunResult]] = {}
    for r in results:
        by_case.setdefault(r.case, []).append(r)
    families = {
        c.name: _family(c.name, c.family, by_case[c.name])
        for c in suite.cases
        if c.family is not None and c.name in by_case
    }
    failing = [r for r in results if not r.met]
    slowest = sorted(results, key=lambda r: (-r.wall_s, r.label))[:SLOWEST]
    return {
        "suite": suite.name,
        "runs": len(results),
        "met": sum(r.met for r in results),
        "families": families,
        "failing_total": len(failing),
        "failing": [_listed(r) for r in failing[:MAX_LISTED]],
        "slowest": [_listed(r) for r in slowest],
    }


def _plot(name: str, doc: dict[str, Any]) -> bytes:
    """One family's parameters: each drawn value (x) against the outcome (y), met green, not met red."""
    from matplotlib.backends.backend_agg import FigureCanvasAgg
    from matplotlib.figure import Figure

    params = doc["parameters"]
    cols = min(3, max(1, len(params)))
    rows = max(1, -(-len(params) // cols))
    fig = Figure(figsize=(4.2 * cols, 2.6 * rows + 0.6), layout="constrained")
    FigureCanvasAgg(fig)
    fig.suptitle(
        f"{name}: {doc['met']} of {doc['runs']} runs met their case (green met, red not; grey: the span allowed)"
    )
    axes = fig.subplots(rows, cols, squeeze=False).ravel()
    for ax, (pname, cov) in zip(axes, params.items(), strict=False):
        count = cov["unit"] == Unit.COUNT.value
        lo, hi = (cov["span"][0] - 0.5, cov["span"][1] + 0.5) if count else cov["span"]
        ax.axvspan(lo, hi, color="0.92", zorder=0)
        for k, run in enumerate(doc["drawn"]):
            value = run["values"].get(pname)
            if value is None:
                continue
            y = OUTCOMES.index(run["outcome"]) + 0.3 * (((k * 0.618) % 1.0) - 0.5)  # spread, deterministic
            ax.plot(value, y, "o", ms=5, color="tab:green" if run["met"] else "tab:red", alpha=0.8)
        if count:
            ax.set_xticks(range(int(cov["span"][0]), int(cov["span"][1]) + 1))
            ax.set_xlim(lo - 0.2, hi + 0.2)
        else:
            for edge in [b["low"] for b in cov["bins"][1:]]:
                ax.axvline(edge, color="white", lw=1.0, zorder=0)  # the bins the coverage counts
        ax.set_yticks(range(len(OUTCOMES)), OUTCOMES)
        ax.set_ylim(-0.6, len(OUTCOMES) - 0.4)
        ax.set_xlabel(f"{pname} ({cov['unit']})")
        ax.set_title(f"{cov['bins_covered']} of {len(cov['bins'])} bins drawn", fontsize=9)
    for ax in axes[len(params) :]:
        ax.set_visible(False)
    buf = io.BytesIO()
    fig.savefig(buf, format="png", dpi=90)
    return buf.getvalue()


def write_campaign(report: Path, suite: Suite, results: list[RunResult]) -> list[Path]:
    """Write `report/campaign.json` and `report/campaign/<family>.png` (atomically); the paths written.
    Raises `OutputError` (one line) when one cannot be written."""
    doc = campaign_json(suite, results)
    written = [write_json(report / "campaign.json", doc)]
    for name, fam in doc["families"].items():
        if fam["plot"] is not None:
            written.append(write_atomic(report / fam["plot"], _plot(name, fam)))
    return written
