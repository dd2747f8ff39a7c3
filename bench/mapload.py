"""`palletpilot bench mapload`: how long a large map file takes to load and check.

For each size in `--nodes` (default 10,000 and 100,000) it generates a warehouse map file with
exactly that many nodes (`warehouse_map`), writes it as YAML and as JSON (the same document) to a
temporary folder next to a copy of the bundled vehicle file, and measures:

- `n<N>_yaml_check_s`, `n<N>_json_check_s`: `check_map` in this process (parse, validate, build
  curves and graph, every check, curvature against the vehicle);
- `n<N>_yaml_cli_s`, `n<N>_json_cli_s`: the whole `palletpilot map check MAP` subprocess, interpreter
  start and imports included (issue #16 bounds it: <= 2 s for 10,000 nodes, <= 20 s for 100,000
  on two cores);
- `n<N>_edges`, `n<N>_yaml_mb`, `n<N>_json_mb`, `n<N>_generate_s`: the map's size.

The map: `aisles` along x (two-way lines between waypoints `spacing` m apart, heading 0), each cell
with a pallet (or drop) spur on alternating sides: a pre-pallet node 2.5 m along and 2.5 m aside
reached by an arc or a Bezier (with or without control points), the pallet 2.5 m further on a
forward line, both left in reverse. A cross-aisle at the west end (x = -3 m) joins the aisles with
quarter arcs of radius 3 m; at the east end a three-point turnaround turns the truck back into its
aisle. Seeded: the curve kinds, slot types and heights.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import subprocess
import sys
import tempfile
import time
from pathlib import Path
from typing import Any

import numpy as np

from palletpilot.executor.apps.cli_args import count, seed
from palletpilot.geometry.fileio import bundled_path

CELLS_PER_AISLE = 40
SPACING_M = 3.0
AISLE_GAP_M = 12.0
CROSS_X_M = -3.0
SPUR_M = 2.5
HEIGHTS_M = (0.0, 1.0, 1.8)
MAX_NODES = 1_000_000


_EXTRA = 4  # nodes of an aisle besides its cells: two at the cross-aisle, two for the turnaround


def _aisle_plan(nodes: int, cells: int) -> list[list[bool]]:
    """Aisles as a spur flag per cell, adding up to exactly `nodes` nodes with their `_EXTRA` nodes.

    An empty list stands for the few plain waypoints of a map too small for an aisle.
    """
    full = _EXTRA + 3 * cells
    aisles: list[list[bool]] = []
    rest = nodes
    while rest >= full:
        aisles.append([True] * cells)
        rest -= full
    if rest > _EXTRA:
        m = rest - _EXTRA  # waypoints plus two nodes per spur
        spurs = m // 3
        aisles.append([True] * spurs + [False] * (m - 3 * spurs))
    elif rest > 0 and aisles:
        aisles[-1].extend([False] * rest)  # a few more plain waypoints at the east end
    elif rest > 0:
        aisles.append([])
    return aisles


def warehouse_map(nodes: int, seed: int = 0, vehicle: str | None = "forklift.yaml") -> dict[str, Any]:
    """A sound map document (the map-file schema) with exactly `nodes` nodes; world frame, metres, degrees.

    Every node can be reached from every other (and back): an aisle is left west into the cross-aisle
    or east through a three-point turnaround (forward quarter arc, reverse quarter arc, line back).
    """
    rng = np.random.default_rng(seed)
    doc_nodes: list[dict[str, Any]] = []
    edges: list[dict[str, Any]] = []
    aisles = _aisle_plan(nodes, CELLS_PER_AISLE)
    if aisles == [[]]:  # fewer nodes than one aisle needs: plain waypoints on a two-way line
        for c in range(nodes):
            doc_nodes.append({"id": f"a0_{c}", "type": "waypoint", "x": c * SPACING_M, "y": 0.0, "yaw_deg": 0})
            if c > 0:
                edges.append({"from": f"a0_{c - 1}", "to": f"a0_{c}", "both_ways": True})
        aisles = []
    for r, spurs in enumerate(aisles):
        y = r * AISLE_GAP_M
        for c, spur in enumerate(spurs):
            x = c * SPACING_M
            w = f"a{r}_{c}"
            doc_nodes.append({"id": w, "type": "waypoint", "x": x, "y": y, "yaw_deg": 0})
            if c > 0:
                edges.append({"from": f"a{r}_{c - 1}", "to": w, "both_ways": True})
            if spur:
                edges += _spur(doc_nodes, rng, w, x, y, 1 if (c + r) % 2 == 0 else -1)
        north, south = f"x{r}_n", f"x{r}_s"
        for nid, dy in ((south, -3.0), (north, 3.0)):
            doc_nodes.append({"id": nid, "type": "intersection", "x": CROSS_X_M, "y": y + dy, "yaw_deg": 90})
            edges.append({"from": f"a{r}_0", "to": nid, "curve": "arc", "both_ways": True})
        edges.append({"from": south, "to": north, "both_ways": True})
        if r > 0:
            edges.append({"from": f"x{r - 1}_n", "to": south, "both_ways": True})
        # The turnaround, on the side away from the last cell's spur.
        last, x_last = f"a{r}_{len(spurs) - 1}", (len(spurs) - 1) * SPACING_M
        side = -1 if (len(spurs) - 1 + r) % 2 == 0 else 1
        turn, back = f"t{r}_turn", f"t{r}_back"
        doc_nodes.append({"id": turn, "type": "waypoint", "x": x_last + 3.0, "y": y + side * 3.0, "yaw_deg": 90})
        doc_nodes.append({"id": back, "type": "waypoint", "x": x_last + 6.0, "y": y, "yaw_deg": 0})
        edges += [
            {"from": last, "to": turn, "curve": "arc", "speed_limit": 0.5},
            {"from": turn, "to": back, "curve": "arc", "direction": "reverse", "speed_limit": 0.3},
            {"from": back, "to": last},
        ]
    doc: dict[str, Any] = {"name": f"generated warehouse, {nodes} nodes, seed {seed}"}
    if vehicle is not None:
        doc["vehicle"] = vehicle
    doc.update(default_speed_limit=1.0, nodes=doc_nodes, edges=edges)
    return doc


def _spur(
    doc_nodes: list[dict[str, Any]], rng: np.random.Generator, w: str, x: float, y: float, side: int
) -> list[dict[str, Any]]:
    """Add a pre-pallet and a pallet (or drop) node beside waypoint `w` at (x, y) on `side` (+1 left of
    the aisle, -1 right); return the four edges in and out."""
    pre, slot = f"{w}_pre", f"{w}_slot"
    drop = rng.random() < 0.1
    yaw = 90 * side
    doc_nodes.append({"id": pre, "type": "pre_pallet", "x": x + SPUR_M, "y": y + side * SPUR_M, "yaw_deg": yaw})
    doc_nodes.append(
        {
            "id": slot,
            "type": "drop" if drop else "pallet",
            "x": x + SPUR_M,
            "y": y + side * 2 * SPUR_M,
            "yaw_deg": yaw,
            "pre_pallet": pre,
            "height": float(HEIGHTS_M[int(rng.integers(len(HEIGHTS_M)))]),
        }
    )
    kind = int(rng.integers(3))  # arc, bezier with default handles, bezier with control points
    into: dict[str, Any] = {"curve": "arc"} if kind == 0 else {"curve": "bezier"}
    out: dict[str, Any] = dict(into)
    if kind == 2:
        h = SPUR_M / 2
        into["control"] = [[x + h, y], [x + SPUR_M, y + side * h]]
        out["control"] = [[x + SPUR_M, y + side * h], [x + h, y]]
    return [
        {"from": w, "to": pre, **into, "speed_limit": 0.6},
        {"from": pre, "to": slot, "speed_limit": 0.3},
        {"from": slot, "to": pre, "direction": "reverse", "speed_limit": 0.3},
        {"from": pre, "to": w, **out, "direction": "reverse", "speed_limit": 0.5},
    ]


def _flow(item: dict[str, Any]) -> str:
    """One mapping in YAML flow style (ids are plain words; numbers and lists print as in JSON)."""
    fields = (f"{k}: {v}" if isinstance(v, str) else f"{k}: {json.dumps(v)}" for k, v in item.items())
    return "{" + ", ".join(fields) + "}"


def map_yaml(doc: dict[str, Any]) -> str:
    """YAML text of a map document, one node or edge per line as in the example map."""
    head = [f"{k}: {json.dumps(v)}" for k, v in doc.items() if k not in ("nodes", "edges")]
    lines = list(head)
    for key in ("nodes", "edges"):
        lines.append(f"{key}:" if doc[key] else f"{key}: []")
        lines += [f"  - {_flow(item)}" for item in doc[key]]
    return "\n".join(lines) + "\n"


def write_map(folder: Path, nodes: int, seed: int = 0) -> tuple[Path, Path]:
    """Write the generated map as `map_N.yaml` and `map_N.json` (and `forklift.yaml`) into `folder`."""
    folder.mkdir(parents=True, exist_ok=True)
    shutil.copyfile(bundled_path("missions", "forklift.yaml"), folder / "forklift.yaml")
    doc = warehouse_map(nodes, seed)
    yaml_path = folder / f"map_{nodes}.yaml"
    json_path = folder / f"map_{nodes}.json"
    yaml_path.write_text(map_yaml(doc))
    json_path.write_text(json.dumps(doc))
    return yaml_path, json_path


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument(
        "--nodes", type=node_counts, default=[10_000, 100_000], help="node counts, comma-separated (1..1000000)"
    )
    parser.add_argument("--seed", type=seed, default=0)


def node_counts(text: str) -> list[int]:
    """An argparse type: a comma-separated list of node counts, each an integer in 1..1,000,000."""
    parse = count(1, MAX_NODES)
    return list(dict.fromkeys(parse(t.strip()) for t in text.split(",")))


def _time_cli(path: Path) -> float:
    """Wall-clock seconds of `palletpilot map check PATH` in a fresh interpreter (imports included)."""
    t0 = time.perf_counter()
    proc = subprocess.run(
        [sys.executable, "-m", "palletpilot.cli", "map", "check", str(path)], capture_output=True, text=True
    )
    elapsed = time.perf_counter() - t0
    if proc.returncode != 0:
        raise RuntimeError(f"map check of {path} failed ({proc.returncode}): {proc.stderr.strip()[:500]}")
    return elapsed


def run(args: argparse.Namespace) -> dict:
    """Generate, write and check each map size; the figures per size (`n10000_...`) and format."""
    from palletpilot.control import load_vehicle
    from palletpilot.roadmap import check_map

    kappa = load_vehicle(bundled_path("missions", "forklift.yaml")).max_curvature
    result: dict[str, Any] = {"seed": args.seed, "cpus": os.cpu_count()}
    with tempfile.TemporaryDirectory(prefix="palletpilot-mapload-") as tmp:
        for n in args.nodes:
            t0 = time.perf_counter()
            paths = write_map(Path(tmp), n, args.seed)
            key = f"n{n}_"
            result[key + "generate_s"] = round(time.perf_counter() - t0, 2)
            for path in paths:
                fmt = path.suffix.lstrip(".")
                t0 = time.perf_counter()
                roadmap, problems = check_map(path, kappa)
                result[f"{key}{fmt}_check_s"] = round(time.perf_counter() - t0, 3)
                if problems or roadmap is None:
                    raise RuntimeError(f"generated map {path} has problems: {problems[:3]}")
                result[key + "edges"] = roadmap.graph.number_of_edges()
                del roadmap
                result[f"{key}{fmt}_cli_s"] = round(_time_cli(path), 3)
                result[f"{key}{fmt}_mb"] = round(path.stat().st_size / 2**20, 2)
            for path in paths:
                path.unlink()
    return result
