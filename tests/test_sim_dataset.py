"""Segmentation datasets from the simulator: seeded, varied frame bundles."""

import numpy as np
import pytest

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
    from palletpilot.sim.dataset import random_scenario

    with pytest.raises(ValueError, match="mounts must be one of all, pickup"):
        random_scenario(np.random.default_rng(0), mounts="steep")


def test_randomised_frames_are_deterministic_and_vary_the_look():
    plain = render_frame(3, seed=5)
    a = render_frame(3, seed=5, randomise=True)
    b = render_frame(3, seed=5, randomise=True)
    np.testing.assert_array_equal(a.rgb, b.rgb)  # still a function of (seed, index)
    np.testing.assert_array_equal(a.labels, b.labels)
    assert a.rgb is not None and plain.rgb is not None
    assert np.abs(a.rgb.astype(int) - plain.rgb.astype(int)).mean() > 5.0  # other colours and light
    same_geometry = a.labels == plain.labels  # the scene is the same apart from pallet types
    assert same_geometry.mean() > 0.5


def test_randomised_scenarios_draw_pallet_types_that_fit():
    from palletpilot.sim.dataset import FLOOR_TYPES, RACK_TYPES, random_scenario

    seen: dict[str, set[str]] = {"floor": set(), "rack": set()}
    film = 0
    for i in range(30):
        rng, style = np.random.default_rng([2, i]), np.random.default_rng([2, i, 1])
        sc, _, _ = random_scenario(rng, style=style)
        for p in sc.pallets:
            seen["rack" if p.node.startswith("rack") else "floor"].add(p.type)
            film += int(p.film)
    assert seen["rack"] <= set(RACK_TYPES) and seen["floor"] <= set(FLOOR_TYPES)
    assert {"industrial", "plastic", "half"} <= seen["floor"] and "plastic" in seen["rack"]
    assert film > 0


def test_random_lighting_and_colours_change_the_look_not_the_labels():
    from palletpilot.sim.dataset import random_lighting, random_scenario, randomise_appearance
    from palletpilot.sim.simulator import Simulator

    for i in range(20):
        light = random_lighting(np.random.default_rng(i))
        assert light.unit_direction()[2] > 0.3  # from above
        assert 0.0 < max(light.colour) < 3.0 and 0.1 < light.ambient < 0.7
    sc, pose, fork_height = random_scenario(np.random.default_rng([5, 7]))
    frames = []
    for styled in (False, True):
        sim = Simulator(sc)
        if styled:
            randomise_appearance(sim, np.random.default_rng(4))
        sim.forklift.state.pose = pose
        sim.forklift.state.fork_height = fork_height
        frames.append(sim.grab())
    np.testing.assert_array_equal(frames[0].labels, frames[1].labels)
    assert frames[0].rgb is not None and frames[1].rgb is not None
    assert np.abs(frames[0].rgb.astype(int) - frames[1].rgb.astype(int)).mean() > 5.0


def test_novel_looks_come_from_outside_the_standard_randomisation():
    from palletpilot.sim.dataset import random_lighting

    for i in range(20):
        light = random_lighting(np.random.default_rng(i), novel=True)
        assert 0.13 < light.unit_direction()[2] < 0.35  # low light (8..20 deg), never drawn for training
    a = render_frame(3, seed=5, randomise=True, novel=True)
    b = render_frame(3, seed=5, novel=True)
    np.testing.assert_array_equal(a.rgb, b.rgb)  # deterministic, and novel implies randomised
    standard = render_frame(3, seed=5, randomise=True)
    assert a.rgb is not None and standard.rgb is not None
    assert np.abs(a.rgb.astype(int) - standard.rgb.astype(int)).mean() > 5.0


def test_segment_dataset_command_renders_novel_looks_and_refuses_unknown_ones(tmp_path, capsys):
    from palletpilot.cli import main

    assert (
        main(["segment", "dataset", str(tmp_path / "novel"), "--frames", "1", "--seed", "5", "--randomise", "novel"])
        == 0
    )
    written = load_bundle(tmp_path / "novel" / "frame_00000.npz")
    np.testing.assert_array_equal(written.rgb, render_frame(0, seed=5, randomise=True, novel=True).rgb)
    with pytest.raises(SystemExit) as exc:
        main(["segment", "dataset", str(tmp_path / "x"), "--frames", "1", "--randomise", "strange"])
    assert exc.value.code == 2
    assert "invalid choice: 'strange'" in capsys.readouterr().err


def test_realism_frames_are_valid_seeded_deterministic_and_keep_the_scene(tmp_path):
    from palletpilot.perception.frames import save_bundle

    for index in (3, 4):
        a = render_frame(index, seed=5, realism=True, mounts="pickup")
        b = render_frame(index, seed=5, realism=True, mounts="pickup")
        for key in ("rgb", "labels", "depth", "K"):
            np.testing.assert_array_equal(getattr(a, key), getattr(b, key))  # a function of (seed, index)
        assert a.truth.keys() == b.truth.keys() and (a.dist is None) == (b.dist is None)
        again = load_bundle(save_bundle(tmp_path / f"{index}.npz", a))  # a valid bundle, written and read back
        np.testing.assert_array_equal(again.rgb, a.rgb)
        if a.dist is not None:
            np.testing.assert_array_equal(again.dist, a.dist)
            np.testing.assert_array_equal(b.dist, a.dist)
        randomised = render_frame(index, seed=5, randomise=True, mounts="pickup")
        assert a.rgb is not None and randomised.rgb is not None
        assert np.abs(a.rgb.astype(int) - randomised.rgb.astype(int)).mean() > 2.0  # another look ...
        if a.dist is None:  # ... of the same scene (its own generator)
            np.testing.assert_array_equal(a.labels, randomised.labels)
            np.testing.assert_array_equal(a.K, randomised.K)
        assert {7, 8} & set(np.unique(a.labels).tolist())  # a pallet in view (Pickup mounts)


def _synthetic_bundle():
    from palletpilot.perception.frames import FrameBundle
    from palletpilot.sim.camera import d435_color_intrinsics

    rng = np.random.default_rng(0)
    labels = np.zeros((480, 640), np.uint8)
    labels[200:260, 250:400] = SemanticClass.PALLET_EMPTY
    labels[:100] = SemanticClass.VERTICAL
    depth = np.full((480, 640), 2.0, np.float32)
    rgb = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    return FrameBundle(depth=depth, K=d435_color_intrinsics(640, 480), labels=labels, rgb=rgb)


def test_camera_effects_are_seeded_and_keep_labels_depth_and_image_aligned():
    from palletpilot.sim.dataset_realism import camera_effects

    bundle = _synthetic_bundle()
    distorted = 0
    for s in range(12):
        a = camera_effects(bundle, np.random.default_rng(s))
        b = camera_effects(bundle, np.random.default_rng(s))
        np.testing.assert_array_equal(a.rgb, b.rgb)
        np.testing.assert_array_equal(a.labels, b.labels)
        assert a.rgb is not None and a.rgb.shape == (480, 640, 3) and a.labels is not None
        assert set(np.unique(a.labels).tolist()) <= {0, 1, 7}  # nearest-neighbour labels: no new classes
        assert np.all(a.depth == 2.0)
        if a.dist is not None:
            distorted += 1
            k1 = a.dist[0]
            assert -0.3 <= k1 <= 0.05 and a.K[0, 0] >= bundle.K[0, 0]  # zoomed in, never out
            assert a.labels[230, 325] == SemanticClass.PALLET_EMPTY  # near the principal point: in place
        else:
            np.testing.assert_array_equal(a.labels, bundle.labels)
    assert 2 <= distorted <= 10


def test_distortion_maps_invert_opencv_projection():
    import cv2

    from palletpilot.sim.camera import d435_color_intrinsics
    from palletpilot.sim.dataset_realism import distortion_maps

    K = d435_color_intrinsics(640, 480)
    dist = np.array([-0.28, 0.06, 0.001, -0.0015, 0.0])
    map_x, map_y, K_out = distortion_maps(K, (480, 640), dist)
    assert K_out[0, 0] > K[0, 0] and K_out[0, 2] == K[0, 2]
    assert 0 <= map_x.min() and map_x.max() <= 639 and 0 <= map_y.min() and map_y.max() <= 479  # no empty border
    v, u = np.mgrid[0:480:40, 0:640:40]
    rays = np.stack([(map_x[v, u] - K[0, 2]) / K[0, 0], (map_y[v, u] - K[1, 2]) / K[1, 1], np.ones(u.shape)], -1)
    seen, _ = cv2.projectPoints(rays.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K_out, dist)
    np.testing.assert_allclose(seen.reshape(-1, 2), np.stack([u.ravel(), v.ravel()], 1), atol=0.05)


def test_worn_pallets_change_colours_only_and_chip_only_blocks():
    from palletpilot.geometry import SE2
    from palletpilot.sim.dataset_realism import wear_pallet
    from palletpilot.sim.world import Texture, pallet_mesh

    mesh = pallet_mesh(SE2(1.0, 2.0, 0.3), cargo_size=(1.0, 0.8, 0.6))
    pallet = mesh.classes == SemanticClass.PALLET_FULL
    chipped = 0
    for s in range(10):
        worn = wear_pallet(mesh, False, np.random.default_rng(s))
        again = wear_pallet(mesh, False, np.random.default_rng(s))
        np.testing.assert_array_equal(worn.albedo, again.albedo)
        np.testing.assert_array_equal(worn.vertices, mesh.vertices)
        np.testing.assert_array_equal(worn.classes, mesh.classes)
        np.testing.assert_array_equal(worn.albedo[~pallet], mesh.albedo[~pallet])  # the load untouched
        assert not np.array_equal(worn.albedo[pallet], mesh.albedo[pallet])
        assert worn.albedo.min() >= 0.0 and worn.albedo.max() <= 1.0
        chip = worn.texture == Texture.CONCRETE
        if chip.any():
            chipped += 1
            vertical_grain = np.abs(mesh.tangent_u[:, 2]) > 0.9
            assert chip.sum() == 9 * 12  # the nine blocks, all of them, twelve triangles each
            assert vertical_grain[chip].sum() >= 9 * 8  # their side faces (the grain runs up them)
        np.testing.assert_array_equal(mesh.texture[pallet & ~chip], worn.texture[pallet & ~chip])
    assert 1 <= chipped <= 9
    assert not np.shares_memory(wear_pallet(mesh, True, np.random.default_rng(0)).albedo, mesh.albedo)


def test_wide_mounts_reach_level_low_and_high_views_of_the_same_scene():
    from palletpilot.sim.dataset import random_scenario

    heights, tilts = [], []
    for i in range(40):
        wide, _, _ = random_scenario(np.random.default_rng([3, i]), mounts="wide")
        plain, _, _ = random_scenario(np.random.default_rng([3, i]), mounts="all")
        assert [p.node for p in wide.pallets] == [p.node for p in plain.pallets]  # same draws after the mount
        heights.append(wide.camera.mount.z)
        tilts.append(wide.camera.mount.tilt_deg)
    assert min(heights) < 0.3 and max(heights) > 1.0 and min(tilts) < 10.0 and max(tilts) > 45.0
    frame = render_frame(2, seed=5, mounts="wide", realism=True)
    assert frame.rgb is not None and frame.rgb.shape == (480, 640, 3)


def test_a_distorted_realism_frame_undistorts_back_to_its_render():
    import cv2

    from palletpilot.perception.distortion import undistort_bundle

    real = render_frame(5, seed=5, realism=True, mounts="pickup")
    assert real.dist is not None and real.dist[0] < -0.1  # this frame has strong barrel distortion
    render = render_frame(5, seed=5, randomise=True, mounts="pickup")
    back = undistort_bundle(real)  # perception's own undistortion, to the zoomed K
    zoom, cx, cy = back.K[0, 0] / render.K[0, 0], render.K[0, 2], render.K[1, 2]
    zoomed = cv2.warpAffine(
        render.labels,
        np.array([[zoom, 0, cx - zoom * cx], [0, zoom, cy - zoom * cy]]),
        (640, 480),
        flags=cv2.INTER_NEAREST,
    )
    seen = back.labels != 255
    assert seen.mean() > 0.95 and (back.labels == zoomed)[seen].mean() > 0.99


def test_segment_dataset_command_renders_real_looks_on_wide_mounts(tmp_path):
    from palletpilot.cli import main

    out = tmp_path / "real"
    args = ["segment", "dataset", str(out), "--frames", "1", "--seed", "7", "--randomise", "real", "--mounts", "wide"]
    assert main(args) == 0
    written = load_bundle(out / "frame_00000.npz")
    same = render_frame(0, seed=7, mounts="wide", realism=True)
    np.testing.assert_array_equal(written.rgb, same.rgb)
    assert (written.dist is None) == (same.dist is None)  # a lens distortion drawn travels with the frame
