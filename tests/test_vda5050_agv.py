"""End to end: `palletpilot agv --sim` as a subprocess on a real mosquitto broker, driven by a small VDA 5050
master in the test: an order with a pick at a pallet node (base up to the decision point, the drop in the
horizon), an update that stitches at the decision point and releases the drop, the broker restarted while
the truck drives (it keeps driving, reconnects and republishes its state), both actions FINISHED, every
message schema-valid, and a clean shutdown that leaves `connection` OFFLINE and a finished `run.mcap`.

In process, without a broker (the master's messages handed to `Agv.on_message`): a short order's session
recorded to one `run.mcap` (channels, events, `palletpilot replay` on it; a killed session's file)."""

from __future__ import annotations

import contextlib
import json
import os
import shutil
import signal
import subprocess
import sys
import threading
import time
from pathlib import Path

import pytest
from mcap.exceptions import McapError
from mcap.records import Channel, Message
from mcap.stream_reader import StreamReader
from test_vda5050_mqtt import (
    MISSIONS,
    Broker,
    Master,
    action,
    make_order,
    needs_broker,
    status,
    write_config,
)

from palletpilot.cli import main
from palletpilot.executor.adapters.mcap.recording import RECORDING
from palletpilot.executor.adapters.mcap.replay import read_recording
from palletpilot.executor.apps.vda5050 import validation

AGV = [sys.executable, "-m", "palletpilot.cli", "agv"]
PATH = ["a2", "a3", "floor_a3_pre", "floor_a3", "floor_a3_pre", "a3", "a_bot", "c_w", "j_charge", "j_drop"]
TAIL = ["drop_pre", "drop", "drop_pre"]
SCENARIO = """\
map: {map}
forks: {forks}
seed: 11
start: a2
camera:
  mount: {{x: -0.10, y: 0.0, z: 0.45, tilt_deg: 22, pan_deg: 0.5, roll_deg: -0.3}}
  perturbation: {{xyz_sigma: 0.002, angle_sigma_deg: 0.2}}
  noise: {{depth_noise: true, invalid_rate: 0.005, flying_pixel_rate: 0.5, label_noise: true, label_noise_px: 2}}
noise: {{localization_xy_sigma: 0.003, localization_yaw_sigma_deg: 0.05}}
pallets:
  - {{node: floor_a3}}
"""


@needs_broker
def test_pick_and_drop_order_through_a_broker_restart(tmp_path: Path) -> None:
    broker = Broker(tmp_path)
    broker.start()
    config = write_config(tmp_path, broker.port, visualization_hz=1.0)
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text(SCENARIO.format(map=MISSIONS / "warehouse.yaml", forks=MISSIONS / "forks.yaml"))
    log = (tmp_path / "agv.log").open("w")
    agv = subprocess.Popen(
        [*AGV, "--config", str(config), "--sim", str(scenario), "--report", str(tmp_path / "agv")],
        stdout=subprocess.PIPE,
        stderr=log,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    master = Master(broker.port)
    try:
        assert agv.stdout is not None
        assert agv.stdout.readline().startswith("agv ready: uagv/v2/palletpilot/0001/")
        master.wait("ONLINE", lambda d: d["connectionState"] == "ONLINE", 60, name="connection")
        master.wait("a first state", lambda d: True, 30)

        pick = action("pick", "pick1", "HARD", loadType="EPAL", stationType="floor", loadId="L-0042")
        drop = action("drop", "drop1", "HARD")
        path = PATH + TAIL
        master.send_order("t1", path, actions={3: [pick], 11: [drop]}, released=6)  # base up to a3
        s = master.wait("the order", lambda d: d["orderId"] == "t1", 20)
        assert [n["released"] for n in s["nodeStates"]].count(False) == len(path) - 6
        assert status(s, "drop1") == "WAITING"

        s = master.wait("the pick", lambda d: status(d, "pick1") in ("FINISHED", "FAILED"), 120)
        assert status(s, "pick1") == "FINISHED", s["errors"]
        loads = master.wait("the load", lambda d: bool(d["loads"]), 10)["loads"]
        assert loads[0]["loadId"] == "L-0042" and loads[0]["loadType"] == "eur"
        seen = [status(d, "pick1") for d in master.messages("state")]
        assert "INITIALIZING" not in seen and seen.index("WAITING") < seen.index("RUNNING") < seen.index("FINISHED")
        running = [d for d in master.messages("state") if status(d, "pick1") == "RUNNING"]
        assert all(d["lastNodeId"] == "floor_a3" and not d["driving"] for d in running)  # at its node, standing

        # the decision point is a3: release the rest, stitching there (its sequenceId is 10)
        master.send_order("t1", path[5:], update=1, seq0=10, actions={6: [drop]})
        master.wait("the update", lambda d: d["orderUpdateId"] == 1 and all(n["released"] for n in d["nodeStates"]), 20)

        master.wait("the truck on its way", lambda d: d["lastNodeId"] in ("a_bot", "c_w") and d["driving"], 90)
        before = master.state()
        assert before is not None
        broker.stop()  # the broker goes away while the truck drives
        time.sleep(3.0)
        broker.start()
        online = master.wait(
            "ONLINE after the restart",
            lambda d: d["connectionState"] == "ONLINE" and d["headerId"] > 1,
            60,
            "connection",
        )
        assert online["headerId"] >= 2  # the will of the new connection and a new ONLINE
        after = master.wait("a state after the restart", lambda d: d["headerId"] > before["headerId"], 30)
        assert after["orderId"] == "t1"

        s = master.wait("the drop", lambda d: status(d, "drop1") in ("FINISHED", "FAILED"), 150)
        assert status(s, "drop1") == "FINISHED", s["errors"]
        s = master.wait(
            "the end of the order", lambda d: d["orderUpdateId"] == 1 and not d["nodeStates"] and not d["driving"], 30
        )
        assert s["lastNodeId"] == "drop_pre" and s["loads"] == [] and s["errors"] == []
        assert abs(s["agvPosition"]["x"] - 15.5) < 0.2 and abs(s["agvPosition"]["y"] + 1.5) < 0.2

        ids = [d["headerId"] for d in master.messages("state")]
        assert ids == sorted(ids) and len(set(ids)) == len(ids)
        assert master.invalid == [], master.invalid[:10]
        assert len(master.messages("state")) > 20 and master.messages("visualization")

        agv.send_signal(signal.SIGTERM)
        assert agv.wait(timeout=30) == 0
        # the session's recording, finished on SIGTERM: every leg's task (the Delivery may still have been
        # finishing its last state when the signal came: then it is cancelled)
        results = read_recording(tmp_path / "agv" / RECORDING).run["results"]
        tasks = [(r["type"], r["reason"]) for r in results]
        assert tasks[:3] == [("move", None), ("pickup", None), ("move", None)], tasks
        assert tasks[3:] in ([("delivery", None)], [("delivery", "cancelled")]), tasks
        late = Master(broker.port)
        try:
            assert late.wait("OFFLINE", lambda d: True, 10, name="connection")["connectionState"] == "OFFLINE"
        finally:
            late.close()
    finally:
        if agv.poll() is None:
            agv.kill()
            agv.wait()
        master.close()
        broker.stop()
        log.close()
        print((tmp_path / "agv.log").read_text()[-3000:])


# -- the session's recording (in process, no broker: the master's messages handed in directly) -----------


def advertised(port: int | None) -> set[str]:
    """The topics a Foxglove WebSocket server on 127.0.0.1:`port` advertises."""
    from websockets.sync.client import connect

    seen: set[str] = set()
    with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=5) as ws:
        for _ in range(10):
            msg = ws.recv(timeout=5)
            doc = json.loads(msg) if isinstance(msg, str) else {}
            if doc.get("op") == "advertise":
                seen |= {ch["topic"] for ch in doc["channels"]}
                if "/vehicle/state" in seen:
                    break
    return seen


def test_an_agv_session_is_recorded_to_one_run_mcap(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    """A short order (b_bot -> b1, 2 m, one move leg) on the simulated warehouse: after the AGV's normal shutdown
    run.mcap decodes with the run's channels, the truck and tf recorded through the session, the order and
    the leg as events; `palletpilot replay` gives the session's report (the leg's Move task)."""
    from test_recording import read_mcap

    from palletpilot.executor.adapters.mcap.recording import Recorder
    from palletpilot.executor.apps.vda5050.agv import Agv
    from palletpilot.executor.apps.vda5050.config import load_config
    from palletpilot.executor.apps.vda5050.vehicle import sim_backend

    loaded = load_config(write_config(tmp_path, 1883))  # never connected
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text(
        f"map: {MISSIONS / 'warehouse.yaml'}\nforks: {MISSIONS / 'forks.yaml'}\nseed: 3\nstart: b_bot\n"
    )
    backend = sim_backend(loaded, scenario, labels="truth")
    backend.follower.mpc.solve_deadline_s = None  # about the recording: a loaded machine must not fail the leg
    recorder = Recorder(tmp_path / RECORDING, port=0, wall=True, flush_s=1.0)  # and live, on any free port
    the_agv = Agv(loaded, backend, recorder=recorder)
    thread = threading.Thread(target=the_agv.run, daemon=True)
    thread.start()
    try:
        head = {"headerId": 1, "timestamp": validation.Stamper()(), "version": "2.1.0"}
        head |= {"manufacturer": "palletpilot", "serialNumber": "0001"}
        the_agv.on_message("order", json.dumps({**head, **make_order("rec1", ["b_bot", "b1"])}).encode())
        deadline = time.monotonic() + 30.0
        while not the_agv.legs and time.monotonic() < deadline:
            time.sleep(0.05)
        live = advertised(recorder.port)
        time.sleep(0.3)  # a few ticks of standing still after the leg
        shutil.copy(tmp_path / RECORDING, tmp_path / "killed.mcap")  # the file as a crash would leave it
    finally:
        the_agv.stop()
        thread.join(timeout=10)
        errors = the_agv.finish_recording()
        backend.close()
    assert errors == [] and [leg["ok"] for leg in the_agv.legs] == [True], the_agv.legs
    assert {"/tf", "/vehicle/state", "/scene/truck", "/log", "/events"} <= live

    rec = read_mcap(tmp_path / RECORDING)
    counts = {topic: len(m) for topic, m in rec["messages"].items()}
    assert counts["/tf"] > 20 and counts["/vehicle/state"] > 20 and counts["/scene/truck"] >= 1
    assert counts["/roadmap/graph"] == 1 and counts["/scene/roadmap"] == 1 and counts["/report/run"] == 1
    events = [doc["event"] for _, doc in rec["messages"]["/events"]]
    assert events.index("order_accepted") < events.index("leg_start") < events.index("task_start")
    assert events.index("task_end") < events.index("leg_end")
    run = rec["messages"]["/report/run"][0][1]
    assert run["success"] and [r["type"] for r in run["results"]] == ["move"]
    assert rec["metadata"]["palletpilot"]["session"] and "recording_cost" in rec["metadata"]
    xy = [(d["x_m"], d["y_m"]) for _, d in rec["messages"]["/vehicle/state"] if d["x_m"] is not None]
    assert abs(xy[0][1] - 3.0) < 0.2 and abs(xy[-1][1] - 5.0) < 0.2  # from b_bot to b1

    assert main(["replay", str(tmp_path / RECORDING), "--report", str(tmp_path / "replayed")]) == 0
    report = json.loads((tmp_path / "replayed" / "report.json").read_text())
    assert report["success"] and [t["type"] for t in report["tasks"]] == ["move"] and report["legs"]
    assert "replayed" in capsys.readouterr().out

    # killed before the end: no summary and an open chunk, but the flushed chunks read in order (a streaming
    # reader stops at the open one); replay needs the summary and the session report, and refuses in one line
    topics: dict[int, str] = {}
    seen: list[str] = []
    with (tmp_path / "killed.mcap").open("rb") as f, contextlib.suppress(McapError):
        for record in StreamReader(f).records:
            if isinstance(record, Channel):
                topics[record.id] = record.topic
            elif isinstance(record, Message):
                seen.append(topics[record.channel_id])
    assert seen.count("/tf") > 10 and "/roadmap/graph" in seen
    assert main(["replay", str(tmp_path / "killed.mcap"), "--report", str(tmp_path / "no")]) == 2
    err = capsys.readouterr().err.strip()
    assert len(err.splitlines()) == 1 and "killed.mcap" in err, err
