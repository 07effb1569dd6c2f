import numpy as np
import pytest

from calibration.calibfile import CalibrationDoc, CalibrationStore
from calibration.camera import Camera, look_at_c2w
from rig.assembly import load_rig_calibration


def test_rig_reads_the_keepers_calibration_and_names_its_version(tmp_path):
    k = np.array([[500.0, 0, 320.5], [0, 500, 240.5], [0, 0, 1]])
    cams = {f"cam{i:02d}": Camera(k, 640, 480, np.zeros(5), look_at_c2w(np.array([np.cos(i), np.sin(i), 0.3]), np.zeros(3))) for i in range(3)}
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
    figures = {"cam0": {"uncertainty": {"extrinsics_cv_rotation_deg": 0.04, "extrinsics_cv_translation_mm": 0.3}},
               "cam1": {"uncertainty": {"extrinsics_cv_rotation_deg": 0.02, "extrinsics_cv_translation_mm": 0.5}}}
    CalibrationStore(tmp_path / "calibration.json").commit(CalibrationDoc(cams, figures))
    # The worst camera's figures: the rig is only as good as its worst camera.
    assert load_rig_calibration(tmp_path / "calibration.json").uncertainty == {"rotation_deg": 0.04, "translation_mm": 0.5}


def test_missing_calibration_is_one_sentence(tmp_path):
    with pytest.raises(ValueError, match="calibration"):
        load_rig_calibration(tmp_path / "nope.json")
