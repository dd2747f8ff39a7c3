"""Map files: the example map is sound, and each kind of problem is caught with a clear line."""

from pathlib import Path

import pytest
import yaml

from palletpilot.control import load_vehicle
from palletpilot.geometry.fileio import bundled_path
from palletpilot.roadmap import NodeType, RoadmapError, check_map, load_map

MISSIONS = bundled_path("missions")
EXAMPLE = MISSIONS / "warehouse.yaml"

# A minimal sound map: a corridor node, a pre-pallet node and a pallet node 2.5 m ahead.
BASE = {
    "name": "mini",
    "nodes": [
        {"id": "w", "type": "waypoint", "x": 0.0, "y": 0.0, "yaw_deg": 0},
        {"id": "pre", "type": "pre_pallet", "x": 3.0, "y": 3.0, "yaw_deg": 90},
        {"id": "p", "type": "pallet", "x": 3.0, "y": 5.5, "yaw_deg": 90, "pre_pallet": "pre"},
    ],
    "edges": [
        {"from": "w", "to": "pre", "curve": "arc"},
        {"from": "pre", "to": "p"},
        {"from": "p", "to": "pre", "direction": "reverse"},
        {"from": "pre", "to": "w", "curve": "arc", "direction": "reverse"},
    ],
}


def write(tmp_path: Path, doc: dict) -> Path:
    path = tmp_path / "map.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def variant(**changes) -> dict:
    doc = yaml.safe_load(yaml.safe_dump(BASE))
    doc.update(changes)
    return doc


def problems_of(tmp_path: Path, doc: dict, max_curvature: float | None = None) -> list[str]:
    _, problems = check_map(write(tmp_path, doc), max_curvature)
    return problems


def test_example_map_is_sound_against_its_vehicle():
    vehicle = load_vehicle(MISSIONS / "forklift.yaml")
    roadmap, problems = check_map(EXAMPLE, vehicle.max_curvature)
    assert problems == []
    types = {n.type for n in roadmap.nodes()}
    assert {NodeType.PALLET, NodeType.PRE_PALLET, NodeType.CHARGING, NodeType.DROP} <= types
    pallets = [n for n in roadmap.nodes() if n.type is NodeType.PALLET]
    assert any(n.height > 0 for n in pallets) and any(n.height == 0 for n in pallets)  # rack and floor
    assert {e.curve.kind for e in roadmap.edges()} >= {"line", "arc"}


def test_the_minimal_map_is_sound(tmp_path):
    assert problems_of(tmp_path, BASE, max_curvature=1.0) == []


def test_duplicate_node_id(tmp_path):
    doc = variant(nodes=[*BASE["nodes"], {"id": "pre", "type": "waypoint", "x": 9, "y": 9}])
    assert any("duplicate node id 'pre'" in p for p in problems_of(tmp_path, doc))


def test_edge_to_unknown_node(tmp_path):
    doc = variant(edges=[*BASE["edges"], {"from": "w", "to": "ghost"}])
    problems = problems_of(tmp_path, doc)
    assert any("edge 'w->ghost': unknown node 'ghost'" in p for p in problems)


def test_pallet_node_without_straight_edge_from_its_pre_pallet_node(tmp_path):
    doc = variant(edges=[e for e in BASE["edges"] if not (e["from"] == "pre" and e["to"] == "p")])
    problems = problems_of(tmp_path, doc)
    assert any("pallet node 'p': no straight edge from its pre-pallet node 'pre'" in p for p in problems)


def test_pallet_entry_must_be_a_line(tmp_path):
    # A bezier entry between the same nodes is not the straight edge the pickup needs.
    edges = [dict(e) for e in BASE["edges"]]
    edges[1] = {"from": "pre", "to": "p", "curve": "bezier", "control": [[3.0, 4.0], [3.0, 4.5]]}
    problems = problems_of(tmp_path, variant(edges=edges))
    assert any("edge 'pre->p' must be a forward line, is a forward bezier" in p for p in problems)


def test_pallet_node_needs_its_reverse_exit(tmp_path):
    doc = variant(edges=[e for e in BASE["edges"] if not (e["from"] == "p")])
    assert any("no reverse edge back to its pre-pallet node" in p for p in problems_of(tmp_path, doc))


def test_curve_tangent_disagreeing_with_node_heading(tmp_path):
    nodes = [dict(n) for n in BASE["nodes"]]
    nodes[1]["yaw_deg"] = 80  # the arc from w arrives heading 90 deg
    problems = problems_of(tmp_path, variant(nodes=nodes))
    assert any("edge 'w->pre': end tangent 90.0 deg disagrees with node 'pre' heading 80.0 deg" in p for p in problems)


def test_curvature_above_the_vehicle_limit(tmp_path):
    # The arc w -> pre has radius 3 m (curvature 0.333 1/m).
    assert problems_of(tmp_path, BASE, max_curvature=0.5) == []
    problems = problems_of(tmp_path, BASE, max_curvature=0.25)
    assert any("edge 'w->pre': curvature 0.333 1/m (radius 3.00 m) is above the vehicle's limit" in p for p in problems)


def test_typed_nodes_need_a_heading(tmp_path):
    nodes = [dict(n) for n in BASE["nodes"]]
    del nodes[2]["yaw_deg"]
    assert any("node 'p': a pallet node needs a heading" in p for p in problems_of(tmp_path, variant(nodes=nodes)))


def test_schema_errors_name_the_field(tmp_path):
    nodes = [dict(n) for n in BASE["nodes"]]
    nodes[0]["x"] = "far"
    nodes[1]["type"] = "rocket"
    problems = problems_of(tmp_path, variant(nodes=nodes))
    assert any("nodes[0].x" in p for p in problems)
    assert any("nodes[1].type" in p for p in problems)


def test_every_problem_is_reported_at_once(tmp_path):
    doc = variant(
        nodes=[*BASE["nodes"], {"id": "w", "type": "waypoint", "x": 1, "y": 1}],
        edges=[*BASE["edges"], {"from": "w", "to": "nowhere"}],
    )
    problems = problems_of(tmp_path, doc)
    assert len(problems) == 2
    assert all(p.startswith(str(tmp_path / "map.yaml")) for p in problems)


def test_load_map_raises_with_every_problem(tmp_path):
    doc = variant(edges=[*BASE["edges"], {"from": "w", "to": "ghost"}])
    with pytest.raises(RoadmapError) as info:
        load_map(write(tmp_path, doc))
    assert "1 problem" in str(info.value)
    assert len(info.value.problems) == 1


def test_missing_file_and_bad_yaml(tmp_path):
    with pytest.raises(RoadmapError, match="cannot read"):
        load_map(tmp_path / "nope.yaml")
    bad = tmp_path / "bad.yaml"
    bad.write_text("nodes: [\n  - {id: a\n")
    with pytest.raises(RoadmapError, match="not valid YAML"):
        load_map(bad)


def test_both_ways_edges_and_bezier_defaults(tmp_path):
    doc = variant()
    doc["nodes"].append({"id": "q", "type": "waypoint", "x": -4.0, "y": 0.0, "yaw_deg": 0})
    doc["nodes"].append({"id": "r", "type": "waypoint", "x": -8.0, "y": 2.0, "yaw_deg": 0})
    doc["edges"].append({"from": "q", "to": "w", "both_ways": True})
    doc["edges"].append({"from": "r", "to": "q", "curve": "bezier"})
    roadmap = load_map(write(tmp_path, doc))
    assert roadmap.edge("w", "q").curve.start_pose.xy.tolist() == [0.0, 0.0]
    bez = roadmap.edge("r", "q").curve
    assert abs(bez.start_pose.yaw) < 1e-6 and abs(bez.end_pose.yaw) < 1e-6
