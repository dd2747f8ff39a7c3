"""The AGV: VDA 5050 orders executed by the runner's task machines, state published over MQTT.

Threads: paho's network thread hands in messages (`on_message`: orders go through the `OrderManager`,
instant actions set flags); the executor thread (`run`) drives the truck; a publisher thread sends the
state on every event and at least every `state_interval_s`, and the visualization at its rate. Only the
executor thread touches the vehicle: it samples it after every clock tick (`TickClock` hook) into a
`Snapshot` that the other threads read.

Execution, one `Runner` per leg (`OrderManager.plan_next`), each with a one-task `Mission`:

- `move`: a Move task to the leg's last node along exactly the order's edges (`OrderPlanner` hands the
  runner the order's route); nodes on the way count as traversed when the truck passes within their
  deviation range, the last one when the truck stands there. Edges with `maxSpeed` are slowed for the leg.
- `pick`: at the pallet node's pre-pallet node, the adaptive Pickup (`loadType` -> pallet type, `height`).
  Its approach (calibrate, estimate, re-plan, enter) is the traversal of the order's last edge: the action
  stays WAITING (section 6.11, table 2; node actions start at their node, 6.10.2) until the forks are in
  and the pallet node is traversed, then RUNNING while the truck stands and lifts, FINISHED once the load
  is lifted; the pre-pallet node is traversed when the truck has backed out. Backing out waits (the runner
  held as in a pause, the scanners' narrow set muting the load ahead of the forks) until that edge is
  released. A failed Pickup: FAILED with the reason in an error (`palletNotFound`, ...).
- `drop`: the checked Delivery likewise (WAITING until the forks are in the slot, RUNNING while lowering).
- `actions`: node actions of the current node (`startCharging`, `stopCharging`).

An error in this AGV's own code (not a task's failure) stops the truck and halts the order with a FATAL
`internalError`; the executor thread goes on. After a failure the truck stays stopped and takes no further
leg until the master cancels the order or sends a new one. Connection loss changes nothing here: the
truck goes on up to the last released node.

Instant actions: `instant.AgvInstantActions` (a base of `Agv`) runs them on the network thread.

VDA 5050 3.0.0 (`protocol_version: 3.0.0`): the same AGV behind a version layer (`v3.V3Side`): messages in are
checked and translated to the 2.1 form before `on_message` goes on, `v3_out.MessagesV3` builds the messages
out, and its zone guard runs on every tick.

Crash safety: `restart.AgvJournal` (a base of `Agv`) checkpoints to the journal (`persist`) on every
`changed()` and restores the last checkpoint after a restart, with its safe rule.

Recording (`executor.recording`, with a `Recorder`): the whole session in one file. The recorder wraps
the vehicle once (every leg's runner drives the wrapper) and the camera, follows each leg's runner
(`attach` / `detach`), ticks with the clock (`TickClock` hook), and takes the session's own events as
`/log` and `/events` entries: `order_accepted`, `order_rejected`, `message_rejected`, `instant_action`,
`leg_start`, `leg_end`, `leg_failed`. `finish_recording()` writes the session's `/report/run` (every
leg's task results, the legs; success when every leg succeeded) and closes the file.

Public API: `Agv` (`run`, `stop`, `connect`, `publisher`, `on_message`, `finish_recording`, and from
`AgvJournal`: `attach_journal`, `checkpoint_doc`, `restore`), `AgvControls`, `OrderPlanner`.
"""

from __future__ import annotations

import contextlib
import hashlib
import math
import threading
import time
from collections.abc import Callable
from typing import TYPE_CHECKING, Any, cast

from palletpilot.executor.adapters.local_perception import LocalPerception
from palletpilot.executor.apps import compose
from palletpilot.executor.apps.vda5050 import validation
from palletpilot.executor.apps.vda5050.actions import LOAD_HANDLING_DEVICE, IllegalTransitionError
from palletpilot.executor.apps.vda5050.config import Loaded
from palletpilot.executor.apps.vda5050.instant import AgvInstantActions
from palletpilot.executor.apps.vda5050.legs import (
    AgvControls,
    OrderPlanner,
    SlotFields,
    from_where_it_stands,
    speed_limits,
)
from palletpilot.executor.apps.vda5050.midedge import locate
from palletpilot.executor.apps.vda5050.models import Action, ActionStatus, AgvError
from palletpilot.executor.apps.vda5050.mqtt import AgvLink
from palletpilot.executor.apps.vda5050.orders import Leg, OrderManager, VehicleView
from palletpilot.executor.apps.vda5050.persist import Persister
from palletpilot.executor.apps.vda5050.restart import AgvJournal
from palletpilot.executor.apps.vda5050.routes import DEFAULT_DEVIATION_XY, pallet_name
from palletpilot.executor.apps.vda5050.state import Messages, Snapshot, error_type, reason_level
from palletpilot.executor.apps.vda5050.v3 import V3, MessagesV3, V3Side
from palletpilot.executor.apps.vda5050.validation import Headers
from palletpilot.executor.apps.vda5050.vehicle import Backend
from palletpilot.executor.core.behaviour import Settings
from palletpilot.executor.core.errors import CANCELLED, INTERNAL_ERROR
from palletpilot.executor.core.mission import Mission
from palletpilot.executor.core.results import TaskResult
from palletpilot.executor.core.runner import Runner
from palletpilot.executor.ports import VehiclePort
from palletpilot.geometry import angle_diff
from palletpilot.perception.specs import builtin_pallet

if TYPE_CHECKING:
    from palletpilot.executor.adapters.mcap.recording import Recorder

A = ActionStatus
STOPPED_SPEED = 0.01
"""m/s: a cancelOrder cancels the running leg once the truck is this slow (the runner's service stop)."""


class Agv(AgvInstantActions, AgvJournal):
    """One VDA 5050 AGV over a vehicle backend (see the module docstring). `recorder`: record the whole
    session into it (the caller closes it with `finish_recording`)."""

    def __init__(
        self,
        loaded: Loaded,
        backend: Backend,
        log: Callable[[str], None] = lambda line: None,
        settings: Settings | None = None,
        software_version: str = "",
        recorder: Recorder | None = None,
    ) -> None:
        cfg = loaded.config
        self.loaded, self.config, self.backend, self.log = loaded, cfg, backend, log
        self.roadmap = loaded.roadmap
        self.recorder = recorder
        self.vehicle: VehiclePort = backend.vehicle
        """What the runners drive and the AGV samples (the recorder's pass-through wrapper when recording)."""
        self.grab = backend.grab
        self._in_slot = False
        """A pick or drop leg waits with the forks in the slot for the back-out's release (`legs.SlotFields`)."""
        self.results: list[TaskResult] = []
        """Every leg's task results, in order (the session's `/report/run`)."""
        self.legs: list[dict[str, Any]] = []
        """One line per leg run: order, kind, route, outcome, times (s)."""
        self.session_name = f"vda5050 {cfg.manufacturer}/{cfg.serial_number}"
        """The recording's name for the session (its `/report/run` mission)."""
        if recorder is not None:
            follower, name = backend.follower, self.session_name
            self.vehicle = recorder.start_session(
                backend.vehicle, backend.clock.now, backend.params, backend.forks, self.roadmap, follower, name
            )
            self.grab = recorder.wrap_grab(backend.grab)
            perception = backend.perception
            if isinstance(perception, LocalPerception) and perception.segmenter is not None:
                perception.segmenter = recorder.wrap_segmenter(perception.segmenter)
        self.vehicle = cast(VehiclePort, SlotFields(self.vehicle, lambda: self._in_slot))
        self.orders = OrderManager(loaded.roadmap, cfg.map_name, loaded.vehicle)
        version = hashlib.sha256(loaded.map_path.read_bytes()).hexdigest()[:12]
        headers = Headers(cfg.protocol_version, cfg.manufacturer, cfg.serial_number)
        self.messages = (MessagesV3 if cfg.protocol_version == V3 else Messages)(
            headers,
            cfg.map_name,
            version,
            loaded.vehicle,
            cfg.state_interval_s,
            cfg.visualization_hz,
            cfg.max_load_kg,
            fork_length=backend.forks.tip_x,
        )
        self.v3: V3Side | None = (
            V3Side(self.orders, self.messages, loaded, backend, log) if cfg.protocol_version == V3 else None
        )
        """The 3.0 version layer (`v3`): its inbound side, zones and zone guard; None on 2.x."""
        self.software_version = software_version
        self.settings = settings or Settings()
        self.controls = AgvControls()
        backend.clock.hook = self._on_tick
        self.link: AgvLink | None = None
        self.on_sent: Callable[[str, dict[str, Any]], None] | None = None
        self.snapshot = Snapshot()
        self.charging = False
        self.halted: str | None = None
        self.leg: Leg | None = None
        self.runner: Runner | None = None
        self.heading = 0.0
        self.distance = 0.0
        self.load: dict[str, Any] | None = None
        self._carried_type = "eur"
        self._pause_action: str | None = None
        self._cancel_action: str | None = None
        self._last_node: tuple[str, int] = ("", 0)
        self._wake = threading.Event()
        self._stop = threading.Event()
        self.persister: Persister | None = None
        """The journal's writer (`attach_journal`): a checkpoint on every `changed()`."""
        self._reserved: dict[str, int] = {}
        """The headerIds reserved per topic by the last checkpoint built."""

    # -- wiring -----------------------------------------------------------------------------------
    def connect(self) -> AgvLink:
        """Create the MQTT link (not started) with this AGV's callbacks."""
        self.link = AgvLink(
            self.config,
            self.messages,
            self.on_message,
            on_connected=self.changed,
            log=self.log,
            software_version=self.software_version,
        )
        return self.link

    def changed(self) -> None:
        """An event: publish the state now and checkpoint it (from any thread; never waits for the disk)."""
        self._wake.set()
        if self.persister is not None:
            self.persister.request()

    def _note(self, event: str, **data: Any) -> None:
        """A session event for the recording (any thread; nothing without a recorder)."""
        if self.recorder is not None:
            self.recorder.note(event, data)

    def finish_recording(self) -> list[str]:
        """End the session's recording (after `run` returned): `/report/run` with every leg's results and
        the legs, then the file finished and the live server stopped. Returns the recorder's error lines
        (none without a recorder)."""
        rec = self.recorder
        if rec is None:
            return []
        success = all(leg["ok"] for leg in self.legs)  # a leg cancelled (by the master, at shutdown) did not succeed
        extra = {"clock": self.backend.clock.stats(), "legs": self.legs}
        rec.finish_session(self.session_name, success, self.results, extra)
        rec.close()
        return list(rec.errors)

    def _send(self, name: str, build: Callable[[], dict[str, Any]]) -> None:
        if self.link is None:
            return
        message = self.link.send(name, build)
        if message is not None and self.on_sent is not None:
            self.on_sent(name, message)

    def state_message(self) -> dict[str, Any]:
        """A state message of now (takes a headerId)."""
        o = self.orders
        with o.lock:
            base_end = o.base_end()
            new_base = o.has_horizon() and 0 <= base_end < o.cursor + 1
        return self.messages.state(
            o,
            self.snapshot,
            paused=self.controls.master_pause,
            charging=self.charging,
            new_base_request=new_base,
            distance_since_last_node=self.distance,
            load=self.load,
        )

    def publish_state(self) -> None:
        """Publish the state (when connected)."""
        self._send("state", self.state_message)

    def publisher(self, stop: threading.Event) -> None:
        """The publisher thread: state on events and every `state_interval_s`, visualization at its rate."""
        cfg = self.config
        next_state = 0.0
        vis_period = 1.0 / cfg.visualization_hz if cfg.visualization_hz > 0 else math.inf
        next_vis = time.monotonic() + vis_period
        while not stop.is_set():
            now = time.monotonic()
            woke = self._wake.wait(max(0.0, min(next_state, next_vis) - now))
            self._wake.clear()
            now = time.monotonic()
            if woke or now >= next_state:
                self.publish_state()
                next_state = now + cfg.state_interval_s
            if now >= next_vis:
                self._send("visualization", lambda: self.messages.visualization(self.snapshot))
                next_vis = max(next_vis + vis_period, now)

    # -- messages in (network thread) ---------------------------------------------------------------
    def on_message(self, name: str, payload: bytes) -> None:
        """An order or instantActions message from the broker (3.0: and zoneSet, responses; via `v3`)."""
        doc, why = validation.parse_message(payload)
        if doc is None:
            self.orders.malformed(name, why or "unreadable")
            self.log(f"agv: {name}: {why}")
            self._note("message_rejected", topic=name, why=why)
        elif (routed := (name, doc) if self.v3 is None else self.v3.inbound.handle(name, doc)) is not None:
            if self.v3 is None and routed[0] in ("order", "instantActions"):
                self._follow_version(routed[1])
            if routed[0] in ("order", "instantActions"):
                (self._order if routed[0] == "order" else self._instant)(routed[1])
        self.changed()

    def _follow_version(self, doc: dict[str, Any]) -> None:
        """Answer in the master's 2.x minor version: a 2.0 master refuses states headed 2.1.0, and the
        messages this AGV sends are valid in both (2.1 only adds optional fields)."""
        version = doc.get("version")
        if not isinstance(version, str):
            return
        minor = ".".join(version.split(".")[:2])
        wanted = {"2.0": "2.0.0", "2.1": "2.1.0"}.get(minor)
        if wanted is not None and wanted != self.messages.headers.version:
            self.log(f"agv: the master speaks VDA 5050 {version}: answering in {wanted}")
            self.messages.headers.version = wanted

    def view(self) -> VehicleView:
        """The truck as the acceptance flow sees it (with the roadmap edge it stands on part way, if any)."""
        s = self.snapshot
        on = None
        if self.leg is None:
            with contextlib.suppress(KeyError, ValueError, RuntimeError):  # the roadmap changing meanwhile
                on = locate(self.roadmap, self.orders.last_rm, s.x, s.y, DEFAULT_DEVIATION_XY)
        fault = "; ".join(s.faults) or None
        return VehicleView(s.x, s.y, s.theta, self.heading, s.loaded, self.charging, fault, on)

    def _order(self, doc: dict[str, Any]) -> None:
        decision = self.orders.receive_order(doc, self.view())
        oid = f"{doc.get('orderId')}/{doc.get('orderUpdateId')}"
        ids = {"order_id": doc.get("orderId"), "order_update_id": doc.get("orderUpdateId")}
        if decision.accepted:
            self.halted = None
            self.log(f"agv: order {oid} accepted ({decision.kind})")
            self._note("order_accepted", **ids, kind=decision.kind, nodes=len(doc.get("nodes") or []))
        elif decision.error is not None:
            self.log(f"agv: order {oid} rejected: {decision.error.error_type}: {decision.error.description}")
            error = decision.error
            self._note("order_rejected", **ids, error_type=error.error_type, description=error.description)

    # -- the executor thread ------------------------------------------------------------------------
    def stop(self) -> None:
        """Ask `run` to end: the running leg is cancelled (the truck stops), then the loop returns."""
        self._stop.set()
        self.controls.cancel("the AGV is shutting down")

    def run(self) -> None:
        """Drive the truck until `stop()`: idle ticks while there is nothing to do, else the next leg."""
        self._sample()
        start = self.backend.start_node or self._nearest_node()
        self.heading = self._axis_heading(start) if start else self.snapshot.theta
        while not self._stop.is_set():
            leg = None
            try:
                if self.halted is None and not self.controls.master_pause and self._cancel_action is None:
                    leg = self.orders.plan_next()
                if leg is None:
                    self.vehicle.stop()
                    self.backend.clock.tick()
                    continue
                self._leg(leg)
            except Exception as exc:  # never an exit: the truck stops and the master hears why
                self._internal_failure(leg, exc)
            self.changed()

    def _internal_failure(self, leg: Leg | None, exc: Exception) -> None:
        """A bug in this AGV's own code (not the runner's, which fails its task): stop the truck, drop the
        leg, halt until the master sends an order (or cancels), and report a FATAL `internalError`."""
        import traceback

        with contextlib.suppress(Exception):
            self.vehicle.stop()
        self.runner, self.leg, self.halted = None, None, INTERNAL_ERROR
        self.controls.gate = None
        self.controls.refresh()
        where = f" in a {leg.kind} leg" if leg is not None else ""
        why = f"{type(exc).__name__}{where}: {exc}"
        self.log(f"agv: internal error{where}: {''.join(traceback.format_exception(exc)).rstrip()}")
        error = AgvError(
            error_type(INTERNAL_ERROR),
            reason_level(INTERNAL_ERROR),
            f"{INTERNAL_ERROR}: {why}"[:500],
            (("reason", INTERNAL_ERROR),),
            "the truck stopped; check it, then cancel the order (cancelOrder) and send a new one",
        )
        with self.orders.lock:
            self.orders.errors.append(error)

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

    # -- every tick (executor thread) ----------------------------------------------------------------
    def _sample(self) -> Snapshot:
        v = self.vehicle
        pose = v.localization()
        safety = v.safety_state()
        snap = Snapshot(
            pose.x,
            pose.y,
            pose.yaw,
            float(v.speed),
            float(v.steering),
            bool(v.load_detected()),
            self.backend.battery(),
            bool(safety.protective_stop),
            tuple(safety.intrusions),
            tuple(v.faults()),
        )
        self.snapshot = snap
        return snap

    def _on_tick(self) -> None:
        if self.recorder is not None:
            self.recorder.tick()  # what the truck read this tick, before it is sampled anew
        before = self.snapshot
        snap = self._sample()
        self.distance += abs(snap.speed) * self.backend.clock.dt
        changed = (
            before.driving != snap.driving
            or before.loaded != snap.loaded
            or before.protective_stop != snap.protective_stop
            or before.faults != snap.faults
        )
        o = self.orders
        leg = self.leg
        if leg is not None and leg.kind == "move":
            with o.lock:
                i = o.cursor
                if i < len(o.rm) and o.rm[i] in leg.route[1:-1]:
                    n = self.roadmap.node(o.rm[i])
                    pos = o.nodes[i].position or {}
                    tol = float(pos.get("allowedDeviationXY", 0.0)) or DEFAULT_DEVIATION_XY
                    if math.hypot(n.pose.x - snap.x, n.pose.y - snap.y) <= tol:
                        o.arrive(n.id)
        if self.v3 is not None:
            changed = self.v3.tick(self.controls, snap) or changed
        last = (o.last_node_id, o.last_node_seq)
        if last != self._last_node:
            self._last_node, self.distance, changed = last, 0.0, True
        gate = self.controls.gate
        if gate is not None and o.can_enter(gate):
            self.controls.gate = None
            self.controls.refresh()
            changed = True
        if self._in_slot and (snap.speed < -0.02 or leg is None):
            self._in_slot = False  # backing out: the scanners watch behind the truck (any field set)
        if self._pause_action is not None and not snap.driving:
            self._finish(self._pause_action)
            self._pause_action, changed = None, True
        if self._cancel_action is not None and self.controls.stopping and abs(snap.speed) < STOPPED_SPEED:
            self.controls.stopping = False  # standing: the leg ends now (no safety stop at this speed)
            self.controls.cancel("cancelled by the master (cancelOrder)")
        if self._cancel_action is not None and self.runner is None and not snap.driving:
            with o.lock:  # one state: the order deleted and the cancel FINISHED
                o.cancel()
                self._finish(self._cancel_action)
            self._cancel_action, changed = None, True
            self.controls.reset()
        if changed:
            self.changed()

    def _finish(self, action_id: str) -> None:
        with contextlib.suppress(KeyError, IllegalTransitionError):
            self.orders.actions.set(action_id, A.FINISHED)

    def _nearest_node(self) -> str | None:
        s = self.snapshot
        best = min(self.roadmap.nodes(), key=lambda n: math.hypot(n.pose.x - s.x, n.pose.y - s.y), default=None)
        if best is None or math.hypot(best.pose.x - s.x, best.pose.y - s.y) > DEFAULT_DEVIATION_XY:
            return None
        return best.id

    def _axis_heading(self, node: str) -> float:
        """The truck's heading at a node: the node's yaw, or its reverse when the truck faces the other way."""
        yaw = self.roadmap.node(node).pose.yaw
        return yaw if abs(angle_diff(self.snapshot.theta, yaw)) <= math.pi / 2 else yaw + math.pi
