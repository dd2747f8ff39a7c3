"""RealSense sources without hardware: software_device frames recorded to .db3, played back and checked.

The synthetic camera: a 640x480 depth imager (f 380 px) and a 640x480 colour imager (f 600 px, an
off-centre principal point) 15 mm to its right (identity rotation). The depth image is a wall at
2.0 m + 0.1 m per frame with a 1.0 m box in front of it (depth pixels u 280..359, v 200..279), stored
with 0.5 mm depth units. Colour pixel (u, v) is (u % 256, v % 256, 40 * frame).
"""

from __future__ import annotations

import sqlite3
import sys

import numpy as np
import pytest

pytest.importorskip("pyrealsense2")

from palletpilot.perception import realsense
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.frames import load_bundle
from palletpilot.perception.realsense import (
    CameraSource,
    EndOfRecordingError,
    RealSenseSource,
    RecordingSource,
    extract_recording,
)
from palletpilot.perception.realsense_synthetic import write_software_recording

H, W = 480, 640
K_DEPTH = np.array([[380.0, 0.0, 320.0], [0.0, 380.0, 240.0], [0.0, 0.0, 1.0]])
K_COLOUR = np.array([[600.0, 0.0, 331.5], [0.0, 600.0, 235.25], [0.0, 0.0, 1.0]])
BASELINE_M = 0.015
DEPTH_UNITS = 0.0005
BOX_Z, BOX_U, BOX_V = 1.0, (280, 360), (200, 280)
N_FRAMES = 6


def wall_z(n: int) -> float:
    return 2.0 + 0.1 * n


def depth_image(n: int) -> np.ndarray:
    d = np.full((H, W), wall_z(n))
    d[BOX_V[0] : BOX_V[1], BOX_U[0] : BOX_U[1]] = BOX_Z
    return d


def colour_image(n: int) -> np.ndarray:
    c = np.zeros((H, W, 3), np.uint8)
    c[..., 0] = np.arange(W)[None, :] % 256
    c[..., 1] = (np.arange(H) % 256)[:, None]
    c[..., 2] = 40 * n
    return c


def T_colour_depth() -> np.ndarray:
    T = np.eye(4)
    T[0, 3] = BASELINE_M
    return T


def record(path, frames=N_FRAMES, skip_colour=()):
    return write_software_recording(
        path,
        [depth_image(n) for n in range(frames)],
        [None if n in skip_colour else colour_image(n) for n in range(frames)],
        K_depth=K_DEPTH,
        K_colour=K_COLOUR,
        T_colour_depth=T_colour_depth(),
        depth_units=DEPTH_UNITS,
    )


def expected_aligned(n: int) -> np.ndarray:
    """Depth (m) each colour pixel should see; NaN where it is not predictable (edges, occlusion shadow)."""
    v, u = np.mgrid[0:H, 0:W].astype(np.float64)

    def classify(du: float, dv: float) -> np.ndarray:
        x = (u + du - K_COLOUR[0, 2]) / K_COLOUR[0, 0]
        y = (v + dv - K_COLOUR[1, 2]) / K_COLOUR[1, 1]

        def depth_pixel(z: float) -> tuple[np.ndarray, np.ndarray]:  # colour ray at depth z -> depth image
            return (K_DEPTH[0, 0] * (x * z - BASELINE_M) / z + K_DEPTH[0, 2], K_DEPTH[1, 1] * y + K_DEPTH[1, 2])

        def in_box(ud: np.ndarray, vd: np.ndarray) -> np.ndarray:
            return (ud >= BOX_U[0] - 0.5) & (ud < BOX_U[1] - 0.5) & (vd >= BOX_V[0] - 0.5) & (vd < BOX_V[1] - 0.5)

        box = in_box(*depth_pixel(BOX_Z))
        shadow = ~box & in_box(*depth_pixel(wall_z(n)))  # wall seen by colour, hidden from depth
        return np.where(box, 1, np.where(shadow, 2, 0))

    cls = classify(0, 0)
    stable = np.ones((H, W), bool)
    for du in (-2, 0, 2):  # rs.align splats each depth pixel over a rounded footprint: edges move ~1 px
        for dv in (-2, 0, 2):
            stable &= classify(du, dv) == cls
    out = np.where(cls == 1, BOX_Z, wall_z(n))
    return np.where(stable & (cls != 2), out, np.nan)


@pytest.fixture(scope="module")
def recording(tmp_path_factory):
    return record(tmp_path_factory.mktemp("rs") / "synthetic.db3")


def test_recorder_writes_every_frame_to_db3(recording):
    with sqlite3.connect(recording) as db:
        counts = dict(
            db.execute(
                "select t.name, count(*) from messages m join topics t on t.id = m.topic_id "
                "where t.name like '%/image/data%' group by t.name"
            ).fetchall()
        )
    assert sorted(counts.values()) == [N_FRAMES, N_FRAMES]


def test_playback_yields_every_frame_in_metres_aligned_to_colour(recording):
    with RecordingSource(recording) as src:
        assert isinstance(src, CameraSource)
        bundles, stamps = [], []
        for bundle in src:
            bundles.append(bundle)
            stamps.append(src.last_stamp)
        assert src.frames_read == N_FRAMES and src.unpaired == 0
        with pytest.raises(EndOfRecordingError):
            src.grab()
    assert len(bundles) == N_FRAMES
    for n, (b, st) in enumerate(zip(bundles, stamps, strict=True)):
        assert st.frame_number == n and st.depth_frame_number == n
        assert st.depth_timestamp_s == pytest.approx(1.0 + n / 30.0)
        assert st.timestamp_s == pytest.approx(1.0 + n / 30.0 + 0.002)
        assert st.timestamp_domain == "hardware_clock"
        assert b.depth.dtype == np.float32 and b.depth.shape == (H, W)
        assert b.K.dtype == np.float64
        np.testing.assert_array_equal(b.K, K_COLOUR)
        np.testing.assert_array_equal(b.rgb, colour_image(n))
        assert b.labels is None and b.fork_height == 0.0
        want = expected_aligned(n)
        known = np.isfinite(want)
        assert known.mean() > 0.9
        np.testing.assert_allclose(b.depth[known], want[known], rtol=1e-6)
        # the box appears where the colour camera sees it: shifted by f_c * baseline / z, scaled by f_c / f_d
        _, cols = np.nonzero(np.isclose(b.depth, BOX_Z))
        u_left = K_COLOUR[0, 0] * ((BOX_U[0] - 0.5 - K_DEPTH[0, 2]) / K_DEPTH[0, 0] + BASELINE_M) + K_COLOUR[0, 2]
        assert cols.min() == pytest.approx(u_left, abs=1.0)
        # holes only in the occlusion shadow next to the box, none elsewhere
        holes = b.depth == 0
        assert np.all(~known[holes] | (want[holes] == 0))
        assert holes.sum() < 0.01 * H * W


def test_unpaired_depth_frame_is_skipped(tmp_path):
    path = record(tmp_path / "gap.db3", frames=4, skip_colour={2})
    with RecordingSource(path) as src:
        got = [(src.grab(), src.last_stamp.frame_number)[1] for _ in range(3)]
        with pytest.raises(EndOfRecordingError):
            src.grab()
        assert got == [0, 1, 3] and src.unpaired == 1


def test_depth_filters_fill_holes(tmp_path):
    depth = depth_image(0)
    depth[100:104, 150:154] = 0.0  # a 4 x 4 hole in the wall, far from the box
    path = write_software_recording(
        tmp_path / "hole.db3",
        [depth],
        [colour_image(0)],
        K_depth=K_DEPTH,
        K_colour=K_COLOUR,
        T_colour_depth=T_colour_depth(),
        depth_units=DEPTH_UNITS,
    )
    with RecordingSource(path) as src:
        raw = src.grab()
    with RecordingSource(path, filters=["hole_filling", "spatial", "temporal"]) as src:
        filled = src.grab()
    region = (slice(0, 60), slice(30, 130))  # the hole's image in colour (near u 68, v 14) lies in here
    assert (raw.depth[region] == 0).sum() > 0
    assert (filled.depth[region] == 0).sum() == 0
    with pytest.raises(PerceptionError, match="unknown depth filter"):
        RecordingSource(path, filters=["median"])


def test_extract_recording_writes_loadable_bundles(recording, tmp_path):
    out = tmp_path / "frames"
    paths = extract_recording(recording, out)
    assert [p.name for p in paths] == [f"frame_{i:04d}.npz" for i in range(N_FRAMES)]
    for n, p in enumerate(paths):
        b = load_bundle(p)
        np.testing.assert_array_equal(b.K, K_COLOUR)
        np.testing.assert_array_equal(b.rgb, colour_image(n))
        assert np.nanmax(b.depth) == pytest.approx(wall_z(n), rel=1e-6)
    assert len(extract_recording(recording, tmp_path / "two", count=2)) == 2
    with pytest.raises(PerceptionError, match="already holds"):
        extract_recording(recording, out)


def test_missing_and_unreadable_recordings(recording, tmp_path):
    with pytest.raises(PerceptionError, match="no such recording"):
        RecordingSource(tmp_path / "nope.db3")
    junk = tmp_path / "junk.db3"
    junk.write_bytes(b"not a recording at all")
    with pytest.raises(PerceptionError, match="not a RealSense recording"):
        RecordingSource(junk)
    empty_db = tmp_path / "empty.db3"
    sqlite3.connect(empty_db).execute("create table t (x)").connection.close()
    with pytest.raises(PerceptionError, match=r"cannot read this rosbag2 \.db3"):
        RecordingSource(empty_db)
    renamed = tmp_path / "renamed.bag"
    renamed.write_bytes(recording.read_bytes())
    with pytest.raises(PerceptionError, match="rename it"):
        RecordingSource(renamed)
    ros1 = tmp_path / "old.bag"
    ros1.write_bytes(b"#ROSBAG V2.0\n\x04\x00\x00\x00")
    with pytest.raises(PerceptionError, match=r"cannot read this ROS 1 \.bag"):
        RecordingSource(ros1)
    with pytest.raises(PerceptionError, match="is a directory"):
        RecordingSource(tmp_path)


class FakeDevice:
    def __init__(self, serial: str, name: str) -> None:
        rs = realsense.import_pyrealsense2()
        self.info = {rs.camera_info.serial_number: serial, rs.camera_info.name: name}

    def supports(self, key):
        return key in self.info

    def get_info(self, key):
        return self.info[key]


class FakeContext:
    def __init__(self, devices):
        self.devices = devices

    def query_devices(self):
        return list(self.devices)


def test_no_camera_is_a_clear_error():
    with pytest.raises(PerceptionError, match="no RealSense camera found"):
        RealSenseSource(context=FakeContext([]))


def test_unknown_serial_lists_the_cameras_found():
    ctx = FakeContext([FakeDevice("111", "Intel RealSense D435I"), FakeDevice("222", "Intel RealSense D435")])
    with pytest.raises(PerceptionError) as err:
        RealSenseSource("999", context=ctx)
    msg = str(err.value)
    assert (
        "serial 999 not found" in msg and "111 (Intel RealSense D435I)" in msg and "222 (Intel RealSense D435)" in msg
    )


def test_unsupported_stream_settings_are_refused():
    with pytest.raises(PerceptionError, match="width 1280"):
        RealSenseSource(width=1280, context=FakeContext([]))
    with pytest.raises(PerceptionError, match="fps 60"):
        RealSenseSource(fps=60, context=FakeContext([]))


def test_missing_pyrealsense2_says_how_to_install(monkeypatch, tmp_path):
    monkeypatch.setitem(sys.modules, "pyrealsense2", None)
    with pytest.raises(PerceptionError, match="BUILD_PYTHON_BINDINGS") as err:
        RecordingSource(tmp_path / "x.db3")
    assert "Jetson" in str(err.value) and "\n" not in str(err.value)
    with pytest.raises(PerceptionError, match="librealsense"):
        RealSenseSource()
