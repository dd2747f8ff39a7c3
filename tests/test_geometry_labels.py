"""Labels from depth geometry (issue 37): the pallet, the floor and the forks found without the segmentation
model, a model giving noise changes nothing in the fused mode, and a reason says which source saw a pallet."""

from __future__ import annotations

import dataclasses
import math
from pathlib import Path

import numpy as np
import pytest
import yaml

from palletpilot.bench.pallet import FrameSpec, render
from palletpilot.geometry import SE2, SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.calibration import calibrate
from palletpilot.perception.calibration_io import Calibration
from palletpilot.perception.frames import FrameBundle, SemanticClass
from palletpilot.perception.geometry_labels import (
    LabelsMode,
    calibration_labels,
    load_mask,
    pallet_labels,
    sources_note,
)
from palletpilot.perception.pallet import PalletNotFound, estimate_pallet
from palletpilot.perception.specs import PalletType, load_forks
from palletpilot.sim.scenario import Scenario
from palletpilot.testing import assert_checks, assert_failed, assert_succeeded

MISSIONS = bundled_path("missions")
FORKS = load_forks(MISSIONS / "forks.yaml")
PALLET = (SemanticClass.PALLET_EMPTY, SemanticClass.PALLET_FULL)


def _noise(shape: tuple[int, ...], seed: int = 0) -> np.ndarray:
    """A segmentation model that gives noise: every pixel a random class."""
    return np.random.default_rng(seed).integers(0, 10, shape).astype(np.uint8)


@pytest.fixture(scope="module")
def frames() -> dict[str, tuple[FrameBundle, list[FrameBundle], SE2, float]]:
    """A loaded floor pallet and an empty rack pallet, both misplaced; each with a calibration frame,
    where the pallet should stand (forklift frame) and its support height."""
    out = {}
    for name, node, loaded, height in (("floor", "floor_b2", True, 0.0), ("rack", "rack_a2", False, 1.0)):
        spec = FrameSpec(node, loaded, dx=0.03, dy=-0.18, dyaw_deg=6.0, ahead=0.9, seed=11)
        frame, cal = render(spec, calibration_frames=1)
        out[name] = (frame, cal, SE2(FORKS.tip_x + spec.ahead, 0.0, 0.0), height)
    return out


def _truth(frame: FrameBundle) -> tuple[Calibration, SE3]:
    return Calibration(SE3.from_matrix(frame.truth["T_forklift_camera_true"]), "true"), SE3.from_matrix(
        frame.truth["T_forklift_pallet_true"]
    )


@pytest.mark.parametrize("where", ["floor", "rack"])
def test_geometry_finds_the_pallet_pixels_the_simulator_labels(frames, where):
    frame, _, expected, height = frames[where]
    cal, _ = _truth(frame)
    found = pallet_labels(
        frame, cal.T_forklift_camera_at(frame.fork_height), PalletType.eur(), LabelsMode.GEOMETRY,
        expected=expected, support_height_m=height,
    )  # fmt: skip
    truth = np.isin(frame.truth["labels_true"], PALLET)
    mine = np.isin(found.labels, PALLET)
    assert found.model_px is None and found.geometry_px == mine.sum()
    assert (mine & truth).sum() >= 0.8 * truth.sum()  # most of the pallet
    assert (mine & ~truth).sum() <= 0.25 * mine.sum()  # little else (the floor's noise at its foot)


@pytest.mark.parametrize("where", ["floor", "rack"])
def test_geometry_and_fused_estimate_with_a_model_that_gives_noise(frames, where):
    frame, _, expected, height = frames[where]
    cal, T_true = _truth(frame)
    noisy = dataclasses.replace(frame, labels=_noise(frame.depth.shape))
    with pytest.raises(PalletNotFound):  # the model alone: nothing to go on
        estimate_pallet(noisy, cal, expected=expected, labels=LabelsMode.MODEL, support_height_m=height)
    reference = estimate_pallet(frame, cal, expected=expected, labels=LabelsMode.MODEL, support_height_m=height)
    for mode in (LabelsMode.GEOMETRY, LabelsMode.FUSED):
        est = estimate_pallet(noisy, cal, expected=expected, labels=mode, support_height_m=height)
        err = T_true.inv() @ est.T_forklift_pallet
        assert abs(err.t[1]) < 0.010 and abs(err.t[0]) < 0.020, (mode, err.t)
        assert abs(math.degrees(err.to_se2().yaw)) < 0.6, mode
        assert est.extras["labels"] == mode and est.extras["geometry_pixels"] > 1000
        ref = T_true.inv() @ reference.T_forklift_pallet  # as good as with the simulator's labels
        assert abs(err.t[1]) < abs(ref.t[1]) + 0.005
    fused = estimate_pallet(noisy, cal, expected=expected, labels=LabelsMode.FUSED, support_height_m=height)
    assert fused.extras["model_pixels"] == 0  # noise makes no blob: the model saw nothing


def test_a_load_on_the_pallet_is_cargo_by_geometry(frames):
    frame, _, expected, _ = frames["floor"]
    cal, _ = _truth(frame)
    est = estimate_pallet(frame, cal, expected=expected, labels=LabelsMode.GEOMETRY)
    assert est.extras["deck_pixels"] == 0  # the load hides the deck: no deck yaw from the load's foot


def test_a_reason_says_which_source_saw_the_pallet(frames):
    frame, _, expected, _ = frames["floor"]
    cal, _ = _truth(frame)
    T_cf = cal.T_forklift_camera_at(frame.fork_height)
    # Told the pallet stands on 1 m beams: the geometry sees nothing in that band, the model sees it.
    wrong = pallet_labels(frame, T_cf, PalletType.eur(), LabelsMode.FUSED, expected=expected, support_height_m=1.0)
    assert wrong.geometry_px < 150 < (wrong.model_px or 0)
    assert "only the model sees a pallet" in sources_note(wrong)
    noisy = dataclasses.replace(frame, labels=_noise(frame.depth.shape))
    right = pallet_labels(noisy, T_cf, PalletType.eur(), LabelsMode.FUSED, expected=expected)
    assert "only the geometry sees a pallet" in sources_note(right)
    with pytest.raises(PalletNotFound, match="geometry: 0 pixels"):
        estimate_pallet(frame, cal, expected=expected, labels=LabelsMode.GEOMETRY, support_height_m=1.0)


def test_calibration_from_geometry_alone(frames):
    cal_frame = frames["floor"][1][0]
    T_true = SE3.from_matrix(cal_frame.truth["T_forklift_camera_true"])
    bare = dataclasses.replace(cal_frame, labels=None, rgb=None)
    labels = calibration_labels(bare, FORKS, LabelsMode.GEOMETRY)
    truth_forks = cal_frame.truth["labels_true"] == SemanticClass.FORKS
    mine = labels == SemanticClass.FORKS
    assert (mine & truth_forks).sum() >= 0.85 * truth_forks.sum() and (mine & ~truth_forks).sum() < 0.05 * mine.sum()
    for mode, frame in (
        (LabelsMode.GEOMETRY, bare),
        (LabelsMode.FUSED, dataclasses.replace(cal_frame, labels=_noise(labels.shape))),
    ):
        result = calibrate([frame], FORKS, labels=mode)
        err = T_true.inv() @ result.T_forklift_camera
        assert np.all(np.abs(err.t) < 0.006), (mode, err.t)


class NoiseSegmenter:
    """A segmentation model replaced by noise (the issue's test of geometry first)."""

    def __init__(self, *_: object) -> None:
        self.calls = 0

    def segment(self, rgb: np.ndarray) -> np.ndarray:
        self.calls += 1
        return _noise(rgb.shape[:2], self.calls)


def _mission(tmp_path: Path) -> Path:
    path = tmp_path / "mission.yaml"
    tasks = [{"type": "pickup", "node": "floor_b2"}]
    path.write_text(yaml.safe_dump({"name": "noise", "map": str(MISSIONS / "warehouse.yaml"), "tasks": tasks}))
    return path


def _scenario() -> Scenario:
    sc = Scenario.model_validate(
        {
            "map": "warehouse.yaml",
            "start": "b1",
            "seed": 5,
            "pallets": [{"node": "floor_b2", "dx": 0.10, "dy": -0.22, "dyaw_deg": 7.0, "loaded": True}],
        }
    )
    sc.folder = MISSIONS
    return sc


def test_a_pickup_succeeds_with_the_model_replaced_by_noise(tmp_path, run_mission, monkeypatch):
    monkeypatch.setattr("palletpilot.executor.apps.app.OnnxSegmenter", NoiseSegmenter)
    r = run_mission(_mission(tmp_path), _scenario(), labels="fused")
    assert_succeeded(r)
    assert_checks(r)
    assert r.summary["tasks"][0]["attempts"] >= 2  # found misplaced, re-planned, found aligned
    r = run_mission(_mission(tmp_path), _scenario(), labels="model")
    assert_failed(r, "calibration_failed")  # the model alone finds no forks in noise: the truck stays stopped
    assert abs(r.sim.speed) < 1e-3 and not r.sim.pallets[0].carried


def test_pixels_without_a_return_count_as_seen_past_the_face(frames):
    # A time-of-flight camera returns no depth where a ray passes the pallet and meets nothing in range:
    # through the pockets and beside the face. Those pixels are evidence of the open pockets and sides.
    frame, _, expected, height = frames["rack"]
    cal, T_true = _truth(frame)
    T_cf = cal.T_forklift_camera_at(frame.fork_height)
    face = float(np.median(frame.depth[np.isin(frame.truth["labels_true"], PALLET)]))
    d = frame.depth.copy()
    d[d > face + 1.3] = 0.0  # nothing behind the pallet returns (the rack's back, the far wall)
    tof = dataclasses.replace(frame, depth=d)
    est = estimate_pallet(tof, cal, expected=expected, labels=LabelsMode.GEOMETRY, support_height_m=height)
    err = T_true.inv() @ est.T_forklift_pallet
    assert abs(err.t[1]) < 0.010 and abs(math.degrees(err.to_se2().yaw)) < 0.6
    assert all(abs(w - 0.2275) < 0.01 for w in est.pocket_widths_m), est.pocket_widths_m
    from palletpilot.perception.pallet import DEFAULT_CONFIG
    from palletpilot.perception.pallet_face import _no_return_rays

    rs, cs = slice(0, d.shape[0]), slice(0, d.shape[1])
    assert len(_no_return_rays(tof, T_cf, rs, cs, height, DEFAULT_CONFIG).w) > 1000  # they are used
    off = dataclasses.replace(DEFAULT_CONFIG, no_return_range_m=0.0)
    assert len(_no_return_rays(tof, T_cf, rs, cs, height, off).w) == 0


def test_the_deck_layer_of_a_loaded_pallet_is_told_by_ray_not_by_noisy_depth():
    """A loaded pallet's deck layer (cross board and deck front, above the pockets) is masked wherever depth
    noise puts its pixels along their rays, and the block layer below never is: a cut on the noisy points
    kept the deck-layer pixels that noise put far (and, looking down, low), which pushed the face fit back."""
    pallet = PalletType.eur()
    cam = np.array([0.0, 0.0, 1.6])  # forklift frame; the entry face 3.5 m ahead, where depth scatters ~5 cm
    T_fp = SE3(None, (3.5, 0.0, 0.0))
    ys, zs = np.meshgrid(np.linspace(-0.38, 0.38, 40), np.linspace(0.01, 0.14, 27))
    face = np.stack([np.full_like(ys, 3.5), ys, zs], axis=-1)  # the entry face's true points
    load = np.stack([np.full_like(ys, 3.52), ys, 0.17 + 4 * zs], axis=-1)  # a load's front above the deck
    true = np.concatenate([face, load])
    ray = (true - cam) / (true[..., :1] - cam[0])  # per unit forklift x, as depth noise moves a point
    rng = np.random.default_rng(3)
    points = true + ray * rng.normal(0.0, 0.05, true.shape[:2])[..., None]
    mask, loaded = load_mask(points, T_fp, pallet, cam)
    assert loaded
    layer, z = mask[: len(face)], face[..., 2]
    assert layer[(z > pallet.pocket_height + 0.002) & (z < pallet.height)].all()
    assert not layer[z < pallet.pocket_height - 0.002].any()
