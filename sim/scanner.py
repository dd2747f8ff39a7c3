"""The simulated safety laser scanners and the truck's safety function behind them.

Every simulation step `SimScanner.update` draws the fields (`control.safety.safety_fields`) for the
truck's speed, direction of travel and selected field set, and tests them against the world's solids
that cut the scan plane (people, boxes, rack uprights, walls, resting pallets and loads; the carried
pallet is part of the truck). It then acts as a safety PLC would, independent of the executor:

- warning field intruded: the drive speed is capped at `warning_speed`;
- protective field intruded: a protective stop, braking at `emergency_decel`; it holds until the
  protective field the truck would have at `warning_speed` stayed clear for `restart_delay_s`.

The direction of travel is the commanded one (the drive's direction signal), else the measured one,
else the one selected with the field set before the truck drives (`select`), else the last. Poses in the
world frame, sizes in metres.

Public API: `SimScanner`.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from palletpilot.control.safety import FieldRect, FieldSet, SafetyState, TravelDirection, safety_fields
from palletpilot.control.vehicle import VehicleParams
from palletpilot.geometry import SE2
from palletpilot.sim.contacts import Solid, SolidSet, box_solid, overlap_matrix

_MOVING = 1e-3  # m/s


class SimScanner:
    """The scanners and the safety function of one simulated truck (`state` after each `update`)."""

    def __init__(self, params: VehicleParams) -> None:
        self.params = params
        self.field_set: FieldSet = "normal"
        self.direction: TravelDirection = "forward"
        self.held = False  # a protective stop holds the truck
        self.clear_s = 0.0  # how long the restart fields have been clear while held (s)
        self.state = SafetyState()
        self.protective_zone: list[Solid] = []  # the field to keep clear as solids (world), after `update`

    def select(self, field_set: FieldSet, direction: TravelDirection) -> None:
        """Select the field case: the set and the direction of travel the truck is about to drive. It holds
        while the truck stands and nothing is commanded; a command or motion then sets the direction."""
        self.field_set, self.direction = field_set, direction

    @property
    def enabled(self) -> bool:
        """True when the vehicle file has scanners."""
        return self.params.safety_scanner is not None

    def _zone(self, rects: Sequence[FieldRect], pose: SE2) -> list[Solid]:
        """Field rectangles as thin solids in the scan plane (world frame)."""
        scanner = self.params.safety_scanner
        assert scanner is not None
        z = scanner.scan_height
        return [
            box_solid("field", str(k), pose, (r.x0, r.y0, z - 0.01), (r.x1, r.y1, z + 0.01))
            for k, r in enumerate(rects)
        ]

    def _hits(self, groups: Sequence[Sequence[FieldRect]], pose: SE2, world: SolidSet) -> list[list[Solid]]:
        """For each group of field rectangles (forklift frame, the truck at `pose`), the world solids in
        any of them (each once, by kind and id), all groups tested in one go."""
        scanner = self.params.safety_scanner
        assert scanner is not None
        rects = [r for group in groups for r in group]
        if not rects or not len(world):
            return [[] for _ in groups]
        z0, z1 = scanner.scan_height - 0.01, scanner.scan_height + 0.01
        lo = np.array([(r.x0, r.y0, z0) for r in rects])
        hi = np.array([(r.x1, r.y1, z1) for r in rects])
        inside = overlap_matrix(SolidSet.boxes(["field"] * len(rects), lo, hi, pose), world)
        found: list[dict[tuple[str, str], Solid]] = [{} for _ in groups]
        group_of = [g for g, group in enumerate(groups) for _ in group]
        for i, j in zip(*np.nonzero(inside), strict=True):  # by field, then in the world's order
            solid = world.solids[j]
            found[group_of[i]].setdefault((solid.kind, solid.id), solid)
        return [list(f.values()) for f in found]

    def update(
        self,
        dt: float,
        pose: SE2,
        speed: float,
        speed_cmd: float,
        front_x: float,
        world: Sequence[Solid] | SolidSet,
    ) -> SafetyState:
        """One step (`dt`, s) at the true `pose` (world), measured `speed` and commanded `speed_cmd` (m/s);
        `front_x` (m, forklift frame) is the truck's leading end going forward; `world` the solids."""
        scanner = self.params.safety_scanner
        if scanner is None:
            return self.state
        if abs(speed_cmd) > _MOVING:
            self.direction = "forward" if speed_cmd > 0 else "reverse"
        elif abs(speed) > _MOVING:
            self.direction = "forward" if speed > 0 else "reverse"
        direction = self.direction
        fields = safety_fields(self.params, speed, direction, self.field_set, front_x)
        assert fields is not None
        restart = safety_fields(self.params, max(abs(speed), scanner.warning_speed), direction, self.field_set, front_x)
        assert restart is not None
        groups = [fields.protective, fields.warning] + ([restart.protective] if self.held else [])
        protective, warning, *waiting = self._hits(groups, pose, SolidSet.of(world))
        if protective:
            self.held, self.clear_s = True, 0.0
        elif self.held:
            if waiting[0]:
                self.clear_s = 0.0
            else:
                self.clear_s += dt
                if self.clear_s >= scanner.restart_delay_s - 1e-9:
                    self.held = False
        # What must stay clear now: while held, the field it waits on to drive on (people keep out of it).
        self.protective_zone = self._zone(restart.protective if self.held else fields.protective, pose)
        seen = {f"{s.kind} '{s.id}'": None for s in protective + warning}
        self.state = SafetyState(
            field_set=self.field_set,
            direction=direction,
            warning=bool(warning),
            protective_stop=self.held,
            speed_limit=scanner.warning_speed if warning or self.held else None,
            intrusions=tuple(seen),
        )
        return self.state
