"""VDA 5050 3.0 zones (section 6.4): the zone sets a 3.0 AGV holds, and the checks its truck keeps to.

Zone sets come on the `zoneSet` topic (DISABLED when new, section 6.4.2), are enabled with the instant action
`enableZoneSet` (one ENABLED set per mapId) and deleted with `deleteZoneSet`. A set with a `zoneSetId` already
held is not taken (`DUPLICATE_ZONE_SET`, WARNING). A set for another mapId than the AGV's map is refused.

Zone types (`ZoneType`), all contour-based ones checked with the truck's contour (`Footprint`: the body and
the forks, forklift frame, its origin at the fork heels; the AGV grows it by `v3.CONTOUR_MARGIN_M` for a
load's overhang) at every 5 cm of the path, headed as the truck drives there (an edge driven in reverse turns
the forks behind):
- BLOCKED: an order whose path from its first node to its last released node crosses one is refused
  (`NO_ROUTE_TO_TARGET`, naming the zone and the edge), and a truck that would enter one (an order taken before
  the set was enabled) holds before it (`BLOCKED_ZONE_AHEAD`, CRITICAL) until the zone set or the order
  changes; standing inside one is a `BLOCKED_ZONE_VIOLATION` (CRITICAL).
- SPEED_LIMIT: every order edge whose path touches one gets that `maximumSpeed` (the lowest of several),
  so the truck slows on the edge before it enters the zone (section 6.4.1.1) and keeps the limit inside:
  on orders received after the set was enabled, and on the roadmap edges of every leg that starts afterwards
  (`legs.speed_limits`); a leg already running keeps its speeds.
- LINE_GUIDED: honoured as it is: the truck only ever drives the roadmap's edges.
- PRIORITY, PENALTY: honoured as they are: the truck plans no route of its own (the order's edges).
- RELEASE: entered only with the master's grant (`release.ReleaseGate`: zone requests, responses); a
  `releaseLossBehavior` EVACUATE is refused (the truck has no evacuation behaviour).
- COORDINATED_REPLANNING, ACTION, DIRECTED, BIDIRECTED: not supported; a zone set with one is refused whole
  (`UNSUPPORTED_ZONE_TYPE`, WARNING, naming the zone and its type), never half honoured.

Public API: `ZoneType`, `SUPPORTED`, `Zone`, `ZoneSet`, `ZoneStore`, `Footprint`, `PathPose`,
`polygon_hits`, `order_path`.
"""

from __future__ import annotations

import math
import threading
from collections.abc import Iterable, Sequence
from dataclasses import dataclass
from enum import Enum
from typing import Any

import numpy as np

from palletpilot.executor.apps.vda5050.models import AgvError, ErrorLevel
from palletpilot.roadmap import Roadmap

PATH_STEP_M = 0.05
"""m: the path's poses checked against the zones."""


class ZoneType(str, Enum):
    """`zoneType` of a zone (section 7.6)."""

    BLOCKED = "BLOCKED"
    LINE_GUIDED = "LINE_GUIDED"
    RELEASE = "RELEASE"
    COORDINATED_REPLANNING = "COORDINATED_REPLANNING"
    SPEED_LIMIT = "SPEED_LIMIT"
    ACTION = "ACTION"
    PRIORITY = "PRIORITY"
    PENALTY = "PENALTY"
    DIRECTED = "DIRECTED"
    BIDIRECTED = "BIDIRECTED"


SUPPORTED = (
    ZoneType.BLOCKED,
    ZoneType.LINE_GUIDED,
    ZoneType.RELEASE,
    ZoneType.SPEED_LIMIT,
    ZoneType.PRIORITY,
    ZoneType.PENALTY,
)
"""The zone types this AGV honours (the factsheet's `supportedZones`)."""


@dataclass(frozen=True)
class Zone:
    """One zone: its polygon (map frame, m; at least three vertices), for SPEED_LIMIT its speed (m/s), for
    RELEASE its `releaseLossBehavior` (STOP or CONTINUE; None: STOP)."""

    zone_id: str
    zone_type: ZoneType
    vertices: np.ndarray
    maximum_speed: float | None = None
    release_loss: str | None = None


@dataclass
class ZoneSet:
    """A zone set held by the AGV."""

    zone_set_id: str
    map_id: str
    zones: tuple[Zone, ...]
    enabled: bool = False


@dataclass(frozen=True)
class Footprint:
    """The truck's contour in its own frame (m): x from `rear_x` to `front_x` (the fork tips), y within
    +-`width`/2."""

    rear_x: float
    front_x: float
    width: float

    def corners(self, x: float, y: float, heading: float) -> np.ndarray:
        """The contour's four corners (map frame, m) with the truck at (x, y) facing `heading` (rad)."""
        c, s = math.cos(heading), math.sin(heading)
        local = [(self.rear_x, -self.width / 2), (self.front_x, -self.width / 2)]
        local += [(self.front_x, self.width / 2), (self.rear_x, self.width / 2)]
        return np.array([(x + c * u - s * v, y + s * u + c * v) for u, v in local])


@dataclass(frozen=True)
class PathPose:
    """A pose on an order's path (map frame, m, rad) and the order edge it lies on (its index)."""

    x: float
    y: float
    heading: float
    edge: int


def _inside(point: np.ndarray, polygon: np.ndarray) -> bool:
    """Even-odd rule: is `point` inside the closed `polygon`?"""
    x, y = float(point[0]), float(point[1])
    inside = False
    n = len(polygon)
    for i in range(n):
        (x1, y1), (x2, y2) = polygon[i], polygon[(i + 1) % n]
        if (y1 > y) != (y2 > y) and x < x1 + (y - y1) * (x2 - x1) / (y2 - y1):
            inside = not inside
    return inside


def _cross(o: np.ndarray, a: np.ndarray, b: np.ndarray) -> float:
    return float((a[0] - o[0]) * (b[1] - o[1]) - (a[1] - o[1]) * (b[0] - o[0]))


def _segments_cross(p1: np.ndarray, p2: np.ndarray, q1: np.ndarray, q2: np.ndarray) -> bool:
    d1, d2 = _cross(q1, q2, p1), _cross(q1, q2, p2)
    d3, d4 = _cross(p1, p2, q1), _cross(p1, p2, q2)
    return ((d1 > 0) != (d2 > 0)) and ((d3 > 0) != (d4 > 0))


def polygon_hits(a: np.ndarray, b: np.ndarray) -> bool:
    """True when two simple polygons (vertex arrays, map frame) overlap: an edge crossing or one inside."""
    if _inside(a[0], b) or _inside(b[0], a):
        return True
    return any(
        _segments_cross(a[i], a[(i + 1) % len(a)], b[j], b[(j + 1) % len(b)])
        for i in range(len(a))
        for j in range(len(b))
    )


def _bbox_apart(a: np.ndarray, b: np.ndarray) -> bool:
    return bool(
        a[:, 0].max() < b[:, 0].min()
        or b[:, 0].max() < a[:, 0].min()
        or a[:, 1].max() < b[:, 1].min()
        or b[:, 1].max() < a[:, 1].min()
    )


def contour_hits(footprint: Footprint, pose: PathPose | tuple[float, float, float], zone: Zone) -> bool:
    """True when the truck's contour at `pose` (x, y, heading) overlaps the zone."""
    x, y, h = (pose.x, pose.y, pose.heading) if isinstance(pose, PathPose) else pose
    corners = footprint.corners(x, y, h)
    return not _bbox_apart(corners, zone.vertices) and polygon_hits(corners, zone.vertices)


def order_path(roadmap: Roadmap, nodes: Sequence[dict[str, Any]], released_only: bool = True) -> list[PathPose]:
    """The poses every `PATH_STEP_M` along an order's edges (2.1 form: nodes in order, node i to i+1 by edge
    i): a roadmap edge between two roadmap nodes along its curve (reversed edges headed backwards), else a
    straight line between the nodes' positions; up to the last released node with `released_only`."""
    out: list[PathPose] = []
    for i in range(len(nodes) - 1):
        a, b = nodes[i], nodes[i + 1]
        if released_only and not b.get("released", False):
            break
        ia, ib = str(a.get("nodeId")), str(b.get("nodeId"))
        if ia in roadmap and ib in roadmap and roadmap.graph.has_edge(ia, ib):
            edge = roadmap.edge(ia, ib)
            n = max(1, math.ceil(edge.length / PATH_STEP_M))
            smp = edge.curve.sample(np.linspace(0.0, edge.length, n + 1))
            flip = 0.0 if edge.direction.sign > 0 else math.pi
            out += [
                PathPose(float(x), float(y), float(h) + flip, i)
                for x, y, h in zip(smp.x, smp.y, smp.heading, strict=False)
            ]
            continue
        pa, pb = _position(roadmap, a), _position(roadmap, b)
        if pa is None or pb is None:
            continue
        length = math.hypot(pb[0] - pa[0], pb[1] - pa[1])
        heading = math.atan2(pb[1] - pa[1], pb[0] - pa[0])
        for t in np.linspace(0.0, 1.0, max(1, math.ceil(length / PATH_STEP_M)) + 1):
            out.append(PathPose(pa[0] + t * (pb[0] - pa[0]), pa[1] + t * (pb[1] - pa[1]), heading, i))
    return out


def _position(roadmap: Roadmap, node: dict[str, Any]) -> tuple[float, float] | None:
    pos = node.get("nodePosition")
    if isinstance(pos, dict):
        return float(pos["x"]), float(pos["y"])
    node_id = str(node.get("nodeId"))
    if node_id in roadmap:
        p = roadmap.node(node_id).pose
        return p.x, p.y
    return None


def _error(error_type: str, level: ErrorLevel, what: str, refs: Iterable[tuple[str, str]]) -> AgvError:
    return AgvError(error_type, level, what, tuple(refs))


class ZoneStore:
    """The zone sets an AGV holds (thread safe: the network thread adds and enables, the executor checks)."""

    def __init__(self, map_id: str) -> None:
        self.map_id = map_id
        self.sets: dict[str, ZoneSet] = {}
        self.lock = threading.Lock()
        self.generation = 0
        """Counts every change of what is enabled (a truck holding before a zone waits for a change)."""

    def add(self, doc: dict[str, Any]) -> AgvError | None:
        """A `zoneSet` message's set (schema-valid), DISABLED; the error that refuses it, or None."""
        body = doc["zoneSet"]
        set_id, map_id = str(body["zoneSetId"]), str(body["mapId"])
        refs = [("zoneSetId", set_id)]
        with self.lock:
            if set_id in self.sets:
                why = f"zone set '{set_id}' is already held; a changed set needs a new zoneSetId"
                return _error("DUPLICATE_ZONE_SET", ErrorLevel.WARNING, why, refs)
        if map_id != self.map_id:
            why = f"zone set '{set_id}' is for map '{map_id}'; this truck drives map '{self.map_id}'"
            return _error("UNKNOWN_MAP_ID", ErrorLevel.WARNING, why, [*refs, ("mapId", map_id)])
        zones = []
        for z in body["zones"]:
            kind = ZoneType(z["zoneType"])
            if kind not in SUPPORTED:
                why = (
                    f"zone set '{set_id}' refused: zone '{z['zoneId']}' is of type {kind.value}, which this truck "
                    f"does not support (it honours {', '.join(k.value for k in SUPPORTED)})"
                )
                refs += [("zoneId", str(z["zoneId"])), ("zoneType", kind.value)]
                return _error("UNSUPPORTED_ZONE_TYPE", ErrorLevel.WARNING, why, refs)
            vertices = np.array([(float(v["x"]), float(v["y"])) for v in z["vertices"]])
            speed = z.get("maximumSpeed") if kind is ZoneType.SPEED_LIMIT else None
            if speed is not None and float(speed) <= 0.0:
                why = f"zone '{z['zoneId']}': maximumSpeed {speed} m/s must be above 0"
                return _error("VALIDATION_FAILURE", ErrorLevel.WARNING, why, [*refs, ("zoneId", str(z["zoneId"]))])
            loss = z.get("releaseLossBehavior") if kind is ZoneType.RELEASE else None
            if loss not in (None, "STOP", "CONTINUE"):
                why = f"zone '{z['zoneId']}': releaseLossBehavior {loss} is not supported (STOP or CONTINUE)"
                refs += [("zoneId", str(z["zoneId"]))]
                return _error("UNSUPPORTED_ZONE_TYPE", ErrorLevel.WARNING, why, refs)
            zones.append(Zone(str(z["zoneId"]), kind, vertices, None if speed is None else float(speed), loss))
        with self.lock:
            self.sets[set_id] = ZoneSet(set_id, map_id, tuple(zones))
        return None

    def enable(self, set_id: str) -> str | None:
        """`enableZoneSet`: this set ENABLED, the others of its map DISABLED; why not, or None."""
        with self.lock:
            chosen = self.sets.get(set_id)
            if chosen is None:
                return f"no zone set '{set_id}' is held"
            for s in self.sets.values():
                if s.map_id == chosen.map_id:
                    s.enabled = s is chosen
            self.generation += 1
        return None

    def delete(self, set_id: str) -> str | None:
        """`deleteZoneSet`; why not, or None."""
        with self.lock:
            if self.sets.pop(set_id, None) is None:
                return f"no zone set '{set_id}' is held"
            self.generation += 1
        return None

    def active(self) -> list[Zone]:
        """The zones of the enabled set of this AGV's map."""
        with self.lock:
            return [z for s in self.sets.values() if s.enabled and s.map_id == self.map_id for z in s.zones]

    def active_set_id(self) -> str:
        """The enabled set's id for this map ("" without one)."""
        with self.lock:
            return next((s.zone_set_id for s in self.sets.values() if s.enabled and s.map_id == self.map_id), "")

    def to_json(self) -> list[dict[str, Any]]:
        """The state's `zoneSets`."""
        with self.lock:
            return [
                {"zoneSetId": s.zone_set_id, "mapId": s.map_id, "zoneSetStatus": "ENABLED" if s.enabled else "DISABLED"}
                for s in self.sets.values()
            ]

    def blocked_crossing(self, footprint: Footprint, path: Sequence[PathPose]) -> tuple[Zone, PathPose] | None:
        """The first BLOCKED zone the truck's contour meets along `path`, with the pose where, or None."""
        blocked = [z for z in self.active() if z.zone_type is ZoneType.BLOCKED]
        for pose in path:
            for zone in blocked:
                if contour_hits(footprint, pose, zone):
                    return zone, pose
        return None

    def edge_speed_limits(self, footprint: Footprint, path: Sequence[PathPose]) -> dict[int, float]:
        """Per order edge index, the lowest `maximumSpeed` (m/s) of the SPEED_LIMIT zones its path touches."""
        limits: dict[int, float] = {}
        zones = [z for z in self.active() if z.zone_type is ZoneType.SPEED_LIMIT and z.maximum_speed is not None]
        for pose in path:
            for zone in zones:
                if contour_hits(footprint, pose, zone):
                    assert zone.maximum_speed is not None
                    limits[pose.edge] = min(limits.get(pose.edge, math.inf), zone.maximum_speed)
        return limits
