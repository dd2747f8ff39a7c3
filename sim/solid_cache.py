"""What a `Simulator` keeps between steps so that a step costs little, with nothing it checks left out.

- The static solids (walls, rack uprights and beams, standing people and boxes) as one `SolidSet`,
  built once: they never move.
- The world the truck can meet (static, walking people, resting pallets and their loads) as a
  `SolidSet`, rebuilt only when a resting pallet moved, was lifted or set down, or a person walked.
- The truck's body, forks and backrest as boxes in the forklift frame for each lift height, placed in
  the world by the pose with one array operation (`truck`).
- The truck's pose as an SE3 (`pose3`) and as a 4x4 matrix (`matrix4`), built once per pose rather
  than once per use.

Every entry is keyed by what it is built from (poses are compared by identity: `SE2` and `SE3` are
immutable, so a new pose is a new object), so a stale entry can never be used; `clear()` drops all.
Poses in the world frame, sizes in metres.

Public API: `SolidCache`, `WorldSolids`.
"""

from __future__ import annotations

import math
from collections.abc import Callable, Sequence
from dataclasses import dataclass
from typing import TYPE_CHECKING, Any

import numpy as np

from palletpilot.geometry import SE2, SE3
from palletpilot.sim.contacts import EMPTY, LocalBoxes, Solid, SolidSet

if TYPE_CHECKING:
    from palletpilot.sim.pallets import ForkBoxes, SimPallet

_MEMO_LIMIT = 256  # lift heights remembered (the mast moves through many while lifting)


@dataclass(frozen=True)
class WorldSolids:
    """The solids the truck can meet now (world frame) and which of them are resting pallets (the
    pallet boxes, not their loads: the forks meet those through their boards and blocks instead)."""

    solids: SolidSet
    pallet: np.ndarray  # (N,) bool


class SolidCache:
    """The caches of one simulator (see the module's docstring)."""

    def __init__(self, fixed: Sequence[Solid]) -> None:
        self.static = SolidSet.of(fixed)
        self.clear()

    def clear(self) -> None:
        """Forget everything but the static solids."""
        self._world_key: Any = None
        self._world = WorldSolids(self.static, np.zeros(len(self.static), dtype=bool))
        self._pose_key: SE2 | None = None
        self._pose3 = SE3.identity()
        self._matrix_key: SE2 | None = None
        self._matrix = np.eye(4)
        self._forks: dict[float, ForkBoxes] = {}
        self._truck: dict[float, tuple[LocalBoxes, LocalBoxes, LocalBoxes]] = {}

    def pose3(self, pose: SE2) -> SE3:
        """`pose.to_se3()`, built once per pose."""
        if pose is not self._pose_key:
            self._pose_key, self._pose3 = pose, pose.to_se3()
        return self._pose3

    def matrix4(self, pose: SE2) -> np.ndarray:
        """The 4x4 matrix of `pose` on the floor (`pose.to_se3().matrix` up to rounding), once per pose;
        read-only."""
        if pose is not self._matrix_key:
            c, s = math.cos(pose.yaw), math.sin(pose.yaw)
            m = np.array([[c, -s, 0.0, pose.x], [s, c, 0.0, pose.y], [0.0, 0.0, 1.0, 0.0], [0.0, 0.0, 0.0, 1.0]])
            m.setflags(write=False)
            self._matrix_key, self._matrix = pose, m
        return self._matrix

    def world(
        self, pallets: Sequence[SimPallet], walkers: list[Solid], solids_of: Callable[[SimPallet], list[Solid]]
    ) -> WorldSolids:
        """Static solids, then `walkers`, then each resting pallet's `solids_of(p)`, in that order."""
        key = (tuple((p.T_world_pallet, p.loaded) for p in pallets if not p.carried), tuple(walkers))
        if key != self._world_key:
            resting = [s for p in pallets if not p.carried for s in solids_of(p)]
            moving = SolidSet.of(walkers) + SolidSet.of(resting) if walkers or resting else EMPTY
            solids = self.static + moving
            pallet = np.array([k == "pallet" for k in solids.kinds], dtype=bool)
            self._world_key, self._world = key, WorldSolids(solids, pallet)
        return self._world

    def fork_boxes(self, height: float, build: Callable[[], ForkBoxes]) -> ForkBoxes:
        """The forks' and backrest's boxes at lift `height` (m): `build()` once per height."""
        boxes = self._forks.get(height)
        if boxes is None:
            if len(self._forks) >= _MEMO_LIMIT:
                self._forks.clear()
            boxes = self._forks[height] = build()
        return boxes

    def truck(self, pose: SE2, body: tuple[np.ndarray, np.ndarray], forks: ForkBoxes, carried: list[Solid]) -> SolidSet:
        """The truck's parts in the world: the body (`body`: lo, hi in the forklift frame), the `carried`
        pallets and loads (world solids), then the forks and backrest, in that order."""
        entry = self._truck.get(forks.height)
        if entry is None:
            if len(self._truck) >= _MEMO_LIMIT:
                self._truck.clear()
            kinds = ("body", *forks.names)
            lo, hi = np.vstack([body[0], forks.lo]), np.vstack([body[1], forks.hi])
            parts = (LocalBoxes.of(kinds, lo, hi), LocalBoxes.of(kinds[:1], lo[:1], hi[:1]))
            entry = self._truck[forks.height] = (*parts, LocalBoxes.of(kinds[1:], lo[1:], hi[1:]))
        every, hull, tools = entry
        if not carried:
            return every.placed(pose)
        return hull.placed(pose) + SolidSet.of(carried) + tools.placed(pose)
