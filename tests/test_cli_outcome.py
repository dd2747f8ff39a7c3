"""The closing summary of `run` and `robot`: what a shift lead reads at the end of a mission."""

from __future__ import annotations

from palletpilot.executor.apps.cli_outcome import task_line
from palletpilot.executor.core.results import TaskResult
from palletpilot.executor.ports.vocabulary import Outcome


def _estimate(lateral: float, along: float, yaw: float, aligned: bool) -> dict:
    return {"lateral_mm": lateral, "longitudinal_mm": along, "yaw_deg": yaw, "aligned": aligned}


def test_a_pickup_line_says_how_far_off_the_pallet_was_the_replans_and_the_time():
    task = TaskResult(index=0, type="pickup", node="floor_b2", result=Outcome.SUCCEEDED, attempts=2)
    task.start_s, task.end_s = 3.0, 74.25
    task.record = {
        "estimates": [_estimate(-195.2, 120.4, -5.93, False), _estimate(2.0, -1.0, 0.1, True)],
        "temporary_nodes": [{"pallet": "tmp_p1", "pre_pallet": "tmp_pp1"}],
    }
    line = task_line(task)
    assert line.startswith("pickup    floor_b2       succeeded in 71.2 s")
    assert "found 195 mm sideways, 120 mm along, 5.9 deg off its node; 1 re-plan(s), 2 estimate(s)" in line


def test_a_pickup_line_names_its_manoeuvres_and_their_segments():
    task = TaskResult(index=0, type="pickup", node="rack_n2", result=Outcome.SUCCEEDED, attempts=2)
    task.start_s, task.end_s = 0.0, 89.5
    task.record = {
        "estimates": [_estimate(302.8, -199.6, -10.1, False), _estimate(-3.7, -2.7, 0.0, True)],
        "temporary_nodes": [
            {"pallet": "rack_n2~1", "manoeuvre": {"segments": 2, "directions": ["reverse", "forward"]}}
        ],
    }
    assert task_line(task).endswith("; 1 re-plan(s), 2 estimate(s), 1 manoeuvre(s) of 2 segments")


def test_other_tasks_give_their_outcome_reason_and_time_without_estimates():
    task = TaskResult(index=1, type="delivery", node="drop", result=Outcome.FAILED, reason=None)
    task.start_s, task.end_s = 80.0, 100.0
    assert task_line(task) == "delivery  drop           failed in 20.0 s"


def test_a_failed_task_is_numbered_from_one_as_the_progress_line_numbers_it(capsys):
    from types import SimpleNamespace

    from palletpilot.executor.apps.cli_outcome import mission_outcome
    from palletpilot.executor.core.controls import Controls
    from palletpilot.executor.ports.vocabulary import Reason

    done = TaskResult(index=0, type="pickup", node="floor_b2", result=Outcome.SUCCEEDED)
    failed = TaskResult(index=1, type="delivery", node="drop", result=Outcome.FAILED, reason=Reason.CANCELLED)
    failed.message = "cancelled by the operator"
    runner = SimpleNamespace(results=[done, failed], trajectory=[], mission=SimpleNamespace(tasks=[0, 1, 2]))
    result = SimpleNamespace(summary={}, success=False, write_errors=[], runner=runner)
    mission_outcome(result, None, False, Controls(), "vehicle")
    err = capsys.readouterr().err
    assert "mission failed: task 2 of 3 (delivery): cancelled: cancelled by the operator; vehicle stopped" in err
