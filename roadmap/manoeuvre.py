"""Manoeuvres: a short forward-and-reverse sequence to a pose that no single curve reaches (world frame).

A driver who cannot swing into a slot in one curve backs up (straight or turning), perhaps pulls forward
and backs again, then drives in. `plan_manoeuvre` does the same: it searches short moves from `start`
(arcs of a few fixed curvatures under the vehicle's limit, and straight lines, each driven forward or in
reverse: at most `ManoeuvreLimits.max_moves` of them) and ends with the forward curve `connect` makes to
`goal`. Every pose along every segment keeps the truck's `Footprint`, grown by `clearance_m`, clear of
every `Obstacle` (racks, stored pallets, the pallet to be picked), and within `reach_m` of the start or the
goal: a manoeuvre stays in the stretch of aisle the truck stands in. Shortest first: fewer moves, then
the shorter path (a change of direction counts `REVERSAL_COST_M`).

Poses are the forklift's (x, y in m, yaw in rad: the fork tips' direction). A segment's curve runs in the
direction of travel: its tangent is the truck's yaw driving forward, the yaw + pi in reverse (as roadmap
edges, `roadmap.graph`).

Public API: `Footprint`, `Obstacle`, `ManoeuvreSegment`, `Manoeuvre`, `ManoeuvreLimits`, `plan_manoeuvre`,
`arc_then_line`, `footprint_hits`, `outline_hits`.
"""

from __future__ import annotations

import collections
import dataclasses
import itertools
import math
from collections.abc import Callable, Iterator, Sequence
from typing import Any

import numpy as np

from palletpilot.geometry import SE2
from palletpilot.roadmap.curves import Arc, CubicBezier, Curve, Line
from palletpilot.roadmap.errors import RoadmapError
from palletpilot.roadmap.graph import Direction
from palletpilot.roadmap.synthesis import connect

REVERSAL_COST_M = 1.0
"""A change of the direction of travel costs as much as this much more path (m): the truck stops there."""
ROUGH_CURVATURE_SLACK = 1.5
"""`connect` is not tried where a coarse look at its curves finds none below this many times the limit."""
SAMPLE_STEP_M = 0.02
"""Poses are checked against the obstacles every this many metres of path (m)."""


@dataclasses.dataclass(frozen=True)
class Footprint:
    """The truck's outline on the floor, a rectangle in the forklift frame (m): from `rear_x` (negative,
    behind the fork heels) to `front_x` (the fork tips, or the far end of a carried load), `half_width`
    either side of the centre line."""

    rear_x: float
    front_x: float
    half_width: float

    def corners(self, grow: float = 0.0) -> np.ndarray:
        """The four corners (4, 2) counter-clockwise, grown by `grow` (m) on every side."""
        x0, x1, w = self.rear_x - grow, self.front_x + grow, self.half_width + grow
        return np.array([[x0, -w], [x1, -w], [x1, w], [x0, w]])


@dataclasses.dataclass(frozen=True)
class Obstacle:
    """A known static obstacle, a convex polygon on the floor: `corners` (k, 2) in the world frame (m),
    counter-clockwise; `name` says what it is in messages (`the rack at 'r3'`). `approach_only`: only the
    empty truck passes it (the pallet to pick, and its rack: the loaded truck leaves them behind), so it is
    kept clear of the empty outline."""

    name: str
    corners: np.ndarray
    approach_only: bool = False

    @classmethod
    def box(
        cls, name: str, pose: SE2, x0: float, x1: float, y0: float, y1: float, approach_only: bool = False
    ) -> Obstacle:
        """The rectangle x0..x1, y0..y1 (m) of the frame `pose` (world)."""
        local = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)
        return cls(name, pose.apply(local), approach_only)


@dataclasses.dataclass(frozen=True)
class ManoeuvreSegment:
    """One move: the truck drives along `curve` (in its direction of travel) `direction`."""

    curve: Curve
    direction: Direction

    def poses(self, step_m: float = SAMPLE_STEP_M) -> np.ndarray:
        """The truck's poses along the move (n, 3): x, y (m), yaw (rad), about every `step_m` (m)."""
        n = max(2, math.ceil(self.curve.length / step_m) + 1)
        smp = self.curve.sample(np.linspace(0.0, self.curve.length, n))
        yaw = smp.heading + (0.0 if self.direction is Direction.FORWARD else math.pi)
        return np.column_stack([smp.x, smp.y, yaw])

    @property
    def start_pose(self) -> SE2:
        """The truck's pose where the move starts (world)."""
        p = self.curve.start_pose
        return p if self.direction is Direction.FORWARD else SE2(p.x, p.y, p.yaw + math.pi)

    @property
    def end_pose(self) -> SE2:
        """The truck's pose where the move ends (world)."""
        p = self.curve.end_pose
        return p if self.direction is Direction.FORWARD else SE2(p.x, p.y, p.yaw + math.pi)

    def to_json(self) -> dict[str, Any]:
        """Plain JSON that `from_json` turns back into the same curve (full precision)."""
        c = self.curve
        doc: dict[str, Any] = {"direction": self.direction.value, "curve": c.kind}
        if isinstance(c, Line):
            doc["points"] = [c.p0.tolist(), c.p1.tolist()]
        elif isinstance(c, Arc):
            doc["start"] = [float(c.p0[0]), float(c.p0[1]), float(c.heading0)]
            doc["points"] = [c.p1.tolist()]
        elif isinstance(c, CubicBezier):
            doc["points"] = c.control.tolist()
        else:
            raise RoadmapError(f"a manoeuvre cannot hold a {c.kind} curve")
        return doc

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> ManoeuvreSegment:
        """The inverse of `to_json`."""
        kind, pts = doc["curve"], [np.asarray(p, dtype=float) for p in doc["points"]]
        curve: Curve
        if kind == "line":
            curve = Line(pts[0], pts[1])
        elif kind == "arc":
            curve = Arc(SE2(*map(float, doc["start"])), pts[0])
        elif kind == "bezier":
            curve = CubicBezier(*pts)
        else:
            raise RoadmapError(f"a manoeuvre cannot hold a {kind} curve")
        return cls(curve, Direction(doc["direction"]))


@dataclasses.dataclass(frozen=True)
class Manoeuvre:
    """Moves from a start pose to a goal pose, in order; the last one is driven forward."""

    segments: tuple[ManoeuvreSegment, ...]

    @property
    def length(self) -> float:
        """Path length (m)."""
        return float(sum(s.curve.length for s in self.segments))

    @property
    def reversals(self) -> int:
        """How many times the direction of travel changes (the truck stops at each)."""
        return sum(a.direction is not b.direction for a, b in itertools.pairwise(self.segments))

    @property
    def directions(self) -> list[str]:
        """Each move's direction of travel (`forward`, `reverse`)."""
        return [s.direction.value for s in self.segments]

    def to_json(self) -> list[dict[str, Any]]:
        """Plain JSON, one entry per move."""
        return [s.to_json() for s in self.segments]

    @classmethod
    def from_json(cls, doc: Sequence[dict[str, Any]]) -> Manoeuvre:
        """The inverse of `to_json`."""
        return cls(tuple(ManoeuvreSegment.from_json(d) for d in doc))


@dataclasses.dataclass(frozen=True)
class ManoeuvreLimits:
    """How far the search goes (m, counts). `curvature_share`: the moves' arcs turn at these shares of the
    vehicle's curvature limit (both ways; 0 is a straight line), a little short of it so the follower keeps
    some steering in hand; `lengths_m`: each move's length."""

    clearance_m: float = 0.10
    reach_m: float = 3.0
    max_moves: int = 2
    curvature_share: tuple[float, ...] = (0.0, 0.5, 0.85)
    lengths_m: tuple[float, ...] = (0.3, 0.6, 0.9, 1.2, 1.6, 2.0)
    max_connects: int = 160


def footprint_hits(
    poses: np.ndarray, footprint: Footprint, obstacles: Sequence[Obstacle], grow: float
) -> Obstacle | None:
    """The first obstacle that the footprint (grown by `grow`, m) overlaps at any of `poses` (n, 3), or None.

    Separating axes between two convex polygons, for all poses at once."""
    local = footprint.corners(grow)
    c, s = np.cos(poses[:, 2]), np.sin(poses[:, 2])
    # truck corners (n, 4, 2) in the world
    tx = poses[:, 0, None] + c[:, None] * local[None, :, 0] - s[:, None] * local[None, :, 1]
    ty = poses[:, 1, None] + s[:, None] * local[None, :, 0] + c[:, None] * local[None, :, 1]
    truck = np.stack([tx, ty], axis=-1)
    centre = poses[:, :2]
    reach = float(np.hypot(*np.abs(local).max(axis=0)))
    for obstacle in obstacles:
        poly = obstacle.corners
        # a quick miss: the circles around the truck and around the obstacle do not meet
        radius = float(np.max(np.hypot(*(poly - poly.mean(axis=0)).T)))
        near = np.hypot(*(centre - poly.mean(axis=0)).T) <= reach + radius
        if not near.any():
            continue
        if _overlap(truck[near], poly).any():
            return obstacle
    return None


def outline_hits(
    poses: np.ndarray, loaded: Footprint, empty: Footprint, obstacles: Sequence[Obstacle], grow: float
) -> Obstacle | None:
    """The first obstacle the truck at any of `poses` (n, 3) comes within `grow` (m) of: the `loaded` outline
    against most, the `empty` one against those passed on the way in only (`Obstacle.approach_only`)."""
    found = footprint_hits(poses, loaded, [o for o in obstacles if not o.approach_only], grow)
    if found is None:
        found = footprint_hits(poses, empty, [o for o in obstacles if o.approach_only], grow)
    return found


def _axes(corners: np.ndarray) -> np.ndarray:
    """Edge normals (..., k, 2) of polygons (..., k, 2)."""
    edges = np.roll(corners, -1, axis=-2) - corners
    return np.stack([-edges[..., 1], edges[..., 0]], axis=-1)


def _overlap(truck: np.ndarray, poly: np.ndarray) -> np.ndarray:
    """Whether each truck rectangle (n, 4, 2) overlaps the convex polygon (k, 2): no separating axis."""
    separated = np.zeros(len(truck), dtype=bool)
    for axes in (_axes(truck[:, :2]), np.broadcast_to(_axes(poly), (len(truck), *poly.shape))):
        for j in range(axes.shape[1]):
            a = axes[:, j]  # (n, 2)
            pt = np.einsum("nkd,nd->nk", truck, a)
            pp = poly @ a.T  # (k, n)
            separated |= (pt.max(axis=1) < pp.min(axis=0)) | (pp.max(axis=0) < pt.min(axis=1))
    return ~separated


def _move(pose: SE2, direction: Direction, curvature: float, length: float) -> ManoeuvreSegment:
    """The move from the truck's `pose` (world) along an arc of `curvature` (1/m, in the direction of
    travel; 0: a line) for `length` (m)."""
    h0 = pose.yaw if direction is Direction.FORWARD else pose.yaw + math.pi
    p0 = pose.xy
    if curvature == 0.0:
        return ManoeuvreSegment(Line(p0, p0 + length * np.array([math.cos(h0), math.sin(h0)])), direction)
    h1 = h0 + curvature * length
    p1 = p0 + np.array([math.sin(h1) - math.sin(h0), -(math.cos(h1) - math.cos(h0))]) / curvature
    return ManoeuvreSegment(Arc(SE2(p0[0], p0[1], h0), p1), direction)


def _moves(limits: ManoeuvreLimits, max_curvature: float) -> list[tuple[Direction, float, float]]:
    """Every (direction, curvature, length) of one move, reverse first."""
    ks = sorted({sign * share * max_curvature for share in limits.curvature_share for sign in (1.0, -1.0)})
    return [(d, k, length) for d in (Direction.REVERSE, Direction.FORWARD) for k in ks for length in limits.lengths_m]


@dataclasses.dataclass
class _Search:
    """One search's inputs and its tally of what was tried (for the message when nothing fits)."""

    start: SE2
    goal: SE2
    max_curvature: float
    footprint: Footprint
    empty: Footprint
    obstacles: Sequence[Obstacle]
    limits: ManoeuvreLimits
    connector: Callable[[SE2, SE2, float], Curve]
    connects: int = 0
    blocked: int = 0
    out_of_reach: int = 0
    no_curve: int = 0
    hits: collections.Counter[str] = dataclasses.field(default_factory=collections.Counter)

    def clear(self, segment: ManoeuvreSegment) -> bool:
        """True when the move stays within reach and keeps the clearance from every obstacle."""
        poses = segment.poses()
        far = np.minimum(
            np.hypot(poses[:, 0] - self.start.x, poses[:, 1] - self.start.y),
            np.hypot(poses[:, 0] - self.goal.x, poses[:, 1] - self.goal.y),
        )
        if float(far.max()) > self.limits.reach_m:
            self.out_of_reach += 1
            return False
        obstacle = self.hit(poses)
        if obstacle is not None:
            self.blocked += 1
            self.hits[obstacle.name] += 1
            return False
        return True

    def hit(self, poses: np.ndarray) -> Obstacle | None:
        """The first obstacle the truck comes within the clearance of at `poses` (n, 3) (`outline_hits`)."""
        return outline_hits(poses, self.footprint, self.empty, self.obstacles, self.limits.clearance_m)

    def sequences(self) -> Iterator[tuple[ManoeuvreSegment, ...]]:
        """Collision-free move sequences from the start, fewer moves first, then the shorter."""
        moves = _moves(self.limits, self.max_curvature)
        level: list[tuple[ManoeuvreSegment, ...]] = [()]
        yield ()  # no move first: an arc and a line straight from the start
        for _ in range(self.limits.max_moves):
            grown: list[tuple[float, tuple[ManoeuvreSegment, ...]]] = []
            for seq in level:
                pose = seq[-1].end_pose if seq else self.start
                for d, k, length in moves:
                    if seq and seq[-1].direction is d:
                        continue  # two moves one way: the search's other lengths and curvatures cover them
                    segment = _move(pose, d, k, length)
                    if self.clear(segment):
                        grown.append((_cost((*seq, segment)), (*seq, segment)))
            grown.sort(key=lambda item: item[0])
            level = [seq for _, seq in grown]
            yield from level

    def finish(self, seq: tuple[ManoeuvreSegment, ...]) -> Manoeuvre | None:
        """The sequence ended forward at the goal, when that is clear: by an arc and a straight line into the
        goal (`arc_then_line`, no search), else by the curve `connector` makes."""
        pose = seq[-1].end_pose if seq else self.start
        local = pose.inv() @ self.goal
        if local.x <= 0.05:  # the goal behind the truck: no forward curve (and no connect to pay for)
            self.no_curve += 1
            return None
        tail = arc_then_line(pose, self.goal, self.max_curvature * max(self.limits.curvature_share))
        if tail is not None and all(self.clear(t) for t in tail):
            return Manoeuvre((*seq, *tail))
        if not seq:
            return None  # the connector's single curve is the roadmap's own re-plan, tried before
        if _rough_curvature(pose, self.goal) > ROUGH_CURVATURE_SLACK * self.max_curvature:
            self.no_curve += 1
            return None  # hopeless for `connect` (a coarse look at its Beziers): not worth its search
        self.connects += 1
        try:
            last = ManoeuvreSegment(self.connector(pose, self.goal, self.max_curvature), Direction.FORWARD)
        except RoadmapError:
            self.no_curve += 1
            return None
        return Manoeuvre((*seq, last)) if self.clear(last) else None


def _rough_curvature(pose: SE2, goal: SE2) -> float:
    """About the least peak |curvature| (1/m) of the Beziers from `pose` to `goal` that `connect` searches:
    the best of a coarse grid of handle lengths, each curve looked at in 24 parameter steps."""
    chord = float(np.hypot(*(goal.xy - pose.xy)))
    h = np.array([0.25, 0.45, 0.65, 0.85, 1.05]) * chord
    a, b = (g.ravel() for g in np.meshgrid(h, h))
    u0 = np.array([math.cos(pose.yaw), math.sin(pose.yaw)])
    u1 = np.array([math.cos(goal.yaw), math.sin(goal.yaw)])
    p0, p3 = pose.xy, goal.xy
    p1, p2 = p0 + a[:, None] * u0, p3 - b[:, None] * u1  # (m, 2)
    t = np.linspace(0.0, 1.0, 25)[None, :, None]
    d1 = 3 * (1 - t) ** 2 * (p1 - p0)[:, None] + 6 * (1 - t) * t * (p2 - p1)[:, None] + 3 * t**2 * (p3 - p2)[:, None]
    d2 = 6 * (1 - t) * (p2 - 2 * p1 + p0)[:, None] + 6 * t * (p3 - 2 * p2 + p1)[:, None]
    cross = d1[..., 0] * d2[..., 1] - d1[..., 1] * d2[..., 0]
    speed = np.maximum(np.hypot(d1[..., 0], d1[..., 1]), 1e-9)
    return float(np.min(np.max(np.abs(cross) / speed**3, axis=1)))


def arc_then_line(pose: SE2, goal: SE2, max_curvature: float, min_line_m: float = 0.3) -> list[ManoeuvreSegment] | None:
    """Forward from `pose` to `goal` (world) along an arc that turns the truck to the goal's heading and a
    straight line of at least `min_line_m` (m) into the goal, with |curvature| <= `max_curvature` (1/m);
    None when there is none. (A line alone when the poses are already in line.)"""
    theta, phi = pose.yaw, goal.yaw
    turn = math.remainder(phi - theta, 2.0 * math.pi)
    u = np.array([math.cos(phi), math.sin(phi)])
    n = np.array([-u[1], u[0]])
    gap = pose.xy - goal.xy
    if abs(turn) < 1e-6:
        ahead = float(-gap @ u)
        if abs(float(gap @ n)) > 1e-3 or ahead < min_line_m:
            return None
        return [ManoeuvreSegment(Line(pose.xy, goal.xy), Direction.FORWARD)]
    w = np.array([math.sin(phi) - math.sin(theta), -(math.cos(phi) - math.cos(theta))])
    if abs(float(n @ w)) < 1e-9:
        return None
    radius = -float(n @ gap) / float(n @ w)  # signed: 1 / curvature
    if radius * turn <= 0.0 or abs(radius) * max_curvature < 1.0:
        return None  # it would turn the other way, or tighter than the truck can
    end = pose.xy + radius * w
    line = float((goal.xy - end) @ u)
    if line < min_line_m:
        return None
    return [
        ManoeuvreSegment(Arc(pose, end), Direction.FORWARD),
        ManoeuvreSegment(Line(end, goal.xy), Direction.FORWARD),
    ]


def _cost(seq: Sequence[ManoeuvreSegment]) -> float:
    """Path length (m) plus `REVERSAL_COST_M` per change of direction, counting the last forward move."""
    changes = sum(a.direction is not b.direction for a, b in itertools.pairwise(seq))
    ends_reverse = bool(seq) and seq[-1].direction is Direction.REVERSE
    return sum(s.curve.length for s in seq) + REVERSAL_COST_M * (changes + ends_reverse)


def plan_manoeuvre(
    start: SE2,
    goal: SE2,
    max_curvature: float,
    footprint: Footprint,
    obstacles: Sequence[Obstacle],
    limits: ManoeuvreLimits | None = None,
    connector: Callable[[SE2, SE2, float], Curve] = connect,
    empty: Footprint | None = None,
) -> Manoeuvre:
    """The shortest manoeuvre found from the truck's `start` to `goal` (poses in the world frame, m, rad)
    with |curvature| <= `max_curvature` (1/m), keeping `footprint` (the loaded truck; `empty`, default the
    same, for `approach_only` obstacles) clear of `obstacles` (see the module docstring). Raises
    `RoadmapError` saying what was tried and why nothing fits."""
    limits = limits or ManoeuvreLimits()
    if max_curvature <= 0:
        raise RoadmapError(f"curvature limit must be positive, got {max_curvature}")
    search = _Search(start, goal, max_curvature, footprint, empty or footprint, obstacles, limits, connector)
    goal_hit = search.hit(np.array([[goal.x, goal.y, goal.yaw]]))
    if goal_hit is not None:
        raise RoadmapError(
            f"no manoeuvre: the truck at the new pre-pallet pose would come within {limits.clearance_m:.2f} m "
            f"of {goal_hit.name}"
        )
    best: tuple[float, Manoeuvre] | None = None
    moves = 0
    for seq in search.sequences():
        if best is not None and (len(seq) > moves or _cost(seq) >= best[0]):
            break  # fewer moves found, or none left that could be shorter (a level is sorted by cost)
        if search.connects >= limits.max_connects:
            break
        found = search.finish(seq)
        if found is not None:
            cost = _cost(found.segments)
            if best is None or cost < best[0]:
                best, moves = (cost, found), len(seq)
    if best is not None:
        return best[1]
    worst = ", ".join(f"{name} ({n})" for name, n in search.hits.most_common(2))
    hit = f" (most often: {worst})" if worst else ""
    raise RoadmapError(
        f"no manoeuvre of up to {limits.max_moves} moves and a forward curve within {limits.reach_m:.1f} m: "
        f"{search.blocked} moves came within {limits.clearance_m:.2f} m of an obstacle{hit}, "
        f"{search.out_of_reach} went out of reach, {search.connects} forward curves were tried "
        f"({search.no_curve} infeasible or behind)"
    )
