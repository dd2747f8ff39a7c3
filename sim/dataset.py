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
  entry face and a load on it in view 1.2-3.0 m ahead of the fork tips), redrawn until one is; with
  `mounts="wide"` (views a forklift camera rarely gives but real photos do: level near the floor, or
  from high up) height 0.08..1.6 m, tilt 0..60 deg, pan +-10 deg, roll +-5 deg;
- the camera: D435-like 640x480 with depth noise, dropouts and flying pixels, RGB sensor noise
  1..4 levels, the renderer's per-frame lighting variation (light direction, ambient and diffuse
  intensity +-20 %, colour tint, ceiling-lamp phase); labels are exact (no label noise);
- 0..4 clutter items (people and boxes of random size) beside or beyond the target, never on it.

With `randomise=True` (`palletpilot segment dataset --randomise`; domain randomisation, for a model
that has to work on a real camera) each frame also draws, from its own generator seeded with
`(seed, index, 1)`, so that the poses, mounts and clutter drawn above stay those of the plain frame:

- pallet types: every pallet is `eur`, `plastic` or `half` (`industrial` and `industrial_long`
  1200 x 1000 pallets too on floor nodes, where they fit); loaded pallets are wrapped in stretch
  film one time in three, and their load may overhang the entry face by up to 0.06 m;
- colours (the per-triangle `albedo` of the built meshes, scaled per material so that the tone
  differences between boards, uprights and beams stay): the floor (concrete from dark to pale,
  painted epoxy grey / green / ochre), walls, rack uprights and beams (any of the common rack
  colours), every pallet on its own (wood from pale to dark and weathered grey, painted blue or red,
  plastic black / grey / blue), every load on its own (cartons brown or white, coloured bins, white
  sacks, film from clear to black), boxes, people's clothes and the forks;
- light: direction (elevation 20..85 deg, any azimuth), ambient and direct intensity, colour
  temperature (warm sodium to cool LED), ceiling-lamp modulation, exposure (x0.5..1.7, saturating)
  and RGB sensor noise 1..8 levels.

With `novel=True` as well (`--randomise novel`) the looks come from settings that the randomisation
above never draws, for measuring a model on looks it was not trained on: every material (floor,
walls, racks, pallets, loads, boxes, clothes) any hue at saturation 0.3..1 with any of the renderer's
textures; light from low (elevation 8..20 deg), exposure x0.3..0.5 or x1.7..2.5 and a strong colour
cast. Its own generator is seeded with `(seed, index, 2)`.

With `realism=True` as well (it implies `randomise`) each frame also gets what real pallets and real
cameras show and the renders lack (`sim.dataset_realism`, its own generator seeded with
`(seed, index, 3)`, so the frame's scene, colours and light stay those of the randomised frame): every
board and block its own tone, replaced and weathered boards, pressed-chip blocks, dirt towards the
floor; in the image wear blotches on the pallet, glare, auto-exposure with a soft shoulder and lens
distortion (labels and depth remapped with the RGB, K zoomed, the coefficients as the bundle's
`dist`).

Photometric effects that need no re-render (blur, motion blur, colour noise, gamma, JPEG, vignetting)
are drawn per training step by `perception.training_batches.augment`.

Scenarios the simulator refuses (a bigger pallet or a clutter item overlapping something) are drawn
again from the same generator, so frame `i` still depends only on `(seed, i)` (and `randomise`).

Simulator-only truth keys (`T_forklift_camera_true`, `T_forklift_pallet_true`) stay in the bundles.
"""

from __future__ import annotations

import math
from collections.abc import Iterator
from functools import lru_cache
from pathlib import Path
from typing import Any

import numpy as np

from palletpilot.geometry import SE2
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.frames import FrameBundle, SemanticClass, save_bundle
from palletpilot.perception.specs import ForkGeometry, PalletType, load_forks
from palletpilot.perception.view import pickup_view
from palletpilot.roadmap import NodeType, load_map
from palletpilot.sim.camera import Lighting, RaycastRenderer, d435_color_intrinsics
from palletpilot.sim.dataset_realism import camera_effects, wear_pallet
from palletpilot.sim.scenario import CameraMount, Scenario, SimError
from palletpilot.sim.simulator import Simulator
from palletpilot.sim.world import LabeledMesh, Texture

MISSIONS_DIR = bundled_path("missions")
"""Folder of the example map, fork and vehicle files."""
MAP_FILE = "warehouse.yaml"

MOUNTS = ("all", "pickup", "wide")
"""Camera mount sets: every mount of the ranges above, or only those fit for the Pickup."""
MAX_LATERAL_M = 0.35
MAX_YAW_DEG = 15.0
_FAR_SHARE = 1.0 / 8.0
_LOW_FORKS_AT_RACK_SHARE = 1.0 / 7.0
_MAX_DRAWS = 50
"""Scenario draws per frame before giving up (the simulator refuses overlapping placements)."""


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
    """A random camera mount; with `mounts="pickup"` redrawn until `pickup_view` finds no problem, with
    `mounts="wide"` from wider ranges (the same number of draws, so the rest of the frame is unchanged)."""
    if mounts not in MOUNTS:
        raise ValueError(f"mounts must be one of {', '.join(MOUNTS)}, got {mounts!r}")
    wide = mounts == "wide"
    while True:
        mount = {
            "x": float(rng.uniform(-0.15, -0.05)),
            "y": float(rng.uniform(-0.05, 0.05)),
            "z": float(rng.uniform(0.08, 1.6) if wide else rng.uniform(0.3, 0.6)),
            "tilt_deg": float(rng.uniform(0.0, 60.0) if wide else rng.uniform(15.0, 40.0)),
            "pan_deg": float(rng.uniform(-10.0, 10.0) if wide else rng.uniform(-3.0, 3.0)),
            "roll_deg": float(rng.uniform(-5.0, 5.0) if wide else rng.uniform(-2.0, 2.0)),
        }
        if mounts != "pickup" or _suits_pickup(mount, Path(missions_dir)):
            return mount


def _suits_pickup(mount: dict[str, float], missions_dir: Path) -> bool:
    """Does `palletpilot calibrate` find this mount fit for the Pickup (entry face and load in view)?"""
    T_forklift_camera = CameraMount.model_validate(mount).T_forklift_camera()
    view = pickup_view(
        T_forklift_camera, d435_color_intrinsics(640, 480), (640, 480), _forks(missions_dir), PalletType.eur()
    )
    return not view.problems()


def random_scenario(
    rng: np.random.Generator,
    missions_dir: Path = MISSIONS_DIR,
    mounts: str = "all",
    style: np.random.Generator | None = None,
) -> tuple[Scenario, SE2, float]:
    """A random scenario (see the module docstring) drawn from `rng`; `mounts`: "all" or "pickup".

    With `style` (domain randomisation), pallet types, film, overhang and the RGB noise level are
    drawn from it (the geometry drawn from `rng` is the same). Returns (scenario, `T_world_forklift`
    standing pose near the target's pre-pallet node, fork height in m). The scenario starts at the
    pre-pallet node; `render_frame` moves the forklift.
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
    if style is not None:
        heights = dict(nodes)
        for pallet in pallets:
            _style_pallet(pallet, heights[str(pallet["node"])] > 0.0, style)
        noise["rgb_sigma"] = float(style.uniform(1.0, 8.0))
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


FLOOR_TYPES = {"eur": 0.4, "plastic": 0.2, "half": 0.1, "industrial": 0.2, "industrial_long": 0.1}
"""Pallet types and their shares at floor nodes with `randomise`."""
RACK_TYPES = {"eur": 0.6, "plastic": 0.25, "half": 0.15}
"""Pallet types and their shares at rack nodes (1200 x 1000 pallets do not fit the example racks)."""


def _style_pallet(pallet: dict, at_rack: bool, style: np.random.Generator) -> None:
    """Draw a randomised pallet's type, and for a loaded one stretch film and overhang, into its placement."""
    types = RACK_TYPES if at_rack else FLOOR_TYPES
    names = list(types)
    pallet["type"] = names[int(style.choice(len(names), p=list(types.values())))]
    if pallet["loaded"]:
        pallet["film"] = bool(style.random() < 1.0 / 3.0)
        pallet["overhang_m"] = float(style.uniform(0.0, 0.06)) if style.random() < 0.25 else 0.0


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


def render_frame(
    index: int,
    seed: int,
    missions_dir: Path = MISSIONS_DIR,
    mounts: str = "all",
    randomise: bool = False,
    novel: bool = False,
    realism: bool = False,
) -> FrameBundle:
    """Frame `index` of the dataset with `seed`: a random scenario rendered with the `Simulator` (640x480).

    Deterministic for `(seed, index, mounts, randomise, novel, realism)`; `randomise`: domain
    randomisation, `novel`: with looks the randomisation never draws, `realism` (implies `randomise`):
    with worn pallets and a real camera's effects on top (module docstring). The bundle carries RGB,
    depth (m), exact labels, the fork height (m) and the simulator's truth keys.
    """
    rng = np.random.default_rng([int(seed), int(index)])
    randomise = randomise or realism
    style = np.random.default_rng([int(seed), int(index), 2 if novel else 1]) if randomise or novel else None
    real = np.random.default_rng([int(seed), int(index), 3]) if realism else None
    for _attempt in range(_MAX_DRAWS):
        sc, pose, fork_height = random_scenario(rng, missions_dir, mounts, style)
        try:
            sim = Simulator(sc)
            break
        except SimError:  # a pallet or clutter item overlapping something: draw the scene again
            continue
    else:
        raise SimError(f"dataset frame {index} (seed {seed}): no valid scenario in {_MAX_DRAWS} draws")
    if style is not None:
        randomise_appearance(sim, style, novel, real)
    sim.forklift.state.pose = pose  # teleport: a dataset frame needs no driving
    sim.forklift.state.fork_height = fork_height
    sim.forklift.fork_height_cmd = fork_height
    return sim.grab() if real is None else camera_effects(sim.grab(), real)


def iter_frames(
    n: int,
    seed: int,
    start: int = 0,
    missions_dir: Path = MISSIONS_DIR,
    mounts: str = "all",
    randomise: bool = False,
    novel: bool = False,
    realism: bool = False,
) -> Iterator[FrameBundle]:
    """Frames `start .. start + n - 1` of the dataset with `seed` (see `render_frame`)."""
    for i in range(start, start + n):
        yield render_frame(i, seed, missions_dir, mounts, randomise, novel, realism)


def generate_dataset(
    out_dir: str | Path,
    n: int,
    seed: int,
    start: int = 0,
    missions_dir: Path = MISSIONS_DIR,
    mounts: str = "all",
    randomise: bool = False,
    novel: bool = False,
    realism: bool = False,
) -> list[Path]:
    """Render frames `start .. start + n - 1` for `seed` and save them as `out_dir/frame_%05d.npz`.

    Returns the written paths. Existing files of the same name are overwritten.
    """
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    paths = []
    frames = iter_frames(n, seed, start, missions_dir, mounts, randomise, novel, realism)
    for i, bundle in enumerate(frames, start=start):
        paths.append(save_bundle(out / f"frame_{i:05d}.npz", bundle))
    return paths


# -- domain randomisation: colours and light ------------------------------------------------------

_FILM = np.array([0.80, 0.82, 0.84])
_STYLED_CLASSES = (
    SemanticClass.DRIVABLE,
    SemanticClass.VERTICAL,
    SemanticClass.OTHER_OBJECT,
    SemanticClass.PERSON,
)
"""Classes of the world mesh whose colours the randomisation draws."""
_WALL = np.array([0.78, 0.77, 0.72])
_RACK_COLOURS = np.array(
    [
        (0.10, 0.22, 0.55),  # blue
        (0.85, 0.38, 0.08),  # orange
        (0.55, 0.55, 0.55),  # galvanised
        (0.80, 0.70, 0.10),  # yellow
        (0.12, 0.40, 0.18),  # green
        (0.60, 0.10, 0.08),  # red
        (0.15, 0.15, 0.16),  # anthracite
        (0.80, 0.80, 0.78),  # white
    ]
)


def _tint(style: np.random.Generator, colour: np.ndarray | tuple, spread: float = 0.06) -> np.ndarray:
    """`colour` with a per-channel tint of +-`spread` (relative)."""
    return np.asarray(colour, float) * style.uniform(1.0 - spread, 1.0 + spread, 3)


def _any_colour(style: np.random.Generator, sat: tuple[float, float] = (0.2, 0.9)) -> np.ndarray:
    """A random colour: uniform hue, saturation in `sat`, value 0.05..0.85 (linear albedo)."""
    h, sv, v = style.uniform(0.0, 6.0), style.uniform(*sat), style.uniform(0.05, 0.85)
    rgb = np.clip(np.abs(((h + np.array([0.0, 4.0, 2.0])) % 6.0) - 3.0) - 1.0, 0.0, 1.0)
    return v * (1.0 - sv + sv * rgb)


def _floor_colour(style: np.random.Generator) -> tuple[np.ndarray, int | None]:
    """Concrete from dark to pale, or painted epoxy (grey, green, ochre, blue-grey; plain texture)."""
    if style.random() < 0.7:
        return _tint(style, np.full(3, style.uniform(0.18, 0.75)), 0.05), None
    epoxy = [(0.35, 0.37, 0.38), (0.15, 0.35, 0.20), (0.55, 0.45, 0.28), (0.25, 0.30, 0.38), (0.55, 0.55, 0.52)]
    return _tint(style, epoxy[int(style.integers(len(epoxy)))]) * style.uniform(0.7, 1.3), int(Texture.PLAIN)


def _wall_colour(style: np.random.Generator) -> np.ndarray:
    """Light paint of any tint, grey cladding or brick."""
    k = style.random()
    if k < 0.6:
        return _tint(style, np.full(3, style.uniform(0.45, 0.9)), 0.1)
    if k < 0.85:
        return _any_colour(style, (0.1, 0.5))
    return _tint(style, (0.45, 0.20, 0.12)) * style.uniform(0.6, 1.3)


def _pallet_colour(style: np.random.Generator, plastic: bool) -> tuple[np.ndarray, int | None]:
    """A pallet's colour and texture: wood (pale to dark, weathered grey), painted blue / red, or plastic."""
    if plastic or style.random() < 0.08:  # plastic (or a plastic-looking wooden one): plain black / grey / blue
        k = style.random()
        colour = (
            np.full(3, style.uniform(0.02, 0.08))
            if k < 0.4
            else np.full(3, style.uniform(0.12, 0.5))
            if k < 0.75
            else _tint(style, (0.08, 0.18, 0.45), 0.25)
        )
        return colour, int(Texture.PLAIN)
    k = style.random()
    if k < 0.62:  # natural wood, pale to dark
        lightness = style.uniform(0.45, 1.15)
        return _tint(style, (0.72, 0.55, 0.34), 0.08) * lightness, None
    if k < 0.82:  # weathered grey
        return _tint(style, np.full(3, style.uniform(0.22, 0.55)) * (1.05, 1.0, 0.92), 0.05), None
    painted = [(0.10, 0.25, 0.55), (0.10, 0.25, 0.55), (0.55, 0.12, 0.10), (0.12, 0.40, 0.18)]  # CHEP, LPR, ...
    return _tint(style, painted[int(style.integers(len(painted)))], 0.15), None


def _cargo_colour(style: np.random.Generator, film: bool) -> tuple[np.ndarray, int | None]:
    """A load's colour and texture: stretch film (clear to black), cartons, coloured bins, sacks, dark crates."""
    if film:
        k = style.random()
        if k < 0.7:
            return _tint(style, np.full(3, style.uniform(0.55, 0.92)), 0.05), None
        if k < 0.85:
            return np.full(3, style.uniform(0.03, 0.12)), None
        return _tint(style, (0.35, 0.5, 0.75), 0.2), None
    k = style.random()
    if k < 0.45:
        return _tint(style, (0.62, 0.45, 0.28), 0.1) * style.uniform(0.6, 1.3), int(Texture.CARDBOARD)
    if k < 0.6:
        return _tint(style, np.full(3, style.uniform(0.6, 0.85)), 0.04), int(Texture.CARDBOARD)
    if k < 0.8:
        return _any_colour(style, (0.5, 1.0)), int(Texture.PAINTED_METAL)
    if k < 0.9:
        return _tint(style, (0.80, 0.76, 0.66), 0.08), int(Texture.FABRIC)
    return np.full(3, style.uniform(0.04, 0.3)), int(Texture.PLAIN)


def _recolour(mesh: LabeledMesh, rows: np.ndarray, colour: np.ndarray, texture: int | None) -> None:
    """Give the triangles `rows` the mean colour `colour`, keeping their tone differences (in place)."""
    if not rows.any():
        return
    mean = np.maximum(mesh.albedo[rows].mean(axis=0), 1e-3)
    mesh.albedo[rows] = np.clip(mesh.albedo[rows] / mean * colour, 0.0, 1.0)
    if texture is not None:
        mesh.texture[rows] = texture


def _novel_look(style: np.random.Generator) -> tuple[np.ndarray, int]:
    """A colour and texture that the standard randomisation never draws: any hue, saturation 0.3..1, any texture."""
    return _any_colour(style, (0.3, 1.0)), int(style.integers(len(Texture)))


def _copy(mesh: LabeledMesh) -> LabeledMesh:
    """A copy whose albedo and texture may be changed without touching `mesh`."""
    return LabeledMesh.merge([mesh, LabeledMesh.empty()])


def _styled_world(mesh: LabeledMesh, style: np.random.Generator, novel: bool = False) -> LabeledMesh:
    """The floor, walls, racks, boxes and people with random colours (per material; `novel`: `_novel_look`)."""
    out = _copy(mesh)
    keys = np.column_stack([out.classes.astype(np.int32), np.round(out.albedo * 200).astype(np.int32)])
    materials, inverse = np.unique(keys, axis=0, return_inverse=True)
    inverse = inverse.ravel()
    floor_colour, floor_texture = _floor_colour(style)
    for m, key in enumerate(materials):
        rows = inverse == m
        cls, albedo = int(key[0]), key[1:] / 200.0
        texture: int | None = None
        if novel and cls in _STYLED_CLASSES:
            colour, texture = _novel_look(style)
        elif cls == SemanticClass.DRIVABLE:
            colour, texture = floor_colour, floor_texture
        elif cls == SemanticClass.VERTICAL and np.allclose(albedo, _WALL, atol=0.02):
            colour = _wall_colour(style)
        elif cls == SemanticClass.VERTICAL:
            colour = _tint(style, _RACK_COLOURS[int(style.integers(len(_RACK_COLOURS)))], 0.1)
        elif cls == SemanticClass.OTHER_OBJECT:
            colour = _any_colour(style)
        elif cls == SemanticClass.PERSON:
            colour = _any_colour(style) if style.random() < 0.7 else albedo * style.uniform(0.4, 1.3)
        else:
            continue
        _recolour(out, rows, colour, texture)
    return out


def _styled_pallet(mesh: LabeledMesh, plastic: bool, style: np.random.Generator, novel: bool = False) -> LabeledMesh:
    """One pallet and its load with random colours (the pallet as a whole, the load as a whole).

    `novel`: both from `_novel_look`.
    """
    out = _copy(mesh)
    pallet = (out.classes == SemanticClass.PALLET_EMPTY) | (out.classes == SemanticClass.PALLET_FULL)
    cargo = out.classes == SemanticClass.CARGO
    if novel:
        _recolour(out, pallet, *_novel_look(style))
        _recolour(out, cargo, *_novel_look(style))
        return out
    _recolour(out, pallet, *_pallet_colour(style, plastic))
    film = cargo & np.all(np.abs(out.albedo - _FILM) < 0.02, axis=1)
    _recolour(out, film, *_cargo_colour(style, True))
    _recolour(out, cargo & ~film, *_cargo_colour(style, False))
    return out


def random_lighting(style: np.random.Generator, novel: bool = False) -> Lighting:
    """A random light: direction, ambient and direct intensity, colour temperature, lamp rows and exposure.

    `novel`: from outside those ranges: low light (elevation 8..20 deg), exposure x0.3..0.5 or x1.7..2.5
    and a strong colour cast.
    """
    low, high = (8.0, 20.0) if novel else (20.0, 85.0)
    elevation, azimuth = np.radians(style.uniform(low, high)), style.uniform(0.0, 2.0 * np.pi)
    direction = (np.cos(elevation) * np.cos(azimuth), np.cos(elevation) * np.sin(azimuth), np.sin(elevation))
    ambient, diffuse = float(style.uniform(0.15, 0.6)), float(style.uniform(0.3, 1.0))
    warm, cool = np.array([1.0, 0.80, 0.58]), np.array([0.86, 0.94, 1.0])
    t = style.uniform(0.0, 1.0)
    colour = (1.0 - t) * warm + t * cool
    if style.random() < 0.1:
        colour = colour * (0.9, 1.0, 0.85)  # fluorescent green cast
    # Exposure: relative to the default light's brightness (0.4 + 0.7 * ~0.7), x0.5..1.7, saturating.
    gain = np.exp(style.uniform(np.log(0.5), np.log(1.7)))
    if novel:
        colour = colour * (0.55 + 0.45 * _any_colour(style, (0.6, 1.0)) / 0.85)
        gain = style.uniform(0.3, 0.5) if style.random() < 0.5 else style.uniform(1.7, 2.5)
    exposure = float(gain) * 0.9 / (ambient + 0.6 * diffuse)
    colour = colour / colour.max() * exposure
    return Lighting(
        direction=(float(direction[0]), float(direction[1]), float(direction[2])),
        ambient=ambient,
        diffuse=diffuse,
        colour=(float(colour[0]), float(colour[1]), float(colour[2])),
        lamp_period_m=float(style.uniform(3.0, 9.0)),
        lamp_depth=float(style.uniform(0.0, 0.35)),
    )


class _LitRenderer(RaycastRenderer):
    """A `RaycastRenderer` whose frames use a given base lighting (the simulator passes none)."""

    def __init__(self, static: LabeledMesh, lighting: Lighting) -> None:
        super().__init__(static)
        self.lighting = lighting

    def render(self, *args: Any, **kwargs: Any) -> FrameBundle:
        """`RaycastRenderer.render` with `lighting` defaulting to this renderer's."""
        kwargs["lighting"] = kwargs.get("lighting") or self.lighting
        return super().render(*args, **kwargs)


def randomise_appearance(
    sim: Simulator, style: np.random.Generator, novel: bool = False, real: np.random.Generator | None = None
) -> None:
    """Recolour the built world, pallets, loads and forks of `sim` and give its renderer a random light.

    Works on the simulator's meshes after it is built (the world's shape and labels are untouched);
    `novel`: with looks the standard randomisation never draws (module docstring); `real`: each pallet
    then also worn (`sim.dataset_realism.wear_pallet`) with draws from this generator.
    """
    world = _styled_world(sim._fixed_mesh, style, novel)
    pallets = [
        _styled_pallet(sim._pallet_mesh(p), p.type.material == "plastic", style, novel)
        for p in sim.pallets
        if not p.carried
    ]
    if real is not None:
        plastic = [p.type.material == "plastic" for p in sim.pallets if not p.carried]
        pallets = [wear_pallet(mesh, is_plastic, real) for mesh, is_plastic in zip(pallets, plastic, strict=True)]
    forks = _copy(sim._forks_local)
    forks.albedo[:] = np.clip(forks.albedo * style.uniform(0.6, 2.5), 0.0, 1.0)
    sim._forks_local = forks
    sim._renderer = _LitRenderer(LabeledMesh.merge([world, *pallets]), random_lighting(style, novel))
