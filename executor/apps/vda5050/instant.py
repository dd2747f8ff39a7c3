"""The AGV's instant actions (VDA 5050 `instantActions`), as `agv.Agv` runs them on the network thread.

- `startPause` / `stopPause`: the runner's controls pause (a driving truck's pause is RUNNING until it
  stands, then FINISHED; `agv.Agv` finishes it);
- `cancelOrder`: RUNNING while the truck brakes to a standstill as in a pause (a cancel at speed would be
  the truck's latched safety stop, and it could never drive again); then the running leg is cancelled, and
  once no leg runs the order is deleted (its actions FAILED, no node or edge states) in the same state
  that reports the cancelOrder FINISHED (a master, e.g. coatyio's vda-5050-lib, reads the order's end
  then as a cancellation);
- `startCharging` / `stopCharging`: only at a charging node (within `CHARGER_RADIUS_M`) and standing,
  else FAILED with `chargingError`;
- `initPosition`: accepted only when it agrees with localization (`INIT_POSITION_XY_M`,
  `INIT_POSITION_YAW`), on this truck's map, while no order runs, and (with `lastNodeId`) at that node;
  it then sets lastNodeId, else FAILED with `initPositionError`;
- `stateRequest`, `factsheetRequest`: FINISHED at once (the factsheet is published).

A refused action is FAILED with a WARNING error naming the action; the truck never moves for one. A 2.0.x
master's list may be named `instantActions`, as the published 2.0.0 JSON schema has it (2.1: `actions`).

Public API: `AgvInstantActions` (a base of `agv.Agv`), `CHARGER_RADIUS_M`, `INIT_POSITION_XY_M`,
`INIT_POSITION_YAW`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from palletpilot.executor.apps.vda5050.actions import IllegalTransitionError
from palletpilot.executor.apps.vda5050.config import AgvConfig
from palletpilot.executor.apps.vda5050.models import Action, ActionStatus, AgvError, ErrorLevel
from palletpilot.executor.apps.vda5050.orders import OrderManager
from palletpilot.executor.apps.vda5050.routes import DEFAULT_DEVIATION_XY
from palletpilot.executor.apps.vda5050.state import Messages, Snapshot
from palletpilot.geometry import angle_diff
from palletpilot.roadmap import NodeType, Roadmap

A = ActionStatus
CHARGER_RADIUS_M = 0.3
"""The truck charges when it stands this close to a charging node."""
INIT_POSITION_XY_M = 0.5
INIT_POSITION_YAW = math.radians(15.0)
"""initPosition is accepted when it agrees with localization within these."""


class AgvInstantActions:
    """The instant-action side of `agv.Agv` (module docstring); the attributes below are the AGV's."""

    orders: OrderManager
    messages: Messages
    roadmap: Roadmap
    config: AgvConfig
    controls: Any  # agv.AgvControls
    snapshot: Snapshot
    charging: bool
    halted: str | None
    heading: float
    software_version: str
    _pause_action: str | None
    _cancel_action: str | None
    log: Callable[[str], None]
    _note: Callable[..., None]
    _send: Callable[[str, Callable[[], dict[str, Any]]], None]
    _axis_heading: Callable[[str], float]

    def _instant(self, doc: dict[str, Any]) -> None:
        if str(doc.get("version", "")).startswith("2.0.") and "actions" not in doc and "instantActions" in doc:
            doc = {**doc, "actions": doc.pop("instantActions")}  # the 2.0.0 JSON schema's name (2.1: `actions`)
        for record in self.orders.receive_instant_actions(doc):
            a = record.action
            try:
                self._run_instant(a)
            except IllegalTransitionError as exc:
                self.log(f"agv: {exc}")

    def _run_instant(self, a: Action) -> None:
        o, t = self.orders, a.action_type
        self.log(f"agv: instant action {t} ({a.action_id})")
        self._note("instant_action", action_type=t, action_id=a.action_id)
        if t == "startPause":
            self.controls.master_pause = True
            self.controls.refresh()
            o.actions.pause()
            if self.snapshot.driving:
                o.actions.set(a.action_id, A.RUNNING)
                self._pause_action = a.action_id
            else:
                o.actions.set(a.action_id, A.FINISHED)
        elif t == "stopPause":
            self.controls.master_pause = False
            self.controls.refresh()
            o.actions.unpause()
            o.actions.set(a.action_id, A.FINISHED)
        elif t == "cancelOrder":
            o.actions.set(a.action_id, A.RUNNING)  # the order goes once the truck stands (`agv.Agv`)
            self.halted = None
            self._cancel_action = a.action_id
            self.controls.stopping = True  # braked to a standstill first, then the leg is cancelled (`agv.Agv`)
            self.controls.refresh()
        elif t in ("startCharging", "stopCharging"):
            self._charging(a, t == "startCharging")
        elif t == "initPosition":
            self._init_position(a)
        elif t == "stateRequest":
            o.actions.set(a.action_id, A.FINISHED)
        elif t == "factsheetRequest":
            self._send("factsheet", lambda: self.messages.factsheet(self.software_version))
            o.actions.set(a.action_id, A.FINISHED)

    def _fail(self, a: Action, error_type_: str, why: str, refs: tuple[tuple[str, str], ...] = ()) -> None:
        error = AgvError(
            error_type_, ErrorLevel.WARNING, why, (("actionId", a.action_id), ("actionType", a.action_type), *refs)
        )
        self.orders.fail_action(a.action_id, error, why)

    def _charging(self, a: Action, start: bool) -> None:
        s = self.snapshot
        if start:
            near = any(
                math.hypot(n.pose.x - s.x, n.pose.y - s.y) <= CHARGER_RADIUS_M
                for n in self.roadmap.nodes()
                if n.type is NodeType.CHARGING
            )
            if not near or s.driving:
                self._fail(a, "chargingError", "startCharging: the truck does not stand at a charging node")
                return
        self.charging = start
        self.orders.actions.set(a.action_id, A.FINISHED)

    def _init_position(self, a: Action) -> None:
        s = self.snapshot
        x, y, theta, map_id = (a.param(k) for k in ("x", "y", "theta", "mapId"))
        node = a.param("lastNodeId")
        if self.orders.executing():
            return self._fail(a, "initPositionError", "initPosition: not while an order runs (cancel it first)")
        if map_id != self.config.map_name:
            return self._fail(
                a,
                "initPositionError",
                f"initPosition: mapId '{map_id}' is not this truck's map '{self.config.map_name}'",
            )
        off = math.hypot(float(x) - s.x, float(y) - s.y)
        if off > INIT_POSITION_XY_M or abs(angle_diff(float(theta), s.theta)) > INIT_POSITION_YAW:
            return self._fail(
                a, "initPositionError", f"initPosition: the pose is {off:.2f} m from where localization puts the truck"
            )
        if node is not None:
            if (
                node not in self.roadmap
                or math.hypot(self.roadmap.node(node).pose.x - s.x, self.roadmap.node(node).pose.y - s.y)
                > DEFAULT_DEVIATION_XY
            ):
                return self._fail(a, "initPositionError", f"initPosition: the truck does not stand at node '{node}'")
            with self.orders.lock:
                self.orders.last_node_id, self.orders.last_node_seq = str(node), 0
                self.orders.last_rm, self.orders.rm = str(node), []
                self.orders.stitch_block = None
            self.heading = self._axis_heading(str(node))
        self.orders.actions.set(a.action_id, A.FINISHED)
        return None
