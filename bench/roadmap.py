"""`palletpilot bench roadmap`: planning time on a generated 10,000-node warehouse grid.

The grid: `rows` parallel two-way aisles along x with nodes every `spacing` metres, and two-way
cross-aisles along y at every `cross_every`-th column; quarter arcs of radius `spacing` let the
forklift turn from an aisle into a cross-aisle and back. Queries are seeded random pairs of nodes at
least half the grid's diagonal apart.
"""

from __future__ import annotations

import argparse
import math
import time

import numpy as np

from palletpilot.executor.apps.cli_args import count, seed
from palletpilot.geometry import SE2
from palletpilot.roadmap import Arc, Edge, Line, Node, NodeType, Planner, Roadmap


def warehouse_grid(rows: int = 100, cols: int = 100, spacing: float = 2.0, cross_every: int = 10) -> Roadmap:
    """A rows x cols grid of intersection nodes (no heading) with aisles, cross-aisles and turn arcs."""
    rm = Roadmap(f"warehouse grid {rows}x{cols}", "<generated grid>")
    nid = [[f"n{r}_{c}" for c in range(cols)] for r in range(rows)]
    for r in range(rows):
        for c in range(cols):
            rm.add_node(Node(nid[r][c], NodeType.INTERSECTION, SE2(c * spacing, r * spacing), has_heading=False))

    def xy(r: int, c: int) -> np.ndarray:
        return np.array([c * spacing, r * spacing])

    def two_way(a: tuple[int, int], b: tuple[int, int]) -> None:
        line = Line(xy(*a), xy(*b))
        rm.add_edge(Edge(nid[a[0]][a[1]], nid[b[0]][b[1]], line))
        rm.add_edge(Edge(nid[b[0]][b[1]], nid[a[0]][a[1]], line.reversed()))

    for r in range(rows):
        for c in range(cols - 1):
            two_way((r, c), (r, c + 1))
    cross = [c for c in range(0, cols, cross_every)]
    for c in cross:
        for r in range(rows - 1):
            two_way((r, c), (r + 1, c))
    # Turns at each cross-aisle node (r, c): from the aisle neighbour (r, c -/+ 1) into (r +/- 1, c) and back.
    for c in cross:
        for r in range(rows):
            for dc in (-1, 1):
                for dr in (-1, 1):
                    if not (0 <= c + dc < cols and 0 <= r + dr < rows):
                        continue
                    heading = 0.0 if dc == -1 else math.pi  # driving along the aisle towards column c
                    start = xy(r, c + dc)
                    arc = Arc(SE2(start[0], start[1], heading), xy(r + dr, c))
                    rm.add_edge(Edge(nid[r][c + dc], nid[r + dr][c], arc))
                    rm.add_edge(Edge(nid[r + dr][c], nid[r][c + dc], arc.reversed()))
    return rm


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument("--rows", type=count(2, 2000), default=100)
    parser.add_argument("--cols", type=count(2, 2000), default=100)
    parser.add_argument("--queries", type=count(1), default=50)
    parser.add_argument("--seed", type=seed, default=0)


def run(args: argparse.Namespace) -> dict:
    """Build the grid, plan seeded far-apart queries, return the figures."""
    t0 = time.perf_counter()
    rm = warehouse_grid(args.rows, args.cols)
    generate_s = time.perf_counter() - t0
    planner = Planner(rm)
    ids = [n.id for n in rm.nodes()]
    xy = np.array([n.pose.xy for n in rm.nodes()])
    diag = float(np.hypot(*(xy.max(axis=0) - xy.min(axis=0))))
    rng = np.random.default_rng(args.seed)

    t0 = time.perf_counter()
    planner.plan(ids[0], ids[1])  # builds the (node, heading) state arrays once
    build_ms = (time.perf_counter() - t0) * 1e3

    times: list[float] = []
    lengths: list[float] = []
    while len(times) < args.queries:
        a, b = rng.integers(len(ids), size=2)
        if np.hypot(*(xy[a] - xy[b])) < 0.5 * diag:
            continue
        t0 = time.perf_counter()
        route = planner.plan(ids[a], ids[b])
        times.append((time.perf_counter() - t0) * 1e3)
        lengths.append(route.length)
    return {
        "nodes": rm.graph.number_of_nodes(),
        "edges": rm.graph.number_of_edges(),
        "queries": len(times),
        "seed": args.seed,
        "plan_ms_median": round(float(np.median(times)), 3),
        "plan_ms_p95": round(float(np.percentile(times, 95)), 3),
        "plan_ms_max": round(float(np.max(times)), 3),
        "state_build_ms": round(build_ms, 1),
        "grid_generate_s": round(generate_s, 2),
        "mean_route_m": round(float(np.mean(lengths)), 1),
    }
