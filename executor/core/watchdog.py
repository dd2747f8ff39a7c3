"""Watchdogs: checks on every control tick that stop the vehicle when its inputs or outputs go wrong.

- stale localization: the last fix is older than `localization_max_age_s` -> `sensor_timeout`;
- stale camera frames: a frame handed to perception is older than `camera_max_age_s` -> `sensor_timeout`;
- a vehicle that does not follow its commands: its measured speed stays more than `speed_tolerance`
  (m/s) away from what the commands make a truck of these limits do, for `command_persist_s` ->
  `vehicle_fault`;
- a localization that jumps: between two ticks the fix moves more than the truck can have moved
  (|v| dt, and the yaw its steering allows) by over `localization_jump_m` or `localization_jump_deg`
  -> `localization_fault` (the truck would otherwise steer its true self off the path to follow it);
- a streak of `overrun_streak` control ticks that started late (wall clock) -> `vehicle_fault`: the
  truck no longer gets its commands at the control rate.

Each raises `TaskFailed` with the reason and the measured figure in the message; the runner then stops
the vehicle. `CommandedVehicle` wraps a `VehiclePort` to remember what was commanded.

Public API: `WatchdogLimits`, `Watchdogs`, `CommandedVehicle`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

from palletpilot.control.vehicle import VehicleParams
from palletpilot.executor.core.clock import Clock
from palletpilot.executor.core.errors import LOCALIZATION_FAULT, SENSOR_TIMEOUT, VEHICLE_FAULT, TaskFailed
from palletpilot.executor.ports import PassThroughVehicle, VehiclePort
from palletpilot.geometry import SE2, wrap_angle
from palletpilot.perception.frames import FrameBundle


@dataclass(frozen=True)
class WatchdogLimits:
    """When a watchdog fires (s, m/s, ticks)."""

    localization_max_age_s: float = 0.5
    camera_max_age_s: float = 0.5
    speed_tolerance: float = 0.2
    command_persist_s: float = 0.5
    overrun_streak: int = 5
    localization_jump_m: float = 0.15
    localization_jump_deg: float = 5.0


class CommandedVehicle(PassThroughVehicle):
    """A `VehiclePort` that remembers the last speed commanded (`commanded_speed`, m/s)."""

    def __init__(self, inner: VehiclePort) -> None:
        super().__init__(inner)
        self.commanded_speed = 0.0
        self.emergency = False

    def drive(self, speed: float, steering: float) -> None:
        """Drive command (m/s, rad); ignored after an emergency stop, capped at the safety scanners'
        speed limit while their warning field is intruded (the truck caps it too)."""
        if self.emergency:
            self.inner.stop()
            return
        limit = self.inner.safety_state().speed_limit
        if limit is not None:
            speed = min(max(speed, -limit), limit)
        self.commanded_speed = speed
        self.inner.drive(speed, steering)

    def stop(self) -> None:
        """Brake to a standstill at the service brake."""
        self.commanded_speed = 0.0
        self.inner.stop()

    def emergency_stop(self) -> None:
        """The truck's safety stop (latched until the run ends)."""
        self.emergency = True
        self.commanded_speed = 0.0
        self.inner.emergency_stop()


class Watchdogs:
    """The per-tick checks of the module docstring."""

    PULL = 0.05
    """Share of the speed error the reference takes over per tick (a 1 s time constant at 20 Hz)."""

    def __init__(self, params: VehicleParams, limits: WatchdogLimits | None = None) -> None:
        self.params = params
        self.limits = limits or WatchdogLimits()
        self._v_expected: float | None = None
        self._cmd_prev = 0.0
        self._bad_since: float | None = None
        self._last_fix: SE2 | None = None

    def reset(self) -> None:
        """Forget the speed and pose history (after a pause or a resume)."""
        self._v_expected = None
        self._bad_since = None
        self._last_fix = None

    def check(self, now: float, vehicle: CommandedVehicle, clock: Clock) -> None:
        """All per-tick checks; raises `TaskFailed` (`sensor_timeout`, `vehicle_fault`)."""
        lim = self.limits
        stamp = vehicle.localization_stamp()
        age = now - stamp
        if age > lim.localization_max_age_s:
            limit = lim.localization_max_age_s
            raise TaskFailed(SENSOR_TIMEOUT, f"localization is stale: last fix {age:.2f} s old (limit {limit} s)")
        if clock.overrun_streak >= lim.overrun_streak:
            raise TaskFailed(
                VEHICLE_FAULT,
                f"control loop overran {clock.overrun_streak} ticks in a row (limit {lim.overrun_streak}): "
                "the truck no longer gets its commands at the control rate",
            )
        self._check_speed(now, vehicle, clock.dt)
        self._check_jump(vehicle, clock.dt)

    def _check_jump(self, vehicle: CommandedVehicle, dt: float) -> None:
        """Compare the fix's move since the last tick with what the measured speed allows (world frame)."""
        fix = vehicle.localization()
        last, self._last_fix = self._last_fix, fix
        if last is None:
            return
        travel = abs(vehicle.speed) * dt + self.params.max_accel * dt * dt
        moved = math.hypot(fix.x - last.x, fix.y - last.y)
        turned = abs(math.degrees(wrap_angle(fix.yaw - last.yaw)))
        turn_allowed = math.degrees(travel * self.params.max_curvature)
        lim = self.limits
        if moved - travel > lim.localization_jump_m or turned - turn_allowed > lim.localization_jump_deg:
            raise TaskFailed(
                LOCALIZATION_FAULT,
                f"localization jumped {moved:.2f} m / {turned:.1f} deg in {dt:.2f} s where the truck at "
                f"{vehicle.speed:.2f} m/s moves {travel:.2f} m (limits +{lim.localization_jump_m} m, "
                f"+{lim.localization_jump_deg} deg)",
            )

    def _check_speed(self, now: float, vehicle: CommandedVehicle, dt: float) -> None:
        """Compare the measured speed with a reference driven by the commands alone.

        The reference follows the commands with the truck's lag and limits and is pulled towards the
        measurement only slowly (`PULL` per tick, about a second's time constant), so a small model
        mismatch fades while a vehicle that drifts away from its commands builds up an error.
        """
        measured = vehicle.speed
        if self._v_expected is None:
            self._v_expected, self._cmd_prev = measured, vehicle.commanded_speed
            return
        # The scanners' protective stop brakes like the safety stop, whatever was commanded.
        braking_hard = vehicle.emergency or vehicle.inner.safety_state().protective_stop
        predicted = self._model_step(self._v_expected, self._cmd_prev, dt, braking_hard)
        self._cmd_prev = vehicle.commanded_speed
        error = measured - predicted
        self._v_expected = predicted + self.PULL * error
        if abs(error) <= self.limits.speed_tolerance:
            self._bad_since = None
            return
        if self._bad_since is None:
            self._bad_since = now
        if now - self._bad_since >= self.limits.command_persist_s:
            raise TaskFailed(
                VEHICLE_FAULT,
                f"the vehicle does not follow its commands: it measures {measured:.2f} m/s where the commands "
                f"give {predicted:.2f} m/s, for {now - self._bad_since:.2f} s",
            )

    def _model_step(self, v: float, cmd: float, dt: float, emergency: bool = False) -> float:
        """The speed one tick on: first-order lag towards the (clipped) command, bounded accel / decel."""
        p = self.params
        cmd = min(max(cmd, -p.max_speed_reverse), p.max_speed_forward)
        lag = max(p.actuator_lag_s, dt)
        dv = (cmd - v) * (1.0 if emergency else min(1.0, dt / lag))
        braking = abs(cmd) < abs(v) or cmd * v < 0
        decel = p.emergency_decel if emergency else p.max_decel
        dv_max = (decel if braking else p.max_accel) * dt
        return v + min(max(dv, -dv_max), dv_max)

    def check_frame(self, frame: FrameBundle, now: float) -> None:
        """Refuse a camera frame older than the limit (`sensor_timeout`); frames without a stamp pass."""
        stamp = frame.stamp_s
        if stamp is None or not math.isfinite(stamp):
            return
        age = now - stamp
        if age > self.limits.camera_max_age_s:
            raise TaskFailed(
                SENSOR_TIMEOUT, f"camera frame is stale: {age:.2f} s old (limit {self.limits.camera_max_age_s} s)"
            )
