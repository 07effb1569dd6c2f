"""The keeper on a synthetic rig: knocks found and attributed, no false alarms, corrections that hold."""

from __future__ import annotations

import numpy as np
import pytest

from calibration.calibfile import CalibrationDoc, CalibrationStore
from calibration.drift import THOROUGH, fiducial_drift
from calibration.keeper import OK, RECALIBRATE, WARN, Keeper, KeeperConfig, assess, plot_history
from calibration.simulated import render_planes, rig_frame_scene, ring_rig, sensor
from calibration.so3 import axis_angle_to_matrix


@pytest.fixture(scope="module")
def rig():
    rng = np.random.default_rng(7)
    planes, fiducials = rig_frame_scene(rng)
    cams = {f"cam{i}": c for i, c in enumerate(ring_rig(4, radius=0.5, arc_deg=90))}
    clean = {n: render_planes(c, planes, supersample=2) for n, c in cams.items()}
    return planes, fiducials, cams, clean


def knock(camera, deg: float, rng) -> np.ndarray:
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    c2w = camera.c2w.copy()
    c2w[:3, :3] = c2w[:3, :3] @ axis_angle_to_matrix(np.radians(deg) * axis)
    return c2w


def new_keeper(tmp_path, cams, fiducials=None) -> Keeper:
    path = tmp_path / "calibration.json"
    CalibrationStore(path).commit(CalibrationDoc(dict(cams), source="board", fiducials=fiducials))
    return Keeper(path, KeeperConfig())


def test_no_false_alarms_over_100_captures_with_noise_and_lighting(rig):
    _, _, cams, clean = rig
    calib = CalibrationDoc(dict(cams), source="board")
    rng = np.random.default_rng(1)
    refs = {n: (sensor(img, rng), cams[n].c2w) for n, img in clean.items()}
    worst = 0.0
    for _ in range(100):
        gain, offset = rng.uniform(0.7, 1.3), rng.uniform(-0.06, 0.06)
        result = assess(
            calib, {n: sensor(img, rng, noise=0.015, gain=gain, offset=offset) for n, img in clean.items()}, refs, KeeperConfig()
        )
        assert result.status == OK, result
        worst = max(worst, max(c.effect_px for c in result.cameras.values()))
    assert worst < 0.25


def test_knock_is_detected_attributed_and_corrected(tmp_path, rig):
    planes, fiducials, cams, clean = rig
    keeper = new_keeper(tmp_path, cams)
    rng = np.random.default_rng(2)
    keeper.set_reference({n: sensor(img, rng) for n, img in clean.items()})
    knocked = knock(cams["cam2"], 0.1, rng)
    images = {n: sensor(img, rng, gain=1.1) for n, img in clean.items()}
    images["cam2"] = sensor(render_planes(cams["cam2"].with_c2w(knocked), planes, supersample=2), rng, gain=1.1)
    rec = keeper.check(images, capture="after-knock", mode=THOROUGH)
    assert rec["status"] == WARN
    assert [n for n, c in rec["cameras"].items() if c["status"] != OK] == ["cam2"]
    assert rec["cameras"]["cam2"]["rotation_deg"] == pytest.approx(0.1, abs=0.01)
    assert keeper.store.versions() == [1, 2]
    corrected = keeper.store.load()
    assert corrected.parent == 1 and corrected.source == "drift-correction"
    # Reprojection of the rig's fiducials in the knocked image: pre-knock calibration vs corrected.
    fid_img = images["cam2"]
    markers = np.concatenate([np.asarray(v) for v in fiducials["markers"].values()])

    def rms(cam) -> float:
        from calibration.drift import detect_fiducials

        seen = detect_fiducials(fid_img, fiducials["dictionary"])
        obj = np.concatenate([np.asarray(fiducials["markers"][i]) for i in seen])
        img = np.concatenate(list(seen.values()))
        uv, _ = cam.project(obj)
        return float(np.sqrt(np.mean(np.sum((uv - img) ** 2, 1))))

    truth = rms(cams["cam2"].with_c2w(knocked))
    before = rms(cams["cam2"])
    after = rms(corrected.cameras["cam2"])
    assert before > truth + 0.5
    assert after <= truth + 0.2
    assert len(markers) > 0
    # The next capture is OK against the corrected calibration.
    rec2 = keeper.check(images, capture="next", mode=THOROUGH)
    assert rec2["status"] == OK


def test_large_knock_raises_alarm_and_flags_captures(tmp_path, rig):
    planes, _, cams, clean = rig
    keeper = new_keeper(tmp_path, cams)
    rng = np.random.default_rng(3)
    keeper.set_reference({n: sensor(img, rng) for n, img in clean.items()})
    images = {n: sensor(img, rng) for n, img in clean.items()}
    images["cam1"] = sensor(render_planes(cams["cam1"].with_c2w(knock(cams["cam1"], 1.0, rng)), planes, supersample=2), rng)
    for cap in ("c1", "c2"):
        rec = keeper.check(images, capture=cap)
    assert rec["status"] == RECALIBRATE
    alarm = keeper.alarm()
    assert alarm["cameras"] == ["cam1"] and alarm["flagged_captures"] == ["c1", "c2"]
    assert keeper.store.versions() == [1]  # large drift is never "corrected" silently
    sha = plot_history(keeper.history(), tmp_path / "drift.png", keeper.config)
    assert len(sha) == 64 and (tmp_path / "drift.png").stat().st_size > 1000


def test_fiducials_give_pose_without_background(rig):
    planes, fiducials, cams, clean = rig
    rng = np.random.default_rng(4)
    cam = cams["cam1"]
    est = fiducial_drift(cam, sensor(clean["cam1"], rng), fiducials)
    assert est is not None and est.matches >= 8
    assert est.rotation_deg < 0.1 and est.translation_mm < 3.0
    moved = knock(cam, 0.5, rng)
    est = fiducial_drift(cam, sensor(render_planes(cam.with_c2w(moved), planes, supersample=2), rng), fiducials)
    assert est.rotation_deg == pytest.approx(0.5, abs=0.08)
