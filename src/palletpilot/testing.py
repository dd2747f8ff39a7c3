"""pytest plugin for mission tests in Python: the `run_mission` fixture and assertions on its result.

Installed with palletpilot (entry point `pytest11`), so any project with palletpilot installed can write:

```python
from palletpilot.testing import assert_checks, assert_failed, assert_succeeded


def test_floor_pickup(run_mission):
    result = run_mission("missions/pickup_floor_b2.yaml", "missions/floor_b2.yaml", seed=4)
    assert_succeeded(result)
    assert_checks(result, delivered_within_m=0.05)   # + no contact, travel height, only the target moved


def test_person_blocks_the_aisle(run_mission):
    result = run_mission("move.yaml", scenario={"map": "warehouse.yaml", "start": "b1", ...}, folder="missions")
    assert_failed(result, "path_blocked")
```

`run_mission(mission, scenario=None, *, seed=None, folder=None, **run_options)` runs the mission in the
simulator with its report in the test's `tmp_path` and returns an `executor.app.SimRun` (`success`,
`summary`, `sim`, `runner`, `report`). `scenario` is a scenario file, a scenario mapping (files in it
relative to `folder`), a `sim.scenario.Scenario`, or None (the default warehouse). The checks are
those of `palletpilot test` (`executor.suite_run.check_run`), so a suite case and a pytest test mean
the same thing.

Public API: the fixture `run_mission`; `assert_succeeded`, `assert_failed`, `assert_checks`, `checks_of`.
"""

from __future__ import annotations

from collections.abc import Callable
from pathlib import Path
from typing import TYPE_CHECKING, Any

import pytest

if TYPE_CHECKING:  # the simulator is imported when a test runs a mission, not when pytest loads plugins
    from palletpilot.executor.apps.app import SimRun
    from palletpilot.sim.scenario import Scenario

RunMission = Callable[..., "SimRun"]


@pytest.fixture
def run_mission(tmp_path: Path) -> RunMission:
    """Run a mission in the simulator; each call gets its own report folder under `tmp_path`."""
    calls = iter(range(1_000_000))

    def run(
        mission: str | Path,
        scenario: str | Path | dict[str, Any] | Scenario | None = None,
        *,
        seed: int | None = None,
        folder: str | Path | None = None,
        **options: Any,
    ) -> SimRun:
        from palletpilot.executor.apps.app import run_simulated
        from palletpilot.sim.scenario import Scenario

        report = tmp_path / f"run{next(calls)}"
        if isinstance(scenario, Scenario):
            return run_simulated(mission, seed=seed, report_dir=report, scenario=scenario, **options)
        if isinstance(scenario, dict):
            sc = Scenario.model_validate(scenario)
            sc.folder = Path(folder) if folder is not None else Path(mission).parent
            return run_simulated(mission, seed=seed, report_dir=report, scenario=sc, **options)
        return run_simulated(mission, scenario, seed=seed, report_dir=report, **options)

    return run


def _failed_task(result: SimRun) -> dict[str, Any] | None:
    return next((t for t in result.summary["tasks"] if t["result"] != "succeeded"), None)


def assert_succeeded(result: SimRun) -> None:
    """Every task succeeded; otherwise the first failed task's reason and message."""
    failed = _failed_task(result)
    assert result.success and failed is None, f"mission failed: {failed}"


def assert_failed(result: SimRun, *reasons: str) -> None:
    """The mission failed, and its first failed task with one of `reasons` (any reason when none given)."""
    failed = _failed_task(result)
    assert not result.success and failed is not None, "the mission succeeded"
    assert not reasons or failed["reason"] in reasons, f"failed with {failed['reason']}, expected {reasons}"


def checks_of(result: SimRun, **checks: Any) -> list[str]:
    """The `palletpilot test` checks (`Checks`; defaults: no contact, travel height, only the target
    moved) on a finished run: one line per violation."""
    from palletpilot.executor.apps.suite import Checks
    from palletpilot.executor.apps.suite_run import check_run

    assert result.report is not None, "the run wrote no report (run it through the run_mission fixture)"
    folder = Path(result.report).parent
    return check_run(folder, result.runner.mission, result.sim.roadmap, result.runner.ctx.params, Checks(**checks))


def assert_checks(result: SimRun, **checks: Any) -> None:
    """No violation of the checks (see `checks_of`)."""
    problems = checks_of(result, **checks)
    assert not problems, "\n".join(problems)
