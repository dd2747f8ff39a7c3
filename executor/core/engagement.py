"""How deep the forks go into the pallet: the alignment tolerances, the rack's limit and the minimum engagement.

A pallet standing deeper than its rack node can be entered only as far as the mast allows: the truck's
heels go at most `Settings.rack_overrun` past the node before the mast meets the rack's front beam, so
the fork tips stop short of where they would reach at the node. That is allowed while the forks still
carry the pallet type's minimum engagement (`PalletType.required_engagement`: `min_fork_engagement` of
its length, default two thirds, and the balance: the load's centre of mass, the pallet's middle,
`balance_margin` inside the tips), with `Settings.longitudinal_margin` for localization and control.
Where they would not, the Pickup refuses with `no_feasible_approach`, saying how deep the tips could
reach and what the pallet needs (mm).

At a re-plan's node held back at the rack's limit, the far alignment tolerance is what the engagement
allows (`pickup_tolerances`); elsewhere it keeps the geometry's (the tips past the back row of blocks),
so a pallet the truck can reach fully is still re-planned to until it is. Before entering,
`engagement_problems` checks the depth the forks will reach against the estimate (`SafetyCheck`).

`rack_engagement` is the rule itself, a pure function of the vehicle, the tolerances and where the pallet
stands relative to its node (the benchmarks judge a refusal against the simulator's truth with it).

Public API: `geometry_tolerances`, `pickup_tolerances`, `rack_limited_pose`, `RackEngagement`,
`rack_engagement`, `mast_reach`, `engagement_problems`, `tip_depth`, `forks_outside_pockets`.
"""

from __future__ import annotations

import dataclasses
import math

from palletpilot.control.vehicle import BodyParams
from palletpilot.executor.core.behaviour import Context, Settings
from palletpilot.executor.core.errors import NO_FEASIBLE_APPROACH, TaskFailed
from palletpilot.geometry import SE2
from palletpilot.perception.alignment import AlignmentTolerances
from palletpilot.perception.specs import ForkGeometry, PalletType

_AT_LIMIT_M = 1e-3
"""A node this close (m) to the rack's overrun limit stands at it."""


def geometry_tolerances(forks: ForkGeometry, pallet: PalletType, settings: Settings) -> AlignmentTolerances:
    """The alignment tolerances (pallet frame) that the pockets leave the forks `forks` in `pallet`, less
    the margins of `settings`: the Pickup's and the benchmark's verdicts judge by the same ones."""
    return AlignmentTolerances.from_geometry(
        forks,
        pallet,
        lateral_margin_m=settings.lateral_margin,
        longitudinal_margin_m=settings.longitudinal_margin,
        yaw_limit_deg=settings.yaw_limit_deg,
    )


@dataclasses.dataclass(frozen=True)
class RackEngagement:
    """How a pallet standing deeper in a rack than its node is entered, held back at the rack's limit (m):
    the pallet `deeper_m` than the node, the truck's pallet node `back_m` short of serving it fully, the
    fork tips then `reach_m` into the pallet where it needs `need_m` (`why`); `lead_m` is what a turned
    mast's leading front corner gains on the straight mast's front."""

    deeper_m: float
    back_m: float
    reach_m: float
    need_m: float
    why: str
    lead_m: float

    def enough(self, margin_m: float) -> bool:
        """Do the forks carry the minimum engagement with `margin_m` (m) to spare?"""
        return self.reach_m - margin_m >= self.need_m


def mast_reach(body: BodyParams, rel: SE2) -> float:
    """How far (m) past the rack node the truck at `rel` (its pose in the node's frame) goes, measured where
    the mast meets the beam: the heels' x, plus what the leading front corner of a turned mast gains on the
    straight mast's front."""
    return rel.x + body.front_x * (math.cos(rel.yaw) - 1.0) + 0.5 * body.width * abs(math.sin(rel.yaw))


def rack_engagement(
    body: BodyParams, tolerances: AlignmentTolerances, pallet: PalletType, rack_overrun_m: float, rel: SE2
) -> RackEngagement | None:
    """The rack's limit on a pallet node at `rel` (the node that serves the pallet fully, in the rack node's
    frame): how the truck, going at most `rack_overrun_m` past the rack node, enters the pallet; None when
    the limit costs nothing (the node within it, or held back less than the far tolerance)."""
    reach_past = mast_reach(body, rel)
    excess = reach_past - rack_overrun_m
    if excess <= 0.0:
        return None
    back = excess / max(math.cos(rel.yaw), 0.5)  # along the pallet's own axis
    if back <= tolerances.longitudinal_far_m:
        return None
    need, why = pallet.required_engagement()
    reach = min(tolerances.reach_m - back, pallet.length)  # how deep the tips go into the pallet, held back
    return RackEngagement(rel.x, back, reach, need, why, reach_past - rel.x)


def _at_rack_limit(ctx: Context) -> bool:
    """True when the current pallet node is a re-plan's node held back at the rack's overrun limit."""
    original = ctx.roadmap.node(ctx.memory.node_task().node)
    if original.height <= 0.0 or not ctx.memory.pallet_node or ctx.memory.pallet_node == original.id:
        return False
    rel = original.pose.inv() @ ctx.roadmap.node(ctx.memory.pallet_node).pose
    return mast_reach(ctx.params.body, rel) >= ctx.settings.rack_overrun - _AT_LIMIT_M


def pickup_tolerances(ctx: Context) -> AlignmentTolerances:
    """The alignment tolerances of this truck's forks and the pallet type, less the Settings' margins; at a
    node held back at the rack's limit the far one is what the minimum engagement allows (m)."""
    tol = geometry_tolerances(ctx.forks, ctx.pallet_type, ctx.settings)
    if not _at_rack_limit(ctx):
        return tol
    need, _ = ctx.pallet_type.required_engagement()
    engaged_far = tol.reach_m - need - ctx.settings.longitudinal_margin
    return dataclasses.replace(tol, longitudinal_far_m=max(tol.longitudinal_far_m, engaged_far))


def rack_limited_pose(ctx: Context, pallet_node_pose: SE2) -> SE2:
    """The corrected pallet node pose (world), held back at a rack so the heels never pass the original
    node by more than `Settings.rack_overrun` (m) along its heading (less where the truck stands turned: the
    mast's leading front corner goes no further than the straight mast's front would); the forks then
    enter less deep.

    Raises `TaskFailed(no_feasible_approach)` when, held back, the fork tips would not reach the pallet
    type's minimum engagement (with the longitudinal margin), naming how deep they could reach (mm).
    Records `engagement` in the task's report when the tips stop short of the back blocks.
    """
    original = ctx.roadmap.node(ctx.memory.node_task().node)
    if original.height <= 0.0:
        return pallet_node_pose
    rel = original.pose.inv() @ pallet_node_pose
    pallet = ctx.pallet_type
    held = rack_engagement(
        ctx.params.body,
        geometry_tolerances(ctx.forks, ctx.pallet_type, ctx.settings),
        pallet,
        ctx.settings.rack_overrun,
        rel,
    )
    if held is None:
        return pallet_node_pose
    margin = ctx.settings.longitudinal_margin
    figures = {
        "deeper_mm": round(rel.x * 1e3, 1),
        "reach_mm": round(held.reach_m * 1e3, 1),
        "required_mm": round(held.need_m * 1e3, 1),
        "margin_mm": round(margin * 1e3, 1),
        "pallet_length_mm": round(pallet.length * 1e3, 1),
    }
    ctx.memory.record.setdefault("engagement", []).append({**figures, "enough": held.enough(margin)})
    if not held.enough(margin):
        lead = held.lead_m
        turned = f" ({lead * 1e3:.0f} mm less turned {math.degrees(rel.yaw):+.0f} deg)" if lead > _AT_LIMIT_M else ""
        raise TaskFailed(
            NO_FEASIBLE_APPROACH,
            f"the pallet stands {rel.x * 1e3:.0f} mm deeper in the rack than node '{original.id}': the truck may "
            f"go {ctx.settings.rack_overrun * 1e3:.0f} mm past it{turned} before the mast meets the rack, and the fork "
            f"tips could then reach {held.reach_m * 1e3:.0f} mm into the pallet; it needs {held.need_m * 1e3:.0f} mm "
            f"({held.why}) and {margin * 1e3:.0f} mm margin",
        )
    ctx.log("short_engagement", **figures)
    return pallet_node_pose @ SE2(-held.back_m, 0.0, 0.0)


def tip_depth(forks: ForkGeometry, T_pallet_forklift: SE2) -> float:
    """How deep (m) the shallower fork tip lies in the pallet, past its entry face, with the truck at
    `T_pallet_forklift` (the forklift in the pallet frame; x along the pockets from the entry face)."""
    return min(float(T_pallet_forklift.apply([forks.tip_x, y])[0]) for y in forks.centres_y)


def engagement_problems(forks: ForkGeometry, pallet: PalletType, T_pallet_forklift: SE2, margin: float) -> list[str]:
    """Why the forks, with the truck at `T_pallet_forklift` (where it will stand at the pallet node, in the
    estimated pallet's frame), would not carry the pallet: too little of its depth for the pallet type's
    minimum engagement or its balance, with `margin` (m). Empty when they would."""
    depth = min(tip_depth(forks, T_pallet_forklift), pallet.length)
    need, why = pallet.required_engagement()
    if depth - margin >= need:
        return []
    return [
        f"the fork tips would reach {depth * 1e3:.0f} mm into the pallet, it needs {need * 1e3:.0f} mm ({why}) "
        f"and {margin * 1e3:.0f} mm margin"
    ]


def forks_outside_pockets(ctx: Context, T_world_pallet: SE2, T_world_forklift: SE2) -> list[str]:
    """Where a fork would not enter its pocket, entering straight ahead from `T_world_forklift`: one line
    per fork with how far (mm) its side passes outside the pocket at the entry face or at the fork tip's
    depth. Both poses are in the world frame (SE2)."""
    forks, pallet = ctx.forks, ctx.pallet_type
    T_pallet_forklift = T_world_pallet.inv() @ T_world_forklift
    depth = min(pallet.length, forks.length)
    half_free = 0.5 * pallet.pocket_width - 0.5 * forks.width
    problems = []
    for name, fork_y, pocket_y in zip(("left", "right"), forks.centres_y, pallet.pocket_centres_y, strict=True):
        worst = 0.0
        for x_pallet in (0.0, depth):
            # the fork's centre line, a line along the forklift's x axis, at this depth in the pallet
            c, s_ = math.cos(T_pallet_forklift.yaw), math.sin(T_pallet_forklift.yaw)
            origin = T_pallet_forklift.apply([0.0, fork_y])
            if abs(c) < 1e-6:
                worst = math.inf
                break
            y = origin[1] + (x_pallet - origin[0]) * s_ / c
            worst = max(worst, abs(y - pocket_y) - half_free)
        if worst > 0.0:
            problems.append(f"the {name} fork would pass {worst * 1e3:.0f} mm beside its pocket")
    return problems
