"""Task state machines: states and transitions as data, behaviours per state.

Every task type is a `transitions` state machine built from `TASK_SPECS` (states, transitions). Each
non-final state has a behaviour that works in the py_trees manner: `start(ctx)` once, `update(ctx)`
every control tick returning `None` (running) or a trigger name (`done`, `aligned`, `misaligned`,
`fail`), `stop(ctx)` on leaving. Every state has a timeout; any failure ends the task in `failed`
with a reason code, and the runner stops the vehicle.

The adaptive Pickup follows ARCHITECTURE.md: drive to the pre-pallet node, calibrate, raise the forks,
estimate the pallet; when misaligned, lower the forks, back off to the node before the pre-pallet
node, add temporary pallet and pre-pallet nodes from the estimate joined by a feasible curve, approach
the new pre-pallet node and repeat (at most `max_attempts` estimates); then the proximity safety
check, enter, lift, reverse out, return to the roadmap and remove the temporary nodes. `--no-adapt` runs the paper's
original Pickup: no camera, only the safety check.
"""

from __future__ import annotations

import math
from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from control.errors import ControlError
from control.follower import Follower, FollowerStatus
from control.vehicle import VehicleParams
from executor.ports import PerceptionService, VehiclePort
from geometry import SE2, PalletpilotError
from perception.alignment import AlignmentTolerances, check_alignment
from perception.calibration import CalibrationError
from perception.calibration_io import Calibration
from perception.errors import PerceptionError
from perception.frames import FrameBundle
from perception.pallet import PalletEstimate, fuse_estimates
from perception.specs import ENTRY_GAP_M, ForkGeometry, PalletType, node_pose_for_pallet
from perception.view import pickup_view
from roadmap import Direction, Edge, Node, NodeType, Overlay, Planner, Roadmap, RoadmapError, connect, reference_path
from roadmap.planner import Route

# -- reason codes of a failed task ------------------------------------------------------------------
CALIBRATION_FAILED = "calibration_failed"
PALLET_NOT_FOUND = "pallet_not_found"
STILL_MISALIGNED = "still_misaligned"
NO_FEASIBLE_APPROACH = "no_feasible_approach"
SAFETY_CHECK_FAILED = "safety_check_failed"
CONTROLLER_ERROR = "controller_error"
COLLISION = "collision"
PALLET_NOT_LIFTED = "pallet_not_lifted"
NO_ROUTE = "no_route"
TIMEOUT = "timeout"
CANCELLED = "cancelled"

# -- the machines as data ---------------------------------------------------------------------------


@dataclass(frozen=True)
class TaskSpec:
    """States (in order; `succeeded` and `failed` are final) and transitions (trigger, source, dest)."""

    states: tuple[str, ...]
    transitions: tuple[tuple[str, str, str], ...]


_FINAL = ("succeeded", "failed")
TASK_SPECS: dict[str, TaskSpec] = {
    "pickup": TaskSpec(
        (
            "drive_to_pre_pallet",
            "calibrate",
            "raise_forks",
            "estimate_pallet",
            "lower_forks",
            "back_off",
            "replan",
            "approach",
            "safety_check",
            "enter",
            "lift",
            "reverse_out",
            "return_to_roadmap",
            *_FINAL,
        ),
        (
            ("done", "drive_to_pre_pallet", "calibrate"),
            ("done", "calibrate", "raise_forks"),
            ("done", "raise_forks", "estimate_pallet"),
            ("aligned", "estimate_pallet", "safety_check"),
            ("misaligned", "estimate_pallet", "lower_forks"),
            ("done", "lower_forks", "back_off"),
            ("done", "back_off", "replan"),
            ("done", "replan", "approach"),
            ("done", "approach", "calibrate"),
            ("done", "safety_check", "enter"),
            ("done", "enter", "lift"),
            ("done", "lift", "reverse_out"),
            ("done", "reverse_out", "return_to_roadmap"),
            ("done", "return_to_roadmap", "succeeded"),
            ("fail", "*", "failed"),
        ),
    ),
    "pickup_no_adapt": TaskSpec(
        ("drive_to_pre_pallet", "raise_forks", "safety_check", "enter", "lift", "reverse_out", *_FINAL),
        (
            ("done", "drive_to_pre_pallet", "raise_forks"),
            ("done", "raise_forks", "safety_check"),
            ("done", "safety_check", "enter"),
            ("done", "enter", "lift"),
            ("done", "lift", "reverse_out"),
            ("done", "reverse_out", "succeeded"),
            ("fail", "*", "failed"),
        ),
    ),
    "delivery": TaskSpec(
        ("drive_to_pre_drop", "raise_forks", "enter", "lower", "reverse_out", *_FINAL),
        (
            ("done", "drive_to_pre_drop", "raise_forks"),
            ("done", "raise_forks", "enter"),
            ("done", "enter", "lower"),
            ("done", "lower", "reverse_out"),
            ("done", "reverse_out", "succeeded"),
            ("fail", "*", "failed"),
        ),
    ),
    "move": TaskSpec(("drive", *_FINAL), (("done", "drive", "succeeded"), ("fail", "*", "failed"))),
    "charge": TaskSpec(
        ("drive", "charge", *_FINAL),
        (("done", "drive", "charge"), ("done", "charge", "succeeded"), ("fail", "*", "failed")),
    ),
    "wait": TaskSpec(("wait", *_FINAL), (("done", "wait", "succeeded"), ("fail", "*", "failed"))),
}


class MachineModel:
    """The object a task's `transitions` machine drives; `state` names the current state."""

    state: str


def build_machine(task: str, graph: bool = False) -> MachineModel:
    """A fresh machine of a task type from `TASK_SPECS`; with `graph`, one that can draw itself (mermaid)."""
    from transitions import Machine
    from transitions.extensions import GraphMachine

    spec = TASK_SPECS[task]
    model = MachineModel()
    kwargs = {"graph_engine": "mermaid", "title": f"{task} task"} if graph else {}
    (GraphMachine if graph else Machine)(
        model=model,
        states=list(spec.states),
        transitions=[{"trigger": t, "source": s, "dest": d} for t, s, d in spec.transitions],
        initial=spec.states[0],
        auto_transitions=False,
        **kwargs,
    )
    return model


def mermaid(task: str) -> str:
    """The state diagram of a task type as mermaid text (drawn by `transitions`)."""
    return build_machine(task, graph=True).get_graph().draw(None)  # type: ignore[attr-defined]


# -- what the behaviours share -----------------------------------------------------------------------


class TaskFailed(PalletpilotError):  # noqa: N818 - a task's end, raised inside behaviours
    """A behaviour's failure with a reason code."""

    def __init__(self, reason: str, message: str) -> None:
        super().__init__(message)
        self.reason = reason


@dataclass
class Settings:
    """Executor parameters (m, s, rad)."""

    max_attempts: int = 3  # pallet estimates per pickup (the first one and the re-plans)
    # Alignment tolerances come from the fork and pocket geometry (`perception.alignment`), less these
    # margins for localization and control errors.
    lateral_margin: float = 0.010
    longitudinal_margin: float = 0.010
    yaw_limit_deg: float = 2.0
    fork_clearance: float = 0.025  # fork bottoms above the pallet's underside when entering
    lift_delta: float = 0.08  # lift above the entry height to carry
    travel_height: float = 0.0  # fork height while driving empty
    calibration_retries: int = 1
    frames_per_estimate: int = 3  # the pallet stands still: averaging frames (and localization fixes) cuts noise
    beam_margin: float = 0.10  # a clear beam reaches this far short of the pallet's back, at least
    return_on_failure: bool = False
    adapt: bool = True


@dataclass
class Context:
    """Everything a behaviour may use, and what it records for the report."""

    vehicle: VehiclePort
    perception: PerceptionService | None
    grab: Callable[[], FrameBundle]
    roadmap: Roadmap
    planner: Planner
    follower: Follower
    params: VehicleParams
    forks: ForkGeometry
    pallet_type: PalletType
    settings: Settings
    now: Callable[[], float]
    log: Callable[..., None]
    at_node: str
    heading: float
    # Task-scoped (reset per task):
    task: Any = None
    overlay: Overlay | None = None
    pallet_node: str = ""
    pre_node: str = ""
    node_before: str | None = None
    last_route: Route | None = None
    attempts: int = 0
    calibration: Calibration | None = None
    estimate: PalletEstimate | None = None
    record: dict[str, Any] = field(default_factory=dict)
    planned_paths: list[list[tuple[float, float]]] = field(default_factory=list)


class Behaviour:
    """A state's work: `start` once, `update` per tick (None while running, else a trigger), `stop`."""

    timeout_s: float = 60.0

    def start(self, ctx: Context) -> None:
        """Begin the state's work."""

    def update(self, ctx: Context) -> str | None:
        """One tick; None while running, else the trigger to fire."""
        raise NotImplementedError

    def stop(self, ctx: Context) -> None:
        """Leave the state (also on failure or timeout)."""


# -- driving ----------------------------------------------------------------------------------------


class FollowRoute(Behaviour):
    """Plan (or take) a route and follow it with the path follower until the forklift stands at its end."""

    def __init__(self, target: Callable[[Context], str], via: Callable[[Context], Route] | None = None) -> None:
        self.target = target
        self.via = via
        self.route: Route | None = None

    def start(self, ctx: Context) -> None:
        goal = self.target(ctx)
        try:
            self.route = self.via(ctx) if self.via else ctx.planner.plan(ctx.at_node, goal, start_yaw=ctx.heading)
        except RoadmapError as exc:
            raise TaskFailed(NO_ROUTE, str(exc)) from None
        if not self.route.edges:
            return
        path = reference_path(self.route)
        ctx.planned_paths.append(
            [(float(x), float(y)) for x, y in zip(path.stacked("x"), path.stacked("y"), strict=True)]
        )
        self.timeout_s = 30.0 + 4.0 * path.length / 0.5
        ctx.follower.start(path)
        ctx.log("route", nodes=self.route.nodes, length_m=round(self.route.length, 3))

    def update(self, ctx: Context) -> str | None:
        assert self.route is not None
        if not self.route.edges:
            return "done"
        v = ctx.vehicle
        try:
            cmd = ctx.follower.update(ctx.now(), v.localization(), v.speed, v.steering)
        except ControlError as exc:
            raise TaskFailed(CONTROLLER_ERROR, str(exc)) from None
        v.drive(cmd.speed, cmd.steering)
        if cmd.status is FollowerStatus.SUCCEEDED:
            v.stop()
            last = self.route.edges[-1]
            ctx.at_node, ctx.heading = self.route.nodes[-1], last.yaw_end
            ctx.last_route = self.route
            return "done"
        if cmd.status is FollowerStatus.FAILED:
            raise TaskFailed(CONTROLLER_ERROR, "the path follower failed")
        return None

    def stop(self, ctx: Context) -> None:
        ctx.follower.stop()
        ctx.vehicle.stop()


class SetForks(Behaviour):
    """Move the forks to a height (m) and wait until they are there."""

    timeout_s = 30.0

    def __init__(self, height: Callable[[Context], float], check: Callable[[Context], None] | None = None) -> None:
        self.height = height
        self.check = check
        self.target = 0.0

    def start(self, ctx: Context) -> None:
        mast = ctx.params.mast
        self.target = min(max(self.height(ctx), mast.min_height), mast.max_height)
        ctx.vehicle.stop()
        ctx.vehicle.set_fork_height(self.target)

    def update(self, ctx: Context) -> str | None:
        if abs(ctx.vehicle.fork_height - self.target) > 0.002:
            return None
        if self.check:
            self.check(ctx)
        return "done"


class Wait(Behaviour):
    """Stand still for a time (s)."""

    def __init__(self, seconds: Callable[[Context], float]) -> None:
        self.seconds = seconds
        self.until = 0.0

    def start(self, ctx: Context) -> None:
        ctx.vehicle.stop()
        self.until = ctx.now() + self.seconds(ctx)
        self.timeout_s = self.seconds(ctx) + 10.0

    def update(self, ctx: Context) -> str | None:
        return "done" if ctx.now() >= self.until else None


# -- perception --------------------------------------------------------------------------------------


class CalibrateCamera(Behaviour):
    """Calibrate the camera from the forks and the floor; retry once, then fail (the last good stays)."""

    timeout_s = 20.0

    def update(self, ctx: Context) -> str | None:
        assert ctx.perception is not None
        if abs(ctx.vehicle.speed) > 1e-3:
            ctx.vehicle.stop()
            return None
        errors = []
        for attempt in range(1 + ctx.settings.calibration_retries):
            frame = ctx.grab()
            try:
                ctx.calibration = ctx.perception.calibrate([frame])
            except (CalibrationError, PerceptionError) as exc:
                errors.append(str(exc))
                ctx.log("calibration_failed", attempt=attempt + 1, error=str(exc))
                continue
            ctx.record.setdefault("calibrations", []).append(ctx.calibration.to_json())
            ctx.log("calibrated", xyz_m=ctx.calibration.to_json()["xyz_m"], quality=ctx.calibration.quality)
            # A mount too steep for the Pickup explains a later "no entry face" or a hidden load.
            h, w = frame.depth.shape
            view = pickup_view(
                ctx.calibration.T_forklift_camera,
                frame.K,
                (w, h),
                ctx.forks,
                ctx.pallet_type,
                fork_clearance_m=ctx.settings.fork_clearance,
            )
            problems = view.problems()
            if problems:
                ctx.log("camera_mount_warning", problems=problems)
            return "done"
        raise TaskFailed(CALIBRATION_FAILED, f"calibration failed: {errors[-1]}")


class EstimatePallet(Behaviour):
    """Estimate the pallet with the raised forks; aligned with the (current) pallet node, or misaligned."""

    timeout_s = 20.0

    def update(self, ctx: Context) -> str | None:
        assert ctx.perception is not None and ctx.calibration is not None
        ctx.attempts += 1
        estimates, errors = [], []
        for _ in range(max(1, ctx.settings.frames_per_estimate)):
            try:
                pose = ctx.vehicle.localization()
                estimates.append(ctx.perception.estimate_pallet(ctx.grab(), ctx.calibration, pose))
            except PerceptionError as exc:
                errors.append(str(exc))
        if not estimates:
            raise TaskFailed(PALLET_NOT_FOUND, errors[-1])
        est = fuse_estimates(estimates)
        assert est.T_world_pallet is not None
        ctx.estimate = est
        node = ctx.roadmap.node(ctx.pallet_node)
        tolerances = AlignmentTolerances.from_geometry(
            ctx.forks,
            ctx.pallet_type,
            lateral_margin_m=ctx.settings.lateral_margin,
            longitudinal_margin_m=ctx.settings.longitudinal_margin,
            yaw_limit_deg=ctx.settings.yaw_limit_deg,
        )
        al = check_alignment(est.T_world_pallet, node, tolerances)
        world = est.T_world_pallet.to_se2()
        entry = {
            "problems": list(al.problems),
            "attempt": ctx.attempts,
            "against_node": ctx.pallet_node,
            "T_world_pallet": {
                "x_m": round(world.x, 4),
                "y_m": round(world.y, 4),
                "yaw_deg": round(math.degrees(world.yaw), 3),
            },
            "lateral_mm": round(al.lateral_m * 1e3, 1),
            "longitudinal_mm": round(al.longitudinal_m * 1e3, 1),
            "yaw_deg": round(math.degrees(al.yaw_rad), 3),
            "aligned": al.aligned,
        }
        ctx.record.setdefault("estimates", []).append(entry)
        ctx.log("pallet_estimate", **entry)
        if al.aligned:
            return "aligned"
        if ctx.attempts >= ctx.settings.max_attempts:
            raise TaskFailed(
                STILL_MISALIGNED,
                f"pallet still off after {ctx.attempts} estimates: {entry['lateral_mm']} mm lateral, "
                f"{entry['longitudinal_mm']} mm along, {entry['yaw_deg']} deg",
            )
        return "misaligned"


class Replan(Behaviour):
    """Add temporary pallet and pre-pallet nodes from the estimate, joined to the node before by a curve."""

    def update(self, ctx: Context) -> str | None:
        assert ctx.estimate is not None and ctx.estimate.T_world_pallet is not None and ctx.overlay is not None
        original = ctx.roadmap.node(ctx.task.node)
        original_pre = ctx.roadmap.node(ctx.roadmap.pre_pallet_of(ctx.task.node))
        standoff = original.pose.distance_to(original_pre.pose)
        new_pallet_pose = node_pose_for_pallet(ctx.estimate.T_world_pallet)
        new_pre_pose = new_pallet_pose @ SE2(-standoff, 0.0, 0.0)
        k = ctx.attempts
        pallet_id, pre_id = f"{ctx.task.node}~{k}", f"{original_pre.id}~{k}"
        before = ctx.roadmap.node(ctx.node_before or "")
        try:
            curve = connect(SE2(before.pose.x, before.pose.y, ctx.heading), new_pre_pose, ctx.params.max_curvature)
        except RoadmapError as exc:
            raise TaskFailed(NO_FEASIBLE_APPROACH, f"no feasible approach to the estimated pallet: {exc}") from None
        ov = ctx.overlay
        ov.add_node(Node(pre_id, NodeType.PRE_PALLET, new_pre_pose))
        ov.add_node(Node(pallet_id, NodeType.PALLET, new_pallet_pose, height=original.height, pre_pallet=pre_id))
        entry_speed = ctx.roadmap.edge(original_pre.id, original.id).speed_limit
        ov.add_edge(Edge(before.id, pre_id, curve, Direction.FORWARD, 0.5))
        ov.add_edge(Edge(pre_id, before.id, curve.reversed(), Direction.REVERSE, 0.5))
        ov.add_edge(ctx.roadmap.line_edge(pre_id, pallet_id, Direction.FORWARD, entry_speed))
        ov.add_edge(ctx.roadmap.line_edge(pallet_id, pre_id, Direction.REVERSE, entry_speed))
        ctx.pallet_node, ctx.pre_node = pallet_id, pre_id
        ctx.record.setdefault("temporary_nodes", []).append(
            {
                "pallet": pallet_id,
                "pre_pallet": pre_id,
                "x_m": round(new_pallet_pose.x, 4),
                "y_m": round(new_pallet_pose.y, 4),
                "yaw_deg": round(math.degrees(new_pallet_pose.yaw), 3),
            }
        )
        ctx.log("replanned", pallet=pallet_id, pre_pallet=pre_id, curve=curve.kind)
        return "done"


class SafetyCheck(Behaviour):
    """Both fork-tip beams must pass through the pockets: never enter when one stops at the pallet."""

    def update(self, ctx: Context) -> str | None:
        pre = ctx.roadmap.node(ctx.pre_node)
        pallet = ctx.roadmap.node(ctx.pallet_node)
        face = pre.pose.distance_to(pallet.pose) + ENTRY_GAP_M - ctx.forks.tip_x  # tips to the entry face
        need = face + ctx.pallet_type.length - ctx.settings.beam_margin
        left, right = ctx.vehicle.proximity_ranges()
        ctx.log("safety_check", left_m=round(left, 3), right_m=round(right, 3), need_m=round(need, 3))
        if left < need or right < need:
            raise TaskFailed(
                SAFETY_CHECK_FAILED,
                f"proximity beams blocked: left {left:.2f} m, right {right:.2f} m, a pocket passes beyond {need:.2f} m",
            )
        return "done"


class ReturnToRoadmap(FollowRoute):
    """After a pickup at temporary nodes, back out to the node before them, so they can be removed."""

    def __init__(self) -> None:
        super().__init__(lambda ctx: ctx.at_node, via=self._route)

    @staticmethod
    def _route(ctx: Context) -> Route:
        if not ctx.roadmap.node(ctx.pre_node).temporary or ctx.node_before is None:
            return Route([ctx.pre_node], [])
        return Route([ctx.pre_node, ctx.node_before], [ctx.roadmap.edge(ctx.pre_node, ctx.node_before)])


class Charge(Behaviour):
    """Stand at the charger for some minutes, or until the battery reports a level."""

    def start(self, ctx: Context) -> None:
        ctx.vehicle.stop()
        self.until = ctx.now() + 60.0 * (ctx.task.minutes or 0.0)
        self.timeout_s = 60.0 * (ctx.task.minutes or 240.0) + 10.0
        if ctx.task.until_level is not None and not hasattr(ctx.vehicle, "battery_level"):
            raise TaskFailed("no_battery_reading", "charging until a level needs a battery reading this vehicle lacks")

    def update(self, ctx: Context) -> str | None:
        if ctx.task.until_level is not None:
            return "done" if ctx.vehicle.battery_level >= ctx.task.until_level else None  # type: ignore[attr-defined]
        return "done" if ctx.now() >= self.until else None


# -- building the machines ---------------------------------------------------------------------------


def _pallet_height(ctx: Context) -> float:
    h = ctx.task.height
    return ctx.roadmap.node(ctx.task.node).height if h is None else h


def _check_lifted(ctx: Context) -> None:
    if not ctx.vehicle.load_detected():
        raise TaskFailed(PALLET_NOT_LIFTED, "the forks were raised but carry no load")


def _check_released(ctx: Context) -> None:
    if ctx.vehicle.load_detected():
        raise TaskFailed(PALLET_NOT_LIFTED, "the forks were lowered but still carry the load")


def _edge_route(start: Callable[[Context], str], end: Callable[[Context], str]) -> Callable[[Context], Route]:
    def route(ctx: Context) -> Route:
        return Route([start(ctx), end(ctx)], [ctx.roadmap.edge(start(ctx), end(ctx))])

    return route


def behaviours(task_type: str, settings: Settings) -> dict[str, Callable[[], Behaviour]]:
    """Factories of the behaviour of every non-final state of a task type."""
    s = settings
    pre = lambda ctx: ctx.pre_node  # noqa: E731
    pallet = lambda ctx: ctx.pallet_node  # noqa: E731
    before = lambda ctx: ctx.node_before or ""  # noqa: E731
    entry_height = lambda ctx: _pallet_height(ctx) + s.fork_clearance  # noqa: E731
    if task_type in ("pickup", "pickup_no_adapt"):
        table: dict[str, Callable[[], Behaviour]] = {
            "drive_to_pre_pallet": lambda: FollowRoute(pre),
            "raise_forks": lambda: SetForks(entry_height),
            "safety_check": SafetyCheck,
            "enter": lambda: FollowRoute(pallet, via=_edge_route(pre, pallet)),
            "lift": lambda: SetForks(lambda ctx: entry_height(ctx) + s.lift_delta, check=_check_lifted),
            "reverse_out": lambda: FollowRoute(pre, via=_edge_route(pallet, pre)),
        }
        if task_type == "pickup":
            table.update(
                {
                    "calibrate": CalibrateCamera,
                    "estimate_pallet": EstimatePallet,
                    "lower_forks": lambda: SetForks(lambda ctx: s.travel_height),
                    "back_off": lambda: FollowRoute(before, via=_edge_route(pre, before)),
                    "replan": Replan,
                    "approach": lambda: FollowRoute(pre, via=_edge_route(before, pre)),
                    "return_to_roadmap": ReturnToRoadmap,
                }
            )
        return table
    if task_type == "delivery":
        carry = lambda ctx: _pallet_height(ctx) + s.fork_clearance + s.lift_delta  # noqa: E731
        return {
            "drive_to_pre_drop": lambda: FollowRoute(pre),
            "raise_forks": lambda: SetForks(carry),
            "enter": lambda: FollowRoute(pallet, via=_edge_route(pre, pallet)),
            "lower": lambda: SetForks(entry_height, check=_check_released),
            "reverse_out": lambda: FollowRoute(pre, via=_edge_route(pallet, pre)),
        }
    if task_type == "move":
        return {"drive": lambda: FollowRoute(lambda ctx: ctx.task.node)}
    if task_type == "charge":
        return {
            "drive": lambda: FollowRoute(lambda ctx: ctx.task.node),
            "charge": Charge,
        }
    if task_type == "wait":
        return {"wait": lambda: Wait(lambda ctx: ctx.task.seconds)}
    raise KeyError(task_type)
