"""Camera sources: a live RealSense D435/D435i, RealSense recordings, and extraction to bundle folders.

Every source yields `FrameBundle`s of ARCHITECTURE.md in the colour camera's optical frame
(`camera`: x right, y down, z out of the lens): `depth` (float32 m, aligned to colour by `rs.align`),
`K` and `dist` of the colour stream, `rgb` (uint8 RGB); no `labels`. `grab_stamped()` returns a
`StampedFrame` (the bundle with the device timestamps and frame numbers); every source keeps the last one
in `last_stamp`.

Sources:

- `RealSenseSource`: a live camera through `rs.pipeline` (serial selection, 640x480 or 848x480 at
  15 or 30 fps, optional spatial / temporal / hole-filling depth filters, optional recording).
- `RecordingSource`: plays a recording back in non-real-time mode, so every recorded frame is read;
  depth and colour frames are paired by device timestamp (unpaired frames are counted, not yielded).

Extraction: `extract_bundles` (any source into `frame_0000.npz` ...), `capture_from_camera`,
`extract_recording`; `describe_devices` lists the connected cameras.

This module holds the live camera and the extraction; the parts live in `perception.realsense_frames`
(librealsense frames to stamped bundles: the lazy pyrealsense2 import, depth filters, alignment,
`StampedFrame`), `perception.realsense_distortion` (the colour stream's lens model as OpenCV's 5
coefficients: `opencv_distortion`, `MAX_DIST_FIT_PX`) and `perception.realsense_recording` (playback:
`RecordingSource`, `EndOfRecordingError`, the recording formats each SDK reads). Their public names are
importable from here too.

pyrealsense2 is imported lazily: this module imports on machines without it (pip has wheels for x86_64
and, from 2.59.1, for aarch64 with CPython 3.9, 3.10 and 3.12: a Jetson on JetPack 6 gets it from pip;
not for aarch64 with 3.11), and only opening a source raises a `PerceptionError` saying how to install it.
Recordings of synthetic frames (no camera needed): `perception.realsense_synthetic`.
"""

from __future__ import annotations

from collections.abc import Iterable
from pathlib import Path
from types import TracebackType
from typing import Any, Protocol, runtime_checkable

from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle, save_bundle
from palletpilot.perception.realsense_distortion import MAX_DIST_FIT_PX, opencv_distortion
from palletpilot.perception.realsense_frames import (
    FILTER_NAMES,
    INSTALL_HINT,
    StampedFrame,
    _check_filters,
    _describe,
    _FrameConverter,
    _new_context,
    _SourceBase,
    import_pyrealsense2,
)
from palletpilot.perception.realsense_recording import EndOfRecordingError, RecordingSource

__all__ = [
    "BUNDLE_PATTERN",
    "FILTER_NAMES",
    "FPS_CHOICES",
    "HEIGHT",
    "INSTALL_HINT",
    "MAX_DIST_FIT_PX",
    "WIDTHS",
    "CameraSource",
    "EndOfRecordingError",
    "RealSenseSource",
    "RecordingSource",
    "StampedFrame",
    "capture_from_camera",
    "describe_devices",
    "extract_bundles",
    "extract_recording",
    "import_pyrealsense2",
    "opencv_distortion",
]

WIDTHS = (640, 848)
"""Supported stream widths (pixels) of the live source; the height is always `HEIGHT`."""
HEIGHT = 480
FPS_CHOICES = (15, 30)
BUNDLE_PATTERN = "frame_{:04d}.npz"


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


def describe_devices(context: Any = None) -> list[str]:
    """One line per connected RealSense device: `serial (name, USB type, firmware)`."""
    rs = import_pyrealsense2()
    ctx = context if context is not None else _new_context(rs)
    return [_describe(rs, dev) for dev in ctx.query_devices()]


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
