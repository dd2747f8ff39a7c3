"""The path-follower interface shared by the MPC and pure pursuit, and what they have in common.

A follower is non-blocking, for the executor's 20 Hz tick (py_trees manner):

    follower.start(path)                                  # once, a `ReferencePath` (world frame)
    cmd = follower.update(t, T_world_forklift, speed, steering)   # every tick
    vehicle.drive(cmd.speed, cmd.steering)                # until cmd.status is not RUNNING
    follower.stop()                                       # on leaving (also on failure)

`update` takes the time `t` (s, any monotonic clock), the localization pose `T_world_forklift`
(`SE2`, world frame) and the measured speed (m/s, negative in reverse) and steering angle (rad,
`yaw_rate = v tan(steering) / wheelbase`). It returns a `DriveCommand`: speed and steering to send,
and the status (running, succeeded, failed).

The follower drives the path's segments in order: it follows a segment, stops at its end (where the
direction of travel changes), then follows the next one; the last segment ends with a precise stop at
the path's end pose (e.g. the pallet node). A segment is done when the forklift stands still
(|speed| <= `stop_speed`) within `end_tolerance` (m, along the path) of its end, or past it.

Safety, common to every follower:
- a control step that fails (solver failure, late solve, non-finite output) never reaches the
  vehicle: the follower brakes instead (speed ramped to 0 at `max_decel`, steering held), and after
  `max_failures` consecutive failures `update` raises `ControlError`;
- progress check: when the forklift has not advanced `progress_min_m` along the segment for
  `progress_timeout_s`, `update` raises `ControlError`.
After a `ControlError` the status is FAILED and further `update`s return braking commands; the
caller must stop the vehicle.

Localization is smoothed by a complementary filter (`PoseFilter`): the pose is predicted from the
measured speed and steering with the kinematic model and pulled towards each localization fix with
gain `pose_filter_gain` (1.0 uses the raw fixes).
"""

from __future__ import annotations

import math
import time
from abc import ABC, abstractmethod
from collections.abc import Callable
from dataclasses import dataclass, field
from enum import Enum

import numpy as np

from palletpilot.control.errors import ControlError
from palletpilot.control.model import KinematicModel
from palletpilot.control.vehicle import VehicleParams
from palletpilot.geometry import SE2, wrap_angle
from palletpilot.roadmap.path import PathSegment, ReferencePath


class FollowerStatus(str, Enum):
    """Outcome of a follower tick."""

    RUNNING = "running"
    SUCCEEDED = "succeeded"
    FAILED = "failed"


@dataclass(frozen=True)
class DriveCommand:
    """What to send to the vehicle: speed (m/s, negative in reverse), steering angle (rad), and the status."""

    speed: float
    steering: float
    status: FollowerStatus


@dataclass(frozen=True)
class TrackingError:
    """The forklift's pose against the path at the nearest reference point (estimated pose).

    `lateral` (m, positive left of the path), `heading` (rad, forklift yaw minus path yaw) and
    `remaining` (m along the path to the segment's end, negative past it).
    """

    lateral: float
    heading: float
    remaining: float


@dataclass
class FollowerConfig:
    """Settings common to every follower (SI units)."""

    control_dt: float = 0.05
    """Nominal tick period (s); the executor's 20 Hz."""
    end_tolerance: float = 0.01
    """A segment is done within this distance (m, along the path) of its end, standing still."""
    stop_speed: float = 0.005
    """Standing still: |speed| at most this (m/s)."""
    max_failures: int = 3
    """Consecutive failed control steps before `ControlError`."""
    progress_timeout_s: float = 5.0
    """`ControlError` when the forklift advances less than `progress_min_m` in this long (s)."""
    progress_min_m: float = 0.01
    pose_filter_gain: float = 0.15
    """Complementary filter gain per tick on localization fixes (1.0: raw localization)."""
    max_lateral_accel: float = 0.5
    """m/s^2: the speed profile slows curves to sqrt(a / |curvature|)."""
    stop_decel: float = 0.4
    """m/s^2: the planned deceleration to each segment end (gentler than `max_decel`: a smooth stop)."""
    plan_accel: float = 0.4
    """m/s^2: the planned acceleration of the speed reference."""


class SegmentTrack:
    """One path segment prepared for tracking: unwrapped headings, vehicle curvature, speed profile.

    Arrays are per sample of the segment (world frame); `s` starts at 0. `kappa` is the curvature of
    the forklift origin's path relative to its x axis (d yaw / d forward displacement, 1/m): the
    path's curvature forward, its negative in reverse, so `steering = atan(kappa * wheelbase)`.
    """

    def __init__(self, seg: PathSegment, index: int, model: KinematicModel, config: FollowerConfig) -> None:
        self.segment = seg
        self.index = index
        self.direction = int(seg.direction)
        self.s = np.asarray(seg.s, dtype=float) - float(seg.s[0])
        self.x = np.asarray(seg.x, dtype=float)
        self.y = np.asarray(seg.y, dtype=float)
        self.heading = np.unwrap(np.asarray(seg.heading, dtype=float))
        self.kappa = self.direction * np.asarray(seg.curvature, dtype=float)
        self.length = float(self.s[-1])
        vmax = model.max_speed_forward if self.direction > 0 else model.max_speed_reverse
        self.speed_limit = np.minimum(np.asarray(seg.speed_limit, dtype=float), vmax)
        self.end_pose = seg.end_pose
        self.speed_profile = self._speed_profile(model, config)
        self.name = f"segment {index} ({', '.join(seg.edges)})"

    def _speed_profile(self, model: KinematicModel, config: FollowerConfig) -> np.ndarray:
        """Largest reference speed (m/s, unsigned) per sample: limits, curvature, steering rate, the stop."""
        v = self.speed_limit.copy()
        k = np.abs(self.kappa)
        v = np.minimum(v, np.sqrt(config.max_lateral_accel / np.maximum(k, 1e-6)))
        # Steering rate: over a 0.5 m window the steering must not change faster than the rate limit.
        steer = np.arctan(self.kappa * model.wheelbase)
        window = 0.5
        for i in range(len(self.s)):
            near = np.abs(self.s - self.s[i]) <= window
            dsteer = float(np.ptp(steer[near]))
            if dsteer > 1e-6:
                v[i] = min(v[i], model.max_steering_rate * 2 * window / dsteer)
        # Backward pass with the planned deceleration: slow down before lower limits, a smooth stop at the end.
        v[-1] = 0.0
        ds = np.diff(self.s)
        for i in range(len(v) - 2, -1, -1):
            v[i] = min(v[i], math.sqrt(v[i + 1] ** 2 + 2.0 * config.stop_decel * ds[i]))
        return v

    def limit_at(self, s: float) -> float:
        """The hard speed limit (m/s, unsigned) at arc length `s`: the edge's limit and the vehicle's."""
        return float(np.interp(s, self.s, self.speed_limit))

    def profile_at(self, s: float | np.ndarray) -> float | np.ndarray:
        """Reference speed limit (m/s, unsigned) at arc length `s` (m) from the segment start."""
        return np.interp(s, self.s, self.speed_profile)

    def sample(self, s: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
        """x, y (m), unwrapped heading (rad) and vehicle curvature (1/m) at arc lengths `s` (clipped)."""
        s = np.clip(s, 0.0, self.length)
        return (
            np.interp(s, self.s, self.x),
            np.interp(s, self.s, self.y),
            np.interp(s, self.s, self.heading),
            np.interp(s, self.s, self.kappa),
        )

    def project(self, x: float, y: float, s_guess: float, back: float = 0.5, ahead: float = 1.5) -> float:
        """Arc length (m) of the point of the segment nearest to (x, y), searched near `s_guess`.

        Past the ends the projection continues along the end tangents, so the result may be
        negative or exceed `length`.
        """
        lo = int(np.searchsorted(self.s, s_guess - back, side="left"))
        hi = int(np.searchsorted(self.s, s_guess + ahead, side="right"))
        lo, hi = max(0, lo - 1), min(len(self.s), hi + 1)
        if hi - lo < 2:
            lo, hi = max(0, min(lo, len(self.s) - 2)), min(len(self.s), max(hi, 2))
        px, py = self.x[lo:hi], self.y[lo:hi]
        ax, ay = px[:-1], py[:-1]
        dx, dy = np.diff(px), np.diff(py)
        seg_len2 = np.maximum(dx * dx + dy * dy, 1e-12)
        u = np.clip(((x - ax) * dx + (y - ay) * dy) / seg_len2, 0.0, 1.0)
        d2 = (ax + u * dx - x) ** 2 + (ay + u * dy - y) ** 2
        j = int(np.argmin(d2))
        s = float(self.s[lo + j] + u[j] * (self.s[lo + j + 1] - self.s[lo + j]))
        # Beyond either end: extend along the end tangent (travel direction).
        travel = self.heading + (0.0 if self.direction > 0 else math.pi)
        if s <= 0.0:
            s = float((x - self.x[0]) * math.cos(travel[0]) + (y - self.y[0]) * math.sin(travel[0]))
            s = min(s, 0.0)
        elif s >= self.length:
            along = (x - self.x[-1]) * math.cos(travel[-1]) + (y - self.y[-1]) * math.sin(travel[-1])
            s = self.length + max(float(along), 0.0)
        return s

    def error(self, pose: SE2, s: float) -> TrackingError:
        """The pose's errors against the reference at arc length `s` (see `TrackingError`)."""
        xr, yr, hr, _ = self.sample(np.array([s]))
        c, sn = math.cos(hr[0]), math.sin(hr[0])
        lateral = -sn * (pose.x - xr[0]) + c * (pose.y - yr[0])
        return TrackingError(
            lateral=float(lateral),
            heading=float(wrap_angle(pose.yaw - hr[0])),
            remaining=self.length - s,
        )


class PoseFilter:
    """Complementary filter of `T_world_forklift`: odometry prediction, localization correction."""

    def __init__(self, model: KinematicModel, gain: float) -> None:
        self.model = model
        self.gain = float(np.clip(gain, 0.0, 1.0))
        self.pose: SE2 | None = None

    def reset(self) -> None:
        """Forget the estimate; the next fix is taken as is."""
        self.pose = None

    def update(self, fix: SE2, speed: float, steering: float, dt: float) -> SE2:
        """The new estimate (world frame) from a localization fix and the measured speed and steering."""
        if self.pose is None or self.gain >= 1.0 or dt <= 0.0 or dt > 1.0:
            self.pose = fix
            return fix
        p = self.pose
        z = self.model.step(np.array([p.x, p.y, p.yaw, steering]), np.array([speed, 0.0]), dt)
        k = self.gain
        yaw = z[2] + k * wrap_angle(fix.yaw - z[2])
        self.pose = SE2(z[0] + k * (fix.x - z[0]), z[1] + k * (fix.y - z[1]), yaw)
        return self.pose


class StepFailed(Exception):  # noqa: N818 - internal signal, not an error of the package
    """A control step produced no usable command (the reason is the message)."""


@dataclass
class StepInput:
    """What a follower's control law gets each tick (world frame, SI units)."""

    t: float
    dt: float
    pose: SE2
    speed: float
    steering: float
    s: float
    error: TrackingError


@dataclass
class FollowerLog:
    """Per-tick records for benchmarks and tests: solve times (s) and tracking errors."""

    solve_s: list[float] = field(default_factory=list)
    lateral: list[float] = field(default_factory=list)
    heading: list[float] = field(default_factory=list)
    segment: list[int] = field(default_factory=list)
    failures: int = 0


class Follower(ABC):
    """Base of the path followers: segment sequencing, pose filter, braking, failure and progress checks."""

    name = "follower"

    def __init__(self, params: VehicleParams, config: FollowerConfig | None = None) -> None:
        self.params = params
        self.model = KinematicModel.from_params(params)
        self.config = config if config is not None else FollowerConfig()
        self.filter = PoseFilter(self.model, self.config.pose_filter_gain)
        self.log = FollowerLog()
        self._tracks: list[SegmentTrack] = []
        self._index = 0
        self._status = FollowerStatus.SUCCEEDED
        # Fault injection (the simulator's `solver_failure`): a message fails this control step like a solver.
        self.step_fault: Callable[[float], str | None] | None = None
        self._t_prev: float | None = None
        self._s = 0.0
        self._failures = 0
        self._last_speed_cmd = 0.0
        self._best_s = 0.0
        self._t_progress: float | None = None

    # -- the interface ------------------------------------------------------------------
    @property
    def status(self) -> FollowerStatus:
        """The status of the last tick."""
        return self._status

    @property
    def segment_index(self) -> int:
        """Index of the segment being followed."""
        return self._index

    @property
    def distance_to_go(self) -> float:
        """Path length (m) still ahead: the rest of this segment and all the following ones."""
        if not self._tracks or self._index >= len(self._tracks):
            return 0.0
        rest = self._tracks[self._index].length - self._s  # progress `_s` runs from 0 along the segment
        return max(rest, 0.0) + sum(t.length for t in self._tracks[self._index + 1 :])

    def start(self, path: ReferencePath) -> None:
        """Begin following `path` (world frame) from its first segment."""
        if not path.segments:
            raise ControlError("path has no segments to follow")
        self._tracks = [SegmentTrack(seg, i, self.model, self.config) for i, seg in enumerate(path.segments)]
        self._index = 0
        self._status = FollowerStatus.RUNNING
        self._t_prev = None
        self._failures = 0
        self._last_speed_cmd = 0.0
        self.filter.reset()
        self._begin_segment()

    def update(self, t: float, pose: SE2, speed: float, steering: float) -> DriveCommand:
        """One tick: localization `pose` (`T_world_forklift`), measured speed (m/s) and steering (rad)."""
        dt = self.config.control_dt if self._t_prev is None else t - self._t_prev
        self._t_prev = t
        if self._status is not FollowerStatus.RUNNING:
            return DriveCommand(self._brake(speed, dt), steering, self._status)
        est = self.filter.update(pose, speed, steering, dt)
        track = self._tracks[self._index]
        self._s = track.project(est.x, est.y, self._s)
        err = track.error(est, min(max(self._s, 0.0), track.length))
        err = TrackingError(err.lateral, err.heading, track.length - self._s)
        self.log.lateral.append(err.lateral)
        self.log.heading.append(err.heading)
        self.log.segment.append(self._index)

        if err.remaining <= self.config.end_tolerance and abs(speed) <= self.config.stop_speed:
            if self._index + 1 < len(self._tracks):
                self._index += 1
                self._begin_segment()
                track = self._tracks[self._index]
                self._s = track.project(est.x, est.y, 0.0)
                err = track.error(est, min(max(self._s, 0.0), track.length))
                err = TrackingError(err.lateral, err.heading, track.length - self._s)
            else:
                self._status = FollowerStatus.SUCCEEDED
                self._last_speed_cmd = 0.0
                return DriveCommand(0.0, steering, self._status)

        self._check_progress(t, track)
        step = StepInput(t, dt, est, speed, steering, self._s, err)
        try:
            injected = self.step_fault(t) if self.step_fault is not None else None
            if injected is not None:
                raise StepFailed(injected)
            v_cmd, steer_cmd = self._control(self._tracks[self._index], step)
            v_cmd, steer_cmd = self._checked(v_cmd, steer_cmd, self._tracks[self._index])
        except StepFailed as exc:
            self._failures += 1
            self.log.failures += 1
            brake = DriveCommand(self._brake(speed, dt), steering, FollowerStatus.RUNNING)
            self._last_speed_cmd = brake.speed
            if self._failures >= self.config.max_failures:
                self._status = FollowerStatus.FAILED
                raise ControlError(
                    f"{self.name}: {self._failures} consecutive failed control steps on "
                    f"{self._tracks[self._index].name}, braking; last: {exc}"
                ) from None
            return brake
        self._failures = 0
        self._last_speed_cmd = v_cmd
        return DriveCommand(v_cmd, steer_cmd, FollowerStatus.RUNNING)

    def stop(self) -> None:
        """Leave: forget the path; further updates brake and report the last status."""
        if self._status is FollowerStatus.RUNNING:
            self._status = FollowerStatus.FAILED
        self._tracks = self._tracks[self._index : self._index + 1]
        self._index = 0

    # -- helpers ------------------------------------------------------------------------
    def _begin_segment(self) -> None:
        self._s = 0.0
        self._best_s = 0.0
        self._t_progress = None  # set on the next update, with its clock
        self._start_segment(self._tracks[self._index])

    def _check_progress(self, t: float, track: SegmentTrack) -> None:
        if self._t_progress is None:
            self._t_progress = t
        if self._s >= self._best_s + self.config.progress_min_m:
            self._best_s = self._s
            self._t_progress = t
        elif t - self._t_progress > self.config.progress_timeout_s:
            self._status = FollowerStatus.FAILED
            raise ControlError(
                f"{self.name}: no progress for {t - self._t_progress:.1f} s on {track.name} "
                f"at {self._s:.2f} m of {track.length:.2f} m"
            )

    def _brake(self, speed: float, dt: float) -> float:
        """Speed command ramping the measured speed to 0 at the deceleration limit (m/s)."""
        step = self.params.max_decel * max(dt, 0.0)
        return float(math.copysign(max(abs(speed) - step, 0.0), speed)) if speed else 0.0

    def _checked(self, speed: float, steering: float, track: SegmentTrack) -> tuple[float, float]:
        """Reject non-finite commands and clip to the vehicle's limits and the segment's direction."""
        if not (math.isfinite(speed) and math.isfinite(steering)):
            raise StepFailed(f"non-finite command (speed {speed}, steering {steering})")
        p = self.params
        limit = track.limit_at(min(max(self._s, 0.0), track.length))
        speed = min(max(speed, 0.0), limit) if track.direction > 0 else max(min(speed, 0.0), -limit)
        return speed, float(np.clip(steering, -p.max_steering, p.max_steering))

    # -- for subclasses -----------------------------------------------------------------
    def _start_segment(self, track: SegmentTrack) -> None:  # noqa: B027 - optional hook
        """Called when a segment begins (reset warm starts and the like)."""

    @abstractmethod
    def _control(self, track: SegmentTrack, step: StepInput) -> tuple[float, float]:
        """Speed (m/s) and steering (rad) for this tick; raise `StepFailed` when there is none."""


def lag_compensated(current: float, target: float, lag: float, dt: float) -> float:
    """Command for a first-order lag (time constant `lag`, s) to move from `current` to `target` in `dt`."""
    return current + (target - current) * max(1.0, lag / dt) if dt > 0 else target


def timed() -> float:
    """Wall clock for solve timing (s)."""
    return time.perf_counter()
