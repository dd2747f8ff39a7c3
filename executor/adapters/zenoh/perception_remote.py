"""The perception service's client (`RemotePerception`) and a service subprocess for one run (`LocalService`).

`RemotePerception` implements the `PerceptionService` port (`executor.ports`) over Zenoh: every call
is a query to `PREFIX/NAME` of a `palletpilot perception serve` process (`executor.perception_server`,
wire format `perception.wire`) with its own deadline (`Deadlines`: calibrate 10 s, estimate 3 s,
volume check 2 s). A service that does not answer (not running, killed, restarted, unreachable) or
answers `busy` is asked again after a short backoff, at most `retries` times; then the call raises
the failure the task already handles, with the reason `perception_unavailable` (`UNAVAILABLE`):

- `calibrate`: `CalibrationUnavailableError` (a `CalibrationError`): the Pickup retries its calibration
  once, then fails with `calibration_failed`;
- `estimate_pallet`: `PalletUnavailableError` (a `PalletNotFound`): the Pickup fails with
  `pallet_not_found`, or, when it then looks at the entry volume, with `safety_check_failed`;
- `check_volume`: `VolumeCheckUnavailableError`, a `TaskFailed` with `safety_check_failed`: an entry
  the camera cannot check is never entered.

The vehicle already stands while perception works, and every failed task stops it. Every wait has a
deadline: a call returns within `Deadlines.bound(name)` (attempts x deadline + backoffs + a grace for
the transport) whatever the network does. A service's own answer (a pallet not found, a failed
calibration) is raised as the same exception type with the same reason, never retried.

With `frame=None` (`frames=None` for `calibrate`) the service grabs the frame from its own camera at
the given lift height (`fork_height`, m): on a truck the frames never cross the network.

`LocalService` runs `palletpilot perception serve` as a subprocess on a free loopback port with the
run's forks, pallet type and model, waits for its ready line (`ready_timeout_s`), and stops it
(SIGTERM, then SIGKILL after `stop_timeout_s`) when the run ends, also on a failure or Ctrl-C; the
service also exits by itself when its parent dies. `remote_perception(mode, ...)` gives the client for
`palletpilot run --perception remote|serve-local` and checks the service's forks against the run's.

Public API: `RemotePerception`, `Deadlines`, `LocalService`, `remote_perception`, `free_port`, `PerceptionMode`,
`UNAVAILABLE`, `PerceptionUnavailableError`, `CalibrationUnavailableError`, `PalletUnavailableError`,
`VolumeCheckUnavailableError`.
"""

from __future__ import annotations

import contextlib
import os
import queue
import selectors
import shutil
import subprocess
import sys
import tempfile
import time
import weakref
from collections.abc import Iterator, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any, Literal, cast

import zenoh

from palletpilot.executor.adapters.processes import end_process, free_port, keep_heap_mapped
from palletpilot.executor.adapters.zenoh.perception_server import (
    DEFAULT_LISTEN,
    PARENT_ENV,
    zenoh_config,
    zenoh_problem,
)
from palletpilot.executor.core.errors import SAFETY_CHECK_FAILED, TaskFailed
from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import dumps_json
from palletpilot.perception import wire
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.clearance import Volume, VolumeCheck
from palletpilot.perception.errors import CalibrationError, PerceptionError
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.labels_mode import DEFAULT_LABELS_MODE, LabelsMode
from palletpilot.perception.pallet_estimate import NotFoundReason, PalletEstimate, PalletNotFound
from palletpilot.perception.specs import ForkGeometry, PalletType

PerceptionMode = Literal["local", "remote", "serve-local"]
"""Where a run's perception works: in process, a running service, or a service started for the run."""

UNAVAILABLE = "perception_unavailable"
"""The reason of a call the service did not answer (after its retries)."""


class PerceptionUnavailableError(PerceptionError):
    """The service did not answer `health` or `segment` within the deadline and retries."""

    reason = UNAVAILABLE


class CalibrationUnavailableError(CalibrationError):
    """`calibrate` got no answer: the task's calibration failure, reason `perception_unavailable`."""

    reason = UNAVAILABLE


class PalletUnavailableError(PalletNotFound):
    """`estimate_pallet` got no answer: the task's `pallet_not_found`, reason `perception_unavailable`."""

    def __init__(self, message: str) -> None:
        super().__init__(cast(NotFoundReason, UNAVAILABLE), message)


class VolumeCheckUnavailableError(TaskFailed):
    """`check_volume` got no answer: the entry cannot be checked, so the task fails (`safety_check_failed`)."""

    def __init__(self, message: str) -> None:
        super().__init__(SAFETY_CHECK_FAILED, f"{message}: the camera cannot check the volume, nothing is entered")


@dataclass(frozen=True)
class Deadlines:
    """Per-call deadlines (s, wall clock), retries and the backoff (s) before each retry."""

    calibrate_s: float = 10.0
    estimate_s: float = 3.0
    check_s: float = 2.0
    segment_s: float = 3.0
    health_s: float = 2.0
    retries: int = 2
    backoff_s: tuple[float, ...] = (0.2, 0.5)
    grace_s: float = 0.5
    """Beyond a query's own timeout the client waits this long for Zenoh to end it, then gives up anyway."""

    def of(self, name: str) -> float:
        """The deadline (s) of one attempt of request `name`."""
        return {
            "calibrate": self.calibrate_s,
            "estimate_pallet": self.estimate_s,
            "check_volume": self.check_s,
            "segment": self.segment_s,
        }.get(name, self.health_s)

    def backoff(self, attempt: int) -> float:
        """The pause (s) before retry `attempt` (0-based)."""
        return self.backoff_s[min(attempt, len(self.backoff_s) - 1)] if self.backoff_s else 0.0

    def bound(self, name: str) -> float:
        """The longest a call of `name` can take (s): every attempt, its grace and every backoff."""
        return (self.retries + 1) * (self.of(name) + self.grace_s) + sum(self.backoff(i) for i in range(self.retries))


_DONE = object()


def _close(session: zenoh.Session) -> None:
    with contextlib.suppress(zenoh.ZError):
        session.close()


@dataclass
class _Stats:
    calls: int = 0
    retries: int = 0
    unavailable: int = 0
    last_ms: dict[str, float] = field(default_factory=dict)


class RemotePerception:
    """`PerceptionService` over Zenoh: the client of `palletpilot perception serve` (module docstring).

    `connect`: the service's endpoints (`tcp/HOST:PORT`); `session`: an open Zenoh session to use
    instead (not closed by `close()`). `depth`: how frames travel (`f32` exact metres, `mm16`
    millimetres, half the bytes).
    """

    def __init__(
        self,
        connect: Sequence[str] = (DEFAULT_LISTEN,),
        prefix: str = wire.DEFAULT_PREFIX,
        deadlines: Deadlines | None = None,
        session: zenoh.Session | None = None,
        depth: wire.DepthEncoding = "f32",
    ) -> None:
        self.prefix = prefix.rstrip("/")
        self.deadlines = deadlines or Deadlines()
        self.endpoints = list(connect)
        self.depth: wire.DepthEncoding = depth
        self.stats = _Stats()
        self._last_good: Calibration | None = None
        self._cal_doc: tuple[Calibration, dict[str, Any]] | None = None
        self._own = session is None
        if session is None:
            try:
                session = zenoh.open(zenoh_config(connect=self.endpoints))
            except zenoh.ZError as exc:
                raise PerceptionError(
                    f"perception service at {', '.join(self.endpoints)}: {zenoh_problem(exc)}"
                ) from None
            self._finalizer = weakref.finalize(self, _close, session)  # never a process that hangs at exit
        self._session: zenoh.Session | None = session

    def close(self) -> None:
        """Close the Zenoh session (when this client opened it)."""
        if self._session is not None and self._own:
            self._finalizer()
        self._session = None

    def __enter__(self) -> RemotePerception:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    @property
    def where(self) -> str:
        """The service, for messages: `PREFIX on ENDPOINTS`."""
        return f"{self.prefix} on {', '.join(self.endpoints) or 'the session'}"

    # -- the port ------------------------------------------------------------------------------------

    def calibrate(self, frames: Sequence[FrameBundle] | None, fork_height: float = 0.0) -> Calibration:
        """`T_forklift_camera` (lift height 0) from frames of the forks and the floor (`CalibrationError`);
        `frames=None`: one frame from the service's camera at `fork_height` (m)."""
        if frames is not None and not frames:
            raise CalibrationError("no frames to calibrate from")
        params = {"fork_height": fork_height} if frames is None else {}
        reply = self._call("calibrate", params, list(frames or ()), CalibrationUnavailableError)
        calibration = wire.calibration_from_json(reply, self._key("calibrate"))
        self._last_good = calibration
        return calibration

    def estimate_pallet(
        self,
        frame: FrameBundle | None,
        calibration: Calibration,
        T_world_forklift: SE2,
        expected_T_world_pallet: SE2 | None = None,
        pallet: PalletType | None = None,
        support_height_m: float = 0.0,
        fork_height: float = 0.0,
    ) -> PalletEstimate:
        """The pallet's pose in the forklift and world frames (`PalletNotFound`, with its reason); see
        `PerceptionService.estimate_pallet`. `frame=None`: the service's camera at `fork_height` (m)."""
        params: dict[str, Any] = {
            "calibration": self._calibration_json(calibration),
            "T_world_forklift": wire.se2_to_json(T_world_forklift),
            "expected_T_world_pallet": None
            if expected_T_world_pallet is None
            else wire.se2_to_json(expected_T_world_pallet),
            "pallet": None if pallet is None else wire.pallet_to_json(pallet),
            "support_height_m": support_height_m,
        }
        if frame is None:
            params["fork_height"] = fork_height
        reply = self._call("estimate_pallet", params, [] if frame is None else [frame], PalletUnavailableError)
        return wire.estimate_from_json(reply, self._key("estimate_pallet"))

    def check_volume(
        self, frame: FrameBundle | None, calibration: Calibration, volume: Volume, fork_height: float = 0.0
    ) -> VolumeCheck:
        """Depth points inside `volume` (forklift frame, m) and the share of it seen; `frame=None`: the
        service's camera at `fork_height` (m). No answer: `VolumeCheckUnavailableError` (`safety_check_failed`)."""
        params: dict[str, Any] = {
            "calibration": self._calibration_json(calibration),
            "volume": wire.volume_to_json(volume),
        }
        if frame is None:
            params["fork_height"] = fork_height
        reply = self._call("check_volume", params, [] if frame is None else [frame], VolumeCheckUnavailableError)
        return wire.volume_check_from_json(reply, self._key("check_volume"))

    def segment(self, frame: FrameBundle | None, fork_height: float = 0.0) -> FrameBundle:
        """The frame with labels from the service's model (`frame=None`: the service's camera)."""
        params = {"fork_height": fork_height} if frame is None else {}
        payload = self._call("segment", params, [] if frame is None else [frame], PerceptionUnavailableError, raw=True)
        return wire.decode_frame(payload, self._key("segment"))

    def health(self) -> dict[str, Any]:
        """The service's health: model, provider, camera, uptime_s, requests_served, last_error, forks, ..."""
        reply = self._call("health", {}, [], PerceptionUnavailableError)
        body = reply.get("health")
        if not isinstance(body, dict):
            raise PerceptionError(f"{self._key('health')}: malformed health reply")
        return body

    @property
    def last_good(self) -> Calibration | None:
        """The last calibration the service returned to this client."""
        return self._last_good

    def _calibration_json(self, calibration: Calibration) -> dict[str, Any]:
        """The calibration's wire document, made once per calibration (it goes with every request)."""
        if self._cal_doc is None or self._cal_doc[0] is not calibration:
            self._cal_doc = (calibration, wire.calibration_to_json(calibration))
        return self._cal_doc[1]

    # -- queries -------------------------------------------------------------------------------------

    def _key(self, name: str) -> str:
        return f"{self.prefix}/{name}"

    def _call(
        self,
        name: str,
        params: dict[str, Any],
        frames: list[FrameBundle],
        unavailable: type[Exception],
        raw: bool = False,
    ) -> Any:
        """One request with retries; the decoded JSON reply (or the raw payload with `raw`)."""
        deadline = self.deadlines.of(name)
        payload = (
            b"" if name == "health" else wire.encode_request({**params, "timeout_s": deadline}, frames, self.depth)
        )
        key = self._key(name)
        self.stats.calls += 1
        attempts = self.deadlines.retries + 1
        why = ""
        for attempt in range(attempts):
            if attempt:
                self.stats.retries += 1
                time.sleep(self.deadlines.backoff(attempt - 1))
            t0 = time.perf_counter()
            reply, why = self._get(key, payload, deadline)
            if reply is None:
                continue
            self.stats.last_ms[name] = (time.perf_counter() - t0) * 1e3
            if raw and wire.is_frame(reply):
                return reply
            doc = wire.decode_json(reply, key)
            if "error" in doc:
                kind = doc["error"].get("type") if isinstance(doc["error"], dict) else None
                if kind in ("busy", "expired"):  # the service is there but cannot take it now: ask again
                    why = f"answered {kind}"
                    continue
                raise wire.error_from_json(doc, key)
            return doc
        self.stats.unavailable += 1
        raise unavailable(
            f"perception service unavailable: {key} on {', '.join(self.endpoints) or 'the session'}: {why} "
            f"({attempts} attempts, {deadline:g} s deadline each)"
        )

    def _get(self, key: str, payload: bytes | bytearray, deadline: float) -> tuple[bytes | None, str]:
        """The first reply's payload to one query, or None and why; returns within `deadline + grace_s`."""
        session = self._session
        if session is None:
            return None, "the client is closed"
        replies: queue.SimpleQueue[Any] = queue.SimpleQueue()
        handler = zenoh.handlers.Callback(replies.put, lambda: replies.put(_DONE))
        try:
            session.get(key, handler, payload=payload, timeout=deadline)
        except zenoh.ZError as exc:
            return None, f"query failed: {zenoh_problem(exc)}"
        end = time.monotonic() + deadline + self.deadlines.grace_s
        while True:
            try:
                item = replies.get(timeout=max(0.0, end - time.monotonic()))
            except queue.Empty:
                return None, f"no answer within {deadline:g} s"
            if item is _DONE:
                return None, "no service answers (not running, or unreachable)"
            reply = cast(zenoh.Reply, item)
            if reply.ok is not None:
                return reply.ok.payload.to_bytes(), ""
            err = reply.err
            text = err.payload.to_string() if err is not None else "unknown"
            if "timeout" in text.lower():
                return None, f"no answer within {deadline:g} s"
            return None, f"transport error: {text[:200]}"


# -- a service for one run -------------------------------------------------------------------------


class LocalService:
    """`palletpilot perception serve` as a subprocess on a free loopback port, for one run (module docstring).

    `start()` returns the endpoint once the service printed its ready line; `stop()` ends it. The
    service's stderr goes to a log file whose last line explains a failed start.
    """

    def __init__(
        self,
        forks: ForkGeometry,
        pallet: PalletType,
        model: str | Path | None = None,
        prefix: str = wire.DEFAULT_PREFIX,
        ready_timeout_s: float = 60.0,
        stop_timeout_s: float = 5.0,
        labels: LabelsMode = DEFAULT_LABELS_MODE,
    ) -> None:
        self.forks, self.pallet, self.model, self.prefix = forks, pallet, model, prefix
        self.labels = labels
        self.ready_timeout_s, self.stop_timeout_s = ready_timeout_s, stop_timeout_s
        self.process: subprocess.Popen[bytes] | None = None
        self.endpoint: str | None = None
        self.returncode: int | None = None
        self.ready_line = ""
        self._folder: Path | None = None

    def start(self) -> str:
        """Start the service and wait for its ready line; the endpoint (`tcp/127.0.0.1:PORT`)."""
        self._folder = Path(tempfile.mkdtemp(prefix="palletpilot-perception-"))
        forks, pallet = self._folder / "forks.json", self._folder / "pallet.json"
        # Only the fields the run's file set: a profile it leaves unknown stays unknown in the service.
        forks.write_text(dumps_json(self.forks.model_dump(mode="json", exclude_unset=True)))
        pallet.write_text(dumps_json(self.pallet.model_dump(mode="json")))
        problem = ""
        for _ in range(3):  # another process may take the free port before the service binds it
            endpoint = f"tcp/127.0.0.1:{free_port()}"
            argv = [sys.executable, "-m", "palletpilot.cli", "perception", "serve", "--listen", endpoint]
            argv += ["--forks", str(forks), "--pallet", str(pallet), "--prefix", self.prefix, "--labels", self.labels]
            if self.model is not None:
                argv += ["--model", str(self.model)]
            problem = self._launch(argv)
            if not problem:
                self.endpoint = endpoint
                return endpoint
            if "in use" not in problem:
                break
        self.stop()
        raise PerceptionError(f"perception service did not start: {problem}")

    def _launch(self, argv: list[str]) -> str:
        """Start one process and wait for its ready line: '' when ready, else why not (process ended)."""
        assert self._folder is not None
        log = (self._folder / "service.log").open("wb")
        env = {**os.environ, PARENT_ENV: str(os.getpid())}
        with log:  # the child holds its own descriptor
            self.process = subprocess.Popen(
                argv, stdin=subprocess.DEVNULL, stdout=subprocess.PIPE, stderr=log, env=env, start_new_session=True
            )
        assert self.process.stdout is not None
        end = time.monotonic() + self.ready_timeout_s
        buffer = b""
        with selectors.DefaultSelector() as sel:
            sel.register(self.process.stdout, selectors.EVENT_READ)
            while b"\n" not in buffer:
                left = end - time.monotonic()
                if left <= 0:
                    self._end_process()
                    return f"no ready line within {self.ready_timeout_s:g} s"
                if not sel.select(timeout=min(left, 0.5)):
                    continue
                chunk = os.read(self.process.stdout.fileno(), 4096)
                if not chunk:  # the process ended
                    self._end_process()
                    return self._last_log_line() or f"exited with code {self.returncode}"
                buffer += chunk
        self.ready_line = buffer.decode(errors="replace").strip()
        if "ready" not in self.ready_line:
            self._end_process()
            return f"unexpected output: {self.ready_line[:200]}"
        return ""

    def _last_log_line(self) -> str:
        assert self._folder is not None
        try:
            lines = (self._folder / "service.log").read_text(errors="replace").strip().splitlines()
        except OSError:
            return ""
        return lines[-1] if lines else ""

    def _end_process(self) -> None:
        """SIGTERM, then SIGKILL after `stop_timeout_s`; reap it."""
        proc, self.process = self.process, None
        if proc is None:
            return
        self.returncode = end_process(proc, self.stop_timeout_s)
        if proc.stdout is not None:
            proc.stdout.close()

    def stop(self) -> None:
        """Stop the service (idempotent) and remove its files."""
        self._end_process()
        if self._folder is not None:
            shutil.rmtree(self._folder, ignore_errors=True)
            self._folder = None

    def __enter__(self) -> LocalService:
        self.start()
        return self

    def __exit__(self, *_exc: object) -> None:
        self.stop()


@contextlib.contextmanager
def remote_perception(
    mode: PerceptionMode,
    connect: Sequence[str],
    forks: ForkGeometry,
    pallet: PalletType,
    model: str | Path | None = None,
    prefix: str = wire.DEFAULT_PREFIX,
    labels: LabelsMode = DEFAULT_LABELS_MODE,
) -> Iterator[RemotePerception]:
    """The client for `run --perception remote` (the service at `connect`) or `serve-local` (a service
    started for the run, stopped on leaving). The service must answer `health` and use the run's forks,
    or `PerceptionError` says why before anything moves. The run's process keeps its heap mapped
    (`keep_heap_mapped`): every request encodes a frame of megabytes. A service whose labels mode is not
    the run's `labels` is refused too (a remote one is started with its own `--labels`)."""
    keep_heap_mapped()
    with contextlib.ExitStack() as stack:
        if mode == "serve-local":
            service = LocalService(forks, pallet, model, prefix, labels=labels)
            stack.callback(service.stop)
            connect = [service.start()]
        elif not connect:
            connect = [DEFAULT_LISTEN]
        client = stack.enter_context(RemotePerception(connect, prefix))
        health = client.health()
        if health.get("forks") != forks.model_dump(mode="json"):
            raise PerceptionError(
                f"perception service {client.where}: its forks {health.get('forks')} are not the run's "
                f"{forks.model_dump(mode='json')} (start it with the run's --forks file)"
            )
        theirs = health.get("labels", str(LabelsMode.MODEL))  # services from before the option used the model
        if theirs != labels:
            raise PerceptionError(
                f"perception service {client.where}: it selects pixels by '{theirs}' labels, the run by '{labels}' "
                f"(start it with --labels {labels}, or run with --labels {theirs})"
            )
        yield client
