"""Map files at scale and in JSON: a generated 10,000-node map loads in bounded time, JSON maps are the
same maps as YAML ones, every range problem is one line naming the file and field, and the fast
paths (the YAML reader, the batched curve geometry and checks) give exactly what the plain ones give.

The figures live in `palletpilot bench mapload`; the time bound here is loose (two busy cores).
"""

from __future__ import annotations

import json
import math
import shutil
import time
from pathlib import Path

import numpy as np
import pytest
import yaml

from palletpilot.bench.mapload import map_yaml, warehouse_map, write_map
from palletpilot.cli import main
from palletpilot.control import load_vehicle
from palletpilot.geometry.fileio import bundled_path
from palletpilot.roadmap import CubicBezier, Planner, RoadmapError, check_map, load_map, map_vehicle_file
from palletpilot.roadmap.curves import bezier_curvature_bounds, bezier_geometry, max_abs_curvatures
from palletpilot.roadmap.mapread import fast_yaml, read_map_data

MISSIONS = bundled_path("missions")
KAPPA = load_vehicle(MISSIONS / "forklift.yaml").max_curvature


def summary(roadmap) -> tuple[list, list]:
    """Everything a load decides: nodes and edges in order, with their exact numbers."""
    nodes = [(n.id, n.type, n.pose, n.has_heading, n.height, n.pre_pallet) for n in roadmap.nodes()]
    edges = [
        (e.start, e.end, e.curve.kind, e.length, e.yaw_start, e.yaw_end, e.direction, e.speed_limit)
        for e in roadmap.edges()
    ]
    return nodes, edges


# -- scale ------------------------------------------------------------------------------------------


def test_a_generated_10k_node_map_checks_in_bounded_time(tmp_path: Path) -> None:
    yaml_path, _ = write_map(tmp_path, 10_000, seed=1)
    t0 = time.perf_counter()
    roadmap, problems = check_map(yaml_path, KAPPA)
    elapsed = time.perf_counter() - t0
    assert problems == []
    assert roadmap is not None and len(roadmap.nodes()) == 10_000
    assert roadmap.graph.number_of_edges() > 20_000
    assert elapsed < 5.0, f"check_map of 10,000 nodes took {elapsed:.1f} s (about 0.7 s on an idle machine)"


@pytest.mark.parametrize("nodes", [1, 2, 3, 4, 5, 121, 122, 123, 124, 125, 126, 250])
def test_the_generator_makes_exactly_n_nodes_and_a_sound_map(tmp_path: Path, nodes: int) -> None:
    yaml_path, _ = write_map(tmp_path, nodes)
    roadmap, problems = check_map(yaml_path, KAPPA)
    assert problems == [] and roadmap is not None
    assert len(roadmap.nodes()) == nodes


def test_the_generated_map_is_connected_both_ways(tmp_path: Path) -> None:
    yaml_path, _ = write_map(tmp_path, 600, seed=2)
    planner = Planner(load_map(yaml_path))
    slots = ["a0_0_slot", "a0_39_slot", "a1_20_slot", "a3_39_slot", "a4_5_slot"]
    for start in slots:
        for goal in slots:
            if start != goal:
                route = planner.plan(start, goal)
                assert route.nodes[0] == start and route.nodes[-1] == goal


def test_bench_mapload_prints_its_figures(capsys: pytest.CaptureFixture[str]) -> None:
    assert main(["bench", "mapload", "--json", "--nodes", "300", "--seed", "2"]) == 0
    figures = json.loads(capsys.readouterr().out)
    for key in ("n300_yaml_check_s", "n300_json_check_s", "n300_yaml_cli_s", "n300_json_cli_s", "n300_edges"):
        assert key in figures
    assert figures["seed"] == 2


@pytest.mark.parametrize("value", ["0", "-5", "1000001", "x", "10,,20", "1.5"])
def test_bench_mapload_refuses_bad_node_counts(value: str, capsys: pytest.CaptureFixture[str]) -> None:
    with pytest.raises(SystemExit) as info:
        main(["bench", "mapload", "--nodes", value])
    assert info.value.code == 2
    assert "argument --nodes: must be an integer" in capsys.readouterr().err


def test_the_generator_is_seeded() -> None:
    assert warehouse_map(500, seed=4) == warehouse_map(500, seed=4)
    assert warehouse_map(500, seed=4) != warehouse_map(500, seed=5)


# -- JSON maps --------------------------------------------------------------------------------------


def example_as_json(folder: Path) -> Path:
    """The example map converted with json.dumps, next to a copy of its vehicle file."""
    shutil.copy(MISSIONS / "forklift.yaml", folder / "forklift.yaml")
    path = folder / "warehouse.json"
    path.write_text(json.dumps(yaml.safe_load((MISSIONS / "warehouse.yaml").read_text())))
    return path


def test_the_example_map_as_json_is_the_same_map(tmp_path: Path) -> None:
    path = example_as_json(tmp_path)
    roadmap, problems = check_map(path, KAPPA)
    assert problems == [] and roadmap is not None
    assert summary(roadmap) == summary(load_map(MISSIONS / "warehouse.yaml"))


def test_the_example_map_as_json_plans_the_same_routes(tmp_path: Path) -> None:
    from_json = Planner(load_map(example_as_json(tmp_path)))
    from_yaml = Planner(load_map(MISSIONS / "warehouse.yaml"))
    ids = [n.id for n in from_yaml.roadmap.nodes()]
    for start in ids[::3]:
        for goal in ids[1::4]:
            try:
                expected = from_yaml.plan(start, goal)
            except RoadmapError as exc:
                with pytest.raises(RoadmapError, match="no route"):
                    from_json.plan(start, goal)
                assert "no route" in str(exc)
                continue
            got = from_json.plan(start, goal)
            assert got.nodes == expected.nodes and got.length == expected.length


def test_a_json_map_finds_its_vehicle_file_next_to_it(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    path = example_as_json(tmp_path)
    assert map_vehicle_file(path) == tmp_path / "forklift.yaml"
    assert main(["map", "check", str(path)]) == 0
    assert f"curvature limit {KAPPA:.3f} 1/m from {tmp_path / 'forklift.yaml'}" in capsys.readouterr().out
    assert main(["plan", str(path), "charger", "floor_a1", "--json"]) == 0
    assert json.loads(capsys.readouterr().out)["nodes"][-1] == "floor_a1"


def test_generated_yaml_and_json_maps_load_the_same(tmp_path: Path) -> None:
    yaml_path, json_path = write_map(tmp_path, 2_000, seed=3)
    from_yaml, from_json = load_map(yaml_path), load_map(json_path)
    assert summary(from_yaml) == summary(from_json)
    assert Planner(from_yaml).plan("a0_3", "a3_17").nodes == Planner(from_json).plan("a0_3", "a3_17").nodes


def test_a_json_map_with_nan_or_a_bad_vehicle(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    nan = tmp_path / "nan.json"
    nan.write_text('{"nodes": [{"id": "a", "type": "waypoint", "x": NaN, "y": 0}]}')
    _, problems = check_map(nan, None)
    assert problems == [f"{nan}: not valid JSON: NaN is not a number in JSON (RFC 8259)"]
    bad = tmp_path / "bad.json"
    bad.write_text(json.dumps({"vehicle": "nothere.yaml", "nodes": [{"id": "a", "type": "waypoint", "x": 0, "y": 0}]}))
    assert main(["map", "check", str(bad)]) == 2
    assert "nothere.yaml: cannot read" in capsys.readouterr().err


# -- ranges and field checks ------------------------------------------------------------------------

BASE = {
    "nodes": [
        {"id": "w", "type": "waypoint", "x": 0.0, "y": 0.0, "yaw_deg": 0},
        {"id": "pre", "type": "pre_pallet", "x": 3.0, "y": 3.0, "yaw_deg": 90},
        {"id": "p", "type": "pallet", "x": 3.0, "y": 5.5, "yaw_deg": 90, "pre_pallet": "pre", "height": 1.0},
    ],
    "edges": [
        {"from": "w", "to": "pre", "curve": "arc"},
        {"from": "pre", "to": "p"},
        {"from": "p", "to": "pre", "direction": "reverse"},
        {"from": "pre", "to": "w", "curve": "arc", "direction": "reverse"},
    ],
}


def problems_of(tmp_path: Path, change, suffix: str = ".yaml") -> tuple[Path, list[str]]:
    doc = json.loads(json.dumps(BASE))
    change(doc)
    path = tmp_path / f"warehouse{suffix}"
    path.write_text(json.dumps(doc) if suffix == ".json" else yaml.safe_dump(doc))
    return path, check_map(path, None)[1]


def node(i: int, **fields):
    return lambda d: d["nodes"][i].update(fields)


def edge(i: int, **fields):
    return lambda d: d["edges"][i].update(fields)


@pytest.mark.parametrize(
    ("change", "line"),
    [
        (node(0, x=12000.5), "nodes[0].x: must be within -10000..10000 m (got 12000.5)"),
        (node(1, y=-10000.001), "nodes[1].y: must be within -10000..10000 m (got -10000.001)"),
        (node(2, height=20.5), "nodes[2].height: must be within 0..20 m (got 20.5)"),
        (node(2, height=-0.1), "nodes[2].height: must be within 0..20 m (got -0.1)"),
        (node(0, yaw_deg=361), "nodes[0].yaw_deg: must be within -360..360 deg (got 361)"),
        (node(0, yaw_deg=-400.0), "nodes[0].yaw_deg: must be within -360..360 deg (got -400.0)"),
        (node(0, id=""), "nodes[0].id: must not be empty"),
        (node(0, id="  "), "nodes[0].id: must not be blank"),
        (node(2, pre_pallet=""), "nodes[2].pre_pallet: must not be empty"),
        (node(0, x="1.5"), "nodes[0].x: Input should be a valid number"),
        (node(0, x=True), "nodes[0].x: Input should be a valid number"),
        (node(0, x=math.nan), "nodes[0].x: Input should be a finite number"),
        (node(0, yaw_deg=math.inf), "nodes[0].yaw_deg: Input should be a finite number"),
        (
            edge(1, curve="bezier", control=[[3, 4], [3, 20000]]),
            "edges[1].control[1][1]: must be within -10000..10000 m (got 20000)",
        ),
        (
            edge(1, curve="bezier", control=[[3, math.nan], [3, 5]]),
            "edges[1].control[0][1]: Input should be a finite number",
        ),
        (edge(1, curve="bezier", control=[[3, 4]]), "edges[1].control: must be 2 points [[x, y], [x, y]] (got 1)"),
        (edge(1, speed_limit=0), "edges[1].speed_limit: Input should be greater than 0"),
        (edge(1, both_ways="yes"), "edges[1].both_ways: Input should be a valid boolean"),
        (edge(1, to=""), "edges[1].to: must not be empty"),
        (lambda d: d.update(nodes=[]), "nodes: a map needs at least one node"),
        (lambda d: d.update(vehicle=""), "vehicle: must not be empty"),
    ],
)
def test_each_range_problem_is_one_line_naming_file_and_field(tmp_path: Path, change, line: str) -> None:
    path, problems = problems_of(tmp_path, change)
    assert problems == [f"{path}: {line}"]


def test_yaw_within_range_is_a_heading_however_written(tmp_path: Path) -> None:
    _, problems = problems_of(tmp_path, node(1, yaw_deg=-270))  # -270 deg is 90 deg
    assert problems == []
    _, problems = problems_of(tmp_path, node(1, yaw_deg=450))
    assert problems and "must be within -360..360 deg" in problems[0]


def test_every_range_problem_is_reported_at_once(tmp_path: Path) -> None:
    def spoil(d: dict) -> None:
        d["nodes"][0].update(x=1e6, y=-1e6, yaw_deg=1000)
        d["nodes"][2].update(height=99, id="")
        d["edges"][0].update(speed_limit=-1)

    path, problems = problems_of(tmp_path, spoil, ".json")
    assert [p.split(": ")[1] for p in problems] == [
        "nodes[0].x",
        "nodes[0].y",
        "nodes[0].yaw_deg",
        "nodes[2].id",
        "nodes[2].height",
        "edges[0].speed_limit",
    ]
    assert all(p.startswith(f"{path}: ") for p in problems)


def test_map_check_prints_each_problem_on_its_own_line(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    def spoil(d: dict) -> None:
        d["nodes"][0]["x"] = 50000
        d["nodes"][1]["height"] = 30

    path, _ = problems_of(tmp_path, spoil)
    assert main(["map", "check", str(path)]) == 2
    err = capsys.readouterr().err.strip().splitlines()
    assert err == [
        f"{path}: nodes[0].x: must be within -10000..10000 m (got 50000)",
        f"{path}: nodes[1].height: must be within 0..20 m (got 30)",
    ]


@pytest.mark.parametrize(
    ("control", "message"),
    [
        ([[3.0, 6.0], [3.0, 2.0]], "edge 'pre->p': bezier: the control points make a cusp near t = "),
        ([[3.0, 3.0], [3.0, 4.0]], "edge 'pre->p': bezier: a control point coincides with its end point"),
    ],
)
def test_degenerate_bezier_control_points(tmp_path: Path, control, message: str) -> None:
    _, problems = problems_of(tmp_path, edge(1, curve="bezier", control=control))
    assert any(message in p for p in problems), problems


def test_a_curve_of_zero_length(tmp_path: Path) -> None:
    def twin(d: dict) -> None:
        d["nodes"].append({"id": "w2", "type": "waypoint", "x": 0.0, "y": 0.0})
        d["edges"].append({"from": "w", "to": "w2"})

    path, problems = problems_of(tmp_path, twin)
    assert problems == [f"{path}: edge 'w->w2': line has zero length"]


# -- the fast paths give what the plain ones give ---------------------------------------------------

YAML_DOCS = [
    "",
    "a: 1",
    "- 1\n- 2.5\n- .inf\n- .nan\n- 0x1F\n- 017\n- 1_000\n- 1:30\n- 1.5e+3\n- 1.5e3\n- yes\n- off\n- ~\n- ''\n- '1'\n",
    "a: {b: [1, 2, {c: d}], e: }\nf: [[], {}]\n? x\n: y\n",
    "a: 1\na: 2\n1: a\n2.5: b\ntrue: c\nnull: d\n",
    "key: |\n  multi\n  line\nk: >\n  folded\n",
]


@pytest.mark.parametrize("text", [*YAML_DOCS, (MISSIONS / "warehouse.yaml").read_text()])
def test_the_fast_yaml_reader_builds_what_pyyaml_builds(text: str) -> None:
    expected = yaml.load(text, Loader=yaml.CSafeLoader)
    assert repr(fast_yaml(text)[0]) == repr(expected)


@pytest.mark.parametrize(
    "text",
    ["a: &x 1\nb: *x\n", "<<: {a: 1}\nb: 2\n", "- !!str 12\n", "- 2001-12-14\n", "{? [1]: 2}\n"],
)
def test_unusual_yaml_goes_to_pyyaml(tmp_path: Path, text: str) -> None:
    path = tmp_path / "m.yaml"
    path.write_text(text)
    try:
        expected = yaml.load(text, Loader=yaml.CSafeLoader)
    except yaml.YAMLError:
        with pytest.raises(RoadmapError, match="not valid YAML"):
            read_map_data(path)
        return
    assert read_map_data(path) == expected


def test_yaml_limits_hold_on_the_fast_path(tmp_path: Path) -> None:
    deep = tmp_path / "deep.yaml"
    deep.write_text("nodes: " + "[" * 150 + "]" * 150 + "\n")
    with pytest.raises(RoadmapError, match="nested deeper than 100 levels"):
        read_map_data(deep)
    bomb = tmp_path / "bomb.yaml"
    lines = ["a0: &a0 [x, x, x, x, x, x, x, x, x, x]"]
    lines += [f"a{i}: &a{i} [*a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}, *a{i - 1}]" for i in range(1, 12)]
    bomb.write_text("\n".join(lines) + "\n")
    with pytest.raises(RoadmapError, match="too large: more than"):
        read_map_data(bomb)


def test_a_changed_map_is_read_again(tmp_path: Path) -> None:
    path = tmp_path / "m.yaml"
    path.write_text(map_yaml(warehouse_map(30, vehicle="one.yaml")))
    assert map_vehicle_file(path) == tmp_path / "one.yaml"
    path.write_text(map_yaml(warehouse_map(31, vehicle="other.yaml")))
    assert len(load_map(path).nodes()) == 31
    assert map_vehicle_file(path) == tmp_path / "other.yaml"


def random_beziers(n: int, seed: int) -> np.ndarray:
    rng = np.random.default_rng(seed)
    return rng.normal(size=(n, 4, 2)) * rng.uniform(0.2, 20.0, size=(n, 1, 1))


def test_batched_bezier_geometry_equals_one_by_one() -> None:
    control = random_beziers(400, 1)
    length, headings, _ = bezier_geometry(control)
    for c, n, (h0, h1) in zip(control, length, headings, strict=True):
        one = CubicBezier(*c)
        assert one.length == n
        checked = CubicBezier.checked(c, float(n), (float(h0), float(h1)))
        assert checked.start_pose == one.start_pose and checked.end_pose == one.end_pose
        assert checked.start_heading == one.start_pose.yaw and checked.end_heading == one.end_pose.yaw


def test_batched_curvature_equals_one_by_one_and_the_bound_holds() -> None:
    control = random_beziers(300, 2)
    curves = [CubicBezier(*c) for c in control]
    one_by_one = np.array([c.max_abs_curvature() for c in curves])
    assert np.array_equal(max_abs_curvatures(curves), one_by_one)
    bound = bezier_curvature_bounds(control)
    t = np.linspace(0.0, 1.0, 4001)
    for curve, b in zip(curves, bound, strict=True):
        d1, d2 = curve._derivative(t, 1), curve._derivative(t, 2)
        kappa = np.abs(d1[:, 0] * d2[:, 1] - d1[:, 1] * d2[:, 0]) / np.hypot(d1[:, 0], d1[:, 1]) ** 3
        assert kappa.max() <= b
    for limit in (0.1, 0.5, 2.0):
        fast = max_abs_curvatures(curves, known_below=limit)
        assert np.array_equal(fast > limit, one_by_one > limit)
        assert np.array_equal(fast[one_by_one > limit], one_by_one[one_by_one > limit])


def test_cusps_are_found() -> None:
    control = np.array(
        [
            [[0, 0], [2, 0], [-1, 0], [1, 0]],  # runs on, turns back, runs on again
            [[0, 0], [1, 1], [0, 1], [1, 0]],  # the tangent vanishes at t = 0.5
            [[0, 0], [1, 0], [2, 1], [2, 2]],  # a smooth turn
        ],
        dtype=float,
    )
    _, _, cusp = bezier_geometry(control)
    assert 0.0 < cusp[0] < 1.0 and cusp[1] == pytest.approx(0.5, abs=1e-3) and np.isnan(cusp[2])
