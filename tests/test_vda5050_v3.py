"""VDA 5050 3.0.0 (`protocol_version: 3.0.0`): the vendored schemas and their errata, the version layer's
translations both ways, and the zones, with the AGV in this process on a simulated clock (`test_vda5050_fastsim`).
Every message the AGV builds here is validated against the 3.0.0 schemas."""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

import pytest
from test_vda5050_fastsim import SCENARIO, FastAgv
from test_vda5050_mqtt import MISSIONS, action, make_order, write_config

from palletpilot.executor.apps.vda5050 import validation
from palletpilot.executor.apps.vda5050.agv import Agv
from palletpilot.executor.apps.vda5050.config import load_config
from palletpilot.executor.apps.vda5050.models import ConnectionState
from palletpilot.executor.apps.vda5050.v3 import order_from_v3
from palletpilot.executor.apps.vda5050.v3_out import error_type_v3
from palletpilot.executor.apps.vda5050.vehicle import TickClock, sim_backend
from palletpilot.executor.apps.vda5050.zones import Footprint, contour_hits
from palletpilot.executor.core.clock import SimClock
from palletpilot.geometry.fileio import bundled_path

V3 = "3.0.0"
HEAD = {"version": V3, "manufacturer": "palletpilot", "serialNumber": "0001"}


class FastAgvV3(FastAgv):
    """`FastAgv` whose messages carry a 3.0.0 header."""

    def send(self, topic: str, doc: dict[str, Any]) -> None:
        self.header_id += 1
        head = {"headerId": self.header_id, "timestamp": validation.Stamper()(), **HEAD, **doc.pop("_head", {})}
        self.agv.on_message(topic, json.dumps({**head, **doc}).encode())


def fast_agv_v3(tmp_path: Path, start: str = "b_bot") -> FastAgvV3:
    """The 3.0 AGV on the example warehouse (as `test_vda5050_fastsim.fast_agv`)."""
    loaded = load_config(write_config(tmp_path, 1883, protocol_version=V3, interface_name=None))
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text(
        SCENARIO.format(map=MISSIONS / "warehouse.yaml", forks=MISSIONS / "forks.yaml", seed=11, start=start)
    )
    backend = sim_backend(loaded, scenario, labels="truth")
    wall = backend.clock.inner
    backend.clock = TickClock(SimClock(wall._step, dt=wall.dt), now=backend.clock._now)  # type: ignore[attr-defined]
    backend.follower.mpc.solve_deadline_s = None  # type: ignore[attr-defined]
    lines: list[str] = []
    fast = FastAgvV3(Agv(loaded, backend, log=lines.append), lines)
    backend.clock.hook = fast.tick
    return fast


def order_v3(order_id: str, path: list[str], **kw: Any) -> dict[str, Any]:
    """`make_order` in 3.0: edges without startNodeId / endNodeId."""
    doc = make_order(order_id, path, **kw)
    for e in doc["edges"]:
        del e["startNodeId"], e["endNodeId"]
    return doc


def zone_set(set_id: str, *zones: dict[str, Any]) -> dict[str, Any]:
    return {"zoneSet": {"mapId": "warehouse", "zoneSetId": set_id, "zones": list(zones)}}


def box(zone_id: str, kind: str, x0: float, y0: float, x1: float, y1: float, **extra: Any) -> dict[str, Any]:
    vertices = [{"x": x0, "y": y0}, {"x": x1, "y": y0}, {"x": x1, "y": y1}, {"x": x0, "y": y1}]
    return {"zoneId": zone_id, "zoneType": kind, "vertices": vertices, **extra}


class Watch:
    """Every tick: the state and visualization built and validated against 3.0.0, the pose kept."""

    def __init__(self, fast: FastAgvV3) -> None:
        self.fast, self.problems, self.poses, self.states = fast, [], [], 0
        self.planned = 0

    def __call__(self) -> None:
        agv = self.fast.agv
        s = agv.state_message()
        self.states += 1
        self.planned += "plannedPath" in s and len(s["intermediatePath"]["polyline"]) >= 1
        for topic, msg in (("state", s), ("visualization", agv.messages.visualization(agv.snapshot))):
            self.problems += [f"{topic}: {p}" for p in validation.problems(topic, msg, V3)]
        snap = agv.snapshot
        self.poses.append((self.fast.now(), snap.x, snap.y, snap.theta, snap.speed))


def test_the_published_3_0_schemas_need_the_errata_and_are_vendored_unchanged() -> None:
    reference = Path(__file__).resolve().parents[1] / ".." / "shared" / "reference" / "vda5050-3.0.0" / "json_schemas"
    for topic in validation.TOPICS_V3:
        ours = bundled_path("executor", "apps", "vda5050", "schemas", "3.0.0", f"{topic}.schema").read_bytes()
        if reference.is_dir():
            assert ours == (reference / f"{topic}.schema").read_bytes(), topic
        if topic in validation.TRAILING_COMMAS_V3:
            with pytest.raises(json.JSONDecodeError):
                validation.load_schema(topic, errata=False, version=V3)
        assert validation.load_schema(topic, version=V3)["title"]
    assert validation.problems("connection", {"connectionState": "CONNECTIONBROKEN"}, V3)


def test_config_3_0_topics_and_connection_broken(tmp_path: Path) -> None:
    loaded = load_config(write_config(tmp_path, 1883, protocol_version=V3, interface_name=None))
    assert loaded.config.topic_prefix == "vda5050/v3/palletpilot/0001"
    assert load_config(write_config(tmp_path, 1883)).config.topic_prefix == "uagv/v2/palletpilot/0001"
    fast = fast_agv_v3(tmp_path)
    will = fast.agv.messages.connection(ConnectionState.CONNECTIONBROKEN)
    assert will["connectionState"] == "CONNECTION_BROKEN" and will["version"] == V3
    assert validation.problems("connection", will, V3) == []
    factsheet = fast.agv.messages.factsheet("1.0")
    assert validation.problems("factsheet", factsheet, V3) == []
    assert factsheet["typeSpecification"]["supportedZones"] == [
        "BLOCKED",
        "LINE_GUIDED",
        "RELEASE",
        "SPEED_LIMIT",
        "PRIORITY",
        "PENALTY",
    ]
    fast.agv.backend.close()


def test_order_translation_renames_and_derives_the_edges_nodes() -> None:
    doc = {"headerId": 1, "timestamp": "2026-01-01T00:00:00.000Z", **HEAD, **order_v3("o", ["b_bot", "b1", "b2"])}
    doc["edges"][0]["maximumSpeed"] = 0.4
    doc["nodes"][1]["nodePosition"] = {"x": 20.0, "y": 5.0, "mapId": "warehouse"}
    doc["nodes"][1]["nodePosition"]["allowedDeviationXY"] = {"a": 0.8, "b": 0.3, "theta": 0.0}
    doc["nodes"][1]["actions"] = [{"actionId": "x", "actionType": "pick", "blockingType": "SINGLE", "retriable": True}]
    assert validation.problems("order", doc, V3) == []
    out, unsupported = order_from_v3(doc)
    assert unsupported == [] and validation.problems("order", out) == []
    assert [(e["startNodeId"], e["endNodeId"]) for e in out["edges"]] == [("b_bot", "b1"), ("b1", "b2")]
    assert out["edges"][0]["maxSpeed"] == 0.4 and "maximumSpeed" not in out["edges"][0]
    doc["edges"][1]["corridor"] = {"leftWidth": 0.5, "rightWidth": 0.5, "releaseRequired": True}
    doc["edges"][1]["reachOrientationBeforeEntering"] = False
    assert order_from_v3(doc)[1] == [] and "releaseRequired" not in order_from_v3(doc)[0]["edges"][1]["corridor"]
    doc["edges"][0]["reachOrientationBeforeEntering"] = True
    assert order_from_v3(doc)[1] == ["order.edges.reachOrientationBeforeEntering"]
    assert out["nodes"][1]["nodePosition"]["allowedDeviationXY"] == 0.3
    assert out["nodes"][1]["actions"][0]["blockingType"] == "HARD" and "retriable" not in out["nodes"][1]["actions"][0]
    assert (
        error_type_v3("palletNotFound") == "PALLET_NOT_FOUND" and error_type_v3("noRouteError") == "NO_ROUTE_TO_TARGET"
    )


def test_a_3_0_order_is_driven_and_every_message_is_3_0_valid(tmp_path: Path) -> None:
    fast = fast_agv_v3(tmp_path)
    agv, watch = fast.agv, Watch(fast)
    fast.checks.append(watch)
    fast.at(0.5, lambda: fast.send("order", {**make_order("old", ["b_bot", "b1"]), "_head": {"version": "2.1.0"}}))
    fast.at(1.0, lambda: fast.send("order", order_v3("o1", ["b_bot", "b1", "b2"])))
    fast.at(2.0, lambda: fast.send("instantActions", {"actions": [action("stateRequest", "sr1")]}))
    fast.run_until(lambda: agv.state_message()["lastNodeId"] == "b2" and not agv.snapshot.driving, 60)
    s = agv.state_message()
    assert watch.problems == [] and watch.states > 100 and watch.planned > 20
    assert s["orderId"] == "o1" and s["nodeStates"] == [] and s["errors"] == [], s["errors"]
    assert [a["actionId"] for a in s["instantActionStates"]] == ["sr1"] and s["actionStates"] == []
    assert "agvPosition" not in s and s["mobileRobotPosition"]["localized"] is True
    assert validation.problems("state", s) != []  # a 3.0 state is no 2.1 state: the renames are real
    fast.send("instantActions", {"actions": [action("clearInstantActions", "c1")]})
    assert [a["actionId"] for a in agv.state_message()["instantActionStates"]] == ["c1"]


def test_a_2_x_message_is_refused_by_a_3_0_agv(tmp_path: Path) -> None:
    fast = fast_agv_v3(tmp_path)
    fast.send("order", {**make_order("old", ["b_bot", "b1"]), "_head": {"version": "2.1.0"}})
    s = fast.agv.state_message()
    assert s["orderId"] == "" and [e["errorType"] for e in s["errors"]] == ["VALIDATION_FAILURE"], s["errors"]
    fast.agv.backend.close()


def test_an_order_across_a_blocked_zone_is_refused(tmp_path: Path) -> None:
    fast = fast_agv_v3(tmp_path)
    agv = fast.agv
    fast.at(0.2, lambda: fast.send("zoneSet", zone_set("z1", box("wall", "BLOCKED", 18.5, 10.0, 21.5, 11.0))))
    fast.at(0.3, lambda: fast.send("instantActions", {"actions": [action("enableZoneSet", "e1", zoneSetId="z1")]}))
    fast.at(1.0, lambda: fast.send("order", order_v3("o1", ["b_bot", "b1", "b2", "b3"])))
    fast.run_until(lambda: fast.now() > 6.0, 60)
    s = agv.state_message()
    assert s["orderId"] == "" and not s["driving"], s
    (error,) = s["errors"]
    assert error["errorType"] == "NO_ROUTE_TO_TARGET" and "BLOCKED zone 'wall'" in error["errorDescription"]
    # the fork tips (1.15 m ahead of the heels) would reach y = 10.15 standing at b2 (y = 9): edge b1-b2
    assert {"referenceKey": "edgeId", "referenceValue": "b1-b2"} in error["errorReferences"]
    assert math.hypot(agv.snapshot.x - 20.0, agv.snapshot.y - 3.0) < 0.05


def test_the_truck_holds_before_a_blocked_zone_enabled_while_it_drives(tmp_path: Path) -> None:
    fast = fast_agv_v3(tmp_path)
    agv, watch = fast.agv, Watch(fast)
    fast.checks.append(watch)
    wall = box("wall", "BLOCKED", 18.5, 10.0, 21.5, 11.0)
    fast.at(0.5, lambda: fast.send("zoneSet", zone_set("z1", wall)))
    fast.at(1.0, lambda: fast.send("order", order_v3("o1", ["b_bot", "b1", "b2", "b3"])))
    fast.at(4.0, lambda: fast.send("instantActions", {"actions": [action("enableZoneSet", "e1", zoneSetId="z1")]}))
    fast.run_until(lambda: fast.now() > 40.0, 90)
    s = agv.state_message()
    assert watch.problems == []
    footprint = agv.v3.inbound.footprint if agv.v3 else Footprint(0, 0, 0)
    zone = agv.v3.zones.active()[0] if agv.v3 else None
    assert zone is not None and not any(contour_hits(footprint, (x, y, th), zone) for _, x, y, th, _ in watch.poses)
    assert not s["driving"] and s["lastNodeId"] in ("b1", "b2") and 6.0 < agv.snapshot.y < 10.0, s
    assert [e["errorType"] for e in s["errors"]] == ["BLOCKED_ZONE_AHEAD"] and s["errors"][0][
        "errorLevel"
    ] == "CRITICAL"
    fast.send("instantActions", {"actions": [action("cancelOrder", "c1")]})


def test_speed_limit_zones_slow_the_truck_before_and_inside(tmp_path: Path) -> None:
    fast = fast_agv_v3(tmp_path)
    agv, watch = fast.agv, Watch(fast)
    fast.checks.append(watch)
    slow = box("slow", "SPEED_LIMIT", 18.0, 9.5, 22.0, 10.5, maximumSpeed=0.3)
    fast.at(0.2, lambda: fast.send("zoneSet", zone_set("z1", slow)))
    fast.at(0.3, lambda: fast.send("instantActions", {"actions": [action("enableZoneSet", "e1", zoneSetId="z1")]}))
    fast.at(1.0, lambda: fast.send("order", order_v3("o1", ["b_bot", "b1", "b2", "b3", "b_top"])))
    fast.run_until(lambda: agv.state_message()["lastNodeId"] == "b_top" and not agv.snapshot.driving, 90)
    assert watch.problems == [] and agv.state_message()["errors"] == []
    assert agv.v3 is not None
    zone, footprint = agv.v3.zones.active()[0], agv.v3.inbound.footprint
    inside = [abs(v) for _, x, y, th, v in watch.poses if contour_hits(footprint, (x, y, th), zone)]
    outside = [abs(v) for _, x, y, th, v in watch.poses if y < 3.5 or y > 16.0]
    assert inside and max(inside) <= 0.3 + 0.02, max(inside)
    assert max(outside) > 0.6  # elsewhere the truck drives faster: the limit is the zone's


def test_zone_sets_unsupported_duplicate_and_unknown_responses(tmp_path: Path) -> None:
    fast = fast_agv_v3(tmp_path)
    agv = fast.agv
    fast.send("zoneSet", zone_set("z1", box("r", "COORDINATED_REPLANNING", 0, 0, 1, 1)))
    errors = agv.state_message()["errors"]
    assert [e["errorType"] for e in errors] == ["UNSUPPORTED_ZONE_TYPE"]
    assert "COORDINATED_REPLANNING" in errors[0]["errorDescription"]
    assert agv.state_message()["zoneSets"] == []
    fast.send("zoneSet", zone_set("z2", box("ok", "LINE_GUIDED", 0, 0, 1, 1)))
    fast.send("zoneSet", zone_set("z2", box("ok", "LINE_GUIDED", 0, 0, 1, 1)))
    fast.send("responses", {"responses": [{"requestId": "nope", "grantType": "GRANTED"}]})
    fast.send("instantActions", {"actions": [action("enableZoneSet", "e9", zoneSetId="missing")]})
    s = agv.state_message()
    assert s["zoneSets"] == [{"zoneSetId": "z2", "mapId": "warehouse", "zoneSetStatus": "DISABLED"}]
    kinds = [e["errorType"] for e in s["errors"]]
    assert kinds == ["UNSUPPORTED_ZONE_TYPE", "DUPLICATE_ZONE_SET", "UNKNOWN_REQUEST", "INVALID_INSTANT_ACTION"], kinds
    assert next(a for a in s["instantActionStates"] if a["actionId"] == "e9")["actionStatus"] == "FAILED"
    assert validation.problems("state", s, V3) == []
    agv.backend.close()


def test_standing_inside_a_blocked_zone_is_a_violation_until_the_zone_goes(tmp_path: Path) -> None:
    fast = fast_agv_v3(tmp_path)
    agv = fast.agv
    kinds: list[list[str]] = []
    fast.checks.append(lambda: kinds.append([e["errorType"] for e in agv.state_message()["errors"]]))
    fast.at(0.2, lambda: fast.send("zoneSet", zone_set("z1", box("here", "BLOCKED", 19.0, 2.0, 21.0, 4.0))))
    fast.at(0.3, lambda: fast.send("instantActions", {"actions": [action("enableZoneSet", "e1", zoneSetId="z1")]}))
    fast.at(3.0, lambda: fast.send("instantActions", {"actions": [action("deleteZoneSet", "d1", zoneSetId="z1")]}))
    fast.run_until(lambda: fast.now() > 5.0, 60)
    during = kinds[10:55]  # 0.5 s .. 2.75 s at 20 Hz: the violation, steadily (no flapping)
    assert during and all(k == ["BLOCKED_ZONE_VIOLATION"] for k in during), during[:5]
    assert kinds[-1] == [] and agv.state_message()["zoneSets"] == [] and not agv.snapshot.driving


def test_a_failed_pick_is_a_critical_error_in_3_0(tmp_path: Path) -> None:
    fast = fast_agv_v3(tmp_path)
    agv = fast.agv
    pick = action("pick", "p1", "HARD", loadType="EPAL", stationType="floor")  # no pallet at floor_b1
    fast.at(
        1.0,
        lambda: fast.send("order", order_v3("o1", ["b_bot", "b1", "floor_b1_pre", "floor_b1"], actions={3: [pick]})),
    )
    fast.run_until(lambda: agv.halted is not None and not agv.snapshot.driving, 120)
    s = agv.state_message()
    assert validation.problems("state", s, V3) == []
    (error,) = s["errors"]
    assert error["errorLevel"] == "CRITICAL" and error["errorType"] == error["errorType"].upper(), error
    assert next(a for a in s["actionStates"] if a["actionId"] == "p1")["actionStatus"] == "FAILED"


def test_a_3_0_agv_restored_from_a_journal_stays_3_0(tmp_path: Path) -> None:
    fast = fast_agv_v3(tmp_path)
    agv = fast.agv
    agv._sample()
    agv.heading = agv._axis_heading("b_bot")  # as `run` sets it
    fast.send("order", order_v3("o1", ["b_bot", "b1", "b2"]))
    assert agv.state_message()["orderId"] == "o1"
    doc = json.loads(json.dumps(agv.checkpoint_doc()))
    again = Agv(agv.loaded, agv.backend)
    again.restore({**doc, "version": "2.1.0"}, source="agv.db")  # a journal a 2.1 master's messages left
    s = again.state_message()
    assert s["version"] == V3 and s["orderId"] == "o1" and validation.problems("state", s, V3) == []
    agv.backend.close()


def release_run(tmp_path: Path, answer: Callable[[FastAgvV3, dict[str, Any]], None], until_s: float = 60.0) -> Watch:
    """The truck from b_bot to b3 across RELEASE zone 'gate' (y 10..11 in aisle B); `answer(fast, state)` runs
    every tick (the master's side)."""
    tmp_path.mkdir(parents=True, exist_ok=True)
    fast = fast_agv_v3(tmp_path)
    watch = Watch(fast)
    fast.checks.append(watch)
    fast.checks.append(lambda: answer(fast, fast.agv.state_message()))
    gate = box("gate", "RELEASE", 18.5, 10.0, 21.5, 11.0, releaseLossBehavior="STOP")
    fast.at(0.2, lambda: fast.send("zoneSet", zone_set("z1", gate)))
    fast.at(0.3, lambda: fast.send("instantActions", {"actions": [action("enableZoneSet", "e1", zoneSetId="z1")]}))
    fast.at(1.0, lambda: fast.send("order", order_v3("o1", ["b_bot", "b1", "b2", "b3"])))
    fast.run_until(lambda: fast.now() > until_s, 120)
    return watch


def in_gate(fast: FastAgvV3, pose: tuple[float, float, float, float, float]) -> bool:
    assert fast.agv.v3 is not None
    zone = next(z for z in fast.agv.v3.zones.active() if z.zone_id == "gate")
    return contour_hits(fast.agv.v3.inbound.footprint, pose[1:4], zone)


def respond(fast: FastAgvV3, request_id: str, grant: str) -> None:
    fast.send("responses", {"responses": [{"requestId": request_id, "grantType": grant}]})


def test_a_release_zone_is_entered_only_once_granted(tmp_path: Path) -> None:
    granted: list[float] = []
    requests: list[list[dict[str, Any]]] = []

    def master(fast: FastAgvV3, s: dict[str, Any]) -> None:
        requests.append(s["zoneRequests"])
        if not granted and s["zoneRequests"] and fast.now() > 15.0:  # answered late: the truck waits
            assert not s["driving"] and s["zoneRequests"][0]["requestStatus"] == "REQUESTED"
            granted.append(fast.now())
            respond(fast, s["zoneRequests"][0]["requestId"], "GRANTED")

    watch = release_run(tmp_path, master)
    fast = watch.fast
    s = fast.agv.state_message()
    assert watch.problems == [] and granted and s["lastNodeId"] == "b3" and s["errors"] == [], s
    first = next(r for r in requests if r)[0]
    assert first["requestType"] == "ACCESS" and first["zoneId"] == "gate" and first["zoneSetId"] == "z1"
    assert not any(in_gate(fast, p) for p in watch.poses if p[0] < granted[0])
    assert any(in_gate(fast, p) for p in watch.poses)
    assert s["zoneRequests"] == []  # left the zone: the request is gone


def test_a_rejected_release_holds_the_truck_and_a_revoked_one_stops_it_inside(tmp_path: Path) -> None:
    def reject(fast: FastAgvV3, s: dict[str, Any]) -> None:
        if s["zoneRequests"]:
            respond(fast, s["zoneRequests"][0]["requestId"], "REJECTED")

    watch = release_run(tmp_path / "rejected", reject, until_s=30.0)
    fast = watch.fast
    s = fast.agv.state_message()
    assert watch.problems == [] and not any(in_gate(fast, p) for p in watch.poses) and not s["driving"]
    assert s["zoneRequests"] == [] and [e["errorType"] for e in s["errors"]] == ["NODE_UNREACHABLE"]
    assert s["errors"][0]["errorLevel"] == "CRITICAL" and s["lastNodeId"] in ("b1", "b2")

    def grant_then_revoke(fast: FastAgvV3, s: dict[str, Any]) -> None:
        for r in s["zoneRequests"]:
            if r["requestStatus"] == "REQUESTED":
                respond(fast, r["requestId"], "GRANTED")
            elif r["requestStatus"] == "GRANTED" and fast.agv.snapshot.y > 9.0:  # in the zone (forks first)
                respond(fast, r["requestId"], "REVOKED")

    watch = release_run(tmp_path / "revoked", grant_then_revoke, until_s=40.0)
    fast = watch.fast
    s = fast.agv.state_message()
    assert watch.problems == [] and not s["driving"] and s["lastNodeId"] != "b3", s
    assert [r["requestStatus"] for r in s["zoneRequests"]] == ["REVOKED"]
    assert [e["errorType"] for e in s["errors"]] == ["RELEASE_LOST"] and in_gate(fast, watch.poses[-1])


def test_speed_limit_zones_apply_to_a_leg_as_it_starts(tmp_path: Path) -> None:
    """A zone set enabled after the order was taken still slows the legs that start afterwards."""
    from palletpilot.executor.apps.vda5050.legs import speed_limits
    from palletpilot.executor.apps.vda5050.orders import Leg

    fast = fast_agv_v3(tmp_path)
    agv = fast.agv
    assert agv.v3 is not None
    fast.send("zoneSet", zone_set("z1", box("slow", "SPEED_LIMIT", 18.0, 9.5, 22.0, 10.5, maximumSpeed=0.25)))
    fast.send("instantActions", {"actions": [action("enableZoneSet", "e1", zoneSetId="z1")]})
    route = ("b1", "b2", "b3", "b_top")
    assert agv.v3.leg_speed_limits(route) == {0: 0.25, 1: 0.25}  # the contour touches it from both edges
    leg = Leg("pick", 0, route)  # any leg kind: the zones are the roadmap's, not the order's
    with speed_limits(agv.orders, agv.roadmap, leg, agv.v3.leg_speed_limits):
        assert [agv.roadmap.edge(a, b).speed_limit for a, b in itertools.pairwise(route)] == [0.25, 0.25, 1.0]
    assert [agv.roadmap.edge(a, b).speed_limit for a, b in itertools.pairwise(route)] == [1.0, 1.0, 1.0]
    agv.backend.close()
