"""The AGV: VDA 5050 orders executed by the runner's task machines, state published over MQTT.

Threads: paho's network thread hands in messages (`on_message`: orders go through the `OrderManager`,
instant actions set flags); the executor thread (`run`) drives the truck; a publisher thread sends the
state on every event and at least every `state_interval_s`, and the visualization at its rate. Only the
executor thread touches the vehicle: it samples it after every clock tick (`TickClock` hook) into a
`Snapshot` that the other threads read.

Execution: one `Runner` per leg (`OrderManager.plan_next`), each with a one-task `Mission` (`move` along
exactly the order's edges, `pick` with the adaptive Pickup, `drop` with the checked Delivery, or the node
`actions`), run by `leg_run.AgvLegs` (a base of `Agv`; there: what each kind of leg does and when its
action is WAITING, RUNNING, FINISHED or FAILED). On every tick the AGV counts the nodes a move leg passes
within their deviation range as traversed, and opens the gate a leg waits at once the order releases it.

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
from palletpilot.executor.apps.vda5050 import validation
from palletpilot.executor.apps.vda5050.actions import IllegalTransitionError
from palletpilot.executor.apps.vda5050.config import Loaded
from palletpilot.executor.apps.vda5050.instant import AgvInstantActions
from palletpilot.executor.apps.vda5050.leg_run import AgvLegs
from palletpilot.executor.apps.vda5050.legs import AgvControls, OrderPlanner, SlotFields
from palletpilot.executor.apps.vda5050.midedge import locate
from palletpilot.executor.apps.vda5050.models import ActionStatus, AgvError
from palletpilot.executor.apps.vda5050.mqtt import AgvLink
from palletpilot.executor.apps.vda5050.orders import Leg, OrderManager, VehicleView
from palletpilot.executor.apps.vda5050.persist import Persister
from palletpilot.executor.apps.vda5050.restart import AgvJournal
from palletpilot.executor.apps.vda5050.routes import DEFAULT_DEVIATION_XY
from palletpilot.executor.apps.vda5050.state import Messages, Snapshot, error_type, reason_level
from palletpilot.executor.apps.vda5050.v3 import V3, MessagesV3, V3Side
from palletpilot.executor.apps.vda5050.validation import Headers
from palletpilot.executor.apps.vda5050.vehicle import Backend
from palletpilot.executor.core.behaviour import Settings
from palletpilot.executor.core.errors import INTERNAL_ERROR
from palletpilot.executor.core.results import TaskResult
from palletpilot.executor.core.runner import Runner
from palletpilot.executor.ports import VehiclePort
from palletpilot.geometry import angle_diff

if TYPE_CHECKING:
    from palletpilot.executor.adapters.mcap.recording import Recorder

__all__ = ["STOPPED_SPEED", "Agv", "AgvControls", "OrderPlanner"]

A = ActionStatus
STOPPED_SPEED = 0.01
"""m/s: a cancelOrder cancels the running leg once the truck is this slow (the runner's service stop)."""


class Agv(AgvInstantActions, AgvJournal, AgvLegs):
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
