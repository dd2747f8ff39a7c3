"""A test bridge between the independent 2.0 master (master.js, coatyio vda-5050-lib) and a 3.0.0 AGV.

No public VDA 5050 3.0 master exists (November 2026: coatyio's vda-5050-lib 1.6 speaks 1.1, 2.0 and 2.1; the
`vda5050_core` Python package is robot side and 2.x; VDA5050 issue #618 only discusses such an adapter), so
the 3.0 tests run the 2.0 master's scenarios through this bridge, written from the 3.0.0 text independently of
the AGV's own version layer (which translates the other way round):

- master -> AGV (`order`, `instantActions` on `uagv/v2/...`): checked against the 2.1.0 schemas, translated to
  3.0 (version 3.0.0, edges without startNodeId / endNodeId, `maxSpeed` -> `maximumSpeed`, a deviation
  radius -> an ellipse of two equal half axes, `*Description` -> `*Descriptor`), checked against the 3.0.0
  schemas, published on `vda5050/v3/...`;
- AGV -> master (`state`, `connection`; `factsheet` and `visualization` checked only): checked against the
  3.0.0 schemas, translated back to 2.0 (`agvPosition`, `batteryState`, `eStop`, instant action states
  back in `actionStates`, 3.0-only fields dropped, URGENT -> WARNING, CRITICAL -> FATAL), checked against
  the 2.1.0 schemas (a 2.0 message is valid there), published on `uagv/v2/...`.

Every schema problem is kept in `problems` (`topic: path: what`); `counts` counts the messages per topic.
"""

from __future__ import annotations

import json
import threading
from typing import Any

import paho.mqtt.client as mqtt
from paho.mqtt.enums import CallbackAPIVersion

from palletpilot.executor.apps.vda5050 import validation

V2_PREFIX = "uagv/v2/palletpilot/{serial}"
V3_PREFIX = "vda5050/v3/palletpilot/{serial}"
_DESCRIPTIONS = ("nodeDescription", "edgeDescription", "actionDescription")


def _rename(doc: Any, old: str, new: str) -> Any:
    """Every key `old` in nested dicts and lists as `new`."""
    if isinstance(doc, list):
        return [_rename(x, old, new) for x in doc]
    if isinstance(doc, dict):
        return {(new if k == old else k): _rename(v, old, new) for k, v in doc.items()}
    return doc


def order_to_v3(doc: dict[str, Any]) -> dict[str, Any]:
    """A 2.x order as 3.0 sends it."""
    out = dict(doc, version="3.0.0")
    for name in _DESCRIPTIONS:
        out = _rename(out, name, name.replace("Description", "Descriptor"))
    nodes = []
    for n in out["nodes"]:
        n = dict(n)
        pos = n.get("nodePosition")
        if isinstance(pos, dict):
            pos = {k: v for k, v in pos.items() if k != "mapDescription"}
            if "allowedDeviationXY" in pos:
                r = float(pos["allowedDeviationXY"])
                pos["allowedDeviationXY"] = {"a": r, "b": r, "theta": 0.0}
            n["nodePosition"] = pos
        nodes.append(n)
    edges = []
    for e in out["edges"]:
        e = {k: v for k, v in e.items() if k not in ("startNodeId", "endNodeId", "rotationAllowed")}
        for old, new in (("maxSpeed", "maximumSpeed"), ("maxHeight", "maximumMobileRobotHeight")):
            if old in e:
                e[new] = e.pop(old)
        edges.append(e)
    out.pop("zoneSetId", None)
    return {**out, "nodes": nodes, "edges": edges}


def instant_to_v3(doc: dict[str, Any]) -> dict[str, Any]:
    """A 2.x instantActions message as 3.0 sends it (instant actions are blockingType NONE in 3.0)."""
    actions = [dict(a, blockingType="NONE") for a in _rename(doc["actions"], "actionDescription", "actionDescriptor")]
    return dict(doc, version="3.0.0", actions=actions)


def _action_state_to_v2(a: dict[str, Any]) -> dict[str, Any]:
    out = {k: v for k, v in a.items() if k not in ("actionDescriptor", "actionResult")}
    if "actionResult" in a:
        out["resultDescription"] = a["actionResult"]
    if "actionDescriptor" in a:
        out["actionDescription"] = a["actionDescriptor"]
    return out


def state_to_v2(doc: dict[str, Any]) -> dict[str, Any]:
    """A 3.0 state as a 2.0 master reads it."""
    dropped = ("zoneSets", "plannedPath", "intermediatePath", "zoneRequests", "edgeRequests", "zoneActionStates")
    out = {k: v for k, v in doc.items() if k not in dropped}
    out["version"] = "2.0.0"
    pos = out.pop("mobileRobotPosition", None)
    if pos is not None:
        out["agvPosition"] = {
            **{k: v for k, v in pos.items() if k != "localized"},
            "positionInitialized": pos["localized"],
        }
    power = out.pop("powerSupply")
    out["batteryState"] = {"batteryCharge": power["stateOfCharge"], "charging": power["charging"]}
    safety = out["safetyState"]
    out["safetyState"] = {"eStop": safety["activeEmergencyStop"], "fieldViolation": safety["fieldViolation"]}
    states = [*out["actionStates"], *out.pop("instantActionStates")]
    out["actionStates"] = [_action_state_to_v2(a) for a in states]
    levels = {"URGENT": "WARNING", "CRITICAL": "FATAL"}
    out["errors"] = [dict(e, errorLevel=levels.get(e["errorLevel"], e["errorLevel"])) for e in out["errors"]]
    for old, new in (("nodeDescriptor", "nodeDescription"), ("edgeDescriptor", "edgeDescription")):
        out = _rename(out, old, new)
    out["information"] = _rename(out.get("information", []), "infoDescriptor", "infoDescription")
    return out


class Bridge:
    """The bridge on one broker for one AGV (see the module docstring); `close()` ends it."""

    def __init__(self, port: int, serial: str = "0001") -> None:
        self.v2, self.v3 = V2_PREFIX.format(serial=serial), V3_PREFIX.format(serial=serial)
        self.problems: list[str] = []
        self.counts: dict[str, int] = {}
        self._lock = threading.Lock()
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"bridge-v3-{serial}")
        self.client.on_connect = self._on_connect
        self.client.on_message = self._on_message
        self._ready = threading.Event()
        self.client.connect("127.0.0.1", port)
        self.client.loop_start()
        assert self._ready.wait(10), "the bridge did not connect"

    def _on_connect(self, client: mqtt.Client, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
        topics = [f"{self.v2}/order", f"{self.v2}/instantActions"]
        topics += [f"{self.v3}/{t}" for t in ("state", "connection", "factsheet", "visualization")]
        client.subscribe([(t, 0) for t in topics])
        self._ready.set()

    def _check(self, where: str, topic: str, doc: Any, version: str) -> None:
        found = validation.problems(topic, doc, version)
        with self._lock:
            self.counts[f"{where} {topic}"] = self.counts.get(f"{where} {topic}", 0) + 1
            self.problems += [f"{where} {topic}: {p}" for p in found]

    def _on_message(self, client: mqtt.Client, userdata: Any, message: mqtt.MQTTMessage) -> None:
        topic = message.topic.rsplit("/", 1)[-1]
        doc = json.loads(bytes(message.payload))
        if message.topic.startswith(self.v2):  # from the master
            if topic == "instantActions" and "instantActions" in doc and "actions" not in doc:
                doc["actions"] = doc.pop("instantActions")  # the 2.0.0 JSON schema's name (2.1, 3.0: `actions`)
            self._check("master 2.0", topic, doc, "2.1.0")
            out = order_to_v3(doc) if topic == "order" else instant_to_v3(doc)
            self._check("to AGV 3.0", topic, out, "3.0.0")
            client.publish(f"{self.v3}/{topic}", json.dumps(out), qos=0)
            return
        self._check("AGV 3.0", topic, doc, "3.0.0")
        if topic == "state":
            out = state_to_v2(doc)
        elif topic == "connection":
            state = {"CONNECTION_BROKEN": "CONNECTIONBROKEN"}.get(doc["connectionState"], doc["connectionState"])
            out = dict(doc, version="2.0.0", connectionState=state)
        else:
            return
        self._check("to master 2.0", topic, out, "2.1.0")
        client.publish(
            f"{self.v2}/{topic}", json.dumps(out), qos=1 if topic == "connection" else 0, retain=message.retain
        )

    def close(self) -> None:
        """Disconnect."""
        self.client.disconnect()
        self.client.loop_stop()
