"""The stand-in truck's camera, rendered in a child process (`palletpilot sim serve SCENARIO --ros`).

A frame of the simulated RGB-D camera takes about 40 ms of ray casting and numpy shading that holds the
GIL for much of it. Rendered in the stand-in's own process it delayed the DDS receive thread, and with it
the receipt of drive commands, by up to a frame (issue #19). `CameraProcess` renders in a child process
('spawn' start method: a fresh interpreter, no forked DDS or Open3D threads) that holds its own copy of
the world, a `Simulator` built from the same scenario and seed, and so the same static world, camera
mount (`T_forklift_camera_true`), camera model, noise settings and camera noise generator.

Per frame the stand-in sends a `CameraState`: what `Simulator.grab()` depends on that changes while it
runs (the true forklift pose `T_world_forklift` (m, rad), the fork height (m), every pallet's true
`T_world_pallet` with its loaded and carried flags, the walking people's walk times (s), and the
simulated time (s)). The child puts its simulator in that state (`apply_camera_state`) and calls its
`grab()`; since the parent's simulator never grabs, the child's camera generator draws exactly the
numbers the parent's would have, and the frames are those `sim.grab()` would give for the same states
(deterministic per seed). `tests/test_ros_standin.py` checks it frame for frame.

The child then either publishes the frame itself (`publish=True`: colour `rgb8`, depth `16UC1` in mm,
`camera_info`, on the robot file's camera topics, through its own transport of the robot file's kind and
domain) or hands the `FrameBundle` back (`publish=False`; the stand-in publishes it, for an in-process
transport). Header stamps are the state's wall-clock time (`time.time()`, s: the exposure), frame id the
robot file's camera frame. One request is in flight at a time: the stand-in asks for the next frame only
when the last is done, so a slow render lowers the frame rate and never queues stale states.

The child always dies with the stand-in: it reads its requests from the socket, which reaches end of
file when the parent exits in any way (SIGTERM, SIGINT, SIGKILL); it also checks that its parent is still
its parent (`os.getppid`) at least every `PARENT_CHECK_S`. It ignores SIGINT (a terminal's Ctrl-C reaches
the whole process group; the stand-in ends it by closing the socket). Its stdout goes nowhere (the
stand-in's stdout carries the ready line); its stderr is the stand-in's.

Public API: `CameraState`, `camera_state(sim)`, `apply_camera_state(sim, state)`, `camera_messages`, `CameraProcess`,
`CameraProcessError`.
"""

from __future__ import annotations

import contextlib
import os
import signal
import socket
import subprocess
import sys
import time
import traceback
from collections.abc import Sequence
from dataclasses import dataclass
from multiprocessing.connection import Connection
from typing import TYPE_CHECKING, Any

from palletpilot.executor.adapters.processes import end_process
from palletpilot.geometry import SE2, SE3, PalletpilotError

if TYPE_CHECKING:
    from palletpilot.executor.adapters.ros.config import RobotConfig
    from palletpilot.perception.frames import FrameBundle
    from palletpilot.sim.scenario import Scenario
    from palletpilot.sim.simulator import Simulator

PARENT_CHECK_S = 0.5
"""The child checks at least this often (s) that its parent lives (besides the socket's end of file)."""
START_TIMEOUT_S = 60.0
"""How long `CameraProcess.wait_ready` waits for the child's world and transport (s)."""
CHILD_NICENESS = 5
"""The child's scheduling priority below the stand-in's and the executor's (`os.nice`): on a busy computer
the truck's command receipt, its state topics and the executor's control loop come before the camera, whose
frame rate drops instead (a real camera is hardware of its own and never slows the truck controller)."""
STOP_TIMEOUT_S = 3.0
"""How long `CameraProcess.close` waits for the child to exit before it terminates it (s)."""


class CameraProcessError(PalletpilotError):
    """The camera child failed (its world, its transport, a frame) or died."""


@dataclass(frozen=True)
class CameraState:
    """What a camera frame of `Simulator.grab()` depends on that changes while the stand-in runs.

    `stamp_s`: wall-clock time of the state (`time.time()`, s), the frame's header stamp; `sim_time_s`:
    the simulator's time (s), the bundle's `stamp_s`; `T_world_forklift`: the true forklift pose (world
    frame, m and rad); `fork_height_m`: fork bottoms above the floor (m); `pallets`: each pallet's true
    `T_world_pallet` (world frame), loaded and carried flags, in the simulator's order; `walk_t_s`: how
    long each clutter item has walked (s).
    """

    stamp_s: float
    sim_time_s: float
    T_world_forklift: SE2
    fork_height_m: float
    pallets: tuple[tuple[SE3, bool, bool], ...]
    walk_t_s: tuple[float, ...]


def camera_state(sim: Simulator, stamp_s: float | None = None) -> CameraState:
    """The camera-relevant state of `sim` now; `stamp_s` defaults to `time.time()` (s)."""
    return CameraState(
        stamp_s=time.time() if stamp_s is None else stamp_s,
        sim_time_s=float(sim.time),
        T_world_forklift=sim.forklift.state.pose,
        fork_height_m=float(sim.forklift.state.fork_height),
        pallets=tuple((p.T_world_pallet, bool(p.loaded), bool(p.carried)) for p in sim.pallets),
        walk_t_s=tuple(float(t) for t in sim.walk_t),
    )


def _resting_key(sim: Simulator) -> tuple[tuple[bytes, bool], ...]:
    """What the renderer's static scene holds of the pallets: the resting ones' poses and loads."""
    return tuple((p.T_world_pallet.matrix.tobytes(), p.loaded) for p in sim.pallets if not p.carried)


def apply_camera_state(sim: Simulator, state: CameraState) -> None:
    """Put `sim` in `state` for `grab()`: forklift pose and fork height, pallets, walkers, time.

    The render and beam scenes (which hold the resting pallets) are rebuilt only when a pallet was lifted,
    set down or moved while resting, as the simulator itself does when it steps. Raises
    `CameraProcessError` when the state's pallets or walkers do not match this simulator's scenario.
    """
    if len(state.pallets) != len(sim.pallets) or len(state.walk_t_s) != len(sim.walk_t):
        raise CameraProcessError(
            f"camera state of {len(state.pallets)} pallets and {len(state.walk_t_s)} walkers, the scenario has "
            f"{len(sim.pallets)} and {len(sim.walk_t)}"
        )
    before = _resting_key(sim)
    sim.time = state.sim_time_s
    sim.forklift.state.pose = state.T_world_forklift
    sim.forklift.state.fork_height = state.fork_height_m
    for p, (T_world_pallet, loaded, carried) in zip(sim.pallets, state.pallets, strict=True):
        p.T_world_pallet, p.loaded, p.carried = T_world_pallet, loaded, carried
    sim.walk_t = list(state.walk_t_s)
    if _resting_key(sim) != before:
        sim.static_changed()  # the simulator's own hook for a changed set of resting pallets


# -- the child ------------------------------------------------------------------------------------------------
def camera_messages(frame: FrameBundle, config: RobotConfig, stamp_s: float) -> list[tuple[str, Any, Any]]:
    """(topic, message, QoS) of a frame: colour `rgb8`, depth `16UC1` (mm), `camera_info`."""
    from palletpilot.executor.adapters.ros import messages as msgs
    from palletpilot.executor.adapters.ros.camera import camera_info, depth_image, rgb_image

    cam = config.camera
    header = msgs.Header(stamp=msgs.stamp(stamp_s), frame_id=config.frames.camera)
    out: list[tuple[str, Any, Any]] = []
    if frame.rgb is not None:
        out.append((cam.color.name, rgb_image(frame.rgb, header), cam.color.qos.spec()))
    out.append((cam.depth.name, depth_image(frame.depth, header), cam.depth.qos.spec()))
    out.append((cam.info.name, camera_info(frame.K, frame.width, frame.height, header), cam.info.qos.spec()))
    return out


def _child(conn: Connection) -> None:
    """The child's work: take the set-up message, build the world (and the transport), then render each
    requested state.

    Set-up: `(scenario, seed, config, publish, parent pid)`. Replies on `conn`: `("ready",)` once, then per
    request `("frame", render_ms, bundle or None)`, or `("error", one line)` before it exits. Exits on end
    of file, a `None` request, or a lost parent.
    """
    signal.signal(signal.SIGINT, signal.SIG_IGN)
    with contextlib.suppress(OSError):
        os.nice(CHILD_NICENESS)
    transport = None
    try:
        scenario, seed, config, publish, parent = conn.recv()
        from palletpilot.sim.simulator import Simulator

        sim = Simulator(scenario, seed=seed)
        if publish:
            from palletpilot.executor.adapters.ros.messages import CameraInfo, Image
            from palletpilot.executor.adapters.ros.transport import open_transport

            transport = open_transport(config.transport, config.domain_id, node_name="palletpilot_standin_camera")
            cam = config.camera
            for spec, msg_type in ((cam.color, Image), (cam.depth, Image), (cam.info, CameraInfo)):
                transport.advertise(spec.name, msg_type, spec.qos.spec())
        conn.send(("ready",))
        while os.getppid() == parent:
            if not conn.poll(PARENT_CHECK_S):
                continue
            state = conn.recv()
            if state is None:
                break
            t0 = time.perf_counter()
            apply_camera_state(sim, state)
            frame = sim.grab()
            if transport is not None:
                for topic, msg, qos in camera_messages(frame, config, state.stamp_s):
                    transport.publish(topic, msg, qos)
            conn.send(("frame", (time.perf_counter() - t0) * 1e3, None if publish else frame))
    except (EOFError, BrokenPipeError, ConnectionResetError, KeyboardInterrupt):
        pass  # the stand-in is gone or ends us
    except PalletpilotError as exc:
        _send_error(conn, str(exc))
    except Exception as exc:  # a bug or a library failure: one line back, the trace on stderr
        traceback.print_exc()
        _send_error(conn, f"{type(exc).__name__}: {exc}")
    finally:
        if transport is not None:
            transport.close()
        conn.close()


def main(argv: Sequence[str] | None = None) -> int:
    """`python -m palletpilot.executor.apps.standin.camera FD`: the camera child on socket FD (inherited)."""
    args = sys.argv[1:] if argv is None else argv
    if len(args) != 1 or not args[0].isdigit():
        print(
            "usage: python -m palletpilot.executor.apps.standin.camera FD (started by the stand-in)",
            file=sys.stderr,
        )
        return 2
    _child(Connection(int(args[0])))
    return 0


def _send_error(conn: Connection, line: str) -> None:
    try:
        conn.send(("error", line))
    except (OSError, EOFError):
        pass


# -- the parent's handle ----------------------------------------------------------------------------------------
class CameraProcess:
    """The camera child of a stand-in (module docstring): `request(state)` when `idle`, `poll()` each tick.

    `scenario` and `seed` must be the stand-in simulator's (`sim.scenario`, `sim.seed`); `publish`: the
    child publishes on `config`'s camera topics itself (True) or hands the bundles back (False).
    """

    def __init__(self, scenario: Scenario, seed: int, config: RobotConfig, publish: bool = True) -> None:
        ours, theirs = socket.socketpair()
        self.publish = publish
        try:
            self._proc = subprocess.Popen(
                [sys.executable, "-m", "palletpilot.executor.apps.standin.camera", str(theirs.fileno())],
                pass_fds=(theirs.fileno(),),
                stdin=subprocess.DEVNULL,
                stdout=subprocess.DEVNULL,
            )
        except OSError as exc:
            ours.close()
            raise CameraProcessError(f"camera child: cannot start {sys.executable}: {exc}") from None
        finally:
            theirs.close()  # the child holds its own copy: it sees end of file when we go, and we when it does
        self._conn = Connection(ours.detach())
        self._conn.send((scenario, seed, config, publish, os.getpid()))
        self.ready = False
        self.busy = False
        self.frames = 0
        self.render_ms: list[float] = []
        self.error: str | None = None

    @property
    def pid(self) -> int | None:
        """The child's process id."""
        return self._proc.pid

    @property
    def idle(self) -> bool:
        """True when the child is up, has no request in flight and has not failed."""
        return self.ready and not self.busy and self.error is None

    def request(self, state: CameraState) -> None:
        """Ask for a frame of `state` (only when `idle`; non-blocking: a few hundred bytes on the socket)."""
        if not self.idle:
            raise CameraProcessError("camera child: a frame was requested while it is not idle")
        try:
            self._conn.send(state)
        except (OSError, EOFError) as exc:
            self._fail(f"camera child: the socket is closed ({exc})")
            return
        self.busy = True

    def poll(self, timeout_s: float = 0.0) -> list[FrameBundle]:
        """Take the child's replies (waiting up to `timeout_s`, s, for the first): the bundles handed back
        (with `publish=False`). Sets `error` (one line) when the child failed or died."""
        bundles: list[FrameBundle] = []
        if self.error is not None or self._conn.closed:
            return bundles
        try:
            while self._conn.poll(timeout_s):
                timeout_s = 0.0
                reply = self._conn.recv()
                if reply[0] == "ready":
                    self.ready = True
                elif reply[0] == "frame":
                    self.busy = False
                    self.frames += 1
                    if len(self.render_ms) < 1_000_000:
                        self.render_ms.append(float(reply[1]))
                    if reply[2] is not None:
                        bundles.append(reply[2])
                else:
                    self._fail(f"camera child: {reply[1]}")
                    break
        except (EOFError, OSError):
            self._fail(f"camera child exited (code {self._proc.poll()})")
        return bundles

    def wait_ready(self, timeout_s: float = START_TIMEOUT_S) -> None:
        """Block until the child is up (its world built, its transport open); `CameraProcessError` if not."""
        deadline = time.monotonic() + timeout_s
        while not self.ready and self.error is None and time.monotonic() < deadline:
            self.poll(min(0.1, max(deadline - time.monotonic(), 0.0)))
        if self.error is not None:
            raise CameraProcessError(self.error)
        if not self.ready:
            raise CameraProcessError(f"camera child not ready after {timeout_s:g} s")

    def _fail(self, line: str) -> None:
        if self.error is None:
            self.error = line
        self.busy = False

    def close(self) -> None:
        """End the child (a `None` request and the socket closed; terminate, then kill, if it lingers)."""
        if not self._conn.closed:
            try:
                self._conn.send(None)
            except (OSError, EOFError):
                pass
            self._conn.close()
        try:
            self._proc.wait(STOP_TIMEOUT_S)
        except subprocess.TimeoutExpired:
            end_process(self._proc, STOP_TIMEOUT_S)

    def __enter__(self) -> CameraProcess:
        return self

    def __exit__(self, *exc: object) -> None:
        self.close()


if __name__ == "__main__":
    from palletpilot.executor.apps.standin import camera as standin_camera  # the module proper: one copy of its classes

    sys.exit(standin_camera.main())
