"""How a task ends badly: `TaskFailed` with a reason code, and the reason codes (README, "Reasons").

Public API: `TaskFailed`, and the reason codes below.
"""

from __future__ import annotations

from palletpilot.geometry import PalletpilotError

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
TIMEOUT = "timeout"
CANCELLED = "cancelled"
SENSOR_TIMEOUT = "sensor_timeout"
VEHICLE_FAULT = "vehicle_fault"
LOCALIZATION_FAULT = "localization_fault"
INTERNAL_ERROR = "internal_error"


class TaskFailed(PalletpilotError):  # noqa: N818 - a task's end, raised inside behaviours
    """A behaviour's failure with a reason code."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason
