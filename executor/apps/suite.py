"""Mission test suites (`SUITE.yaml`): what to run, what to expect, what must hold in every run.

A suite lists cases; each names a mission and a scenario, or a scenario family (a base scenario whose
pallets, camera mount and clutter are drawn at random from a seed), the expected outcome, and checks
that apply to every run. Files are relative to the suite file.

```yaml
name: example warehouse before go-live
checks:                               # every run of every case (a case's own `checks` override these)
  no_contact: true                    # nothing touched: people, boxes, racks, walls, other pallets
  travel_height: true                 # loaded and faster than creep speed: forks at travel height
  only_target_moved: true             # no pallet moved but those the mission's pickups name
  max_task_s: 600                     # every task within this (simulated s)
  max_replans: 3                      # re-plans per task at most
  delivered_within_m: 0.05            # a delivered pallet within this of its drop node (m) ...
  delivered_yaw_deg: 3.0              # ... and this (deg)
cases:
  - name: demo
    mission: pickup_delivery.yaml
    scenario: scenario_demo.yaml
    expect: success
  - name: misplaced_floor_pallets
    mission: pickup_floor.yaml
    family:
      base: scenario_floor.yaml       # the scenario the draws start from
      runs: 8
      seed: 1
      pallets: {nodes: [floor_b2], dx: [-0.10, 0.10], dy: [-0.30, 0.30], dyaw_deg: [-10, 10]}
      mount: {tilt_deg: [18, 26], pan_deg: [-2, 2], roll_deg: [-1.5, 1.5]}
      clutter: {count: [0, 1], choose: [{kind: person, x: 27.5, y: 9.5}]}
    expect: success
  - name: person_in_the_aisle
    mission: pickup_floor.yaml
    scenario: scenario_blocked.yaml
    expect: failure
    reasons: [path_blocked]           # the first failed task's reason is one of these
  - name: unknown_node
    mission: bad_mission.yaml
    expect: rejected                  # refused before anything moves
    message: "unknown node"           # a part of the refusal
```

Public API: `Suite`, `Case`, `Checks`, `Family`, `load_suite`, `SuiteError`, `RunSpec` (one run of a
case, picklable, made by `Suite.runs`).
"""

from __future__ import annotations

import re
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal

import numpy as np
from pydantic import Field, field_validator, model_validator

from palletpilot.geometry import PalletpilotError
from palletpilot.geometry.errors import collect, raise_problems
from palletpilot.geometry.fileio import FileModel, load_yaml_model, validate_model

Span = tuple[float, float]
"""A closed range [low, high] a value is drawn from, uniformly."""
CASE_NAME = re.compile(r"^[A-Za-z0-9][A-Za-z0-9_.-]{0,63}$")


class SuiteError(PalletpilotError):
    """A suite file that cannot be run as written; one line per problem naming the file and field."""


def _span(value: Span, name: str, low: float, high: float) -> Span:
    a, b = value
    if a > b:
        raise ValueError(f"{name}: low {a} is above high {b}")
    if a < low or b > high:
        raise ValueError(f"{name}: [{a}, {b}] is outside {low}..{high}")
    return value


class Checks(FileModel):
    """What must hold in every run (a `None` limit is not checked)."""

    no_contact: bool = True
    travel_height: bool = True
    only_target_moved: bool = True
    max_task_s: float | None = Field(None, gt=0.0, le=86_400.0)
    max_replans: int | None = Field(None, ge=0, le=100)
    delivered_within_m: float | None = Field(None, gt=0.0, le=5.0)
    delivered_yaw_deg: float | None = Field(None, gt=0.0, le=180.0)


class PalletDraw(FileModel):
    """Misplacement drawn for pallets at nodes: `nodes` (default: the mission's pickup nodes)."""

    nodes: list[str] | None = Field(None, min_length=1, max_length=1000)
    dx: Span = (0.0, 0.0)
    dy: Span = (0.0, 0.0)
    dyaw_deg: Span = (0.0, 0.0)

    @model_validator(mode="after")
    def _spans(self) -> PalletDraw:
        _span(self.dx, "dx", -2.0, 2.0)
        _span(self.dy, "dy", -2.0, 2.0)
        _span(self.dyaw_deg, "dyaw_deg", -180.0, 180.0)
        return self


class MountDraw(FileModel):
    """Camera mount angles drawn per run (degrees; unset: the base scenario's)."""

    tilt_deg: Span | None = None
    pan_deg: Span | None = None
    roll_deg: Span | None = None

    @model_validator(mode="after")
    def _spans(self) -> MountDraw:
        for name, low, high in (("tilt_deg", 0.0, 89.0), ("pan_deg", -90.0, 90.0), ("roll_deg", -180.0, 180.0)):
            value = getattr(self, name)
            if value is not None:
                _span(value, name, low, high)
        return self


class ClutterDraw(FileModel):
    """`count` (a range of whole numbers) distinct items of `choose` added per run (scenario clutter items)."""

    choose: list[dict[str, Any]] = Field(min_length=1, max_length=100)
    count: tuple[int, int] = (0, 1)

    @model_validator(mode="after")
    def _count(self) -> ClutterDraw:
        a, b = self.count
        if not 0 <= a <= b <= len(self.choose):
            raise ValueError(f"count: [{a}, {b}] must lie within 0..{len(self.choose)} (the items to choose from)")
        return self


class Family(FileModel):
    """A scenario family: `runs` scenarios drawn from `base` with `seed` (each run also gets its own
    simulator seed, so sensor noise differs too)."""

    base: str = Field(min_length=1, max_length=4096)
    runs: int = Field(1, ge=1, le=10_000)
    seed: int = Field(0, ge=0, le=2**32 - 1)
    pallets: PalletDraw | None = None
    mount: MountDraw | None = None
    clutter: ClutterDraw | None = None


class Case(FileModel):
    """One case: a mission in a scenario (or a family of them) and the outcome expected."""

    name: str
    mission: str = Field(min_length=1, max_length=4096)
    scenario: str | None = Field(None, min_length=1, max_length=4096)
    family: Family | None = None
    seeds: int = Field(1, ge=1, le=10_000, description="runs of a plain scenario, each with another seed")
    expect: Literal["success", "failure", "rejected"] = "success"
    reasons: list[str] = Field(default_factory=list, max_length=50)
    message: str | None = Field(None, min_length=1, max_length=500)
    checks: dict[str, Any] = Field(default_factory=dict)

    @field_validator("name")
    @classmethod
    def _name(cls, value: str) -> str:
        if not CASE_NAME.match(value):
            raise ValueError("1..64 letters, digits, '_', '.', '-' (it names the case's report folder)")
        return value

    @model_validator(mode="after")
    def _consistent(self) -> Case:
        if self.scenario is not None and self.family is not None:
            raise ValueError("give scenario or family, not both")
        if self.reasons and self.expect != "failure":
            raise ValueError("reasons: only with expect: failure")
        if self.message is not None and self.expect != "rejected":
            raise ValueError("message: only with expect: rejected")
        if self.family is not None and self.seeds != 1:
            raise ValueError("seeds: a family has runs instead")
        return self


class Suite(FileModel):
    """A suite file: a name, checks for every run, and the cases."""

    name: str = Field("suite", min_length=1, max_length=200)
    checks: Checks = Checks()
    cases: list[Case] = Field(min_length=1, max_length=10_000)
    folder: Path = Field(Path("."), exclude=True)
    source: str = Field("suite", exclude=True)

    @model_validator(mode="after")
    def _unique(self) -> Suite:
        seen: set[str] = set()
        for i, case in enumerate(self.cases):
            if case.name in seen:
                raise ValueError(f"cases[{i}].name: '{case.name}' is used twice")
            seen.add(case.name)
        return self

    def checks_of(self, case: Case) -> Checks:
        """The suite's checks with the case's own keys over them."""
        return Checks.model_validate({**self.checks.model_dump(), **case.checks})

    def runs(self, only: list[str] | None = None) -> list[RunSpec]:
        """Every run of every case (of `only`, when given), in file order; deterministic."""
        out: list[RunSpec] = []
        for case in self.cases:
            if only and case.name not in only:
                continue
            out += _case_runs(self, case)
        return out


@dataclass(frozen=True)
class RunSpec:
    """One run of a case: what a worker process needs (picklable)."""

    case: str
    index: int
    mission: Path
    checks: dict[str, Any]
    expect: str
    reasons: tuple[str, ...] = ()
    message: str | None = None
    scenario_path: Path | None = None
    scenario_doc: dict[str, Any] | None = None  # a drawn scenario (its folder: `scenario_folder`)
    scenario_folder: Path | None = None
    seed: int | None = None
    drawn: dict[str, Any] = field(default_factory=dict)  # what the family drew, for the report

    @property
    def label(self) -> str:
        """`case#k`: the name in tables, JUnit and report folders."""
        return f"{self.case}#{self.index}"


def _case_runs(suite: Suite, case: Case) -> list[RunSpec]:
    checks = suite.checks_of(case).model_dump()
    common: dict[str, Any] = {
        "case": case.name,
        "mission": suite.folder / case.mission,
        "checks": checks,
        "expect": case.expect,
        "reasons": tuple(case.reasons),
        "message": case.message,
    }
    if case.family is None:
        path = None if case.scenario is None else suite.folder / case.scenario
        if case.seeds == 1:
            return [RunSpec(index=0, scenario_path=path, **common)]
        return [RunSpec(index=k, scenario_path=path, seed=1000 + k, **common) for k in range(case.seeds)]
    return [RunSpec(index=k, **common, **draw) for k, draw in enumerate(_draws(suite, case, case.family))]


def _draws(suite: Suite, case: Case, fam: Family) -> list[dict[str, Any]]:
    """The family's scenarios, drawn from its seed: `scenario_doc`, `scenario_folder`, `seed`, `drawn`."""
    from palletpilot.executor.core.mission import load_mission
    from palletpilot.sim.scenario import load_scenario

    base_path = suite.folder / fam.base
    base = load_scenario(base_path)
    doc = base.model_dump(mode="json", exclude_unset=True)
    mission = load_mission(suite.folder / case.mission)
    targets = [t.node for t in mission.tasks if t.type == "pickup"]
    rng = np.random.default_rng(fam.seed)
    out = []
    for _ in range(fam.runs):
        run = {**doc, "pallets": [dict(p) for p in doc.get("pallets", [])], "clutter": list(doc.get("clutter", []))}
        drawn: dict[str, Any] = {}
        if fam.pallets is not None:
            nodes = fam.pallets.nodes or targets
            for p in run["pallets"]:
                if p.get("node") in nodes:
                    for key in ("dx", "dy", "dyaw_deg"):
                        lo, hi = getattr(fam.pallets, key)
                        p[key] = round(float(rng.uniform(lo, hi)), 4)
                    drawn[p["node"]] = {k: p[k] for k in ("dx", "dy", "dyaw_deg")}
        if fam.mount is not None:
            camera = dict(run.get("camera", {}))
            mount = dict(camera.get("mount", {}))
            for key in ("tilt_deg", "pan_deg", "roll_deg"):
                span = getattr(fam.mount, key)
                if span is not None:
                    mount[key] = drawn[key] = round(float(rng.uniform(*span)), 3)
            run["camera"] = {**camera, "mount": mount}
        if fam.clutter is not None:
            lo, hi = fam.clutter.count
            k = int(rng.integers(lo, hi + 1))
            picked = sorted(rng.choice(len(fam.clutter.choose), size=k, replace=False).tolist()) if k else []
            run["clutter"] += [fam.clutter.choose[i] for i in picked]
            drawn["clutter"] = picked
        seed = int(rng.integers(2**31))
        run["seed"] = seed
        out.append({"scenario_doc": run, "scenario_folder": base.folder, "seed": seed, "drawn": drawn})
    return out


def load_suite(path: str | Path) -> Suite:
    """Read a suite file and check that every file it names exists (one line per problem, `SuiteError`).

    Whether a mission or scenario is valid is the runs' business (a case may expect a refusal); a
    family's base scenario and mission must be valid, since the draws start from them.
    """
    path = Path(path)
    suite = load_yaml_model(path, Suite, SuiteError)
    suite.folder, suite.source = path.parent, str(path)
    problems: list[str] = []
    for i, case in enumerate(suite.cases):
        files = [("mission", case.mission), ("scenario", case.scenario)]
        if case.family is not None:
            files.append(("family.base", case.family.base))
        for key, name in files:
            if name is not None and not (suite.folder / name).is_file():
                problems.append(f"{path}: cases[{i}].{key}: {suite.folder / name}: no such file")
        merged = {**suite.checks.model_dump(), **case.checks}
        collect(problems, lambda: validate_model(merged, Checks, f"{path}: cases[{i}].checks", SuiteError))  # noqa: B023
    raise_problems(problems, SuiteError)
    return suite
