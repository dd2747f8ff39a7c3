"""The Pickup's manoeuvre: forward and reverse moves to a corrected pre-pallet node no single curve reaches.

When the re-plan finds no roadmap node from which one drivable curve reaches the new pre-pallet node
(`pickup.Replan`, `nodes_back`), it plans a manoeuvre from the node the truck backed off to
(`roadmap.manoeuvre.plan_manoeuvre`): a few moves forward and in reverse within the aisle, then forward
into the new pre-pallet node, under the vehicle's curvature limit. The manoeuvre becomes temporary waypoint
nodes (`PRE~k.m1`, `PRE~k.m2`, ...) and edges, each driven in its direction, both ways (the way back
drives every move the other way), in the task's overlay; the path follower drives them like any route,
stopping where the direction changes, in the simulator and on a truck.

What the truck must keep clear of, with `ManoeuvreLimits.clearance_m` to spare (world frame, m): the
static obstacles the map states, that is the racks behind its rack slots (pallet and drop nodes above the
floor: from where the mast would meet the front beam, `Settings.rack_overrun`, `RACK_DEPTH_M` deep and
`RACK_HALF_BAY_M` either side of the slot) and the pallets that may stand in its other slots (at their
nodes, grown by `STORED_PALLET_MARGIN_M` on the floor, `RACK_PALLET_MARGIN_M` in a rack), and the pallet to
be picked where it was estimated. The truck's outline is the loaded one (body, and a pallet on the forks),
since it leaves the same way with the load; the empty one for the pallet to pick and its rack, which only
the empty truck passes. Behind the body, the scanners' reversing field is kept clear of what cuts the
scan plane (racks, pallets on the floor), not of pallets stored on a rack's beams above it. Anything
else (people, boxes) the safety scanners watch for, as on every route.
A re-plan's single approach curve is held to the same (`check_curve_clear`): one that would pass too near
counts as no curve from that node.

Public API: `RACK_DEPTH_M`, `RACK_HALF_BAY_M`, `STORED_PALLET_MARGIN_M`, `RACK_PALLET_MARGIN_M`,
`truck_footprint`, `static_obstacles`, `manoeuvre_planner`, `check_curve_clear`, `with_manoeuvre`,
`manoeuvre_record`, `add_manoeuvre_edges`, `manoeuvre_nodes`, `exit_route`.
"""

from __future__ import annotations

import dataclasses
import itertools
import math
from collections.abc import Callable
from typing import Any

from palletpilot.control.safety import stopping_distance
from palletpilot.executor.core.behaviour import Context, TemporaryNodes
from palletpilot.executor.core.engagement import tip_depth
from palletpilot.executor.core.errors import NO_FEASIBLE_APPROACH, TaskFailed
from palletpilot.executor.core.jobs import Job
from palletpilot.geometry import SE2
from palletpilot.perception.specs import ENTRY_GAP_M
from palletpilot.roadmap import Curve, Direction, Edge, Node, NodeType, RoadmapError, Route
from palletpilot.roadmap.manoeuvre import (
    Footprint,
    Manoeuvre,
    ManoeuvreLimits,
    ManoeuvreSegment,
    Obstacle,
    outline_hits,
    plan_manoeuvre,
)

RACK_DEPTH_M = 1.2
"""How deep (m) a rack behind a rack slot is taken to be, from its front beam (a 1.1 m rack, and more)."""
RACK_HALF_BAY_M = 1.40
"""How far (m) a rack is taken to reach either side of a rack slot's centre line (a 2.7 m bay with its
uprights); neighbouring slots' racks join into one row."""
STORED_PALLET_MARGIN_M = 0.15
"""A pallet stored in another floor slot is taken to stand within this much (m) of its node ..."""
RACK_PALLET_MARGIN_M = 0.05
"""... and one on a rack's beams, set against the rack, within this much."""
TARGET_MARGIN_M = 0.05
"""The pallet to be picked stands within this much (m) of its estimate."""
MANOEUVRE_SPEED = 0.3
"""m/s on a manoeuvre's moves."""
FIELD_TRACKING_M = 0.05
"""m: the reversing field is kept this much clear of what cuts the scan plane (beyond the field itself), for
the path follower's tracking: with none, a loaded exit stopped on rack uprights inside its field."""


def truck_footprint(ctx: Context, load_front_x: float | None = None) -> Footprint:
    """The truck's outline in the forklift frame (m): its body, and the forks carrying a pallet of the task's
    type (`load_front_x`: the load's far end, by default the pallet's when the forks are fully in; or the
    fork tips when they reach further); behind it, the safety scanners' protective field when reversing at
    `MANOEUVRE_SPEED` (`Footprint.field_m`: a rack inside it would stop the truck)."""
    params, pallet = ctx.params, ctx.pallet_type
    body, scanner = params.body, params.safety_scanner
    load = ENTRY_GAP_M + pallet.length if load_front_x is None else load_front_x
    field = 0.0 if scanner is None else scanner.protective_margin + stopping_distance(params, MANOEUVRE_SPEED)
    behind = field - ManoeuvreLimits.clearance_m + FIELD_TRACKING_M  # the field, and a margin for tracking
    return Footprint(body.rear_x, max(ctx.forks.tip_x, load), 0.5 * max(body.width, pallet.width), behind)


def static_obstacles(ctx: Context, target: SE2) -> list[Obstacle]:
    """The map's racks and stored pallets, and the pallet to be picked at `target` (`T_world_pallet`, the
    estimate), as obstacles (world frame; see the module docstring). The pallet to pick and its rack are
    passed by the empty truck only (`Obstacle.approach_only`)."""
    pallet, st = ctx.pallet_type, ctx.settings
    face = st.rack_overrun + ctx.params.body.front_x  # the rack's front beam, in the node's frame (m)
    scanner = ctx.params.safety_scanner
    scan_height = math.inf if scanner is None else scanner.scan_height
    out = []
    for node in ctx.roadmap.nodes():
        if node.temporary or node.type not in (NodeType.PALLET, NodeType.DROP):
            continue
        mine = node.id == ctx.memory.node_task().node
        if node.height > 0.0:
            out.append(
                Obstacle.box(
                    f"the rack at '{node.id}'",
                    node.pose,
                    face,
                    face + RACK_DEPTH_M,
                    -RACK_HALF_BAY_M,
                    RACK_HALF_BAY_M,
                    approach_only=mine,
                )
            )
        if not mine:
            m = RACK_PALLET_MARGIN_M if node.height > 0.0 else STORED_PALLET_MARGIN_M
            x0, x1, half = ENTRY_GAP_M - m, ENTRY_GAP_M + pallet.length + m, 0.5 * pallet.width + m
            seen = node.height < scan_height  # one on a rack's beams is above the scanners' plane
            out.append(Obstacle.box(f"a pallet at '{node.id}'", node.pose, x0, x1, -half, half, in_scan_plane=seen))
    half = 0.5 * pallet.width + TARGET_MARGIN_M
    out.append(
        Obstacle.box(
            "the pallet to pick",
            target,
            -TARGET_MARGIN_M,
            pallet.length + TARGET_MARGIN_M,
            -half,
            half,
            True,
            picked=True,
        )
    )
    return out


def _outlines(ctx: Context, spec: TemporaryNodes, target: SE2) -> tuple[Footprint, Footprint, list[Obstacle]]:
    """The loaded and the empty outline of the truck, and the obstacles, for a re-plan towards the pallet
    estimated at `target` (`T_world_pallet`) with the new pallet node `spec.pallet_pose`."""
    # the load's far end once picked: the forks held back at a rack leave more of the pallet beyond the tips
    reach = min(tip_depth(ctx.forks, target.inv() @ spec.pallet_pose), ctx.pallet_type.length)
    loaded = truck_footprint(ctx, ctx.forks.tip_x + ctx.pallet_type.length - reach)
    empty = dataclasses.replace(loaded, front_x=ctx.forks.tip_x, half_width=0.5 * ctx.params.body.width)
    return loaded, empty, static_obstacles(ctx, target)


def manoeuvre_planner(ctx: Context, spec: TemporaryNodes, target: SE2) -> Callable[[], Manoeuvre]:
    """The search for a manoeuvre from `spec.before` (the truck heading `spec.heading` there) to the new
    pre-pallet pose, its inputs taken now: a function to run off the control loop (`ctx.jobs`); it raises
    `RoadmapError` saying what it tried when no manoeuvre fits."""
    before = ctx.roadmap.node(spec.before).pose
    start = SE2(before.x, before.y, spec.heading)
    loaded, empty, obstacles = _outlines(ctx, spec, target)
    limit = ctx.params.max_curvature
    return lambda: plan_manoeuvre(start, spec.pre_pose, limit, loaded, obstacles, ManoeuvreLimits(), empty=empty)


def check_curve_clear(ctx: Context, spec: TemporaryNodes, curve: Curve, target: SE2) -> None:
    """`RoadmapError` when a re-plan's single approach curve (forward, and backed along in reverse) would
    bring the truck within the clearance of a static obstacle, as a manoeuvre's moves may not."""
    loaded, empty, obstacles = _outlines(ctx, spec, target)
    clearance = ManoeuvreLimits.clearance_m
    hit = outline_hits(ManoeuvreSegment(curve, Direction.FORWARD).poses(), loaded, empty, obstacles, clearance)
    if hit is not None:
        raise RoadmapError(f"the curve would bring the truck within {clearance:.2f} m of {hit.name}")


def with_manoeuvre(ctx: Context, spec: TemporaryNodes, job: Job[Manoeuvre], failures: list[str]) -> TemporaryNodes:
    """`spec` with the manoeuvre `job` found (logged as `manoeuvre_planned`: its moves and their
    directions); when it found none, `TaskFailed(no_feasible_approach)` naming every node tried for a
    single curve (`failures`) and what the manoeuvre's search tried."""
    try:
        manoeuvre = job.result()
    except RoadmapError as exc:
        ctx.log("manoeuvre_infeasible", node=spec.before, error=str(exc))
        n, limit = len(failures), max(1, ctx.settings.replan_back_nodes)
        raise TaskFailed(
            NO_FEASIBLE_APPROACH,
            f"no feasible approach to the estimated pallet: tried {n} node{'' if n == 1 else 's'} back along "
            f"the route (at most {limit}): " + "; ".join(failures) + f"; and a manoeuvre from '{spec.before}': {exc}",
        ) from None
    ctx.log(
        "manoeuvre_planned",
        node=spec.before,
        segments=len(manoeuvre.segments),
        directions=manoeuvre.directions,
        reversals=manoeuvre.reversals,
        length_m=round(manoeuvre.length, 3),
    )
    return dataclasses.replace(spec, manoeuvre=manoeuvre)


def manoeuvre_record(spec: TemporaryNodes) -> dict[str, Any]:
    """The report's record of a re-plan's manoeuvre (`{"manoeuvre": {...}}`: its moves, their directions,
    the changes of direction, the length in m), empty without one."""
    m = spec.manoeuvre
    if m is None:
        return {}
    return {
        "manoeuvre": {
            "segments": len(m.segments),
            "directions": m.directions,
            "reversals": m.reversals,
            "length_m": round(m.length, 3),
        }
    }


def manoeuvre_nodes(spec: TemporaryNodes) -> list[str]:
    """The ids of a re-plan's manoeuvre waypoints, in driving order (none without a manoeuvre)."""
    n = len(spec.manoeuvre.segments) if spec.manoeuvre is not None else 0
    return [f"{spec.pre}.m{i}" for i in range(1, n)]


def add_manoeuvre_edges(ctx: Context, spec: TemporaryNodes) -> list[Edge]:
    """Add a re-plan's manoeuvre to the task's overlay: its waypoints (the truck's pose where each move
    ends) and, per move, the edge driven its way and the edge back driven the other way. The pre-pallet
    node must be in the overlay already. Returns the edges added."""
    assert ctx.memory.overlay is not None and spec.manoeuvre is not None
    ov = ctx.memory.overlay
    segments = spec.manoeuvre.segments
    for node_id, seg in zip(manoeuvre_nodes(spec), segments, strict=False):
        ov.add_node(Node(node_id, NodeType.WAYPOINT, seg.end_pose))
    chain = [spec.before, *manoeuvre_nodes(spec), spec.pre]
    edges = []
    for (a, b), seg in zip(itertools.pairwise(chain), segments, strict=True):
        back = Direction.REVERSE if seg.direction is Direction.FORWARD else Direction.FORWARD
        edges.append(ov.add_edge(Edge(a, b, seg.curve, seg.direction, MANOEUVRE_SPEED)))
        edges.append(ov.add_edge(Edge(b, a, seg.curve.reversed(), back, MANOEUVRE_SPEED)))
    return edges


def exit_route(ctx: Context) -> Route:
    """From the (temporary) pre-pallet node back to the node before it: along the edge between them, or
    back through a re-plan's manoeuvre, every move driven the other way."""
    pre, before = ctx.memory.pre_node, ctx.memory.node_before or ""
    spec = next((t for t in reversed(ctx.memory.temporary) if t.pre == pre and t.before == before), None)
    nodes = [pre, *reversed(manoeuvre_nodes(spec)), before] if spec is not None else [pre, before]
    return Route(nodes, [ctx.roadmap.edge(a, b) for a, b in itertools.pairwise(nodes)])
