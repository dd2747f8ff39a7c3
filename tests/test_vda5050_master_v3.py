"""The independent master's scenarios (test_vda5050_master.py) against a 3.0.0 AGV: no public VDA 5050 3.0
master exists, so coatyio's 2.0 master speaks to `palletpilot agv` configured with `protocol_version: 3.0.0`
through `vda_master/bridge_v3.Bridge`, which translates every message both ways and checks each against the
3.0.0 schemas on the AGV's side and the 2.1.0 ones on the master's."""

from __future__ import annotations

from pathlib import Path
from typing import Any

import pytest
from test_vda5050_agv import PATH, TAIL
from test_vda5050_master import restart_steps, run_scenario
from test_vda5050_mqtt import action, make_order, needs_broker

V3 = "3.0.0"


def bridged(summary: dict[str, Any]) -> None:
    """Every bridged message schema-valid on both sides, and messages in both directions."""
    assert summary["bridge_problems"] == [], summary["bridge_problems"][:10]
    counts = summary["bridge_counts"]
    assert counts.get("to AGV 3.0 order", 0) >= 1 and counts.get("to master 2.0 state", 0) > 10, counts


@needs_broker
def test_v3_a_pick_and_drop_order(tmp_path: Path) -> None:
    pick = action("pick", "pick1", "HARD", loadType="EPAL", stationType="floor", loadId="L-0042")
    drop = action("drop", "drop1", "HARD")
    order = make_order("m1", PATH + TAIL, actions={3: [pick], 11: [drop]})
    summary = run_scenario(tmp_path, "a2", [{"order": order}], version=V3)
    bridged(summary)
    (step,) = summary["steps"]
    assert summary["processed"] and step["processed"] and step["error"] is None, summary
    assert summary["errors"] == [] and step["actions"]["pick1"][-1] == "FINISHED"
    assert step["actions"]["drop1"][-1] == "FINISHED"
    assert "INITIALIZING" not in step["actions"]["pick1"] + step["actions"]["drop1"]
    assert summary["loadsAfter"]["pick1"] == ["L-0042"] and summary["loadsAfter"]["drop1"] == []
    assert summary["finalLoads"] == [] and summary["lastNodeId"] == "drop_pre"


@needs_broker
def test_v3_a_new_order_from_the_drop_node_while_the_truck_waits_to_back_out(tmp_path: Path) -> None:
    pick = action("pick", "pick1", "HARD", loadType="EPAL", stationType="floor", loadId="L-0042")
    drop = action("drop", "drop1", "HARD")
    first = make_order("m1", [*PATH, "drop_pre", "drop"], actions={3: [pick], 11: [drop]})
    steps = [{"order": first}, {"order": make_order("m2", ["drop", "drop_pre", "j_drop"])}]
    summary = run_scenario(tmp_path, "a2", steps, version=V3)
    bridged(summary)
    assert summary["processed"] and [s["processed"] for s in summary["steps"]] == [True, True], summary
    assert summary["steps"][1]["lastNodeId"] == "j_drop" and summary["errors"] == [] and not summary["driving"]


@needs_broker
@pytest.mark.parametrize(
    ("how", "start", "path", "rest", "end"),
    [
        ("last", "b_bot", ["b_bot", "b1", "b2", "b3"], ["b2", "b3"], "b3"),
        ("here", "b_bot", ["b_bot", "b1", "b2", "b3"], ["b2", "b3"], "b3"),
        ("last", "a3", ["a3", "a_bot", "c_w", "j_charge"], ["c_w", "j_charge"], "j_charge"),
    ],
)
def test_v3_restarts_after_a_cancel_part_way_along_an_edge(
    tmp_path: Path, how: str, start: str, path: list[str], rest: list[str], end: str
) -> None:
    cancel_at = path[1]
    roadmap_xy = {"b1": (20.0, 5.0), "a_bot": (6.0, 3.0)}[cancel_at]
    steps = restart_steps(start, [cancel_at, *path[2:]], cancel_at, rest, how, roadmap_xy)
    steps[0]["order"] = make_order("r1", path)
    summary = run_scenario(tmp_path, start, steps, version=V3)
    bridged(summary)
    cancelled, restarted = summary["steps"]
    assert cancelled["byCancelation"] and cancelled["lastNodeId"] == cancel_at, cancelled
    assert restarted["processed"] and restarted["error"] is None and restarted["lastNodeId"] == end, summary
    assert not summary["driving"] and not [e for e in summary["errors"] if "controllerError" in e], summary["errors"]
