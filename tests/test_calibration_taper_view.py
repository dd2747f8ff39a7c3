"""Issue 17: a tapered top face hidden from a shallow mount, and forks files that state the blade profile or not."""

import math

import numpy as np
import pytest
import yaml

from palletpilot.geometry import SE3
from palletpilot.geometry.fileio import bundled_path
from palletpilot.perception import calibration as cal
from palletpilot.perception.calibration import LIMITS, calibrate
from palletpilot.perception.errors import PerceptionError
from palletpilot.perception.specs import ForkGeometry, load_forks
from palletpilot.sim.scenario import Scenario
from palletpilot.sim.simulator import Simulator

MISSIONS = bundled_path("missions")
PROFILE_KEYS = {"taper_length", "tip_thickness", "taper_side"}
BOX = load_forks(MISSIONS / "forks.yaml").model_dump(exclude_unset=True, exclude=PROFILE_KEYS)
UNKNOWN = ForkGeometry.model_validate(BOX)  # the nominal box, profile left out: unknown
STATED_BOX = ForkGeometry.model_validate({**BOX, "taper_length": 0.0})  # "measured: plain boxes"
# A short, steep taper (55 mm down to 12 mm: 37 deg) seen from a shallow mount (20 deg down, 0.6 m up): its
# sloping top faces away from the camera. The beyond-tip evidence finds fewer pixels than it needs.
SHALLOW = {"x": -0.05, "y": 0.01, "z": 0.6, "tilt_deg": 20.0, "pan_deg": 1.0, "roll_deg": 0.5}


def render(tmp_path, true: ForkGeometry, seed: int = 0):
    path = tmp_path / "true_forks.yaml"
    path.write_text(yaml.safe_dump({k: v for k, v in true.model_dump().items() if v is not None}))
    camera = {"mount": SHALLOW, "noise": {"label_noise": True}}
    sc = Scenario.model_validate(
        {"map": "warehouse.yaml", "start": "c_w", "seed": seed, "forks": str(path), "camera": camera}
    )
    sc.folder = MISSIONS
    sim = Simulator(sc)
    return sim.grab(), sim.T_forklift_camera_true


def test_the_forks_file_states_the_profile_or_leaves_it_unknown(tmp_path):
    def load(**extra) -> ForkGeometry:
        path = tmp_path / "forks.yaml"
        path.write_text(yaml.safe_dump({**BOX, **extra}))
        return load_forks(path)

    assert not load().profile_stated and not UNKNOWN.profile_stated
    box = load(taper_length=0)
    assert box.profile_stated and not box.tapered and box == load()  # same blades, stated
    assert load(taper_length=0.1, tip_thickness=0.018).profile_stated
    with pytest.raises(PerceptionError) as info:
        load(taper_length=-0.01)
    assert len(info.value.problems) == 1 and "taper_length" in info.value.problems[0]


def test_a_taper_hidden_from_a_shallow_mount_is_flagged(tmp_path):
    true = ForkGeometry.model_validate({**BOX, "taper_length": 0.055, "tip_thickness": 0.012})
    frame, truth = render(tmp_path, true)
    calib = calibrate([frame], UNKNOWN)
    assert (calib.T_forklift_camera.t - truth.t)[0] > 0.04  # off by about the taper's length
    assert calib.quality["beyond_tip_points"] < LIMITS.min_beyond_points  # the frame shows (almost) nothing
    assert calib.quality["tip_trusted"] is False
    assert calib.quality["tip_view_deg"] < calib.quality["tip_view_needed_deg"]
    (warning,) = calib.warnings
    assert "fork tips cannot be verified" in warning and f"{calib.quality['tip_view_deg']:.0f} deg" in warning
    assert "forks measure" in warning and "taper_length: 0" in warning


def test_box_blades_warn_only_while_the_file_leaves_the_profile_unknown(tmp_path):
    frame, truth = render(tmp_path, STATED_BOX)
    stated = calibrate([frame], STATED_BOX)
    assert stated.quality["tip_trusted"] and not stated.warnings
    assert np.all(np.abs(stated.T_forklift_camera.t - truth.t) < 0.005)
    unknown = calibrate([frame], UNKNOWN)  # the same blades and fit, but nothing says they are boxes
    assert unknown.quality["tip_trusted"] is False and "cannot be verified" in unknown.warnings[0]
    assert unknown.T_forklift_camera.isclose(stated.T_forklift_camera, atol=1e-9, atol_rot=1e-9)


def _tips_seen_at(angle_deg: float) -> list[cal._Edges]:
    """Tip edge rays descending at `angle_deg` along x (camera frame = forklift frame)."""
    a = math.radians(angle_deg)
    rays = np.tile([math.cos(a), 0.0, -math.sin(a)], (10, 1))
    return [cal._Edges(rays, np.zeros((0, 3)), np.zeros(0))]


@pytest.mark.parametrize(
    ("angle", "forks", "trusted"),
    [(30.0, UNKNOWN, False), (45.0, UNKNOWN, True), (30.0, STATED_BOX, True)],
)
def test_the_view_check_needs_the_steepest_taper_in_view_or_a_stated_profile(angle, forks, trusted):
    quality: dict = {"tip_trusted": True}
    warnings: list[str] = []
    cal._tip_view_check(_tips_seen_at(angle), SE3.identity(), forks, quality, warnings)
    assert quality["tip_view_deg"] == pytest.approx(angle)
    assert quality["tip_trusted"] is trusted and len(warnings) == (0 if trusted else 1)
    # Already untrusted (fork pixels beyond the tips): left as it is, one warning is enough.
    quality, warnings = {"tip_trusted": False}, []
    cal._tip_view_check(_tips_seen_at(angle), SE3.identity(), forks, quality, warnings)
    assert quality["tip_trusted"] is False and not warnings
