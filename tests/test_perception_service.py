"""Perception as a service: the wire format, a real `palletpilot perception serve` process and its client,
a service that dies or hangs mid-run, and missions run with `--perception local|remote|serve-local`.

Every session talks over explicit loopback endpoints on free ports (multicast scouting off), so the
tests never meet another process's service.
"""

from __future__ import annotations

import dataclasses
import json
import os
import signal
import threading
import time
from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
import yaml

zenoh = pytest.importorskip("zenoh")

from palletpilot.bench.pallet import FrameSpec, render  # noqa: E402
from palletpilot.cli import main  # noqa: E402
from palletpilot.executor.adapters.local_perception import LocalPerception  # noqa: E402
from palletpilot.executor.adapters.zenoh.perception_remote import (  # noqa: E402
    UNAVAILABLE,
    CalibrationUnavailableError,
    Deadlines,
    LocalService,
    PalletUnavailableError,
    RemotePerception,
    free_port,
)
from palletpilot.executor.adapters.zenoh.perception_server import PerceptionServer, zenoh_config  # noqa: E402
from palletpilot.executor.apps.app import run_simulated  # noqa: E402
from palletpilot.executor.core.errors import TaskFailed  # noqa: E402
from palletpilot.geometry import SE2, SE3  # noqa: E402
from palletpilot.geometry.fileio import bundled_path  # noqa: E402
from palletpilot.perception import wire  # noqa: E402
from palletpilot.perception.clearance import Volume, VolumeCheck  # noqa: E402
from palletpilot.perception.errors import CalibrationError, PerceptionError  # noqa: E402
from palletpilot.perception.frames import FrameBundle  # noqa: E402
from palletpilot.perception.pallet import PalletNotFound  # noqa: E402
from palletpilot.perception.segmentation import DEFAULT_MODEL, OnnxSegmenter  # noqa: E402
from palletpilot.perception.specs import PalletType, builtin_pallet, load_forks  # noqa: E402

MISSIONS = bundled_path("missions")
FORKS = load_forks(MISSIONS / "forks.yaml")
POSE = SE2(4.0, 2.0, 0.3)
ENTRY = Volume(1.25, 2.5, -0.45, 0.45, 0.0, 1.2)


@pytest.fixture(scope="module")
def frames() -> tuple[FrameBundle, list[FrameBundle]]:
    """A 640 x 480 pallet frame 1.5 m ahead (labels from the simulator) and one calibration frame."""
    spec = FrameSpec("floor_b2", loaded=False, dx=0.0, dy=0.08, dyaw_deg=4.0, ahead=1.5, seed=3)
    frame, cal = render(spec, calibration_frames=1)
    return frame, cal


@pytest.fixture(scope="module")
def local() -> LocalPerception:
    return LocalPerception(FORKS, PalletType.eur(), segmenter=OnnxSegmenter(DEFAULT_MODEL))


@pytest.fixture(scope="module")
def service() -> Iterator[LocalService]:
    """A real `palletpilot perception serve` subprocess on a free loopback port."""
    svc = LocalService(FORKS, PalletType.eur())
    svc.start()
    yield svc
    svc.stop()


@pytest.fixture
def client(service: LocalService) -> Iterator[RemotePerception]:
    assert service.endpoint is not None
    with RemotePerception([service.endpoint]) as c:
        yield c


# -- the wire format -------------------------------------------------------------------------------


def test_frame_round_trip_is_exact(frames):
    frame, _ = frames
    frame = dataclasses.replace(frame, stamp_s=12.5)
    back = wire.decode_frame(wire.encode_frame(frame))
    assert np.array_equal(back.depth, frame.depth, equal_nan=True) and back.depth.dtype == np.float32
    assert np.array_equal(back.labels, frame.labels) and np.array_equal(back.rgb, frame.rgb)
    assert np.array_equal(back.K, frame.K) and back.fork_height == frame.fork_height and back.stamp_s == 12.5
    assert back.truth == {}  # simulator truth never travels
    bare = wire.decode_frame(wire.encode_frame(dataclasses.replace(frame, labels=None, rgb=None)))
    assert bare.labels is None and bare.rgb is None
    mm = wire.decode_frame(wire.encode_frame(frame, depth="mm16"))
    assert np.nanmax(np.abs(mm.depth - np.nan_to_num(frame.depth))) <= 0.0005 + 1e-6
    params, decoded = wire.decode_request(wire.encode_request({"a": [1, 2]}, [frame, frame]))
    assert params == {"a": [1, 2]} and len(decoded) == 2


def test_results_and_errors_round_trip(frames, local):
    frame, cal_frames = frames
    calibration = local.calibrate(cal_frames)
    back = wire.calibration_from_json(
        wire.decode_json(wire.encode_json(wire.calibration_to_json(calibration)), "t"), "t"
    )
    assert np.array_equal(back.T_forklift_camera.matrix, calibration.T_forklift_camera.matrix)
    assert back.method == calibration.method and back.warnings == calibration.warnings
    est = local.estimate_pallet(frame, calibration, POSE)
    doc = wire.decode_json(wire.encode_json(wire.estimate_to_json(est)), "t")
    e2 = wire.estimate_from_json(doc, "t")
    assert np.array_equal(e2.T_forklift_pallet.matrix, est.T_forklift_pallet.matrix)
    assert e2.T_world_pallet is not None and est.T_world_pallet is not None
    assert np.array_equal(e2.T_world_pallet.matrix, est.T_world_pallet.matrix)
    assert e2.spread == est.spread and e2.pocket_widths_m == est.pocket_widths_m and e2.n_points == est.n_points
    check = VolumeCheck(points=12, nearest_x_m=None, seen=0.25)
    assert wire.volume_check_from_json(wire.volume_check_to_json(check), "t") == check
    assert wire.volume_from_json(wire.volume_to_json(ENTRY), "t") == ENTRY
    industrial = builtin_pallet("industrial")
    assert industrial is not None
    assert wire.pallet_from_json(wire.pallet_to_json(industrial), "t") == industrial

    not_found = wire.error_from_json(wire.error_to_json(PalletNotFound("no_entry_face", "flat")), "t")
    assert isinstance(not_found, PalletNotFound) and not_found.reason == "no_entry_face"
    assert str(not_found) == "pallet not found (no entry face): flat"
    assert isinstance(wire.error_from_json(wire.error_to_json(CalibrationError("no forks")), "t"), CalibrationError)
    busy = wire.error_to_json(wire.ServiceBusyError("full"), "busy")
    assert isinstance(wire.error_from_json(busy, "t"), wire.ServiceBusyError)
    with pytest.raises(PerceptionError, match="result version 2"):
        wire.decode_json(b'{"version": 2}', "t")


@pytest.mark.parametrize(
    ("damage", "message"),
    [
        (lambda b: b[:-7], "but the header declares"),
        (lambda b: b"XXXX" + b[4:], "not an encoded frame bundle"),
        (lambda b: b[:4] + b"\x09" + b[5:], "frame format version 9"),
        (lambda b: b[:8] + (99999).to_bytes(4, "little") + b[12:], "each side must be 1..4096 px"),
        (lambda b: b[:12], "shorter than a frame header"),
        (lambda b: b[:20] + b"x" + b[21:], "frame meta: not valid JSON"),
    ],
)
def test_a_bad_frame_payload_is_one_line(frames, damage, message):
    frame, _ = frames
    with pytest.raises(PerceptionError, match=message) as info:
        wire.decode_frame(damage(wire.encode_frame(frame)), "pp/estimate_pallet")
    assert str(info.value).startswith("pp/estimate_pallet") and "\n" not in str(info.value)


def test_a_frame_that_breaks_the_bundle_contract_is_refused(frames):
    frame, _ = frames
    blob = bytearray(wire.encode_frame(frame))
    meta_end = 20 + int.from_bytes(blob[16:20], "little")
    blob[meta_end : meta_end + 4] = np.float32(-1.0).tobytes()  # a negative depth
    with pytest.raises(PerceptionError, match="pp: frame: depth: contains negative depths"):
        wire.decode_frame(bytes(blob), "pp")


# -- a real service and its client -----------------------------------------------------------------


def test_remote_gives_the_results_of_local(frames, local, client):
    frame, cal_frames = frames
    health = client.health()
    assert health["model"] == "segmenter.onnx" and health["camera"] == "none" and health["provider"]
    assert health["uptime_s"] > 0 and health["forks"] == FORKS.model_dump(mode="json")

    calibration = local.calibrate(cal_frames)
    remote_cal = client.calibrate(cal_frames)
    assert np.allclose(remote_cal.T_forklift_camera.matrix, calibration.T_forklift_camera.matrix, atol=1e-12)
    assert client.last_good is remote_cal

    expected = POSE @ SE3.from_matrix(frame.truth["T_forklift_pallet_true"]).to_se2()
    for f in (frame, dataclasses.replace(frame, labels=None)):  # labels from the frame, and from the model
        mine = local.estimate_pallet(f, calibration, POSE, expected)
        theirs = client.estimate_pallet(f, calibration, POSE, expected)
        assert np.allclose(theirs.T_forklift_pallet.matrix, mine.T_forklift_pallet.matrix, atol=1e-12)
        assert theirs.n_points == mine.n_points and theirs.spread == mine.spread
    assert client.check_volume(frame, calibration, ENTRY) == local.check_volume(frame, calibration, ENTRY)
    segmented = client.segment(dataclasses.replace(frame, labels=None))
    assert segmented.labels is not None and segmented.labels.shape == frame.depth.shape

    # the service's own answers come back as the same exception, with the same reason
    pallet = np.isin(frame.labels, (7, 8))  # the pallet gone: from the labels and from the depth
    no_pallet = dataclasses.replace(
        frame, labels=np.where(pallet, 0, frame.labels).astype(np.uint8), depth=np.where(pallet, 0.0, frame.depth)
    )
    with pytest.raises(PalletNotFound) as mine_info:
        local.estimate_pallet(no_pallet, calibration, POSE)
    with pytest.raises(PalletNotFound) as info:
        client.estimate_pallet(no_pallet, calibration, POSE)
    assert info.value.reason == mine_info.value.reason and str(info.value) == str(mine_info.value)
    with pytest.raises(CalibrationError):  # no depth: neither floor nor forks
        client.calibrate([dataclasses.replace(cal_frames[0], depth=np.zeros_like(cal_frames[0].depth))])
    with pytest.raises(PerceptionError, match="no frame in the request, and the service has no camera"):
        client.estimate_pallet(None, calibration, POSE)


def test_a_bad_request_is_an_error_reply_and_the_service_keeps_serving(service, client):
    assert service.endpoint is not None
    with zenoh.open(zenoh_config(connect=[service.endpoint])) as session:
        replies = list(session.get("palletpilot/perception/estimate_pallet", payload=b"garbage " * 10, timeout=3.0))
    assert len(replies) == 1 and replies[0].ok is not None
    doc = json.loads(replies[0].ok.payload.to_bytes())
    assert doc["version"] == 1 and doc["error"]["type"] == "PerceptionError"
    assert "not a perception request" in doc["error"]["message"]
    health = client.health()
    assert "not a perception request" in health["last_error"] and service.process is not None
    assert service.process.poll() is None


class _SlowPerception(LocalPerception):
    """Checks a volume in 1 s (a long request)."""

    def check_volume(self, frame, calibration, volume):
        time.sleep(1.0)
        return VolumeCheck(0, None, 1.0)


def test_a_long_request_does_not_stop_health_and_a_full_queue_answers_busy(frames, local):
    frame, cal_frames = frames
    port = free_port()
    server = PerceptionServer(_SlowPerception(FORKS), queue_size=1)
    server.start(zenoh_config(listen=[f"tcp/127.0.0.1:{port}"]))
    try:
        request = wire.encode_request(
            {
                "calibration": wire.calibration_to_json(local.calibrate(cal_frames)),
                "volume": wire.volume_to_json(ENTRY),
            },
            [frame],
        )
        with zenoh.open(zenoh_config(connect=[f"tcp/127.0.0.1:{port}"])) as session:
            key = "palletpilot/perception/check_volume"
            results: list[dict] = []

            def ask() -> None:
                for r in session.get(key, payload=request, timeout=5.0):
                    results.append(json.loads(r.ok.payload.to_bytes()))

            threads = [threading.Thread(target=ask) for _ in range(3)]
            for t in threads:
                t.start()
                time.sleep(0.15)
            t0 = time.perf_counter()
            health = list(session.get("palletpilot/perception/health", timeout=2.0))
            assert len(health) == 1 and time.perf_counter() - t0 < 0.5  # answered while the worker is busy
            for t in threads:
                t.join(timeout=10.0)
        kinds = sorted(r.get("error", {}).get("type", "ok") for r in results)
        assert kinds == ["busy", "ok", "ok"], results
    finally:
        server.close()


def test_a_dead_or_hung_service_fails_within_its_deadline_with_the_unavailable_reason(frames, local):
    frame, cal_frames = frames
    calibration = local.calibrate(cal_frames)
    deadlines = Deadlines(estimate_s=0.5, calibrate_s=0.5, retries=2, backoff_s=(0.1, 0.2))
    svc = LocalService(FORKS, PalletType.eur())
    endpoint = svc.start()
    try:
        with RemotePerception([endpoint], deadlines=deadlines) as client:
            client.estimate_pallet(frame, calibration, POSE)
            assert svc.process is not None
            os.kill(svc.process.pid, signal.SIGSTOP)  # hung: every attempt runs into its deadline
            t0 = time.perf_counter()
            with pytest.raises(PalletUnavailableError) as info:
                client.estimate_pallet(frame, calibration, POSE)
            hung_s = time.perf_counter() - t0
            assert info.value.reason == UNAVAILABLE and isinstance(info.value, PalletNotFound)
            assert "3 attempts" in str(info.value) and "within 0.5 s" in str(info.value)
            assert 3 * 0.5 <= hung_s <= deadlines.bound("estimate_pallet") + 0.5

            os.kill(svc.process.pid, signal.SIGKILL)  # dead: the retries end as soon as nobody answers
            svc.process.wait(timeout=10)
            t0 = time.perf_counter()
            with pytest.raises(CalibrationUnavailableError) as cal_info:
                client.calibrate(cal_frames)
            assert time.perf_counter() - t0 <= deadlines.bound("calibrate") + 0.5
            assert cal_info.value.reason == UNAVAILABLE and isinstance(cal_info.value, CalibrationError)
            with pytest.raises(TaskFailed) as check_info:
                client.check_volume(frame, calibration, ENTRY)
            assert check_info.value.reason == "safety_check_failed"
    finally:
        svc.stop()


def test_serve_prints_one_ready_line_and_exits_0_on_sigint():
    svc = LocalService(FORKS, PalletType.eur(), prefix="test/perception")
    endpoint = svc.start()
    try:
        assert svc.ready_line == f"perception service ready on {endpoint} prefix test/perception"
        assert svc.process is not None
        svc.process.send_signal(signal.SIGINT)
        assert svc.process.wait(timeout=20) == 0
    finally:
        svc.stop()


# -- missions --------------------------------------------------------------------------------------


def _world(folder: Path) -> tuple[Path, Path]:
    """The cheapest mission: pick up an aligned pallet one node ahead (b1 -> floor_b2)."""
    assert main(["examples", "--out", str(folder)]) == 0
    mission = folder / "short.yaml"
    mission.write_text(
        yaml.safe_dump({"name": "short", "map": "warehouse.yaml", "tasks": [{"type": "pickup", "node": "floor_b2"}]})
    )
    sc = folder / "short_scenario.yaml"
    sc.write_text(
        yaml.safe_dump({"map": "warehouse.yaml", "start": "b1", "seed": 3, "pallets": [{"node": "floor_b2"}]})
    )
    return mission, sc


def _services_of_this_process() -> list[int]:
    """Pids of `perception serve` processes this test process started and that still run."""
    pids = []
    for entry in Path("/proc").iterdir():
        if not entry.name.isdigit():
            continue
        try:
            stat = (entry / "stat").read_text().rsplit(")", 1)[1].split()
            cmdline = (entry / "cmdline").read_bytes()
        except OSError:
            continue
        if int(stat[1]) == os.getpid() and b"perception\x00serve" in cmdline:
            pids.append(int(entry.name))
    return pids


def test_run_gives_the_same_outcome_with_local_remote_and_serve_local_perception(tmp_path, capsys, service):
    mission, sc = _world(tmp_path / "world")
    capsys.readouterr()
    before = set(_services_of_this_process())  # the module's own service
    summaries = {}
    for mode in ("local", "remote", "serve-local"):
        argv = ["run", str(mission), "--scenario", str(sc), "--json", "--report", str(tmp_path / mode)]
        argv += ["--perception", mode] + (["--perception-connect", service.endpoint] if mode == "remote" else [])
        assert main(argv) == 0, capsys.readouterr().err
        summaries[mode] = json.loads(capsys.readouterr().out)
        assert set(_services_of_this_process()) <= before  # the run's service is gone with the run
    assert summaries["local"]["success"]
    assert summaries["remote"] == summaries["local"] and summaries["serve-local"] == summaries["local"]


def test_a_service_killed_mid_mission_ends_the_pickup_cleanly(tmp_path):
    mission, sc = _world(tmp_path / "world")
    svc = LocalService(FORKS, PalletType.eur())
    endpoint = svc.start()

    def kill_after_calibration(runner) -> None:
        def listen(event: str, _data: dict, _t: float) -> None:
            if event == "calibrated" and svc.process is not None and svc.process.poll() is None:
                os.kill(svc.process.pid, signal.SIGKILL)

        runner.listeners.append(listen)

    try:
        r = run_simulated(
            mission,
            sc,
            report_dir=tmp_path / "report",
            perception="remote",
            perception_connect=[endpoint],
            on_start=kill_after_calibration,
        )
    finally:
        svc.stop()
    task = r.runner.results[0]
    assert not r.success and task.reason in ("pallet_not_found", "safety_check_failed"), task.message
    assert "perception service unavailable" in (task.message or "")
    assert r.sim.collisions == [] and abs(r.sim.speed) < 1e-3 and not r.sim.pallets[0].carried
