"""Pallets in the simulated warehouse and how the forks handle them: entering, lifting, carrying, setting down.

The forks and the carriage's load backrest are boxes; every step near a pallet they are tested against
the pallet's boards and blocks (separating axes, in the pallet frame). A fork that meets a part while
entering is a collision: it is recorded in `collisions`, the forklift stops and stays stopped. When
both forks are at least half-way into the pockets and rise to the underside of the deck, the pallet
rides on them (`T_forks_pallet`); lowered onto the floor or a rack beam (`RackSupport`) it stays there.

`PalletPhysics` is a part of `sim.simulator.Simulator` (a mixin: it works on the simulator's pallets,
forks and racks). Poses in the world frame, sizes in metres.

Public API: `SimPallet`, `RackSupport`, `PalletPhysics`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import Any

import numpy as np

from palletpilot.geometry import SE3
from palletpilot.perception.specs import ForkGeometry, PalletType
from palletpilot.sim.world import PalletCondition, Rack, pallet_parts

_BACKREST = ((-0.12, -0.40, 0.0), (0.0, 0.40, 1.2))  # load backrest box (m), forklift frame above lift height


@dataclass
class SimPallet:
    """A pallet in the simulated world (poses in the world frame)."""

    node: str  # the pallet node it was placed at; "" for a pallet standing free on the floor
    T_world_pallet: SE3
    loaded: bool
    carried: bool = False
    T_forks_pallet: SE3 | None = field(default=None, repr=False)  # relative to the fork bottoms while carried
    lifted: bool = False  # the truck has lifted it at least once
    initial: SE3 | None = field(default=None, repr=False)  # where the scenario put it
    id: str = ""  # its node, or `pallets[i]` (its index in the scenario) for a free one
    type: PalletType = field(default_factory=PalletType.eur, repr=False)
    condition: PalletCondition | None = field(default=None, repr=False)  # build tolerance, damage, film
    parts: list[Any] = field(default_factory=list, repr=False)  # its real boards and blocks (pallet frame)

    def __post_init__(self) -> None:
        if self.initial is None:
            self.initial = self.T_world_pallet
        if not self.id:
            self.id = self.node
        if not self.parts:
            self.parts = pallet_parts(self.type, self.condition)
        self.part_lo = np.array([q.lo for q in self.parts])
        self.part_hi = np.array([q.hi for q in self.parts])


@dataclass(frozen=True)
class RackSupport:
    """Beams a pallet can stand on: the pallet-node footprint of a rack bay and the beam-top height (m)."""

    T_world_rack: SE3
    rack: Rack
    top_z: float
    node: str = ""

    def supports(self, xy: np.ndarray) -> bool:
        """True when world point `xy` lies over this rack bay."""
        local = self.T_world_rack.inv().apply([xy[0], xy[1], 0.0])
        half = 0.5 * self.rack.bay_width
        return bool(-0.2 <= local[0] <= self.rack.depth + 0.2 and -half <= local[1] <= half)


class PalletPhysics:
    """The forks meeting, lifting, carrying and setting down pallets (a part of `Simulator`)."""

    pallets: list[SimPallet]
    forks: ForkGeometry
    pallet_type: PalletType
    collisions: list[dict[str, Any]]
    time: float
    _racks: list[RackSupport]

    @property
    def fork_height(self) -> float:
        """Measured fork height (m); the simulator's."""
        raise NotImplementedError

    @property
    def T_world_forklift3(self) -> SE3:
        """True forklift pose (SE3 on the floor); the simulator's."""
        raise NotImplementedError

    def _collide(self, record: dict[str, Any]) -> None:
        raise NotImplementedError

    def _static_changed(self) -> None:
        raise NotImplementedError

    def _fork_boxes(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        h = self.fork_height
        boxes = [
            (name, lo, hi) for name, (lo, hi) in zip(("left fork", "right fork"), self.forks.boxes(h), strict=True)
        ]
        # The heel fillets (a heel radius in the forks file) stand on the blades next to the carriage.
        heels = zip(("left fork heel", "right fork heel"), self.forks.heel_boxes(h), strict=False)
        boxes += [(name, lo, hi) for name, (lo, hi) in heels]
        lo, hi = (np.array(v) for v in _BACKREST)
        boxes.append(("load backrest", lo + np.array([0.0, 0.0, h]), hi + np.array([0.0, 0.0, h])))
        return boxes

    def _update_pallets(self) -> None:
        T_wf = self.T_world_forklift3
        changed = False
        for p in self.pallets:
            if p.carried:
                assert p.T_forks_pallet is not None
                p.T_world_pallet = T_wf @ SE3.from_translation(0, 0, self.fork_height) @ p.T_forks_pallet
                support = self._support_z(p.T_world_pallet.t[:2])
                if p.T_world_pallet.t[2] <= support + 1e-4:
                    xyz = p.T_world_pallet.t.copy()
                    xyz[2] = support
                    p.T_world_pallet = SE3(p.T_world_pallet.rotation, xyz)
                    p.carried, p.T_forks_pallet, changed = False, None, True
                continue
            if np.hypot(*(p.T_world_pallet.t[:2] - T_wf.t[:2])) > 3.5:
                continue
            if self._try_lift(p, T_wf):
                changed = True
                continue
            hit = self._contact(p, T_wf)
            if hit is not None and not self.collisions:
                part = hit.partition(" hit ")[0]
                message = f"t={self.time:.2f} s: {hit} of the pallet '{p.id}'"
                self._collide(
                    {"t_s": round(self.time, 3), "kind": "pallet", "id": p.id, "part": part, "message": message}
                )
        if changed:
            self._static_changed()

    def _support_z(self, xy: np.ndarray) -> float:
        for r in self._racks:
            if r.supports(xy):
                return r.top_z
        return 0.0

    def _fork_in_pallet(self, p: SimPallet, T_wf: SE3) -> tuple[np.ndarray, np.ndarray]:
        """Fork and backrest boxes as 2D corners (B, 4, 2) and z ranges (B, 2) in the pallet frame."""
        T_pf = p.T_world_pallet.inv() @ T_wf
        corners, z = [], []
        for _, lo, hi in self._fork_boxes():
            c = np.array([[lo[0], lo[1], lo[2]], [hi[0], lo[1], lo[2]], [hi[0], hi[1], lo[2]], [lo[0], hi[1], lo[2]]])
            pts = T_pf.apply(c)
            corners.append(pts[:, :2])
            z.append((pts[0, 2], pts[0, 2] + hi[2] - lo[2]))
        return np.array(corners), np.array(z)

    def _contact(self, p: SimPallet, T_wf: SE3, tol: float = 1e-3) -> str | None:
        """The first (box, part) pair that overlaps by more than `tol` (m), or None."""
        corners, z = self._fork_in_pallet(p, T_wf)
        lo, hi = p.part_lo, p.part_hi
        names = [b[0] for b in self._fork_boxes()]
        for b in range(len(corners)):
            z_overlap = (np.minimum(z[b, 1], hi[:, 2]) - np.maximum(z[b, 0], lo[:, 2])) > tol
            if not z_overlap.any():
                continue
            c = corners[b]
            ex, ey = c[1] - c[0], c[3] - c[0]
            axes = [np.array([1.0, 0.0]), np.array([0.0, 1.0]), ex / np.linalg.norm(ex), ey / np.linalg.norm(ey)]
            overlap = z_overlap.copy()
            for ax in axes:
                proj = c @ ax
                part_corners = np.stack(
                    [
                        lo[:, 0] * ax[0] + lo[:, 1] * ax[1],
                        hi[:, 0] * ax[0] + lo[:, 1] * ax[1],
                        hi[:, 0] * ax[0] + hi[:, 1] * ax[1],
                        lo[:, 0] * ax[0] + hi[:, 1] * ax[1],
                    ],
                    axis=1,
                )
                overlap &= (
                    np.minimum(proj.max(), part_corners.max(axis=1)) - np.maximum(proj.min(), part_corners.min(axis=1))
                ) > tol
            if overlap.any():
                return f"{names[b]} hit {p.parts[int(np.argmax(overlap))].name}"
        return None

    def _try_lift(self, p: SimPallet, T_wf: SE3) -> bool:
        """Attach the pallet when both forks are deep in the pockets and touch the deck from below."""
        corners, z = self._fork_in_pallet(p, T_wf)
        pt = p.type
        pocket_top = pt.pocket_height
        forks_x, forks_y = corners[:2, :, 0], corners[:2, :, 1]
        depth_in = np.minimum(forks_x.max(axis=1), pt.length) - np.maximum(forks_x.min(axis=1), 0.0)
        inside = (
            np.all(depth_in >= 0.5 * pt.length)
            and np.all(np.abs(forks_y) <= 0.5 * pt.width)
            and np.all(z[:2, 1] >= pocket_top - 1e-3)
            and np.all(z[:2, 0] < pocket_top)
        )
        if not inside:
            return False
        # Lifting only works when nothing but the deck underside is touched: test a hair lower.
        lowered = T_wf @ SE3.from_translation(0.0, 0.0, -0.002 - (z[:2, 1].max() - pocket_top))
        if self._contact(p, lowered) is not None:
            return False
        T_forks_world = (T_wf @ SE3.from_translation(0, 0, self.fork_height)).inv()
        lift = SE3.from_translation(0.0, 0.0, self.forks.thickness - pocket_top)
        T_forks_pallet = T_forks_world @ p.T_world_pallet
        planar = T_forks_pallet.to_se2().to_se3()  # the pallet settles level on the forks
        p.T_forks_pallet = lift @ planar
        p.carried = p.lifted = True
        return True
