"""Reference paths: a planned route sampled into one continuous path for the controller (world frame).

Per sample: arc length `s` (m, cumulative along the whole path in the direction of travel), `x`, `y`
(m), `heading` (the forklift's yaw, rad: the curve tangent forward, tangent + pi in reverse),
`curvature` (d heading / ds along the travel, 1/m), `direction` (+1 forward, -1 reverse) and
`speed_limit` (m/s). The path is split into segments where the direction of travel changes; the
forklift stops at the end of each segment before following the next.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from palletpilot.geometry import SE2, wrap_angle
from palletpilot.roadmap.errors import RoadmapError
from palletpilot.roadmap.graph import Edge
from palletpilot.roadmap.planner import Route


@dataclass(frozen=True)
class PathSegment:
    """Samples of a stretch of path driven in one direction (see module docstring for units)."""

    s: np.ndarray
    x: np.ndarray
    y: np.ndarray
    heading: np.ndarray
    curvature: np.ndarray
    speed_limit: np.ndarray
    direction: int
    edges: tuple[str, ...]

    @property
    def length(self) -> float:
        """Length (m) of the segment."""
        return float(self.s[-1] - self.s[0])

    @property
    def start_pose(self) -> SE2:
        """Forklift pose at the start of the segment."""
        return SE2(self.x[0], self.y[0], self.heading[0])

    @property
    def end_pose(self) -> SE2:
        """Forklift pose at the end of the segment."""
        return SE2(self.x[-1], self.y[-1], self.heading[-1])

    def __len__(self) -> int:
        return len(self.s)


@dataclass(frozen=True)
class ReferencePath:
    """A route sampled for the controller: its segments, in order."""

    segments: tuple[PathSegment, ...]

    @property
    def length(self) -> float:
        """Total length (m)."""
        return float(sum(seg.length for seg in self.segments))

    @property
    def end_pose(self) -> SE2:
        """Forklift pose at the end of the path (e.g. at the pallet node)."""
        return self.segments[-1].end_pose

    def stacked(self, name: str) -> np.ndarray:
        """One per-sample field (`s`, `x`, `y`, `heading`, ...) over the whole path, joints repeated."""
        return np.concatenate([getattr(seg, name) for seg in self.segments])


def _sample_edge(edge: Edge, step_m: float) -> tuple[np.ndarray, ...]:
    n = max(1, math.ceil(edge.length / step_m))
    smp = edge.curve.sample(np.linspace(0.0, edge.length, n + 1))
    heading = smp.heading if edge.direction.sign > 0 else smp.heading + math.pi
    return smp.s, smp.x, smp.y, np.asarray(wrap_angle(heading)), smp.curvature


def reference_path(route: Route, step_m: float = 0.05, speed_cap: float | None = None) -> ReferencePath:
    """Sample a route at about `step_m` (m) per sample into segments of one travel direction each; with
    `speed_cap` (m/s) no sample's speed limit is above it (e.g. creeping with raised forks)."""
    if not route.edges:
        raise RoadmapError(f"route {' -> '.join(route.nodes)} has no edges to follow")
    if step_m <= 0:
        raise RoadmapError(f"path sample step must be positive, got {step_m}")
    segments: list[PathSegment] = []
    parts: list[tuple[np.ndarray, ...]] = []
    names: list[str] = []
    s0 = 0.0

    def close() -> None:
        nonlocal s0, parts, names
        s_all, x_all, y_all, heading_all, curvature_all, speed_all = (
            np.concatenate(a) for a in zip(*parts, strict=True)
        )
        segments.append(
            PathSegment(
                s_all,
                x_all,
                y_all,
                heading_all,
                curvature_all,
                speed_all,
                direction=current.direction.sign,
                edges=tuple(names),
            )
        )
        s0 = float(s_all[-1])
        parts, names = [], []

    current = route.edges[0]
    for edge in route.edges:
        if edge.direction is not current.direction:
            close()
        current = edge
        s, x, y, heading, curvature = _sample_edge(edge, step_m)
        offset = s0 if not parts else float(parts[-1][0][-1])
        limit = edge.speed_limit if speed_cap is None else min(edge.speed_limit, speed_cap)
        speed = np.full_like(s, limit)
        if parts:  # the joint sample already ends the previous edge: keep the slower limit there
            parts[-1][5][-1] = min(parts[-1][5][-1], limit)
            s, x, y, heading, curvature, speed = s[1:], x[1:], y[1:], heading[1:], curvature[1:], speed[1:]
        parts.append((s + offset, x, y, heading, curvature, speed))
        names.append(edge.name)
    close()
    return ReferencePath(tuple(segments))
