"""run.mcap: a recorded simulated pickup read back with the `mcap` reader, channel by channel."""

import json
import logging
import re
import socket
from collections import Counter, defaultdict
from pathlib import Path

import pytest
from mcap.reader import make_reader
from mcap_protobuf.decoder import DecoderFactory
from test_executor_missions import mission_file, scenario

from palletpilot.cli import main
from palletpilot.executor.adapters.mcap import recording_channels, recording_scene
from palletpilot.executor.adapters.mcap.recording import RECORDING, SIM_EPOCH_NS, TOPICS
from palletpilot.executor.adapters.processes import free_port
from palletpilot.executor.apps.app import run_simulated
from palletpilot.geometry.fileio import bundled_path

LAYOUT = "foxglove/palletpilot_layout.json"

PICKUP = [{"type": "pickup", "node": "floor_b2"}]


def _run(folder: Path, **kw):
    return run_simulated(
        mission_file(folder, PICKUP),
        scenario=scenario("b1", [{"node": "floor_b2"}]),
        report_dir=folder / "report",
        **kw,
    )


def read_mcap(path: Path) -> dict:
    """Every message of the file, decoded (protobuf through its schema, JSON parsed), in file order."""
    factory = DecoderFactory()
    messages: dict[str, list] = defaultdict(list)
    times: list[int] = []
    with path.open("rb") as f:
        reader = make_reader(f)
        summary = reader.get_summary()
        assert summary is not None
        schemas = {ch.topic: summary.schemas[ch.schema_id] for ch in summary.channels.values()}
        encodings = {ch.topic: ch.message_encoding for ch in summary.channels.values()}
        decoders: dict[int, object] = {}
        for schema, channel, message in reader.iter_messages(log_time_order=False):
            times.append(message.log_time)
            if channel.message_encoding == "json":
                assert schema.encoding == "jsonschema" and json.loads(schema.data)["type"] == "object"
                messages[channel.topic].append((message.log_time, json.loads(message.data)))
            else:
                assert channel.message_encoding == "protobuf" and schema.encoding == "protobuf"
                decode = decoders.setdefault(schema.id, factory.decoder_for("protobuf", schema))
                messages[channel.topic].append((message.log_time, decode(message.data)))
        metadata = {m.name: m.metadata for m in reader.iter_metadata()}
    return {"schemas": schemas, "encodings": encodings, "messages": messages, "times": times, "metadata": metadata}


@pytest.fixture(scope="module")
def recorded(tmp_path_factory):
    folder = tmp_path_factory.mktemp("recorded")
    r = _run(folder)
    assert r.success and r.write_errors == []
    report = json.loads((folder / "report" / "report.json").read_text())
    events = (folder / "report" / "events.jsonl").read_text().splitlines()
    return folder / "report", report, events, read_mcap(folder / "report" / RECORDING)


def test_every_channel_is_recorded_with_its_schema_and_decodes(recorded):
    _, _, _, rec = recorded
    documented = set(re.findall(r"`(/[a-z_/]+)`", recording_channels.__doc__ or ""))
    assert documented == set(TOPICS)  # the docstring's channel list is the recorder's
    assert set(rec["schemas"]) == set(TOPICS)
    for topic, name in TOPICS.items():
        assert rec["schemas"][topic].name == name, topic
        assert rec["encodings"][topic] == ("json" if name.startswith("palletpilot.") else "protobuf")
        assert rec["messages"][topic], f"{topic}: no message"


def test_counts_and_timestamps(recorded):
    _, report, events, rec = recorded
    msgs = rec["messages"]
    count = Counter({t: len(m) for t, m in msgs.items()})
    ticks = report["clock"]["ticks"]
    assert count["/tf"] == count["/vehicle/state"] == count["/sim/true_pose"] == ticks
    assert count["/log"] == count["/events"] == len(events)
    assert [e for _, e in msgs["/events"]] == [json.loads(line) for line in events]
    frames = count["/camera/rgb"]
    assert frames >= 3 and count["/camera/depth"] == count["/camera/calibration"] == frames
    assert 1 <= count["/camera/segmentation"] <= frames
    assert count["/report/task"] == len(report["tasks"]) and count["/report/run"] == 1
    # /tf: map -> base_link from the first tick, base_link -> camera from the calibration on
    tf = [m for _, m in msgs["/tf"]]
    assert all(t.transforms[0].parent_frame_id == "map" and t.transforms[0].child_frame_id == "base_link" for t in tf)
    assert tf[-1].transforms[1].child_frame_id == "camera"
    # time: never decreasing in the file, within the run's simulated span
    times = rec["times"]
    assert times == sorted(times)
    assert SIM_EPOCH_NS <= times[0] and times[-1] <= SIM_EPOCH_NS + round(report["simulated_s"] * 1e9)
    cloud = msgs["/camera/depth"][0][1]
    assert cloud.frame_id == "camera" and len(cloud.data) > 1000 * cloud.point_stride
    assert msgs["/camera/rgb"][0][1].data[:2] == b"\xff\xd8"  # JPEG
    levels = {m.message.split(":")[0]: m.level for _, m in msgs["/log"]}
    assert levels["state_start"] == 1 and levels["mission_start"] == 2  # DEBUG, INFO
    cost = rec["metadata"]["recording_cost"]
    assert int(cost["ticks"]) == ticks and float(cost["mean_ms"]) > 0


def test_estimates_and_state_match_the_report(recorded):
    _, report, _, rec = recorded
    msgs = rec["messages"]
    task = report["tasks"][0]
    run = msgs["/report/run"][0][1]
    assert run["success"] is report["success"] and run["seed"] == report["seed"]
    assert run["results"][0]["record"]["estimates"] == task["estimates"]
    assert msgs["/report/task"][0][1]["record"]["estimates"] == task["estimates"]
    shown = msgs["/scene/pallet_estimates"][-1][1].entities
    assert len(shown) == len(task["estimates"])
    meta = {kv.key: kv.value for kv in shown[-1].metadata}
    assert float(meta["lateral_mm"]) == task["estimates"][-1]["lateral_mm"]
    assert meta["aligned"] == str(task["estimates"][-1]["aligned"])
    calibration = msgs["/perception/calibration"][0][1]
    assert calibration == task["calibrations"][0]
    states = [m for _, m in msgs["/vehicle/state"]]
    assert states[-1]["loaded"] is True and states[0]["loaded"] is False
    assert any(s["lateral_error_m"] is not None for s in states)
    assert {s["state"] for s in states} >= {"drive_to_pre_pallet", "calibrate", "enter"}


def test_the_recorder_does_not_change_the_run(recorded, tmp_path):
    _, report, _, _ = recorded
    r = _run(tmp_path, record=False)
    assert not (tmp_path / "report" / RECORDING).exists()
    again = json.loads((tmp_path / "report" / "report.json").read_text())
    assert _without_wall_clock(again) == _without_wall_clock(report) and r.success


def _without_wall_clock(doc):
    """The report less what differs between any two runs: the run's id, wall-clock times (solves, runtimes)."""
    if isinstance(doc, dict):
        return {k: _without_wall_clock(v) for k, v in doc.items() if k not in ("run_id", "solve_ms", "runtime_ms")}
    if isinstance(doc, list):
        return [_without_wall_clock(v) for v in doc]
    return doc


def test_an_error_in_the_recorder_ends_the_recording_not_the_run(tmp_path, monkeypatch):
    def broken(*args, **kwargs):
        raise RuntimeError("no truck to draw")

    monkeypatch.setattr(recording_scene, "truck_update", broken)
    r = _run(tmp_path)
    assert r.success
    assert len(r.write_errors) == 1 and "recording stopped (tick): RuntimeError: no truck to draw" in r.write_errors[0]
    rec = read_mcap(tmp_path / "report" / RECORDING)  # finished and readable: what came before the error
    assert len(rec["messages"]["/log"]) >= 3 and "/report/run" not in rec["messages"]


def test_foxglove_serves_the_channels_live(tmp_path):
    from websockets.sync.client import connect

    port = free_port()
    seen: dict[str, str] = {}

    def look(runner):  # the run has started: the server advertises every channel
        # foxglove-sdk 0.30 speaks the Foxglove WebSocket protocol under the name `foxglove.sdk.v1` (the
        # Foxglove app offers it); older servers named it `foxglove.websocket.v1`
        protocols = ["foxglove.sdk.v1", "foxglove.websocket.v1"]
        with connect(f"ws://127.0.0.1:{port}", subprotocols=protocols, open_timeout=5) as ws:
            assert ws.subprotocol in protocols
            for _ in range(20):
                msg = ws.recv(timeout=5)
                doc = json.loads(msg) if isinstance(msg, str) else {}
                if doc.get("op") == "advertise":
                    seen.update({ch["topic"]: ch["schemaName"] for ch in doc["channels"]})
                    if set(seen) >= set(TOPICS):
                        break
        runner.cancel()  # enough: the live view was seen

    r = _run(tmp_path, foxglove=port, on_start=look)
    assert seen == TOPICS
    assert not r.success and r.summary["tasks"][0]["reason"] == "cancelled"


def test_a_viewer_joining_10_s_into_the_run_gets_the_roadmap(tmp_path):
    """Latched channels: the roadmap is sent at the start only, yet a late viewer receives it."""
    import struct
    import threading
    import time

    from websockets.sync.client import connect

    port = free_port()
    got: dict[str, float] = {}

    def join_late(runner) -> None:
        while runner.clock.now() < 10.0:  # 10 simulated seconds into the run
            time.sleep(0.05)
        got["joined_s"] = runner.clock.now()
        with connect(f"ws://127.0.0.1:{port}", subprotocols=["foxglove.sdk.v1"], open_timeout=5) as ws:
            channels: dict[str, int] = {}
            while "/scene/roadmap" not in channels or "/roadmap/graph" not in channels:
                msg = ws.recv(timeout=5)
                doc = json.loads(msg) if isinstance(msg, str) else {}
                if doc.get("op") == "advertise":
                    channels.update({ch["topic"]: ch["id"] for ch in doc["channels"]})
            subs = {1: "/scene/roadmap", 2: "/roadmap/graph"}
            ws.send(
                json.dumps(
                    {"op": "subscribe", "subscriptions": [{"id": k, "channelId": channels[t]} for k, t in subs.items()]}
                )
            )
            deadline = time.monotonic() + 20
            while time.monotonic() < deadline and not set(subs.values()) <= set(got):
                msg = ws.recv(timeout=20)
                if isinstance(msg, bytes) and msg[0] == 1:  # messageData: opcode, subscription id, time, payload
                    got[subs[struct.unpack_from("<I", msg, 1)[0]]] = len(msg) - 13
        runner.cancel()

    def on_start(runner) -> None:
        threading.Thread(target=join_late, args=(runner,), daemon=True).start()

    r = _run(tmp_path, foxglove=port, on_start=on_start)
    assert got["joined_s"] >= 10.0
    assert got.get("/scene/roadmap", 0) > 100 and got.get("/roadmap/graph", 0) > 100, got
    assert r.summary["tasks"][0]["reason"] == "cancelled"


def test_foxglove_port_in_use_is_one_line_exit_2(tmp_path, capsys):
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        code = main(
            ["run", str(mission_file(tmp_path, PICKUP)), "--report", str(tmp_path / "r"), "--foxglove", str(port)]
        )
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and f"--foxglove: cannot serve on 127.0.0.1:{port}" in err[0], err


def _layout_topics(layout: dict) -> set[str]:
    """Every topic a Foxglove layout's panels name: 3D topics, image and calibration topics, plot paths
    (`/topic.field`), the log panel's topic."""
    topics: set[str] = set()
    for panel, config in layout["configById"].items():
        kind = panel.split("!")[0]
        if kind == "3D":
            topics |= set(config["topics"])
        elif kind == "Image":
            topics |= {config["imageMode"]["imageTopic"], config["imageMode"]["calibrationTopic"]}
        elif kind == "Plot":
            topics |= {p["value"].split(".")[0] for p in config["paths"]}
        elif kind == "RosOut":
            topics.add(config["topicToRender"])
    return topics


def test_the_shipped_layout_shows_recorded_channels(recorded, tmp_path, capsys):
    _, _, _, rec = recorded
    layout = json.loads((bundled_path("missions") / LAYOUT).read_text())
    kinds = {p.split("!")[0] for p in layout["configById"]}
    assert kinds == {"3D", "Image", "Plot", "RosOut"}
    topics = _layout_topics(layout)
    assert topics <= set(rec["messages"]), topics - set(rec["messages"])
    assert {"/camera/segmentation", "/vehicle/state", "/log", "/scene/pallet_estimates"} <= topics
    plotted = {p["value"].split(".", 1)[1] for c in layout["configById"].values() for p in c.get("paths", [])}
    state = rec["messages"]["/vehicle/state"][0][1]
    assert {"lateral_error_m", "speed_mps"} <= plotted and plotted <= set(state)
    assert main(["examples", "--out", str(tmp_path / "ex")]) == 0 and (tmp_path / "ex" / LAYOUT).is_file()


def test_agv_foxglove_port_in_use_is_one_line_exit_2(tmp_path, capsys):
    """`palletpilot agv --foxglove PORT` as `run`'s: a taken port is one line and exit 2, before connecting."""
    from test_vda5050_mqtt import MISSIONS, write_config

    config = write_config(tmp_path, 1883)
    with socket.socket() as taken:
        taken.bind(("127.0.0.1", 0))
        taken.listen()
        port = taken.getsockname()[1]
        args = ["--sim", str(MISSIONS / "suite" / "floor_b2.yaml"), "--report", str(tmp_path / "r")]
        code = main(["agv", "--config", str(config), *args, "--labels", "truth", "--foxglove", str(port)])
    err = capsys.readouterr().err.strip().splitlines()
    assert code == 2 and len(err) == 1 and f"--foxglove: cannot serve on 127.0.0.1:{port}" in err[0], err


def test_a_viewers_failed_handshake_stays_out_of_the_runs_output(caplog: pytest.LogCaptureFixture) -> None:
    """A client asking for `foxglove.websocket.v1` is refused by the SDK; the refusal is not printed."""
    import time

    from palletpilot.executor.adapters.mcap.recording import Recorder

    recorder = Recorder(None, port=0, wall=True)
    try:
        port = recorder.port
        assert port is not None
        request = (
            f"GET / HTTP/1.1\r\nHost: 127.0.0.1:{port}\r\nConnection: Upgrade\r\nUpgrade: websocket\r\n"
            "Sec-WebSocket-Version: 13\r\nSec-WebSocket-Key: dGhlIHNhbXBsZSBub25jZQ==\r\n"
            "Sec-WebSocket-Protocol: foxglove.websocket.v1\r\n\r\n"
        )
        with caplog.at_level(logging.DEBUG), socket.create_connection(("127.0.0.1", port), timeout=5) as sock:
            sock.sendall(request.encode())
            assert sock.recv(4096).startswith(b"HTTP/1.1 400")
            time.sleep(0.5)  # the SDK logs from its own thread
        assert not [r for r in caplog.records if r.levelno >= logging.WARNING and "handshake" in r.getMessage()]
    finally:
        recorder.close()
