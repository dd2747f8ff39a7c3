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

from palletpilot.control.errors import ControlError
from palletpilot.control.follower import DriveCommand, Follower, FollowerConfig, FollowerStatus, TrackingError
from palletpilot.control.model import KinematicModel
from palletpilot.control.mpc import MpcConfig, MpcFollower, MpcWeights
from palletpilot.control.pure_pursuit import PurePursuitConfig, PurePursuitFollower
from palletpilot.control.vehicle import BatteryParams, BodyParams, MastParams, VehicleParams, load_vehicle

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
