"""The AGV in this process on the simulated warehouse in simulated time (a `SimClock` steps the simulator as
fast as the CPU allows, some 40x real time), the master's messages handed to `Agv.on_message` at chosen
simulated times from the executor thread itself, so a scenario runs the same every time (`FastAgv`,
`fast_agv`; tests/test_vda5050_random.py uses them too).

- The crash of issue 39: a pick-and-drop order ending at `drop`, then a new order from `drop` (as openTCS
  sends from a destination point) while the truck still waits in the slot for its back-out: the back-out
  runs (the load just dropped does not hold it), the new order's route follows, the process lives.
- An exception in the AGV's own code: the truck stops, a FATAL internalError, the executor goes on."""

from __future__ import annotations

import json
import math
import threading
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

from test_vda5050_mqtt import MISSIONS, action, make_order, write_config

from palletpilot.executor.apps.vda5050 import validation
from palletpilot.executor.apps.vda5050.agv import Agv
from palletpilot.executor.apps.vda5050.config import load_config
from palletpilot.executor.apps.vda5050.vehicle import TickClock, sim_backend
from palletpilot.executor.core.clock import SimClock

SCENARIO = """\
map: {map}
forks: {forks}
seed: {seed}
start: {start}
pallets:
  - {{node: floor_a3}}
  - {{node: floor_b2}}
"""
HEAD = {"version": "2.1.0", "manufacturer": "palletpilot", "serialNumber": "0001"}
PICK_DROP = ["a2", "a3", "floor_a3_pre", "floor_a3", "floor_a3_pre", "a3", "a_bot", "c_w", "j_charge", "j_drop"]


@dataclass
class FastAgv:
    """An `Agv` on a simulated clock; `at(t, fn)` runs `fn` on the executor thread at simulated time t (s)."""

    agv: Agv
    lines: list[str]
    schedule: list[tuple[float, Callable[[], None]]] = field(default_factory=list)
    checks: list[Callable[[], None]] = field(default_factory=list)
    header_id: int = 0
    failure: BaseException | None = None

    def now(self) -> float:
        """Simulated seconds."""
        return self.agv.backend.clock.now()

    def at(self, t: float, fn: Callable[[], None]) -> None:
        self.schedule.append((t, fn))
        self.schedule.sort(key=lambda item: item[0])

    def send(self, topic: str, doc: dict[str, Any]) -> None:
        """Hand a message to the AGV as the network thread would (a fresh header)."""
        self.header_id += 1
        head = {"headerId": self.header_id, "timestamp": validation.Stamper()(), **HEAD}
        self.agv.on_message(topic, json.dumps({**head, **doc}).encode())

    def state(self) -> dict[str, Any]:
        """The AGV's state now, as a 2.x master reads it."""
        return self.agv.state_message()

    def tick(self) -> None:
        """The clock hook: the AGV's own sampling, then what is due, then the checks."""
        self.agv._on_tick()
        try:
            while self.schedule and self.schedule[0][0] <= self.now():
                self.schedule.pop(0)[1]()
            for check in self.checks:
                check()
        except Exception as exc:  # the test's own failure: reported, not handed to the runner
            self.failure = self.failure or exc

    def run_until(self, done: Callable[[], bool], wall_s: float) -> None:
        """Run the executor thread until `done()` (polled) or `wall_s` of wall time, then stop it."""
        thread = threading.Thread(target=self._run, daemon=True)
        thread.start()
        deadline = time.monotonic() + wall_s
        try:
            while thread.is_alive() and self.failure is None and not done() and time.monotonic() < deadline:
                time.sleep(0.02)
            assert thread.is_alive(), f"the executor thread ended: {self.failure!r}"
        finally:
            self.agv.stop()
            thread.join(timeout=30)
            self.agv.backend.close()
        if self.failure is not None:
            raise self.failure

    def _run(self) -> None:
        try:
            self.agv.run()
        except BaseException as exc:  # the test reports it
            self.failure = exc


def fast_agv(tmp_path: Path, seed: int = 11, start: str = "a2") -> FastAgv:
    """The AGV on missions/warehouse.yaml with pallets at floor_a3 and floor_b2, simulator labels, a simulated
    clock and no MPC wall-clock deadline (a loaded CI machine must not fail a leg)."""
    loaded = load_config(write_config(tmp_path, 1883))  # never connected
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text(
        SCENARIO.format(map=MISSIONS / "warehouse.yaml", forks=MISSIONS / "forks.yaml", seed=seed, start=start)
    )
    backend = sim_backend(loaded, scenario, labels="truth")
    wall = backend.clock.inner
    backend.clock = TickClock(SimClock(wall._step, dt=wall.dt), now=backend.clock._now)  # type: ignore[attr-defined]
    backend.follower.mpc.solve_deadline_s = None  # type: ignore[attr-defined]
    lines: list[str] = []
    fast = FastAgv(Agv(loaded, backend, log=lines.append), lines)
    backend.clock.hook = fast.tick
    return fast


def state_problems(fast: FastAgv) -> list[str]:
    return validation.problems("state", fast.agv.state_message())


# -- the crash of issue 39 -----------------------------------------------------------------------------------


def test_a_new_order_from_the_drop_node_while_the_truck_waits_in_the_slot(tmp_path: Path) -> None:
    fast = fast_agv(tmp_path)
    agv = fast.agv
    pick = action("pick", "pick1", "HARD", loadType="EPAL", stationType="floor", loadId="L-0042")
    drop = action("drop", "drop1", "HARD")
    path = [*PICK_DROP, "drop_pre", "drop"]  # the order ends at the drop node: no back-out released
    fast.at(1.0, lambda: fast.send("order", make_order("m1", path, actions={3: [pick], 11: [drop]})))
    sent: list[float] = []

    def waiting_in_the_slot() -> None:
        s = agv.state_message()
        if not sent and s["lastNodeId"] == "drop" and not s["nodeStates"] and agv.controls.gate == "drop_pre":
            assert [a["actionStatus"] for a in s["actionStates"]] == ["FINISHED", "FINISHED"]
            sent.append(fast.now())
            fast.send("order", make_order("m2", ["drop", "drop_pre", "j_drop"]))  # drop1 goes with it

    fast.checks.append(waiting_in_the_slot)
    fast.run_until(lambda: bool(sent) and agv.runner is None and agv.state_message()["lastNodeId"] == "j_drop", 40)
    s = agv.state_message()
    assert sent and s["orderId"] == "m2" and s["lastNodeId"] == "j_drop" and not s["nodeStates"], "\n".join(
        [*fast.lines[-6:], json.dumps(s)]
    )
    assert s["errors"] == [] and agv.halted is None, s["errors"]
    assert [leg["ok"] for leg in agv.legs] == [True, True, True, True, True], agv.legs
    assert agv.legs[3]["kind"] == "drop" and agv.legs[3]["end_s"] - sent[0] < 15.0  # no 30 s path_blocked


def test_an_error_in_the_agv_s_own_code_stops_the_truck_and_is_reported(tmp_path: Path) -> None:
    fast = fast_agv(tmp_path, start="b_bot")
    agv = fast.agv
    real = agv._speed_limits

    def broken(leg: Any) -> Any:
        if len(agv.legs) == 1:  # the second leg
            raise RuntimeError("a bug")
        return real(leg)

    agv._speed_limits = broken  # type: ignore[method-assign]
    fast.at(1.0, lambda: fast.send("order", make_order("o1", ["b_bot", "b1"])))
    fast.at(20.0, lambda: fast.send("order", make_order("o2", ["b1", "b2"])))
    fast.run_until(lambda: fast.now() > 40.0, 60)
    s = agv.state_message()
    assert [e["errorType"] for e in s["errors"]] == ["internalError"], s["errors"]
    assert s["errors"][0]["errorLevel"] == "FATAL" and "RuntimeError" in s["errors"][0]["errorDescription"]
    assert agv.halted == "internal_error" and not s["driving"] and state_problems(fast) == []
    assert s["lastNodeId"] == "b1"  # the first order ran; the second's leg never started


# -- pick and drop run at their node --------------------------------------------------------------------------


def test_pick_and_drop_wait_until_their_node_is_reached(tmp_path: Path) -> None:
    """Section 6.11 (table 2) and 6.10.2: a node action is WAITING until its node is reached. The adaptive
    approach (calibrate, estimate, re-plan, enter) is the traversal of the order's last edge; the pick runs at
    the pallet node with the truck standing, the drop likewise at the drop node."""
    fast = fast_agv(tmp_path)
    agv = fast.agv
    pick = action("pick", "pick1", "HARD", loadType="EPAL", stationType="floor", loadId="L-0042")
    drop = action("drop", "drop1", "HARD")
    path = [*PICK_DROP, "drop_pre", "drop", "drop_pre"]
    fast.at(1.0, lambda: fast.send("order", make_order("m1", path, actions={3: [pick], 11: [drop]})))
    seen: list[tuple[str | None, str | None, str, bool]] = []

    def record() -> None:
        s = agv.state_message()
        statuses = {a["actionId"]: a["actionStatus"] for a in s["actionStates"]}
        seen.append((statuses.get("pick1"), statuses.get("drop1"), s["lastNodeId"], s["driving"]))

    fast.checks.append(record)
    fast.run_until(lambda: bool(seen) and seen[-1][1] == "FINISHED" and seen[-1][2] == "drop_pre", 60)
    for name, index, node in (("pick1", 0, "floor_a3"), ("drop1", 1, "drop")):
        statuses = [row[index] or "" for row in seen]  # "" before the order
        assert "INITIALIZING" not in statuses and statuses[-1] == "FINISHED", (name, sorted(set(statuses)))
        reached = next(i for i, row in enumerate(seen) if row[2] == node)
        assert set(statuses[:reached]) - {""} == {"WAITING"}, (name, sorted(set(statuses[:reached])))
        running = [row for row in seen if row[index] == "RUNNING"]
        assert running and all(row[2] == node and not row[3] for row in running), (name, running[:3])


# -- a new order after a cancel part way along an edge (section 6.6.3.1) ------------------------------------


def position(x: float, y: float, deviation: float = 0.0) -> dict[str, Any]:
    out: dict[str, Any] = {"x": x, "y": y, "mapId": "warehouse"}
    if deviation:
        out["allowedDeviationXY"] = deviation
    return out


def cancel_then(tmp_path: Path, start: str, path: list[str], when: Callable[[dict[str, Any]], bool], restart: Any):
    """Drive `path`, cancel when `when(state)`, then once the truck stands send `restart(state)` (an order);
    returns the AGV, its log and the states (dicts) seen after the restart order."""
    fast = fast_agv(tmp_path, start=start)
    agv = fast.agv
    fast.at(1.0, lambda: fast.send("order", make_order("c1", path)))
    phase: list[str] = []
    after: list[dict[str, Any]] = []

    def follow() -> None:
        s = agv.state_message()
        if not phase and s["orderId"] == "c1" and when(s):
            phase.append("cancel")
            fast.send("instantActions", {"actions": [action("cancelOrder", "cancel1")]})
        elif phase == ["cancel"] and not s["driving"] and agv.runner is None and agv._cancel_action is None:
            phase.append("restart")
            fast.send("order", restart(s))
        elif len(phase) == 2:
            after.append(s)

    fast.checks.append(follow)
    fast.run_until(lambda: len(after) > 5 and after[-1]["orderId"] == "c2" and not after[-1]["nodeStates"], 60)
    return agv, fast.lines, after


def test_restart_after_a_cancel_on_a_straight_edge_from_the_last_node_passed(tmp_path: Path) -> None:
    def restart(s: dict[str, Any]) -> dict[str, Any]:
        assert s["lastNodeId"] == "b1" and 6.0 < s["agvPosition"]["y"] < 8.5, s["agvPosition"]
        order = make_order("c2", ["b1", "b2", "b3"])
        order["nodes"][0]["nodePosition"] = position(20.0, 5.0, deviation=4.0)  # the truck is within 4 m of b1
        return order

    agv, lines, after = cancel_then(
        tmp_path, "b_bot", ["b_bot", "b1", "b2", "b3"], lambda s: s["agvPosition"]["y"] > 6.5, restart
    )
    assert "agv: order c2/0 accepted (new)" in lines, lines[-5:]
    assert after[-1]["lastNodeId"] == "b3" and after[-1]["errors"] == [], after[-1]["errors"]
    assert abs(after[-1]["agvPosition"]["y"] - 13.0) < 0.3 and [leg["ok"] for leg in agv.legs][-1]


def test_restart_after_a_cancel_on_a_straight_edge_from_a_temporary_node(tmp_path: Path) -> None:
    def restart(s: dict[str, Any]) -> dict[str, Any]:
        order = make_order("c2", ["here", "b2", "b3"])
        p = s["agvPosition"]
        order["nodes"][0]["nodePosition"] = position(p["x"], p["y"])  # where the truck stands
        order["edges"][0]["startNodeId"] = "here"
        return order

    agv, lines, after = cancel_then(
        tmp_path, "b_bot", ["b_bot", "b1", "b2", "b3"], lambda s: s["agvPosition"]["y"] > 6.5, restart
    )
    assert "agv: order c2/0 accepted (new)" in lines, lines[-5:]
    assert after[0]["lastNodeId"] == "here" and after[-1]["lastNodeId"] == "b3" and after[-1]["errors"] == []
    assert agv.legs[-1]["ok"] and agv.legs[-1]["route"] == ["b1", "b2", "b3"]  # from b1's edge, part way


def test_restart_after_a_cancel_on_a_curve_from_the_last_node_passed(tmp_path: Path) -> None:
    """a_bot -> c_w is an arc of radius 3 m: cancelled on it, the order from a_bot (its deviation range reaching
    the truck, as a master sets it) drives on along the arc from where the truck stands, no controllerError."""

    def restart(s: dict[str, Any]) -> dict[str, Any]:
        p = s["agvPosition"]
        off = math.hypot(p["x"] - 6.0, p["y"] - 3.0)
        assert s["lastNodeId"] == "a_bot" and 0.5 < off < 3.5 and p["y"] > 0.2, (p, s["lastNodeId"])  # on the arc
        order = make_order("c2", ["a_bot", "c_w", "j_charge"])
        order["nodes"][0]["nodePosition"] = position(6.0, 3.0, deviation=off + 0.3)
        return order

    agv, lines, after = cancel_then(
        tmp_path, "a3", ["a3", "a_bot", "c_w", "j_charge"], lambda s: s["agvPosition"]["x"] > 6.6, restart
    )
    assert "agv: order c2/0 accepted (new)" in lines, lines[-5:]
    assert after[-1]["lastNodeId"] == "j_charge" and after[-1]["errors"] == [], after[-1]["errors"]
    assert abs(after[-1]["agvPosition"]["x"] - 11.0) < 0.3 and agv.legs[-1]["ok"]


def test_an_order_far_away_is_refused_for_its_distance(tmp_path: Path) -> None:
    fast = fast_agv(tmp_path, start="b_bot")
    fast.at(1.0, lambda: fast.send("order", make_order("far", ["a2", "a3"])))  # 22 m away, heading the other way
    fast.run_until(lambda: fast.now() > 3.0, 30)
    errors = fast.agv.state_message()["errors"]
    assert len(errors) == 1 and errors[0]["errorType"] == "noRouteError", errors
    assert "m from the truck" in errors[0]["errorDescription"] and "heading" not in errors[0]["errorDescription"]
