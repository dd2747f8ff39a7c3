"""The AGV's journal (`executor.vda5050.persist`): its order state survives a SIGKILL.

- Without MQTT: the order manager's state to a checkpoint and back; sessions (a foreign journal refused in
  one line, exit 2 from the CLI; a finished journal's headerIds carried over; an unfinished one resumed);
  the safe restore rule of `Agv.restore` on the simulated truck (the interrupted action FAILED, the truck
  halted, a truck away from lastNodeId refuses to stitch there, the load from the sensor) and the write time.
- End to end: `palletpilot agv --sim` as a subprocess on a real broker, SIGKILLed while it drives an order,
  restarted on the same journal: its first state continues the order (orderId, orderUpdateId, lastNodeId,
  nodeStates, headerIds above the last one sent) and the truck stays standing until cancelOrder.
"""

from __future__ import annotations

import json
import os
import signal
import subprocess
import sys
import time
from pathlib import Path
from typing import Any

import pytest
from test_vda5050_mqtt import MISSIONS, Broker, Master, action, make_order, needs_broker, status, write_config

from palletpilot.cli import main
from palletpilot.executor.adapters.stores.journal import Journal, JournalError
from palletpilot.executor.apps.vda5050 import validation
from palletpilot.executor.apps.vda5050.config import load_config
from palletpilot.executor.apps.vda5050.orders import OrderManager, VehicleView
from palletpilot.executor.apps.vda5050.persist import (
    HEADER_BLOCK,
    JOURNAL_NAME,
    Persister,
    agv_meta,
    open_session,
    orders_doc,
    restore_orders,
)

AGV = [sys.executable, "-m", "palletpilot.cli", "agv"]
SCENARIO = MISSIONS / "suite" / "floor_b2.yaml"  # the truck starts at b1, an empty pallet at floor_b2
PATH = ["b1", "b2", "floor_b2_pre", "floor_b2"]
META = agv_meta("palletpilot", "0001", "warehouse")


def message(body: dict[str, Any], header_id: int = 1) -> bytes:
    """A master's message (order or instantActions) with its header."""
    head = {"headerId": header_id, "timestamp": validation.Stamper()(), "version": "2.1.0"}
    head |= {"manufacturer": "palletpilot", "serialNumber": "0001"}
    return json.dumps({**head, **body}).encode()


def pick() -> dict[str, Any]:
    return action("pick", "pick1", "HARD", loadType="EPAL", stationType="floor", loadId="L-7")


# -- the checkpoint layer ---------------------------------------------------------------------------------


def test_the_order_state_round_trips_through_a_checkpoint(tmp_path: Path) -> None:
    loaded = load_config(write_config(tmp_path, 1883))
    o = OrderManager(loaded.roadmap, "warehouse", loaded.vehicle)
    doc = {"headerId": 3, "timestamp": "2026-01-01T00:00:00.000Z", "version": "2.1.0"}
    doc |= {"manufacturer": "palletpilot", "serialNumber": "0001"}
    doc |= make_order("o1", PATH, actions={3: [pick()]}, released=3)
    assert o.receive_order(doc, VehicleView(20.0, 5.0, 1.5708, 1.5708)).accepted
    assert o.arrive("b2") is not None
    o.actions.set("pick1", o.actions.get("pick1").status.INITIALIZING)
    saved = json.loads(json.dumps(orders_doc(o)))  # strict JSON, as the journal stores it

    back = OrderManager(loaded.roadmap, "warehouse", loaded.vehicle)
    restore_orders(back, saved, loaded.roadmap)
    assert (back.order_id, back.order_update_id, back.last_node_id, back.last_node_seq) == ("o1", 0, "b2", 2)
    assert back.last_rm == "b2" and back.cursor == 2 and back.rm == o.rm
    assert back.node_states() == o.node_states() and back.edge_states() == o.edge_states()
    assert back.actions.to_json() == o.actions.to_json() and back.received == [doc]
    # an update stitching at the decision point (floor_b2_pre, sequenceId 4) is accepted as before the restart
    update = {**doc, "headerId": 4, **make_order("o1", PATH[2:], update=1, seq0=4, actions={1: [pick()]})}
    assert back.receive_order(update, VehicleView(20.0, 9.0, 1.5708, 1.5708)).kind == "update"
    assert len(back.received) == 2

    saved["roadmapNodes"][1] = "nowhere"
    with pytest.raises(ValueError, match="nowhere"):
        restore_orders(OrderManager(loaded.roadmap, "warehouse", loaded.vehicle), saved, loaded.roadmap)


def test_sessions_new_resumed_finished_and_foreign(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = tmp_path / JOURNAL_NAME
    s = open_session(path, META)
    assert s.restored is None and s.headers == {}
    with Journal.open(path) as j:
        j.checkpoint({"format": 1, "headers": {"state": 1500, "connection": 1003}})
    s = open_session(path, META)  # unfinished: resumed
    assert s.restored is not None and s.headers["state"] == 1500 and s.resumes == 1
    with Journal.open(path) as j:
        j.finish(True, "stopped")
    s = open_session(path, META)  # finished: a new session, the headerIds carried over
    assert s.restored is None and s.headers == {"state": 1500, "connection": 1003}
    assert Journal.open(path).meta["headers"]["state"] == 1500

    with pytest.raises(JournalError, match="0002"):
        open_session(path, agv_meta("palletpilot", "0002", "warehouse"))
    mission = tmp_path / "mission.db"
    Journal.create(mission, {"mission": "m.yaml"}).close()
    with pytest.raises(JournalError, match="not the journal of a VDA 5050 AGV"):
        open_session(mission, META)
    (tmp_path / "junk.db").write_text("not a database")
    with pytest.raises(JournalError, match=r"junk\.db"):
        open_session(tmp_path / "junk.db", META)

    config = write_config(tmp_path, 1883)
    argv = ["agv", "--config", str(config), "--sim", str(SCENARIO), "--report", str(tmp_path / "r")]
    assert main([*argv, "--journal", str(mission)]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "mission.db" in err, err


def test_restore_fails_the_running_action_and_halts_the_truck(tmp_path: Path) -> None:
    """A pick INITIALIZING on its way at b2 when the process died; the simulator restarts at b1."""
    from palletpilot.executor.apps.vda5050.agv import Agv
    from palletpilot.executor.apps.vda5050.restart import LAST_NODE_MISMATCH, LOAD_MISMATCH, ORDER_INTERRUPTED
    from palletpilot.executor.apps.vda5050.vehicle import sim_backend

    loaded = load_config(write_config(tmp_path, 1883))
    backend = sim_backend(loaded, SCENARIO, labels="truth")
    try:
        before = Agv(loaded, backend)
        before._sample()
        before.heading = before._axis_heading("b1")  # as `run` sets it
        before.on_message("order", message(make_order("o1", PATH, actions={3: [pick()]}, released=3)))
        assert before.orders.arrive("b2") is not None
        before.orders.actions.set("pick1", before.orders.actions.get("pick1").status.RUNNING)
        before.load = {"loadType": "eur", "loadId": "L-0", "loadPosition": "LHD"}  # the sensor feels none
        for _ in range(7):
            before.messages.state(before.orders, before.snapshot, **_flags())  # headerIds 0..6
        doc = json.loads(json.dumps(before.checkpoint_doc()))

        lines: list[str] = []
        agv = Agv(loaded, backend, log=lines.append)
        agv.restore(doc, source="agv.db")
        agv.heading = agv._axis_heading("b1")
        state = agv.state_message()
        assert validation.problems("state", state) == []
        assert state["headerId"] == 7 + HEADER_BLOCK  # above every id of the dead process
        assert (state["orderId"], state["orderUpdateId"], state["lastNodeId"]) == ("o1", 0, "b2")
        assert [n["nodeId"] for n in state["nodeStates"]] == ["floor_b2_pre", "floor_b2"]
        assert status(state, "pick1") == "FAILED" and not state["driving"] and state["loads"] == []
        types = [e["errorType"] for e in state["errors"]]
        assert types == [ORDER_INTERRUPTED, ORDER_INTERRUPTED, LAST_NODE_MISMATCH, LOAD_MISMATCH], types
        assert "pick 'pick1' was RUNNING" in state["errors"][0]["errorDescription"]
        assert agv.halted == ORDER_INTERRUPTED and agv.orders.plan_next() is not None  # only halted keeps it
        assert "restored order 'o1'/0" in lines[-1]
        again = Agv(loaded, backend)  # killed once more before anything happened: the same findings, once
        again.restore(json.loads(json.dumps(agv.checkpoint_doc())))
        errors = again.state_message()["errors"]
        assert [e["errorType"] for e in errors] == [ORDER_INTERRUPTED, ORDER_INTERRUPTED, LAST_NODE_MISMATCH]

        # the truck is 4 m from b2: an update stitching there is refused; cancelOrder, then a new order from b1
        update = make_order("o1", PATH[2:], update=1, seq0=4)
        agv.on_message("order", message(update, 2))
        assert agv.orders.order_update_id == 0 and agv.orders.errors[-1].error_type == "orderUpdateError"
        agv.on_message("instantActions", message({"actions": [action("cancelOrder", "c1")]}, 3))
        assert agv.halted is None and status(agv.state_message(), "c1") == "RUNNING"
        agv._on_tick()  # a tick of the standing truck: the order goes, in one state with the cancel FINISHED
        s = agv.state_message()
        assert agv.orders.node_states() == [] and status(s, "c1") == "FINISHED" and status(s, "pick1") == "FAILED"
        agv.on_message("order", message(make_order("o2", ["b1", "b2"]), 4))
        s = agv.state_message()
        assert s["orderId"] == "o2" and s["lastNodeId"] == "b1" and s["errors"] == [], s["errors"]
    finally:
        backend.close()


def _flags() -> dict[str, Any]:
    return {
        "paused": False,
        "charging": False,
        "new_base_request": False,
        "distance_since_last_node": 0.0,
        "load": None,
    }


def test_checkpoints_are_written_off_the_loop_and_timed(tmp_path: Path) -> None:
    path = tmp_path / JOURNAL_NAME
    open_session(path, META)
    body = {"format": 1, "orders": {"nodes": [{"nodeId": f"n{i}", "actions": []} for i in range(40)]}}
    p = Persister(path, lambda: body, log=lambda line: None)
    p.start()
    t0 = time.perf_counter()
    for _ in range(200):
        p.request()  # what the control loop does: cheap, never waits for the disk
    requesting_ms = (time.perf_counter() - t0) * 1000.0
    assert p.flush()
    for _ in range(20):
        assert p.flush()
    p.close(finish=True, reason="done")
    stats = p.stats()
    print(f"200 requests {requesting_ms:.2f} ms; checkpoint writes: {stats}")
    assert requesting_ms < 50.0 and 21 <= stats["checkpoints"] < 200  # coalesced
    with Journal.open(path) as j:
        assert j.finished and j.last_checkpoint() == body


# -- end to end -------------------------------------------------------------------------------------------


def _start(config: Path, report: Path, log: Any) -> subprocess.Popen[str]:
    agv = subprocess.Popen(
        [*AGV, "--config", str(config), "--sim", str(SCENARIO), "--labels", "truth", "--report", str(report)],
        stdout=subprocess.PIPE,
        stderr=log,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    assert agv.stdout is not None
    assert agv.stdout.readline().startswith("agv ready: uagv/v2/palletpilot/0001/")
    return agv


@needs_broker
def test_a_killed_agv_continues_its_order_after_a_restart(tmp_path: Path) -> None:
    broker = Broker(tmp_path)
    broker.start()
    config = write_config(tmp_path, broker.port, state_interval_s=1.0)
    report = tmp_path / "agv"
    log = (tmp_path / "agv.log").open("w")
    master = Master(broker.port)
    agv = _start(config, report, log)
    restarted: subprocess.Popen[str] | None = None
    try:
        master.wait("a first state", lambda d: True, 30)
        master.send_order("o1", PATH, actions={3: [pick()]})
        before = master.wait("on its way from b2", lambda d: d["lastNodeId"] == "b2" and d["driving"], 40)
        agv.send_signal(signal.SIGKILL)
        agv.wait(timeout=10)
        last = master.messages("state")[-1]
        seen = len(master.received)

        restarted = _start(config, report, log)
        deadline = time.monotonic() + 20
        while not (later := [d for n, d, *_ in master.received[seen:] if n == "state"]):
            assert time.monotonic() < deadline, "no state after the restart"
            time.sleep(0.05)
        first = later[0]
        assert (first["orderId"], first["orderUpdateId"]) == ("o1", 0)
        assert first["lastNodeId"] == "b2" and first["lastNodeSequenceId"] >= before["lastNodeSequenceId"]
        assert [n["nodeId"] for n in first["nodeStates"]] == ["floor_b2_pre", "floor_b2"]
        assert [e["edgeId"] for e in first["edgeStates"]] == ["b2-floor_b2_pre", "floor_b2_pre-floor_b2"]
        assert first["headerId"] > last["headerId"]
        conns = master.wait("ONLINE again", lambda d: d["headerId"] > 1, 10, name="connection")
        assert all(c["headerId"] < conns["headerId"] for c in master.messages("connection") if c is not conns)
        assert status(first, "pick1") == "WAITING"  # it had not started: nothing ran, nothing failed
        types = {e["errorType"] for e in first["errors"]}
        assert {"orderInterrupted", "lastNodeMismatch"} <= types  # the simulator starts again at b1
        time.sleep(1.5)
        states = [d for n, d, *_ in master.received[seen:] if n == "state"]
        assert not any(d["driving"] for d in states) and states[-1]["lastNodeId"] == "b2"

        master.send_instant(action("cancelOrder", "c1"))
        s = master.wait("cancelled", lambda d: status(d, "c1") == "FINISHED", 15)
        assert s["nodeStates"] == [] and status(s, "pick1") == "FAILED" and not s["driving"]
        ids = [d["headerId"] for d in master.messages("state")[-len(states) - 2 :]]
        assert ids == sorted(ids)
        assert master.invalid == [], master.invalid[:10]

        restarted.send_signal(signal.SIGTERM)  # a clean stop with no order executing finishes the journal
        assert restarted.wait(timeout=20) == 0
        with Journal.open(report / JOURNAL_NAME) as j:
            assert j.finished and j.resumes == 1
    finally:
        for p in (agv, restarted):
            if p is not None and p.poll() is None:
                p.kill()
                p.wait()
        master.close()
        broker.stop()
        log.close()
        print((tmp_path / "agv.log").read_text()[-3000:])
