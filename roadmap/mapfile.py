"""Map files (YAML, or JSON with the same schema for a `.json` file): loading with validation that
reports every problem, one line each (`warehouse.yaml: nodes[3].x: must be within -10000..10000 m`).

```yaml
name: example warehouse
vehicle: forklift.yaml          # optional: vehicle file (relative to this file) for the curvature limit
default_speed_limit: 1.0        # m/s, for edges that give none
parking_types: [park]           # optional: node types a truck may wait at after a failure (default: park)
nodes:
  - {id: a1_pre, type: pre_pallet, x: 4.0, y: 2.0, yaw_deg: 90}
  - {id: a1, type: pallet, x: 4.0, y: 3.5, yaw_deg: 90, pre_pallet: a1_pre, height: 0.0}
  - {id: x1, type: intersection, x: 4.0, y: 0.0}            # no yaw_deg: no heading constraint
edges:
  - {from: x1, to: a1_pre, curve: arc}                      # line (default), arc or bezier
  - {from: a1_pre, to: a1}
  - {from: a1, to: a1_pre, direction: reverse, speed_limit: 0.3}
  - {from: x1, to: x2, both_ways: true}                     # also x2 -> x1 along the same curve
  - {from: x2, to: x3, curve: bezier, control: [[1, 2], [3, 4]]}
```
An arc is fixed by its start node's heading (or, if that node has none, its end node's) and its end
point. A bezier without `control` leaves and arrives along the node headings with handles of a third
of the chord. Angles are in degrees in the file, radians inside.

Ranges (world frame): node coordinates and Bezier control points within +-10 km (`COORD_LIMIT_M`),
heights 0..20 m (`HEIGHT_MAX_M`), `yaw_deg` within -360..360 (`YAW_LIMIT_DEG`; kept as written, any
value in range is a heading, 270 and -90 are the same). Numbers must be numbers (`"3.5"` or `true`
are not), ids must not be empty or blank. Structural checks: duplicate node ids, edges naming
unknown nodes, an edge from a node to itself, duplicate edges, curves of zero length, arcs that
cannot be drawn, Bezier control points on an end point or making a cusp (the curve stops and
turns back).

Loading scales to 100,000-node maps (`bench mapload`): the YAML is read by `roadmap.mapread`, the
curves are built and checked in arrays by `roadmap.mapbuild`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Annotated, Literal

from pydantic import ConfigDict, Field, StringConstraints, ValidationError

from palletpilot.geometry.fileio import FileModel, error_message
from palletpilot.roadmap.errors import RoadmapError
from palletpilot.roadmap.graph import Direction, NodeType, Roadmap
from palletpilot.roadmap.mapbuild import build_roadmap
from palletpilot.roadmap.mapread import gc_paused, map_vehicle_entry, read_map_data

COORD_LIMIT_M = 10_000.0
"""Node coordinates and Bezier control points lie within +-10 km of the map origin (m)."""
HEIGHT_MAX_M = 20.0
"""The highest load height of a pallet or drop node (m)."""
YAW_LIMIT_DEG = 360.0
"""`yaw_deg` lies within -360..360 degrees."""

Coord = Annotated[float, Field(ge=-COORD_LIMIT_M, le=COORD_LIMIT_M, strict=True)]
Name = Annotated[str, StringConstraints(min_length=1, pattern=r"\S")]
Speed = Annotated[float, Field(gt=0.0, strict=True)]

# Fields with a range, for the message: name -> (low, high, unit).
_RANGES: dict[str, tuple[float, float, str]] = {
    "x": (-COORD_LIMIT_M, COORD_LIMIT_M, "m"),
    "y": (-COORD_LIMIT_M, COORD_LIMIT_M, "m"),
    "control": (-COORD_LIMIT_M, COORD_LIMIT_M, "m"),
    "height": (0.0, HEIGHT_MAX_M, "m"),
    "yaw_deg": (-YAW_LIMIT_DEG, YAW_LIMIT_DEG, "deg"),
}


class _Strict(FileModel):
    """A file schema (unknown keys, NaN and infinities are errors)."""


class NodeSpec(_Strict):
    """A node as written in a map file (world frame: x, y in m, yaw_deg in degrees, height in m)."""

    id: Name
    type: NodeType
    x: Coord
    y: Coord
    yaw_deg: Annotated[float, Field(ge=-YAW_LIMIT_DEG, le=YAW_LIMIT_DEG, strict=True)] | None = None
    height: Annotated[float, Field(ge=0.0, le=HEIGHT_MAX_M, strict=True)] = 0.0
    pre_pallet: Name | None = None


class EdgeSpec(_Strict):
    """An edge as written in a map file (`control`: two Bezier control points, world frame, m)."""

    model_config = ConfigDict(populate_by_name=True)

    start: Name = Field(alias="from")
    end: Name = Field(alias="to")
    curve: Literal["line", "arc", "bezier"] = "line"
    control: list[tuple[Coord, Coord]] | None = Field(None, min_length=2, max_length=2)
    direction: Direction = Direction.FORWARD
    speed_limit: Speed | None = None
    both_ways: Annotated[bool, Field(strict=True)] = False


class MapSpec(_Strict):
    """A whole map file (`default_speed_limit` in m/s)."""

    name: str = "roadmap"
    vehicle: Name | None = None
    default_speed_limit: Speed = 1.0
    parking_types: list[NodeType] | None = Field(None, min_length=1)
    nodes: list[NodeSpec] = Field(min_length=1)
    edges: list[EdgeSpec] = Field(default_factory=list)


def load_map(path: str | Path) -> Roadmap:
    """Load and validate a map file. Structural problems raise one `RoadmapError` listing all of them.

    Geometry against a vehicle (curvature) is checked by `Roadmap.check(max_curvature)`;
    `check_map` does both.
    """
    with gc_paused():
        roadmap, problems = _load(Path(path))
        problems += roadmap.check()
    if problems:
        raise RoadmapError(f"{path}: {len(problems)} problem(s) in the map", [f"{path}: {p}" for p in problems])
    return roadmap


def check_map(path: str | Path, max_curvature: float | None) -> tuple[Roadmap | None, list[str]]:
    """Every problem of a map file, one line each, including curvature above `max_curvature` (1/m)."""
    with gc_paused():
        try:
            roadmap, problems = _load(Path(path))
        except RoadmapError as exc:
            return None, exc.problems
        problems += roadmap.check(max_curvature)
    return roadmap, [f"{path}: {p}" for p in problems]


def map_vehicle_file(path: str | Path) -> Path | None:
    """The vehicle file a map names (resolved against the map's folder), or None.

    A large map is parsed once for this and a `load_map` or `check_map` of it, in either order.
    """
    vehicle = map_vehicle_entry(path)
    if isinstance(vehicle, str) and vehicle.strip():
        return Path(path).parent / vehicle
    return None


def _schema_lines(where: str, exc: ValidationError) -> list[str]:
    """One line per schema problem: `where: nodes[3].x: must be within -10000..10000 m (got 12000.0)`."""
    lines = []
    for err in exc.errors(include_url=False):
        loc = ""
        for part in err["loc"]:
            loc += f"[{part}]" if isinstance(part, int) else (f".{part}" if loc else str(part))
        field = next((p for p in reversed(err["loc"]) if isinstance(p, str)), "")
        msg = error_message(err, MapSpec)
        if err["type"] in ("greater_than_equal", "less_than_equal") and field in _RANGES:
            low, high, unit = _RANGES[field]
            msg = f"must be within {low:g}..{high:g} {unit} (got {err['input']})"
        elif err["type"] == "string_too_short":
            msg = "must not be empty"
        elif err["type"] == "string_pattern_mismatch":
            msg = "must not be blank"
        elif err["type"] in ("too_short", "too_long") and field == "control" and isinstance(err["input"], list):
            msg = f"must be 2 points [[x, y], [x, y]] (got {len(err['input'])})"
        elif err["type"] == "too_short" and loc == "nodes":
            msg = "a map needs at least one node"
        lines.append(f"{where}: {loc or 'file'}: {msg}")
    return lines


def _load(path: Path) -> tuple[Roadmap, list[str]]:
    raw = read_map_data(path)
    try:
        spec = MapSpec.model_validate(raw)
    except ValidationError as exc:
        lines = _schema_lines(str(path), exc)
        raise RoadmapError(lines[0] if len(lines) == 1 else f"{path}: {len(lines)} problems", lines) from None
    return build_roadmap(spec, str(path))
