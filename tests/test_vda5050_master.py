"""End to end with an independent VDA 5050 master that no one here wrote: coatyio's `vda-5050-lib` (npm, pinned
in tests/vda_master/package-lock.json, its `MasterController` speaks VDA 5050 2.0 and validates every topic
object both ways) assigns a drive-pick-drive-drop order to `palletpilot agv --sim` on a real mosquitto broker
and follows the state until the library reports the order processed. The Node packages are installed once per
machine with `npm ci` into .cache/vda_master (never committed)."""

from __future__ import annotations

import json
import os
import shutil
import subprocess
import sys
from pathlib import Path

import pytest
from test_vda5050_agv import PATH, SCENARIO, TAIL
from test_vda5050_mqtt import MISSIONS, ROOT, Broker, action, make_order, needs_broker, write_config

HARNESS = Path(__file__).resolve().parent / "vda_master"
CACHE = ROOT / ".cache" / "vda_master"


def node_harness() -> Path:
    """The master script's folder with vda-5050-lib installed (`npm ci` once per lockfile); skips without npm."""
    node, npm = shutil.which("node"), shutil.which("npm")
    if node is None or npm is None:
        pytest.skip("needs node and npm (Debian packages nodejs, npm; `make test` installs them when root)")
    lock = (HARNESS / "package-lock.json").read_text()
    CACHE.mkdir(parents=True, exist_ok=True)
    (CACHE / ".gitignore").write_text("*\n")  # node_modules never shows up in git status
    installed = CACHE / "node_modules" / "vda-5050-lib" / "package.json"
    if not installed.exists() or (CACHE / "package-lock.json").read_text() != lock:
        for name in ("package.json", "package-lock.json"):
            shutil.copyfile(HARNESS / name, CACHE / name)
        done = subprocess.run(
            [npm, "ci", "--no-audit", "--no-fund"], cwd=CACHE, capture_output=True, text=True, timeout=300
        )
        assert done.returncode == 0, f"npm ci in {CACHE} failed: {done.stderr[-2000:]}"
    shutil.copyfile(HARNESS / "master.js", CACHE / "master.js")
    return CACHE


@needs_broker
def test_an_independent_2_0_master_runs_a_pick_and_drop_order(tmp_path: Path) -> None:
    harness = node_harness()
    broker = Broker(tmp_path)
    broker.start()
    config = write_config(tmp_path, broker.port)  # 2.1.0 by default: the AGV answers a 2.0 master in 2.0.0
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text(SCENARIO.format(map=MISSIONS / "warehouse.yaml", forks=MISSIONS / "forks.yaml"))
    pick = action("pick", "pick1", "HARD", loadType="EPAL", stationType="floor", loadId="L-0042")
    drop = action("drop", "drop1", "HARD")
    order = tmp_path / "order.json"
    order.write_text(json.dumps(make_order("m1", PATH + TAIL, actions={3: [pick], 11: [drop]})))
    log = (tmp_path / "agv.log").open("w")
    agv = subprocess.Popen(
        [
            *(sys.executable, "-m", "palletpilot.cli", "agv", "--config", str(config), "--sim", str(scenario)),
            *("--report", str(tmp_path / "agv")),
        ],
        stdout=subprocess.PIPE,
        stderr=log,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert agv.stdout is not None
        assert agv.stdout.readline().startswith("agv ready: uagv/v2/palletpilot/0001/")
        master = subprocess.run(
            ["node", str(harness / "master.js"), str(broker.port), "0001", str(order), "150"],
            cwd=harness,
            capture_output=True,
            text=True,
            timeout=180,
        )
        lines = master.stdout.strip().splitlines()
        assert lines, f"the master printed nothing: {master.stderr[-2000:]}"
        summary = json.loads(lines[-1])
        assert master.returncode == 0 and summary["processed"], (summary, master.stderr[-2000:])
        assert summary["error"] is None and not summary["byCancelation"]
        assert summary["errors"] == []
        assert summary["actions"]["pick1"][-1] == "FINISHED" and summary["actions"]["drop1"][-1] == "FINISHED"
        assert summary["loadsAfter"]["pick1"] == ["L-0042"]
        assert summary["loadsAfter"]["drop1"] == []
        assert summary["finalLoads"] == [] and summary["lastNodeId"] == "drop_pre"
        assert summary["nodesTraversed"][:2] == ["a2", "a3"] and summary["states"] > 10
    finally:
        agv.terminate()
        try:
            agv.wait(timeout=30)
        except subprocess.TimeoutExpired:
            agv.kill()
            agv.wait()
        broker.stop()
        log.close()
        print((tmp_path / "agv.log").read_text()[-3000:])
