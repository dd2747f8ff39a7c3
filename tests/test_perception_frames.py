"""Frame bundles (.npz contract), semantic class ids, fork and pallet geometry specs."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import FrameBundle, SemanticClass, load_bundle, save_bundle
from palletpilot.perception.specs import ForkGeometry, PalletType, load_forks, load_pallet_type

FORKS_FILE = bundled_path("missions") / "forks.yaml"


def _bundle(h: int = 6, w: int = 8) -> FrameBundle:
    rng = np.random.default_rng(0)
    depth = rng.uniform(0.3, 5.0, (h, w)).astype(np.float32)
    depth[0, 0] = 0.0
    depth[1, 1] = np.nan
    K = np.array([[6.0, 0.0, (w - 1) / 2], [0.0, 6.0, (h - 1) / 2], [0.0, 0.0, 1.0]])  # fx ~ 0.75 width
    labels = rng.choice([0, 1, 5, 7, 255], (h, w)).astype(np.uint8)
    rgb = rng.integers(0, 256, (h, w, 3), dtype=np.uint8)
    T = np.eye(4)
    T[:3, 3] = [0.1, 0.0, 0.5]
    return FrameBundle(
        depth,
        K,
        labels,
        rgb,
        fork_height=0.25,
        truth={"T_forklift_camera_true": T, "T_forklift_pallet_true": np.eye(4)},
    )


def _write_npz(path: Path, **arrays: np.ndarray) -> Path:
    np.savez(path, **arrays)
    return path


def test_semantic_class_ids_are_fixed() -> None:
    assert [int(c) for c in SemanticClass] == [0, 1, 2, 3, 4, 5, 6, 7, 8, 9, 255]
    assert SemanticClass.FORKS == 5 and SemanticClass.PALLET_FULL == 8 and SemanticClass.PERSON == 9


def test_round_trip_keeps_every_field(tmp_path: Path) -> None:
    bundle = _bundle()
    path = save_bundle(tmp_path / "frame.npz", bundle)
    loaded = load_bundle(path)
    np.testing.assert_array_equal(loaded.depth, bundle.depth)  # NaN == NaN for array_equal here
    assert loaded.depth.dtype == np.float32 and loaded.K.dtype == np.float64
    np.testing.assert_array_equal(loaded.K, bundle.K)
    np.testing.assert_array_equal(loaded.labels, bundle.labels)
    np.testing.assert_array_equal(loaded.rgb, bundle.rgb)
    assert loaded.fork_height == 0.25
    assert set(loaded.truth) == {"T_forklift_camera_true", "T_forklift_pallet_true"}
    np.testing.assert_array_equal(loaded.truth["T_forklift_camera_true"], bundle.truth["T_forklift_camera_true"])
    assert loaded.valid_depth().sum() == bundle.depth.size - 2


def test_unlabeled_pixels_are_valid_labels() -> None:
    b = _bundle()
    labels = b.labels.copy()
    labels[0, :3] = (255, 9, 0)  # unlabeled, person, drivable
    assert FrameBundle(b.depth, b.K, labels).labels is not None


def test_optional_fields_may_be_absent(tmp_path: Path) -> None:
    b = _bundle()
    path = _write_npz(tmp_path / "min.npz", depth=b.depth, K=b.K)
    loaded = load_bundle(path)
    assert loaded.labels is None and loaded.rgb is None and loaded.fork_height == 0.0 and loaded.truth == {}


@pytest.mark.parametrize(
    ("change", "key", "words"),
    [
        (lambda a: a.pop("K"), "K", "missing"),
        (lambda a: a.pop("depth"), "depth", "missing"),
        (lambda a: a.update(depth=a["depth"].astype(np.float64)), "depth", "float32"),
        (lambda a: a.update(depth=a["depth"][None]), "depth", "shape"),
        (lambda a: a.update(K=np.eye(4)), "K", "(3, 3)"),
        (lambda a: a.update(K=np.eye(3, dtype=np.float32)), "K", "float64"),
        (lambda a: a.update(labels=a["labels"].astype(np.int32)), "labels", "uint8"),
        (lambda a: a.update(labels=a["labels"][:, :-1]), "labels", "does not match"),
        (lambda a: a.update(labels=np.full_like(a["labels"], 42)), "labels", "unknown class ids [42]"),
        (lambda a: a["labels"].__setitem__((slice(0, 2), 0), [255, 10]), "labels", "unknown class ids [10]"),
        (lambda a: a.update(rgb=a["rgb"][..., :2]), "rgb", "shape"),
        (lambda a: a.update(fork_height=np.array([0.1, 0.2])), "fork_height", "scalar"),
        (lambda a: a.update(T_forklift_camera_true=np.eye(3)), "T_forklift_camera_true", "4 x 4"),
        (lambda a: a.update(lables=a["labels"]), "lables", "unknown key"),
        (lambda a: a["depth"].__setitem__((0, 1), -1.0), "depth", "negative"),
        (lambda a: a["depth"].__setitem__((0, 1), np.inf), "depth", "inf"),
    ],
)
def test_bad_bundle_files_raise_one_clear_line(tmp_path: Path, change, key: str, words: str) -> None:
    b = _bundle()
    arrays = {
        "depth": b.depth.copy(),
        "K": b.K,
        "labels": b.labels.copy(),
        "rgb": b.rgb,
        "fork_height": np.array(0.1),
        "T_forklift_camera_true": np.eye(4),
    }
    change(arrays)
    path = _write_npz(tmp_path / "bad.npz", **arrays)
    with pytest.raises(PerceptionError) as info:
        load_bundle(path)
    message = str(info.value)
    assert "\n" not in message
    assert message.startswith(f"{path}: {key}: ")
    assert words in message


def test_not_an_npz_is_a_perception_error(tmp_path: Path) -> None:
    text = tmp_path / "frame.npz"
    text.write_text("depth: not really\n")
    with pytest.raises(PerceptionError, match=r"frame\.npz: not a frame bundle: not an \.npz \(zip\) archive"):
        load_bundle(text)
    single = tmp_path / "depth.npy"
    np.save(single, np.zeros((2, 2), np.float32))
    with pytest.raises(PerceptionError, match=r"depth\.npy: not an \.npz archive"):
        load_bundle(single)
    with pytest.raises(PerceptionError, match="no such file"):
        load_bundle(tmp_path / "missing.npz")


def test_bundle_constructor_validates() -> None:
    b = _bundle()
    with pytest.raises(PerceptionError, match="FrameBundle: K: shape"):
        FrameBundle(b.depth, np.eye(2))
    with pytest.raises(PerceptionError, match="truth keys must end in '_true'"):
        FrameBundle(b.depth, b.K, truth={"T_forklift_camera": np.eye(4)})


def test_fork_file_matches_eur_pockets() -> None:
    forks = load_forks(FORKS_FILE)
    pallet = PalletType.eur()
    assert forks.centres_y == pytest.approx(pallet.pocket_centres_y)
    assert forks.centres_y[0] == pytest.approx(0.18625)
    assert forks.heel_x == pytest.approx(0.0)
    # Each blade fits inside its pocket, with room on both sides and above.
    for centre in pallet.pocket_centres_y:
        assert forks.width < pallet.pocket_width and forks.thickness < pallet.pocket_height
        assert abs(centre) - 0.5 * pallet.pocket_width < forks.centre_y - 0.5 * forks.width
    lo, hi = forks.boxes(0.3)[0]
    np.testing.assert_allclose(lo, [0.0, 0.10625, 0.3])
    np.testing.assert_allclose(hi, [1.15, 0.26625, 0.35])


def test_eur_pallet_dimensions_add_up() -> None:
    p = PalletType.eur()
    assert p.pocket_width == pytest.approx(0.2275)
    assert p.pocket_height == pytest.approx(0.100)
    assert p.bottom_board_thickness + p.block_height + p.cross_board_thickness + p.top_board_thickness == (
        pytest.approx(0.144)
    )
    parts = p.parts()
    kinds = [q.kind for q in parts]
    assert kinds.count("top_board") == 5 and kinds.count("cross_board") == 3
    assert kinds.count("block") == 9 and kinds.count("bottom_board") == 3  # 11 boards, 9 blocks (EPAL)
    lo = np.min([q.lo for q in parts], axis=0)
    hi = np.max([q.hi for q in parts], axis=0)
    np.testing.assert_allclose(lo, [0.0, -0.4, 0.0])
    np.testing.assert_allclose(hi, [1.2, 0.4, 0.144])
    # Pockets open to the floor: no part occupies the pocket cross-section at the entry face.
    for y in p.pocket_centres_y:
        for q in parts:
            inside = q.lo[1] < y < q.hi[1] and q.lo[2] < 0.05 < q.hi[2]
            assert not inside, q.name


def test_bad_spec_files_raise_perception_error(tmp_path: Path) -> None:
    bad = tmp_path / "forks.yaml"
    bad.write_text("length: 1.15\nwidth: -0.16\nthickness: 0.05\ninner_gap: 0.2125\n")
    with pytest.raises(PerceptionError) as info:
        load_forks(bad)
    assert str(bad) in str(info.value)
    assert any("width" in line for line in info.value.problems)
    assert any("tip_x" in line for line in info.value.problems)
    pallet = tmp_path / "pallet.yaml"
    pallet.write_text("block_height: 0.1\n")
    with pytest.raises(PerceptionError, match=r"layers add up to 166\.0 mm"):
        load_pallet_type(pallet)
    with pytest.raises(ValueError):
        ForkGeometry(length=1.0, width=0.1, thickness=0.05, inner_gap=0.2, tip_x=1.0, colour="red")
