"""Curve synthesis: a drivable curve between two forklift poses under a curvature limit (world frame).

Used by the adaptive pickup to connect the node before the pre-pallet node with a new pre-pallet
node displaced and rotated from the estimated pallet pose. The curve leaves `start` along its heading
and arrives at `end` along its heading, driven forward. A straight line is returned when the poses
are collinear; otherwise the cubic Bezier whose largest curvature is smallest over its two handle
lengths. When even that one is too tight, or the target is behind the start, `RoadmapError` says why.
"""

from __future__ import annotations

import math

import numpy as np

from palletpilot.geometry import SE2, angle_diff
from palletpilot.roadmap.curves import CubicBezier, Curve, Line
from palletpilot.roadmap.errors import RoadmapError

_COLLINEAR_TOL_M = 1e-4
_COLLINEAR_TOL_RAD = 1e-4


def _peak_curvature(bez: CubicBezier) -> float:
    smp = bez.sample(np.linspace(0.0, bez.length, 200))
    return float(np.max(np.abs(smp.curvature)))


def _turns_back(bez: CubicBezier, chord_heading: float) -> bool:
    """True when the curve heads more than 90 degrees away from the chord somewhere (a loop or a hook)."""
    smp = bez.sample(np.linspace(0.0, bez.length, 100))
    return bool(np.any(np.abs(angle_diff(smp.heading, chord_heading)) > math.pi / 2))


def connect(start: SE2, end: SE2, max_curvature: float) -> Curve:
    """A forward-driven curve from `start` to `end` (poses in m, rad) with |curvature| <= `max_curvature` (1/m)."""
    from scipy.optimize import minimize  # here: a map check need not load scipy.optimize

    if max_curvature <= 0:
        raise RoadmapError(f"curvature limit must be positive, got {max_curvature}")
    chord = end.xy - start.xy
    dist = float(np.hypot(*chord))
    if dist < 1e-6:
        raise RoadmapError("no curve: start and end poses are at the same place")
    local = start.inv() @ end  # the end pose seen from the start pose
    if local.x <= 0.0:
        raise RoadmapError(
            f"no feasible curve: the target lies behind the start heading ({local.x:.2f} m ahead, "
            f"{local.y:.2f} m to the side)"
        )
    if abs(local.y) < _COLLINEAR_TOL_M and abs(local.yaw) < _COLLINEAR_TOL_RAD:
        return Line(start.xy, end.xy)
    chord_heading = math.atan2(chord[1], chord[0])

    def cost(handles: np.ndarray) -> float:
        a, b = handles * dist
        if a <= 0.02 * dist or b <= 0.02 * dist:
            return 1e6
        bez = CubicBezier.from_poses(start, end, a, b)
        penalty = 1e3 if _turns_back(bez, chord_heading) else 0.0
        return _peak_curvature(bez) + penalty

    grid = np.linspace(0.1, 1.0, 7)
    best = min(((a, b) for a in grid for b in grid), key=lambda ab: cost(np.array(ab)))
    res = minimize(cost, np.array(best), method="Nelder-Mead", options={"xatol": 1e-3, "fatol": 1e-5})
    a, b = res.x * dist
    bez = CubicBezier.from_poses(start, end, a, b)
    kappa = _peak_curvature(bez)
    if _turns_back(bez, chord_heading) or kappa > max_curvature:
        raise RoadmapError(
            f"no feasible curve: reaching {local.y:+.2f} m sideways and {math.degrees(local.yaw):+.1f} deg "
            f"over {local.x:.2f} m needs a radius of {1 / kappa:.2f} m, the vehicle turns no tighter than "
            f"{1 / max_curvature:.2f} m"
        )
    return bez
