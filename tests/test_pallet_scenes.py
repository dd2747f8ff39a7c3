"""`sim.pallet_scenes` and `palletpilot segment scenes`: procedural pallet scenes for a segmenter that transfers."""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
import pytest

from palletpilot.cli import main
from palletpilot.perception.frames import SemanticClass
from palletpilot.perception.segmentation_data import png_pairs, read_png_pair
from palletpilot.sim.pallet_scenes import pallet_boxes, render_scene

PALLET = (int(SemanticClass.PALLET_EMPTY), int(SemanticClass.PALLET_FULL))


def test_a_frame_depends_only_on_seed_and_index():
    a_rgb, a_lab = render_scene(3, 7)
    b_rgb, b_lab = render_scene(3, 7)
    c_rgb, _ = render_scene(3, 8)
    assert np.array_equal(a_rgb, b_rgb) and np.array_equal(a_lab, b_lab)
    assert not np.array_equal(a_rgb, c_rgb)


def test_frames_show_pallets_with_exact_labels_of_the_known_classes():
    seen_pallet = 0
    for i in range(12):
        rgb, lab = render_scene(0, i)
        assert rgb.shape == (480, 640, 3) and rgb.dtype == np.uint8
        assert lab.shape == (480, 640) and lab.dtype == np.uint8
        known = {int(c) for c in SemanticClass if c != SemanticClass.UNLABELED}
        assert set(np.unique(lab).tolist()) <= known  # every pixel labelled
        pallet = np.isin(lab, PALLET)
        seen_pallet += int(pallet.sum() > 200)
        if (lab == int(SemanticClass.CARGO)).any():  # a load sits on a loaded pallet
            assert (lab == int(SemanticClass.PALLET_FULL)).any()
    assert seen_pallet >= 9  # the camera looks at a pallet; a few frames may hide it behind clutter


def test_a_pallet_is_a_block_or_stringer_pallet_of_plausible_size():
    rng = np.random.default_rng(0)
    for _ in range(50):
        boxes, deck = pallet_boxes(rng, 1.0, loaded=False)
        lo = np.min([b.t - b.size / 2 for b in boxes], axis=0)
        hi = np.max([b.t + b.size / 2 for b in boxes], axis=0)
        length, width, height = hi - lo
        assert 1.0 - 1e-9 <= length <= 1.3 + 1e-9 and 0.75 - 1e-9 <= width <= 1.2 + 1e-9
        assert 0.09 < height < 0.2 and abs(height - deck) < 1e-9 and lo[2] >= -1e-12
        assert all(b.label == int(SemanticClass.PALLET_EMPTY) for b in boxes)


def test_the_command_writes_the_labelled_png_format_training_reads(tmp_path: Path):
    out = tmp_path / "scenes"
    assert main(["segment", "scenes", str(out), "--frames", "3", "--seed", "2", "--start", "5"]) == 0
    pairs = png_pairs(out)
    assert [p[0].name for p in pairs] == [f"scene_002_{i:06d}.png" for i in (5, 6, 7)]
    rgb, lab = read_png_pair(*pairs[0])
    want_rgb, want_lab = render_scene(2, 5)
    assert np.array_equal(lab, want_lab) and np.array_equal(rgb, want_rgb)
    assert not list(out.glob("*.tmp"))
    assert cv2.imread(str(pairs[1][1]), cv2.IMREAD_UNCHANGED).dtype == np.uint8


@pytest.mark.parametrize("argv", [["--frames", "0"], ["--frames", "2", "--jobs", "0"], ["--frames", "x"]])
def test_bad_options_are_refused_with_exit_2(tmp_path: Path, argv: list[str], capsys):
    with pytest.raises(SystemExit) as exc:
        main(["segment", "scenes", str(tmp_path / "o"), *argv])
    assert exc.value.code == 2
    assert "Traceback" not in capsys.readouterr().err
