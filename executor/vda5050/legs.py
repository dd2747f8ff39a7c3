"""What the AGV's legs run with: the runner's controls (`AgvControls`: the master's pause and the gate a leg
waits at), the planner that hands the runner exactly the order's edges (`OrderPlanner`), and the order's
`maxSpeed` on the leg's roadmap edges (`speed_limits`).

Public API: `AgvControls`, `OrderPlanner`, `speed_limits`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
from collections.abc import Iterator

from palletpilot.executor.controls import Controls
from palletpilot.executor.vda5050.orders import Leg, OrderManager
from palletpilot.roadmap import Edge, Planner, Roadmap, Route


class AgvControls(Controls):
    """The runner's controls: paused while the master paused the truck or a leg waits for a release."""

    def __init__(self) -> None:
        super().__init__()
        self.master_pause = False
        self.gate: str | None = None
        """A roadmap node the running leg waits to be allowed to enter."""

    def refresh(self) -> None:
        """Recompute `paused` from the master's pause and the gate."""
        self.paused = self.master_pause or self.gate is not None

    def reset(self) -> None:
        """Clear a cancel and the gate; the master's pause stays."""
        super().reset()
        self.gate = None
        self.refresh()


class OrderPlanner(Planner):
    """A planner that answers the leg's route with exactly the order's edges (and plans anything else)."""

    def __init__(self, roadmap: Roadmap, route: tuple[str, ...]) -> None:
        super().__init__(roadmap)
        self.route = route

    def plan(self, start: str, goal: str, start_yaw: float | None = None, goal_yaw: float | None = None) -> Route:
        """The order's route from its first to its last node; other requests go to the roadmap planner."""
        r = self.route
        if len(r) >= 2 and start == r[0] and goal == r[-1]:
            return Route(list(r), [self.roadmap.edge(a, b) for a, b in itertools.pairwise(r)])
        return super().plan(start, goal, start_yaw=start_yaw, goal_yaw=goal_yaw)


@contextlib.contextmanager
def speed_limits(orders: OrderManager, roadmap: Roadmap, leg: Leg) -> Iterator[None]:
    """Slow the roadmap edges of a move leg to the order's `maxSpeed` (m/s) for the leg, then restore them."""
    replaced: list[Edge] = []
    if leg.kind == "move":
        with orders.lock:
            first = orders.cursor - 1
            edges = orders.edges[first : first + len(leg.route) - 1]
        for (a, b), e in zip(itertools.pairwise(leg.route), edges, strict=False):
            limit = e.raw.get("maxSpeed")
            old = roadmap.edge(a, b)
            if limit is not None and float(limit) < old.speed_limit:
                roadmap.remove_edge(a, b)
                roadmap.add_edge(dataclasses.replace(old, speed_limit=float(limit)))
                replaced.append(old)
    try:
        yield
    finally:
        for old in replaced:
            roadmap.remove_edge(old.start, old.end)
            roadmap.add_edge(old)
