"""Is the estimated pallet where the roadmap's pallet node expects it? Step 5 of the adaptive pickup.

The nominal pallet at a pallet node is `pallet_pose_at_node(node.pose, node.height)` (world frame:
entry face `ENTRY_GAP_M` ahead of the fork heels, straight ahead). The differences are those of the
estimated `T_world_pallet` in the nominal pallet frame: lateral (y, m), longitudinal (x, m, positive:
farther away than expected) and yaw (rad).

Tolerances come from the geometry:

- lateral: each fork must stay inside its pocket. With the forks and pockets centred as designed the
  clearance per side is `(pocket_width - fork_width) / 2` (33.75 mm for the example forks and a EUR
  pallet); in general it is the smaller clearance of the two forks. A yawed pallet also moves the
  fork tips sideways by `reach * sin(yaw)` at full insertion, so the lateral check is
  `|lateral| + reach * |sin(yaw)| <= clearance - lateral_margin`, `reach` being how far the tips go
  into the pallet at the node (`tip_x - ENTRY_GAP_M`).
- longitudinal: nearer than expected, the carriage (at the fork heels) would push the pallet before
  the node is reached: at most `ENTRY_GAP_M - longitudinal_margin`. Farther, the tips must still reach
  the back row of blocks (the back cross board carries the deck): at most
  `reach - back_row_x - longitudinal_margin`, and never less than the margin itself.
- yaw: `yaw_limit_deg`, and no more than what the lateral clearance allows on its own.

With the estimate's spread (`PalletSpread`, 1-sigma), "aligned" means aligned with its uncertainty
taken into account: each difference plus `ALIGNMENT_SIGMAS` (k = 2) of its 1-sigma must lie within its
tolerance, i.e. `|lateral| + reach * |sin(yaw)| + k * sqrt(sigma_y^2 + (reach * cos(yaw) * sigma_yaw)^2)`,
`longitudinal - k * sigma_x` against the near tolerance and `|yaw| + k * sigma_yaw`: every side where a
miss means contact. The far side (the pallet deeper than the node: the forks reach less far) keeps its
tolerance alone, which already holds the margin to the back blocks: a rack lets the truck go only so
deep, and a pallet 30 mm deeper than its node stated to +-5 mm was re-planned in vain until
`still_misaligned` (`bench missions --seed 1`, 2 of 50 runs). The spread is stated in the forklift frame,
which at the pre-pallet node looks along the node (x along, y across, to within the misplacement's few
degrees), so its x and y serve as the longitudinal and lateral sigmas. k = 2: an estimate judged aligned
is within the tolerances with about 98 % confidence on each (one-sided, Gaussian); the tolerances'
own margins (`lateral_margin_m`, ...) are for localization and control, not for the estimate.

Misaligned results carry the corrected pallet node: `node_pose_for_pallet(T_world_pallet)`.
"""

from __future__ import annotations

import math
from dataclasses import dataclass
from typing import Protocol

from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.angles import wrap_angle
from palletpilot.perception.pallet_estimate import PalletSpread
from palletpilot.perception.specs import (
    ENTRY_GAP_M,
    ForkGeometry,
    PalletType,
    node_pose_for_pallet,
    pallet_pose_at_node,
)

ALIGNMENT_SIGMAS = 2.0
"""k: an estimate is aligned when each difference plus k of its stated 1-sigma lies within its tolerance."""


class PalletNodeLike(Protocol):
    """What the check needs of a roadmap pallet node (`roadmap.Node` fits): its pose and load height (m)."""

    @property
    def pose(self) -> SE2: ...

    @property
    def height(self) -> float: ...


@dataclass(frozen=True)
class AlignmentTolerances:
    """Allowed differences: lateral (m, each side), longitudinal near / far (m) and yaw (rad)."""

    lateral_m: float
    longitudinal_near_m: float
    longitudinal_far_m: float
    yaw_rad: float
    reach_m: float
    """How far the fork tips go into a pallet standing exactly at the node (m)."""

    @classmethod
    def from_geometry(
        cls,
        forks: ForkGeometry,
        pallet: PalletType | None = None,
        lateral_margin_m: float = 0.010,
        longitudinal_margin_m: float = 0.010,
        yaw_limit_deg: float = 2.0,
    ) -> AlignmentTolerances:
        """Tolerances from fork and pocket geometry with the given safety margins (see the module docstring)."""
        pallet = pallet or PalletType.eur()
        half_pocket, half_fork = 0.5 * pallet.pocket_width, 0.5 * forks.width
        clearances = []
        for fork_y, pocket_y in zip(forks.centres_y, pallet.pocket_centres_y, strict=True):
            clearances.append(
                min(pocket_y + half_pocket - (fork_y + half_fork), (fork_y - half_fork) - (pocket_y - half_pocket))
            )
        lateral = min(clearances) - lateral_margin_m
        reach = forks.tip_x - ENTRY_GAP_M
        back_row = pallet.block_rows_x[2]
        far = max(reach - back_row - longitudinal_margin_m, longitudinal_margin_m)
        near = max(ENTRY_GAP_M - longitudinal_margin_m, 0.0)
        yaw = math.radians(yaw_limit_deg)
        if lateral > 0 and reach > 0:
            yaw = min(yaw, math.asin(min(1.0, lateral / reach)))
        return cls(max(lateral, 0.0), near, far, yaw, reach)

    def to_json(self) -> dict[str, float]:
        """Tolerances in mm and degrees."""
        return {
            "lateral_mm": round(self.lateral_m * 1e3, 2),
            "longitudinal_near_mm": round(self.longitudinal_near_m * 1e3, 2),
            "longitudinal_far_mm": round(self.longitudinal_far_m * 1e3, 2),
            "yaw_deg": round(math.degrees(self.yaw_rad), 3),
        }


@dataclass(frozen=True)
class AlignmentResult:
    """The alignment decision with the three differences (estimate in the nominal pallet frame).

    `corrected_node_pose` (world, SE2) is the pallet node that would serve the estimated pallet; it is
    set when `aligned` is false. `problems` names each exceeded tolerance. `uncertainty`: what the
    estimate's spread added to the lateral sweep, the longitudinal and the yaw difference (m, m, rad;
    k sigma each, zeros without a spread).
    """

    aligned: bool
    lateral_m: float
    longitudinal_m: float
    yaw_rad: float
    tolerances: AlignmentTolerances
    problems: tuple[str, ...] = ()
    corrected_node_pose: SE2 | None = None
    uncertainty: tuple[float, float, float] = (0.0, 0.0, 0.0)

    def to_json(self) -> dict:
        """The decision in mm and degrees."""
        doc: dict = {
            "aligned": self.aligned,
            "lateral_mm": round(self.lateral_m * 1e3, 2),
            "longitudinal_mm": round(self.longitudinal_m * 1e3, 2),
            "yaw_deg": round(math.degrees(self.yaw_rad), 3),
            "tolerances": self.tolerances.to_json(),
            "uncertainty": {
                "lateral_mm": round(self.uncertainty[0] * 1e3, 2),
                "longitudinal_mm": round(self.uncertainty[1] * 1e3, 2),
                "yaw_deg": round(math.degrees(self.uncertainty[2]), 3),
            },
            "problems": list(self.problems),
        }
        if self.corrected_node_pose is not None:
            p = self.corrected_node_pose
            doc["corrected_node"] = {
                "x_m": round(p.x, 4),
                "y_m": round(p.y, 4),
                "yaw_deg": round(math.degrees(p.yaw), 3),
            }
        return doc


def check_alignment(
    T_world_pallet: SE3,
    node: PalletNodeLike,
    tolerances: AlignmentTolerances,
    spread: PalletSpread | None = None,
    k_sigma: float = ALIGNMENT_SIGMAS,
) -> AlignmentResult:
    """Compare an estimated `T_world_pallet` with the pallet expected at `node`, with the estimate's
    `spread` (1-sigma, forklift frame) taken into account at `k_sigma` when given (see the module docstring)."""
    T_nominal = pallet_pose_at_node(node.pose, node.height)
    diff = (T_nominal.inv() @ T_world_pallet).to_se2()
    lateral, longitudinal, yaw = diff.y, diff.x, float(wrap_angle(diff.yaw))
    tol = tolerances
    u_lat = u_lon = u_yaw = 0.0
    if spread is not None:
        u_lat = k_sigma * math.hypot(spread.y_m, tol.reach_m * math.cos(yaw) * spread.yaw_rad)
        u_lon, u_yaw = k_sigma * spread.x_m, k_sigma * spread.yaw_rad
    problems = []
    tips = tol.reach_m * abs(math.sin(yaw))
    if abs(lateral) + tips + u_lat > tol.lateral_m:
        also = f" and {k_sigma:g} sigma of the estimate's {u_lat * 1e3:.1f} mm" if spread is not None else ""
        problems.append(
            f"lateral {lateral * 1e3:+.1f} mm (with the yaw's {tips * 1e3:.1f} mm at the fork tips{also}) exceeds "
            f"{tol.lateral_m * 1e3:.1f} mm"
        )
    lon_u = f" ({k_sigma:g} sigma: {u_lon * 1e3:.1f} mm)" if spread is not None else ""
    if longitudinal - u_lon < -tol.longitudinal_near_m:
        problems.append(
            f"longitudinal {longitudinal * 1e3:+.1f} mm{lon_u}: nearer than {tol.longitudinal_near_m * 1e3:.1f} mm"
        )
    if longitudinal > tol.longitudinal_far_m:  # engagement, not contact: the tolerance alone (module docstring)
        far = tol.longitudinal_far_m * 1e3
        problems.append(f"longitudinal {longitudinal * 1e3:+.1f} mm: farther than {far:.1f} mm")
    if abs(yaw) + u_yaw > tol.yaw_rad:
        yaw_u = f" ({k_sigma:g} sigma: {math.degrees(u_yaw):.2f} deg)" if spread is not None else ""
        problems.append(f"yaw {math.degrees(yaw):+.2f} deg{yaw_u} exceeds {math.degrees(tol.yaw_rad):.2f} deg")
    aligned = not problems
    return AlignmentResult(
        aligned=aligned,
        lateral_m=lateral,
        longitudinal_m=longitudinal,
        yaw_rad=yaw,
        tolerances=tol,
        problems=tuple(problems),
        corrected_node_pose=None if aligned else node_pose_for_pallet(T_world_pallet),
        uncertainty=(u_lat, u_lon, u_yaw),
    )
