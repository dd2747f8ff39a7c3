"""The perception service's wire format: frame bundles as compact binary, results and errors as JSON.

Used by `executor.perception_server` (the `palletpilot perception serve` process) and
`executor.perception_remote` (`RemotePerception`); nothing here knows the transport (Zenoh).

**Frame bundle** (`encode_frame` / `decode_frame`), little-endian, no compression (loopback and a
LAN carry a 640 x 480 RGB-D frame, 2.4 MB, in a few milliseconds; compressing it costs more):

| bytes | field |
| --- | --- |
| 4 | magic `PPFB` |
| 1 | format version (1) |
| 1 | depth encoding: 1 float32 metres, 2 uint16 millimetres (0: no data) |
| 1 | flags: bit 0 labels present, bit 1 rgb present |
| 1 | reserved (0) |
| 4, 4 | image height H, width W (px, uint32) |
| 4 | length of the JSON meta (bytes, uint32) |
| n | JSON meta: `{"K": 3 x 3 (px), "fork_height": m, "stamp_s": s or null}`, and `"dist"` (below) |
| H W 4 (or 2) | depth, row-major, camera optical frame (z-depth along the optical axis) |
| H W | labels uint8 (class ids), when flagged |
| H W 3 | rgb uint8, RGB order, when flagged |

The meta holds `"dist": [k1, k2, p1, p2, ...]` (OpenCV order) only for a frame with lens distortion
coefficients: a frame without them is sent byte for byte as before the key existed, and a meta without
it decodes to a frame without it. Truth arrays (`*_true`, simulator-only) are not sent: perception never
reads them. The decoder checks the header against the limits (`MAX_IMAGE_SIDE`, `MAX_META_BYTES`) and
the exact payload size before it allocates anything, then builds the `FrameBundle`, whose constructor
checks the whole data contract (`perception.bundle_contract`). Every problem raises `PerceptionError`,
one line naming `where` (the key the payload came on): `palletpilot/perception/estimate_pallet: frame:
...`.

**Request** (`encode_request` / `decode_request`): magic `PPRQ`, version (1), frame count (0..16),
reserved (0), JSON parameter length (uint32), the parameters (strict JSON), then per frame its length
(uint32) and its encoded bundle. No frame: the service grabs one from its own camera.

**Results** are strict JSON (UTF-8) with `"version": 1` (`encode_json` / `decode_json`): a
`Calibration` as its calibration file document (`perception.calibration_io`, checked as a file is)
plus the exact transform (quaternion and translation, bit for bit: `se3_to_json`); a `PalletEstimate`
with its exact transforms and spread; a `VolumeCheck`; an error as `{"error": {"type", "reason",
"message", ...}}`, re-raised on the client as the same exception type with the same reason
(`error_to_json` / `error_from_json`): `PalletNotFound` (its `reason`), `CalibrationError`,
`PerceptionError`, and `ServiceBusyError` (the service's queue is full).

Public API: `encode_frame`, `decode_frame`, `encode_request`, `decode_request`, `encode_json`,
`decode_json`, `calibration_to_json` / `calibration_from_json`, `estimate_to_json` /
`estimate_from_json`, `volume_check_to_json` / `volume_check_from_json`, `volume_to_json` /
`volume_from_json`, `se2_to_json` / `se2_from_json`, `se3_to_json` / `se3_from_json`, `pallet_to_json` /
`pallet_from_json`, `error_to_json` / `error_from_json`, `ServiceBusyError`, `is_frame`, the constants `WIRE_VERSION`,
`DEFAULT_PREFIX`, `QUERIES`, `MAX_META_BYTES`, `MAX_PARAMS_BYTES`, `MAX_FRAMES`.
"""

from __future__ import annotations

import math
import struct
from collections.abc import Mapping, Sequence
from typing import Any, Literal, cast

import numpy as np
from scipy.spatial.transform import Rotation

from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.fileio import dumps_json, parse_json, validate_model
from palletpilot.perception.bundle_contract import DIST_LENGTHS, MAX_IMAGE_SIDE
from palletpilot.perception.calibration_io import Calibration, CalibrationFile
from palletpilot.perception.clearance import Volume, VolumeCheck
from palletpilot.perception.errors import CalibrationError, PerceptionError
from palletpilot.perception.frames import _CHECK_AS, FrameBundle
from palletpilot.perception.pallet_estimate import NotFoundReason, PalletEstimate, PalletNotFound, PalletSpread
from palletpilot.perception.specs import PalletType

WIRE_VERSION = 1
"""The version of every payload (binary header byte, JSON `version`)."""
DEFAULT_PREFIX = "palletpilot/perception"
"""The key prefix of the service's queryables."""
QUERIES = ("calibrate", "estimate_pallet", "check_volume", "segment", "health")
"""The queryables under the prefix (`PREFIX/NAME`)."""
MAX_META_BYTES = 64 * 1024
"""The largest JSON meta of one frame (bytes): K, fork height, stamp and 14 distortion coefficients take about 600."""
MAX_PARAMS_BYTES = 1024 * 1024
"""The largest JSON parameter block of a request or JSON result (bytes); a pallet type is about 1 kB."""
MAX_FRAMES = 16
"""The most frames one request carries (a calibration from several frames)."""

DepthEncoding = Literal["f32", "mm16"]

_FRAME_MAGIC = b"PPFB"
_REQUEST_MAGIC = b"PPRQ"
_FRAME_HEADER = struct.Struct("<4sBBBBIII")
_REQUEST_HEADER = struct.Struct("<4sBBHI")
_LENGTH = struct.Struct("<I")
_DEPTH_CODES: dict[DepthEncoding, int] = {"f32": 1, "mm16": 2}
_HAS_LABELS, _HAS_RGB = 1, 2
_MAX_MM = 65535


class ServiceBusyError(PerceptionError):
    """The service's request queue is full: try again shortly."""

    reason = "busy"


def is_frame(payload: bytes) -> bool:
    """True when `payload` starts like an encoded frame bundle (else it is JSON)."""
    return payload[:4] == _FRAME_MAGIC


# -- frame bundles ---------------------------------------------------------------------------------


def encode_frame(frame: FrameBundle, depth: DepthEncoding = "f32") -> bytearray:
    """The frame as the binary of the module docstring (truth arrays left out).

    `depth`: `f32` sends the float32 metres as they are; `mm16` sends whole millimetres (half the
    bytes; a RealSense measures in millimetres anyway), NaN as 0, and refuses depths beyond 65.535 m.
    """
    head, arrays = _frame_parts(frame, depth)
    out = bytearray(_parts_size(head, arrays))
    _write_parts(out, 0, head, arrays)
    return out


def _frame_parts(frame: FrameBundle, depth: DepthEncoding) -> tuple[bytes, list[np.ndarray]]:
    """The header with the meta, and the arrays in wire order as C-contiguous arrays of their wire dtype."""
    h, w = frame.depth.shape
    flags = (_HAS_LABELS if frame.labels is not None else 0) | (_HAS_RGB if frame.rgb is not None else 0)
    doc: dict[str, Any] = {"K": frame.K.tolist(), "fork_height": frame.fork_height, "stamp_s": frame.stamp_s}
    if frame.dist is not None:
        doc["dist"] = frame.dist.tolist()
    meta = dumps_json(doc).encode()
    if depth == "mm16":
        mm = np.rint(np.nan_to_num(frame.depth, nan=0.0) * 1000.0)
        if mm.size and float(mm.max()) > _MAX_MM:
            raise PerceptionError(f"frame: depth up to {float(mm.max()) / 1e3:.3f} m does not fit uint16 millimetres")
        arrays = [mm.astype("<u2")]
    else:
        arrays = [np.ascontiguousarray(frame.depth, dtype="<f4")]
    arrays += [np.ascontiguousarray(a) for a in (frame.labels, frame.rgb) if a is not None]
    head = _FRAME_HEADER.pack(_FRAME_MAGIC, WIRE_VERSION, _DEPTH_CODES[depth], flags, 0, h, w, len(meta)) + meta
    return head, arrays


def _parts_size(head: bytes, arrays: Sequence[np.ndarray]) -> int:
    return len(head) + sum(a.nbytes for a in arrays)


def _write_parts(out: bytearray, offset: int, head: bytes, arrays: Sequence[np.ndarray]) -> int:
    """Copy `head` and the arrays' bytes into `out` from `offset` (one copy each); the offset after them.

    Encoding writes every frame straight into the one buffer that goes on the wire: a 640 x 480 RGB-D
    frame is 2.4 MB, and each extra copy of it (`tobytes`, a join) costs the service's client 0.1-1 ms.
    """
    view = memoryview(out)
    view[offset : offset + len(head)] = head
    offset += len(head)
    for a in arrays:
        view[offset : offset + a.nbytes] = a.data.cast("B")
        offset += a.nbytes
    return offset


def decode_frame(payload: bytes | memoryview, where: str = "frame") -> FrameBundle:
    """The `FrameBundle` of an encoded payload; every problem raises `PerceptionError` (`where: ...`)."""
    data = memoryview(payload)
    if len(data) < _FRAME_HEADER.size:
        raise PerceptionError(f"{where}: {len(data)} bytes, shorter than a frame header ({_FRAME_HEADER.size})")
    magic, version, code, flags, reserved, h, w, meta_len = _FRAME_HEADER.unpack_from(data)
    if magic != _FRAME_MAGIC:
        raise PerceptionError(
            f"{where}: not an encoded frame bundle (magic {bytes(magic)!r}, expected {_FRAME_MAGIC!r})"
        )
    if version != WIRE_VERSION:
        raise PerceptionError(f"{where}: frame format version {version}, this build reads {WIRE_VERSION}")
    encodings = {v: k for k, v in _DEPTH_CODES.items()}
    if code not in encodings:
        raise PerceptionError(f"{where}: unknown depth encoding {code} (1 float32 m, 2 uint16 mm)")
    if flags & ~(_HAS_LABELS | _HAS_RGB) or reserved:
        raise PerceptionError(f"{where}: unknown flags 0x{flags:02x} or reserved byte {reserved} set")
    if not (1 <= h <= MAX_IMAGE_SIDE and 1 <= w <= MAX_IMAGE_SIDE):
        raise PerceptionError(f"{where}: image {w} x {h} px: each side must be 1..{MAX_IMAGE_SIDE} px")
    if meta_len > MAX_META_BYTES:
        raise PerceptionError(f"{where}: meta of {meta_len} bytes (at most {MAX_META_BYTES})")
    depth_size = 4 if encodings[code] == "f32" else 2
    sizes = [h * w * depth_size, h * w if flags & _HAS_LABELS else 0, h * w * 3 if flags & _HAS_RGB else 0]
    expected = _FRAME_HEADER.size + meta_len + sum(sizes)
    if len(data) != expected:
        raise PerceptionError(
            f"{where}: {len(data)} bytes, but the header declares {expected} ({w} x {h} px, flags 0x{flags:02x})"
        )
    offset = _FRAME_HEADER.size
    meta = _meta(bytes(data[offset : offset + meta_len]), where)
    offset += meta_len

    def array(dtype: str, size: int, shape: tuple[int, ...]) -> np.ndarray:
        nonlocal offset
        out = np.frombuffer(data, dtype=dtype, count=size // np.dtype(dtype).itemsize, offset=offset)
        offset += size
        return out.reshape(shape)

    if encodings[code] == "f32":
        depth = array("<f4", sizes[0], (h, w)).astype(np.float32)  # a native, writable copy
    else:
        depth = array("<u2", sizes[0], (h, w)).astype(np.float32) / np.float32(1000.0)
    labels = array("u1", sizes[1], (h, w)).copy() if sizes[1] else None
    rgb = array("u1", sizes[2], (h, w, 3)).copy() if sizes[2] else None
    token = _CHECK_AS.set((f"{where}: frame", None))
    try:
        return FrameBundle(
            depth, meta["K"], labels, rgb, meta["fork_height"], stamp_s=meta["stamp_s"], dist=meta["dist"]
        )
    finally:
        _CHECK_AS.reset(token)


def _meta(text: bytes, where: str) -> dict[str, Any]:
    """The frame's JSON meta: K (float64 3 x 3), fork height (m), stamp (s or None) and the optional lens
    distortion coefficients (float64 vector or None; their count and values are the bundle contract's)."""
    doc = _json_object(text, f"{where}: frame meta")
    unknown = sorted(set(doc) - {"K", "fork_height", "stamp_s", "dist"})
    if unknown or "K" not in doc:
        raise PerceptionError(f"{where}: frame meta: needs K, fork_height, stamp_s; unknown keys {unknown}")
    K = _matrix(doc["K"], 3, f"{where}: frame meta: K")
    fork_height = _number(doc.get("fork_height", 0.0), f"{where}: frame meta: fork_height")
    stamp = doc.get("stamp_s")
    dist = doc.get("dist")
    if dist is not None:
        if not isinstance(dist, list) or len(dist) > max(DIST_LENGTHS):
            raise PerceptionError(f"{where}: frame meta: dist: expected a list of at most {max(DIST_LENGTHS)} numbers")
        dist = np.array([_number(v, f"{where}: frame meta: dist") for v in dist], dtype=np.float64)
    return {
        "K": K,
        "fork_height": fork_height,
        "stamp_s": None if stamp is None else _number(stamp, f"{where}: stamp_s"),
        "dist": dist,
    }


# -- requests --------------------------------------------------------------------------------------


def encode_request(
    params: Mapping[str, Any], frames: Sequence[FrameBundle] = (), depth: DepthEncoding = "f32"
) -> bytearray:
    """A request: JSON parameters and 0..`MAX_FRAMES` frames (module docstring), in one buffer."""
    if len(frames) > MAX_FRAMES:
        raise PerceptionError(f"request: {len(frames)} frames, at most {MAX_FRAMES}")
    text = dumps_json(dict(params)).encode()
    parts = [_frame_parts(frame, depth) for frame in frames]
    sizes = [_parts_size(head, arrays) for head, arrays in parts]
    out = bytearray(_REQUEST_HEADER.size + len(text) + sum(_LENGTH.size + n for n in sizes))
    _REQUEST_HEADER.pack_into(out, 0, _REQUEST_MAGIC, WIRE_VERSION, len(frames), 0, len(text))
    offset = _REQUEST_HEADER.size
    out[offset : offset + len(text)] = text
    offset += len(text)
    for (head, arrays), size in zip(parts, sizes, strict=True):
        _LENGTH.pack_into(out, offset, size)
        offset = _write_parts(out, offset + _LENGTH.size, head, arrays)
    return out


def decode_request(payload: bytes | memoryview, where: str = "request") -> tuple[dict[str, Any], list[FrameBundle]]:
    """The parameters and frames of a request; every problem raises `PerceptionError` (`where: ...`)."""
    data = memoryview(payload)
    if len(data) < _REQUEST_HEADER.size:
        raise PerceptionError(f"{where}: {len(data)} bytes, shorter than a request header ({_REQUEST_HEADER.size})")
    magic, version, count, reserved, length = _REQUEST_HEADER.unpack_from(data)
    if magic != _REQUEST_MAGIC:
        raise PerceptionError(
            f"{where}: not a perception request (magic {bytes(magic)!r}, expected {_REQUEST_MAGIC!r})"
        )
    if version != WIRE_VERSION:
        raise PerceptionError(f"{where}: request format version {version}, this build reads {WIRE_VERSION}")
    if count > MAX_FRAMES or reserved:
        raise PerceptionError(f"{where}: {count} frames (at most {MAX_FRAMES}) or reserved bytes {reserved} set")
    if length > MAX_PARAMS_BYTES:
        raise PerceptionError(f"{where}: parameters of {length} bytes (at most {MAX_PARAMS_BYTES})")
    offset = _REQUEST_HEADER.size
    if offset + length > len(data):
        raise PerceptionError(f"{where}: truncated: the parameters run past the end ({len(data)} bytes)")
    params = _json_object(bytes(data[offset : offset + length]), f"{where}: parameters")
    offset += length
    frames = []
    for i in range(count):
        if offset + _LENGTH.size > len(data):
            raise PerceptionError(f"{where}: truncated: frame {i} of {count} is missing")
        (size,) = _LENGTH.unpack_from(data, offset)
        offset += _LENGTH.size
        if offset + size > len(data):
            raise PerceptionError(f"{where}: truncated: frame {i} declares {size} bytes, {len(data) - offset} remain")
        frames.append(decode_frame(data[offset : offset + size], f"{where}: frame {i}" if count > 1 else where))
        offset += size
    if offset != len(data):
        raise PerceptionError(f"{where}: {len(data) - offset} bytes after the last frame")
    return params, frames


# -- JSON results ----------------------------------------------------------------------------------


def encode_json(doc: Mapping[str, Any]) -> bytes:
    """Strict JSON (UTF-8) of `doc` with `"version": WIRE_VERSION` first."""
    return dumps_json({"version": WIRE_VERSION, **doc}).encode()


def decode_json(payload: bytes, where: str) -> dict[str, Any]:
    """A JSON object of version `WIRE_VERSION` (its `version` key removed); else `PerceptionError`."""
    doc = _json_object(payload, where)
    version = doc.pop("version", None)
    if version != WIRE_VERSION:
        raise PerceptionError(f"{where}: result version {version!r}, this build reads {WIRE_VERSION}")
    return doc


def _json_object(text: bytes, where: str) -> dict[str, Any]:
    if len(text) > MAX_PARAMS_BYTES:
        raise PerceptionError(f"{where}: {len(text)} bytes of JSON (at most {MAX_PARAMS_BYTES})")
    try:
        decoded = text.decode("utf-8")
    except UnicodeDecodeError as exc:
        raise PerceptionError(f"{where}: not UTF-8 JSON (byte 0x{text[exc.start]:02x} at {exc.start})") from None
    doc = parse_json(decoded, where, PerceptionError)
    if not isinstance(doc, dict):
        raise PerceptionError(f"{where}: expected a JSON object, got {type(doc).__name__}")
    return doc


def _number(value: object, where: str) -> float:
    if isinstance(value, bool) or not isinstance(value, (int, float)) or not math.isfinite(value):
        raise PerceptionError(f"{where}: expected a finite number, got {value!r}"[:300])
    return float(value)


def _matrix(value: object, n: int, where: str) -> np.ndarray:
    if not isinstance(value, list) or len(value) != n or not all(isinstance(r, list) and len(r) == n for r in value):
        raise PerceptionError(f"{where}: expected a {n} x {n} matrix of numbers")
    return np.array([[_number(v, where) for v in row] for row in value], dtype=np.float64)


def se3_to_json(T: SE3) -> dict[str, list[float]]:
    """`{"quat_xyzw": [x, y, z, w], "t_m": [x, y, z]}`: the transform bit for bit (a 4 x 4 matrix would
    round through the rotation matrix and back)."""
    return {"quat_xyzw": T.rotation.as_quat(canonical=False).tolist(), "t_m": T.t.tolist()}


def se3_from_json(value: object, where: str) -> SE3:
    """The `SE3` of `se3_to_json`: a unit quaternion (within 1e-9) and a translation (m)."""
    if not isinstance(value, dict) or set(value) != {"quat_xyzw", "t_m"}:
        raise PerceptionError(f"{where}: expected {{quat_xyzw: [x, y, z, w], t_m: [x, y, z]}}")
    q, t = value["quat_xyzw"], value["t_m"]
    if not isinstance(q, list) or len(q) != 4 or not isinstance(t, list) or len(t) != 3:
        raise PerceptionError(f"{where}: expected a quaternion of 4 and a translation of 3 numbers")
    quat = np.array([_number(v, where) for v in q])
    if abs(float(np.linalg.norm(quat)) - 1.0) > 1e-9:
        raise PerceptionError(f"{where}: quat_xyzw is not a unit quaternion (norm {float(np.linalg.norm(quat)):.12g})")
    try:  # exactly the sender's quaternion (it is a unit one); `from_quat` would normalise it again
        rotation = Rotation(quat, normalize=False)
    except TypeError:  # a SciPy without the argument
        rotation = Rotation.from_quat(quat)
    return SE3(rotation, [_number(v, where) for v in t])


def _field(doc: Mapping[str, Any], key: str, where: str) -> Any:
    if key not in doc:
        raise PerceptionError(f"{where}: missing '{key}'")
    return doc[key]


def calibration_to_json(calibration: Calibration) -> dict[str, Any]:
    """`{"calibration": the calibration file document, "T_forklift_camera_exact": se3_to_json}` (lift height 0)."""
    return {
        "calibration": calibration.to_json(),
        "T_forklift_camera_exact": se3_to_json(calibration.T_forklift_camera),
    }


def calibration_from_json(doc: Mapping[str, Any], where: str) -> Calibration:
    """A calibration sent by `calibration_to_json`, checked as a calibration file is (`calibration_io`)."""
    model = validate_model(_field(doc, "calibration", where), CalibrationFile, f"{where}: calibration", PerceptionError)
    exact = se3_from_json(_field(doc, "T_forklift_camera_exact", where), f"{where}: T_forklift_camera_exact")
    if float(np.max(np.abs(exact.matrix - np.array(model.T_forklift_camera)))) > 1e-6:
        raise PerceptionError(f"{where}: T_forklift_camera_exact disagrees with the calibration's T_forklift_camera")
    return Calibration(exact, model.method, dict(model.quality), tuple(model.warnings))


def estimate_to_json(estimate: PalletEstimate) -> dict[str, Any]:
    """Everything of a `PalletEstimate`, transforms exact (`se3_to_json`; forklift and world frames)."""
    return {
        "estimate": {
            "T_forklift_pallet": se3_to_json(estimate.T_forklift_pallet),
            "T_world_pallet": None if estimate.T_world_pallet is None else se3_to_json(estimate.T_world_pallet),
            "spread": {
                "x_m": estimate.spread.x_m,
                "y_m": estimate.spread.y_m,
                "yaw_rad": estimate.spread.yaw_rad,
                "x_common_m": estimate.spread.x_common_m,
                "y_common_m": estimate.spread.y_common_m,
                "yaw_common_rad": estimate.spread.yaw_common_rad,
            },
            "n_points": estimate.n_points,
            "n_face_points": estimate.n_face_points,
            "pocket_widths_m": list(estimate.pocket_widths_m),
            "pocket_centres_y_m": list(estimate.pocket_centres_y_m),
            "residual_rms_w": estimate.residual_rms_w,
            "runtime_ms": estimate.runtime_ms,
            "extras": estimate.extras,
        }
    }


def estimate_from_json(doc: Mapping[str, Any], where: str) -> PalletEstimate:
    """The `PalletEstimate` of `estimate_to_json`; a malformed document raises `PerceptionError`."""
    e = _field(doc, "estimate", where)
    if not isinstance(e, dict):
        raise PerceptionError(f"{where}: estimate: expected an object")
    spread = _field(e, "spread", where)
    pair = lambda key: _pair(_field(e, key, where), f"{where}: {key}")  # noqa: E731
    world = e.get("T_world_pallet")
    extras = e.get("extras", {})
    return PalletEstimate(
        T_forklift_pallet=se3_from_json(_field(e, "T_forklift_pallet", where), f"{where}: T_forklift_pallet"),
        spread=PalletSpread(
            *(_number(_field(spread, k, where), f"{where}: spread.{k}") for k in ("x_m", "y_m", "yaw_rad")),
            *(
                _number(spread.get(k, 0.0), f"{where}: spread.{k}")  # optional: services from before them
                for k in ("x_common_m", "y_common_m", "yaw_common_rad")
            ),
        ),
        n_points=int(_number(_field(e, "n_points", where), f"{where}: n_points")),
        n_face_points=int(_number(_field(e, "n_face_points", where), f"{where}: n_face_points")),
        pocket_widths_m=pair("pocket_widths_m"),
        pocket_centres_y_m=pair("pocket_centres_y_m"),
        residual_rms_w=_number(_field(e, "residual_rms_w", where), f"{where}: residual_rms_w"),
        T_world_pallet=None if world is None else se3_from_json(world, f"{where}: T_world_pallet"),
        runtime_ms=_number(e.get("runtime_ms", 0.0), f"{where}: runtime_ms"),
        extras=dict(extras) if isinstance(extras, dict) else {},
    )


def _pair(value: object, where: str) -> tuple[float, float]:
    if not isinstance(value, list) or len(value) != 2:
        raise PerceptionError(f"{where}: expected two numbers")
    return _number(value[0], where), _number(value[1], where)


def volume_check_to_json(check: VolumeCheck) -> dict[str, Any]:
    """`{"volume_check": {points, nearest_x_m (forklift frame, m, or null), seen (0..1)}}`."""
    return {"volume_check": {"points": check.points, "nearest_x_m": check.nearest_x_m, "seen": check.seen}}


def volume_check_from_json(doc: Mapping[str, Any], where: str) -> VolumeCheck:
    """The `VolumeCheck` of `volume_check_to_json`."""
    v = _field(doc, "volume_check", where)
    if not isinstance(v, dict):
        raise PerceptionError(f"{where}: volume_check: expected an object")
    nearest = v.get("nearest_x_m")
    return VolumeCheck(
        points=int(_number(_field(v, "points", where), f"{where}: points")),
        nearest_x_m=None if nearest is None else _number(nearest, f"{where}: nearest_x_m"),
        seen=_number(_field(v, "seen", where), f"{where}: seen"),
    )


def volume_to_json(volume: Volume) -> list[float]:
    """`[x0, x1, y0, y1, z0, z1]` (m, forklift frame), exact."""
    return [volume.x0, volume.x1, volume.y0, volume.y1, volume.z0, volume.z1]


def volume_from_json(value: object, where: str) -> Volume:
    """The `Volume` of `volume_to_json`."""
    if not isinstance(value, list) or len(value) != 6:
        raise PerceptionError(f"{where}: expected [x0, x1, y0, y1, z0, z1] (m)")
    return Volume(*(_number(v, where) for v in value))


def se2_to_json(pose: SE2) -> list[float]:
    """`[x, y, yaw]` (m, m, rad)."""
    return [pose.x, pose.y, pose.yaw]


def se2_from_json(value: object, where: str) -> SE2:
    """The `SE2` of `se2_to_json`."""
    if not isinstance(value, list) or len(value) != 3:
        raise PerceptionError(f"{where}: expected [x_m, y_m, yaw_rad]")
    return SE2(*(_number(v, where) for v in value))


def pallet_to_json(pallet: PalletType) -> dict[str, Any]:
    """The pallet type as its file document (metres)."""
    return pallet.model_dump(mode="json")


def pallet_from_json(value: object, where: str) -> PalletType:
    """A pallet type document, checked as a pallet type file is (`perception.specs`)."""
    return validate_model(value, PalletType, where, PerceptionError)


# -- errors ----------------------------------------------------------------------------------------


def error_to_json(exc: BaseException, kind: str | None = None) -> dict[str, Any]:
    """`{"error": {"type", "reason", "message", "detail"}}` for a failed request.

    `kind` overrides the type (`busy`, `bad_request`, `internal`); else it is the exception's class:
    `PalletNotFound` (with its `reason` and `detail`), `CalibrationError`, `PerceptionError`.
    """
    if kind is None:
        kind = next(
            (
                t.__name__
                for t in (PalletNotFound, CalibrationError, ServiceBusyError, PerceptionError)
                if isinstance(exc, t)
            ),
            "internal",
        )
    error: dict[str, Any] = {"type": kind, "message": str(exc), "reason": getattr(exc, "reason", None)}
    if isinstance(exc, PalletNotFound):
        error["detail"] = exc.detail
    return {"error": error}


def error_from_json(doc: Mapping[str, Any], where: str) -> PerceptionError:
    """The exception an error document stands for (same type, reason and message), to be raised."""
    error = doc.get("error")
    if not isinstance(error, dict):
        return PerceptionError(f"{where}: malformed error reply")
    kind, message, reason = error.get("type"), str(error.get("message", "")), error.get("reason")
    exc: PerceptionError
    if kind == "PalletNotFound" and isinstance(reason, str):
        exc = PalletNotFound(cast(NotFoundReason, reason), str(error.get("detail", message)))
        exc.args = (message,)
        exc.problems = [message]
    elif kind == "CalibrationError":
        exc = CalibrationError(message)
        if reason is not None:
            exc.reason = reason  # type: ignore[attr-defined]
    elif kind in ("ServiceBusyError", "busy"):
        exc = ServiceBusyError(message)
    elif kind == "PerceptionError":
        exc = PerceptionError(message)
    else:  # bad_request, internal: the service says what went wrong
        exc = PerceptionError(f"{where}: the service failed ({kind}): {message}")
    return exc
