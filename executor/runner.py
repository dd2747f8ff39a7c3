"""The runner: a mission's tasks in order over the vehicle and perception ports, at the 20 Hz control tick.

Time comes from a `Clock`: `SimClock` advances the simulator by one tick per step (deterministic,
much faster than real time), a wall clock would sleep to the next tick on the robot. Each task is a
`transitions` machine (`executor.tasks`); the runner calls the current state's behaviour every tick,
enforces the state's timeout, fires the trigger it returns and records everything: events (JSON
lines), states with start and end times, calibrations, pallet estimates, attempts, tracking errors
and the driven trajectory. On any failure the vehicle stops and the task ends with a reason code;
`pause()`, `resume()` and `cancel()` may be called between ticks (e.g. from a signal handler).
"""

from __future__ import annotations

import contextlib
import json
import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TextIO

from control.follower import Follower
from control.mpc import MpcFollower
from control.vehicle import VehicleParams
from executor.mission import Mission
from executor.ports import PerceptionService, VehiclePort
from executor.tasks import (
    CANCELLED,
    TIMEOUT,
    Behaviour,
    Context,
    Settings,
    TaskFailed,
    behaviours,
    build_machine,
)
from perception.frames import FrameBundle
from perception.specs import ForkGeometry, PalletType
from roadmap import Planner, Roadmap

CONTROL_DT = 0.05


class SimClock:
    """Simulated time: each tick advances the simulator by `dt` seconds."""

    def __init__(self, step: Callable[[float], None], dt: float = CONTROL_DT) -> None:
        self._step = step
        self.dt = dt
        self.t = 0.0

    def now(self) -> float:
        """Seconds since the start."""
        return self.t

    def tick(self) -> None:
        """Advance one control period."""
        self._step(self.dt)
        self.t += self.dt


@dataclass
class TaskResult:
    """How one task went, for the report."""

    index: int
    type: str
    node: str | None
    result: str = "pending"
    reason: str | None = None
    message: str | None = None
    attempts: int = 0
    start_s: float = 0.0
    end_s: float = 0.0
    states: list[dict[str, Any]] = field(default_factory=list)
    record: dict[str, Any] = field(default_factory=dict)

    def summary(self) -> dict[str, Any]:
        """`type`, `node`, `result`, `reason`, `attempts` (the `--json` summary)."""
        return {
            "type": self.type,
            "node": self.node,
            "result": self.result,
            "reason": self.reason,
            "attempts": self.attempts,
        }


class Runner:
    """Runs one mission on a vehicle (simulated or real) and records it."""

    def __init__(
        self,
        mission: Mission,
        roadmap: Roadmap,
        vehicle: VehiclePort,
        perception: PerceptionService | None,
        grab: Callable[[], FrameBundle],
        clock: SimClock,
        params: VehicleParams,
        forks: ForkGeometry,
        start_node: str,
        settings: Settings | None = None,
        follower: Follower | None = None,
        events: TextIO | None = None,
        progress: TextIO | None = None,
    ) -> None:
        self.mission = mission
        self.clock = clock
        self.settings = settings or Settings()
        self.events = events
        self.progress = progress
        self.results: list[TaskResult] = []
        self.trajectory: list[tuple[float, float, float, float]] = []  # t, x, y, yaw of localization
        self._paused = False
        self._cancelled = False
        start = roadmap.node(start_node)
        self.ctx = Context(
            vehicle=vehicle,
            perception=perception,
            grab=grab,
            roadmap=roadmap,
            planner=Planner(roadmap),
            follower=follower or MpcFollower(params),
            params=params,
            forks=forks,
            pallet_type=PalletType.eur(),
            settings=self.settings,
            now=clock.now,
            log=self._log,
            at_node=start_node,
            heading=start.pose.yaw,
        )

    # -- control from outside ----------------------------------------------------------------
    def pause(self) -> None:
        """Hold the vehicle still until `resume()`; the current state's timeout does not run meanwhile."""
        self._paused = True

    def resume(self) -> None:
        """Continue after `pause()`."""
        self._paused = False

    def cancel(self) -> None:
        """Stop the vehicle and end the mission (the current task fails with reason `cancelled`)."""
        self._cancelled = True

    # -- recording ---------------------------------------------------------------------------
    def _log(self, event: str, **data: Any) -> None:
        if self.events is not None:
            doc = {"t": round(self.clock.now(), 3), "event": event, **data}
            self.events.write(json.dumps(doc, default=_jsonable) + "\n")
            self.events.flush()  # a line per state change: cheap, and `tail -f events.jsonl` follows the run

    def _show(self, task: TaskResult, state: str) -> None:
        if self.progress is None:
            return
        togo = ""
        follower = self.ctx.follower
        if state in (
            "drive",
            "drive_to_pre_pallet",
            "drive_to_pre_drop",
            "approach",
            "enter",
            "reverse_out",
            "back_off",
        ):
            remaining = getattr(follower, "distance_to_go", None)
            if remaining is not None:
                togo = f" {remaining:5.1f} m to go"
        line = (
            f"\r[{self.clock.now():7.1f} s] task {task.index + 1}/{len(self.mission.tasks)} {task.type}"
            f" {task.node or ''} | {state} | attempt {max(task.attempts, 1)}{togo}   "
        )
        self.progress.write(line)
        self.progress.flush()

    # -- running -----------------------------------------------------------------------------
    def run(self) -> bool:
        """Run every task in order; stops at the first failure. True when all succeeded."""
        self._log("mission_start", name=self.mission.name, tasks=len(self.mission.tasks))
        ok = True
        for i, task in enumerate(self.mission.tasks):
            result = self._run_task(i, task)
            self.results.append(result)
            if result.result != "succeeded":
                ok = False
                break
        self._brake_to_standstill()
        self._log("mission_end", success=ok)
        if self.progress is not None:
            self.progress.write("\n")
        return ok

    def _run_task(self, index: int, task: Any) -> TaskResult:
        ctx = self.ctx
        kind = task.type if task.type != "pickup" or self.settings.adapt else "pickup_no_adapt"
        table = behaviours(kind, self.settings)
        node = getattr(task, "node", None)
        result = TaskResult(index, task.type, node, start_s=self.clock.now())
        ctx.task, ctx.attempts, ctx.calibration, ctx.estimate = task, 0, None, None
        ctx.record = result.record
        if node is not None and task.type in ("pickup", "delivery"):
            ctx.pallet_node, ctx.pre_node = node, ctx.roadmap.pre_pallet_of(node)
        model = build_machine(kind)
        self._log("task_start", index=index, type=task.type, node=node)
        with contextlib.ExitStack() as stack:
            ctx.overlay = stack.enter_context(ctx.roadmap.overlay())  # temporary nodes vanish with the task
            behaviour: Behaviour | None = None
            entered = self.clock.now()
            active = 0.0  # time spent in the state while not paused
            while model.state not in ("succeeded", "failed"):
                state = model.state
                try:
                    if behaviour is None:
                        behaviour = table[state]()
                        entered, active = self.clock.now(), 0.0
                        self._log("state_start", task=index, state=state)
                        behaviour.start(ctx)
                    if self._cancelled:
                        raise TaskFailed(CANCELLED, "cancelled by the operator")
                    if self._paused:
                        ctx.vehicle.stop()
                        self.clock.tick()
                        continue
                    trigger = behaviour.update(ctx)
                    if trigger is None and active > behaviour.timeout_s:
                        raise TaskFailed(TIMEOUT, f"state '{state}' timed out after {behaviour.timeout_s:.0f} s")
                    faults = ctx.vehicle.faults()
                    if faults:
                        raise TaskFailed("collision", "; ".join(faults))
                except TaskFailed as exc:
                    trigger = "fail"
                    result.reason, result.message = exc.reason, str(exc)
                    self._log("task_failed", task=index, state=state, reason=exc.reason, message=str(exc))
                if trigger is None:
                    self._record_tick()
                    self._show(result, state)
                    self.clock.tick()
                    active += self.clock.dt
                    continue
                if behaviour is not None:
                    behaviour.stop(ctx)
                result.states.append(
                    {
                        "state": state,
                        "start_s": round(entered, 3),
                        "end_s": round(self.clock.now(), 3),
                        "outcome": trigger,
                    }
                )
                self._log("state_end", task=index, state=state, outcome=trigger)
                if state == "estimate_pallet" and trigger == "misaligned":
                    ctx.node_before = self._node_before()
                getattr(model, trigger)()
                behaviour = None
                if state == "drive_to_pre_pallet" and trigger == "done":
                    ctx.node_before = self._node_before()
            self._brake_to_standstill()
            if model.state == "failed" and self.settings.return_on_failure and ctx.pre_node and not self._cancelled:
                self._return_to_pre_pallet()
        result.result = model.state
        result.attempts = ctx.attempts
        result.end_s = self.clock.now()
        self._log("task_end", task=index, result=result.result, reason=result.reason)
        return result

    def _brake_to_standstill(self, limit_s: float = 10.0) -> None:
        """Command a stop and let time run until the vehicle stands (|speed| < 1 mm/s)."""
        vehicle = self.ctx.vehicle
        vehicle.stop()
        t_end = self.clock.now() + limit_s
        while abs(vehicle.speed) >= 1e-3 and self.clock.now() < t_end:
            vehicle.stop()
            self.clock.tick()

    def _node_before(self) -> str | None:
        """The node before the pre-pallet node: on the route that reached it, else a node joined both ways."""
        ctx = self.ctx
        route = ctx.last_route
        if route is not None and ctx.pre_node in route.nodes:
            before = route.node_before(ctx.pre_node)
            if before is not None and ctx.roadmap.graph.has_edge(ctx.pre_node, before):
                return before
        original_pre = ctx.roadmap.pre_pallet_of(ctx.task.node)
        for u in ctx.roadmap.graph.predecessors(original_pre):
            if u != ctx.task.node and ctx.roadmap.graph.has_edge(original_pre, u) and not ctx.roadmap.node(u).temporary:
                return u
        return None

    def _record_tick(self) -> None:
        pose = self.ctx.vehicle.localization()
        if not self.trajectory or self.clock.now() - self.trajectory[-1][0] >= 0.2:
            self.trajectory.append((self.clock.now(), pose.x, pose.y, pose.yaw))

    def _return_to_pre_pallet(self) -> None:
        """Optional after a failure: drive back to the pre-pallet node (best effort, logged)."""
        ctx = self.ctx
        from executor.tasks import FollowRoute

        if ctx.at_node == ctx.pre_node:
            return
        try:
            behaviour = FollowRoute(lambda c: c.pre_node)
            behaviour.start(ctx)
            t_end = self.clock.now() + behaviour.timeout_s
            while self.clock.now() < t_end and behaviour.update(ctx) is None and not ctx.vehicle.faults():
                self.clock.tick()
            behaviour.stop(ctx)
            self._log("returned_to_pre_pallet", node=ctx.at_node)
        except Exception as exc:
            ctx.vehicle.stop()
            self._log("return_failed", error=str(exc))


def _jsonable(obj: object) -> object:
    if hasattr(obj, "tolist"):
        return obj.tolist()  # type: ignore[no-any-return]
    if isinstance(obj, float) and not math.isfinite(obj):
        return None
    return str(obj)
