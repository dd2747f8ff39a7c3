"""NURBS trajectories of VDA 5050 edges: evaluation and comparison with a roadmap curve.

An order's edge may carry a `trajectory` (degree, knotVector, controlPoints with optional weights). The
truck drives the roadmap's curves, so a trajectory is drivable when it lies on the roadmap edge's curve
(within `TOLERANCE_M` both ways); otherwise the order is refused with an `orderError`.

Public API: `TOLERANCE_M`, `trajectory_problem(trajectory)`, `evaluate(trajectory, n)`,
`deviation(trajectory, curve)`.
"""

from __future__ import annotations

import itertools
from typing import Any

import numpy as np

from palletpilot.roadmap import Curve

TOLERANCE_M = 0.05
"""How far (m) a trajectory may lie from the roadmap curve it stands for."""


def trajectory_problem(trajectory: dict[str, Any]) -> str | None:
    """Why a schema-valid trajectory is not a NURBS curve (knot count, order of knots, weights), or None."""
    degree = int(trajectory["degree"])
    knots = [float(k) for k in trajectory["knotVector"]]
    points = trajectory["controlPoints"]
    if len(points) < degree + 1:
        return f"a degree-{degree} NURBS needs at least {degree + 1} control points, got {len(points)}"
    if len(knots) != len(points) + degree + 1:
        need = len(points) + degree + 1
        return f"knotVector has {len(knots)} knots; {len(points)} control points of degree {degree} need {need}"
    if any(b < a for a, b in itertools.pairwise(knots)):
        return "knotVector must not decrease"
    if knots[degree] >= knots[-degree - 1]:
        return "knotVector leaves no parameter range to evaluate"
    if any(float(p.get("weight", 1.0)) <= 0.0 for p in points):
        return "control point weights must be positive"
    return None


def evaluate(trajectory: dict[str, Any], n: int = 64) -> np.ndarray:
    """`n` points (n x 2, m) of a valid NURBS trajectory, evenly spaced in its parameter (Cox-de Boor)."""
    p = int(trajectory["degree"])
    U = np.asarray(trajectory["knotVector"], dtype=float)
    pts = trajectory["controlPoints"]
    P = np.array([[float(c["x"]), float(c["y"])] for c in pts])
    w = np.array([float(c.get("weight", 1.0)) for c in pts])
    out = np.empty((n, 2))
    for i, u in enumerate(np.linspace(U[p], U[-p - 1], n)):
        basis = _basis(U, p, len(pts), u)
        bw = basis * w
        out[i] = bw @ P / bw.sum()
    return out


def _basis(U: np.ndarray, p: int, count: int, u: float) -> np.ndarray:
    """The `count` B-spline basis functions of degree p at u (the last span includes its right end)."""
    last = U[-p - 1]
    N = np.array(
        [1.0 if (U[i] <= u < U[i + 1]) or (u == last and U[i] < u <= U[i + 1]) else 0.0 for i in range(len(U) - 1)]
    )
    for k in range(1, p + 1):
        nxt = np.zeros(len(U) - 1 - k)
        for i in range(len(nxt)):
            a = U[i + k] - U[i]
            b = U[i + k + 1] - U[i + 1]
            left = (u - U[i]) / a * N[i] if a > 0 else 0.0
            right = (U[i + k + 1] - u) / b * N[i + 1] if b > 0 else 0.0
            nxt[i] = left + right
        N = nxt
    return N[:count]


def deviation(trajectory: dict[str, Any], curve: Curve, n: int = 64) -> float:
    """The largest distance (m) between the trajectory and the curve, both ways (a discrete Hausdorff
    distance on `n` trajectory points and curve samples every 2 cm), including the end points."""
    traj = evaluate(trajectory, n)
    s = np.linspace(0.0, curve.length, max(int(curve.length / 0.02), 2) + 1)
    samples = curve.sample(s)
    ref = np.column_stack([samples.x, samples.y])
    d = np.linalg.norm(traj[:, None, :] - ref[None, :, :], axis=2)
    ends = max(float(np.linalg.norm(traj[0] - ref[0])), float(np.linalg.norm(traj[-1] - ref[-1])))
    return max(float(d.min(axis=1).max()), float(d.min(axis=0).max()), ends)
