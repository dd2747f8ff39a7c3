"""Roadmap curves in the world frame (x, y in m): line, circular arc, cubic Bezier.

Every curve is parametrised by arc length s in [0, length] from its start point to its end point.
`heading` is the tangent direction of that parametrisation (rad), `curvature` its signed curvature
d(heading)/ds (1/m, positive turning left). The vehicle's yaw on a reverse edge is heading + pi; its
curvature in the direction of travel is the same number.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from dataclasses import dataclass
from functools import cached_property
from typing import Any

import numpy as np
from numpy.typing import ArrayLike

from palletpilot.geometry import SE2, wrap_angle
from palletpilot.roadmap.errors import RoadmapError


@dataclass(frozen=True)
class CurveSamples:
    """Samples of a curve at arc lengths `s` (m): position (m), tangent heading (rad), curvature (1/m)."""

    s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    curvature: np.ndarray


class Curve(ABC):
    """A planar curve from `start` to `end`, parametrised by arc length."""

    kind: str = ""

    @property
    @abstractmethod
    def length(self) -> float:
        """Arc length (m)."""

    @abstractmethod
    def sample(self, s: ArrayLike) -> CurveSamples:
        """Position, tangent heading and curvature at arc lengths `s` (m), clipped to [0, length]."""

    @abstractmethod
    def to_dict(self) -> dict[str, Any]:
        """The curve as map-file data (`curve` and its parameters)."""

    def _end(self, at_end: bool) -> tuple[np.ndarray, float]:
        smp = self.sample([self.length if at_end else 0.0])
        return np.array([smp.x[0], smp.y[0]]), float(smp.heading[0])

    @cached_property
    def start_pose(self) -> SE2:
        """Start point with the tangent heading there."""
        p, h = self._end(False)
        return SE2(p[0], p[1], h)

    @cached_property
    def end_pose(self) -> SE2:
        """End point with the tangent heading there."""
        p, h = self._end(True)
        return SE2(p[0], p[1], h)

    @abstractmethod
    def reversed(self) -> Curve:
        """The same curve traversed from end to start."""

    def max_abs_curvature(self, step_m: float = 0.02) -> float:
        """Largest |curvature| (1/m) along the curve, sampled every `step_m`."""
        n = max(2, math.ceil(self.length / step_m) + 1)
        return float(np.max(np.abs(self.sample(np.linspace(0.0, self.length, n)).curvature)))


class Line(Curve):
    """A straight segment from `p0` to `p1` (m)."""

    kind = "line"

    def __init__(self, p0: ArrayLike, p1: ArrayLike) -> None:
        self.p0 = np.asarray(p0, dtype=float).reshape(2)
        self.p1 = np.asarray(p1, dtype=float).reshape(2)
        d = self.p1 - self.p0
        self._length = float(np.hypot(*d))
        if self._length < 1e-9:
            raise RoadmapError("line has zero length")
        self._heading = math.atan2(d[1], d[0])

    @property
    def length(self) -> float:
        return self._length

    def sample(self, s: ArrayLike) -> CurveSamples:
        s_arr = np.clip(np.atleast_1d(np.asarray(s, dtype=float)), 0.0, self._length)
        u = (self.p1 - self.p0) / self._length
        return CurveSamples(
            s_arr,
            self.p0[0] + s_arr * u[0],
            self.p0[1] + s_arr * u[1],
            np.full_like(s_arr, self._heading),
            np.zeros_like(s_arr),
        )

    def _end(self, at_end: bool) -> tuple[np.ndarray, float]:
        return (self.p1 if at_end else self.p0), self._heading

    def reversed(self) -> Line:
        return Line(self.p1, self.p0)

    def to_dict(self) -> dict[str, Any]:
        return {"curve": "line"}


class Arc(Curve):
    """A circular arc leaving `start` (point and tangent heading) and ending at point `p1`.

    The circle is fixed by the start tangent and the end point; its end heading follows from them.
    """

    kind = "arc"

    def __init__(self, start: SE2, p1: ArrayLike) -> None:
        self.p0 = start.xy
        self.p1 = np.asarray(p1, dtype=float).reshape(2)
        self.heading0 = start.yaw
        chord = self.p1 - self.p0
        c = float(np.hypot(*chord))
        if c < 1e-9:
            raise RoadmapError("arc has zero length")
        # alpha: angle from the start tangent to the chord; the arc turns by 2 * alpha.
        alpha = float(wrap_angle(math.atan2(chord[1], chord[0]) - self.heading0))
        if abs(alpha) < 1e-6:
            raise RoadmapError("arc end lies on the start tangent: use a line")
        if abs(alpha) > math.pi - 1e-6:
            raise RoadmapError("arc end lies straight behind the start tangent")
        self.curvature = 2.0 * math.sin(alpha) / c
        self.sweep = 2.0 * alpha
        self._length = abs(self.sweep / self.curvature)

    @property
    def radius(self) -> float:
        """Radius (m)."""
        return 1.0 / abs(self.curvature)

    @property
    def length(self) -> float:
        return self._length

    def sample(self, s: ArrayLike) -> CurveSamples:
        s_arr = np.clip(np.atleast_1d(np.asarray(s, dtype=float)), 0.0, self._length)
        k = self.curvature
        h = self.heading0 + k * s_arr
        x = self.p0[0] + (np.sin(h) - math.sin(self.heading0)) / k
        y = self.p0[1] - (np.cos(h) - math.cos(self.heading0)) / k
        return CurveSamples(s_arr, x, y, np.asarray(wrap_angle(h)), np.full_like(s_arr, k))

    def _end(self, at_end: bool) -> tuple[np.ndarray, float]:
        if not at_end:
            return self.p0, self.heading0
        return self.p1, self.heading0 + self.sweep

    def reversed(self) -> Arc:
        end = self.end_pose
        return Arc(SE2(end.x, end.y, end.yaw + math.pi), self.p0)

    def to_dict(self) -> dict[str, Any]:
        return {"curve": "arc"}


class CubicBezier(Curve):
    """A cubic Bezier through control points p0..p3 (m), re-parametrised by arc length."""

    kind = "bezier"
    _TABLE = 1024  # parameter samples of the arc-length table

    def __init__(self, p0: ArrayLike, p1: ArrayLike, p2: ArrayLike, p3: ArrayLike) -> None:
        self.control = np.array([p0, p1, p2, p3], dtype=float).reshape(4, 2)
        if np.allclose(self.control[0], self.control[1]) or np.allclose(self.control[2], self.control[3]):
            raise RoadmapError("bezier: a control point coincides with its end point (undefined tangent)")
        t = np.linspace(0.0, 1.0, self._TABLE + 1)
        d1 = self._derivative(t, 1)
        speed = np.hypot(d1[:, 0], d1[:, 1])
        # Trapezoidal integration of |dB/dt| gives the arc-length table s(t).
        self._t = t
        self._s = np.concatenate([[0.0], np.cumsum(0.5 * (speed[1:] + speed[:-1]) * np.diff(t))])
        self._length = float(self._s[-1])
        if self._length < 1e-9:
            raise RoadmapError("bezier has zero length")

    @classmethod
    def from_poses(cls, start: SE2, end: SE2, handle0_m: float, handle1_m: float) -> CubicBezier:
        """A Bezier leaving `start` along its heading and arriving at `end` along its heading."""
        u0 = np.array([math.cos(start.yaw), math.sin(start.yaw)])
        u1 = np.array([math.cos(end.yaw), math.sin(end.yaw)])
        return cls(start.xy, start.xy + handle0_m * u0, end.xy - handle1_m * u1, end.xy)

    def _point(self, t: np.ndarray) -> np.ndarray:
        p = self.control
        mt = 1.0 - t
        return (
            (mt**3)[:, None] * p[0]
            + (3 * mt**2 * t)[:, None] * p[1]
            + (3 * mt * t**2)[:, None] * p[2]
            + (t**3)[:, None] * p[3]
        )

    def _derivative(self, t: np.ndarray, order: int) -> np.ndarray:
        p = self.control
        if order == 1:
            mt = 1.0 - t
            return (
                (3 * mt**2)[:, None] * (p[1] - p[0])
                + (6 * mt * t)[:, None] * (p[2] - p[1])
                + (3 * t**2)[:, None] * (p[3] - p[2])
            )
        return (6 * (1.0 - t))[:, None] * (p[2] - 2 * p[1] + p[0]) + (6 * t)[:, None] * (p[3] - 2 * p[2] + p[1])

    @property
    def length(self) -> float:
        return self._length

    def sample(self, s: ArrayLike) -> CurveSamples:
        s_arr = np.clip(np.atleast_1d(np.asarray(s, dtype=float)), 0.0, self._length)
        t = np.interp(s_arr, self._s, self._t)
        p = self._point(t)
        d1 = self._derivative(t, 1)
        d2 = self._derivative(t, 2)
        speed = np.hypot(d1[:, 0], d1[:, 1])
        curvature = (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) / np.maximum(speed, 1e-12) ** 3
        return CurveSamples(s_arr, p[:, 0], p[:, 1], np.arctan2(d1[:, 1], d1[:, 0]), curvature)

    def reversed(self) -> CubicBezier:
        return CubicBezier(*self.control[::-1])

    def to_dict(self) -> dict[str, Any]:
        return {"curve": "bezier", "control": self.control[1:3].round(6).tolist()}
