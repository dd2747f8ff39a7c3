"""A truck standing part way along a roadmap edge (after a cancelOrder, section 6.6.3.1), and the rest of that
edge from where it stands.

- `locate(roadmap, last, x, y)`: the edge out of roadmap node `last` the truck at (x, y) (map frame, m)
  stands on, farther than the normal node tolerance from `last` (`OnEdge`), or None.
- `rest_of(edge, s, node_id)`: a temporary edge from a new node at arc length `s` (m) of `edge` to its end,
  along the same curve (lines, arcs and cubic Beziers split exactly), with the edge's direction and speed.

Public API: `OnEdge`, `locate`, `rest_of`, `ON_EDGE_LATERAL_M`.
"""

from __future__ import annotations

import contextlib
import math
from dataclasses import dataclass

import numpy as np

from palletpilot.geometry import SE2
from palletpilot.roadmap import Edge, Node, NodeType, Roadmap, RoadmapError
from palletpilot.roadmap.curves import Arc, CubicBezier, Curve, Line

ON_EDGE_LATERAL_M = 0.3
"""m: the truck counts as on an edge within this of its curve."""
_STEP_M = 0.02


@dataclass(frozen=True)
class OnEdge:
    """The truck on roadmap edge `start` -> `end`, `s` (m) along it, `lateral` (m) off its curve."""

    start: str
    end: str
    s: float
    lateral: float


def locate(roadmap: Roadmap, last: str, x: float, y: float, near_node_m: float) -> OnEdge | None:
    """The (non-temporary) edge out of `last` that passes nearest (x, y), when the truck stands on it (within
    `ON_EDGE_LATERAL_M`) more than `near_node_m` from `last` and short of the edge's end; else None."""
    if not last or last not in roadmap:
        return None
    start = roadmap.node(last)
    if math.hypot(start.pose.x - x, start.pose.y - y) <= near_node_m:
        return None
    best: OnEdge | None = None
    for end in roadmap.graph.successors(last):
        edge = roadmap.edge(last, end)
        if edge.temporary:
            continue
        s, lateral = _project(edge.curve, x, y)
        if lateral <= ON_EDGE_LATERAL_M and s < edge.length - 1e-3 and (best is None or lateral < best.lateral):
            best = OnEdge(last, end, s, lateral)
    return best


def _project(curve: Curve, x: float, y: float) -> tuple[float, float]:
    """Arc length (m) of the curve's point nearest (x, y), and the distance to it (m)."""
    s = np.linspace(0.0, curve.length, max(2, int(curve.length / _STEP_M) + 1))
    smp = curve.sample(s)
    d = np.hypot(np.asarray(smp.x) - x, np.asarray(smp.y) - y)
    i = int(np.argmin(d))
    return float(s[i]), float(d[i])


def rest_of(edge: Edge, s: float, node_id: str) -> tuple[Node, Edge]:
    """A waypoint `node_id` at arc length `s` (m) of `edge` (its pose: the point and the truck's heading there)
    and the edge from it to `edge.end` along the rest of the same curve (temporary both)."""
    curve = edge.curve
    smp = curve.sample([s])
    p = np.array([float(smp.x[0]), float(smp.y[0])])
    tangent = float(smp.heading[0])
    sign = 0.0 if edge.direction.sign > 0 else math.pi
    node = Node(node_id, NodeType.WAYPOINT, SE2(p[0], p[1], tangent + sign), temporary=True)
    end = curve.sample([curve.length])
    p1 = np.array([float(end.x[0]), float(end.y[0])])
    rest: Curve = Line(p, p1)
    with contextlib.suppress(RoadmapError):  # a sliver of an arc or a Bezier left: the line to its end
        if isinstance(curve, Arc):
            rest = Arc(SE2(p[0], p[1], tangent), p1)
        elif isinstance(curve, CubicBezier):
            rest = _bezier_tail(curve, curve.parameter_at(s))
    return node, Edge(node_id, edge.end, rest, edge.direction, edge.speed_limit, temporary=True)


def _bezier_tail(curve: CubicBezier, t: float) -> CubicBezier:
    """The part t..1 of a cubic Bezier (de Casteljau)."""
    p0, p1, p2, p3 = curve.control
    p01, p12, p23 = p0 + t * (p1 - p0), p1 + t * (p2 - p1), p2 + t * (p3 - p2)
    p012, p123 = p01 + t * (p12 - p01), p12 + t * (p23 - p12)
    return CubicBezier(p012 + t * (p123 - p012), p123, p23, p3)
