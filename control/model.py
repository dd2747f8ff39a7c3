"""Kinematic model of the forklift for the controllers (world or any planar frame, SI units).

The forklift is a tricycle whose origin sits on the fixed front axle at the fork heels (see `control.vehicle`);
the steered drive wheel is `wheelbase` behind it. Kinematically it is a bicycle with the reference
point on the unsteered axle:

    state   z = (x, y, yaw, steering)         m, m, rad, rad
    inputs  u = (speed, steering_rate)        m/s (negative in reverse), rad/s
    x'        = speed * cos(yaw)
    y'        = speed * sin(yaw)
    yaw'      = speed * tan(steering) / wheelbase      (positive steering turns left going forward)
    steering' = steering_rate

The same equations drive `sim.forklift.SimForklift` (which adds actuator lag, slip and limits).
`KinematicModel` gives the CasADi expressions for the MPC (continuous right-hand side and an RK4
step) and a numpy step for prediction and tests.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import TypeVar

import casadi as ca
import numpy as np

from palletpilot.control.vehicle import VehicleParams

NX = 4
"""State size: x, y, yaw, steering."""
NU = 2
"""Input size: speed, steering rate."""

_Sym = TypeVar("_Sym", ca.SX, ca.MX, ca.DM)
"""A CasADi expression type (DM for numeric evaluation): one call uses one type throughout."""


@dataclass(frozen=True)
class KinematicModel:
    """The forklift's kinematic bicycle model with its limits, from `VehicleParams`."""

    wheelbase: float
    max_steering: float
    max_steering_rate: float
    max_speed_forward: float
    max_speed_reverse: float
    max_accel: float
    max_decel: float
    actuator_lag: float

    @classmethod
    def from_params(cls, params: VehicleParams) -> KinematicModel:
        """The model of the vehicle file's forklift (degrees converted to radians)."""
        return cls(
            wheelbase=params.wheelbase,
            max_steering=params.max_steering,
            max_steering_rate=math.radians(params.max_steering_rate_deg_s),
            max_speed_forward=params.max_speed_forward,
            max_speed_reverse=params.max_speed_reverse,
            max_accel=params.max_accel,
            max_decel=params.max_decel,
            actuator_lag=params.actuator_lag_s,
        )

    @property
    def max_curvature(self) -> float:
        """Tightest curvature (1/m) of the origin's path."""
        return math.tan(self.max_steering) / self.wheelbase

    def steering_for_curvature(self, curvature: float | np.ndarray) -> float | np.ndarray:
        """Steering angle (rad) whose path curvature (1/m, d yaw / d forward displacement) is `curvature`."""
        return np.arctan(np.asarray(curvature) * self.wheelbase)

    def rhs(self, z: _Sym, u: _Sym) -> _Sym:
        """Continuous-time right-hand side dz/dt (CasADi expression)."""
        v, rate = u[0], u[1]
        return ca.vertcat(
            v * ca.cos(z[2]),
            v * ca.sin(z[2]),
            v * ca.tan(z[3]) / self.wheelbase,
            rate,
        )

    def rk4(self, z: _Sym, u: _Sym, dt: float) -> _Sym:
        """State after `dt` seconds with constant inputs (one RK4 step, CasADi expression)."""
        k1 = self.rhs(z, u)
        k2 = self.rhs(z + 0.5 * dt * k1, u)
        k3 = self.rhs(z + 0.5 * dt * k2, u)
        k4 = self.rhs(z + dt * k3, u)
        return z + dt / 6.0 * (k1 + 2 * k2 + 2 * k3 + k4)

    def step(self, z: np.ndarray, u: np.ndarray, dt: float) -> np.ndarray:
        """State after `dt` seconds with constant inputs (numpy, exact arc integration)."""
        x, y, yaw, steering = (float(a) for a in z)
        v, rate = float(u[0]), float(u[1])
        steering_end = steering + rate * dt
        # Integrate the heading with the mean steering curvature, then move along the arc exactly.
        kappa = 0.5 * (math.tan(steering) + math.tan(steering_end)) / self.wheelbase
        dist = v * dt
        dyaw = dist * kappa
        if abs(dyaw) > 1e-9:
            r = dist / dyaw
            dx_l, dy_l = r * math.sin(dyaw), r * (1.0 - math.cos(dyaw))
        else:
            dx_l, dy_l = dist, 0.0
        c, s = math.cos(yaw), math.sin(yaw)
        return np.array([x + c * dx_l - s * dy_l, y + s * dx_l + c * dy_l, yaw + dyaw, steering_end])
