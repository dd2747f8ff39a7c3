"""VDA 5050 3.0.0 outgoing messages: the 2.1 builders' messages renamed for 3.0 (the `v3` version layer).

`MessagesV3` (a `state.Messages`): `mobileRobotPosition` with `localized`, `powerSupply` with `stateOfCharge`,
`safetyState.activeEmergencyStop` (AUTOACK has no 3.0 value: the protective field's stop is `fieldViolation`
only), `*Descriptor`, `actionResult`, the instant actions' states in `instantActionStates` (kept until
`clearInstantActions`), `zoneSets`, `zoneRequests` (`release`), `plannedPath` (a degree-1 NURBS from the truck
through the rest of the base, `traversedNodes` its nodes) and `intermediatePath` (its points within 3 m, ETAs at
the current speed; both repeated in the visualization), errors with the 3.0 error types (`ERROR_TYPES`, else
camelCase as UPPER_SNAKE; a failed leg, after which the truck stands until a new order, CRITICAL instead of
WARNING), the visualization's `referenceStateHeaderId`, CONNECTION_BROKEN, and the factsheet in 3.0's names
(`factsheet_v3`: `mobileRobotGeometry`, `mobileRobotActions`, `supportedZones`, ...).

Public API: `V3`, `MessagesV3`, `factsheet_v3`, `ERROR_TYPES`, `error_type_v3`.
"""

from __future__ import annotations

import itertools
import math
import re
import threading
import time
from typing import Any

from palletpilot.executor.apps.vda5050.models import ConnectionState
from palletpilot.executor.apps.vda5050.orders import OrderManager
from palletpilot.executor.apps.vda5050.release import ReleaseGate
from palletpilot.executor.apps.vda5050.state import Messages, Snapshot
from palletpilot.executor.apps.vda5050.validation import format_timestamp
from palletpilot.executor.apps.vda5050.zones import SUPPORTED, ZoneStore
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
_ESTOP = {"AUTOACK": "NONE", "MANUAL": "MANUAL", "REMOTE": "REMOTE", "NONE": "NONE"}


def error_type_v3(error_type: str) -> str:
    """A 2.1 errorType in 3.0's spelling: the predefined one, else `palletNotFound` -> `PALLET_NOT_FOUND`."""
    if error_type in ERROR_TYPES:
        return ERROR_TYPES[error_type]
    if error_type.isupper():
        return error_type
    return re.sub(r"(?<!^)(?=[A-Z])", "_", error_type).upper()


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
    """An error in 3.0: its type respelled; a failed leg's WARNING (the truck halted, it takes new orders) is
    CRITICAL, as section 6.6.5.1 defines that level."""
    out = {**e, "errorType": error_type_v3(str(e["errorType"]))}
    halted = any(r.get("referenceKey") == "reason" for r in e.get("errorReferences", []))
    if halted and e["errorLevel"] == "WARNING":
        out["errorLevel"] = "CRITICAL"
    return out


def _position(p: dict[str, Any]) -> dict[str, Any]:
    out = {k: v for k, v in p.items() if k not in ("positionInitialized", "mapDescription")}
    out["localized"] = bool(p["positionInitialized"])
    return out


class MessagesV3(Messages):
    """The AGV's outgoing messages in 3.0 (module docstring): the 2.1 builders' messages, renamed."""

    zones: ZoneStore
    instant_lock: threading.Lock
    instant_ids: dict[str, dict[str, Any]]
    """The instant actions' last states by actionId (3.0 keeps them until clearInstantActions)."""
    own_states: dict[str, dict[str, Any]]
    """The states of the instant actions this layer runs itself."""
    roadmap: Roadmap | None = None
    gate: ReleaseGate
    last_planned: dict[str, Any] | None = None
    """The last state's plannedPath (the visualization repeats it)."""
    last_state_header: int = 0

    def attach(self, zones: ZoneStore, roadmap: Roadmap, gate: ReleaseGate) -> None:
        """Give the builder the zone store, the roadmap (plannedPath) and the RELEASE zones' requests."""
        self.zones, self.roadmap, self.gate = zones, roadmap, gate
        self.instant_ids, self.own_states = {}, {}
        self.instant_lock = threading.Lock()
        """Guards `instant_ids` and `own_states` (the network thread adds, the publisher reads)."""

    def state(self, orders: OrderManager, snap: Snapshot, **kw: Any) -> dict[str, Any]:
        """The 3.0 state (see the module docstring)."""
        s = super().state(orders, snap, **kw)
        self.last_state_header = int(s["headerId"])
        order_states = []
        with self.instant_lock:
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
        self.last_planned = planned
        if planned is not None:
            out["plannedPath"] = planned
            out["intermediatePath"] = intermediate_path(planned, snap)
        out["mobileRobotPosition"] = _position(s["agvPosition"])
        for k in ("velocity", "loads", "driving", "paused", "newBaseRequest"):
            out[k] = s[k]
        out["zoneRequests"] = self.gate.to_json()
        out["distanceSinceLastNode"] = s["distanceSinceLastNode"]
        out["actionStates"] = order_states
        out["instantActionStates"] = instant_states
        out["powerSupply"] = {"stateOfCharge": battery["batteryCharge"], "charging": battery["charging"]}
        out["operatingMode"] = s["operatingMode"]
        out["errors"] = [_error(e) for e in s["errors"]] + [e.to_json() for e in self.gate.errors()]
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
        if self.last_planned is not None:  # the state's plannedPath, the intermediatePath from here
            out["plannedPath"] = self.last_planned
            out["intermediatePath"] = intermediate_path(self.last_planned, snap)
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


INTERMEDIATE_M = 3.0
"""m: how far ahead the intermediatePath reaches."""
ETA_MIN_SPEED = 0.2
"""m/s: the intermediatePath's ETAs assume at least this speed (a standing truck about to start)."""


def intermediate_path(planned: dict[str, Any], snap: Snapshot, now_ms: int | None = None) -> dict[str, Any]:
    """`intermediatePath`: the plannedPath's points within `INTERMEDIATE_M` of the truck (map frame, m), the
    first where it stands, each with an ETA at its current speed (at least `ETA_MIN_SPEED`)."""
    ms = int(time.time() * 1000) if now_ms is None else now_ms
    speed = max(abs(snap.speed), ETA_MIN_SPEED)
    points = [(snap.x, snap.y)] + [(p["x"], p["y"]) for p in planned["trajectory"]["controlPoints"][1:]]
    out, travelled = [], 0.0
    for i, (x, y) in enumerate(points):
        if i:
            travelled += math.dist(points[i - 1], (x, y))
        if travelled > INTERMEDIATE_M:
            break
        out.append({"x": round(x, 4), "y": round(y, 4), "eta": format_timestamp(ms + round(1000 * travelled / speed))})
    return {"polyline": out}


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
