"""A local MQTT broker for tests and benchmarks: a throwaway broker on a free loopback port.

`Broker(folder, port=None, kind="auto")` writes its configuration and log into `folder` and, on `start()`,
runs the broker as a child process listening on 127.0.0.1 only, anonymous, without persistence (a restart
forgets retained messages and sessions), and returns once the port accepts TCP connections. `stop()` ends it
(SIGTERM, then SIGKILL after `STOP_TIMEOUT_S`); a `Broker` is also a context manager (start ... stop).

Which broker (`kind`):
- `"mosquitto"`: Debian's Eclipse Mosquitto (`/usr/sbin/mosquitto`, else `mosquitto` on PATH; Debian package
  `mosquitto`). Preferred: it is what the tests were written against, and it is fast.
- `"amqtt"`: the pure-Python broker of the `amqtt` package (MQTT 3.1.1, which is what the AGV speaks), when
  `amqtt` is importable in this interpreter (`python -m amqtt.scripts.broker_script`) or its `amqtt` console
  script is on PATH (e.g. installed with `pipx install amqtt`: amqtt 0.12 pins `websockets==15.0.1`, which
  clashes with palletpilot's own environment, so it is best kept in a virtual environment of its own).
  Not fully conformant: amqtt 0.12.1 delivers QoS 0 messages to a QoS 1 subscription at QoS 1 (MQTT 3.1.1,
  3.8.4: the lower of the two), so a test of the QoS a master receives needs mosquitto.
- `"auto"` (default): mosquitto when installed, else amqtt, else `BrokerUnavailableError`.

The children start in a session of their own, so Ctrl-C in a terminal reaches the parent only, which stops
them in its own order (`stop()`), never half of them.

Public API: `Broker`, `BrokerUnavailableError`, `available_kind`, `broker_command`, `free_port`, `KINDS`,
`MOSQUITTO`.
"""

from __future__ import annotations

import importlib.util
import shutil
import socket
import subprocess
import sys
import time
from pathlib import Path
from types import TracebackType
from typing import IO, Literal

from palletpilot.executor.adapters.processes import end_process, free_port
from palletpilot.geometry import PalletpilotError

MOSQUITTO = Path("/usr/sbin/mosquitto")
KINDS = ("auto", "mosquitto", "amqtt")
HOST = "127.0.0.1"
START_TIMEOUT_S = 15.0  # amqtt imports for a few seconds on a loaded machine
STOP_TIMEOUT_S = 10.0
_PORT_TRIES = 3  # a free port found by bind() can be taken by another process before the broker binds it

Kind = Literal["auto", "mosquitto", "amqtt"]


class BrokerUnavailableError(PalletpilotError):
    """No MQTT broker can be run here (none installed), or the broker did not come up (the message says why)."""


def _mosquitto() -> list[str] | None:
    if MOSQUITTO.exists():
        return [str(MOSQUITTO)]
    found = shutil.which("mosquitto")
    return [found] if found else None


def _amqtt() -> list[str] | None:
    if importlib.util.find_spec("amqtt") is not None:
        return [sys.executable, "-m", "amqtt.scripts.broker_script"]
    found = shutil.which("amqtt")
    return [found] if found else None


def broker_command(kind: Kind) -> tuple[str, list[str]] | None:
    """The broker `kind` resolves to here and the command that runs it (config file not yet appended), or None."""
    if kind not in KINDS:
        raise BrokerUnavailableError(f"unknown MQTT broker kind {kind!r}: one of {', '.join(KINDS)}")
    if kind in ("auto", "mosquitto"):
        cmd = _mosquitto()
        if cmd is not None:
            return "mosquitto", cmd
        if kind == "mosquitto":
            return None
    cmd = _amqtt()
    return ("amqtt", cmd) if cmd is not None else None


def available_kind(kind: Kind = "auto") -> str | None:
    """`"mosquitto"` or `"amqtt"`: the broker `Broker(..., kind=kind)` would run here; None when none can."""
    found = broker_command(kind)
    return found[0] if found else None


def _missing(kind: Kind) -> str:
    mosquitto = "mosquitto (Debian package mosquitto: /usr/sbin/mosquitto)"
    amqtt = "amqtt (`pip install amqtt` in this interpreter, or its `amqtt` script on PATH)"
    wanted = {"mosquitto": mosquitto, "amqtt": amqtt}.get(kind, f"{mosquitto} or {amqtt}")
    return f"no MQTT broker to start: needs {wanted}"


class Broker:
    """A local MQTT broker on 127.0.0.1:`port` (a free one when None); files in `folder`.

    Attributes: `kind` ("mosquitto" or "amqtt", resolved at construction), `port`, `host`, `conf` (its
    configuration file), `log` (its stdout and stderr), `proc` (the child process while running).
    Raises `BrokerUnavailableError` at construction when no broker of `kind` is installed.
    """

    def __init__(self, folder: Path, port: int | None = None, kind: Kind = "auto") -> None:
        found = broker_command(kind)
        if found is None:
            raise BrokerUnavailableError(_missing(kind))
        self.kind, self._command = found
        self.folder = Path(folder)
        self.folder.mkdir(parents=True, exist_ok=True)
        self._fixed_port = port is not None
        self.port = port if port is not None else free_port()
        self.host = HOST
        self.conf = self.folder / ("mosquitto.conf" if self.kind == "mosquitto" else "amqtt.yaml")
        self.log = self.folder / f"{self.kind}.log"
        self.proc: subprocess.Popen[bytes] | None = None
        self._log_file: IO[bytes] | None = None
        self._write_conf()

    def _write_conf(self) -> None:
        if self.kind == "mosquitto":
            self.conf.write_text(f"listener {self.port} {HOST}\nallow_anonymous true\npersistence false\n")
        else:  # amqtt: one TCP listener, anonymous logins, none of the default logging or $SYS plugins
            self.conf.write_text(
                f"listeners:\n  default:\n    type: tcp\n    bind: {HOST}:{self.port}\n"
                "plugins:\n  amqtt.plugins.authentication.AnonymousAuthPlugin:\n    allow_anonymous: true\n"
            )

    @property
    def running(self) -> bool:
        """Whether the broker's process is alive."""
        return self.proc is not None and self.proc.poll() is None

    def start(self, timeout_s: float = START_TIMEOUT_S) -> None:
        """Run the broker and return once it accepts connections (within `timeout_s` s per try).

        On a port taken meanwhile (the broker exits at once), a broker with a port of its own choice tries
        again on another free port (the first start only: a restart keeps the port). Raises
        `BrokerUnavailableError` with the end of its log otherwise.
        """
        if self.running:
            return
        for attempt in range(_PORT_TRIES):
            why = self._start_once(timeout_s)
            if why is None:
                self._fixed_port = True  # a restart comes back on the same port: clients reconnect to it
                return
            self.stop()
            if self._fixed_port or attempt == _PORT_TRIES - 1 or why.startswith("did not accept"):
                tail = self.log.read_text(errors="replace")[-500:].strip()
                raise BrokerUnavailableError(f"{self.kind} on {HOST}:{self.port} {why}; {self.log}: {tail}")
            self.port = free_port()
            self._write_conf()

    def _start_once(self, timeout_s: float) -> str | None:
        """None once the port accepts, else why not."""
        self._log_file = self.log.open("ab")
        self.proc = subprocess.Popen(
            [*self._command, "-c", str(self.conf)],
            stdin=subprocess.DEVNULL,
            stdout=self._log_file,
            stderr=subprocess.STDOUT,
            start_new_session=True,  # Ctrl-C goes to the parent, which stops the broker last
        )
        deadline = time.monotonic() + timeout_s
        while time.monotonic() < deadline:
            code = self.proc.poll()
            if code is not None:
                return f"exited with code {code}"
            with socket.socket() as s:
                s.settimeout(1.0)
                if s.connect_ex((HOST, self.port)) == 0:
                    return None
            time.sleep(0.05)
        return f"did not accept connections within {timeout_s:g} s"

    def stop(self) -> None:
        """End the broker: SIGTERM, SIGKILL after `STOP_TIMEOUT_S` s; a no-op when not running."""
        proc, self.proc = self.proc, None
        if proc is not None:
            end_process(proc, STOP_TIMEOUT_S)
        if self._log_file is not None:
            self._log_file.close()
            self._log_file = None

    def __enter__(self) -> Broker:
        self.start()
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.stop()

    def __repr__(self) -> str:
        return f"Broker({self.kind} on {self.host}:{self.port}, {'running' if self.running else 'stopped'})"
