"""The stand-in truck's simulated truth, live over Foxglove WebSocket (`palletpilot sim serve ... --ros --foxglove`).

`StandInView` serves what the simulator behind the stand-in knows, on the channels of `palletpilot run
--foxglove` (`executor.recording_channels`; one `executor.recording.Recorder` without a file, so the
shipped Foxglove layout shows it too), fed from the stand-in's control loop (`StandIn.run(stop, on_tick=
view.tick)`), stamped with wall time:

- `/tf` (`map -> base_link`: the true forklift pose; `base_link -> camera`: the true camera mount at the
  lift height) and `/sim/true_pose`, every `EVERY_TICKS` control ticks (10 Hz at the 20 Hz control rate);
- `/vehicle/state`: true pose (m, deg), speed (m/s), steering (deg), the drive command's speed (m/s), fork
  height (m), load; `state` is the truck controller's (`driving`, `command_timeout`, `emergency_stop`),
  `task` -1 (the stand-in knows no tasks); at the same rate;
- `/scene/truck` (forks at their height, load), `/scene/safety_fields` (the scanners' fields, intrusions):
  on change; `/scene/beams`, `/vehicle/beams`: at 2 Hz (`BEAMS_EVERY`);
- `/scene/true_pallets`, `/scene/obstacles` (`executor.recording_sim.SimFeed`): on change, walking people
  at 1 Hz; `/scene/roadmap`, `/roadmap/graph`: at the start.
- A viewer may connect at any time and Foxglove WebSocket keeps nothing: the scenes that change seldom
  (roadmap, pallets, obstacles, truck, safety fields) are sent again every `STATIC_EVERY_S` (2 s).

The channels of the executor's own view (plans, MPC horizon, estimates, camera, events, reports) are
advertised, as by any `Recorder`, and stay silent here. The view only reads the simulator: it never
draws from its random generators (localization noise, camera), so the stand-in behaves as without it.

Public API: `StandInView`, `EVERY_TICKS`, `STATIC_EVERY_S`.
"""

from __future__ import annotations

import math
import time
from typing import TYPE_CHECKING, Any

from palletpilot.control.safety import safety_fields
from palletpilot.executor.adapters.mcap import recording_scene as scene
from palletpilot.executor.adapters.mcap.recording import Recorder
from palletpilot.executor.adapters.mcap.recording_channels import BEAMS_EVERY, SIM_EPOCH_NS, finite
from palletpilot.executor.adapters.mcap.recording_sim import SimFeed
from palletpilot.geometry import SE3

if TYPE_CHECKING:
    from palletpilot.executor.apps.standin.truck import StandIn
    from palletpilot.sim.simulator import Simulator

EVERY_TICKS = 2
"""`/tf`, `/sim/true_pose` and `/vehicle/state` every this many control ticks (10 Hz at 20 Hz)."""
STATIC_EVERY_S = 2.0
"""The seldom-changing scenes are sent again this often (wall s) for viewers that connect later."""


class StandInView:
    """The live view of a stand-in's simulator (module docstring). `port` 0 takes any free port (see
    `port`); a port that cannot be served raises `executor.recording_channels.RecordingError`."""

    def __init__(self, sim: Simulator, port: int, host: str = "127.0.0.1") -> None:
        self.sim = sim
        self.rec = Recorder(None, port, wall=True, host=host)
        self.feed = SimFeed(sim)
        self._ticks = 0
        self._truck_key: Any = None
        self._safety_key: Any = None
        self._last_static = time.monotonic()
        self._errors: list[str] = []
        ns = self._ns()
        roadmap = sim.roadmap
        nodes = [scene.node_json(n) for n in roadmap.nodes()]
        edges = [scene.edge_json(e) for e in roadmap.edges()]
        self.rec.log_json("/roadmap/graph", {"name": roadmap.name, "nodes": nodes, "edges": edges}, ns)
        self._roadmap = scene.roadmap_update(roadmap, ns, temporary=False)  # built once: the map is fixed
        self._static(ns)

    @property
    def port(self) -> int:
        """The port it serves on."""
        port = self.rec.port
        assert port is not None  # the recorder was made with a server
        return port

    def _ns(self) -> int:
        """Wall time now as a log time (ns): the recorder stamps `SIM_EPOCH_NS` + the time it is given."""
        return self.rec.ns(time.time() - SIM_EPOCH_NS * 1e-9)

    def _static(self, ns: int) -> None:
        """The scenes that change seldom, whole: roadmap, pallets and obstacles, truck and safety fields."""
        self.rec.log_scene("/scene/roadmap", self._roadmap, ns)
        self.feed.start(self.rec, ns)  # true pallets, obstacles
        self._truck_key = self._safety_key = None

    def tick(self, standin: StandIn) -> None:
        """One control tick of `standin` (its loop's hook): log what is due. Errors end the view (one line
        in `errors`), never the stand-in."""
        self._ticks += 1
        if not self.rec.active:
            return
        try:
            self._tick(standin)
        except Exception as exc:
            self._errors.append(f"foxglove: the live view stopped: {type(exc).__name__}: {exc}")
            self.rec.close()

    @property
    def errors(self) -> list[str]:
        """What went wrong in the view (one line each); the view stopped at the first."""
        return self._errors + self.rec.errors

    def _tick(self, standin: StandIn) -> None:
        sim, rec, tick = self.sim, self.rec, self._ticks
        ns = self._ns()
        if time.monotonic() - self._last_static >= STATIC_EVERY_S:
            self._last_static = time.monotonic()
            self._static(ns)
        if tick % EVERY_TICKS == 0:
            self._pose(standin, ns)
            self.feed.tick(rec, ns, tick // EVERY_TICKS)
        height, loaded = sim.fork_height, sim.load_detected()
        key = (round(height, 3), loaded)
        if key != self._truck_key:
            self._truck_key = key
            rec.log_scene("/scene/truck", scene.truck_update(sim.vehicle, sim.forks, height, loaded, ns), ns)
        self._safety(ns)
        if tick % BEAMS_EVERY == 0 and standin.last_ranges is not None:
            left, right = standin.last_ranges  # as published this tick: the view casts no rays of its own
            beams = {"left_m": finite(left, 4), "right_m": finite(right, 4), "read_by": "sim"}
            rec.log_json("/vehicle/beams", beams, ns)
            rec.log_scene("/scene/beams", scene.beams_update(sim.forks, height, (left, right), ns), ns)

    def _pose(self, standin: StandIn, ns: int) -> None:
        """`/tf` and `/vehicle/state` from the truth."""
        sim, rec = self.sim, self.rec
        pose, height = sim.true_pose, sim.fork_height
        mount = SE3.from_translation(0.0, 0.0, height) @ sim.T_forklift_camera_true
        tf = scene.tf_tree(ns, pose, mount)
        assert tf is not None  # both transforms are known
        rec.ch_tf.log(tf, log_time=ns)
        if standin.estop_latched:
            state = "emergency_stop"
        elif standin.timeout_brake:
            state = "command_timeout"
        else:
            state = "driving"
        doc = {
            "t_s": round(sim.time, 3),
            "x_m": round(pose.x, 4),
            "y_m": round(pose.y, 4),
            "yaw_deg": round(math.degrees(pose.yaw), 3),
            "speed_mps": finite(sim.speed, 4),
            "steering_deg": finite(math.degrees(sim.steering), 3),
            "commanded_speed_mps": finite(standin.command_speed, 4),
            "fork_height_m": finite(height, 4),
            "loaded": bool(sim.load_detected()),
            "lateral_error_m": None,
            "heading_error_deg": None,
            "solve_ms": None,
            "state": state,
            "task": -1,
        }
        rec.log_json("/vehicle/state", doc, ns)

    def _safety(self, ns: int) -> None:
        """`/scene/safety_fields` when the fields or their intrusions changed."""
        sim = self.sim
        params = sim.vehicle
        if params.safety_scanner is None:
            return
        s = sim.safety_state()
        speed = abs(sim.speed)
        key = (s.field_set, s.direction, s.warning, s.protective_stop, s.intrusions, round(speed, 1))
        if key == self._safety_key:
            return
        self._safety_key = key
        fields = safety_fields(params, speed, s.direction, s.field_set, sim.forks.tip_x)
        z = params.safety_scanner.scan_height
        update = scene.safety_update(fields, s.warning, s.protective_stop, s.intrusions, z, ns)
        self.rec.log_scene("/scene/safety_fields", update, ns)

    def close(self) -> None:
        """Stop the server (idempotent)."""
        self.rec.close()
