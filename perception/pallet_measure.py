"""A pallet type measured from RGB-D frames of a pallet (`palletpilot pallet measure`, issue 37).

The frames show one pallet standing on the floor the truck stands on, its entry face towards the
camera (frame bundles, as `estimate-pallet` takes them; labels as the `labels` mode needs them).
Each frame is estimated with a family pallet type (`perception.pallet_family`; the command's default
`block_2pocket_800`): the estimator measures the six block-column edges within the family's ranges
(pallet y, m), and the pockets' top above the floor (forklift z = 0 from the calibration): the pocket
height. The frames are fused by the median of each
edge and height; their scatter (sample standard deviation, m) is reported with them.

The written type is exact (no family): face width, block columns (right, middle, left) and pocket
height (`block_height` = pocket height less the bottom boards) measured; everything the entry face does
not show (length, deck boards, board thicknesses, block length) is the family's nominal geometry. The
middle column is centred on the face in a pallet type, so the pockets' lateral layout comes from the
column widths.

Public API: `PalletMeasurement`, `measure_pallet`, `pallet_type_yaml`, `MeasureError`.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle
from palletpilot.perception.labels_mode import LabelsMode
from palletpilot.perception.pallet import DEFAULT_CONFIG, PalletEstimatorConfig, PalletNotFound, estimate_pallet
from palletpilot.perception.specs import PalletType


class MeasureError(PerceptionError):
    """The frames do not give a pallet type: no frame found the pallet, or it does not stand on the floor."""


@dataclass
class PalletMeasurement:
    """A pallet's entry side measured from frames (m), fused by the median, with the frames' scatter."""

    family: PalletType
    edges_y_m: tuple[float, ...]  # six block-column edges, right to left, pallet y
    pocket_height_m: float
    scatter_m: dict[str, float]  # sample standard deviation over the frames per dimension (0 with one frame)
    frames_used: int
    frames_refused: dict[str, str] = field(default_factory=dict)  # frame name -> why

    @property
    def face_width_m(self) -> float:
        """The entry face's width (m)."""
        return self.edges_y_m[5] - self.edges_y_m[0]

    @property
    def block_columns_m(self) -> tuple[float, float, float]:
        """Block column widths (m), right to left."""
        e = self.edges_y_m
        return (e[1] - e[0], e[3] - e[2], e[5] - e[4])

    @property
    def pocket_widths_m(self) -> tuple[float, float]:
        """(left, right) pocket widths (m)."""
        e = self.edges_y_m
        return (e[4] - e[3], e[2] - e[1])

    def pallet_type(self, name: str) -> PalletType:
        """The measured exact pallet type (validated): the family's nominal with the measured entry side."""
        fields = self.family.model_dump(exclude={"family", "ranges", "name"})
        fields.update(
            name=name,
            width=round(self.face_width_m, 4),
            block_columns=tuple(round(c, 4) for c in self.block_columns_m),
            block_height=round(self.pocket_height_m - self.family.bottom_board_thickness, 4),
        )
        fields["height"] = round(
            fields["bottom_board_thickness"]
            + fields["block_height"]
            + fields["cross_board_thickness"]
            + fields["top_board_thickness"],
            4,
        )
        if self.family.deck == "closed":
            fields.pop("top_board_widths")
        return PalletType.model_validate(fields)

    def to_json(self) -> dict[str, Any]:
        """Millimetres: face width, block columns, pocket widths and height, and their scatter."""
        return {
            "family": self.family.name,
            "frames_used": self.frames_used,
            "frames_refused": self.frames_refused,
            "face_width_mm": round(1e3 * self.face_width_m, 1),
            "block_columns_mm": [round(1e3 * c, 1) for c in self.block_columns_m],
            "pocket_widths_mm": [round(1e3 * w, 1) for w in self.pocket_widths_m],
            "pocket_height_mm": round(1e3 * self.pocket_height_m, 1),
            "column_edges_y_mm": [round(1e3 * e, 1) for e in self.edges_y_m],
            "scatter_mm": {k: round(1e3 * v, 2) for k, v in self.scatter_m.items()},
        }


def measure_pallet(
    frames: Sequence[FrameBundle],
    calibration: Calibration,
    family: PalletType,
    names: Sequence[str] | None = None,
    config: PalletEstimatorConfig = DEFAULT_CONFIG,
    labels: LabelsMode = LabelsMode.MODEL,
) -> PalletMeasurement:
    """Measure the pallet in `frames` (the pallet on the truck's floor) within `family` (a pallet type with
    a family); `labels` selects the pallet's pixels as `estimate_pallet` does (`model`: the frames' labels;
    `geometry`: depth alone; `fused`: both); `names` name the frames in messages. Raises `MeasureError`
    where no frame gives the pallet on the floor (naming each frame's reason) and `PerceptionError` for a
    type without a family."""
    if family.family is None:
        raise PerceptionError(f"{family.name}: not a family pallet type (no family: and ranges:); give one")
    names = list(names) if names is not None else [f"frame {i}" for i in range(len(frames))]
    edges, heights, refused = [], [], {}
    for name, frame in zip(names, frames, strict=True):
        try:
            est = estimate_pallet(frame, calibration, family, config=config, labels=labels)
        except PalletNotFound as exc:
            refused[name] = exc.detail
            continue
        height = est.extras.get("pocket_height_m")
        if height is None:
            top = est.extras.get("pocket_top_z_m")
            refused[name] = f"the pallet does not stand on the floor (its pocket tops at z = {top} m)"
            continue
        edges.append(est.extras["column_edges_y_m"])
        heights.append(float(height))
    if not edges:
        why = "; ".join(f"{n}: {r}" for n, r in refused.items())
        raise MeasureError(f"no frame showed the pallet on the floor within the {family.name} family: {why}")
    e = np.array(edges, dtype=float)
    h = np.array(heights)
    med = np.median(e, axis=0)

    def spread(values: np.ndarray) -> float:
        return float(np.std(values, ddof=1)) if len(values) > 1 else 0.0

    scatter = {
        "face_width": spread(e[:, 5] - e[:, 0]),
        "block_column_right": spread(e[:, 1] - e[:, 0]),
        "block_column_middle": spread(e[:, 3] - e[:, 2]),
        "block_column_left": spread(e[:, 5] - e[:, 4]),
        "pocket_left": spread(e[:, 4] - e[:, 3]),
        "pocket_right": spread(e[:, 2] - e[:, 1]),
        "pocket_height": spread(h),
    }
    return PalletMeasurement(
        family=family,
        edges_y_m=tuple(float(v) for v in med),
        pocket_height_m=float(np.median(h)),
        scatter_m=scatter,
        frames_used=len(edges),
        frames_refused=refused,
    )


def pallet_type_yaml(pallet: PalletType, measurement: PalletMeasurement, source: str) -> str:
    """A pallet type file (YAML) for `pallet`, with a header naming the frames and the measured figures."""
    m = measurement.to_json()
    sc = m["scatter_mm"]
    lines = [
        "# Pallet type (perception.specs.PalletType; README 'Pallet type'), metres.",
        f"# Measured by `palletpilot pallet measure` from {source}",
        f"# ({m['frames_used']} frames used, {len(m['frames_refused'])} refused) within the {m['family']} family.",
        f"# Face {m['face_width_mm']} mm (scatter {sc['face_width']} mm); block columns "
        f"{' / '.join(str(c) for c in m['block_columns_mm'])} mm (scatter {sc['block_column_right']} / "
        f"{sc['block_column_middle']} / {sc['block_column_left']} mm);",
        f"# pockets {m['pocket_widths_mm'][0]} / {m['pocket_widths_mm'][1]} mm wide (left / right; scatter "
        f"{sc['pocket_left']} / {sc['pocket_right']} mm), {m['pocket_height_mm']} mm high (scatter "
        f"{sc['pocket_height']} mm).",
        "# Not seen from the entry face, so the family's nominal: length, deck, board thicknesses, block length.",
    ]
    for key, value in pallet.model_dump(exclude={"family", "ranges"}).items():
        if key == "top_board_widths" and pallet.deck == "closed":
            continue
        if isinstance(value, tuple):
            value = "[" + ", ".join(f"{v:g}" for v in value) + "]"
        elif isinstance(value, float):
            value = f"{value:g}"
        elif isinstance(value, str) and key == "name":
            value = '"' + value.replace("\\", "\\\\").replace('"', '\\"') + '"'
        lines.append(f"{key}: {value}")
    return "\n".join(lines) + "\n"
