"""`palletpilot agv`: run as one AGV of a fleet, orders from a VDA 5050 master over MQTT (wired in by `executor.cli`).

`palletpilot agv --config agv.yaml (--sim SCENARIO | --robot robot.yaml) [--labels fused|geometry|model|truth]
[--seed N] [--report DIR] [--journal FILE] [--foxglove [PORT]] [--foxglove-host HOST] [--quiet]` checks the config file
(and the map, vehicle, TLS files it names) and the scenario first: a problem is one line on stderr and exit 2. Then it
connects to the broker (retrying with backoff until it gets through), prints one line on stdout,
`agv ready: <interface>/v2/<manufacturer>/<serial>/ (simulated scenario ...)`, and runs until SIGINT or
SIGTERM: the truck stops, `connection` goes OFFLINE, and it exits 0. Progress (connection, orders accepted
or rejected, legs, failures) goes to stderr unless `--quiet`.

The whole session is recorded to `DIR/run.mcap` (default `out/agv/<serialNumber>`, so AGVs started side by
side on one machine keep their own files): `executor.recording`, the channels of `palletpilot run` over
every leg, orders and legs on `/log` and `/events`; finished when the AGV stops, flushed every `FLUSH_S`
seconds so a crash loses little. `--foxglove` also serves it live. A file that cannot be written is one
line on stderr, and the AGV drives on without it. `palletpilot replay DIR/run.mcap --report R` gives the
session's report (every leg's task) once the AGV has stopped cleanly; it refuses, in one line, the file of
a killed AGV (no summary, no `/report/run`), whose flushed chunks a streaming MCAP reader still reads.

The order state is journalled (`executor.vda5050.persist`) to `--journal FILE` (default `DIR/agv.db`): on
every event (order accepted, node traversed, action state, load, cancel) a checkpoint is committed off the
control loop. Started on an unfinished journal (the AGV was killed, or stopped while an order executed), it
restores the order, its progress, action states, errors, load and headerIds, publishes them in its first
state, and stays halted (the running action FAILED, `orderInterrupted`) until the master sends an order it
accepts or cancelOrder (`Agv.restore`). A clean stop with no order executing finishes the journal; the next
start begins a new one (headerIds carried over). A journal of another AGV, map or program is one line on
stderr and exit 2.

`--sim SCENARIO` drives the simulated warehouse of a scenario in real time (its map must be the config's);
`--robot robot.yaml` needs the ROS 2 adapter (`palletpilot.executor.adapters.ros`) and says so when it is missing.
"""

from __future__ import annotations

import argparse
import signal
import sys
import threading
from importlib import metadata
from pathlib import Path
from types import FrameType
from typing import Any

from palletpilot.executor.adapters.mcap.recording_channels import add_foxglove_argument
from palletpilot.executor.apps.cli_args import add_labels_argument, number, out_folder, seed

FLUSH_S = 5.0
"""The session's recording finishes its current chunk at least this often (wall seconds)."""


def _version() -> str:
    try:
        return metadata.version("palletpilot")
    except metadata.PackageNotFoundError:
        return "unknown"


def cmd_agv(args: argparse.Namespace) -> int:
    """Check the inputs, connect, drive until SIGINT / SIGTERM, then go OFFLINE."""
    from palletpilot.executor.adapters.mcap.recording import Recorder, start_recording
    from palletpilot.executor.apps.vda5050.agv import Agv
    from palletpilot.executor.apps.vda5050.config import load_config
    from palletpilot.executor.apps.vda5050.persist import JOURNAL_NAME, Persister, agv_meta, open_session

    stop = threading.Event()
    agv: Agv | None = None
    recorder: Recorder | None = None

    def on_signal(signum: int, _frame: FrameType | None) -> None:
        stop.set()
        if agv is not None:
            agv.stop()

    # first thing: a signal while the inputs load or the simulator builds ends the command cleanly
    previous = {s: signal.signal(s, on_signal) for s in (signal.SIGINT, signal.SIGTERM)}
    try:
        loaded = load_config(args.config)
        cfg = loaded.config
        folder = Path(args.report) if args.report else Path("out/agv") / cfg.serial_number
        journal_path = Path(args.journal) if args.journal else folder / JOURNAL_NAME
        session = open_session(journal_path, agv_meta(cfg.manufacturer, cfg.serial_number, cfg.map_name))
        backend = _backend(args, loaded)
        try:
            folder.mkdir(parents=True, exist_ok=True)
            recorder = start_recording(folder, args.foxglove, wall=True, host=args.foxglove_host, flush_s=FLUSH_S)
        except BaseException:  # RecordingError: the port is taken
            backend.close()
            raise
    except BaseException:
        _restore(previous)
        raise

    def log(line: str) -> None:
        if not args.quiet:
            print(line, file=sys.stderr, flush=True)

    assert recorder is not None  # a report folder always
    _announce(recorder, args.foxglove_host, log)
    agv = Agv(loaded, backend, log=log, software_version=_version(), recorder=recorder)
    persister = Persister(session.path, agv.checkpoint_doc, log=log)
    try:
        agv.messages.headers.start_at(session.headers)
        if session.restored is not None:
            agv.restore(session.restored, source=str(session.path))
        persister.start()
    except BaseException:
        agv.finish_recording()
        backend.close()
        _restore(previous)
        raise
    agv.attach_journal(persister)
    persister.flush()  # the restored state and the headerIds reserved, committed before anything is sent
    link = agv.connect()
    if stop.is_set():
        agv.stop()
    publisher = threading.Thread(target=agv.publisher, args=(stop,), name="vda5050-publisher", daemon=True)
    try:
        publisher.start()
        link.start()
        where = f"simulated scenario {args.sim}" if args.sim else f"robot {args.robot}"
        print(f"agv ready: {loaded.config.topic_prefix}/ ({where})", flush=True)
        agv.run()
    finally:
        stop.set()
        agv.stop()
        try:
            _finish(agv, len(recorder.errors), publisher, link)
        finally:
            executing = agv.orders.executing()  # run() has returned: the last state
            persister.close(finish=not executing, reason=None if executing else "stopped with no order executing")
            log(f"agv: journal {session.path}: {_journal_line(persister.stats())}")
            backend.close()
            _restore(previous)
    log("agv: stopped (connection OFFLINE)")
    return 0


def _restore(previous: dict[signal.Signals, Any]) -> None:
    """Put back the signal handlers `cmd_agv` replaced."""
    for signum, handler in previous.items():
        signal.signal(signum, handler)


def _announce(recorder: Any, host: str, log: Any) -> None:
    """The recording's start-up errors (always printed) and the live view's address."""
    for line in recorder.errors:
        print(f"agv: {line}", file=sys.stderr, flush=True)
    if recorder.port is not None:
        log(f"foxglove: live on ws://{host}:{recorder.port}")


def _backend(args: argparse.Namespace, loaded: Any) -> Any:
    """The truck the AGV drives: the simulator (`--sim SCENARIO`) or a real one (`--robot robot.yaml`)."""
    from palletpilot.executor.apps.vda5050.vehicle import BackendError, robot_backend, sim_backend
    from palletpilot.perception.labels_mode import SIM_TRUTH, LabelsMode

    if args.sim:
        return sim_backend(loaded, args.sim, labels=args.labels, seed=args.seed, speed=args.sim_speed)
    if args.sim_speed != 1.0:
        raise BackendError("--sim-speed: only with --sim (a real truck runs in real time)")
    if args.labels == SIM_TRUTH:
        raise BackendError("--labels truth: the simulator's labels exist only with --sim")
    return robot_backend(loaded, args.robot, labels=LabelsMode(args.labels))


def _finish(agv: Any, reported: int, publisher: threading.Thread, link: Any) -> None:
    """After `agv.run()`: finish run.mcap (its errors past the `reported` first), stop the publisher, send
    the last state, close the broker link."""
    for line in agv.finish_recording()[reported:]:  # run.mcap finished, the live port freed
        print(f"agv: {line}", file=sys.stderr, flush=True)
    publisher.join(timeout=2.0)
    agv.publish_state()
    link.close()


def _journal_line(stats: dict[str, float]) -> str:
    if not stats.get("checkpoints"):
        return "no checkpoints written"
    return (
        f"{stats['checkpoints']:.0f} checkpoints, write time mean {stats['mean_ms']:.1f} ms, "
        f"p50 {stats['p50_ms']:.1f} ms, max {stats['max_ms']:.1f} ms (off the control loop)"
    )


def add_parsers(subparsers: argparse._SubParsersAction) -> None:
    """Register `agv` on the `palletpilot` sub-command parser."""
    p = subparsers.add_parser("agv", help="run as a VDA 5050 AGV: orders from a fleet manager over MQTT")
    p.add_argument("--config", required=True, metavar="AGV.yaml", help="broker, identity, map and rates (agv.yaml)")
    where = p.add_mutually_exclusive_group(required=True)
    where.add_argument("--sim", metavar="SCENARIO", help="drive the simulated warehouse of a scenario in real time")
    where.add_argument("--robot", metavar="ROBOT.yaml", help="drive a real truck (needs the ROS 2 adapter)")
    add_labels_argument(p, sim=True)
    p.add_argument("--seed", type=seed, help="--sim: override the scenario's seed")
    p.add_argument(
        "--sim-speed",
        type=number(0.1, 20.0),
        default=1.0,
        metavar="FACTOR",
        help="--sim: simulated seconds per wall-clock second at most (default 1, real time); above 1 for tests: "
        "as fast as the machine allows, no wall-clock deadlines",
    )
    p.add_argument(
        "--report",
        type=out_folder,
        metavar="DIR",
        help="folder for the session's recording run.mcap (default out/agv/SERIAL)",
    )
    p.add_argument(
        "--journal",
        metavar="FILE",
        help="the crash-safe journal of the AGV's order state (default DIR/agv.db): an unfinished one is resumed",
    )
    add_foxglove_argument(p)
    p.add_argument("--quiet", action="store_true", help="no progress lines on stderr")
    p.set_defaults(func=cmd_agv)
