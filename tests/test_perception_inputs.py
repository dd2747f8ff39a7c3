"""Perception inputs are checked before they are used (issue #16): frame bundles (limits read from the
`.npy` headers before anything is decompressed, corrupt archives, K, depth, fork height, labels),
calibration files and fork / pallet type files. Every problem is one line naming the file and field.
"""

from __future__ import annotations

import io
import json
import struct
import zipfile
from pathlib import Path

import numpy as np
import pytest

from palletpilot.geometry import SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception import bundle_archive
from palletpilot.perception.calibration_io import (
    MAX_CAMERA_DISTANCE_M,
    Calibration,
    load_calibration,
    save_calibration,
)
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import (
    FORK_HEIGHT_RANGE_M,
    MAX_IMAGE_SIDE,
    FrameBundle,
    load_bundle,
    load_bundles,
    save_bundle,
)
from palletpilot.perception.specs import ForkGeometry, PalletType, load_forks, load_pallet_type, pallet_type

H, W = 48, 64


def _k(fx: float = 60.0, fy: float = 60.0, cx: float = (W - 1) / 2, cy: float = (H - 1) / 2, s: float = 0.0):
    return np.array([[fx, s, cx], [0.0, fy, cy], [0.0, 0.0, 1.0]])


def _arrays() -> dict[str, np.ndarray]:
    rng = np.random.default_rng(1)
    depth = rng.uniform(0.5, 4.0, (H, W)).astype(np.float32)
    depth[0, :4] = [0.0, np.nan, 0.0, np.nan]  # no readings
    return {
        "depth": depth,
        "K": _k(),
        "labels": rng.choice([0, 1, 5, 7, 255], (H, W)).astype(np.uint8),
        "rgb": rng.integers(0, 256, (H, W, 3), dtype=np.uint8),
        "fork_height": np.array(0.3),
    }


def _npz(path: Path, arrays: dict[str, np.ndarray], compressed: bool = True) -> Path:
    (np.savez_compressed if compressed else np.savez)(path, **arrays)
    return path


def _npy(descr: str, shape: tuple[int, ...], payload: bytes = b"") -> bytes:
    header = repr({"descr": descr, "fortran_order": False, "shape": shape}).encode()
    header += b" " * (-(10 + len(header) + 1) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header + payload


def _zip(path: Path, members: dict[str, bytes]) -> Path:
    with zipfile.ZipFile(path, "w", zipfile.ZIP_DEFLATED) as zf:
        for name, raw in members.items():
            zf.writestr(name, raw)
    return path


def _npy_bytes(a: np.ndarray) -> bytes:
    buf = io.BytesIO()
    np.save(buf, a)
    return buf.getvalue()


def _problems(path: Path, **kwargs) -> list[str]:
    with pytest.raises(PerceptionError) as info:
        load_bundle(path, **kwargs)
    assert all(line.startswith(f"{path}: ") and "\n" not in line for line in info.value.problems)
    assert "\n" not in str(info.value) and str(info.value).startswith(f"{path}: ")
    return info.value.problems


# -- frame bundles: reading ----------------------------------------------------------------------------


@pytest.mark.parametrize("compressed", [True, False])
def test_stored_and_compressed_bundles_load_exactly(tmp_path: Path, compressed: bool) -> None:
    arrays = {**_arrays(), "T_forklift_camera_true": np.eye(4), "labels_true": np.zeros((H, W), np.uint8)}
    b = load_bundle(_npz(tmp_path / "f.npz", arrays, compressed))
    np.testing.assert_array_equal(b.depth, arrays["depth"])
    np.testing.assert_array_equal(b.rgb, arrays["rgb"])
    assert b.depth.flags.writeable and b.depth.dtype == np.float32
    assert b.fork_height == 0.3 and set(b.truth) == {"T_forklift_camera_true", "labels_true"}


def test_fortran_ordered_arrays_load_as_saved(tmp_path: Path) -> None:
    arrays = _arrays()
    arrays["rgb"] = np.asfortranarray(arrays["rgb"])
    arrays["depth"] = np.asfortranarray(arrays["depth"])
    b = load_bundle(_npz(tmp_path / "f.npz", arrays))
    np.testing.assert_array_equal(b.rgb, arrays["rgb"])
    np.testing.assert_array_equal(b.depth, arrays["depth"])


def test_limits_are_checked_before_anything_is_decompressed(tmp_path: Path, monkeypatch) -> None:
    def no_data(*_args: object) -> None:
        raise AssertionError("array data read before the headers were checked")

    monkeypatch.setattr(bundle_archive, "_read_data", no_data)
    k = _npy_bytes(_k())
    # a 100000 x 100000 depth image declared in a file of a few hundred bytes
    path = _zip(tmp_path / "huge.npz", {"depth.npy": _npy("<f4", (100_000, 100_000)), "K.npy": k})
    assert path.stat().st_size < 1000
    assert any("depth: shape must be (H, W) with 1..4096 px a side" in p for p in _problems(path))
    # the zip directory claiming 1.6 GB for a member: refused from the directory alone
    data = bytearray(_npz(tmp_path / "f.npz", _arrays()).read_bytes())
    pos = data.find(b"PK\x01\x02")
    while data[pos + 46 : pos + 46 + 7] != b"rgb.npy":
        pos = data.find(b"PK\x01\x02", pos + 4)
    data[pos + 24 : pos + 28] = struct.pack("<I", 1_600_000_000)
    (tmp_path / "bomb.npz").write_bytes(bytes(data))
    assert "too large: the arrays unpack to 152" in _problems(tmp_path / "bomb.npz")[0]


def test_object_arrays_are_never_unpickled(tmp_path: Path, monkeypatch) -> None:
    monkeypatch.setattr("pickle.loads", lambda *_: pytest.fail("unpickled"))
    monkeypatch.setattr("pickle.load", lambda *_: pytest.fail("unpickled"))
    arrays = {**_arrays(), "evil_true": np.array([{"x": 1}], dtype=object)}
    assert "evil_true: an object array (a pickle)" in _problems(_npz(tmp_path / "f.npz", arrays))[0]


def test_a_bundle_reports_every_problem_at_once(tmp_path: Path) -> None:
    arrays = _arrays()
    arrays["K"] = _k(fx=1e-3)
    arrays["fork_height"] = np.array(50.0)
    arrays["labels"][0, 0] = 42
    path = _npz(tmp_path / "f.npz", arrays)
    problems = _problems(path)
    keys = [line[len(f"{path}: ") :].split(":")[0] for line in problems]
    assert "K" in keys and "fork_height" in keys and "labels" in keys
    with pytest.raises(PerceptionError, match=r"\(and \d+ more problems\)"):
        load_bundle(path)


def test_header_sizes_disagreeing_with_the_archive_are_corrupt(tmp_path: Path) -> None:
    path = _zip(tmp_path / "f.npz", {"depth.npy": _npy("<f4", (H, W), b"\0" * 16), "K.npy": _npy_bytes(_k())})
    assert _problems(path) == [
        f"{path}: corrupt frame bundle: depth: the array header declares shape ({H}, {W}) of float32 "
        f"({H * W * 4} bytes) but the member holds 16 bytes of data"
    ]


@pytest.mark.parametrize(
    ("damage", "words"),
    [
        (lambda b: b[: len(b) // 2], "corrupt frame bundle: no zip directory"),
        (lambda b: b[:-5], "corrupt frame bundle: no zip directory"),
        (lambda b: b"", "empty file"),
        (lambda b: b"\x93NUMPY" + b[6:], "a single .npy array"),
        (lambda b: b"hello world", "not an .npz (zip) archive"),
    ],
)
def test_damaged_archives_are_one_line(tmp_path: Path, damage, words: str) -> None:
    good = _npz(tmp_path / "good.npz", _arrays()).read_bytes()
    (tmp_path / "bad.npz").write_bytes(damage(good))
    problems = _problems(tmp_path / "bad.npz")
    assert len(problems) == 1 and words in problems[0]


def test_every_flipped_bit_in_the_data_is_caught(tmp_path: Path) -> None:
    good = _npz(tmp_path / "good.npz", _arrays()).read_bytes()
    info = zipfile.ZipFile(io.BytesIO(good)).getinfo("depth.npy")
    start = info.header_offset + 30 + len("depth.npy") + struct.unpack("<H", good[info.header_offset + 28 :][:2])[0]
    rng = np.random.default_rng(0)
    for pos in rng.integers(start, start + info.compress_size, 25):
        bad = bytearray(good)
        bad[pos] ^= 1 << int(rng.integers(8))
        (tmp_path / "bad.npz").write_bytes(bytes(bad))
        assert "corrupt frame bundle: depth: " in _problems(tmp_path / "bad.npz")[0]


def test_too_many_members_are_refused_from_the_directory(tmp_path: Path) -> None:
    arrays = {**_arrays(), **{f"x{i}_true": np.zeros(1) for i in range(70)}}
    assert "too many arrays: 75 (a frame bundle holds at most 64)" in _problems(_npz(tmp_path / "f.npz", arrays))[0]


def test_members_that_are_not_arrays_or_bundle_keys(tmp_path: Path) -> None:
    members = {"depth.npy": _npy_bytes(_arrays()["depth"]), "K.npy": _npy_bytes(_k())}
    path = _zip(tmp_path / "f.npz", {**members, "notes.txt": b"x", "a\nb_true.npy": b"", "lables.npy": b""})
    problems = _problems(path)
    assert any("'notes.txt': not an array" in p for p in problems)
    assert any("'a\\nb_true.npy': not an array" in p for p in problems)  # never a line break in a message
    assert any("lables: unknown key" in p for p in problems)


def test_not_a_regular_file(tmp_path: Path) -> None:
    (tmp_path / "dir.npz").mkdir()
    assert "a folder" in _problems(tmp_path / "dir.npz")[0]
    assert "no such file" in _problems(tmp_path / "missing.npz")[0]


# -- frame bundles: values -----------------------------------------------------------------------------


@pytest.mark.parametrize(
    ("K", "words"),
    [
        (_k(fx=0.0), "fx, fy > 0"),
        (_k(fx=-60.0), "fx, fy > 0"),
        (_k(fx=1e-3, fy=1e-3), "fx 0.001 px is implausible"),
        (_k(fx=1e6, fy=1e6), "fx 1e+06 px is implausible"),
        (_k(fy=200.0), "pixels that far from square"),
        (_k(cx=W + 10.0), "principal point cx"),
        (_k(cy=-5.0), "principal point cy"),
        (_k(s=5.0), "skew K[0, 1] = 5 px"),
        (_k(cx=np.nan), "non-finite"),
        (np.eye(4), "shape must be (3, 3)"),
        (np.eye(3, dtype=np.float32), "dtype must be float64"),
    ],
)
def test_implausible_intrinsics(tmp_path: Path, K: np.ndarray, words: str) -> None:
    problems = _problems(_npz(tmp_path / "f.npz", {**_arrays(), "K": K}))
    assert problems[0].startswith(f"{tmp_path / 'f.npz'}: K: ") and words in problems[0]


def test_plausible_intrinsics_pass() -> None:
    depth = np.ones((480, 640), np.float32)
    for K in (_k(612.4, 612.4, 319.5, 239.5), _k(64.0, 48.0, 0.0, 479.0), _k(12800.0, 9600.0, 639.5, -0.5)):
        FrameBundle(depth, K)


@pytest.mark.parametrize(
    ("value", "words"),
    [
        (np.inf, "contains inf"),
        (-np.inf, "contains inf"),
        (-0.5, "negative depths"),
        (1500.0, "depth must be in metres"),
    ],
)
def test_depth_values(tmp_path: Path, value: float, words: str) -> None:
    arrays = _arrays()
    arrays["depth"][3, 3] = value
    assert words in _problems(_npz(tmp_path / "f.npz", arrays))[0]


def test_depth_without_any_reading_is_a_valid_bundle(tmp_path: Path) -> None:
    for depth in (np.zeros((H, W), np.float32), np.full((H, W), np.nan, np.float32)):
        b = load_bundle(_npz(tmp_path / "f.npz", {**_arrays(), "depth": depth}))
        assert not b.valid_depth().any()


def test_fork_height_any_mast_or_the_vehicles(tmp_path: Path) -> None:
    lo, hi = FORK_HEIGHT_RANGE_M
    for value, words in ((np.nan, "must be a finite number"), (-3.0, "-3 m is outside"), (50.0, "50 m is outside")):
        path = _npz(tmp_path / "f.npz", {**_arrays(), "fork_height": np.array(value)})
        assert words in _problems(path)[0]
    path = _npz(tmp_path / "f.npz", {**_arrays(), "fork_height": np.array(3.0)})
    assert load_bundle(path).fork_height == 3.0  # any mast's range
    assert "3 m is outside the mast's range 0..2 m" in _problems(path, mast_range_m=(0.0, 2.0))[0]
    near_floor = _npz(tmp_path / "g.npz", {**_arrays(), "fork_height": np.array(-0.01)})
    assert load_bundle(near_floor, mast_range_m=(0.0, 2.0)).fork_height == -0.01  # sensor noise
    assert lo == 0.0 and hi == 20.0


def test_labels_and_sizes(tmp_path: Path) -> None:
    arrays = _arrays()
    arrays["labels"][1, 1] = 10
    assert "labels: unknown class ids [10]" in _problems(_npz(tmp_path / "f.npz", arrays))[0]
    half = {**_arrays(), "labels": np.zeros((H // 2, W), np.uint8)}
    assert "labels: shape (24, 64) does not match depth (48, 64)" in _problems(_npz(tmp_path / "f.npz", half))[0]
    big = {**_arrays(), "depth": np.ones((1, MAX_IMAGE_SIDE + 1), np.float32)}
    assert any("depth: shape must be (H, W)" in p for p in _problems(_npz(tmp_path / "f.npz", big)))


def test_need_labels(tmp_path: Path) -> None:
    arrays = _arrays()
    del arrays["labels"], arrays["rgb"]
    path = _npz(tmp_path / "f.npz", arrays)
    assert load_bundle(path).labels is None
    assert "labels: missing, and there is no rgb" in _problems(path, need_labels=True)[0]


def test_bundles_built_in_memory_are_checked_too() -> None:
    a = _arrays()
    with pytest.raises(PerceptionError, match=r"^FrameBundle: K: fx 0\.001 px is implausible"):
        FrameBundle(a["depth"], _k(fx=1e-3))
    with pytest.raises(PerceptionError, match="fork_height: 50 m is outside"):
        FrameBundle(a["depth"], _k(), fork_height=50.0)


def test_load_bundles_reports_every_bad_file(tmp_path: Path) -> None:
    good = save_bundle(tmp_path / "good.npz", FrameBundle(**{k: v for k, v in _arrays().items() if k != "fork_height"}))
    bad_k = _npz(tmp_path / "bad_k.npz", {**_arrays(), "K": _k(fx=0.0)})
    text = tmp_path / "text.npz"
    text.write_text("x")
    assert len(load_bundles([good, good])) == 2
    with pytest.raises(PerceptionError) as info:
        load_bundles([text, good, bad_k])
    assert [p.split(": ")[0] for p in info.value.problems] == [str(text), str(bad_k)]
    assert str(info.value).startswith("2 of 3 frame bundles are bad: ")
    with pytest.raises(PerceptionError, match="fork_height"):
        load_bundles([_npz(tmp_path / "h.npz", {**_arrays(), "fork_height": np.array(3.0)})], mast_range_m=(0, 2))
    with pytest.raises(PerceptionError, match="no frame bundles"):
        load_bundles([])


# -- calibration files --------------------------------------------------------------------------------


def _cal_doc(tmp_path: Path) -> dict:
    T = SE3.from_xyz_rpy([-0.1, 0.0, 0.45], np.radians([-112.0, 0.0, -90.0]))
    path = save_calibration(tmp_path / "good.json", Calibration(T, "model", {"floor_rms_m": 0.002}))
    return json.loads(path.read_text())


def _cal_problems(path: Path) -> list[str]:
    with pytest.raises(PerceptionError) as info:
        load_calibration(path)
    assert all(line.startswith(f"{path}: ") and "\n" not in line for line in info.value.problems)
    return info.value.problems


def test_calibration_round_trip_and_tolerance(tmp_path: Path) -> None:
    doc = _cal_doc(tmp_path)
    back = load_calibration(tmp_path / "good.json")
    assert back.method == "model" and back.quality == {"floor_rms_m": 0.002}
    doc["T_forklift_camera"][0][0] += 2e-5  # a hand-edited file: within tolerance, made orthonormal
    path = tmp_path / "edited.json"
    path.write_text(json.dumps(doc))
    R = load_calibration(path).T_forklift_camera.R
    np.testing.assert_allclose(R.T @ R, np.eye(3), atol=1e-12)


@pytest.mark.parametrize(
    ("change", "words"),
    [
        (
            lambda d: d["T_forklift_camera"][0].__setitem__(3, "0.1"),
            "T_forklift_camera[0][3]: Input should be a valid number",
        ),
        (lambda d: d["T_forklift_camera"][0].__setitem__(3, 1e6), "the camera is 1e+06 m from the forklift origin"),
        (lambda d: d["T_forklift_camera"][0].__setitem__(0, 2.0), "not orthonormal"),
        (
            lambda d: d["T_forklift_camera"].__setitem__(2, [-v for v in d["T_forklift_camera"][2][:3]] + [0.45]),
            "reflection",
        ),
        (lambda d: d["T_forklift_camera"][3].__setitem__(2, 1.0), "the last row must be [0, 0, 0, 1]"),
        (lambda d: d.update(xyz_m=[1.0, 0.0, 0.45]), "xyz_m: [1.0, 0.0, 0.45] disagrees"),
        (lambda d: d.update(rpy_deg=[0.0, 0.0, 0.0]), "rpy_deg: [0.0, 0.0, 0.0] is "),
        (lambda d: d.update(extra_key=1), "extra_key: Extra inputs are not permitted"),
        (lambda d: d.update(method=""), "method: String should have at least 1 character"),
        (lambda d: d.update(tilt_deg=400.0), "tilt_deg: Input should be less than or equal to 180"),
    ],
)
def test_bad_calibration_fields(tmp_path: Path, change, words: str) -> None:
    doc = _cal_doc(tmp_path)
    change(doc)
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    problems = _cal_problems(path)
    assert any(words in line for line in problems), problems


def test_every_calibration_problem_at_once(tmp_path: Path) -> None:
    doc = _cal_doc(tmp_path)
    doc["T_forklift_camera"][1][1] = "x"
    doc["method"] = 1
    doc["typo"] = True
    path = tmp_path / "bad.json"
    path.write_text(json.dumps(doc))
    assert len(_cal_problems(path)) == 3


@pytest.mark.parametrize(
    ("content", "words"),
    [
        (b"", "not valid JSON"),
        (b'{"T_forklift_camera": NaN}', "NaN is not a number"),
        ('{"method": "mod\u00e8le"}'.encode("latin-1"), "not UTF-8"),
        (bytes(range(256)), "not UTF-8"),
        (b"{}", "not a calibration file"),
        (b'"T_forklift_camera"', "not a calibration file"),
        (b" " * (2**20 + 1), "too large"),
    ],
)
def test_unreadable_calibration_files(tmp_path: Path, content: bytes, words: str) -> None:
    path = tmp_path / "bad.json"
    path.write_bytes(content)
    assert words in _cal_problems(path)[0]
    (tmp_path / "dir.json").mkdir()
    assert "a folder" in _cal_problems(tmp_path / "dir.json")[0]


def test_camera_distance_limit_is_generous_for_real_mounts() -> None:
    assert 2.0 < MAX_CAMERA_DISTANCE_M <= 5.0


# -- fork and pallet type files -----------------------------------------------------------------------

FORKS = dict(length=1.15, width=0.16, thickness=0.05, inner_gap=0.2125, tip_x=1.15)


def test_bundled_forks_and_eur_pallet_pass() -> None:
    assert load_forks(bundled_path("missions") / "forks.yaml") == ForkGeometry(**FORKS)
    assert PalletType.eur().pocket_width == pytest.approx(0.2275)
    assert pallet_type("EUR") == PalletType.eur()


@pytest.mark.parametrize(
    ("changes", "words"),
    [
        ({"length": float("inf")}, "length: Input should be a finite number"),
        ({"length": 30.0, "tip_x": 3.0}, "length: 30 m is outside 0.5..3 m"),
        ({"width": 0.0}, "width: 0 m is outside 0.03..0.4 m"),
        ({"thickness": -0.05}, "thickness: -0.05 m is outside 0.01..0.2 m"),
        ({"inner_gap": 5.0}, "inner_gap: 5 m is outside 0.02..2 m"),
        ({"tip_x": -2.0}, "tip_x: -2 m is outside 0.3..4 m"),
        ({"tip_x": 3.0}, "tip_x: puts the fork heels (tip_x - length) at x = 1.85 m, outside -1..1 m"),
        ({"width": "0.16"}, "width: Input should be a valid number"),
        ({"width": True}, "width: Input should be a valid number"),
    ],
)
def test_bad_fork_files(tmp_path: Path, changes: dict, words: str) -> None:
    path = tmp_path / "forks.yaml"
    path.write_text(json.dumps({**FORKS, **changes}).replace("Infinity", ".inf"))
    with pytest.raises(PerceptionError) as info:
        load_forks(path)
    assert any(line == f"{path}: {words}" or line.startswith(f"{path}: {words}") for line in info.value.problems), (
        info.value.problems
    )


@pytest.mark.parametrize(
    ("text", "words"),
    [
        ("width: 50\n", "width: 50 m is outside 0.3..3 m"),
        ("length: 0.4\n", "block_length: three block rows of 0.145 m do not fit in the pallet length (0.4 m)"),
        ("block_columns: [0.3, 0.3, 0.3]\n", "block_columns: the block columns are 0.9 m wide in all"),
        ("top_board_widths: [0.6]\n", "top_board_widths: 0.6 m is outside 0.02..0.5 m"),
        ("top_board_widths: [0.45, 0.45]\n", "top_board_widths: the deck boards are 0.9 m wide in all"),
        ("block_height: 0.1\n", "height: layers add up to 166.0 mm"),
        ("height: .nan\n", "height: Input should be a finite number"),
        ("name: ''\n", "name: String should have at least 1 character"),
    ],
)
def test_bad_pallet_type_files(tmp_path: Path, text: str, words: str) -> None:
    path = tmp_path / "pallet.yaml"
    path.write_text(text)
    with pytest.raises(PerceptionError) as info:
        load_pallet_type(path)
    assert any(line.startswith(f"{path}: {words}") for line in info.value.problems), info.value.problems


def test_unknown_pallet_type_name() -> None:
    with pytest.raises(PerceptionError, match=r"^eru: not a known pallet type \(eur, epal, eur/epal\)"):
        pallet_type("eru")
