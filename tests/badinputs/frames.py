"""Bad perception inputs: frame bundles (`frame_`), calibration files (`cal_`), fork files (`forks_`) and
pallet type files (`pallet_`), through `palletpilot calibrate` and `palletpilot estimate-pallet`.

Every case starts from the valid rendered bundle `{frame}` (or the valid calibration `{cal}`, the
example `forks.yaml`) and breaks one thing: bytes of the archive (bit flips, truncation, a patched
zip directory), an array (crafted `.npy` headers that declare huge shapes in a tiny file, pickles,
mismatched sizes, an implausible K, depth or fork height, unknown class ids), or a field of a file.
"""

from __future__ import annotations

import io
import json
import re
import struct
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np

from . import Case, Fixtures, dump, example, write

BAD = "{case}/bad.npz"
CALIBRATE = ("calibrate", BAD, "--forks", "{ex}/forks.yaml")
ESTIMATE = ("estimate-pallet", BAD, "--calibration", "{cal}")

Setup = Callable[[Fixtures, Path], None]


# -- building bad bundles ------------------------------------------------------------------------------


def _arrays(fx: Fixtures) -> dict[str, np.ndarray]:
    """The valid bundle's arrays, to change into a bad one."""
    with np.load(fx.frame) as data:
        return {key: data[key].copy() for key in data.files}


def _npz(folder: Path, arrays: dict[str, np.ndarray], name: str = "bad.npz") -> Path:
    """Write `arrays` as a compressed `.npz` (object arrays are pickled, as numpy does)."""
    buf = io.BytesIO()
    np.savez_compressed(buf, **arrays)
    return write(folder, name, buf.getvalue())


def _changed(change: Callable[[dict[str, np.ndarray]], None]) -> Setup:
    """A setup writing the valid bundle with `change` applied to its arrays."""

    def setup(fx: Fixtures, folder: Path) -> None:
        arrays = _arrays(fx)
        change(arrays)
        _npz(folder, arrays)

    return setup


def _k(**entries: float) -> Setup:
    """A setup changing entries of K: fx, fy, cx, cy, s (skew)."""
    where = {"fx": (0, 0), "fy": (1, 1), "cx": (0, 2), "cy": (1, 2), "s": (0, 1)}

    def change(a: dict[str, np.ndarray]) -> None:
        for name, value in entries.items():
            a["K"][where[name]] = value

    return _changed(change)


def _fork_height(value: float) -> Setup:
    return _changed(lambda a: a.update(fork_height=np.array(value)))


def _bytes(change: Callable[[bytes], bytes]) -> Setup:
    """A setup writing the valid bundle's bytes after `change`."""

    def setup(fx: Fixtures, folder: Path) -> None:
        write(folder, "bad.npz", change(fx.frame.read_bytes()))

    return setup


def _data_offset(data: bytes, member: str) -> tuple[int, int]:
    """(start, length) of a member's compressed data in a zip archive."""
    info = zipfile.ZipFile(io.BytesIO(data)).getinfo(member)
    off = info.header_offset
    name_len, extra_len = struct.unpack("<HH", data[off + 26 : off + 30])
    return off + 30 + name_len + extra_len, info.compress_size


def _central_entry(data: bytes, member: str) -> int:
    """Offset of a member's entry in the zip's central directory."""
    pos = data.find(b"PK\x01\x02")
    while pos >= 0:
        name_len = struct.unpack("<H", data[pos + 28 : pos + 30])[0]
        if data[pos + 46 : pos + 46 + name_len] == member.encode():
            return pos
        pos = data.find(b"PK\x01\x02", pos + 4)
    raise AssertionError(f"{member} not in the central directory")


def _flip(member: str, fraction: float, bit: int = 0x10) -> Callable[[bytes], bytes]:
    """Flip one bit at `fraction` of the way through a member's compressed data."""

    def change(data: bytes) -> bytes:
        start, length = _data_offset(data, member)
        pos = start + int(fraction * length)
        return data[:pos] + bytes([data[pos] ^ bit]) + data[pos + 1 :]

    return change


def _stored(change: Callable[[bytes], bytes]) -> Setup:
    """A setup writing the valid bundle uncompressed (`np.savez`, as some tools do), then `change`d."""

    def setup(fx: Fixtures, folder: Path) -> None:
        buf = io.BytesIO()
        np.savez(buf, **_arrays(fx))
        write(folder, "bad.npz", change(buf.getvalue()))

    return setup


def _flip_shape_digit(data: bytes) -> bytes:
    """Flip one bit of the first `(480` in the uncompressed depth header: it then declares 580 rows."""
    start, _ = _data_offset(data, "depth.npy")
    pos = data.index(b"(480", start) + 1
    return data[:pos] + bytes([data[pos] ^ 0x01]) + data[pos + 1 :]


def _patch_central(member: str, field_offset: int, fmt: str, value: Callable[[int], int]) -> Callable[[bytes], bytes]:
    """Change one field of a member's central directory entry (16: CRC-32, 24: uncompressed size)."""

    def change(data: bytes) -> bytes:
        pos = _central_entry(data, member) + field_offset
        size = struct.calcsize(fmt)
        old = struct.unpack(fmt, data[pos : pos + size])[0]
        return data[:pos] + struct.pack(fmt, value(old)) + data[pos + size :]

    return change


def _npy(descr: str, shape: tuple[int, ...], payload: bytes = b"\0" * 16) -> bytes:
    """An `.npy` file whose header declares `descr` and `shape`, followed by only `payload`."""
    header = repr({"descr": descr, "fortran_order": False, "shape": shape}).encode("latin1")
    header += b" " * (-(10 + len(header) + 1) % 64) + b"\n"
    return b"\x93NUMPY\x01\x00" + struct.pack("<H", len(header)) + header + payload


def _zip(members: dict[str, bytes]) -> Setup:
    """A setup writing a deflated zip of raw members next to a valid K (and depth unless given)."""

    def setup(fx: Fixtures, folder: Path) -> None:
        arrays = _arrays(fx)
        buf = io.BytesIO()
        with zipfile.ZipFile(buf, "w", zipfile.ZIP_DEFLATED) as zf:
            for key in ("depth", "K"):
                if f"{key}.npy" not in members:
                    npy = io.BytesIO()
                    np.save(npy, arrays[key])
                    zf.writestr(f"{key}.npy", npy.getvalue())
            for name, raw in members.items():
                zf.writestr(name, raw)
        write(folder, "bad.npz", buf.getvalue())

    return setup


def _declared_size(size: int) -> Setup:
    """The valid bundle with the zip directory claiming rgb unpacks to `size` bytes (nothing else changed)."""
    return _bytes(_patch_central("rgb.npy", 24, "<I", lambda _old: size))


def _many_members(fx: Fixtures, folder: Path) -> None:
    arrays = _arrays(fx)
    arrays.update({f"extra{i}_true": np.zeros(1) for i in range(100)})
    _npz(folder, arrays)


def _folder(fx: Fixtures, folder: Path) -> None:
    (folder / "bad.npz").mkdir()


def _npy_only(fx: Fixtures, folder: Path) -> None:
    buf = io.BytesIO()
    np.save(buf, _arrays(fx)["depth"])
    write(folder, "bad.npz", buf.getvalue())


def _pickled(key: str) -> Setup:
    return _changed(lambda a: a.update({key: np.array([{"x": 1}, None], dtype=object)}))


def _second_bad(fx: Fixtures, folder: Path) -> None:
    arrays = _arrays(fx)
    write(folder, "good.npz", fx.frame.read_bytes())
    arrays["K"][0, 0] = 0.0
    _npz(folder, arrays, "b.npz")
    write(folder, "a.npz", b"not a bundle")


FRAME_CASES = [
    # damaged archives
    Case("frame_bitflip_depth_data", CALIBRATE, 2, "corrupt frame bundle", _bytes(_flip("depth.npy", 0.5))),
    Case("frame_bitflip_rgb_data", ESTIMATE, 2, "corrupt frame bundle", _bytes(_flip("rgb.npy", 0.3, 0x01))),
    Case("frame_bitflip_labels_data", CALIBRATE, 2, "corrupt frame bundle", _bytes(_flip("labels.npy", 0.7, 0x80))),
    Case("frame_bitflip_header_start", ESTIMATE, 2, "corrupt frame bundle", _bytes(_flip("K.npy", 0.0, 0x04))),
    Case(
        "frame_stored_bitflip_data",
        ESTIMATE,
        2,
        "corrupt frame bundle: rgb: Bad CRC-32",
        _stored(_flip("rgb.npy", 0.5, 0x02)),
    ),
    Case(
        "frame_stored_bitflip_header",
        CALIBRATE,
        2,
        "corrupt frame bundle: depth: the array header declares shape (580, 640)",
        _stored(_flip_shape_digit),
    ),
    Case(
        "frame_bitflip_crc",
        CALIBRATE,
        2,
        "corrupt frame bundle: depth: Bad CRC-32",
        _bytes(_patch_central("depth.npy", 16, "<I", lambda crc: crc ^ 0x100)),
    ),
    Case(
        "frame_directory_size_off",
        ESTIMATE,
        2,
        "corrupt frame bundle: K: the array header declares",
        _bytes(_patch_central("K.npy", 24, "<I", lambda n: n + 8)),
    ),
    Case("frame_declared_1_6_gb", CALIBRATE, 2, "too large: the arrays unpack to", _declared_size(1_600_000_000)),
    Case("frame_truncated_half", CALIBRATE, 2, "corrupt frame bundle", _bytes(lambda b: b[: len(b) // 2])),
    Case("frame_truncated_tail", ESTIMATE, 2, "corrupt frame bundle", _bytes(lambda b: b[:-10])),
    Case("frame_empty_file", CALIBRATE, 2, "bad.npz: empty file", _bytes(lambda b: b"")),
    Case("frame_text_file", ESTIMATE, 2, "not an .npz (zip) archive", _bytes(lambda b: b"depth: 1.0\n")),
    Case("frame_single_npy", CALIBRATE, 2, "a single .npy array", _npy_only),
    Case("frame_folder", ESTIMATE, 2, "bad.npz: a folder", _folder),
    Case("frame_missing_file", CALIBRATE, 2, "bad.npz: no such file"),
    Case("frame_too_many_members", ESTIMATE, 2, "(a frame bundle holds at most 64)", _many_members),
    # crafted or odd members
    Case("frame_missing_depth", CALIBRATE, 2, "bad.npz: depth: missing", _changed(lambda a: a.pop("depth"))),
    Case("frame_missing_k", ESTIMATE, 2, "bad.npz: K: missing", _changed(lambda a: a.pop("K"))),
    Case("frame_zip_with_text_member", CALIBRATE, 2, "'notes.txt': not an array", _zip({"notes.txt": b"hello"})),
    Case("frame_unknown_key", ESTIMATE, 2, "lables: unknown key", _changed(lambda a: a.update(lables=a["labels"]))),
    Case("frame_pickled_labels", CALIBRATE, 2, "labels: an object array (a pickle)", _pickled("labels")),
    Case("frame_pickled_truth", ESTIMATE, 2, "evil_true: an object array (a pickle)", _pickled("evil_true")),
    Case(
        "frame_huge_declared_depth",
        CALIBRATE,
        2,
        "depth: shape must be (H, W) with 1..4096 px a side, got (100000, 100000)",
        _zip({"depth.npy": _npy("<f4", (100000, 100000))}),
    ),
    Case(
        "frame_huge_declared_truth",
        ESTIMATE,
        2,
        "junk_true: shape (1000000000,): more elements",
        _zip({"junk_true.npy": _npy("<f8", (1_000_000_000,))}),
    ),
    Case(
        "frame_header_larger_than_data",
        CALIBRATE,
        2,
        "corrupt frame bundle: rgb: the array header declares shape (480, 640, 3)",
        _zip({"rgb.npy": _npy("|u1", (480, 640, 3))}),
    ),
    Case(
        "frame_negative_shape",
        ESTIMATE,
        2,
        "negative size in shape",
        _zip({"labels.npy": _npy("|u1", (-480, 640))}),
    ),
    Case("frame_not_npy_member", CALIBRATE, 2, "corrupt frame bundle: depth", _zip({"depth.npy": b"PK not numpy"})),
    # arrays of the wrong kind or size
    Case(
        "frame_labels_half_size",
        CALIBRATE,
        2,
        "labels: shape (240, 320) does not match depth (480, 640)",
        _changed(lambda a: a.update(labels=a["labels"][::2, ::2].copy())),
    ),
    Case(
        "frame_rgb_four_channels",
        ESTIMATE,
        2,
        "rgb: shape must be (H, W, 3) with 1..4096 px a side, got (480, 640, 4)",
        _changed(lambda a: a.update(rgb=np.zeros((480, 640, 4), np.uint8))),
    ),
    Case(
        "frame_depth_float64",
        CALIBRATE,
        2,
        "depth: dtype must be float32",
        _changed(lambda a: a.update(depth=a["depth"].astype(np.float64))),
    ),
    Case(
        "frame_depth_3d",
        ESTIMATE,
        2,
        "depth: shape must be (H, W)",
        _changed(lambda a: a.update(depth=a["depth"][None])),
    ),
    Case(
        "frame_depth_image_too_big",
        CALIBRATE,
        2,
        "depth: shape must be (H, W) with 1..4096 px a side, got (1, 5000)",
        _changed(lambda a: a.update(depth=np.ones((1, 5000), np.float32))),
    ),
    Case(
        "frame_depth_inf",
        CALIBRATE,
        2,
        "depth: contains inf",
        _changed(lambda a: a["depth"].__setitem__((5, 5), np.inf)),
    ),
    Case(
        "frame_depth_negative",
        ESTIMATE,
        2,
        "depth: contains negative depths",
        _changed(lambda a: a["depth"].__setitem__((5, 5), -1.0)),
    ),
    Case(
        "frame_depth_millimetres",
        CALIBRATE,
        2,
        "depth must be in metres",
        _changed(lambda a: a.update(depth=a["depth"] * np.float32(1000))),
    ),
    # intrinsics
    Case("frame_k_zero_focal", CALIBRATE, 2, "K: is not a pinhole matrix", _k(fx=0.0)),
    Case("frame_k_negative_focal", ESTIMATE, 2, "fx, fy > 0", _k(fy=-600.0)),
    Case("frame_k_tiny_focal", CALIBRATE, 2, "K: fx 0.001 px is implausible", _k(fx=1e-3, fy=1e-3)),
    Case("frame_k_huge_focal", ESTIMATE, 2, "K: fx 1e+09 px is implausible", _k(fx=1e9, fy=1e9)),
    Case("frame_k_nan", CALIBRATE, 2, "K: has non-finite entries", _k(cx=float("nan"))),
    Case("frame_k_principal_point_outside", ESTIMATE, 2, "principal point cx 5000", _k(cx=5000.0)),
    Case("frame_k_skew", CALIBRATE, 2, "skew K[0, 1] = 100", _k(s=100.0)),
    Case("frame_k_stretched_pixels", ESTIMATE, 2, "pixels that far from square", _k(fy=3000.0)),
    Case("frame_k_4x4", CALIBRATE, 2, "K: shape must be (3, 3)", _changed(lambda a: a.update(K=np.eye(4)))),
    Case(
        "frame_k_float32",
        ESTIMATE,
        2,
        "K: dtype must be float64",
        _changed(lambda a: a.update(K=a["K"].astype(np.float32))),
    ),
    # lens distortion (optional `dist`)
    Case(
        "frame_dist_3_coefficients",
        CALIBRATE,
        2,
        "dist: must be a float64 vector of 4, 5, 8, 12 or 14",
        _changed(lambda a: a.update(dist=np.array([0.1, 0.0, 0.0]))),
    ),
    Case(
        "frame_dist_nan",
        ESTIMATE,
        2,
        "dist: has non-finite coefficients",
        _changed(lambda a: a.update(dist=np.array([np.nan, 0.0, 0.0, 0.0, 0.0]))),
    ),
    Case(
        "frame_dist_tangential",
        CALIBRATE,
        2,
        "dist: p1, p2 up to 0.3: beyond 0.1",
        _changed(lambda a: a.update(dist=np.array([0.0, 0.0, 0.3, 0.0]))),
    ),
    Case(
        "frame_dist_folds",
        ESTIMATE,
        2,
        "dist: the lens model folds back",
        _changed(lambda a: a.update(dist=np.array([-3.0, 0.0, 0.0, 0.0, 0.0]))),
    ),
    # fork height
    Case("frame_fork_height_nan", CALIBRATE, 2, "fork_height: must be a finite number", _fork_height(float("nan"))),
    Case("frame_fork_height_negative", ESTIMATE, 2, "fork_height: -3 m is outside", _fork_height(-3.0)),
    Case("frame_fork_height_50m", CALIBRATE, 2, "fork_height: 50 m is outside any mast's range", _fork_height(50.0)),
    Case(
        "frame_fork_height_above_the_mast",
        (*ESTIMATE, "--vehicle", "{ex}/forklift.yaml"),
        2,
        "fork_height: 3 m is outside the mast's range 0..2 m",
        _fork_height(3.0),
    ),
    Case(
        "frame_fork_height_array",
        ESTIMATE,
        2,
        "fork_height: must be a scalar number",
        _changed(lambda a: a.update(fork_height=np.array([0.1, 0.2]))),
    ),
    Case(
        "frame_fork_height_string",
        CALIBRATE,
        2,
        "fork_height: must be a scalar number",
        _changed(lambda a: a.update(fork_height=np.array("0.5"))),
    ),
    # labels
    Case(
        "frame_labels_unknown_class",
        CALIBRATE,
        2,
        "labels: unknown class ids [42]",
        _changed(lambda a: a["labels"].__setitem__((0, 0), 42)),
    ),
    Case(
        "frame_labels_int32",
        ESTIMATE,
        2,
        "labels: dtype must be uint8",
        _changed(lambda a: a.update(labels=a["labels"].astype(np.int32))),
    ),
    Case(  # the model mode needs labels or RGB; geometry and fused (the default) go on from the depth
        "frame_no_labels_no_rgb",
        (*ESTIMATE, "--labels", "model"),
        2,
        "bad.npz: labels: missing, and there is no rgb",
        _changed(lambda a: [a.pop("labels"), a.pop("rgb")]),
    ),
    Case(
        "frame_truth_transform_3x3",
        ESTIMATE,
        2,
        "T_forklift_camera_true: a transform must be a finite 4 x 4",
        _changed(lambda a: a.update(T_forklift_camera_true=np.eye(3))),
    ),
    # every problem of every input, at once
    Case(
        "frame_every_problem_of_a_bundle",
        ESTIMATE,
        2,
        "fork_height: 50 m is outside",
        _changed(lambda a: [a["K"].__setitem__((0, 0), 1e9), a.update(fork_height=np.array(50.0))]),
    ),
    Case(
        "frame_and_calibration_both_bad",
        ("estimate-pallet", BAD, "--calibration", "{case}/cal.json"),
        2,
        "cal.json: not valid JSON",
        lambda fx, folder: [_k(fx=0.0)(fx, folder), write(folder, "cal.json", "{")],
    ),
    Case(
        "frame_calibrate_reports_every_bad_bundle",
        ("calibrate", "{case}/a.npz", "{case}/good.npz", "{case}/b.npz", "--forks", "{ex}/forks.yaml"),
        2,
        "b.npz: K: is not a pinhole matrix",
        _second_bad,
    ),
]


# -- calibration files ----------------------------------------------------------------------------------

CAL = "{case}/cal.json"
WITH_CAL = ("estimate-pallet", "{frame}", "--calibration", CAL)


def _cal(change: Callable[[dict], object]) -> Setup:
    """A setup writing the valid calibration with `change` applied to its document."""

    def setup(fx: Fixtures, folder: Path) -> None:
        doc = json.loads(fx.cal.read_text())
        change(doc)
        write(folder, "cal.json", json.dumps(doc))

    return setup


def _cal_text(change: Callable[[str], str | bytes]) -> Setup:
    def setup(fx: Fixtures, folder: Path) -> None:
        write(folder, "cal.json", change(fx.cal.read_text()))

    return setup


def _value(text: str, key: str, value: str) -> str:
    """JSON text with the value of `key` (a number) replaced by `value` as it stands."""
    return re.sub(rf'"{key}": [^,\n]+', f'"{key}": {value}', text, count=1)


def _set_t(row: int, col: int, value: object) -> Callable[[dict], object]:
    return lambda d: d["T_forklift_camera"][row].__setitem__(col, value)


def _scale_rotation(d: dict) -> None:
    for r in range(3):
        for c in range(3):
            d["T_forklift_camera"][r][c] *= 1.5


def _reflect(d: dict) -> None:
    for c in range(3):
        d["T_forklift_camera"][0][c] *= -1.0


def _cal_folder(fx: Fixtures, folder: Path) -> None:
    (folder / "cal.json").mkdir()


CAL_CASES = [
    Case(
        "cal_string_number",
        WITH_CAL,
        2,
        "T_forklift_camera[0][3]: Input should be a valid number",
        _cal(_set_t(0, 3, "0.1")),
    ),
    Case(
        "cal_boolean_number",
        WITH_CAL,
        2,
        "T_forklift_camera[1][1]: Input should be a valid number",
        _cal(_set_t(1, 1, True)),
    ),
    Case("cal_null_number", WITH_CAL, 2, "T_forklift_camera[2][3]", _cal(_set_t(2, 3, None))),
    Case("cal_nan", WITH_CAL, 2, "NaN is not a number in JSON", _cal_text(lambda t: _value(t, "tilt_deg", "NaN"))),
    Case(
        "cal_infinity", WITH_CAL, 2, "Infinity is not a number", _cal_text(lambda t: _value(t, "pan_deg", "-Infinity"))
    ),
    Case(
        "cal_translation_1e6_m",
        WITH_CAL,
        2,
        "T_forklift_camera: the camera is 1e+06 m from the forklift origin",
        _cal(lambda d: [_set_t(0, 3, 1e6)(d), d.pop("xyz_m")]),
    ),
    Case("cal_not_a_rotation", WITH_CAL, 2, "rotation block is not orthonormal", _cal(_scale_rotation)),
    Case("cal_reflection", WITH_CAL, 2, "a reflection, not a proper rotation", _cal(_reflect)),
    Case("cal_last_row", WITH_CAL, 2, "the last row must be [0, 0, 0, 1]", _cal(_set_t(3, 0, 0.5))),
    Case(
        "cal_three_rows",
        WITH_CAL,
        2,
        "T_forklift_camera[3]: Field required",
        _cal(lambda d: d.update(T_forklift_camera=d["T_forklift_camera"][:3])),
    ),
    Case("cal_xyz_disagrees", WITH_CAL, 2, "xyz_m: [", _cal(lambda d: d["xyz_m"].__setitem__(0, 0.5))),
    Case("cal_rpy_disagrees", WITH_CAL, 2, "rpy_deg: [", _cal(lambda d: d["rpy_deg"].__setitem__(2, 0.0))),
    Case(
        "cal_unknown_key",
        WITH_CAL,
        2,
        "T_forklift_camra: Extra inputs are not permitted",
        _cal(lambda d: d.update(T_forklift_camra=1)),
    ),
    Case(
        "cal_method_number", WITH_CAL, 2, "method: Input should be a valid string", _cal(lambda d: d.update(method=3))
    ),
    Case("cal_no_transform", WITH_CAL, 2, "not a calibration file", _cal_text(lambda t: "{}")),
    Case("cal_a_list", WITH_CAL, 2, "not a calibration file", _cal_text(lambda t: "[1, 2, 3]")),
    Case(
        "cal_latin1",
        WITH_CAL,
        2,
        "not UTF-8 text: byte 0xe9",
        _cal_text(lambda t: t.replace('"model"', '"mod\u00e9le"').encode("latin-1")),
    ),
    Case("cal_binary", WITH_CAL, 2, "not UTF-8 text", _cal_text(lambda t: bytes(range(256)) * 4)),
    Case("cal_empty", WITH_CAL, 2, "cal.json: not valid JSON", _cal_text(lambda t: "")),
    Case("cal_truncated", WITH_CAL, 2, "cal.json: not valid JSON", _cal_text(lambda t: t[: len(t) // 2])),
    Case("cal_too_large", WITH_CAL, 2, "cal.json: too large", _cal_text(lambda t: t + " " * (2 * 2**20))),
    Case("cal_folder", WITH_CAL, 2, "cal.json: a folder", _cal_folder),
    Case("cal_missing", WITH_CAL, 2, "cal.json: cannot read"),
    Case(
        "cal_yaml_instead",
        WITH_CAL,
        2,
        "cal.json: not valid JSON",
        _cal_text(lambda t: "T_forklift_camera: identity\n"),
    ),
]


# -- fork and pallet type files -------------------------------------------------------------------------

FORKS = "{case}/forks.yaml"
WITH_FORKS = ("calibrate", "{frame}", "--forks", FORKS)


def _forks(**changes: object) -> Setup:
    def setup(fx: Fixtures, folder: Path) -> None:
        doc = example(fx, "forks.yaml")
        for key, value in changes.items():
            if value is None:
                doc.pop(key)
            else:
                doc[key] = value
        write(folder, "forks.yaml", dump(doc))

    return setup


FORKS_CASES = [
    Case(
        "forks_length_inf",
        WITH_FORKS,
        2,
        "forks.yaml: length: Input should be a finite number",
        _forks(length=float("inf")),
    ),
    Case("forks_length_nan", WITH_FORKS, 2, "length: Input should be a finite number", _forks(length=float("nan"))),
    Case("forks_length_30m", WITH_FORKS, 2, "length: 30 m is outside 0.5..3 m", _forks(length=30.0, tip_x=30.0)),
    Case("forks_width_negative", WITH_FORKS, 2, "width: -0.16 m is outside 0.03..0.4 m", _forks(width=-0.16)),
    Case("forks_thickness_zero", WITH_FORKS, 2, "thickness: 0 m is outside", _forks(thickness=0.0)),
    Case("forks_inner_gap_10m", WITH_FORKS, 2, "inner_gap: 10 m is outside 0.02..2 m", _forks(inner_gap=10.0)),
    Case("forks_tip_behind_the_truck", WITH_FORKS, 2, "tip_x: -5 m is outside 0.3..4 m", _forks(tip_x=-5.0)),
    Case("forks_heels_far_ahead", WITH_FORKS, 2, "tip_x: puts the fork heels", _forks(tip_x=3.5)),
    Case("forks_string_number", WITH_FORKS, 2, "thickness: Input should be a valid number", _forks(thickness="0.05")),
    Case("forks_missing_tip_x", WITH_FORKS, 2, "tip_x: Field required", _forks(tip_x=None)),
    Case("forks_unknown_key", WITH_FORKS, 2, "colour: Extra inputs are not permitted", _forks(colour="red")),
    Case("forks_every_problem", WITH_FORKS, 2, "width: 5 m is outside", _forks(length=0.0, width=5.0)),
]

PALLET = "{case}/pallet.yaml"


WITH_PALLET = ("estimate-pallet", "{frame}", "--calibration", "{cal}", "--pallet", PALLET)


def _pallet(text: str) -> Setup:
    def setup(fx: Fixtures, folder: Path) -> None:
        write(folder, "pallet.yaml", text)

    return setup


PALLET_CASES = [
    Case("pallet_width_50m", WITH_PALLET, 2, "pallet.yaml: width: 50 m is outside 0.3..3 m", _pallet("width: 50\n")),
    Case(
        "pallet_layers_do_not_add_up",
        WITH_PALLET,
        2,
        "height: layers add up to 166.0 mm",
        _pallet("block_height: 0.1\n"),
    ),
    Case(
        "pallet_no_room_for_pockets", WITH_PALLET, 2, "no room for pockets", _pallet("block_columns: [0.3, 0.3, 0.3]\n")
    ),
    Case("pallet_inf_height", WITH_PALLET, 2, "height: Input should be a finite number", _pallet("height: .inf\n")),
    Case(
        "pallet_negative_block", WITH_PALLET, 2, "block_height: -0.078 m is outside", _pallet("block_height: -0.078\n")
    ),
    Case(
        "pallet_no_deck_boards",
        WITH_PALLET,
        2,
        "top_board_widths: Tuple should have at least 1 item",
        _pallet("top_board_widths: []\n"),
    ),
    Case("pallet_string_number", WITH_PALLET, 2, "length: Input should be a valid number", _pallet("length: '1.2'\n")),
    Case("pallet_unknown_key", WITH_PALLET, 2, "pockets: Extra inputs are not permitted", _pallet("pockets: 2\n")),
    Case("pallet_unknown_type_name", (*WITH_PALLET[:-1], "eru"), 2, "eru: not a known pallet type"),
    Case(
        "pallet_calibrate",
        ("calibrate", "{frame}", "--forks", "{ex}/forks.yaml", "--pallet", PALLET),
        2,
        "pallet.yaml: length: 0.05 m is outside",
        _pallet("length: 0.05\n"),
    ),
]

CASES: list[Case] = FRAME_CASES + CAL_CASES + FORKS_CASES + PALLET_CASES
