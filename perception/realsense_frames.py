"""librealsense frames as frame bundles: what the live and the recorded RealSense sources share.

Every source of `perception.realsense` yields `FrameBundle`s of ARCHITECTURE.md in the colour camera's
optical frame (`camera`: x right, y down, z out of the lens); `_FrameConverter` makes them:

- `depth`: float32 H x W z-depth in metres (raw z16 units times the frame's depth units), aligned to
  the colour image by librealsense's `rs.align(rs.stream.color)` after the optional depth filters
  (`FILTER_NAMES`); 0 means no data.
- `K`: float64 3 x 3 intrinsics of the colour stream (the image the depth is aligned to).
- `dist`: the colour stream's lens distortion as OpenCV's 5 coefficients, or None
  (`perception.realsense_distortion`).
- `rgb`: uint8 H x W x 3 in RGB order. No `labels`; `fork_height` 0 (the source does not know the lift).

Timestamps do not fit `FrameBundle`, so `grab_stamped()` returns a `StampedFrame` (bundle plus the
device timestamps in seconds and the frame numbers) and every source keeps the last one in `last_stamp`.

pyrealsense2 is imported lazily (`import_pyrealsense2`): this module imports on machines without it, and
only opening a source raises a `PerceptionError` saying how to install it (`INSTALL_HINT`).

Public API (all also importable from `perception.realsense`): `import_pyrealsense2`, `INSTALL_HINT`,
`StampedFrame`, `FILTER_NAMES`. Package-internal (used by `perception.realsense` and
`perception.realsense_recording`): `_new_context` (a seam for tests that fake the connected devices),
`_check_filters`, `_FrameConverter`, `_SourceBase` (context manager and `grab()` over `grab_stamped()`),
`_describe` (one line per device).
"""

from __future__ import annotations

import math
from collections.abc import Callable, Iterable, Sequence
from dataclasses import dataclass
from types import ModuleType, TracebackType
from typing import Any

import numpy as np

from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.realsense_distortion import opencv_distortion

__all__ = ["FILTER_NAMES", "INSTALL_HINT", "StampedFrame", "import_pyrealsense2"]

FILTER_NAMES = ("spatial", "temporal", "hole_filling")
"""Optional depth post-processing filters, applied in this order before alignment."""

INSTALL_HINT = (
    "pyrealsense2 is not importable: install it with `pip install pyrealsense2` where a wheel exists "
    "(x86_64 Linux and Windows; aarch64 Linux, e.g. a Jetson on JetPack 6, from 2.59.1 with CPython 3.9, "
    "3.10 or 3.12); elsewhere build librealsense from source with the Python bindings: "
    "`cmake .. -DBUILD_PYTHON_BINDINGS=ON -DPYTHON_EXECUTABLE=$(which python3) "
    "-DFORCE_RSUSB_BACKEND=ON && make -j4 && sudo make install`, then put the built pyrealsense2 on "
    "PYTHONPATH (librealsense doc/installation_jetson.md and wrappers/python/readme.md)"
)


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


def _describe(rs: ModuleType, dev: Any) -> str:
    def info(key: Any) -> str:
        return str(dev.get_info(key)) if dev.supports(key) else "?"

    details = [info(rs.camera_info.name)]
    if dev.supports(rs.camera_info.usb_type_descriptor):
        details.append(f"USB {info(rs.camera_info.usb_type_descriptor)}")
    if dev.supports(rs.camera_info.firmware_version):
        details.append(f"firmware {info(rs.camera_info.firmware_version)}")
    return f"{info(rs.camera_info.serial_number)} ({', '.join(details)})"
