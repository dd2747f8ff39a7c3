"""Bad map files and map commands: `map check`, `map show` and `plan`.

Each case copies the example map and its vehicle file into its folder and spoils one thing (or writes
a file of its own); every one must exit 2 with a line naming the file and, for a field, the field.
"""

from __future__ import annotations

import json
import math
from collections.abc import Callable
from pathlib import Path
from typing import Any

from badinputs import Case, Fixtures, dump, example, write

MAP = "warehouse.yaml"
VEHICLE = "forklift.yaml"
CHECK = ("map", "check", "{case}/" + MAP)
NAN, INF = math.nan, math.inf

Change = Callable[[dict], Any]


def copies(fx: Fixtures, folder: Path) -> None:
    """Writable copies of the example map and its vehicle file."""
    for name in (MAP, VEHICLE):
        write(folder, name, (fx.ex / name).read_bytes())


def spoil(change: Change, name: str = MAP) -> Callable[[Fixtures, Path], None]:
    """A setup: the example map (or vehicle file) with `change(doc)` applied."""

    def setup(fx: Fixtures, folder: Path) -> None:
        copies(fx, folder)
        doc = example(fx, name)
        change(doc)
        write(folder, name, dump(doc))

    return setup


def raw(data: str | bytes, name: str = MAP) -> Callable[[Fixtures, Path], None]:
    """A setup: the example files with `name` replaced by `data`."""

    def setup(fx: Fixtures, folder: Path) -> None:
        copies(fx, folder)
        write(folder, name, data)

    return setup


def as_json(change: Change, text: Callable[[str], str] = lambda t: t) -> Callable[[Fixtures, Path], None]:
    """A setup: the example map as `warehouse.json` (json.dumps, then `text` applied), spoiled by `change`."""

    def setup(fx: Fixtures, folder: Path) -> None:
        copies(fx, folder)
        doc = example(fx, MAP)
        change(doc)
        write(folder, "warehouse.json", text(json.dumps(doc)))

    return setup


def node(i: int, **fields: Any) -> Change:
    return lambda d: d["nodes"][i].update(fields)


def edge(i: int, **fields: Any) -> Change:
    return lambda d: d["edges"][i].update(fields)


def add_node(**fields: Any) -> Change:
    return lambda d: d["nodes"].append(fields)


def add_edge(**fields: Any) -> Change:
    return lambda d: d["edges"].append(fields)


def top(**fields: Any) -> Change:
    return lambda d: d.update(fields)


def drop(key: str) -> Change:
    return lambda d: d.pop(key)


def both(*changes: Change) -> Change:
    def change(d: dict) -> None:
        for c in changes:
            c(d)

    return change


# The first edge runs a_top (6, 17) -> a1 (6, 15), both heading -90 deg.
BEZIER = {"curve": "bezier"}
BOMB = "\n".join(
    ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    + [f"a{i}: &a{i} [*a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}]" for i in range(1, 12)]
    + ["nodes: *a11"]
)

FIELDS = [
    Case(
        "map_node_x_nan", CHECK, 2, "warehouse.yaml: nodes[3].x: Input should be a finite number", spoil(node(3, x=NAN))
    ),
    Case("map_node_y_inf", CHECK, 2, "nodes[4].y: Input should be a finite number", spoil(node(4, y=-INF))),
    Case(
        "map_node_yaw_nan", CHECK, 2, "nodes[0].yaw_deg: Input should be a finite number", spoil(node(0, yaw_deg=NAN))
    ),
    Case(
        "map_node_height_nan",
        CHECK,
        2,
        "nodes[19].height: Input should be a finite number",
        spoil(node(19, height=NAN)),
    ),
    Case("map_node_x_far", CHECK, 2, "nodes[2].x: must be within -10000..10000 m", spoil(node(2, x=12000.0))),
    Case(
        "map_node_y_far",
        CHECK,
        2,
        "nodes[2].y: must be within -10000..10000 m (got -1000000.0)",
        spoil(node(2, y=-1e6)),
    ),
    Case(
        "map_node_x_overflows",
        CHECK,
        2,
        "nodes[0].x: Input should be a finite number",
        raw("nodes:\n  - {id: a, type: waypoint, x: 1.0e+999, y: 0}\n"),
    ),
    Case(
        "map_node_yaw_out_of_range",
        CHECK,
        2,
        "nodes[0].yaw_deg: must be within -360..360 deg",
        spoil(node(0, yaw_deg=720)),
    ),
    Case(
        "map_node_height_negative",
        CHECK,
        2,
        "nodes[19].height: must be within 0..20 m (got -0.5)",
        spoil(node(19, height=-0.5)),
    ),
    Case(
        "map_node_height_too_high",
        CHECK,
        2,
        "nodes[19].height: must be within 0..20 m (got 25.0)",
        spoil(node(19, height=25.0)),
    ),
    Case("map_node_x_is_text", CHECK, 2, "nodes[0].x: Input should be a valid number", spoil(node(0, x="far"))),
    Case(
        "map_node_x_is_quoted_number", CHECK, 2, "nodes[0].x: Input should be a valid number", spoil(node(0, x="6.0"))
    ),
    Case("map_node_y_is_bool", CHECK, 2, "nodes[0].y: Input should be a valid number", spoil(node(0, y=True))),
    Case("map_node_x_is_list", CHECK, 2, "nodes[0].x: Input should be a valid number", spoil(node(0, x=[6, 17]))),
    Case("map_node_type_unknown", CHECK, 2, "nodes[0].type: Input should be 'waypoint'", spoil(node(0, type="rocket"))),
    Case(
        "map_node_unknown_key",
        CHECK,
        2,
        "nodes[0].colour: Extra inputs are not permitted",
        spoil(node(0, colour="red")),
    ),
    Case("map_node_id_missing", CHECK, 2, "nodes[0].id: Field required", spoil(lambda d: d["nodes"][0].pop("id"))),
    Case("map_node_id_empty", CHECK, 2, "nodes[1].id: must not be empty", spoil(node(1, id=""))),
    Case("map_node_id_blank", CHECK, 2, "nodes[1].id: must not be blank", spoil(node(1, id="   "))),
    Case("map_node_id_number", CHECK, 2, "nodes[1].id: Input should be a valid string", spoil(node(1, id=7))),
    Case("map_unknown_top_key", CHECK, 2, "lanes: Extra inputs are not permitted", spoil(top(lanes=[]))),
    Case("map_edge_unknown_key", CHECK, 2, "edges[0].radius: Extra inputs are not permitted", spoil(edge(0, radius=3))),
    Case(
        "map_edge_direction_unknown",
        CHECK,
        2,
        "edges[0].direction: Input should be 'forward' or 'reverse'",
        spoil(edge(0, direction="sideways")),
    ),
    Case(
        "map_edge_speed_zero",
        CHECK,
        2,
        "edges[0].speed_limit: Input should be greater than 0",
        spoil(edge(0, speed_limit=0)),
    ),
    Case(
        "map_edge_speed_nan",
        CHECK,
        2,
        "edges[0].speed_limit: Input should be a finite number",
        spoil(edge(0, speed_limit=NAN)),
    ),
    Case(
        "map_edge_both_ways_text",
        CHECK,
        2,
        "edges[0].both_ways: Input should be a valid boolean",
        spoil(edge(0, both_ways="yes")),
    ),
    Case("map_edge_to_empty", CHECK, 2, "edges[0].to: must not be empty", spoil(edge(0, to=""))),
    Case(
        "map_default_speed_negative",
        CHECK,
        2,
        "default_speed_limit: Input should be greater than 0",
        spoil(top(default_speed_limit=-1.0)),
    ),
    Case("map_no_nodes", CHECK, 2, "nodes: a map needs at least one node", spoil(top(nodes=[]))),
    Case("map_nodes_missing", CHECK, 2, "nodes: Field required", spoil(drop("nodes"))),
    Case("map_nodes_not_a_list", CHECK, 2, "nodes: Input should be a valid list", spoil(top(nodes="a_top"))),
    Case("map_top_is_a_list", CHECK, 2, "file: Input should be a valid dictionary", raw("- a\n- b\n")),
    Case("map_vehicle_empty", CHECK, 2, "vehicle: must not be empty", spoil(top(vehicle=""))),
]

BEZIERS = [
    Case(
        "map_bezier_control_nan",
        CHECK,
        2,
        "edges[0].control[0][0]: Input should be a finite number",
        spoil(edge(0, **BEZIER, control=[[NAN, 16.0], [6.0, 15.5]])),
    ),
    Case(
        "map_bezier_control_inf",
        CHECK,
        2,
        "edges[0].control[1][1]: Input should be a finite number",
        spoil(edge(0, **BEZIER, control=[[6.0, 16.0], [6.0, INF]])),
    ),
    Case(
        "map_bezier_control_far",
        CHECK,
        2,
        "edges[0].control[1][0]: must be within -10000..10000 m (got 50000.0)",
        spoil(edge(0, **BEZIER, control=[[6.0, 16.0], [5e4, 15.5]])),
    ),
    Case(
        "map_bezier_control_text",
        CHECK,
        2,
        "edges[0].control[0][1]: Input should be a valid number",
        spoil(edge(0, **BEZIER, control=[[6.0, "up"], [6.0, 15.5]])),
    ),
    Case(
        "map_bezier_one_control_point",
        CHECK,
        2,
        "edges[0].control: must be 2 points [[x, y], [x, y]] (got 1)",
        spoil(edge(0, **BEZIER, control=[[6.0, 16.0]])),
    ),
    Case(
        "map_bezier_control_on_a_line",
        CHECK,
        2,
        "edge 'a_top->a1': control points are only for a bezier, not a line",
        spoil(edge(0, control=[[6.0, 16.0], [6.0, 15.5]])),
    ),
    Case(
        "map_bezier_cusp",
        CHECK,
        2,
        "edge 'a_top->a1': bezier: the control points make a cusp near t =",
        spoil(edge(0, **BEZIER, control=[[6.0, 14.0], [6.0, 18.0]])),
    ),
    Case(
        "map_bezier_control_on_end_point",
        CHECK,
        2,
        "edge 'a_top->a1': bezier: a control point coincides with its end point",
        spoil(edge(0, **BEZIER, control=[[6.0, 17.0], [6.0, 15.5]])),
    ),
    Case(
        "map_bezier_needs_headings",
        CHECK,
        2,
        "edge 'a_top->free': a bezier without control points needs headings at both nodes",
        spoil(
            both(
                add_node(id="free", type="waypoint", x=2.0, y=30.0),
                add_edge(**{"from": "a_top", "to": "free", "curve": "bezier"}),
            )
        ),
    ),
]

STRUCTURE = [
    Case("map_duplicate_id", CHECK, 2, "warehouse.yaml: duplicate node id 'a_top'", spoil(node(1, id="a_top"))),
    Case(
        "map_edge_unknown_node",
        CHECK,
        2,
        "edge 'a1->nowhere': unknown node 'nowhere'",
        spoil(add_edge(**{"from": "a1", "to": "nowhere"})),
    ),
    Case(
        "map_edge_to_itself",
        CHECK,
        2,
        "edge 'a1->a1': starts and ends at the same node",
        spoil(add_edge(**{"from": "a1", "to": "a1"})),
    ),
    Case(
        "map_edge_duplicate",
        CHECK,
        2,
        "edge 'a_top->a1': duplicate edge",
        spoil(lambda d: d["edges"].append(dict(d["edges"][0]))),
    ),
    Case(
        "map_zero_length_line",
        CHECK,
        2,
        "edge 'a1->twin': line has zero length",
        spoil(both(add_node(id="twin", type="waypoint", x=6.0, y=15.0), add_edge(**{"from": "a1", "to": "twin"}))),
    ),
    Case(
        "map_arc_without_headings",
        CHECK,
        2,
        "an arc needs a heading (yaw_deg) at its start or end node",
        spoil(
            both(
                add_node(id="p", type="waypoint", x=40.0, y=0.0),
                add_node(id="q", type="waypoint", x=43.0, y=3.0),
                add_edge(**{"from": "p", "to": "q", "curve": "arc"}),
            )
        ),
    ),
    Case(
        "map_tangent_disagrees",
        CHECK,
        2,
        "edge 'a_top->a1': end tangent -90.0 deg disagrees with node 'a1' heading -80.0 deg",
        spoil(node(1, yaw_deg=-80)),
    ),
    Case(
        "map_pallet_without_pre_pallet_node",
        CHECK,
        2,
        "pallet node 'floor_a1': pre-pallet node 'nowhere' does not exist",
        spoil(node(17, pre_pallet="nowhere")),
    ),
    Case(
        "map_parking_types_pallet",
        CHECK,
        2,
        "parking_types: pallet nodes are slots or their approaches",
        spoil(top(parking_types=["pallet"])),
    ),
    Case(
        "map_curvature_above_the_vehicle",
        CHECK,
        2,
        "is above the vehicle's limit",
        spoil(lambda d: d.update(max_steering_deg=10), VEHICLE),
    ),
    Case(
        "map_every_problem_reported",
        CHECK,
        2,
        "edge 'a1->nowhere': unknown node 'nowhere'",
        spoil(both(node(1, id="a_top"), add_edge(**{"from": "a1", "to": "nowhere"}))),
    ),
]

FILES = [
    Case("map_missing_file", ("map", "check", "{case}/nothere.yaml"), 2, "nothere.yaml: cannot read"),
    Case("map_is_a_folder", ("map", "check", "{case}"), 2, "cannot read: Is a directory"),
    Case("map_empty_file", CHECK, 2, "file: Input should be a valid dictionary", raw("")),
    Case("map_latin1", CHECK, 2, "not UTF-8 text", raw("name: caf\xe9\nnodes: []\n".encode("latin-1"))),
    Case("map_binary", CHECK, 2, "not UTF-8 text", raw(bytes(range(256)) * 4)),
    Case("map_yaml_syntax", CHECK, 2, "warehouse.yaml: not valid YAML: line", raw("nodes: [\n  - {id: a\n")),
    Case("map_yaml_python_tag", CHECK, 2, "not valid YAML", raw("nodes: !!python/object/apply:os.system ['true']\n")),
    Case("map_yaml_anchor_bomb", CHECK, 2, "too large: more than", raw(BOMB)),
    Case(
        "map_yaml_nested_too_deep",
        CHECK,
        2,
        "nested deeper than 100 levels",
        raw("nodes: " + "[" * 200 + "]" * 200 + "\n"),
    ),
    Case("map_yaml_two_documents", CHECK, 2, "not valid YAML", raw("nodes: []\n---\nnodes: []\n")),
    Case(
        "map_json_nan",
        ("map", "check", "{case}/warehouse.json"),
        2,
        "not valid JSON: NaN is not a number in JSON",
        as_json(lambda d: None, lambda t: t.replace('"x": 6', '"x": NaN', 1)),
    ),
    Case(
        "map_json_infinity",
        ("map", "check", "{case}/warehouse.json"),
        2,
        "not valid JSON: -Infinity is not a number in JSON",
        as_json(lambda d: None, lambda t: t.replace('"y": 17', '"y": -Infinity', 1)),
    ),
    Case(
        "map_json_syntax",
        ("map", "check", "{case}/warehouse.json"),
        2,
        "warehouse.json: not valid JSON: line 1",
        as_json(lambda d: None, lambda t: t[:-5]),
    ),
    Case(
        "map_json_out_of_range",
        ("map", "check", "{case}/warehouse.json"),
        2,
        "warehouse.json: nodes[5].x: must be within -10000..10000 m (got 1000000000.0)",
        as_json(node(5, x=1e9)),
    ),
    Case(
        "map_json_wrong_type",
        ("map", "check", "{case}/warehouse.json"),
        2,
        "warehouse.json: nodes[5].y: Input should be a valid number",
        as_json(node(5, y="0")),
    ),
    Case(
        "map_json_bad_vehicle",
        ("map", "check", "{case}/warehouse.json"),
        2,
        "nothere.yaml: cannot read",
        as_json(top(vehicle="nothere.yaml")),
    ),
    Case("map_vehicle_missing", CHECK, 2, "nothere.yaml: cannot read", spoil(top(vehicle="nothere.yaml"))),
    Case(
        "map_vehicle_bad",
        CHECK,
        2,
        "forklift.yaml: wheelbase: Input should be greater than 0",
        spoil(lambda d: d.update(wheelbase=-1.35), VEHICLE),
    ),
    Case(
        "map_vehicle_option_missing",
        (*CHECK, "--vehicle", "{case}/nothere.yaml"),
        2,
        "nothere.yaml: cannot read",
        copies,
    ),
]

COMMANDS = [
    Case("map_plan_unknown_from", ("plan", "{ex}/warehouse.yaml", "nowhere", "a1"), 2, "unknown node 'nowhere'"),
    Case(
        "map_plan_unknown_to",
        ("plan", "{ex}/warehouse.yaml", "charger", "nowhere", "--json"),
        2,
        "unknown node 'nowhere'",
    ),
    Case(
        "map_plan_no_route",
        ("plan", "{case}/warehouse.yaml", "charger", "island"),
        2,
        "no route from 'charger'",
        spoil(add_node(id="island", type="waypoint", x=50.0, y=50.0)),
    ),
    Case(
        "map_plan_bad_map",
        ("plan", "{case}/warehouse.yaml", "charger", "floor_a1"),
        2,
        "nodes[3].x: Input should be a finite number",
        spoil(node(3, x=NAN)),
    ),
    Case(
        "map_plan_missing_map", ("plan", "{case}/nothere.yaml", "charger", "floor_a1"), 2, "nothere.yaml: cannot read"
    ),
    Case(
        "map_show_out_txt",
        ("map", "show", "{case}/warehouse.yaml", "--out", "{case}/x.txt"),
        2,
        "must end in .png",
        copies,
    ),
    Case(
        "map_show_bad_map",
        ("map", "show", "{case}/warehouse.yaml", "--out", "{case}/m.png"),
        2,
        "duplicate node id 'a_top'",
        spoil(node(1, id="a_top")),
    ),
    Case(
        "map_show_route_unknown_node",
        ("map", "show", "{ex}/warehouse.yaml", "--out", "{case}/m.png", "--route", "a1", "nowhere"),
        2,
        "unknown node 'nowhere'",
    ),
]

CASES = FIELDS + BEZIERS + STRUCTURE + FILES + COMMANDS
