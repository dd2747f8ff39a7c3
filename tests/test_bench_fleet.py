"""`palletpilot bench fleet` on its smallest run (two AGV processes, one one-edge order each, about 15 s) and
the local broker it starts (`executor.vda5050.broker`): start, stop, restart on the same port, and which broker
is chosen when mosquitto or amqtt is missing."""

from __future__ import annotations

import json
import os
import socket
import subprocess
import sys
from pathlib import Path

import pytest

from palletpilot.executor.apps.vda5050 import broker as broker_module
from palletpilot.executor.apps.vda5050.broker import Broker, BrokerUnavailableError, available_kind

needs_broker = pytest.mark.skipif(available_kind() is None, reason="needs mosquitto or amqtt (an MQTT broker)")

KEYS = {"agvs", "orders", "orders_finished", "state_latency_ms_p99", "order_to_motion_ms_p99", "cpu_per_agv_percent"}


def accepts(port: int) -> bool:
    with socket.socket() as s:
        return s.connect_ex(("127.0.0.1", port)) == 0


@needs_broker
@pytest.mark.parametrize("protocol", ["2.1.0", "3.0.0"])
def test_two_agvs_finish_their_orders(protocol: str) -> None:
    cmd = [sys.executable, "-m", "palletpilot.cli", "bench", "fleet", "--json", "--agvs", "2"]
    cmd += ["--orders-per-agv", "1", "--edges-per-order", "1", "--seed", "3", "--protocol", protocol]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=120, env={**os.environ, "PYTHONUNBUFFERED": "1"})
    assert done.returncode == 0, done.stderr[-2000:]
    figures = json.loads(done.stdout)
    assert KEYS <= set(figures)
    assert figures["agvs"] == 2 and figures["orders"] == 2 and figures["protocol"] == protocol
    assert figures["orders_finished"] == figures["orders"], figures["failures"]
    assert figures["state_latency_ms_p99"] is not None and figures["state_latency_ms_p99"] >= 0
    assert figures["order_to_motion_ms_p99"] is not None and figures["order_to_motion_ms_p99"] > 0
    assert figures["cpu_per_agv_percent"] is not None and figures["cpu_per_agv_percent"] > 0


def test_bad_options_exit_2() -> None:
    cmd = [sys.executable, "-m", "palletpilot.cli", "bench", "fleet", "--agvs", "0"]
    done = subprocess.run(cmd, capture_output=True, text=True, timeout=60)
    assert done.returncode == 2
    assert "--agvs" in done.stderr and "Traceback" not in done.stderr


@needs_broker
def test_broker_starts_restarts_on_its_port_and_stops(tmp_path: Path) -> None:
    with Broker(tmp_path) as b:
        assert b.running and accepts(b.port)
        port = b.port
        b.stop()
        assert not b.running
        b.start()
        assert b.port == port and accepts(port)
    assert not b.running and not accepts(port)
    b.stop()  # a no-op when stopped


def test_broker_choice_and_a_clear_error_without_any(monkeypatch: pytest.MonkeyPatch, tmp_path: Path) -> None:
    monkeypatch.setattr(broker_module, "MOSQUITTO", tmp_path / "no-mosquitto")
    monkeypatch.setattr(broker_module.shutil, "which", lambda name: None)
    monkeypatch.setattr(broker_module.importlib.util, "find_spec", lambda name: None)
    assert available_kind() is None
    with pytest.raises(BrokerUnavailableError, match="no MQTT broker to start: needs mosquitto"):
        Broker(tmp_path)
    # amqtt's console script on PATH (e.g. from pipx) when mosquitto is missing; never when mosquitto is asked for
    monkeypatch.setattr(broker_module.shutil, "which", lambda name: "/opt/amqtt/bin/amqtt" if name == "amqtt" else None)
    assert available_kind() == "amqtt" and available_kind("mosquitto") is None
    b = Broker(tmp_path)
    assert b.kind == "amqtt" and f"bind: 127.0.0.1:{b.port}" in b.conf.read_text()
    assert broker_module.broker_command("amqtt") == ("amqtt", ["/opt/amqtt/bin/amqtt"])
    # amqtt importable here: run as a module of this interpreter
    monkeypatch.setattr(broker_module.importlib.util, "find_spec", lambda name: object())
    assert broker_module.broker_command("auto") == ("amqtt", [sys.executable, "-m", "amqtt.scripts.broker_script"])
    # mosquitto installed: preferred
    fake = tmp_path / "mosquitto"
    fake.write_text("")
    monkeypatch.setattr(broker_module, "MOSQUITTO", fake)
    assert available_kind() == "mosquitto" and available_kind("amqtt") == "amqtt"
    with pytest.raises(BrokerUnavailableError, match="unknown MQTT broker kind"):
        broker_module.broker_command("rabbit")  # type: ignore[arg-type]
