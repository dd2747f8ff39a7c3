"""The calibration result and its JSON file (the output of `palletpilot calibrate --json`).

```json
{"T_forklift_camera": [[...4 x 4...]], "xyz_m": [x, y, z], "rpy_deg": [roll, pitch, yaw],
 "tilt_deg": 22.0, "pan_deg": 0.5, "roll_about_optical_deg": -0.3,
 "method": "model", "quality": {...}, "warnings": ["fork tips: ..."]}
```
`T_forklift_camera` is always for lift height 0; at lift height h the camera is at
`Trans(0, 0, h) @ T_forklift_camera`. `xyz_m` and `rpy_deg` restate it (roll, pitch, yaw of the
optical frame in the forklift frame); tilt, pan and roll about the optical axis are the mount angles
of `sim.camera.camera_mount_pose` (the paper's "roll", "pitch" and "yaw"). `palletpilot calibrate`
adds `pickup_view` (`perception.view`).

Reading a file (`load_calibration`) checks everything before the calibration is used, and reports
every problem as one line naming the file and the field (`CALIB.json: T_forklift_camera: ...`):
strict UTF-8 JSON of at most `MAX_CALIBRATION_BYTES` (no NaN or Infinity), numbers where numbers go
(a string `"0.5"` is refused), no unknown keys (a misspelt key is an error, not silently ignored);
`T_forklift_camera` a 4 x 4 rigid transform whose rotation is proper (orthonormal within
`ROTATION_TOLERANCE`, determinant +1) and whose camera lies within `MAX_CAMERA_DISTANCE_M` of the
forklift origin (on the floor midway between the forks, at the fork heels: the camera rides on the
fork carriage, so a translation of kilometres is a broken file); `xyz_m` and `rpy_deg`, when given,
must agree with it (they only restate it; edit `T_forklift_camera`).
"""

from __future__ import annotations

import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Annotated, Any

import numpy as np
from pydantic import Field, ValidationInfo, field_validator
from pydantic_core import PydanticCustomError
from scipy.spatial.transform import Rotation

from palletpilot.geometry import SE3, GeometryError
from palletpilot.geometry.fileio import FileModel, parse_json, read_text, validate_model, write_json
from palletpilot.perception.errors import PerceptionError

R_LEVEL = np.array([[0.0, 0.0, 1.0], [-1.0, 0.0, 0.0], [0.0, -1.0, 0.0]])
"""Rotation of a level camera looking along forklift +x: optical axes in the forklift frame (paper eq. 6)."""


def mount_angles(T_forklift_camera: SE3) -> tuple[float, float, float]:
    """(tilt, pan, roll) in rad with R = Rz(pan) R_LEVEL Rx(-tilt) Rz(roll) (`camera_mount_pose`)."""
    r_rel = Rotation.from_matrix(R_LEVEL).inv()
    # R = Rz(pan) L Rx(-tilt) Rz(roll)  =>  L^-1 Rz(pan) L = rotation about L^-1 z = optical -y.
    # So L^-1 R = Ry'(-pan) Rx(-tilt) Rz(roll) in optical axes: intrinsic y-x-z Euler angles.
    m = r_rel * T_forklift_camera.rotation
    a, b, c = m.as_euler("YXZ")  # intrinsic: about y, then x, then z
    return -b, -a, c


@dataclass(frozen=True)
class Calibration:
    """`T_forklift_camera` at lift height 0, the method that found it and its quality figures."""

    T_forklift_camera: SE3
    method: str
    quality: dict[str, Any] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()  # what the operator should know (an untrusted tip, ...): stderr of `calibrate`

    def T_forklift_camera_at(self, lift_height: float) -> SE3:
        """The camera pose at a lift height (m): the camera rides on the carriage."""
        return SE3.from_translation(0.0, 0.0, lift_height) @ self.T_forklift_camera

    def to_json(self) -> dict[str, Any]:
        """The JSON document of the module docstring."""
        xyz, rpy = self.T_forklift_camera.to_xyz_rpy()
        tilt, pan, roll = mount_angles(self.T_forklift_camera)
        return {
            "T_forklift_camera": np.round(self.T_forklift_camera.matrix, 9).tolist(),
            "xyz_m": np.round(xyz, 6).tolist(),
            "rpy_deg": np.round(np.degrees(rpy), 4).tolist(),
            "tilt_deg": round(math.degrees(tilt), 4),
            "pan_deg": round(math.degrees(pan), 4),
            "roll_about_optical_deg": round(math.degrees(roll), 4),
            "method": self.method,
            "quality": self.quality,
            "warnings": list(self.warnings),
        }


MAX_CALIBRATION_BYTES = 2**20
"""The largest calibration file read (bytes); one written by `palletpilot calibrate` is about 1.2 kB."""
ROTATION_TOLERANCE = 1e-4
"""How far `R^T R` may stray from the identity (and det R from 1) in a calibration file."""
MAX_CAMERA_DISTANCE_M = 5.0
"""The farthest a calibrated camera may be from the forklift origin (m); real mounts are within 2 m."""
XYZ_TOLERANCE_M = 1e-3
"""How far `xyz_m` may differ from the translation of `T_forklift_camera` (m)."""
RPY_TOLERANCE_DEG = 0.05
"""How far the rotation of `rpy_deg` may differ from that of `T_forklift_camera` (deg)."""

_Number = Annotated[float, Field(strict=True)]
"""A JSON number (an int or a float, finite: `FileModel`), never a string or a boolean."""
_Row = tuple[_Number, _Number, _Number, _Number]
_Triple = tuple[_Number, _Number, _Number]


def _problem(text: str) -> PydanticCustomError:
    """A validation error whose message is `text` as it stands (no 'Value error, ' prefix)."""
    return PydanticCustomError("calibration", text)


class CalibrationFile(FileModel):
    """The schema of a calibration JSON file (module docstring); metres and degrees, forklift frame."""

    T_forklift_camera: tuple[_Row, _Row, _Row, _Row] = Field(
        description="4 x 4 homogeneous transform from the camera's optical frame to the forklift frame, lift height 0"
    )
    xyz_m: _Triple | None = Field(None, description="translation of T_forklift_camera (m), restated")
    rpy_deg: _Triple | None = Field(None, description="roll, pitch, yaw of T_forklift_camera (deg), restated")
    tilt_deg: _Number | None = Field(None, ge=-180.0, le=180.0, description="mount tilt (deg), restated")
    pan_deg: _Number | None = Field(None, ge=-180.0, le=180.0, description="mount pan (deg), restated")
    roll_about_optical_deg: _Number | None = Field(None, ge=-180.0, le=180.0, description="mount roll (deg)")
    method: str = Field("unknown", min_length=1, max_length=64, description="the method that found it")
    quality: dict[str, Any] = Field(default_factory=dict, description="quality figures (informative)")
    warnings: list[Annotated[str, Field(max_length=2000)]] = Field(
        default_factory=list, max_length=50, description="the calibration's warnings (informative)"
    )
    pickup_view: dict[str, Any] | None = Field(None, description="the mount check of `calibrate` (informative)")

    @field_validator("T_forklift_camera")
    @classmethod
    def _rigid(cls, rows: tuple[tuple[float, ...], ...]) -> tuple[tuple[float, ...], ...]:
        m = np.array(rows, dtype=float)
        if not np.allclose(m[3], [0.0, 0.0, 0.0, 1.0], rtol=0.0, atol=ROTATION_TOLERANCE):
            raise _problem(f"the last row must be [0, 0, 0, 1], got {m[3].tolist()}")
        r = m[:3, :3]
        off = float(np.max(np.abs(r.T @ r - np.eye(3))))
        if off > ROTATION_TOLERANCE:
            raise _problem(
                f"the rotation block is not orthonormal (R^T R differs from the identity by up to {off:.3g}; "
                f"tolerance {ROTATION_TOLERANCE:g})"
            )
        det = float(np.linalg.det(r))
        if abs(det - 1.0) > ROTATION_TOLERANCE:
            raise _problem(f"the rotation block has determinant {det:.4g}: a reflection, not a proper rotation")
        distance = float(np.linalg.norm(m[:3, 3]))
        if distance > MAX_CAMERA_DISTANCE_M:
            raise _problem(
                f"the camera is {distance:.4g} m from the forklift origin (at most {MAX_CAMERA_DISTANCE_M:g} m: "
                "it rides on the fork carriage)"
            )
        return rows

    @field_validator("xyz_m")
    @classmethod
    def _xyz_restates(cls, xyz: tuple[float, ...] | None, info: ValidationInfo) -> tuple[float, ...] | None:
        rows = info.data.get("T_forklift_camera")
        if xyz is None or rows is None:
            return xyz
        t = np.array(rows)[:3, 3]
        if float(np.max(np.abs(np.array(xyz) - t))) > XYZ_TOLERANCE_M:
            raise _problem(
                f"{list(xyz)} disagrees with the translation of T_forklift_camera {np.round(t, 6).tolist()} "
                "(xyz_m only restates it: edit T_forklift_camera)"
            )
        return xyz

    @field_validator("rpy_deg")
    @classmethod
    def _rpy_restates(cls, rpy: tuple[float, ...] | None, info: ValidationInfo) -> tuple[float, ...] | None:
        rows = info.data.get("T_forklift_camera")
        if rpy is None or rows is None:
            return rpy
        r_file = Rotation.from_matrix(np.array(rows)[:3, :3])
        r_rpy = Rotation.from_euler("xyz", rpy, degrees=True)
        angle = math.degrees((r_file.inv() * r_rpy).magnitude())
        if angle > RPY_TOLERANCE_DEG:
            back = np.round(r_file.as_euler("xyz", degrees=True), 4).tolist()
            raise _problem(
                f"{list(rpy)} is {angle:.3g} deg off the rotation of T_forklift_camera (roll, pitch, yaw {back} "
                "deg; rpy_deg only restates it: edit T_forklift_camera)"
            )
        return rpy


def save_calibration(path: str | Path, calibration: Calibration) -> Path:
    """Write a calibration JSON file, atomically (strict JSON; `OutputError` when it cannot be written)."""
    return write_json(path, calibration.to_json())


def load_calibration(path: str | Path) -> Calibration:
    """Read and check a calibration JSON file (module docstring); problems raise `PerceptionError`, one line each."""
    path = Path(path)
    if path.is_dir():
        raise PerceptionError(f"{path}: a folder, not a calibration file (.json)")
    doc = parse_json(read_text(path, PerceptionError, MAX_CALIBRATION_BYTES), str(path), PerceptionError)
    if not isinstance(doc, dict) or "T_forklift_camera" not in doc:
        raise PerceptionError(
            f"{path}: not a calibration file (no 'T_forklift_camera'; `palletpilot calibrate --out` writes one)"
        )
    model = validate_model(doc, CalibrationFile, str(path), PerceptionError)
    try:
        T = SE3.from_matrix(np.array(model.T_forklift_camera, dtype=float), atol=ROTATION_TOLERANCE)
    except GeometryError as exc:  # the model has checked it; kept as a last guard
        raise PerceptionError(f"{path}: T_forklift_camera: {exc}") from None
    return Calibration(T, model.method, dict(model.quality), tuple(model.warnings))
