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
    (scene / "gt.json").write_text(json.dumps({"sim3_rig_to_object": sim3.to_dict(), "train": {"c2w_opencv_object": true_obj.tolist()}}))
    out = exact_camera_capture(scene, tmp_path / "exact")
    got = np.stack([f.camera.c2w for f in read_capture(out).frames])
    np.testing.assert_allclose(sim3.apply_to_c2w(got), true_obj, atol=1e-9)
    # The recorded capture is left as it was, and the images are the same.
    np.testing.assert_allclose(np.stack([f.camera.c2w for f in read_capture(scene / "train").frames]), noisy_rig, atol=1e-12)
    assert sorted(p.name for p in (out / "images").iterdir()) == sorted(p.name for p in (scene / "train" / "images").iterdir())


def test_the_report_reads_the_machine_beside_each_variant_and_leaves_what_a_run_lacks_empty(tmp_path, monkeypatch):
    import benchmarks.bench_rig_scenes as bench

    monkeypatch.setattr(bench, "RESULTS", tmp_path / "results")
    mean = {"fgpsnr": 27.0, "iou": 0.97, "psnr": 28.0, "ssim": 0.9, "lpips": 0.1}
    # A reused twin records None: its time was taken on another day's machine.
    for variant, walls, machine in (
        ("new-cpu-vall", (60.0, 64.0, 70.0, 75.0), (1600.0, 1700.0, 2000.0, None)),
        ("old-cpu-vall", (25.0, 27.0, 30.0), None),
    ):
        for i, wall in enumerate(walls):
            doc = {
                "scene": bench.SCENES[i],
                "variant": variant,
                "train_wall_s": wall,
                "load": 1.0,
                "mean": mean,
                "mean_refined": mean if machine else None,
            }
            if machine:
                doc["machine_ref_ms"] = machine[i]
                doc["cpu"] = None if machine[i] is None else "AMD EPYC, 2 cores, AVX2 (no AVX-512), no native bfloat16"
            run = tmp_path / "runs" / variant / f"{bench.SCENES[i]}-r0.json"
            run.parent.mkdir(parents=True, exist_ok=True)
            run.write_text(json.dumps(doc))
    text = bench.write_report(tmp_path, 0)
    rows = {
        line.split(" | ")[0][2:]: line.split(" | ") for line in text.splitlines() if line.startswith("| new-") or line.startswith("| old-")
    }
    header = next(line for line in text.splitlines() if line.startswith("| variant")).split(" | ")
    median, machine = header.index("median s"), header.index("anchor ms")
    assert rows["new-cpu-vall"][median] == "67.0" and rows["new-cpu-vall"][machine] == "1700"
    assert rows["old-cpu-vall"][median] == "27.0" and rows["old-cpu-vall"][machine] == "-"
    # Runs without test-time refinement leave its columns empty rather than nan.
    refined = header.index("fgPSNR ref.")
    assert rows["new-cpu-vall"][refined] == "27.000" and rows["old-cpu-vall"][refined] == "-"
    # The CPU a variant trained on is named once; a variant with no record of it is left out.
    cpus = next(line for line in text.splitlines() if line.startswith("CPUs the timed runs trained on"))
    assert "`new-cpu-vall` AMD EPYC, 2 cores, AVX2 (no AVX-512), no native bfloat16" in cpus and "old-cpu-vall" not in cpus
    assert (tmp_path / "results" / "rig_scenes.md").read_text() == text


def test_a_new_report_replaces_only_its_tables_and_keeps_the_sections_written_below_them(tmp_path):
    import benchmarks.bench_rig_scenes as bench

    mean = {"fgpsnr": 27.0, "iou": 0.97, "psnr": 28.0, "ssim": 0.9, "lpips": 0.1}
    doc = {"scene": bench.SCENES[0], "variant": "a-cpu-vall", "train_wall_s": 50.0, "load": 1.0, "mean": mean}
    run = tmp_path / "runs" / "a-cpu-vall" / f"{bench.SCENES[0]}-r0.json"
    run.parent.mkdir(parents=True)
    run.write_text(json.dumps(doc))
    out = tmp_path / "report.md"
    hand = "## Issue 1: what a person measured\n\nA reading that no run regenerates.\n"
    out.write_text("# old tables\n\n| a-cpu-vall | stale |\n\n" + hand)
    text = bench.write_report(tmp_path, 0, out=out)
    assert out.read_text() == text and text.endswith(hand)
    assert "stale" not in text and text.startswith("# Reference benchmark") and text.count("## Issue 1") == 1
    # Written again, the same: the kept sections are not stacked up.
    assert bench.write_report(tmp_path, 0, out=out) == text
