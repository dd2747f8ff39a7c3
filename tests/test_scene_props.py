"""`sim.scene_props`: the clutter of the procedural pallet scenes is labelled what it is, never pallet."""

from __future__ import annotations

import numpy as np

from palletpilot.perception.frames import SemanticClass
from palletpilot.sim.pallet_scenes import _textures, render_scene
from palletpilot.sim.scene_props import (
    clutter_box,
    distractor,
    draw_cables,
    drawer_cabinet,
    filled_shelf,
    flying_shapes,
    person,
)

OTHER = int(SemanticClass.OTHER_OBJECT)
DRIVABLE = int(SemanticClass.DRIVABLE)
PALLET = (int(SemanticClass.PALLET_EMPTY), int(SemanticClass.PALLET_FULL))


def test_props_stand_on_their_support_and_are_never_labelled_pallet():
    rng = np.random.default_rng(4)
    for _ in range(30):
        xy, z = rng.uniform(-3, 3, 2), float(rng.choice([0.0, 0.8]))
        for boxes in (
            [clutter_box(rng, xy, 1.0, z)],
            distractor(rng, xy, 1.0, z),
            filled_shelf(rng, xy, 1.0, z),
            drawer_cabinet(rng, xy, 1.0, z),
        ):
            assert all(b.label == OTHER for b in boxes)
            bottom = min(float((b.t - np.abs(b.R) @ (b.size / 2))[2]) for b in boxes)
            assert abs(bottom - z) < 1e-6  # standing on the floor or table, not floating or sunk
        people = person(rng, xy)
        assert all(b.label == int(SemanticClass.PERSON) for b in people)
        top = max(float((b.t + np.abs(b.R) @ (b.size / 2))[2]) for b in people)
        assert 1.4 < top < 2.1  # full size whatever the scene's scale


def test_cables_lie_only_on_the_floor_and_shapes_cover_what_they_paint():
    rng = np.random.default_rng(1)
    labels = np.full((120, 160), int(SemanticClass.VERTICAL), np.uint8)
    labels[60:] = DRIVABLE
    labels[70:90, 40:80] = PALLET[0]
    for _ in range(20):
        lab = labels.copy()
        rgb = np.zeros((120, 160, 3), np.float32)
        draw_cables(rgb, lab, rng, DRIVABLE)
        changed = lab != labels
        assert np.all(labels[changed] == DRIVABLE) and np.all(lab[changed] == OTHER)
        assert np.all(rgb[~changed] == 0)
    textures = _textures(np.random.default_rng(0))
    painted = 0
    for _ in range(20):
        lab = labels.copy()
        rgb = np.zeros((120, 160, 3), np.float32)
        flying_shapes(rgb, lab, rng, textures)
        changed = lab != labels
        assert np.all(lab[changed] == OTHER)
        painted += int(changed.sum() > 0)
    assert painted >= 5  # some frames get shapes, others none


def test_people_and_dense_clutter_appear_in_the_scenes():
    seen_person = sum(bool((render_scene(9, i)[1] == int(SemanticClass.PERSON)).any()) for i in range(24))
    assert 2 <= seen_person <= 20
