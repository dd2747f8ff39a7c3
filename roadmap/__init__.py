"""The roadmap: nodes and curves, map files, routes, reference paths, overlays, curve synthesis.

Public API:
- `Roadmap`, `Node`, `NodeType`, `Edge`, `Direction`: the graph (networkx DiGraph inside);
  `Roadmap.overlay()` adds temporary nodes and edges for a scope; `Roadmap.check(max_curvature)`.
- `Line`, `Arc`, `CubicBezier` (`Curve`): arc-length parametrised curves in the world frame.
- `load_map(path)`, `check_map(path, max_curvature)`: map files, YAML or JSON (format and ranges in
  `roadmap.mapfile`; 100,000-node maps load in seconds: `roadmap.mapread`, `roadmap.mapbuild`).
- `Planner(roadmap).plan(start, goal)` -> `Route` (nodes, edges, length, `node_before`).
- `reference_path(route, step_m)` -> `ReferencePath` of `PathSegment`s split at direction changes.
- `connect(start, end, max_curvature)`: a feasible curve between two poses, or `RoadmapError` why not.
- `RoadmapError`.
"""

from palletpilot.roadmap.curves import Arc, CubicBezier, Curve, CurveSamples, Line
from palletpilot.roadmap.errors import RoadmapError
from palletpilot.roadmap.graph import Direction, Edge, Node, NodeType, Overlay, Roadmap
from palletpilot.roadmap.mapbuild import build_curve
from palletpilot.roadmap.mapfile import check_map, load_map, map_vehicle_file
from palletpilot.roadmap.path import PathSegment, ReferencePath, reference_path
from palletpilot.roadmap.planner import Planner, Route, plan_route
from palletpilot.roadmap.synthesis import connect

__all__ = [
    "Arc",
    "CubicBezier",
    "Curve",
    "CurveSamples",
    "Direction",
    "Edge",
    "Line",
    "Node",
    "NodeType",
    "Overlay",
    "PathSegment",
    "Planner",
    "ReferencePath",
    "Roadmap",
    "RoadmapError",
    "Route",
    "build_curve",
    "check_map",
    "connect",
    "load_map",
    "map_vehicle_file",
    "plan_route",
    "reference_path",
]
