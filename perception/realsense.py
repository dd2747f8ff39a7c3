"""Camera sources: a live RealSense D435/D435i, RealSense recordings, and extraction to bundle folders.

Every source yields `FrameBundle`s of ARCHITECTURE.md in the colour camera's optical frame
(`camera`: x right, y down, z out of the lens):

- `depth`: float32 H x W z-depth in metres (raw z16 units times the frame's depth units), aligned to
  the colour image by librealsense's `rs.align(rs.stream.color)`; 0 means no data.
- `K`: float64 3 x 3 intrinsics of the colour stream (the image the depth is aligned to).
- `dist`: the colour stream's lens distortion as OpenCV's 5 coefficients (k1, k2, p1, p2, k3), or None
  when the stream reports none (model `none`, or all coefficients zero, as many D435 colour streams do).
  `rs.align` puts each depth point where librealsense's own projection (`rs2_project_point_to_pixel`, with
  the colour stream's model) lands it, so `dist` must describe that projection (`opencv_distortion`):
  `brown_conrady` is OpenCV's model, coefficient for coefficient. `inverse_brown_conrady` (most D4xx colour
  streams) and `modified_brown_conrady` are, in pyrealsense2 2.59, the same polynomial with the tangential
  terms applied to the radially distorted point, both for projecting (the "inverse" in the name describes
  how older SDKs used the coefficients, distorted to ideal, which 2.59 no longer does); their coefficients
  are converted by fitting OpenCV's 5 to the SDK's projection over the whole image, refused when the fit
  misses by more than `MAX_DIST_FIT_PX`. The fisheye models (`ftheta`, `kannala_brandt4`) are refused.
- `rgb`: uint8 H x W x 3 in RGB order. No `labels`; `fork_height` 0 (the source does not know the lift).

Timestamps do not fit `FrameBundle`, so `grab_stamped()` returns a `StampedFrame` (bundle plus the
device timestamps in seconds and the frame numbers) and every source keeps the last one in `last_stamp`.

Sources:

- `RealSenseSource`: a live camera through `rs.pipeline` (serial selection, 640x480 or 848x480 at
  15 or 30 fps, optional spatial / temporal / hole-filling depth filters, optional recording).
- `RecordingSource`: plays a recording back in non-real-time mode, so every recorded frame is read;
  depth and colour frames are paired by device timestamp (unpaired frames are counted, not yielded).

pyrealsense2 2.59 records rosbag2 files and refuses any extension but `.db3`; for playback it picks
the reader by extension: `.db3` is read as rosbag2 (SQLite), anything else as a ROS 1 `.bag`
(older SDKs, realsense-viewer). Whatever the installed SDK cannot read raises `PerceptionError`
naming the file, the format found and the SDK version.

pyrealsense2 is imported lazily: this module imports on machines without it (pip has wheels for x86_64
and, from 2.59.1, for aarch64 with CPython 3.9, 3.10 and 3.12: a Jetson on JetPack 6 gets it from pip;
not for aarch64 with 3.11), and only opening a source raises a `PerceptionError` saying how to install it.
Recordings of synthetic frames (no camera needed): `perception.realsense_synthetic`.
"""

from __future__ import annotations

import functools
import math
import queue
import threading
from collections import deque
from collections.abc import Callable, Iterable, Iterator, Sequence
from dataclasses import dataclass
from pathlib import Path
from types import ModuleType, TracebackType
from typing import Any, Protocol, runtime_checkable

import numpy as np

from palletpilot.perception.distortion import fit_brown_conrady
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle, save_bundle

WIDTHS = (640, 848)
"""Supported stream widths (pixels) of the live source; the height is always `HEIGHT`."""
HEIGHT = 480
FPS_CHOICES = (15, 30)
FILTER_NAMES = ("spatial", "temporal", "hole_filling")
"""Optional depth post-processing filters, applied in this order before alignment."""
BUNDLE_PATTERN = "frame_{:04d}.npz"
MAX_DIST_FIT_PX = 0.1
"""The largest miss (px) of OpenCV's 5 coefficients fitted to a RealSense stream's own lens model."""
_FIT_GRID = (33, 25)  # ideal points across the image (and 5 % beyond its borders) for that fit

INSTALL_HINT = (
    "pyrealsense2 is not importable: install it with `pip install pyrealsense2` where a wheel exists "
    "(x86_64 Linux and Windows; aarch64 Linux, e.g. a Jetson on JetPack 6, from 2.59.1 with CPython 3.9, "
    "3.10 or 3.12); elsewhere build librealsense from source with the Python bindings: "
    "`cmake .. -DBUILD_PYTHON_BINDINGS=ON -DPYTHON_EXECUTABLE=$(which python3) "
    "-DFORCE_RSUSB_BACKEND=ON && make -j4 && sudo make install`, then put the built pyrealsense2 on "
    "PYTHONPATH (librealsense doc/installation_jetson.md and wrappers/python/readme.md)"
)

_SQLITE_MAGIC = b"SQLite format 3\x00"
_ROS1_MAGIC = b"#ROSBAG V2.0"


def import_pyrealsense2() -> ModuleType:
    """Import pyrealsense2 or raise `PerceptionError` with the way to install librealsense."""
    try:
        import pyrealsense2 as rs  # lazy: optional on aarch64
    except ImportError as exc:
        raise PerceptionError(f"{INSTALL_HINT} ({exc})") from None
    return rs


def _new_context(rs: ModuleType) -> Any:
    """A librealsense context (a seam for tests that fake the connected devices)."""
    return rs.context()


@dataclass(frozen=True, eq=False)
class StampedFrame:
    """A frame bundle with its RealSense timestamps.

    `timestamp_s` / `depth_timestamp_s`: device timestamps (s) of the colour and depth frames, in the
    clock named by `timestamp_domain` (`global_time`, `hardware_clock` or `system_time`);
    `frame_number` / `depth_frame_number`: the streams' frame counters.
    """

    bundle: FrameBundle
    timestamp_s: float
    depth_timestamp_s: float
    timestamp_domain: str
    frame_number: int
    depth_frame_number: int


@runtime_checkable
class CameraSource(Protocol):
    """Anything that yields aligned RGB-D frame bundles; close it (or use `with`) to free the device."""

    def grab(self) -> FrameBundle:
        """The next frame bundle (depth m, K, rgb in the colour camera's optical frame)."""
        ...

    def close(self) -> None:
        """Release the camera or file; calling it twice is harmless."""
        ...

    def __enter__(self) -> CameraSource: ...

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None: ...


class EndOfRecordingError(PerceptionError):
    """A `RecordingSource` has yielded every paired frame of its file."""


def _check_filters(filters: Iterable[str]) -> tuple[str, ...]:
    names = tuple(filters)
    unknown = [n for n in names if n not in FILTER_NAMES]
    if unknown:
        raise PerceptionError(f"unknown depth filter(s) {', '.join(unknown)} (known: {', '.join(FILTER_NAMES)})")
    return tuple(n for n in FILTER_NAMES if n in names)


class _FrameConverter:
    """Depth + colour librealsense frames -> filtered, aligned `StampedFrame` (one per source: filters keep state)."""

    def __init__(self, rs: ModuleType, filters: Sequence[str], where: str) -> None:
        self._rs = rs
        self._where = where
        makers: dict[str, Callable[[], Any]] = {
            "spatial": rs.spatial_filter,
            "temporal": rs.temporal_filter,
            "hole_filling": rs.hole_filling_filter,
        }
        self._filters = [makers[name]() for name in _check_filters(filters)]
        self._align = rs.align(rs.stream.color)
        # Python cannot build a frameset from two frames directly: a processing block can.
        self._partner: Any = None
        self._composed = rs.frame_queue(2, keep_frames=True)
        self._composer = rs.processing_block(self._compose)
        self._composer.start(self._composed)

    def _compose(self, frame: Any, source: Any) -> None:
        source.frame_ready(source.allocate_composite_frame([frame, self._partner]))

    def convert(self, depth: Any, colour: Any) -> StampedFrame:
        """Filter the depth frame, align it to the colour frame and copy both into a bundle."""
        rs = self._rs
        depth_ts, colour_ts = depth.get_timestamp(), colour.get_timestamp()
        depth_no, colour_no = depth.get_frame_number(), colour.get_frame_number()
        domain = colour.get_frame_timestamp_domain().name
        for f in self._filters:
            depth = f.process(depth)
        self._partner = colour
        try:
            self._composer.invoke(depth)
            ok, frameset = self._composed.try_wait_for_frame(5000)
        finally:
            self._partner = None
        if not ok:
            raise PerceptionError(f"{self._where}: librealsense did not compose depth frame {depth_no} with colour")
        aligned = self._align.process(frameset.as_frameset()).as_frameset()
        a_depth, a_colour = aligned.get_depth_frame(), aligned.get_color_frame()
        if not a_depth or not a_colour:
            raise PerceptionError(f"{self._where}: rs.align returned no depth for frame {depth_no}")
        units = float(a_depth.as_depth_frame().get_units())
        if not (units > 0 and math.isfinite(units)):
            raise PerceptionError(f"{self._where}: depth frame {depth_no} has depth units {units} (need > 0 m)")
        z16 = np.asanyarray(a_depth.get_data())
        depth_m = (z16.astype(np.float32) * np.float32(units)).astype(np.float32)
        rgb = _to_rgb(rs, a_colour, self._where)
        intr = a_colour.get_profile().as_video_stream_profile().get_intrinsics()
        K = np.array([[intr.fx, 0.0, intr.ppx], [0.0, intr.fy, intr.ppy], [0.0, 0.0, 1.0]], dtype=np.float64)
        if rgb.shape[:2] != depth_m.shape:
            raise PerceptionError(f"{self._where}: aligned depth {depth_m.shape} does not match colour {rgb.shape[:2]}")
        dist = opencv_distortion(rs, intr, self._where)
        bundle = FrameBundle(depth=depth_m, K=K, rgb=rgb, dist=dist)
        return StampedFrame(
            bundle=bundle,
            timestamp_s=colour_ts / 1000.0,
            depth_timestamp_s=depth_ts / 1000.0,
            timestamp_domain=domain,
            frame_number=int(colour_no),
            depth_frame_number=int(depth_no),
        )


def opencv_distortion(rs: ModuleType, intr: Any, where: str) -> np.ndarray | None:
    """A RealSense stream's lens distortion (`rs.intrinsics`) as OpenCV's 5 coefficients, or None when it has
    none; `PerceptionError` for a model this cannot express (module docstring)."""
    model = intr.model
    coeffs = tuple(float(c) for c in intr.coeffs)
    if model == rs.distortion.none or not any(coeffs):
        return None
    if model == rs.distortion.brown_conrady:
        return np.array(coeffs[:5], dtype=np.float64)
    if model in (rs.distortion.inverse_brown_conrady, rs.distortion.modified_brown_conrady):
        key = (int(model), coeffs, intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy)
        dist, miss_px = _fitted_distortion(rs, key)
        if miss_px > MAX_DIST_FIT_PX:
            raise PerceptionError(
                f"{where}: colour lens model {model.name} [{', '.join(f'{c:.4g}' for c in coeffs)}]: OpenCV's 5 "
                "coefficients fitted to "
                f"librealsense's projection miss it by {miss_px:.2f} px (at most {MAX_DIST_FIT_PX:g}): not supported"
            )
        return dist
    raise PerceptionError(
        f"{where}: colour lens model {model.name} (a fisheye model) is not supported: perception undistorts "
        "Brown-Conrady lenses (OpenCV's k1, k2, p1, p2, k3)"
    )


@functools.lru_cache(maxsize=8)
def _fitted_distortion(rs: ModuleType, key: tuple[Any, ...]) -> tuple[np.ndarray | None, float]:
    """OpenCV's 5 coefficients fitted to librealsense's own projection of a stream (`key`: its model, the
    coefficients, width, height, fx, fy, ppx, ppy) and the largest miss (px); None when they are all zero."""
    model, coeffs, w, h, fx, fy, ppx, ppy = key
    intr = rs.intrinsics()
    intr.width, intr.height, intr.fx, intr.fy, intr.ppx, intr.ppy = w, h, fx, fy, ppx, ppy
    intr.model, intr.coeffs = rs.distortion(model), list(coeffs)
    us = np.linspace(-0.05 * w, 1.05 * w, _FIT_GRID[0])
    vs = np.linspace(-0.05 * h, 1.05 * h, _FIT_GRID[1])
    ideal = np.array([((u - ppx) / fx, (v - ppy) / fy) for v in vs for u in us])
    pixels = np.array([rs.rs2_project_point_to_pixel(intr, [x, y, 1.0]) for x, y in ideal], dtype=np.float64)
    distorted = np.column_stack([(pixels[:, 0] - ppx) / fx, (pixels[:, 1] - ppy) / fy])
    dist, miss = fit_brown_conrady(ideal, distorted)
    if not np.any(np.abs(dist) > 1e-9):  # an SDK that projects this model without distortion
        return None, 0.0
    return dist, miss * max(fx, fy)


def _to_rgb(rs: ModuleType, colour: Any, where: str) -> np.ndarray:
    """Copy a colour frame into a uint8 H x W x 3 RGB array (rgb8, bgr8, rgba8, bgra8)."""
    fmt = colour.get_profile().format()
    data = np.asanyarray(colour.get_data())
    if fmt == rs.format.rgb8:
        return np.array(data, dtype=np.uint8, copy=True)
    if fmt == rs.format.bgr8:
        return np.ascontiguousarray(data[..., ::-1], dtype=np.uint8)
    if fmt == rs.format.rgba8:
        return np.ascontiguousarray(data[..., :3], dtype=np.uint8)
    if fmt == rs.format.bgra8:
        return np.ascontiguousarray(data[..., 2::-1], dtype=np.uint8)
    raise PerceptionError(f"{where}: colour format {fmt.name} is not supported (need rgb8, bgr8, rgba8 or bgra8)")


class _SourceBase:
    """Context manager, iteration and `grab()` for the sources built on `grab_stamped()`."""

    last_stamp: StampedFrame | None = None

    def grab_stamped(self) -> StampedFrame:  # pragma: no cover - overridden
        raise NotImplementedError

    def grab(self) -> FrameBundle:
        """The next frame bundle; its timestamps are in `last_stamp`."""
        return self.grab_stamped().bundle

    def close(self) -> None:  # pragma: no cover - overridden
        raise NotImplementedError

    def __enter__(self) -> _SourceBase:
        return self

    def __exit__(
        self, exc_type: type[BaseException] | None, exc: BaseException | None, tb: TracebackType | None
    ) -> None:
        self.close()

    def __del__(self) -> None:
        try:
            self.close()
        except Exception:
            pass


def describe_devices(context: Any = None) -> list[str]:
    """One line per connected RealSense device: `serial (name, USB type, firmware)`."""
    rs = import_pyrealsense2()
    ctx = context if context is not None else _new_context(rs)
    return [_describe(rs, dev) for dev in ctx.query_devices()]


def _describe(rs: ModuleType, dev: Any) -> str:
    def info(key: Any) -> str:
        return str(dev.get_info(key)) if dev.supports(key) else "?"

    details = [info(rs.camera_info.name)]
    if dev.supports(rs.camera_info.usb_type_descriptor):
        details.append(f"USB {info(rs.camera_info.usb_type_descriptor)}")
    if dev.supports(rs.camera_info.firmware_version):
        details.append(f"firmware {info(rs.camera_info.firmware_version)}")
    return f"{info(rs.camera_info.serial_number)} ({', '.join(details)})"


class RealSenseSource(_SourceBase):
    """A live D435/D435i: depth (z16) and colour (rgb8) streams, depth aligned to colour.

    `serial`: the camera to open (default: the first one found). `width` 640 or 848, height 480,
    `fps` 15 or 30. `filters`: any of `FILTER_NAMES`, applied to depth before alignment.
    `record_to`: also record the raw streams to this file while the source is open (pyrealsense2 2.59
    needs a `.db3` name). `timeout_s`: longest wait (s) for a frameset before `PerceptionError`.
    """

    def __init__(
        self,
        serial: str | None = None,
        *,
        width: int = 640,
        fps: int = 30,
        filters: Iterable[str] = (),
        record_to: str | Path | None = None,
        timeout_s: float = 5.0,
        context: Any = None,
    ) -> None:
        self._pipeline: Any = None
        if width not in WIDTHS:
            raise PerceptionError(f"RealSense: width {width} not supported (use {' or '.join(map(str, WIDTHS))})")
        if fps not in FPS_CHOICES:
            raise PerceptionError(f"RealSense: fps {fps} not supported (use {' or '.join(map(str, FPS_CHOICES))})")
        filters = _check_filters(filters)
        rs = import_pyrealsense2()
        ctx = context if context is not None else _new_context(rs)
        devices = list(ctx.query_devices())
        found = [_describe(rs, d) for d in devices]
        if not devices:
            raise PerceptionError(
                f"no RealSense camera found (pyrealsense2 {rs.__version__} sees no devices): "
                "connect a D435/D435i to a USB 3 port and check `rs-enumerate-devices`"
            )
        serials = [str(d.get_info(rs.camera_info.serial_number)) for d in devices]
        if serial is None:
            serial = serials[0]
        elif serial not in serials:
            raise PerceptionError(f"RealSense camera with serial {serial} not found; found: {'; '.join(found)}")
        self.serial: str = serial
        self.device_name: str = found[serials.index(serial)]
        self.width, self.height, self.fps = width, HEIGHT, fps
        self.timeout_s = float(timeout_s)
        self.record_to = Path(record_to) if record_to is not None else None
        where = f"RealSense {serial}"

        config = rs.config()
        config.enable_device(serial)
        config.enable_stream(rs.stream.depth, width, HEIGHT, rs.format.z16, fps)
        config.enable_stream(rs.stream.color, width, HEIGHT, rs.format.rgb8, fps)
        if self.record_to is not None:
            config.enable_record_to_file(str(self.record_to))
        pipeline = rs.pipeline(ctx)
        try:
            profile = pipeline.start(config)
        except RuntimeError as exc:
            hint = ""
            if self.record_to is not None and "extension" in str(exc):
                hint = f" (pyrealsense2 {rs.__version__} records rosbag2: name the file *.db3)"
            raise PerceptionError(
                f"{where}: cannot start depth + colour {width}x{HEIGHT} at {fps} fps"
                f"{' recording to ' + str(self.record_to) if self.record_to else ''}: {exc}{hint}"
            ) from None
        self._pipeline = pipeline
        self.depth_scale: float = float(profile.get_device().first_depth_sensor().get_depth_scale())
        """Metres per raw depth unit reported by the camera (frames carry their own units too)."""
        self._converter = _FrameConverter(rs, filters, where)
        self._where = where

    def grab_stamped(self) -> StampedFrame:
        """Wait for the next frameset and return it filtered, aligned and stamped."""
        if self._pipeline is None:
            raise PerceptionError(f"{getattr(self, '_where', 'RealSense')}: source is closed")
        ok, frames = self._pipeline.try_wait_for_frames(int(self.timeout_s * 1000))
        if not ok:
            raise PerceptionError(f"{self._where}: no frames within {self.timeout_s:g} s (camera unplugged?)")
        depth, colour = frames.get_depth_frame(), frames.get_color_frame()
        if not depth or not colour:
            raise PerceptionError(f"{self._where}: frameset without depth or colour")
        self.last_stamp = self._converter.convert(depth, colour)
        return self.last_stamp

    def close(self) -> None:
        """Stop streaming (and finish the recording, if any)."""
        pipeline, self._pipeline = getattr(self, "_pipeline", None), None
        if pipeline is not None:
            pipeline.stop()


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
    `frames_read` counts the bundles yielded. `filters` as for `RealSenseSource`.
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


def extract_bundles(source: CameraSource, out_dir: str | Path, count: int | None = None, warmup: int = 0) -> list[Path]:
    """Save `count` bundles (all, for a recording, when None) of `source` as `out_dir/frame_0000.npz` ...

    `warmup` frames are grabbed and dropped first (auto exposure settling on a live camera).
    Refuses an `out_dir` that already holds `frame_*.npz` files. Returns the written paths.
    """
    out = Path(out_dir)
    if count is not None and count < 1:
        raise PerceptionError(f"count must be >= 1, got {count}")
    if count is None and not isinstance(source, RecordingSource):
        raise PerceptionError("a live camera needs a frame count")
    if out.exists() and not out.is_dir():
        raise PerceptionError(f"{out}: not a directory")
    if out.is_dir() and any(out.glob("frame_*.npz")):
        raise PerceptionError(f"{out}: already holds frame_*.npz bundles; choose an empty folder")
    try:
        out.mkdir(parents=True, exist_ok=True)
    except OSError as exc:
        raise PerceptionError(f"{out}: cannot create: {exc.strerror or exc}") from None
    written: list[Path] = []
    try:
        for _ in range(warmup):
            source.grab()
        while count is None or len(written) < count:
            bundle = source.grab()
            written.append(save_bundle(out / BUNDLE_PATTERN.format(len(written)), bundle))
    except EndOfRecordingError:
        if not written:
            raise PerceptionError(f"{getattr(source, 'path', 'source')}: no depth + colour frame pair") from None
    return written


def capture_from_camera(
    out_dir: str | Path,
    count: int = 10,
    serial: str | None = None,
    *,
    width: int = 640,
    fps: int = 30,
    filters: Iterable[str] = (),
    warmup: int = 30,
    context: Any = None,
) -> list[Path]:
    """Save `count` bundles from a live camera (after `warmup` frames) into `out_dir`; return the paths."""
    with RealSenseSource(serial, width=width, fps=fps, filters=filters, context=context) as cam:
        return extract_bundles(cam, out_dir, count=count, warmup=warmup)


def extract_recording(
    path: str | Path, out_dir: str | Path, count: int | None = None, *, filters: Iterable[str] = ()
) -> list[Path]:
    """Save the bundles of a recording (the first `count`, or all) into `out_dir`; return the paths."""
    with RecordingSource(path, filters=filters) as rec:
        return extract_bundles(rec, out_dir, count=count)
