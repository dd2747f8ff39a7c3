"""What a calibrated camera sees of a pallet at the Pickup standpoint: a check of the camera mount.

The camera rides on the fork carriage, and the Pickup raises the forks to the pallet before it looks,
so the pallet's place in the image depends only on the mount and on how far ahead of the fork tips
the entry face is, not on the pallet's height. `pickup_view` projects, for every distance in a range,

- the entry face (its four corners, the pallet misplaced sideways by up to `lateral_m`): the pallet
  pose needs the whole face in the image;
- the bottom `load_view_m` of a load standing on the deck at the face: the segmentation can only tell
  an empty pallet from a loaded one when the space just above the deck is in the image.

A steep mount keeps the fork tips in view (the calibration needs them) but may lose the far pallet's
top edge and its load above the image. Frames: forklift frame at lift height 0 (ARCHITECTURE.md),
camera optical frame; lengths in m.
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from palletpilot.geometry import SE3
from palletpilot.perception.specs import ForkGeometry, PalletType

PICKUP_AHEAD_M = (1.2, 3.0)
"""Entry face distances ahead of the fork tips (m) from which the Pickup estimates the pallet (issue 5)."""
STEP_M = 0.05
"""Distance step (m) of the check."""


@dataclass(frozen=True)
class PickupView:
    """Distances (m, entry face ahead of the fork tips) at which the camera sees what the Pickup needs.

    `face_m` / `load_m`: (nearest, farthest) distance in the checked range with the whole entry face /
    the load zone in the image, or None when it is never in view. `ahead_m` is the Pickup's range.
    """

    ahead_m: tuple[float, float]
    face_m: tuple[float, float] | None
    load_m: tuple[float, float] | None

    @staticmethod
    def _covers(span: tuple[float, float] | None, ahead: tuple[float, float]) -> bool:
        return span is not None and span[0] <= ahead[0] + 1e-9 and span[1] >= ahead[1] - 1e-9

    @property
    def face_ok(self) -> bool:
        """The whole entry face is in the image over the Pickup's whole range."""
        return self._covers(self.face_m, self.ahead_m)

    @property
    def load_ok(self) -> bool:
        """The load zone above the deck is in the image over the Pickup's whole range."""
        return self._covers(self.load_m, self.ahead_m)

    def to_json(self) -> dict:
        """`{"ahead_m", "entry_face_in_view_m", "load_in_view_m", "entry_face_ok", "load_ok"}`."""
        return {
            "ahead_m": list(self.ahead_m),
            "entry_face_in_view_m": None if self.face_m is None else list(self.face_m),
            "load_in_view_m": None if self.load_m is None else list(self.load_m),
            "entry_face_ok": self.face_ok,
            "load_ok": self.load_ok,
        }

    def problems(self) -> list[str]:
        """One line per thing the Pickup will miss with this mount (empty when the mount is fine)."""
        lo, hi = self.ahead_m
        out = []
        for name, span, ok in (("the entry face", self.face_m, self.face_ok), ("a load", self.load_m, self.load_ok)):
            if ok:
                continue
            seen = "never" if span is None else f"only {span[0]:.2f}-{span[1]:.2f} m ahead of the fork tips"
            out.append(f"{name} is in the image {seen}; the Pickup looks from {lo:.2f}-{hi:.2f} m")
        return out


def pickup_view(
    T_forklift_camera: SE3,
    K: np.ndarray,
    image_size: tuple[int, int],
    forks: ForkGeometry,
    pallet: PalletType,
    ahead_m: tuple[float, float] = PICKUP_AHEAD_M,
    lateral_m: float = 0.35,
    load_view_m: float = 0.10,
    fork_clearance_m: float = 0.025,
    margin_px: float = 2.0,
) -> PickupView:
    """Where a pallet at the Pickup standpoint is in view of a camera (see the module docstring).

    `T_forklift_camera` at lift height 0 (`Calibration.T_forklift_camera`), `K` and `image_size`
    (width, height in px) of the colour/depth image. The forks stand `fork_clearance_m` above the
    pallet's underside (the Pickup's `fork_clearance`). A point counts as in view `margin_px` inside
    the image border. Distances are checked every `STEP_M` over `ahead_m`.
    """
    lo, hi = float(ahead_m[0]), float(ahead_m[1])
    distances = np.round(np.arange(lo, hi + 0.5 * STEP_M, STEP_M), 6)
    bottom = -fork_clearance_m  # pallet underside, relative to the fork bottoms at lift height 0
    top = bottom + pallet.height
    half = 0.5 * pallet.width
    T_camera_forklift = T_forklift_camera.inv()
    w, h = image_size

    def in_view(points: np.ndarray) -> bool:
        p = T_camera_forklift.apply(points)
        if np.any(p[:, 2] <= 0.0):
            return False
        uv = (K @ (p / p[:, 2:3]).T).T[:, :2]
        return bool(
            np.all((uv[:, 0] >= margin_px) & (uv[:, 0] <= w - 1 - margin_px))
            and np.all((uv[:, 1] >= margin_px) & (uv[:, 1] <= h - 1 - margin_px))
        )

    face, load = [], []
    for d in distances:
        x = forks.tip_x + d
        corners = [(x, s * (half + lateral_m), z) for s in (-1.0, 1.0) for z in (bottom, top)]
        face.append(in_view(np.array(corners)))
        load.append(in_view(np.array([(x + 0.05, 0.0, top + load_view_m)])))  # front of a load, mid face

    def span(seen: list[bool]) -> tuple[float, float] | None:
        idx = np.flatnonzero(seen)
        return None if idx.size == 0 else (float(distances[idx[0]]), float(distances[idx[-1]]))

    return PickupView((lo, hi), span(face), span(load))
