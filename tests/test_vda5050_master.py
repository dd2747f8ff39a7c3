"""End to end with an independent VDA 5050 master that no one here wrote: coatyio's `vda-5050-lib` (npm, pinned
in tests/vda_master/package-lock.json, its `MasterController` speaks VDA 5050 2.0 and validates every topic
object both ways) assigns a drive-pick-drive-drop order to `palletpilot agv --sim` on a real mosquitto broker
and follows the state until the library reports the order processed. The Node packages are installed once per
machine with `npm ci` into .cache/vda_master (never committed)."""

from __future__ import annotations

import json
import os
import shutil
import signal
import subprocess
import sys
from pathlib import Path
from typing import Any

import pytest
from test_vda5050_agv import AGV, PATH, SCENARIO, TAIL
from test_vda5050_mqtt import MISSIONS, ROOT, Broker, action, make_order, needs_broker, write_config
from vda_master.bridge_v3 import Bridge

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
        assert "INITIALIZING" not in summary["actions"]["pick1"] + summary["actions"]["drop1"]  # WAITING to the node
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


# -- scenarios of issue 39, the AGV's simulator at up to 4x real time (--sim-speed 4) ----------------------------

START = """\
map: {map}
forks: {forks}
seed: 11
start: {start}
pallets:
  - {{node: floor_a3}}
"""


def run_scenario(
    tmp_path: Path, start: str, steps: list[dict[str, Any]], timeout_s: int = 150, version: str = "2.1.0"
) -> dict[str, Any]:
    """`palletpilot agv --sim --sim-speed 4` from roadmap node `start`, the independent master running `steps`
    (master.js); its summary, after the AGV ended cleanly. With `version` 3.0.0 the AGV speaks 3.0 and the
    master's messages go through `vda_master/bridge_v3.Bridge` both ways; the summary then has the bridge's
    `bridge_problems` (schema problems, both sides) and `bridge_counts` (messages per direction and topic)."""
    harness = node_harness()
    broker = Broker(tmp_path)
    broker.start()
    v3 = version.startswith("3.")
    extra: dict[str, Any] = {"protocol_version": version, "interface_name": None} if v3 else {}
    config = write_config(tmp_path, broker.port, **extra)
    bridge = Bridge(broker.port) if v3 else None
    scenario = tmp_path / "scenario.yaml"
    scenario.write_text(START.format(map=MISSIONS / "warehouse.yaml", forks=MISSIONS / "forks.yaml", start=start))
    (tmp_path / "steps.json").write_text(json.dumps({"steps": steps}))
    log = (tmp_path / "agv.log").open("w")
    agv = subprocess.Popen(
        [
            *AGV,
            "--config",
            str(config),
            "--sim",
            str(scenario),
            "--sim-speed",
            "4",
            "--labels",
            "truth",
            "--report",
            str(tmp_path / "agv"),
        ],
        stdout=subprocess.PIPE,
        stderr=log,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
    )
    try:
        assert agv.stdout is not None
        prefix = "vda5050/v3" if v3 else "uagv/v2"
        assert agv.stdout.readline().startswith(f"agv ready: {prefix}/palletpilot/0001/")
        master = subprocess.run(
            [
                "node",
                str(harness / "master.js"),
                str(broker.port),
                "0001",
                str(tmp_path / "steps.json"),
                str(timeout_s),
            ],
            cwd=harness,
            capture_output=True,
            text=True,
            timeout=timeout_s + 30,
        )
        lines = master.stdout.strip().splitlines()
        assert lines, f"the master printed nothing: {master.stderr[-2000:]}"
        summary: dict[str, Any] = json.loads(lines[-1])
        assert agv.poll() is None, f"the AGV exited with {agv.returncode}"
        agv.send_signal(signal.SIGTERM)
        assert agv.wait(timeout=30) == 0
        if bridge is not None:
            summary["bridge_problems"], summary["bridge_counts"] = bridge.problems, bridge.counts
        return summary
    finally:
        if agv.poll() is None:
            agv.kill()
            agv.wait()
        if bridge is not None:
            bridge.close()
        broker.stop()
        log.close()
        print((tmp_path / "agv.log").read_text()[-3000:])


@needs_broker
def test_master_a_new_order_from_the_drop_node_while_the_truck_waits_to_back_out(tmp_path: Path) -> None:
    """The crash of issue 39 (exit 70, KeyError): the order ends at `drop`, the next starts there (openTCS)."""
    pick = action("pick", "pick1", "HARD", loadType="EPAL", stationType="floor", loadId="L-0042")
    drop = action("drop", "drop1", "HARD")
    first = make_order("m1", [*PATH, "drop_pre", "drop"], actions={3: [pick], 11: [drop]})
    summary = run_scenario(
        tmp_path, "a2", [{"order": first}, {"order": make_order("m2", ["drop", "drop_pre", "j_drop"])}]
    )
    assert summary["processed"] and [s["processed"] for s in summary["steps"]] == [True, True], summary
    assert summary["steps"][0]["lastNodeId"] == "drop" and summary["steps"][1]["lastNodeId"] == "j_drop"
    assert summary["errors"] == [] and not summary["driving"]


def restart_steps(start: str, path: list[str], cancel_at: str, rest: list[str], how: str, at: tuple[float, float]):
    first = make_order("r2", [path[0] if how == "last" else "here", *rest])
    first["nodes"][0]["nodePosition"] = {"x": at[0], "y": at[1], "mapId": "warehouse"}
    return [{"order": make_order("r1", path), "cancelAtNode": cancel_at}, {"order": first, "restart": how}]


@needs_broker
@pytest.mark.parametrize(
    ("how", "start", "path", "rest", "end"),
    [
        ("last", "b_bot", ["b_bot", "b1", "b2", "b3"], ["b2", "b3"], "b3"),  # a straight edge, last node passed
        ("here", "b_bot", ["b_bot", "b1", "b2", "b3"], ["b2", "b3"], "b3"),  # a temporary node at the truck
        ("last", "a3", ["a3", "a_bot", "c_w", "j_charge"], ["c_w", "j_charge"], "j_charge"),  # on the arc
    ],
)
def test_master_restarts_after_a_cancel_part_way_along_an_edge(
    tmp_path: Path, how: str, start: str, path: list[str], rest: list[str], end: str
) -> None:
    """Section 6.6.3.1, both ways: cancelOrder once the second node is passed, then the new order."""
    cancel_at = path[1]
    roadmap_xy = {"b1": (20.0, 5.0), "a_bot": (6.0, 3.0)}[cancel_at]
    steps = restart_steps(start, [cancel_at, *path[2:]], cancel_at, rest, how, roadmap_xy)
    steps[0]["order"] = make_order("r1", path)
    summary = run_scenario(tmp_path, start, steps)
    cancelled, restarted = summary["steps"]
    assert cancelled["byCancelation"] and cancelled["lastNodeId"] == cancel_at, cancelled
    assert restarted["processed"] and restarted["error"] is None and restarted["lastNodeId"] == end, summary
    assert not summary["driving"] and not [e for e in summary["errors"] if "controllerError" in e], summary["errors"]
