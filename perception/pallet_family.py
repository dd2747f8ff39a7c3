"""Pallet families: a pallet type whose entry side may vary within ranges (issue 37, point 2).

A pallet type (`perception.specs.PalletType`) describes one exact pallet. Real warehouses hold many
block pallets that differ from the EPAL by centimetres (one-way pallets with pressed-chip blocks of
about 91 / 108 / 91 mm and 256 mm pockets, chemical-industry pallets with wider middle blocks, ...).
A type may therefore declare a family and ranges around its nominal geometry:

```yaml
family: block_2pocket           # three block columns across the entry face, two pockets, open to the floor
ranges:                         # each [lowest, highest] in metres; what is left out is exact
  width: [0.795, 0.805]         # the entry face
  block_columns: [0.08, 0.16]   # each block column
  pocket_width: [0.20, 0.28]    # each pocket
  pocket_height: [0.095, 0.13]  # floor to the underside of the cross boards
```

For a family type the estimator measures the pocket openings: every block-column edge is searched over
its range (not `max_edge_offset_m` around one nominal edge), the lateral centre comes from the measured
pockets, the pocket height is measured from the face's bottom edge, and a face outside the ranges is
refused (`pockets_inconsistent`). The nominal geometry (the type's own fields) must lie inside the
ranges; it seeds the face fit.

Frames: pallet frame (ARCHITECTURE.md), lateral positions along y, heights above the underside.

Public API: `PalletFamily`, `FAMILIES`, `FamilyRanges`, `RANGE_LIMITS_M`.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import ConfigDict, Field, ValidationInfo, field_validator
from pydantic_core import PydanticCustomError

from palletpilot.geometry.fileio import FileModel

PalletFamily = Literal["block_2pocket"]
"""Families a pallet type may declare: `block_2pocket`, a two-pocket block pallet (three block columns,
pockets open to the floor between them). Stringer pallets are not modelled (their three stringers run
the whole length; the block model's side walls would be wrong)."""
FAMILIES: dict[str, str] = {"block_2pocket": "two-pocket block pallet: three block columns, two pockets"}
"""Each family and what it is."""

_Number = Annotated[float, Field(strict=True)]
_Range = tuple[_Number, _Number]

RANGE_LIMITS_M: dict[str, tuple[float, float, str]] = {
    "width": (0.3, 3.0, "the entry face"),
    "block_columns": (0.02, 1.0, "each block column"),
    "pocket_width": (0.05, 1.5, "each pocket"),
    "pocket_height": (0.03, 0.3, "floor to the underside of the cross boards"),
}
"""Plausible bounds (m) of each range: (lowest, highest, what it is)."""


class FamilyRanges(FileModel):
    """The ranges of a family's varying dimensions (m, each `[lowest, highest]`); left out: exact."""

    model_config = ConfigDict(frozen=True)

    width: _Range | None = Field(None, description="the entry face (m)")
    block_columns: _Range | None = Field(None, description="each of the three block columns (m)")
    pocket_width: _Range | None = Field(None, description="each of the two pockets (m)")
    pocket_height: _Range | None = Field(None, description="floor to the underside of the cross boards (m)")

    @field_validator("width", "block_columns", "pocket_width", "pocket_height")
    @classmethod
    def _ordered(cls, value: tuple[float, float] | None, info: ValidationInfo) -> tuple[float, float] | None:
        if value is None:
            return value
        assert info.field_name is not None
        lo, hi, what = RANGE_LIMITS_M[info.field_name]
        for v in value:
            if not lo <= v <= hi:
                raise PydanticCustomError("out_of_range", f"{v:g} m is outside {lo:g}..{hi:g} m ({what})")
        if value[0] > value[1]:
            raise PydanticCustomError(
                "dimensions", f"[{value[0]:g}, {value[1]:g}]: the lowest is above the highest (give [lowest, highest])"
            )
        return value

    def bounds(self, name: str, nominal: float) -> tuple[float, float]:
        """(lowest, highest) (m) of dimension `name`: its range, or the nominal value where it has none."""
        value = getattr(self, name)
        return (nominal, nominal) if value is None else (float(value[0]), float(value[1]))

    def nominal_problems(self, nominal: dict[str, tuple[float, ...]]) -> list[str]:
        """Where the nominal values (`nominal[name]`: the type's own, one or more each) lie outside the ranges:
        one line per dimension, `ranges.NAME: ...`."""
        problems = []
        for name, values in nominal.items():
            value = getattr(self, name)
            if value is None:
                continue
            lo, hi = value
            off = [v for v in values if not lo - 1e-9 <= v <= hi + 1e-9]
            if off:
                shown = ", ".join(f"{v:g}" for v in off)
                problems.append(
                    f"ranges.{name}: the type's own {name.replace('_', ' ')} ({shown} m) lies outside "
                    f"[{lo:g}, {hi:g}] m (the nominal geometry must be one of the family)"
                )
        return problems
