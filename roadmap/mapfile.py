"""Map files (YAML): loading with validation that reports every problem, one line each.

```yaml
name: example warehouse
vehicle: forklift.yaml          # optional: vehicle file (relative to this file) for the curvature limit
default_speed_limit: 1.0        # m/s, for edges that give none
parking_types: [park]           # optional: node types a truck may wait at after a failure (default: park)
nodes:
  - {id: a1_pre, type: pre_pallet, x: 4.0, y: 2.0, yaw_deg: 90}
  - {id: a1, type: pallet, x: 4.0, y: 3.5, yaw_deg: 90, pre_pallet: a1_pre, height: 0.0}
  - {id: x1, type: intersection, x: 4.0, y: 0.0}            # no yaw_deg: no heading constraint
edges:
  - {from: x1, to: a1_pre, curve: arc}                      # line (default), arc or bezier
  - {from: a1_pre, to: a1}
  - {from: a1, to: a1_pre, direction: reverse, speed_limit: 0.3}
  - {from: x1, to: x2, both_ways: true}                     # also x2 -> x1 along the same curve
  - {from: x2, to: x3, curve: bezier, control: [[1, 2], [3, 4]]}
```
An arc is fixed by its start node's heading (or, if that node has none, its end node's) and its end
point. A bezier without `control` leaves and arrives along the node headings with handles of a third
of the chord. Angles are in degrees in the file, radians inside.
"""

from __future__ import annotations

import math
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import BaseModel, ConfigDict, Field

from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import read_yaml, validate_model
from palletpilot.roadmap.curves import Arc, CubicBezier, Curve, Line
from palletpilot.roadmap.errors import RoadmapError
from palletpilot.roadmap.graph import NOT_FOR_PARKING, Direction, Edge, Node, NodeType, Roadmap


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid")


class NodeSpec(_Strict):
    """A node as written in a map file."""

    id: str
    type: NodeType
    x: float
    y: float
    yaw_deg: float | None = None
    height: float = Field(0.0, ge=0.0)
    pre_pallet: str | None = None


class EdgeSpec(_Strict):
    """An edge as written in a map file."""

    model_config = ConfigDict(extra="forbid", populate_by_name=True)

    start: str = Field(alias="from")
    end: str = Field(alias="to")
    curve: Literal["line", "arc", "bezier"] = "line"
    control: list[tuple[float, float]] | None = Field(None, min_length=2, max_length=2)
    direction: Direction = Direction.FORWARD
    speed_limit: float | None = Field(None, gt=0.0)
    both_ways: bool = False


class MapSpec(_Strict):
    """A whole map file."""

    name: str = "roadmap"
    vehicle: str | None = None
    default_speed_limit: float = Field(1.0, gt=0.0)
    parking_types: list[NodeType] | None = Field(None, min_length=1)
    nodes: list[NodeSpec]
    edges: list[EdgeSpec] = []


def _tangent_towards(node: Node, target: np.ndarray) -> float:
    """The node's heading axis, pointed towards `target`: yaw or yaw + pi."""
    u = np.array([math.cos(node.pose.yaw), math.sin(node.pose.yaw)])
    return node.pose.yaw if float(u @ (target - node.pose.xy)) >= 0.0 else node.pose.yaw + math.pi


def build_curve(start: Node, end: Node, kind: str, control: list[tuple[float, float]] | None = None) -> Curve:
    """The curve of an edge between two nodes, as the map file describes it (see module docstring)."""
    if kind == "line":
        return Line(start.pose.xy, end.pose.xy)
    if kind == "arc":
        if start.has_heading:
            return Arc(SE2(start.pose.x, start.pose.y, _tangent_towards(start, end.pose.xy)), end.pose.xy)
        if end.has_heading:
            back = _tangent_towards(end, start.pose.xy)
            return Arc(SE2(end.pose.x, end.pose.y, back), start.pose.xy).reversed()
        raise RoadmapError("an arc needs a heading (yaw_deg) at its start or end node")
    if control is not None:
        return CubicBezier(start.pose.xy, control[0], control[1], end.pose.xy)
    if not (start.has_heading and end.has_heading):
        raise RoadmapError("a bezier without control points needs headings at both nodes")
    chord = float(np.hypot(*(end.pose.xy - start.pose.xy)))
    h0 = _tangent_towards(start, end.pose.xy)
    h1 = _tangent_towards(end, start.pose.xy) + math.pi
    return CubicBezier.from_poses(
        SE2(start.pose.x, start.pose.y, h0), SE2(end.pose.x, end.pose.y, h1), chord / 3, chord / 3
    )


def load_map(path: str | Path) -> Roadmap:
    """Load and validate a map file. Structural problems raise one `RoadmapError` listing all of them.

    Geometry against a vehicle (curvature) is checked by `Roadmap.check(max_curvature)`;
    `check_map` does both.
    """
    roadmap, problems = _load(Path(path))
    problems += roadmap.check()
    if problems:
        raise RoadmapError(f"{path}: {len(problems)} problem(s) in the map", [f"{path}: {p}" for p in problems])
    return roadmap


def check_map(path: str | Path, max_curvature: float | None) -> tuple[Roadmap | None, list[str]]:
    """Every problem of a map file, one line each, including curvature above `max_curvature` (1/m)."""
    try:
        roadmap, problems = _load(Path(path))
    except RoadmapError as exc:
        return None, exc.problems
    problems += roadmap.check(max_curvature)
    return roadmap, [f"{path}: {p}" for p in problems]


def map_vehicle_file(path: str | Path) -> Path | None:
    """The vehicle file a map names (resolved against the map's folder), or None."""
    raw = read_yaml(path, RoadmapError)
    if isinstance(raw, dict) and isinstance(raw.get("vehicle"), str):
        return Path(path).parent / raw["vehicle"]
    return None


def _load(path: Path) -> tuple[Roadmap, list[str]]:
    spec = validate_model(read_yaml(path, RoadmapError), MapSpec, str(path), RoadmapError)

    roadmap = Roadmap(spec.name, str(path))
    problems: list[str] = []
    if spec.parking_types is not None:
        banned = [t.value for t in spec.parking_types if t in NOT_FOR_PARKING]
        if banned:
            problems.append(
                f"parking_types: {', '.join(banned)} nodes are slots or their approaches, no place to wait "
                f"(allowed: {', '.join(t.value for t in NodeType if t not in NOT_FOR_PARKING)})"
            )
        roadmap.parking_types = frozenset(t for t in spec.parking_types if t not in NOT_FOR_PARKING)
    for ns in spec.nodes:
        if ns.id in roadmap:
            problems.append(f"duplicate node id '{ns.id}'")
            continue
        roadmap.add_node(
            Node(
                ns.id,
                ns.type,
                SE2(ns.x, ns.y, math.radians(ns.yaw_deg or 0.0)),
                has_heading=ns.yaw_deg is not None,
                height=ns.height,
                pre_pallet=ns.pre_pallet,
            )
        )
    for es in spec.edges:
        name = f"{es.start}->{es.end}"
        unknown = [n for n in (es.start, es.end) if n not in roadmap]
        if unknown:
            problems += [f"edge '{name}': unknown node '{n}'" for n in unknown]
            continue
        if es.start == es.end:
            problems.append(f"edge '{name}': starts and ends at the same node")
            continue
        if es.control is not None and es.curve != "bezier":
            problems.append(f"edge '{name}': control points are only for a bezier, not a {es.curve}")
            continue
        try:
            curve = build_curve(roadmap.node(es.start), roadmap.node(es.end), es.curve, es.control)
        except RoadmapError as exc:
            problems.append(f"edge '{name}': {exc}")
            continue
        speed = es.speed_limit or spec.default_speed_limit
        pairs = [(es.start, es.end, curve)] + ([(es.end, es.start, curve.reversed())] if es.both_ways else [])
        for u, v, c in pairs:
            if roadmap.graph.has_edge(u, v):
                problems.append(f"edge '{u}->{v}': duplicate edge")
                continue
            roadmap.add_edge(Edge(u, v, c, es.direction, speed))
    return roadmap, problems
