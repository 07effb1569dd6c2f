"""Rig calibration: a synthetic 4-camera rig against ground truth, OpenCV's stereo pair, hard cases."""

from __future__ import annotations

import cv2
import numpy as np
import pytest

from calibration.board import detect_board, parse_board
from calibration.camera import invert_rigid
from calibration.intrinsics import CalibrationError
from calibration.multiview import calibrate_rig
from calibration.simulated import rig_board_views, ring_rig
from calibration.so3 import geodesic_angle_deg
from tests.conftest import require_shared

SPEC = parse_board("charuco:11x8:0.025:0.015:DICT_5X5_100")


@pytest.fixture(scope="module")
def session():
    rng = np.random.default_rng(0)
    cams = {f"cam{i}": c for i, c in enumerate(ring_rig(4, radius=0.5, arc_deg=90))}
    images, _ = rig_board_views(SPEC, cams, rng, shared=16, close_ups=12)
    dets = {n: {f: detect_board(SPEC, im) for f, im in v.items()} for n, v in images.items()}
    return cams, dets


def test_synthetic_rig_extrinsics_within_005_deg_and_05_mm(session):
    cams, dets = session
    rig = calibrate_rig(dets, {n: (640, 480) for n in dets})
    to_ref = invert_rigid(cams["cam0"].c2w)
    for n, cam in cams.items():
        truth = to_ref @ cam.c2w
        est = rig.cameras[n].c2w
        assert geodesic_angle_deg(truth[:3, :3], est[:3, :3]) < 0.05, n
        assert 1000 * np.linalg.norm(truth[:3, 3] - est[:3, 3]) < 0.5, n
        assert rig.rms_px[n] < 0.15
        assert rig.coverage[n] > 0.4
    assert set(rig.single_camera_frames) >= {f"cam0_close{k:02d}" for k in range(12) if dets["cam0"][f"cam0_close{k:02d}"] is not None}
    assert all(v["rotation_deg"] < 0.05 for v in rig.extrinsics_cv.values())
    assert all(v is not None and v < 1.5 for v in rig.intrinsics_cv_px.values())


def test_camera_that_never_sees_the_board_is_named(session):
    _, dets = session
    blind = {**dets, "cam9": {f: None for f in dets["cam0"]}}
    with pytest.raises(CalibrationError, match="cam9"):
        calibrate_rig(blind, {n: (640, 480) for n in blind}, cross_validate=False)


def test_camera_sharing_no_frame_is_named(session):
    _, dets = session
    # cam3 keeps only its own close-ups: calibratable alone, but not linked to the rig.
    alone = {**dets, "cam3": {f: d for f, d in dets["cam3"].items() if f.startswith("cam3_close")}}
    with pytest.raises(CalibrationError, match="cam3 share no board frame"):
        calibrate_rig(alone, {n: (640, 480) for n in alone}, cross_validate=False)


def test_opencv_stereo_pair_agrees_with_stereo_calibrate():
    folder = require_shared("calibration", "opencv_chessboard")
    spec = parse_board("chessboard:9x6:0.025")
    dets = {
        side: {p.stem[len(side) :]: detect_board(spec, cv2.imread(str(p))) for p in sorted(folder.glob(f"{side}*.jpg"))}
        for side in ("left", "right")
    }
    rig = calibrate_rig(dets, {"left": (640, 480), "right": (640, 480)}, cross_validate=False)
    assert rig.rms_px["left"] <= 0.409 and rig.rms_px["right"] <= 0.459
    # OpenCV's stereo_calib sample on the same list: stereoCalibrate with per-camera intrinsics.
    frames = sorted(dets["left"])
    obj = [dets["left"][f].object_points.astype(np.float32) for f in frames]
    pts = {s: [(dets[s][f].uv - 0.5).astype(np.float32) for f in frames] for s in dets}
    k, d = {}, {}
    for s in dets:
        _, k[s], d[s], _, _ = cv2.calibrateCamera(obj, pts[s], (640, 480), None, None)
    rms, *_, r, t, _, _ = cv2.stereoCalibrate(
        obj, pts["left"], pts["right"], k["left"], d["left"], k["right"], d["right"], (640, 480), flags=cv2.CALIB_USE_INTRINSIC_GUESS
    )
    right_viewmat = invert_rigid(rig.cameras["right"].c2w)  # rig frame = left camera
    assert geodesic_angle_deg(right_viewmat[:3, :3], r) < 0.1
    assert np.linalg.norm(right_viewmat[:3, 3] - t.ravel()) < 0.002  # metres, baseline ~ 0.083
    assert rms < 0.5
