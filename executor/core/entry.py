"""Before the forks go in: the entry volume of a pallet and the volume of a drop slot must be free.

The narrow field set of the safety scanners mutes the corridor where the forks and the pallet go, so
before entering, the truck looks there itself: the camera's depth points inside the volume
(`perception.clearance.check_volume`, forklift frame at the standpoint) and, where the camera cannot
see it (a carried load hides a drop slot from a carriage camera), the fork-tip beams, which must reach
past the volume's far end. Something there holds the task: the check repeats every
`RECHECK_S` while the truck stands, and after `Settings.blocked_wait_s` the task fails, `path_blocked`
before a pickup, `slot_occupied` before a delivery. Nothing has moved by then.

A pallet of a family (`perception.pallet_family`: its pockets vary within ranges) is entered only where
the forks fit the pockets the estimate *measured* (`pocket_fit_problems`, `entry_pocket_fit`: each fork
`POCKET_SIDE_MARGIN_M` inside its pocket at the entry face and at the tips' depth, the fork tops
`POCKET_TOP_CLEARANCE_M` under the pocket top); else `safety_check_failed` with the figures, before any
move. `CheckVolume(..., fit=entry_pocket_fit)` runs it first.

Public API: `CheckVolume`, `entry_volume`, `entry_volume_at`, `slot_volume`, `pocket_fit_problems`,
`entry_pocket_fit`, `RECHECK_S`, `MIN_SEEN`, `POCKET_SIDE_MARGIN_M`, `POCKET_TOP_CLEARANCE_M`.
"""

from __future__ import annotations

import math
from collections.abc import Callable

from palletpilot.executor.core.behaviour import Behaviour, Context
from palletpilot.executor.core.calibration_trust import calibration_for_checks
from palletpilot.executor.core.errors import SAFETY_CHECK_FAILED, Reason, TaskFailed
from palletpilot.geometry import SE2
from palletpilot.perception.clearance import Volume, VolumeCheck
from palletpilot.perception.pallet import PalletEstimate
from palletpilot.perception.specs import ENTRY_GAP_M, ForkGeometry, PalletType, pallet_pose_at_node

RECHECK_S = 1.0
"""s between two looks while the volume is not free."""

MIN_SEEN = 0.5
"""The camera must see at least this share of a volume for its check to count."""

_STANDING = 1e-3  # m/s

POCKET_SIDE_MARGIN_M = 0.010
"""Each fork's sides must stay this far (m) inside its measured pocket (localization and control errors)."""
POCKET_TOP_CLEARANCE_M = 0.010
"""The fork tops must pass this far (m) under the measured pocket top (the deck sags under a load)."""


def _half_corridor(ctx: Context) -> float:
    scanner = ctx.params.safety_scanner
    return scanner.mute_half_width if scanner is not None else 0.5 * ctx.pallet_type.width + 0.05


def entry_volume(ctx: Context) -> tuple[Volume, float] | None:
    """The pickup's entry volume in the forklift frame: from the fork tips to just short of the estimated
    entry face, the muted corridor wide, from the floor (or the fork bottoms) to the backrest's top;
    with the beams' far limit (m from the tips). None without an estimate or with no room to check."""
    if ctx.memory.estimated_pallet is None:
        return None
    return entry_volume_at(ctx, ctx.memory.estimated_pallet.to_se2())


def entry_volume_at(ctx: Context, T_world_pallet: SE2) -> tuple[Volume, float] | None:
    """`entry_volume` for a pallet at `T_world_pallet` (world frame; the entry face's centre)."""
    T_fp = ctx.vehicle.localization().inv() @ T_world_pallet
    face_x = T_fp.x - 0.5 * ctx.pallet_type.width * abs(math.sin(T_fp.yaw))
    x0, x1 = ctx.forks.tip_x + 0.10, face_x - 0.10  # clear of the tips and the face (depth noise)
    if x1 <= x0:
        return None
    h = ctx.vehicle.fork_height  # fork bottoms; what is below them (a rack's beam) the forks pass over
    half = _half_corridor(ctx)
    volume = Volume(x0, x1, -half, half, max(0.05, h - 0.01), h + 1.2)
    return volume, face_x - ctx.forks.tip_x + ctx.pallet_type.length - ctx.settings.beam_margin


def slot_volume(ctx: Context) -> tuple[Volume, float] | None:
    """A delivery's slot volume in the forklift frame: where the carried pallet will stand at the drop
    node and the way there, from just beyond the load's front, a pallet's width plus 5 cm either side,
    from just above the slot's floor (or beam top) to a load's height; with the beams' far limit."""
    node = ctx.roadmap.node(ctx.memory.pallet_node)
    height = ctx.memory.load_task().height
    h = height if height is not None else node.height
    T_fp: SE2 = ctx.vehicle.localization().inv() @ pallet_pose_at_node(node.pose, h).to_se2()
    pt = ctx.pallet_type
    far = T_fp.x + pt.length
    x0 = ENTRY_GAP_M + pt.length + 0.15  # beyond the carried pallet's back, with the Pickup's tolerance
    if far <= x0:
        return None
    half = 0.5 * pt.width + 0.05
    volume = Volume(x0, far + 0.05, T_fp.y - half, T_fp.y + half, h + 0.03, h + 1.2)
    return volume, far - ctx.forks.tip_x - ctx.settings.beam_margin


def pocket_fit_problems(
    forks: ForkGeometry,
    pallet: PalletType,
    estimate: PalletEstimate,
    T_pallet_forklift: SE2,
    fork_clearance: float,
    side_margin: float = POCKET_SIDE_MARGIN_M,
    top_clearance: float = POCKET_TOP_CLEARANCE_M,
) -> list[str]:
    """Where the forks would not fit the pockets `estimate` measured, entering straight ahead from
    `T_pallet_forklift` (the truck in the pallet frame, SE2) with the fork bottoms `fork_clearance` (m)
    above the pallet's underside: one line per problem with the figures (mm). Laterally each fork, at the
    entry face and at the tips' depth, must keep `side_margin` inside its pocket (`pocket_widths_m`,
    `pocket_centres_y_m`, pallet frame); vertically its top must pass `top_clearance` under the measured
    pocket height (`extras["pocket_height_m"]`; where it was not measured, the family's lowest)."""
    problems = []
    depth = min(pallet.length, forks.length)
    c, s_ = math.cos(T_pallet_forklift.yaw), math.sin(T_pallet_forklift.yaw)
    names = ("left", "right")
    for name, fork_y, pocket_y, width in zip(
        names, forks.centres_y, estimate.pocket_centres_y_m, estimate.pocket_widths_m, strict=True
    ):
        origin = T_pallet_forklift.apply([0.0, fork_y])
        if abs(c) < 1e-6:
            problems.append(f"the {name} fork would run across the pallet (turned 90 deg to it)")
            continue
        # the fork's centre line along the truck's x, at the face and at the tips' depth
        ys = [origin[1] + (x - origin[0]) * s_ / c for x in (0.0, depth)]
        worst = min(0.5 * width - abs(y - pocket_y) - 0.5 * forks.width for y in ys)
        if worst < side_margin:
            where = f"pass {-1e3 * worst:.0f} mm beside" if worst < 0 else f"keep {1e3 * worst:.0f} mm inside"
            problems.append(
                f"the {name} fork ({1e3 * forks.width:.0f} mm wide) would {where} its measured pocket "
                f"({1e3 * width:.0f} mm wide at y = {1e3 * pocket_y:+.0f} mm), less than the "
                f"{1e3 * side_margin:.0f} mm margin"
            )
    height = estimate.extras.get("pocket_height_m")
    measured = height is not None
    if height is None:
        height = pallet.bounds("pocket_height")[0]
    top = fork_clearance + forks.thickness + top_clearance
    if top > height:
        problems.append(
            f"the forks ({1e3 * forks.thickness:.0f} mm thick, {1e3 * fork_clearance:.0f} mm above the underside) "
            f"and {1e3 * top_clearance:.0f} mm clearance need {1e3 * top:.0f} mm, the pockets are "
            f"{1e3 * height:.0f} mm high ({'measured' if measured else 'the family lowest'})"
        )
    return problems


def entry_pocket_fit(ctx: Context) -> list[str]:
    """`pocket_fit_problems` for the Pickup's pallet from where the truck stands (none for an exact pallet
    type, whose pockets `SafetyCheck` checks, or without an estimate)."""
    if ctx.pallet_type.family is None or ctx.memory.estimate is None or ctx.memory.estimated_pallet is None:
        return []
    T_pallet_forklift = ctx.memory.estimated_pallet.to_se2().inv() @ ctx.vehicle.localization()
    return pocket_fit_problems(
        ctx.forks, ctx.pallet_type, ctx.memory.estimate, T_pallet_forklift, ctx.settings.fork_clearance
    )


class CheckVolume(Behaviour):
    """Stand and make sure a volume ahead of the forks is free (camera, else beams); hold while it is not,
    fail with `reason` after `Settings.blocked_wait_s`. With `fit` (e.g. `entry_pocket_fit`), first fail
    with `safety_check_failed` where it names a problem (the forks would not fit the pockets)."""

    def __init__(
        self,
        volume: Callable[[Context], tuple[Volume, float] | None],
        reason: Reason,
        what: str,
        fit: Callable[[Context], list[str]] | None = None,
    ) -> None:
        self.volume = volume
        self.reason = reason
        self.what = what
        self.fit = fit

    def start(self, ctx: Context) -> None:
        ctx.vehicle.stop()
        self.timeout_s = ctx.settings.blocked_wait_s + 30.0
        self.first_blocked: float | None = None
        self.next_look = ctx.now()

    def update(self, ctx: Context) -> str | None:
        if abs(ctx.vehicle.speed) > _STANDING or ctx.now() < self.next_look:
            ctx.vehicle.stop()
            return None
        problems = self.fit(ctx) if self.fit is not None else []
        if problems:
            ctx.log("pocket_fit", what=self.what, problems=problems)
            raise TaskFailed(SAFETY_CHECK_FAILED, "; ".join(problems))
        spec = self.volume(ctx)
        if spec is None:
            ctx.log("entry_check", what=self.what, skipped="no room between the forks and the target")
            return "done"
        volume, beams_far = spec
        look = self._camera(ctx, volume)
        if look is None:
            return None  # no frame this tick
        blocked = self._blocked(ctx, look, beams_far)
        if blocked is None:
            if self.first_blocked is not None:
                ctx.log("entry_clear", what=self.what, waited_s=round(ctx.now() - self.first_blocked, 2))
            return "done"
        now = ctx.now()
        if self.first_blocked is None:
            self.first_blocked = now
            ctx.log("entry_blocked", what=self.what, why=blocked, volume=volume.to_json())
        if now - self.first_blocked >= ctx.settings.blocked_wait_s:
            raise TaskFailed(self.reason, f"{self.what} is not free after {now - self.first_blocked:.0f} s: {blocked}")
        self.next_look = now + RECHECK_S
        return None

    def _camera(self, ctx: Context, volume: Volume) -> VolumeCheck | bool | None:
        """The camera's look (False: no camera or calibration), or None when no frame came this tick."""
        # A trusted calibration where the truck has one (untrusted axes kept from it, `calibration_trust`);
        # else the service's last good one: a look with a forward position a few cm off beats none.
        last_good = ctx.perception.last_good if ctx.perception is not None else None
        calibration = calibration_for_checks(ctx) or last_good
        if ctx.perception is None or calibration is None:
            return False
        frame = ctx.frame()
        if frame is None:
            return None
        return ctx.perception.check_volume(frame, calibration, volume)

    def _blocked(self, ctx: Context, look: VolumeCheck | bool, beams_far: float) -> str | None:
        """Why the volume is not free, or None."""
        record = {"what": self.what, "beams_far_m": round(beams_far, 3)}
        if isinstance(look, VolumeCheck):
            record.update(look.to_json())
            if look.occupied and look.seen >= MIN_SEEN:
                ctx.log("entry_check", **record, free=False)
                return f"the camera sees {look.points} points of an object {look.nearest_x_m:.2f} m ahead"
        left, right = ctx.vehicle.proximity_ranges()
        record.update({"left_m": round(left, 3), "right_m": round(right, 3)})
        if min(left, right) < beams_far:
            ctx.log("entry_check", **record, free=False)
            return f"a fork-tip beam stops {min(left, right):.2f} m ahead, short of the far end {beams_far:.2f} m"
        ctx.log("entry_check", **record, free=True)
        return None
