"""What the AGV's legs run with: the runner's controls (`AgvControls`: the master's pause and the gate a leg
waits at), the planner that hands the runner exactly the order's edges (`OrderPlanner`), and the order's
`maxSpeed` on the leg's roadmap edges (`speed_limits`).

The route of a leg that starts with the truck part way along its first edge (`from_where_it_stands`).

A pick or drop leg that waits, forks in the slot, for its back-out to be released keeps the scanners' narrow
field set (`SlotFields`): the normal forward fields would see the load just handled ahead of the forks, and
the protective stop would hold the truck for good.

Public API: `AgvControls`, `OrderPlanner`, `speed_limits`, `from_where_it_stands`, `HERE`, `SlotFields`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import itertools
import math
from collections.abc import Callable, Iterator
from typing import Any

from palletpilot.executor.apps.vda5050.midedge import locate, rest_of
from palletpilot.executor.apps.vda5050.orders import Leg, OrderManager
from palletpilot.executor.apps.vda5050.routes import DEFAULT_DEVIATION_XY
from palletpilot.executor.core.controls import Controls
from palletpilot.executor.ports import VehiclePort
from palletpilot.roadmap import Edge, Planner, Roadmap, Route

HERE = "_here_after_"
"""The id prefix of the temporary node where a leg starts part way along an edge."""


class AgvControls(Controls):
    """The runner's controls: paused while the master paused the truck, a leg waits for a release, or a
    cancelOrder brings the truck to a standstill before the leg is cancelled (`stopping`: the service brake,
    never the latched safety stop a cancel at speed would be)."""

    def __init__(self) -> None:
        super().__init__()
        self.master_pause = False
        self.gate: str | None = None
        """A roadmap node the running leg waits to be allowed to enter."""
        self.stopping = False
        """A cancelOrder waits for the truck to stand before it cancels the leg."""
        self.zone_hold = False
        """A 3.0 AGV holds before a BLOCKED zone (`v3.ZoneGuard`)."""

    def refresh(self) -> None:
        """Recompute `paused` from the master's pause, the gate, a cancel's stop and a zone hold."""
        self.paused = self.master_pause or self.gate is not None or self.stopping or self.zone_hold

    def reset(self) -> None:
        """Clear a cancel, its stop and the gate; the master's pause stays."""
        super().reset()
        self.gate = None
        self.stopping = False
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
def speed_limits(
    orders: OrderManager,
    roadmap: Roadmap,
    leg: Leg,
    zone_limits: Callable[[tuple[str, ...]], dict[int, float]] | None = None,
) -> Iterator[None]:
    """Slow the roadmap edges of a move leg to the order's `maxSpeed` (m/s) for the leg, and the edges of any
    leg to `zone_limits(route)` (m/s by the index of the route's edge: a 3.0 AGV's SPEED_LIMIT zones), then
    restore them."""
    limits: dict[int, float] = dict(zone_limits(leg.route)) if zone_limits is not None else {}
    if leg.kind == "move":
        with orders.lock:
            first = orders.cursor - 1
            edges = orders.edges[first : first + len(leg.route) - 1]
        for i, e in enumerate(edges):
            if e.raw.get("maxSpeed") is not None:
                limits[i] = min(limits.get(i, math.inf), float(e.raw["maxSpeed"]))
    replaced: list[Edge] = []
    for i, (a, b) in enumerate(itertools.pairwise(leg.route)):
        if i not in limits or not roadmap.graph.has_edge(a, b):
            continue
        old = roadmap.edge(a, b)
        if limits[i] < old.speed_limit:
            roadmap.remove_edge(a, b)
            roadmap.add_edge(dataclasses.replace(old, speed_limit=limits[i]))
            replaced.append(old)
    try:
        yield
    finally:
        for old in replaced:
            roadmap.remove_edge(old.start, old.end)
            roadmap.add_edge(old)


@contextlib.contextmanager
def from_where_it_stands(roadmap: Roadmap, leg: Leg, x: float, y: float) -> Iterator[tuple[str, ...]]:
    """The leg's route from where the truck at (x, y) (map frame, m) stands: when it stands part way along the
    route's first edge (an order restarted after a cancel, section 6.6.3.1), a temporary node there and the
    rest of that edge replace the first node for the leg; else the route as it is."""
    route = leg.route
    on = locate(roadmap, route[0], x, y, DEFAULT_DEVIATION_XY) if leg.kind == "move" and len(route) >= 2 else None
    if on is None or on.end != route[1]:
        yield route
        return
    with roadmap.overlay() as overlay:
        node, edge = rest_of(roadmap.edge(on.start, on.end), on.s, f"{HERE}{on.start}")
        overlay.add_node(node)
        overlay.add_edge(edge)
        yield (node.id, *route[1:])


class SlotFields:
    """The vehicle as the AGV's runners drive it (every call passed through), except that while `in_slot()`
    (a pick or drop standing with the forks in the slot until its back-out is released) the scanners keep
    the narrow field set, whatever set a drive asks for (backing out, the reverse fields watch anyway)."""

    def __init__(self, vehicle: VehiclePort, in_slot: Callable[[], bool]) -> None:
        self._vehicle, self._in_slot = vehicle, in_slot

    def set_safety_field_set(self, name: str, direction: str = "forward") -> None:
        """Select the scanners' field case: the set `narrow` while in the slot, else `name`; `direction` as asked."""
        self._vehicle.set_safety_field_set("narrow" if self._in_slot() else name, direction)

    def __getattr__(self, name: str) -> Any:
        return getattr(self._vehicle, name)
