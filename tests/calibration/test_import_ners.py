import json
from dataclasses import replace

import numpy as np
import pytest

from calibration.capture import read_capture
from calibration.import_ners import decode_coco_rle, import_ners_misc, import_ners_mvmc, mask_from_png, pytorch3d_camera
from tests.conftest import require_shared


def visual_hull_iou(cameras, masks, samples=40, num_depths=100):
    """Per view, the share of its mask that the other views' visual hull explains (its IoU with the
    hull's projection, which lies inside the mask): a mask pixel is covered when some point on its ray
    projects into every other mask. Exact up to the pixel stride (`samples` across the longer image side)
    and `num_depths` samples along each ray."""
    dist = np.median([np.linalg.norm(c.center) for c in cameras])
    depths = np.linspace(0.4 * dist, 1.6 * dist, num_depths)
    ious = []
    for i, (cam, mask) in enumerate(zip(cameras, masks)):
        step = max(1, max(mask.shape) // samples)
        v, u = np.nonzero(mask[::step, ::step])
        uv = np.stack([u, v], 1) * step + 0.5
        rays = cam.pixel_rays_camera(uv) @ cam.c2w[:3, :3].T
        pts = (cam.center + rays[:, None, :] * depths[None, :, None]).reshape(-1, 3)
        inside = np.ones(len(pts), bool)
        for j, (other, m) in enumerate(zip(cameras, masks)):
            if j == i:
                continue
            q, z = other.project(pts)
            q = np.floor(np.nan_to_num(q, nan=-1.0)).astype(int)
            seen = (z > 0) & (q[:, 0] >= 0) & (q[:, 1] >= 0) & (q[:, 0] < other.width) & (q[:, 1] < other.height)
            hit = np.zeros(len(pts), bool)
            hit[seen] = m[q[seen, 1], q[seen, 0]]
            inside &= hit
        ious.append(inside.reshape(len(uv), num_depths).any(1).mean())
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
    # NeRS's fitted cameras agree with the masks, so the engine gets one global correction, not one per camera.
    assert len(cap) == 8 and cap.meta["pose_source"] == "optimized"
    cap = read_capture(tmp_path / "car")
    cams = [cap.camera(i) for i in range(len(cap))]
    masks = [cap.mask(i) for i in range(len(cap))]
    # The other seven masks' visual hull re-projects onto every mask (measured 0.987-1.0).
    assert visual_hull_iou(cams, masks).min() > 0.98

    # The check can tell the conventions apart: R not transposed, or the principal point where NeRS's
    # own crop code puts it for these photos (PIL's (W, H) read as (H, W): pixel (225, 300)), carve
    # the hull away (measured mean IoU 0.69 and 0.46).
    ann = json.loads((src / "annotations.json").read_text())["annotations"]
    opt = [a["camera_optimized"] for a in ann]
    transposed = [pytorch3d_camera(np.array(c["R"]).T, np.array(c["T"]), c["fov"], 600, 450) for c in opt]
    assert visual_hull_iou(transposed, masks).mean() < 0.8
    swapped = [replace(cam, K=np.array([[1, 0, -75.0], [0, 1, 75.0], [0, 0, 1]]) @ cam.K) for cam in cams]
    assert visual_hull_iou(swapped, masks).mean() < 0.7


def test_mvmc_initial_cameras_are_rough(tmp_path):
    src = require_shared("real", "ners", "mvmc", "7246694387")
    cap = import_ners_mvmc(src, tmp_path / "car", cameras="camera_initial")
    assert cap.meta["pose_source"] == "rough" and cap.meta["calibration_id"] == "ners:camera_initial"


def test_espresso_rough_poses(tmp_path):
    src = require_shared("real", "ners", "espresso")
    cap = import_ners_misc(src, tmp_path / "espresso")
    assert len(cap) == 7 and cap.meta["pose_source"] == "rough"
    # The mask PNGs are white-on-black RGB with an opaque alpha: each is a silhouette, not the whole photo.
    covers = [cap.mask(i).mean() for i in range(7)]
    assert 0.05 < min(covers) and max(covers) < 0.6
    ious = visual_hull_iou([cap.camera(i) for i in range(7)], [cap.mask(i) for i in range(7)])
    # Azimuth/elevation alone are rough, yet the hull still explains most of every mask.
    assert np.median(ious) > 0.8


def test_mask_png_channels():
    """Alpha is the mask where it varies; an opaque alpha leaves the colour to say it; gray is itself."""
    silhouette = np.zeros((4, 5), bool)
    silhouette[1:3, 2:4] = True
    white_on_black = np.repeat(silhouette[..., None].astype(np.float32), 3, axis=2)
    opaque = np.concatenate([white_on_black, np.ones((4, 5, 1), np.float32)], axis=2)
    cut_out = np.concatenate([np.full((4, 5, 3), 0.3, np.float32), silhouette[..., None].astype(np.float32)], axis=2)
    for m in (silhouette.astype(np.float32), white_on_black, opaque, cut_out):
        np.testing.assert_array_equal(mask_from_png(m), silhouette)
