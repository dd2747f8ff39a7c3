"""Camera sources on the truck: realsense-ros topics, or the RealSense straight through pyrealsense2.

Both give `FrameBundle`s (`perception.frames`) in the colour camera's optical frame
(`camera_color_optical_frame`: x right, y down, z out of the lens), with `stamp_s` on the runner's
clock and `fork_height` (m) read from the truck when the frame is taken:

- `RosCamera`: `sensor_msgs/Image` colour (`rgb8` or `bgr8`) and depth aligned to it (`16UC1` in mm,
  realsense-ros's default, or `32FC1` in m; 0 or NaN: no data), and `sensor_msgs/CameraInfo` (`k`: the
  colour image's intrinsics). The newest colour and depth images whose header stamps are at most
  `camera.pair_tolerance_s` apart make a bundle; its stamp is when the older of the two arrived.
- `RealSenseCamera`: `perception.realsense.RealSenseSource` (librealsense's `rs.align` to colour), grabbed
  on a background thread so that the control loop never waits for the camera.

`grab()` raises `PerceptionError` when no frame is there yet; the runner's camera watchdog decides when
that (or an old frame) is a `sensor_timeout`.
"""

from __future__ import annotations

import dataclasses
import threading
import time
from collections import deque
from collections.abc import Callable
from typing import Any

import numpy as np

from palletpilot.executor.adapters.ros import messages as msgs
from palletpilot.executor.adapters.ros.config import RobotConfig
from palletpilot.executor.adapters.ros.transport import Transport
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle

_KEEP = 4
"""Images kept per stream for pairing colour with depth."""


def image_to_rgb(img: msgs.Image) -> np.ndarray:
    """uint8 H x W x 3 RGB of an `rgb8` or `bgr8` image."""
    if img.encoding not in ("rgb8", "bgr8"):
        raise PerceptionError(f"colour image encoding '{img.encoding}' (need rgb8 or bgr8)")
    rows = _rows(img, 3)
    rgb = rows.reshape(img.height, img.width, 3)
    return np.ascontiguousarray(rgb[:, :, ::-1] if img.encoding == "bgr8" else rgb)


def image_to_depth(img: msgs.Image) -> np.ndarray:
    """float32 H x W z-depth in metres of a `16UC1` (mm) or `32FC1` (m) image; 0 means no data."""
    if img.encoding in ("16UC1", "mono16"):
        d = _rows(img, 2).view(">u2" if img.is_bigendian else "<u2").reshape(img.height, img.width)
        return (d.astype(np.float32) * np.float32(0.001)).astype(np.float32)
    if img.encoding == "32FC1":
        d = _rows(img, 4).view(">f4" if img.is_bigendian else "<f4").reshape(img.height, img.width)
        out = d.astype(np.float32)
        out[~np.isfinite(out)] = 0.0
        return out
    raise PerceptionError(f"depth image encoding '{img.encoding}' (need 16UC1 in mm or 32FC1 in m)")


def _rows(img: msgs.Image, bytes_per_pixel: int) -> np.ndarray:
    """The image's pixel bytes without row padding, as uint8 H x (W * bytes_per_pixel)."""
    row = img.width * bytes_per_pixel
    if img.step < row or len(img.data) < img.step * img.height:
        raise PerceptionError(
            f"{img.encoding} image {img.width}x{img.height}: step {img.step} and {len(img.data)} bytes do not fit"
        )
    data = np.frombuffer(bytes(img.data), dtype=np.uint8, count=img.step * img.height).reshape(img.height, img.step)
    return data[:, :row]


def rgb_image(rgb: np.ndarray, header: msgs.Header) -> msgs.Image:
    """An `rgb8` `sensor_msgs/Image` of uint8 H x W x 3 RGB."""
    h, w = rgb.shape[:2]
    return msgs.Image(
        header=header, height=h, width=w, encoding="rgb8", step=3 * w, data=np.ascontiguousarray(rgb).tobytes()
    )


def depth_image(depth_m: np.ndarray, header: msgs.Header) -> msgs.Image:
    """A `16UC1` (mm) `sensor_msgs/Image` of float z-depth in metres (NaN or <= 0: 0, no data)."""
    h, w = depth_m.shape
    mm = np.nan_to_num(np.asarray(depth_m, dtype=np.float64), nan=0.0) * 1000.0
    data = np.clip(np.rint(mm), 0, 65535).astype("<u2")
    return msgs.Image(header=header, height=h, width=w, encoding="16UC1", step=2 * w, data=data.tobytes())


def camera_info(K: np.ndarray, width: int, height: int, header: msgs.Header) -> msgs.CameraInfo:
    """`sensor_msgs/CameraInfo` of a pinhole camera without distortion (`plumb_bob`, zero coefficients)."""
    k = [float(v) for v in np.asarray(K, dtype=np.float64).ravel()]
    p = [k[0], k[1], k[2], 0.0, k[3], k[4], k[5], 0.0, k[6], k[7], k[8], 0.0]
    return msgs.CameraInfo(
        header=header,
        height=height,
        width=width,
        distortion_model="plumb_bob",
        d=[0.0] * 5,
        k=k,
        r=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        p=p,
    )


class RosCamera:
    """Frame bundles from realsense-ros topics (module docstring)."""

    def __init__(
        self,
        transport: Transport,
        config: RobotConfig,
        fork_height: Callable[[], float] = lambda: 0.0,
        now: Callable[[], float] = time.monotonic,
    ) -> None:
        cam = config.camera
        self.config = config
        self.fork_height = fork_height
        self.now = now
        self._lock = threading.Lock()
        self._color: deque[tuple[msgs.Image, float]] = deque(maxlen=_KEEP)
        self._depth: deque[tuple[msgs.Image, float]] = deque(maxlen=_KEEP)
        transport.subscribe(cam.color.name, msgs.Image, cam.color.qos.spec(), self._keep(self._color))
        transport.subscribe(cam.depth.name, msgs.Image, cam.depth.qos.spec(), self._keep(self._depth))
        self._info = transport.subscribe(cam.info.name, msgs.CameraInfo, cam.info.qos.spec())
        self._last: tuple[int, int, FrameBundle] | None = None
        self.frames = 0

    def _keep(self, queue: deque[tuple[msgs.Image, float]]) -> Callable[[msgs.Image, float], None]:
        def on_image(img: msgs.Image, received_s: float) -> None:
            with self._lock:
                queue.append((img, received_s))

        return on_image

    def _pair(self) -> tuple[tuple[msgs.Image, float], tuple[msgs.Image, float]] | None:
        """The newest colour and depth images whose stamps are within the tolerance."""
        tol = self.config.camera.pair_tolerance_s
        with self._lock:
            colors, depths = list(self._color), list(self._depth)
        best = None
        for c in reversed(colors):
            tc = msgs.seconds(c[0].header.stamp)
            for d in reversed(depths):
                if abs(msgs.seconds(d[0].header.stamp) - tc) <= tol:
                    if best is None or min(c[1], d[1]) > min(best[0][1], best[1][1]):
                        best = (c, d)
                    break
        return best

    def problems(self) -> list[str]:
        """Why no frame can be made (a silent or unpaired stream), [] when one can."""
        cam, out = self.config.camera, []
        with self._lock:
            have_color, have_depth = bool(self._color), bool(self._depth)
        for spec, ok in ((cam.color, have_color), (cam.depth, have_depth), (cam.info, self._info.latest())):
            if not ok:
                out.append(f"camera: {spec.name}: never heard")
        if not out and self._pair() is None:
            out.append(
                f"camera: no colour and depth image within {cam.pair_tolerance_s:g} s of each other "
                f"({cam.color.name}, {cam.depth.name})"
            )
        return out

    def grab(self) -> FrameBundle:
        """The newest paired frame as a bundle (`PerceptionError` when there is none)."""
        pair = self._pair()
        info = self._info.latest()
        if pair is None or info is None:
            problems = self.problems()
            raise PerceptionError("; ".join(problems) or "camera: no frame yet")
        (color, t_c), (depth, t_d) = pair
        if self._last is not None and self._last[0] == id(color) and self._last[1] == id(depth):
            return self._last[2]
        if (color.width, color.height) != (depth.width, depth.height):
            raise PerceptionError(
                f"camera: depth {depth.width}x{depth.height} is not aligned to colour {color.width}x{color.height} "
                f"(use realsense-ros's aligned_depth_to_color)"
            )
        K = np.array(info.msg.k, dtype=np.float64).reshape(3, 3)
        if (info.msg.width, info.msg.height) not in ((color.width, color.height), (0, 0)):
            raise PerceptionError(
                f"camera: {self.config.camera.info.name} is for {info.msg.width}x{info.msg.height}, "
                f"the colour image is {color.width}x{color.height}"
            )
        received = min(t_c, t_d)
        bundle = FrameBundle(
            depth=image_to_depth(depth),
            K=K,
            dist=_distortion(info.msg.distortion_model, list(info.msg.d), self.config.camera.info.name),
            rgb=image_to_rgb(color),
            fork_height=self.fork_height(),
            stamp_s=self.now() - (time.monotonic() - received),
        )
        self._last = (id(color), id(depth), bundle)
        self.frames += 1
        return bundle

    def close(self) -> None:
        """Nothing to release (the transport owns the subscriptions)."""


OPENCV_MODELS = ("plumb_bob", "rational_polynomial", "")
"""camera_info distortion models whose `d` is OpenCV's coefficients ("": unset, realsense-ros before 4.x)."""


def _distortion(model: str, d: list[float], topic: str) -> np.ndarray | None:
    """The frame's `dist` from a camera_info's `distortion_model` and `d` (None: no distortion); a model
    perception does not undistort (fisheye `equidistant`) is refused with a `PerceptionError`."""
    if not any(d):
        return None
    if model not in OPENCV_MODELS or len(d) not in (4, 5, 8, 12, 14):
        raise PerceptionError(
            f"camera: {topic}: distortion_model '{model}' with {len(d)} coefficients is not undistorted here "
            f"(use {' or '.join(m for m in OPENCV_MODELS if m)}, or the rectified image)"
        )
    return np.array(d, dtype=np.float64)


class RealSenseCamera:
    """A live RealSense through pyrealsense2, grabbed on a background thread (module docstring)."""

    def __init__(
        self,
        serial: str | None = None,
        fork_height: Callable[[], float] = lambda: 0.0,
        now: Callable[[], float] = time.monotonic,
        source: Any = None,
    ) -> None:
        if source is None:
            from palletpilot.perception.realsense import RealSenseSource

            source = RealSenseSource(serial)
        self.source = source
        self.fork_height = fork_height
        self.now = now
        self._latest: tuple[FrameBundle, float] | None = None
        self._error: str | None = None
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._run, name="realsense-grab", daemon=True)
        self._thread.start()

    def _run(self) -> None:
        while not self._stop.is_set():
            try:
                bundle = self.source.grab()
            except PerceptionError as exc:
                self._error = str(exc)
                time.sleep(0.1)
                continue
            self._latest, self._error = (bundle, time.monotonic()), None

    def problems(self) -> list[str]:
        """Why no frame can be made, [] when one can."""
        if self._latest is None:
            return [f"camera: RealSense: no frame yet{': ' + self._error if self._error else ''}"]
        return []

    def grab(self) -> FrameBundle:
        """The newest frame, stamped on the runner's clock, with the fork height now."""
        latest = self._latest
        if latest is None:
            raise PerceptionError(self.problems()[0])
        bundle, received = latest
        return dataclasses.replace(
            bundle, fork_height=self.fork_height(), stamp_s=self.now() - (time.monotonic() - received)
        )

    def close(self) -> None:
        """Stop the grab thread and release the camera."""
        self._stop.set()
        self._thread.join(timeout=2.0)
        self.source.close()
