"""Scene entities and images for the run recording (`executor.recording`): Foxglove well-known messages.

Pure builders, no state: each turns the project's types into `foxglove.messages` objects that the 3D
and image panels draw without plugins. Frames (REP 105 names, ARCHITECTURE.md conventions):

- `map`: the world frame, z up (metres).
- `base_link`: the forklift frame (origin on the floor midway between the forks at the fork heels, x
  towards the fork tips, y left, z up).
- `camera`: the camera's optical frame (x right, y down, z out of the lens; ROS
  `camera_color_optical_frame`), placed by the calibration (`T_forklift_camera` at the lift height).

Every message on a scene topic carries the topic's whole state (its entities replace all earlier
ones), so a viewer that seeks shows the right scene from the last message alone.

Public API: the `*_entities` / `*_update` builders, `pose_se2`, `pose_se3`, `quat_yaw`, `stamp`,
`edge_json`, `node_json`, `curve_json`, `curves_from_json`, `cube_corners` (camera images and clouds:
`executor.recording_camera`).
"""

from __future__ import annotations

import itertools
import json
import math
from collections.abc import Iterable, Sequence
from typing import Any

import numpy as np
from foxglove.messages import (
    ArrowPrimitive,
    Color,
    CubePrimitive,
    FrameTransform,
    FrameTransforms,
    KeyValuePair,
    LinePrimitive,
    LinePrimitiveLineType,
    Point3,
    Pose,
    Quaternion,
    SceneEntity,
    SceneEntityDeletion,
    SceneEntityDeletionType,
    SceneUpdate,
    SpherePrimitive,
    TextPrimitive,
    Timestamp,
    Vector3,
)

from palletpilot.control.safety import SafetyFields
from palletpilot.control.vehicle import VehicleParams
from palletpilot.geometry import SE2, SE3
from palletpilot.perception.alignment import AlignmentTolerances
from palletpilot.perception.specs import ForkGeometry, PalletType
from palletpilot.roadmap import Arc, CubicBezier, Curve, Direction, Edge, Line, Node, NodeType, Roadmap

MAP, BASE_LINK, CAMERA = "map", "base_link", "camera"
"""Frame ids (REP 105): the world, the forklift, the camera's optical frame."""

NODE_COLOURS: dict[NodeType, tuple[float, float, float]] = {
    NodeType.WAYPOINT: (0.5, 0.5, 0.5),
    NodeType.INTERSECTION: (0.5, 0.5, 0.5),
    NodeType.CHARGING: (0.17, 0.63, 0.17),
    NodeType.PRE_PALLET: (0.12, 0.47, 0.71),
    NodeType.PALLET: (1.0, 0.5, 0.05),
    NodeType.DROP: (0.58, 0.4, 0.74),
    NodeType.PARK: (0.55, 0.34, 0.29),
}
"""Node colours, as in `roadmap.draw`."""


_OBSTACLE_HEIGHT_M = {"rack": 2.0, "person": 1.75, "box": 0.5}


def stamp(ns: int) -> Timestamp:
    """A foxglove timestamp from nanoseconds since the epoch."""
    return Timestamp(ns // 1_000_000_000, ns % 1_000_000_000)


def colour(rgb: Sequence[float], a: float = 1.0) -> Color:
    """A colour from r, g, b in 0..1 and alpha."""
    return Color(r=float(rgb[0]), g=float(rgb[1]), b=float(rgb[2]), a=a)


def quat_yaw(yaw: float) -> Quaternion:
    """The rotation about z by `yaw` (rad)."""
    return Quaternion(x=0.0, y=0.0, z=math.sin(0.5 * yaw), w=math.cos(0.5 * yaw))


def pose_se2(p: SE2, z: float = 0.0) -> Pose:
    """A planar pose (m, rad) at height `z` (m)."""
    return Pose(position=Vector3(x=p.x, y=p.y, z=z), orientation=quat_yaw(p.yaw))


def vector_quat(T: SE3) -> tuple[Vector3, Quaternion]:
    """The translation (m) and rotation of a 3D pose."""
    x, y, z, w = (float(v) for v in T.rotation.as_quat())
    t = T.t
    return Vector3(x=float(t[0]), y=float(t[1]), z=float(t[2])), Quaternion(x=x, y=y, z=z, w=w)


def pose_se3(T: SE3) -> Pose:
    """A 3D pose."""
    position, orientation = vector_quat(T)
    return Pose(position=position, orientation=orientation)


def tf_tree(ns: int, T_map_base: SE2 | None, T_base_camera: SE3 | None) -> FrameTransforms | None:
    """The `/tf` message at `ns`: `map -> base_link` (the truck on the floor) and `base_link -> camera`
    (the camera mount at the current lift), each where known; None when neither is."""
    ts = stamp(ns)
    transforms = []
    if T_map_base is not None:
        transforms.append(
            FrameTransform(
                timestamp=ts,
                parent_frame_id=MAP,
                child_frame_id=BASE_LINK,
                translation=Vector3(x=T_map_base.x, y=T_map_base.y, z=0.0),
                rotation=quat_yaw(T_map_base.yaw),
            )
        )
    if T_base_camera is not None:
        translation, rotation = vector_quat(T_base_camera)
        transforms.append(
            FrameTransform(
                timestamp=ts,
                parent_frame_id=BASE_LINK,
                child_frame_id=CAMERA,
                translation=translation,
                rotation=rotation,
            )
        )
    return FrameTransforms(transforms=transforms) if transforms else None


def _box(pose: Pose, size: Sequence[float], rgba: Sequence[float]) -> CubePrimitive:
    return CubePrimitive(pose=pose, size=Vector3(x=size[0], y=size[1], z=size[2]), color=colour(rgba[:3], rgba[3]))


def _at(x: float, y: float, z: float) -> Pose:
    return Pose(position=Vector3(x=x, y=y, z=z), orientation=Quaternion(w=1.0))


def _line(
    points: Iterable[Sequence[float]], rgba: Sequence[float], thickness: float, loop: bool = False
) -> LinePrimitive:
    pts = [Point3(x=float(p[0]), y=float(p[1]), z=float(p[2]) if len(p) > 2 else 0.0) for p in points]
    kind = LinePrimitiveLineType.LineLoop if loop else LinePrimitiveLineType.LineStrip
    return LinePrimitive(
        type=kind,
        pose=_at(0, 0, 0),
        thickness=thickness,
        scale_invariant=False,
        points=pts,
        color=colour(rgba[:3], rgba[3]),
    )


def _meta(**items: Any) -> list[KeyValuePair]:
    return [KeyValuePair(key=k, value=str(v)) for k, v in items.items()]


def _update(entities: list[SceneEntity], ns: int) -> SceneUpdate:
    """The topic's whole state: delete every earlier entity, then these."""
    return SceneUpdate(
        deletions=[SceneEntityDeletion(timestamp=stamp(ns), type=SceneEntityDeletionType.All)], entities=entities
    )


# -- the roadmap ------------------------------------------------------------------------------------


def edge_points(edge: Edge, step_m: float = 0.1) -> np.ndarray:
    """Points (n, 2) along an edge's curve (map frame, m), about `step_m` apart."""
    n = max(2, math.ceil(edge.length / step_m) + 1)
    smp = edge.curve.sample(np.linspace(0.0, edge.length, n))
    return np.column_stack([smp.x, smp.y])


def roadmap_entities(
    nodes: Sequence[Node], edges: Sequence[Edge], ns: int, prefix: str, temporary: bool
) -> list[SceneEntity]:
    """Nodes (spheres, heading arrows, ids) and edges (lines; reverse edges dashed in a lighter grey) in `map`."""
    if not nodes and not edges:
        return []
    alpha = 1.0
    fwd, rev = (0.3, 0.3, 0.3, alpha), (0.65, 0.65, 0.65, alpha)
    if temporary:
        fwd, rev = (0.85, 0.1, 0.6, 1.0), (0.95, 0.55, 0.8, 1.0)
    lines = [
        _line(edge_points(e), fwd if e.direction is Direction.FORWARD else rev, 0.03 if temporary else 0.02)
        for e in edges
    ]
    spheres, arrows, texts = [], [], []
    for node in nodes:
        rgb = NODE_COLOURS[node.type]
        spheres.append(
            SpherePrimitive(pose=pose_se2(node.pose, 0.02), size=Vector3(x=0.15, y=0.15, z=0.15), color=colour(rgb))
        )
        if node.has_heading and node.type not in (NodeType.WAYPOINT, NodeType.INTERSECTION):
            arrows.append(
                ArrowPrimitive(
                    pose=pose_se2(node.pose, 0.03),
                    shaft_length=0.4,
                    shaft_diameter=0.04,
                    head_length=0.15,
                    head_diameter=0.1,
                    color=colour(rgb),
                )
            )
        texts.append(
            TextPrimitive(
                pose=pose_se2(SE2(node.pose.x, node.pose.y, 0.0), 0.25),
                billboard=True,
                font_size=12.0,
                scale_invariant=True,
                color=colour((0.1, 0.1, 0.1)),
                text=node.id,
            )
        )
    return [
        SceneEntity(
            timestamp=stamp(ns),
            frame_id=MAP,
            id=f"{prefix}",
            lines=lines,
            spheres=spheres,
            arrows=arrows,
            texts=texts,
            metadata=_meta(nodes=len(nodes), edges=len(edges)),
        )
    ]


def roadmap_update(roadmap: Roadmap, ns: int, temporary: bool) -> SceneUpdate:
    """The roadmap's permanent nodes and edges (`temporary` False), or its temporary ones (True)."""
    nodes = [n for n in roadmap.nodes() if n.temporary == temporary]
    edges = [e for e in roadmap.edges() if e.temporary == temporary]
    return _update(roadmap_entities(nodes, edges, ns, "temporary" if temporary else "roadmap", temporary), ns)


def curve_json(curve: Curve) -> dict[str, Any]:
    """A curve as plain JSON that `curve_from_json` rebuilds exactly (map frame, m, rad)."""
    if isinstance(curve, Line):
        return {"kind": "line", "p0": curve.p0.tolist(), "p1": curve.p1.tolist()}
    if isinstance(curve, Arc):
        return {
            "kind": "arc",
            "start": [float(curve.p0[0]), float(curve.p0[1]), curve.heading0],
            "p1": curve.p1.tolist(),
        }
    if isinstance(curve, CubicBezier):
        return {"kind": "bezier", "control": np.asarray(curve.control).tolist()}
    n = max(2, math.ceil(curve.length / 0.05) + 1)  # another curve: a polyline of lines is drawn alike
    smp = curve.sample(np.linspace(0.0, curve.length, n))
    return {"kind": "polyline", "points": np.column_stack([smp.x, smp.y]).tolist()}


def curves_from_json(doc: dict[str, Any]) -> list[Curve]:
    """The inverse of `curve_json` (a polyline comes back as its lines)."""
    kind = doc["kind"]
    if kind == "line":
        return [Line(doc["p0"], doc["p1"])]
    if kind == "arc":
        x, y, yaw = doc["start"]
        return [Arc(SE2(x, y, yaw), doc["p1"])]
    if kind == "bezier":
        return [CubicBezier(*np.asarray(doc["control"], dtype=float))]
    pts = np.asarray(doc["points"], dtype=float)
    return [Line(a, b) for a, b in itertools.pairwise(pts) if np.hypot(*(b - a)) > 1e-9]


def edge_json(edge: Edge) -> dict[str, Any]:
    """An edge as plain JSON (`/roadmap/graph`)."""
    return {
        "start": edge.start,
        "end": edge.end,
        "curve": curve_json(edge.curve),
        "direction": edge.direction.value,
        "speed_limit": edge.speed_limit,
        "temporary": edge.temporary,
    }


def node_json(node: Node) -> dict[str, Any]:
    """A node as plain JSON (`/roadmap/graph`): pose [x, y, yaw] (map frame, m, rad)."""
    return {
        "id": node.id,
        "type": node.type.value,
        "pose": [node.pose.x, node.pose.y, node.pose.yaw],
        "has_heading": node.has_heading,
        "height": node.height,
        "pre_pallet": node.pre_pallet,
        "temporary": node.temporary,
    }


# -- paths --------------------------------------------------------------------------------------------


def paths_update(paths: Sequence[Sequence[Point3]], ns: int) -> SceneUpdate:
    """The planned reference paths (`map`): the newest bright, the earlier ones faded."""
    lines = []
    for i, pts in enumerate(paths):
        newest = i == len(paths) - 1
        rgba = (0.12, 0.47, 0.71, 1.0 if newest else 0.35)
        lines.append(
            LinePrimitive(
                type=LinePrimitiveLineType.LineStrip,
                pose=_at(0, 0, 0.01),
                thickness=0.05 if newest else 0.03,
                points=list(pts),
                color=colour(rgba[:3], rgba[3]),
            )
        )
    entities = [
        SceneEntity(timestamp=stamp(ns), frame_id=MAP, id="planned", lines=lines, metadata=_meta(paths=len(paths)))
    ]
    return _update(entities if lines else [], ns)


def polyline_update(
    entity_id: str, points: Sequence[Point3], ns: int, rgba: Sequence[float], thickness: float
) -> SceneUpdate:
    """One line strip in `map` (the driven path, the MPC horizon); no points: nothing shown."""
    if len(points) < 2:
        return _update([], ns)
    line = LinePrimitive(
        type=LinePrimitiveLineType.LineStrip,
        pose=_at(0, 0, 0.02),
        thickness=thickness,
        points=list(points),
        color=colour(rgba[:3], rgba[3]),
    )
    return _update([SceneEntity(timestamp=stamp(ns), frame_id=MAP, id=entity_id, lines=[line])], ns)


# -- the truck ----------------------------------------------------------------------------------------


def truck_update(params: VehicleParams, forks: ForkGeometry, fork_height: float, loaded: bool, ns: int) -> SceneUpdate:
    """The truck in `base_link` (follows localization): body, mast, the forks at `fork_height` (m)."""
    b = params.body
    length = b.front_x - b.rear_x
    cubes = [
        _box(_at(b.rear_x + 0.5 * length, 0.0, 0.5 * b.height), (length, b.width, b.height), (0.95, 0.75, 0.1, 0.45)),
        _box(
            _at(b.front_x + 0.04, 0.0, 0.5 * (params.mast.max_height + 0.3)),
            (0.08, 0.7 * b.width, params.mast.max_height + 0.3),
            (0.3, 0.3, 0.3, 0.6),
        ),
    ]
    # Carriage and blades: from the heel (x = tip_x - length) to the tips, bottoms at the lift height.
    heel = forks.tip_x - forks.length
    cubes.append(_box(_at(heel - 0.03, 0.0, fork_height + 0.25), (0.05, 0.9 * b.width, 0.5), (0.2, 0.2, 0.2, 0.9)))
    for y in forks.centres_y:
        cubes.append(
            _box(
                _at(heel + 0.5 * forks.length, y, fork_height + 0.5 * forks.thickness),
                (forks.length, forks.width, forks.thickness),
                (0.15, 0.15, 0.15, 1.0),
            )
        )
    entity = SceneEntity(
        timestamp=stamp(ns),
        frame_id=BASE_LINK,
        id="truck",
        frame_locked=True,
        cubes=cubes,
        metadata=_meta(fork_height_m=round(fork_height, 4), loaded=loaded),
    )
    return _update([entity], ns)


def beams_update(
    forks: ForkGeometry, fork_height: float, ranges: tuple[float, float], ns: int, max_m: float = 3.0
) -> SceneUpdate:
    """The fork-tip beams in `base_link`: from each tip forward to its range (m; `inf`: `max_m`, dimmed)."""
    lines, texts = [], []
    z = fork_height + 0.5 * forks.thickness
    for y, r in zip(forks.centres_y, ranges, strict=True):
        hit = math.isfinite(r)
        end = forks.tip_x + (r if hit else max_m)
        rgba = (0.9, 0.1, 0.1, 1.0) if hit else (0.9, 0.1, 0.1, 0.25)
        lines.append(_line([(forks.tip_x, y, z), (end, y, z)], rgba, 0.01))
        texts.append(
            TextPrimitive(
                pose=_at(end, y, z + 0.05),
                billboard=True,
                font_size=11.0,
                scale_invariant=True,
                color=colour(rgba[:3]),
                text=f"{r:.2f} m" if hit else "clear",
            )
        )
    entity = SceneEntity(
        timestamp=stamp(ns), frame_id=BASE_LINK, id="beams", frame_locked=True, lines=lines, texts=texts
    )
    return _update([entity], ns)


def safety_update(
    fields: SafetyFields | None, warning: bool, protective: bool, intrusions: Sequence[str], z: float, ns: int
) -> SceneUpdate:
    """The safety scanners' fields in `base_link` (scan plane at `z`, m): protective red, warning amber;
    filled when intruded, with what intrudes."""
    if fields is None:
        return _update([], ns)
    lines, cubes = [], []
    for rects, hot, rgb in (
        (fields.warning, warning, (1.0, 0.65, 0.0)),
        (fields.protective, protective, (0.9, 0.1, 0.1)),
    ):
        for r in rects:
            lines.append(_line([(x, y, z) for x, y in r.corners()], (*rgb, 1.0), 0.03, loop=True))
            if hot:
                cubes.append(
                    _box(
                        _at(0.5 * (r.x0 + r.x1), 0.5 * (r.y0 + r.y1), z), (r.x1 - r.x0, r.y1 - r.y0, 0.01), (*rgb, 0.3)
                    )
                )
    texts = []
    if intrusions:
        texts.append(
            TextPrimitive(
                pose=_at(0.0, 0.0, z + 0.6),
                billboard=True,
                font_size=12.0,
                scale_invariant=True,
                color=colour((0.9, 0.1, 0.1)),
                text="in the field: " + ", ".join(intrusions),
            )
        )
    entity = SceneEntity(
        timestamp=stamp(ns),
        frame_id=BASE_LINK,
        id="safety_fields",
        frame_locked=True,
        lines=lines,
        cubes=cubes,
        texts=texts,
        metadata=_meta(
            field_set=fields.field_set, direction=fields.direction, warning=warning, protective_stop=protective
        ),
    )
    return _update([entity], ns)


# -- pallets ------------------------------------------------------------------------------------------


def pallet_cubes(T_world_pallet: SE3, pallet: PalletType, loaded: bool, rgba: Sequence[float]) -> list[CubePrimitive]:
    """A pallet (and its load) as boxes in `map`: the pallet frame's origin is the centre of the entry face
    on the underside, x into the pallet."""
    centre = T_world_pallet @ SE3.from_translation(0.5 * pallet.length, 0.0, 0.5 * pallet.height)
    cubes = [_box(pose_se3(centre), (pallet.length, pallet.width, pallet.height), rgba)]
    if loaded:
        h = 1.0
        load = T_world_pallet @ SE3.from_translation(0.5 * pallet.length, 0.0, pallet.height + 0.5 * h)
        cubes.append(_box(pose_se3(load), (pallet.length, pallet.width, h), (0.6, 0.45, 0.25, 0.35)))
    return cubes


def pose_record(T: SE3) -> dict[str, float]:
    """`x_m`, `y_m`, `yaw_deg` of a pose (as `Simulator.pallet_records` rounds them)."""
    p2 = T.to_se2()
    return {"x_m": round(p2.x, 4), "y_m": round(p2.y, 4), "yaw_deg": round(math.degrees(p2.yaw), 3)}


def true_pallets_update(pallets: Sequence[Any], ns: int) -> SceneUpdate:
    """The simulator's pallets (`sim.pallets.SimPallet`) in `map`, green; their report record as metadata
    (`id`, `node`, `initial`, `final`, `loaded`, `carried`, `on_forks`, as JSON)."""
    entities = []
    for p in pallets:
        record = {
            "id": p.id,
            "node": p.node or None,
            "initial": pose_record(p.initial if p.initial is not None else p.T_world_pallet),
            "final": pose_record(p.T_world_pallet),
            "loaded": p.loaded,
            "carried": p.lifted,
            "on_forks": p.carried,
        }
        entities.append(
            SceneEntity(
                timestamp=stamp(ns),
                frame_id=MAP,
                id=f"pallet/{p.id}",
                cubes=pallet_cubes(p.T_world_pallet, p.type, p.loaded, (0.17, 0.63, 0.17, 0.6)),
                metadata=[KeyValuePair(key="record", value=json.dumps(record))],
            )
        )
    return _update(entities, ns)


def estimate_entity(
    index: int,
    entry: dict[str, Any],
    T_world_pallet: SE3,
    T_world_nominal: SE3,
    tolerances: AlignmentTolerances,
    pallet: PalletType,
    ns: int,
) -> SceneEntity:
    """One pallet estimate in `map`: the estimated pallet (orange), the pallet expected at the node (grey
    outline), and the tolerance box of the entry face's centre around it (green: aligned, red: not) with
    the yaw limit as two rays; the estimate's figures as text and metadata."""
    aligned = bool(entry.get("aligned"))
    tol_rgb = (0.1, 0.7, 0.1) if aligned else (0.85, 0.1, 0.1)
    z = float(T_world_nominal.t[2]) + 0.01
    nominal = T_world_nominal.to_se2()
    box = [
        (-tolerances.longitudinal_near_m, -tolerances.lateral_m),
        (tolerances.longitudinal_far_m, -tolerances.lateral_m),
    ]
    box += [
        (tolerances.longitudinal_far_m, tolerances.lateral_m),
        (-tolerances.longitudinal_near_m, tolerances.lateral_m),
    ]
    tol_box = [(*nominal.apply(np.array(c)), z) for c in box]
    rays = []
    for sign in (-1.0, 1.0):
        end = nominal @ SE2(
            pallet.length * math.cos(sign * tolerances.yaw_rad),
            pallet.length * math.sin(sign * tolerances.yaw_rad),
            0.0,
        )
        rays.append(_line([(nominal.x, nominal.y, z), (end.x, end.y, z)], (*tol_rgb, 0.8), 0.01))
    outline_local = [(0, -0.5), (1, -0.5), (1, 0.5), (0, 0.5)]
    outline = [(*nominal.apply(np.array([a * pallet.length, b * pallet.width])), z) for a, b in outline_local]
    text = (
        f"estimate {entry.get('attempt', index + 1)}: lateral {entry.get('lateral_mm')} mm, along "
        f"{entry.get('longitudinal_mm')} mm, yaw {entry.get('yaw_deg')} deg: {'aligned' if aligned else 'misaligned'}"
    )
    top = T_world_pallet @ SE3.from_translation(0.5 * pallet.length, 0.0, pallet.height + 0.4)
    return SceneEntity(
        timestamp=stamp(ns),
        frame_id=MAP,
        id=f"estimate/{index}",
        cubes=pallet_cubes(T_world_pallet, pallet, False, (1.0, 0.5, 0.05, 0.55)),
        lines=[
            _line(outline, (0.4, 0.4, 0.4, 1.0), 0.015, loop=True),
            _line(tol_box, (*tol_rgb, 1.0), 0.02, loop=True),
            *rays,
        ],
        texts=[
            TextPrimitive(
                pose=pose_se3(top),
                billboard=True,
                font_size=12.0,
                scale_invariant=True,
                color=colour(tol_rgb),
                text=text,
            )
        ],
        metadata=_meta(
            against_node=entry.get("against_node"),
            aligned=aligned,
            lateral_mm=entry.get("lateral_mm"),
            longitudinal_mm=entry.get("longitudinal_mm"),
            yaw_deg=entry.get("yaw_deg"),
            tolerances=tolerances.to_json(),
            problems="; ".join(entry.get("problems", [])),
        ),
    )


def obstacles_update(outlines: Sequence[tuple[str, str, np.ndarray]], ns: int) -> SceneUpdate:
    """Racks, people and boxes of the simulated warehouse as upright boxes in `map` (their floor
    rectangle; `kind` and `id` as metadata)."""
    colours = {"rack": (0.29, 0.35, 0.54, 0.5), "person": (0.89, 0.1, 0.11, 0.8), "box": (0.55, 0.43, 0.19, 0.7)}
    entities = []
    for k, (kind, id_, corners) in enumerate(outlines):
        c = np.asarray(corners, dtype=float)
        centre = c.mean(axis=0)
        ex, ey = c[1] - c[0], c[3] - c[0]
        yaw = math.atan2(ex[1], ex[0])
        h = _OBSTACLE_HEIGHT_M.get(kind, 1.0)
        cube = _box(
            pose_se2(SE2(float(centre[0]), float(centre[1]), yaw), 0.5 * h),
            (float(np.hypot(*ex)), float(np.hypot(*ey)), h),
            colours.get(kind, (0.5, 0.5, 0.5, 0.5)),
        )
        entities.append(
            SceneEntity(
                timestamp=stamp(ns), frame_id=MAP, id=f"{kind}/{k}", cubes=[cube], metadata=_meta(kind=kind, id=id_)
            )
        )
    return _update(entities, ns)


def cube_corners(cube: Any) -> np.ndarray:
    """The floor rectangle (4, 2) of a decoded CubePrimitive (`map`), counter-clockwise: the inverse of
    `obstacles_update`."""
    p, q, s = cube.pose.position, cube.pose.orientation, cube.size
    yaw = 2.0 * math.atan2(q.z, q.w)
    hx, hy = 0.5 * s.x, 0.5 * s.y
    local = np.array([[-hx, -hy], [hx, -hy], [hx, hy], [-hx, hy]])
    c, sn = math.cos(yaw), math.sin(yaw)
    return local @ np.array([[c, sn], [-sn, c]]) + np.array([p.x, p.y])
