"""VDA 5050 message parts as typed records: orders, actions, errors and the enumerations.

Incoming messages are first checked against the official schemas (`validation.problems`); these
records are built from messages that passed, so field access needs no more checks. Outgoing parts
(`AgvError`, ...) turn themselves into the JSON the schemas describe (`to_json`).

Public API: `ActionStatus`, `BlockingType`, `ErrorLevel`, `EStop`, `ConnectionState`, `OperatingMode`,
`Action`, `OrderNode`, `OrderEdge`, `Order`, `ErrorRef`, `AgvError`, `ORDER_REJECTIONS` and the error
types (`VALIDATION_ERROR`, `ORDER_ERROR`, `ORDER_UPDATE_ERROR`, `NO_ROUTE_ERROR`, `NO_ORDER_TO_CANCEL`,
`INSTANT_ACTION_ERROR`).
"""

from __future__ import annotations

from dataclasses import dataclass, field
from enum import Enum
from typing import Any


class ActionStatus(str, Enum):
    """`actionStatus` of an `actionState` (section 6.11)."""

    WAITING = "WAITING"
    INITIALIZING = "INITIALIZING"
    RUNNING = "RUNNING"
    PAUSED = "PAUSED"
    FINISHED = "FINISHED"
    FAILED = "FAILED"


class BlockingType(str, Enum):
    """`blockingType` of an action (section 6.12)."""

    NONE = "NONE"
    SOFT = "SOFT"
    HARD = "HARD"


class ErrorLevel(str, Enum):
    """`errorLevel`: WARNING (the AGV is ready to start) or FATAL (user intervention required)."""

    WARNING = "WARNING"
    URGENT = "URGENT"
    """3.0 only."""
    CRITICAL = "CRITICAL"
    """3.0 only: the truck stops, takes new orders (a 2.x state says FATAL)."""
    FATAL = "FATAL"


class EStop(str, Enum):
    """`safetyState.eStop`: how an active e-stop is acknowledged, or NONE."""

    AUTOACK = "AUTOACK"
    MANUAL = "MANUAL"
    REMOTE = "REMOTE"
    NONE = "NONE"


class ConnectionState(str, Enum):
    """`connectionState` of the connection topic (section 6.14)."""

    ONLINE = "ONLINE"
    OFFLINE = "OFFLINE"
    CONNECTIONBROKEN = "CONNECTIONBROKEN"
    CONNECTION_BROKEN = "CONNECTION_BROKEN"
    """3.0's spelling of CONNECTIONBROKEN."""


class OperatingMode(str, Enum):
    """`operatingMode` of the state (Table 1)."""

    AUTOMATIC = "AUTOMATIC"
    SEMIAUTOMATIC = "SEMIAUTOMATIC"
    MANUAL = "MANUAL"
    SERVICE = "SERVICE"
    TEACHIN = "TEACHIN"


VALIDATION_ERROR = "validationError"
ORDER_ERROR = "orderError"
ORDER_UPDATE_ERROR = "orderUpdateError"
NO_ROUTE_ERROR = "noRouteError"
NO_ORDER_TO_CANCEL = "noOrderToCancel"
INSTANT_ACTION_ERROR = "instantActionError"
"""An instant action this AGV cannot perform (unknown type, wrong scope, bad parameters): the action is
FAILED and this warning names it (section 6.1.1: report the error and reject)."""
ORDER_REJECTIONS = frozenset({VALIDATION_ERROR, ORDER_ERROR, ORDER_UPDATE_ERROR, NO_ROUTE_ERROR})
"""Warnings of a rejected order: reported until the AGV accepts a new order (section 6.6.4)."""


@dataclass(frozen=True)
class Action:
    """An action of a node, an edge or an instantActions message."""

    action_id: str
    action_type: str
    blocking_type: BlockingType
    parameters: tuple[tuple[str, Any], ...] = ()
    description: str | None = None

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> Action:
        """From a schema-valid action object."""
        params = tuple((str(p["key"]), p["value"]) for p in doc.get("actionParameters", ()))
        return cls(
            str(doc["actionId"]),
            str(doc["actionType"]),
            BlockingType(doc["blockingType"]),
            params,
            doc.get("actionDescription"),
        )

    def param(self, key: str, default: Any = None) -> Any:
        """The value of parameter `key` (the first one given), or `default`."""
        return next((v for k, v in self.parameters if k == key), default)

    def has(self, key: str) -> bool:
        """True when the parameter `key` is given."""
        return any(k == key for k, _ in self.parameters)


@dataclass(frozen=True)
class OrderNode:
    """A node of an order; `position` is the raw `nodePosition` object (or None)."""

    node_id: str
    sequence_id: int
    released: bool
    actions: tuple[Action, ...] = ()
    position: dict[str, Any] | None = None
    description: str | None = None

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> OrderNode:
        """From a schema-valid node object."""
        return cls(
            str(doc["nodeId"]),
            int(doc["sequenceId"]),
            bool(doc["released"]),
            tuple(Action.from_json(a) for a in doc["actions"]),
            doc.get("nodePosition"),
            doc.get("nodeDescription"),
        )

    def state(self) -> dict[str, Any]:
        """Its `nodeState` in the state message."""
        out: dict[str, Any] = {"nodeId": self.node_id, "sequenceId": self.sequence_id, "released": self.released}
        if self.description is not None:
            out["nodeDescription"] = self.description
        if self.position is not None:
            out["nodePosition"] = {k: self.position[k] for k in ("x", "y", "theta", "mapId") if k in self.position}
        return out


@dataclass(frozen=True)
class OrderEdge:
    """An edge of an order; `raw` keeps the optional fields (maxSpeed, trajectory, ...)."""

    edge_id: str
    sequence_id: int
    released: bool
    start_node_id: str
    end_node_id: str
    actions: tuple[Action, ...] = ()
    raw: dict[str, Any] = field(default_factory=dict)

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> OrderEdge:
        """From a schema-valid edge object."""
        return cls(
            str(doc["edgeId"]),
            int(doc["sequenceId"]),
            bool(doc["released"]),
            str(doc["startNodeId"]),
            str(doc["endNodeId"]),
            tuple(Action.from_json(a) for a in doc["actions"]),
            dict(doc),
        )

    def state(self) -> dict[str, Any]:
        """Its `edgeState` in the state message."""
        out: dict[str, Any] = {"edgeId": self.edge_id, "sequenceId": self.sequence_id, "released": self.released}
        if "edgeDescription" in self.raw:
            out["edgeDescription"] = self.raw["edgeDescription"]
        return out


@dataclass(frozen=True)
class Order:
    """An order message (schema-valid)."""

    header_id: int
    version: str
    order_id: str
    order_update_id: int
    nodes: tuple[OrderNode, ...]
    edges: tuple[OrderEdge, ...]
    zone_set_id: str | None = None

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> Order:
        """From a schema-valid order message."""
        return cls(
            int(doc["headerId"]),
            str(doc["version"]),
            str(doc["orderId"]),
            int(doc["orderUpdateId"]),
            tuple(OrderNode.from_json(n) for n in doc["nodes"]),
            tuple(OrderEdge.from_json(e) for e in doc["edges"]),
            doc.get("zoneSetId"),
        )


ErrorRef = tuple[str, str]
"""An error reference: (referenceKey, referenceValue)."""


@dataclass(frozen=True)
class AgvError:
    """An entry of the state's `errors`: type, level, references, description, hint."""

    error_type: str
    level: ErrorLevel
    description: str
    references: tuple[ErrorRef, ...] = ()
    hint: str | None = None

    def to_json(self) -> dict[str, Any]:
        """The `error` object of the state message."""
        out: dict[str, Any] = {
            "errorType": self.error_type,
            "errorLevel": self.level.value,
            "errorDescription": self.description,
        }
        if self.references:
            out["errorReferences"] = [{"referenceKey": k, "referenceValue": v} for k, v in self.references]
        if self.hint:
            out["errorHint"] = self.hint
        return out

    def ref(self, key: str) -> str | None:
        """The value of the first reference with `key`, or None."""
        return next((v for k, v in self.references if k == key), None)
