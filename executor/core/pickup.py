"""The adaptive Pickup's own behaviours: calibrate, estimate the pallet, re-plan, safety check.

Perception runs off the control loop (`ctx.jobs`): a state grabs its frame(s) while the truck stands,
submits the work and polls for the result each tick, so its timeout fires and the vehicle keeps being
commanded while perception runs. A result computed from a frame older than the vehicle's last motion
(`ctx.memory.last_motion_s`) is never used: the frame is grabbed again.

Public API: `CalibrateCamera`, `EstimatePallet`, `Replan`, `SafetyCheck`, `add_temporary_nodes`,
`approach_curve`, `approach_route`, `nodes_back`, and from `executor.core.engagement` (the tolerances and
the rack's limit) `forks_outside_pockets`. A re-plan's manoeuvre: `executor.core.manoeuvre`.
"""

from __future__ import annotations

import itertools
import math
from typing import Any

from palletpilot.executor.core.behaviour import Behaviour, Context, TemporaryNodes
from palletpilot.executor.core.calibration_trust import LAST_GOOD_SOURCE, note_trusted, trusted_axes_only
from palletpilot.executor.core.engagement import (
    engagement_problems,
    forks_outside_pockets,
    pickup_tolerances,
    rack_limited_pose,
)
from palletpilot.executor.core.entry import MIN_SEEN, RECHECK_S, entry_volume_at
from palletpilot.executor.core.errors import (
    CALIBRATION_FAILED,
    NO_FEASIBLE_APPROACH,
    PALLET_NOT_FOUND,
    PATH_BLOCKED,
    SAFETY_CHECK_FAILED,
    STILL_MISALIGNED,
    TaskFailed,
)
from palletpilot.executor.core.jobs import Job
from palletpilot.executor.core.manoeuvre import (
    add_manoeuvre_edges,
    check_curve_clear,
    manoeuvre_nodes,
    manoeuvre_planner,
    manoeuvre_record,
    with_manoeuvre,
)
from palletpilot.geometry import SE2, SE3, angle_diff
from palletpilot.perception.alignment import check_alignment
from palletpilot.perception.calibration import CalibrationError
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.pallet import TYPE_REFUSALS, FramePolicy, PalletEstimate
from palletpilot.perception.specs import ENTRY_GAP_M, node_pose_for_pallet, pallet_pose_at_node
from palletpilot.perception.view import pickup_view
from palletpilot.roadmap import Curve, Direction, Edge, Node, NodeType, RoadmapError, Route, connect
from palletpilot.roadmap.graph import TANGENT_TOLERANCE_RAD
from palletpilot.roadmap.manoeuvre import Manoeuvre

STANDING_SPEED = 1e-3
"""m/s: below this the vehicle stands (frames for perception are taken only then)."""


def _stale(ctx: Context, frame_s: float) -> bool:
    """True when the vehicle or its forks moved after the frame was taken."""
    return ctx.memory.last_motion_s > frame_s


def _frame_time(ctx: Context, frame: FrameBundle) -> float:
    stamp = frame.stamp_s
    return ctx.clock_now() if stamp is None else stamp


class CalibrateCamera(Behaviour):
    """Calibrate the camera from the forks and the floor; retry once, then fail (the last good stays).

    An untrusted axis is never used for the entry (`executor.calibration_trust.trusted_axes_only`): a
    calibration whose fork tips cannot be trusted keeps x from the truck's last trusted calibration when
    the mount has not moved (event `calibration_axis_kept`). Without a trusted calibration to keep it from,
    it first takes another look (`Settings.calibration_retries` fresh frames, event `calibration_untrusted`):
    a few noisy pixels past the tips trip the check now and then (one simulated pickup in 20), a tapered
    blade every time. Then the task fails with `calibration_failed` (event `calibration_refused`).
    """

    timeout_s = 20.0

    def start(self, ctx: Context) -> None:
        ctx.vehicle.stop()
        self.job: Job[Calibration] | None = None
        self.frame: FrameBundle | None = None
        self.frame_s = 0.0
        self.errors: list[str] = []
        self.untrusted = 0  # calibrations with an untrusted axis and nothing to keep it from

    def update(self, ctx: Context) -> str | None:
        perception = ctx.perception
        assert perception is not None
        if self.job is None:
            if abs(ctx.vehicle.speed) > STANDING_SPEED:
                ctx.vehicle.stop()
                return None
            frame = ctx.frame()
            if frame is None:
                return None
            self.frame, self.frame_s = frame, _frame_time(ctx, frame)
            note_trusted(ctx, perception.last_good, LAST_GOOD_SOURCE)  # before the new one replaces it
            self.job = ctx.jobs.submit(
                "calibrate",
                lambda: perception.calibrate([frame]),
                latency_s=ctx.settings.calibration_latency_s,
                delay_of=perception,
            )
            return None
        if not self.job.poll(ctx.clock_now()):
            return None
        job, self.job = self.job, None
        if _stale(ctx, self.frame_s):
            ctx.log("perception_result_discarded", state="calibrate", reason="the vehicle moved after the frame")
            return None
        try:
            calibration = job.result()
        except (CalibrationError, PerceptionError) as exc:
            self.errors.append(str(exc))
            ctx.log("calibration_failed", attempt=len(self.errors), error=str(exc))
            if len(self.errors) > ctx.settings.calibration_retries:
                raise TaskFailed(CALIBRATION_FAILED, f"calibration failed: {self.errors[-1]}") from None
            return None
        if calibration.untrusted_axes and ctx.memory.trusted_calibration is None:
            self.untrusted += 1
            if self.untrusted <= ctx.settings.calibration_retries:  # look again: noise, not a taper?
                axes = sorted(a.value for a in calibration.untrusted_axes)
                ctx.log("calibration_untrusted", attempt=self.untrusted, axes=axes, warnings=list(calibration.warnings))
                return None
        calibration = trusted_axes_only(ctx, calibration)
        ctx.memory.calibration = calibration
        ctx.memory.record.setdefault("calibrations", []).append(calibration.to_json())
        ctx.log("calibrated", xyz_m=calibration.to_json()["xyz_m"], quality=calibration.quality)
        if calibration.warnings:  # e.g. fork tips that cannot be trusted: the forks file needs the taper
            ctx.log("calibration_warning", warnings=list(calibration.warnings))
        self._check_view(ctx, calibration)
        return "done"

    def _check_view(self, ctx: Context, calibration: Calibration) -> None:
        """A mount too steep for the Pickup explains a later "no entry face" or a hidden load."""
        assert self.frame is not None
        h, w = self.frame.depth.shape
        view = pickup_view(
            calibration.T_forklift_camera,
            self.frame.K,
            (w, h),
            ctx.forks,
            ctx.pallet_type,
            fork_clearance_m=ctx.settings.fork_clearance,
        )
        problems = view.problems()
        if problems:
            ctx.log("camera_mount_warning", problems=problems)

    def stop(self, ctx: Context) -> None:
        if self.job is not None:
            self.job.cancel()


class EstimatePallet(Behaviour):
    """Estimate the pallet with the raised forks; aligned with the (current) pallet node, or misaligned.

    Takes `frames_per_estimate` frames on consecutive ticks (each with its localization fix) while the
    truck stands, estimates them off the loop and fuses the estimates; while the fused yaw is still
    uncertain, another round of frames, up to `max_frames_per_estimate` (`_frame_policy`). When as many
    frames refused the pallet type as gave an estimate, `pallet_not_found`: a type in doubt is not entered
    (unless something stands in the entry volume before the pallet, hiding part of its face: then, as
    when no pallet is seen, hold and look again, `path_blocked` after the wait).
    """

    timeout_s = 20.0

    def start(self, ctx: Context) -> None:
        ctx.vehicle.stop()
        ctx.memory.attempts += 1
        self.frames: list[tuple[FrameBundle, SE2, float]] = []
        self.estimates: list[PalletEstimate] = []  # of the frames estimated so far, over the rounds
        self.errors: list[tuple[str, str]] = []  # (reason, message) of the frames without an estimate
        self.wanted = max(1, ctx.settings.frames_per_estimate)
        self.job: Job[tuple[list[PalletEstimate], list[tuple[str, str]]]] | None = None
        self.blocked_since: float | None = None  # something stood in the entry volume since (task time, s)
        self.look_at = 0.0  # task time (s) of the next look while blocked
        self.timeout_s = EstimatePallet.timeout_s + ctx.settings.blocked_wait_s

    def update(self, ctx: Context) -> str | None:
        perception, calibration = ctx.perception, ctx.memory.calibration
        assert perception is not None and calibration is not None
        if self.job is None:
            if abs(ctx.vehicle.speed) > STANDING_SPEED:
                ctx.vehicle.stop()
                self._restart(ctx)
                return None
            if ctx.now() < self.look_at:
                return None
            frame = ctx.frame()
            if frame is not None:
                self.frames.append((frame, ctx.vehicle.localization(), _frame_time(ctx, frame)))
            if len(self.frames) < self.wanted:
                return None
            taken = self.frames[len(self.estimates) + len(self.errors) :]  # each estimated frame gave one of them
            expected, pallet = _expected_pallet(ctx), ctx.pallet_type
            support = ctx.roadmap.node(ctx.memory.pallet_node).height  # the floor, or the rack's beams

            def estimate() -> tuple[list[PalletEstimate], list[tuple[str, str]]]:
                estimates, errors = [], []
                for f, pose, _ in taken:
                    try:
                        estimates.append(
                            perception.estimate_pallet(f, calibration, pose, expected, pallet, support_height_m=support)
                        )
                    except PerceptionError as exc:
                        errors.append((str(getattr(exc, "reason", "")), str(exc)))
                return estimates, errors

            self.job = ctx.jobs.submit(
                "estimate_pallet", estimate, latency_s=len(taken) * ctx.settings.estimate_latency_s, delay_of=perception
            )
            return None
        if not self.job.poll(ctx.clock_now()):
            return None
        job, self.job = self.job, None
        if _stale(ctx, min(t for _, _, t in self.frames)):
            ctx.log("perception_result_discarded", state="estimate_pallet", reason="the vehicle moved after the frames")
            self._restart(ctx)
            return None
        estimates, errors = job.result()
        self.estimates += estimates
        self.errors += errors
        if not self.estimates:
            why = self.errors[-1][1] if self.errors else "no pallet estimate"
            if self._blocked_in_front(ctx):
                return None  # something stands before the pallet: look again later
            raise TaskFailed(PALLET_NOT_FOUND, why)
        verdict = _frame_policy(ctx).after_round(self.estimates, [r for r, _ in self.errors], len(self.frames))
        if verdict.type_in_doubt:
            refusals = [m for r, m in self.errors if r in TYPE_REFUSALS]
            n_frames = len(self.frames)
            if self._blocked_in_front(ctx):  # (which forgets this round's frames)
                return None  # something before the pallet hides part of its face: look again later
            raise TaskFailed(
                PALLET_NOT_FOUND,
                f"{len(refusals)} of {n_frames} frames refused the pallet type "
                f"({ctx.pallet_type.name}), so it is not entered: {refusals[-1]}",
            )
        fused = verdict.fused
        assert fused is not None
        if verdict.more:
            self.wanted = len(self.frames) + verdict.more
            ctx.log(
                "estimate_more_frames",
                frames=len(self.frames),
                more=verdict.more,
                yaw_sigma_deg=round(math.degrees(fused.spread.yaw_rad), 3),
                limit_deg=ctx.settings.estimate_yaw_sigma_deg,
            )
            return None
        return self._judge(ctx, fused, _mean_pose([pose for _, pose, _ in self.frames]))

    def _restart(self, ctx: Context) -> None:
        """Forget the frames and estimates taken so far (the truck moved): start the first round again."""
        self.frames.clear()
        self.estimates, self.errors = [], []
        self.wanted = max(1, ctx.settings.frames_per_estimate)

    def _blocked_in_front(self, ctx: Context) -> bool:
        """No pallet seen: is a person or an object standing in the entry volume before the pallet node
        (hiding it)? Then hold and look again every `RECHECK_S`; `path_blocked` after the wait."""
        assert ctx.perception is not None and ctx.memory.calibration is not None
        node = ctx.roadmap.node(ctx.memory.pallet_node)
        spec = entry_volume_at(ctx, pallet_pose_at_node(node.pose, node.height).to_se2())
        frame = self.frames[-1][0] if self.frames else None
        self._restart(ctx)
        if spec is None or frame is None:
            return False
        look = ctx.perception.check_volume(frame, ctx.memory.calibration, spec[0])
        if not (look.occupied and look.seen >= MIN_SEEN):
            return False
        now = ctx.now()
        if self.blocked_since is None:
            self.blocked_since = now
            ctx.log("entry_blocked", what="the pallet's entry volume", why="no pallet seen past it", **look.to_json())
        if now - self.blocked_since >= ctx.settings.blocked_wait_s:
            raise TaskFailed(
                PATH_BLOCKED,
                f"the pallet's entry volume is not free after {now - self.blocked_since:.0f} s: the camera sees "
                f"{look.points} points of an object {look.nearest_x_m:.2f} m ahead, and no pallet past it",
            )
        self.look_at = now + RECHECK_S
        return True

    def _judge(self, ctx: Context, est: PalletEstimate, stood: SE2) -> str:
        """`aligned` or `misaligned` for the fused estimate `est`, the truck having stood at `stood` (world)."""
        assert est.T_world_pallet is not None
        _check_envelope(ctx, est.T_world_pallet.to_se2(), ctx.memory.estimated_pallet)
        ctx.memory.estimate, ctx.memory.estimated_pallet = est, est.T_world_pallet
        node = ctx.roadmap.node(ctx.memory.pallet_node)
        al = check_alignment(est.T_world_pallet, node, pickup_tolerances(ctx), est.spread)  # offsets + 2 stated sigmas
        world = est.T_world_pallet.to_se2()
        # Where the truck stands matters too: the forks enter from there, and `SafetyCheck` refuses a stance
        # that puts a fork beside its pocket. Judged from the mean of the frames' localization fixes (one
        # fix is noisier).
        ctx.memory.stance = stood
        stance = forks_outside_pockets(ctx, world, stood) if al.aligned else []
        entry: dict[str, Any] = {
            "problems": list(al.problems),
            "stance_problems": stance,
            "attempt": ctx.memory.attempts,
            "against_node": ctx.memory.pallet_node,
            "T_world_pallet": {
                "x_m": round(world.x, 4),
                "y_m": round(world.y, 4),
                "yaw_deg": round(math.degrees(world.yaw), 3),
            },
            "lateral_mm": round(al.lateral_m * 1e3, 1),
            "longitudinal_mm": round(al.longitudinal_m * 1e3, 1),
            "yaw_deg": round(math.degrees(al.yaw_rad), 3),
            "uncertainty_mm_mm_deg": [
                round(al.uncertainty[0] * 1e3, 1),
                round(al.uncertainty[1] * 1e3, 1),
                round(math.degrees(al.uncertainty[2]), 3),
            ],
            "aligned": al.aligned,
        }
        ctx.memory.record.setdefault("estimates", []).append(entry)
        ctx.log("pallet_estimate", **entry)
        if al.aligned and stance and ctx.settings.adapt and ctx.memory.attempts < ctx.settings.max_attempts:
            return "misaligned"  # the pallet is where the node says, the truck is not: back off and approach again
        if al.aligned:
            return "aligned"
        if not ctx.settings.adapt:  # `--no-adapt`: no re-plan, so never entered as it stands
            raise TaskFailed(
                SAFETY_CHECK_FAILED,
                "without adaptation (--no-adapt) the truck does not re-plan, and the forks do not fit the pallet "
                f"as it stands ({entry['lateral_mm']} mm lateral, {entry['longitudinal_mm']} mm along, "
                f"{entry['yaw_deg']} deg off node '{ctx.memory.pallet_node}'): " + "; ".join(al.problems),
            )
        if ctx.memory.attempts >= ctx.settings.max_attempts:
            raise TaskFailed(
                STILL_MISALIGNED,
                f"pallet still off after {ctx.memory.attempts} estimates: {entry['lateral_mm']} mm lateral, "
                f"{entry['longitudinal_mm']} mm along, {entry['yaw_deg']} deg",
            )
        return "misaligned"

    def stop(self, ctx: Context) -> None:
        if self.job is not None:
            self.job.cancel()


STANCE_FIXES = 5
"""Localization fixes (one a tick, standing) whose mean `SafetyCheck` takes for the truck's stance, unless
the estimate's own (`TaskMemory.stance`) is still where the truck stands: within `STANCE_SAME_M` and
`STANCE_SAME_DEG` of a fix (the localization's noise; it has not moved)."""
STANCE_SAME_M = 0.02
STANCE_SAME_DEG = 0.5


def _mean_pose(poses: list[SE2]) -> SE2:
    """The mean of poses taken standing (world): x and y averaged, the yaw by its mean direction."""
    yaw = math.atan2(sum(math.sin(p.yaw) for p in poses), sum(math.cos(p.yaw) for p in poses))
    return SE2(sum(p.x for p in poses) / len(poses), sum(p.y for p in poses) / len(poses), yaw)


def _frame_policy(ctx: Context) -> FramePolicy:
    """The Settings' frames per estimate as a `FramePolicy`."""
    st = ctx.settings
    per = max(1, st.frames_per_estimate)
    return FramePolicy(per, max(per, st.max_frames_per_estimate), math.radians(st.estimate_yaw_sigma_deg))


def _expected_pallet(ctx: Context) -> SE2:
    """Where this pickup's pallet is expected (`T_world_pallet`, world): the previous estimate, else the
    pallet node's nominal pose. Perception fits only the pallet instance standing there."""
    if ctx.memory.estimated_pallet is not None:
        return ctx.memory.estimated_pallet.to_se2()
    node = ctx.roadmap.node(ctx.memory.pallet_node)
    return pallet_pose_at_node(node.pose, node.height).to_se2()


def _check_envelope(ctx: Context, pallet: SE2, previous: SE3 | None) -> None:
    """The estimated pallet (`T_world_pallet`, SE2) must be the mission's: inside the envelope of the task's
    node (`Settings.envelope_*`, with `envelope_tolerance*` for the estimate's error at its edge) and where
    the previous estimate of this pickup saw it; else `pallet_not_found` with the figures, and nothing is
    re-planned towards it."""
    st = ctx.settings
    node = ctx.roadmap.node(ctx.memory.node_task().node)
    nominal = pallet_pose_at_node(node.pose, node.height).to_se2()
    off = nominal.inv() @ pallet
    yaw_deg = math.degrees(off.yaw)
    lateral, along = st.envelope_lateral + st.envelope_tolerance, st.envelope_longitudinal + st.envelope_tolerance
    if abs(off.y) > lateral or abs(off.x) > along or abs(yaw_deg) > st.envelope_yaw_deg + st.envelope_tolerance_deg:
        raise TaskFailed(
            PALLET_NOT_FOUND,
            f"the pallet seen stands {off.y:+.2f} m to the side, {off.x:+.2f} m along and {yaw_deg:+.1f} deg off "
            f"node '{node.id}' (envelope +-{st.envelope_lateral:.2f} m, +-{st.envelope_longitudinal:.2f} m, "
            f"+-{st.envelope_yaw_deg:.0f} deg): not the mission's pallet",
        )
    if previous is not None:
        jump = previous.to_se2().distance_to(pallet)
        if jump > st.estimate_jump:
            raise TaskFailed(
                PALLET_NOT_FOUND,
                f"the pallet estimate jumped {jump:.2f} m from the previous one (limit {st.estimate_jump:.2f} m): "
                "another object, not the pallet seen before",
            )


def approach_curve(ctx: Context, spec: TemporaryNodes) -> Curve:
    """The forward curve from `spec.before` (the truck heading `spec.heading` there) to the new pre-pallet
    pose under the vehicle's curvature limit; `RoadmapError` says why there is none."""
    before = ctx.roadmap.node(spec.before)
    return connect(SE2(before.pose.x, before.pose.y, spec.heading), spec.pre_pose, ctx.params.max_curvature)


def add_temporary_nodes(ctx: Context, spec: TemporaryNodes, curve: Curve | None = None) -> list[Edge]:
    """Add a re-plan's temporary pallet and pre-pallet nodes and their edges to the task's overlay; the
    edges added (the approach curve `spec.before` <-> new pre-pallet node, and the straight entry).

    `curve`: the approach curve when the caller made it already (`approach_curve`). Raises
    `TaskFailed(no_feasible_approach)` when no drivable curve joins `spec.before` to the new pre-pallet
    node. Used by `Replan` and, with the journalled record, by a resume: the same record, the same graph.
    """
    assert ctx.memory.overlay is not None
    original = ctx.roadmap.node(ctx.memory.node_task().node)
    original_pre = ctx.roadmap.node(ctx.roadmap.pre_pallet_of(ctx.memory.node_task().node))
    if curve is None and spec.manoeuvre is None:
        try:
            curve = approach_curve(ctx, spec)
        except RoadmapError as exc:
            raise TaskFailed(
                NO_FEASIBLE_APPROACH, f"no feasible approach to the estimated pallet from '{spec.before}': {exc}"
            ) from None
    ov = ctx.memory.overlay
    ov.add_node(Node(spec.pre, NodeType.PRE_PALLET, spec.pre_pose))
    ov.add_node(Node(spec.pallet, NodeType.PALLET, spec.pallet_pose, height=original.height, pre_pallet=spec.pre))
    entry_speed = ctx.roadmap.edge(original_pre.id, original.id).speed_limit
    if curve is not None:
        edges = [
            ov.add_edge(Edge(spec.before, spec.pre, curve, Direction.FORWARD, 0.5)),
            ov.add_edge(Edge(spec.pre, spec.before, curve.reversed(), Direction.REVERSE, 0.5)),
        ]
    else:
        edges = add_manoeuvre_edges(ctx, spec)
    edges += [
        ov.add_edge(ctx.roadmap.line_edge(spec.pre, spec.pallet, Direction.FORWARD, entry_speed)),
        ov.add_edge(ctx.roadmap.line_edge(spec.pallet, spec.pre, Direction.REVERSE, entry_speed)),
    ]
    ctx.memory.temporary.append(spec)
    ctx.log(
        "replanned",
        pallet=spec.pallet,
        pre_pallet=spec.pre,
        curve=curve.kind if curve is not None else "manoeuvre",
        joined_to=spec.before,
        via=list(spec.back_path),
    )
    return edges


def nodes_back(ctx: Context, start: str, heading: float, limit: int) -> list[tuple[str, float, tuple[str, ...]]]:
    """Up to `limit` nodes to join a re-plan's new pre-pallet node to, nearest first: `start` (the node the
    truck backed off to, where it heads `heading`, rad), then nodes further back. Each as (node, the truck's
    heading there, the nodes it backs along from `start` to it, both included).

    A step back from a node goes to the node before it on the route that reached the task's pre-pallet
    node (`ctx.memory.route_to_pre`), else to a roadmap predecessor joined to it both ways; always along an edge
    driven in reverse that leaves with the truck's heading, never to a pallet, drop or temporary node.
    """
    path: tuple[str, ...] = (start,)
    out = [(start, heading, path)]
    if start not in ctx.roadmap:
        return out
    seen = {
        start,
        ctx.memory.pre_node,
        ctx.memory.node_task().node,
        ctx.roadmap.pre_pallet_of(ctx.memory.node_task().node),
    }
    here, yaw = start, heading
    while len(out) < limit:
        step = _step_back(ctx, here, yaw, seen)
        if step is None:
            break
        here, yaw, path = step.end, step.yaw_end, (*path, step.end)
        seen.add(here)
        out.append((here, yaw, path))
    return out


def _step_back(ctx: Context, here: str, heading: float, seen: set[str]) -> Edge | None:
    """The reverse edge from `here` one node further back (see `nodes_back`), or None."""
    graph, route = ctx.roadmap.graph, ctx.memory.route_to_pre
    on_route = [route[i - 1] for i in range(1, len(route)) if route[i] == here]
    for u in [*on_route, *(p for p in graph.predecessors(here) if p not in on_route)]:
        if u in seen or u not in graph or not (graph.has_edge(here, u) and graph.has_edge(u, here)):
            continue
        node = ctx.roadmap.node(u)
        if node.temporary or node.type in (NodeType.PALLET, NodeType.DROP):
            continue
        edge = ctx.roadmap.edge(here, u)
        same_heading = abs(angle_diff(edge.yaw_start, heading)) <= 2 * TANGENT_TOLERANCE_RAD
        if edge.direction is Direction.REVERSE and same_heading:
            return edge
    return None


def approach_route(ctx: Context) -> Route:
    """The approach to a re-plan's new pre-pallet node: from where the truck stands, back along the roadmap
    to the node the new node is joined to (when that lies further back), then forward along the new curve."""
    spec = (
        ctx.memory.temporary[-1]
        if ctx.memory.temporary and ctx.memory.temporary[-1].pre == ctx.memory.pre_node
        else None
    )
    if spec is None:
        nodes = [ctx.memory.node_before or "", ctx.memory.pre_node]
    else:
        path = [*spec.back_path, *manoeuvre_nodes(spec)]
        first = path.index(ctx.memory.at_node) if ctx.memory.at_node in path else 0
        nodes = [*path[first:], spec.pre]
    return Route(nodes, [ctx.roadmap.edge(a, b) for a, b in itertools.pairwise(nodes)])


class Replan(Behaviour):
    """Add temporary pallet and pre-pallet nodes from the estimate, joined by a drivable curve to the node
    the truck backed off to or, when no curve fits from there, to a node further back along the route
    (`nodes_back`, at most `Settings.replan_back_nodes` nodes tried); the approach then backs the truck
    to that node first (`approach_route`), and the return to the roadmap leaves through it. When no node
    gives a curve, a manoeuvre from the node the truck backed off to (`executor.core.manoeuvre`, planned
    off the loop); when none fits either, `no_feasible_approach` saying what was tried."""

    def start(self, ctx: Context) -> None:
        self.job: Job[Manoeuvre] | None = None
        self.spec: TemporaryNodes | None = None
        self.failures: list[str] = []

    def update(self, ctx: Context) -> str | None:
        if self.job is None:
            return self._curves(ctx)
        if not self.job.poll(ctx.clock_now()):
            return None
        job, self.job = self.job, None
        assert self.spec is not None
        spec = with_manoeuvre(ctx, self.spec, job, self.failures)  # or `no_feasible_approach`
        self._add(ctx, spec, None, tried=len(self.failures) + 1)
        return "done"

    def _curves(self, ctx: Context) -> str | None:
        """Try one curve from each node back; else start the manoeuvre's search (None while it runs)."""
        assert ctx.memory.estimated_pallet is not None and ctx.memory.overlay is not None
        original = ctx.roadmap.node(ctx.memory.node_task().node)
        original_pre = ctx.roadmap.node(ctx.roadmap.pre_pallet_of(ctx.memory.node_task().node))
        standoff = original.pose.distance_to(original_pre.pose)
        new_pallet_pose = rack_limited_pose(ctx, node_pose_for_pallet(ctx.memory.estimated_pallet))
        k = ctx.memory.attempts
        limit = max(1, ctx.settings.replan_back_nodes)
        specs = []
        for before, heading, path in nodes_back(ctx, ctx.memory.node_before or "", ctx.memory.heading, limit):
            spec = TemporaryNodes(
                k=k,
                pallet=f"{ctx.memory.node_task().node}~{k}",
                pre=f"{original_pre.id}~{k}",
                pallet_pose=new_pallet_pose,
                pre_pose=new_pallet_pose @ SE2(-standoff, 0.0, 0.0),
                before=before,
                heading=heading,
                via=path if len(path) > 1 else (),
            )
            specs.append(spec)
            try:
                curve = approach_curve(ctx, spec)
                check_curve_clear(ctx, spec, curve, ctx.memory.estimated_pallet.to_se2())  # the static obstacles
            except RoadmapError as exc:
                self.failures.append(f"from '{before}': {exc}")
                ctx.log("approach_infeasible", node=before, error=str(exc))
                continue
            self._add(ctx, spec, curve, tried=len(self.failures) + 1)
            return "done"
        self.spec = specs[0]  # the node the truck stands at: the manoeuvre starts there
        plan = manoeuvre_planner(ctx, self.spec, ctx.memory.estimated_pallet.to_se2())
        self.job = ctx.jobs.submit("manoeuvre", plan)
        return None

    @staticmethod
    def _add(ctx: Context, spec: TemporaryNodes, curve: Curve | None, tried: int) -> None:
        edges = add_temporary_nodes(ctx, spec, curve)
        ctx.memory.pallet_node, ctx.memory.pre_node, ctx.memory.node_before = spec.pallet, spec.pre, spec.before
        pose = spec.pallet_pose
        entry: dict[str, Any] = {
            "pallet": spec.pallet,
            "pre_pallet": spec.pre,
            "x_m": round(pose.x, 4),
            "y_m": round(pose.y, 4),
            "yaw_deg": round(math.degrees(pose.yaw), 3),
            "joined_to": spec.before,
            "nodes_tried": tried,
            "backs_along": list(spec.back_path),
            "curve": curve.kind if curve is not None else "manoeuvre",
            "edges": [e.name for e in edges],
            **manoeuvre_record(spec),
        }
        ctx.memory.record.setdefault("temporary_nodes", []).append(entry)


class SafetyCheck(Behaviour):
    """Both fork-tip beams must pass through the pockets: never enter when one stops at the pallet. With an
    estimate, the forks must also lie in the pockets from where the truck stands: the stance the estimate
    was judged from, while the truck is still there, else the mean of `STANCE_FIXES` localization fixes
    taken standing (one fix's noise alone could refuse a good stance)."""

    def start(self, ctx: Context) -> None:
        ctx.vehicle.stop()
        self.fixes: list[SE2] = []
        stood, here = ctx.memory.stance, ctx.vehicle.localization()
        if (
            stood is not None
            and here.distance_to(stood) < STANCE_SAME_M
            and abs(angle_diff(here.yaw, stood.yaw)) < math.radians(STANCE_SAME_DEG)
        ):
            self.fixes = [stood] * STANCE_FIXES  # the estimate's own stance: both checks judge the same pose

    def update(self, ctx: Context) -> str | None:
        if ctx.memory.estimated_pallet is not None and len(self.fixes) < STANCE_FIXES:
            self.fixes.append(ctx.vehicle.localization())
            if len(self.fixes) < STANCE_FIXES:
                return None
        pre = ctx.roadmap.node(ctx.memory.pre_node)
        pallet = ctx.roadmap.node(ctx.memory.pallet_node)
        face = pre.pose.distance_to(pallet.pose) + ENTRY_GAP_M - ctx.forks.tip_x  # tips to the entry face
        need = face + ctx.pallet_type.length - ctx.settings.beam_margin
        left, right = ctx.vehicle.proximity_ranges()
        ctx.log("safety_check", left_m=round(left, 3), right_m=round(right, 3), need_m=round(need, 3))
        if left < need or right < need:
            raise TaskFailed(
                SAFETY_CHECK_FAILED,
                f"proximity beams blocked: left {left:.2f} m, right {right:.2f} m, a pocket passes beyond {need:.2f} m",
            )
        # A clear beam may also pass beside the pallet: with an estimate, each fork must lie in its pocket,
        # and at the pallet node the forks must carry the pallet type's minimum engagement (its balance).
        if ctx.memory.estimated_pallet is not None:
            T_world_pallet = ctx.memory.estimated_pallet.to_se2()
            problems = forks_outside_pockets(ctx, T_world_pallet, _mean_pose(self.fixes))
            at_node = T_world_pallet.inv() @ pallet.pose
            problems += engagement_problems(ctx.forks, ctx.pallet_type, at_node, margin=0.0)
            if problems:
                raise TaskFailed(SAFETY_CHECK_FAILED, "; ".join(problems))
        return "done"
