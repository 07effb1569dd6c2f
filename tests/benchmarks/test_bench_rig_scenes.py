"""The rig-scenes benchmark's oracle capture: the training views on their true poses."""

from __future__ import annotations

import json

import numpy as np

from benchmarks.bench_rig_scenes import exact_camera_capture
from calibration.camera import look_at_c2w
from calibration.capture import read_capture
from calibration.sim3 import Sim3
from calibration.so3 import axis_angle_to_matrix


def test_exact_camera_capture_records_the_true_poses_in_the_rig_frame(tmp_path):
    scene = tmp_path / "scene"
    (scene / "train" / "images").mkdir(parents=True)
    sim3 = Sim3(1.02, axis_angle_to_matrix(np.array([0.1, -0.2, 0.3])), np.array([0.05, -0.1, 0.2]))
    true_obj = np.stack([look_at_c2w(np.array([np.cos(a), np.sin(a), 0.4]), np.zeros(3)) for a in (0.0, 2.0, 4.0)])
    noisy_rig = sim3.inverse().apply_to_c2w(true_obj)
    noisy_rig[:, :3, 3] += 0.001
    opengl = np.diag([1.0, -1.0, -1.0, 1.0])
    frames = []
    for i, c2w in enumerate(noisy_rig):
        (scene / "train" / "images" / f"{i}.png").write_bytes(b"")
        frames.append({"file_path": f"images/{i}.png", "transform_matrix": (c2w @ opengl).tolist()})
    intrinsics = {"fl_x": 300.0, "fl_y": 300.0, "cx": 160.0, "cy": 120.0, "w": 320, "h": 240}
    (scene / "train" / "transforms.json").write_text(json.dumps({**intrinsics, "frames": frames}))
    (scene / "gt.json").write_text(json.dumps({"sim3_rig_to_object": sim3.to_dict(),
                                               "train": {"c2w_opencv_object": true_obj.tolist()}}))
    out = exact_camera_capture(scene, tmp_path / "exact")
    got = np.stack([f.camera.c2w for f in read_capture(out).frames])
    np.testing.assert_allclose(sim3.apply_to_c2w(got), true_obj, atol=1e-9)
    # The recorded capture is left as it was, and the images are the same files.
    np.testing.assert_allclose(np.stack([f.camera.c2w for f in read_capture(scene / "train").frames]), noisy_rig, atol=1e-12)
    assert (out / "images").resolve() == (scene / "train" / "images").resolve()
