"""What every state's behaviour shares: the executor settings, the task context and the `Behaviour` base.

A behaviour works in the py_trees manner: `start(ctx)` once, `update(ctx)` every control tick returning
`None` (running) or a trigger name (`done`, `aligned`, `misaligned`, `fail`), `stop(ctx)` on leaving,
`resume(ctx)` after a pause. Nothing in `update` may block: long work goes to `ctx.jobs`.

Public API: `Settings`, `Context`, `Behaviour`, `TemporaryNodes`.
"""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass, field
from typing import Any

from palletpilot.control.follower import Follower
from palletpilot.control.vehicle import VehicleParams
from palletpilot.executor.core.jobs import Jobs
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


@dataclass
class Context:
    """Everything a behaviour may use, and what it records for the report."""

    vehicle: VehiclePort
    perception: PerceptionService | None
    roadmap: Roadmap
    planner: Planner
    follower: Follower
    params: VehicleParams
    forks: ForkGeometry
    pallet_type: PalletType
    settings: Settings
    now: Callable[[], float]  # task time (s): the clock less the time spent paused
    log: Callable[..., None]
    at_node: str
    heading: float
    jobs: Jobs
    clock_now: Callable[[], float]  # the clock (s), for frame stamps and perception jobs
    # A fresh camera frame (stamped, checked by the watchdog), or None when none is available this tick.
    frame: Callable[[], FrameBundle | None]
    last_motion_s: float = 0.0  # clock time (s) the vehicle or its forks last moved
    # Task-scoped (reset per task):
    task: Any = None
    overlay: Overlay | None = None
    pallet_node: str = ""
    pre_node: str = ""
    node_before: str | None = None
    last_route: Route | None = None
    # The nodes of the route that reached the task's own pre-pallet node (ending there): re-plans back
    # along it (journalled).
    route_to_pre: list[str] = field(default_factory=list)
    attempts: int = 0
    calibration: Calibration | None = None
    # Run-scoped: the newest calibration whose every axis was measured and trusted, and where it came
    # from; `CalibrateCamera` keeps untrusted axes from it (never reset between tasks).
    trusted_calibration: tuple[Calibration, str] | None = None
    estimate: PalletEstimate | None = None
    estimated_pallet: SE3 | None = None  # T_world_pallet of the last fused estimate (the re-plan's input)
    temporary: list[TemporaryNodes] = field(default_factory=list)
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

    def resume(self, ctx: Context) -> None:
        """Continue after a pause (the runner stopped the vehicle and held the forks meanwhile)."""
