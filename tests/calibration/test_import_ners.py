import cv2
import numpy as np
import pytest

from calibration.capture import read_capture
from calibration.import_ners import decode_coco_rle, import_ners_misc, import_ners_mvmc, pytorch3d_camera
from tests.conftest import require_shared


def visual_hull_iou(cameras, masks, n=80):
    """Carve a voxel grid with every mask, re-project the hull; per-view IoU with the masks."""
    d = np.median([np.linalg.norm(c.center) for c in cameras])
    g = np.linspace(-0.6 * d, 0.6 * d, n)
    pts = np.stack(np.meshgrid(g, g, g, indexing="ij"), -1).reshape(-1, 3)
    keep = np.ones(len(pts), bool)
    for c, m in zip(cameras, masks):
        uv, z = c.project(pts)
        ok = (z > 0) & np.all(uv >= 0, 1) & (uv[:, 0] < c.width) & (uv[:, 1] < c.height)
        inside = np.zeros(len(pts), bool)
        inside[ok] = m[uv[ok, 1].astype(int), uv[ok, 0].astype(int)]
        keep &= inside
    ious = []
    for c, m in zip(cameras, masks):
        uv, _ = c.project(pts[keep])
        img = np.zeros(m.shape, np.uint8)
        img[np.clip(uv[:, 1].astype(int), 0, c.height - 1), np.clip(uv[:, 0].astype(int), 0, c.width - 1)] = 1
        img = cv2.dilate(img, np.ones((5, 5), np.uint8)) > 0
        ious.append((img & m).sum() / max((img | m).sum(), 1))
    return np.array(ious)


def test_rle_decoding_is_column_major():
    # 2x3 image, column-major runs: 1 background, 2 foreground, 3 background.
    m = decode_coco_rle("1 2 3", (2, 3))
    np.testing.assert_array_equal(m, [[False, True, False], [True, False, False]])
    with pytest.raises(ValueError, match="covers 5 pixels"):
        decode_coco_rle("1 4", (2, 3))


def test_pytorch3d_camera_axes():
    # Identity R, camera 2 m in front of the origin: the origin projects to the image centre, and a
    # point at PyTorch3D +X (left) lands on the left half of the image.
    cam = pytorch3d_camera(np.eye(3), np.array([0.0, 0.0, 2.0]), 60.0, 600, 450)
    uv, z = cam.project(np.array([[0.0, 0, 0], [0.1, 0, 0], [0, 0.1, 0]]))
    np.testing.assert_allclose(uv[0], [300, 225])
    assert z[0] == pytest.approx(2.0)
    assert uv[1, 0] < 300 and uv[2, 1] < 225
    assert cam.K[0, 0] == pytest.approx(300 / np.tan(np.radians(30)))


def test_mvmc_car_poses_agree_with_masks(tmp_path):
    src = require_shared("real", "ners", "mvmc", "7246694387")
    cap = import_ners_mvmc(src, tmp_path / "car")
    assert len(cap) == 8 and cap.meta["pose_source"] == "rough"
    cap = read_capture(tmp_path / "car")
    cams = [cap.camera(i) for i in range(len(cap))]
    masks = [cap.mask(i) for i in range(len(cap))]
    ious = visual_hull_iou(cams, masks)
    # NeRS's optimised cameras are consistent with the masks: the visual hull reprojects onto them.
    assert ious.min() > 0.9
    # A wrong convention (R not transposed) carves the hull away: the test can tell.
    import json

    ann = json.loads((src / "annotations.json").read_text())["annotations"]
    wrong = [pytorch3d_camera(np.array(a["camera_optimized"]["R"]).T, np.array(a["camera_optimized"]["T"]), a["camera_optimized"]["fov"], 600, 450) for a in ann]
    assert visual_hull_iou(wrong, masks).mean() < ious.mean() - 0.2


def test_espresso_rough_poses(tmp_path):
    src = require_shared("real", "ners", "espresso")
    cap = import_ners_misc(src, tmp_path / "espresso")
    assert len(cap) == 7 and cap.meta["pose_source"] == "rough"
    ious = visual_hull_iou([cap.camera(i) for i in range(7)], [cap.mask(i) for i in range(7)])
    # Azimuth/elevation alone are rough, yet the hull still explains most of every mask.
    assert np.median(ious) > 0.8
