"""End to end: `palletpilot agv --sim` as a subprocess on a real mosquitto broker, driven by a small VDA 5050
master in the test: an order with a pick at a pallet node (base up to the decision point, the drop in the
horizon), an update that stitches at the decision point and releases the drop, the broker restarted while
the truck drives (it keeps driving, reconnects and republishes its state), both actions FINISHED, every
message schema-valid, and a clean shutdown that leaves `connection` OFFLINE."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

from test_vda5050_mqtt import MISSIONS, Broker, Master, action, needs_broker, status, write_config

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
        [sys.executable, "-m", "palletpilot.cli", "agv", "--config", str(config), "--sim", str(scenario)],
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
        assert seen.index("INITIALIZING") < seen.index("RUNNING") < seen.index("FINISHED")

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
