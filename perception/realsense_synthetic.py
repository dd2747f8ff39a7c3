"""Synthetic RealSense recordings: frames of your own written as a recording librealsense plays back.

`write_software_recording` records depth and colour images through librealsense's `software_device`
and `rs.recorder`, with no camera attached, so that the playback path (`realsense_recording.RecordingSource`,
`palletpilot capture --recording`) can be tested and demonstrated on any machine with pyrealsense2.

Public API: `write_software_recording`.
"""

from __future__ import annotations

from collections.abc import Sequence
from pathlib import Path
from typing import Any

import numpy as np

from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.realsense_frames import import_pyrealsense2


def write_software_recording(
    path: str | Path,
    depth_m: Sequence[np.ndarray],
    rgb: Sequence[np.ndarray | None],
    *,
    K_depth: np.ndarray,
    K_colour: np.ndarray,
    T_colour_depth: np.ndarray | None = None,
    fps: int = 30,
    depth_units: float = 0.001,
    colour_delay_s: float = 0.002,
    serial: str = "000000000000",
) -> Path:
    """Record synthetic frames to a RealSense recording without hardware (`software_device` + `rs.recorder`).

    `depth_m[i]`: float H x W z-depth (m) in the *depth* camera's optical frame (0 or NaN: no data),
    stored as z16 in `depth_units` (m per unit). `rgb[i]`: uint8 H' x W' x 3 colour image, or None to
    record depth without colour for that frame. `K_depth` / `K_colour`: 3 x 3 intrinsics (no distortion).
    `T_colour_depth`: 4 x 4 rigid transform from depth to colour optical frame (default identity).
    Frame i is stamped 1000 + i / fps * 1000 ms (depth) and `colour_delay_s` later (colour), in the
    hardware clock. `path` must end in `.db3` on pyrealsense2 2.59. Returns the path.
    """
    rs = import_pyrealsense2()
    path = Path(path)
    if len(depth_m) != len(rgb) or not depth_m:
        raise PerceptionError(f"{path}: need as many rgb entries as depth frames (>= 1)")
    dh, dw = depth_m[0].shape
    colour_shape = next((im.shape for im in rgb if im is not None), None)
    if colour_shape is None or len(colour_shape) != 3 or colour_shape[2] != 3:
        raise PerceptionError(f"{path}: need at least one H x W x 3 colour image")
    ch, cw = colour_shape[:2]
    T = np.eye(4) if T_colour_depth is None else np.asarray(T_colour_depth, dtype=np.float64)

    def intrinsics(K: np.ndarray, w: int, h: int) -> Any:
        intr = rs.intrinsics()
        intr.width, intr.height = w, h
        intr.fx, intr.fy, intr.ppx, intr.ppy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
        intr.model = rs.distortion.brown_conrady
        intr.coeffs = [0.0] * 5
        return intr

    def video_stream(kind: Any, uid: int, w: int, h: int, bpp: int, fmt: Any, K: np.ndarray) -> Any:
        vs = rs.video_stream()
        vs.type, vs.index, vs.uid = kind, 0, uid
        vs.width, vs.height, vs.fps, vs.bpp, vs.fmt = w, h, fps, bpp, fmt
        vs.intrinsics = intrinsics(K, w, h)
        return vs

    device = rs.software_device()
    device.register_info(rs.camera_info.name, "Intel RealSense D435I (software_device)")
    device.register_info(rs.camera_info.serial_number, serial)
    depth_sensor = device.add_sensor("Stereo Module")
    colour_sensor = device.add_sensor("RGB Camera")
    depth_profile = depth_sensor.add_video_stream(
        video_stream(rs.stream.depth, 0, dw, dh, 2, rs.format.z16, K_depth)
    ).as_video_stream_profile()
    depth_sensor.add_read_only_option(rs.option.depth_units, float(depth_units))
    colour_profile = colour_sensor.add_video_stream(
        video_stream(rs.stream.color, 1, cw, ch, 3, rs.format.rgb8, K_colour)
    ).as_video_stream_profile()
    extr = rs.extrinsics()
    extr.rotation = [float(x) for x in T[:3, :3].T.ravel()]  # librealsense: column-major 3 x 3
    extr.translation = [float(x) for x in T[:3, 3]]
    depth_profile.register_extrinsics_to(colour_profile, extr)

    try:
        recorder = rs.recorder(str(path), device)
    except RuntimeError as exc:
        raise PerceptionError(f"{path}: pyrealsense2 {rs.__version__} cannot record here: {exc}") from None
    depth_sensor.open(depth_profile)
    colour_sensor.open(colour_profile)
    depth_sensor.start(lambda f: None)
    colour_sensor.start(lambda f: None)
    try:
        for i, (d, c) in enumerate(zip(depth_m, rgb, strict=True)):
            stamp_ms = 1000.0 + i * 1000.0 / fps
            z = np.nan_to_num(np.asarray(d, dtype=np.float64), nan=0.0) / depth_units
            frame = rs.software_video_frame()
            frame.pixels = np.ascontiguousarray(np.clip(np.rint(z), 0, 65535).astype(np.uint16))
            frame.bpp, frame.stride = 2, dw * 2
            frame.timestamp, frame.domain, frame.frame_number = stamp_ms, rs.timestamp_domain.hardware_clock, i
            frame.depth_units = float(depth_units)
            frame.profile = depth_profile
            depth_sensor.on_video_frame(frame)
            if c is None:
                continue
            frame = rs.software_video_frame()
            frame.pixels = np.ascontiguousarray(c, dtype=np.uint8)
            frame.bpp, frame.stride = 3, cw * 3
            frame.timestamp = stamp_ms + colour_delay_s * 1000.0
            frame.domain, frame.frame_number = rs.timestamp_domain.hardware_clock, i
            frame.profile = colour_profile
            colour_sensor.on_video_frame(frame)
    finally:
        for sensor in (depth_sensor, colour_sensor):
            sensor.stop()
            sensor.close()
        recorder.pause()
        del recorder  # the recorder writes the file's end when destroyed
    return path
