"""Roadmap errors."""

from palletpilot.geometry import PalletpilotError


class RoadmapError(PalletpilotError):
    """A bad map, an unknown node, no route, or no feasible curve; the message names what is at fault."""
