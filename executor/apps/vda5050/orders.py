"""The order acceptance flow of VDA 5050 (section 6.6, Figure 8) as a pure state machine: `OrderManager`.

No MQTT, no vehicle: messages in, decisions and state fields out, so every rule is unit-tested.

Acceptance of an `order` message, in this order:

1. Valid? The schema (`validation`), a protocol of major version 2 (2.0.x and 2.1.x masters), and the
   structure: at least one node, one edge fewer than nodes, edges joining consecutive nodes, sequenceIds
   increasing along node, edge, node, ..., the base (released) before the horizon with the first node
   released, unique actionIds, `allowedDeviationTheta` >= 0. Otherwise `validationError`.
2. Same `orderId` as the current order: a lower `orderUpdateId` is stale (`orderUpdateError`, the current
   order goes on), an equal one is a resend and ignored. A higher one is an update; a new `orderId` while
   the truck still executes (nodeStates left or order actions neither FINISHED nor FAILED) must stitch too.
3. Stitching: while executing, the first node must be the decision point (the last released node: same
   nodeId and sequenceId); when the order is done, it must be `lastNodeId` / `lastNodeSequenceId`.
   Otherwise `orderUpdateError`. The stitching node keeps the content it had (section 6.6.2); the old
   horizon is replaced by the update's nodes and edges. After a restart that found the truck away from
   lastNodeId (`stitch_block`, see `persist`), nothing stitches (`orderUpdateError`) until a new order.
4. Route and actions (`routes.RouteChecker`): nodes on the roadmap by id or position, roadmap edges
   drivable in sequence (`noRouteError`), edge fields and node actions this truck can perform, no zone set
   (`orderError`); an order is refused while charging or with a FATAL vehicle fault (`orderError`).
5. A new order (not executing) starts where the truck stands: within the first node's deviation range,
   else `noRouteError` (checked before the route, so a far order is refused for its distance). After a
   cancel part way along an edge (section 6.6.3.1, `VehicleView.on_edge`) it may start at lastNodeId with a
   deviation range that reaches the truck, or at a node off the roadmap where the truck stands (a temporary
   node): either way it goes on along that edge (the heading is the edge's, not the cancelled leg's).
   Accepted: node and edge states of the new order, the action states of its actions (WAITING; earlier
   action states go, running instant actions stay), the first node traversed at once.

A rejection is a WARNING naming `headerId`, `topic`, `orderId`, `orderUpdateId` and what is at fault
(`node.nodeId`, `edge.edgeId`, `actionId`, `actionParameter`, `field`); rejections are reported until an
order is accepted. Progress: `arrive(node)` traverses the next node, `plan_next()` says what to do next
(`Leg`): run a node's actions, move along released edges to the next stop, or a pick or drop.

Public API: `OrderManager`, `VehicleView`, `Decision`, `Leg`.
"""

from __future__ import annotations

import itertools
import threading
from dataclasses import dataclass, field
from typing import Any, Literal

from palletpilot.control.vehicle import VehicleParams
from palletpilot.executor.apps.vda5050 import validation
from palletpilot.executor.apps.vda5050.actions import (
    CATALOGUE,
    EDGE,
    INSTANT,
    NODE,
    ActionRecord,
    ActionTable,
    check_parameters,
)
from palletpilot.executor.apps.vda5050.midedge import OnEdge
from palletpilot.executor.apps.vda5050.models import (
    INSTANT_ACTION_ERROR,
    NO_ORDER_TO_CANCEL,
    NO_ROUTE_ERROR,
    ORDER_ERROR,
    ORDER_UPDATE_ERROR,
    VALIDATION_ERROR,
    Action,
    ActionStatus,
    AgvError,
    ErrorLevel,
    ErrorRef,
    Order,
    OrderEdge,
    OrderNode,
)
from palletpilot.executor.apps.vda5050.routes import Problem, RouteChecker
from palletpilot.roadmap import Roadmap

SUPPORTED_MAJOR = "2"
"""Messages of protocol versions 2.x are read (2.0.0 and 2.1.0 masters)."""
MAX_RECEIVED = 16
"""`OrderManager.received` keeps this many order messages (the journal's copy of the order as received)."""


@dataclass(frozen=True)
class VehicleView:
    """What the acceptance flow needs of the truck: its pose (map frame, m and rad), the heading it drives
    off with (rad: along its node's axis), whether the forks carry a load, whether it charges, a FATAL
    fault if any, and the roadmap edge it stands on part way (`midedge.OnEdge`), if any."""

    x: float
    y: float
    theta: float
    heading: float
    loaded: bool = False
    charging: bool = False
    fault: str | None = None
    on_edge: OnEdge | None = None
    """Where the truck stands part way along a roadmap edge out of lastNodeId (after a cancel), if it does."""


@dataclass(frozen=True)
class Decision:
    """What became of an order message: `new`, `update` (same orderId), `stitch` (a new orderId appended
    to the running one), `ignored` (a resend) or `rejected` with its error."""

    kind: Literal["new", "update", "stitch", "ignored", "rejected"]
    error: AgvError | None = None

    @property
    def accepted(self) -> bool:
        """True for new, update and stitch."""
        return self.kind in ("new", "update", "stitch")


@dataclass(frozen=True)
class Leg:
    """The next thing to do: `actions` (run the node actions of the current node), `move` (drive the
    roadmap route `route` through released nodes), `pick` or `drop` (at roadmap node `route[-1]`, the
    order's node `index`)."""

    kind: Literal["actions", "move", "pick", "drop"]
    index: int
    route: tuple[str, ...] = ()
    actions: tuple[Action, ...] = field(default_factory=tuple)


def _major(version: object) -> str:
    return str(version).split(".", 1)[0]


class OrderManager:
    """The AGV's order, its node, edge and action states, and the order-related errors (thread-safe)."""

    def __init__(self, roadmap: Roadmap, map_id: str, params: VehicleParams) -> None:
        self.routes = RouteChecker(roadmap, map_id, params)
        self.order_id = ""
        self.order_update_id = 0
        self.last_node_id = ""
        self.last_node_seq = 0
        self.nodes: list[OrderNode] = []
        self.edges: list[OrderEdge] = []
        self.rm: list[str] = []
        """The roadmap node of every order node."""
        self.cursor = 0
        """Index of the next node to traverse: `nodes[:cursor]` are traversed."""
        self.actions = ActionTable()
        self.errors: list[AgvError] = []
        """Order-related warnings: rejections, noOrderToCancel, instant action errors, failed actions."""
        self.last_rm = ""
        """The roadmap node of `last_node_id` (kept after a cancel)."""
        self.received: list[dict[str, Any]] = []
        """The order messages accepted since the last new order, as received (the last `MAX_RECEIVED`)."""
        self.stitch_block: str | None = None
        """Why no order may stitch at the current one (after a restart the truck is not at lastNodeId): every
        update or stitch is refused with it (`orderUpdateError`) until a new order is accepted or initPosition
        sets the node."""
        self.lock = threading.RLock()

    # -- queries -----------------------------------------------------------------------------------
    def executing(self) -> bool:
        """Step 3 of Figure 8: nodeStates left, or order actions neither FINISHED nor FAILED."""
        with self.lock:
            return self.cursor < len(self.nodes) or bool(self.actions.active((NODE, EDGE)))

    def base_end(self) -> int:
        """Index of the decision point (the last released node); -1 without an order."""
        released = [i for i, n in enumerate(self.nodes) if n.released]
        return released[-1] if released else -1

    def node_states(self) -> list[dict[str, Any]]:
        """`nodeStates`: the nodes still to traverse, base and horizon."""
        with self.lock:
            return [n.state() for n in self.nodes[self.cursor :]]

    def edge_states(self) -> list[dict[str, Any]]:
        """`edgeStates`: the edges whose end node is not yet traversed."""
        with self.lock:
            return [e.state() for e in self.edges[max(self.cursor - 1, 0) :]] if self.nodes else []

    def has_horizon(self) -> bool:
        """True when the order has unreleased nodes."""
        return any(not n.released for n in self.nodes[self.cursor :])

    # -- orders ------------------------------------------------------------------------------------
    def receive_order(self, doc: dict[str, Any], view: VehicleView) -> Decision:
        """Run the acceptance flow on an order message (see the module docstring)."""
        with self.lock:
            refs: list[ErrorRef] = [("headerId", str(doc.get("headerId", ""))), ("topic", "order")]
            for key in ("orderId", "orderUpdateId"):
                if isinstance(doc.get(key), (str, int)) and not isinstance(doc.get(key), bool):
                    refs.append((key, str(doc[key])))
            problems = [(p, [("field", p.split(":", 1)[0])]) for p in validation.problems("order", doc)]
            if not problems and _major(doc["version"]) != SUPPORTED_MAJOR:
                problems = [(f"protocol version {doc['version']} is not 2.x", [("field", "version")])]
            if problems:
                return self._reject(VALIDATION_ERROR, "the order is not valid", refs, problems)
            order = Order.from_json(doc)
            problems = _structure(order)
            ids = [a.action_id for n in order.nodes for a in n.actions] + [
                a.action_id for e in order.edges for a in e.actions
            ]
            if order.order_id == self.order_id and order.order_update_id > self.order_update_id:
                known = {r.action.action_id for r in self.actions} - self._horizon_action_ids()
                problems += [(f"actionId '{i}' is already in use", [("actionId", i)]) for i in ids if i in known]
            if problems:
                return self._reject(VALIDATION_ERROR, "the order is not valid", refs, problems)
            if order.order_id == self.order_id and self.order_id:
                if order.order_update_id < self.order_update_id:
                    why = f"orderUpdateId {order.order_update_id} is older than the current {self.order_update_id}"
                    return self._reject(ORDER_UPDATE_ERROR, why, refs, [])
                if order.order_update_id == self.order_update_id:
                    return Decision("ignored")
                kind: Literal["new", "update", "stitch"] = "update"
            else:
                kind = "stitch" if self.executing() else "new"
            if kind != "new" and self.stitch_block is not None:
                why = f"the order cannot continue from lastNodeId '{self.last_node_id}': {self.stitch_block}"
                return self._reject(ORDER_UPDATE_ERROR, why, [*refs, ("lastNodeId", self.last_node_id)], [])
            decision = self._continue(order, kind, view, refs)
            if decision.accepted:
                self.received = [*([] if decision.kind == "new" else self.received), doc][-MAX_RECEIVED:]
            return decision

    def _continue(
        self, order: Order, kind: Literal["new", "update", "stitch"], view: VehicleView, refs: list[ErrorRef]
    ) -> Decision:
        first = order.nodes[0]
        join = -1
        if kind != "new":
            join = self.base_end() if self.executing() else self.cursor - 1
            if self.executing():
                at = self.nodes[join]
                ok = (at.node_id, at.sequence_id) == (first.node_id, first.sequence_id)
                where = f"the decision point '{at.node_id}' (sequenceId {at.sequence_id})"
            else:
                ok = (self.last_node_id, self.last_node_seq) == (first.node_id, first.sequence_id)
                where = f"lastNodeId '{self.last_node_id}' (lastNodeSequenceId {self.last_node_seq})"
            if not ok:
                why = f"the first node '{first.node_id}' (sequenceId {first.sequence_id}) is not {where}"
                return self._reject(ORDER_UPDATE_ERROR, why, [*refs, ("node.nodeId", first.node_id)], [])
        if join >= 0:  # the current order up to the stitching node, which keeps its content
            nodes = self.nodes[: join + 1] + list(order.nodes[1:])
            edges = self.edges[:join] + list(order.edges)
            known = self.rm[: join + 1]
            heading = view.heading if join == 0 else self.routes.roadmap.edge(self.rm[join - 1], self.rm[join]).yaw_end
        else:  # a new order, or an update after a cancel (the stitching node is lastNodeId)
            nodes, edges, known, heading = list(order.nodes), list(order.edges), [], view.heading
        on = view.on_edge if kind == "new" and self._starts_on_edge(first, view.on_edge) else None
        if on is not None:  # section 6.6.3.1: from lastNodeId (wide deviation) or a node where the truck stands
            known, heading = [on.start], self.routes.roadmap.edge(on.start, on.end).yaw_start
        loaded = self._loaded_at_join(view.loaded)
        checked = self.routes.check(nodes, edges, known, heading, loaded)
        if kind == "new" and checked.rm[0] is not None:  # the real cause first: not where the truck stands
            problem = self.routes.stands_at(first, checked.rm[0], view.x, view.y, view.theta)
            if problem is not None:
                return self._reject(NO_ROUTE_ERROR, "the order does not start where the truck stands", refs, [problem])
        if on is not None and len(nodes) > 1 and checked.rm[1] != on.end:
            why = (
                f"the truck stands on edge '{on.start}->{on.end}', {on.s:.2f} m past '{on.start}', and cannot turn "
                f"on the spot: an order from there goes on along that edge to '{on.end}'"
            )
            checked.no_route.insert(0, (why, [("node.nodeId", first.node_id)]))
        if checked.no_route:
            return self._reject(
                NO_ROUTE_ERROR, "no route for the order on this truck's roadmap", refs, checked.no_route
            )
        problems = list(checked.order)
        if order.zone_set_id is not None:
            problems.append(("this truck uses no zones: give no zoneSetId", [("zoneSetId", order.zone_set_id)]))
        if view.charging:
            problems.append(
                ("the truck is charging: stop charging first (stopCharging)", [("batteryState.charging", "true")])
            )
        if view.fault:
            problems.append((f"the truck cannot drive: {view.fault}", [("errorLevel", "FATAL")]))
        if problems:
            return self._reject(ORDER_ERROR, "the order asks for what this truck cannot do", refs, problems)
        rm = [r for r in checked.rm if r is not None]
        self._accept(order, kind, nodes, edges, rm, join)
        return Decision(kind)

    def _starts_on_edge(self, first: OrderNode, on: OnEdge | None) -> bool:
        """A new order starts on the edge the truck stands on: its first node is that edge's start (lastNodeId,
        its deviation range reaching the truck: `stands_at` checks it) or a node that is not on the roadmap (a
        temporary node where the truck stands)."""
        if on is None:
            return False
        return first.node_id == on.start or (first.node_id not in self.routes.roadmap and first.position is not None)

    def _horizon_action_ids(self) -> set[str]:
        """The action ids of the current horizon (an update replaces them)."""
        end = self.base_end()
        return {a.action_id for n in self.nodes[end + 1 :] for a in n.actions} | {
            a.action_id for e in self.edges[max(end, 0) :] for a in e.actions
        }

    def _loaded_at_join(self, loaded: bool) -> bool:
        """The load on the forks once the current base's pending picks and drops are done."""
        horizon = self._horizon_action_ids()
        for r in self.actions:
            if (
                r.scope == NODE
                and not r.final
                and r.action.action_type in ("pick", "drop")
                and r.action.action_id not in horizon
            ):
                loaded = r.action.action_type == "pick"
        return loaded

    def _accept(
        self,
        order: Order,
        kind: str,
        nodes: list[OrderNode],
        edges: list[OrderEdge],
        rm: list[str],
        join: int,
    ) -> None:
        self.errors = [
            e for e in self.errors if e.level is ErrorLevel.FATAL
        ]  # warnings last until an order is accepted
        self.order_id, self.order_update_id = order.order_id, order.order_update_id
        if kind == "new":
            self.stitch_block = None  # it starts where the truck stands (checked)
        if kind == "new" or join < 0:
            if kind == "new":
                self.actions.new_order()
            self.nodes, self.edges, self.rm, self.cursor = nodes, edges, rm, 0
            new_nodes, new_edges = (nodes, edges) if kind == "new" else (nodes[1:], edges)
        else:
            self.actions.remove(self._horizon_action_ids())
            self.nodes, self.edges, self.rm = nodes, edges, rm
            new_nodes, new_edges = nodes[join + 1 :], edges[join:]
        for n in new_nodes:
            for a in n.actions:
                self.actions.add(a, NODE)
        for e in new_edges:
            for a in e.actions:
                self.actions.add(a, EDGE)
        if self.cursor == 0:  # the first node: the truck stands on it (or it is lastNodeId of an update)
            node = self.nodes[0]
            self.cursor = 1
            self.last_node_id, self.last_node_seq = node.node_id, node.sequence_id
            self.last_rm = self.rm[0]

    def _reject(self, error_type: str, what: str, refs: list[ErrorRef], problems: list[Problem]) -> Decision:
        lines = [p for p, _ in problems]
        extra: list[ErrorRef] = []
        for _, r in problems:
            extra += [x for x in r if x not in extra]
        error = AgvError(
            error_type,
            ErrorLevel.WARNING,
            what + (": " + "; ".join(lines[:10]) if lines else ""),
            tuple(refs + extra[:40]),
            "the truck keeps the order it had; send a corrected order",
        )
        self.errors.append(error)
        return Decision("rejected", error)

    # -- progress ----------------------------------------------------------------------------------
    def can_enter(self, to_node: str) -> bool:
        """True when the next edge is released and leads to roadmap node `to_node` (also released)."""
        with self.lock:
            i = self.cursor
            return (
                0 < i < len(self.nodes)
                and self.edges[i - 1].released
                and self.nodes[i].released
                and self.rm[i] == to_node
            )

    def arrive(self, rm_node: str) -> OrderNode | None:
        """Traverse the next node when it is released and matches roadmap node `rm_node`; the node, or None."""
        with self.lock:
            if not self.can_enter(rm_node):
                return None
            node = self.nodes[self.cursor]
            self.last_rm = self.rm[self.cursor]
            self.cursor += 1
            self.last_node_id, self.last_node_seq = node.node_id, node.sequence_id
            return node

    def plan_next(self) -> Leg | None:
        """What to do next from the last traversed node; None when waiting (no released way on, or done)."""
        with self.lock:
            i = self.cursor - 1
            if i < 0 or i >= len(self.nodes):
                return None
            here = self.nodes[i]
            pending = tuple(
                a
                for a in here.actions
                if a.action_type not in ("pick", "drop")
                and a.action_id in self.actions
                and self.actions.get(a.action_id).status is ActionStatus.WAITING
            )
            if pending:
                return Leg("actions", i, (self.rm[i],), pending)
            if not self.can_enter(self.rm[self.cursor] if self.cursor < len(self.rm) else ""):
                return None
            nxt = self.nodes[self.cursor]
            for a in nxt.actions:
                if a.action_type in ("pick", "drop") and self.actions.get(a.action_id).status is ActionStatus.WAITING:
                    return Leg(
                        "pick" if a.action_type == "pick" else "drop",
                        self.cursor,
                        (self.rm[i], self.rm[self.cursor]),
                        (a,),
                    )
            j = self.cursor
            while (
                j + 1 < len(self.nodes)
                and not self.nodes[j].actions
                and self.nodes[j + 1].released
                and self.edges[j].released
                and not any(a.action_type in ("pick", "drop") for a in self.nodes[j + 1].actions)
            ):
                j += 1
            return Leg("move", j, tuple(self.rm[i : j + 1]))

    # -- instant actions ---------------------------------------------------------------------------
    def receive_instant_actions(self, doc: dict[str, Any]) -> list[ActionRecord]:
        """Record an instantActions message: its actions WAITING to be run (returned), unknown or malformed
        ones FAILED with an `instantActionError`, a `cancelOrder` without an order FAILED with
        `noOrderToCancel` (section 6.6.3.2); a message failing its schema is one `validationError`."""
        with self.lock:
            refs: list[ErrorRef] = [("headerId", str(doc.get("headerId", ""))), ("topic", "instantActions")]
            problems = [(p, [("field", p.split(":", 1)[0])]) for p in validation.problems("instantActions", doc)]
            if not problems and _major(doc["version"]) != SUPPORTED_MAJOR:
                problems = [(f"protocol version {doc['version']} is not 2.x", [("field", "version")])]
            if problems:
                self._reject(VALIDATION_ERROR, "the instantActions message is not valid", refs, problems)
                return []
            out: list[ActionRecord] = []
            for item in doc["actions"]:
                action = Action.from_json(item)
                arefs = [*refs, ("actionId", action.action_id), ("actionType", action.action_type)]
                if action.action_id in self.actions:
                    self.errors.append(
                        AgvError(
                            INSTANT_ACTION_ERROR,
                            ErrorLevel.WARNING,
                            f"actionId '{action.action_id}' is already in use",
                            tuple(arefs),
                        )
                    )
                    continue
                spec = CATALOGUE.get(action.action_type)
                why = None
                if spec is None or INSTANT not in spec.scopes:
                    why = f"action '{action.action_type}' is not supported as an instant action by this truck"
                else:
                    bad = check_parameters(action, spec)
                    if bad:
                        why = "; ".join(p for p, _ in bad)
                        arefs += [r for _, rs in bad for r in rs]
                record = self.actions.add(action, INSTANT)
                if why is not None:
                    self.actions.set(action.action_id, ActionStatus.FAILED, why)
                    self.errors.append(AgvError(INSTANT_ACTION_ERROR, ErrorLevel.WARNING, why, tuple(arefs)))
                elif action.action_type == "cancelOrder" and not self.executing():
                    self.actions.set(action.action_id, ActionStatus.FAILED, "no order to cancel")
                    self.errors.append(
                        AgvError(
                            NO_ORDER_TO_CANCEL,
                            ErrorLevel.WARNING,
                            "cancelOrder: the truck has no order to cancel",
                            (("actionId", action.action_id),),
                        )
                    )
                else:
                    out.append(record)
            return out

    def malformed(self, topic: str, why: str) -> None:
        """A message that is not a JSON object (or not UTF-8): a `validationError` naming the topic."""
        with self.lock:
            self._reject(VALIDATION_ERROR, f"the {topic} message cannot be read: {why}", [("topic", topic)], [])

    def cancel(self, result: str = "cancelled by cancelOrder") -> list[str]:
        """Delete the order (orderId and orderUpdateId are kept): its unfinished actions FAILED, no node or
        edge states left. Returns the ids of the actions that failed."""
        with self.lock:
            failed = self.actions.fail_pending((NODE, EDGE), result)
            self.nodes, self.edges, self.rm, self.cursor = [], [], [], 0
            return failed

    def fail_action(self, action_id: str, error: AgvError, result: str | None = None) -> None:
        """An action failed: FAILED with `result`, and its error reported until an order is accepted."""
        with self.lock:
            record = self.actions.get(action_id)
            if not record.final:
                self.actions.set(action_id, ActionStatus.FAILED, result)
            self.errors.append(error)


def _structure(order: Order) -> list[Problem]:
    """validationError problems beyond the schema: counts, joins, sequenceIds, base before horizon, ids."""
    out: list[Problem] = []
    nodes, edges = order.nodes, order.edges
    if not nodes:
        return [("an order has at least one node", [("field", "nodes")])]
    if len(edges) != len(nodes) - 1:
        return [(f"{len(nodes)} nodes need {len(nodes) - 1} edges, got {len(edges)}", [("field", "edges")])]
    if not nodes[0].released:
        out.append(("the first node must be released (the base)", [("node.nodeId", nodes[0].node_id)]))
    seq: list[tuple[int, str, str]] = []
    released: list[tuple[bool, str, str]] = []
    for i, n in enumerate(nodes):
        seq.append((n.sequence_id, "node.nodeId", n.node_id))
        released.append((n.released, "node.nodeId", n.node_id))
        if i < len(edges):
            e = edges[i]
            seq.append((e.sequence_id, "edge.edgeId", e.edge_id))
            released.append((e.released, "edge.edgeId", e.edge_id))
            if e.start_node_id != n.node_id or e.end_node_id != nodes[i + 1].node_id:
                out.append(
                    (
                        f"edge '{e.edge_id}' runs {e.start_node_id} -> {e.end_node_id}, "
                        f"not {n.node_id} -> {nodes[i + 1].node_id}",
                        [("edge.edgeId", e.edge_id)],
                    )
                )
    for (a, _, _), (b, key, value) in itertools.pairwise(seq):
        if b != a + 1:
            out.append(
                (f"sequenceId {b} of {value} must follow {a} by one (nodes and edges alternate)", [(key, value)])
            )
    for (a, _, _), (b, key, value) in itertools.pairwise(released):
        if b and not a:
            out.append((f"{value} is released after an unreleased node or edge (base before horizon)", [(key, value)]))
    ids = [a.action_id for n in nodes for a in n.actions] + [a.action_id for e in edges for a in e.actions]
    for dup in sorted({i for i in ids if ids.count(i) > 1}):
        out.append((f"actionId '{dup}' is used more than once", [("actionId", dup)]))
    for n in nodes:
        if n.position is not None and float(n.position.get("allowedDeviationTheta", 0.0)) < 0.0:
            out.append((f"node '{n.node_id}': allowedDeviationTheta must be 0..pi", [("node.nodeId", n.node_id)]))
    return out
