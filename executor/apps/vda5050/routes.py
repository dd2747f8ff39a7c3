"""Orders against the roadmap and the vehicle: node matching, edges, headings, edge fields, node actions.

- Nodes match a roadmap node by `nodeId`, or else by `nodePosition` within `allowedDeviationXY` (and
  `allowedDeviationTheta` when `theta` is given); 0 or no deviation means the truck's normal tolerance,
  `DEFAULT_DEVIATION_XY` and `DEFAULT_DEVIATION_THETA`. A node on another map (`mapId`) has no route.
- Edges must be roadmap edges between the matched nodes, drivable one after the other: a forklift cannot
  turn on the spot, so each edge leaves a node with the heading the truck arrives with (`noRouteError`).
- Edge fields: `maxSpeed`, `maxHeight`, `minHeight`, `orientation` (+`orientationType`), `maxRotationSpeed`,
  `trajectory` (must lie on the roadmap curve, `nurbs`), `corridor` (the truck keeps to the curve, always
  inside) and `length` are honoured; `direction` (line-guided junctions) is not (`orderError`).
- Node actions follow `actions.CATALOGUE`; a `pick` or `drop` node is entered from its pre-pallet node,
  which must be the order's node before it and (when the order goes on) after it; picks and drops
  alternate with the load on the forks. Edge actions are not supported.

Public API: `RouteChecker`, `Problem`, `DEFAULT_DEVIATION_XY`, `DEFAULT_DEVIATION_THETA`,
`HEADING_TOLERANCE`, `LIFT_MARGIN_M`, `pallet_name`, `load_type_names`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field

import numpy as np

from palletpilot.control.vehicle import VehicleParams
from palletpilot.executor.apps.vda5050 import nurbs
from palletpilot.executor.apps.vda5050.actions import CATALOGUE, LOAD_HANDLING_DEVICE, NODE, check_parameters
from palletpilot.executor.apps.vda5050.models import Action, BlockingType, ErrorRef, OrderEdge, OrderNode
from palletpilot.geometry import angle_diff
from palletpilot.perception.specs import BUILTIN_PALLETS, PALLET_ALIASES
from palletpilot.roadmap import Direction, Edge, NodeType, Roadmap

DEFAULT_DEVIATION_XY = 0.25
"""m: the truck's normal tolerance at a node (an order's `allowedDeviationXY` 0 or absent)."""
DEFAULT_DEVIATION_THETA = math.radians(10.0)
"""rad: the truck's normal heading tolerance at a node (`allowedDeviationTheta` absent)."""
HEADING_TOLERANCE = math.radians(5.0)
"""rad: consecutive edges join when the truck's heading differs by less than this."""
LIFT_MARGIN_M = 0.15
"""m: a pick or drop height leaves this much of the mast's range to lift the load (as the mission check)."""

Problem = tuple[str, list[ErrorRef]]
"""A problem line and the error references that name what is at fault."""


def pallet_name(load_type: str) -> str | None:
    """The built-in pallet type of a `loadType` (any case: `eur`, `EPAL`, `industrial`, ...), or None."""
    key = PALLET_ALIASES.get(load_type.lower(), load_type.lower())
    return key if key in BUILTIN_PALLETS else None


def load_type_names() -> list[str]:
    """Every `loadType` an order may name, as the factsheet's loadSets list them: the built-in pallet types,
    then their aliases in capitals (`EPAL`); orders match them in any case."""
    return [*BUILTIN_PALLETS, *(alias.upper() for alias in PALLET_ALIASES)]


@dataclass
class Checked:
    """The outcome of checking an order's nodes and edges: the roadmap node of every node (None where none
    matched), the roadmap edge of every edge, and the problems by error type."""

    rm: list[str | None]
    edges: list[Edge | None] = field(default_factory=list)
    no_route: list[Problem] = field(default_factory=list)
    order: list[Problem] = field(default_factory=list)


class RouteChecker:
    """Checks orders against one roadmap (its map id `map_id`) and one vehicle."""

    def __init__(self, roadmap: Roadmap, map_id: str, params: VehicleParams) -> None:
        self.roadmap = roadmap
        self.map_id = map_id
        self.params = params
        nodes = [n for n in roadmap.nodes() if not n.temporary]
        self._ids = [n.id for n in nodes]
        self._xy = np.array([[n.pose.x, n.pose.y] for n in nodes]) if nodes else np.zeros((0, 2))

    # -- nodes ---------------------------------------------------------------------------------
    def match(self, node: OrderNode) -> tuple[str | None, Problem | None]:
        """The roadmap node of an order node: by id, else the nearest by position within its deviation."""
        ref: list[ErrorRef] = [("node.nodeId", node.node_id)]
        pos = node.position
        if pos is not None and pos.get("mapId") != self.map_id:
            return None, (
                f"node '{node.node_id}' is on map '{pos.get('mapId')}'; this truck has map '{self.map_id}'",
                ref,
            )
        if node.node_id in self.roadmap:
            rm = self.roadmap.node(node.node_id)
            if rm.temporary:
                return None, (f"node '{node.node_id}' is not a node of the roadmap", ref)
            if pos is not None:
                off = math.hypot(float(pos["x"]) - rm.pose.x, float(pos["y"]) - rm.pose.y)
                if off > _xy_tolerance(node):
                    return None, (
                        f"node '{node.node_id}': nodePosition is {off:.2f} m from the roadmap node of that id "
                        f"(allowed {_xy_tolerance(node):.2f} m)",
                        ref,
                    )
            return node.node_id, None
        if pos is None or not len(self._ids):
            return None, (f"node '{node.node_id}' is not a roadmap node and has no nodePosition to match", ref)
        d = np.hypot(self._xy[:, 0] - float(pos["x"]), self._xy[:, 1] - float(pos["y"]))
        for i in np.argsort(d):
            if d[i] > _xy_tolerance(node):
                break
            candidate = self.roadmap.node(self._ids[i])
            if "theta" in pos and not _theta_ok(node, candidate.pose.yaw, axis=not candidate.has_heading):
                continue
            return candidate.id, None
        return None, (
            f"node '{node.node_id}': no roadmap node within {_xy_tolerance(node):.2f} m of "
            f"({float(pos['x']):.2f}, {float(pos['y']):.2f})",
            ref,
        )

    def stands_at(self, node: OrderNode, rm_id: str, x: float, y: float, theta: float) -> Problem | None:
        """Why the truck at (x, y, theta) is not on `node` (matched to `rm_id`) within its deviation, or None."""
        pos = node.position
        px, py = (
            (float(pos["x"]), float(pos["y"]))
            if pos
            else (self.roadmap.node(rm_id).pose.x, self.roadmap.node(rm_id).pose.y)
        )
        off = math.hypot(x - px, y - py)
        ref: list[ErrorRef] = [("node.nodeId", node.node_id)]
        if off > _xy_tolerance(node):
            return (
                f"the first node '{node.node_id}' is {off:.2f} m from the truck (allowed {_xy_tolerance(node):.2f} m): "
                "not trivially reachable",
                ref,
            )
        if pos is not None and "theta" in pos and not _theta_ok(node, theta):
            return (f"the truck's heading is not within allowedDeviationTheta of node '{node.node_id}'", ref)
        return None

    # -- a whole order ----------------------------------------------------------------------------
    def check(
        self,
        nodes: list[OrderNode],
        edges: list[OrderEdge],
        known: list[str],
        heading: float,
        loaded: bool,
    ) -> Checked:
        """Check `nodes` and `edges` (an order, or the current order's prefix plus an update): `known` maps the
        prefix's nodes already (its last node is where the new part joins, the truck arriving there with
        `heading`); `loaded`: the forks carry a load at that point. Nodes and edges before the join are not
        checked again."""
        first = max(len(known) - 1, 0)
        out = Checked(rm=list(known) + [None] * (len(nodes) - len(known)))
        for i in range(len(known), len(nodes)):
            rm, problem = self.match(nodes[i])
            out.rm[i] = rm
            if problem is not None:
                out.no_route.append(problem)
        out.edges = [None] * len(edges)
        h: float | None = heading
        for i in range(first, len(edges)):
            h = self._edge(out, nodes, edges, i, h)
        if known:  # a pick or drop at the join: the update's next node must be where the truck backs out to
            k = len(known) - 1
            for a in nodes[k].actions:
                if a.action_type in ("pick", "drop") and k + 1 < len(nodes):
                    refs = [("node.nodeId", nodes[k].node_id), ("actionId", a.action_id), ("actionType", a.action_type)]
                    out.order += self._handling(a.action_type, a, nodes, out.rm, k, refs, join=True)
        for i in range(len(known), len(nodes)):
            loaded = self._node_actions(out, nodes, i, loaded)
        for e in edges[first:]:
            for a in e.actions:
                out.order.append(
                    (
                        f"edge '{e.edge_id}': action '{a.action_type}' is not supported on edges by this truck",
                        [("edge.edgeId", e.edge_id), ("actionId", a.action_id), ("actionType", a.action_type)],
                    )
                )
        return out

    def _edge(
        self, out: Checked, nodes: list[OrderNode], edges: list[OrderEdge], i: int, h: float | None
    ) -> float | None:
        e = edges[i]
        a, b = out.rm[i], out.rm[i + 1]
        ref: list[ErrorRef] = [("edge.edgeId", e.edge_id)]
        if a is None or b is None:
            return None
        if not self.roadmap.graph.has_edge(a, b) or self.roadmap.edge(a, b).temporary:
            out.no_route.append((f"edge '{e.edge_id}': the roadmap has no edge from '{a}' to '{b}'", ref))
            return None
        rm_edge = self.roadmap.edge(a, b)
        out.edges[i] = rm_edge
        if h is not None and abs(angle_diff(rm_edge.yaw_start, h)) > HEADING_TOLERANCE:
            out.no_route.append(
                (
                    f"edge '{e.edge_id}': the truck reaches '{a}' heading {math.degrees(h):.0f} deg and cannot leave "
                    f"along '{a}->{b}' heading {math.degrees(rm_edge.yaw_start):.0f} deg (no turning on the spot)",
                    ref,
                )
            )
        end = nodes[i + 1]
        if end.position is not None and "theta" in end.position and not _theta_ok(end, rm_edge.yaw_end):
            out.no_route.append(
                (
                    f"node '{end.node_id}': the truck arrives heading {math.degrees(rm_edge.yaw_end):.0f} deg, not "
                    f"theta {math.degrees(float(end.position['theta'])):.0f} deg",
                    [("node.nodeId", end.node_id)],
                )
            )
        out.order += self._edge_fields(e, rm_edge)
        return rm_edge.yaw_end

    def _edge_fields(self, e: OrderEdge, rm: Edge) -> list[Problem]:
        """Problems with the optional fields of an edge this truck honours or cannot use."""
        raw, p = e.raw, self.params
        out: list[Problem] = []

        def bad(field_name: str, why: str) -> None:
            out.append(
                (f"edge '{e.edge_id}': {field_name}: {why}", [("edge.edgeId", e.edge_id), ("field", field_name)])
            )

        if "maxSpeed" in raw and float(raw["maxSpeed"]) <= 0.0:
            bad("maxSpeed", "must be above 0")
        if "maxHeight" in raw and float(raw["maxHeight"]) < p.body.height:
            bad("maxHeight", f"{float(raw['maxHeight']):.2f} m is below the truck's height {p.body.height:.2f} m")
        if "minHeight" in raw and float(raw["minHeight"]) > p.mast.travel_height_empty:
            bad("minHeight", "the forks travel at their travel height; carrying them higher is not supported")
        if "direction" in raw:
            bad("direction", "is for line-guided trucks; this truck follows the roadmap's curves")
        if "orientation" in raw:
            want = float(raw["orientation"])
            if raw.get("orientationType", "TANGENTIAL") == "GLOBAL":
                ok = all(abs(angle_diff(y, want)) <= HEADING_TOLERANCE for y in (rm.yaw_start, rm.yaw_end))
            else:
                ok = abs(angle_diff(want, 0.0 if rm.direction is Direction.FORWARD else math.pi)) <= HEADING_TOLERANCE
            if not ok:
                bad("orientation", f"the roadmap edge is driven {rm.direction.value}; the truck cannot turn on it")
        if "maxRotationSpeed" in raw:
            speed = min(rm.speed_limit, float(raw.get("maxSpeed", math.inf)), p.max_speed_forward)
            omega = speed * rm.curve.max_abs_curvature()
            if omega > float(raw["maxRotationSpeed"]) + 1e-9:
                bad("maxRotationSpeed", f"the curve turns at up to {omega:.2f} rad/s at its speed limit")
        if "trajectory" in raw:
            why = nurbs.trajectory_problem(raw["trajectory"])
            if why is None:
                off = nurbs.deviation(raw["trajectory"], rm.curve)
                if off > nurbs.TOLERANCE_M:
                    why = f"lies up to {off:.2f} m off the roadmap curve (the truck drives the roadmap's curves)"
            if why is not None:
                bad("trajectory", why)
        return out

    def _node_actions(self, out: Checked, nodes: list[OrderNode], i: int, loaded: bool) -> bool:
        """Check node i's actions; returns whether the forks carry a load after them."""
        node, rm = nodes[i], out.rm[i]
        for a in node.actions:
            refs: list[ErrorRef] = [
                ("node.nodeId", node.node_id),
                ("actionId", a.action_id),
                ("actionType", a.action_type),
            ]
            spec = CATALOGUE.get(a.action_type)
            if spec is None or NODE not in spec.scopes:
                where = "at all" if spec is None else "on nodes"
                out.order.append((f"node '{node.node_id}': action '{a.action_type}' is not supported {where}", refs))
                continue
            for why, keys in check_parameters(a, spec):
                out.order.append((f"action '{a.action_id}': {why}", refs + keys))
            if (
                a.action_type == "startCharging"
                and rm is not None
                and self.roadmap.node(rm).type is not NodeType.CHARGING
            ):
                out.order.append((f"node '{node.node_id}': startCharging needs a charging node", refs))
            if a.action_type not in ("pick", "drop"):
                continue
            if len(node.actions) > 1:
                out.order.append((f"node '{node.node_id}': a {a.action_type} node carries no other action", refs))
            if a.blocking_type is BlockingType.NONE:
                out.order.append(
                    (
                        f"action '{a.action_id}': a {a.action_type} stops the truck; blockingType NONE is not possible",
                        refs,
                    )
                )
            out.order += self._handling(a.action_type, a, nodes, out.rm, i, refs)
            if (a.action_type == "pick") == loaded:
                state = "carry a load already" if loaded else "are empty"
                out.order.append((f"action '{a.action_id}': the forks {state} at node '{node.node_id}'", refs))
        return _after_actions(node, loaded)

    def _handling(
        self,
        kind: str,
        a: Action,
        nodes: list[OrderNode],
        rm: list[str | None],
        i: int,
        refs: list[ErrorRef],
        join: bool = False,
    ) -> list[Problem]:
        """Problems of a pick or drop at node i: the node's type, its pre-pallet node before and after it in
        the order, the height, loadType and lhd. `join`: only the node after it (the join of an update)."""
        out: list[Problem] = []
        here = rm[i]
        if here is None:
            return out
        node = self.roadmap.node(here)
        types = (NodeType.PALLET,) if kind == "pick" else (NodeType.DROP, NodeType.PALLET)
        if node.type not in types or node.pre_pallet is None:
            want = "a pallet node" if kind == "pick" else "a drop or pallet node"
            return [
                (
                    f"node '{nodes[i].node_id}': a {kind} needs {want} with a pre-pallet node, "
                    f"not a {node.type.value} node",
                    refs,
                )
            ]
        pre = node.pre_pallet
        if not join and (i == 0 or rm[i - 1] != pre):
            out.append(
                (
                    f"node '{nodes[i].node_id}': a {kind} is entered from its pre-pallet node '{pre}', "
                    "which must be the order's node before it",
                    refs,
                )
            )
        if i + 1 < len(nodes) and rm[i + 1] is not None and rm[i + 1] != pre:
            out.append(
                (
                    f"node '{nodes[i].node_id}': after a {kind} the truck backs out to '{pre}', "
                    "which must be the order's next node",
                    refs,
                )
            )
        if join:
            return out
        mast = self.params.mast
        height = a.param("height")
        if isinstance(height, (int, float)) and not isinstance(height, bool):
            if not mast.min_height <= float(height) <= mast.max_height - LIFT_MARGIN_M:
                out.append(
                    (
                        f"action '{a.action_id}': height {float(height):.2f} m is outside the mast's range "
                        f"{mast.min_height:.2f}..{mast.max_height - LIFT_MARGIN_M:.2f} m",
                        [*refs, ("actionParameter", "height")],
                    )
                )
        load_type = a.param("loadType")
        if isinstance(load_type, str) and pallet_name(load_type) is None:
            known = ", ".join(load_type_names())
            out.append(
                (
                    f"action '{a.action_id}': loadType '{load_type}' is not a pallet type of this truck (the "
                    f"factsheet's loadSets: {known}; any case)",
                    [*refs, ("actionParameter", "loadType")],
                )
            )
        lhd = a.param("lhd")
        if isinstance(lhd, str) and lhd != LOAD_HANDLING_DEVICE:
            out.append(
                (
                    f"action '{a.action_id}': lhd '{lhd}' is not this truck's ({LOAD_HANDLING_DEVICE})",
                    [*refs, ("actionParameter", "lhd")],
                )
            )
        return out


def _after_actions(node: OrderNode, loaded: bool) -> bool:
    for a in node.actions:
        if a.action_type == "pick":
            loaded = True
        elif a.action_type == "drop":
            loaded = False
    return loaded


def _xy_tolerance(node: OrderNode) -> float:
    dev = float(node.position.get("allowedDeviationXY", 0.0)) if node.position else 0.0
    return dev if dev > 0.0 else DEFAULT_DEVIATION_XY


def _theta_ok(node: OrderNode, yaw: float, axis: bool = False) -> bool:
    """True when `yaw` is within the node's allowed theta deviation of its `theta` (either way along an axis)."""
    assert node.position is not None
    theta = float(node.position["theta"])
    dev = float(node.position.get("allowedDeviationTheta", DEFAULT_DEVIATION_THETA))
    off = abs(angle_diff(yaw, theta))
    if axis:
        off = min(off, math.pi - off)
    return off <= max(dev, 1e-6)
