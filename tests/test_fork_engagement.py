"""Minimum fork engagement (issue 40): a rack pallet deeper than its node is taken while the forks carry the
pallet type's share of its depth (default two thirds) and its balance holds (the load's centre of mass
inside the fork tips, with margin); otherwise the failure says how deep the tips could reach."""

from __future__ import annotations

import json
import math
from pathlib import Path

import pytest
from test_executor_missions import run, scenario

from palletpilot.executor.core.engagement import engagement_problems, tip_depth
from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.specs import PalletType, load_forks

FORKS = load_forks(bundled_path("missions", "forks.yaml"))


def test_the_engagement_rule_and_the_balance() -> None:
    eur = PalletType.eur()
    need, why = eur.required_engagement()
    assert need == pytest.approx(0.8) and "min_fork_engagement" in why  # two thirds of 1200 mm
    # Half the depth would put the load's middle over the tips: the balance margin asks for more.
    lenient = PalletType(min_fork_engagement=0.5, balance_margin=0.1)
    need, why = lenient.required_engagement()
    assert need == pytest.approx(0.7) and "centre of mass at 600 mm" in why
    # The truck's heels 0.05 m before the face: the tips 1100 mm in; 0.42 m further back, 680 mm.
    assert tip_depth(FORKS, SE2(-0.05, 0.0, 0.0)) == pytest.approx(1.10)
    assert engagement_problems(FORKS, lenient, SE2(-0.05, 0.0, 0.0), margin=0.01) == []
    problems = engagement_problems(FORKS, lenient, SE2(-0.47, 0.0, 0.0), margin=0.01)
    assert len(problems) == 1 and "reach 680 mm" in problems[0] and "it needs 700 mm" in problems[0], problems
    # A yawed truck: the shallower tip counts.
    assert tip_depth(FORKS, SE2(-0.05, 0.0, 0.05)) < 1.10 * 0.999


def test_a_rack_pallet_200_mm_deeper_than_its_node_is_taken(tmp_path: Path) -> None:
    # Issue 40: 200 mm deeper, 0.28 m to the side and 8 deg turned, loaded: `no_feasible_approach` before
    # (the tips 101 mm short of the back blocks); the forks now carry about 1000 of its 1200 mm.
    sc = scenario("a1", [{"node": "rack_a2", "dx": 0.20, "dy": 0.28, "dyaw_deg": 8.0, "loaded": True}])
    r = run(tmp_path, [{"type": "pickup", "node": "rack_a2"}], sc)
    result = r.runner.results[0]
    assert r.success and r.sim.pallets[0].carried, result.message
    assert r.sim.collisions == []
    record = json.loads(Path(r.report).read_text())["tasks"][0]
    engagement = record["engagement"][-1]
    assert engagement["enough"] and engagement["required_mm"] == pytest.approx(800.0)
    assert 850.0 < engagement["reach_mm"] < 1100.0, engagement


def test_a_turned_pallet_is_held_back_until_the_masts_leading_corner_clears_the_beam() -> None:
    # Issue 40, the envelope at +-15 deg: a pallet 0.09 m deeper and 15 deg turned needs no hold-back by the
    # heels alone (0.10 m allowed), but the turned mast's front corner, 0.55 m to the side, leads by
    # 0.55 sin 15 deg = 0.14 m: without more hold-back it met the rack's front beam in the simulator.
    from types import SimpleNamespace

    from palletpilot.control.vehicle import load_vehicle
    from palletpilot.executor.core.behaviour import Settings, TaskMemory
    from palletpilot.executor.core.engagement import rack_limited_pose
    from palletpilot.executor.core.mission import PickupTask
    from palletpilot.roadmap import Node, NodeType

    node = Node("r", NodeType.PALLET, SE2(0.0, 0.0, 0.0), height=1.0, pre_pallet="r_pre")
    params = load_vehicle(bundled_path("missions", "forklift.yaml"))
    memory = TaskMemory(at_node="r_pre", heading=0.0, task=PickupTask(type="pickup", node="r"))
    ctx = SimpleNamespace(
        roadmap=SimpleNamespace(node=lambda _id: node),
        memory=memory,
        settings=Settings(),
        params=params,
        forks=FORKS,
        pallet_type=PalletType.eur(),
        log=lambda *a, **k: None,
    )
    straight = rack_limited_pose(ctx, SE2(0.09, 0.0, 0.0))  # type: ignore[arg-type]
    assert straight.x == pytest.approx(0.09)  # the heels' 0.10 m allowance covers it
    turned = rack_limited_pose(ctx, SE2(0.09, 0.0, math.radians(15.0)))  # type: ignore[arg-type]
    body = params.body
    corner = turned.x + body.front_x * math.cos(turned.yaw) + 0.5 * body.width * abs(math.sin(turned.yaw))
    assert corner <= Settings.rack_overrun + body.front_x + 1e-6  # no further than the straight mast's front
    assert turned.x < 0.09 - 0.1  # held back along the pallet's axis by about 0.14 m
    # Deeper still, the forks would carry too little: the refusal says the turn took its share.
    from palletpilot.executor.core.errors import TaskFailed

    with pytest.raises(TaskFailed, match=r"may go 100 mm past it \(146 mm less turned \+15 deg\)"):
        rack_limited_pose(ctx, SE2(0.35, 0.0, math.radians(15.0)))  # type: ignore[arg-type]
