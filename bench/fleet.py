"""`palletpilot bench fleet`: a fleet of simulated VDA 5050 AGVs on one MQTT broker, driven by one master.

One local broker (`executor.vda5050.broker.Broker`: mosquitto, else amqtt; `--broker` to choose) on a free
loopback port; `--agvs N` AGVs, each a `palletpilot agv --config <its agv.yaml> --sim
missions/suite/floor_b2.yaml --labels truth --seed <its seed>` subprocess with a serial number of its own
(0001, 0002, ...) and a simulated warehouse of its own
(the example warehouse, the truck at `b1`, driven in real time at 20 Hz by the MPC follower), all speaking
`--protocol` (2.1.0, or 3.0.0: `vda5050/v3/...` topics and 3.0 messages); and a master in
this process (paho) that subscribes to every AGV's `state` and `connection` and gives each AGV
`--orders-per-agv K` move orders one after the other: each along 1 to `--edges-per-order` edges of the
warehouse's one-way loop (seeded), starting where the previous one ended, the next sent once the previous is
finished. An order is finished at the first state with its `orderId`, no node or edge states left, not
driving and `lastNodeId` its last node; failed on a state error naming its `orderId` (rejected) or a leg's
failure `reason` (the truck stopped: e.g. the MPC missed its deadline on an overloaded machine), or when not
finished within 30 s + 15 s per edge; that AGV then gets no more orders.

Figures (one machine, one clock; the measuring window runs from the first order to the last order's end):
- `agvs`, `orders` (sent), `orders_finished`, `orders_failed`, `failures` (the first few, one line each);
- `state_latency_ms_p50` / `_p99` / `_max`: a state message's `timestamp` (stamped by the AGV as it builds
  the message, UTC milliseconds, so +-1 ms) to its receipt in the master, over every state received in the
  window; `state_latency_ms_p99_driving`: the same over the states that show the truck driving (its control
  loop and MPC busy in the same process); `state_messages`, `states_per_s`;
- `order_to_motion_ms_p50` / `_p99` / `_max`: an order published by the master to the master's receipt of the
  first state of that order that shows the truck `driving` or a `lastNodeId` past the order's first node
  (so it includes the AGV's acceptance and route planning, the truck starting to move, and one state's
  latency);
- `cpu_per_agv_percent` (mean) and `cpu_per_agv_percent_max`: each AGV process's CPU time (user + system)
  in the window over the window's wall time, in percent of one core; `broker_cpu_percent` likewise;
  `cpus` (this machine's), `load_avg_1min_start` and `load_avg_1min` (at the window's start and end: the
  machine's other load shows in every figure);
- `startup_s` (all AGVs launched to all ONLINE with a first state), `wall_s` (the window), `broker`
  (mosquitto or amqtt), `seed`, and the goal: `goal_state_latency_ms_p99` (50 ms) and `meets_goal` (that
  p99 met and every order finished: a fleet whose trucks stop for want of CPU meets no goal).

`--out DIR` keeps each AGV's `agv-<serial>.yaml`, `agv-<serial>.log` (its stderr), `agv-<serial>/run.mcap`
(its recording) and `broker/` (the broker's config and log) in DIR, to look into a failure. Every child
process runs in a session of its own and is always ended (SIGTERM, SIGKILL after 10 s), the AGVs first
and then the broker, on success, on errors, on Ctrl-C and on SIGTERM to the bench.

A fleet that cannot be brought up raises `FleetBenchError` (one line, exit 2); no broker to start,
`BrokerUnavailableError` likewise.

Public API: `add_arguments`, `run`, `FleetBenchError`.
"""

from __future__ import annotations

import argparse
import json
import os
import queue
import signal
import subprocess
import sys
import tempfile
import threading
import time
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from datetime import datetime
from pathlib import Path
from types import FrameType
from typing import IO, Any

import numpy as np

from palletpilot.executor.adapters.stores.report import ms_stats
from palletpilot.executor.apps.cli_args import count, out_folder, seed
from palletpilot.executor.apps.vda5050.broker import KINDS, Broker
from palletpilot.geometry import PalletpilotError

STATE_LATENCY_GOAL_MS = 50.0
PROTOCOLS = ("2.1.0", "3.0.0")
PREFIXES = {"2.1.0": "uagv/v2/palletpilot", "3.0.0": "vda5050/v3/palletpilot"}
LOOP = ["b1", "b2", "b3", "b_top", "t_e", "t_w", "a_top", "a1", "a2", "a3", "a_bot", "c_w", "j_charge", "j_drop"]
LOOP += ["c_e", "b_bot"]  # the example warehouse's one-way loop, from the scenario's start node b1
SCENARIO = ("missions", "suite", "floor_b2.yaml")  # the truck at b1, facing up aisle B
READY_TIMEOUT_S = 60.0  # per AGV launched: N processes import and build their simulators side by side
ORDER_TIMEOUT_S = 30.0
ORDER_TIMEOUT_PER_EDGE_S = 15.0
STOP_TIMEOUT_S = 10.0
POLL_S = 0.02
MAX_FAILURE_LINES = 10


class FleetBenchError(PalletpilotError):
    """The fleet could not be brought up: an AGV did not start or come ONLINE, or the master could not connect
    (the message names the AGV and ends with its log's last lines)."""


def add_arguments(parser: argparse.ArgumentParser) -> None:
    """Options of this benchmark."""
    parser.add_argument("--agvs", type=count(1, 100), default=10, help="simulated AGVs, one process each")
    parser.add_argument("--orders-per-agv", type=count(1, 100), default=3, help="move orders per AGV, in turn")
    parser.add_argument("--edges-per-order", type=count(1, 8), default=2, help="an order covers 1..this edges")
    parser.add_argument("--seed", type=seed, default=7, help="order lengths and the simulators' seeds")
    parser.add_argument(
        "--state-interval-s",
        type=count(1, 30),
        default=1,
        help="each AGV publishes its state on events and at least this often (s)",
    )
    parser.add_argument("--visualization-hz", type=count(0, 20), default=2, help="each AGV's visualization rate")
    parser.add_argument(
        "--protocol",
        choices=PROTOCOLS,
        default=PROTOCOLS[0],
        help="the VDA 5050 version the AGVs and the master speak (3.0.0: vda5050/v3 topics, 3.0 messages)",
    )
    parser.add_argument(
        "--broker",
        choices=KINDS,
        default="auto",
        help="the local MQTT broker: mosquitto, amqtt, or auto (mosquitto when installed, else amqtt)",
    )
    parser.add_argument(
        "--out", type=out_folder, help="keep the AGVs' configs and logs and the broker's log here (else a temp folder)"
    )


@dataclass
class _Order:
    """One order sent: its path, when (monotonic s), order to motion (s), and how it ended."""

    order_id: str
    path: list[str]
    sent_mono: float
    motion_s: float | None = None
    done: str | None = None  # "finished" or "failed: why"


@dataclass
class _Agv:
    """One AGV of the fleet: its process, its orders (lengths in edges, drawn up front) and its progress."""

    serial: str
    sim_seed: int
    lengths: list[int]
    proc: subprocess.Popen[str] | None = None
    log: IO[str] | None = None
    node: str = LOOP[0]
    position: int = 0
    online: bool = False
    first_state: bool = False
    orders: list[_Order] = field(default_factory=list)
    header: int = 0
    stopped: bool = False  # no more orders (one failed)
    cpu_start_s: float = 0.0


class _Master:
    """The master: every AGV's state and connection through one paho client; receipt times on both clocks."""

    def __init__(self, port: int, agvs: dict[str, _Agv], prefix: str, protocol: str = PROTOCOLS[0]) -> None:
        import paho.mqtt.client as mqtt
        from paho.mqtt.enums import CallbackAPIVersion

        self.agvs, self.prefix, self.protocol = agvs, prefix, protocol
        self.lock = threading.Lock()
        self.latencies_s: list[float] = []
        self.latencies_driving_s: list[float] = []  # those of states showing the truck driving
        self.measuring = False
        self.states = 0
        self.connected = threading.Event()
        self.client = mqtt.Client(CallbackAPIVersion.VERSION2, client_id=f"bench-fleet-master-{os.getpid()}")
        self.client.on_message = self._on_message

        def on_connect(client: Any, userdata: Any, flags: Any, reason: Any, properties: Any) -> None:
            client.subscribe([(f"{prefix}/+/state", 0), (f"{prefix}/+/connection", 1)])
            self.connected.set()

        self.client.on_connect = on_connect
        self.client.connect("127.0.0.1", port, keepalive=30)
        self.client.loop_start()

    def _on_message(self, client: Any, userdata: Any, message: Any) -> None:
        received_wall, received_mono = time.time(), time.monotonic()
        _, serial, name = message.topic.rsplit("/", 2)
        agv = self.agvs.get(serial)
        if agv is None:
            return
        doc = json.loads(message.payload)
        with self.lock:
            if name == "connection":
                agv.online = doc.get("connectionState") == "ONLINE"
                return
            agv.first_state = True
            stamp = datetime.fromisoformat(str(doc["timestamp"]).replace("Z", "+00:00")).timestamp()
            if self.measuring:
                self.states += 1
                self.latencies_s.append(received_wall - stamp)
                if doc.get("driving"):
                    self.latencies_driving_s.append(received_wall - stamp)
            self._progress(agv, doc, received_mono)

    def _progress(self, agv: _Agv, doc: dict[str, Any], received_mono: float) -> None:
        """An order's motion and end, from one state (under the lock)."""
        if not agv.orders or agv.orders[-1].done is not None:
            return
        order = agv.orders[-1]
        if doc.get("orderId") != order.order_id:
            return
        last = doc.get("lastNodeId")
        if order.motion_s is None and (doc.get("driving") or (last and last != order.path[0])):
            order.motion_s = received_mono - order.sent_mono
        for error in doc.get("errors", []):
            refs = {r.get("referenceKey"): r.get("referenceValue") for r in error.get("errorReferences", [])}
            if refs.get("orderId") == order.order_id or "reason" in refs:  # rejected, or a leg failed
                order.done = f"failed: {error.get('errorType')}: {error.get('errorDescription', '')}"[:200]
                agv.stopped = True
                return
        if (
            not doc.get("nodeStates")
            and not doc.get("edgeStates")
            and not doc.get("driving")
            and last == order.path[-1]
        ):
            order.done = "finished"
            agv.node = last

    def send_order(self, agv: _Agv, order_id: str, path: list[str]) -> None:
        """Publish a move order along `path` to `agv` and record it."""
        from palletpilot.executor.apps.vda5050.validation import Stamper

        nodes, edges = [], []
        for i, node in enumerate(path):
            nodes.append({"nodeId": node, "sequenceId": 2 * i, "released": True, "actions": []})
            if i:
                edges.append(
                    {
                        "edgeId": f"{path[i - 1]}-{node}",
                        "sequenceId": 2 * i - 1,
                        "released": True,
                        "actions": [],
                    }
                )
                if self.protocol == "2.1.0":  # 3.0 edges join their nodes by sequenceId
                    edges[-1].update(startNodeId=path[i - 1], endNodeId=node)
        agv.header += 1
        doc = {
            "headerId": agv.header,
            "timestamp": Stamper()(),
            "version": self.protocol,
            "manufacturer": "palletpilot",
            "serialNumber": agv.serial,
            "orderId": order_id,
            "orderUpdateId": 0,
            "nodes": nodes,
            "edges": edges,
        }
        with self.lock:
            agv.orders.append(_Order(order_id, list(path), time.monotonic()))
        self.client.publish(f"{self.prefix}/{agv.serial}/order", json.dumps(doc), qos=0)

    def close(self) -> None:
        """Stop the network thread and disconnect."""
        self.client.loop_stop()
        self.client.disconnect()


def _write_config(folder: Path, serial: str, port: int, args: argparse.Namespace) -> Path:
    """missions/agv.yaml for one AGV: this broker, its serial number, absolute map and vehicle paths."""
    import yaml

    from palletpilot.geometry.fileio import bundled_path

    doc = yaml.safe_load(bundled_path("missions", "agv.yaml").read_text())
    doc["broker"].update(host="127.0.0.1", port=port)
    doc.update(
        serial_number=serial,
        map=str(bundled_path("missions", "warehouse.yaml")),
        vehicle=str(bundled_path("missions", "forklift.yaml")),
        state_interval_s=float(args.state_interval_s),
        visualization_hz=float(args.visualization_hz),
        protocol_version=args.protocol,
    )
    if args.protocol != "2.1.0":
        doc["interface_name"] = None  # the version's own (vda5050 on 3.0)
    path = folder / f"agv-{serial}.yaml"
    path.write_text(yaml.safe_dump(doc))
    return path


def _launch(agv: _Agv, config: Path, scenario: Path, folder: Path, ready: queue.Queue[tuple[str, str]]) -> None:
    """Start one `palletpilot agv` in a session of its own; its first stdout line goes to `ready`."""
    cmd = [sys.executable, "-m", "palletpilot.cli", "agv", "--config", str(config), "--sim", str(scenario)]
    report = folder / f"agv-{agv.serial}"
    for old in report.glob("agv.db*"):  # an earlier run's journal (`--out` reused) would restore its order
        old.unlink()
    cmd += ["--labels", "truth", "--seed", str(agv.sim_seed), "--report", str(report)]
    agv.log = (folder / f"agv-{agv.serial}.log").open("w")
    agv.proc = subprocess.Popen(
        cmd,
        stdin=subprocess.DEVNULL,
        stdout=subprocess.PIPE,
        stderr=agv.log,
        text=True,
        env={**os.environ, "PYTHONUNBUFFERED": "1"},
        start_new_session=True,  # Ctrl-C reaches the bench only, which stops every AGV itself
    )
    proc = agv.proc

    def read() -> None:
        assert proc.stdout is not None
        line = proc.stdout.readline()
        ready.put((agv.serial, line))
        for _ in proc.stdout:  # keep the pipe drained
            pass

    threading.Thread(target=read, daemon=True).start()


def _stop_all(agvs: list[_Agv]) -> None:
    """SIGTERM every AGV still running, wait up to `STOP_TIMEOUT_S` s for all, then SIGKILL the rest."""
    running = [a.proc for a in agvs if a.proc is not None and a.proc.poll() is None]
    for proc in running:
        proc.terminate()
    deadline = time.monotonic() + STOP_TIMEOUT_S
    for proc in running:
        try:
            proc.wait(timeout=max(0.1, deadline - time.monotonic()))
        except subprocess.TimeoutExpired:
            proc.kill()
            proc.wait()
    for a in agvs:
        if a.log is not None:
            a.log.close()
            a.log = None


def _cpu_s(pid: int) -> float | None:
    """User + system CPU time (s) of a running process from Linux's /proc/PID/stat; None once it is gone (or
    without /proc). No psutil: it is not among palletpilot's dependencies."""
    try:
        stat = Path(f"/proc/{pid}/stat").read_text()
    except OSError:
        return None
    fields = stat[stat.rindex(")") + 2 :].split()  # after "pid (comm) ": state is field 3, utime 14, stime 15
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")


@contextmanager
def _sigterm_as_interrupt() -> Iterator[None]:
    """SIGTERM to the bench raises KeyboardInterrupt (in the main thread), so the cleanup runs as on Ctrl-C."""
    if threading.current_thread() is not threading.main_thread():
        yield
        return

    def handler(signum: int, frame: FrameType | None) -> None:
        raise KeyboardInterrupt

    previous = signal.signal(signal.SIGTERM, handler)
    try:
        yield
    finally:
        signal.signal(signal.SIGTERM, previous)


def _tail(path: Path, chars: int = 300) -> str:
    try:
        return path.read_text(errors="replace")[-chars:].strip().replace("\n", " | ")
    except OSError:
        return ""


def run(args: argparse.Namespace) -> dict:
    """Start the broker and the fleet, run the orders, stop everything; the figures as a dict."""
    from palletpilot.geometry.fileio import bundled_path

    rng = np.random.default_rng(args.seed)
    serials = [f"{i + 1:04d}" for i in range(args.agvs)]
    agvs = {
        s: _Agv(
            s,
            int(rng.integers(0, 2**31)),
            [int(n) for n in rng.integers(1, args.edges_per_order + 1, args.orders_per_agv)],
        )
        for s in serials
    }
    scenario = bundled_path(*SCENARIO)
    startup_s = 0.0
    with tempfile.TemporaryDirectory(prefix="palletpilot-bench-fleet-") as tmp, _sigterm_as_interrupt():
        folder = Path(args.out or tmp)
        folder.mkdir(parents=True, exist_ok=True)
        broker = Broker(folder / "broker", kind=args.broker)
        master: _Master | None = None
        try:
            broker.start()
            master = _Master(broker.port, agvs, PREFIXES[args.protocol], args.protocol)
            if not master.connected.wait(10):
                raise FleetBenchError(f"bench fleet: the master could not connect to {broker!r}")
            ready: queue.Queue[tuple[str, str]] = queue.Queue()
            launched = time.monotonic()
            for a in agvs.values():
                _launch(a, _write_config(folder, a.serial, broker.port, args), scenario, folder, ready)
            _wait_ready(agvs, master, ready, folder, READY_TIMEOUT_S * args.agvs)
            startup_s = time.monotonic() - launched
            figures = _drive(agvs, master, broker)
        finally:
            if master is not None:
                master.close()
            _stop_all(list(agvs.values()))
            broker.stop()
    head = {"agvs": args.agvs, "protocol": args.protocol, "seed": args.seed, "broker": broker.kind}
    return {**head, "startup_s": round(startup_s, 1), **figures}


def _wait_ready(
    agvs: dict[str, _Agv], master: _Master, ready: queue.Queue[tuple[str, str]], folder: Path, timeout_s: float
) -> None:
    """Until every AGV printed its ready line, is ONLINE and sent a first state; RuntimeError otherwise."""
    deadline = time.monotonic() + timeout_s
    waiting = set(agvs)
    while waiting:
        try:
            serial, line = ready.get(timeout=max(0.1, deadline - time.monotonic()))
        except queue.Empty:
            raise FleetBenchError(f"bench fleet: AGVs {sorted(waiting)} not ready within {timeout_s:g} s") from None
        if not line.startswith("agv ready:"):
            why = line.strip() or _tail(folder / f"agv-{serial}.log")
            raise FleetBenchError(f"bench fleet: AGV {serial} did not start: {why}")
        waiting.discard(serial)
    while time.monotonic() < deadline:
        with master.lock:
            if all(a.online and a.first_state for a in agvs.values()):
                return
        time.sleep(POLL_S)
    raise FleetBenchError(f"bench fleet: not every AGV came ONLINE with a state within {timeout_s:g} s")


def _drive(agvs: dict[str, _Agv], master: _Master, broker: Broker) -> dict[str, Any]:
    """Send every AGV its orders in turn until all are done; the measured figures."""
    fleet = list(agvs.values())
    for a in fleet:
        assert a.proc is not None
        a.cpu_start_s = _cpu_s(a.proc.pid) or 0.0
    broker_cpu0 = _cpu_s(broker.proc.pid) if broker.proc is not None else None
    load_start = os.getloadavg()[0]
    start = time.monotonic()
    with master.lock:
        master.measuring = True
    while True:
        now = time.monotonic()
        busy = False
        for a in fleet:
            with master.lock:
                current = a.orders[-1] if a.orders else None
                if current is not None and current.done is None:
                    edges = len(current.path) - 1
                    if now - current.sent_mono > ORDER_TIMEOUT_S + ORDER_TIMEOUT_PER_EDGE_S * edges:
                        current.done = f"failed: not finished within {now - current.sent_mono:.0f} s"
                        a.stopped = True
                    else:
                        busy = True
                        continue
                if a.stopped or len(a.orders) >= len(a.lengths):
                    continue
            if a.proc is not None and a.proc.poll() is not None:
                a.stopped = True
                with master.lock:
                    a.orders.append(_Order(f"fleet-{a.serial}-dead", [a.node], now, done="failed: AGV exited"))
                continue
            n = a.lengths[len(a.orders)]
            path = [LOOP[(a.position + i) % len(LOOP)] for i in range(n + 1)]
            a.position = (a.position + n) % len(LOOP)
            master.send_order(a, f"fleet-{a.serial}-{len(a.orders) + 1}", path)
            busy = True
        if not busy:
            break
        time.sleep(POLL_S)
    wall_s = time.monotonic() - start
    with master.lock:
        master.measuring = False
        latencies = list(master.latencies_s)
        driving = ms_stats(list(master.latencies_driving_s))
        states = master.states
    cpu = []
    for a in fleet:
        assert a.proc is not None
        end = _cpu_s(a.proc.pid)
        if end is not None:
            cpu.append(100.0 * (end - a.cpu_start_s) / wall_s)
    broker_cpu1 = _cpu_s(broker.proc.pid) if broker.proc is not None else None
    orders = [o for a in fleet for o in a.orders if not o.order_id.endswith("-dead")]
    failures = [f"{o.order_id}: {o.done}" for a in fleet for o in a.orders if o.done != "finished"]
    latency = ms_stats(latencies)
    motion = ms_stats([o.motion_s for o in orders if o.motion_s is not None])
    p99 = latency["p99"]
    return {
        "orders": len(orders),
        "orders_finished": sum(o.done == "finished" for o in orders),
        "orders_failed": len(failures),
        "state_latency_ms_p50": latency["median"],
        "state_latency_ms_p99": p99,
        "state_latency_ms_max": latency["max"],
        "state_latency_ms_p99_driving": driving["p99"],
        "order_to_motion_ms_p50": motion["median"],
        "order_to_motion_ms_p99": motion["p99"],
        "order_to_motion_ms_max": motion["max"],
        "cpu_per_agv_percent": round(float(np.mean(cpu)), 1) if cpu else None,
        "cpu_per_agv_percent_max": round(float(np.max(cpu)), 1) if cpu else None,
        "broker_cpu_percent": (
            round(100.0 * (broker_cpu1 - broker_cpu0) / wall_s, 2)
            if broker_cpu0 is not None and broker_cpu1 is not None
            else None
        ),
        "state_messages": states,
        "states_per_s": round(states / wall_s, 1),
        "wall_s": round(wall_s, 1),
        "cpus": os.cpu_count(),
        "load_avg_1min_start": round(load_start, 2),
        "load_avg_1min": round(os.getloadavg()[0], 2),
        "goal_state_latency_ms_p99": STATE_LATENCY_GOAL_MS,
        "meets_goal": p99 is not None and p99 <= STATE_LATENCY_GOAL_MS and not failures,
        "failures": failures[:MAX_FAILURE_LINES],
    }
