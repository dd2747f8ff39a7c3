"""Drawing a roadmap (and a route) with matplotlib, world frame, metres."""

from __future__ import annotations

import math
from pathlib import Path

import matplotlib

matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
from matplotlib.axes import Axes

from palletpilot.roadmap.graph import Direction, NodeType, Roadmap
from palletpilot.roadmap.planner import Route

NODE_STYLE = {
    NodeType.WAYPOINT: ("o", "#7f7f7f"),
    NodeType.INTERSECTION: ("s", "#7f7f7f"),
    NodeType.CHARGING: ("P", "#2ca02c"),
    NodeType.PRE_PALLET: ("^", "#1f77b4"),
    NodeType.PALLET: ("s", "#ff7f0e"),
    NodeType.DROP: ("D", "#9467bd"),
    NodeType.PARK: ("h", "#8c564b"),
}


def draw_roadmap(roadmap: Roadmap, ax: Axes, route: Route | None = None, labels: bool = True) -> None:
    """Draw nodes (marker per type, arrow for heading), edges (dashed: reverse) and a route on `ax`."""
    for edge in roadmap.edges():
        smp = edge.curve.sample(np.linspace(0.0, edge.length, max(2, int(edge.length / 0.1))))
        style = "--" if edge.direction is Direction.REVERSE else "-"
        ax.plot(smp.x, smp.y, style, color="#bbbbbb", lw=1.0, zorder=1)
        mid = len(smp.s) // 2
        ax.annotate(
            "",
            xy=(smp.x[mid + 1 if mid + 1 < len(smp.s) else mid], smp.y[mid + 1 if mid + 1 < len(smp.s) else mid]),
            xytext=(smp.x[mid - 1], smp.y[mid - 1]),
            arrowprops={"arrowstyle": "->", "color": "#999999", "lw": 0.8},
            zorder=1,
        )
    if route is not None:
        for edge in route.edges:
            smp = edge.curve.sample(np.linspace(0.0, edge.length, max(2, int(edge.length / 0.05))))
            style = "--" if edge.direction is Direction.REVERSE else "-"
            ax.plot(smp.x, smp.y, style, color="#d62728", lw=2.5, zorder=3)
    for node in roadmap.nodes():
        marker, color = NODE_STYLE[node.type]
        ax.plot(node.pose.x, node.pose.y, marker, color=color, ms=7 if node.type is NodeType.PALLET else 5, zorder=4)
        if node.has_heading and node.type not in (NodeType.WAYPOINT, NodeType.INTERSECTION):
            ax.arrow(
                node.pose.x,
                node.pose.y,
                0.6 * math.cos(node.pose.yaw),
                0.6 * math.sin(node.pose.yaw),
                head_width=0.2,
                color=color,
                zorder=4,
                length_includes_head=True,
            )
        if labels:
            ax.annotate(node.id, (node.pose.x, node.pose.y), xytext=(3, 3), textcoords="offset points", fontsize=6)
    ax.set_aspect("equal")
    ax.set_xlabel("x (m)")
    ax.set_ylabel("y (m)")
    ax.grid(True, lw=0.3)


def save_roadmap_png(roadmap: Roadmap, out: str | Path, route: Route | None = None) -> Path:
    """Draw the roadmap (and route) to a PNG file; returns its path."""
    out = Path(out)
    out.parent.mkdir(parents=True, exist_ok=True)
    fig, ax = plt.subplots(figsize=(11, 9), dpi=120)
    draw_roadmap(roadmap, ax, route)
    title = roadmap.name + (f"\nroute {route.nodes[0]} -> {route.nodes[-1]}: {route.length:.1f} m" if route else "")
    ax.set_title(title, fontsize=10)
    fig.tight_layout()
    fig.savefig(out)
    plt.close(fig)
    return out
