"""Run recordings: the simulator's truth (`SimFeed`): the true pose, pallets, racks, boxes and people.

Public API: `SimFeed`.
"""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

import numpy as np
from foxglove.messages import PoseInFrame

from palletpilot.executor.adapters.mcap import recording_scene as scene
from palletpilot.executor.adapters.mcap.recording_channels import OBSTACLES_EVERY, PALLETS_EVERY

if TYPE_CHECKING:
    from palletpilot.executor.adapters.mcap.recording import Recorder
    from palletpilot.sim.simulator import Simulator


class SimFeed:
    """The simulator's truth for a recording: the true pose, the true pallets (moving while carried),
    the racks, boxes and people; and, at the end, the contacts and the pallets' report records."""

    def __init__(self, sim: Simulator) -> None:
        self.sim = sim
        self._pallet_key: Any = None
        self._walkers = any(c.path for c in sim.scenario.clutter)

    def _pallets_key(self) -> tuple[Any, ...]:
        return tuple((p.carried, p.lifted, *np.round(p.T_world_pallet.t, 3)) for p in self.sim.pallets)

    def start(self, rec: Recorder, ns: int) -> None:
        """The scene at the start: pallets, obstacles."""
        self._pallets(rec, ns, force=True)
        rec.log_scene("/scene/obstacles", scene.obstacles_update(self.sim.obstacle_outlines(), ns), ns)

    def tick(self, rec: Recorder, ns: int, tick: int) -> None:
        """One tick: the true pose; pallets when they changed (4 Hz while one is carried); walking people."""
        pose = self.sim.true_pose
        rec.ch_true_pose.log(
            PoseInFrame(timestamp=scene.stamp(ns), frame_id=scene.MAP, pose=scene.pose_se2(pose)), log_time=ns
        )
        rec.count_message("/sim/true_pose")
        carried = any(p.carried for p in self.sim.pallets)
        if not carried or tick % PALLETS_EVERY == 0:
            self._pallets(rec, ns)
        if self._walkers and tick % OBSTACLES_EVERY == 0:
            rec.log_scene("/scene/obstacles", scene.obstacles_update(self.sim.obstacle_outlines(), ns), ns)

    def _pallets(self, rec: Recorder, ns: int, force: bool = False) -> None:
        key = self._pallets_key()
        if force or key != self._pallet_key:
            self._pallet_key = key
            rec.log_scene("/scene/true_pallets", scene.true_pallets_update(self.sim.pallets, ns), ns)

    def finish(self, rec: Recorder, ns: int) -> dict[str, Any]:
        """The final scene; the report's simulator figures (`collisions`, `pallets`, `seed`)."""
        self._pallets(rec, ns, force=True)
        return {"seed": self.sim.seed, "collisions": self.sim.collisions, "pallets": self.sim.pallet_records()}
