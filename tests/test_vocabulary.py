"""The typed vocabulary (executor.vocabulary): every reason has its metadata, the derived sets agree with
the table, and the members stay their wire strings."""

from __future__ import annotations

import json
import sqlite3

from palletpilot.executor.apps.vda5050.models import ErrorLevel
from palletpilot.executor.apps.vda5050.state import FATAL_REASONS, error_type, reason_level
from palletpilot.executor.core import errors
from palletpilot.executor.core.results import TaskResult
from palletpilot.executor.core.runner import STAY_STOPPED
from palletpilot.executor.ports import vocabulary
from palletpilot.executor.ports.vocabulary import REASONS, Outcome, Reason


def test_every_reason_has_its_metadata() -> None:
    assert set(REASONS) == set(Reason)
    for reason, meta in REASONS.items():
        assert meta.meaning and len(meta.meaning.splitlines()) == 1, reason
        assert meta.level in (vocabulary.ErrorLevel.WARNING, vocabulary.ErrorLevel.FATAL)
        assert meta.exit_code == vocabulary.EXIT_FAILED


def test_the_reason_codes_of_errors_are_the_members() -> None:
    codes = {v for k, v in vars(errors).items() if k.isupper()}
    assert codes <= set(Reason)
    assert errors.SENSOR_TIMEOUT is Reason.SENSOR_TIMEOUT


def test_stay_stopped_and_fatal_come_from_the_one_table() -> None:
    assert {r for r, m in REASONS.items() if m.stays_stopped} == STAY_STOPPED
    assert {r for r, m in REASONS.items() if m.level == vocabulary.ErrorLevel.FATAL} == FATAL_REASONS


def test_a_truck_that_stays_stopped_is_fatal_to_the_fleet_manager() -> None:
    """The drift of issue 38: sensor_timeout stayed stopped but was reported as a WARNING. Only an
    operator's cancel stays stopped without needing a person."""
    assert STAY_STOPPED - FATAL_REASONS == {Reason.CANCELLED}
    assert reason_level("sensor_timeout") is ErrorLevel.FATAL
    assert reason_level(Reason.SENSOR_TIMEOUT) is ErrorLevel.FATAL
    assert reason_level("pallet_not_found") is ErrorLevel.WARNING
    assert error_type(Reason.SENSOR_TIMEOUT) == "sensorTimeout"


def test_members_are_their_wire_strings() -> None:
    assert Reason.PATH_BLOCKED == "path_blocked" and Outcome.SUCCEEDED == "succeeded"
    assert f"{Reason.COLLISION}: x" == "collision: x" and str(Outcome.FAILED) == "failed"
    assert (
        json.dumps({"reason": Reason.NO_LOAD, "result": Outcome.FAILED}) == '{"reason": "no_load", "result": "failed"}'
    )
    db = sqlite3.connect(":memory:")
    db.execute("CREATE TABLE t (r TEXT)")
    db.execute("INSERT INTO t VALUES (?)", (Reason.TIMEOUT,))
    assert db.execute("SELECT r FROM t").fetchone() == ("timeout",)
    assert vocabulary.info("no such reason") is None


def test_a_task_result_round_trips_through_json_as_members() -> None:
    result = TaskResult(0, "pickup", "P1", result=Outcome.FAILED, reason=Reason.STILL_MISALIGNED)
    back = TaskResult.from_json(json.loads(json.dumps(result.to_json())))
    assert back == result
    assert back.result is Outcome.FAILED and back.reason is Reason.STILL_MISALIGNED
