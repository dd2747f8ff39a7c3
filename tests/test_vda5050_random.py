"""A seeded, bounded random sequence of schema-valid messages at the in-process AGV in simulated time
(`test_vda5050_fastsim.FastAgv`): orders along roadmap walks with picks and drops, updates at the decision
point, stitches, stale resends, orders starting elsewhere, cancels, pauses and other instant actions. It asserts
no exit of the executor thread, no internalError, every state schema-valid, and a standing truck after every
failed leg. `PALLETPILOT_VDA_RANDOM_RUNS` (default 3) and `PALLETPILOT_VDA_RANDOM_MESSAGES` (default 30) size
it; the figures are printed (`pytest -s`). The same on a 3.0.0 AGV: the messages go through the test bridge's
2.x -> 3.0 translation (`vda_master/bridge_v3`), zone sets (BLOCKED, SPEED_LIMIT and RELEASE boxes, enabled at
once) and responses to the truck's zone requests come in among them, and every state is checked against the
3.0.0 schema."""

from __future__ import annotations

import math
import os
import random
import time
from pathlib import Path
from typing import Any

import pytest
from test_vda5050_fastsim import FastAgv, fast_agv
from test_vda5050_mqtt import action, make_order
from test_vda5050_v3 import FastAgvV3, fast_agv_v3
from vda_master.bridge_v3 import instant_to_v3, order_to_v3, state_to_v2

from palletpilot.executor.apps.vda5050 import validation
from palletpilot.geometry import angle_diff


class TranslatedV3(FastAgvV3):
    """A 3.0 AGV that the 2.x random master talks to through the bridge's translations."""

    def send(self, topic: str, doc: dict[str, Any]) -> None:
        if topic == "order":
            doc = order_to_v3({**doc, "version": "2.1.0"})
        elif topic == "instantActions":
            doc = instant_to_v3({**doc, "version": "2.1.0"})
        super().send(topic, {k: v for k, v in doc.items() if k != "version"})

    def state(self) -> dict[str, Any]:
        return state_to_v2(self.agv.state_message())


# -- the random sequence ----------------------------------------------------------------------------------


class RandomMaster:
    """Schema-valid messages at random: orders along roadmap walks (some with picks and drops), updates at
    the decision point, stale and resent updates, orders starting elsewhere, and instant actions."""

    KINDS = (
        ("new", 5),
        ("update", 5),
        ("stale", 1),
        ("elsewhere", 1),
        ("restart", 3),
        ("cancel", 3),
        ("pause", 1),
        ("resume", 3),
        ("instant", 2),
        ("zones", 0),
    )

    def __init__(self, fast: FastAgv, rng: random.Random, zones: int = 0) -> None:
        self.fast, self.rng = fast, rng
        self.kinds = [(k, zones if k == "zones" else w) for k, w in self.KINDS]
        self.roadmap = fast.agv.roadmap
        self.order_id, self.update, self.count = "", 0, 0
        self.nodes: list[tuple[str, int]] = []  # the last order's (nodeId, sequenceId), decision point last
        self.path: list[str] = []  # the roadmap nodes of its base
        self.sent: dict[str, int] = {}

    def walk(self, start: str, heading: float | None, n: int) -> list[str]:
        """A roadmap walk from `start` driveable without turning on the spot, picking at pallet nodes."""
        path = [start]
        if start not in self.roadmap:  # a temporary node of a restart: an update adds nothing to it
            return path
        for _ in range(n):
            here = path[-1]
            nexts = [
                b
                for b in self.roadmap.graph.successors(here)
                if not self.roadmap.edge(here, b).temporary
                and (heading is None or abs(angle_diff(self.roadmap.edge(here, b).yaw_start, heading)) < 0.09)
            ]
            if not nexts:
                break
            nxt = self.rng.choice(nexts)
            heading = self.roadmap.edge(here, nxt).yaw_end
            path.append(nxt)
        return path

    def heading_at(self, path: list[str]) -> float | None:
        if len(path) >= 2 and self.roadmap.graph.has_edge(path[-2], path[-1]):
            return float(self.roadmap.edge(path[-2], path[-1]).yaw_end)
        return None

    def actions_for(self, path: list[str]) -> dict[int, list[dict[str, Any]]]:
        """A pick or drop at most pallet and drop nodes of the walk, alternating with the load."""
        out: dict[int, list[dict[str, Any]]] = {}
        loaded = self.fast.agv.snapshot.loaded
        for i, n in enumerate(path[1:], start=1):
            node = self.roadmap.node(n)
            if node.pre_pallet is not None and self.rng.random() < 0.8:
                kind = "drop" if loaded or node.type.value == "drop" else "pick"
                self.count += 1
                params = {"loadType": self.rng.choice(["EPAL", "eur"]), "stationType": "floor"}
                if kind == "drop":
                    params = {}
                out[i] = [action(kind, f"{kind}{self.count}", "HARD", **params)]
                loaded = kind == "pick"
        return out

    def order(
        self, order_id: str, path: list[str], update: int, seq0: int, first: dict[str, Any] | None = None
    ) -> None:
        """Send an order along `path` (its base released at random); `first`: the first node's nodePosition."""
        released = self.rng.choice([None, None, max(1, len(path) - 1), max(1, len(path) // 2)])
        doc = make_order(order_id, path, update, seq0, actions=self.actions_for(path), released=released)
        if first is not None:
            doc["nodes"][0]["nodePosition"] = first
        base = [(n["nodeId"], n["sequenceId"]) for n in doc["nodes"] if n["released"]]
        self.order_id, self.update = order_id, update
        self.nodes, self.path = base, path[: len(base)]
        self.fast.send("order", doc)

    def restart(self, s: dict[str, Any], last: str, on_to: str) -> None:
        """Section 6.6.3.1, either way at random: from lastNodeId with a deviation range reaching the truck, or
        from a temporary node where it stands; on along the edge it stands on."""
        p, node = s["agvPosition"], self.roadmap.node(last)
        rest = self.walk(on_to, self.roadmap.edge(last, on_to).yaw_end, self.rng.randint(0, 4))
        if self.rng.random() < 0.5:
            path, pos = [last, *rest], {"x": node.pose.x, "y": node.pose.y}
            pos["allowedDeviationXY"] = math.hypot(p["x"] - node.pose.x, p["y"] - node.pose.y) + 0.2
        else:
            path, pos = [f"here{self.count}", *rest], {"x": p["x"], "y": p["y"]}
        self.order(f"r{self.count}", path, 0, 0, first={**pos, "mapId": "warehouse"})

    def fire(self) -> str:
        """One message; returns its kind."""
        kinds, weights = zip(*self.kinds, strict=True)
        kind = self.rng.choices(kinds, weights)[0]
        agv, s = self.fast.agv, self.fast.state()
        self.count += 1
        if kind == "new":  # from where the truck is, or stitched at the decision point while it executes
            released = [n for n in s["nodeStates"] if n["released"]]
            start, seq = (released[-1]["nodeId"], released[-1]["sequenceId"]) if released else (None, 0)
            heading = self.heading_at(self.path) if start is not None else agv.heading
            on = agv.view().on_edge if start is None and agv.leg is None else None
            if on is not None:  # cancelled part way along an edge
                self.restart(s, on.start, on.end)
                return kind
            if start is None:
                start, seq = s["lastNodeId"] or agv.backend.start_node or "a2", s["lastNodeSequenceId"]
            self.order(f"r{self.count}", self.walk(start, heading, self.rng.randint(1, 6)), 0, seq)
        elif kind == "update" and self.nodes:
            node, seq = self.nodes[-1]
            path = self.walk(node, self.heading_at(self.path), self.rng.randint(1, 5))
            self.order(self.order_id, path, self.update + 1, seq)
        elif kind == "stale" and self.nodes:
            self.fast.send("order", make_order(self.order_id, [self.nodes[0][0]], max(self.update - 1, 0), 0))
        elif kind == "restart" and agv.leg is None and (on := agv.view().on_edge) is not None:
            self.restart(s, on.start, on.end)
        elif kind == "elsewhere":
            start = self.rng.choice([n.id for n in self.roadmap.nodes() if not n.temporary])
            self.order(f"r{self.count}", self.walk(start, None, self.rng.randint(0, 3)), 0, 0)
        elif kind in ("cancel", "pause", "resume", "instant"):
            kind_of = {"cancel": "cancelOrder", "pause": "startPause", "resume": "stopPause"}.get(kind)
            if kind_of is None:
                kind_of = self.rng.choice(["stateRequest", "factsheetRequest", "startCharging", "stopCharging"])
            self.fast.send("instantActions", {"actions": [action(kind_of, f"i{self.count}")]})
        elif kind == "zones":
            self.zone_set()
        else:
            return "none"
        return kind

    def zone_set(self) -> None:
        """A 3.0 zone set: a BLOCKED, SPEED_LIMIT or RELEASE box around a random roadmap node, enabled at once;
        or, half the time while the truck has zone requests, a response to one (any grant type)."""
        requests = self.fast.agv.state_message().get("zoneRequests", [])
        if requests and self.rng.random() < 0.5:
            grant = self.rng.choice(["GRANTED", "GRANTED", "QUEUED", "REJECTED", "REVOKED"])
            response = {"requestId": self.rng.choice(requests)["requestId"], "grantType": grant}
            self.fast.send("responses", {"responses": [response]})
            return
        node = self.rng.choice([n for n in self.roadmap.nodes() if not n.temporary]).pose
        half = self.rng.uniform(0.3, 1.5)
        x0, y0, x1, y1 = node.x - half, node.y - half, node.x + half, node.y + half
        zone: dict[str, Any] = {
            "zoneId": f"z{self.count}",
            "zoneType": self.rng.choice(["BLOCKED", "SPEED_LIMIT", "RELEASE"]),
        }
        zone["vertices"] = [{"x": x0, "y": y0}, {"x": x1, "y": y0}, {"x": x1, "y": y1}, {"x": x0, "y": y1}]
        if zone["zoneType"] == "SPEED_LIMIT":
            zone["maximumSpeed"] = self.rng.uniform(0.1, 0.5)
        set_id = f"set{self.count}"
        self.fast.send("zoneSet", {"zoneSet": {"mapId": "warehouse", "zoneSetId": set_id, "zones": [zone]}})
        self.fast.send("instantActions", {"actions": [action("enableZoneSet", f"e{self.count}", zoneSetId=set_id)]})


def random_run(tmp_path: Path, seed: int, messages: int, version: str = "2.1.0") -> dict[str, Any]:
    """One seeded run: `messages` messages at random simulated intervals; the figures of the run. On 3.0.0
    the AGV speaks 3.0 (`TranslatedV3`) and zone sets come in too."""
    rng = random.Random(seed)
    tmp_path.mkdir(parents=True, exist_ok=True)
    start = rng.choice(["a2", "b_bot", "c_w"])
    v3 = version.startswith("3.")
    fast: FastAgv = fast_agv(tmp_path, seed=seed, start=start) if not v3 else _translated(tmp_path, start)
    agv = fast.agv
    master = RandomMaster(fast, rng, zones=3 if v3 else 0)

    def state_problems(fast: FastAgv) -> list[str]:
        return validation.problems("state", fast.agv.state_message(), version)

    fired: list[str] = []
    invalid: list[list[str]] = []
    moving_while_halted: list[tuple[float, str, float]] = []
    halted_since: list[float | None] = [None]
    states = [0]
    t = 1.0
    for _ in range(messages):
        t += rng.expovariate(1.0 / 8.0)

        def fire() -> None:
            fired.append(master.fire())
            states[0] += 1
            problems = state_problems(fast)
            if problems:
                invalid.append(problems)

        fast.at(t, fire)

    def standing_after_errors() -> None:
        now = fast.now()
        if agv.halted is None:
            halted_since[0] = None
        elif halted_since[0] is None:
            halted_since[0] = now
        elif now - halted_since[0] > 3.0 and abs(agv.snapshot.speed) > 0.02:
            moving_while_halted.append((now, agv.halted, agv.snapshot.speed))
        if round(now / fast.agv.backend.clock.dt) % 40 == 0:  # a state every 2 s of simulated time
            states[0] += 1
            problems = state_problems(fast)
            if problems:
                invalid.append(problems)

    fast.checks.append(standing_after_errors)
    fast.run_until(lambda: fast.now() > t + 20.0, 120)
    final = agv.state_message()
    return {
        "seed": seed,
        "messages": len(fired),
        "kinds": {k: fired.count(k) for k in sorted(set(fired))},
        "states": states[0],
        "invalid": invalid,
        "moving_while_halted": moving_while_halted,
        "internal": [e for e in final["errors"] if e["errorType"] == "internalError"]
        + [line for line in fast.lines if "internal error" in line],
        "legs": len(agv.legs),
        "failed_legs": sum(not leg["ok"] for leg in agv.legs),
        "sim_s": round(fast.now(), 1),
    }


def _translated(tmp_path: Path, start: str) -> TranslatedV3:
    fast = fast_agv_v3(tmp_path, start=start)
    out = TranslatedV3(fast.agv, fast.lines)
    fast.agv.backend.clock.hook = out.tick
    return out


@pytest.mark.parametrize("version", ["2.1.0", "3.0.0"])
def test_random_valid_messages_never_end_the_agv(tmp_path: Path, version: str) -> None:
    runs = int(os.environ.get("PALLETPILOT_VDA_RANDOM_RUNS", "3"))
    messages = int(os.environ.get("PALLETPILOT_VDA_RANDOM_MESSAGES", "30"))
    started = time.monotonic()
    figures = [random_run(tmp_path / f"run{seed}", seed, messages, version) for seed in range(1, runs + 1)]
    total = sum(f["messages"] for f in figures)
    print(
        f"random sequence ({version}): {runs} runs, {total} messages, {sum(f['states'] for f in figures)} states, "
        f"{sum(f['legs'] for f in figures)} legs ({sum(f['failed_legs'] for f in figures)} failed), "
        f"{sum(f['sim_s'] for f in figures):.0f} s simulated in {time.monotonic() - started:.0f} s, exits 0"
    )
    for f in figures:
        assert f["internal"] == [], f
        assert f["invalid"] == [], f["invalid"][:3]
        assert f["moving_while_halted"] == [], f["moving_while_halted"][:3]
    assert total == runs * messages and sum(f["legs"] for f in figures) > runs  # the truck did drive
    assert sum(f["kinds"].get("new", 0) + f["kinds"].get("update", 0) for f in figures) > runs
