"""The AGV's legs: one `Runner` per leg of the order, its action states and results, as `agv.Agv` runs them.

`agv.Agv.run` takes the next leg (`OrderManager.plan_next`) and runs it here (`_leg`) on the executor
thread, each with a one-task `Mission`:

- `move`: a Move task to the leg's last node along exactly the order's edges (`legs.OrderPlanner` hands the
  runner the order's route); nodes on the way count as traversed when the truck passes within their
  deviation range (`agv.Agv`'s tick), the last one when the truck stands there. Edges with `maxSpeed` are
  slowed for the leg (`legs.speed_limits`; 3.0: and SPEED_LIMIT zones).
- `pick`: at the pallet node's pre-pallet node, the adaptive Pickup (`loadType` -> pallet type, `height`).
  Its approach (calibrate, estimate, re-plan, enter) is the traversal of the order's last edge: the action
  stays WAITING (section 6.11, table 2; node actions start at their node, 6.10.2) until the forks are in
  and the pallet node is traversed, then RUNNING while the truck stands and lifts, FINISHED once the load
  is lifted; the pre-pallet node is traversed when the truck has backed out. Backing out waits (the runner
  held as in a pause, the scanners' narrow set muting the load ahead of the forks: `legs.SlotFields`) until
  that edge is released. A failed Pickup: FAILED with the reason in an error (`palletNotFound`, ...).
- `drop`: the checked Delivery likewise (WAITING until the forks are in the slot, RUNNING while lowering).
- `actions`: node actions of the current node (`startCharging`, `stopCharging`).

The runner's events (`_on_event`, on its thread) move the action states on; an action PAUSED by the master
takes its new status on the resume (`_set`). A leg that fails (not by a cancel) halts the truck with an
error naming the leg's order node and action (`_leg_failed`); it takes no further leg until the master
cancels the order or sends a new one. Each leg's task results and one line per leg (order, kind, route,
outcome, times) are kept for the session's recording (`results`, `legs`; events `leg_start`, `leg_end`,
`leg_failed`).

Public API: `AgvLegs` (a base of `agv.Agv`; the attributes it declares are the AGV's).
"""

from __future__ import annotations

import contextlib
import threading
from collections.abc import Callable
from typing import TYPE_CHECKING, Any

from palletpilot.executor.apps import compose
from palletpilot.executor.apps.vda5050.actions import LOAD_HANDLING_DEVICE, IllegalTransitionError
from palletpilot.executor.apps.vda5050.config import Loaded
from palletpilot.executor.apps.vda5050.legs import AgvControls, OrderPlanner, from_where_it_stands, speed_limits
from palletpilot.executor.apps.vda5050.models import Action, ActionStatus, AgvError
from palletpilot.executor.apps.vda5050.orders import Leg, OrderManager
from palletpilot.executor.apps.vda5050.routes import pallet_name
from palletpilot.executor.apps.vda5050.state import Snapshot, error_type, reason_level
from palletpilot.executor.apps.vda5050.v3 import V3Side
from palletpilot.executor.apps.vda5050.vehicle import Backend
from palletpilot.executor.core.behaviour import Settings
from palletpilot.executor.core.errors import CANCELLED
from palletpilot.executor.core.mission import Mission
from palletpilot.executor.core.results import TaskResult
from palletpilot.executor.core.runner import Runner
from palletpilot.executor.ports import VehiclePort
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.specs import builtin_pallet
from palletpilot.roadmap import Roadmap

if TYPE_CHECKING:
    from palletpilot.executor.adapters.mcap.recording import Recorder

__all__ = ["AgvLegs"]

A = ActionStatus


class AgvLegs:
    """The leg side of `agv.Agv` (module docstring); the attributes below are the AGV's."""

    loaded: Loaded
    backend: Backend
    roadmap: Roadmap
    orders: OrderManager
    vehicle: VehiclePort
    grab: Callable[[], FrameBundle]
    settings: Settings
    controls: AgvControls
    recorder: Recorder | None
    v3: V3Side | None
    snapshot: Snapshot
    heading: float
    halted: str | None
    load: dict[str, Any] | None
    leg: Leg | None
    runner: Runner | None
    results: list[TaskResult]
    legs: list[dict[str, Any]]
    _carried_type: str
    _in_slot: bool
    _cancel_action: str | None
    _stop: threading.Event
    log: Callable[[str], None]
    changed: Callable[[], None]
    _note: Callable[..., None]
    _nearest_node: Callable[[], str | None]
    _axis_heading: Callable[[str], float]
    _charging: Callable[[Action, bool], None]

    def _leg(self, leg: Leg) -> None:
        o = self.orders
        if leg.kind == "actions":
            for a in leg.actions:
                if a.action_type in ("startCharging", "stopCharging"):
                    o.actions.set(a.action_id, A.RUNNING)
                    self._charging(a, a.action_type == "startCharging")
            return
        action = leg.actions[0] if leg.actions else None
        mission, pallet = self._mission(leg, action)
        self.log(f"agv: {leg.kind} {' -> '.join(leg.route)}")
        node_ref = [("node.nodeId", o.nodes[leg.index].node_id)] if leg.index < len(o.nodes) else []
        line: dict[str, Any] = {
            "order_id": o.order_id,
            "order_update_id": o.order_update_id,
            "kind": leg.kind,
            "route": list(leg.route),
            "ok": False,
            "reason": None,
            "start_s": round(self.backend.clock.now(), 3),
        }
        self._note("leg_start", **{k: line[k] for k in ("order_id", "order_update_id", "kind", "route")})
        self.leg = leg
        s = self.snapshot
        with self._speed_limits(leg), from_where_it_stands(self.roadmap, leg, s.x, s.y) as route:
            parts = compose.Parts(
                mission,
                self.roadmap,
                self.vehicle,
                self.backend.perception,
                self.grab,
                self.backend.clock,
                self.backend.params,
                self.backend.forks,
                route[0],
                self.backend.follower,
                observers=(*self.backend.listeners, self._on_event),
                planner=OrderPlanner(self.roadmap, route),
                start_heading=self.heading if route == leg.route else self.roadmap.node(route[0]).pose.yaw,
            )
            runner = compose.build_runner(
                parts, compose.Outputs(recorder=self.recorder), self.settings, controls=self.controls
            )
            self.runner = runner
            try:
                ok = runner.run()
            finally:
                if self.recorder is not None:
                    self.recorder.detach()
        self.runner, self.leg = None, None
        self.heading = runner.ctx.memory.heading
        near = None if ok else self._nearest_node()
        if near is not None:  # stopped at a node (cancelled, failed): the heading it stands with there
            self.heading = self._axis_heading(near)
        self.controls.gate = None
        self.controls.refresh()
        result = runner.results[-1] if runner.results else None
        self.results.extend(runner.results)
        line.update(ok=ok, reason=None if ok else (result.reason if result else None) or "internal_error")
        line["end_s"] = round(self.backend.clock.now(), 3)
        self.legs.append(line)
        self._note("leg_end" if ok or line["reason"] == CANCELLED else "leg_failed", **line)
        if ok:
            if leg.kind == "move":
                for node in leg.route[1:]:
                    o.arrive(node)
            elif action is not None:
                if leg.kind == "pick":
                    self._carried_type = pallet
                self._set(action, A.FINISHED)
            return
        self._leg_failed(leg, action, result, node_ref)

    def _mission(self, leg: Leg, action: Action | None) -> tuple[Mission, str]:
        """The one-task mission of a leg (move, pickup, delivery) and the pallet type it handles."""
        task: dict[str, Any] = {"type": "move", "node": leg.route[-1]}
        pallet = self._carried_type
        if action is not None:
            height = action.param("height")
            task = {"type": "pickup" if leg.kind == "pick" else "delivery", "node": leg.route[-1]}
            if isinstance(height, (int, float)) and not isinstance(height, bool):
                task["height"] = float(height)
            load_type = action.param("loadType")
            if isinstance(load_type, str) and pallet_name(load_type):
                pallet = str(pallet_name(load_type))
        doc = {"name": f"vda5050 {self.orders.order_id}", "map": str(self.loaded.map_path), "pallet_type": pallet}
        return Mission.model_validate({**doc, "tasks": [task]}), pallet

    def _leg_failed(
        self, leg: Leg, action: Action | None, result: TaskResult | None, node_ref: list[tuple[str, str]]
    ) -> None:
        """A leg that failed (not by a cancel): the truck halts, the error names the leg's order node (a new
        order may have come since) and its action (FAILED, when it is still this order's)."""
        o = self.orders
        reason = (result.reason if result else None) or "internal_error"
        message = (result.message if result else None) or reason
        if reason == CANCELLED and (self._cancel_action is not None or self._stop.is_set()):
            return
        self.halted = reason
        refs: list[tuple[str, str]] = list(node_ref)
        record = o.actions.record_of(action) if action is not None else None
        if action is not None and record is not None:
            refs += [("actionId", action.action_id), ("actionType", action.action_type)]
        error = AgvError(
            error_type(reason),
            reason_level(reason),
            f"{reason}: {message}",
            (*refs, ("reason", reason)),
            "the truck stopped; cancel the order (cancelOrder) and send a new one",
        )
        if action is not None and record is not None and not record.final:
            o.fail_action(action.action_id, error, f"{reason}: {message}")
        else:
            with o.lock:
                o.errors.append(error)
        self.log(f"agv: {leg.kind} failed: {reason}: {message}")

    def _speed_limits(self, leg: Leg) -> contextlib.AbstractContextManager[None]:
        """The order's `maxSpeed` (3.0: and SPEED_LIMIT zones) on the leg's roadmap edges while it runs."""
        return speed_limits(self.orders, self.roadmap, leg, self.v3.leg_speed_limits if self.v3 else None)

    def _set(self, action: Action, status: ActionStatus) -> None:
        """Move an order action on; while it is PAUSED the new status waits for the resume. Nothing when its
        order's action states are gone (a new order came while the leg ran)."""
        record = self.orders.actions.record_of(action)
        if record is None:
            return
        try:
            if record.status is A.PAUSED and status in (A.INITIALIZING, A.RUNNING):
                record.resume_to = status
            elif not record.final:
                self.orders.actions.set(action.action_id, status)
        except IllegalTransitionError as exc:
            self.log(f"agv: {exc}")
        self.changed()

    def _on_event(self, event: str, data: dict[str, Any], t: float) -> None:
        """The runner's events (its thread): action states, traversed nodes and gates of pick and drop."""
        leg, runner = self.leg, self.runner
        if leg is None or runner is None or leg.kind not in ("pick", "drop") or not leg.actions:
            return
        a, pre, node = leg.actions[0], leg.route[0], leg.route[-1]
        state = data.get("state")
        if event == "state_start":
            if state == "reverse_out" and not self.orders.can_enter(pre):
                self._in_slot = True  # before the back-out's drive selects its fields (`legs.SlotFields`)
                self.vehicle.set_safety_field_set("narrow", "reverse")
                self._gate(pre)
            elif state == "return_to_roadmap":
                ctx = runner.ctx.memory
                if ctx.node_before and ctx.pre_node and self.roadmap.node(ctx.pre_node).temporary:
                    if not self.orders.can_enter(ctx.node_before):
                        self._gate(ctx.node_before)
        elif event == "state_end" and data.get("outcome") == "done":
            if state == "enter":  # the node is reached: the action runs there (the truck stands)
                self.orders.arrive(node)
                self._set(a, A.RUNNING)
            elif state == ("lift" if leg.kind == "pick" else "lower"):
                self._handled(a, leg.kind)
            elif state == "reverse_out":
                self.orders.arrive(pre)
            elif state == "return_to_roadmap":
                self.orders.arrive(runner.ctx.memory.at_node)
            self.changed()

    def _handled(self, a: Action, kind: str) -> None:
        """A pick or drop's load moved: FINISHED, and the load reported (or no longer)."""
        if kind == "pick":
            name = pallet_name(str(a.param("loadType", "eur"))) or "eur"
            pallet = builtin_pallet(name)
            load: dict[str, Any] = {"loadType": name, "loadPosition": LOAD_HANDLING_DEVICE}
            if a.has("loadId"):
                load["loadId"] = str(a.param("loadId"))
            if pallet is not None:
                load["loadDimensions"] = {"length": pallet.length, "width": pallet.width, "height": pallet.height}
            self.load = load
        else:
            self.load = None
        self._set(a, A.FINISHED)

    def _gate(self, node: str) -> None:
        self.controls.gate = node
        self.controls.refresh()
        self.log(f"agv: waiting for the order to release the way to '{node}'")
        self.changed()
