"""Segmentation service: the shipped ONNX model on a fresh simulator frame, metadata, errors, ensure_labels."""

import numpy as np
import pytest

from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle, SemanticClass
from palletpilot.perception.segmentation import (
    DEFAULT_MODEL,
    GroundTruthSegmenter,
    OnnxSegmenter,
    SegmentationScore,
    SegmentationService,
    confusion,
    ensure_labels,
    evaluate_segmenter,
    iou_from_confusion,
    load_hidden_mask,
)
from palletpilot.sim.scenario import load_scenario
from palletpilot.sim.simulator import Simulator

MISSIONS = bundled_path("missions")


@pytest.fixture(scope="module")
def segmenter() -> OnnxSegmenter:
    return OnnxSegmenter(DEFAULT_MODEL)


@pytest.fixture(scope="module")
def sim_frame() -> FrameBundle:
    """A freshly rendered frame (D435 noise, lighting variation) from the floor scenario's pre-pallet node."""
    sc = load_scenario(MISSIONS / "scenario_floor.yaml")
    sc.camera.noise = sc.camera.noise.model_copy(update={"label_noise": False})  # exact truth to score against
    sim = Simulator(sc, seed=123)
    sim.set_fork_height(0.03)
    for _ in range(20):
        sim.step()
    return sim.grab()


def test_shipped_model_is_small_and_has_its_metadata(segmenter):
    assert DEFAULT_MODEL.stat().st_size <= 10 * 1024 * 1024
    assert segmenter.input_size == (640, 480)  # full D435 colour resolution: no resize for camera frames
    assert segmenter.info.labels_output == "labels"
    assert segmenter.info.class_ids == tuple(range(10))
    assert segmenter.info.class_names[SemanticClass.PALLET_FULL] == "pallet_full"
    assert len(segmenter.info.mean) == 3 and len(segmenter.info.std) == 3
    assert "CPUExecutionProvider" in segmenter.providers
    assert isinstance(segmenter, SegmentationService)


def test_shipped_model_segments_a_fresh_sim_frame(segmenter, sim_frame):
    labels = segmenter.segment(sim_frame.rgb)
    assert labels.shape == sim_frame.labels.shape and labels.dtype == np.uint8
    iou = iou_from_confusion(confusion(sim_frame.labels, labels))
    assert iou[SemanticClass.DRIVABLE] > 0.9
    assert iou[SemanticClass.FORKS] > 0.9
    assert iou[SemanticClass.PALLET_EMPTY] > 0.6  # the misplaced empty pallet ahead


def test_labels_output_is_the_argmax_of_the_logits(segmenter, sim_frame):
    fast = segmenter.segment(sim_frame.rgb)  # the model's in-graph argmax (frame size = input size)
    logits = segmenter.logits(sim_frame.rgb)
    assert logits.shape == (10, 480, 640)
    np.testing.assert_array_equal(fast, logits.argmax(axis=0).astype(np.uint8))


def test_other_frame_sizes_go_through_the_logits(segmenter, sim_frame):
    half = sim_frame.rgb[::2, ::2].copy()  # 320 x 240: resized up to the input, logits resized back
    labels = segmenter.segment(half)
    assert labels.shape == (240, 320) and labels.dtype == np.uint8
    iou = iou_from_confusion(confusion(sim_frame.labels[::2, ::2], labels))
    assert iou[SemanticClass.DRIVABLE] > 0.9 and iou[SemanticClass.FORKS] > 0.9


def test_labels_output_must_exist(tmp_path):
    onnx = pytest.importorskip("onnx")
    proto = onnx.load(str(DEFAULT_MODEL))
    for entry in proto.metadata_props:
        if entry.key == "labels_output":
            entry.value = "nope"
    path = tmp_path / "badlabels.onnx"
    onnx.save(proto, str(path))
    with pytest.raises(PerceptionError, match=r"badlabels\.onnx: metadata labels_output 'nope' is not an output"):
        OnnxSegmenter(path)


def test_evaluate_segmenter_pools_pixels(sim_frame):
    result = evaluate_segmenter(GroundTruthSegmenter.from_bundle(sim_frame), [sim_frame])
    assert result["frames"] == 1
    assert result["iou"]["drivable"] == 1.0 and result["iou"]["forks"] == 1.0
    assert result["iou"]["other_vehicle"] is None


def _pallets_scene() -> np.ndarray:
    """Labels with three pallets: one cut off by the top edge, one under its load, one inside the image."""
    labels = np.full((60, 80), SemanticClass.DRIVABLE, dtype=np.uint8)
    labels[0:10, 5:25] = SemanticClass.PALLET_EMPTY  # cut off at the top: a load could stand on it unseen
    labels[0:8, 30:50] = SemanticClass.CARGO  # loaded pallet whose load is in view ...
    labels[8:14, 30:50] = SemanticClass.PALLET_FULL  # ... cut off at the top at its side
    labels[0:12, 55:75] = SemanticClass.PALLET_FULL  # loaded pallet whose load is out of view
    labels[30:40, 20:40] = SemanticClass.PALLET_EMPTY  # fully in view, the space above it too
    labels[13, 30:50] = SemanticClass.PALLET_FULL
    labels[0:14, 50] = SemanticClass.PALLET_FULL  # joins the middle pallet to the top row
    return labels


def test_load_hidden_mask_marks_pallets_cut_off_where_their_load_would_be():
    labels = _pallets_scene()
    hidden = load_hidden_mask(labels)
    assert hidden[0:10, 5:25].all()  # empty pallet at the top edge
    assert hidden[0:12, 55:75].all()  # loaded pallet whose load is out of view
    assert not hidden[8:14, 30:51].any()  # the load next to it shows the pallet is loaded
    assert not hidden[30:40, 20:40].any()  # inside the image
    assert not hidden[labels == SemanticClass.CARGO].any()


def test_segmentation_score_either_pallet_class_counts_only_where_the_load_is_hidden():
    truth = _pallets_scene()
    pred = truth.copy()
    pred[0:10, 5:25] = SemanticClass.PALLET_FULL  # wrong class on the hidden-load pallet
    pred[30:40, 20:30] = SemanticClass.PALLET_FULL  # wrong class on the pallet in full view
    score = SegmentationScore()
    score.add(truth, pred)
    result = score.result()
    empty_px = int((truth == SemanticClass.PALLET_EMPTY).sum())
    assert result["iou"]["pallet_empty"] == pytest.approx(round(100 / empty_px, 4))  # 100 px right of 400
    assert result["iou_load_hidden_either"]["pallet_empty"] == pytest.approx(round(300 / 400, 4))
    assert result["iou"]["drivable"] == result["iou_load_hidden_either"]["drivable"] == 1.0
    assert result["load_hidden_share"]["pallet_empty"] == pytest.approx(0.5)
    pred[0:10, 5:25] = SemanticClass.DRIVABLE  # not a pallet at all: wrong under both scores
    score = SegmentationScore()
    score.add(truth, pred)
    assert score.result()["iou_load_hidden_either"]["pallet_empty"] == pytest.approx(round(100 / 400, 4))


def test_missing_model_file_is_one_clear_error(tmp_path):
    path = tmp_path / "nope.onnx"
    with pytest.raises(PerceptionError, match=r"nope\.onnx: segmentation model not found"):
        OnnxSegmenter(path)


def test_corrupt_model_file_is_one_clear_error(tmp_path):
    path = tmp_path / "garbage.onnx"
    path.write_bytes(np.random.default_rng(0).integers(0, 256, 4096, dtype=np.uint8).tobytes())
    with pytest.raises(PerceptionError, match=r"garbage\.onnx: not a readable ONNX segmentation model") as err:
        OnnxSegmenter(path)
    assert "\n" not in str(err.value)


def test_model_without_metadata_is_refused(tmp_path):
    onnx = pytest.importorskip("onnx")
    proto = onnx.load(str(DEFAULT_MODEL))
    del proto.metadata_props[:]
    path = tmp_path / "bare.onnx"
    onnx.save(proto, str(path))
    with pytest.raises(PerceptionError, match=r"bare\.onnx: model metadata lacks input_width"):
        OnnxSegmenter(path)


def test_segment_rejects_a_non_rgb_image(segmenter):
    with pytest.raises(PerceptionError, match="uint8 H x W x 3"):
        segmenter.segment(np.zeros((48, 64), np.uint8))


def test_ensure_labels_fills_missing_labels(segmenter, sim_frame):
    bare = FrameBundle(depth=sim_frame.depth, K=sim_frame.K, rgb=sim_frame.rgb, fork_height=sim_frame.fork_height)
    filled = ensure_labels(bare, segmenter)
    assert filled.labels is not None and filled.labels.shape == bare.depth.shape
    assert filled.fork_height == bare.fork_height and filled.rgb is bare.rgb
    assert ensure_labels(sim_frame, segmenter) is sim_frame  # labelled: unchanged
    truth = ensure_labels(bare, GroundTruthSegmenter(lambda: sim_frame.labels))
    np.testing.assert_array_equal(truth.labels, sim_frame.labels)
    with pytest.raises(PerceptionError, match="no rgb"):
        ensure_labels(FrameBundle(depth=sim_frame.depth, K=sim_frame.K), segmenter)


def test_ground_truth_segmenter_checks_the_size(sim_frame):
    seg = GroundTruthSegmenter(sim_frame.labels)
    with pytest.raises(PerceptionError, match="do not fit"):
        seg.segment(np.zeros((10, 10, 3), np.uint8))


def test_training_crops_are_drawn_around_pallets():
    from palletpilot.perception.training_batches import sample_crop

    labels = np.zeros((480, 640), np.uint8)
    labels[40:70, 500:600] = SemanticClass.PALLET_FULL
    rng = np.random.default_rng(0)
    for _ in range(50):
        rows, cols = sample_crop(labels, (384, 288), 1.0, rng)
        assert rows.stop - rows.start == 288 and cols.stop - cols.start == 384
        assert 0 <= rows.start and rows.stop <= 480 and 0 <= cols.start and cols.stop <= 640
        assert (labels[rows, cols] == SemanticClass.PALLET_FULL).any()
    a = [sample_crop(labels, (384, 288), 0.5, np.random.default_rng(7)) for _ in range(2)]
    assert a[0] == a[1]  # deterministic for the generator's seed
