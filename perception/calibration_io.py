"""The calibration result and its JSON file (the output of `palletpilot calibrate --json`).

```json
{"T_forklift_camera": [[...4 x 4...]], "xyz_m": [x, y, z], "rpy_deg": [roll, pitch, yaw],
 "tilt_deg": 22.0, "pan_deg": 0.5, "roll_about_optical_deg": -0.3,
 "method": "model", "quality": {...}}
```
`T_forklift_camera` is always for lift height 0; at lift height h the camera is at
`Trans(0, 0, h) @ T_forklift_camera`. `xyz_m` and `rpy_deg` restate it (roll, pitch, yaw of the
optical frame in the forklift frame); tilt, pan and roll about the optical axis are the mount angles
of `sim.camera.camera_mount_pose` (the paper's "roll", "pitch" and "yaw").
"""

from __future__ import annotations

import json
import math
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import numpy as np
from scipy.spatial.transform import Rotation

from palletpilot.geometry import SE3, GeometryError
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
        }


def save_calibration(path: str | Path, calibration: Calibration) -> Path:
    """Write a calibration JSON file."""
    path = Path(path)
    path.write_text(json.dumps(calibration.to_json(), indent=2) + "\n")
    return path


def load_calibration(path: str | Path) -> Calibration:
    """Read a calibration JSON file; a missing or malformed file raises `PerceptionError` naming it."""
    path = Path(path)
    try:
        doc = json.loads(path.read_text())
    except OSError as exc:
        raise PerceptionError(f"{path}: cannot read: {exc.strerror or exc}") from None
    except json.JSONDecodeError as exc:
        raise PerceptionError(f"{path}: not valid JSON: line {exc.lineno}: {exc.msg}") from None
    if not isinstance(doc, dict) or "T_forklift_camera" not in doc:
        raise PerceptionError(f"{path}: not a calibration file (no 'T_forklift_camera')")
    try:
        T = SE3.from_matrix(np.asarray(doc["T_forklift_camera"], dtype=float))
    except (GeometryError, ValueError, TypeError) as exc:
        raise PerceptionError(f"{path}: T_forklift_camera: {exc}") from None
    return Calibration(T, str(doc.get("method", "unknown")), dict(doc.get("quality", {})))
