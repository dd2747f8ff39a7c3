"""The ego forks' geometry: the blades as a pydantic model (metres, forklift frame), read from the forks file.

Forklift frame (ARCHITECTURE.md): origin on the floor midway between the forks, x along the forks towards
the tips, y left, z up. A fork occupies x in [tip_x - length, tip_x], z in [h, h + thickness] at lift
height h. Every dimension read from a file is checked against a plausible range (`FORK_RANGES_M`), and the
message names the field, the range and the value (`forks.yaml: length: 30 m is outside 0.5..3 m (one fork
blade, heel to tip)`). The fork tips must lie ahead of the truck and the heels near the forklift origin
(`HEEL_X_RANGE_M`), so a tip far behind the truck or a fork kilometres long never reaches the calibration.

Public API (re-exported by `perception.specs`): `ForkGeometry`, `load_forks`, `FORK_RANGES_M`,
`HEEL_X_RANGE_M`.
"""

from __future__ import annotations

from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import ConfigDict, Field, ValidationInfo, field_validator
from pydantic_core import PydanticCustomError

from palletpilot.geometry.fileio import FileModel, FileNumber, check_ranges, load_yaml_model
from palletpilot.perception.errors import PerceptionError

FORK_RANGES_M: dict[str, tuple[float, float, str]] = {
    "length": (0.5, 3.0, "one fork blade, heel to tip"),
    "width": (0.03, 0.4, "one fork, side to side"),
    "thickness": (0.01, 0.2, "blade thickness"),
    "inner_gap": (0.02, 2.0, "between the inner sides of the forks"),
    "tip_x": (0.3, 4.0, "x of the fork tips ahead of the forklift origin"),
    "taper_length": (0.0, 0.5, "over which the blade thins towards the tip; 0: no taper"),
    "tip_thickness": (0.003, 0.2, "blade thickness at the tip"),
    "heel_radius": (0.0, 0.2, "inner radius of the bend at the heel; 0: a sharp corner"),
}
"""Plausible fork dimensions (m): (lowest, highest, what it is)."""
HEEL_X_RANGE_M = (-1.0, 1.0)
"""Where the fork heels (`tip_x - length`, m) may lie: at the carriage, near the forklift origin."""


class ForkGeometry(FileModel):
    """The two forks of the ego forklift (metres, forklift frame; see the module docstring).

    The blade profile (optional; the defaults are today's box): over the last `taper_length` the
    blade thins linearly from `thickness` to `tip_thickness` (ISO 2328 blades thin over their last
    50-150 mm), the `taper_side` face sloping (`top`: the top face descends to the tip, the bottom
    stays flat; `bottom`: the bottom rises). `heel_radius` is the inner radius of the bend where the
    blade meets the shank: a fillet on the top face at the heel. `top_z` and `bottom_z` give the faces.
    A file that gives `taper_length` states the profile (`taper_length: 0`: measured, plain boxes); one
    that leaves it out leaves the profile unknown (`profile_stated`).
    """

    model_config = ConfigDict(frozen=True)

    length: FileNumber = Field(description="length of one fork blade along x (m)")
    width: FileNumber = Field(description="width of one fork along y (m)")
    thickness: FileNumber = Field(description="blade thickness along z (m), at full thickness")
    inner_gap: FileNumber = Field(description="gap between the inner sides of the two forks (m)")
    tip_x: FileNumber = Field(description="x of the fork tips in the forklift frame (m)")
    taper_length: FileNumber = Field(
        0.0,
        validate_default=True,
        description="length (m) over which the blade thins towards the tip; 0: none (stated: measured boxes)",
    )
    tip_thickness: FileNumber | None = Field(
        None, validate_default=True, description="blade thickness at the tip (m); required with a taper"
    )
    taper_side: Literal["top", "bottom"] = Field("top", description="which face slopes over the taper")
    heel_radius: FileNumber = Field(0.0, description="inner radius (m) of the bend at the heel")

    @field_validator("length", "width", "thickness", "inner_gap", "tip_x")
    @classmethod
    def _plausible(cls, value: float, info: ValidationInfo) -> float:
        check_ranges(value, info, FORK_RANGES_M)
        if info.field_name == "tip_x" and "length" in info.data:
            heel = value - info.data["length"]
            lo, hi = HEEL_X_RANGE_M
            if not lo <= heel <= hi:
                raise PydanticCustomError(
                    "out_of_range",
                    f"puts the fork heels (tip_x - length) at x = {heel:g} m, outside {lo:g}..{hi:g} m "
                    "(the heels sit at the carriage, near the forklift origin)",
                )
        return value

    @field_validator("taper_length")
    @classmethod
    def _taper_fits(cls, value: float, info: ValidationInfo) -> float:
        check_ranges(value, info, FORK_RANGES_M)
        length = info.data.get("length")
        if length is not None and value > 0.5 * length:
            raise PydanticCustomError(
                "dimensions", f"{value:g} m is more than half the blade length ({length:g} m): a taper runs at the tip"
            )
        return value

    @field_validator("tip_thickness")
    @classmethod
    def _tip_thinner(cls, value: float | None, info: ValidationInfo) -> float | None:
        taper = info.data.get("taper_length")
        if value is None:
            if taper:
                raise PydanticCustomError(
                    "missing", f"required with taper_length {taper:g} m (the blade thickness at the tip, m)"
                )
            return value
        check_ranges(value, info, FORK_RANGES_M)
        if taper is not None and taper == 0.0:
            raise PydanticCustomError(
                "dimensions", "needs taper_length > 0 (the length over which the blade thins to the tip)"
            )
        thickness = info.data.get("thickness")
        if thickness is not None and value > thickness:
            raise PydanticCustomError(
                "dimensions", f"{value:g} m is more than the blade thickness ({thickness:g} m): a taper thins the blade"
            )
        return value

    @field_validator("heel_radius")
    @classmethod
    def _heel_fits(cls, value: float, info: ValidationInfo) -> float:
        check_ranges(value, info, FORK_RANGES_M)
        length, taper = info.data.get("length"), info.data.get("taper_length")
        if length is not None and taper is not None and value + taper > length:
            raise PydanticCustomError(
                "dimensions", f"{value:g} m and the taper ({taper:g} m) are longer than the blade ({length:g} m)"
            )
        return value

    @property
    def heel_x(self) -> float:
        """x (m) of the fork heels (where the blades meet the carriage) in the forklift frame."""
        return self.tip_x - self.length

    @property
    def centre_y(self) -> float:
        """|y| (m) of each fork's centre line: the left fork is at +centre_y, the right at -centre_y."""
        return 0.5 * self.inner_gap + 0.5 * self.width

    @property
    def centres_y(self) -> tuple[float, float]:
        """y (m) of the (left, right) fork centre lines in the forklift frame."""
        return (self.centre_y, -self.centre_y)

    @property
    def outer_width(self) -> float:
        """Distance (m) between the outer sides of the two forks."""
        return self.inner_gap + 2.0 * self.width

    @property
    def tapered(self) -> bool:
        """True when the blade thins towards the tip (`taper_length` > 0 and a thinner tip)."""
        return self.taper_length > 0.0 and self.tip_thickness is not None and self.tip_thickness < self.thickness

    @property
    def profile_stated(self) -> bool:
        """True when the forks file states the blade profile (`taper_length`, 0 for plain box blades).

        False: the file leaves it at its default, so the profile is unknown (the blades are taken as boxes,
        but a tapered top face may hide from a shallow camera: `perception.calibration._tip_view_check`).
        """
        return "taper_length" in self.model_fields_set

    @property
    def taper_start_x(self) -> float:
        """x (m) where the taper starts (the tip when there is none)."""
        return self.tip_x - self.taper_length

    @property
    def tip_top_z(self) -> float:
        """Height (m) of the top face at the tip, at lift height 0 (the fork-top edge the camera sees end)."""
        if self.tapered and self.taper_side == "top":
            assert self.tip_thickness is not None
            return self.tip_thickness
        return self.thickness

    def _taper_drop(self, x: np.ndarray) -> np.ndarray:
        """How much (m) the sloping face has moved in at x: 0 up to the taper, thickness - tip_thickness at the tip."""
        if not self.tapered:
            return np.zeros_like(x)
        assert self.tip_thickness is not None
        u = np.clip((x - self.taper_start_x) / self.taper_length, 0.0, 1.0)
        return u * (self.thickness - self.tip_thickness)

    def top_z(self, x: np.ndarray | float) -> np.ndarray:
        """Height (m) of the blade's top face at x (forklift frame, lift height 0), heel fillet included."""
        x = np.asarray(x, dtype=float)
        z = self.thickness - (self._taper_drop(x) if self.taper_side == "top" else 0.0)
        r = self.heel_radius
        if r > 0.0:  # a concave quarter circle from (heel_x, thickness + r) to (heel_x + r, thickness)
            d = np.clip(self.heel_x + r - x, 0.0, r)
            z = z + r - np.sqrt(r * r - d * d)
        return np.asarray(z, dtype=float)

    def bottom_z(self, x: np.ndarray | float) -> np.ndarray:
        """Height (m) of the blade's bottom face at x (forklift frame, lift height 0)."""
        x = np.asarray(x, dtype=float)
        return self._taper_drop(x) if self.taper_side == "bottom" else np.zeros_like(x)

    def profile_doc(self) -> dict[str, float | str]:
        """The profile fields (as a forks file states them)."""
        doc: dict[str, float | str] = {"thickness": self.thickness, "taper_length": self.taper_length}
        if self.tip_thickness is not None:
            doc["tip_thickness"] = self.tip_thickness
        doc["taper_side"] = self.taper_side
        doc["heel_radius"] = self.heel_radius
        return doc

    def heel_boxes(self, lift_height: float = 0.0) -> list[tuple[np.ndarray, np.ndarray]]:
        """Boxes (lo, hi) around the heel fillets of the (left, right) forks on top of the blades (none without one)."""
        r = self.heel_radius
        if r <= 0.0:
            return []
        out = []
        for cy in self.centres_y:
            lo = np.array([self.heel_x, cy - 0.5 * self.width, lift_height + self.thickness])
            hi = np.array([self.heel_x + r, cy + 0.5 * self.width, lift_height + self.thickness + r])
            out.append((lo, hi))
        return out

    def boxes(self, lift_height: float = 0.0) -> list[tuple[np.ndarray, np.ndarray]]:
        """Axis-aligned (lo, hi) corners of the (left, right) fork blades in the forklift frame at lift height (m).

        Full thickness to the tip: a tapered blade lies inside its box (contacts stay conservative);
        the heel fillets are `heel_boxes`.
        """
        out = []
        for cy in self.centres_y:
            lo = np.array([self.heel_x, cy - 0.5 * self.width, lift_height])
            hi = np.array([self.tip_x, cy + 0.5 * self.width, lift_height + self.thickness])
            out.append((lo, hi))
        return out


def load_forks(path: str | Path) -> ForkGeometry:
    """Load a fork geometry YAML file; a bad file raises `PerceptionError` (one line per problem)."""
    return load_yaml_model(path, ForkGeometry, PerceptionError)
