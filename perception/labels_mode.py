"""Which source selects perception's pixels: the typed vocabulary of `--labels` (no heavy imports, so the
command line can use it).

Public API: `LabelsMode`, `DEFAULT_LABELS_MODE`, `MODES` (what each mode needs and what it is robust to),
`SIM_TRUTH` (the simulator's own labels fed as the model's: `run --labels truth`, for comparison).
The labels themselves are made in `perception.geometry_labels`.
"""

from __future__ import annotations

import enum


class LabelsMode(enum.StrEnum):
    """Which source selects perception's pixels (the pallet's, the floor's, the forks')."""

    MODEL = "model"
    GEOMETRY = "geometry"
    FUSED = "fused"


DEFAULT_LABELS_MODE = LabelsMode.FUSED
"""The mode of every command (`run`, `robot`, `agv`, `calibrate`, `estimate-pallet`, the benchmarks)."""

MODES: dict[LabelsMode, tuple[str, str]] = {
    LabelsMode.MODEL: (
        "the segmentation model's labels (RGB, or labels in the frame)",
        "what the model was trained on (the simulator's looks); on real photos it labels a third of a pallet",
    ),
    LabelsMode.GEOMETRY: (
        "depth, the calibration, where the pallet should stand (node, envelope, floor or beam height)",
        "any look (colour, texture, light): no model is run; a person or a box at the pallet's height in "
        "the envelope is depth like any other (the entry check and the scanners guard them)",
    ),
    LabelsMode.FUSED: (
        "as geometry, plus RGB for the model's hints",
        "as geometry, and a model giving noise changes nothing; the model adds persons and loads it sees "
        "as coherent blobs, and its pallet pixels where the geometry sees none",
    ),
}
"""What each mode needs and what it is robust to."""


SIM_TRUTH = "truth"
"""`--labels truth` of simulated runs: the simulator's exact labels in the `model` mode (for comparison)."""
