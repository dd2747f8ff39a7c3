"""Behaviours that move the truck: follow a route, set the fork height, wait, charge.

Public API: `FollowRoute` (creeps while the forks are above travel height; selects the safety
scanners' field set, `field_set_for`), `SetForks`, `Wait`, `ReturnToRoadmap`, `Charge`, `travel_height`.
"""

from __future__ import annotations

from collections.abc import Callable

from palletpilot.control.errors import ControlError
from palletpilot.control.follower import FollowerStatus
from palletpilot.executor.core.behaviour import Behaviour, Context
from palletpilot.executor.core.errors import CONTROLLER_ERROR, NO_ROUTE, Reason, TaskFailed
from palletpilot.executor.core.manoeuvre import exit_route
from palletpilot.executor.core.mission import ChargeTask
from palletpilot.roadmap import Direction, NodeType, RoadmapError, reference_path
from palletpilot.roadmap.planner import Route

TRAVEL_HEIGHT_TOLERANCE = 0.05
"""m: forks higher than this above the travel height make the truck creep (`VehicleParams.creep_speed`)."""


def travel_height(ctx: Context) -> float:
    """The fork height (m) to drive at: the vehicle file's loaded or empty travel height (load sensor)."""
    mast = ctx.params.mast
    return mast.travel_height_loaded if ctx.vehicle.load_detected() else mast.travel_height_empty


def field_set_for(ctx: Context, route: Route) -> str:
    """The safety scanners' field set for a route: `narrow` when it enters a pallet or drop node forwards
    whose load stands in the scan plane (on the floor), else `normal` (a rack's pallet is above the plane,
    and the normal field keeps watching the floor in front of and under the rack)."""
    scanner = ctx.params.safety_scanner
    if scanner is None or not route.edges:
        return "normal"
    last = ctx.roadmap.node(route.nodes[-1])
    entering = last.type in (NodeType.PALLET, NodeType.DROP) and route.edges[-1].direction is Direction.FORWARD
    return "narrow" if entering and last.height < scanner.scan_height else "normal"


class FollowRoute(Behaviour):
    """Plan (or take) a route and follow it with the path follower until the forklift stands at its end.

    `drives`: the runner holds this state (task time stands still) while the safety scanners' protective
    stop holds the truck, and fails it with `path_blocked` after `Settings.blocked_wait_s`.
    """

    drives = True

    def __init__(
        self,
        target: Callable[[Context], str],
        via: Callable[[Context], Route] | None = None,
        check: Callable[[Context], None] | None = None,
    ) -> None:
        self.target = target
        self.via = via
        self.check = check  # runs before the truck moves; raises TaskFailed to refuse
        self.route: Route | None = None

    def start(self, ctx: Context) -> None:
        if self.check is not None:
            self.check(ctx)
        goal = self.target(ctx)
        try:
            self.route = (
                self.via(ctx) if self.via else ctx.planner.plan(ctx.memory.at_node, goal, start_yaw=ctx.memory.heading)
            )
        except RoadmapError as exc:
            raise TaskFailed(NO_ROUTE, str(exc)) from None
        if not self.route.edges:
            return
        field_set = field_set_for(ctx, self.route)
        # the direction too: standing, the truck is watched the way it is about to drive
        ctx.vehicle.set_safety_field_set(field_set, self.route.edges[0].direction.value)
        raised = ctx.vehicle.fork_height > travel_height(ctx) + TRAVEL_HEIGHT_TOLERANCE
        path = reference_path(self.route, speed_cap=ctx.params.creep_speed if raised else None)
        ctx.memory.planned_paths.append(
            [(float(x), float(y)) for x, y in zip(path.stacked("x"), path.stacked("y"), strict=True)]
        )
        self.timeout_s = 30.0 + 4.0 * path.length / 0.5
        ctx.follower.start(path)
        ctx.log("route", nodes=self.route.nodes, length_m=round(self.route.length, 3), safety_fields=field_set)

    def update(self, ctx: Context) -> str | None:
        assert self.route is not None
        if not self.route.edges:
            return "done"
        v = ctx.vehicle
        try:
            cmd = ctx.follower.update(ctx.now(), v.localization(), v.speed, v.steering)
        except ControlError as exc:
            raise TaskFailed(CONTROLLER_ERROR, str(exc)) from None
        v.drive(cmd.speed, cmd.steering)
        if cmd.status is FollowerStatus.SUCCEEDED:
            v.stop()
            last = self.route.edges[-1]
            ctx.memory.at_node, ctx.memory.heading = self.route.nodes[-1], last.yaw_end
            ctx.memory.last_route = self.route
            return "done"
        if cmd.status is FollowerStatus.FAILED:
            raise TaskFailed(CONTROLLER_ERROR, "the path follower failed")
        return None

    def stop(self, ctx: Context) -> None:
        ctx.follower.stop()
        ctx.vehicle.stop()


class SetForks(Behaviour):
    """Move the forks to a height (m) and wait until they are there."""

    timeout_s = 30.0

    def __init__(self, height: Callable[[Context], float], check: Callable[[Context], None] | None = None) -> None:
        self.height = height
        self.check = check
        self.target = 0.0

    def start(self, ctx: Context) -> None:
        mast = ctx.params.mast
        self.target = min(max(self.height(ctx), mast.min_height), mast.max_height)
        ctx.vehicle.stop()
        ctx.vehicle.set_fork_height(self.target)

    def resume(self, ctx: Context) -> None:
        ctx.vehicle.set_fork_height(self.target)

    def update(self, ctx: Context) -> str | None:
        if abs(ctx.vehicle.fork_height - self.target) > 0.002:
            return None
        if self.check:
            self.check(ctx)
        return "done"


class Wait(Behaviour):
    """Stand still for a time (s)."""

    def __init__(self, seconds: Callable[[Context], float]) -> None:
        self.seconds = seconds
        self.until = 0.0

    def start(self, ctx: Context) -> None:
        ctx.vehicle.stop()
        self.until = ctx.now() + self.seconds(ctx)
        self.timeout_s = self.seconds(ctx) + 10.0

    def update(self, ctx: Context) -> str | None:
        return "done" if ctx.now() >= self.until else None


class ReturnToRoadmap(FollowRoute):
    """After a pickup at temporary nodes, back out to the node before them, so they can be removed."""

    def __init__(self) -> None:
        super().__init__(lambda ctx: ctx.memory.at_node, via=self._route)

    @staticmethod
    def _route(ctx: Context) -> Route:
        if not ctx.roadmap.node(ctx.memory.pre_node).temporary or ctx.memory.node_before is None:
            return Route([ctx.memory.pre_node], [])
        return exit_route(ctx)  # the edge back, or a re-plan's manoeuvre driven the other way


class Charge(Behaviour):
    """Stand at the charger for some minutes, or until the battery reports a level."""

    def start(self, ctx: Context) -> None:
        ctx.vehicle.stop()
        task = ctx.memory.task_of(ChargeTask)
        self.until = ctx.now() + 60.0 * (task.minutes or 0.0)
        self.timeout_s = 60.0 * (task.minutes or 240.0) + 10.0
        if task.until_level is not None and getattr(ctx.vehicle, "battery_level", None) is None:
            raise TaskFailed(
                Reason.NO_BATTERY_READING, "charging until a level needs a battery reading this vehicle lacks"
            )

    def update(self, ctx: Context) -> str | None:
        until_level = ctx.memory.task_of(ChargeTask).until_level
        if until_level is not None:
            level = getattr(ctx.vehicle, "battery_level", None)
            if level is None:
                raise TaskFailed(Reason.NO_BATTERY_READING, "the battery reading was lost while charging")
            return "done" if level >= until_level else None
        return "done" if ctx.now() >= self.until else None
