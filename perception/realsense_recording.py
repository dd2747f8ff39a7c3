"""RealSense recordings played back as a camera source: every recorded frame, depth paired with colour.

`RecordingSource` plays a recording back in non-real-time mode, so every recorded frame is read; depth and
colour frames are paired by device timestamp (unpaired frames are counted, not yielded), then filtered,
aligned and stamped as a live camera's are (`perception.realsense_frames`). After the last pair `grab()`
raises `EndOfRecordingError`.

pyrealsense2 2.59 records rosbag2 files and refuses any extension but `.db3`; for playback it picks
the reader by extension: `.db3` is read as rosbag2 (SQLite), anything else as a ROS 1 `.bag`
(older SDKs, realsense-viewer). Whatever the installed SDK cannot read raises `PerceptionError`
naming the file, the format found and the SDK version (`_sniff_recording` looks at the file's first
bytes before librealsense does). Recordings of synthetic frames (no camera needed):
`perception.realsense_synthetic`.

Public API (both also importable from `perception.realsense`): `RecordingSource`, `EndOfRecordingError`.
"""

from __future__ import annotations

import queue
import threading
from collections import deque
from collections.abc import Iterable, Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.realsense_frames import (
    StampedFrame,
    _check_filters,
    _describe,
    _FrameConverter,
    _new_context,
    _SourceBase,
    import_pyrealsense2,
)

__all__ = ["EndOfRecordingError", "RecordingSource"]

_SQLITE_MAGIC = b"SQLite format 3\x00"
_ROS1_MAGIC = b"#ROSBAG V2.0"


class EndOfRecordingError(PerceptionError):
    """A `RecordingSource` has yielded every paired frame of its file."""


def _sniff_recording(rs: ModuleType, path: Path) -> None:
    """Raise `PerceptionError` for files the installed SDK cannot play (before librealsense sees them)."""
    if not path.exists():
        raise PerceptionError(f"{path}: no such recording")
    if path.is_dir():
        raise PerceptionError(f"{path}: is a directory; give the recording file (the .db3 inside a rosbag2 folder)")
    try:
        with path.open("rb") as fh:
            head = fh.read(16)
    except OSError as exc:
        raise PerceptionError(f"{path}: cannot read: {exc.strerror or exc}") from None
    if head.startswith(_SQLITE_MAGIC):
        if path.suffix != ".db3":
            raise PerceptionError(
                f"{path}: a rosbag2 (SQLite) recording, but pyrealsense2 {rs.__version__} reads rosbag2 only "
                "from files named *.db3: rename it"
            )
    elif head.startswith(_ROS1_MAGIC):
        if path.suffix == ".db3":
            raise PerceptionError(f"{path}: a ROS 1 bag named .db3: rename it to .bag")
    else:
        raise PerceptionError(
            f"{path}: not a RealSense recording (neither a rosbag2 .db3 nor a ROS 1 .bag; file starts {head[:12]!r})"
        )


class RecordingSource(_SourceBase):
    """Plays a RealSense recording back as a camera source, every frame, as fast as it is read.

    Non-real-time playback: librealsense waits for the consumer, so no frame is skipped. Depth and
    colour frames are paired by device timestamp (within half a frame period); a frame without a
    partner is counted in `unpaired` and skipped. `grab()` raises `EndOfRecordingError` after the last pair.
    `frames_read` counts the bundles yielded. `filters` as for `realsense.RealSenseSource`.
    """

    def __init__(self, path: str | Path, *, filters: Iterable[str] = (), timeout_s: float = 10.0) -> None:
        # Everything `close()` touches exists before anything can fail.
        self._sensors: list[Any] = []
        self._closing = False
        self._queue: queue.Queue[tuple[str, Any]] = queue.Queue(maxsize=8)
        self._depth: deque[Any] = deque()
        self._colour: deque[Any] = deque()
        self._playback: Any = None
        self.path = Path(path)
        filters = _check_filters(filters)
        rs = import_pyrealsense2()
        self._rs = rs
        _sniff_recording(rs, self.path)
        kind = "rosbag2 .db3" if self.path.suffix == ".db3" else "ROS 1 .bag"
        try:
            device = _new_context(rs).load_device(str(self.path))
        except RuntimeError as exc:
            raise PerceptionError(
                f"{self.path}: pyrealsense2 {rs.__version__} cannot read this {kind}: {exc}"
            ) from None
        playback = device.as_playback()
        playback.set_real_time(False)
        self._playback = playback
        self.duration_s: float = playback.get_duration().total_seconds()
        self.device_name: str = _describe(rs, device)
        self.timeout_s = float(timeout_s)
        self.frames_read = 0
        self.unpaired = 0

        depth_profile = colour_profile = None
        depth_sensor = colour_sensor = None
        streams: list[str] = []
        for sensor in playback.query_sensors():
            for prof in sensor.get_stream_profiles():
                streams.append(_describe_profile(prof))
                if prof.stream_type() == rs.stream.depth and depth_profile is None:
                    depth_profile, depth_sensor = prof, sensor
                elif prof.stream_type() == rs.stream.color and colour_profile is None:
                    colour_profile, colour_sensor = prof, sensor
        if depth_profile is None or colour_profile is None:
            missing = "depth" if depth_profile is None else "colour"
            raise PerceptionError(
                f"{self.path}: recording has no {missing} stream (streams: {', '.join(streams) or 'none'})"
            )
        assert depth_sensor is not None and colour_sensor is not None  # found with their profiles
        self.fps = min(depth_profile.fps(), colour_profile.fps())
        self._tolerance_ms = 500.0 / self.fps if self.fps > 0 else 50.0

        # Callbacks run on librealsense threads; blocking on the bounded queue throttles the reader.
        self._stopped = threading.Event()
        self._end = False
        playback.set_status_changed_callback(self._on_status)
        if depth_sensor is colour_sensor:
            groups = [(depth_sensor, [depth_profile, colour_profile])]
        else:
            groups = [(depth_sensor, [depth_profile]), (colour_sensor, [colour_profile])]
        for sensor, profiles in groups:
            sensor.open(profiles)
            self._sensors.append(sensor)
        # Playback starts with the first sensor started: hold it until every stream has its callback,
        # or the other stream's first frames are read before anyone listens.
        playback.pause()
        for sensor, _ in groups:
            sensor.start(self._on_frame)
        playback.resume()
        self._converter = _FrameConverter(rs, filters, str(self.path))

    def _put(self, item: tuple[str, Any]) -> None:
        while not self._closing:
            try:
                self._queue.put(item, timeout=0.1)
                return
            except queue.Full:
                continue

    def _on_frame(self, frame: Any) -> None:
        self._put(("frame", frame))

    def _on_status(self, status: Any) -> None:
        if status == self._rs.playback_status.stopped:
            self._put(("stopped", None))

    def _next_item(self) -> tuple[str, Any] | None:
        """The next queued item; None once the file has ended and the queue stays empty."""
        if self._stopped.is_set():
            try:  # stragglers from the stream threads after the end-of-file notice
                return self._queue.get(timeout=0.05)
            except queue.Empty:
                return None
        try:
            return self._queue.get(timeout=self.timeout_s)
        except queue.Empty:
            raise PerceptionError(f"{self.path}: playback stalled: no frame within {self.timeout_s:g} s") from None

    def _pair(self) -> tuple[Any, Any] | None:
        """Pop a matching depth / colour pair, dropping frames that can no longer find a partner."""
        while self._depth and self._colour:
            d, c = self._depth[0], self._colour[0]
            same_clock = d.get_frame_timestamp_domain() == c.get_frame_timestamp_domain()
            dt = d.get_timestamp() - c.get_timestamp() if same_clock else 0.0
            if abs(dt) <= self._tolerance_ms:
                self._depth.popleft()
                self._colour.popleft()
                return d, c
            (self._depth if dt < 0 else self._colour).popleft()
            self.unpaired += 1
        return None

    def grab_stamped(self) -> StampedFrame:
        """The next depth / colour pair of the recording, aligned and stamped; `EndOfRecordingError` at the end."""
        if self._closing:
            raise PerceptionError(f"{self.path}: source is closed")
        while True:
            pair = self._pair()
            if pair is not None:
                self.last_stamp = self._converter.convert(*pair)
                self.frames_read += 1
                return self.last_stamp
            if self._end:
                self.unpaired += len(self._depth) + len(self._colour)
                self._depth.clear()
                self._colour.clear()
                raise EndOfRecordingError(f"{self.path}: end of recording after {self.frames_read} frames")
            item = self._next_item()
            if item is None:
                self._end = True
                continue
            kind, frame = item
            if kind == "stopped":
                self._stopped.set()
            elif frame.get_profile().stream_type() == self._rs.stream.depth:
                self._depth.append(frame)
            else:
                self._colour.append(frame)

    def __iter__(self) -> Iterator[FrameBundle]:
        """The remaining bundles of the recording."""
        while True:
            try:
                yield self.grab()
            except EndOfRecordingError:
                return

    def close(self) -> None:
        """Stop playback and release the file."""
        if self._closing:
            return
        self._closing = True  # stream threads blocked in `_put` give up within 0.1 s
        self._depth.clear()
        self._colour.clear()
        while True:
            try:
                self._queue.get_nowait()
            except queue.Empty:
                break
        sensors, self._sensors = self._sensors, []
        for sensor in sensors:
            try:
                sensor.stop()
            except RuntimeError:
                pass  # never started
            sensor.close()
        self._playback = None


def _describe_profile(prof: Any) -> str:
    if prof.is_video_stream_profile():
        v = prof.as_video_stream_profile()
        return f"{prof.stream_name()} {v.width()}x{v.height()} {prof.format().name} {prof.fps()} fps"
    return f"{prof.stream_name()} {prof.format().name} {prof.fps()} fps"
