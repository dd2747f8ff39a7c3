"""Control errors."""

from palletpilot.geometry import PalletpilotError


class ControlError(PalletpilotError):
    """A bad vehicle file, a failed or late solve, no progress; the message says which."""
