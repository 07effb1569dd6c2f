"""How well can any twin fit the rig scenes' held-out silhouettes, given the calibration noise the captures do not state?

    python -m benchmarks.bench_noise_ceiling [--scenes A,B] [--views 3 5 all] [--runs DIR --variant NAME] [--out FILE]

Each rig scene's training cameras carry 0.1 deg / 1 mm of noise per camera; its held-out cameras are
exact in the rig frame and inherit the twin's rig-to-object Sim(3), which the twin can only estimate
from the noisy training views. This benchmark places the *true* mesh (`gt_mesh.ply`) with:

- the true Sim(3) (`gt.json`): the silhouettes' agreement with the held-out masks when nothing is wrong
  (what the z-buffer rasterization and the masks' anti-aliasing leave);
- the best Sim(3) the noisy training cameras allow: the one that brings the true surface's projections
  through the recorded (noisy) cameras closest, in pixels, to its projections through the true cameras,
  over the training views used. A method that holds one rig Sim(3) sees the object only through those
  cameras, so it cannot be expected to place even a perfect shape better; it can land above this
  ceiling by chance, when its errors happen to cancel the noise.

and scores the held-out silhouette IoU, as the protocol does (mask against rendered coverage). With
`--runs DIR --variant NAME` (a `bench_rig_scenes` work directory) the twins' own held-out IoU is listed
beside it. Writes benchmarks/results/noise_ceiling.md.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import numpy as np

from benchmarks._common import RESULTS, load_line
from benchmarks.bench_rig_scenes import RIG_SCENES, SCENES, surface_points, views_for

FIT_POINTS = 2_000
METHOD = """The true mesh placed by the true Sim(3) and by the best Sim(3) the noisy training cameras allow (the one
whose recorded cameras, mapped to the object frame, project 2,000 true-surface points closest to where the true
cameras project them), scored on the 12 exact held-out views as the protocol scores a twin (silhouette IoU,
mask against rendered coverage). *Noise*: that reprojection error (RMS px) at each Sim(3). *Twin*: the twin's
own held-out IoU at its nominal poses (`bench_rig_scenes` runs). Held-out cameras inherit the Sim(3) only, so a
twin cannot be expected to beat the ceiling, though its errors may by chance cancel some of the noise."""


def project(points: np.ndarray, c2w: np.ndarray, K: np.ndarray) -> np.ndarray:
    """Pixel coordinates [P, 2] of object points [P, 3] through an OpenCV camera (c2w [4, 4], K [3, 3])."""
    w2c = np.linalg.inv(c2w)
    cam = points @ w2c[:3, :3].T + w2c[:3, 3]
    return cam[:, :2] / cam[:, 2:3] * [K[0, 0], K[1, 1]] + [K[0, 2], K[1, 2]]


def best_sim3(rig_c2w: np.ndarray, true_c2w: np.ndarray, Ks: np.ndarray, points: np.ndarray, start):
    """The rig-to-object Sim(3) (near `start`) minimising the reprojection of `points` [P, 3] through the rig
    cameras rig_c2w [C, 4, 4] mapped to the object frame, against their projection through true_c2w [C, 4, 4];
    returns (Sim3, RMS pixels at the optimum, RMS pixels at `start`)."""
    from scipy.optimize import least_squares
    from scipy.spatial.transform import Rotation

    from calibration.sim3 import Sim3

    targets = [project(points, t, k) for t, k in zip(true_c2w, Ks)]

    def sim3(x: np.ndarray) -> Sim3:
        return Sim3(start.scale * np.exp(x[6]), Rotation.from_rotvec(x[:3]).as_matrix() @ start.rotation, start.translation + x[3:6])

    def residuals(x: np.ndarray) -> np.ndarray:
        c2w = sim3(x).apply_to_c2w(rig_c2w)
        return np.concatenate([(project(points, c, k) - t).ravel() for c, k, t in zip(c2w, Ks, targets)])

    fit = least_squares(residuals, np.zeros(7))
    rms = lambda r: float(np.sqrt(np.mean(r**2)))  # noqa: E731
    return sim3(fit.x), rms(fit.fun), rms(residuals(np.zeros(7)))


def heldout_iou(vertices: np.ndarray, faces: np.ndarray, cameras, masks: np.ndarray, sim3) -> float:
    """Mean held-out silhouette IoU of the mesh (object frame) seen by rig-frame `cameras` placed by `sim3`."""
    from reconstruction.inspect import rasterize_mesh

    out = []
    for cam, mask in zip(cameras, masks):
        placed = cam.with_c2w(sim3.apply_to_c2w(cam.c2w[None])[0])
        mask = placed.crop(mask)
        depth, _, _ = rasterize_mesh(vertices, faces, placed)
        covered = np.isfinite(depth)
        out.append((covered & mask).sum() / max((covered | mask).sum(), 1))
    return float(np.mean(out))


def scene_row(scene: Path, views: str, runs: Path | None, variant: str | None) -> dict:
    import trimesh

    from calibration.capture import load_views, read_capture
    from calibration.sim3 import Sim3

    gt = json.loads((scene / "gt.json").read_text())
    mesh = trimesh.load(scene / "gt_mesh.ply", process=False)
    vertices, faces = np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces)
    train = read_capture(scene / "train")
    idx = views_for(gt, len(train), views)
    rig_c2w = np.stack([train.frames[i].camera.c2w for i in idx])
    Ks = np.stack([train.frames[i].camera.K for i in idx])
    true_c2w = np.asarray(gt["train"]["c2w_opencv_object"], np.float64)[idx]
    true_sim3 = Sim3.from_dict(gt["sim3_rig_to_object"])
    fitted, rms, rms_true = best_sim3(rig_c2w, true_c2w, Ks, surface_points(vertices, faces, FIT_POINTS), true_sim3)
    held = read_capture(scene / "heldout")
    _, masks, cams = load_views(held, list(range(len(held))))
    row = {
        "scene": scene.name,
        "views": len(idx),
        "rms_px_true": rms_true,
        "rms_px_best": rms,
        "iou_true": heldout_iou(vertices, faces, cams, masks, true_sim3),
        "iou_best": heldout_iou(vertices, faces, cams, masks, fitted),
    }
    run = None if runs is None else runs / "runs" / f"{variant}-v{views}" / f"{scene.name}-r0.json"
    row["iou_twin"] = json.loads(run.read_text())["mean"]["iou"] if run is not None and run.exists() else None
    return row


def table(rows: list[dict]) -> list[str]:
    out = [
        "| scene | views | noise, RMS px at the true Sim(3) | at the best Sim(3) | held-out IoU, true mesh at the true Sim(3) "
        "| at the best Sim(3) (ceiling) | twin | twin / ceiling gap |",
        "|---|---:|---:|---:|---:|---:|---:|---:|",
    ]
    for r in rows:
        twin = "-" if r["iou_twin"] is None else f"{r['iou_twin']:.3f}"
        gap = "-" if r["iou_twin"] is None else f"{r['iou_twin'] - r['iou_best']:+.3f}"
        out.append(
            f"| {r['scene']} | {r['views']} | {r['rms_px_true']:.2f} | {r['rms_px_best']:.2f} | {r['iou_true']:.3f} "
            f"| {r['iou_best']:.3f} | {twin} | {gap} |"
        )
    mean = lambda k: np.mean([r[k] for r in rows])  # noqa: E731
    twins = [r["iou_twin"] for r in rows if r["iou_twin"] is not None]
    twin_mean = f"{np.mean(twins):.3f}" if len(twins) == len(rows) else "-"
    gap = f"{np.mean(twins) - mean('iou_best'):+.3f}" if len(twins) == len(rows) else "-"
    out.append(
        f"| **mean** | | {mean('rms_px_true'):.2f} | {mean('rms_px_best'):.2f} | {mean('iou_true'):.3f} "
        f"| **{mean('iou_best'):.3f}** | {twin_mean} | {gap} |"
    )
    return out


def main() -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--views", nargs="+", default=["3", "5", "all"], choices=["3", "5", "all"])
    ap.add_argument("--runs", type=Path, default=None, help="a bench_rig_scenes work directory, for the twins' own IoU")
    ap.add_argument("--variant", default=None, help="its variant and preset, e.g. op2-cpu")
    ap.add_argument("--out", type=Path, default=RESULTS / "noise_ceiling.md")
    args = ap.parse_args()
    if not (RIG_SCENES / "scenes").is_dir():
        print(f"cannot run: the rig scenes are not at {RIG_SCENES} (set CADSPLAT_SHARED_DATA)")
        return 2
    lines = [
        "# Held-out silhouette ceiling under the rig scenes' calibration noise (`python -m benchmarks.bench_noise_ceiling`)",
        "",
        METHOD,
        "",
    ]
    for views in args.views:
        rows = [scene_row(RIG_SCENES / "scenes" / s, views, args.runs, args.variant) for s in args.scenes.split(",")]
        lines += [f"## {views} training views" + (f" (twins: `{args.variant}`)" if args.variant else ""), "", *table(rows), ""]
        print("\n".join(lines[-len(rows) - 4 :]))
    lines.append(f"Written by `python -m benchmarks.bench_noise_ceiling`; {load_line()}.")
    args.out.write_text("\n".join(lines) + "\n")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
