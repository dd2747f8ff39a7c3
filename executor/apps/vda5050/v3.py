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
  `retriable: false`); `reachOrientationBeforeEntering`, `direction`, a corridor's `releaseRequired` are
  refused (`UNSUPPORTED_PARAMETER`). The zones (`zones.ZoneStore`) refuse an order across a BLOCKED zone and
  put SPEED_LIMIT zones' `maximumSpeed` on the edges they touch.
- `zoneSet` (a new set, DISABLED) and the instant actions `enableZoneSet`, `deleteZoneSet` and
  `clearInstantActions` are handled here; `responses` are schema-checked and logged: this AGV makes no
  requests (no RELEASE or COORDINATED_REPLANNING zones, no corridors with releaseRequired), so no response
  can answer one; a response to an unknown requestId is a WARNING `UNKNOWN_REQUEST`.
- out (`MessagesV3`): the 2.1 messages renamed for 3.0 (`mobileRobotPosition` with `localized`,
  `powerSupply` with `stateOfCharge`, `safetyState.activeEmergencyStop` (AUTOACK has no 3.0 value: the
  protective field's stop is `fieldViolation` only), `*Descriptor`, `actionResult`), instant actions'
  states in `instantActionStates` (kept until `clearInstantActions`), `zoneSets`, `plannedPath` (a degree-1
  NURBS from the truck through the rest of the base, `traversedNodes` its nodes), errors with the 3.0 error
  types (`ERROR_TYPES`, else camelCase as UPPER_SNAKE), the factsheet's 3.0 names (`mobileRobotGeometry`,
  `supportedZones`, ...) and CONNECTION_BROKEN. The topic prefix `vda5050/v3/...` comes from `config`.

A truck that would enter a BLOCKED zone (one enabled after its order was taken) holds before it
(`ZoneGuard`, every control tick): the contour along the order's path ahead, over the braking distance and
a margin, is checked; the hold (the runner paused, service brake) lasts until the zone set or the order
changes, with a CRITICAL `BLOCKED_ZONE_AHEAD` error (`BLOCKED_ZONE_VIOLATION` when already inside).

Public API: `V3`, `order_from_v3`, `instant_from_v3`, `MessagesV3`, `factsheet_v3`, `ERROR_TYPES`,
`error_type_v3`, `V3Inbound`, `ZoneGuard`, `V3Side`.
"""

from __future__ import annotations

import itertools
import math
import re
from collections.abc import Callable
from typing import Any

from palletpilot.executor.apps.vda5050 import validation
from palletpilot.executor.apps.vda5050.config import Loaded
from palletpilot.executor.apps.vda5050.legs import AgvControls
from palletpilot.executor.apps.vda5050.models import AgvError, ConnectionState, ErrorLevel
from palletpilot.executor.apps.vda5050.orders import OrderManager
from palletpilot.executor.apps.vda5050.state import Messages, Snapshot
from palletpilot.executor.apps.vda5050.vehicle import Backend
from palletpilot.executor.apps.vda5050.zones import SUPPORTED, Footprint, ZoneStore, contour_hits, order_path
from palletpilot.roadmap import Roadmap

V3 = "3.0.0"
ERROR_TYPES = {
    "validationError": "VALIDATION_FAILURE",
    "noRouteError": "NO_ROUTE_TO_TARGET",
    "noOrderToCancel": "NO_ORDER_TO_CANCEL",
    "instantActionError": "INVALID_INSTANT_ACTION",
    "orderError": "INVALID_ORDER_ACTION",
}
"""2.1 error types with a predefined 3.0 one (section 6.6.5.4); others go camelCase -> UPPER_SNAKE."""
_EDGE_RENAMES = {
    "maximumSpeed": "maxSpeed",
    "maximumMobileRobotHeight": "maxHeight",
    "minimumLoadHandlingDeviceHeight": "minHeight",
    "edgeDescriptor": "edgeDescription",
}
_REFUSED_EDGE_FIELDS = ("reachOrientationBeforeEntering", "direction")
_ESTOP = {"AUTOACK": "NONE", "MANUAL": "MANUAL", "REMOTE": "REMOTE", "NONE": "NONE"}
OWN_INSTANT = ("enableZoneSet", "deleteZoneSet", "clearInstantActions")
"""Instant actions this layer runs itself (the rest go to the order manager)."""


def error_type_v3(error_type: str) -> str:
    """A 2.1 errorType in 3.0's spelling: the predefined one, else `palletNotFound` -> `PALLET_NOT_FOUND`."""
    if error_type in ERROR_TYPES:
        return ERROR_TYPES[error_type]
    if error_type.isupper():
        return error_type
    return re.sub(r"(?<!^)(?=[A-Z])", "_", error_type).upper()


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
            if key in e:
                unsupported.append(f"order.edges.{key}")
                edge.pop(key)
        corridor = e.get("corridor")
        if isinstance(corridor, dict):
            c = {k: v for k, v in corridor.items() if k not in ("corridorReferencePoint", "releaseLossBehavior")}
            c.pop("releaseRequired", None)
            if corridor.get("releaseRequired"):
                unsupported.append("order.edges.corridor.releaseRequired")
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


def _descriptors(items: list[dict[str, Any]], old: str, new: str) -> list[dict[str, Any]]:
    return [{(new if k == old else k): v for k, v in item.items()} for item in items]


def _action_state(a: dict[str, Any]) -> dict[str, Any]:
    out = {k: v for k, v in a.items() if k not in ("actionDescription", "resultDescription")}
    if "actionDescription" in a:
        out["actionDescriptor"] = a["actionDescription"]
    if "resultDescription" in a:
        out["actionResult"] = a["resultDescription"]
    return out


def _error(e: dict[str, Any]) -> dict[str, Any]:
    return {**e, "errorType": error_type_v3(str(e["errorType"]))}


def _position(p: dict[str, Any]) -> dict[str, Any]:
    out = {k: v for k, v in p.items() if k not in ("positionInitialized", "mapDescription")}
    out["localized"] = bool(p["positionInitialized"])
    return out


class MessagesV3(Messages):
    """The AGV's outgoing messages in 3.0 (module docstring): the 2.1 builders' messages, renamed."""

    zones: ZoneStore
    instant_ids: dict[str, dict[str, Any]]
    """The instant actions' last states by actionId (3.0 keeps them until clearInstantActions)."""
    own_states: dict[str, dict[str, Any]]
    """The states of the instant actions this layer runs itself."""
    roadmap: Roadmap | None = None
    last_state_header: int = 0

    def attach(self, zones: ZoneStore, roadmap: Roadmap) -> None:
        """Give the builder the zone store and the roadmap (plannedPath)."""
        self.zones, self.roadmap = zones, roadmap
        self.instant_ids, self.own_states = {}, {}

    def state(self, orders: OrderManager, snap: Snapshot, **kw: Any) -> dict[str, Any]:
        """The 3.0 state (see the module docstring)."""
        s = super().state(orders, snap, **kw)
        self.last_state_header = int(s["headerId"])
        order_states, instant_states = [], []
        for a in s["actionStates"]:
            if a["actionId"] in self.instant_ids:
                self.instant_ids[a["actionId"]] = _action_state(a)
            else:
                order_states.append(_action_state(a))
        instant_states = [*self.instant_ids.values(), *self.own_states.values()]
        battery = s["batteryState"]
        out: dict[str, Any] = {k: s[k] for k in ("headerId", "timestamp", "version", "manufacturer", "serialNumber")}
        out["maps"] = s["maps"]
        out["zoneSets"] = self.zones.to_json()
        for k in ("orderId", "orderUpdateId", "lastNodeId", "lastNodeSequenceId"):
            out[k] = s[k]
        out["nodeStates"] = _descriptors(s["nodeStates"], "nodeDescription", "nodeDescriptor")
        out["edgeStates"] = _descriptors(s["edgeStates"], "edgeDescription", "edgeDescriptor")
        planned = self.planned_path(orders, snap)
        if planned is not None:
            out["plannedPath"] = planned
        out["mobileRobotPosition"] = _position(s["agvPosition"])
        for k in ("velocity", "loads", "driving", "paused", "newBaseRequest", "distanceSinceLastNode"):
            out[k] = s[k]
        out["actionStates"] = order_states
        out["instantActionStates"] = instant_states
        out["powerSupply"] = {"stateOfCharge": battery["batteryCharge"], "charging": battery["charging"]}
        out["operatingMode"] = s["operatingMode"]
        out["errors"] = [_error(e) for e in s["errors"]]
        out["information"] = _descriptors(s["information"], "infoDescription", "infoDescriptor")
        safety = s["safetyState"]
        out["safetyState"] = {
            "activeEmergencyStop": _ESTOP[safety["eStop"]],
            "fieldViolation": safety["fieldViolation"],
        }
        return out

    def planned_path(self, orders: OrderManager, snap: Snapshot) -> dict[str, Any] | None:
        """`plannedPath`: a degree-1 NURBS (map frame, m) from the truck along the rest of the base (roadmap
        curves every 0.5 m), `traversedNodes` the base's nodes still ahead; None without an order ahead."""
        roadmap = self.roadmap
        if roadmap is None:
            return None
        with orders.lock:
            end = orders.base_end()
            ahead = list(range(orders.cursor, end + 1))
            ids = [orders.nodes[i].node_id for i in ahead]
            rm = [orders.rm[i] if i < len(orders.rm) else None for i in ahead]
            before = orders.rm[orders.cursor - 1] if 0 < orders.cursor <= len(orders.rm) else None
        if not ids:
            return None
        points = [(snap.x, snap.y)]
        prev = before
        for node in rm:
            if node is None or node not in roadmap:
                break
            if prev is not None and prev in roadmap and roadmap.graph.has_edge(prev, node) and prev != before:
                edge = roadmap.edge(prev, node)
                n = max(1, math.ceil(edge.length / 0.5))
                smp = edge.curve.sample([edge.length * j / n for j in range(1, n)])
                points += [(float(x), float(y)) for x, y in zip(smp.x, smp.y, strict=False)]
            p = roadmap.node(node).pose
            points.append((p.x, p.y))
            prev = node
        return _polyline_nurbs(points, ids)

    def visualization(self, snap: Snapshot) -> dict[str, Any]:
        """The 3.0 visualization: position, velocity, and the state it refers to."""
        v = super().visualization(snap)
        out = {k: v[k] for k in ("headerId", "timestamp", "version", "manufacturer", "serialNumber")}
        out["referenceStateHeaderId"] = self.last_state_header
        out["mobileRobotPosition"] = _position(v["agvPosition"])
        out["velocity"] = v["velocity"]
        return out

    def connection(self, state: ConnectionState) -> dict[str, Any]:
        """A 3.0 connection message (CONNECTION_BROKEN for the last will)."""
        msg = super().connection(state)
        if state is ConnectionState.CONNECTIONBROKEN:
            msg["connectionState"] = ConnectionState.CONNECTION_BROKEN.value
        return msg

    def factsheet(self, software_version: str = "") -> dict[str, Any]:
        """The 3.0 factsheet: the 2.1 one with 3.0's names, `supportedZones`, the zone instant actions."""
        return factsheet_v3(super().factsheet(software_version))


def _polyline_nurbs(points: list[tuple[float, float]], ids: list[str]) -> dict[str, Any] | None:
    """A degree-1 NURBS through `points` (clamped, knots by chord length) with `traversedNodes`."""
    pts = [p for i, p in enumerate(points) if i == 0 or math.dist(p, points[i - 1]) > 1e-6]
    if len(pts) < 2:
        return None
    cum = [0.0]
    for a, b in itertools.pairwise(pts):
        cum.append(cum[-1] + math.dist(a, b))
    total = cum[-1]
    knots = [0.0, 0.0, *(c / total for c in cum[1:-1]), 1.0, 1.0]
    control = [{"x": round(x, 4), "y": round(y, 4), "weight": 1.0} for x, y in pts]
    trajectory = {"degree": 1, "knotVector": [round(k, 6) for k in knots], "controlPoints": control}
    return {"trajectory": trajectory, "traversedNodes": ids}


_PHYSICAL = {
    "speedMin": "minimumSpeed",
    "speedMax": "maximumSpeed",
    "accelerationMax": "maximumAcceleration",
    "decelerationMax": "maximumDeceleration",
    "heightMin": "minimumHeight",
    "heightMax": "maximumHeight",
}
_LOAD_SET = {"minLoadhandlingHeight": "minimumLoadhandlingHeight", "maxLoadhandlingHeight": "maximumLoadhandlingHeight"}
_ZONE_ACTIONS = (
    ("enableZoneSet", "enable a zone set received on the zoneSet topic (the others of its map disabled)"),
    ("deleteZoneSet", "delete a zone set"),
    ("clearInstantActions", "remove the finished and failed instant actions from instantActionStates"),
)


def factsheet_v3(f: dict[str, Any]) -> dict[str, Any]:
    """A 2.1 factsheet (`Messages.factsheet`) in 3.0's names."""
    t = dict(f["typeSpecification"])
    kinematic = {"THREEWHEEL": "THREE_WHEEL", "DIFF": "DIFFERENTIAL", "OMNI": "OMNIDIRECTIONAL"}[t.pop("agvKinematic")]
    # the text's name, and the schema's `required` spelling (mobileRobotKinematic): valid for both readings
    t["mobileRobotKinematics"] = t["mobileRobotKinematic"] = kinematic
    t["mobileRobotClass"] = t.pop("agvClass")
    t["maximumLoadMass"] = t.pop("maxLoadMass")
    t["supportedZones"] = [z.value for z in SUPPORTED]
    physical = {_PHYSICAL.get(k, k): v for k, v in f["physicalParameters"].items()}
    limits = f["protocolLimits"]
    timing = dict(limits["timing"])
    timing["minimumOrderInterval"] = timing.pop("minOrderInterval")
    timing["minimumStateInterval"] = timing.pop("minStateInterval")
    actions = []
    for a in f["protocolFeatures"]["agvActions"]:
        action = {k: v for k, v in a.items() if k != "resultDescription"}
        params = [
            {**p, "valueDataType": "NUMBER" if p["valueDataType"] == "FLOAT" else p["valueDataType"]}
            for p in a.get("actionParameters", [])
        ]
        if params:
            action["actionParameters"] = params
        if "resultDescription" in a:
            action["actionResult"] = a["resultDescription"]
        # the 3.0.0 schema has these as strings (its text says boolean): the schema is what masters check
        action["pauseAllowed"] = "false"
        action["cancelAllowed"] = "true" if a["actionType"] in ("pick", "drop") else "false"
        actions.append(action)
    for name, what in _ZONE_ACTIONS:
        params = [] if name == "clearInstantActions" else [{"key": "zoneSetId", "valueDataType": "STRING"}]
        actions.append(
            {
                "actionType": name,
                "actionDescription": what,
                "actionScopes": ["INSTANT"],
                "actionParameters": params,
                "blockingTypes": ["NONE"],
                "pauseAllowed": "false",
                "cancelAllowed": "false",
            }
        )
    envelopes = [
        {"envelope2dId": e["set"], "vertices": e["polygonPoints"], "description": e.get("description", "")}
        for e in f["agvGeometry"]["envelopes2d"]
    ]
    spec = f["loadSpecification"]
    load_sets = [{_LOAD_SET.get(k, k): v for k, v in s.items()} for s in spec["loadSets"]]
    out = {k: f[k] for k in ("headerId", "timestamp", "version", "manufacturer", "serialNumber")}
    out.update(
        typeSpecification=t,
        physicalParameters=physical,
        protocolLimits={"maximumStringLengths": {}, "maximumArrayLengths": {}, "timing": timing},
        protocolFeatures={
            "optionalParameters": f["protocolFeatures"]["optionalParameters"],
            "mobileRobotActions": actions,
        },
        mobileRobotGeometry={"envelopes2d": envelopes},
        loadSpecification={"loadPositions": spec["loadPositions"], "loadSets": load_sets},
        mobileRobotConfiguration=f["vehicleConfig"],
    )
    return out


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
    ) -> None:
        self.orders, self.messages, self.zones = orders, messages, zones
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
            for r in doc["responses"]:  # this AGV makes no requests: nothing a response can answer
                why = f"a response ({r['grantType']}) to request '{r['requestId']}', which this truck never made"
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
            if a["actionType"] not in OWN_INSTANT:
                passed.append(a)
                self.messages.instant_ids.setdefault(
                    str(a["actionId"]), {"actionId": a["actionId"], "actionStatus": "WAITING"}
                )
                continue
            self._own(a)
        return ("instantActions", instant_from_v3(doc, passed)) if passed else None

    def _own(self, a: dict[str, Any]) -> None:
        """enableZoneSet, deleteZoneSet, clearInstantActions: FINISHED, or FAILED with the reason."""
        kind, action_id = str(a["actionType"]), str(a["actionId"])
        params = {str(p["key"]): p["value"] for p in a.get("actionParameters", [])}
        why: str | None = None
        if kind == "clearInstantActions":
            m = self.messages
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
        self.messages.own_states[action_id] = state
        self.log(f"agv: {kind} {params.get('zoneSetId', '')}: {why or 'done'}")


HOLD_MARGIN_M = 0.5
"""m: the truck holds this far (plus its braking distance) before a BLOCKED zone."""


class ZoneGuard:
    """Holds the truck before a BLOCKED zone of the enabled zone set (module docstring); executor thread."""

    def __init__(self, zones: ZoneStore, roadmap: Roadmap, footprint: Footprint, decel: float) -> None:
        self.zones, self.roadmap, self.footprint, self.decel = zones, roadmap, footprint, decel
        self.hold: tuple[int, str, int] | None = None
        """(zone generation, orderId, orderUpdateId) of the hold in force."""
        self.error: AgvError | None = None
        self._path_key: tuple[str, int, int] | None = None
        self._path: list[Any] = []

    def _ahead(self, orders: OrderManager) -> list[Any]:
        """The order's path from the last node passed to the end of the base (cached per progress)."""
        with orders.lock:
            key = (orders.order_id, orders.order_update_id, orders.cursor)
            if key != self._path_key:
                end = orders.base_end()
                ids = orders.rm[max(orders.cursor - 1, 0) : end + 1]
                self._path = order_path(self.roadmap, [{"nodeId": n, "released": True} for n in ids])
                self._path_key = key
        return self._path

    def check(self, orders: OrderManager, snap: Snapshot) -> bool | None:
        """One tick: True to hold the truck, False to release a hold, None when nothing changed."""
        blocked = [z for z in self.zones.active() if z.zone_type.value == "BLOCKED"]
        now = (self.zones.generation, orders.order_id, orders.order_update_id)
        pose = (snap.x, snap.y, snap.theta)
        inside = next((z for z in blocked if contour_hits(self.footprint, pose, z)), None)
        if self.hold is not None:
            if self.hold == now and (orders.nodes or inside is not None):
                return None
            self._clear(orders)
            return False
        if not blocked:
            return None
        zone = inside
        if zone is None and orders.nodes:  # standing too: a leg about to start must not set off into one
            reach = snap.speed**2 / (2.0 * self.decel) + HOLD_MARGIN_M + abs(snap.speed) * 0.2
            zone = self._on_path_ahead(orders, snap, reach, blocked)
        if zone is None:
            return None
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

    def _on_path_ahead(self, orders: OrderManager, snap: Snapshot, reach: float, blocked: list[Any]) -> Any:
        path = self._ahead(orders)
        if not path:
            return None
        near = min(range(len(path)), key=lambda i: (path[i].x - snap.x) ** 2 + (path[i].y - snap.y) ** 2)
        travelled, prev = 0.0, path[near]
        for pose in path[near:]:
            travelled += math.hypot(pose.x - prev.x, pose.y - prev.y)
            prev = pose
            if travelled > reach:
                return None
            for zone in blocked:
                if contour_hits(self.footprint, pose, zone):
                    return zone
        return None

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
        footprint = Footprint(params.body.rear_x, backend.forks.tip_x, params.body.width)
        self.zones = ZoneStore(loaded.config.map_name)
        messages.attach(self.zones, loaded.roadmap)
        self.inbound = V3Inbound(orders, messages, self.zones, loaded.roadmap, footprint, log)
        self.guard = ZoneGuard(self.zones, loaded.roadmap, footprint, params.max_decel)
        self.orders = orders

    def tick(self, controls: AgvControls, snap: Snapshot) -> bool:
        """The zone guard on one control tick (executor thread); True when the hold changed."""
        hold = self.guard.check(self.orders, snap)
        if hold is None:
            return False
        controls.zone_hold = hold
        controls.refresh()
        return True
