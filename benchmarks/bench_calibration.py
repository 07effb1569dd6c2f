"""Calibration benchmark: time, RMS and cross-validation diff against the number of board views;
extrinsic error on a synthetic 4-camera rig; drift-check time per camera; OpenCV's real photographs.
Each time stands beside its ratio to the speed anchor's step read at the start of the run (`x anchor`;
`benchmarks._common.machine_reading`), which the header states with the CPU and the load.

    python -m benchmarks.bench_calibration [--out FILE.md]

Prints markdown tables and writes benchmarks/results/calibration.md (or --out) and a plot beside it.
"""

from __future__ import annotations

import argparse
import time
from pathlib import Path

import cv2
import numpy as np

from benchmarks._common import RESULTS, SHARED, MachineReading, machine_reading
from calibration.board import detect_board, parse_board
from calibration.calibfile import CalibrationDoc
from calibration.camera import invert_rigid
from calibration.drift import CHEAP, THOROUGH
from calibration.intrinsics import calibrate_intrinsics
from calibration.keeper import KeeperConfig, assess
from calibration.multiview import calibrate_rig
from calibration.simulated import render_planes, rig_board_views, rig_frame_scene, ring_rig, sensor
from calibration.so3 import axis_angle_to_matrix, geodesic_angle_deg

SPEC = parse_board("charuco:11x8:0.025:0.015:DICT_5X5_100")
CALIBRATION_DATA = SHARED / "calibration"


def table(head: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(head) + " |", "|" + "---|" * len(head)]
    lines += ["| " + " | ".join(f"{v:.3f}" if isinstance(v, float) else str(v) for v in r) + " |" for r in rows]
    return "\n".join(lines)


def views_sweep(machine: MachineReading) -> tuple[str, list]:
    rng = np.random.default_rng(0)
    cams = {f"cam{i}": c for i, c in enumerate(ring_rig(4, radius=0.5, arc_deg=90))}
    images, _ = rig_board_views(SPEC, cams, rng, shared=16, close_ups=12)
    dets = {n: {f: detect_board(SPEC, im) for f, im in v.items()} for n, v in images.items()}
    to_ref = invert_rigid(cams["cam0"].c2w)
    rows = []
    for shared, close in ((6, 4), (8, 6), (12, 8), (16, 12)):
        keep = {f"shared{j:02d}" for j in range(shared)} | {f"{n}_close{k:02d}" for n in cams for k in range(close)}
        sub = {n: {f: d for f, d in v.items() if f in keep} for n, v in dets.items()}
        t = time.perf_counter()
        rig = calibrate_rig(sub, {n: (640, 480) for n in sub})
        dt = time.perf_counter() - t
        rot = max(geodesic_angle_deg((to_ref @ cams[n].c2w)[:3, :3], rig.cameras[n].c2w[:3, :3]) for n in cams)
        trans = max(1000 * np.linalg.norm((to_ref @ cams[n].c2w)[:3, 3] - rig.cameras[n].c2w[:3, 3]) for n in cams)
        rms = float(np.mean(list(rig.rms_px.values())))
        cv = float(np.mean([v for v in rig.intrinsics_cv_px.values() if v is not None]))
        ex = max(v["rotation_deg"] for v in rig.extrinsics_cv.values()) if rig.extrinsics_cv else float("nan")
        rows.append([shared + close, dt, rms, cv, ex, rot, trans])
    head = [
        "views/camera",
        "calibrate s (4 cams, incl. cross-val)",
        "x anchor",
        "RMS px",
        "intrinsics cross-val px",
        "extrinsics cross-val deg",
        "max rot err deg",
        "max trans err mm",
    ]
    return table(head, [[r[0], r[1], machine.x_anchor(r[1]), *r[2:]] for r in rows]), rows


def drift_timing(machine: MachineReading) -> str:
    rng = np.random.default_rng(1)
    planes, fiducials = rig_frame_scene(rng)
    cams = {f"cam{i}": c for i, c in enumerate(ring_rig(4, radius=0.5, arc_deg=90))}
    clean = {n: render_planes(c, planes, supersample=2) for n, c in cams.items()}
    refs = {n: (sensor(im, rng), cams[n].c2w) for n, im in clean.items()}
    knocked = cams["cam2"].c2w.copy()
    knocked[:3, :3] = knocked[:3, :3] @ axis_angle_to_matrix(np.radians([0.06, 0.08, 0.0]))
    images = {n: sensor(im, rng, gain=1.2) for n, im in clean.items()}
    images["cam2"] = sensor(render_planes(cams["cam2"].with_c2w(knocked), planes, supersample=2), rng, gain=1.2)
    rows = []
    for label, fid in (("background", None), ("background + fiducials", fiducials)):
        calib = CalibrationDoc(dict(cams), fiducials=fid)
        for mode in (CHEAP, THOROUGH):
            t = time.perf_counter()
            reps = 5
            for _ in range(reps):
                res = assess(calib, images, refs, KeeperConfig(), mode=mode)
            per_cam = (time.perf_counter() - t) / reps / len(images) * 1000
            c = res.cameras["cam2"]
            err = geodesic_angle_deg(np.array(c.c2r)[:3, :3], knocked[:3, :3])
            others = max(res.cameras[n].effect_px for n in cams if n != "cam2")
            rows.append([label, mode, per_cam, machine.x_anchor(per_cam / 1000), c.status, c.rotation_deg, err, c.effect_px, others])
    return table(
        [
            "reference",
            "mode",
            "ms / camera",
            "x anchor",
            "knocked cam status",
            "measured deg (true 0.100)",
            "pose error deg",
            "effect px",
            "max effect px, others",
        ],
        rows,
    )


def real_images() -> str:
    rows = []
    if (CALIBRATION_DATA / "opencv_chessboard").exists():
        spec = parse_board("chessboard:9x6:0.025")
        for side, ref in (("left", 0.409), ("right", 0.459)):
            dets = {
                p.name: detect_board(spec, cv2.imread(str(p)))
                for p in sorted((CALIBRATION_DATA / "opencv_chessboard").glob(f"{side}*.jpg"))
            }
            r = calibrate_intrinsics(dets, (640, 480))
            rows.append([f"OpenCV chessboard {side} (13 views)", r.rms_px, ref, f"fx {r.camera.K[0, 0]:.1f} fy {r.camera.K[1, 1]:.1f}"])
    if (CALIBRATION_DATA / "charuco").exists():
        spec = parse_board("charuco:5x7:0.04:0.02:DICT_6X6_250")
        dets = {i: detect_board(spec, cv2.imread(str(CALIBRATION_DATA / "charuco" / f"img_0{i}.jpg"))) for i in range(4)}
        r = calibrate_intrinsics(dets, (640, 480))
        k = r.camera.K
        ref = (452.51, 456.77, 317.70 + 0.5, 277.75 + 0.5)
        dev = [100 * (a / b - 1) for a, b in zip((k[0, 0], k[1, 1], k[0, 2], k[1, 2]), ref)]
        rows.append(["ChArUco tutorial (4 views)", r.rms_px, 0.182, "fx/fy/cx/cy vs reference: " + ", ".join(f"{d:+.2f} %" for d in dev)])
    return table(["set", "our RMS px", "OpenCV RMS px", "intrinsics"], rows) if rows else "(shared data absent)"


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument("--out", type=Path, default=RESULTS / "calibration.md")
    args = ap.parse_args()
    machine = machine_reading()
    sweep_md, rows = views_sweep(machine)
    parts = [
        machine.header(),
        "## Real photographs",
        real_images(),
        "## Synthetic 4-camera rig: views sweep",
        sweep_md,
        "## Drift check (0.1 deg knock on cam2)",
        drift_timing(machine),
    ]
    text = "\n\n".join(parts) + "\n"
    print(text)
    args.out.parent.mkdir(parents=True, exist_ok=True)
    args.out.write_text(text)
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    r = np.array([row[:7] for row in rows], float)
    fig, axes = plt.subplots(1, 3, figsize=(12, 3.5))
    axes[0].plot(r[:, 0], r[:, 1], "o-")
    axes[0].set(xlabel="board views per camera", ylabel="calibration time (s)")
    axes[1].plot(r[:, 0], r[:, 2], "o-", label="RMS")
    axes[1].plot(r[:, 0], r[:, 3], "s-", label="intrinsics cross-val")
    axes[1].set(xlabel="board views per camera", ylabel="px")
    axes[1].legend()
    axes[2].plot(r[:, 0], r[:, 5], "o-", label="rotation error (deg)")
    axes[2].plot(r[:, 0], r[:, 6] / 10, "s-", label="translation error (cm)")
    axes[2].axhline(0.05, color="gray", ls="--", lw=1)
    axes[2].set(xlabel="board views per camera")
    axes[2].legend()
    fig.tight_layout()
    fig.savefig(args.out.with_suffix(".png"), dpi=100)


if __name__ == "__main__":
    main()
