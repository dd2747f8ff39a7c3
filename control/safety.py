"""The safety laser scanners' fields and the safety state a vehicle reports.

Fields are rectangles on the floor in the forklift frame (origin at the fork heels, x towards the fork
tips, y left; metres), drawn from the vehicle file's `safety_scanner` (`SafetyScannerParams`) and
`body`, for the current speed and direction of travel and the selected field set:

- `normal`, forward (fork tips leading): from the body's front to `front_x` (fork tips, or the load's
  front) plus the protective length; the body's width plus `lateral_margin` either side.
- `normal`, reverse: behind the body's rear, as wide.
- `narrow` (entering a pallet or a floor drop slot, forward only): two side fields ahead of the body's
  front, beside the muted corridor `|y| < mute_half_width` where the forks and the pallet go.

The protective length is the stopping distance `v t_response + v^2 / (2 emergency_decel)` plus
`protective_margin`; the warning field reaches `warning_extra` beyond it. A simulator or a robot
adapter evaluates intrusions; the executor only reads `SafetyState`.

Public API: `FIELD_SETS`, `TRAVEL_DIRECTIONS`, `FieldRect`, `SafetyFields`, `SafetyState`, `safety_fields`,
`stopping_distance`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Literal

from palletpilot.control.vehicle import VehicleParams

FieldSet = Literal["normal", "narrow"]
TravelDirection = Literal["forward", "reverse"]
FIELD_SETS: tuple[FieldSet, ...] = ("normal", "narrow")
TRAVEL_DIRECTIONS: tuple[TravelDirection, ...] = ("forward", "reverse")


@dataclass(frozen=True)
class FieldRect:
    """An axis-aligned rectangle in the forklift frame (m): x from `x0` to `x1`, y from `y0` to `y1`."""

    x0: float
    y0: float
    x1: float
    y1: float

    def corners(self) -> list[tuple[float, float]]:
        """The four corners (forklift frame, m), counter-clockwise."""
        return [(self.x0, self.y0), (self.x1, self.y0), (self.x1, self.y1), (self.x0, self.y1)]


@dataclass(frozen=True)
class SafetyFields:
    """The protective and warning fields active now (forklift frame)."""

    field_set: FieldSet
    direction: TravelDirection
    protective: tuple[FieldRect, ...]
    warning: tuple[FieldRect, ...]


@dataclass(frozen=True)
class SafetyState:
    """What the truck's safety function reports: the active field set and direction, whether the warning
    field is intruded (speed capped at `speed_limit`, m/s), whether a protective stop holds the truck, and
    what is in the fields (`intrusions`: readable names where the vehicle knows them)."""

    field_set: FieldSet = "normal"
    direction: TravelDirection = "forward"
    warning: bool = False
    protective_stop: bool = False
    speed_limit: float | None = None
    intrusions: tuple[str, ...] = field(default_factory=tuple)

    def to_json(self) -> dict[str, object]:
        """Plain JSON for events and reports."""
        return {
            "field_set": self.field_set,
            "direction": self.direction,
            "warning": self.warning,
            "protective_stop": self.protective_stop,
            "speed_limit_mps": self.speed_limit,
            "intrusions": list(self.intrusions),
        }


def stopping_distance(params: VehicleParams, speed: float) -> float:
    """Distance (m) the truck travels from `speed` (m/s) until it stands after a protective stop:
    the reaction time at speed, then braking at `emergency_decel`."""
    scanner = params.safety_scanner
    response = scanner.response_time_s if scanner is not None else 0.0
    v = abs(speed)
    return v * response + v * v / (2.0 * params.emergency_decel)


def safety_fields(
    params: VehicleParams,
    speed: float,
    direction: TravelDirection,
    field_set: FieldSet,
    front_x: float,
) -> SafetyFields | None:
    """The fields at `speed` (m/s) in `direction`, for `field_set`; `front_x` (m) is the truck's leading
    end when travelling forward (fork tips or a carried load's front). None without scanners."""
    scanner = params.safety_scanner
    if scanner is None:
        return None
    body = params.body
    protective_len = scanner.protective_margin + stopping_distance(params, speed)
    warning_len = protective_len + scanner.warning_extra
    half = 0.5 * body.width + scanner.lateral_margin
    if direction == "reverse":
        rear = body.rear_x
        return SafetyFields(
            field_set,
            direction,
            (FieldRect(rear - protective_len, -half, rear, half),),
            (FieldRect(rear - warning_len, -half, rear, half),),
        )
    if field_set == "narrow":
        reach = body.front_x + scanner.narrow_margin + stopping_distance(params, speed)
        body_half, mute = 0.5 * body.width, scanner.mute_half_width
        sides = (FieldRect(body.front_x, mute, reach, body_half), FieldRect(body.front_x, -body_half, reach, -mute))
        return SafetyFields(field_set, direction, sides, sides)
    return SafetyFields(
        field_set,
        direction,
        (FieldRect(body.front_x, -half, front_x + protective_len, half),),
        (FieldRect(body.front_x, -half, front_x + warning_len, half),),
    )
