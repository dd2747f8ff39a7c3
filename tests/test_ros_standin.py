"""The stand-in truck's parts (`palletpilot sim serve --ros`).

1. The camera child (`executor.ros.standin_camera`): its frames are exactly the stand-in simulator's own
   `grab()` for the same states (every noise source on, a pallet lifted on the way), and it dies with its
   parent, even one killed with SIGKILL.
2. The live view (`sim serve --ros --foxglove 0`): a Foxglove WebSocket client is accepted, the truth's
   channels are advertised and `/vehicle/state` streams; a port in use is one line and exit 2.
"""

from __future__ import annotations

import json
import os
import queue
import signal
import socket
import struct
import subprocess
import sys
import textwrap
import threading
import time
from pathlib import Path

import numpy as np
import pytest

from palletpilot.executor.adapters.mcap.recording_channels import TOPICS
from palletpilot.executor.adapters.ros.config import load_robot
from palletpilot.executor.apps.standin.camera import (
    CameraProcess,
    CameraState,
    apply_camera_state,
    camera_state,
)
from palletpilot.geometry import SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.frames import FrameBundle
from palletpilot.sim.scenario import Scenario
from palletpilot.sim.simulator import Simulator

ROBOT = bundled_path("missions", "robot.yaml")


def _scenario() -> Scenario:
    """Every random source of the camera on: mount perturbation, depth, label and RGB noise, lighting."""
    scenario = Scenario.model_validate(
        {
            "map": "warehouse.yaml",
            "start": "floor_b2_pre",
            "seed": 11,
            "camera": {
                "perturbation": {"xyz_sigma": 0.003, "angle_sigma_deg": 0.3},
                "noise": {"label_noise": True, "rgb_sigma": 2.0, "lighting_variation": True},
            },
            "pallets": [{"node": "floor_b2", "dy": 0.05, "dyaw_deg": 3.0, "loaded": True}],
        }
    )
    scenario.folder = bundled_path("missions")
    return scenario


def _same(a: FrameBundle, b: FrameBundle) -> bool:
    arrays = all(np.array_equal(getattr(a, k), getattr(b, k)) for k in ("depth", "labels", "rgb", "K"))
    truth = a.truth.keys() == b.truth.keys() and all(np.array_equal(a.truth[k], b.truth[k]) for k in a.truth)
    return arrays and truth and a.stamp_s == b.stamp_s and a.fork_height == b.fork_height


def _states(sim: Simulator) -> list[CameraState]:
    """Three states of `sim`, each grabbed by `sim` too (`sim.frames`): at the start, after driving with the
    forks rising, and with the pallet lifted off its place (resting pallets change: the scene is rebuilt)."""
    states = [camera_state(sim)]
    for _ in range(6):
        sim.drive(0.4, 0.05)
        sim.set_fork_height(0.2)
        sim.step(0.05)
    states.append(camera_state(sim))
    p = sim.pallets[0]
    p.T_world_pallet = SE3.from_translation(0.0, 0.0, 0.12) @ p.T_world_pallet
    p.carried, p.T_forks_pallet = True, SE3.identity()
    sim._static_changed()  # as the simulator does when it lifts a pallet
    states.append(camera_state(sim))
    return states


def test_child_frames_are_the_simulators_own() -> None:
    scenario = _scenario()
    truck = Simulator(scenario)
    with CameraProcess(scenario, truck.seed, load_robot(ROBOT), publish=False) as camera:
        camera.wait_ready()
        expected, got = [], []
        for state in _states(truck):
            apply_camera_state(truck, state)  # a no-op here: the state is the truck's own
            expected.append(truck.grab())
            camera.request(state)
            deadline = time.monotonic() + 30.0
            while camera.busy and time.monotonic() < deadline:
                got += camera.poll(0.5)
        assert camera.error is None and camera.frames == 3
    assert len(got) == 3
    assert all(_same(g, e) for g, e in zip(got, expected, strict=True))
    assert got[2].labels is not None and got[1].labels is not None and not np.array_equal(got[2].labels, got[1].labels)


def test_child_dies_with_its_parent_even_on_sigkill() -> None:
    parent_code = textwrap.dedent(
        f"""
        import time
        from palletpilot.executor.adapters.ros.config import load_robot
        from palletpilot.executor.apps.standin.camera import CameraProcess
        from palletpilot.sim.scenario import Scenario
        from palletpilot.geometry.fileio import bundled_path
        sc = Scenario.model_validate({{"map": "warehouse.yaml", "start": "b1"}})
        sc.folder = bundled_path("missions")
        camera = CameraProcess(sc, 1, load_robot({str(ROBOT)!r}), publish=False)
        camera.wait_ready()
        print(camera.pid, flush=True)
        time.sleep(60)
        """
    )
    parent = subprocess.Popen([sys.executable, "-c", parent_code], stdout=subprocess.PIPE, text=True)
    try:
        assert parent.stdout is not None
        child = int(parent.stdout.readline())
        parent.send_signal(signal.SIGKILL)
        parent.wait(timeout=10)
        deadline = time.monotonic() + 5.0
        while time.monotonic() < deadline and _running(child):
            time.sleep(0.05)
        assert not _running(child), f"camera child {child} outlived its parent (SIGKILL)"
    finally:
        if parent.poll() is None:
            parent.kill()
            parent.wait()


def _running(pid: int) -> bool:
    """True while `pid` exists and has not exited (a zombie waiting for init to reap it has exited)."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except FileNotFoundError:
        return False
    return stat.rpartition(")")[2].split()[0] != "Z" and os.path.exists(f"/proc/{pid}")


FED = {
    "/tf", "/sim/true_pose", "/vehicle/state", "/vehicle/beams", "/scene/truck", "/scene/beams",
    "/scene/safety_fields", "/scene/true_pallets", "/scene/obstacles", "/scene/roadmap", "/roadmap/graph",
}  # fmt: skip


def test_sim_serve_foxglove_streams_the_truth(tmp_path: Path) -> None:
    pytest.importorskip("cyclonedds")
    from websockets.sync.client import connect

    from palletpilot.executor.adapters.ros.dds import loopback_env

    scenario = tmp_path / "scenario.yaml"
    missions = bundled_path("missions")
    scenario.write_text(
        f"map: {missions / 'warehouse.yaml'}\nforks: {missions / 'forks.yaml'}\nstart: b1\n"
        "pallets: [{node: floor_b2, loaded: true}]\n"
    )
    env = {**os.environ, **loopback_env(tmp_path), "PYTHONUNBUFFERED": "1"}
    cmd = [sys.executable, "-m", "palletpilot.cli", "sim", "serve", str(scenario), "--ros", "--camera-hz", "0"]
    proc = subprocess.Popen(
        [*cmd, "--foxglove", "0"], env=env, stdout=subprocess.PIPE, stderr=subprocess.PIPE, text=True
    )
    lines: queue.Queue[str] = queue.Queue()
    assert proc.stderr is not None and proc.stdout is not None
    threading.Thread(target=lambda: [lines.put(line) for line in proc.stderr or []], daemon=True).start()
    try:
        assert proc.stdout.readline().startswith("stand-in truck ready:")
        line = lines.get(timeout=30)
        assert line.startswith("foxglove: live on ws://127.0.0.1:"), line
        url = line.split()[-1]
        protocols = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
        advertised: dict[str, int] = {}
        with connect(url, subprotocols=protocols, open_timeout=5) as ws:
            deadline = time.monotonic() + 10.0
            while not FED <= set(advertised) and time.monotonic() < deadline:
                msg = ws.recv(timeout=5)
                doc = json.loads(msg) if isinstance(msg, str) else {}
                if doc.get("op") == "advertise":
                    advertised |= {ch["topic"]: ch["id"] for ch in doc["channels"]}
            assert FED <= set(advertised) <= set(TOPICS)
            sub = {"op": "subscribe", "subscriptions": [{"id": 1, "channelId": advertised["/vehicle/state"]}]}
            ws.send(json.dumps(sub))
            state = None
            while state is None and time.monotonic() < deadline:
                msg = ws.recv(timeout=5)
                if isinstance(msg, bytes) and msg[0] == 1 and struct.unpack_from("<I", msg, 1)[0] == 1:
                    state = json.loads(msg[13:])
        assert state is not None and state["task"] == -1 and state["state"] == "command_timeout"
        proc.send_signal(signal.SIGINT)
        assert proc.wait(timeout=20) == 0
    finally:
        if proc.poll() is None:
            proc.kill()
            proc.wait()


def test_sim_serve_foxglove_port_in_use_is_one_line_exit_2(tmp_path: Path, capsys: pytest.CaptureFixture[str]) -> None:
    pytest.importorskip("cyclonedds")
    from palletpilot.executor.apps.cli import main

    scenario = tmp_path / "scenario.yaml"
    missions = bundled_path("missions")
    scenario.write_text(f"map: {missions / 'warehouse.yaml'}\nforks: {missions / 'forks.yaml'}\nstart: b1\n")
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code = main(["sim", "serve", str(scenario), "--ros", "--foxglove", str(port)])
    captured = capsys.readouterr()
    err = captured.err.strip().splitlines()
    assert code == 2 and len(err) == 1 and f"--foxglove: cannot serve on 127.0.0.1:{port}" in err[0], err
    assert not captured.out  # refused before the ready line
