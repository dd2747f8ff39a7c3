"""Perception as a service: a `LocalPerception` behind Zenoh queryables (`palletpilot perception serve`).

The service declares one queryable per request under a key prefix (`perception.wire.DEFAULT_PREFIX`,
`palletpilot/perception`): `calibrate`, `estimate_pallet`, `check_volume`, `segment` and `health`.
Requests and replies are in the wire format of `perception.wire`: a request carries JSON parameters
and, in the simulator, its frames; a request without a frame is served from the service's own camera
(`--camera realsense`: the frames never cross the network), with the lift height (`fork_height`, m)
from the request. Replies are JSON with `"version": 1` (a calibration, a pallet estimate, a volume
check, the health) or, for `segment`, the frame with its labels as an encoded bundle; a failure is a
JSON error naming its type and reason (`PalletNotFound` and its reason, `CalibrationError`, ...).

Concurrency: the geometry is CPU-bound, so one worker thread runs the requests in order from a
bounded queue (`queue_size`); a request that finds the queue full is answered `busy` at once, and
one that waited longer than its `timeout_s` (the client gave up) is answered `expired` without being
run. `health` is answered on Zenoh's own thread, so it answers while a long request runs. A bad
request (a malformed payload, a frame that breaks the bundle contract, a bug) is an error reply with
the reason and counts in `last_error`; it never stops the service.

Sessions: `zenoh_config` builds the configuration both ends use: explicit endpoints (`listen` for the
service, `connect` for a client or for a service that joins a router), multicast scouting off, quick
reconnection (a restarted peer is found again within a second).

Public API: `PerceptionServer` (`start(config)`, `close()`, `handle(name, payload)`, `health()`),
`zenoh_config`, `zenoh_problem`, `DEFAULT_LISTEN`, `DEFAULT_QUEUE_SIZE`.
"""

from __future__ import annotations

import contextlib
import dataclasses
import json
import queue
import threading
import time
from collections.abc import Sequence
from typing import Any, Literal

import zenoh

from palletpilot.executor.adapters.local_perception import LocalPerception
from palletpilot.perception import wire
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.errors import CalibrationError, PerceptionError
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.pallet_estimate import PalletNotFound
from palletpilot.perception.realsense import CameraSource
from palletpilot.perception.segmentation import OnnxSegmenter
from palletpilot.perception.specs import PalletType

PARENT_ENV = "PALLETPILOT_SERVE_PARENT"
"""Set by `executor.perception_remote.LocalService`: the service exits when the process of this id is gone."""

DEFAULT_LISTEN = "tcp/127.0.0.1:7447"
"""Where `palletpilot perception serve` listens unless told (loopback: the same computer only)."""
DEFAULT_QUEUE_SIZE = 4
"""Requests waiting for the worker beyond the one it runs; one more is answered `busy`."""

Mode = Literal["peer", "client", "router"]


def zenoh_config(listen: Sequence[str] = (), connect: Sequence[str] = (), mode: Mode = "peer") -> zenoh.Config:
    """A Zenoh session configuration on explicit endpoints (`tcp/HOST:PORT`), multicast scouting off.

    Raises `PerceptionError` (one line) for an endpoint Zenoh does not accept.
    """
    config = zenoh.Config()
    try:
        config.insert_json5("mode", json.dumps(mode))
        config.insert_json5("listen/endpoints", json.dumps(list(listen)))
        config.insert_json5("connect/endpoints", json.dumps(list(connect)))
        config.insert_json5("scouting/multicast/enabled", "false")
        # A restarted service is found again quickly (Zenoh's default waits up to 4 s between attempts).
        config.insert_json5(
            "connect/retry", '{"period_init_ms": 200, "period_max_ms": 1000, "period_increase_factor": 2}'
        )
    except zenoh.ZError as exc:
        raise PerceptionError(f"zenoh configuration: {zenoh_problem(exc)}") from None
    return config


def zenoh_problem(exc: BaseException) -> str:
    """A Zenoh error as one short line (without the Rust source location)."""
    text = " ".join(str(exc).split())
    for marker in (" at /", " at src/"):
        text = text.split(marker)[0]
    if text.count("[") > text.count("]"):  # the cut left a bracket of the nested error open
        i = text.rindex("[")
        text = text[:i] + text[i + 1 :]
    return text[:300]


@dataclasses.dataclass
class _Stats:
    started: float = dataclasses.field(default_factory=time.monotonic)
    served: int = 0
    errors: int = 0
    busy: int = 0
    last_error: str | None = None


class PerceptionServer:
    """A `LocalPerception` (and optionally a camera) behind Zenoh queryables under `prefix`.

    The perception's `segmenter` labels frames that come without labels (`health` names its model);
    `camera`: the service's own camera for requests without a frame (`camera_serial` names it);
    `queue_size`: requests that may wait behind the one the worker runs.
    """

    def __init__(
        self,
        perception: LocalPerception,
        prefix: str = wire.DEFAULT_PREFIX,
        camera: CameraSource | None = None,
        camera_serial: str | None = None,
        queue_size: int = DEFAULT_QUEUE_SIZE,
    ) -> None:
        self.perception = perception
        self.prefix = prefix.rstrip("/")
        self.camera = camera
        self.camera_serial = camera_serial
        self.stats = _Stats()
        self._queue: queue.Queue[tuple[str, zenoh.Query, float] | None] = queue.Queue(maxsize=queue_size)
        self._session: zenoh.Session | None = None
        self._queryables: list[Any] = []
        self._worker: threading.Thread | None = None
        self._lock = threading.Lock()  # the stats, written by the worker and Zenoh's threads
        self._calibrations: dict[str, Calibration] = {}  # the worker's cache of checked calibrations

    # -- lifecycle -----------------------------------------------------------------------------------

    def start(self, config: zenoh.Config) -> None:
        """Open the session, declare the queryables and start the worker; `PerceptionError` when Zenoh refuses."""
        try:
            self._session = zenoh.open(config)
            for name in wire.QUERIES:
                self._queryables.append(self._session.declare_queryable(self.key(name), self._callback(name)))
        except zenoh.ZError as exc:
            self.close()
            raise PerceptionError(f"perception service: {zenoh_problem(exc)}") from None
        self._worker = threading.Thread(target=self._work, name="perception-service", daemon=True)
        self._worker.start()

    def close(self) -> None:
        """Stop answering: undeclare, let the worker finish its request, close the session and the camera."""
        for q in self._queryables:
            with contextlib.suppress(zenoh.ZError):
                q.undeclare()
        self._queryables.clear()
        if self._worker is not None:
            while True:  # queued requests are answered by nobody: their clients time out and retry
                try:
                    item = self._queue.get_nowait()
                except queue.Empty:
                    break
                if item is not None:
                    item[1].drop()
            self._queue.put(None)
            self._worker.join(timeout=30.0)
            self._worker = None
        if self._session is not None:
            self._session.close()
            self._session = None
        if self.camera is not None:
            self.camera.close()
            self.camera = None

    def __enter__(self) -> PerceptionServer:
        return self

    def __exit__(self, *_exc: object) -> None:
        self.close()

    def key(self, name: str) -> str:
        """The key of one queryable (`PREFIX/NAME`)."""
        return f"{self.prefix}/{name}"

    # -- Zenoh side ----------------------------------------------------------------------------------

    def _callback(self, name: str) -> Any:
        def on_query(query: zenoh.Query) -> None:
            if name == "health":
                self._reply(query, name, wire.encode_json(self.health()))
                return
            try:
                self._queue.put_nowait((name, query, time.monotonic()))
            except queue.Full:
                with self._lock:
                    self.stats.busy += 1
                busy = wire.ServiceBusyError(f"{self.key(name)}: busy: {self._queue.maxsize} requests are waiting")
                self._reply(query, name, wire.encode_json(wire.error_to_json(busy, "busy")))

        return on_query

    def _reply(self, query: zenoh.Query, name: str, payload: bytes | bytearray) -> None:
        try:
            query.reply(self.key(name), payload)
        except zenoh.ZError as exc:  # the client went away: nothing to answer
            self._note_error(f"{self.key(name)}: reply failed: {zenoh_problem(exc)}")
        finally:
            query.drop()  # finalises the query: the client's get ends now, not at its timeout

    def _work(self) -> None:
        while True:
            item = self._queue.get()
            if item is None:
                return
            name, query, received = item
            try:
                payload = query.payload
                data = payload.to_bytes() if payload is not None else b""
                reply = self.handle(name, data, received)
            except Exception as exc:  # never lose the worker: a bug in one request is that request's error
                reply = wire.encode_json(wire.error_to_json(exc, "internal"))
                self._note_error(f"{self.key(name)}: internal error: {type(exc).__name__}: {exc}")
            self._reply(query, name, reply)

    # -- requests ------------------------------------------------------------------------------------

    def handle(self, name: str, payload: bytes, received: float | None = None) -> bytes | bytearray:
        """Run one request (`name` in `wire.QUERIES`) and return its reply payload; never raises for
        a bad request (its reply is a JSON error). `received`: when it arrived (`time.monotonic`)."""
        where = self.key(name)
        try:
            if name == "health":
                return wire.encode_json(self.health())
            params, frames = wire.decode_request(payload, where)
            timeout = params.get("timeout_s")
            if received is not None and isinstance(timeout, (int, float)) and time.monotonic() - received > timeout:
                raise _ExpiredError(
                    f"{where}: waited {time.monotonic() - received:.1f} s in the queue, past its {timeout} s"
                )
            reply = self._run(name, params, frames, where)
        except _ExpiredError as exc:
            return wire.encode_json(wire.error_to_json(exc, "expired"))
        except PerceptionError as exc:
            if not isinstance(exc, (PalletNotFound, CalibrationError)):
                self._note_error(str(exc))  # a bad request; a pallet not found or a failed calibration is an answer
            reply = wire.encode_json(wire.error_to_json(exc))
        with self._lock:
            self.stats.served += 1
        return reply

    def _run(self, name: str, params: dict[str, Any], frames: list[FrameBundle], where: str) -> bytes | bytearray:
        p = self.perception
        if name == "calibrate":
            shots = frames or [self._grab(params, where) for _ in range(_count(params, where))]
            return wire.encode_json(wire.calibration_to_json(p.calibrate(shots)))
        if name == "segment":
            frame = self._one(frames, params, where)
            if frame.rgb is None:
                raise PerceptionError(f"{where}: frame: no rgb to segment")
            if p.segmenter is None:
                raise PerceptionError(f"{where}: the service has no segmentation model")
            return wire.encode_frame(dataclasses.replace(frame, labels=p.segmenter.segment(frame.rgb)))
        if name not in ("estimate_pallet", "check_volume"):
            raise PerceptionError(f"{where}: unknown request (known: {', '.join(wire.QUERIES)})")
        frame = self._one(frames, params, where)
        calibration = self._calibration(_param(params, "calibration", where), f"{where}: calibration")
        if name == "check_volume":
            volume = wire.volume_from_json(_param(params, "volume", where), f"{where}: volume")
            return wire.encode_json(wire.volume_check_to_json(p.check_volume(frame, calibration, volume)))
        pose = wire.se2_from_json(_param(params, "T_world_forklift", where), f"{where}: T_world_forklift")
        expected = params.get("expected_T_world_pallet")
        pallet = params.get("pallet")
        support = params.get("support_height_m", 0.0)  # clients from before the field: the floor
        if isinstance(support, bool) or not isinstance(support, (int, float)) or not -1.0 <= support <= 20.0:
            raise PerceptionError(f"{where}: support_height_m: expected a number of m in -1..20, got {support!r}")
        estimate = p.estimate_pallet(
            frame,
            calibration,
            pose,
            None if expected is None else wire.se2_from_json(expected, f"{where}: expected_T_world_pallet"),
            None if pallet is None else _pallet(pallet, f"{where}: pallet"),
            support_height_m=float(support),
        )
        return wire.encode_json(wire.estimate_to_json(estimate))

    def _one(self, frames: list[FrameBundle], params: dict[str, Any], where: str) -> FrameBundle:
        if len(frames) > 1:
            raise PerceptionError(f"{where}: {len(frames)} frames; this request takes one")
        return frames[0] if frames else self._grab(params, where)

    def _grab(self, params: dict[str, Any], where: str) -> FrameBundle:
        """A frame from the service's camera at the request's lift height (`fork_height`, m)."""
        if self.camera is None:
            raise PerceptionError(f"{where}: no frame in the request, and the service has no camera (--camera none)")
        height = params.get("fork_height", 0.0)
        if isinstance(height, bool) or not isinstance(height, (int, float)):
            raise PerceptionError(f"{where}: fork_height: expected a number (m), got {height!r}")
        return dataclasses.replace(self.camera.grab(), fork_height=float(height), stamp_s=None)

    def _calibration(self, doc: object, where: str) -> Calibration:
        """A calibration document, checked once per distinct document (clients send the same one often)."""
        key = json.dumps(doc, sort_keys=True)
        calibration = self._calibrations.get(key)
        if calibration is None:
            if not isinstance(doc, dict):
                raise PerceptionError(f"{where}: expected an object")
            calibration = wire.calibration_from_json(doc, where)
            if len(self._calibrations) >= 8:
                self._calibrations.clear()
            self._calibrations[key] = calibration
        return calibration

    # -- health --------------------------------------------------------------------------------------

    def health(self) -> dict[str, Any]:
        """Model, ONNX provider, camera serial ("none"), uptime (s), requests served, last error."""
        seg = self.perception.segmenter
        with self._lock:
            s = dataclasses.replace(self.stats)
        return {
            "health": {
                "service": "palletpilot perception",
                "prefix": self.prefix,
                "model": None if not isinstance(seg, OnnxSegmenter) else seg.model_path.name,
                "provider": None if not isinstance(seg, OnnxSegmenter) else seg.providers[0],
                "camera": self.camera_serial or ("none" if self.camera is None else "unknown"),
                "uptime_s": round(time.monotonic() - s.started, 3),
                "requests_served": s.served,
                "errors": s.errors,
                "busy_replies": s.busy,
                "queued": self._queue.qsize(),
                "last_error": s.last_error,
                "forks": self.perception.forks.model_dump(mode="json"),
                "pallet": self.perception.pallet.name,
                "labels": str(self.perception.labels),
            }
        }

    def _note_error(self, message: str) -> None:
        with self._lock:
            self.stats.errors += 1
            self.stats.last_error = message[:500]


class _ExpiredError(PerceptionError):
    """The client gave up on the request before the worker reached it."""


def _param(params: dict[str, Any], key: str, where: str) -> Any:
    if key not in params:
        raise PerceptionError(f"{where}: missing parameter '{key}'")
    return params[key]


def _count(params: dict[str, Any], where: str) -> int:
    n = params.get("frames", 1)
    if isinstance(n, bool) or not isinstance(n, int) or not 1 <= n <= wire.MAX_FRAMES:
        raise PerceptionError(f"{where}: frames: expected 1..{wire.MAX_FRAMES} camera frames, got {n!r}")
    return n


_PALLETS: dict[str, PalletType] = {}


def _pallet(doc: object, where: str) -> PalletType:
    """A pallet type document, validated once per distinct document."""
    key = json.dumps(doc, sort_keys=True)
    if key not in _PALLETS:
        if len(_PALLETS) >= 32:
            _PALLETS.clear()
        _PALLETS[key] = wire.pallet_from_json(doc, where)
    return _PALLETS[key]
