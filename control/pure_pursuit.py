"""Regulated pure pursuit: the baseline path follower, with the `Follower` interface of the MPC.

Each tick (world frame, estimated pose): the look-ahead point lies `lookahead` metres further along
the segment than the forklift's projection (past the end, on the end tangent); the arc through the
forklift origin, tangent to its heading and through that point, has curvature `2 y / d^2` (y: the
point's lateral offset in the forklift frame, d: its distance), and the steering is
`atan(curvature * wheelbase)`, for either direction of travel. The look-ahead grows with speed.

Speed regulation (as in Nav2's regulated pure pursuit): the segment's speed profile (edge limits,
lateral acceleration, smooth stop at the end), slowed further on tight commanded curvature, a
creep speed for the last centimetres, and 0 once the end is reached.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from palletpilot.control.follower import Follower, FollowerConfig, SegmentTrack, StepInput, timed
from palletpilot.control.vehicle import VehicleParams


@dataclass
class PurePursuitConfig:
    """Look-ahead (m, and s times speed) and speed regulation of the pure-pursuit follower."""

    lookahead_time: float = 0.8
    min_lookahead: float = 0.35
    max_lookahead: float = 1.5
    regulated_min_radius: float = 1.0
    """Below this radius of the commanded arc (m) the speed is scaled by radius / this."""
    creep_speed: float = 0.03
    """m/s: the slowest approach speed before the segment end."""
    min_speed: float = 0.05
    """m/s: regulation never slows below this (except at the end)."""


class PurePursuitFollower(Follower):
    """Regulated pure pursuit on the estimated pose; see the module docstring."""

    name = "pure_pursuit"

    def __init__(
        self,
        params: VehicleParams,
        config: PurePursuitConfig | None = None,
        follower_config: FollowerConfig | None = None,
    ) -> None:
        super().__init__(params, follower_config)
        self.pp = config if config is not None else PurePursuitConfig()

    def _control(self, track: SegmentTrack, step: StepInput) -> tuple[float, float]:
        t0 = timed()
        pose, pp = step.pose, self.pp
        ld = float(np.clip(pp.lookahead_time * abs(step.speed), pp.min_lookahead, pp.max_lookahead))
        s_target = step.s + ld
        if s_target <= track.length:
            x, y, _, _ = track.sample(np.array([s_target]))
            tx, ty = float(x[0]), float(y[0])
        else:  # past the end: continue along the end tangent in the direction of travel
            travel = float(track.heading[-1]) + (0.0 if track.direction > 0 else math.pi)
            extra = s_target - track.length
            tx = float(track.x[-1]) + extra * math.cos(travel)
            ty = float(track.y[-1]) + extra * math.sin(travel)
        local = pose.inv().apply(np.array([tx, ty]))
        d2 = float(local @ local)
        kappa = 2.0 * float(local[1]) / max(d2, 1e-6)
        kappa = float(np.clip(kappa, -self.model.max_curvature, self.model.max_curvature))
        steering = math.atan(kappa * self.model.wheelbase)

        remaining = step.error.remaining
        v = float(track.profile_at(min(max(step.s, 0.0), track.length)))
        radius = 1.0 / max(abs(kappa), 1e-6)
        if radius < pp.regulated_min_radius:
            v = max(v * radius / pp.regulated_min_radius, min(v, pp.min_speed))
        if remaining > self.config.end_tolerance * 0.5:
            v = max(v, pp.creep_speed)
        else:
            v = 0.0
        self.log.solve_s.append(timed() - t0)
        return track.direction * v, steering
