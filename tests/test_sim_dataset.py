"""Segmentation datasets from the simulator: seeded, varied frame bundles."""

import numpy as np

from palletpilot.perception.frames import SemanticClass, load_bundle
from palletpilot.sim.dataset import generate_dataset, pallet_nodes, render_frame


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


def test_pickup_mounts_are_the_ones_calibrate_accepts():
    from palletpilot.perception.calibration_io import mount_angles
    from palletpilot.perception.specs import PalletType, load_forks
    from palletpilot.perception.view import pickup_view
    from palletpilot.sim.camera import d435_color_intrinsics
    from palletpilot.sim.dataset import MISSIONS_DIR, random_scenario

    forks = load_forks(MISSIONS_DIR / "forks.yaml")
    tilts = {"all": [], "pickup": []}
    for mounts, found in tilts.items():
        for i in range(40):
            sc, _, _ = random_scenario(np.random.default_rng([3, i]), mounts=mounts)
            T = sc.camera.mount.T_forklift_camera()
            view = pickup_view(T, d435_color_intrinsics(640, 480), (640, 480), forks, PalletType.eur())
            if mounts == "pickup":
                assert view.problems() == []
            found.append(np.degrees(mount_angles(T)[0]))
    assert max(tilts["all"]) > 30.0  # the full set has mounts too steep for the Pickup ...
    assert max(tilts["pickup"]) < 28.0  # ... the pickup set none


def test_unknown_mount_set_is_refused():
    import pytest

    from palletpilot.sim.dataset import random_scenario

    with pytest.raises(ValueError, match="mounts must be one of all, pickup"):
        random_scenario(np.random.default_rng(0), mounts="steep")
