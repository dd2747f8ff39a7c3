"""Curves, the planner, reference paths, overlays and curve synthesis."""

import itertools
import math

import networkx as nx
import numpy as np
import pytest

from palletpilot.bench.roadmap import warehouse_grid
from palletpilot.control import load_vehicle
from palletpilot.geometry import SE2, angle_diff
from palletpilot.geometry.fileio import bundled_path
from palletpilot.roadmap import (
    Arc,
    CubicBezier,
    Direction,
    Edge,
    Line,
    Node,
    NodeType,
    Planner,
    RoadmapError,
    connect,
    load_map,
    reference_path,
)

MISSIONS = bundled_path("missions")


@pytest.fixture(scope="module")
def warehouse():
    return load_map(MISSIONS / "warehouse.yaml")


@pytest.fixture(scope="module")
def max_curvature():
    return load_vehicle(MISSIONS / "forklift.yaml").max_curvature


# -- curves ------------------------------------------------------------------------------


def test_arc_geometry():
    arc = Arc(SE2(0.0, 0.0, 0.0), (3.0, 3.0))  # quarter circle of radius 3 turning left
    assert arc.radius == pytest.approx(3.0)
    assert arc.length == pytest.approx(1.5 * math.pi)
    assert arc.end_pose.isclose(SE2(3.0, 3.0, math.pi / 2), atol=1e-9, atol_yaw=1e-9)
    smp = arc.sample(np.linspace(0, arc.length, 50))
    assert np.allclose(np.hypot(smp.x - 0.0, smp.y - 3.0), 3.0)  # centre at (0, 3)
    assert np.allclose(smp.curvature, 1 / 3)
    back = arc.reversed()
    assert back.start_pose.isclose(SE2(3.0, 3.0, -math.pi / 2), atol=1e-9, atol_yaw=1e-9)
    assert back.curvature == pytest.approx(-1 / 3)


def test_arc_on_the_start_tangent_is_refused():
    with pytest.raises(RoadmapError, match="use a line"):
        Arc(SE2(0, 0, 0), (5.0, 0.0))


def test_bezier_length_and_curvature():
    bez = CubicBezier((0, 0), (1, 0), (2, 1), (3, 1))
    t = np.linspace(0, 1, 20001)
    pts = bez._point(t)
    assert bez.length == pytest.approx(np.sum(np.hypot(*np.diff(pts, axis=0).T)), rel=1e-6)
    # Curvature against a finite difference of the sampled heading.
    s = np.linspace(0.1, bez.length - 0.1, 400)
    smp = bez.sample(s)
    dh = np.gradient(np.unwrap(smp.heading), s)
    assert np.allclose(smp.curvature, dh, atol=2e-3)
    assert bez.reversed().start_pose.isclose(SE2(3, 1, math.pi), atol=1e-9, atol_yaw=1e-9)


# -- planner -----------------------------------------------------------------------------


def test_route_over_curves_into_a_pallet_node(warehouse):
    route = Planner(warehouse).plan("charger", "rack_b3")
    assert route.nodes[0] == "charger" and route.nodes[-1] == "rack_b3"
    assert route.nodes[-2] == "rack_b3_pre"  # the pallet is entered from its pre-pallet node
    kinds = {e.curve.kind for e in route.edges}
    assert {"arc", "line"} <= kinds
    assert route.edges[0].direction is Direction.REVERSE  # backing out of the charger first
    assert route.length == pytest.approx(sum(e.length for e in route.edges))
    assert route.node_before("rack_b3_pre") == "b3"
    assert route.node_before("charger") is None


def test_routes_keep_the_forklift_heading_continuous(warehouse):
    planner = Planner(warehouse)
    for start, goal in [("rack_b3", "drop"), ("floor_a1", "rack_a1"), ("drop", "charger"), ("floor_b2", "floor_a3")]:
        route = planner.plan(start, goal)
        for a, b in itertools.pairwise(route.edges):
            assert abs(angle_diff(a.yaw_end, b.yaw_start)) < math.radians(1.0), (a.name, b.name)
        assert abs(angle_diff(route.edges[-1].yaw_end, warehouse.node(goal).pose.yaw)) < 1e-6


def test_one_way_loop_is_honoured(warehouse):
    # b3 -> b2 would be against the traffic of aisle B: the route must go round the loop.
    route = Planner(warehouse).plan("b3", "b2")
    assert len(route.nodes) > 3
    assert all(not (e.start == "b3" and e.end == "b2") for e in route.edges)


def test_no_route_names_both_nodes(warehouse):
    with pytest.raises(RoadmapError, match=r"no route from 'island' .*'charger'"):
        with warehouse.overlay() as ov:
            ov.add_node(Node("island", NodeType.WAYPOINT, SE2(50, 50, 0)))
            Planner(warehouse).plan("island", "charger")
    with pytest.raises(RoadmapError, match="unknown node 'ghost'"):
        Planner(warehouse).plan("charger", "ghost")


def _state_graph_shortest(rm, start, goal):
    """Independent check: Dijkstra in networkx over (node, rounded vehicle heading) states."""
    g = nx.DiGraph()
    for e in rm.edges():
        u = (e.start, round(math.degrees(e.yaw_start)) % 360)
        v = (e.end, round(math.degrees(e.yaw_end)) % 360)
        g.add_edge(u, v, w=e.length)
    sources = [n for n in g if n[0] == start]
    best = math.inf
    lengths = nx.multi_source_dijkstra_path_length(g, sources, weight="w")
    for n, d in lengths.items():
        if n[0] == goal:
            best = min(best, d)
    return best


def test_planner_matches_an_independent_search():
    rm = warehouse_grid(rows=12, cols=12, cross_every=4)
    planner = Planner(rm)
    rng = np.random.default_rng(3)
    ids = [n.id for n in rm.nodes()]
    for _ in range(25):
        a, b = rng.choice(len(ids), size=2, replace=False)
        route = planner.plan(ids[a], ids[b])
        assert route.length == pytest.approx(_state_graph_shortest(rm, ids[a], ids[b]), rel=1e-9)


# -- reference paths ---------------------------------------------------------------------


def test_reference_path_splits_at_direction_changes(warehouse):
    route = Planner(warehouse).plan("rack_b3", "drop")
    path = reference_path(route, step_m=0.05)
    assert [seg.direction for seg in path.segments] == [-1, 1]
    back, ahead = path.segments
    assert back.edges == ("rack_b3->rack_b3_pre", "rack_b3_pre->b3")
    # Reversing out keeps the forks facing the pallet: heading stays the pallet node's yaw.
    assert abs(angle_diff(back.heading[0], warehouse.node("rack_b3").pose.yaw)) < 1e-9
    assert back.end_pose.isclose(ahead.start_pose, atol=1e-9, atol_yaw=1e-9)
    assert path.length == pytest.approx(route.length, rel=1e-9)
    assert ahead.end_pose.isclose(warehouse.node("drop").pose, atol=1e-9, atol_yaw=1e-6)


def test_reference_path_is_continuous_and_labelled(warehouse):
    route = Planner(warehouse).plan("charger", "rack_b3")
    path = reference_path(route, step_m=0.05)
    for seg in path.segments:
        ds = np.diff(seg.s)
        assert np.all(ds > 0) and np.all(ds <= 0.05 + 1e-9)
        assert np.allclose(np.hypot(np.diff(seg.x), np.diff(seg.y)), ds, rtol=1e-3, atol=1e-4)  # s is arc length
        assert np.max(np.abs(angle_diff(seg.heading[1:], seg.heading[:-1]))) < 0.05
    fwd = path.segments[-1]
    # On the arc b3 -> rack_b3_pre (radius 2.5 m, turning left) the curvature is +1/2.5.
    assert np.isclose(fwd.curvature, 1 / 2.5).sum() > 10
    assert fwd.speed_limit[-1] == pytest.approx(0.3)  # the pallet entry's limit


# -- overlays ----------------------------------------------------------------------------


def test_overlay_adds_and_removes_temporary_nodes(warehouse):
    before = (warehouse.graph.number_of_nodes(), warehouse.graph.number_of_edges())
    planner = Planner(warehouse)
    planner.plan("charger", "rack_b3")
    pallet = warehouse.node("rack_b3")
    new_pallet = SE2(pallet.pose.x - 0.2, pallet.pose.y + 0.25, pallet.pose.yaw + math.radians(5))
    new_pre = new_pallet @ SE2(-2.5, 0.0, 0.0)
    with warehouse.overlay() as ov:
        ov.add_node(Node("rack_b3_pre*", NodeType.PRE_PALLET, new_pre))
        ov.add_node(Node("rack_b3*", NodeType.PALLET, new_pallet, pre_pallet="rack_b3_pre*", height=1.0))
        start = warehouse.node("b3").pose
        curve = connect(SE2(start.x, start.y, math.pi / 2), new_pre, max_curvature=1.0)
        ov.add_edge(Edge("b3", "rack_b3_pre*", curve))
        ov.add_edge(warehouse.line_edge("rack_b3_pre*", "rack_b3*", speed_limit=0.3))
        route = planner.plan("charger", "rack_b3*")  # the planner sees the overlay
        assert route.nodes[-3:] == ["b3", "rack_b3_pre*", "rack_b3*"]
        assert warehouse.node("rack_b3*").temporary
        # The overlay is checked like the base map: its pallet node still lacks the reverse exit.
        missing_exit = "pallet node 'rack_b3*': no reverse edge back to its pre-pallet node 'rack_b3_pre*'"
        assert warehouse.check() == [missing_exit]
    assert (warehouse.graph.number_of_nodes(), warehouse.graph.number_of_edges()) == before
    assert "rack_b3*" not in warehouse
    with pytest.raises(RoadmapError):
        planner.plan("charger", "rack_b3*")


def test_overlay_is_removed_on_error(warehouse):
    before = warehouse.graph.number_of_nodes()
    with pytest.raises(RuntimeError):
        with warehouse.overlay() as ov:
            ov.add_node(Node("tmp", NodeType.WAYPOINT, SE2(1, 1, 0)))
            raise RuntimeError("task failed")
    assert warehouse.graph.number_of_nodes() == before


# -- curve synthesis ---------------------------------------------------------------------


@pytest.mark.parametrize(
    "dx, dy, dyaw_deg",
    [(4.0, 0.3, 10.0), (4.0, -0.35, -15.0), (3.0, 0.2, 0.0), (5.0, 1.5, 30.0), (2.5, 0.0, 8.0)],
)
def test_connect_reaches_displaced_pre_pallet_nodes(dx, dy, dyaw_deg, max_curvature):
    start = SE2(6.0, 11.0, -math.pi / 2)
    end = start @ SE2(dx, dy, math.radians(dyaw_deg))
    curve = connect(start, end, max_curvature)
    assert curve.start_pose.isclose(start, atol=1e-9, atol_yaw=1e-6)
    assert curve.end_pose.isclose(end, atol=1e-9, atol_yaw=1e-6)
    assert curve.max_abs_curvature() <= max_curvature


def test_connect_straight_ahead_is_a_line():
    start = SE2(0, 0, 0.3)
    assert isinstance(connect(start, start @ SE2(3.0, 0, 0), 1.0), Line)


def test_connect_refuses_a_target_behind():
    with pytest.raises(RoadmapError, match="behind the start heading"):
        connect(SE2(0, 0, 0), SE2(-1.0, 0.5, 0.0), 1.0)


def test_connect_says_why_a_tight_target_is_infeasible(max_curvature):
    with pytest.raises(RoadmapError, match=r"needs a radius of .* no tighter than 0\.78 m"):
        connect(SE2(0, 0, 0), SE2(0.8, 1.5, 0.0), max_curvature)
