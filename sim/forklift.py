"""Simulated forklift: kinematic tricycle with actuator lag, slip noise and a rate-limited mast.

State in the world frame: the pose of the forklift origin (midway between the forks on the fixed
front axle, at the fork heels), its speed `v` (m/s, positive with the fork tips leading), the steering
angle and the fork height (m, fork bottoms above the floor).

Steering sign: `steering` is the angle whose tangent over the wheelbase is the path curvature,
`yaw_rate = v * tan(steering) / wheelbase`, positive turning left when driving forward. The steered
drive wheel sits `wheelbase` behind the origin, so its physical wheel angle is `-steering`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from palletpilot.control.vehicle import VehicleParams
from palletpilot.geometry import SE2


def _clip(value: float, lo: float, hi: float) -> float:
    """`value` limited to [lo, hi] as a float, as `float(np.clip(...))` gives it, without numpy's cost."""
    return float(min(max(value, lo), hi))


@dataclass
class ForkliftState:
    """True state of the simulated forklift (world frame, SI units)."""

    pose: SE2
    v: float = 0.0
    steering: float = 0.0
    fork_height: float = 0.0


class SimForklift:
    """Integrates the forklift at a fixed step; commands are speed (m/s), steering (rad) and fork height (m)."""

    def __init__(
        self,
        params: VehicleParams,
        pose: SE2,
        rng: np.random.Generator | None = None,
        slip_sigma: float = 0.0,
        fork_height: float = 0.0,
    ) -> None:
        self.params = params
        self.state = ForkliftState(pose, fork_height=fork_height)
        self.rng = rng if rng is not None else np.random.default_rng(0)
        self.slip_sigma = slip_sigma  # relative 1-sigma noise on travelled distance and turn per step
        self.speed_cmd = 0.0
        self.steering_cmd = 0.0
        self.fork_height_cmd = fork_height
        self.odometer = 0.0  # m travelled, for progress checks
        self.emergency = False  # the safety stop is latched: brake at emergency_decel, no drive commands
        self.protective_stop = False  # the scanners' stop (not latched): brake at emergency_decel meanwhile
        self.speed_cap: float | None = None  # m/s, the scanners' warning-field cap

    # -- commands -----------------------------------------------------------------------
    def command(self, speed: float, steering: float) -> None:
        """Set the drive command: speed (m/s, negative in reverse) and steering angle (rad), clipped to limits."""
        p = self.params
        if self.emergency:
            return
        self.speed_cmd = _clip(speed, -p.max_speed_reverse, p.max_speed_forward)
        self.steering_cmd = _clip(steering, -p.max_steering, p.max_steering)

    def command_fork_height(self, height: float) -> None:
        """Set the fork height target (m), clipped to the mast's range."""
        m = self.params.mast
        self.fork_height_cmd = _clip(height, m.min_height, m.max_height)

    def stop(self) -> None:
        """Command zero speed (the actuators still brake at their limits); steering is held."""
        self.speed_cmd = 0.0

    def emergency_stop(self) -> None:
        """Latch the safety stop: zero speed at `emergency_decel`, drive commands ignored from now on."""
        self.emergency = True
        self.speed_cmd = 0.0

    # -- integration --------------------------------------------------------------------
    def step(self, dt: float) -> None:
        """Advance the state by `dt` seconds."""
        p, s = self.params, self.state
        lag = max(p.actuator_lag_s, dt)
        # Speed: first-order lag towards the command, bounded by acceleration / deceleration. The safety
        # stop (and the scanners' protective stop) acts on the brakes directly: no drive-controller lag,
        # the emergency deceleration. The warning field caps the command.
        hard = self.emergency or self.protective_stop
        cmd = 0.0 if hard else self.speed_cmd
        if self.speed_cap is not None:
            cmd = _clip(cmd, -self.speed_cap, self.speed_cap)
        over_cap = self.speed_cap is not None and abs(s.v) > self.speed_cap  # safe speed: braked, not lagged
        dv = (cmd - s.v) * (1.0 if hard or over_cap else min(1.0, dt / lag))
        braking = abs(cmd) < abs(s.v) or cmd * s.v < 0
        decel = p.emergency_decel if hard else p.max_decel
        dv_max = (decel if braking else p.max_accel) * dt
        v_new = s.v + _clip(dv, -dv_max, dv_max)
        # Steering: first-order lag towards the command, bounded by the steering rate and angle.
        rate = math.radians(p.max_steering_rate_deg_s)
        dd = _clip((self.steering_cmd - s.steering) * min(1.0, dt / lag), -rate * dt, rate * dt)
        steering = _clip(s.steering + dd, -p.max_steering, p.max_steering)

        v_mean = 0.5 * (s.v + v_new)
        dist = v_mean * dt
        dyaw = dist * math.tan(steering) / p.wheelbase
        if self.slip_sigma > 0.0 and dist != 0.0:
            dist *= 1.0 + self.slip_sigma * self.rng.standard_normal()
            dyaw *= 1.0 + self.slip_sigma * self.rng.standard_normal()
        # Exact integration along the arc of constant curvature over the step.
        if abs(dyaw) > 1e-9:
            r = dist / dyaw
            local = SE2(r * math.sin(dyaw), r * (1.0 - math.cos(dyaw)), dyaw)
        else:
            local = SE2(dist, 0.0, dyaw)
        s.pose = s.pose @ local
        s.v, s.steering = v_new, steering
        self.odometer += abs(dist)

        m = self.params.mast
        dh = self.fork_height_cmd - s.fork_height
        limit = (m.lift_speed if dh > 0 else m.lower_speed) * dt
        s.fork_height += _clip(dh, -limit, limit)

    @property
    def stopped(self) -> bool:
        """True when the forklift stands still (|v| below 1 mm/s)."""
        return abs(self.state.v) < 1e-3


@dataclass(frozen=True)
class LocalizationNoise:
    """1-sigma noise of the localization estimate: position (m) and yaw (rad)."""

    xy_sigma: float = 0.0
    yaw_sigma: float = 0.0

    def measure(self, true_pose: SE2, rng: np.random.Generator) -> SE2:
        """A noisy `T_world_forklift` as localization would report it."""
        if self.xy_sigma == 0.0 and self.yaw_sigma == 0.0:
            return true_pose
        dx, dy = rng.normal(0.0, self.xy_sigma, 2) if self.xy_sigma > 0 else (0.0, 0.0)
        dyaw = rng.normal(0.0, self.yaw_sigma) if self.yaw_sigma > 0 else 0.0
        return SE2(true_pose.x + dx, true_pose.y + dy, true_pose.yaw + dyaw)
