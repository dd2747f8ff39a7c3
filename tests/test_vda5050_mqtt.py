"""VDA 5050 over a real MQTT broker: a mosquitto (else amqtt) started on a free loopback port, the AGV in this
process on the simulated warehouse (wall clock), and a small master (paho) that checks every message it receives
against the official schemas. `Broker` (from `palletpilot.executor.apps.vda5050.broker`, re-exported here) and
`Master` are reused by the end-to-end tests."""

from __future__ import annotations

import json
import math
import socket
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path
from typing import Any

import paho.mqtt.client as mqtt
import pytest
from paho.mqtt.enums import CallbackAPIVersion

from palletpilot.executor.apps.vda5050 import validation
from palletpilot.executor.apps.vda5050.broker import Broker, available_kind

ROOT = Path(__file__).resolve().parents[1]
MISSIONS = ROOT / "missions"
PREFIX = "uagv/v2/palletpilot/0001"

needs_broker = pytest.mark.skipif(
    available_kind() is None,
    reason="needs an MQTT broker: mosquitto (/usr/sbin/mosquitto: Debian package mosquitto; `make test` installs it)"
    " or amqtt",
)
needs_mosquitto = pytest.mark.skipif(
    available_kind() != "mosquitto",
    reason="checks the QoS a subscriber gets: amqtt 0.12 delivers QoS 0 messages at the subscription's QoS 1",
)


class Master:
    """A minimal VDA 5050 master: sends orders and instant actions, records and validates what the AGV sends."""

    def __init__(self, port: int, prefix: str = PREFIX, version: str = "2.1.0") -> None:
        self.prefix, self.version = prefix, version
        self.received: list[tuple[str, dict[str, Any], bool, int, float]] = []
        self.invalid: list[str] = []
        self._header = 0
        self._lock = threading.Lock()
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"master-{port}-{time.monotonic_ns()}")
        self.client.on_message = self._on_message
        self.client.on_connect = lambda c, u, f, r, p: c.subscribe(f"{prefix}/#", qos=1)
        self.client.reconnect_delay_set(1, 2)
        self.client.connect("127.0.0.1", port, keepalive=10)
        self.client.loop_start()

    def _on_message(self, client: Any, userdata: Any, message: mqtt.MQTTMessage) -> None:
        name = message.topic.rsplit("/", 1)[-1]
        if name in ("order", "instantActions"):
            return
        doc = json.loads(message.payload)
        problems = validation.problems(name, doc)
        if not validation.STRICT_TIMESTAMP.fullmatch(str(doc.get("timestamp"))):
            problems.append(f"timestamp {doc.get('timestamp')} is not UTC with milliseconds and Z")
        with self._lock:
            self.invalid += [f"{name} #{doc.get('headerId')}: {p}" for p in problems]
            self.received.append((name, doc, bool(message.retain), int(message.qos), time.monotonic()))

    def close(self) -> None:
        self.client.loop_stop()
        self.client.disconnect()

    def messages(self, name: str) -> list[dict[str, Any]]:
        with self._lock:
            return [d for n, d, *_ in self.received if n == name]

    def state(self) -> dict[str, Any] | None:
        states = self.messages("state")
        return states[-1] if states else None

    def wait(
        self, what: str, test: Callable[[dict[str, Any]], bool], timeout: float, name: str = "state"
    ) -> dict[str, Any]:
        """The first message on `name` (latest first) meeting `test` within `timeout` s, else fail with `what`."""
        deadline = time.monotonic() + timeout
        while time.monotonic() < deadline:
            for doc in reversed(self.messages(name)):
                if test(doc):
                    return doc
            time.sleep(0.1)
        last = self.state()
        raise AssertionError(f"timed out waiting for {what}; last state: {json.dumps(last)[:1500]}")

    def _head(self) -> dict[str, Any]:
        self._header += 1
        return {
            "headerId": self._header,
            "timestamp": validation.Stamper()(),
            "version": self.version,
            "manufacturer": "palletpilot",
            "serialNumber": "0001",
        }

    def send_order(self, order_id: str, path: list[str], update: int = 0, seq0: int = 0, **kw: Any) -> dict[str, Any]:
        doc = {**self._head(), **make_order(order_id, path, update, seq0, **kw)}
        self.client.publish(f"{self.prefix}/order", json.dumps(doc), qos=0)
        return doc

    def send_instant(self, *actions: dict[str, Any]) -> None:
        doc = {**self._head(), "actions": list(actions)}
        self.client.publish(f"{self.prefix}/instantActions", json.dumps(doc), qos=0)


def make_order(
    order_id: str,
    path: list[str],
    update: int = 0,
    seq0: int = 0,
    actions: dict[int, list[dict[str, Any]]] | None = None,
    released: int | None = None,
) -> dict[str, Any]:
    base = len(path) if released is None else released
    nodes, edges = [], []
    for i, n in enumerate(path):
        nodes.append(
            {"nodeId": n, "sequenceId": seq0 + 2 * i, "released": i < base, "actions": (actions or {}).get(i, [])}
        )
        if i:
            edges.append(
                {
                    "edgeId": f"{path[i - 1]}-{n}",
                    "sequenceId": seq0 + 2 * i - 1,
                    "released": i < base,
                    "startNodeId": path[i - 1],
                    "endNodeId": n,
                    "actions": [],
                }
            )
    return {"orderId": order_id, "orderUpdateId": update, "nodes": nodes, "edges": edges}


def action(action_type: str, action_id: str, blocking: str = "NONE", **params: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"actionId": action_id, "actionType": action_type, "blockingType": blocking}
    if params:
        out["actionParameters"] = [{"key": k, "value": v} for k, v in params.items()]
    return out


def write_config(folder: Path, port: int, **extra: Any) -> Path:
    """missions/agv.yaml with absolute paths, this broker's port and the given overrides."""
    import yaml

    doc = yaml.safe_load((MISSIONS / "agv.yaml").read_text())
    doc["broker"]["port"] = port
    doc["map"] = str(MISSIONS / "warehouse.yaml")
    doc["vehicle"] = str(MISSIONS / "forklift.yaml")
    doc.update(extra)
    path = folder / "agv.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def status(state: dict[str, Any], action_id: str) -> str | None:
    return next((a["actionStatus"] for a in state["actionStates"] if a["actionId"] == action_id), None)


def check_sequence(messages: list[dict[str, Any]]) -> None:
    """headerIds increase by one and timestamps never go back, message after message."""
    ids = [m["headerId"] for m in messages]
    assert ids == list(range(ids[0], ids[0] + len(ids))), ids
    stamps = [m["timestamp"] for m in messages]
    assert stamps == sorted(stamps) and len(set(stamps)) == len(stamps)


# -- the AGV in this process --------------------------------------------------------------------------


@pytest.fixture(scope="module")
def broker(tmp_path_factory: pytest.TempPathFactory) -> Iterator[Broker]:
    if available_kind() is None:
        pytest.skip("needs an MQTT broker: mosquitto (/usr/sbin/mosquitto: Debian package mosquitto) or amqtt")
    b = Broker(tmp_path_factory.mktemp("broker"))
    b.start()
    yield b
    b.stop()


@pytest.fixture(scope="module")
def agv(broker: Broker, tmp_path_factory: pytest.TempPathFactory) -> Iterator[Any]:
    from palletpilot.executor.apps.vda5050.agv import Agv
    from palletpilot.executor.apps.vda5050.config import load_config
    from palletpilot.executor.apps.vda5050.vehicle import sim_backend

    folder = tmp_path_factory.mktemp("agv")
    loaded = load_config(write_config(folder, broker.port, visualization_hz=5.0, state_interval_s=5.0))
    backend = sim_backend(loaded, MISSIONS / "suite" / "floor_b2.yaml", labels="truth")
    lines: list[str] = []
    the_agv = Agv(loaded, backend, log=lines.append, software_version="test")
    the_agv.lines = lines
    link = the_agv.connect()
    stop = threading.Event()
    threads = [
        threading.Thread(target=the_agv.run, daemon=True),
        threading.Thread(target=the_agv.publisher, args=(stop,), daemon=True),
    ]
    for t in threads:
        t.start()
    link.start()
    assert link.connected.wait(20), lines
    probe = Master(broker.port)  # the retained ONLINE is at the broker before any test's master subscribes
    try:
        probe.wait("ONLINE", lambda d: d["connectionState"] == "ONLINE", 20, name="connection")
    finally:
        probe.close()
    yield the_agv
    stop.set()
    the_agv.stop()
    for t in threads:
        t.join(timeout=10)
    if link.connected.is_set():
        link.close()


@pytest.fixture
def master(broker: Broker) -> Iterator[Master]:
    m = Master(broker.port, version="2.0.0")
    time.sleep(0.3)
    yield m
    m.close()
    assert m.invalid == [], m.invalid[:10]


@needs_broker
def test_online_retained_and_factsheet(agv: Any, master: Master) -> None:
    online = master.wait("connection ONLINE", lambda d: d["connectionState"] == "ONLINE", 5, name="connection")
    retained = [(r, q) for n, d, r, q, _ in master.received if n == "connection" and d is online]
    assert retained == [(True, 1)]  # retained, QoS 1
    facts = master.wait("the factsheet", lambda d: True, 5, name="factsheet")
    assert next(r for n, d, r, *_ in master.received if n == "factsheet") is True
    assert facts["typeSpecification"]["agvClass"] == "FORKLIFT"


@needs_broker
@needs_mosquitto
def test_states_count_up_and_visualization_runs(agv: Any, master: Master) -> None:
    for _ in range(3):
        master.send_instant(action("stateRequest", f"sr{time.monotonic_ns()}"))
        time.sleep(0.4)
    time.sleep(1.5)
    states = master.messages("state")
    assert len(states) >= 3
    check_sequence(states)
    vis = master.messages("visualization")
    assert len(vis) >= 5  # 5 Hz
    check_sequence(vis)
    flags = {(n, r, q) for n, d, r, q, _ in master.received if n in ("state", "visualization")}
    assert flags == {("state", False, 0), ("visualization", False, 0)}  # QoS 0, not retained
    s = states[-1]
    assert s["agvPosition"]["mapId"] == "warehouse" and s["operatingMode"] == "AUTOMATIC"
    assert math.hypot(s["agvPosition"]["x"] - 20.0, s["agvPosition"]["y"] - 5.0) < 0.2  # at b1
    assert s["loads"] == [] and s["safetyState"]["eStop"] == "NONE"


@needs_broker
def test_a_2_0_0_master_order_is_accepted(agv: Any, master: Master) -> None:
    master.send_order("o-v200", ["b1"])
    s = master.wait("the 2.0.0 order", lambda d: d["orderId"] == "o-v200", 10)
    assert s["lastNodeId"] == "b1" and s["nodeStates"] == [] and s["errors"] == []
    assert s["version"] == "2.0.0"  # answered in the master's version (a 2.0 master refuses 2.1.0 headers)
    master.send_order("o-bad", ["nowhere"])
    s = master.wait("noRouteError", lambda d: any(e["errorType"] == "noRouteError" for e in d["errors"]), 10)
    error = next(e for e in s["errors"] if e["errorType"] == "noRouteError")
    keys = {r["referenceKey"]: r["referenceValue"] for r in error["errorReferences"]}
    assert keys["orderId"] == "o-bad" and keys["node.nodeId"] == "nowhere" and keys["topic"] == "order"


@needs_broker
def test_instant_actions(agv: Any, master: Master) -> None:
    master.send_instant(action("dance", "x1"), action("cancelOrder", "c0"))
    s = master.wait("both FAILED", lambda d: status(d, "x1") == "FAILED" and status(d, "c0") == "FAILED", 10)
    types = {e["errorType"] for e in s["errors"]}
    assert {"instantActionError", "noOrderToCancel"} <= types
    master.send_instant(action("startPause", "sp1"))
    master.wait("paused", lambda d: d["paused"] and status(d, "sp1") == "FINISHED", 10)
    master.send_instant(action("stopPause", "sp2"))
    master.wait("resumed", lambda d: not d["paused"] and status(d, "sp2") == "FINISHED", 10)
    before = len(master.messages("factsheet"))
    master.send_instant(action("factsheetRequest", "f1"))
    master.wait("factsheet FINISHED", lambda d: status(d, "f1") == "FINISHED", 10)
    assert len(master.messages("factsheet")) == before + 1


@needs_broker
def test_pause_and_cancel_an_order_while_driving(agv: Any, master: Master) -> None:
    master.send_order("o-drive", ["b1", "b2", "b3", "b_top"], seq0=0)
    master.wait("driving", lambda d: d["orderId"] == "o-drive" and d["driving"], 20)
    master.send_instant(action("startPause", "p1"))
    s = master.wait("paused and standing", lambda d: d["paused"] and status(d, "p1") == "FINISHED", 15)
    assert not s["driving"]
    time.sleep(1.0)
    held = master.state()
    assert held is not None and not held["driving"] and held["paused"]
    master.send_instant(action("stopPause", "p2"))
    master.wait("driving again", lambda d: not d["paused"] and d["driving"], 15)
    master.send_instant(action("cancelOrder", "c1"))
    s = master.wait("cancelled", lambda d: status(d, "c1") == "FINISHED", 20)
    assert not s["driving"] and s["nodeStates"] == [] and s["edgeStates"] == []
    assert s["orderId"] == "o-drive"  # orderId and orderUpdateId are kept
    cancelling = [status(d, "c1") for d in master.messages("state") if status(d, "c1")]
    assert cancelling[0] == "RUNNING"
    master.send_instant(action("cancelOrder", "c2"))
    master.wait("nothing to cancel", lambda d: status(d, "c2") == "FAILED", 10)
    # a new order starts where the truck stopped, from the node it passed last (a wide deviation range)
    last = s["lastNodeId"]
    assert last in ("b1", "b2", "b3")


@needs_broker
def test_last_will_then_reconnect(agv: Any, master: Master) -> None:
    states_before = len(master.messages("state"))
    sock = agv.link.client.socket()
    assert sock is not None
    sock.shutdown(socket.SHUT_RDWR)  # the connection breaks without a DISCONNECT: the broker sends the will
    master.wait("the last will", lambda d: d["connectionState"] == "CONNECTIONBROKEN", 15, name="connection")
    broken = [
        i
        for i, (n, d, *_) in enumerate(master.received)
        if n == "connection" and d["connectionState"] == "CONNECTIONBROKEN"
    ]
    deadline = time.monotonic() + 20
    while time.monotonic() < deadline:
        later = [d for n, d, *_ in master.received[broken[0] :] if n == "connection"]
        if any(d["connectionState"] == "ONLINE" for d in later):
            break
        time.sleep(0.1)
    else:
        raise AssertionError(f"no ONLINE after the last will: {agv.lines[-5:]}")
    time.sleep(0.5)
    assert len(master.messages("state")) > states_before  # the state is published again after reconnecting


@needs_broker
def test_clean_shutdown_is_offline(agv: Any, broker: Broker) -> None:
    agv.stop()
    agv.link.close()
    late = Master(broker.port)  # retained: a master that connects later still learns it
    try:
        s = late.wait("OFFLINE", lambda d: True, 5, name="connection")
        assert s["connectionState"] == "OFFLINE"
        assert late.invalid == []
    finally:
        late.close()
