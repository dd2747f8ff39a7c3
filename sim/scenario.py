"""Scenario files (YAML): which map, where the forklift starts, where the pallets really are, the
camera mount, the noise and the seed. Paths are relative to the scenario file.

```yaml
map: warehouse.yaml
forks: forks.yaml                 # fork geometry (ARCHITECTURE.md)
vehicle: forklift.yaml            # optional: default is the map's own vehicle file
seed: 7
start: charger                    # node where the forklift starts, with the node's heading
camera:
  width: 640                      # 640x480 or 848x480
  height: 480
  mount:                          # true T_forklift_camera at lift height 0
    x: -0.10                      # m, forklift frame
    y: 0.0
    z: 0.45
    tilt_deg: 20                  # downward tilt of the optical axis below horizontal
    pan_deg: 0.0                  # rotation about the forklift's z axis, positive to the left
    roll_deg: 0.0                 # rotation about the optical axis
  perturbation:                   # random mount change per run (vibration), 1-sigma
    xyz_sigma: 0.0                # m
    angle_sigma_deg: 0.0
  noise:                          # sim.camera.CameraNoise; these are its defaults (D435-like, on)
    depth_noise: true             # sigma(z) = z^2 * disparity_sigma_px / (f * baseline_m)
    invalid_rate: 0.005           # share of depth pixels with no data
    flying_pixel_rate: 0.5        # share of depth-edge pixels that mix depths
    stereo_shadow: true           # no depth where the right imager (50 mm to +x) cannot see the point
    depth_scale_error: 0.003      # every depth times 1 + s, s drawn once per camera in +-this
    label_noise: false            # random dilation / erosion of class boundaries ...
    label_noise_px: 2             # ... by up to this many pixels
noise:
  localization_xy_sigma: 0.0      # m
  localization_yaw_sigma_deg: 0.0
  slip_sigma: 0.0                 # relative, per control step
pallets:                          # placed at roadmap pallet nodes plus the misplacement
  - {node: rack_b3, dx: 0.10, dy: -0.15, dyaw_deg: 5, loaded: true}   # dx, dy in the node's frame (m)
  - {x: 14.0, y: 2.0, yaw_deg: 90, loaded: false}                      # free on the floor, no node
  - node: floor_b2                # optional, per pallet (defaults: a new EUR pallet)
    type: industrial              # eur, industrial, industrial_long, half, plastic or a pallet type file
    loaded: true
    overhang_m: 0.04              # the load's front this far past the entry face (0..0.1 m; loaded only)
    film: true                    # load and top deck wrapped in stretch film (class cargo; loaded only)
    tolerance_m: 0.005            # boards and blocks off their drawing by up to this (0..0.01 m) ...
    tolerance_seed: 3             # ... drawn with this seed (which also picks the chipped corners)
    damage: {chipped_blocks: 2, chip_m: 0.03, missing_bottom_boards: [1]}   # entry-row blocks; boards 0..2
clutter:
  - {kind: person, x: 12.0, y: 3.0, yaw_deg: 0}
  - {kind: person, x: 6.0, y: 18.0, path: [[6.0, 2.0]], speed: 1.2, repeat: true}  # walks the aisle
  - {kind: box, x: 8.0, y: -2.0, yaw_deg: 20, size: [0.6, 0.4, 0.5]}
```
"""

from __future__ import annotations

import itertools
import math
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, model_validator

from palletpilot.geometry import SE3, PalletpilotError, wrap_angle
from palletpilot.geometry.fileio import FileModel, load_yaml_model
from palletpilot.sim.camera import CameraNoise, camera_mount_pose
from palletpilot.sim.faults import FaultSpec
from palletpilot.sim.world import PalletCondition


class SimError(PalletpilotError):
    """A bad scenario or an impossible simulator request; the message names the file or object."""


MAX_COORD_M = 10_000.0
"""World coordinates (m) in a scenario lie within +-10 km, as map coordinates do."""
MAX_MISPLACEMENT_M = 2.0
"""A pallet placed at a node is at most this far off it (m); further, place it free with x and y."""
Coordinate = Annotated[float, Field(ge=-MAX_COORD_M, le=MAX_COORD_M)]
BoxSide = Annotated[float, Field(gt=0.0, le=20.0)]


class _Strict(FileModel):
    """A file schema (unknown keys, NaN and infinities are errors)."""


class CameraMount(_Strict):
    """Camera pose on the fork carriage at lift height 0, in forklift-frame terms."""

    x: float = Field(-0.10, ge=-3.0, le=3.0)
    y: float = Field(0.0, ge=-2.0, le=2.0)
    z: float = Field(0.45, gt=0.0, le=3.0)
    tilt_deg: float = Field(20.0, ge=0.0, le=89.0)
    pan_deg: float = Field(0.0, ge=-90.0, le=90.0)
    roll_deg: float = Field(0.0, ge=-180.0, le=180.0)

    def T_forklift_camera(self) -> SE3:
        """The mount as `T_forklift_camera` (optical frame: x right, y down, z out of the lens).

        Built as the camera looking along the forklift's x axis, then panned about z (left positive),
        tilted down about the camera's right-pointing axis, and rolled about its optical axis
        (`sim.camera.camera_mount_pose`).
        """
        return camera_mount_pose(
            (self.x, self.y, self.z),
            math.radians(self.tilt_deg),
            math.radians(self.pan_deg),
            math.radians(self.roll_deg),
        )


class MountPerturbation(_Strict):
    """1-sigma random change of the mount per run."""

    xyz_sigma: float = Field(0.0, ge=0.0, le=0.1)
    angle_sigma_deg: float = Field(0.0, ge=0.0, le=10.0)


class CameraSpec(_Strict):
    """The simulated RGB-D camera."""

    width: Literal[640, 848] = 640
    height: Literal[480] = 480
    mount: CameraMount = CameraMount()
    perturbation: MountPerturbation = MountPerturbation()
    noise: CameraNoise = CameraNoise()


class NoiseSpec(_Strict):
    """Localization and actuation noise (camera noise is `camera.noise`); off by default."""

    localization_xy_sigma: float = Field(0.0, ge=0.0, le=1.0)
    localization_yaw_sigma_deg: float = Field(0.0, ge=0.0, le=30.0)
    slip_sigma: float = Field(0.0, ge=0.0, le=0.5)


class PalletDamage(_Strict):
    """Wear and damage of one pallet (`sim.world.PalletCondition`): chipped entry-row blocks, missing
    bottom boards."""

    chipped_blocks: int = Field(0, ge=0, le=3, description="entry-row blocks missing a chunk of their face")
    chip_m: float = Field(0.03, ge=0.005, le=0.06, description="size of each chunk (m)")
    missing_bottom_boards: list[Literal[0, 1, 2]] = Field(
        default_factory=list,
        max_length=3,
        description="bottom boards gone (runners right to left, perimeter front to back)",
    )


class PalletPlacement(_Strict):
    """A pallet at a roadmap pallet node, misplaced by (dx, dy, dyaw) in the node's frame; or standing
    free on the floor at (x, y, yaw_deg): its pallet frame (the entry face's centre) in the world.

    The pallet itself (all optional, defaults: a new EUR pallet): `type` (a built-in name of
    `perception.specs.PALLET_NAMES` or a pallet type file relative to the scenario), `tolerance_m`
    (boards and blocks off the drawing by up to this, 0..0.01 m, drawn with `tolerance_seed`, which
    also picks the chipped corners), `damage` (`PalletDamage`), and for a loaded pallet `overhang_m`
    (the load's front past the entry face, 0..0.1 m) and `film` (load and top deck wrapped in stretch
    film).
    """

    node: str | None = None
    dx: float = Field(0.0, ge=-MAX_MISPLACEMENT_M, le=MAX_MISPLACEMENT_M)
    dy: float = Field(0.0, ge=-MAX_MISPLACEMENT_M, le=MAX_MISPLACEMENT_M)
    dyaw_deg: float = Field(0.0, ge=-180.0, le=180.0)
    x: float | None = Field(None, ge=-MAX_COORD_M, le=MAX_COORD_M)
    y: float | None = Field(None, ge=-MAX_COORD_M, le=MAX_COORD_M)
    yaw_deg: float = Field(0.0, ge=-360.0, le=360.0)
    loaded: bool = False
    type: str = Field("eur", min_length=1, max_length=4096)
    tolerance_m: float = Field(0.0, ge=0.0, le=0.01)
    tolerance_seed: int = Field(0, ge=0, le=2**64 - 1)
    damage: PalletDamage = PalletDamage()
    overhang_m: float = Field(0.0, ge=0.0, le=0.1)
    film: bool = False

    @model_validator(mode="after")
    def _one_place(self) -> PalletPlacement:
        free = self.x is not None or self.y is not None
        if (self.node is None) == (not free):
            raise ValueError("give either node (with dx, dy, dyaw_deg) or x and y (with yaw_deg)")
        if free and (self.x is None or self.y is None):
            raise ValueError("a free-standing pallet needs both x and y")
        if free and {"dx", "dy", "dyaw_deg"} & self.model_fields_set:
            raise ValueError("dx, dy, dyaw_deg: only with node")
        for name in ("overhang_m", "film"):
            if getattr(self, name) and not self.loaded:
                raise ValueError(f"{name}: only with a load (loaded: true)")
        return self

    def condition(self) -> PalletCondition:
        """The pallet's build, damage and load as the simulator renders them."""
        return PalletCondition(
            tolerance_m=self.tolerance_m,
            seed=self.tolerance_seed,
            chipped_blocks=self.damage.chipped_blocks,
            chip_m=self.damage.chip_m,
            missing_bottom_boards=tuple(self.damage.missing_bottom_boards),
            overhang_m=self.overhang_m,
            film=self.film,
        )


class ClutterSpec(_Strict):
    """Something else on the floor: a person or a box (other-object). A person with a `path` walks from
    (x, y) through its points (world, m) at `speed` (m/s), facing the way it walks, then stands at the
    end; with `repeat` it walks back and forth for ever."""

    kind: Literal["person", "box"]
    x: float = Field(ge=-MAX_COORD_M, le=MAX_COORD_M)
    y: float = Field(ge=-MAX_COORD_M, le=MAX_COORD_M)
    yaw_deg: float = Field(0.0, ge=-360.0, le=360.0)
    size: tuple[BoxSide, BoxSide, BoxSide] = (0.6, 0.4, 0.5)
    path: list[tuple[Coordinate, Coordinate]] = Field(default_factory=list, max_length=1000)
    speed: float = Field(1.0, gt=0.0, le=3.0, description="walking speed (m/s)")
    repeat: bool = False

    @model_validator(mode="after")
    def _walkers_are_people(self) -> ClutterSpec:
        if self.path and self.kind != "person":
            raise ValueError("path: only people walk")
        return self

    def pose_at(self, t: float) -> tuple[float, float, float]:
        """(x, y, yaw in rad) in the world at simulated time `t` (s)."""
        points = [(self.x, self.y), *self.path]
        if len(points) < 2:
            return self.x, self.y, math.radians(self.yaw_deg)
        lengths = [math.dist(a, b) for a, b in itertools.pairwise(points)]
        total = sum(lengths)
        travelled = self.speed * max(t, 0.0)
        backwards = False
        if total <= 0.0:
            return self.x, self.y, math.radians(self.yaw_deg)
        if self.repeat:
            travelled %= 2.0 * total
            if travelled > total:
                travelled, backwards = 2.0 * total - travelled, True
        else:
            travelled = min(travelled, total)
        for (a, b), length in zip(itertools.pairwise(points), lengths, strict=True):
            if travelled <= length or (a, b) == (points[-2], points[-1]):
                f = 0.0 if length == 0.0 else min(travelled / length, 1.0)
                yaw = float(wrap_angle(math.atan2(b[1] - a[1], b[0] - a[0]) + (math.pi if backwards else 0.0)))
                return a[0] + f * (b[0] - a[0]), a[1] + f * (b[1] - a[1]), yaw
            travelled -= length
        return points[-1][0], points[-1][1], math.radians(self.yaw_deg)


class Scenario(_Strict):
    """A whole scenario file; paths are resolved against the file's folder by `load_scenario`."""

    map: str
    forks: str = "forks.yaml"
    vehicle: str | None = None
    seed: int = Field(0, ge=0, le=2**64 - 1)
    start: str
    camera: CameraSpec = CameraSpec()
    noise: NoiseSpec = NoiseSpec()
    battery_level: float = Field(0.8, ge=0.0, le=1.0)  # state of charge at the start (with a battery model)
    pallets: list[PalletPlacement] = Field(default_factory=list, max_length=10_000)
    clutter: list[ClutterSpec] = Field(default_factory=list, max_length=10_000)
    faults: list[FaultSpec] = Field(default_factory=list, max_length=1000)  # injected faults (sim.faults)
    folder: Path = Field(Path("."), exclude=True)
    source: str = Field("scenario", exclude=True)
    """How messages name the scenario: its file, or `default warehouse of MISSION`."""

    def path(self, name: str) -> Path:
        """A file named in the scenario, resolved against the scenario's folder."""
        return self.folder / name


def load_scenario(path: str | Path) -> Scenario:
    """Load a scenario file; every problem raises `SimError` naming the file and the field."""
    scenario = load_yaml_model(path, Scenario, SimError)
    scenario.folder = Path(path).parent
    scenario.source = str(path)
    return scenario
