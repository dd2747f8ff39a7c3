"""Segmentation training and evaluation data from the simulator: varied, seeded pre-pallet frames.

`render_frame(index, seed)` builds a random scenario on the example warehouse (`missions/warehouse.yaml`)
and renders one RGB-D frame bundle with ground-truth labels; `generate_dataset(out_dir, n, seed)`
saves `n` of them as `frame_00000.npz`, ... (`perception.frames.save_bundle`). Frame `i` depends
only on `(seed, i)`, so a dataset is reproducible and can be generated in parallel or in pieces.

What varies per frame (all SI units, poses in the world frame unless said otherwise):

- the target: one of the map's pallet nodes (floor_a1..floor_b3, rack_a1..rack_b3), its pallet
  misplaced by +-0.35 m lateral, -0.15..+0.25 m longitudinal and +-15 deg yaw, empty or loaded;
  the other pallet nodes hold a pallet (empty or loaded, smaller misplacements) half of the time;
- where the forklift stands: near the target's pre-pallet node (`<id>_pre`), -1.4..+0.1 m along
  the node's heading, +-0.25 m sideways, +-6 deg yaw; one frame in eight from farther and more askew
  (-3.0..+0.3 m, +-0.8 m, +-25 deg);
- the fork height: at a rack pallet the pallet's height plus 0..60 mm (one in seven frames anywhere
  between the floor and that height), at a floor pallet 0..60 mm;
- the camera mount (`T_forklift_camera` at lift height 0): x -0.15..-0.05 m, y +-0.05 m, height
  0.3..0.6 m, tilt 15..40 deg down, pan +-3 deg, roll +-2 deg; with `mounts="pickup"` only mounts
  that `palletpilot calibrate` finds fit for the Pickup (`perception.view.pickup_view`: a pallet's
  entry face and a load on it in view 1.2-3.0 m ahead of the fork tips), redrawn until one is;
- the camera: D435-like 640x480 with depth noise, dropouts and flying pixels, RGB sensor noise
  1..4 levels, the renderer's per-frame lighting variation (light direction, ambient and diffuse
  intensity +-20 %, colour tint, ceiling-lamp phase); labels are exact (no label noise);
- 0..4 clutter items (people and boxes of random size) beside or beyond the target, never on it.

Simulator-only truth keys (`T_forklift_camera_true`, `T_forklift_pallet_true`) stay in the bundles.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from functools import lru_cache
from pathlib import Path

import numpy as np

from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.frames import FrameBundle, save_bundle
from palletpilot.perception.specs import ForkGeometry, PalletType, load_forks
from palletpilot.perception.view import pickup_view
from palletpilot.roadmap import NodeType, load_map
from palletpilot.sim.camera import d435_color_intrinsics
from palletpilot.sim.scenario import CameraMount, Scenario
from palletpilot.sim.simulator import Simulator

MISSIONS_DIR = bundled_path("missions")
"""Folder of the example map, fork and vehicle files."""
MAP_FILE = "warehouse.yaml"

MOUNTS = ("all", "pickup")
"""Camera mount sets: every mount of the ranges above, or only those fit for the Pickup."""
MAX_LATERAL_M = 0.35
MAX_YAW_DEG = 15.0
_FAR_SHARE = 1.0 / 8.0
_LOW_FORKS_AT_RACK_SHARE = 1.0 / 7.0


@lru_cache(maxsize=4)
def _forks(missions_dir: Path) -> ForkGeometry:
    """The fork geometry of the example files (read once)."""
    return load_forks(missions_dir / "forks.yaml")


@lru_cache(maxsize=4)
def _map_facts(missions_dir: Path) -> tuple[tuple[tuple[str, float, SE2], ...], float]:
    """((pallet id, load height m, pre-pallet pose), ...) sorted by id, and the fork tip x (m)."""
    roadmap = load_map(missions_dir / MAP_FILE)
    ids = {n.id for n in roadmap.nodes()}
    nodes = sorted(
        (n.id, float(n.height), roadmap.node(f"{n.id}_pre").pose)
        for n in roadmap.nodes()
        if n.type is NodeType.PALLET and f"{n.id}_pre" in ids
    )
    return tuple(nodes), float(_forks(missions_dir).tip_x)


def pallet_nodes(missions_dir: Path = MISSIONS_DIR) -> list[tuple[str, float]]:
    """(node id, load height in m) of the example map's pallet nodes that have a pre-pallet node, sorted by id."""
    return [(node, height) for node, height, _ in _map_facts(Path(missions_dir))[0]]


def _mount(rng: np.random.Generator, missions_dir: Path, mounts: str) -> dict[str, float]:
    """A random camera mount; with `mounts="pickup"` redrawn until `pickup_view` finds no problem."""
    if mounts not in MOUNTS:
        raise ValueError(f"mounts must be one of {', '.join(MOUNTS)}, got {mounts!r}")
    while True:
        mount = {
            "x": float(rng.uniform(-0.15, -0.05)),
            "y": float(rng.uniform(-0.05, 0.05)),
            "z": float(rng.uniform(0.3, 0.6)),
            "tilt_deg": float(rng.uniform(15.0, 40.0)),
            "pan_deg": float(rng.uniform(-3.0, 3.0)),
            "roll_deg": float(rng.uniform(-2.0, 2.0)),
        }
        if mounts == "all" or _suits_pickup(mount, Path(missions_dir)):
            return mount


def _suits_pickup(mount: dict[str, float], missions_dir: Path) -> bool:
    """Does `palletpilot calibrate` find this mount fit for the Pickup (entry face and load in view)?"""
    T_forklift_camera = CameraMount.model_validate(mount).T_forklift_camera()
    view = pickup_view(
        T_forklift_camera, d435_color_intrinsics(640, 480), (640, 480), _forks(missions_dir), PalletType.eur()
    )
    return not view.problems()


def random_scenario(
    rng: np.random.Generator, missions_dir: Path = MISSIONS_DIR, mounts: str = "all"
) -> tuple[Scenario, SE2, float]:
    """A random scenario (see the module docstring) drawn from `rng`; `mounts`: "all" or "pickup".

    Returns (scenario, `T_world_forklift` standing pose near the target's pre-pallet node, fork
    height in m). The scenario starts at the pre-pallet node; `render_frame` moves the forklift.
    """
    facts, tip_x = _map_facts(Path(missions_dir))
    target, height, T_world_pre = facts[int(rng.integers(len(facts)))]
    nodes = [(node, h) for node, h, _ in facts]
    pallets = [
        {
            "node": target,
            "dx": float(rng.uniform(-0.15, 0.25)),
            "dy": float(rng.uniform(-MAX_LATERAL_M, MAX_LATERAL_M)),
            "dyaw_deg": float(rng.uniform(-MAX_YAW_DEG, MAX_YAW_DEG)),
            "loaded": bool(rng.random() < 0.5),
        }
    ]
    for node, _ in nodes:
        if node != target and rng.random() < 0.5:
            pallets.append(
                {
                    "node": node,
                    "dx": float(rng.uniform(-0.1, 0.2)),
                    "dy": float(rng.uniform(-0.2, 0.2)),
                    "dyaw_deg": float(rng.uniform(-8.0, 8.0)),
                    "loaded": bool(rng.random() < 0.5),
                }
            )
    mount = _mount(rng, missions_dir, mounts)
    noise = {
        "depth_noise": True,
        "invalid_rate": float(rng.uniform(0.0, 0.01)),
        "flying_pixel_rate": float(rng.uniform(0.2, 0.6)),
        "label_noise": False,
        "rgb_sigma": float(rng.uniform(1.0, 4.0)),
        "lighting_variation": True,
    }
    pose = _standing_pose(rng, T_world_pre)
    clutter = _clutter(rng, pose, tip_x)
    if height > 0.0 and rng.random() >= _LOW_FORKS_AT_RACK_SHARE:
        fork_height = height + rng.uniform(0.0, 0.06)
    elif height > 0.0:
        fork_height = rng.uniform(0.0, height)
    else:
        fork_height = rng.uniform(0.0, 0.06)
    sc = Scenario.model_validate(
        {
            "map": MAP_FILE,
            "seed": int(rng.integers(2**31)),
            "start": f"{target}_pre",
            "camera": {"width": 640, "height": 480, "mount": mount, "noise": noise},
            "pallets": pallets,
            "clutter": clutter,
        }
    )
    sc.folder = Path(missions_dir)
    return sc, pose, float(fork_height)


def _standing_pose(rng: np.random.Generator, T_world_pre: SE2) -> SE2:
    """A forklift pose near the pre-pallet node (offsets in the node's frame)."""
    if rng.random() < _FAR_SHARE:
        dx, dy, dyaw = rng.uniform(-3.0, 0.3), rng.uniform(-0.8, 0.8), rng.uniform(-25.0, 25.0)
    else:
        dx, dy, dyaw = rng.uniform(-1.4, 0.1), rng.uniform(-0.25, 0.25), rng.uniform(-6.0, 6.0)
    return T_world_pre @ SE2(float(dx), float(dy), math.radians(float(dyaw)))


def _clutter(rng: np.random.Generator, T_world_forklift: SE2, tip_x: float) -> list[dict]:
    """0..4 people and boxes in view, beside the approach lane or beyond the target pallet."""
    items = []
    for _ in range(int(rng.integers(0, 5))):
        for _attempt in range(20):
            x, y = rng.uniform(tip_x + 0.3, tip_x + 6.0), rng.uniform(-3.0, 3.0)
            on_lane = abs(y) < 1.5 and x < tip_x + 3.6  # approach lane and the target pallet (or its rack)
            if not on_lane:
                break
        else:
            continue
        wx, wy = T_world_forklift.apply([x, y])
        yaw = float(rng.uniform(-180.0, 180.0))
        if rng.random() < 0.5:
            items.append({"kind": "person", "x": float(wx), "y": float(wy), "yaw_deg": yaw})
        else:
            size = [float(rng.uniform(0.3, 1.0)), float(rng.uniform(0.3, 0.8)), float(rng.uniform(0.3, 1.2))]
            items.append({"kind": "box", "x": float(wx), "y": float(wy), "yaw_deg": yaw, "size": size})
    return items


def render_frame(index: int, seed: int, missions_dir: Path = MISSIONS_DIR, mounts: str = "all") -> FrameBundle:
    """Frame `index` of the dataset with `seed`: a random scenario rendered with the `Simulator` (640x480).

    Deterministic for `(seed, index, mounts)`. The bundle carries RGB, depth (m), exact labels, the
    fork height (m) and the simulator's truth keys.
    """
    rng = np.random.default_rng([int(seed), int(index)])
    sc, pose, fork_height = random_scenario(rng, missions_dir, mounts)
    sim = Simulator(sc)
    sim.forklift.state.pose = pose  # teleport: a dataset frame needs no driving
    sim.forklift.state.fork_height = fork_height
    sim.forklift.fork_height_cmd = fork_height
    return sim.grab()


def iter_frames(
    n: int, seed: int, start: int = 0, missions_dir: Path = MISSIONS_DIR, mounts: str = "all"
) -> Iterator[FrameBundle]:
    """Frames `start .. start + n - 1` of the dataset with `seed` (see `render_frame`)."""
    for i in range(start, start + n):
        yield render_frame(i, seed, missions_dir, mounts)


def generate_dataset(
    out_dir: str | Path, n: int, seed: int, start: int = 0, missions_dir: Path = MISSIONS_DIR, mounts: str = "all"
) -> list[Path]:
    """Render frames `start .. start + n - 1` for `seed` and save them as `out_dir/frame_%05d.npz`.

    Returns the written paths. Existing files of the same name are overwritten.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    for i, bundle in enumerate(iter_frames(n, seed, start, missions_dir, mounts), start=start):
        paths.append(save_bundle(out / f"frame_{i:05d}.npz", bundle))
    return paths
