"""The AGV's outgoing messages: state, visualization, connection and factsheet.

A `Snapshot` is what the truck's sensors said at one control tick (pose from localization, speed,
steering, load sensor, battery, safety scanners, faults); the executor takes one every tick in its own
thread, and the messages are built from the latest one, so no other thread touches the vehicle.

State fields (section 6.10.6): `agvPosition` (map frame, the config's mapId, `positionInitialized`),
`velocity` (`vx` the speed along the forks' axis, `vy` 0, `omega` = v tan(steering) / wheelbase), `loads`
(one load while the load sensor feels one: type and id from the pick, dimensions of its pallet type;
empty otherwise), `batteryState` (charge in %, `charging`; 80 % "good" when the vehicle has no battery
reading), `safetyState` (`eStop` AUTOACK while the protective field stops the truck, MANUAL after a
contact fault; `fieldViolation` from the safety scanners), `errors` (the order manager's warnings, a
field violation as a WARNING, contact faults as FATAL), `operatingMode` AUTOMATIC, and from the order
manager `orderId`, `orderUpdateId`, `lastNodeId`, `lastNodeSequenceId`, `nodeStates`, `edgeStates`,
`actionStates`; `driving`, `paused`, `newBaseRequest`, `distanceSinceLastNode` from the executor.

Public API: `Snapshot`, `Messages` (`state`, `visualization`, `connection`, `factsheet`), `REASON_LEVELS`,
`error_type(reason)`, `vehicle_errors(snapshot)`.
"""

from __future__ import annotations

import math
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

from palletpilot.control.vehicle import VehicleParams
from palletpilot.executor.apps.vda5050.actions import CATALOGUE, LOAD_HANDLING_DEVICE
from palletpilot.executor.apps.vda5050.models import AgvError, ConnectionState, ErrorLevel, EStop, OperatingMode
from palletpilot.executor.apps.vda5050.orders import OrderManager
from palletpilot.executor.apps.vda5050.routes import LIFT_MARGIN_M, load_type_names, pallet_name
from palletpilot.executor.apps.vda5050.validation import Headers
from palletpilot.executor.ports import vocabulary
from palletpilot.perception.specs import BUILTIN_PALLETS, PalletType

DRIVING_SPEED = 0.01
"""m/s: the truck counts as driving above this speed."""
FATAL_REASONS = vocabulary.FATAL_REASONS
"""Task failure reasons after which the truck needs a person (FATAL); all others are WARNINGs. Derived
from the reason table (`executor.vocabulary.REASONS`)."""


def error_type(reason: str) -> str:
    """A task's reason code as an errorType in camelCase: `pallet_not_found` -> `palletNotFound`."""
    head, *rest = reason.split("_")
    return head + "".join(w.capitalize() for w in rest)


def reason_level(reason: str) -> ErrorLevel:
    """FATAL for the reasons in `FATAL_REASONS`, else WARNING."""
    return ErrorLevel.FATAL if reason in FATAL_REASONS else ErrorLevel.WARNING


def _optional_parameters() -> list[dict[str, str]]:
    """The factsheet's optionalParameters: the order fields the AGV honours."""
    supported = [
        "order.nodes.nodePosition",
        "order.nodes.nodePosition.theta",
        "order.nodes.nodePosition.allowedDeviationXY",
        "order.nodes.nodePosition.allowedDeviationTheta",
        "order.edges.maxSpeed",
        "order.edges.maxHeight",
        "order.edges.minHeight",
        "order.edges.orientation",
        "order.edges.orientationType",
        "order.edges.rotationAllowed",
        "order.edges.maxRotationSpeed",
        "order.edges.length",
        "order.edges.corridor",
    ]
    optional = [{"parameter": name, "support": "SUPPORTED"} for name in supported]
    optional.append(
        {
            "parameter": "order.edges.trajectory",
            "support": "SUPPORTED",
            "description": (
                "accepted when it lies on the roadmap edge's curve (within 5 cm): the truck drives the roadmap"
            ),
        }
    )
    return optional


@dataclass(frozen=True)
class Snapshot:
    """The truck at one control tick (SI units, map frame)."""

    x: float = 0.0
    y: float = 0.0
    theta: float = 0.0
    speed: float = 0.0
    steering: float = 0.0
    loaded: bool = False
    battery: float | None = None
    """State of charge 0..1, None without a reading."""
    protective_stop: bool = False
    intrusions: tuple[str, ...] = ()
    faults: tuple[str, ...] = ()
    localized: bool = True

    @property
    def driving(self) -> bool:
        """True while the truck moves."""
        return abs(self.speed) > DRIVING_SPEED


def vehicle_errors(snap: Snapshot) -> list[AgvError]:
    """Errors the vehicle itself raises: contact faults (FATAL), a protective field violation (WARNING)."""
    out = [
        AgvError("collision", ErrorLevel.FATAL, f, (), "inspect the truck and the load; restart the AGV")
        for f in snap.faults
    ]
    if snap.protective_stop:
        what = ", ".join(snap.intrusions) or "an object"
        out.append(AgvError("fieldViolation", ErrorLevel.WARNING, f"protective field violated by {what}"))
    return out


class Messages:
    """Builds the outgoing messages of one AGV (headers from `headers`, one headerId sequence per topic)."""

    def __init__(
        self,
        headers: Headers,
        map_id: str,
        map_version: str,
        params: VehicleParams,
        state_interval_s: float = 30.0,
        visualization_hz: float = 0.0,
        max_load_kg: float = 1500.0,
        fork_length: float = 1.15,
    ) -> None:
        self.headers = headers
        self.map_id = map_id
        self.map_version = map_version
        self.params = params
        self.state_interval_s = state_interval_s
        self.visualization_hz = visualization_hz
        self.max_load_kg = max_load_kg
        self.fork_length = fork_length

    def _position(self, snap: Snapshot) -> dict[str, Any]:
        return {
            "x": float(snap.x),
            "y": float(snap.y),
            "theta": float(math.atan2(math.sin(snap.theta), math.cos(snap.theta))),
            "mapId": self.map_id,
            "positionInitialized": bool(snap.localized),
        }

    def _velocity(self, snap: Snapshot) -> dict[str, Any]:
        omega = snap.speed * math.tan(snap.steering) / self.params.wheelbase
        return {"vx": float(snap.speed), "vy": 0.0, "omega": float(omega)}

    def state(
        self,
        orders: OrderManager,
        snap: Snapshot,
        *,
        paused: bool,
        charging: bool,
        new_base_request: bool,
        distance_since_last_node: float,
        load: dict[str, Any] | None,
        errors: Sequence[AgvError] = (),
    ) -> dict[str, Any]:
        """The state message: the order manager's fields and the snapshot's (see the module docstring)."""
        with orders.lock:
            order_part: dict[str, Any] = {
                "orderId": orders.order_id,
                "orderUpdateId": orders.order_update_id,
                "lastNodeId": orders.last_node_id,
                "lastNodeSequenceId": orders.last_node_seq,
                "nodeStates": orders.node_states(),
                "edgeStates": orders.edge_states(),
                "actionStates": orders.actions.to_json(),
            }
            order_errors = list(orders.errors)
        if snap.faults:
            estop = EStop.MANUAL
        elif snap.protective_stop:
            estop = EStop.AUTOACK
        else:
            estop = EStop.NONE
        battery = {
            "batteryCharge": round(100.0 * snap.battery, 2) if snap.battery is not None else 80.0,
            "charging": bool(charging),
        }
        return {
            **self.headers.header("state"),
            "maps": [{"mapId": self.map_id, "mapVersion": self.map_version, "mapStatus": "ENABLED"}],
            **order_part,
            "agvPosition": self._position(snap),
            "velocity": self._velocity(snap),
            "loads": [load]
            if snap.loaded and load is not None
            else ([{"loadPosition": LOAD_HANDLING_DEVICE}] if snap.loaded else []),
            "driving": snap.driving,
            "paused": bool(paused),
            "newBaseRequest": bool(new_base_request),
            "distanceSinceLastNode": round(float(distance_since_last_node), 3),
            "batteryState": battery,
            "operatingMode": OperatingMode.AUTOMATIC.value,
            "errors": [e.to_json() for e in [*order_errors, *errors, *vehicle_errors(snap)]],
            "information": [],
            "safetyState": {"eStop": estop.value, "fieldViolation": bool(snap.protective_stop)},
        }

    def visualization(self, snap: Snapshot) -> dict[str, Any]:
        """The visualization message: position and velocity."""
        return {
            **self.headers.header("visualization"),
            "agvPosition": self._position(snap),
            "velocity": self._velocity(snap),
        }

    def connection(self, state: ConnectionState) -> dict[str, Any]:
        """A connection message (ONLINE, OFFLINE, or CONNECTIONBROKEN for the last will)."""
        return {**self.headers.header("connection"), "connectionState": state.value}

    def _load_sets(self) -> list[dict[str, Any]]:
        """The factsheet's loadSets: one per name an order's loadType may use (`routes.pallet_name`)."""
        mast = self.params.mast
        load_sets = []
        for load_type in load_type_names():  # every name an order's loadType may use (routes.pallet_name)
            name = pallet_name(load_type) or load_type
            alias = "" if name == load_type else f" ({load_type}: the same as {name})"
            pallet = PalletType.model_validate(BUILTIN_PALLETS[name])
            load_sets.append(
                {
                    "setName": load_type.upper(),
                    "loadType": load_type,
                    "loadPositions": [LOAD_HANDLING_DEVICE],
                    "loadDimensions": {"length": pallet.length, "width": pallet.width, "height": pallet.height},
                    "minLoadhandlingHeight": mast.min_height,
                    "maxLoadhandlingHeight": round(mast.max_height - LIFT_MARGIN_M, 3),
                    "description": f"{pallet.name}{alias}; loadType in any case",
                }
            )
        return load_sets

    def factsheet(self, software_version: str = "") -> dict[str, Any]:
        """The factsheet: from the vehicle file and the supported actions (`actions.CATALOGUE`)."""
        p = self.params
        body = p.body
        length = self.fork_length - body.rear_x
        optional = _optional_parameters()
        mast = p.mast
        load_sets = self._load_sets()
        timing: dict[str, Any] = {
            "minOrderInterval": 0.1,
            "minStateInterval": 0.05,
            "defaultStateInterval": self.state_interval_s,
        }
        if self.visualization_hz > 0:
            timing["visualizationInterval"] = round(1.0 / self.visualization_hz, 3)
        return {
            **self.headers.header("factsheet"),
            "typeSpecification": {
                "seriesName": p.name,
                "seriesDescription": "three-wheel counterbalance forklift with camera-guided pallet pickup",
                "agvKinematic": "THREEWHEEL",
                "agvClass": "FORKLIFT",
                "maxLoadMass": self.max_load_kg,
                "localizationTypes": ["NATURAL"],
                "navigationTypes": ["VIRTUAL_LINE_GUIDED"],
            },
            "physicalParameters": {
                "speedMin": 0.05,
                "speedMax": p.max_speed_forward,
                "accelerationMax": p.max_accel,
                "decelerationMax": p.max_decel,
                "heightMin": body.height,
                "heightMax": max(body.height, mast.max_height),
                "width": body.width,
                "length": round(length, 3),
            },
            "protocolLimits": {"maxStringLens": {}, "maxArrayLens": {}, "timing": timing},
            "protocolFeatures": {
                "optionalParameters": optional,
                "agvActions": [spec.to_json() for spec in CATALOGUE.values()],
            },
            "agvGeometry": {
                "envelopes2d": [
                    {
                        "set": "body",
                        "polygonPoints": [
                            {"x": body.rear_x, "y": -body.width / 2},
                            {"x": self.fork_length, "y": -body.width / 2},
                            {"x": self.fork_length, "y": body.width / 2},
                            {"x": body.rear_x, "y": body.width / 2},
                        ],
                        "description": "the body and the forks (forklift frame: origin at the fork heels)",
                    }
                ]
            },
            "loadSpecification": {"loadPositions": [LOAD_HANDLING_DEVICE], "loadSets": load_sets},
            "vehicleConfig": {"versions": [{"key": "softwareVersion", "value": software_version or "unknown"}]},
        }
