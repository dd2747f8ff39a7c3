"""Manoeuvres: a short forward-and-reverse sequence to a pose that no single curve reaches (world frame).

A driver who cannot swing into a slot in one curve backs up (straight or turning), perhaps pulls forward
and backs again, then drives in. `plan_manoeuvre` does the same: it searches short moves from `start`
(arcs of a few fixed curvatures under the vehicle's limit, and straight lines, each driven forward or in
reverse: at most `ManoeuvreLimits.max_moves` of them) and ends with the forward curve `connect` makes to
`goal`. Every pose along every segment keeps the truck's `Footprint`, grown by `clearance_m`, clear of
every `Obstacle` (racks, stored pallets, the pallet to be picked), and within `reach_m` of the start or the
goal: a manoeuvre stays in the stretch of aisle the truck stands in. Behind the truck, the safety
scanners' reversing field (`Footprint.field_m`) is kept clear too, of the obstacles that cut the scan
plane (racks, pallets on the floor; not a pallet stored on a rack's beams, which the body must clear but
the field does not see): every move is driven in reverse one way or the other, out or back. Shortest
first: fewer moves, then the shorter path (a change of direction counts `REVERSAL_COST_M`).

Poses are the forklift's (x, y in m, yaw in rad: the fork tips' direction). A segment's curve runs in the
direction of travel: its tangent is the truck's yaw driving forward, the yaw + pi in reverse (as roadmap
edges, `roadmap.graph`).

Public API: `Footprint`, `Obstacle`, `ManoeuvreSegment`, `Manoeuvre`, `ManoeuvreLimits`, `plan_manoeuvre`,
`arc_then_line`, `footprint_hits`, `outline_hits`.
"""

from __future__ import annotations

import collections
import dataclasses
import heapq
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
BACK_IN_M = (0.25, 0.4)
"""How far ahead of the goal (m) a manoeuvre may stop to back straight into it (`_Search._back_in`)."""
CURVED_END_COST_M = 0.6
"""A manoeuvre that ends on a curve, with no straight run into the goal, costs as much as this much more
path (m): the path follower stops less precisely at the end of a curve, and the forks enter from there."""
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
    field_m: float = 0.0
    """How far (m) beyond `rear_x` the scanners' protective field reaches when the truck reverses."""

    def corners(self, grow: float = 0.0, field: bool = False) -> np.ndarray:
        """The four corners (4, 2) counter-clockwise, grown by `grow` (m) on every side; with `field`, the
        rear edge moved back by the reversing field."""
        x0 = self.rear_x - grow - (self.field_m if field else 0.0)
        x1, w = self.front_x + grow, self.half_width + grow
        return np.array([[x0, -w], [x1, -w], [x1, w], [x0, w]])


@dataclasses.dataclass(frozen=True)
class Obstacle:
    """A known static obstacle, a convex polygon on the floor: `corners` (k, 2) in the world frame (m),
    counter-clockwise; `name` says what it is in messages (`the rack at 'r3'`). `approach_only`: only the
    empty truck passes it (the pallet to pick, and its rack: the loaded truck leaves them behind), so it is
    kept clear of the empty outline. `in_scan_plane`: it cuts the safety scanners' plane, so the reversing
    field must keep clear of it too (False for a pallet on a rack's beams)."""

    name: str
    corners: np.ndarray
    approach_only: bool = False
    in_scan_plane: bool = True
    picked: bool = False
    """The pallet to be picked: on the forks when the truck leaves (the rest of `approach_only` stays)."""

    @classmethod
    def box(
        cls,
        name: str,
        pose: SE2,
        x0: float,
        x1: float,
        y0: float,
        y1: float,
        approach_only: bool = False,
        in_scan_plane: bool = True,
        picked: bool = False,
    ) -> Obstacle:
        """The rectangle x0..x1, y0..y1 (m) of the frame `pose` (world)."""
        local = np.array([[x0, y0], [x1, y0], [x1, y1], [x0, y1]], dtype=float)
        return cls(name, pose.apply(local), approach_only, in_scan_plane, picked)


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
    final_line_m: float = 0.3
    """An arc into the goal (`arc_then_line`) ends with a straight line of at least this (m)."""
    run_in_m: float = 0.1
    """A curve `connect` makes into the goal ends, where it can, with a straight line this long (m): the
    truck then overshoots its stop straight, not turning on (and the forks enter from there)."""
    max_connects: int = 160
    search_expansions: int = 4000
    """When the moves above find nothing: poses the finer search (`_Search.finer`) expands at most."""
    search_steps_m: tuple[float, ...] = (0.6, 0.3)
    """Its moves' lengths (m): longer ones first (fewer moves to drive), then shorter ones where they find none."""


def footprint_hits(
    poses: np.ndarray, footprint: Footprint, obstacles: Sequence[Obstacle], grow: float
) -> Obstacle | None:
    """The first obstacle that the footprint (grown by `grow`, m; with its reversing field against those in
    the scan plane) overlaps at any of `poses` (n, 3), or None.

    Separating axes between two convex polygons, for all poses at once."""
    if footprint.field_m > 0.0:
        seen = _footprint_hits(poses, footprint.corners(grow, field=True), [o for o in obstacles if o.in_scan_plane])
        if seen is not None:
            return seen
        obstacles = [o for o in obstacles if not o.in_scan_plane]
    return _footprint_hits(poses, footprint.corners(grow), obstacles)


def _footprint_hits(poses: np.ndarray, local: np.ndarray, obstacles: Sequence[Obstacle]) -> Obstacle | None:
    """The first obstacle the rectangle `local` (4, 2, forklift frame) overlaps at any of `poses` (n, 3)."""
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
        goal (`arc_then_line`, no search), else by the curve `connector` makes into a straight run-in of
        `run_in_m`, else by its curve into the goal itself (`CURVED_END_COST_M`)."""
        pose = seq[-1].end_pose if seq else self.start
        local = pose.inv() @ self.goal
        if local.x <= 0.05:  # the goal behind the truck: no forward curve (and no connect to pay for)
            self.no_curve += 1
            return self._back_in(seq)
        tail = arc_then_line(
            pose, self.goal, self.max_curvature * max(self.limits.curvature_share), self.limits.final_line_m
        )
        if tail is not None and all(self.clear(t) for t in tail):
            return Manoeuvre((*seq, *tail))
        backed = self._back_in(seq)
        if backed is not None:
            return backed
        if not seq:
            return None  # the connector's single curve is the roadmap's own re-plan, tried before
        if _rough_curvature(pose, self.goal) > ROUGH_CURVATURE_SLACK * self.max_curvature:
            self.no_curve += 1
            return None  # hopeless for `connect` (a coarse look at its Beziers): not worth its search
        self.connects += 1
        run_in = self.goal @ SE2(-self.limits.run_in_m, 0.0, 0.0)
        line = ManoeuvreSegment(Line(run_in.xy, self.goal.xy), Direction.FORWARD)
        ends: list[tuple[SE2, tuple[ManoeuvreSegment, ...]]] = [(run_in, (line,)), (self.goal, ())]
        for end, run in ends:  # into a straight run-in first, else into the goal
            try:
                last = ManoeuvreSegment(self.connector(pose, end, self.max_curvature), Direction.FORWARD)
            except RoadmapError:
                continue
            if self.clear(last) and all(self.clear(t) for t in run):
                return Manoeuvre((*seq, last, *run))
        self.no_curve += 1
        return None

    def finer(self, length: float) -> Manoeuvre | None:
        """A finer search when the few long moves of `sequences` find nothing (a hybrid A*): short moves
        (`length` m, forward or in reverse, at five curvatures up to the limit's largest share), poses
        kept once per cell (0.1 m, 7.5 deg, direction), the cheapest path plus the distance to the goal
        first; each pose tries the arc and line into the goal, every eighth the connector's curves
        (`finish`). At most `search_expansions` poses: as deterministic as the rest."""
        k = self.max_curvature * max(self.limits.curvature_share)
        steps = [(d, c) for d in (Direction.FORWARD, Direction.REVERSE) for c in (-k, -0.5 * k, 0.0, 0.5 * k, k)]
        cell, turn = 0.1, math.radians(7.5)

        def estimate(pose: SE2) -> float:  # to the goal: the distance, and the heading still to turn
            heading = abs(math.remainder(self.goal.yaw - pose.yaw, 2.0 * math.pi))
            return float(np.hypot(*(pose.xy - self.goal.xy))) + heading / self.max_curvature

        order = itertools.count()
        heap: list[tuple[float, int, tuple[ManoeuvreSegment, ...]]] = [(estimate(self.start), next(order), ())]
        closed: set[tuple[int, int, int, bool]] = set()
        for expanded in itertools.count():
            if not heap or expanded >= self.limits.search_expansions:
                return None
            _, _, seq = heapq.heappop(heap)
            pose = seq[-1].end_pose if seq else self.start
            forward = not seq or seq[-1].direction is Direction.FORWARD
            key = (round(pose.x / cell), round(pose.y / cell), round(pose.yaw / turn) % 48, forward)
            if key in closed:
                continue
            closed.add(key)
            if seq:
                found = self._finish_cheap(seq) if expanded % 8 else self.finish(seq)
                if found is not None:
                    return found
            for d, c in steps:
                step = _move(pose, d, c, length)
                if not self.clear(step):
                    continue
                last = seq[-1] if seq else None
                if last is not None and last.direction is d and math.isclose(_curvature(last), c, abs_tol=1e-6):
                    grown = (*seq[:-1], _move(last.start_pose, d, c, last.curve.length + length))  # one longer move
                else:
                    grown = (*seq, step)
                heapq.heappush(heap, (_cost(grown) + estimate(step.end_pose), next(order), grown))
        return None

    def _finish_cheap(self, seq: tuple[ManoeuvreSegment, ...]) -> Manoeuvre | None:
        """`finish` by the arc and line alone (no connector's search)."""
        pose = seq[-1].end_pose
        tail = arc_then_line(
            pose, self.goal, self.max_curvature * max(self.limits.curvature_share), self.limits.final_line_m
        )
        if tail is not None and all(self.clear(t) for t in tail):
            return Manoeuvre((*seq, *tail))
        return self._back_in(seq)

    def _back_in(self, seq: tuple[ManoeuvreSegment, ...]) -> Manoeuvre | None:
        """The sequence ended by an arc (and a line) forward to a pose `BACK_IN_M` ahead of the goal on its
        line, then straight back into it: where the truck cannot swing into the goal, its rear too near
        what stands behind it. Leaving loaded, the truck drives that line forward towards the pallet's
        rack, so the loaded outline must clear the rack there too."""
        pose = seq[-1].end_pose if seq else self.start
        k = self.max_curvature * max(self.limits.curvature_share)
        kept = [o for o in self.obstacles if o.approach_only and not o.picked]
        for ahead in BACK_IN_M:
            above = self.goal @ SE2(ahead, 0.0, 0.0)
            tail = arc_then_line(pose, above, k, 0.0)
            if tail is None:
                continue
            back = ManoeuvreSegment(Line(above.xy, self.goal.xy), Direction.REVERSE)
            if not all(self.clear(t) for t in (*tail, back)):
                continue
            if footprint_hits(back.poses(), self.footprint, kept, self.limits.clearance_m) is None:
                return Manoeuvre((*seq, *tail, back))
        return None


def _curvature(segment: ManoeuvreSegment) -> float:
    """The signed curvature (1/m, in the direction of travel) of a move made by `_move`: 0 for a line."""
    c = segment.curve
    return float(c.curvature) if isinstance(c, Arc) else 0.0


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
            cost = _cost(found.segments) + (0.0 if isinstance(found.segments[-1].curve, Line) else CURVED_END_COST_M)
            if best is None or cost < best[0]:
                best, moves = (cost, found), len(seq)
    if best is None:
        found = next((m for m in map(search.finer, limits.search_steps_m) if m is not None), None)
        best = None if found is None else (0.0, found)
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
