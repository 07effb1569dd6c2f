from dataclasses import replace

import numpy as np
import pytest

from calibration.calibfile import CalibrationDoc, CalibrationStore
from calibration.camera import Camera, look_at_c2w
from rig.assembly import DRIVERS, build_camera, load_rig_calibration
from rig.camera import CameraError
from rig.config import CAMERA_DRIVERS, parse_config
from rig.oak import OakCamera
from rig.replay import ReplayCamera
from rig.synthetic_driver import PatternCamera


def test_rig_reads_the_keepers_calibration_and_names_its_version(tmp_path):
    k = np.array([[500.0, 0, 320.5], [0, 500, 240.5], [0, 0, 1]])
    cams = {
        f"cam{i:02d}": Camera(k, 640, 480, np.zeros(5), look_at_c2w(np.array([np.cos(i), np.sin(i), 0.3]), np.zeros(3))) for i in range(3)
    }
    store = CalibrationStore(tmp_path / "calibration.json")
    store.commit(CalibrationDoc(cams))
    store.commit(CalibrationDoc(cams, source="auto-correction"))
    cal_id, loaded, uncertainty = load_rig_calibration(tmp_path / "calibration.json")
    assert cal_id == "calibration-v0002"
    assert uncertainty is None  # a hand-made document states no cross-check
    assert set(loaded) == set(cams)
    np.testing.assert_allclose(loaded["cam01"].c2w, cams["cam01"].c2w, atol=1e-12)
    assert load_rig_calibration(None) == ("uncalibrated", {}, None)


def test_rig_passes_the_calibrations_stated_uncertainty_to_its_captures(tmp_path):
    k = np.array([[500.0, 0, 320.5], [0, 500, 240.5], [0, 0, 1]])
    cams = {f"cam{i}": Camera(k, 640, 480, np.zeros(5), look_at_c2w(np.array([np.cos(i), np.sin(i), 0.3]), np.zeros(3))) for i in range(2)}
    figures = {
        "cam0": {"uncertainty": {"extrinsics_cv_rotation_deg": 0.04, "extrinsics_cv_translation_mm": 0.3}},
        "cam1": {"uncertainty": {"extrinsics_cv_rotation_deg": 0.02, "extrinsics_cv_translation_mm": 0.5}},
    }
    CalibrationStore(tmp_path / "calibration.json").commit(CalibrationDoc(cams, figures))
    # The worst camera's figures: the rig is only as good as its worst camera.
    assert load_rig_calibration(tmp_path / "calibration.json").uncertainty == {"rotation_deg": 0.04, "translation_mm": 0.5}


def test_missing_calibration_is_one_sentence(tmp_path):
    with pytest.raises(ValueError, match="calibration"):
        load_rig_calibration(tmp_path / "nope.json")


def test_every_driver_rig_toml_accepts_is_built_by_name(tmp_path):
    assert set(DRIVERS) == set(CAMERA_DRIVERS)
    cfg = parse_config(
        {
            "cameras": [
                {"id": "a", "driver": "oak", "device": "18443010D1C2A41200", "socket": "CAM_B"},
                {"id": "b", "driver": "replay", "path": str(tmp_path)},
                {"id": "c", "driver": "pattern", "width": 320, "height": 240},
            ]
        }
    )
    drivers = [build_camera(c, None, i, len(cfg.cameras)) for i, c in enumerate(cfg.cameras)]
    assert [type(d) for d in drivers] == [OakCamera, ReplayCamera, PatternCamera]
    assert [d.camera_id for d in drivers] == ["a", "b", "c"]
    assert (drivers[0].device_id, drivers[0].socket) == ("18443010D1C2A41200", "CAM_B")
    assert (drivers[2].camera.width, drivers[2].camera.height) == (320, 240)


def test_an_unknown_driver_is_one_sentence_naming_the_known_ones():
    cam = replace(parse_config({"cameras": [{"id": "a", "driver": "pattern"}]}).cameras[0], driver="gige")
    with pytest.raises(CameraError) as e:
        build_camera(cam, None, 0, 1)
    assert str(e.value) == "unknown camera driver 'gige' (known: oak, pattern, replay)"
