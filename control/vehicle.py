"""Vehicle parameters shared by the simulator and the controller (file: `missions/forklift.yaml`).

The forklift is a tricycle: the forklift frame's origin sits midway between the forks on the fixed
front axle (at the fork heels), and the steered drive wheel is `wheelbase` behind it, at the end away
from the forks. Its tightest turn is therefore `tan(max_steering) / wheelbase` (1/m) at the origin.
"""

from __future__ import annotations

import math
from pathlib import Path

from pydantic import ConfigDict, Field, model_validator

from palletpilot.control.errors import ControlError
from palletpilot.geometry.fileio import FileModel, load_yaml_model


class MastParams(FileModel):
    """Fork carriage lift: heights of the fork bottoms (m) and lift speed (m/s)."""

    min_height: float = Field(0.0, ge=0.0, le=15.0)
    max_height: float = Field(2.0, gt=0.0, le=15.0)
    lift_speed: float = Field(0.2, gt=0.0, le=2.0)
    lower_speed: float = Field(0.3, gt=0.0, le=2.0)
    travel_height_empty: float = Field(0.0, ge=0.0, le=15.0, description="fork bottoms while driving empty (m)")
    travel_height_loaded: float = Field(0.10, ge=0.0, le=15.0, description="fork bottoms while driving a load (m)")


class BatteryParams(FileModel):
    """The traction battery, as a state of charge between 0 and 1: drained by driving and lifting,
    charged at a charger. Levels are fractions of a full battery."""

    model_config = ConfigDict(frozen=True)

    drain_per_km: float = Field(0.05, ge=0.0, le=1.0, description="charge used per km driven")
    drain_per_lift_m: float = Field(0.0005, ge=0.0, le=1.0, description="charge used per metre the forks rise")
    charge_per_min: float = Field(0.01, gt=0.0, le=1.0, description="charge gained per minute at a charger")


class BodyParams(FileModel):
    """The truck's body as a box in the forklift frame (origin at the fork heels on the floor, x to the
    fork tips): from `rear_x` to `front_x` (m, behind the heels: negative), `width` (m) and `height` (m,
    the overhead guard). The default is a 1.5 t three-wheel counterbalance truck."""

    model_config = ConfigDict(frozen=True)

    rear_x: float = Field(-1.85, lt=0.0, ge=-10.0)
    front_x: float = Field(-0.12, le=0.0, ge=-5.0)
    width: float = Field(1.10, gt=0.0, le=5.0)
    height: float = Field(2.20, gt=0.0, le=10.0)

    @model_validator(mode="after")
    def _length(self) -> BodyParams:
        if self.rear_x >= self.front_x:
            raise ValueError("rear_x must be behind front_x")
        return self


class SafetyScannerParams(FileModel):
    """2D safety laser scanners as ISO 3691-4 trucks carry them (`control.safety` draws the fields).

    The protective field reaches the stopping distance at the current speed plus `protective_margin`
    ahead of the truck's leading end (fork tips or load when travelling forward, the counterweight in
    reverse); the warning field reaches `warning_extra` further. A warning intrusion caps the speed at
    `warning_speed`; a protective intrusion brakes the truck at `emergency_decel` (the truck's own safety
    function, not the executor's), and it drives on only after the fields at `warning_speed` stayed clear
    for `restart_delay_s`. The `narrow` field set, for entering a pallet or a drop slot on the floor,
    mutes the corridor `mute_half_width` either side of the forks' centre line and watches only the
    body's front corners beside it."""

    model_config = ConfigDict(frozen=True)

    scan_height: float = Field(0.10, gt=0.0, le=1.0, description="scan plane above the floor (m)")
    response_time_s: float = Field(0.20, ge=0.0, le=2.0, description="scanner and safety PLC reaction time (s)")
    protective_margin: float = Field(
        0.20, ge=0.0, le=5.0, description="protective field beyond the stopping distance (m)"
    )
    warning_extra: float = Field(1.50, ge=0.0, le=10.0, description="warning field beyond the protective field (m)")
    warning_speed: float = Field(
        0.30, gt=0.0, le=3.0, description="speed cap while the warning field is intruded (m/s)"
    )
    lateral_margin: float = Field(0.10, ge=0.0, le=2.0, description="fields beyond the body's sides (m)")
    restart_delay_s: float = Field(1.0, ge=0.0, le=60.0, description="clear fields this long before driving on (s)")
    mute_half_width: float = Field(
        0.45, gt=0.0, le=2.0, description="narrow set: muted corridor either side of the forks (m)"
    )
    narrow_margin: float = Field(
        0.05, ge=0.0, le=2.0, description="narrow set: side fields beyond the stopping distance (m)"
    )


class VehicleParams(FileModel):
    """Kinematic and actuator limits of the forklift (SI units unless the name says otherwise)."""

    model_config = ConfigDict(frozen=True)

    name: str = "forklift"
    wheelbase: float = Field(gt=0.0, le=10.0, description="fixed front axle (origin) to steered drive wheel, m")
    max_steering_deg: float = Field(gt=0.0, lt=90.0)
    max_steering_rate_deg_s: float = Field(gt=0.0, le=360.0)
    max_speed_forward: float = Field(gt=0.0, le=10.0, description="m/s, fork tips leading")
    max_speed_reverse: float = Field(gt=0.0, le=10.0, description="m/s")
    max_accel: float = Field(gt=0.0, le=10.0, description="m/s^2")
    max_decel: float = Field(gt=0.0, le=20.0, description="m/s^2")
    emergency_decel: float = Field(
        1.5, gt=0.0, le=20.0, description="m/s^2, the safety stop: the truck's own brake, whatever the drive commands"
    )
    actuator_lag_s: float = Field(0.1, ge=0.0, le=5.0, description="first-order lag of speed and steering")
    creep_speed: float = Field(
        0.3, gt=0.0, le=2.0, description="m/s, the fastest drive with the forks above travel height"
    )
    mast: MastParams = MastParams()
    body: BodyParams = BodyParams()
    battery: BatteryParams | None = None  # no battery model: `until_level` charging is not possible
    safety_scanner: SafetyScannerParams | None = SafetyScannerParams()  # null: a truck without scanners

    @model_validator(mode="after")
    def _mast_range(self) -> VehicleParams:
        m = self.mast
        if m.max_height <= m.min_height:
            raise ValueError("mast.max_height must be above mast.min_height")
        for name in ("travel_height_empty", "travel_height_loaded"):
            if not m.min_height <= getattr(m, name) <= m.max_height:
                raise ValueError(f"mast.{name} must lie within min_height..max_height")
        scanner = self.safety_scanner
        if scanner is not None and scanner.mute_half_width >= 0.5 * self.body.width:
            raise ValueError("safety_scanner.mute_half_width must be less than half the body width")
        if self.emergency_decel < self.max_decel:
            raise ValueError("emergency_decel must be at least max_decel")
        return self

    @property
    def max_steering(self) -> float:
        """Largest steering angle (rad)."""
        return math.radians(self.max_steering_deg)

    @property
    def max_curvature(self) -> float:
        """Tightest path curvature (1/m) the forklift origin can follow."""
        return math.tan(self.max_steering) / self.wheelbase


def load_vehicle(path: str | Path) -> VehicleParams:
    """Load a vehicle file; every problem raises `ControlError` naming the file and field."""
    return load_yaml_model(path, VehicleParams, ControlError)
