"""Building a `Roadmap` from a validated map file (`MapSpec`), with every structural problem found.

The result and the messages are those of adding the nodes and edges one by one in file order (the
first of two nodes with one id wins; an edge whose curve cannot be built is left out, and a later
edge between the same nodes is then no duplicate), but built for 100,000-node maps: node ids in a
dict, the Beziers' lengths and cusps in arrays (`curves.bezier_geometry`), the graph in one go
(`Roadmap.add_many`). Lines and arcs are built one by one (a few microseconds each).

Coordinates are in the world frame (m), headings in radians (the file's degrees converted).
"""

from __future__ import annotations

import math
from typing import TYPE_CHECKING

import numpy as np

from palletpilot.geometry import SE2
from palletpilot.roadmap.curves import Arc, CubicBezier, Curve, Line, bezier_geometry
from palletpilot.roadmap.errors import RoadmapError
from palletpilot.roadmap.graph import NOT_FOR_PARKING, Edge, Node, NodeType, Roadmap

if TYPE_CHECKING:
    from palletpilot.roadmap.mapfile import EdgeSpec, MapSpec


def build_roadmap(spec: MapSpec, source: str) -> tuple[Roadmap, list[str]]:
    """The roadmap of a map file and its structural problems, one line each (not yet prefixed with the file)."""
    roadmap = Roadmap(spec.name, source)
    problems: list[str] = []
    if spec.parking_types is not None:
        banned = [t.value for t in spec.parking_types if t in NOT_FOR_PARKING]
        if banned:
            problems.append(
                f"parking_types: {', '.join(banned)} nodes are slots or their approaches, no place to wait "
                f"(allowed: {', '.join(t.value for t in NodeType if t not in NOT_FOR_PARKING)})"
            )
        roadmap.parking_types = frozenset(t for t in spec.parking_types if t not in NOT_FOR_PARKING)

    nodes: dict[str, Node] = {}
    row_of: dict[str, int] = {}
    for ns in spec.nodes:
        if ns.id in nodes:
            problems.append(f"duplicate node id '{ns.id}'")
            continue
        row_of[ns.id] = len(nodes)
        nodes[ns.id] = Node(
            ns.id,
            ns.type,
            SE2(ns.x, ns.y, math.radians(ns.yaw_deg or 0.0)),
            has_heading=ns.yaw_deg is not None,
            height=ns.height,
            pre_pallet=ns.pre_pallet,
        )
    coords = [(n.pose.x, n.pose.y) for n in nodes.values()]
    xy = np.array(coords, dtype=float).reshape(-1, 2)

    # Pass 1, in file order: the structural problems, and a slot in `curves` for each curve to build
    # (lines and Beziers are filled in afterwards, in arrays).
    curves: list[Curve | str | None] = []
    entries: list[tuple[EdgeSpec, list[str] | None, int, int]] = []  # spec, problems, forward and back slot
    line_slots: list[int] = []
    line_ends: list[tuple[int, int]] = []
    bezier_slots: list[int] = []
    bezier_points: list[tuple[float, ...]] = []  # p0, p1, p2, p3 flattened (m)
    for es in spec.edges:
        start, end = es.start, es.end
        if start not in nodes or end not in nodes:
            unknown = [f"edge '{start}->{end}': unknown node '{n}'" for n in (start, end) if n not in nodes]
            entries.append((es, unknown, -1, -1))
            continue
        if start == end:
            entries.append((es, [f"edge '{start}->{end}': starts and ends at the same node"], -1, -1))
            continue
        if es.control is not None and es.curve != "bezier":
            why = f"edge '{start}->{end}': control points are only for a bezier, not a {es.curve}"
            entries.append((es, [why], -1, -1))
            continue
        slot = len(curves)
        back = slot + 1 if es.both_ways else -1
        if es.curve == "line":
            a, b = row_of[start], row_of[end]
            line_slots += [slot, slot + 1] if es.both_ways else [slot]
            line_ends += [(a, b), (b, a)] if es.both_ways else [(a, b)]
            curves += [None, None] if es.both_ways else [None]
        elif es.curve == "bezier":
            if es.control is not None:
                (c0x, c0y), (c1x, c1y) = es.control
                points = (*coords[row_of[start]], c0x, c0y, c1x, c1y, *coords[row_of[end]])
            else:
                try:
                    points = tuple(_bezier_control(nodes[start], nodes[end], None).ravel().tolist())
                except RoadmapError as exc:
                    entries.append((es, [f"edge '{start}->{end}': {exc}"], -1, -1))
                    continue
            reverse = (*points[6:8], *points[4:6], *points[2:4], *points[0:2])
            bezier_slots += [slot, slot + 1] if es.both_ways else [slot]
            bezier_points += [points, reverse] if es.both_ways else [points]
            curves += [None, None] if es.both_ways else [None]
        else:
            try:
                arc = build_curve(nodes[start], nodes[end], es.curve)
            except RoadmapError as exc:
                entries.append((es, [f"edge '{start}->{end}': {exc}"], -1, -1))
                continue
            curves.append(arc)
            if es.both_ways:
                try:
                    curves.append(arc.reversed())
                except RoadmapError as exc:
                    curves.append(str(exc))
        entries.append((es, None, slot, back))

    for slot, curve in zip(line_slots, _lines(xy, np.array(line_ends, dtype=np.intp).reshape(-1, 2)), strict=True):
        curves[slot] = curve
    bezier_control = np.array(bezier_points, dtype=float).reshape(-1, 4, 2)
    for slot, curve in zip(bezier_slots, _beziers(bezier_control), strict=True):
        curves[slot] = curve

    # Pass 2, in file order: the messages, and the edges whose curves could be built.
    edges: list[Edge] = []
    keys: set[tuple[str, str]] = set()
    for es, edge_problems, slot, back in entries:
        if edge_problems is not None:
            problems += edge_problems
            continue
        forward = curves[slot]
        if isinstance(forward, str):
            problems.append(f"edge '{es.start}->{es.end}': {forward}")
            continue
        speed = es.speed_limit or spec.default_speed_limit
        ways: list[tuple[str, str, Curve | str | None]] = [(es.start, es.end, forward)]
        if back >= 0:
            ways.append((es.end, es.start, curves[back]))
        for u, v, way in ways:
            if (u, v) in keys:
                problems.append(f"edge '{u}->{v}': duplicate edge")
            elif not isinstance(way, Curve):
                problems.append(f"edge '{u}->{v}': {way} (the way back of '{es.start}->{es.end}')")
            else:
                keys.add((u, v))
                edges.append(Edge(u, v, way, es.direction, speed))
    roadmap.add_many(list(nodes.values()), edges)
    return roadmap, problems


def _lines(xy: np.ndarray, ends: np.ndarray) -> list[Curve | str]:
    """A `Line` from row `ends[i, 0]` to row `ends[i, 1]` of the node points `xy` (m), or why not
    ("line has zero length"); lengths and headings computed as `Line(p0, p1)` computes them."""
    points = list(xy)  # one view per node, shared by its lines
    d = xy[ends[:, 1]] - xy[ends[:, 0]]
    length = np.hypot(d[:, 0], d[:, 1]).tolist()
    out: list[Curve | str] = []
    for (a, b), (dx, dy), n in zip(ends.tolist(), d.tolist(), length, strict=True):
        if n < 1e-9:
            out.append("line has zero length")
        else:
            out.append(Line.checked(points[a], points[b], n, math.atan2(dy, dx)))
    return out


def _tangent_towards(node: Node, target: np.ndarray) -> float:
    """The node's heading axis, pointed towards `target`: yaw or yaw + pi."""
    u = np.array([math.cos(node.pose.yaw), math.sin(node.pose.yaw)])
    return node.pose.yaw if float(u @ (target - node.pose.xy)) >= 0.0 else node.pose.yaw + math.pi


def build_curve(start: Node, end: Node, kind: str, control: list[tuple[float, float]] | None = None) -> Curve:
    """The curve of an edge between two nodes, as the map file describes it (see `roadmap.mapfile`).

    `kind` is line, arc or bezier; `control` two Bezier control points (world frame, m).
    """
    if kind == "line":
        return Line(start.pose.xy, end.pose.xy)
    if kind == "arc":
        if start.has_heading:
            return Arc(SE2(start.pose.x, start.pose.y, _tangent_towards(start, end.pose.xy)), end.pose.xy)
        if end.has_heading:
            back = _tangent_towards(end, start.pose.xy)
            return Arc(SE2(end.pose.x, end.pose.y, back), start.pose.xy).reversed()
        raise RoadmapError("an arc needs a heading (yaw_deg) at its start or end node")
    return CubicBezier(*_bezier_control(start, end, control))


def _bezier_control(start: Node, end: Node, control: list[tuple[float, float]] | None) -> np.ndarray:
    """The 4 x 2 control points (m) of a Bezier edge: `control` between the nodes, else handles of a third
    of the chord along the node headings (the arithmetic of `CubicBezier.from_poses`)."""
    if control is not None:
        return np.array([start.pose.xy, control[0], control[1], end.pose.xy], dtype=float).reshape(4, 2)
    if not (start.has_heading and end.has_heading):
        raise RoadmapError("a bezier without control points needs headings at both nodes")
    chord = float(np.hypot(*(end.pose.xy - start.pose.xy)))
    p0 = SE2(start.pose.x, start.pose.y, _tangent_towards(start, end.pose.xy))
    p3 = SE2(end.pose.x, end.pose.y, _tangent_towards(end, start.pose.xy) + math.pi)
    u0 = np.array([math.cos(p0.yaw), math.sin(p0.yaw)])
    u1 = np.array([math.cos(p3.yaw), math.sin(p3.yaw)])
    handle = chord / 3
    return np.array([p0.xy, p0.xy + handle * u0, p3.xy - handle * u1, p3.xy], dtype=float).reshape(4, 2)


def _beziers(control: np.ndarray) -> list[CubicBezier | str]:
    """A `CubicBezier` for each control row (m, 4, 2), or why it cannot be one (as `CubicBezier` says it)."""
    if len(control) == 0:
        return []
    # np.allclose(a, b) of each end point and its neighbour, for all rows at once.
    near_start = np.all(np.abs(control[:, 0] - control[:, 1]) <= 1e-8 + 1e-5 * np.abs(control[:, 1]), axis=1)
    near_end = np.all(np.abs(control[:, 2] - control[:, 3]) <= 1e-8 + 1e-5 * np.abs(control[:, 3]), axis=1)
    length, headings, cusp = bezier_geometry(control)
    out: list[CubicBezier | str] = []
    for i in range(len(control)):
        if near_start[i] or near_end[i]:
            out.append("bezier: a control point coincides with its end point (undefined tangent)")
        elif length[i] < 1e-9:
            out.append("bezier has zero length")
        elif not np.isnan(cusp[i]):
            out.append(
                f"bezier: the control points make a cusp near t = {cusp[i]:.2f} (the curve stops and turns back)"
            )
        else:
            out.append(
                CubicBezier.checked(control[i], float(length[i]), (float(headings[i, 0]), float(headings[i, 1])))
            )
    return out
