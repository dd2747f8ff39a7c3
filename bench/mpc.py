"""`palletpilot bench mpc`: the MPC and pure-pursuit followers side by side in the simulated forklift.

Routes on the example map (`missions/warehouse.yaml`): loop curves, pallet approaches, a reverse out
of a pallet node onto the loop, the charger to a rack pallet; and approach curves to displaced pallet
nodes (a temporary pallet and pre-pallet node per displacement, joined to the node before the
pre-pallet node by `roadmap.connect`, in an overlay). Each route is driven by `SimForklift` at 20 Hz
with actuator lag (the vehicle file's), slip and localization noise, seeded (`--seed`); both followers
see the same noise sequence.

Figures per controller: `solve_ms_median`, `solve_ms_p99` (control computation per tick, wall
clock), `lateral_rms_m`, `lateral_max_m`, `heading_max_deg` (true pose against the path while
driving, all routes), `final_lateral_mm`, `final_heading_deg`, `final_along_mm` (true pose against
the pallet node at the end, worst case over the routes ending at a pallet node), `failures`
(braked ticks), `succeeded` (routes completed), and per route the same errors.
"""

from __future__ import annotations

import argparse
import math
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from palletpilot.control import (
    FollowerConfig,
    FollowerStatus,
    MpcConfig,
    MpcFollower,
    PurePursuitFollower,
    load_vehicle,
)
from palletpilot.control.errors import ControlError
from palletpilot.control.follower import Follower, SegmentTrack
from palletpilot.control.mpc import SOLVERS
from palletpilot.control.vehicle import VehicleParams
from palletpilot.executor.apps.cli_args import count, names, number, seed
from palletpilot.geometry import SE2, wrap_angle
from palletpilot.geometry.fileio import bundled_path
from palletpilot.roadmap import Edge, Line, Node, NodeType, Planner, ReferencePath, connect, load_map, reference_path
from palletpilot.sim.forklift import LocalizationNoise, SimForklift

MAP = bundled_path("missions", "warehouse.yaml")
VEHICLE = bundled_path("missions", "forklift.yaml")

ROUTES: tuple[tuple[str, str], ...] = (
    ("a2", "c_e"),  # straight, 3 m arc, straight
    ("b2", "t_w"),  # straight, 3 m arc, straight
    ("a3", "floor_a3"),  # 1.5 m arc into a pallet approach, stop at the pallet node
    ("b3", "rack_b3"),  # the same on the other side, into a rack
    ("floor_a1", "a3"),  # reverse out of a pallet node, reverse arc, stop, forward down the aisle
    ("charger", "rack_b3"),  # reverse out of the charger, the loop, a rack pallet
)
DISPLACEMENTS: tuple[tuple[str, float, float, float], ...] = (
    # pallet node, displacement along and across its heading (m), yaw (deg)
    ("floor_b2", 0.10, 0.15, 4.0),
    ("floor_b2", -0.05, -0.20, -5.0),
    ("rack_a2", 0.05, -0.12, 3.0),
    ("floor_a2", 0.0, 0.25, -3.0),
)
PRE_PALLET_DISTANCE = 2.5  # m, as in the example map


@dataclass
class RouteResult:
    """Figures of one route driven by one follower (true pose; m, rad, s)."""

    name: str
    status: str
    lateral: list[float] = field(default_factory=list)
    heading: list[float] = field(default_factory=list)
    final_lateral: float | None = None
    final_heading: float | None = None
    final_along: float | None = None
    duration: float = 0.0
    error: str = ""

    def finals(self) -> tuple[float, float, float]:
        """(final_lateral, final_heading, final_along) of a driven route (`drive` sets them when it ends)."""
        assert self.final_lateral is not None and self.final_heading is not None and self.final_along is not None
        return self.final_lateral, self.final_heading, self.final_along


def displaced_route(roadmap_path: Path, params: VehicleParams, spec: tuple[str, float, float, float]) -> ReferencePath:
    """The path from the node before a pallet's pre-pallet node to a displaced copy of the pallet node."""
    pallet_id, along, across, yaw_deg = spec
    rm = load_map(roadmap_path)
    pallet = rm.node(pallet_id)
    pre_id = rm.pre_pallet_of(pallet_id)
    before = next(e.start for e in rm.edges() if e.end == pre_id and e.direction.sign > 0)
    T_world_new = pallet.pose @ SE2(along, across, math.radians(yaw_deg))
    T_world_pre = T_world_new @ SE2(-PRE_PALLET_DISTANCE, 0.0, 0.0)
    with rm.overlay() as ov:
        ov.add_node(Node("tmp_pre", NodeType.PRE_PALLET, T_world_pre))
        ov.add_node(Node("tmp_pallet", NodeType.PALLET, T_world_new, height=pallet.height, pre_pallet="tmp_pre"))
        curve = connect(rm.node(before).pose, T_world_pre, params.max_curvature)
        ov.add_edge(Edge(before, "tmp_pre", curve, speed_limit=0.6))
        ov.add_edge(Edge("tmp_pre", "tmp_pallet", Line(T_world_pre.xy, T_world_new.xy), speed_limit=0.3))
        route = Planner(rm).plan(before, "tmp_pallet")
        return reference_path(route)


def true_errors(path: ReferencePath, pose: SE2, tracks: list[SegmentTrack], state: dict) -> tuple[float, float]:
    """Lateral (m) and heading (rad) error of the true pose against the path's current segment."""
    track = tracks[state["index"]]
    state["s"] = track.project(pose.x, pose.y, state["s"])
    err = track.error(pose, min(max(state["s"], 0.0), track.length))
    return err.lateral, err.heading


def drive(
    follower: Follower,
    path: ReferencePath,
    params: VehicleParams,
    seed: int,
    noise: LocalizationNoise,
    slip: float = 0.0,
    start: SE2 | None = None,
    dt: float = 0.05,
    timeout_s: float | None = None,
    name: str = "route",
) -> RouteResult:
    """Drive `path` with `follower` in a `SimForklift` at 1/dt Hz; the true pose's errors along the way."""
    rng = np.random.default_rng(seed)
    sim = SimForklift(params, start if start is not None else path.segments[0].start_pose, rng=rng, slip_sigma=slip)
    loc_rng = np.random.default_rng(seed + 10_000)
    tracks = [SegmentTrack(seg, i, follower.model, follower.config) for i, seg in enumerate(path.segments)]
    state = {"index": 0, "s": 0.0}
    result = RouteResult(name, "running")
    limit = timeout_s if timeout_s is not None else 60.0 + 4.0 * path.length
    follower.start(path)
    t = 0.0
    try:
        while t < limit:
            fix = noise.measure(sim.state.pose, loc_rng)
            cmd = follower.update(t, fix, sim.state.v, sim.state.steering)
            if follower.segment_index != state["index"]:
                state["index"], state["s"] = follower.segment_index, 0.0
            if cmd.status is not FollowerStatus.RUNNING:
                result.status = cmd.status.value
                break
            if abs(sim.state.v) > 0.01:
                lat, head = true_errors(path, sim.state.pose, tracks, state)
                result.lateral.append(lat)
                result.heading.append(head)
            sim.command(cmd.speed, cmd.steering)
            sim.step(dt)
            t += dt
        else:
            result.status = "timeout"
    except ControlError as exc:
        result.status, result.error = "failed", str(exc)
    follower.stop()
    result.duration = t
    end = path.end_pose
    rel = end.inv() @ sim.state.pose
    result.final_lateral, result.final_heading, result.final_along = rel.y, float(wrap_angle(rel.yaw)), rel.x
    return result


def scenarios(params: VehicleParams) -> list[tuple[str, ReferencePath, bool]]:
    """(name, path, ends at a pallet node) for every benchmark route."""
    rm = load_map(MAP)
    planner = Planner(rm)
    out = []
    for a, b in ROUTES:
        route = planner.plan(a, b)
        out.append((f"{a}->{b}", reference_path(route), rm.node(b).type is NodeType.PALLET))
    for spec in DISPLACEMENTS:
        out.append((f"{spec[0]} displaced {spec[1:]}", displaced_route(MAP, params, spec), True))
    return out


CONTROLLERS = ("mpc", "pure_pursuit")


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument("--seed", type=seed, default=0)
    parser.add_argument("--xy-noise", type=number(0.0, 1.0, "m"), default=0.005, help="localization 1-sigma, m")
    parser.add_argument("--yaw-noise-deg", type=number(0.0, 45.0, "deg"), default=0.2, help="localization 1-sigma, deg")
    parser.add_argument("--slip", type=number(0.0, 0.5), default=0.01, help="relative slip 1-sigma per step")
    parser.add_argument(
        "--solver", choices=SOLVERS, default=MpcConfig.solver, help="MPC solver (see control.mpc.SOLVERS)"
    )
    parser.add_argument("--codegen", action="store_true", help="MPC solver as compiled C (cached)")
    parser.add_argument("--horizon", type=count(2, 200), default=MpcConfig.horizon)
    parser.add_argument("--controllers", type=names(CONTROLLERS), default=list(CONTROLLERS))
    parser.add_argument("--routes", default="", help="comma-separated substrings: only matching routes")
    parser.add_argument("--per-route", action="store_true", help="also list each route's figures")


def _summary(results: list[RouteResult], pallet: list[bool], solve_s: list[float], failures: int) -> dict:
    lat = np.abs(np.concatenate([np.asarray(r.lateral) for r in results if r.lateral] or [np.zeros(1)]))
    head = np.abs(np.concatenate([np.asarray(r.heading) for r in results if r.heading] or [np.zeros(1)]))
    finals = [r.finals() for r, p in zip(results, pallet, strict=True) if p]
    ms = np.asarray(solve_s) * 1e3 if solve_s else np.zeros(1)
    return {
        "solve_ms_median": round(float(np.median(ms)), 3),
        "solve_ms_p99": round(float(np.percentile(ms, 99)), 3),
        "solve_ms_max": round(float(np.max(ms)), 3),
        "lateral_rms_m": round(float(np.sqrt(np.mean(lat**2))), 4),
        "lateral_max_m": round(float(np.max(lat)), 4),
        "heading_max_deg": round(math.degrees(float(np.max(head))), 3),
        "final_lateral_mm": round(max(abs(lateral) for lateral, _, _ in finals) * 1e3, 2) if finals else None,
        "final_heading_deg": round(max(abs(math.degrees(heading)) for _, heading, _ in finals), 3) if finals else None,
        "final_along_mm": round(max(abs(along) for _, _, along in finals) * 1e3, 2) if finals else None,
        "failures": failures,
        "succeeded": f"{sum(r.status == 'succeeded' for r in results)}/{len(results)}",
    }


def _route_figures(r: RouteResult) -> dict:
    lateral, heading, along = r.finals()
    return {
        "status": r.status if not r.error else f"{r.status}: {r.error}",
        "lateral_max_m": round(float(np.max(np.abs(r.lateral))), 4) if r.lateral else None,
        "final_lateral_mm": round(lateral * 1e3, 2),
        "final_heading_deg": round(math.degrees(heading), 3),
        "final_along_mm": round(along * 1e3, 2),
        "duration_s": round(r.duration, 2),
    }


def run(args: argparse.Namespace) -> dict:
    """Drive every route with each controller; return the figures per controller."""
    params = load_vehicle(VEHICLE)
    noise = LocalizationNoise(args.xy_noise, math.radians(args.yaw_noise_deg))
    cases = scenarios(params)
    if args.routes:
        keys = args.routes.split(",")
        cases = [c for c in cases if any(k in c[0] for k in keys)]
    out: dict = {"seed": args.seed, "routes": len(cases), "solver": args.solver, "codegen": args.codegen}
    for ctrl in args.controllers:
        t0 = time.perf_counter()
        if ctrl == "mpc":
            follower: Follower = MpcFollower(
                params, MpcConfig(horizon=args.horizon, solver=args.solver, codegen=args.codegen), FollowerConfig()
            )
        elif ctrl == "pure_pursuit":
            follower = PurePursuitFollower(params, follower_config=FollowerConfig())
        else:
            raise ControlError(f"bench mpc: unknown controller '{ctrl}' (mpc, pure_pursuit)")
        build_s = time.perf_counter() - t0
        results = []
        for i, (name, path, _) in enumerate(cases):
            results.append(drive(follower, path, params, args.seed + i, noise, args.slip, name=name))
        summary = _summary(results, [c[2] for c in cases], follower.log.solve_s, follower.log.failures)
        summary["build_s"] = round(build_s, 2)
        if args.per_route:
            summary["per_route"] = {r.name: _route_figures(r) for r in results}
        out[ctrl] = summary
    return out
