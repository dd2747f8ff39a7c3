"""The runner: a mission's tasks in order over the vehicle and perception ports, at the control tick.

Time comes from a `Clock` (`executor.clock`): simulated or wall. Each task is a `transitions` machine
(`executor.tasks`); every tick the runner checks the operator's controls (pause, cancel), the
watchdogs (`executor.watchdog`) and the vehicle's faults, calls the current state's behaviour, enforces
the state's timeout (paused time does not count) and fires the trigger it returns.

Fail-safe: whatever goes wrong in a tick (a task failure, any exception, a perception crash, a failed
write), the behaviour's `stop()` runs, the vehicle is brought to a standstill (the truck's safety stop
while it moves, `VehiclePort.emergency_stop`), and the task ends with a reason: `internal_error` with
the exception for the unexpected ones. `run()` never raises an `Exception`.

Progress is journalled (`executor.journal`) at every state change when a journal is given; a runner
built with `resume=` continues from the last checkpoint (`executor.resume`).

Public API: `Runner`, `TaskResult`, `SimClock`, `WallClock` (re-exported from `executor.clock`).
"""

from __future__ import annotations

import contextlib
import dataclasses
import math
import traceback
from collections.abc import Callable, Sequence
from typing import Any, TextIO

from palletpilot.control.follower import Follower
from palletpilot.control.mpc import MpcFollower
from palletpilot.control.vehicle import VehicleParams
from palletpilot.executor.core.behaviour import Behaviour, Context, Settings, TaskMemory
from palletpilot.executor.core.clock import Clock, SimClock, WallClock
from palletpilot.executor.core.controls import Controls
from palletpilot.executor.core.driving import FollowRoute, SetForks, travel_height
from palletpilot.executor.core.errors import (
    CANCELLED,
    COLLISION,
    INTERNAL_ERROR,
    PATH_BLOCKED,
    SENSOR_TIMEOUT,
    TIMEOUT,
    Reason,
    TaskFailed,
)
from palletpilot.executor.core.jobs import Jobs
from palletpilot.executor.core.mission import Mission, Task
from palletpilot.executor.core.progress import Progress
from palletpilot.executor.core.results import TaskResult
from palletpilot.executor.core.resume import Checkpointer, ResumePoint
from palletpilot.executor.core.tasks import behaviours, build_machine, pickup_kind
from palletpilot.executor.core.watchdog import CommandedVehicle, WatchdogLimits, Watchdogs
from palletpilot.executor.ports import PerceptionService, RunObserver, VehiclePort
from palletpilot.executor.ports.vocabulary import STAY_STOPPED, Outcome
from palletpilot.geometry import angle_diff
from palletpilot.geometry.fileio import dumps_json
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.specs import ForkGeometry, PalletType
from palletpilot.roadmap import NodeType, Planner, Roadmap, RoadmapError, Route

__all__ = ["Runner", "SimClock", "TaskResult", "WallClock"]

STANDSTILL_SPEED = 1e-3
"""m/s: the vehicle stands below this."""
QUICK_STOP_SPEED = 0.05
"""m/s: a failure above this uses the truck's safety stop, below it the service brake."""
_PAUSED = "__paused__"
_RETURN_STATE = "return_on_failure"
"""The name the drive to a parking node after a failure runs under (events, progress; no machine state)."""
_DRIVING_STATES = (
    "drive",
    "drive_to_pre_pallet",
    "drive_to_pre_drop",
    "approach",
    "enter",
    "reverse_out",
    "back_off",
    _RETURN_STATE,
)
PARK_POSE_TOLERANCE_M = 0.25
PARK_YAW_TOLERANCE_DEG = 10.0
"""After a failure the truck drives to a parking node only from a node it stands on within these."""


class Runner:
    """Runs one mission on a vehicle (simulated or real) and records it."""

    def __init__(
        self,
        mission: Mission,
        roadmap: Roadmap,
        vehicle: VehiclePort,
        perception: PerceptionService | None,
        grab: Callable[[], FrameBundle],
        clock: Clock,
        params: VehicleParams,
        forks: ForkGeometry,
        start_node: str,
        settings: Settings | None = None,
        follower: Follower | None = None,
        events: TextIO | None = None,
        progress: TextIO | None = None,
        controls: Controls | None = None,
        checkpointer: Checkpointer | None = None,
        resume: ResumePoint | None = None,
        listeners: Sequence[RunObserver] = (),
        watchdog_limits: WatchdogLimits | None = None,
        planner: Planner | None = None,
        start_heading: float | None = None,
    ) -> None:
        """A runner of `mission` from `start_node`, facing `start_heading` (rad, world frame; None: the
        node's own yaw). `planner`: plans the tasks' routes (None: the roadmap's `Planner`; the AGV gives
        one that answers with its order's edges). `resume`: continue from this checkpoint."""
        self.mission = mission
        self.pallet_types = mission.pallet_types()  # per task: the pallet it handles
        self.clock = clock
        settings = settings or Settings()
        if mission.blocked_wait_s is not None:  # the mission's own wait, for this run only
            settings = dataclasses.replace(settings, blocked_wait_s=mission.blocked_wait_s)
        self.settings = settings
        self.events = events
        self.progress = Progress(progress) if progress is not None else None
        self.controls = controls or Controls()
        self.checkpointer = checkpointer
        self.listeners: list[RunObserver] = list(listeners)
        self.results: list[TaskResult] = []
        self.trajectory: list[tuple[float, float, float, float]] = []  # t, x, y, yaw of localization
        self.stops: list[dict[str, Any]] = []  # every failure: when, at what speed, when the vehicle stood
        self.write_errors: list[str] = []
        self.watchdogs = Watchdogs(params, watchdog_limits)
        self._grab = grab
        self.paused_total_s = 0.0
        self._paused_since: float | None = None
        self._blocked_since: float | None = None  # the scanners' protective stop holds the task since
        self._no_frame_since: float | None = None
        self._last_fork_height: float | None = None
        self.vehicle = CommandedVehicle(vehicle)
        self.resume_point = resume
        start = roadmap.node(start_node)
        self.ctx = Context(
            vehicle=self.vehicle,
            perception=perception,
            roadmap=roadmap,
            planner=planner or Planner(roadmap),
            follower=follower or MpcFollower(params),
            params=params,
            forks=forks,
            pallet_type=self.pallet_types[0] if self.pallet_types else PalletType.eur(),
            settings=self.settings,
            now=self.task_time,
            log=self.log,
            jobs=Jobs(clock.deterministic, clock.now),
            clock_now=clock.now,
            frame=self._frame,
            memory=TaskMemory(start_node, start.pose.yaw if start_heading is None else start_heading),
        )
        if resume is not None:
            resume.restore_runner(self)

    # -- control from outside ----------------------------------------------------------------
    def pause(self) -> None:
        """Hold the vehicle still until `resume()`; timeouts and progress checks freeze meanwhile."""
        self.controls.pause()

    def resume(self) -> None:
        """Continue after `pause()`."""
        self.controls.resume()

    def cancel(self) -> None:
        """Stop the vehicle and end the mission (the current task fails with reason `cancelled`)."""
        self.controls.cancel()

    def task_time(self) -> float:
        """The clock less the time spent paused (s): what behaviours and path followers see."""
        paused = self.paused_total_s
        if self._paused_since is not None:
            paused += self.clock.now() - self._paused_since
        return self.clock.now() - paused

    # -- recording ---------------------------------------------------------------------------
    def log(self, event: str, **data: Any) -> None:
        """Record an event: a line of events.jsonl (`t` on the runner's clock, s) and every observer's call."""
        t = self.clock.now()
        if self.events is not None:
            self.events.write(dumps_json({"t": round(t, 3), "event": event, **data}) + "\n")
            self.events.flush()  # `tail -f events.jsonl` follows the run
        for listener in self.listeners:
            listener(event, data, t)

    def _show(self, task: TaskResult, state: str) -> None:
        if self.progress is None:
            return
        togo = ""
        if state in _DRIVING_STATES:
            remaining = getattr(self.ctx.follower, "distance_to_go", None)
            if remaining is not None:
                togo = f" {remaining:5.1f} m to go"
        paused = " | PAUSED" if self._paused_since is not None else ""
        # the Pickup's pallet estimates so far, as report.json's `attempts` counts them (other tasks make none)
        estimates = f" | estimate {self.ctx.memory.attempts}" if self.ctx.memory.attempts else ""
        line = (
            f"[{self.clock.now():7.1f} s] task {task.index + 1}/{len(self.mission.tasks)} {task.type}"
            f" {task.node or ''} | {state}{estimates}{togo}{paused}"
        )
        self.progress.show((task.index, state, bool(paused)), line)

    # -- running -----------------------------------------------------------------------------
    def run(self) -> bool:
        """Run every task in order; stops at the first failure. True when all succeeded. Never raises."""
        ok = False
        try:
            first, state = (
                (0, None) if self.resume_point is None else (self.resume_point.task_index, self.resume_point.state)
            )
            if self.resume_point is None:
                self.log("mission_start", name=self.mission.name, tasks=len(self.mission.tasks))
            else:
                self.log("mission_resumed", task=first, state=state, resumes=self.resume_point.resumes)
            ok = True
            for i in range(first, len(self.mission.tasks)):
                result = self._run_task(i, self.mission.tasks[i], state if i == first else None)
                self.results.append(result)
                if result.result != Outcome.SUCCEEDED:
                    ok = False
                    break
                self._checkpoint(i + 1, None, None)
        except Exception as exc:  # outside a task's tick loop: still stop, still report
            ok = False
            self._internal_error(exc, None)
        finally:
            self._stop_safely("mission end")
            self.ctx.jobs.close()
        with contextlib.suppress(Exception):
            self.log("mission_end", success=ok)
        if self.progress is not None:
            self.progress.close()
        return ok

    def _run_task(self, index: int, task: Task, start_state: str | None) -> TaskResult:
        ctx = self.ctx
        kind = pickup_kind(self.settings) if task.type == "pickup" else task.type
        table = behaviours(kind, self.settings)
        node = getattr(task, "node", None)
        result = TaskResult(index, task.type, node, start_s=self.clock.now())
        resuming = start_state is not None and self.resume_point is not None
        memory = ctx.memory
        if not resuming:
            memory.start_task(task)
            if node is not None and task.type in ("pickup", "delivery"):
                memory.pallet_node, memory.pre_node = node, ctx.roadmap.pre_pallet_of(node)
            self.log("task_start", index=index, type=task.type, node=node)
        memory.task = task
        memory.record = result.record
        self.ctx = ctx = dataclasses.replace(ctx, pallet_type=self.pallet_types[index])
        model = build_machine(kind, initial=start_state)
        with contextlib.ExitStack() as stack:
            memory.overlay = stack.enter_context(ctx.roadmap.overlay())  # temporary nodes vanish with the task
            if resuming:
                assert self.resume_point is not None
                self.resume_point.restore_task(self, result)
            behaviour: Behaviour | None = None
            entered, active = self.clock.now(), 0.0  # active: time in the state while not paused
            while model.state not in (Outcome.SUCCEEDED, Outcome.FAILED):
                state = model.state
                trigger: str | None = None
                try:
                    if behaviour is None:
                        self._checkpoint(index, state, result)
                        behaviour = table[state]()
                        entered, active = self.clock.now(), 0.0
                        self.log("state_start", task=index, state=state)
                        behaviour.start(ctx)
                    trigger = self._tick(behaviour, state, active)
                except TaskFailed as exc:
                    trigger = self._fail(result, state, exc.reason, str(exc))
                except Exception as exc:
                    trigger = self._internal_error(exc, result, state)
                if trigger is None or trigger == _PAUSED:
                    self._record_tick(result, state)
                    self.clock.tick()
                    if trigger is None:
                        active += self.clock.dt
                    continue
                self._leave(behaviour, trigger)
                end = round(self.clock.now(), 3)
                result.states.append({"state": state, "start_s": round(entered, 3), "end_s": end, "outcome": trigger})
                self.log("state_end", task=index, state=state, outcome=trigger)
                if state == "estimate_pallet" and trigger == "misaligned":
                    memory.node_before = self._node_before()
                getattr(model, trigger)()
                behaviour = None
                if state == "drive_to_pre_pallet" and trigger == "done":
                    memory.node_before = self._node_before()
                    route = memory.last_route
                    memory.route_to_pre = list(route.nodes) if route and route.nodes[-1] == memory.pre_node else []
            self._stop_safely(result.reason or "task end")
            if model.state == Outcome.FAILED and self.mission.returns_on_failure(task, self.settings.return_on_failure):
                self._return_on_failure(result)  # inside the overlay: it may back out over temporary edges
        result.result = Outcome(model.state)
        result.attempts = memory.attempts
        result.end_s = self.clock.now()
        self.log("task_end", task=index, result=result.result, reason=result.reason)
        return result

    def _tick(self, behaviour: Behaviour, state: str, active: float) -> str | None:
        """One control tick of a state: controls, watchdogs, faults, then the behaviour."""
        ctx, vehicle = self.ctx, self.vehicle
        if self.controls.cancelled:
            raise TaskFailed(CANCELLED, self.controls.cancel_reason or "cancelled by the operator")
        self._track_motion()
        self.watchdogs.check(self.clock.now(), vehicle, self.clock)
        faults = vehicle.faults()
        if faults:
            raise TaskFailed(COLLISION, "; ".join(faults))
        if self.controls.paused:
            if self._paused_since is None:
                self._paused_since = self.clock.now()
                vehicle.stop()
                vehicle.set_fork_height(vehicle.fork_height)  # hold the forks where they are
                self.log("paused", state=state)
                if self.progress is not None:
                    self.progress.note(f"[{self.clock.now():7.1f} s] paused in {state} (SIGUSR2 resumes)")
            vehicle.stop()
            return _PAUSED
        if self._blocked(behaviour, state):
            return _PAUSED
        if self._paused_since is not None:
            self.paused_total_s += self.clock.now() - self._paused_since
            self._paused_since = None
            self.watchdogs.reset()
            self.log("resumed", state=state)
            if self.progress is not None:
                self.progress.note(f"[{self.clock.now():7.1f} s] resumed in {state}")
            behaviour.resume(ctx)
        trigger = behaviour.update(ctx)
        if trigger is None and active > behaviour.timeout_s:
            raise TaskFailed(TIMEOUT, f"state '{state}' timed out after {behaviour.timeout_s:.0f} s")
        return trigger

    def _blocked(self, behaviour: Behaviour, state: str) -> bool:
        """Hold a driving state while the safety scanners' protective stop holds the truck (task time
        stands still, as in a pause); `path_blocked` after `Settings.blocked_wait_s`."""
        now = self.clock.now()
        safety = self.vehicle.safety_state() if getattr(behaviour, "drives", False) else None
        if safety is None or not safety.protective_stop:
            if self._blocked_since is not None:
                self.log("path_clear", state=state, waited_s=round(now - self._blocked_since, 2))
                self._blocked_since = None
            return False
        if self._blocked_since is None:
            self._blocked_since = now
            if self._paused_since is None:
                self._paused_since = now
            self.log("path_blocked_hold", state=state, intrusions=list(safety.intrusions))
            if self.progress is not None:
                what = ", ".join(safety.intrusions) or "something"
                self.progress.note(f"[{now:7.1f} s] path blocked by {what}: holding in {state}")
        self.vehicle.stop()
        waited = now - self._blocked_since
        if waited > self.settings.blocked_wait_s:
            self._blocked_since = None
            if self._paused_since is not None:  # the hold ends with the task
                self.paused_total_s += now - self._paused_since
                self._paused_since = None
            what = ", ".join(safety.intrusions) or "an object in the protective field"
            raise TaskFailed(
                PATH_BLOCKED,
                f"the path stayed blocked by {what} for {waited:.0f} s (limit {self.settings.blocked_wait_s:.0f} s)",
            )
        return True

    def _fail(self, result: TaskResult | None, state: str | None, reason: Reason, message: str) -> str:
        if result is not None and result.reason is None:
            result.reason, result.message = reason, message
        self.stops.append({"t_s": round(self.clock.now(), 3), "reason": reason, "speed": self._speed()})
        with contextlib.suppress(Exception):
            self.log(
                "task_failed",
                task=None if result is None else result.index,
                state=state,
                reason=reason,
                message=message,
            )
        self._stop_safely(reason)
        return "fail"

    def _internal_error(self, exc: BaseException, result: TaskResult | None, state: str | None = None) -> str:
        message = f"{type(exc).__name__}: {exc}"
        with contextlib.suppress(Exception):
            self.log("internal_error", state=state, traceback=traceback.format_exc(limit=8))
        if result is None and self.results:
            result = self.results[-1]
        return self._fail(result, state, INTERNAL_ERROR, message)

    def _leave(self, behaviour: Behaviour | None, trigger: str) -> None:
        """Run the behaviour's `stop()`; an exception there is logged and the vehicle stopped anyway."""
        if behaviour is None:
            return
        try:
            behaviour.stop(self.ctx)
        except Exception as exc:
            with contextlib.suppress(Exception):
                self.log("stop_failed", error=f"{type(exc).__name__}: {exc}")
            self._stop_safely("a behaviour's stop failed")

    def _speed(self) -> float | None:
        try:
            return round(float(self.vehicle.speed), 4)
        except Exception:
            return None

    def _stop_safely(self, why: str, limit_s: float = 10.0) -> None:
        """Bring the vehicle to a standstill (safety stop while it moves); never raises."""
        vehicle = self.vehicle
        try:
            if abs(vehicle.speed) > QUICK_STOP_SPEED:
                vehicle.emergency_stop()
                self.log("safety_stop", why=why, speed=round(vehicle.speed, 3))
            else:
                vehicle.stop()
            t_end = self.clock.now() + limit_s
            while abs(vehicle.speed) >= STANDSTILL_SPEED and self.clock.now() < t_end:
                vehicle.stop()
                self.clock.tick()
            standing = abs(vehicle.speed) < STANDSTILL_SPEED
        except Exception as exc:
            standing = False
            with contextlib.suppress(Exception):
                self.log("stop_error", error=f"{type(exc).__name__}: {exc}")
        if self.stops and "standstill_s" not in self.stops[-1]:
            self.stops[-1]["standstill_s"] = round(self.clock.now(), 3) if standing else None
        if not standing:
            with contextlib.suppress(Exception):
                self.log("vehicle_not_stopped", why=why)

    def _track_motion(self) -> None:
        """Remember when the vehicle or its forks last moved (perception results must be newer)."""
        v = self.vehicle
        height = v.fork_height
        moved_forks = self._last_fork_height is not None and abs(height - self._last_fork_height) > 1e-3
        if abs(v.speed) > STANDSTILL_SPEED or moved_forks:
            self.ctx.memory.last_motion_s = self.clock.now()
        self._last_fork_height = height

    def _frame(self) -> FrameBundle | None:
        """A fresh camera frame, or None this tick; `sensor_timeout` when none came for too long."""
        now = self.clock.now()
        limit = self.watchdogs.limits.camera_max_age_s
        try:
            frame = self._grab()
            self.watchdogs.check_frame(frame, now)
        except (PerceptionError, TaskFailed) as exc:
            if self._no_frame_since is None:
                self._no_frame_since = now
            waited = now - self._no_frame_since
            if waited > limit:
                raise TaskFailed(SENSOR_TIMEOUT, f"no fresh camera frame for {waited:.2f} s: {exc}") from None
            return None
        self._no_frame_since = None
        return frame

    def _checkpoint(self, index: int, state: str | None, result: TaskResult | None) -> None:
        if self.checkpointer is not None:
            self.checkpointer.checkpoint(self, index, state, result)

    def _node_before(self) -> str | None:
        """The node before the pre-pallet node: on the route that reached it, else a node joined both ways."""
        memory, graph = self.ctx.memory, self.ctx.roadmap.graph
        route = memory.last_route
        if route is not None and memory.pre_node in route.nodes:
            before = route.node_before(memory.pre_node)
            if before is not None and graph.has_edge(memory.pre_node, before):
                return before
        pallet = memory.node_task().node
        original_pre = self.ctx.roadmap.pre_pallet_of(pallet)
        for u in graph.predecessors(original_pre):
            if u != pallet and graph.has_edge(original_pre, u) and not self.ctx.roadmap.node(u).temporary:
                return u
        return None

    def _record_tick(self, result: TaskResult, state: str) -> None:
        pose = self.vehicle.localization()
        now = self.clock.now()
        if not self.trajectory or now - self.trajectory[-1][0] >= 0.2:
            self.trajectory.append((now, pose.x, pose.y, pose.yaw))
        self._show(result, state)

    # -- after a failure: to a parking node ------------------------------------------------------
    def _return_on_failure(self, result: TaskResult) -> None:
        """After a failed task whose `return_on_failure` holds: leave the slot, aisle or pallet approach and
        wait at the nearest parking node by route length (the map's `parking_types`). Never raises.

        Logs `returning_on_failure` then `parked`, or `return_failed` with the reason the truck stays
        stopped: the task failed with a reason in `STAY_STOPPED` (or was cancelled), the truck stands off
        the roadmap (between nodes), no parking node can be reached, or the drive there failed (every tick
        runs the task's checks: controls, watchdogs, faults, timeout). The task's record gets
        `return_on_failure`: `parking_node`, `parked`, `route_length_m`, `reason`.
        """
        ctx = self.ctx
        record: dict[str, Any] = {"parking_node": None, "parked": False, "route_length_m": None, "reason": None}
        result.record["return_on_failure"] = record
        why: str | None
        try:
            why = self._park(result, record)
        except TaskFailed as exc:
            why = f"{exc.reason}: {exc}"
            self.stops.append({"t_s": round(self.clock.now(), 3), "reason": exc.reason, "speed": self._speed()})
        except Exception as exc:
            why = f"{INTERNAL_ERROR}: {type(exc).__name__}: {exc}"
            with contextlib.suppress(Exception):
                self.log("internal_error", state=_RETURN_STATE, traceback=traceback.format_exc(limit=8))
        self._stop_safely("return on failure")
        with contextlib.suppress(Exception):
            if why is None:
                record["parked"] = True
                self.log("parked", task=result.index, node=ctx.memory.at_node)
            else:
                record["reason"] = why
                self.log("return_failed", task=result.index, node=ctx.memory.at_node, reason=why)

    def _park(self, result: TaskResult, record: dict[str, Any]) -> str | None:
        """Drive to the nearest parking node (see `_return_on_failure`); None when there, else why the truck
        stays where it is. A failure while moving raises `TaskFailed`."""
        ctx = self.ctx
        if result.reason in STAY_STOPPED or self.controls.cancelled:
            return f"the task failed with {result.reason or CANCELLED}: the truck stays stopped"
        here = ctx.roadmap.node(ctx.memory.at_node)
        pose = self.vehicle.localization()
        off_m = math.hypot(pose.x - here.pose.x, pose.y - here.pose.y)
        off_deg = abs(math.degrees(angle_diff(pose.yaw, ctx.memory.heading)))
        if off_m > PARK_POSE_TOLERANCE_M or off_deg > PARK_YAW_TOLERANCE_DEG:
            return (
                f"the truck stands {off_m:.2f} m and {off_deg:.0f} deg off node '{here.id}', the last it reached "
                f"(limits {PARK_POSE_TOLERANCE_M} m, {PARK_YAW_TOLERANCE_DEG:.0f} deg): off the roadmap, it stays"
            )
        if here.type in (NodeType.PALLET, NodeType.DROP) and here.pre_pallet:
            out = Route([here.id, here.pre_pallet], [ctx.roadmap.edge(here.id, here.pre_pallet)])
            self._drive(result, FollowRoute(lambda c: out.nodes[-1], via=lambda c: out))  # forks where they are
        self._drive(result, SetForks(travel_height))  # out of the slot: forks down to travel height
        parking = ctx.roadmap.parking_nodes()
        types = ", ".join(sorted(t.value for t in ctx.roadmap.parking_types))
        if not parking:
            return f"the map has no node of a parking type ({types})"
        best: Route | None = None
        for node in parking:  # the planner honours the heading; temporary edges lead out of a re-plan
            with contextlib.suppress(RoadmapError):
                route = ctx.planner.plan(ctx.memory.at_node, node.id, start_yaw=ctx.memory.heading)
                if best is None or route.length < best.length:
                    best = route
        if best is None:
            names = ", ".join(f"'{n.id}'" for n in parking)
            return f"no parking node ({types}: {names}) can be reached from '{ctx.memory.at_node}'"
        goal, chosen = best.nodes[-1], best
        record["parking_node"], record["route_length_m"] = goal, round(best.length, 3)
        self.log(
            "returning_on_failure",
            task=result.index,
            failed=result.reason,
            from_node=ctx.memory.at_node,
            node=goal,
            route=best.nodes,
            length_m=round(best.length, 3),
        )
        self._drive(result, FollowRoute(lambda c: goal, via=lambda c: chosen))
        return None

    def _drive(self, result: TaskResult, behaviour: Behaviour) -> None:
        """Run one behaviour to its end outside the task's machine, tick by tick with the task's checks
        (`_tick`: controls, watchdogs, faults, pause, timeout); a failure raises `TaskFailed`."""
        behaviour.start(self.ctx)
        active = 0.0
        try:
            while True:
                trigger = self._tick(behaviour, _RETURN_STATE, active)
                if trigger is not None and trigger != _PAUSED:
                    return
                self._record_tick(result, _RETURN_STATE)
                self.clock.tick()
                if trigger is None:
                    active += self.clock.dt
        finally:
            self._leave(behaviour, "done")
