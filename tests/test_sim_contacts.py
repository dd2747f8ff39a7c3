"""The vectorised contact tests (`sim.contacts`) against a plain pairwise separating-axis test, and the
simulator's caches (`sim.solid_cache`): never stale, rebuilt when something moved."""

import math

import numpy as np
import pytest

from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.sim.contacts import (
    LocalBoxes,
    Solid,
    SolidSet,
    box_solid,
    first_contact,
    overlap_matrix,
    overlapping,
    solid_corners,
)
from palletpilot.sim.scenario import load_scenario
from palletpilot.sim.simulator import Simulator

MISSIONS = bundled_path("missions")


def _pairwise(a: Solid, b: Solid, tol: float = 1e-3) -> bool:
    """The reference: z ranges, then the four edge normals of the two rectangles, one pair at a time."""
    if min(a.z[1], b.z[1]) - max(a.z[0], b.z[0]) <= tol:
        return False
    qa, qb = solid_corners(a), solid_corners(b)
    for quad in (qa, qb):
        for k in range(2):
            edge = quad[k + 1] - quad[k]
            axis = np.array([-edge[1], edge[0]]) / np.linalg.norm(edge)
            pa, pb = qa @ axis, qb @ axis
            if min(pa.max(), pb.max()) - max(pa.min(), pb.min()) <= tol:
                return False
    return True


def _random_solids(rng: np.random.Generator, n: int, spread: float) -> list[Solid]:
    out = []
    for i in range(n):
        x, y = rng.uniform(-spread, spread, 2)
        half = (float(rng.uniform(0.02, 1.5)), float(rng.uniform(0.02, 1.5)))
        z0 = float(rng.uniform(0.0, 1.0))
        out.append(Solid("box", str(i), SE2(x, y, rng.uniform(-math.pi, math.pi)), half, (z0, z0 + rng.uniform(0, 2))))
    return out


def test_every_pair_agrees_with_the_pairwise_separating_axes():
    rng = np.random.default_rng(4)
    parts, world = _random_solids(rng, 12, 3.0), _random_solids(rng, 60, 3.0)
    got = overlap_matrix(SolidSet.of(parts), SolidSet.of(world))
    want = np.array([[_pairwise(p, w) for w in world] for p in parts])
    assert want.sum() > 20 and (~want).sum() > 200  # both outcomes are exercised
    assert np.array_equal(got, want)


@pytest.mark.parametrize(("gap", "touching"), [(-0.002, True), (-0.0005, False), (0.0, False), (0.3, False)])
def test_the_tolerance_holds_at_the_edges(gap: float, touching: bool):
    # Two boxes side by side along x, `gap` apart (negative: overlapping by that much), the one turned
    # by 90 degrees, so the bounding boxes and the separating axes must both agree.
    a = Solid("body", "truck", SE2(0.0, 0.0, 0.0), (0.5, 0.3), (0.0, 1.0))
    b = Solid("box", "b", SE2(0.5 + 0.2 + gap, 0.0, math.pi / 2), (0.3, 0.2), (0.0, 1.0))
    assert (first_contact([a], [b]) is not None) == touching == _pairwise(a, b)
    above = Solid("box", "above", b.pose, b.half, (1.0 - 0.0005, 2.0))  # z overlap within the tolerance
    assert first_contact([a], [above]) is None


def test_first_contact_keeps_the_order_of_parts_then_solids():
    body = Solid("body", "truck", SE2(0.0, 0.0, 0.0), (1.0, 0.5), (0.0, 2.0))
    fork = Solid("left fork", "truck", SE2(1.5, 0.0, 0.0), (0.6, 0.05), (0.0, 0.05))
    far = Solid("box", "far", SE2(9.0, 0.0, 0.0), (0.2, 0.2), (0.0, 1.0))
    at_fork = Solid("box", "at fork", SE2(1.8, 0.0, 0.3), (0.1, 0.1), (0.0, 1.0))
    at_body = Solid("person", "at body", SE2(-0.9, 0.0, 0.0), (0.13, 0.31), (0.0, 1.75))
    contact = first_contact([body, fork], [far, at_fork, at_body])
    assert contact is not None and (contact.part, contact.solid.id) == ("body", "at body")
    assert [s.id for s in overlapping(fork, [at_body, far, at_fork])] == ["at fork"]
    assert first_contact([], [far]) is None and first_contact([body], []) is None


def test_boxes_placed_from_a_moving_frame_are_the_solids_of_that_pose():
    rng = np.random.default_rng(1)
    lo = rng.uniform(-2.0, 0.0, (5, 3))
    hi = lo + rng.uniform(0.05, 2.0, (5, 3))
    pose = SE2(3.2, -1.7, 2.5)
    placed = LocalBoxes.of(["part"] * 5, lo, hi).placed(pose)
    solids = SolidSet.of([box_solid("part", str(k), pose, lo[k], hi[k]) for k in range(5)])
    assert np.allclose(placed.corners, solids.corners, atol=1e-12)
    assert np.allclose(placed.lo, solids.lo, atol=1e-12) and np.allclose(placed.hi, solids.hi, atol=1e-12)
    assert np.allclose(np.abs(placed.axes), np.abs(solids.axes), atol=1e-12)  # the same axes, either sign


def test_the_world_is_kept_between_steps_and_rebuilt_when_a_pallet_moves():
    sim = Simulator(load_scenario(MISSIONS / "scenario_floor.yaml"))
    world = sim._world_solids()
    sim.step()
    assert sim._world_solids() is world  # nothing moved: the same arrays
    pallet = sim.pallets[0]
    before = world.solids.corners[world.solids.kinds.index("pallet")].copy()
    pallet.T_world_pallet = SE3.from_translation(0.5, 0.0, 0.0) @ pallet.T_world_pallet
    moved = sim._world_solids()
    assert moved is not world
    assert np.allclose(moved.solids.corners[moved.solids.kinds.index("pallet")], before + np.array([0.5, 0.0]))
    assert moved.pallet.sum() == len(sim.pallets)  # the pallet boxes, not their loads
    assert len(moved.solids) == len(sim._fixed_solids) + len(sim.pallets) + sum(p.loaded for p in sim.pallets)
