"""Camera messages for the run recording (`executor.recording`): JPEG images, the segmentation overlay,
the depth as a point cloud, the intrinsics; Foxglove well-known messages in the `camera` frame (the
optical frame: x right, y down, z out of the lens).

`RecorderCamera`, a base of `executor.recording.Recorder`, records the frames perception asks for
(`wrap_grab`: `/camera/rgb`, `/camera/depth`, `/camera/calibration`, and labels a frame brings) and the
labels it segments (`wrap_segmenter`: `/camera/segmentation`, stamped as the frame they belong to).

Public API: `jpeg`, `segmentation_overlay`, `compressed_image`, `depth_cloud`, `camera_info`, `CLASS_COLOURS`,
`RecorderCamera` (for `Recorder` only).
"""

from __future__ import annotations

import threading
from collections.abc import Callable
from typing import Any

import cv2
import numpy as np
from foxglove.channels import CameraCalibrationChannel, CompressedImageChannel, PointCloudChannel
from foxglove.messages import (
    CameraCalibration,
    CompressedImage,
    PackedElementField,
    PackedElementFieldNumericType,
    PointCloud,
    Pose,
    Quaternion,
    Vector3,
)

from palletpilot.executor.adapters.mcap.recording_channels import DEPTH_STRIDE, RecordingSegmenter
from palletpilot.executor.adapters.mcap.recording_scene import CAMERA, stamp
from palletpilot.perception.frames import FrameBundle

CLASS_COLOURS = np.array(
    [
        (128, 64, 128),  # 0 drivable
        (70, 70, 70),  # 1 vertical
        (190, 153, 153),  # 2 other-object
        (250, 170, 30),  # 3 other-forklift
        (0, 0, 142),  # 4 other-vehicle
        (220, 20, 60),  # 5 forks (ego)
        (255, 255, 0),  # 6 cargo
        (0, 255, 0),  # 7 pallet-empty
        (0, 170, 255),  # 8 pallet-full
        (255, 0, 255),  # 9 person
    ],
    dtype=np.uint8,
)
"""RGB colour of each semantic class id (ARCHITECTURE.md); 255 (unlabeled) is left uncoloured."""


def jpeg(rgb: np.ndarray, quality: int = 80) -> bytes:
    """JPEG bytes of an RGB uint8 image."""
    ok, buf = cv2.imencode(".jpg", np.ascontiguousarray(rgb[:, :, ::-1]), [cv2.IMWRITE_JPEG_QUALITY, quality])
    if not ok:
        raise ValueError("JPEG encoding failed")
    return buf.tobytes()


def segmentation_overlay(rgb: np.ndarray | None, labels: np.ndarray) -> np.ndarray:
    """The class colours blended over the RGB (half and half; unlabeled pixels keep the RGB). Without RGB,
    the class colours alone."""
    ids = labels.astype(np.intp)
    known = ids < len(CLASS_COLOURS)
    colours = CLASS_COLOURS[np.where(known, ids, 0)]
    if rgb is None:
        return np.where(known[..., None], colours, 0).astype(np.uint8)
    blend = ((rgb.astype(np.uint16) + colours) // 2).astype(np.uint8)
    return np.where(known[..., None], blend, rgb)


def compressed_image(data: bytes, ns: int) -> CompressedImage:
    """A JPEG in the `camera` frame."""
    return CompressedImage(timestamp=stamp(ns), frame_id=CAMERA, data=data, format="jpeg")


_CLOUD_FIELDS = [
    PackedElementField(name="x", offset=0, type=PackedElementFieldNumericType.Float32),
    PackedElementField(name="y", offset=4, type=PackedElementFieldNumericType.Float32),
    PackedElementField(name="z", offset=8, type=PackedElementFieldNumericType.Float32),
    PackedElementField(name="red", offset=12, type=PackedElementFieldNumericType.Uint8),
    PackedElementField(name="green", offset=13, type=PackedElementFieldNumericType.Uint8),
    PackedElementField(name="blue", offset=14, type=PackedElementFieldNumericType.Uint8),
    PackedElementField(name="alpha", offset=15, type=PackedElementFieldNumericType.Uint8),
]
_CLOUD_DTYPE = np.dtype([("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("rgba", "u1", (4,))])


def depth_cloud(depth: np.ndarray, K: np.ndarray, rgb: np.ndarray | None, ns: int, stride: int = 3) -> PointCloud:
    """The depth image as points in the `camera` frame (m; every `stride`-th pixel each way), coloured by
    the RGB (grey without). Pixels without depth (0, NaN) are left out."""
    z = depth[::stride, ::stride].astype(np.float32)
    rows, cols = np.mgrid[0 : depth.shape[0] : stride, 0 : depth.shape[1] : stride]
    valid = np.isfinite(z) & (z > 0)
    zv = z[valid]
    u, v = cols[valid].astype(np.float32), rows[valid].astype(np.float32)
    fx, fy, cx, cy = float(K[0, 0]), float(K[1, 1]), float(K[0, 2]), float(K[1, 2])
    pts = np.empty(zv.size, dtype=_CLOUD_DTYPE)
    pts["x"] = (u - cx) * zv / fx
    pts["y"] = (v - cy) * zv / fy
    pts["z"] = zv
    if rgb is not None:
        pts["rgba"][:, :3] = rgb[::stride, ::stride][valid]
    else:
        pts["rgba"][:, :3] = 160
    pts["rgba"][:, 3] = 255
    return PointCloud(
        timestamp=stamp(ns),
        frame_id=CAMERA,
        pose=Pose(position=Vector3(x=0.0, y=0.0, z=0.0), orientation=Quaternion(w=1.0)),
        point_stride=_CLOUD_DTYPE.itemsize,
        fields=_CLOUD_FIELDS,
        data=pts.tobytes(),
    )


def camera_info(K: np.ndarray, width: int, height: int, ns: int) -> CameraCalibration:
    """The pinhole intrinsics (pixels) of the `camera` frame's images; no distortion (aligned RealSense
    colour and the simulated camera)."""
    k = [float(v) for v in np.asarray(K, dtype=float).reshape(9)]
    p = [k[0], k[1], k[2], 0.0, k[3], k[4], k[5], 0.0, k[6], k[7], k[8], 0.0]
    return CameraCalibration(
        timestamp=stamp(ns),
        frame_id=CAMERA,
        width=int(width),
        height=int(height),
        distortion_model="plumb_bob",
        D=[0.0] * 5,
        K=k,
        R=[1.0, 0.0, 0.0, 0.0, 1.0, 0.0, 0.0, 0.0, 1.0],
        P=p,
    )


class RecorderCamera:
    """The camera side of `Recorder` (module docstring); the attributes below are the recorder's."""

    ch_rgb: CompressedImageChannel
    ch_seg: CompressedImageChannel
    ch_depth: PointCloudChannel
    ch_caminfo: CameraCalibrationChannel
    _lock: threading.Lock
    _epoch_ns: int
    _frame_stamps: dict[int, int]
    _last_frame: FrameBundle | None
    ns: Callable[..., int]
    count_message: Callable[[str], None]
    _guard: Callable[[str, Callable[[], None]], None]

    def wrap_grab(self, grab: Callable[[], FrameBundle]) -> Callable[[], FrameBundle]:
        """`grab` whose frames (the ones perception asks for) are also recorded: RGB, depth, labels."""

        def frame() -> FrameBundle:
            f = grab()
            if f is not self._last_frame:  # a frozen camera repeats its frame: recorded once
                self._last_frame = f
                self._guard("camera frame", lambda: self._frame(f))
            return f

        return frame

    def wrap_segmenter(self, segmenter: Any) -> Any:
        """A segmenter whose labels are also recorded (`/camera/segmentation`)."""
        return RecordingSegmenter(segmenter, self)

    def _frame(self, f: FrameBundle) -> None:
        ns = self.ns()
        stamp_ns = ns if f.stamp_s is None else self._epoch_ns + round(f.stamp_s * 1e9)
        h, w = f.depth.shape
        self.ch_caminfo.log(camera_info(f.K, w, h, stamp_ns), log_time=ns)
        self.count_message("/camera/calibration")
        if f.rgb is not None:
            self.ch_rgb.log(compressed_image(jpeg(f.rgb), stamp_ns), log_time=ns)
            self.count_message("/camera/rgb")
            with self._lock:
                self._frame_stamps = {id(f.rgb): stamp_ns}  # the segmenter's next call belongs to it
        self.ch_depth.log(depth_cloud(f.depth, f.K, f.rgb, stamp_ns, DEPTH_STRIDE), log_time=ns)
        self.count_message("/camera/depth")
        if f.labels is not None:
            self._overlay_now(f.rgb, f.labels, stamp_ns)

    def overlay_segmentation(self, rgb: np.ndarray, labels: np.ndarray) -> None:
        """Labels perception segmented from `rgb` (any thread)."""

        def record() -> None:
            with self._lock:
                stamp_ns = self._frame_stamps.get(id(rgb))
            self._overlay_now(rgb, labels, self.ns() if stamp_ns is None else stamp_ns)

        self._guard("segmentation", record)

    def _overlay_now(self, rgb: np.ndarray | None, labels: np.ndarray, stamp_ns: int) -> None:
        image = segmentation_overlay(rgb, labels)
        self.ch_seg.log(compressed_image(jpeg(image), stamp_ns), log_time=self.ns())
        self.count_message("/camera/segmentation")
