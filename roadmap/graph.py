"""The roadmap: typed nodes and directed curve edges over a networkx DiGraph (world frame).

A node's `pose.yaw` is the heading of the forklift (its x axis, towards the fork tips) when it
stands at the node. For waypoints and intersections only the axis matters: a curve may leave or
arrive along the heading or against it. Nodes without a heading (`has_heading=False`) put no
constraint on their curves. Pallet, pre-pallet, drop, charging and park nodes always have one.

Edges are driven `forward` (fork tips leading, vehicle yaw = curve tangent) or `reverse`
(vehicle yaw = tangent + pi), e.g. backing out of a pallet node.
"""

from __future__ import annotations

import math
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from dataclasses import dataclass, field
from enum import Enum

import networkx as nx
import numpy as np

from palletpilot.geometry import SE2, angle_diff
from palletpilot.geometry.errors import did_you_mean
from palletpilot.roadmap.curves import Curve, Line, max_abs_curvatures
from palletpilot.roadmap.errors import RoadmapError

TANGENT_TOLERANCE_RAD = math.radians(1.0)
"""How far a curve's end tangent may differ from its node's heading axis."""


class NodeType(str, Enum):
    """What a node is for."""

    WAYPOINT = "waypoint"
    INTERSECTION = "intersection"
    CHARGING = "charging"
    PRE_PALLET = "pre_pallet"
    PALLET = "pallet"
    DROP = "drop"
    PARK = "park"


HEADING_REQUIRED = frozenset({NodeType.CHARGING, NodeType.PRE_PALLET, NodeType.PALLET, NodeType.DROP, NodeType.PARK})
"""Node types where the forklift's heading at the node is part of the node's meaning."""

DEFAULT_PARKING_TYPES = frozenset({NodeType.PARK})
"""Node types a truck may wait at when the map names none (`Roadmap.parking_types`)."""
NOT_FOR_PARKING = frozenset({NodeType.PALLET, NodeType.PRE_PALLET, NodeType.DROP})
"""Node types no map may allow for parking: slots and their approaches."""


class Direction(str, Enum):
    """Direction of travel on an edge."""

    FORWARD = "forward"
    REVERSE = "reverse"

    @property
    def sign(self) -> int:
        """+1 forward, -1 reverse."""
        return 1 if self is Direction.FORWARD else -1


@dataclass(frozen=True)
class Node:
    """A roadmap node. `height` (m) is the load height for pallet and drop nodes (0: on the floor)."""

    id: str
    type: NodeType
    pose: SE2
    has_heading: bool = True
    height: float = 0.0
    pre_pallet: str | None = None
    temporary: bool = False


@dataclass(frozen=True)
class Edge:
    """A directed edge from node `start` to node `end` along `curve`; `speed_limit` in m/s."""

    start: str
    end: str
    curve: Curve
    direction: Direction = Direction.FORWARD
    speed_limit: float = 1.0
    temporary: bool = False

    @property
    def name(self) -> str:
        """`start->end`, as used in messages."""
        return f"{self.start}->{self.end}"

    @property
    def length(self) -> float:
        """Arc length (m) of the curve."""
        return self.curve.length

    @property
    def yaw_start(self) -> float:
        """Vehicle yaw (rad) when leaving `start`."""
        h = self.curve.start_heading
        return h if self.direction is Direction.FORWARD else h + math.pi

    @property
    def yaw_end(self) -> float:
        """Vehicle yaw (rad) when arriving at `end`."""
        h = self.curve.end_heading
        return h if self.direction is Direction.FORWARD else h + math.pi


@dataclass
class Overlay:
    """Temporary nodes and edges added to a roadmap; `remove()` takes them all out again."""

    roadmap: Roadmap
    node_ids: list[str] = field(default_factory=list)
    edge_keys: list[tuple[str, str]] = field(default_factory=list)

    def add_node(self, node: Node) -> Node:
        """Add a temporary node (marked `temporary`)."""
        node = Node(node.id, node.type, node.pose, node.has_heading, node.height, node.pre_pallet, temporary=True)
        self.roadmap.add_node(node)
        self.node_ids.append(node.id)
        return node

    def add_edge(self, edge: Edge) -> Edge:
        """Add a temporary edge (marked `temporary`)."""
        edge = Edge(edge.start, edge.end, edge.curve, edge.direction, edge.speed_limit, temporary=True)
        self.roadmap.add_edge(edge)
        self.edge_keys.append((edge.start, edge.end))
        return edge

    def remove(self) -> None:
        """Remove everything this overlay added (edges first, then nodes)."""
        for u, v in reversed(self.edge_keys):
            self.roadmap.remove_edge(u, v)
        for n in reversed(self.node_ids):
            self.roadmap.remove_node(n)
        self.edge_keys.clear()
        self.node_ids.clear()


class Roadmap:
    """Nodes and directed edges; the base map plus any temporary overlay."""

    def __init__(self, name: str = "roadmap", source: str = "<memory>") -> None:
        self.name = name
        self.source = source
        self._graph: nx.DiGraph = nx.DiGraph()
        self.version = 0  # bumped on every change; planners cache on it
        # Node types a truck may wait at (after a failed task): the map file's `parking_types`.
        self.parking_types: frozenset[NodeType] = DEFAULT_PARKING_TYPES

    # -- building -----------------------------------------------------------------------
    def add_node(self, node: Node) -> None:
        """Add a node; a duplicate id is a `RoadmapError`."""
        if node.id in self._graph:
            raise RoadmapError(f"{self.source}: duplicate node id '{node.id}'")
        self._graph.add_node(node.id, node=node)
        self.version += 1

    def add_edge(self, edge: Edge) -> None:
        """Add an edge between existing nodes; unknown nodes or a duplicate edge are a `RoadmapError`."""
        for end in (edge.start, edge.end):
            if end not in self._graph:
                raise RoadmapError(f"{self.source}: edge '{edge.name}' refers to unknown node '{end}'")
        if self._graph.has_edge(edge.start, edge.end):
            raise RoadmapError(f"{self.source}: duplicate edge '{edge.name}'")
        self._graph.add_edge(edge.start, edge.end, edge=edge, length=edge.length)
        self.version += 1

    def add_many(self, nodes: Sequence[Node], edges: Sequence[Edge]) -> None:
        """Add nodes, then edges between them, at once (a map load): the same checks as `add_node`, `add_edge`."""
        ids = [n.id for n in nodes]
        fresh = set(ids)
        if len(fresh) != len(ids) or not fresh.isdisjoint(self._graph):
            seen: set[str] = set()
            for node_id in ids:
                if node_id in seen or node_id in self._graph:
                    raise RoadmapError(f"{self.source}: duplicate node id '{node_id}'")
                seen.add(node_id)
        self._graph.add_nodes_from((n.id, {"node": n}) for n in nodes)
        self.version += 1
        keys = [(e.start, e.end) for e in edges]
        ends = {u for u, _ in keys} | {v for _, v in keys}
        clash = len(set(keys)) != len(keys) or not ends.issubset(self._graph.nodes)
        if not clash and self._graph.number_of_edges():
            clash = any(self._graph.has_edge(u, v) for u, v in keys)
        if clash:
            for edge in edges:
                self.add_edge(edge)  # one by one: raises naming the first bad edge
            return
        self._graph.add_edges_from((e.start, e.end, {"edge": e, "length": e.length}) for e in edges)
        self.version += 1

    def line_edge(
        self, start: str, end: str, direction: Direction = Direction.FORWARD, speed_limit: float = 1.0
    ) -> Edge:
        """An edge along the straight line between two existing nodes (not yet added)."""
        return Edge(start, end, Line(self.node(start).pose.xy, self.node(end).pose.xy), direction, speed_limit)

    def remove_edge(self, start: str, end: str) -> None:
        """Remove an edge."""
        self._graph.remove_edge(start, end)
        self.version += 1

    def remove_node(self, node_id: str) -> None:
        """Remove a node and its edges."""
        self._graph.remove_node(node_id)
        self.version += 1

    @contextmanager
    def overlay(self) -> Iterator[Overlay]:
        """A scope for temporary nodes and edges, removed on exit whatever happens."""
        ov = Overlay(self)
        try:
            yield ov
        finally:
            ov.remove()

    # -- queries ------------------------------------------------------------------------
    @property
    def graph(self) -> nx.DiGraph:
        """The underlying DiGraph (node attribute `node`, edge attributes `edge`, `length`). Do not mutate."""
        return self._graph

    def __contains__(self, node_id: object) -> bool:
        return node_id in self._graph

    def node(self, node_id: str) -> Node:
        """The node with this id, or a `RoadmapError` naming it."""
        try:
            return self._graph.nodes[node_id]["node"]
        except KeyError:
            hint = did_you_mean(str(node_id), [str(n) for n in self._graph.nodes])
            raise RoadmapError(f"{self.source}: unknown node '{node_id}'{hint}") from None

    def edge(self, start: str, end: str) -> Edge:
        """The edge start -> end, or a `RoadmapError` naming it."""
        try:
            return self._graph.edges[start, end]["edge"]
        except KeyError:
            raise RoadmapError(f"{self.source}: no edge '{start}->{end}'") from None

    def nodes(self) -> list[Node]:
        """All nodes."""
        return [d["node"] for _, d in self._graph.nodes(data=True)]

    def parking_nodes(self) -> list[Node]:
        """The (permanent) nodes of a type the map allows for parking (`parking_types`), in map order."""
        return [n for n in self.nodes() if n.type in self.parking_types and not n.temporary]

    def edges(self) -> list[Edge]:
        """All edges."""
        return [d["edge"] for _, _, d in self._graph.edges(data=True)]

    def pre_pallet_of(self, pallet_id: str) -> str:
        """The pre-pallet node serving a pallet (or drop) node."""
        node = self.node(pallet_id)
        if node.type not in (NodeType.PALLET, NodeType.DROP) or node.pre_pallet is None:
            raise RoadmapError(f"{self.source}: node '{pallet_id}' is not a pallet or drop node with a pre-pallet node")
        return node.pre_pallet

    # -- validation ---------------------------------------------------------------------
    def check(self, max_curvature: float | None = None) -> list[str]:
        """Every geometric and structural problem, one line each (empty: the map is sound).

        `max_curvature` (1/m) is the vehicle's limit, tan(max steering) / wheelbase. The edge checks
        run as array operations (a 100,000-node map checks in about a second).
        """
        problems: list[str] = []
        nodes = self.nodes()
        for node in nodes:
            if node.type in HEADING_REQUIRED and not node.has_heading:
                problems.append(f"node '{node.id}': a {node.type.value} node needs a heading (yaw_deg)")
        problems += self._check_edges(self.edges(), max_curvature)
        for node in nodes:
            if node.type is NodeType.PALLET or (node.type is NodeType.DROP and node.pre_pallet is not None):
                problems += self._check_pallet(node)
        return problems

    def _check_edges(self, edges: list[Edge], max_curvature: float | None) -> list[str]:
        """Curve tangents against their nodes' heading axes, and curvature against `max_curvature` (1/m)."""
        if not edges:
            return []
        by_id = {node_id: data["node"] for node_id, data in self._graph.nodes(data=True)}
        tangent = np.array([(e.curve.start_heading, e.curve.end_heading) for e in edges])
        ends = [(by_id[e.start], by_id[e.end]) for e in edges]
        heading = np.array([(a.pose.yaw, b.pose.yaw) for a, b in ends])
        has_heading = np.array([(a.has_heading, b.has_heading) for a, b in ends])
        # The heading is an axis at waypoints: along it or against it are both fine.
        off = np.abs(angle_diff(tangent, heading))
        off = np.minimum(off, math.pi - off)
        bad_tangent = has_heading & (off > TANGENT_TOLERANCE_RAD)
        kappa = np.zeros(len(edges))
        bad_kappa = np.zeros(len(edges), dtype=bool)
        if max_curvature is not None:
            limit = max_curvature * (1.0 + 1e-6)
            kappa = max_abs_curvatures([e.curve for e in edges], known_below=limit)
            bad_kappa = kappa > limit
        problems = []
        for i in np.flatnonzero(bad_tangent.any(axis=1) | bad_kappa):
            edge = edges[i]
            for k, (node_id, where) in enumerate(((edge.start, "start"), (edge.end, "end"))):
                if bad_tangent[i, k]:
                    problems.append(
                        f"edge '{edge.name}': {where} tangent {math.degrees(tangent[i, k]):.1f} deg disagrees with "
                        f"node '{node_id}' heading {math.degrees(heading[i, k]):.1f} deg"
                        f" (off by {math.degrees(off[i, k]):.1f} deg)"
                    )
            if bad_kappa[i]:
                assert max_curvature is not None
                problems.append(
                    f"edge '{edge.name}': curvature {kappa[i]:.3f} 1/m (radius {1 / kappa[i]:.2f} m) is above the "
                    f"vehicle's limit {max_curvature:.3f} 1/m (radius {1 / max_curvature:.2f} m)"
                )
        return problems

    def _check_pallet(self, node: Node) -> list[str]:
        pre = node.pre_pallet
        kind = node.type.value
        if pre is None:
            return [f"{kind} node '{node.id}': no pre_pallet node named"]
        if pre not in self._graph:
            return [f"{kind} node '{node.id}': pre-pallet node '{pre}' does not exist"]
        if self.node(pre).type is not NodeType.PRE_PALLET:
            return [f"{kind} node '{node.id}': '{pre}' is a {self.node(pre).type.value} node, not pre_pallet"]
        problems = []
        if not self._graph.has_edge(pre, node.id):
            problems.append(f"{kind} node '{node.id}': no straight edge from its pre-pallet node '{pre}'")
        else:
            entry = self.edge(pre, node.id)
            if not isinstance(entry.curve, Line) or entry.direction is not Direction.FORWARD:
                problems.append(
                    f"{kind} node '{node.id}': edge '{entry.name}' must be a forward line, "
                    f"is a {entry.direction.value} {entry.curve.kind}"
                )
            elif node.has_heading and abs(angle_diff(entry.yaw_end, node.pose.yaw)) > TANGENT_TOLERANCE_RAD:
                problems.append(
                    f"{kind} node '{node.id}': the forks would arrive heading {math.degrees(entry.yaw_end):.1f} deg, "
                    f"the node says {math.degrees(node.pose.yaw):.1f} deg"
                )
        if not self._graph.has_edge(node.id, pre):
            problems.append(f"{kind} node '{node.id}': no reverse edge back to its pre-pallet node '{pre}'")
        elif self.edge(node.id, pre).direction is not Direction.REVERSE:
            problems.append(f"{kind} node '{node.id}': edge '{node.id}->{pre}' must be driven in reverse")
        return problems
