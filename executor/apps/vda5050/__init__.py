"""VDA 5050 (2.1.0, read from 2.0 masters too): palletpilot as one AGV of a fleet, orders over MQTT.

`palletpilot agv --config agv.yaml --sim SCENARIO` (`cli_agv`) connects to the fleet manager's broker,
takes orders and instant actions, runs them with the executor's task machines (the adaptive Pickup for
`pick`, the checked Delivery for `drop`, Move along the order's edges) and reports its state.

Modules:
- `validation`: the official JSON schemas (vendored in `schemas/`, MIT licence, errata applied), message
  validation, timestamps and headers; `models`: typed records of orders, actions, errors, the enums.
- `orders`: `OrderManager`, the order acceptance flow as a pure state machine (new order, update,
  stitching, stale and equal updates, base and horizon, rejections with error references), progress
  (`arrive`, `plan_next`) and instant actions; `routes`: orders against the roadmap and the vehicle;
  `actions`: the supported actions (`CATALOGUE`) and the action state machine; `nurbs`: trajectories.
- `state`: the outgoing state, visualization, connection and factsheet messages; `config`: `agv.yaml`.
- `mqtt`: `AgvLink` (paho-mqtt 2.x: topics, QoS, retained flags, last will, reconnects with backoff).
- `persist`: the AGV's crash-safe journal (checkpoints of the order state on `executor.journal`, sessions,
  the writer thread).
- `agv`: `Agv`, the vehicle driver (one runner per leg of the order: `leg_run`, with `legs`), with its
  instant actions (`instant`) and its journal side (`restart`); `vehicle`: the simulated or real truck
  behind it (`sim_backend`, `robot_backend`, `TickClock`).

The pure parts (`validation`, `models`, `actions`, `routes`, `orders`, `state`) need no broker and are
re-exported here; `mqtt`, `agv` and `vehicle` are imported from their modules.
"""

from palletpilot.executor.apps.vda5050.actions import CATALOGUE, ActionTable, IllegalTransitionError
from palletpilot.executor.apps.vda5050.config import AgvConfig, AgvConfigError, load_config
from palletpilot.executor.apps.vda5050.models import (
    Action,
    ActionStatus,
    AgvError,
    BlockingType,
    ConnectionState,
    ErrorLevel,
    EStop,
    OperatingMode,
    Order,
    OrderEdge,
    OrderNode,
)
from palletpilot.executor.apps.vda5050.orders import Decision, Leg, OrderManager, VehicleView
from palletpilot.executor.apps.vda5050.state import Messages, Snapshot
from palletpilot.executor.apps.vda5050.validation import Headers, Stamper, load_schema, problems

__all__ = [
    "CATALOGUE",
    "Action",
    "ActionStatus",
    "ActionTable",
    "AgvConfig",
    "AgvConfigError",
    "AgvError",
    "BlockingType",
    "ConnectionState",
    "Decision",
    "EStop",
    "ErrorLevel",
    "Headers",
    "IllegalTransitionError",
    "Leg",
    "Messages",
    "OperatingMode",
    "Order",
    "OrderEdge",
    "OrderManager",
    "OrderNode",
    "Snapshot",
    "Stamper",
    "VehicleView",
    "load_config",
    "load_schema",
    "problems",
]
