"""How a task ends badly: `TaskFailed` with a reason code (README, "Reasons").

The reason codes are the members of `executor.vocabulary.Reason`, with their metadata there; the names
below are the same members, kept for the modules that import them from here.

Public API: `TaskFailed`, `Reason`, and the reason codes below.
"""

from __future__ import annotations

from palletpilot.executor.ports.vocabulary import Reason
from palletpilot.geometry import PalletpilotError

CALIBRATION_FAILED = Reason.CALIBRATION_FAILED
PALLET_NOT_FOUND = Reason.PALLET_NOT_FOUND
STILL_MISALIGNED = Reason.STILL_MISALIGNED
NO_FEASIBLE_APPROACH = Reason.NO_FEASIBLE_APPROACH
SAFETY_CHECK_FAILED = Reason.SAFETY_CHECK_FAILED
CONTROLLER_ERROR = Reason.CONTROLLER_ERROR
COLLISION = Reason.COLLISION
PALLET_NOT_LIFTED = Reason.PALLET_NOT_LIFTED
NO_LOAD = Reason.NO_LOAD
NO_ROUTE = Reason.NO_ROUTE
PATH_BLOCKED = Reason.PATH_BLOCKED
SLOT_OCCUPIED = Reason.SLOT_OCCUPIED
TIMEOUT = Reason.TIMEOUT
CANCELLED = Reason.CANCELLED
SENSOR_TIMEOUT = Reason.SENSOR_TIMEOUT
VEHICLE_FAULT = Reason.VEHICLE_FAULT
LOCALIZATION_FAULT = Reason.LOCALIZATION_FAULT
INTERNAL_ERROR = Reason.INTERNAL_ERROR


class TaskFailed(PalletpilotError):  # noqa: N818 - a task's end, raised inside behaviours
    """A behaviour's failure with a reason code."""

    def __init__(self, reason: Reason, message: str) -> None:
        super().__init__(message)
        self.reason = Reason(reason)
