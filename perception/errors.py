"""Errors of the perception package: one line naming the file, key or frame at fault."""

from __future__ import annotations

from palletpilot.geometry import PalletpilotError


class PerceptionError(PalletpilotError):
    """Bad perception input: a frame bundle or geometry file that cannot be used as it is."""


class CalibrationError(PerceptionError):
    """The frames do not allow a calibration; the message says which feature is missing or how far off."""
