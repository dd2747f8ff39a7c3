"""The executor's typed vocabulary: why a task failed (`Reason`) and how it ended (`Outcome`).

Both are `str`-valued enums: a member equals, hashes, formats and serialises (JSON, SQLite) as its wire
string (`Reason.COLLISION == "collision"`), so reports, events, the journal and the VDA 5050 messages
carry the same strings as before. Everything the rest of the code knows about a reason is in ONE table,
`REASONS`: whether the truck stays stopped after it (no drive to a parking node), its VDA 5050 error
level, the exit code of `palletpilot run` / `robot` it ends with, and a one-line meaning. The sets
`STAY_STOPPED` and `FATAL_REASONS` are derived from the table, so they cannot drift apart.

This module imports nothing but the standard library (it belongs to the ports, `executor.ports`).

Public API: `Reason`, `Outcome`, `ErrorLevel`, `ReasonInfo`, `REASONS`, `STAY_STOPPED`, `FATAL_REASONS`,
`EXIT_OK`, `EXIT_FAILED`, `info(reason)`.
"""

from __future__ import annotations

from dataclasses import dataclass
from enum import Enum
from types import MappingProxyType

EXIT_OK = 0
"""Exit code: the mission succeeded."""
EXIT_FAILED = 1
"""Exit code: the mission (or the command's task) failed; the vehicle stands."""


class _StrEnum(str, Enum):
    """A `str` enum whose `str()` and `format()` are its value on every Python (3.10 has no `StrEnum`)."""

    def __str__(self) -> str:
        return str(self.value)

    def __format__(self, spec: str) -> str:
        return format(str(self.value), spec)


class Reason(_StrEnum):
    """Why a task failed: the reason code of `TaskFailed`, `TaskResult.reason` and report.json."""

    CALIBRATION_FAILED = "calibration_failed"
    PALLET_NOT_FOUND = "pallet_not_found"
    STILL_MISALIGNED = "still_misaligned"
    NO_FEASIBLE_APPROACH = "no_feasible_approach"
    SAFETY_CHECK_FAILED = "safety_check_failed"
    CONTROLLER_ERROR = "controller_error"
    COLLISION = "collision"
    PALLET_NOT_LIFTED = "pallet_not_lifted"
    NO_LOAD = "no_load"
    NO_ROUTE = "no_route"
    PATH_BLOCKED = "path_blocked"
    SLOT_OCCUPIED = "slot_occupied"
    NO_BATTERY_READING = "no_battery_reading"
    TIMEOUT = "timeout"
    CANCELLED = "cancelled"
    SENSOR_TIMEOUT = "sensor_timeout"
    VEHICLE_FAULT = "vehicle_fault"
    LOCALIZATION_FAULT = "localization_fault"
    INTERNAL_ERROR = "internal_error"


class Outcome(_StrEnum):
    """How a task ended (`TaskResult.result`): the final states of every task machine, or not yet run."""

    PENDING = "pending"
    SUCCEEDED = "succeeded"
    FAILED = "failed"


class ErrorLevel(_StrEnum):
    """VDA 5050 `errorLevel` of a task failure reported to the fleet manager (section 6.10.6)."""

    WARNING = "WARNING"
    FATAL = "FATAL"


@dataclass(frozen=True)
class ReasonInfo:
    """What a reason means for the truck: `stays_stopped` (no drive to a parking node after it, whatever
    `return_on_failure` says), `level` (the fleet manager's error level), `exit_code` (of `run` and
    `robot` unless a signal cancelled them: 128 + the signal) and a one-line `meaning`."""

    stays_stopped: bool
    level: ErrorLevel
    exit_code: int
    meaning: str


_W, _F = ErrorLevel.WARNING, ErrorLevel.FATAL


def _reason(stays_stopped: bool, level: ErrorLevel, meaning: str) -> ReasonInfo:
    return ReasonInfo(stays_stopped, level, EXIT_FAILED, meaning)


REASONS: MappingProxyType[Reason, ReasonInfo] = MappingProxyType(
    {
        Reason.CALIBRATION_FAILED: _reason(False, _W, "no trusted camera calibration from the forks and the floor"),
        Reason.PALLET_NOT_FOUND: _reason(False, _W, "no pallet of the expected type where the task expects it"),
        Reason.STILL_MISALIGNED: _reason(False, _W, "the pallet is still outside the tolerance after the re-plans"),
        Reason.NO_FEASIBLE_APPROACH: _reason(False, _W, "no drivable curve reaches the corrected pallet node"),
        Reason.SAFETY_CHECK_FAILED: _reason(False, _W, "the camera did not show the entry or the slot to be free"),
        Reason.CONTROLLER_ERROR: _reason(False, _W, "the path follower failed to produce a command"),
        Reason.COLLISION: _reason(True, _F, "a contact or bumper fault: a person must inspect the truck"),
        Reason.PALLET_NOT_LIFTED: _reason(False, _W, "the load sensor disagrees with the forks' move"),
        Reason.NO_LOAD: _reason(False, _W, "a delivery with empty forks"),
        Reason.NO_ROUTE: _reason(False, _W, "no route on the roadmap to the task's node"),
        Reason.PATH_BLOCKED: _reason(False, _W, "the protective field or the entry volume stayed occupied"),
        Reason.SLOT_OCCUPIED: _reason(False, _W, "the drop slot stayed occupied; the load is still on the forks"),
        Reason.NO_BATTERY_READING: _reason(False, _W, "charging to a level on a vehicle without a battery reading"),
        Reason.TIMEOUT: _reason(False, _W, "a state ran past its timeout"),
        Reason.CANCELLED: _reason(True, _W, "the operator or the fleet manager cancelled the mission"),
        Reason.SENSOR_TIMEOUT: _reason(True, _F, "localization or the camera went silent or stale"),
        Reason.VEHICLE_FAULT: _reason(True, _F, "the truck does not do what it is commanded, or ticks late"),
        Reason.LOCALIZATION_FAULT: _reason(True, _F, "localization jumped further than the truck can move"),
        Reason.INTERNAL_ERROR: _reason(True, _F, "a bug: an unexpected exception in the control loop"),
    }
)
"""Every `Reason`'s metadata; tests assert that no reason lacks it."""

STAY_STOPPED = frozenset(r for r, i in REASONS.items() if i.stays_stopped)
"""Failures after which the truck stays stopped where it is, whatever `return_on_failure` says."""
FATAL_REASONS = frozenset(r for r, i in REASONS.items() if i.level is ErrorLevel.FATAL)
"""Failures reported to the fleet manager as FATAL (a person is needed); all others are WARNINGs."""


def info(reason: str) -> ReasonInfo | None:
    """The metadata of a reason code (a `Reason` or its string), None for a string that is no reason."""
    try:
        return REASONS[Reason(reason)]
    except ValueError:
        return None
