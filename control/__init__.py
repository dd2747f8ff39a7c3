"""Control: forklift kinematic model and vehicle limits; the MPC and pure-pursuit followers come later.

Public API:
- `VehicleParams`, `load_vehicle(path)`: the vehicle file (`missions/forklift.yaml`), shared with `sim/`.
- `ControlError`.
"""

from control.errors import ControlError
from control.vehicle import MastParams, VehicleParams, load_vehicle

__all__ = ["ControlError", "MastParams", "VehicleParams", "load_vehicle"]
