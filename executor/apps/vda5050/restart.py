"""The AGV's crash safety: what it checkpoints to its journal, and how it comes back after a restart.

`AgvJournal` is the part of `agv.Agv` that talks to the journal (`persist`): with a journal attached
(`attach_journal`) every event requests a checkpoint (`checkpoint_doc`), which the journal's own thread
writes; `restore` brings the last checkpoint back before the AGV connects, with the safe rule of the
README ("Under a fleet manager"):

- an order action that was INITIALIZING, RUNNING or PAUSED is FAILED (`ORDER_INTERRUPTED`): its physical
  outcome is unknown; a running `cancelOrder` or `startPause` holds (FINISHED), other instant actions FAILED;
- an order still executing leaves the truck halted until the master sends an order it accepts, or
  cancelOrder (`ORDER_INTERRUPTED` on the order);
- a truck that localization puts away from lastNodeId keeps the node in its state but does not claim to
  stand there: nothing may stitch onto it (`LAST_NODE_MISMATCH`);
- the load sensor wins over the journal (`LOAD_MISMATCH`).

Public API: `AgvJournal`, the errorTypes `ORDER_INTERRUPTED`, `LAST_NODE_MISMATCH`, `LOAD_MISMATCH`.
"""

from __future__ import annotations

import math
import time
from collections.abc import Callable
from typing import Any

from palletpilot.executor.adapters.stores.journal import JournalError
from palletpilot.executor.apps.vda5050.actions import INSTANT, LOAD_HANDLING_DEVICE
from palletpilot.executor.apps.vda5050.models import ActionStatus, AgvError, ErrorLevel, OperatingMode
from palletpilot.executor.apps.vda5050.orders import OrderManager
from palletpilot.executor.apps.vda5050.persist import (
    FORMAT,
    HEADER_BLOCK,
    TOPICS,
    Persister,
    orders_doc,
    restore_orders,
)
from palletpilot.executor.apps.vda5050.routes import DEFAULT_DEVIATION_XY
from palletpilot.executor.apps.vda5050.state import Messages, Snapshot
from palletpilot.roadmap import Roadmap

A = ActionStatus
ORDER_INTERRUPTED = "orderInterrupted"
"""errorType: after a restart, an action whose outcome is unknown (FAILED), or the order that was executing."""
LAST_NODE_MISMATCH = "lastNodeMismatch"
"""errorType: after a restart, localization does not put the truck at lastNodeId."""
LOAD_MISMATCH = "loadMismatch"
"""errorType: after a restart, the load sensor and the journal disagree (the sensor is reported)."""
RESTARTED = "the AGV process restarted"


class AgvJournal:
    """The journal side of `agv.Agv` (module docstring); the attributes below are the AGV's."""

    orders: OrderManager
    messages: Messages
    roadmap: Roadmap
    controls: Any  # agv.AgvControls
    snapshot: Snapshot
    load: dict[str, Any] | None
    charging: bool
    halted: str | None
    persister: Persister | None
    _carried_type: str
    _reserved: dict[str, int]
    log: Callable[[str], None]

    def _sample(self) -> Snapshot:
        raise NotImplementedError  # the AGV's

    def _note(self, event: str, **data: Any) -> None:
        raise NotImplementedError  # the AGV's

    def attach_journal(self, persister: Persister) -> None:
        """Checkpoint to `persister` from now on: on every event, and when a topic has used half of its
        reserved headerIds."""
        self.persister = persister
        self.messages.headers.on_header = self._on_header

    def _on_header(self, topic: str, header_id: int) -> None:
        if self.persister is not None and header_id + HEADER_BLOCK // 2 >= self._reserved.get(topic, 0):
            self.persister.request()

    def checkpoint_doc(self) -> dict[str, Any]:
        """What the AGV needs to come back after a crash (the journal's checkpoint; `persist` module docstring).
        Reserves `HEADER_BLOCK` headerIds per topic ahead of the ones used."""
        o = self.orders
        with o.lock:
            order = orders_doc(o)
        counters = self.messages.headers.counters()
        reserved = {t: counters.get(t, 0) + HEADER_BLOCK for t in sorted({*TOPICS, *counters})}
        self._reserved = reserved
        s = self.snapshot
        return {
            "format": FORMAT,
            "written_unix_s": round(time.time(), 3),
            "orders": order,
            "load": self.load,
            "carried_type": self._carried_type,
            "load_sensor": s.loaded,
            "headers": reserved,
            "version": self.messages.headers.version,
            "operating_mode": OperatingMode.AUTOMATIC.value,
            "paused": self.controls.master_pause,
            "charging": self.charging,
            "halted": self.halted,
            "driving": s.driving,
            "pose": [s.x, s.y, s.theta],
        }

    def restore(self, doc: dict[str, Any], source: str = "the journal") -> None:
        """Come back from a checkpoint (`checkpoint_doc`) before `run`, `connect` and the publisher start,
        with the safe rule of the module docstring. Raises `JournalError` (one line naming `source`) on a
        checkpoint this AGV cannot use."""
        o = self.orders
        try:
            restore_orders(o, doc["orders"], self.roadmap)
            headers = {str(k): int(v) for k, v in dict(doc["headers"]).items()}
            load = doc.get("load")
            if load is not None and not isinstance(load, dict):
                raise TypeError("load is not an object")
        except (KeyError, TypeError, ValueError, AttributeError) as exc:
            why = f"{type(exc).__name__}: {exc}"
            raise JournalError(f"{source}: the last checkpoint cannot be restored: {why}") from None
        self.messages.headers.start_at(headers)
        if doc.get("version") in ("2.0.0", "2.1.0") and self.messages.headers.version.startswith("2."):
            self.messages.headers.version = str(doc["version"])  # the 2.x minor a master spoke (never on 3.0)
        self.load = load
        self._carried_type = str(doc.get("carried_type") or "eur")
        self.controls.master_pause = bool(doc.get("paused"))
        self.controls.refresh()
        snap = self._sample()
        with o.lock:  # the findings of an earlier restart are made anew
            o.errors = [
                e
                for e in o.errors
                if e.error_type not in (LAST_NODE_MISMATCH, LOAD_MISMATCH)
                and not (e.error_type == ORDER_INTERRUPTED and e.ref("actionId") is None)
            ]
            self._fail_interrupted_actions()
            self._halt_an_executing_order()
            self._check_last_node(snap)
        self._check_load(snap)
        failed = [r.action.action_id for r in o.actions if r.result and RESTARTED in r.result]
        self.log(
            f"agv: restored order '{o.order_id}'/{o.order_update_id} at lastNodeId '{o.last_node_id}' from {source}"
            + (f"; interrupted actions FAILED: {', '.join(failed)}" if failed else "")
            + ("; halted until an order update or cancelOrder" if self.halted else "")
            + (f"; not at lastNodeId: {o.stitch_block}" if o.stitch_block else "")
        )
        self._note("restored", order_id=o.order_id, order_update_id=o.order_update_id, last_node_id=o.last_node_id)

    def _fail_interrupted_actions(self) -> None:
        """Actions under way when the process died: their outcome is unknown (under the orders' lock)."""
        o = self.orders
        for record in o.actions:
            a = record.action
            if record.final or record.status is A.WAITING:
                continue
            if record.scope == INSTANT:
                # cancelOrder and startPause hold after the restart (the truck stands); others are lost
                done = a.action_type in ("cancelOrder", "startPause") and record.status is A.RUNNING
                if done and a.action_type == "cancelOrder":
                    o.cancel()  # it had not deleted the order yet (the truck was still stopping)
                record.status, record.resume_to = (A.FINISHED if done else A.FAILED), None
                if not done:
                    record.result = f"interrupted: {RESTARTED}"
                continue
            where = next((n.node_id for n in o.nodes if any(x.action_id == a.action_id for x in n.actions)), None)
            refs = [("actionId", a.action_id), ("actionType", a.action_type)]
            if where is not None:
                refs.append(("node.nodeId", where))
            error = AgvError(
                ORDER_INTERRUPTED,
                ErrorLevel.WARNING,
                f"{a.action_type} '{a.action_id}' was {record.status.value} when {RESTARTED}: its outcome is "
                "unknown (check the truck and its load)",
                tuple(refs),
                "cancel the order (cancelOrder) or send an order update",
            )
            record.resume_to = None
            o.fail_action(a.action_id, error, f"interrupted: {RESTARTED} while it was {record.status.value}")

    def _halt_an_executing_order(self) -> None:
        """An order still executing: the truck stays halted (under the orders' lock)."""
        o = self.orders
        if not o.executing():
            return
        self.halted = ORDER_INTERRUPTED
        o.errors.append(
            AgvError(
                ORDER_INTERRUPTED,
                ErrorLevel.WARNING,
                f"order '{o.order_id}' (orderUpdateId {o.order_update_id}) was interrupted: {RESTARTED} "
                f"after lastNodeId '{o.last_node_id}'; the truck stays halted",
                (("orderId", o.order_id), ("orderUpdateId", str(o.order_update_id))),
                "send an order update (stitching at the decision point) or cancelOrder and a new order",
            )
        )

    def _check_last_node(self, snap: Snapshot) -> None:
        """A truck away from lastNodeId does not claim it: nothing stitches there (under the orders' lock)."""
        o = self.orders
        mismatch = self._away_from_last_node(snap)
        if mismatch is None:
            return
        o.stitch_block = mismatch
        o.errors.append(
            AgvError(
                LAST_NODE_MISMATCH,
                ErrorLevel.WARNING,
                f"after the restart the truck is not at lastNodeId '{o.last_node_id}': {mismatch}; "
                "it does not claim the node",
                (("lastNodeId", o.last_node_id), ("lastNodeSequenceId", str(o.last_node_seq))),
                "cancel the order (cancelOrder), then send a new order from where the truck stands",
            )
        )

    def _check_load(self, snap: Snapshot) -> None:
        """The load sensor wins over the journal."""
        if (self.load is not None) == snap.loaded:
            return
        said = f"a load ({self.load.get('loadId') or self.load.get('loadType')})" if self.load else "no load"
        felt = "one" if snap.loaded else "nothing"
        self.load = None
        with self.orders.lock:
            self.orders.errors.append(
                AgvError(
                    LOAD_MISMATCH,
                    ErrorLevel.WARNING,
                    f"the journal says the forks carried {said}, the load sensor feels {felt} after the restart: "
                    "the loads are reported from the sensor",
                    (("loadPosition", LOAD_HANDLING_DEVICE),),
                    "check the forks",
                )
            )

    def _away_from_last_node(self, snap: Snapshot) -> str | None:
        """Why localization does not put the truck at lastNodeId (its order node's position and deviation
        range, else its roadmap node's within `DEFAULT_DEVIATION_XY`), or None (also without a last node)."""
        o = self.orders
        if not o.last_rm:
            return None
        node = o.nodes[o.cursor - 1] if 0 < o.cursor <= len(o.nodes) else None
        pos = (node.position if node is not None else None) or {}
        if "x" in pos and "y" in pos:
            x, y = float(pos["x"]), float(pos["y"])
        else:
            pose = self.roadmap.node(o.last_rm).pose
            x, y = pose.x, pose.y
        tol = float(pos.get("allowedDeviationXY", 0.0)) or DEFAULT_DEVIATION_XY
        off = math.hypot(snap.x - x, snap.y - y)
        if off <= tol:
            return None
        return f"localization puts it {off:.2f} m from the node (allowed {tol:.2f} m)"
