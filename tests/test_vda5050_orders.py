"""VDA 5050 protocol layer without a vehicle or a broker: schemas, headers, the order acceptance flow,
instant actions, the action state machine, the config file and the outgoing messages."""

from __future__ import annotations

import json
import math
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest

from palletpilot.control.vehicle import load_vehicle
from palletpilot.executor.apps.vda5050 import validation
from palletpilot.executor.apps.vda5050.actions import ActionTable, IllegalTransitionError
from palletpilot.executor.apps.vda5050.config import AgvConfigError, load_config
from palletpilot.executor.apps.vda5050.models import (
    Action,
    ActionStatus,
    AgvError,
    BlockingType,
    ConnectionState,
    ErrorLevel,
)
from palletpilot.executor.apps.vda5050.orders import OrderManager, VehicleView
from palletpilot.executor.apps.vda5050.state import Messages, Snapshot
from palletpilot.roadmap import load_map

ROOT = Path(__file__).resolve().parents[1]
MISSIONS = ROOT / "missions"
REFERENCE = ROOT.parent / "shared" / "reference" / "vda5050-2.1.0" / "json_schemas"
PICK_PATH = ["a2", "a3", "floor_a3_pre", "floor_a3", "floor_a3_pre", "a3", "a_bot", "c_w", "j_charge", "j_drop"]
AT_A2 = VehicleView(6.0, 11.0, -math.pi / 2, -math.pi / 2)


@pytest.fixture(scope="module")
def world() -> tuple[Any, Any]:
    return load_map(MISSIONS / "warehouse.yaml"), load_vehicle(MISSIONS / "forklift.yaml")


@pytest.fixture
def manager(world: tuple[Any, Any]) -> OrderManager:
    roadmap, vehicle = world
    return OrderManager(roadmap, "warehouse", vehicle)


def pick(action_id: str = "p1", **params: Any) -> dict[str, Any]:
    values = {"loadType": "EPAL", "stationType": "floor", **params}
    return {
        "actionId": action_id,
        "actionType": "pick",
        "blockingType": "HARD",
        "actionParameters": [{"key": k, "value": v} for k, v in values.items()],
    }


def order(
    path: list[str],
    order_id: str = "o1",
    update: int = 0,
    seq0: int = 0,
    released: int | None = None,
    actions: dict[int, list[dict[str, Any]]] | None = None,
    version: str = "2.1.0",
    header_id: int = 7,
) -> dict[str, Any]:
    """An order along roadmap node ids; `released`: how many nodes are in the base (default all)."""
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
    return {
        "headerId": header_id,
        "timestamp": "2024-05-01T12:00:00.00Z",
        "version": version,
        "manufacturer": "palletpilot",
        "serialNumber": "0001",
        "orderId": order_id,
        "orderUpdateId": update,
        "nodes": nodes,
        "edges": edges,
    }


def instant(*actions: dict[str, Any]) -> dict[str, Any]:
    return {
        "headerId": 3,
        "timestamp": "2024-05-01T12:00:00.000Z",
        "version": "2.1.0",
        "manufacturer": "palletpilot",
        "serialNumber": "0001",
        "actions": list(actions),
    }


def act(action_type: str, action_id: str = "i1", **params: Any) -> dict[str, Any]:
    out: dict[str, Any] = {"actionId": action_id, "actionType": action_type, "blockingType": "NONE"}
    if params:
        out["actionParameters"] = [{"key": k, "value": v} for k, v in params.items()]
    return out


def refs(error: AgvError | None) -> dict[str, list[str]]:
    assert error is not None
    out: dict[str, list[str]] = {}
    for k, v in error.references:
        out.setdefault(k, []).append(v)
    return out


def rejected(decision: Any, error_type: str) -> AgvError:
    assert decision.kind == "rejected", decision
    assert decision.error.error_type == error_type, decision.error
    assert decision.error.level is ErrorLevel.WARNING
    return decision.error


# -- schemas, timestamps, headers ---------------------------------------------------------------------


@pytest.mark.skipif(not REFERENCE.is_dir(), reason="the shared VDA 5050 reference is not beside the repository")
def test_vendored_schemas_are_the_published_files() -> None:
    for topic in validation.TOPICS:
        vendored = MISSIONS.parent / "executor" / "apps" / "vda5050" / "schemas" / f"{topic}.schema"
        assert vendored.read_bytes() == (REFERENCE / f"{topic}.schema").read_bytes(), topic
    assert (
        "Verband der Automobilindustrie" in (MISSIONS.parent / "executor/apps/vda5050/schemas/LICENSE.txt").read_text()
    )


def test_errata_are_applied() -> None:
    state = validation.load_schema("state")
    assert "PAUSED" in state["properties"]["actionStates"]["items"]["properties"]["actionStatus"]["enum"]
    published = validation.load_schema("state", errata=False)
    assert "PAUSED" not in published["properties"]["actionStates"]["items"]["properties"]["actionStatus"]["enum"]
    facts = validation.load_schema("factsheet")
    blocking = facts["properties"]["protocolFeatures"]["properties"]["agvActions"]["items"]["properties"]
    assert blocking["blockingTypes"]["items"]["enum"] == ["NONE", "SOFT", "HARD"]
    envelope = facts["properties"]["agvGeometry"]["properties"]["envelopes3d"]["items"]["properties"]
    assert envelope["description"]["type"] == "string"


def test_timestamps_are_checked_and_strictly_increasing() -> None:
    assert validation.is_rfc3339("2017-04-15T11:40:03.12Z")
    assert validation.is_rfc3339("2017-04-15T11:40:03+02:00")
    for bad in ("2017-04-15 11:40", "2017-13-15T11:40:03Z", "2017-04-15T11:40:03", "yesterday"):
        assert not validation.is_rfc3339(bad), bad
    doc = order(["a2"])
    doc["timestamp"] = "2017-04-15T25:40:03Z"
    assert any("timestamp" in p for p in validation.problems("order", doc))
    times = iter([1_000_000, 1_000_000, 999_000, 1_000_500])
    stamp = validation.Stamper(lambda: next(times))
    out = [stamp() for _ in range(4)]
    assert out == sorted(out) and len(set(out)) == 4
    assert all(validation.STRICT_TIMESTAMP.fullmatch(t) for t in out)
    assert out[0] == "1970-01-01T00:16:40.000Z"


def test_header_ids_count_per_topic() -> None:
    headers = validation.Headers("2.1.0", "m", "s")
    assert [headers.header("state")["headerId"] for _ in range(3)] == [0, 1, 2]
    assert headers.header("visualization")["headerId"] == 0
    h = headers.header("state")
    assert (h["headerId"], h["version"], h["manufacturer"], h["serialNumber"]) == (3, "2.1.0", "m", "s")


# -- the acceptance flow ------------------------------------------------------------------------------


def test_new_order_is_accepted_and_its_first_node_traversed(manager: OrderManager) -> None:
    d = manager.receive_order(order(PICK_PATH, actions={3: [pick()]}), AT_A2)
    assert d.kind == "new"
    assert (manager.order_id, manager.order_update_id) == ("o1", 0)
    assert (manager.last_node_id, manager.last_node_seq) == ("a2", 0)
    assert [n["nodeId"] for n in manager.node_states()] == PICK_PATH[1:]
    assert manager.edge_states()[0]["edgeId"] == "a2-a3"
    assert [(a["actionId"], a["actionStatus"]) for a in manager.actions.to_json()] == [("p1", "WAITING")]
    assert manager.executing()


def test_a_2_0_0_order_is_accepted(manager: OrderManager) -> None:
    assert manager.receive_order(order(PICK_PATH[:3], version="2.0.0"), AT_A2).kind == "new"


@pytest.mark.parametrize(
    ("change", "where"),
    [
        (lambda d: d.pop("nodes"), "nodes"),
        (lambda d: d.update(version="1.1.0"), "version"),
        (lambda d: d["nodes"][1].update(sequenceId=3), "a3"),
        (lambda d: d["edges"].pop(), "edges"),
        (lambda d: d["edges"][0].update(endNodeId="a1"), "a2-a3"),
        (lambda d: d["nodes"][0].update(released=False), "a2"),
        (lambda d: d.update(nodes=[], edges=[]), "nodes"),
        (lambda d: d["nodes"][1].update(actions=[pick("x")]) or d["nodes"][3].update(actions=[pick("x")]), "x"),
    ],
)
def test_malformed_orders_are_validation_errors(manager: OrderManager, change: Any, where: str) -> None:
    doc = order(PICK_PATH[:5])
    change(doc)
    error = rejected(manager.receive_order(doc, AT_A2), "validationError")
    r = refs(error)
    assert r["headerId"] == ["7"] and r["topic"] == ["order"]
    assert any(where in v for vs in r.values() for v in vs) or where in error.description
    assert manager.order_id == "" and not manager.node_states()


def test_horizon_released_after_base(manager: OrderManager) -> None:
    doc = order(PICK_PATH[:4], released=2)
    doc["edges"][2]["released"] = True  # an edge released after an unreleased node
    rejected(manager.receive_order(doc, AT_A2), "validationError")


def test_base_and_horizon_stop_at_the_decision_point(manager: OrderManager) -> None:
    assert manager.receive_order(order(PICK_PATH, released=3), AT_A2).accepted
    states = manager.node_states()
    assert [n["released"] for n in states] == [True, True] + [False] * (len(PICK_PATH) - 3)
    leg = manager.plan_next()
    assert leg is not None and leg.kind == "move" and leg.route == ("a2", "a3", "floor_a3_pre")
    for node in leg.route[1:]:
        assert manager.arrive(node) is not None
    assert manager.plan_next() is None  # waiting at the decision point for more base
    assert manager.arrive("floor_a3") is None  # a horizon node is never traversed
    assert manager.has_horizon()


def test_update_extends_the_base_at_the_decision_point(manager: OrderManager) -> None:
    manager.receive_order(order(PICK_PATH[:6], released=3, actions={3: [pick()]}), AT_A2)
    update = order(PICK_PATH[2:8], update=1, seq0=4, actions={1: [pick()]})
    d = manager.receive_order(update, AT_A2)
    assert d.kind == "update", d
    assert manager.order_update_id == 1
    assert [n["nodeId"] for n in manager.node_states()] == PICK_PATH[1:8]
    assert all(n["released"] for n in manager.node_states())
    assert [a["actionId"] for a in manager.actions.to_json()] == ["p1"]  # the stitching node's content stays


def test_stale_and_equal_updates(manager: OrderManager) -> None:
    manager.receive_order(order(PICK_PATH[:6], released=3, update=2), AT_A2)
    error = rejected(manager.receive_order(order(PICK_PATH[2:6], update=1, seq0=4), AT_A2), "orderUpdateError")
    assert refs(error)["orderUpdateId"] == ["1"] and refs(error)["orderId"] == ["o1"]
    assert manager.order_update_id == 2 and len(manager.node_states()) == 5  # the order goes on
    assert manager.receive_order(order(PICK_PATH[:6], released=3, update=2), AT_A2).kind == "ignored"
    assert manager.errors == [error]


def test_update_must_stitch_at_the_decision_point(manager: OrderManager) -> None:
    manager.receive_order(order(PICK_PATH[:6], released=3), AT_A2)
    wrong = order(PICK_PATH[1:6], update=1, seq0=2)  # starts at a3, the decision point is floor_a3_pre
    error = rejected(manager.receive_order(wrong, AT_A2), "orderUpdateError")
    assert refs(error)["node.nodeId"] == ["a3"]
    same_id_wrong_seq = order(PICK_PATH[2:6], update=1, seq0=6)
    rejected(manager.receive_order(same_id_wrong_seq, AT_A2), "orderUpdateError")


def test_update_of_a_finished_order_continues_from_last_node(manager: OrderManager) -> None:
    manager.receive_order(order(PICK_PATH[:3]), AT_A2)
    for node in PICK_PATH[1:3]:
        manager.arrive(node)
    assert not manager.executing()
    rejected(manager.receive_order(order(PICK_PATH[1:5], update=1, seq0=2), AT_A2), "orderUpdateError")
    assert manager.receive_order(order(PICK_PATH[2:5], update=1, seq0=4), AT_A2).kind == "update"
    assert manager.plan_next() is not None


def test_new_order_while_executing_must_stitch(manager: OrderManager) -> None:
    manager.receive_order(order(PICK_PATH[:3]), AT_A2)
    rejected(manager.receive_order(order(PICK_PATH[:3], order_id="o2"), AT_A2), "orderUpdateError")
    d = manager.receive_order(order(PICK_PATH[2:5], order_id="o2", seq0=4), AT_A2)
    assert d.kind == "stitch" and manager.order_id == "o2"
    assert [n["nodeId"] for n in manager.node_states()] == PICK_PATH[1:5]


def test_rejections_last_until_an_order_is_accepted(manager: OrderManager) -> None:
    rejected(manager.receive_order(order(["nowhere"]), AT_A2), "noRouteError")
    rejected(manager.receive_order(order(PICK_PATH[:2], version="3.0.0"), AT_A2), "validationError")
    assert len(manager.errors) == 2
    assert manager.receive_order(order(PICK_PATH[:2]), AT_A2).accepted
    assert manager.errors == []


def test_no_route_errors(manager: OrderManager) -> None:
    e = rejected(manager.receive_order(order(["a2", "nowhere"]), AT_A2), "noRouteError")
    assert refs(e)["node.nodeId"] == ["nowhere"]
    e = rejected(manager.receive_order(order(["a2", "a1"]), AT_A2), "noRouteError")  # against the one-way aisle
    assert refs(e)["edge.edgeId"] == ["a2-a1"]
    e = rejected(manager.receive_order(order(["a3", "a_bot"]), AT_A2), "noRouteError")  # not where the truck stands
    assert refs(e)["node.nodeId"] == ["a3"]
    facing_north = VehicleView(6.0, 11.0, math.pi / 2, math.pi / 2)
    e = rejected(manager.receive_order(order(["a2", "a3"]), facing_north), "noRouteError")
    assert "turning on the spot" in e.description
    doc = order(["a2", "a3"])
    doc["nodes"][1]["nodePosition"] = {"x": 6.0, "y": 7.0, "mapId": "another_hall"}
    rejected(manager.receive_order(doc, AT_A2), "noRouteError")


def test_nodes_match_by_position_within_their_deviation(manager: OrderManager) -> None:
    doc = order(["a2", "a3"])
    doc["nodes"][1].update(nodeId="n17", nodePosition={"x": 6.1, "y": 7.05, "mapId": "warehouse"})
    doc["edges"][0]["endNodeId"] = "n17"
    assert manager.receive_order(doc, AT_A2).accepted
    assert manager.rm == ["a2", "a3"]
    doc = order(["a2", "a3"], order_id="o2")
    doc["nodes"][1].update(
        nodeId="n18", nodePosition={"x": 6.3, "y": 7.0, "mapId": "warehouse", "allowedDeviationXY": 0.1}
    )
    doc["edges"][0]["endNodeId"] = "n18"
    fresh = OrderManager(manager.routes.roadmap, "warehouse", manager.routes.params)
    e = rejected(fresh.receive_order(doc, AT_A2), "noRouteError")
    assert refs(e)["node.nodeId"] == ["n18"]
    within = VehicleView(6.2, 11.1, -math.pi / 2, -math.pi / 2)
    doc = order(["a2", "a3"], order_id="o3")
    doc["nodes"][0]["nodePosition"] = {"x": 6.0, "y": 11.0, "mapId": "warehouse", "allowedDeviationXY": 0.5}
    assert fresh.receive_order(doc, within).accepted


@pytest.mark.parametrize(
    ("actions", "key"),
    [
        ({3: [act("dance", "x1")]}, "actionType"),
        ({3: [act("startPause", "x1")]}, "actionType"),
        ({2: [pick()]}, "node.nodeId"),  # a pick at a pre-pallet node
        ({3: [pick(height=5.0)]}, "actionParameter"),
        ({3: [pick(loadType="barrel")]}, "actionParameter"),
        ({3: [pick(lhd="CLAMP")]}, "actionParameter"),
        ({3: [{**pick(), "actionParameters": [{"key": "loadType", "value": "eur"}]}]}, "actionParameter"),
        ({3: [{**pick(), "blockingType": "NONE"}]}, "actionId"),
        ({3: [pick(), pick("p2")]}, "actionId"),
        ({3: [pick()], 5: [pick("p2")]}, "actionId"),  # a second pick with the forks full
    ],
)
def test_order_errors_for_actions_it_cannot_perform(manager: OrderManager, actions: Any, key: str) -> None:
    e = rejected(manager.receive_order(order(PICK_PATH, actions=actions), AT_A2), "orderError")
    assert key in refs(e), e


def test_order_errors_for_fields_it_cannot_use(manager: OrderManager) -> None:
    doc = order(PICK_PATH[:3])
    doc["zoneSetId"] = "zones1"
    assert "zoneSetId" in refs(rejected(manager.receive_order(doc, AT_A2), "orderError"))
    doc = order(PICK_PATH[:3])
    doc["edges"][0]["direction"] = "left"
    assert refs(rejected(manager.receive_order(doc, AT_A2), "orderError"))["field"] == ["direction"]
    doc = order(PICK_PATH[:3])
    doc["edges"][0]["orientation"] = math.pi  # backwards on a forward edge
    rejected(manager.receive_order(doc, AT_A2), "orderError")
    doc = order(PICK_PATH[:3])
    doc["edges"][0]["actions"] = [act("startCharging", "c1")]
    assert refs(rejected(manager.receive_order(doc, AT_A2), "orderError"))["edge.edgeId"] == ["a2-a3"]
    charging = VehicleView(6.0, 11.0, -math.pi / 2, -math.pi / 2, charging=True)
    rejected(manager.receive_order(order(PICK_PATH[:3]), charging), "orderError")


def test_trajectories_on_the_roadmap_curve_are_accepted(manager: OrderManager) -> None:
    line = {"degree": 1, "knotVector": [0, 0, 1, 1], "controlPoints": [{"x": 6, "y": 11}, {"x": 6, "y": 7}]}
    doc = order(["a2", "a3"])
    doc["edges"][0]["trajectory"] = line
    doc["edges"][0]["maxSpeed"] = 0.5
    assert manager.receive_order(doc, AT_A2).accepted
    off = {"degree": 1, "knotVector": [0, 0, 1, 1], "controlPoints": [{"x": 6.5, "y": 11}, {"x": 6.5, "y": 7}]}
    doc = order(["a2", "a3"], order_id="o2")
    doc["edges"][0]["trajectory"] = off
    fresh = OrderManager(manager.routes.roadmap, "warehouse", manager.routes.params)
    assert "trajectory" in refs(rejected(fresh.receive_order(doc, AT_A2), "orderError"))["field"]


def test_legs_of_a_pick_and_drop_order(manager: OrderManager) -> None:
    path = [*PICK_PATH, "drop_pre", "drop", "drop_pre"]
    drop = {"actionId": "d1", "actionType": "drop", "blockingType": "SOFT"}
    assert manager.receive_order(order(path, actions={3: [pick()], 11: [drop]}), AT_A2).accepted
    leg = manager.plan_next()
    assert leg is not None and (leg.kind, leg.route) == ("move", ("a2", "a3", "floor_a3_pre"))
    manager.arrive("a3"), manager.arrive("floor_a3_pre")
    leg = manager.plan_next()
    assert leg is not None and (leg.kind, leg.route, leg.actions[0].action_id) == (
        "pick",
        ("floor_a3_pre", "floor_a3"),
        "p1",
    )
    manager.arrive("floor_a3"), manager.arrive("floor_a3_pre")
    manager.actions.set("p1", ActionStatus.FINISHED)
    leg = manager.plan_next()
    assert leg is not None and leg.kind == "move" and leg.route[-1] == "drop_pre"
    for node in leg.route[1:]:
        manager.arrive(node)
    leg = manager.plan_next()
    assert leg is not None and leg.kind == "drop"


# -- instant actions ----------------------------------------------------------------------------------


def test_unknown_instant_actions_fail_with_an_error(manager: OrderManager) -> None:
    out = manager.receive_instant_actions(instant(act("dance"), act("pick", "i2"), act("stateRequest", "i3")))
    assert [r.action.action_id for r in out] == ["i3"]
    states = {a["actionId"]: a["actionStatus"] for a in manager.actions.to_json()}
    assert states == {"i1": "FAILED", "i2": "FAILED", "i3": "WAITING"}
    assert [e.error_type for e in manager.errors] == ["instantActionError", "instantActionError"]
    assert refs(manager.errors[0])["actionId"] == ["i1"] and refs(manager.errors[0])["topic"] == ["instantActions"]
    manager.receive_instant_actions(instant(act("initPosition", "i4", x=1.0)))
    assert manager.actions.get("i4").status is ActionStatus.FAILED
    manager.receive_instant_actions({"headerId": 1, "actions": []})
    assert manager.errors[-1].error_type == "validationError"


def test_cancel_order_without_an_order(manager: OrderManager) -> None:
    assert manager.receive_instant_actions(instant(act("cancelOrder", "c1"))) == []
    assert manager.actions.get("c1").status is ActionStatus.FAILED
    error = manager.errors[-1]
    assert (error.error_type, error.level, error.references) == (
        "noOrderToCancel",
        ErrorLevel.WARNING,
        (("actionId", "c1"),),
    )


def test_cancel_order_with_an_order(manager: OrderManager) -> None:
    manager.receive_order(order(PICK_PATH, actions={3: [pick()]}), AT_A2)
    [record] = manager.receive_instant_actions(instant(act("cancelOrder", "c1")))
    assert record.action.action_type == "cancelOrder"
    assert manager.cancel() == ["p1"]
    manager.actions.set("c1", ActionStatus.RUNNING)
    manager.actions.set("c1", ActionStatus.FINISHED)  # the AGV does this once the truck stands
    assert manager.actions.get("p1").status is ActionStatus.FAILED
    assert manager.node_states() == [] and manager.edge_states() == []
    assert (manager.order_id, manager.order_update_id, manager.last_node_id) == ("o1", 0, "a2")
    manager.receive_instant_actions(instant(act("cancelOrder", "c2")))  # the order was cancelled already
    assert manager.errors[-1].error_type == "noOrderToCancel"
    assert manager.receive_order(order(PICK_PATH[:3], order_id="o2"), AT_A2).kind == "new"
    assert [a["actionId"] for a in manager.actions.to_json()] == []  # FINISHED/FAILED states go with a new order


# -- the action state machine -------------------------------------------------------------------------


def test_action_state_machine() -> None:
    table = ActionTable()
    a = Action("a1", "pick", BlockingType.HARD)
    table.add(a, "NODE")
    for status in (ActionStatus.INITIALIZING, ActionStatus.RUNNING, ActionStatus.PAUSED, ActionStatus.RUNNING):
        assert table.set("a1", status)
    assert not table.set("a1", ActionStatus.RUNNING)
    table.set("a1", ActionStatus.FINISHED)
    with pytest.raises(IllegalTransitionError):
        table.set("a1", ActionStatus.RUNNING)
    table.add(Action("a2", "drop", BlockingType.HARD), "NODE")
    with pytest.raises(IllegalTransitionError):
        table.set("a2", ActionStatus.PAUSED)  # WAITING -> PAUSED is no transition
    table.set("a2", ActionStatus.INITIALIZING)
    assert table.pause() and table.get("a2").status is ActionStatus.PAUSED
    assert table.unpause() and table.get("a2").status is ActionStatus.INITIALIZING
    table.add(Action("i1", "startPause", BlockingType.NONE), "INSTANT", ActionStatus.WAITING)
    table.set("i1", ActionStatus.RUNNING)
    table.new_order()
    assert [r.action.action_id for r in table] == ["i1"]  # running instant actions stay


# -- configuration and messages -----------------------------------------------------------------------


def test_the_shipped_config_loads() -> None:
    loaded = load_config(MISSIONS / "agv.yaml")
    cfg = loaded.config
    assert cfg.topic_prefix == "uagv/v2/palletpilot/0001"
    assert (cfg.map_name, cfg.client_id, cfg.protocol_version) == ("warehouse", "palletpilot-0001", "2.1.0")


def test_bad_config_is_one_line_per_problem(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> None:
    monkeypatch.delenv("NO_SUCH_AGV_PASSWORD", raising=False)
    bad = tmp_path / "agv.yaml"
    bad.write_text(
        "broker: {port: 70000, username: u, password_env: NO_SUCH_AGV_PASSWORD}\n"
        "manufacturer: a/b\nserial_number: '0 1'\nprotocol_version: 1.1.0\nmap: warehouse.yaml\nstate_interval_s: 60\n"
    )
    with pytest.raises(AgvConfigError) as exc:
        load_config(bad)
    lines = exc.value.problems
    for field in ("broker.port", "manufacturer", "serial_number", "protocol_version", "state_interval_s"):
        assert any(line.startswith(f"{bad}: {field}:") for line in lines), (field, lines)
    good = tmp_path / "agv2.yaml"
    good.write_text(
        f"broker: {{username: u, password_env: NO_SUCH_AGV_PASSWORD, tls: {{ca: missing.pem}}}}\n"
        f"manufacturer: m\nserial_number: s1\nmap: {MISSIONS / 'warehouse.yaml'}\n"
    )
    with pytest.raises(AgvConfigError) as exc:
        load_config(good)
    assert any("broker.password_env" in line for line in exc.value.problems)
    assert any("broker.tls.ca" in line for line in exc.value.problems)
    run = subprocess.run(
        [sys.executable, "-m", "palletpilot.cli", "agv", "--config", str(bad), "--sim", "x.yaml"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 2 and "Traceback" not in run.stderr
    assert len(run.stderr.strip().splitlines()) == len(lines)


def test_robot_mode_checks_the_robot_file() -> None:
    run = subprocess.run(
        [sys.executable, "-m", "palletpilot.cli", "agv", "--config", str(MISSIONS / "agv.yaml"), "--robot", "r.yaml"],
        capture_output=True,
        text=True,
        timeout=120,
    )
    assert run.returncode == 2, run.stderr  # through the ROS 2 adapter, which reads the robot file first
    assert "r.yaml: cannot read" in run.stderr and "Traceback" not in run.stderr


def test_outgoing_messages_are_schema_valid(manager: OrderManager, world: tuple[Any, Any]) -> None:
    _, vehicle = world
    messages = Messages(validation.Headers("2.1.0", "palletpilot", "0001"), "warehouse", "abc", vehicle, 30.0, 2.0)
    manager.receive_order(order(PICK_PATH, actions={3: [pick()]}), AT_A2)
    manager.receive_instant_actions(instant(act("dance")))
    manager.actions.set("p1", ActionStatus.INITIALIZING)
    manager.actions.pause()
    snap = Snapshot(6.0, 11.0, -1.5, 0.4, 0.1, True, 0.5, True, ("person",), ("collision: fork",))
    load = {"loadType": "eur", "loadId": "L1", "loadPosition": "FORKS"}
    state = messages.state(
        manager, snap, paused=True, charging=False, new_base_request=True, distance_since_last_node=1.2, load=load
    )
    assert validation.problems("state", state) == []
    assert state["safetyState"] == {"eStop": "MANUAL", "fieldViolation": True}
    assert {e["errorType"] for e in state["errors"]} == {"instantActionError", "collision", "fieldViolation"}
    assert {a["actionStatus"] for a in state["actionStates"]} == {"PAUSED", "FAILED"}
    assert state["loads"] == [load] and state["batteryState"]["batteryCharge"] == 50.0
    for topic, message in (
        ("visualization", messages.visualization(snap)),
        ("connection", messages.connection(ConnectionState.ONLINE)),
        ("factsheet", messages.factsheet("0.1.0")),
    ):
        assert validation.problems(topic, message) == [], topic
        assert validation.STRICT_TIMESTAMP.fullmatch(message["timestamp"])
    facts = messages.factsheet()
    actions = {a["actionType"] for a in facts["protocolFeatures"]["agvActions"]}
    assert {"pick", "drop", "cancelOrder", "startPause", "factsheetRequest", "initPosition"} <= actions
    json.dumps(facts)


def test_the_factsheet_s_load_sets_name_exactly_the_load_types_orders_accept(world: tuple[Any, Any]) -> None:
    """Issue 39: the factsheet named `eur`, `industrial`, ... while orders accepted `EPAL` too. Every loadSet's
    loadType is accepted by a pick; a loadType that no loadSet names is refused, the refusal naming them."""
    roadmap, vehicle = world
    messages = Messages(validation.Headers("2.1.0", "palletpilot", "0001"), "warehouse", "abc", vehicle, 30.0, 2.0)
    facts = messages.factsheet()
    assert validation.problems("factsheet", facts) == []
    names = [s["loadType"] for s in facts["loadSpecification"]["loadSets"]]
    assert (
        "EPAL" in names
        and "eur" in names
        and len({s["setName"] for s in facts["loadSpecification"]["loadSets"]}) == len(names)
    )
    for name in names:
        manager = OrderManager(roadmap, "warehouse", vehicle)
        decision = manager.receive_order(order(PICK_PATH, actions={3: [pick(loadType=name)]}), AT_A2)
        assert decision.accepted, (name, decision.error)
    manager = OrderManager(roadmap, "warehouse", vehicle)
    decision = manager.receive_order(order(PICK_PATH, actions={3: [pick(loadType="barrel")]}), AT_A2)
    assert decision.error is not None and all(n in decision.error.description for n in names)
