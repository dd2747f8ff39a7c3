"""The Pickup's checks that keep it on the mission's pallet: the envelope around the node, estimates
that jump to another object, and forks that would pass beside their pockets although the beams are clear."""

from __future__ import annotations

import math
from types import SimpleNamespace

import pytest

from palletpilot.executor.core.behaviour import Settings, TaskMemory
from palletpilot.executor.core.errors import TaskFailed
from palletpilot.executor.core.mission import PickupTask
from palletpilot.executor.core.pickup import _check_envelope, forks_outside_pockets
from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.specs import PalletType, load_forks, pallet_pose_at_node
from palletpilot.roadmap import load_map

MISSIONS = bundled_path("missions")
ROADMAP = load_map(MISSIONS / "warehouse.yaml")


def ctx(node: str = "floor_b2") -> SimpleNamespace:
    return SimpleNamespace(
        roadmap=ROADMAP,
        memory=TaskMemory("", 0.0, task=PickupTask(type="pickup", node=node)),
        settings=Settings(),
        forks=load_forks(MISSIONS / "forks.yaml"),
        pallet_type=PalletType.eur(),
    )


def nominal(node: str = "floor_b2") -> SE2:
    n = ROADMAP.node(node)
    return pallet_pose_at_node(n.pose, n.height).to_se2()


@pytest.mark.parametrize(
    ("offset", "accepted"),
    [
        (SE2(0.30, -0.30, math.radians(10.0)), True),  # misplaced, but the mission's pallet
        (SE2(0.42, 0.38, math.radians(15.5)), True),  # at the envelope's corner, estimated a little past it
        (SE2(0.0, 0.44, 0.0), False),  # past the estimate's tolerance
        (SE2(0.0, 0.0, math.radians(16.5)), False),
        (SE2(0.0, 1.0, 0.0), False),  # the neighbour 1.0 m to the side
        (SE2(0.0, -0.45, 0.0), False),
        (SE2(0.5, 0.0, 0.0), False),
        (SE2(0.0, 0.0, math.radians(20.0)), False),
    ],
)
def test_an_estimate_outside_the_envelope_is_not_the_missions_pallet(offset: SE2, accepted: bool) -> None:
    seen = nominal() @ offset
    if accepted:
        _check_envelope(ctx(), seen, None)  # type: ignore[arg-type]
        return
    with pytest.raises(TaskFailed) as info:
        _check_envelope(ctx(), seen, None)  # type: ignore[arg-type]
    assert info.value.reason == "pallet_not_found" and "not the mission's pallet" in str(info.value)
    assert "floor_b2" in str(info.value)


def test_an_estimate_that_jumps_is_another_object() -> None:
    first = nominal() @ SE2(0.05, 0.10, 0.0)
    _check_envelope(ctx(), first @ SE2(0.02, -0.03, 0.01), first.to_se3())  # type: ignore[arg-type]
    with pytest.raises(TaskFailed) as info:
        _check_envelope(ctx(), first @ SE2(0.0, -0.30, 0.0), first.to_se3())  # type: ignore[arg-type]
    assert info.value.reason == "pallet_not_found" and "jumped 0.30 m" in str(info.value)


def test_forks_beside_the_pockets_are_caught_even_when_both_beams_would_read_clear() -> None:
    c = ctx()
    pallet = SE2(3.0, 0.0, 0.0)  # entry face 3 m ahead, square to the truck
    assert forks_outside_pockets(c, pallet, SE2(0.0, 0.0, 0.0)) == []  # type: ignore[arg-type]
    assert forks_outside_pockets(c, pallet, SE2(0.0, 0.02, 0.0)) == []  # type: ignore[arg-type]  # within clearance
    # 0.30 m to the side: the right fork's beam runs through the left pocket, the left one beside the pallet.
    problems = forks_outside_pockets(c, pallet, SE2(0.0, 0.30, 0.0))  # type: ignore[arg-type]
    assert len(problems) == 2 and "left fork would pass" in problems[0]
    # Turned 3 deg: square at the face, but the tips swing out of the pockets deeper in.
    assert forks_outside_pockets(c, pallet, SE2(0.0, 0.0, math.radians(3.0)))  # type: ignore[arg-type]
