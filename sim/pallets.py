"""Pallets in the simulated warehouse and how the forks handle them: entering, lifting, carrying, setting down.

The forks and the carriage's load backrest are boxes; every step near a pallet they are tested against
the pallet's boards and blocks (separating axes, in the pallet frame). A fork that meets a part while
entering is a collision: it is recorded in `collisions`, the forklift stops and stays stopped. When
both forks are at least half-way into the pockets and rise to the underside of the deck, the pallet
rides on them (`T_forks_pallet`); lowered onto the floor or a rack beam (`RackSupport`) it stays there.

`PalletPhysics` is a part of `sim.simulator.Simulator` (a mixin: it works on the simulator's pallets,
forks and racks). Poses in the world frame, sizes in metres.

The forks' boxes are kept per lift height (`ForkBoxes`, in the simulator's `SolidCache`) and tested
against all of a pallet's parts at once (arrays, no loop over boxes or axes).

Public API: `SimPallet`, `RackSupport`, `ForkBoxes`, `PalletPhysics`.
"""

from __future__ import annotations

from dataclasses import dataclass, field
from typing import TYPE_CHECKING, Any

import numpy as np

from palletpilot.geometry import SE2, SE3
from palletpilot.perception.specs import ForkGeometry, PalletType
from palletpilot.sim.world import PalletCondition, Rack, pallet_parts

if TYPE_CHECKING:
    from palletpilot.sim.solid_cache import SolidCache

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
        lo, hi = self.part_lo, self.part_hi  # the parts' floor corners (M, 4) in the pallet frame
        self.part_x = np.stack([lo[:, 0], hi[:, 0], hi[:, 0], lo[:, 0]], axis=1)
        self.part_y = np.stack([lo[:, 1], lo[:, 1], hi[:, 1], hi[:, 1]], axis=1)
        self._inverse: tuple[SE3, np.ndarray] | None = None

    def M_pallet_world(self) -> np.ndarray:
        """`T_world_pallet.inv()` as a 4x4 matrix, computed once per pose (poses are immutable: a move is a
        new object); read-only."""
        if self._inverse is None or self._inverse[0] is not self.T_world_pallet:
            m = self.T_world_pallet.inv().matrix
            m.setflags(write=False)
            self._inverse = (self.T_world_pallet, m)
        return self._inverse[1]


@dataclass(frozen=True)
class ForkBoxes:
    """The fork blades, heel fillets and load backrest at one lift `height` (m) as boxes in the forklift
    frame: `names`, `boxes` (name, lo, hi), their corners `lo`, `hi` (B, 3), the four bottom corners of
    each (B * 4, 3, counter-clockwise from lo) and their heights `dz` (B,)."""

    height: float
    names: tuple[str, ...]
    boxes: list[tuple[str, np.ndarray, np.ndarray]]
    lo: np.ndarray
    hi: np.ndarray
    bottom: np.ndarray
    dz: np.ndarray

    @classmethod
    def of(cls, height: float, boxes: list[tuple[str, np.ndarray, np.ndarray]]) -> ForkBoxes:
        """The boxes (name, lo, hi) at lift `height`."""
        lo = np.array([b[1] for b in boxes], dtype=float)
        hi = np.array([b[2] for b in boxes], dtype=float)
        x0, y0, z0, x1, y1 = lo[:, 0], lo[:, 1], lo[:, 2], hi[:, 0], hi[:, 1]
        corners = [(x0, y0), (x1, y0), (x1, y1), (x0, y1)]
        bottom = np.stack([np.stack([x, y, z0], -1) for x, y in corners], axis=1).reshape(-1, 3)
        return cls(height, tuple(b[0] for b in boxes), boxes, lo, hi, bottom, hi[:, 2] - lo[:, 2])


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
    _solid_cache: SolidCache

    @property
    def fork_height(self) -> float:
        """Measured fork height (m); the simulator's."""
        raise NotImplementedError

    @property
    def T_world_forklift3(self) -> SE3:
        """True forklift pose (SE3 on the floor); the simulator's."""
        raise NotImplementedError

    @property
    def true_pose(self) -> SE2:
        """True forklift pose (SE2, world); the simulator's."""
        raise NotImplementedError

    def _collide(self, record: dict[str, Any]) -> None:
        raise NotImplementedError

    def _static_changed(self) -> None:
        raise NotImplementedError

    def _fork_boxes(self) -> list[tuple[str, np.ndarray, np.ndarray]]:
        """(name, lo, hi) of the fork blades, heel fillets and backrest at the current lift height
        (forklift frame, m); the arrays are shared, never change them."""
        return self._fork_set().boxes

    def _fork_set(self) -> ForkBoxes:
        h = self.fork_height
        return self._solid_cache.fork_boxes(h, lambda: ForkBoxes.of(h, self._build_fork_boxes(h)))

    def _build_fork_boxes(self, h: float) -> list[tuple[str, np.ndarray, np.ndarray]]:
        boxes = [
            (name, lo, hi) for name, (lo, hi) in zip(("left fork", "right fork"), self.forks.boxes(h), strict=True)
        ]
        # The heel fillets (a heel radius in the forks file) stand on the blades next to the carriage.
        heels = zip(("left fork heel", "right fork heel"), self.forks.heel_boxes(h), strict=False)
        boxes += [(name, lo, hi) for name, (lo, hi) in heels]
        lo, hi = (np.array(v) for v in _BACKREST)
        boxes.append(("load backrest", lo + np.array([0.0, 0.0, h]), hi + np.array([0.0, 0.0, h])))
        for _, lo, hi in boxes:
            lo.setflags(write=False)
            hi.setflags(write=False)
        return boxes

    def _update_pallets(self) -> None:
        pose = self.true_pose
        M_wf = self._solid_cache.matrix4(pose)
        changed = False
        for p in self.pallets:
            if p.carried:
                assert p.T_forks_pallet is not None
                T_wf = self.T_world_forklift3
                p.T_world_pallet = T_wf @ SE3.from_translation(0, 0, self.fork_height) @ p.T_forks_pallet
                support = self._support_z(p.T_world_pallet.t[:2])
                if p.T_world_pallet.t[2] <= support + 1e-4:
                    xyz = p.T_world_pallet.t.copy()
                    xyz[2] = support
                    p.T_world_pallet = SE3(p.T_world_pallet.rotation, xyz)
                    p.carried, p.T_forks_pallet, changed = False, None, True
                continue
            if np.hypot(*(p.T_world_pallet.t[:2] - (pose.x, pose.y))) > 3.5:
                continue
            boxes = self._fork_in_pallet(p, M_wf)
            if self._try_lift(p, M_wf, boxes):
                changed = True
                continue
            hit = self._contact(p, M_wf, boxes=boxes)
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

    def _fork_in_pallet(self, p: SimPallet, M_wf: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
        """Fork and backrest boxes as 2D corners (B, 4, 2) and z ranges (B, 2) in the pallet frame, with the
        forklift at `M_wf` (4x4 matrix of `T_world_forklift`)."""
        fb = self._fork_set()
        M_pf = p.M_pallet_world() @ M_wf
        pts = (fb.bottom @ M_pf[:3, :3].T + M_pf[:3, 3]).reshape(-1, 4, 3)
        return pts[..., :2], np.stack([pts[:, 0, 2], pts[:, 0, 2] + fb.dz], axis=-1)

    def _contact(
        self, p: SimPallet, M_wf: np.ndarray, tol: float = 1e-3, boxes: tuple[np.ndarray, np.ndarray] | None = None
    ) -> str | None:
        """The first (box, part) pair that overlaps by more than `tol` (m), or None, with the forklift at
        `M_wf` (4x4 matrix of `T_world_forklift`); `boxes` are `_fork_in_pallet(p, M_wf)` when at hand.
        Separating axes on the floor plane (the pallet's x and y, each box's edges) plus the z ranges,
        every box against every part at once."""
        corners, z = boxes if boxes is not None else self._fork_in_pallet(p, M_wf)
        lo, hi = p.part_lo, p.part_hi
        z_overlap = (np.minimum(z[:, None, 1], hi[None, :, 2]) - np.maximum(z[:, None, 0], lo[None, :, 2])) > tol
        # The pallet's own axes first, on the boxes' bounding boxes (the same figures as their corners'
        # projections): most steps end here, with the forks beside or in front of every part.
        box_lo, box_hi = corners.min(axis=1)[:, None], corners.max(axis=1)[:, None]  # (B, 1, 2)
        floor = np.minimum(box_hi, hi[None, :, :2]) - np.maximum(box_lo, lo[None, :, :2])  # (B, M, 2)
        z_overlap &= (floor > tol).all(axis=-1)
        if not z_overlap.any():
            return None
        ex, ey = corners[:, 1] - corners[:, 0], corners[:, 3] - corners[:, 0]
        ex = ex / np.linalg.norm(ex, axis=-1, keepdims=True)
        ey = ey / np.linalg.norm(ey, axis=-1, keepdims=True)
        unit = np.broadcast_to(np.eye(2), (len(corners), 2, 2))
        axes = np.concatenate([unit, ex[:, None], ey[:, None]], axis=1)  # (B, 4, 2)
        proj = corners @ axes.transpose(0, 2, 1)  # (B, 4 corners, 4 axes)
        ax, ay = axes[:, :, None, None, 0], axes[:, :, None, None, 1]
        parts = p.part_x * ax + p.part_y * ay  # (B, 4 axes, M, 4 corners)
        depth = np.minimum(proj.max(axis=1)[:, :, None], parts.max(axis=-1))
        depth -= np.maximum(proj.min(axis=1)[:, :, None], parts.min(axis=-1))
        overlap = z_overlap & (depth > tol).all(axis=1)  # (B, M)
        rows = np.flatnonzero(overlap.any(axis=1))
        if not rows.size:
            return None
        b = int(rows[0])
        return f"{self._fork_set().names[b]} hit {p.parts[int(np.argmax(overlap[b]))].name}"

    def _try_lift(self, p: SimPallet, M_wf: np.ndarray, boxes: tuple[np.ndarray, np.ndarray] | None = None) -> bool:
        """Attach the pallet when both forks are deep in the pockets and touch the deck from below, with the
        forklift at `M_wf` (4x4 matrix of `T_world_forklift`; `boxes`: `_fork_in_pallet(p, M_wf)`)."""
        corners, z = boxes if boxes is not None else self._fork_in_pallet(p, M_wf)
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
        lowered = M_wf.copy()
        lowered[:3, 3] += lowered[:3, 2] * (-0.002 - (z[:2, 1].max() - pocket_top))
        if self._contact(p, lowered) is not None:
            return False
        T_wf = self.T_world_forklift3
        T_forks_world = (T_wf @ SE3.from_translation(0, 0, self.fork_height)).inv()
        lift = SE3.from_translation(0.0, 0.0, self.forks.thickness - pocket_top)
        T_forks_pallet = T_forks_world @ p.T_world_pallet
        planar = T_forks_pallet.to_se2().to_se3()  # the pallet settles level on the forks
        p.T_forks_pallet = lift @ planar
        p.carried = p.lifted = True
        return True
