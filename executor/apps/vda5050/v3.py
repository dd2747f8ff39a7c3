"""VDA 5050 3.0.0 as a thin version layer over the one AGV (`protocol_version: 3.0.0` in agv.yaml).

The AGV's own code path is 2.1 throughout (its order manager, actions, state builder). A 3.0 AGV only differs
at its edges, here:

- in: every message is checked against the 3.0.0 schemas (`validation`, set `3.0.0`) and a major version 3,
  then `order_from_v3` / `instant_from_v3` give the 2.1 form the order manager reads. Renamed fields:
  `maximumSpeed` -> `maxSpeed`, `maximumMobileRobotHeight` -> `maxHeight`, `minimumLoadHandlingDeviceHeight`
  -> `minHeight`, `*Descriptor` -> `*Description`, `corridorReferencePoint` (KINEMATIC_CENTER) ->
  `corridorRefPoint` (KINEMATICCENTER); an edge's `startNodeId` / `endNodeId` (gone in 3.0) are its
  neighbours by sequenceId; `allowedDeviationXY`, an ellipse in 3.0 (section 6.6.2.1), becomes the circle
  inside it (its smaller half axis); blockingType SINGLE (drive, but no other action) is run as HARD (no
  driving either: stricter, never looser); `retriable` is not supported (a failed action is FAILED at once, as
  `retriable: false`); `direction` and `reachOrientationBeforeEntering: true` (the truck cannot turn on the
  spot) are refused (`UNSUPPORTED_PARAMETER`); a corridor's `releaseRequired` is accepted: the truck never
  leaves the edge's curve (`routes`), so it never needs the release it would have to request (6.6.10). The
  zones (`zones.ZoneStore`) refuse an order across a BLOCKED zone and put SPEED_LIMIT zones' `maximumSpeed`
  on the edges they touch.
- `zoneSet` (a new set, DISABLED) and the instant actions `enableZoneSet`, `deleteZoneSet` and
  `clearInstantActions` are handled here; `responses` answer the RELEASE zones' access requests
  (`release.ReleaseGate`, the only requests this AGV makes: it never deviates into a corridor, has no
  COORDINATED_REPLANNING zones); a response to a requestId it has not made is a WARNING `UNKNOWN_REQUEST`.
- out: `v3_out.MessagesV3`, the 2.1 messages renamed for 3.0 (see there). The topic prefix
  `vda5050/v3/...` comes from `config`.

A truck that would enter a BLOCKED zone (one enabled after its order was taken) holds before it
(`ZoneGuard`, every control tick): the contour along the order's path ahead, over the braking distance and
a margin, is checked; the hold (the runner paused, service brake) lasts until the zone set or the order
changes, with a CRITICAL `BLOCKED_ZONE_AHEAD` error (`BLOCKED_ZONE_VIOLATION` when already inside).

Public API: `V3`, `MessagesV3` (from `v3_out`), `order_from_v3`, `instant_from_v3`, `V3Inbound`,
`ZoneGuard`, `V3Side`.
"""

from __future__ import annotations

import itertools
import math
import time
from collections.abc import Callable
from typing import Any

from palletpilot.executor.apps.vda5050 import validation
from palletpilot.executor.apps.vda5050.config import Loaded
from palletpilot.executor.apps.vda5050.legs import AgvControls
from palletpilot.executor.apps.vda5050.models import AgvError, ErrorLevel
from palletpilot.executor.apps.vda5050.orders import OrderManager
from palletpilot.executor.apps.vda5050.release import ReleaseGate
from palletpilot.executor.apps.vda5050.state import Messages, Snapshot
from palletpilot.executor.apps.vda5050.v3_out import V3, MessagesV3
from palletpilot.executor.apps.vda5050.vehicle import Backend
from palletpilot.executor.apps.vda5050.zones import Footprint, Zone, ZoneStore, ZoneType, contour_hits, order_path
from palletpilot.roadmap import Roadmap

_EDGE_RENAMES = {
    "maximumSpeed": "maxSpeed",
    "maximumMobileRobotHeight": "maxHeight",
    "minimumLoadHandlingDeviceHeight": "minHeight",
    "edgeDescriptor": "edgeDescription",
}
_REFUSED_EDGE_FIELDS = ("reachOrientationBeforeEntering", "direction")
"""Refused when given (reachOrientationBeforeEntering: when true)."""
OWN_INSTANT = ("enableZoneSet", "deleteZoneSet", "clearInstantActions")
"""Instant actions this layer runs itself (the rest go to the order manager)."""


def _action_from_v3(a: dict[str, Any]) -> dict[str, Any]:
    out = {k: v for k, v in a.items() if k not in ("actionDescriptor", "retriable")}
    if "actionDescriptor" in a:
        out["actionDescription"] = a["actionDescriptor"]
    if out.get("blockingType") == "SINGLE":
        out["blockingType"] = "HARD"
    return out


def order_from_v3(doc: dict[str, Any]) -> tuple[dict[str, Any], list[str]]:
    """A schema-valid 3.0 order in the 2.1 form (module docstring), and the unsupported fields it uses."""
    unsupported: list[str] = []
    nodes = []
    for n in doc["nodes"]:
        node = {k: v for k, v in n.items() if k != "nodeDescriptor"}
        if "nodeDescriptor" in n:
            node["nodeDescription"] = n["nodeDescriptor"]
        pos = n.get("nodePosition")
        if isinstance(pos, dict) and isinstance(pos.get("allowedDeviationXY"), dict):
            ellipse = pos["allowedDeviationXY"]
            node["nodePosition"] = {**pos, "allowedDeviationXY": float(min(ellipse["a"], ellipse["b"]))}
        node["actions"] = [_action_from_v3(a) for a in n["actions"]]
        nodes.append(node)
    by_seq = {int(n["sequenceId"]): str(n["nodeId"]) for n in doc["nodes"]}
    edges = []
    for e in doc["edges"]:
        edge = {_EDGE_RENAMES.get(k, k): v for k, v in e.items()}
        seq = int(e["sequenceId"])
        edge["startNodeId"] = by_seq.get(seq - 1, "")
        edge["endNodeId"] = by_seq.get(seq + 1, "")
        for key in _REFUSED_EDGE_FIELDS:
            if key in e and (key != "reachOrientationBeforeEntering" or e[key] is True):
                unsupported.append(f"order.edges.{key}")
            edge.pop(key, None)
        corridor = e.get("corridor")
        if isinstance(corridor, dict):  # never used for a deviation: no release to request, none to lose
            dropped = ("corridorReferencePoint", "releaseLossBehavior", "releaseRequired")
            c = {k: v for k, v in corridor.items() if k not in dropped}
            if "corridorReferencePoint" in corridor:
                c["corridorRefPoint"] = str(corridor["corridorReferencePoint"]).replace("_", "")
            edge["corridor"] = c
        edge["actions"] = [_action_from_v3(a) for a in e["actions"]]
        edges.append(edge)
    head = {k: doc[k] for k in ("headerId", "timestamp", "manufacturer", "serialNumber", "orderId", "orderUpdateId")}
    return {**head, "version": validation.V2, "nodes": nodes, "edges": edges}, sorted(set(unsupported))


def instant_from_v3(doc: dict[str, Any], actions: list[dict[str, Any]]) -> dict[str, Any]:
    """A 3.0 instantActions message's `actions` (those for the order manager) in the 2.1 form."""
    head = {k: doc[k] for k in ("headerId", "timestamp", "manufacturer", "serialNumber")}
    return {**head, "version": validation.V2, "actions": [_action_from_v3(a) for a in actions]}


class V3Inbound:
    """The 3.0 AGV's incoming side (module docstring): `handle(name, doc)` returns the topic and 2.1 message
    for the AGV's own code, or None when handled (or refused) here. Errors go to the order manager's list."""

    def __init__(
        self,
        orders: OrderManager,
        messages: MessagesV3,
        zones: ZoneStore,
        roadmap: Roadmap,
        footprint: Footprint,
        log: Callable[[str], None],
        gate: ReleaseGate,
    ) -> None:
        self.orders, self.messages, self.zones, self.gate = orders, messages, zones, gate
        self.roadmap, self.footprint, self.log = roadmap, footprint, log

    def _warn(self, error: AgvError) -> None:
        with self.orders.lock:
            self.orders.errors.append(error)

    def handle(self, name: str, doc: dict[str, Any]) -> tuple[str, dict[str, Any]] | None:
        """Check a 3.0 message and route it (see the class docstring)."""
        refs = [("headerId", str(doc.get("headerId", ""))), ("topic", name)]
        if name not in validation.TOPICS_V3:
            return None
        problems = validation.problems(name, doc, V3)
        if not problems and str(doc["version"]).split(".")[0] != "3":
            problems = [f"version: protocol version {doc['version']} is not 3.x (this truck speaks {V3})"]
        if problems:
            what = f"the {name} message is not valid: " + "; ".join(problems[:10])
            self._warn(AgvError("VALIDATION_FAILURE", ErrorLevel.WARNING, what, tuple(refs)))
            return None
        if name == "order":
            return self._order(doc, refs)
        if name == "instantActions":
            return self._instant(doc)
        if name == "zoneSet":
            error = self.zones.add(doc)
            if error is not None:
                self._warn(error)
            else:
                self.log(f"agv: zone set '{doc['zoneSet']['zoneSetId']}' received (DISABLED until enableZoneSet)")
        elif name == "responses":
            for r in doc["responses"]:  # the RELEASE zones' access requests (`release`)
                if self.gate.respond(r):
                    self.log(f"agv: zone request '{r['requestId']}': {r['grantType']}")
                    continue
                why = f"a response ({r['grantType']}) to request '{r['requestId']}', which this truck has not made"
                self._warn(AgvError("UNKNOWN_REQUEST", ErrorLevel.WARNING, why, (*refs, ("requestId", r["requestId"]))))
        return None

    def _order(self, doc: dict[str, Any], refs: list[tuple[str, str]]) -> tuple[str, dict[str, Any]] | None:
        order, unsupported = order_from_v3(doc)
        refs = [*refs, ("orderId", str(doc["orderId"])), ("orderUpdateId", str(doc["orderUpdateId"]))]
        if unsupported:
            what = f"the order uses {', '.join(unsupported)}, which this truck does not support"
            self._warn(
                AgvError(
                    "UNSUPPORTED_PARAMETER", ErrorLevel.WARNING, what, (*refs, *(("field", u) for u in unsupported))
                )
            )
            return None
        if not self.zones.active():
            return "order", order
        path = order_path(self.roadmap, order["nodes"])
        crossing = self.zones.blocked_crossing(self.footprint, path)
        if crossing is not None:
            zone, pose = crossing
            e = order["edges"][pose.edge]
            what = (
                f"the order's edge '{e['edgeId']}' ({e['startNodeId']} -> {e['endNodeId']}) takes the truck into "
                f"BLOCKED zone '{zone.zone_id}' of zone set '{self.zones.active_set_id()}' at "
                f"({pose.x:.2f}, {pose.y:.2f}) m"
            )
            zone_refs = (("zoneId", zone.zone_id), ("zoneSetId", self.zones.active_set_id()), ("edgeId", e["edgeId"]))
            self._warn(AgvError("NO_ROUTE_TO_TARGET", ErrorLevel.WARNING, what, (*refs, *zone_refs)))
            return None
        for index, limit in self.zones.edge_speed_limits(
            self.footprint, order_path(self.roadmap, order["nodes"], False)
        ).items():
            edge = order["edges"][index]
            edge["maxSpeed"] = min(float(edge.get("maxSpeed", math.inf)), limit)
        return "order", order

    def _instant(self, doc: dict[str, Any]) -> tuple[str, dict[str, Any]] | None:
        passed = []
        for a in doc["actions"]:
            if a["actionType"] in OWN_INSTANT:
                self._own(a)
                continue
            passed.append(a)
            action_id = str(a["actionId"])
            with self.orders.lock:
                taken = action_id in self.orders.actions  # an id in use: the order manager refuses it
            if not taken:
                with self.messages.instant_lock:
                    self.messages.instant_ids.setdefault(action_id, {"actionId": action_id, "actionStatus": "WAITING"})
        return ("instantActions", instant_from_v3(doc, passed)) if passed else None

    def _own(self, a: dict[str, Any]) -> None:
        """enableZoneSet, deleteZoneSet, clearInstantActions: FINISHED, or FAILED with the reason."""
        kind, action_id = str(a["actionType"]), str(a["actionId"])
        params = {str(p["key"]): p["value"] for p in a.get("actionParameters", [])}
        why: str | None = None
        m = self.messages
        if kind == "clearInstantActions":
            with m.instant_lock:
                for store in (m.instant_ids, m.own_states):
                    for key in [k for k, v in store.items() if v.get("actionStatus") in ("FINISHED", "FAILED")]:
                        del store[key]
        elif not isinstance(params.get("zoneSetId"), str):
            why = f"{kind} needs the parameter zoneSetId (a string)"
        elif kind == "enableZoneSet":
            why = self.zones.enable(params["zoneSetId"])
        else:
            why = self.zones.delete(params["zoneSetId"])
        state = {"actionId": action_id, "actionType": kind, "actionStatus": "FAILED" if why else "FINISHED"}
        if why:
            state["actionResult"] = why
            refs = (("actionId", action_id), ("actionType", kind))
            self._warn(AgvError("INVALID_INSTANT_ACTION", ErrorLevel.WARNING, why, refs))
        with m.instant_lock:
            m.own_states[action_id] = state
        self.log(f"agv: {kind} {params.get('zoneSetId', '')}: {why or 'done'}")


CONTOUR_MARGIN_M = 0.1
"""m: the truck's contour for zones is its body and forks grown by this on every side (a pallet's overhang
beyond the fork tips, localization error)."""
HOLD_MARGIN_M = 0.5
"""m: the truck holds this far (plus its braking distance) before a BLOCKED zone."""


class ZoneGuard:
    """Holds the truck before a BLOCKED zone, and before a RELEASE zone until it is granted (module docstring,
    `release`); executor thread. The zones met along the order's path are worked out once per path and zone
    set (`_hits`); each tick only finds the truck on that path."""

    def __init__(
        self, zones: ZoneStore, roadmap: Roadmap, footprint: Footprint, decel: float, gate: ReleaseGate
    ) -> None:
        self.zones, self.roadmap, self.footprint, self.decel, self.gate = zones, roadmap, footprint, decel, gate
        self.hold: tuple[int, str, int] | None = None
        """(zone generation, orderId, orderUpdateId) of the BLOCKED hold in force."""
        self.error: AgvError | None = None
        self._key: tuple[str, int, int, int] | None = None
        self._path: list[Any] = []
        self._cum: list[float] = []
        self._hits: list[tuple[int, Zone]] = []

    def _ahead(self, orders: OrderManager) -> None:
        """The order's path from the last node passed to the end of the base, its length along the way and
        the zones its contour meets (pose index, zone), worked out again when the progress or zones change."""
        with orders.lock:
            key = (orders.order_id, orders.order_update_id, orders.cursor, self.zones.generation)
            if key == self._key:
                return
            end = orders.base_end()
            ids = orders.rm[max(orders.cursor - 1, 0) : end + 1]
        self._key = key
        self._path = order_path(self.roadmap, [{"nodeId": n, "released": True} for n in ids])
        self._cum = [0.0]
        for a, b in itertools.pairwise(self._path):
            self._cum.append(self._cum[-1] + math.hypot(b.x - a.x, b.y - a.y))
        zones = [z for z in self.zones.active() if z.zone_type in (ZoneType.BLOCKED, ZoneType.RELEASE)]
        self._hits = [
            (i, z) for i, pose in enumerate(self._path) for z in zones if contour_hits(self.footprint, pose, z)
        ]

    def _met_ahead(self, orders: OrderManager, snap: Snapshot) -> dict[str, tuple[Zone, float]]:
        """The BLOCKED and RELEASE zones on the path ahead of the truck: by zoneId, the zone and how far (m)."""
        self._ahead(orders)
        path = self._path
        if not path or not self._hits:
            return {}
        near = min(range(len(path)), key=lambda i: (path[i].x - snap.x) ** 2 + (path[i].y - snap.y) ** 2)
        out: dict[str, tuple[Zone, float]] = {}
        for i, zone in self._hits:
            if i >= near and zone.zone_id not in out:
                out[zone.zone_id] = (zone, self._cum[i] - self._cum[near])
        return out

    def check(self, orders: OrderManager, snap: Snapshot) -> bool:
        """One tick: True while the truck must hold (before a BLOCKED zone, or a RELEASE zone not granted)."""
        active = self.zones.active()
        pose = (snap.x, snap.y, snap.theta)
        inside = [z for z in active if z.zone_type in (ZoneType.BLOCKED, ZoneType.RELEASE)]
        inside = [z for z in inside if contour_hits(self.footprint, pose, z)]
        guarded = any(z.zone_type in (ZoneType.BLOCKED, ZoneType.RELEASE) for z in active)
        ahead = self._met_ahead(orders, snap) if orders.nodes and guarded else {}
        reach = snap.speed**2 / (2.0 * self.decel) + HOLD_MARGIN_M + abs(snap.speed) * 0.2
        release_ahead = {k: v for k, v in ahead.items() if v[0].zone_type is ZoneType.RELEASE}
        release_inside = [z for z in inside if z.zone_type is ZoneType.RELEASE]
        order_key = (orders.order_id, orders.order_update_id)
        wait = self.gate.tick(order_key, release_ahead, release_inside, reach, self.zones.active_set_id(), time.time())
        blocked_inside = next((z for z in inside if z.zone_type is ZoneType.BLOCKED), None)
        near = [z for z, d in ahead.values() if z.zone_type is ZoneType.BLOCKED and d <= reach]
        return self._blocked(orders, blocked_inside, near[0] if near else None) or wait

    def _blocked(self, orders: OrderManager, inside: Zone | None, ahead: Zone | None) -> bool:
        """The BLOCKED hold: set with its error when the truck is in a BLOCKED zone or would reach one; kept
        until the zone set or the order changes."""
        now = (self.zones.generation, orders.order_id, orders.order_update_id)
        if self.hold is not None:
            if self.hold == now and (orders.nodes or inside is not None):
                return True
            self._clear(orders)
        zone = inside or ahead
        if zone is None:
            return False
        kind = "BLOCKED_ZONE_VIOLATION" if inside is not None else "BLOCKED_ZONE_AHEAD"
        what = (
            f"the truck is inside BLOCKED zone '{zone.zone_id}': it stopped"
            if inside is not None
            else f"the order's path enters BLOCKED zone '{zone.zone_id}' ahead: the truck holds before it"
        )
        refs = (("zoneId", zone.zone_id), ("zoneSetId", self.zones.active_set_id()))
        hint = "cancel the order (cancelOrder) or enable a zone set that allows the path"
        self.error = AgvError(kind, ErrorLevel.CRITICAL, what, refs, hint)
        with orders.lock:
            orders.errors.append(self.error)
        self.hold = now
        return True

    def _clear(self, orders: OrderManager) -> None:
        if self.error is not None:
            with orders.lock:
                if self.error in orders.errors:
                    orders.errors.remove(self.error)
        self.hold, self.error = None, None


class V3Side:
    """What a 3.0 AGV adds to the one AGV: the zone store, the inbound side and the zone guard."""

    def __init__(
        self, orders: OrderManager, messages: Messages, loaded: Loaded, backend: Backend, log: Callable[[str], None]
    ) -> None:
        assert isinstance(messages, MessagesV3)
        params = loaded.vehicle
        m = CONTOUR_MARGIN_M
        footprint = Footprint(params.body.rear_x - m, backend.forks.tip_x + m, params.body.width + 2 * m)
        self.zones = ZoneStore(loaded.config.map_name)
        self.gate = ReleaseGate()
        messages.attach(self.zones, loaded.roadmap, self.gate)
        self.inbound = V3Inbound(orders, messages, self.zones, loaded.roadmap, footprint, log, self.gate)
        self.guard = ZoneGuard(self.zones, loaded.roadmap, footprint, params.max_decel, self.gate)
        self.orders = orders
        self._requests: list[dict[str, Any]] = []

    def leg_speed_limits(self, route: tuple[str, ...]) -> dict[int, float]:
        """The SPEED_LIMIT zones' `maximumSpeed` (m/s) by edge of a leg's route, as the leg starts (a zone set
        enabled after the order was taken, too)."""
        path = order_path(self.inbound.roadmap, [{"nodeId": n, "released": True} for n in route])
        return self.zones.edge_speed_limits(self.inbound.footprint, path)

    def tick(self, controls: AgvControls, snap: Snapshot) -> bool:
        """The zone guard on one control tick (executor thread); True when the hold or the zone requests
        changed (a state is due)."""
        hold = self.guard.check(self.orders, snap)
        requests = self.gate.to_json()
        changed = hold != controls.zone_hold or requests != self._requests
        self._requests = requests
        if hold != controls.zone_hold:
            controls.zone_hold = hold
            controls.refresh()
        return changed
