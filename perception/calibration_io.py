"""The calibration result and its JSON file (the output of `palletpilot calibrate --json`).

```json
{"T_forklift_camera": [[...4 x 4...]], "xyz_m": [x, y, z], "rpy_deg": [roll, pitch, yaw],
 "tilt_deg": 22.0, "pan_deg": 0.5, "roll_about_optical_deg": -0.3,
 "method": "model", "quality": {...}, "warnings": ["fork tips: ..."], "untrusted_axes": ["x"]}
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

**Trusted axes** (`CalibrationAxis`, `Calibration.untrusted_axes`): the floor alone fixes the camera's
height z and its roll and pitch (which way is up); the forks fix x (the tips), y and yaw (the blades'
sides). When the tips cannot be trusted (`quality.tip_trusted` false: fork pixels beyond the fitted tips,
or tips seen at a grazing angle, `perception.calibration`), x is untrusted: it may be off by a taper's
length; the `paper` method never checks its tips, so its x is never trusted. `untrusted_axes` lists them
(`[]`: all trusted). A file without the key (written before it existed) loads with the axes its method and
`quality` imply: all trusted, unless `tip_trusted` is false or the method is `paper`. `keep_axes` takes
untrusted axes from an earlier trusted calibration of the same mount (`quality.kept_axes` says from where);
`mount_moved` says whether the trusted axes of two calibrations agree (the Pickup's rule,
`executor.pickup.CalibrateCamera`).
"""

from __future__ import annotations

import enum
import math
from collections.abc import Iterable, Mapping
from dataclasses import InitVar, dataclass, field
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


class CalibrationAxis(enum.StrEnum):
    """One degree of freedom of `T_forklift_camera` (lift height 0), named as the calibration JSON states it.

    `x`, `y`, `z`: the camera's position in the forklift frame (m, `xyz_m`); `roll`, `pitch`, `yaw`: the
    angles of `rpy_deg` (forklift axes, R = Rz(yaw) Ry(pitch) Rx(roll)). The floor alone fixes the height
    z, roll and pitch (the floor normal: the mount's tilt and its roll about the optical axis); the forks
    fix x (the tips at `tip_x`), y (the blades' sides) and yaw (their direction: the mount's pan).
    """

    X = "x"
    Y = "y"
    Z = "z"
    ROLL = "roll"
    PITCH = "pitch"
    YAW = "yaw"


FLOOR_AXES = frozenset({CalibrationAxis.Z, CalibrationAxis.ROLL, CalibrationAxis.PITCH})
"""The axes the floor alone fixes (height, roll, pitch)."""
FORK_AXES = frozenset({CalibrationAxis.X, CalibrationAxis.Y, CalibrationAxis.YAW})
"""The axes the forks fix: x by the tips, y and yaw by the blades' sides."""
TIP_AXES = frozenset({CalibrationAxis.X})
"""The axes only the fork tips fix: untrusted when the tips are (`quality.tip_trusted` false)."""
_TRANSLATION = (CalibrationAxis.X, CalibrationAxis.Y, CalibrationAxis.Z)
_ROTATION = (CalibrationAxis.ROLL, CalibrationAxis.PITCH, CalibrationAxis.YAW)


def untrusted_axes_of(quality: Mapping[str, Any], method: str = "model") -> frozenset[CalibrationAxis]:
    """The axes a calibration's method and quality figures leave untrusted: `TIP_AXES` when `tip_trusted` is
    false, or for the `paper` method (its forward position comes from the farthest fork points, unchecked:
    a 20-30 mm bias on box blades, 90-145 mm on tapered ones in `bench calibration`), less those kept from a
    trusted calibration (`kept_axes`, `keep_axes`)."""
    if quality.get("tip_trusted", True) is not False and method != "paper":
        return frozenset()
    kept = quality.get("kept_axes") or {}
    return frozenset(a for a in TIP_AXES if a.value not in kept)


@dataclass(frozen=True)
class Calibration:
    """`T_forklift_camera` at lift height 0, the method that found it, its quality figures and untrusted axes.

    `untrusted`: the axes that cannot be trusted (`untrusted_axes`, module docstring); None (the default)
    takes them from the method and `quality` (`untrusted_axes_of`), so every calibration `calibrate` makes, and one sent
    over the wire or journalled with its quality, states them.
    """

    T_forklift_camera: SE3
    method: str
    quality: dict[str, Any] = field(default_factory=dict)
    warnings: tuple[str, ...] = ()  # what the operator should know (an untrusted tip, ...): stderr of `calibrate`
    untrusted: InitVar[Iterable[CalibrationAxis | str] | None] = None
    untrusted_axes: frozenset[CalibrationAxis] = field(init=False)

    def __post_init__(self, untrusted: Iterable[CalibrationAxis | str] | None) -> None:
        if untrusted is None:
            axes = untrusted_axes_of(self.quality, self.method)
        else:
            axes = frozenset(map(CalibrationAxis, untrusted))
        object.__setattr__(self, "untrusted_axes", axes)

    @property
    def trusted(self) -> bool:
        """Every axis trusted."""
        return not self.untrusted_axes

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
            "untrusted_axes": sorted(a.value for a in self.untrusted_axes),
        }


@dataclass(frozen=True)
class MountTolerance:
    """How far two calibrations' trusted axes may differ for the mount to count as unmoved (m, deg).

    Two calibrations of one unmoved mount differ by the calibration's own scatter: in the simulator (30
    random mounts of tapered blades, each calibrated with the measured forks file at one place and with
    the nominal one at another, another camera's noise and depth scale) by at most 2.2 mm in z, 1.3 mm in
    y, 0.05 deg in roll and pitch and 0.11 deg in yaw. A camera knocked or re-mounted moves by more; one
    that slid along x alone on its bracket cannot be told apart (measure the blades).
    """

    translation_m: float = 0.005
    angle_deg: float = 0.3


def axis_values(T_forklift_camera: SE3) -> dict[CalibrationAxis, float]:
    """Each axis' value: x, y, z in m, roll, pitch, yaw in rad (`rpy_deg`'s angles)."""
    xyz, rpy = T_forklift_camera.to_xyz_rpy()
    values = dict(zip(_TRANSLATION, map(float, xyz), strict=True))
    values.update(zip(_ROTATION, map(float, rpy), strict=True))
    return values


def mount_moved(new: Calibration, reference: Calibration, tolerance: MountTolerance) -> list[str]:
    """One line per axis trusted in both calibrations whose values differ beyond `tolerance` (the mount
    moved between them); an empty list when they agree."""
    a, b = axis_values(new.T_forklift_camera), axis_values(reference.T_forklift_camera)
    problems = []
    for axis in CalibrationAxis:
        if axis in new.untrusted_axes or axis in reference.untrusted_axes:
            continue
        if axis in _TRANSLATION:
            off, limit, unit = (a[axis] - b[axis]) * 1e3, tolerance.translation_m * 1e3, "mm"
        else:
            off = math.degrees(math.remainder(a[axis] - b[axis], math.tau))
            limit, unit = tolerance.angle_deg, "deg"
        if abs(off) > limit:
            problems.append(f"{axis.value} differs by {off:+.1f} {unit} (tolerance {limit:g} {unit})")
    return problems


def keep_axes(new: Calibration, reference: Calibration, source: str) -> Calibration:
    """`new` with its untrusted axes taken from `reference` (trusted there), all axes then trusted.

    The rest of `new` stands as measured; `quality.kept_axes` records, per axis kept, the value used,
    the value `new` measured and `source` (where `reference` came from). Whether the mount is the same
    is the caller's question (`mount_moved`). Raises `PerceptionError` when `reference` does not trust
    an axis to keep.
    """
    axes = sorted(new.untrusted_axes)
    doubtful = [a.value for a in axes if a in reference.untrusted_axes]
    if doubtful:
        raise PerceptionError(f"the reference calibration ({source}) does not trust {', '.join(doubtful)} either")
    ours, theirs = axis_values(new.T_forklift_camera), axis_values(reference.T_forklift_camera)
    values = {**ours, **{a: theirs[a] for a in axes}}
    xyz = [values[a] for a in _TRANSLATION]
    if any(a in _ROTATION for a in axes):
        T = SE3.from_xyz_rpy(xyz, [values[a] for a in _ROTATION])
    else:
        T = SE3(new.T_forklift_camera.rotation, xyz)
    unit = {a: ("m" if a in _TRANSLATION else "deg") for a in CalibrationAxis}
    scale = {a: (1.0 if a in _TRANSLATION else math.degrees(1.0)) for a in CalibrationAxis}
    kept = {
        a.value: {
            "source": source,
            f"value_{unit[a]}": round(theirs[a] * scale[a], 6),
            f"measured_{unit[a]}": round(ours[a] * scale[a], 6),
        }
        for a in axes
    }
    quality = {**new.quality, "kept_axes": {**(new.quality.get("kept_axes") or {}), **kept}}
    return Calibration(T, new.method, quality, new.warnings, untrusted=frozenset())


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
    untrusted_axes: list[CalibrationAxis] | None = Field(
        None,
        max_length=len(CalibrationAxis),
        description="axes that cannot be trusted (x, y, z, roll, pitch, yaw); absent: as `quality` implies",
    )

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
    untrusted = None if model.untrusted_axes is None else frozenset(model.untrusted_axes)
    return Calibration(T, model.method, dict(model.quality), tuple(model.warnings), untrusted)
