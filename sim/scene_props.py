"""Props for the procedural pallet scenes: wood tones, clutter, look-alikes, furniture, people, overlays.

Real photos of pallets (`../shared/realdata`) are dense with clutter: shelving full of parts, drawer
cabinets, tables, bins, chairs, cables on the floor and people walking by. A segmenter trained on sparse
scenes learns "wooden and boxy means pallet" and labels all of it pallet. These builders put that clutter
into `sim.pallet_scenes`, each labelled what it is (`OTHER_OBJECT`, `PERSON`), so the model has to learn a
pallet's structure (blocks, boards and the dark pockets between them) rather than its colour.

World frame: z up, metres; each builder stands its prop on height `z` at `centre_xy`, any yaw. `scale`
scales a prop with the scene (scale-model pallets on a table stand among scale-model clutter), except people.

Public API: `rot_z`, `wood`, `clutter_box`, `distractor`, `table`, `filled_shelf`, `drawer_cabinet`,
`person`, `draw_cables`, `flying_shapes`.
"""

from __future__ import annotations

import cv2
import numpy as np

from palletpilot.perception.frames import SemanticClass
from palletpilot.sim.box_raster import Box

OTHER = int(SemanticClass.OTHER_OBJECT)
PERSON = int(SemanticClass.PERSON)


def rot_z(yaw: float) -> np.ndarray:
    """The rotation (3x3) by `yaw` (rad) about the world z axis."""
    c, s = np.cos(yaw), np.sin(yaw)
    return np.array([[c, -s, 0.0], [s, c, 0.0], [0.0, 0.0, 1.0]])


def wood(rng: np.random.Generator) -> np.ndarray:
    """A wood tone (RGB 0..1): pale pine to brown, sometimes weathered grey or painted."""
    k = rng.random()
    if k < 0.72:
        base = np.array([0.78, 0.62, 0.42]) * rng.uniform(0.55, 1.2) + rng.normal(0, 0.03, 3)
    elif k < 0.86:
        base = np.array([0.55, 0.53, 0.50]) * rng.uniform(0.6, 1.3)
    elif k < 0.93:
        base = np.array([0.85, 0.78, 0.60]) * rng.uniform(0.8, 1.15)  # pressed chip / fresh pine
    else:
        base = rng.choice([[0.15, 0.3, 0.6], [0.6, 0.15, 0.1], [0.9, 0.9, 0.85], [0.2, 0.2, 0.2]])
        base = np.asarray(base) * rng.uniform(0.8, 1.1)
    return np.clip(base, 0.03, 1.0)


def clutter_box(rng: np.random.Generator, centre_xy: np.ndarray, scale: float, z: float = 0.0) -> Box:
    """A box, crate or cabinet standing at `centre_xy` on height `z` (`OTHER_OBJECT`)."""
    size = np.array([rng.uniform(0.2, 1.5), rng.uniform(0.2, 1.2), rng.uniform(0.1, 1.8)]) * scale
    k = rng.random()
    if k < 0.35:
        colour, tex = np.array([0.72, 0.56, 0.38]) * rng.uniform(0.7, 1.2), 6
    elif k < 0.55:
        colour, tex = wood(rng), 1  # wooden crates and furniture: wood is not always a pallet
    else:
        colour, tex = rng.random(3) ** 0.7, int(rng.choice([0, 0, 4]))
    t = np.array([centre_xy[0], centre_xy[1], z + size[2] / 2])
    return Box(size, rot_z(rng.uniform(0, np.pi)), t, OTHER, np.clip(colour, 0, 1), tex, scale / 100, 0)


def _parts_to_boxes(
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]],
    R: np.ndarray,
    base: np.ndarray,
    label: int,
    tex: int,
    texel_m: float,
    scale: float = 1.0,
) -> list[Box]:
    """Boxes from (size, centre in the prop's frame, colour) parts, scaled by `scale`, placed by yaw `R` at
    `base` (metres)."""
    return [
        Box(size * scale, R, base + R @ (centre * scale), label, np.clip(colour, 0, 1), tex, texel_m, 0)
        for size, centre, colour in parts
    ]


def distractor(rng: np.random.Generator, centre_xy: np.ndarray, scale: float, z: float = 0.0) -> list[Box]:
    """Something with a pallet's look that is not a pallet (`OTHER_OBJECT`): a shelf unit (uprights and shelf
    boards), a slatted wooden crate, a stool or chair on legs, or a ribbed plastic bin, standing at `centre_xy`."""
    R = rot_z(rng.uniform(0, np.pi))
    base = np.array([centre_xy[0], centre_xy[1], z])
    k = rng.random()
    parts: list[tuple[np.ndarray, np.ndarray]] = []  # (size, centre in its own frame)
    if k < 0.3:  # shelf unit
        w, d, h = rng.uniform(0.6, 2.0), rng.uniform(0.3, 0.6), rng.uniform(0.8, 2.2)
        post = rng.uniform(0.03, 0.06)
        for sx in (-1, 1):
            for sy in (-1, 1):
                parts.append((np.array([post, post, h]), np.array([sx * (w - post) / 2, sy * (d - post) / 2, h / 2])))
        for zs in np.linspace(0.05, h - 0.02, int(rng.integers(2, 6))):
            parts.append((np.array([w, d, rng.uniform(0.015, 0.04)]), np.array([0.0, 0.0, zs])))
        colour, tex = (
            np.clip(rng.choice([[0.2, 0.3, 0.7], [0.85, 0.85, 0.85], [0.9, 0.5, 0.1], [0.3, 0.3, 0.3]]), 0, 1),
            0,
        )
    elif k < 0.55:  # slatted crate
        w, d, h = rng.uniform(0.3, 1.0), rng.uniform(0.3, 0.8), rng.uniform(0.2, 0.7)
        n = int(rng.integers(3, 7))
        slat = h / (2 * n - 1)
        for i in range(n):
            zc = (2 * i + 0.5) * slat
            for sy in (-1, 1):
                parts.append((np.array([w, 0.02, slat]), np.array([0.0, sy * d / 2, zc])))
            for sx in (-1, 1):
                parts.append((np.array([0.02, d, slat]), np.array([sx * w / 2, 0.0, zc])))
        colour, tex = wood(rng), 1
    elif k < 0.8:  # stool, chair or small table on four legs
        w, h = rng.uniform(0.3, 0.8), rng.uniform(0.35, 0.8)
        leg = rng.uniform(0.02, 0.05)
        for sx in (-1, 1):
            for sy in (-1, 1):
                parts.append((np.array([leg, leg, h]), np.array([sx * (w - leg) / 2, sy * (w - leg) / 2, h / 2])))
        parts.append((np.array([w, w, rng.uniform(0.02, 0.06)]), np.array([0.0, 0.0, h])))
        colour = wood(rng) if rng.random() < 0.5 else np.clip(rng.random(3), 0.05, 1)
        tex = 1
    else:  # ribbed bin
        w, d, h = rng.uniform(0.3, 0.7), rng.uniform(0.25, 0.5), rng.uniform(0.15, 0.4)
        parts.append((np.array([w, d, h]), np.array([0.0, 0.0, h / 2])))
        for x in np.linspace(-w / 2, w / 2, int(rng.integers(3, 8))):
            parts.append((np.array([0.02, d + 0.02, h]), np.array([x, 0.0, h / 2])))
        colour, tex = np.clip(rng.random(3) ** 0.6, 0.05, 1), 0
    colour = np.asarray(colour, float)
    tinted = [(size, centre, colour * rng.uniform(0.85, 1.1)) for size, centre in parts]
    return _parts_to_boxes(tinted, R, base, OTHER, tex, scale / 150, scale)


def table(rng: np.random.Generator, centre_xy: np.ndarray, top_size: np.ndarray, yaw: float) -> tuple[list[Box], float]:
    """A table (top and four legs, `OTHER_OBJECT`) and the height of its top (metres)."""
    h = rng.uniform(0.5, 0.95)
    th = rng.uniform(0.02, 0.05)
    colour = np.clip(
        rng.choice([[0.9, 0.9, 0.88], [0.6, 0.45, 0.3], [0.1, 0.1, 0.1], [0.7, 0.72, 0.75]]) * rng.uniform(0.8, 1.1),
        0,
        1,
    )
    R = rot_z(yaw)
    c = np.array([centre_xy[0], centre_xy[1], 0.0])
    boxes = [
        Box(np.array([top_size[0], top_size[1], th]), R, c + np.array([0.0, 0.0, h - th / 2]), OTHER, colour, 0, 0.01)
    ]
    for sx in (-1, 1):
        for sy in (-1, 1):
            leg = R @ np.array([sx * (top_size[0] / 2 - 0.05), sy * (top_size[1] / 2 - 0.05), (h - th) / 2])
            boxes.append(Box(np.array([0.04, 0.04, h - th]), R, c + leg, OTHER, colour * 0.7, 0, 0.01))
    return boxes, h


def filled_shelf(rng: np.random.Generator, centre_xy: np.ndarray, scale: float, z: float = 0.0) -> list[Box]:
    """Metal shelving full of parts bins, boxes and tools (`OTHER_OBJECT`): the wall of a workshop or lab."""
    R = rot_z(rng.uniform(0, np.pi))
    w, d, h = rng.uniform(1.0, 2.5), rng.uniform(0.35, 0.6), rng.uniform(1.2, 2.2)
    frame_c = np.array(rng.choice([[0.25, 0.3, 0.6], [0.8, 0.8, 0.8], [0.2, 0.2, 0.2], [0.9, 0.5, 0.15]]))
    post = 0.04
    parts: list[tuple[np.ndarray, np.ndarray, np.ndarray]] = []
    for sx in (-1, 1):
        for sy in (-1, 1):
            parts.append(
                (np.array([post, post, h]), np.array([sx * (w - post) / 2, sy * (d - post) / 2, h / 2]), frame_c)
            )
    levels = np.linspace(0.05, h - 0.03, int(rng.integers(3, 7)))
    for i, zs in enumerate(levels):
        parts.append((np.array([w, d, 0.025]), np.array([0.0, 0.0, zs]), frame_c * rng.uniform(0.9, 1.1)))
        if i == len(levels) - 1:
            break
        room = levels[i + 1] - zs - 0.04
        x = -w / 2 + 0.03
        while x < w / 2 - 0.1 and room > 0.05:  # a row of things on the shelf, left to right
            iw = min(rng.uniform(0.08, 0.45), w / 2 - x - 0.02)
            ih = room * rng.uniform(0.3, 0.95)
            colour = (
                rng.random(3) ** 0.6 if rng.random() < 0.7 else np.array([0.72, 0.56, 0.38]) * rng.uniform(0.7, 1.1)
            )
            if rng.random() < 0.85:
                centre = np.array([x + iw / 2, rng.uniform(-0.05, 0.05) * d, zs + 0.0125 + ih / 2])
                parts.append((np.array([iw, d * rng.uniform(0.5, 0.95), ih]), centre, colour))
            x += iw + rng.uniform(0.0, 0.08)
    return _parts_to_boxes(parts, R, np.array([*centre_xy, z]), OTHER, 0, scale / 150, scale)


def drawer_cabinet(rng: np.random.Generator, centre_xy: np.ndarray, scale: float, z: float = 0.0) -> list[Box]:
    """A parts cabinet with a grid of small drawer fronts (`OTHER_OBJECT`): rows of dark gaps like a pallet's."""
    R = rot_z(rng.uniform(0, np.pi))
    w, d, h = rng.uniform(0.4, 1.0), rng.uniform(0.25, 0.5), rng.uniform(0.5, 1.6)
    body = np.array(rng.choice([[0.6, 0.62, 0.65], [0.3, 0.3, 0.32], [0.25, 0.35, 0.6], [0.85, 0.85, 0.8]]))
    parts = [(np.array([w, d, h]), np.array([0.0, 0.0, h / 2]), body)]
    rows, cols = int(rng.integers(3, 12)), int(rng.integers(2, 7))
    front = np.clip(body * rng.uniform(0.8, 1.3) if rng.random() < 0.6 else rng.random(3), 0, 1)
    gap = rng.uniform(0.08, 0.2)
    for i in range(rows):
        for j in range(cols):
            cw, ch = w / cols * (1 - gap), h / rows * (1 - gap)
            centre = np.array([-w / 2 + (j + 0.5) * w / cols, d / 2 + 0.006, (i + 0.5) * h / rows])
            parts.append((np.array([cw, 0.012, ch]), centre, front))
    return _parts_to_boxes(parts, R, np.array([*centre_xy, z]), OTHER, 0, scale / 150, scale)


def person(rng: np.random.Generator, centre_xy: np.ndarray, z: float = 0.0) -> list[Box]:
    """A person standing at `centre_xy` (`PERSON`), full size whatever the scene's scale: legs, body, arms, head."""
    R = rot_z(rng.uniform(0, 2 * np.pi))
    tall = rng.uniform(1.5, 1.9)
    leg_h, body_h = 0.47 * tall, 0.3 * tall
    trousers = np.array(rng.choice([[0.1, 0.12, 0.25], [0.15, 0.15, 0.15], [0.35, 0.3, 0.25], [0.2, 0.25, 0.45]]))
    shirt = rng.random(3) ** 0.8
    skin = np.array([0.85, 0.65, 0.5]) * rng.uniform(0.5, 1.1)
    stride = rng.uniform(-0.15, 0.15)
    parts = [
        (np.array([0.13, 0.14, leg_h]), np.array([stride, -0.1, leg_h / 2]), trousers),
        (np.array([0.13, 0.14, leg_h]), np.array([-stride, 0.1, leg_h / 2]), trousers),
        (np.array([0.24, 0.42, body_h]), np.array([0.0, 0.0, leg_h + body_h / 2]), shirt),
        (np.array([0.09, 0.09, 0.62 * body_h + 0.2]), np.array([0.0, -0.26, leg_h + 0.3 * body_h]), shirt * 0.95),
        (np.array([0.09, 0.09, 0.62 * body_h + 0.2]), np.array([0.0, 0.26, leg_h + 0.3 * body_h]), shirt * 0.95),
        (np.array([0.18, 0.16, 0.22]), np.array([0.0, 0.0, leg_h + body_h + 0.14]), skin),
        (np.array([0.28, 0.12, 0.08]), np.array([0.06, 0.1, 0.04]), np.full(3, 0.1)),  # shoes
        (np.array([0.28, 0.12, 0.08]), np.array([0.06, -0.1, 0.04]), np.full(3, 0.1)),
    ]
    return _parts_to_boxes(parts, R, np.array([*centre_xy, z]), PERSON, 0, 0.01)


def draw_cables(rgb: np.ndarray, labels: np.ndarray, rng: np.random.Generator, floor_label: int) -> None:
    """Draw cables and hoses over the floor pixels in place: smooth random polylines (`OTHER_OBJECT`)."""
    h, w = labels.shape
    floor = (labels == floor_label).astype(np.uint8)
    for _ in range(int(rng.integers(0, 5))):
        n = int(rng.integers(4, 9))
        pts = np.cumsum(rng.normal(0, 0.12, (n, 2)) * [w, h], axis=0) + rng.uniform(0, 1, 2) * [w, h]
        t = np.linspace(0, n - 1, 8 * n)
        curve = np.stack([np.interp(t, np.arange(n), pts[:, k]) for k in range(2)], axis=1)
        mask = np.zeros((h, w), np.uint8)
        cv2.polylines(mask, [np.round(curve).astype(np.int32)], False, 1, int(rng.integers(1, 6)), cv2.LINE_AA)
        mask &= floor
        colour = rng.choice([[0.05, 0.05, 0.05], [0.92, 0.92, 0.9], [0.9, 0.5, 0.1], [0.2, 0.3, 0.8]])
        on = mask > 0
        rgb[on] = np.asarray(colour, np.float32) * rng.uniform(0.7, 1.1)
        labels[on] = OTHER


def flying_shapes(rgb: np.ndarray, labels: np.ndarray, rng: np.random.Generator, textures: list[np.ndarray]) -> None:
    """Paint a few textured polygons over the frame in place (`OTHER_OBJECT`): things close to the lens.

    Some are wood-toned: wood alone must not read as pallet (domain randomisation's flying distractors).
    """
    h, w = labels.shape
    for _ in range(int(rng.choice([0, 0, 0, 1, 1, 2, 3]))):
        centre = rng.uniform(0, 1, 2) * [w, h]
        radius = rng.uniform(0.04, 0.25) * min(w, h)
        angles = np.sort(rng.uniform(0, 2 * np.pi, int(rng.integers(3, 8))))
        pts = centre + np.stack([np.cos(angles), np.sin(angles)], axis=1) * radius * rng.uniform(
            0.5, 1.0, (len(angles), 1)
        )
        mask = np.zeros((h, w), np.uint8)
        cv2.fillPoly(mask, [np.round(pts).astype(np.int32)], 1)
        on = mask > 0
        colour = wood(rng) if rng.random() < 0.4 else rng.random(3)
        tex = textures[int(rng.integers(0, len(textures)))]
        ys, xs = np.nonzero(on)
        rgb[ys, xs] = colour[None, :] * tex[ys % tex.shape[0], xs % tex.shape[1], None] * rng.uniform(0.5, 1.1)
        labels[on] = OTHER
