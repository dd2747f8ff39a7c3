"""The simulated RGB-D camera: depth geometry, the D435 noise model, labels where the geometry says."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.frames import FrameBundle, SemanticClass
from palletpilot.perception.specs import PalletType, load_forks
from palletpilot.sim.camera import (
    CameraModel,
    CameraNoise,
    RaycastRenderer,
    camera_mount_pose,
    d435_color_intrinsics,
    d435_depth_focal_px,
    perturb_labels,
    render,
)
from palletpilot.sim.depth_artefacts import depth_scale
from palletpilot.sim.world import (
    example_world,
    floor_mesh,
    forks_mesh,
    object_box_mesh,
    pallet_mesh,
    wall_mesh,
)

FORKS_FILE = bundled_path("missions") / "forks.yaml"
CAMERA = CameraModel.d435(640, 480)
# Mount: on the carriage, 45 cm above the fork bottoms, 5 cm ahead of the heels, pitched 30 deg down.
T_FORKLIFT_CAMERA0 = camera_mount_pose((0.05, 0.0, 0.45), np.deg2rad(30.0))


def _pixel_rays(K: np.ndarray, width: int, height: int) -> np.ndarray:
    """(H, W, 3) camera-frame points on the z = 1 plane through every pixel centre."""
    u, v = np.meshgrid(np.arange(width), np.arange(height))
    pix = np.stack([u, v, np.ones_like(u)], axis=-1).astype(float)
    return pix @ np.linalg.inv(K).T


def _project(points_camera: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel (u, v) of camera-frame points, with OpenCV (independent of the renderer)."""
    pix, _ = cv2.projectPoints(points_camera.reshape(-1, 1, 3), np.zeros(3), np.zeros(3), K, None)
    return pix.reshape(-1, 2)


@pytest.fixture(scope="module")
def floor_renderer() -> RaycastRenderer:
    return RaycastRenderer([floor_mesh(-30.0, -30.0, 30.0, 30.0)])


def test_intrinsics_are_d435_like() -> None:
    k640, k848 = d435_color_intrinsics(640, 480), d435_color_intrinsics(848, 480)
    assert k640[0, 0] == pytest.approx(612.0, abs=3.0)
    hfov = np.degrees(2 * np.arctan(424 / k848[0, 0]))
    vfov = np.degrees(2 * np.arctan(240 / k848[1, 1]))
    assert hfov == pytest.approx(69.4, abs=1.0) and vfov == pytest.approx(42.5, abs=1.0)
    assert d435_depth_focal_px(640, 480) == pytest.approx(384.0)
    assert d435_depth_focal_px(848, 480) == pytest.approx(424.0)


def test_mount_pose_looks_forward_and_down() -> None:
    tilt = np.deg2rad(30.0)
    z_axis = T_FORKLIFT_CAMERA0.apply_vectors([0.0, 0.0, 1.0])  # optical axis in the forklift frame
    np.testing.assert_allclose(z_axis, [np.cos(tilt), 0.0, -np.sin(tilt)], atol=1e-12)
    x_axis = T_FORKLIFT_CAMERA0.apply_vectors([1.0, 0.0, 0.0])  # image right = forklift -y
    np.testing.assert_allclose(x_axis, [0.0, -1.0, 0.0], atol=1e-12)


def test_floor_depth_matches_plane_noise_off(floor_renderer: RaycastRenderer) -> None:
    T_world_camera = (
        SE3.from_xyz_rpy((1.0, 2.0, 0.0), (0.0, 0.0, 0.3))
        @ SE3.from_translation(0, 0, 0.3)
        @ (camera_mount_pose((0.05, 0.02, 0.45), np.deg2rad(25.0), pan=0.05, roll=0.03))
    )
    fb = floor_renderer.render(T_world_camera, CAMERA, CameraNoise.off())
    rays_cam = _pixel_rays(CAMERA.K, CAMERA.width, CAMERA.height)
    dirs_world = rays_cam @ T_world_camera.R.T
    with np.errstate(divide="ignore"):
        z_true = -T_world_camera.t[2] / dirs_world[..., 2]  # ray parameter on z = 0 == z-depth (unit z)
    expected_hit = (dirs_world[..., 2] < 0) & (z_true <= CAMERA.max_depth_m) & (z_true >= CAMERA.min_depth_m)
    valid = fb.valid_depth()
    # Near the range limit float32 rounding may flip a pixel; everywhere else validity must agree.
    unsure = np.abs(z_true - CAMERA.max_depth_m) < 1e-3
    assert np.array_equal(valid[~unsure], expected_hit[~unsure])
    assert valid.sum() > 0.4 * valid.size
    np.testing.assert_allclose(fb.depth[valid], z_true[valid], rtol=0, atol=1e-4)
    # Back-projected with the same K, every pixel lands on the floor plane z = 0.
    points_world = T_world_camera.apply(rays_cam[valid] * fb.depth[valid][:, None].astype(float))
    assert np.abs(points_world[:, 2]).max() < 1e-4
    assert np.all(fb.labels[valid] == SemanticClass.DRIVABLE)


def test_depth_is_z_depth_not_ray_length() -> None:
    wall = wall_mesh((3.0, -20.0), (3.0, 20.0), height=10.0, thickness=0.2)  # face at x = 2.9
    T_world_camera = SE3.from_translation(0.0, 0.0, 1.5) @ camera_mount_pose((0.0, 0.0, 0.0), 0.0)
    fb = render([wall], T_world_camera, CAMERA.K, CAMERA.width, CAMERA.height)
    assert fb.valid_depth().all()
    np.testing.assert_allclose(fb.depth, 2.9, atol=1e-5)  # the corner rays are ~20 % longer
    assert np.all(fb.labels == SemanticClass.VERTICAL)


def test_no_depth_closer_than_min_range_but_labels_stay() -> None:
    wall = wall_mesh((0.2, -5.0), (0.2, 5.0), height=4.0, thickness=0.001)
    T_world_camera = SE3.from_translation(0.0, 0.0, 1.0) @ camera_mount_pose((0.0, 0.0, 0.0), 0.0)
    fb = render([wall], T_world_camera, CAMERA.K, CAMERA.width, CAMERA.height)
    assert np.all(fb.depth == 0.0)
    assert np.all(fb.labels == SemanticClass.VERTICAL)


def test_noise_spread_matches_d435_model(floor_renderer: RaycastRenderer) -> None:
    T_world_camera = SE3.from_translation(0.0, 0.0, 1.2) @ camera_mount_pose((0.0, 0.0, 0.0), np.deg2rad(35.0))
    truth = floor_renderer.render(T_world_camera, CAMERA, CameraNoise.off()).depth
    # The zero-mean part only: no scale error (a bias, tested below).
    noise = CameraNoise(flying_pixel_rate=0.0, invalid_rate=0.01, depth_scale_error=0.0, lighting_variation=False)
    rng = np.random.default_rng(7)
    frames = [floor_renderer.render(T_world_camera, CAMERA, noise, rng).depth for _ in range(3)]
    measured = np.stack(frames)
    true = np.broadcast_to(truth, measured.shape)
    ok = (true > 0) & (measured > 0)
    # Dropouts at the configured rate (pixels with true depth).
    dropped = ((true > 0) & (measured == 0)).sum() / (true > 0).sum()
    assert dropped == pytest.approx(0.01, abs=0.003)
    for lo, hi in ((1.2, 1.6), (1.6, 2.2), (2.2, 3.0), (3.0, 4.5)):
        sel = ok & (true >= lo) & (true < hi)
        assert sel.sum() > 5000
        err = measured[sel] - true[sel]
        predicted = np.sqrt(np.mean(noise.sigma_z(true[sel], CAMERA.depth_focal_px) ** 2))
        assert abs(err.mean()) < 0.1 * predicted
        assert err.std() == pytest.approx(predicted, rel=0.10), (lo, hi)
    # sigma(z) = z^2 s / (f B): 2 m at 384 px -> 16.7 mm.
    assert noise.sigma_z(2.0, 384.0) == pytest.approx(4 * 0.08 / (384 * 0.05))


def test_flying_pixels_lie_between_foreground_and_background() -> None:
    world = [
        floor_mesh(-10.0, -10.0, 20.0, 10.0),
        wall_mesh((6.0, -10.0), (6.0, 10.0)),
        pallet_mesh(SE2(2.0, 0.0, 0.0), cargo_size=(1.2, 0.8, 1.2)),
    ]
    T_world_camera = SE3.from_translation(0.0, 0.0, 0.8) @ camera_mount_pose((0.0, 0.0, 0.0), np.deg2rad(5.0))
    renderer = RaycastRenderer(world)
    clean = renderer.render(T_world_camera, CAMERA, CameraNoise.off()).depth
    only_flying = CameraNoise(
        disparity_sigma_px=0.0,
        depth_unit_m=0.0,
        invalid_rate=0.0,
        flying_pixel_rate=1.0,
        stereo_shadow=False,
        depth_scale_error=0.0,
        rgb_sigma=0.0,
        lighting_variation=False,
    )
    noisy = renderer.render(T_world_camera, CAMERA, only_flying, np.random.default_rng(3)).depth
    changed = np.abs(noisy - clean) > 1e-6
    assert 50 < changed.sum() < 0.05 * changed.size
    far = np.where(clean > 0, clean, np.float32(1e3))
    kernel = np.ones((3, 3), np.uint8)
    lo, hi = cv2.erode(far, kernel), cv2.dilate(far, kernel)
    assert np.all(noisy[changed] >= lo[changed] - 1e-5)
    assert np.all(noisy[changed] <= np.minimum(hi[changed], CAMERA.max_depth_m) + 1e-5)
    assert np.all(hi[changed] - lo[changed] > 0.05 * lo[changed])  # only at depth edges


@pytest.fixture(scope="module")
def pickup_view() -> tuple:
    forks = load_forks(FORKS_FILE)
    world = example_world()
    lift = 0.1
    T_world_camera = world.T_world_forklift @ SE3.from_translation(0.0, 0.0, lift) @ T_FORKLIFT_CAMERA0
    renderer = RaycastRenderer(world.static)
    fb = renderer.render(
        T_world_camera,
        CAMERA,
        CameraNoise.off(),
        dynamic=[forks_mesh(forks, lift, world.T_world_forklift)],
        fork_height=lift,
    )
    return forks, world, lift, T_world_camera, fb


def _labels_at(fb: FrameBundle, points_world: np.ndarray, T_world_camera: SE3) -> tuple[np.ndarray, np.ndarray]:
    points_camera = T_world_camera.inv().apply(points_world)
    uv = np.rint(_project(points_camera, fb.K)).astype(int)
    assert np.all((uv >= 0) & (uv < [fb.width, fb.height])), "test point outside the image"
    return fb.labels[uv[:, 1], uv[:, 0]], fb.depth[uv[:, 1], uv[:, 0]] - points_camera[:, 2]


def test_fork_floor_and_pallet_labels_fall_where_the_geometry_says(pickup_view: tuple) -> None:
    forks, world, lift, T_world_camera, fb = pickup_view
    assert fb.fork_height == lift
    # Fork tops (forklift frame), along both blades.
    xs = np.linspace(0.5, forks.tip_x - 0.05, 6)
    fork_tops = np.array([(x, y, lift + forks.thickness) for x in xs for y in forks.centres_y])
    labels, depth_err = _labels_at(fb, world.T_world_forklift.apply(fork_tops), T_world_camera)
    assert np.all(labels == SemanticClass.FORKS)
    assert np.abs(depth_err).max() < 2e-3  # z-depth at the pixel centre vs the point (pixel rounding)
    # The floor between the forks and beside them.
    floor = np.array([(0.6, 0.0, 0.0), (0.9, 0.0, 0.0), (1.5, 0.45, 0.0), (1.5, -0.45, 0.0), (1.6, 0.0, 0.0)])
    labels, depth_err = _labels_at(fb, world.T_world_forklift.apply(floor), T_world_camera)
    assert np.all(labels == SemanticClass.DRIVABLE)
    assert np.abs(depth_err).max() < 5e-3
    # Floor right under a raised fork is hidden by it (occlusion, not a label lookup by position).
    under = np.array([(0.9, y, 0.0) for y in forks.centres_y])
    labels, _ = _labels_at(fb, world.T_world_forklift.apply(under), T_world_camera)
    assert np.all(labels == SemanticClass.FORKS)
    # Pallet (loaded, so pallet-full): front faces of the three entry-side blocks and the cross board.
    pallet = world.pallet
    block_faces = [(0.0, 0.5 * (y0 + y1), 0.06) for y0, y1 in pallet.column_bounds_y()]
    block_faces.append((0.0, 0.0, 0.111))
    labels, depth_err = _labels_at(fb, world.T_world_pallet.apply(np.array(block_faces)), T_world_camera)
    assert np.all(labels == SemanticClass.PALLET_FULL)
    assert np.abs(depth_err).max() < 5e-3
    # The cargo above it, and the floor seen through the open pockets.
    labels, _ = _labels_at(fb, world.T_world_pallet.apply(np.array([[0.05, 0.0, 0.18]])), T_world_camera)
    assert labels[0] == SemanticClass.CARGO
    pockets = np.array([(0.0, y, 0.04) for y in pallet.pocket_centres_y])
    labels, _ = _labels_at(fb, world.T_world_pallet.apply(pockets), T_world_camera)
    assert np.all(labels == SemanticClass.DRIVABLE)


def test_empty_pallet_is_pallet_empty() -> None:
    world = [floor_mesh(-5.0, -5.0, 10.0, 5.0), pallet_mesh(SE2(2.0, 0.0, 0.0), PalletType.eur())]
    T_world_camera = SE3.from_translation(0.0, 0.0, 0.6) @ camera_mount_pose((0.0, 0.0, 0.0), np.deg2rad(15.0))
    fb = render(world, T_world_camera, CAMERA.K, CAMERA.width, CAMERA.height)
    present = set(np.unique(fb.labels).tolist())
    assert SemanticClass.PALLET_EMPTY in present
    assert not present & {SemanticClass.PALLET_FULL, SemanticClass.CARGO}


def test_rgb_is_shaded_per_class(pickup_view: tuple) -> None:
    *_, fb = pickup_view
    assert fb.rgb is not None and fb.rgb.shape == (CAMERA.height, CAMERA.width, 3)
    forks_mean = fb.rgb[fb.labels == SemanticClass.FORKS].mean(axis=0)
    floor_mean = fb.rgb[fb.labels == SemanticClass.DRIVABLE].mean(axis=0)
    assert forks_mean.mean() < 0.5 * floor_mean.mean()  # dark steel against grey concrete
    assert fb.rgb[fb.labels == SemanticClass.DRIVABLE].std(axis=0).mean() > 3.0  # textured, not flat


def test_rendering_is_deterministic_for_a_seed(pickup_view: tuple) -> None:
    forks, world, lift, T_world_camera, _ = pickup_view
    renderer = RaycastRenderer(world.static)
    dynamic = [forks_mesh(forks, lift, world.T_world_forklift)]
    noise = CameraNoise(label_noise=True)
    a = renderer.render(T_world_camera, CAMERA, noise, np.random.default_rng(11), dynamic=dynamic)
    b = renderer.render(T_world_camera, CAMERA, noise, np.random.default_rng(11), dynamic=dynamic)
    c = renderer.render(T_world_camera, CAMERA, noise, np.random.default_rng(12), dynamic=dynamic)
    assert np.array_equal(a.depth, b.depth) and np.array_equal(a.labels, b.labels) and np.array_equal(a.rgb, b.rgb)
    assert not np.array_equal(a.depth, c.depth)
    with pytest.raises(ValueError, match="rng"):
        renderer.render(T_world_camera, CAMERA, noise, None, dynamic=dynamic)


def test_label_noise_moves_only_class_boundaries(pickup_view: tuple) -> None:
    *_, fb = pickup_view
    noisy = perturb_labels(fb.labels, 2, np.random.default_rng(5))
    changed = noisy != fb.labels
    assert changed.any()
    kernel = np.ones((5, 5), np.uint8)  # within 2 px of a boundary
    near_boundary = cv2.dilate(fb.labels, kernel) != cv2.erode(fb.labels, kernel)
    assert np.all(near_boundary[changed])
    assert changed.sum() < 0.1 * changed.size


# -- stereo shadow and depth scale error ---------------------------------------------------------------

# Only the stereo shadow: no disparity noise, quantisation, dropouts, flying pixels or scale error.
ONLY_SHADOW = CameraNoise(
    disparity_sigma_px=0.0,
    depth_unit_m=0.0,
    invalid_rate=0.0,
    flying_pixel_rate=0.0,
    depth_scale_error=0.0,
    rgb_sigma=0.0,
    lighting_variation=False,
)


def _shadowed(renderer: RaycastRenderer, T_world_camera: SE3, noise: CameraNoise) -> tuple[np.ndarray, FrameBundle]:
    """Pixels with exact depth that lose it with `noise` (seed 1), and the exact frame."""
    clean = renderer.render(T_world_camera, CAMERA, CameraNoise.off())
    noisy = renderer.render(T_world_camera, CAMERA, noise, np.random.default_rng(1))
    gone = (clean.depth > 0) & (noisy.depth == 0)
    # Nothing else changes (but float32 rounding: the depth goes through a disparity and back).
    np.testing.assert_allclose(noisy.depth[~gone], clean.depth[~gone], rtol=1e-6, atol=0)
    return gone, clean


def test_stereo_shadow_is_a_band_left_of_a_box_of_the_expected_width() -> None:
    box = object_box_mesh(SE2(2.0, 0.0, 0.0), (0.4, 0.4, 0.6))  # front face at x = 1.8 m
    renderer = RaycastRenderer([floor_mesh(-5.0, -10.0, 30.0, 10.0), box])
    T_world_camera = SE3.from_translation(0.0, 0.0, 0.8) @ camera_mount_pose((0.0, 0.0, 0.0), np.deg2rad(12.0))
    gone, clean = _shadowed(renderer, T_world_camera, ONLY_SHADOW)
    on_box = clean.labels == SemanticClass.OTHER_OBJECT
    fb = CAMERA.K[0, 0] * ONLY_SHADOW.baseline_m
    expected_band = np.zeros_like(gone)
    widths = []
    for v in np.flatnonzero(on_box.any(axis=1)):
        u_box = np.flatnonzero(on_box[v])[0]  # the box's left edge in this row
        band = np.flatnonzero(gone[v])
        # The floor point just left of the band: the right imager sees it past the box's edge.
        u_floor = (band.min() if band.size else u_box) - 1
        assert clean.labels[v, u_floor] == SemanticClass.DRIVABLE
        width = fb * (1.0 / clean.depth[v, u_box] - 1.0 / clean.depth[v, u_floor])
        assert band.size == pytest.approx(width, abs=1.0), v
        if band.size:
            assert band.max() == u_box - 1 and band.size == band.max() - band.min() + 1  # contiguous, at the box
            expected_band[v, band.min() : u_box] = True
        widths.append(width)
    assert max(widths) > 8.0  # a real band: the box top's far edge against the floor 1 m behind it
    assert np.array_equal(gone, expected_band)  # no shadow anywhere else (open floor, right of the box)
    # Without the stereo shadow (everything else equal): no band.
    gone_off, _ = _shadowed(renderer, T_world_camera, ONLY_SHADOW.model_copy(update={"stereo_shadow": False}))
    assert not gone_off.any()


def test_stereo_shadow_leaves_the_open_floor_whole(floor_renderer: RaycastRenderer) -> None:
    T_world_camera = SE3.from_translation(0.0, 0.0, 1.1) @ camera_mount_pose(
        (0.0, 0.0, 0.0), np.deg2rad(40.0), pan=0.2, roll=0.15
    )
    gone, clean = _shadowed(floor_renderer, T_world_camera, ONLY_SHADOW)
    assert clean.valid_depth().mean() > 0.9 and not gone.any()


def test_stereo_shadow_of_a_thin_pole_is_detached_and_as_wide_as_the_pole() -> None:
    # A 2 cm pole 0.6 m ahead of a wall 3 m away: the right imager sees the wall between the pole and
    # its shadow, which is the pole's width, fB (1/0.6 - 1/3) px to the left of the pole.
    pole = object_box_mesh(SE2(0.61, 0.0, 0.0), (0.02, 0.02, 3.0))  # front face at x = 0.6 m
    renderer = RaycastRenderer([wall_mesh((3.1, -10.0), (3.1, 10.0), height=6.0), pole])
    T_world_camera = SE3.from_translation(0.0, 0.0, 1.5) @ camera_mount_pose((0.0, 0.0, 0.0), 0.0)
    gone, clean = _shadowed(renderer, T_world_camera, ONLY_SHADOW)
    v = CAMERA.height // 2
    on_pole = np.flatnonzero(clean.labels[v] == SemanticClass.OTHER_OBJECT)
    band = np.flatnonzero(gone[v])
    shift = CAMERA.K[0, 0] * ONLY_SHADOW.baseline_m * (1.0 / 0.6 - 1.0 / 3.0)  # ~41 px
    assert on_pole.size == pytest.approx(0.02 * CAMERA.K[0, 0] / 0.6, abs=1.0)  # ~20 px
    assert band.size == pytest.approx(on_pole.size, abs=1.0)
    assert band.size == band.max() - band.min() + 1
    assert band.min() == pytest.approx(on_pole.min() - shift, abs=1.0)
    assert band.max() < on_pole.min() - 15  # detached: the wall shows between
    assert np.array_equal(gone.any(axis=1), (clean.labels == SemanticClass.OTHER_OBJECT).any(axis=1))


def test_depth_scale_error_is_fixed_per_camera_and_seeded(floor_renderer: RaycastRenderer) -> None:
    T_world_camera = SE3.from_translation(0.0, 0.0, 1.2) @ camera_mount_pose((0.0, 0.0, 0.0), np.deg2rad(35.0))
    true = floor_renderer.render(T_world_camera, CAMERA, CameraNoise.off())
    assert "depth_scale_true" not in true.truth
    ideal = floor_renderer.render(T_world_camera, CAMERA, CameraNoise.off(), np.random.default_rng(1))
    assert np.array_equal(ideal.depth, true.depth)  # off: ratio exactly 1, whatever the generator
    noise = CameraNoise(invalid_rate=0.0, flying_pixel_rate=0.0, rgb_sigma=0.0, lighting_variation=False)
    assert noise.depth_scale_error == 0.003 and noise.stereo_shadow  # on by default
    assert not CameraNoise.off().stereo_shadow and CameraNoise.off().depth_scale_error == 0.0
    scales = []
    for seed in (1, 2, 3):
        rng = np.random.default_rng(seed)
        frames = [floor_renderer.render(T_world_camera, CAMERA, noise, rng) for _ in range(2)]
        s = float(frames[0].truth["depth_scale_true"])
        assert float(frames[1].truth["depth_scale_true"]) == s  # one camera, one scale
        again = floor_renderer.render(T_world_camera, CAMERA, noise, np.random.default_rng(seed))
        assert float(again.truth["depth_scale_true"]) == s  # deterministic for a seed
        assert abs(s) <= 0.003
        for frame in frames:
            ok = (true.depth > 1.0) & (true.depth < 3.0) & (frame.depth > 0)
            assert ok.sum() > 50000
            ratio = frame.depth[ok] / true.depth[ok]
            assert ratio.mean() == pytest.approx(1.0 + s, abs=2e-4), seed
        scales.append(s)
    assert len(set(scales)) == 3 and max(scales) - min(scales) > 1e-4
    # Off: the true depth (to float32 rounding: the depth still goes through a disparity and back).
    frame = floor_renderer.render(T_world_camera, CAMERA, ONLY_SHADOW, np.random.default_rng(1))
    assert float(frame.truth["depth_scale_true"]) == 0.0
    ok = true.depth > 0
    assert np.array_equal(frame.depth > 0, ok)
    assert np.abs(frame.depth[ok] / true.depth[ok] - 1.0).max() < 1e-6
    with pytest.raises(ValueError, match="depth_scale_error"):
        CameraNoise(depth_scale_error=0.06)


def test_depth_scale_survives_a_generator_state_restore() -> None:
    a = np.random.default_rng(5)
    a.random(1000)  # a camera that has rendered for a while
    b = np.random.default_rng(99)
    b.bit_generator.state = a.bit_generator.state  # as a simulator snapshot restores it
    assert depth_scale(a, 0.003) == depth_scale(b, 0.003) != depth_scale(np.random.default_rng(6), 0.003)
    assert depth_scale(a, 0.0) == 0.0
