"""Segmentation datasets from the simulator: seeded, varied frame bundles."""

import numpy as np

from perception.frames import SemanticClass, load_bundle
from sim.dataset import generate_dataset, pallet_nodes, render_frame


def test_generate_two_frames(tmp_path):
    paths = generate_dataset(tmp_path / "data", 2, seed=5)
    assert [p.name for p in paths] == ["frame_00000.npz", "frame_00001.npz"]
    for p in paths:
        b = load_bundle(p)
        assert b.rgb is not None and b.labels is not None
        assert b.rgb.shape == (480, 640, 3)
        assert "T_forklift_camera_true" in b.truth
        present = set(np.unique(b.labels).tolist())
        assert SemanticClass.FORKS in present and SemanticClass.DRIVABLE in present
    again = render_frame(1, seed=5)
    np.testing.assert_array_equal(again.rgb, load_bundle(paths[1]).rgb)  # deterministic for (seed, index)


def test_pallet_nodes_of_the_example_map():
    ids = [n for n, _ in pallet_nodes()]
    assert "floor_a1" in ids and "rack_b3" in ids
    assert dict(pallet_nodes())["rack_a1"] == 1.0
