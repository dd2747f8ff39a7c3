"""Starting a run on a real truck: where it stands, its camera's frames, and the error that refuses a start.

Shared by the composition roots over the ROS 2 adapter (`executor.apps.robot`'s `run_robot`, the VDA 5050
AGV's `executor.apps.vda5050.robot_backend`).

Public API: `RobotError`, `START_TOLERANCE_M`, `START_TOLERANCE_DEG`, `start_node`, `camera_grab`.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from typing import Any

from palletpilot.geometry import PalletpilotError, angle_diff
from palletpilot.perception.frames import FrameBundle
from palletpilot.roadmap import Roadmap

START_TOLERANCE_M = 0.25
START_TOLERANCE_DEG = 10.0
"""The truck stands on its start node within these."""


class RobotError(PalletpilotError):
    """The run cannot start: a bad input, a silent topic, no tf, a stale calibration (one line each)."""


def start_node(roadmap: Roadmap, pose: Any, named: str | None = None) -> str:
    """The node the truck stands on (within `START_TOLERANCE_*`), or `named` checked the same way."""
    candidates = [roadmap.node(named)] if named is not None and named in roadmap else []
    if named is not None and not candidates:
        raise RobotError(f"--start: unknown node '{named}'")
    nodes = candidates or list(roadmap.nodes())
    best = min(nodes, key=lambda n: math.hypot(n.pose.x - pose.x, n.pose.y - pose.y))
    off_m = math.hypot(best.pose.x - pose.x, best.pose.y - pose.y)
    off_deg = abs(math.degrees(angle_diff(pose.yaw, best.pose.yaw)))
    if off_m > START_TOLERANCE_M or off_deg > START_TOLERANCE_DEG:
        raise RobotError(
            f"localization: the truck stands at x {pose.x:.2f} m, y {pose.y:.2f} m, yaw {math.degrees(pose.yaw):.1f} "
            f"deg, {off_m:.2f} m and {off_deg:.0f} deg from node '{best.id}' (the nearest{' named' if named else ''}; "
            f"limits {START_TOLERANCE_M} m, {START_TOLERANCE_DEG:.0f} deg): drive it onto a node first"
        )
    return best.id


def camera_grab(camera: Any, source: str) -> Callable[[], FrameBundle]:
    """The camera's next frame bundle; without a camera (`camera.source: none`) a `PerceptionError`."""

    def grab() -> FrameBundle:
        if camera is None:
            from palletpilot.perception.errors import PerceptionError

            raise PerceptionError(f"{source}: camera.source: none")
        frame: FrameBundle = camera.grab()
        return frame

    return grab
