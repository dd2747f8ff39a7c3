"""Procedural pallet scenes: labelled colour frames of pallets anywhere, for a segmenter that must transfer.

Issue 37: the shipped segmentation model, trained on renders of one warehouse seen from a forklift's
camera, labels about a third of a real photo's pallet front faces as pallet (`palletpilot bench realdata`).
Real photos show pallets on any floor, on tables, stacked, seen from any height, against any clutter. This
module draws such scenes from scratch, with exact labels, from nothing but numpy and OpenCV (no simulator
map, no Open3D), so that thousands of frames come cheaply on any machine:

- pallets as sets of boxes (`pallet_boxes`): two-pocket and four-way block pallets (EPAL-like, blocks of
  solid wood or pressed chip, optional bottom boards) and three-stringer pallets, every dimension drawn
  within the ranges of real pallets and scaled as a whole (scale models look the same to a camera); each
  board and block its own wood tone, sometimes grey, painted or dirty; some loaded (cartons, film-wrapped
  blocks: `CARGO`, the pallet then `PALLET_FULL`), some stacked, on the floor or on a table;
- clutter (`sim.scene_props`): boxes and crates of cardboard, plastic and wood, pallet look-alikes, shelving
  full of parts, drawer cabinets, tables (`OTHER_OBJECT`), people (`PERSON`), cables on the floor and
  shapes close to the lens painted over the frame;
- a floor (`DRIVABLE`: concrete, epoxy, artificial turf with painted lines, tiles, dark rubber, wooden
  boards) and walls (`VERTICAL`) with posters, doors and windows;
- light: a directional light with ambient share, colour temperature; pocket interiors and the floor
  under a pallet darkened (the occlusion a real pallet's pockets show);
- the camera: any height from a few centimetres to above the pallet, any azimuth, 40..95 deg horizontal
  field of view, sometimes a 16:9 field squeezed to 4:3 (what a segmenter does to a wide photo), the
  pallet anywhere in view, roll +-6 deg.

Camera effects (blur, noise, white balance, gamma, JPEG, vignetting) are drawn per training step by
`perception.training_batches.augment`, not baked in here.

Frames are rasterised with a z-buffer: every box face is a convex polygon, clipped at the near plane,
filled (`cv2.fillConvexPoly`), its inverse depth interpolated in the image plane. World frame: z up,
metres; camera frame: x right, y down, z forward (OpenCV). Frame `index` depends only on `(seed, index)`.

Public API: `SceneSettings`, `render_scene`, `pallet_boxes`, `generate_scenes` (writes `NAME.png` and
`NAME_labels.png`, the labelled-PNG format `perception.train_segmentation` reads).
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np

from palletpilot.geometry.fileio import write_atomic
from palletpilot.geometry.processes import spawn_pool
from palletpilot.perception.frames import SemanticClass
from palletpilot.perception.segmentation_data import LABELS_SUFFIX
from palletpilot.sim.box_raster import Box, Canvas
from palletpilot.sim.scene_props import (
    clutter_box,
    distractor,
    draw_cables,
    drawer_cabinet,
    filled_shelf,
    flying_shapes,
    person,
    rot_z,
    table,
    wood,
)

DRIVABLE = int(SemanticClass.DRIVABLE)
VERTICAL = int(SemanticClass.VERTICAL)
OTHER = int(SemanticClass.OTHER_OBJECT)
CARGO = int(SemanticClass.CARGO)
PALLET_EMPTY = int(SemanticClass.PALLET_EMPTY)
PALLET_FULL = int(SemanticClass.PALLET_FULL)

TEX = 128
"""Side of the square texture images (texels); textures repeat."""


@dataclass(frozen=True)
class SceneSettings:
    """Image size of the rendered frames (pixels)."""

    width: int = 640
    height: int = 480


# -- textures -------------------------------------------------------------------------------------


def _noise(rng: np.random.Generator, cells: int, size: int = TEX) -> np.ndarray:
    """Smooth value noise (size, size) in 0..1 with `cells` cells per side, tileable."""
    grid = rng.random((cells, cells)).astype(np.float32)
    big = cv2.resize(np.tile(grid, (3, 3)), (3 * size, 3 * size), interpolation=cv2.INTER_CUBIC)
    return np.clip(big[size : 2 * size, size : 2 * size], 0.0, 1.0)


def _textures(rng: np.random.Generator) -> list[np.ndarray]:
    """The frame's texture images (TEX, TEX) float32 around 1.0: multiplied by a surface's colour.

    0 flat; 1 wood grain (rows run along the grain); 2 rough wood with knots; 3 pressed chip (speckles);
    4 concrete; 5 turf (fine noise); 6 cardboard (fine fibres); 7 tiles or boards (a grid of seams).
    """
    y = np.arange(TEX, dtype=np.float32)[:, None]
    x = np.arange(TEX, dtype=np.float32)[None, :]
    flat = np.ones((TEX, TEX), np.float32)
    warp = _noise(rng, 4) * rng.uniform(4, 14)
    grain = 1.0 + rng.uniform(0.05, 0.2) * np.sin(2 * np.pi * (y + warp) / rng.uniform(3, 9) + 0 * x)
    grain = grain * (0.9 + 0.2 * _noise(rng, 8))
    knots = grain.copy()
    for _ in range(int(rng.integers(1, 4))):
        cy, cx, r = rng.uniform(0, TEX), rng.uniform(0, TEX), rng.uniform(3, 9)
        knots *= 1.0 - 0.45 * np.exp(-((y - cy) ** 2 + (x - cx) ** 2) / (2 * r * r))
    chip = 0.8 + 0.4 * rng.random((TEX, TEX)).astype(np.float32)
    chip = cv2.GaussianBlur(chip, (3, 3), 0) * (0.9 + 0.2 * _noise(rng, 16))
    concrete = 0.75 + 0.35 * _noise(rng, 6) + 0.12 * (rng.random((TEX, TEX)).astype(np.float32) - 0.5)
    turf = 0.7 + 0.6 * rng.random((TEX, TEX)).astype(np.float32)
    card = 0.93 + 0.1 * cv2.GaussianBlur(rng.random((TEX, TEX)).astype(np.float32), (1, 9), 0)
    tiles = 0.95 + 0.1 * _noise(rng, 4)
    period = int(rng.choice([16, 32, 64]))
    tiles[::period, :] *= 0.55
    if rng.random() < 0.6:
        tiles[:, ::period] *= 0.55
    return [flat, grain, knots, chip, concrete, turf, card, tiles]


# -- geometry -------------------------------------------------------------------------------------


def pallet_boxes(rng: np.random.Generator, scale: float, loaded: bool) -> tuple[list[Box], float]:
    """The boxes of one pallet in its own frame (x along its length, z up, origin on the floor at its centre).

    Returns the boxes (pallet boxes labelled `PALLET_FULL` when `loaded`, else `PALLET_EMPTY`) and the
    height of its top deck (metres). Dimensions in metres before `scale`: length 1.0..1.3, width
    0.75..1.2, blocks 0.07..0.12 high; a stringer pallet one time in five.
    """
    label = PALLET_FULL if loaded else PALLET_EMPTY
    tone = wood(rng)
    tex_block = 3 if rng.random() < 0.35 else 2
    boxes: list[Box] = []

    def part(size, centre, grain: int, tex: int = 1, dark: float = 1.0) -> None:
        jitter = np.clip(tone * rng.uniform(0.8, 1.15) + rng.normal(0, 0.02, 3), 0.02, 1.0)
        if rng.random() < 0.08:
            jitter = np.clip(np.array([0.86, 0.72, 0.50]) * rng.uniform(0.9, 1.1), 0, 1)
        boxes.append(
            Box(
                np.asarray(size, float) * scale,
                np.eye(3),
                np.asarray(centre, float) * scale,
                label,
                jitter,
                tex,
                rng.uniform(0.002, 0.005) * scale,
                grain,
                dark,
            )
        )

    L, W = rng.uniform(1.0, 1.3), rng.uniform(0.75, 1.2)
    board_t = rng.uniform(0.018, 0.026)
    if rng.random() < 0.2:  # stringer pallet: three stringers along x, deck boards across
        sh, st = rng.uniform(0.07, 0.1), rng.uniform(0.035, 0.05)
        for y in (-W / 2 + st / 2, 0.0, W / 2 - st / 2):
            part((L, st, sh), (0, y, board_t + sh / 2), 0, 1)
        n_top = int(rng.integers(5, 9))
        bw = rng.uniform(0.08, 0.14)
        for x in np.linspace(-L / 2 + bw / 2, L / 2 - bw / 2, n_top):
            part((bw, W, board_t), (x, 0, board_t + sh + board_t / 2), 1, 1)
        for x in (-L / 2 + bw / 2, 0.0, L / 2 - bw / 2):
            part((bw, W, board_t), (x, 0, board_t / 2), 1, 1)
        return boxes, 2 * board_t + sh
    bh = rng.uniform(0.07, 0.12)
    bx, by = rng.uniform(0.1, 0.16), rng.uniform(0.1, 0.16)
    bottom = rng.random() < 0.85
    z0 = board_t if bottom else 0.0
    xs = (-L / 2 + bx / 2, 0.0, L / 2 - bx / 2)
    ys = (-W / 2 + by / 2, 0.0, W / 2 - by / 2)
    if bottom:
        for y in ys:
            part((L, by, board_t), (0, y, board_t / 2), 0)
    for x in xs:
        for y in ys:
            inner = 0.55 if (x == 0.0 and y == 0.0) else 1.0
            part((bx, by, bh), (x, y, z0 + bh / 2), 2, tex_block, inner)
    z1 = z0 + bh
    for x in xs:  # the cross boards on the blocks
        part((bx, W, board_t), (x, 0, z1 + board_t / 2), 1)
    z2 = z1 + board_t
    n_top = int(rng.integers(3, 8))
    widths = rng.uniform(0.08, 0.15, n_top)
    for y, w in zip(np.linspace(-W / 2 + 0.07, W / 2 - 0.07, n_top), widths, strict=True):
        part((L, w, board_t), (0, y, z2 + board_t / 2), 0)
    return boxes, z2 + board_t


def _cargo(rng: np.random.Generator, footprint: tuple[float, float], z: float) -> list[Box]:
    """A load on a pallet deck at height `z` (metres) over `footprint` (length, width): cartons or one wrapped block."""
    L, W = footprint
    boxes: list[Box] = []
    if rng.random() < 0.4:  # one wrapped block or bin
        h = rng.uniform(0.3, 1.2) * L
        colour = np.clip(
            rng.choice([[0.75, 0.6, 0.4], [0.9, 0.9, 0.9], [0.2, 0.4, 0.8], [0.8, 0.2, 0.2]]) * rng.uniform(0.7, 1.1),
            0,
            1,
        )
        size = np.array([L * rng.uniform(0.8, 1.03), W * rng.uniform(0.8, 1.03), h])
        boxes.append(Box(size, np.eye(3), np.array([0, 0, z + h / 2]), CARGO, colour, int(rng.choice([0, 6])), L / 200))
        return boxes
    nx, ny = int(rng.integers(1, 4)), int(rng.integers(1, 3))
    layers = int(rng.integers(1, 4))
    ch = rng.uniform(0.15, 0.4) * L
    colour = np.clip(np.array([0.72, 0.56, 0.38]) * rng.uniform(0.7, 1.2), 0, 1)
    for k in range(layers):
        for i in range(nx):
            for j in range(ny):
                if rng.random() < 0.1:
                    continue
                cx = -L / 2 + (i + 0.5) * L / nx
                cy = -W / 2 + (j + 0.5) * W / ny
                size = np.array([L / nx * rng.uniform(0.85, 0.98), W / ny * rng.uniform(0.85, 0.98), ch])
                tint = np.clip(colour * rng.uniform(0.9, 1.1), 0, 1)
                boxes.append(
                    Box(
                        size,
                        rot_z(rng.normal(0, 0.03)),
                        np.array([cx, cy, z + (k + 0.5) * ch]),
                        CARGO,
                        tint,
                        6,
                        L / 300,
                    )
                )
    return boxes


def _place(boxes: list[Box], R: np.ndarray, t: np.ndarray) -> list[Box]:
    """The boxes moved by the pose (R, t) (world from their frame)."""
    return [
        Box(b.size, R @ b.R, R @ b.t + t, b.label, b.colour, b.texture, b.texel_m, b.grain_axis, b.dark) for b in boxes
    ]


# -- the scene ------------------------------------------------------------------------------------


def _floor_and_walls(
    canvas: Canvas, rng: np.random.Generator, extent: float, scale: float
) -> tuple[np.ndarray, int, float]:
    """A floor quad (DRIVABLE) of half side `extent` around the origin and two to four walls (VERTICAL).

    Returns the floor's colour, texture and metres per texel (for shadows drawn on it).
    """
    k = rng.random()
    if k < 0.25:
        colour, tex = np.array([0.55, 0.55, 0.53]) * rng.uniform(0.5, 1.5), 4  # concrete
    elif k < 0.45:
        colour, tex = np.array([0.15, 0.55, 0.25]) * rng.uniform(0.6, 1.3), 5  # turf / green epoxy
    elif k < 0.6:
        colour, tex = rng.random(3) * 0.8 + 0.1, 7  # tiles
    elif k < 0.72:
        colour, tex = np.array([0.1, 0.1, 0.11]) * rng.uniform(0.5, 2.5), 4  # dark rubber or black
    elif k < 0.85:
        colour, tex = wood(rng), 1
    else:
        colour, tex = rng.random(3) * 0.9 + 0.05, int(rng.choice([0, 4, 5]))
    e = extent
    colour = np.clip(colour, 0, 1)
    texel = scale * rng.uniform(0.003, 0.02)
    floor = np.array([[-e, -e, 0], [e, -e, 0], [e, e, 0], [-e, e, 0]], float)
    canvas.polygon(floor, np.array([0, 0, 1.0]), np.eye(3)[:2], colour, DRIVABLE, tex, texel)
    if rng.random() < 0.6:  # painted lines
        for _ in range(int(rng.integers(1, 4))):
            y, yaw, w = rng.uniform(-e / 3, e / 3), rng.uniform(0, np.pi), rng.uniform(0.03, 0.12) * scale
            R = rot_z(yaw)
            line = np.array(
                [[-e, y - w / 2, 0.001], [e, y - w / 2, 0.001], [e, y + w / 2, 0.001], [-e, y + w / 2, 0.001]]
            )
            paint = np.array(rng.choice([[0.95, 0.95, 0.9], [0.95, 0.8, 0.1], [0.9, 0.2, 0.1]]))
            canvas.polygon(line @ R.T, np.array([0, 0, 1.0]), np.eye(3)[:2], paint, DRIVABLE, 4, 0.01)
    height = rng.uniform(2.0, 5.0) * max(scale, 0.5)
    wall_colour = np.clip(
        rng.choice([[0.9, 0.9, 0.88], [0.8, 0.82, 0.85], [0.6, 0.6, 0.58], [0.85, 0.8, 0.7]]) * rng.uniform(0.6, 1.1),
        0,
        1,
    )
    dist = rng.uniform(0.4, 0.95) * e
    for side in rng.permutation(4)[: int(rng.integers(2, 5))]:
        R = rot_z(side * np.pi / 2)
        quad = np.array([[dist, -e, 0], [dist, e, 0], [dist, e, height], [dist, -e, height]]) @ R.T
        canvas.polygon(
            quad,
            R @ np.array([-1.0, 0, 0]),
            np.stack([R @ [0, 1.0, 0], [0, 0, 1.0]]),
            wall_colour,
            VERTICAL,
            int(rng.choice([0, 4])),
            0.02,
        )
        for _ in range(int(rng.integers(0, 6))):  # posters, doors, windows, cabinets flat on the wall
            w, h = rng.uniform(0.2, 1.5) * scale, rng.uniform(0.2, 2.0) * scale
            y, z = rng.uniform(-e / 2, e / 2), rng.uniform(0, height - h)
            d = dist - 0.002
            patch = np.array([[d, y, z], [d, y + w, z], [d, y + w, z + h], [d, y, z + h]]) @ R.T
            tone = np.clip(rng.random(3) * 1.2, 0, 1) if rng.random() < 0.7 else np.ones(3) * rng.uniform(1.0, 1.6)
            canvas.polygon(
                patch,
                R @ np.array([-1.0, 0, 0]),
                np.stack([R @ [0, 1.0, 0], [0, 0, 1.0]]),
                np.clip(tone, 0, 1.6),
                VERTICAL,
                0,
                0.02,
            )
    return colour, tex, texel


def _camera(rng: np.random.Generator, target: np.ndarray, size_m: float, settings: SceneSettings):
    """K (3x3) and the world-to-camera rotation and translation looking at `target` from a random viewpoint."""
    hfov = np.radians(rng.uniform(40, 95))
    fx = settings.width / 2 / np.tan(hfov / 2)
    fy = fx if rng.random() < 0.6 else fx * 4 / 3  # a 16:9 field squeezed into 4:3
    K = np.array(
        [[fx, 0, settings.width / 2 + rng.normal(0, 5)], [0, fy, settings.height / 2 + rng.normal(0, 5)], [0, 0, 1.0]]
    )
    dist = size_m * rng.uniform(0.9, 6.0) * (60 / np.degrees(hfov)) ** 0.5
    azimuth = rng.uniform(-np.pi, np.pi)
    k = rng.random()
    elev = rng.uniform(0.0, 8.0) if k < 0.45 else (rng.uniform(8, 35) if k < 0.85 else rng.uniform(35, 70))
    elev = np.radians(elev)
    eye = target + dist * np.array([np.cos(azimuth) * np.cos(elev), np.sin(azimuth) * np.cos(elev), np.sin(elev)])
    eye[2] = max(eye[2], 0.015 * size_m + 0.01)
    aim = target + rng.normal(0, 0.25 * size_m, 3) * [1, 1, 0.4]
    fwd = aim - eye
    fwd /= np.linalg.norm(fwd)
    right = np.cross(fwd, [0, 0, 1.0])
    right /= max(np.linalg.norm(right), 1e-9)
    down = np.cross(fwd, right)
    R_wc = np.stack([right, down, fwd], axis=1)  # columns: the camera axes in the world
    roll = np.radians(rng.normal(0, 3.0))
    c, s = np.cos(roll), np.sin(roll)
    R_wc = R_wc @ np.array([[c, -s, 0], [s, c, 0], [0, 0, 1.0]])
    R_cw = R_wc.T
    return K, R_cw, -R_cw @ eye


def _clutter(rng: np.random.Generator, placed: list[np.ndarray], scale: float) -> list[Box]:
    """The scene's clutter around the pallets at `placed` (world xy, metres): a sparse room or a dense workshop.

    Boxes and crates, pallet look-alikes (shelves, slatted crates, stools, bins), shelving full of parts,
    drawer cabinets and people (`sim.scene_props`), none closer to a pallet than 1.2 pallet scales.
    """
    objects: list[Box] = []
    dense = rng.random() < 0.5
    s = max(scale, 0.2)
    for _ in range(int(rng.integers(8, 30) if dense else rng.integers(2, 15))):
        xy = rng.normal(0, 3.0 * max(scale, 0.3), 2)
        if any(np.linalg.norm(xy - q) <= 1.2 * scale for q in placed):
            continue
        k = rng.random()
        if k < 0.35:
            objects += distractor(rng, xy, s)
        elif k < 0.7:
            objects.append(clutter_box(rng, xy, s))
        elif k < 0.85:
            objects += filled_shelf(rng, xy, s)
        else:
            objects += drawer_cabinet(rng, xy, s)
    for _ in range(int(rng.choice([0, 0, 0, 1, 1, 2]))):
        xy = rng.normal(0, 2.5 * max(scale, 0.4), 2)
        if all(np.linalg.norm(xy - q) > 0.8 * max(scale, 0.5) for q in placed):
            objects += person(rng, xy)
    return objects


def render_scene(seed: int, index: int, settings: SceneSettings = SceneSettings()) -> tuple[np.ndarray, np.ndarray]:
    """Frame `index` of the procedural set `seed`: RGB (H, W, 3) uint8 and class ids (H, W) uint8 (module docstring)."""
    rng = np.random.default_rng([seed, index, 37])
    scale = float(np.exp(rng.uniform(np.log(0.15), np.log(1.0))))  # scale models to full size
    textures = _textures(rng)
    az, el = rng.uniform(-np.pi, np.pi), np.radians(rng.uniform(25, 85))
    light_dir = -np.array([np.cos(az) * np.cos(el), np.sin(az) * np.cos(el), np.sin(el)])
    temp = rng.uniform(-1, 1)
    light_rgb = np.array([1.0 + 0.12 * temp, 1.0, 1.0 - 0.15 * temp]) * rng.uniform(0.7, 1.2)
    ambient = rng.uniform(0.35, 0.75)

    # the pallets: a group on the floor or on a table, some stacked, some loaded
    objects: list[Box] = []
    on_table = rng.random() < 0.3
    support_z = 0.0
    centre = np.zeros(2)
    if on_table:
        top = np.array([rng.uniform(1.2, 3.0), rng.uniform(0.6, 1.2)]) * max(scale * 3, 1.0)
        table_boxes, support_z = table(rng, centre, top, rng.uniform(0, np.pi))
        objects += table_boxes
    n_pallets = int(rng.choice([1, 1, 2, 2, 3, 4, 5]))
    placed: list[np.ndarray] = []
    footprints: list[tuple[np.ndarray, float, float, float]] = []  # centre, yaw, length, support height
    top = np.zeros(2)
    target = np.array([0.0, 0.0, support_z])
    for p in range(n_pallets):
        xy = np.zeros(2) if p == 0 else rng.normal(0, 1.6 * scale, 2)
        if any(np.linalg.norm(xy - q) < 1.4 * scale for q in placed):
            continue
        if p > 0 and on_table:  # the others stand on the floor, clear of the table
            xy = xy + np.sign(xy + 1e-9) * np.max(top)
        placed.append(xy)
        base_z = support_z if p == 0 else 0.0
        yaw = rng.uniform(-np.pi, np.pi)
        stack = int(rng.choice([1, 1, 1, 1, 2, 3, 5]))
        z = base_z
        for level in range(stack):
            loaded = level == stack - 1 and rng.random() < 0.35
            boxes, deck = pallet_boxes(rng, scale, loaded)
            if level < stack - 1:  # a pallet under another one carries it
                for b in boxes:
                    b.label = PALLET_FULL
            R = rot_z(yaw + rng.normal(0, 0.05))
            t = np.array([xy[0], xy[1], z]) + np.append(rng.normal(0, 0.01 * scale, 2), 0)
            objects += _place(boxes, R, t)
            if loaded:
                footprint = (float(boxes[-1].size[0]), float(np.ptp([b.t[1] for b in boxes]) + boxes[-1].size[1]))
                objects += _place(_cargo(rng, footprint, deck), R, t)
            z += deck
        footprints.append((xy, yaw, 2 * max(float(b.t[0] + b.size[0] / 2) for b in boxes), base_z))
        if p == 0:
            target = np.array([xy[0], xy[1], support_z + 0.5 * (z - support_z)])
    objects += _clutter(rng, placed, scale)
    if on_table:  # small things on the table beside the pallet
        for _ in range(int(rng.integers(0, 4))):
            xy = rng.uniform(-0.5, 0.5, 2) * top
            if all(np.linalg.norm(xy - q) > 0.9 * scale for q in placed):
                small = 0.5 * scale
                objects += (
                    distractor(rng, xy, small, support_z)
                    if rng.random() < 0.5
                    else [clutter_box(rng, xy, small, support_z)]
                )

    K, R_cw, t_cw = _camera(rng, target, 1.2 * scale, settings)
    canvas = Canvas(K, R_cw, t_cw, (settings.width, settings.height), textures, (light_dir, light_rgb, ambient))
    floor_colour, floor_tex, floor_texel = _floor_and_walls(canvas, rng, max(8.0 * scale, 3.0) * 3, max(scale, 0.2))
    for xy, yaw, length, z in footprints:  # the floor (or table) darkened under each pallet: its contact shadow
        grow = rng.uniform(1.0, 1.15)
        half = np.array([0.5 * length * grow, 0.45 * length * grow])
        quad = np.array([[-1, -1], [1, -1], [1, 1], [-1, 1]]) * half
        quad = quad @ rot_z(yaw)[:2, :2].T + xy
        shadow = np.column_stack([quad, np.full(4, z + 0.001)])
        below, colour, tex, texel = (
            (DRIVABLE, floor_colour, floor_tex, floor_texel) if z == 0.0 else (OTHER, None, 0, 0.01)
        )
        shade = rng.uniform(0.3, 0.7)
        colour = np.full(3, 0.1) if colour is None else colour * shade
        canvas.polygon(shadow, np.array([0, 0, 1.0]), np.eye(3)[:2], colour, below, tex, texel)
    for b in objects:
        canvas.box(b)
    rgb = np.clip(canvas.rgb, 0.0, 1.0)
    sky = canvas.labels == 255  # nothing drawn: far background (a ceiling, a hall beyond the walls)
    rgb[sky] = np.clip(rng.uniform(0.4, 1.0) * np.array([1.0, 1.0, 0.97]), 0, 1)
    labels = canvas.labels.copy()
    labels[sky] = VERTICAL
    draw_cables(rgb, labels, rng, DRIVABLE)
    flying_shapes(rgb, labels, rng, textures)
    rgb = np.clip(rgb, 0.0, 1.0)
    return (rgb * 255 + 0.5).astype(np.uint8), labels


def _write_frame(args: tuple[Path, int, int, SceneSettings]) -> str:
    out, seed, index, settings = args
    rgb, labels = render_scene(seed, index, settings)
    name = f"scene_{seed:03d}_{index:06d}"
    ok, png = cv2.imencode(".png", cv2.cvtColor(rgb, cv2.COLOR_RGB2BGR))
    ok2, lab = cv2.imencode(".png", labels)
    if not (ok and ok2):
        raise RuntimeError(f"{name}: PNG encoding failed")
    write_atomic(out / f"{name}{LABELS_SUFFIX}", lab.tobytes())
    write_atomic(out / f"{name}.png", png.tobytes())
    return name


def generate_scenes(
    out_dir: Path, frames: int, seed: int = 0, start: int = 0, jobs: int = 1, settings: SceneSettings = SceneSettings()
) -> list[str]:
    """Render frames `start..start+frames-1` of set `seed` into `out_dir` as labelled PNG frames; their names."""
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    work = [(out, seed, i, settings) for i in range(start, start + frames)]
    if jobs <= 1:
        return [_write_frame(w) for w in work]
    with spawn_pool(jobs) as pool:
        return list(pool.map(_write_frame, work, chunksize=8))
