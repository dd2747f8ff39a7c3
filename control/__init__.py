"""Control: the forklift's kinematic model, vehicle limits, and the path followers.

Public API:
- `VehicleParams` (with `MastParams`, `BodyParams`, `BatteryParams`), `load_vehicle(path)`: the vehicle file
  (`missions/forklift.yaml`), shared with `sim/`.
- `KinematicModel`: state (x, y, yaw, steering), inputs (speed, steering rate); CasADi and numpy.
- Path followers (non-blocking, for the 20 Hz tick): `start(path)`, `update(t, T_world_forklift,
  speed, steering) -> DriveCommand(speed, steering, status)`, `stop()`; `FollowerStatus` running /
  succeeded / failed; `FollowerConfig` (tolerances, failure and progress checks, speed profile):
  - `MpcFollower(params, MpcConfig)`: CasADi multiple-shooting MPC (`control.mpc`);
  - `PurePursuitFollower(params, PurePursuitConfig)`: regulated pure pursuit, the baseline.
- `control.safety`: the safety scanners' fields (`safety_fields`, `stopping_distance`, `FIELD_SETS`)
  and the `SafetyState` a vehicle reports.
- `ControlError`.
"""

from __future__ import annotations

import importlib
from typing import TYPE_CHECKING, Any

from palletpilot.control.errors import ControlError
from palletpilot.control.vehicle import BatteryParams, BodyParams, MastParams, VehicleParams, load_vehicle

if TYPE_CHECKING:
    from palletpilot.control.follower import DriveCommand, Follower, FollowerConfig, FollowerStatus, TrackingError
    from palletpilot.control.model import KinematicModel
    from palletpilot.control.mpc import MpcConfig, MpcFollower, MpcWeights
    from palletpilot.control.pure_pursuit import PurePursuitConfig, PurePursuitFollower

# The model and the followers load CasADi: imported on first use, so that reading a vehicle file
# (`palletpilot map check`) does not pay for it.
_LAZY = {
    **dict.fromkeys(("DriveCommand", "Follower", "FollowerConfig", "FollowerStatus", "TrackingError"), "follower"),
    "KinematicModel": "model",
    **dict.fromkeys(("MpcConfig", "MpcFollower", "MpcWeights"), "mpc"),
    **dict.fromkeys(("PurePursuitConfig", "PurePursuitFollower"), "pure_pursuit"),
}


def __getattr__(name: str) -> Any:
    """The followers and the model, imported on first use (PEP 562)."""
    if name not in _LAZY:
        raise AttributeError(f"module {__name__!r} has no attribute {name!r}")
    value = getattr(importlib.import_module(f"{__name__}.{_LAZY[name]}"), name)
    globals()[name] = value
    return value


__all__ = [
    "BatteryParams",
    "BodyParams",
    "ControlError",
    "DriveCommand",
    "Follower",
    "FollowerConfig",
    "FollowerStatus",
    "KinematicModel",
    "MastParams",
    "MpcConfig",
    "MpcFollower",
    "MpcWeights",
    "PurePursuitConfig",
    "PurePursuitFollower",
    "TrackingError",
    "VehicleParams",
    "load_vehicle",
]
