"""What every state's behaviour shares: the executor settings, the task context and the `Behaviour` base.

A behaviour works in the py_trees manner: `start(ctx)` once, `update(ctx)` every control tick returning
`None` (running) or a trigger name (`done`, `aligned`, `misaligned`, `fail`), `stop(ctx)` on leaving,
`resume(ctx)` after a pause. Nothing in `update` may block: long work goes to `ctx.jobs`.

`Context` splits in two: the run's injected dependencies (vehicle, perception, roadmap, planner, ...:
frozen) and its `TaskMemory` (where the truck stands, the current task's scratch), which the journal
stores at every checkpoint (`TaskMemory.to_json`, `executor.core.resume`).

Public API: `Settings`, `Context`, `TaskMemory`, `JOURNALLED`, `NOT_JOURNALLED`, `Behaviour`,
`TemporaryNodes`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any, TypeVar

import numpy as np

from palletpilot.control.follower import Follower
from palletpilot.control.vehicle import VehicleParams
from palletpilot.executor.core.jobs import Jobs
from palletpilot.executor.core.mission import ChargeTask, DeliveryTask, MoveTask, PickupTask, Task
from palletpilot.executor.ports import PerceptionService, VehiclePort
from palletpilot.geometry import SE2, SE3
from palletpilot.perception.calibration_io import Calibration, MountTolerance
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.pallet import PalletEstimate
from palletpilot.perception.specs import ForkGeometry, PalletType
from palletpilot.roadmap import Overlay, Planner, Roadmap
from palletpilot.roadmap.manoeuvre import Manoeuvre
from palletpilot.roadmap.planner import Route


@dataclass(frozen=True)
class TemporaryNodes:
    """Temporary pallet and pre-pallet nodes of a re-plan (world frame, m and rad), joined to `before`.

    `heading` is the forklift's yaw at `before` when the curve was made; the same record rebuilds the
    same nodes and curves on a resume. `via`: the roadmap nodes the truck backs along to reach `before`,
    from the node it backed off to (first) to `before` (last); empty means `before` alone. `manoeuvre`: the
    forward and reverse moves from `before` to the pre-pallet node when no single curve joins them
    (`executor.core.manoeuvre`).
    """

    k: int
    pallet: str
    pre: str
    pallet_pose: SE2
    pre_pose: SE2
    before: str
    heading: float
    via: tuple[str, ...] = ()
    manoeuvre: Manoeuvre | None = None

    @property
    def back_path(self) -> tuple[str, ...]:
        """The nodes from where the truck backed off to `before`, both included (`(before,)` at least)."""
        return self.via or (self.before,)

    def to_json(self) -> dict[str, Any]:
        """Plain JSON (poses as [x, y, yaw])."""
        p, q = self.pallet_pose, self.pre_pose
        return {
            "k": self.k,
            "pallet": self.pallet,
            "pre": self.pre,
            "pallet_pose": [p.x, p.y, p.yaw],
            "pre_pose": [q.x, q.y, q.yaw],
            "before": self.before,
            "heading": self.heading,
            "via": list(self.via),
            "manoeuvre": self.manoeuvre.to_json() if self.manoeuvre is not None else None,
        }

    @classmethod
    def from_json(cls, doc: dict[str, Any]) -> TemporaryNodes:
        """The inverse of `to_json`."""
        return cls(
            int(doc["k"]),
            str(doc["pallet"]),
            str(doc["pre"]),
            SE2(*map(float, doc["pallet_pose"])),
            SE2(*map(float, doc["pre_pose"])),
            str(doc["before"]),
            float(doc["heading"]),
            tuple(str(n) for n in doc.get("via", ())),
            Manoeuvre.from_json(doc["manoeuvre"]) if doc.get("manoeuvre") else None,
        )


@dataclass(frozen=True)
class Settings:
    """Executor parameters (m, s, rad), immutable: a variant is `dataclasses.replace(settings, ...)`."""

    max_attempts: int = 3  # pallet estimates per pickup (the first one and the re-plans)
    # Alignment tolerances come from the fork and pocket geometry (`perception.alignment`), less these
    # margins for localization and control errors.
    lateral_margin: float = 0.010
    longitudinal_margin: float = 0.010
    yaw_limit_deg: float = 2.0
    fork_clearance: float = 0.025  # fork bottoms above the pallet's underside when entering
    lift_delta: float = 0.08  # lift above the entry height to carry
    calibration_retries: int = 1
    # A calibration with an untrusted axis (x from fork tips it cannot trust) keeps that axis from the last
    # trusted calibration of this truck only when its trusted axes agree with that one within these (m, deg;
    # `perception.calibration_io.mount_moved`); else the Pickup refuses (`CalibrateCamera`).
    calibration_mount_tolerance_m: float = MountTolerance.translation_m
    calibration_mount_tolerance_deg: float = MountTolerance.angle_deg
    frames_per_estimate: int = 3  # the pallet stands still: averaging frames (and localization fixes) cuts noise
    # ... and rounds of that many more while the fused yaw 1-sigma is above `estimate_yaw_sigma_deg`, up to
    # `max_frames_per_estimate` frames (`perception.pallet.FramePolicy`): a far loaded face is never judged
    # on three uncertain frames.
    max_frames_per_estimate: int = 9
    estimate_yaw_sigma_deg: float = 0.25
    beam_margin: float = 0.10  # a clear beam reaches this far short of the pallet's back, at least
    # Re-plan: when no drivable curve joins the node the truck backed off to and the new pre-pallet node,
    # try nodes further back along the route that reached the pre-pallet node: this many nodes in all.
    replan_back_nodes: int = 3
    # After a failed task, leave for the nearest parking node (the mission's `return_on_failure` decides;
    # this is the default when the mission says nothing).
    return_on_failure: bool = False
    # False (`--no-adapt`): no re-plan; the camera still calibrates, estimates and checks the entry, and a
    # pallet the forks do not fit as it stands is refused (`safety_check_failed`).
    adapt: bool = True
    # With `adapt` False: the paper's original Pickup, beams only, no camera. A baseline for `bench missions`
    # alone: no command that drives a truck (run, robot, agv) sets it.
    paper_baseline: bool = False
    # The mission's pallet stands within this envelope of its node (m, m, deg); an estimate outside it is
    # another pallet or object (`pallet_not_found`), never a reason to re-plan there. Between two estimates
    # of one pickup the pallet does not move: a jump beyond `estimate_jump` (m) is another object too.
    envelope_lateral: float = 0.40
    envelope_longitudinal: float = 0.40
    envelope_yaw_deg: float = 15.0
    # A pallet placed at the envelope's edge is estimated a few cm or under a degree past it: the check allows
    # this much beyond the envelope (m, deg), far short of a neighbour (1.0 m in a lane).
    envelope_tolerance: float = 0.03
    envelope_tolerance_deg: float = 1.0
    estimate_jump: float = 0.15
    # At a rack node (height > 0) the truck's heels go at most this far past the node along its heading:
    # further, the mast meets the rack's front beam. A pallet standing deeper is entered only this far.
    rack_overrun: float = 0.10
    # A protective stop of the safety scanners, or something in the entry volume, holds the task this long
    # (s) before it fails with `path_blocked` (an occupied drop slot: `slot_occupied`).
    blocked_wait_s: float = 30.0
    # Simulated clocks only: how long perception takes in simulated time (s), per call / per frame.
    calibration_latency_s: float = 0.3
    estimate_latency_s: float = 0.1


T = TypeVar("T")

JournalDoc = dict[str, Any]
"""A checkpoint's plain JSON (the journal's `ctx`)."""

JOURNALLED = (
    "at_node",
    "heading",
    "attempts",
    "pallet_node",
    "pre_node",
    "node_before",
    "route_to_pre",
    "calibration",
    "estimated_pallet",
    "temporary",
)
"""The `TaskMemory` fields a checkpoint stores (`TaskMemory.to_json`), in the journal's order."""

NOT_JOURNALLED = {
    "task": "the checkpoint's task index names it in the mission",
    "overlay": "the task's overlay is reopened and the temporary nodes added again",
    "last_route": "re-planned by the state that needs it",
    "estimate": "a resumed state estimates again (the fused pose is journalled: estimated_pallet)",
    "record": "journalled with the task's result (the checkpoint's `current`)",
    "last_motion_s": "the checkpoint's time: nothing moved since",
    "trusted_calibration": "a resumed run trusts anew (or perception's last good calibration seeds it)",
    "planned_paths": "journalled as the checkpoint's `planned`, each path once",
    "stance": "a resumed safety check takes its own localization fixes",
}
"""Why each other `TaskMemory` field is not in a checkpoint's `ctx` (rebuilt or stored elsewhere)."""


def _se3_json(T: SE3 | None) -> list[list[float]] | None:
    return None if T is None else np.asarray(T.matrix).tolist()


def _se3(doc: Any) -> SE3 | None:
    return None if doc is None else SE3.from_matrix(np.asarray(doc, dtype=float))


@dataclass
class TaskMemory:
    """What the run and its current task remember between ticks, the part of a run a checkpoint stores
    (`to_json`, `JOURNALLED`; the rest is rebuilt on a resume: `NOT_JOURNALLED`). World frame, m and rad.

    Run-scoped: where the truck stands on the roadmap (`at_node`, `heading`), when it last moved, the
    trusted calibration, the paths planned. Task-scoped: the rest, reset by `start_task`.
    """

    at_node: str
    heading: float
    last_motion_s: float = 0.0  # clock time (s) the vehicle or its forks last moved
    # The newest calibration whose every axis was measured and trusted, and where it came from;
    # `CalibrateCamera` keeps untrusted axes from it (never reset between tasks).
    trusted_calibration: tuple[Calibration, str] | None = None
    planned_paths: list[list[tuple[float, float]]] = field(default_factory=list)
    # Task-scoped:
    task: Task | None = None
    overlay: Overlay | None = None
    pallet_node: str = ""
    pre_node: str = ""
    node_before: str | None = None
    last_route: Route | None = None
    # The nodes of the route that reached the task's own pre-pallet node (ending there): re-plans back
    # along it.
    route_to_pre: list[str] = field(default_factory=list)
    attempts: int = 0
    calibration: Calibration | None = None
    estimate: PalletEstimate | None = None
    estimated_pallet: SE3 | None = None  # T_world_pallet of the last fused estimate (the re-plan's input)
    stance: SE2 | None = None  # where the truck stood for that estimate (world: its frames' mean fix)
    temporary: list[TemporaryNodes] = field(default_factory=list)
    record: dict[str, Any] = field(default_factory=dict)

    def start_task(self, task: Task) -> None:
        """A new task: no attempts, calibration, estimate or temporary nodes yet (the rest carries over)."""
        self.task, self.attempts, self.calibration, self.estimate, self.estimated_pallet = task, 0, None, None, None
        self.temporary, self.route_to_pre, self.stance = [], [], None

    def task_of(self, kind: type[T]) -> T:
        """The current task, a `kind`; `TypeError` for any other (a bug: an internal error)."""
        task = self.task
        if not isinstance(task, kind):
            raise TypeError(f"the current task ({type(task).__name__}) is no {kind.__name__}")
        return task

    def node_task(self) -> PickupTask | DeliveryTask | MoveTask | ChargeTask:
        """The current task, one that goes to a node; `TypeError` for any other (a bug: an internal error)."""
        task = self.task
        if not isinstance(task, PickupTask | DeliveryTask | MoveTask | ChargeTask):
            raise TypeError(f"the current task ({type(task).__name__}) goes to no node")
        return task

    def load_task(self) -> PickupTask | DeliveryTask:
        """The current task, a Pickup or a Delivery; `TypeError` for any other (a bug: an internal error)."""
        task = self.task
        if not isinstance(task, PickupTask | DeliveryTask):
            raise TypeError(f"the current task ({type(task).__name__}) handles no load")
        return task

    def to_json(self) -> JournalDoc:
        """The `JOURNALLED` fields as plain JSON (poses as 4x4 matrices, temporary nodes as their records)."""
        cal = self.calibration
        return {
            "at_node": self.at_node,
            "heading": self.heading,
            "attempts": self.attempts,
            "pallet_node": self.pallet_node,
            "pre_node": self.pre_node,
            "node_before": self.node_before,
            "route_to_pre": self.route_to_pre,
            "calibration": None
            if cal is None
            else {"T": _se3_json(cal.T_forklift_camera), "method": cal.method, "quality": cal.quality},
            "estimated_pallet": _se3_json(self.estimated_pallet),
            "temporary": [t.to_json() for t in self.temporary],
        }

    def restore_position(self, doc: JournalDoc) -> None:
        """Where the truck stood at a checkpoint (`to_json`'s `at_node`, `heading`)."""
        self.at_node, self.heading = str(doc["at_node"]), float(doc["heading"])

    def restore_task(self, doc: JournalDoc) -> list[TemporaryNodes]:
        """The task-scoped fields of a checkpoint (`to_json`) but the temporary nodes, which are returned
        for the caller to add back to the roadmap's overlay (`temporary` is left empty); no estimate."""
        self.attempts = int(doc["attempts"])
        self.pallet_node, self.pre_node = str(doc["pallet_node"]), str(doc["pre_node"])
        self.node_before = doc["node_before"]
        self.route_to_pre = [str(n) for n in doc.get("route_to_pre", [])]
        cal = doc["calibration"]
        self.calibration = (
            None if cal is None else Calibration(_se3(cal["T"]), str(cal["method"]), dict(cal["quality"]))  # type: ignore[arg-type]
        )
        self.estimated_pallet = _se3(doc["estimated_pallet"])
        self.estimate = None
        self.temporary = []
        return [TemporaryNodes.from_json(spec) for spec in doc["temporary"]]


@dataclass(frozen=True)
class Context:
    """What a behaviour is given: the run's injected dependencies (frozen; the runner gives each task its
    `pallet_type` with `dataclasses.replace`) and `memory`, what the run and the task remember."""

    vehicle: VehiclePort
    perception: PerceptionService | None
    roadmap: Roadmap
    planner: Planner
    follower: Follower
    params: VehicleParams
    forks: ForkGeometry
    pallet_type: PalletType  # the current task's pallet (the mission's)
    settings: Settings
    now: Callable[[], float]  # task time (s): the clock less the time spent paused
    log: Callable[..., None]
    jobs: Jobs
    clock_now: Callable[[], float]  # the clock (s), for frame stamps and perception jobs
    # A fresh camera frame (stamped, checked by the watchdog), or None when none is available this tick.
    frame: Callable[[], FrameBundle | None]
    memory: TaskMemory


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

    def resume(self, ctx: Context) -> None:
        """Continue after a pause (the runner stopped the vehicle and held the forks meanwhile)."""
