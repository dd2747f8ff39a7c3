"""Roadmap curves in the world frame (x, y in m): line, circular arc, cubic Bezier.

Every curve is parametrised by arc length s in [0, length] from its start point to its end point.
`heading` is the tangent direction of that parametrisation (rad), `curvature` its signed curvature
d(heading)/ds (1/m, positive turning left). The vehicle's yaw on a reverse edge is heading + pi; its
curvature in the direction of travel is the same number.
"""

from __future__ import annotations

import math
from abc import ABC, abstractmethod
from collections.abc import Sequence
from dataclasses import dataclass
from functools import cached_property
from typing import Any, cast

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

    @property
    def start_heading(self) -> float:
        """Tangent heading (rad, wrapped to [-pi, pi)) at the start: `start_pose.yaw` without building a pose."""
        return _wrap(self._end(False)[1])

    @property
    def end_heading(self) -> float:
        """Tangent heading (rad, wrapped to [-pi, pi)) at the end: `end_pose.yaw` without building a pose."""
        return _wrap(self._end(True)[1])

    @abstractmethod
    def reversed(self) -> Curve:
        """The same curve traversed from end to start."""

    def max_abs_curvature(self, step_m: float = 0.02) -> float:
        """Largest |curvature| (1/m) along the curve, sampled every `step_m`."""
        n = max(2, math.ceil(self.length / step_m) + 1)
        return float(np.max(np.abs(self.sample(np.linspace(0.0, self.length, n)).curvature)))


def _wrap(angle: float) -> float:
    """An angle (rad) wrapped to [-pi, pi) exactly as `SE2` wraps its yaw."""
    return (float(angle) + math.pi) % (2.0 * math.pi) - math.pi


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

    @classmethod
    def checked(cls, p0: np.ndarray, p1: np.ndarray, length: float, heading: float) -> Line:
        """A line between points (2-vectors, m) whose length (m, not zero) and heading (rad,
        `math.atan2` of p1 - p0) the caller has computed (a map load builds lines in arrays)."""
        line = cls.__new__(cls)
        line.p0, line.p1, line._length, line._heading = p0, p1, length, heading
        return line

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

    @property
    def start_heading(self) -> float:
        return _wrap(self._heading)

    @property
    def end_heading(self) -> float:
        return _wrap(self._heading)

    def reversed(self) -> Line:
        return Line(self.p1, self.p0)

    def max_abs_curvature(self, step_m: float = 0.02) -> float:
        """0: a line does not turn."""
        return 0.0

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

    def max_abs_curvature(self, step_m: float = 0.02) -> float:
        """|curvature| (1/m): constant along an arc."""
        return abs(self.curvature)

    def to_dict(self) -> dict[str, Any]:
        return {"curve": "arc"}


class CubicBezier(Curve):
    """A cubic Bezier through control points p0..p3 (m), re-parametrised by arc length.

    The arc-length table s(t) (`_TABLE` + 1 samples of t) is built when first needed; a map load
    builds many Beziers at once with `bezier_geometry` and `CubicBezier.checked`, without tables.
    """

    kind = "bezier"
    _TABLE = 1024  # parameter samples of the arc-length table
    _T = np.linspace(0.0, 1.0, _TABLE + 1)

    def __init__(self, p0: ArrayLike, p1: ArrayLike, p2: ArrayLike, p3: ArrayLike) -> None:
        self.control = np.array([p0, p1, p2, p3], dtype=float).reshape(4, 2)
        if np.allclose(self.control[0], self.control[1]) or np.allclose(self.control[2], self.control[3]):
            raise RoadmapError("bezier: a control point coincides with its end point (undefined tangent)")
        self._length = float(self._s[-1])
        if self._length < 1e-9:
            raise RoadmapError("bezier has zero length")

    _headings: tuple[float, float] | None = None  # tangent headings (rad) at t = 0 and 1, when known

    @classmethod
    def checked(cls, control: np.ndarray, length: float, headings: tuple[float, float]) -> CubicBezier:
        """A Bezier from control points (4 x 2, m) already checked by `bezier_geometry`, with its length (m)
        and end tangent headings (rad) from there."""
        bez = cls.__new__(cls)
        bez.control = control
        bez._length = length
        bez._headings = headings
        return bez

    @property
    def start_heading(self) -> float:
        return _wrap(self._headings[0]) if self._headings is not None else super().start_heading

    @property
    def end_heading(self) -> float:
        return _wrap(self._headings[1]) if self._headings is not None else super().end_heading

    @cached_property
    def _s(self) -> np.ndarray:
        """Arc length (m) at each parameter of `_T`: trapezoidal integration of |dB/dt|."""
        return _arc_length_tables(self.control[None])[0]

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

    def parameter_at(self, s: float) -> float:
        """The Bezier parameter t (0..1) at arc length `s` (m) from the start (the arc-length table)."""
        return float(np.interp(s, self._s, self._T))

    def sample(self, s: ArrayLike) -> CurveSamples:
        s_arr = np.clip(np.atleast_1d(np.asarray(s, dtype=float)), 0.0, self._length)
        t = np.interp(s_arr, self._s, self._T)
        return self._samples_at(s_arr, t)

    def _samples_at(self, s_arr: np.ndarray, t: np.ndarray) -> CurveSamples:
        p = self._point(t)
        d1 = self._derivative(t, 1)
        d2 = self._derivative(t, 2)
        speed = np.hypot(d1[:, 0], d1[:, 1])
        curvature = (d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) / np.maximum(speed, 1e-12) ** 3
        return CurveSamples(s_arr, p[:, 0], p[:, 1], np.arctan2(d1[:, 1], d1[:, 0]), curvature)

    def _end(self, at_end: bool) -> tuple[np.ndarray, float]:
        # The table maps s = 0 to t = 0 and s = length to t = 1 exactly: no table needed at the ends.
        s = self._length if at_end else 0.0
        smp = self._samples_at(np.array([s]), np.array([1.0 if at_end else 0.0]))
        return np.array([smp.x[0], smp.y[0]]), float(smp.heading[0])

    def reversed(self) -> CubicBezier:
        return CubicBezier(*self.control[::-1])

    def to_dict(self) -> dict[str, Any]:
        return {"curve": "bezier", "control": self.control[1:3].round(6).tolist()}


# -- many Beziers at once (map files with tens of thousands of curves) -----------------------

_CHUNK = 512  # Beziers per batch: (512, 1025) float arrays, a few MB each


def _derivative_tables(control: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """dB/dt (x and y, each m x (`_TABLE` + 1)) on the table's t grid for control points (m, 4, 2).

    The same arithmetic, in the same order, as `CubicBezier._derivative(t, 1)`.
    """
    t = CubicBezier._T
    mt = 1.0 - t
    a, b, c = 3 * mt**2, 6 * mt * t, 3 * t**2
    d01 = control[:, 1] - control[:, 0]
    d12 = control[:, 2] - control[:, 1]
    d23 = control[:, 3] - control[:, 2]
    out = []
    for k in (0, 1):  # (a * d01 + b * d12) + c * d23, in place
        d = np.multiply(a, d01[:, k, None])
        d += np.multiply(b, d12[:, k, None])
        d += np.multiply(c, d23[:, k, None])
        out.append(d)
    return out[0], out[1]


def _arc_length_tables(control: np.ndarray) -> np.ndarray:
    """Arc-length tables s(t) (m, `_TABLE` + 1) of Beziers with control points (m, 4, 2)."""
    dx, dy = _derivative_tables(control)
    speed = np.hypot(dx, dy)
    steps = 0.5 * (speed[:, 1:] + speed[:, :-1]) * np.diff(CubicBezier._T)
    return np.concatenate([np.zeros((len(control), 1)), np.cumsum(steps, axis=1)], axis=1)


def bezier_geometry(control: np.ndarray) -> tuple[np.ndarray, np.ndarray, np.ndarray]:
    """Lengths (m), end headings and cusps of Beziers with control points `control` (m, 4, 2), in chunks.

    Returns `length` (m,), `headings` (m, 2): the tangent headings (rad) at the start and the end,
    and `cusp` (m,): the curve parameter t in (0, 1) near which the tangent turns back (more than
    90 degrees between two neighbouring table samples, or vanishes), NaN when it never does.
    Lengths and headings equal those of `CubicBezier(...)` exactly.
    """
    control = np.asarray(control, dtype=float).reshape(-1, 4, 2)
    length = np.empty(len(control))
    headings = np.empty((len(control), 2))
    cusp = np.full(len(control), np.nan)
    t = CubicBezier._T
    for lo in range(0, len(control), _CHUNK):
        part = control[lo : lo + _CHUNK]
        dx, dy = _derivative_tables(part)
        speed = np.hypot(dx, dy)
        steps = np.add(speed[:, 1:], speed[:, :-1])
        steps *= 0.5
        steps *= np.diff(t)
        length[lo : lo + len(part)] = np.cumsum(steps, axis=1)[:, -1]
        headings[lo : lo + len(part), 0] = np.arctan2(dy[:, 0], dx[:, 0])
        headings[lo : lo + len(part), 1] = np.arctan2(dy[:, -1], dx[:, -1])
        # A tangent that vanishes on a sample, or turns by 90 degrees or more between two: a cusp.
        dot = np.multiply(dx[:, 1:], dx[:, :-1])
        dot += np.multiply(dy[:, 1:], dy[:, :-1])
        back = dot <= 0.0
        for i in np.flatnonzero(back.any(axis=1)):
            cusp[lo + i] = float(t[int(np.argmax(back[i]))])
    return length, headings, cusp


def max_abs_curvatures(curves: Sequence[Curve], step_m: float = 0.02, known_below: float | None = None) -> np.ndarray:
    """`curve.max_abs_curvature(step_m)` (1/m) of each curve; Beziers in batches, on the same samples.

    The batch interpolates the arc-length tables as `np.interp` does; values agree with the
    one-by-one method to the last bits. With `known_below` (1/m), a Bezier whose curvature is
    provably at most that everywhere (`bezier_curvature_bounds`) gets that bound instead of being
    sampled: a check against `known_below` comes out the same, several times faster.
    """
    out = np.zeros(len(curves))
    beziers: list[int] = []
    for i, curve in enumerate(curves):
        if isinstance(curve, CubicBezier):
            beziers.append(i)
        else:
            out[i] = curve.max_abs_curvature(step_m)
    if not beziers:
        return out
    control = np.stack([cast(CubicBezier, curves[i]).control for i in beziers])
    index = np.asarray(beziers)
    if known_below is not None:
        bound = bezier_curvature_bounds(control)
        low = bound <= known_below
        out[index[low]] = bound[low]
        control, index = control[~low], index[~low]
    for lo in range(0, len(index), _CHUNK):
        out[index[lo : lo + _CHUNK]] = _bezier_max_curvature(control[lo : lo + _CHUNK], step_m)
    return out


def bezier_curvature_bounds(control: np.ndarray, pieces: int = 8) -> np.ndarray:
    """An upper bound (1/m) on |curvature| over the whole of each Bezier (m, 4, 2); inf where unknown.

    On each of `pieces` equal parameter intervals the tangent B'(t) is a quadratic Bezier and B''(t)
    a segment, each inside the hull of its control points; so |curvature| = |B' x B''| / |B'|^3 <=
    max |B''| / min |B'|^2 <= (largest B'' end) / (distance from 0 to the tangent's hull)^2.
    The bound is made a millionth larger against rounding.
    """
    control = np.asarray(control, dtype=float).reshape(-1, 4, 2)
    a = control[:, 1] - control[:, 0]
    b = control[:, 2] - control[:, 1]
    c = control[:, 3] - control[:, 2]
    quad, lin, const = 3 * (a - 2 * b + c), 6 * (b - a), 3 * a  # B'(t) = quad t^2 + lin t + const
    t = np.linspace(0.0, 1.0, pieces + 1)[None, :, None]
    d1 = quad[:, None] * t**2 + lin[:, None] * t + const[:, None]  # (m, pieces + 1, 2)
    d2 = 2 * quad[:, None] * t + lin[:, None]
    p0, p2 = d1[:, :-1], d1[:, 1:]
    p1 = p0 + (0.5 / pieces) * d2[:, :-1]  # middle control point of B' on the interval
    top = np.maximum(np.hypot(d2[:, :-1, 0], d2[:, :-1, 1]), np.hypot(d2[:, 1:, 0], d2[:, 1:, 1]))
    gap = _distance_to_triangle(p0, p1, p2)
    with np.errstate(divide="ignore", invalid="ignore"):
        ratio = np.where(gap > 0.0, top / gap**2, np.inf)
    return np.max(ratio, axis=1) * (1.0 + 1e-6)


def _distance_to_triangle(p0: np.ndarray, p1: np.ndarray, p2: np.ndarray) -> np.ndarray:
    """Distance from the origin to the triangles (p0, p1, p2) (arrays of 2-vectors); 0 inside."""

    def cross(u: np.ndarray, v: np.ndarray) -> np.ndarray:
        return u[..., 0] * v[..., 1] - u[..., 1] * v[..., 0]

    def to_segment(p: np.ndarray, q: np.ndarray) -> np.ndarray:
        d = q - p
        dd = np.sum(d * d, axis=-1)
        with np.errstate(divide="ignore", invalid="ignore"):
            k = np.clip(np.where(dd > 0.0, -np.sum(p * d, axis=-1) / dd, 0.0), 0.0, 1.0)
        closest = p + k[..., None] * d
        return np.hypot(closest[..., 0], closest[..., 1])

    s0, s1, s2 = cross(p1 - p0, -p0), cross(p2 - p1, -p1), cross(p0 - p2, -p2)
    inside = ((s0 >= 0) & (s1 >= 0) & (s2 >= 0)) | ((s0 <= 0) & (s1 <= 0) & (s2 <= 0))
    edge = np.minimum(np.minimum(to_segment(p0, p1), to_segment(p1, p2)), to_segment(p2, p0))
    return np.where(inside, 0.0, edge)


def _bezier_max_curvature(control: np.ndarray, step_m: float) -> np.ndarray:
    """Largest |curvature| (1/m) of Beziers (m, 4, 2), sampled every `step_m` of arc length."""
    t_grid = CubicBezier._T
    tables = _arc_length_tables(control)
    m, width = tables.shape
    length = tables[:, -1]
    # np.linspace(0, length, n) for each curve: j * (length / (n - 1)), the last sample exactly `length`.
    counts = np.maximum(2, np.ceil(length / step_m).astype(np.int64) + 1)
    row = np.repeat(np.arange(m), counts)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    j = np.arange(len(row)) - starts[row]
    s = j * (length / (counts - 1))[row]
    last = starts + counts - 1
    s[last] = length
    # np.interp(s, table, t_grid) row by row: find each sample's table interval with all rows laid end to
    # end (offset apart), then interpolate on the row's own numbers.
    offset = np.arange(m) * (float(length.max()) + 1.0)
    flat = (tables + offset[:, None]).ravel()
    k = np.searchsorted(flat, s + offset[row], side="right") - 1 - row * width
    k = np.clip(k, 0, width - 1)
    at_end = k >= width - 1
    k1 = np.minimum(k + 1, width - 1)
    s0, s1 = tables[row, k], tables[row, k1]
    with np.errstate(divide="ignore", invalid="ignore"):
        slope = (t_grid[k1] - t_grid[k]) / (s1 - s0)
        t = np.where(at_end | (s0 == s), t_grid[k], slope * (s - s0) + t_grid[k])
    p = control[row]
    mt = 1.0 - t
    d1 = (
        (3 * mt**2)[:, None] * (p[:, 1] - p[:, 0])
        + (6 * mt * t)[:, None] * (p[:, 2] - p[:, 1])
        + (3 * t**2)[:, None] * (p[:, 3] - p[:, 2])
    )
    d2 = (6 * (1.0 - t))[:, None] * (p[:, 2] - 2 * p[:, 1] + p[:, 0]) + (6 * t)[:, None] * (
        p[:, 3] - 2 * p[:, 2] + p[:, 1]
    )
    speed = np.hypot(d1[:, 0], d1[:, 1])
    kappa = np.abs((d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) / np.maximum(speed, 1e-12) ** 3)
    return np.maximum.reduceat(kappa, starts)
