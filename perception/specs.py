"""Known geometry perception relies on: the ego forks (`perception.fork_geometry`, re-exported here) and the
pallet type.

Both are pydantic models in metres. Frames (ARCHITECTURE.md):

- forklift frame: origin on the floor midway between the forks, x along the forks towards the tips,
  y left, z up. A fork occupies x in [tip_x - length, tip_x], z in [h, h + thickness] at lift height h.
- pallet frame: origin at the centre of the entry face on the pallet's underside, x into the pallet along
  the pockets, y left, z up. The pallet occupies x in [0, length], y in [-width/2, width/2], z in [0, height].

Every dimension read from a file is checked against a plausible range (`FORK_RANGES_M`,
`PALLET_RANGES_M`), and the message names the field, the range and the value
(`forks.yaml: length: 30 m is outside 0.5..3 m (one fork blade, heel to tip)`); numbers must be
numbers (a string or a boolean is refused), finite, and unknown keys are errors (`FileModel`). The
fork tips must lie ahead of the truck and the heels near the forklift origin (`HEEL_X_RANGE_M`), so a
tip far behind the truck or a fork kilometres long never reaches the calibration.

A pallet type may declare a family (`family: block_2pocket`) and `ranges:` its entry side varies in
around its own fields (`perception.pallet_family`); the estimator then measures the face within them.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path
from typing import Literal

import numpy as np
from pydantic import ConfigDict, Field, ValidationInfo, field_validator, model_validator
from pydantic_core import PydanticCustomError

from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.fileio import FileModel, FileNumber, check_ranges, load_yaml_model
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.fork_geometry import FORK_RANGES_M as FORK_RANGES_M
from palletpilot.perception.fork_geometry import HEEL_X_RANGE_M as HEEL_X_RANGE_M
from palletpilot.perception.fork_geometry import ForkGeometry as ForkGeometry
from palletpilot.perception.fork_geometry import load_forks as load_forks
from palletpilot.perception.pallet_family import FamilyRanges, PalletFamily

_MM = 5e-4  # tolerance (m) when checking that dimensions add up

PALLET_RANGES_M: dict[str, tuple[float, float, str]] = {
    "length": (0.3, 3.0, "along the pockets"),
    "width": (0.3, 3.0, "the entry face"),
    "height": (0.05, 0.5, "floor to deck top"),
    "top_board_thickness": (0.005, 0.1, "deck boards"),
    "top_board_widths": (0.02, 0.5, "each deck board"),
    "cross_board_thickness": (0.005, 0.1, "cross boards"),
    "block_height": (0.02, 0.3, "blocks"),
    "block_length": (0.03, 1.0, "blocks along x"),
    "block_columns": (0.02, 1.0, "each block column"),
    "bottom_board_thickness": (0.005, 0.1, "bottom boards"),
    "balance_margin": (0.0, 0.5, "the load's centre of mass inside the fork tips"),
}
"""Plausible pallet dimensions (m): (lowest, highest, what it is); tuples: each element."""

MIN_FORK_ENGAGEMENT = 2.0 / 3.0
"""The share of a pallet's length (along the pockets) the forks must carry by default: warehouse rules
commonly ask for two thirds of the load's depth (`PalletType.min_fork_engagement`)."""
ENGAGEMENT_SHARE_RANGE = (0.5, 1.0)
"""`min_fork_engagement` lies within this: below half the load's depth its middle is not over the forks."""
BALANCE_MARGIN_M = 0.05
"""m: by default the load's centre of mass (the pallet's middle) lies at least this far inside the fork
tips (`PalletType.balance_margin`)."""


PartKind = Literal["top_board", "cross_board", "block", "bottom_board"]
DeckKind = Literal["boards", "across", "closed"]
"""The top deck: `boards` along x spread over the width (EUR), `across` boards along y spread over the
length (a pallet entered on the side its deck boards run along), `closed` one solid deck (plastic)."""
BottomKind = Literal["runners", "perimeter", "none"]
"""Under the blocks: `runners` along x under each block column (pockets open to the floor, EUR),
`perimeter` along y under each block row (a board across the entry closes the pockets' bottom),
`none` (legs standing on the floor; `bottom_board_thickness` must then be 0)."""


@dataclass(frozen=True)
class PalletPart:
    """One solid part of a pallet: an axis-aligned box [lo, hi] (m) in the pallet frame."""

    name: str
    kind: PartKind
    lo: np.ndarray
    hi: np.ndarray

    @property
    def size(self) -> np.ndarray:
        """Edge lengths (m) along x, y, z."""
        return self.hi - self.lo


class PalletType(FileModel):
    """A block pallet entered on its `width` side, built of boards and blocks (metres, pallet frame).

    The file describes the pallet as the forks see it: `width` is the entry face, `length` runs along
    the pockets (a 1200 x 1000 pallet entered on its 1200 side has width 1.2, length 1.0).
    From the floor up: bottom boards (`bottom_boards`: along x under the block columns, along y under
    the block rows, or none: legs), blocks (3 rows along x by the block columns along y), cross boards
    (along y, on top of each block row) and the top deck (`deck`: boards along x, boards along y, or
    closed). The pockets lie between the block columns, from the floor (or the top of a perimeter
    bottom board) up to the underside of the cross boards. `material` only changes how the simulator
    renders it. Every field is optional; the defaults are the EUR/EPAL pallet.
    """

    model_config = ConfigDict(frozen=True, validate_default=True)  # the defaults meet the checks too

    # Fields that are checked against others come after them (`height` last): a validator sees the
    # fields above it (`ValidationInfo.data`), so each problem names its own field.
    name: str = Field("EUR/EPAL", min_length=1, max_length=64)
    length: FileNumber = Field(1.2, description="along x, the fork direction (m)")
    width: FileNumber = Field(0.8, description="along y, the entry face (m)")
    material: Literal["wood", "plastic"] = Field("wood", description="how the simulator renders it")
    deck: DeckKind = Field("boards", description="top deck: boards along x, boards along y (across) or closed")
    top_board_thickness: FileNumber = 0.022
    top_board_widths: tuple[FileNumber, ...] = Field(
        (0.145, 0.100, 0.145, 0.100, 0.145),
        min_length=1,
        max_length=20,
        description="deck boards, spread evenly over the width (deck: boards) or the length (deck: across)",
    )
    cross_board_thickness: FileNumber = Field(0.022, description="boards along y on the blocks")
    block_height: FileNumber = 0.078
    block_length: FileNumber = Field(0.145, description="block (and cross board) size along x")
    block_columns: tuple[FileNumber, FileNumber, FileNumber] = Field(
        (0.100, 0.145, 0.100), description="block widths along y, right to left; pockets between them"
    )
    bottom_boards: BottomKind = Field("runners", description="runners (along x), perimeter (along y) or none (legs)")
    bottom_board_thickness: FileNumber = Field(
        0.022, description="bottom boards (runners: under each block column; perimeter: under each block row)"
    )
    height: FileNumber = Field(0.144, description="total height (m); must equal the sum of the layers")
    family: PalletFamily | None = Field(
        None, description="a family whose entry side varies within `ranges` (perception.pallet_family); none: exact"
    )
    ranges: FamilyRanges | None = Field(None, description="the family's ranges (m) around the fields above")
    min_fork_engagement: FileNumber = Field(
        MIN_FORK_ENGAGEMENT,
        description="the share of `length` the forks must carry (0.5..1; default 2/3, a common warehouse rule)",
    )
    balance_margin: FileNumber = Field(
        BALANCE_MARGIN_M,
        description="m (0..0.5): the load's centre of mass (the pallet's middle) this far inside the fork tips",
    )

    @field_validator(*(k for k in PALLET_RANGES_M if k != "bottom_board_thickness"))
    @classmethod
    def _plausible(cls, value: float | tuple[float, ...], info: ValidationInfo) -> float | tuple[float, ...]:
        check_ranges(value, info, PALLET_RANGES_M)
        return value

    @field_validator("bottom_board_thickness")
    @classmethod
    def _bottom_fits(cls, value: float, info: ValidationInfo) -> float:
        if info.data.get("bottom_boards") == "none":
            if value != 0.0:
                raise PydanticCustomError(
                    "dimensions", f"{value:g} m, but bottom_boards is none (legs on the floor): give 0"
                )
            return value
        check_ranges(value, info, PALLET_RANGES_M)
        return value

    @field_validator("top_board_widths")
    @classmethod
    def _deck_fits(cls, widths: tuple[float, ...], info: ValidationInfo) -> tuple[float, ...]:
        across = info.data.get("deck") == "across"
        span = info.data.get("length" if across else "width")
        if span is not None and sum(widths) > span + _MM:
            raise PydanticCustomError(
                "dimensions",
                f"the deck boards are {sum(widths):g} m wide in all, more than the pallet's "
                f"{'length' if across else 'width'} ({span:g} m)",
            )
        return widths

    @field_validator("block_length")
    @classmethod
    def _rows_fit(cls, block_length: float, info: ValidationInfo) -> float:
        length = info.data.get("length")
        if length is not None and 3 * block_length >= length:
            raise PydanticCustomError(
                "dimensions", f"three block rows of {block_length:g} m do not fit in the pallet length ({length:g} m)"
            )
        return block_length

    @field_validator("block_columns")
    @classmethod
    def _pockets_fit(cls, columns: tuple[float, ...], info: ValidationInfo) -> tuple[float, ...]:
        width = info.data.get("width")
        if width is not None and sum(columns) >= width:
            raise PydanticCustomError(
                "dimensions",
                f"the block columns are {sum(columns):g} m wide in all: no room for pockets in {width:g} m",
            )
        return columns

    @field_validator("height")
    @classmethod
    def _layers_add_up(cls, height: float, info: ValidationInfo) -> float:
        names = ("bottom_board_thickness", "block_height", "cross_board_thickness", "top_board_thickness")
        if all(n in info.data for n in names):
            layers = sum(info.data[n] for n in names)
            if abs(layers - height) > _MM:
                raise PydanticCustomError(
                    "dimensions",
                    f"layers add up to {layers * 1e3:.1f} mm (bottom + block + cross + top) but height is "
                    f"{height * 1e3:.1f} mm",
                )
        return height

    @field_validator("family")
    @classmethod
    def _family_fits(cls, family: str | None, info: ValidationInfo) -> str | None:
        if family is not None and info.data.get("bottom_boards") == "perimeter":
            raise PydanticCustomError(
                "family", f"{family}: its pockets are open to the floor; bottom_boards must be runners or none"
            )
        return family

    @field_validator("ranges")
    @classmethod
    def _ranges_hold_the_type(cls, ranges: FamilyRanges | None, info: ValidationInfo) -> FamilyRanges | None:
        if "family" not in info.data:
            return ranges  # the family's own problem is reported
        family = info.data["family"]
        if (ranges is None) != (family is None):
            raise PydanticCustomError(
                "family",
                "needed with a family (the dimensions that vary, each [lowest, highest] m)"
                if ranges is None
                else "only with a family (family: block_2pocket); an exact type has none",
            )
        d = info.data
        if ranges is None or not all(k in d for k in ("width", "block_columns", "bottom_board_thickness")):
            return ranges
        pocket = 0.5 * (d["width"] - sum(d["block_columns"]))
        problems = ranges.nominal_problems(
            {
                "width": (d["width"],),
                "block_columns": tuple(d["block_columns"]),
                "pocket_width": (pocket,),
                "pocket_height": (d["bottom_board_thickness"] + d["block_height"],),
            }
        )
        if problems:
            raise PydanticCustomError("dimensions", "; ".join(p.removeprefix("ranges.") for p in problems))
        return ranges

    @field_validator("min_fork_engagement")
    @classmethod
    def _engagement_share(cls, share: float) -> float:
        lo, hi = ENGAGEMENT_SHARE_RANGE
        if not lo <= share <= hi:
            raise PydanticCustomError(
                "out_of_range",
                f"{share:g} is outside {lo:g}..{hi:g} (the share of the pallet's length the forks carry)",
            )
        return share

    def required_engagement(self) -> tuple[float, str]:
        """How deep (m) the fork tips must reach into the pallet from its entry face, and which rule sets it:
        `min_fork_engagement` of its `length`, or the balance (the load's centre of mass, the pallet's middle,
        `balance_margin` inside the tips), whichever asks more."""
        share = self.min_fork_engagement * self.length
        balance = 0.5 * self.length + self.balance_margin
        if balance > share:
            middle, margin = 0.5e3 * self.length, self.balance_margin * 1e3
            return balance, f"the load's centre of mass at {middle:.0f} mm plus the {margin:.0f} mm balance margin"
        return share, f"{self.min_fork_engagement:.2f} of its {self.length * 1e3:.0f} mm depth (min_fork_engagement)"

    @model_validator(mode="after")
    def _closed_deck_has_no_boards(self) -> PalletType:
        if self.deck == "closed" and "top_board_widths" in self.model_fields_set:
            raise ValueError("top_board_widths: a closed deck (deck: closed) has no boards; leave it out")
        return self

    @classmethod
    def eur(cls) -> PalletType:
        """The EUR/EPAL 1 pallet: 1200 x 800 x 144 mm, entered on the 800 mm side.

        EPAL parts: 5 top boards 22 mm (145/100/145/100/145 mm wide), 3 cross boards 145 x 22 mm,
        9 blocks 78 mm high (145 mm along x; 100/145/100 mm along y), 3 bottom boards 22 mm:
        22 + 78 + 22 + 22 = 144 mm. Pockets 227.5 mm wide, 100 mm high, open to the floor.
        """
        return cls()

    # -- derived ------------------------------------------------------------------------
    def bounds(self, name: str) -> tuple[float, float]:
        """(lowest, highest) (m) of `width`, `block_columns` (each), `pocket_width` or `pocket_height`:
        the family's range, else the type's own value (for the columns, the narrowest and widest)."""
        own = {
            "width": (self.width, self.width),
            "block_columns": (min(self.block_columns), max(self.block_columns)),
            "pocket_width": (self.pocket_width, self.pocket_width),
            "pocket_height": (self.pocket_height, self.pocket_height),
        }[name]
        value = None if self.ranges is None else getattr(self.ranges, name)
        return own if value is None else (float(value[0]), float(value[1]))

    @property
    def pocket_width(self) -> float:
        """Width (m) of each of the two pockets along y."""
        return 0.5 * (self.width - sum(self.block_columns))

    @property
    def pocket_height(self) -> float:
        """Height (m) of the pockets: floor to the underside of the cross boards."""
        return self.bottom_board_thickness + self.block_height

    @property
    def pocket_floor(self) -> float:
        """Height (m) where the pocket's opening starts: the perimeter board's top, else the floor (0)."""
        return self.bottom_board_thickness if self.bottom_boards == "perimeter" else 0.0

    @property
    def face_deck_bounds_y(self) -> list[tuple[float, float]]:
        """(y_lo, y_hi) (m) of the top deck layer on the entry face: the boards, or the whole width."""
        if self.deck != "boards":
            return [(-0.5 * self.width, 0.5 * self.width)]
        return [(float(p.lo[1]), float(p.hi[1])) for p in self.parts() if p.kind == "top_board"]

    @property
    def pocket_centres_y(self) -> tuple[float, float]:
        """y (m) of the (left, right) pocket centres in the pallet frame."""
        c = 0.5 * self.block_columns[1] + 0.5 * self.pocket_width
        return (c, -c)

    @property
    def block_rows_x(self) -> tuple[float, float, float]:
        """x (m) of the front edge of each block row (entry side, middle, back)."""
        return (0.0, 0.5 * (self.length - self.block_length), self.length - self.block_length)

    def column_bounds_y(self) -> list[tuple[float, float]]:
        """(y_lo, y_hi) (m) of the three block columns, right to left."""
        w = self.width
        right, middle, left = self.block_columns
        return [(-0.5 * w, -0.5 * w + right), (-0.5 * middle, 0.5 * middle), (0.5 * w - left, 0.5 * w)]

    def parts(self) -> list[PalletPart]:
        """Every board and block as an axis-aligned box in the pallet frame."""
        parts: list[PalletPart] = []
        z_block = self.bottom_board_thickness
        z_cross = z_block + self.block_height
        z_top = z_cross + self.cross_board_thickness
        columns = self.column_bounds_y()
        w2 = 0.5 * self.width
        if self.bottom_boards == "runners":
            for j, (y0, y1) in enumerate(columns):
                parts.append(
                    PalletPart(
                        f"bottom_board_{j}",
                        "bottom_board",
                        np.array([0.0, y0, 0.0]),
                        np.array([self.length, y1, z_block]),
                    )
                )
        elif self.bottom_boards == "perimeter":
            for i, x0 in enumerate(self.block_rows_x):
                parts.append(
                    PalletPart(
                        f"bottom_board_{i}",
                        "bottom_board",
                        np.array([x0, -w2, 0.0]),
                        np.array([x0 + self.block_length, w2, z_block]),
                    )
                )
        for i, x0 in enumerate(self.block_rows_x):
            for j, (y0, y1) in enumerate(columns):
                parts.append(
                    PalletPart(
                        f"block_{i}{j}",
                        "block",
                        np.array([x0, y0, z_block]),
                        np.array([x0 + self.block_length, y1, z_cross]),
                    )
                )
            parts.append(
                PalletPart(
                    f"cross_board_{i}",
                    "cross_board",
                    np.array([x0, -0.5 * self.width, z_cross]),
                    np.array([x0 + self.block_length, 0.5 * self.width, z_top]),
                )
            )
        if self.deck == "closed":
            lo, hi = np.array([0.0, -w2, z_top]), np.array([self.length, w2, self.height])
            return [*parts, PalletPart("top_deck", "top_board", lo, hi)]
        n = len(self.top_board_widths)
        if self.deck == "across":  # boards along y, spread over the length from the entry face
            gap = (self.length - sum(self.top_board_widths)) / (n - 1) if n > 1 else 0.0
            x = 0.0
            for k, bw in enumerate(self.top_board_widths):
                lo, hi = np.array([x, -w2, z_top]), np.array([x + bw, w2, self.height])
                parts.append(PalletPart(f"top_board_{k}", "top_board", lo, hi))
                x += bw + gap
            return parts
        gap = (self.width - sum(self.top_board_widths)) / (n - 1) if n > 1 else 0.0
        y = -0.5 * self.width if n > 1 else -0.5 * self.top_board_widths[0]
        for k, bw in enumerate(self.top_board_widths):
            parts.append(
                PalletPart(
                    f"top_board_{k}",
                    "top_board",
                    np.array([0.0, y, z_top]),
                    np.array([self.length, y + bw, self.height]),
                )
            )
            y += bw + gap
        return parts


def load_pallet_type(path: str | Path) -> PalletType:
    """Load a pallet type YAML file (fields of `PalletType`, missing ones default to EUR/EPAL)."""
    return load_yaml_model(path, PalletType, PerceptionError)


BUILTIN_PALLETS: dict[str, dict[str, object]] = {
    "eur": {},
    "industrial": {
        "name": "industrial 1200x1000 (1000 side)",
        "length": 1.2,
        "width": 1.0,
        "top_board_widths": (0.145, 0.100, 0.100, 0.145, 0.100, 0.100, 0.145),
        "block_columns": (0.145, 0.145, 0.145),
    },
    "industrial_long": {
        "name": "industrial 1200x1000 (1200 side)",
        "length": 1.0,
        "width": 1.2,
        "deck": "across",
        "top_board_widths": (0.145, 0.100, 0.100, 0.100, 0.145),
        "block_columns": (0.145, 0.145, 0.145),
        "bottom_boards": "perimeter",
    },
    "half": {
        "name": "half 800x600",
        "length": 0.8,
        "width": 0.6,
        "top_board_widths": (0.100, 0.100, 0.100),
        "block_length": 0.100,
        "block_columns": (0.080, 0.100, 0.080),
    },
    "plastic": {
        "name": "plastic 1200x800 (closed deck, 3 runners)",
        "material": "plastic",
        "deck": "closed",
        "top_board_thickness": 0.02,
        "cross_board_thickness": 0.02,
        "block_height": 0.1,
        "block_length": 0.16,
        "block_columns": (0.12, 0.16, 0.12),
        "bottom_board_thickness": 0.02,
        "height": 0.16,
    },
    "block_2pocket_800": {
        "name": "two-pocket block pallet, 800 mm face",
        "block_columns": (0.100, 0.120, 0.100),
        "family": "block_2pocket",
        "ranges": {
            "width": (0.795, 0.805),
            "block_columns": (0.080, 0.160),
            "pocket_width": (0.200, 0.280),
            "pocket_height": (0.095, 0.130),
        },
    },
}
"""The built-in pallet types by name (fields that differ from EUR/EPAL). `missions/pallet_*.yaml` hold
the same types as files: `industrial` is a 1200 x 1000 block pallet entered on its 1000 side,
`industrial_long` the same pallet entered on its 1200 side (deck boards and bottom boards then run
across the entry), `half` an 800 x 600 pallet entered on its 600 side, `plastic` a 1200 x 800
plastic pallet with a closed deck on nine legs and three runners. `block_2pocket_800` is a family
(`perception.pallet_family`): any two-pocket block pallet entered on an 800 mm face (ISO 6780 and EPAL:
800 mm, built to +-3..5 mm), block columns 80-160 mm (half pallets' 80 mm to the chemical-industry
pallets' 155 mm middle support; EPAL 100 / 145 / 100), pockets 200-280 mm wide (EPAL 227.5 mm, one-way
pallets about 256 mm) and 95-130 mm high (ISO 6780: fork openings at least 95 mm high where free, EPAL
100 mm); the nominal EPAL-like geometry (100 / 120 / 100 mm columns) only seeds the face fit."""
PALLET_ALIASES = {"epal": "eur", "eur/epal": "eur"}
PALLET_NAMES = (*BUILTIN_PALLETS, *PALLET_ALIASES)
"""Names of the built-in pallet types, any case."""


def builtin_pallet(name: str) -> PalletType | None:
    """The built-in pallet type `name` (any case, `PALLET_NAMES`), or None."""
    key = PALLET_ALIASES.get(name.lower(), name.lower())
    fields = BUILTIN_PALLETS.get(key)
    return None if fields is None else PalletType.model_validate(fields)


def pallet_type(name: str) -> PalletType:
    """A pallet type by name (`PALLET_NAMES`) or from a YAML file path."""
    builtin = builtin_pallet(name)
    if builtin is not None:
        return builtin
    if not Path(name).exists() and not Path(name).suffix:
        eur = ", ".join(("eur", *PALLET_ALIASES))
        others = ", ".join(k for k in BUILTIN_PALLETS if k != "eur")
        raise PerceptionError(
            f"{name}: not a known pallet type ({eur}) nor another built-in ({others}) nor a pallet type file"
        )
    return load_pallet_type(name)


def pallet_type_in(name: str, folder: Path) -> PalletType:
    """A pallet type named in a file (a mission, a scenario): a built-in name (`PALLET_NAMES`) or a pallet
    type file relative to `folder` (that file's folder). Raises `PerceptionError`, one line per problem."""
    builtin = builtin_pallet(name)
    if builtin is not None:
        return builtin
    where = folder / name
    return load_pallet_type(where) if where.suffix else pallet_type(name)


ENTRY_GAP_M = 0.05
"""At a pallet node the pallet's entry face stands this far ahead of the fork heels (forklift x = 0),
so the fork tips reach `tip_x - ENTRY_GAP_M` into the pallet."""


def pallet_pose_at_node(T_world_node: SE2, height: float) -> SE3:
    """`T_world_pallet` of a pallet placed exactly at a roadmap pallet node (node heading, load height m)."""
    return T_world_node.to_se3(height) @ SE3.from_translation(ENTRY_GAP_M, 0.0, 0.0)


def node_pose_for_pallet(T_world_pallet: SE3) -> SE2:
    """The pallet node (forklift pose with the forks fully in) that serves a pallet at `T_world_pallet`."""
    return (T_world_pallet @ SE3.from_translation(-ENTRY_GAP_M, 0.0, 0.0)).to_se2()
