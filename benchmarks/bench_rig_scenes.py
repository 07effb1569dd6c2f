"""The reference benchmark: the engine on the path-traced rig captures of `shared/data/rig_scenes`.

    python -m benchmarks.bench_rig_scenes [--scenes A,B] [--variant NAME] [--preset cpu]
        [--views all|5|3] [--pose-mode global|per_camera] [--override KEY=JSON ...] [--vanilla ITERS ...]
        [--vanilla-eps2d PX2] [--refine-steps N] [--work DIR] [--report-only] [--plot VARIANT] [--out FILE] [--rescore] [--exact-cameras]

Each scene (8 YCB objects, 9-13 training views at 320x240, a metric rig frame, 0.1 deg / 1 mm
calibration noise the capture does not state, a deformed and decimated CAD variant among 110
distractors) goes through the engine as a user runs it (`reconstruct` against the scenes' library)
and is scored against the scene's ground truth:

- held-out views (12 per scene, exact poses) at the twin's nominal poses and after test-time
  refinement, with the paper's metric set (`reconstruction.evaluation`);
- training-camera poses, registration -> twin: ADD-S (the true mesh placed by the estimated and by
  the true camera, symmetric mean closest-point distance, % of the bounding-sphere diameter; near-
  symmetric turns cost nothing by construction), rotation and centre error;
- geometry: the twin's deformed mesh and the CAD model against the true surface (symmetric mean
  closest-point distance, exact point-to-triangle from 20k samples of each surface, and its p95, % of
  the diameter).

`--exact-cameras` trains on the true training poses instead of the recorded ones: an oracle that says what
the calibration noise costs (name the variant apart). `--vanilla ITERS` also trains masked vanilla 3DGS (`baselines.train_vanilla_3dgs`) on the same
views for each iteration count given (`--vanilla-eps2d` draws it with another screen-space dilation than 3DGS's
0.3 px^2, in training and in evaluation; its runs are named apart). Every run is cached as JSON under the work directory, keyed
by variant, so interrupted sweeps resume and variants are compared paired, per scene.
Writes benchmarks/results/rig_scenes.md (`--out`: another file) and rig_scenes.png beside it (the engine variant against
vanilla 3DGS per scene and view count, and each variant's quality against its training time). The report's tables are
regenerated from every run under the work directory; the sections written by hand below them are kept.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks._common import RESULTS, SHARED, cpu_line, symmetric_surface_distance, write_results
from reconstruction.render.anchor import anchor_ms

RIG_SCENES = SHARED / "rig_scenes"
SCENES = (
    "050_medium_clamp",
    "037_scissors",
    "043_phillips_screwdriver",
    "011_banana",
    "072-c_toy_airplane",
    "033_spatula",
    "077_rubiks_cube",
    "061_foam_brick",
)
SURFACE_SAMPLES = 20_000
POSE_SAMPLES = 3_000


def surface_points(vertices: np.ndarray, faces: np.ndarray, n: int, seed: int = 0) -> np.ndarray:
    """n points [n, 3] drawn uniformly (by area) on a triangle mesh."""
    import trimesh

    pts, _ = trimesh.sample.sample_surface(trimesh.Trimesh(vertices, faces, process=False), n, seed=seed)
    return np.asarray(pts, np.float64)


def add_s_pct(c2w_est: np.ndarray, c2w_true: np.ndarray, points: np.ndarray, diameter: float) -> np.ndarray:
    """ADD-S per camera [C]: the object points [P, 3] placed by the estimated and by the true camera
    (object-frame c2w [C, 4, 4]), symmetric mean closest-point distance, % of `diameter`."""
    from scipy.spatial import cKDTree

    tree = cKDTree(points)
    out = []
    for est, true in zip(c2w_est, c2w_true):
        # The same camera frame seen from both poses: the object moves by true @ est^-1 in its own frame.
        m = true @ np.linalg.inv(est)
        moved = points @ m[:3, :3].T + m[:3, 3]
        d = 0.5 * (tree.query(moved)[0].mean() + cKDTree(moved).query(points)[0].mean())
        out.append(100.0 * d / diameter)
    return np.asarray(out)


def sim3_add_s_pct(sim3_est, sim3_true, points: np.ndarray, diameter: float) -> float:
    """ADD-S of a rig-to-object Sim(3): the object points [P, 3] carried by est ∘ true^-1 against
    themselves, % of `diameter` (what every new camera of the rig inherits)."""
    from scipy.spatial import cKDTree

    moved = (sim3_est @ sim3_true.inverse()).apply(points)
    return float(100.0 * 0.5 * (cKDTree(points).query(moved)[0].mean() + cKDTree(moved).query(points)[0].mean()) / diameter)


def pose_scores(c2w_est: np.ndarray, c2w_true: np.ndarray, points: np.ndarray, diameter: float) -> dict:
    from calibration.so3 import geodesic_angle_deg

    adds = add_s_pct(c2w_est, c2w_true, points, diameter)
    rot = geodesic_angle_deg(c2w_true[:, :3, :3], c2w_est[:, :3, :3])
    ctr = 100.0 * np.linalg.norm(c2w_est[:, :3, 3] - c2w_true[:, :3, 3], axis=1) / diameter
    return {
        "adds_pct_median": float(np.median(adds)),
        "rotation_deg_median": float(np.median(rot)),
        "center_pct_diameter_median": float(np.median(ctr)),
        "adds_pct": adds.tolist(),
    }


def views_for(gt: dict, n: int, views: str) -> list[int]:
    return list(range(n)) if views == "all" else [int(i) for i in gt["subsets"][views]]


def exact_camera_capture(scene: Path, out: Path) -> Path:
    """A copy of the scene's training capture at `out` whose recorded cameras are the true ones (the oracle
    without calibration noise): the images, masks and backgrounds copied (a capture reads only inside its own
    folder, so links out are refused), transforms.json rewritten from
    gt.json's true object-frame cameras through the inverse of the true rig-to-object Sim(3)."""
    from calibration.sim3 import Sim3

    gt = json.loads((scene / "gt.json").read_text())
    doc = json.loads((scene / "train" / "transforms.json").read_text())
    rig_c2w = Sim3.from_dict(gt["sim3_rig_to_object"]).inverse().apply_to_c2w(np.asarray(gt["train"]["c2w_opencv_object"], np.float64))
    out.mkdir(parents=True, exist_ok=True)
    for entry in (scene / "train").iterdir():
        if entry.is_dir() and not (out / entry.name).exists():
            shutil.copytree(entry, out / entry.name)
    opengl = np.diag([1.0, -1.0, -1.0, 1.0])  # transforms.json holds OpenGL-axis c2w
    for frame, c2w in zip(doc["frames"], rig_c2w):
        frame["transform_matrix"] = (c2w @ opengl).tolist()
    (out / "transforms.json").write_text(json.dumps(doc, indent=1))
    return out


def train_dir(scene: Path, variant_dir: Path, args) -> Path:
    """The training capture a run uses: the scene's, or with --exact-cameras its copy on the true poses."""
    if getattr(args, "exact_cameras", False):
        return exact_camera_capture(scene, variant_dir / f"{scene.name}-exact-train")
    return scene / "train"


def score_heldout(scene: Path, twin_dir: Path, args, library: Path | None = None, **engine) -> tuple:
    """The protocol on the scene's held-out views (nominal and refined); trains the twin first (against
    `library`, with the engine's arguments) unless `twin_dir` holds one.
    Returns (twin, {mean, mean_refined, num_splats})."""
    from reconstruction.evaluation import run_protocol

    run = run_protocol(
        train_dir(scene, twin_dir.parent, args),
        scene / "heldout",
        library,
        twin_dir,
        refine_steps=args.refine_steps,
        seed=args.seed,
        reuse=True,
        overwrite=True,
        **engine,
    )
    return run.twin, {"mean": run.mean, "mean_refined": run.mean_refined, "num_splats": int(run.twin.num_splats)}


def pose_and_geometry_scores(twin, scene: Path, gt: dict, idx: list[int], train_dir: Path | None = None) -> dict:
    """Training-pose (registration and trained), Sim(3) and geometry scores of a CAD-frame twin."""
    import trimesh

    from calibration.capture import read_capture
    from calibration.sim3 import Sim3
    from reconstruction.surface import self_intersecting_faces

    doc = {}
    true_mesh = trimesh.load(scene / "gt_mesh.ply", process=False)
    diameter = 2.0 * float(gt["object"]["bounding_sphere_radius_m"])
    pts = surface_points(np.asarray(true_mesh.vertices), np.asarray(true_mesh.faces), POSE_SAMPLES)
    train = read_capture(train_dir or scene / "train")
    truth = np.asarray(gt["train"]["c2w_opencv_object"], np.float64)[idx]
    rig_c2w = np.stack([train.frames[i].camera.c2w for i in idx])
    registered = twin.sim3_rig_to_object_init.apply_to_c2w(rig_c2w)
    trained = np.stack([c.c2w_object_opencv for c in twin.cameras])
    doc["pose_registration"] = pose_scores(registered, truth, pts, diameter)
    doc["pose_trained"] = pose_scores(trained, truth, pts, diameter)
    doc["sim3_scale"] = float(twin.sim3_rig_to_object.scale)
    true_sim3 = Sim3.from_dict(gt["sim3_rig_to_object"])
    doc["sim3_adds_pct"] = {
        "registration": sim3_add_s_pct(twin.sim3_rig_to_object_init, true_sim3, pts, diameter),
        "twin": sim3_add_s_pct(twin.sim3_rig_to_object, true_sim3, pts, diameter),
    }
    for name, mesh in (("cad", twin.load_mesh_cad()), ("deformed", twin.load_mesh_deformed())):
        mean, p95 = symmetric_surface_distance(
            mesh.vertices, mesh.faces, np.asarray(true_mesh.vertices), np.asarray(true_mesh.faces), SURFACE_SAMPLES
        )
        welded = trimesh.Trimesh(mesh.vertices, mesh.faces, process=True)
        doc[f"geometry_{name}"] = {
            "mean_pct": 100 * mean / diameter,
            "p95_pct": 100 * p95 / diameter,
            "watertight": bool(welded.is_watertight),
            "crossing_faces": int(self_intersecting_faces(mesh.vertices, mesh.faces).sum()),
        }
    return doc


def machine_reading(twin_dir: Path) -> dict:
    """The speed anchor's step now (`reconstruction.render.anchor.anchor_ms`) and the CPU (`cpu_line`) when the twin in
    `twin_dir` is about to be trained; None for both when one is there to reuse, since its time was taken on the
    machine of its own day."""
    if (twin_dir / "twin.json").exists():
        return {"machine_ref_ms": None, "cpu": None}
    return {"machine_ref_ms": anchor_ms(), "cpu": cpu_line()}


def run_engine(scene: Path, lib: Path, work: Path, args) -> dict:
    key = f"{args.variant}-{args.preset}-v{args.views}"
    cache = work / "runs" / key / f"{scene.name}-r{args.refine_steps}.json"
    gt = json.loads((scene / "gt.json").read_text())
    if cache.exists():
        doc = json.loads(cache.read_text())
        if args.rescore:
            from reconstruction.twin import load_twin

            doc.update(
                pose_and_geometry_scores(
                    load_twin(work / "twins" / key / scene.name),
                    scene,
                    gt,
                    doc["train_views"],
                    train_dir(scene, work / "twins" / key, args),
                )
            )
            cache.write_text(json.dumps(doc, indent=1))
        return doc
    n = len(gt["train"]["c2w_opencv_object"])
    idx = views_for(gt, n, args.views)
    overrides = {k: json.loads(v) for k, v in (o.split("=", 1) for o in args.override)}
    machine = machine_reading(work / "twins" / key / scene.name)
    twin, scores = score_heldout(
        scene,
        work / "twins" / key / scene.name,
        args,
        library=lib,
        preset=args.preset,
        views=idx,
        pose_mode=args.pose_mode,
        overrides=overrides or None,
    )
    doc = {
        "scene": scene.name,
        "variant": key,
        "train_views": idx,
        "train_wall_s": float(twin.timings_s["total"]),
        "timings_s": twin.timings_s,
        "pose_mode": twin.pose_mode,
        "model_id": twin.model_id,
        "right_model": twin.model_id == gt["model_id"],
        "load": os.getloadavg()[0],
        **machine,
        **scores,
        **pose_and_geometry_scores(twin, scene, gt, idx, train_dir(scene, work / "twins" / key, args)),
    }
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text(json.dumps(doc, indent=1))
    return doc


def run_vanilla(scene: Path, iterations: int, work: Path, args) -> dict:
    from calibration.capture import load_views, read_capture
    from reconstruction.baselines import VanillaConfig, train_vanilla_3dgs, vanilla_twin
    from reconstruction.gaussians import EPS2D_3DGS
    from reconstruction.twin import save_twin

    eps = "" if args.vanilla_eps2d == EPS2D_3DGS else f"-e{args.vanilla_eps2d:g}"
    key = f"vanilla-i{iterations}{eps}-v{args.views}"
    cache = work / "runs" / key / f"{scene.name}-r{args.refine_steps}.json"
    if cache.exists():
        return json.loads(cache.read_text())
    gt = json.loads((scene / "gt.json").read_text())
    train = read_capture(scene / "train")
    idx = views_for(gt, len(train), args.views)
    twin_dir = work / "twins" / key / scene.name
    machine = machine_reading(twin_dir)
    if not (twin_dir / "twin.json").exists():
        images, masks, cams = load_views(train, idx)
        cfg = replace(VanillaConfig().scaled(iterations), eps2d=args.vanilla_eps2d)
        result = train_vanilla_3dgs(images, masks, cams, cfg, seed=args.seed)
        save_twin(vanilla_twin(result, cams, [str(train.frames[i].camera_id) for i in idx]), twin_dir, overwrite=True)
    twin, scores = score_heldout(scene, twin_dir, args)
    doc = {
        "scene": scene.name,
        "variant": key,
        "train_views": idx,
        "train_wall_s": float(twin.timings_s["total"]),
        "load": os.getloadavg()[0],
        **machine,
        **scores,
    }
    cache.parent.mkdir(parents=True, exist_ok=True)
    cache.write_text(json.dumps(doc, indent=1))
    return doc


# ------------------------------------------------------------------------------------ report


def _m(doc: dict, key: str, refined: bool = False) -> float:
    m = doc.get("mean_refined") if refined else doc.get("mean")
    return float("nan") if not m or m.get(key) is None else float(m[key])


def plot_against_vanilla(runs: dict[str, dict[str, dict]], engine: str, out: Path) -> bool:
    """Per view count, each scene's held-out fgPSNR of the engine variant `engine` and of every vanilla 3DGS run on
    the same views; last panel, each variant's mean fgPSNR against its mean training time. False: nothing to plot."""
    views = [v for v in ("all", "5", "3") if any(k.startswith(f"{engine}-") and k.endswith(f"-v{v}") for k in runs)]
    if not views:
        return False
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, axes = plt.subplots(1, len(views) + 1, figsize=(4.2 * (len(views) + 1), 3.8))
    x = np.arange(len(SCENES))
    colours = {"all": "C0", "5": "C1", "3": "C2"}
    for ax, v in zip(axes, views):
        for variant, by in runs.items():
            if not variant.endswith(f"-v{v}") or not (variant.startswith(f"{engine}-") or variant.startswith("vanilla-")):
                continue
            y = [_m(by[s], "fgpsnr") if s in by else np.nan for s in SCENES]
            twin = variant.startswith(f"{engine}-")
            ax.plot(x, y, "o-" if twin else "s--", mfc=None if twin else "none", label=variant.rsplit("-v", 1)[0])
            axes[-1].plot(
                np.mean([d["train_wall_s"] for d in by.values()]),
                np.nanmean(y),
                "o" if twin else "s",
                color=colours[v],
                mfc=None if twin else "none",
            )
            axes[-1].annotate(
                f"{variant.rsplit('-v', 1)[0].replace('-cpu', '')} ({v})",
                (np.mean([d["train_wall_s"] for d in by.values()]), np.nanmean(y)),
                fontsize=7,
                xytext=(3, 3),
                textcoords="offset points",
            )
        ax.set_xticks(x, [s.split("_", 1)[1] for s in SCENES], rotation=60, fontsize=7)
        ax.set_title(f"{'all' if v == 'all' else v} training views")
        ax.set_ylabel("held-out fgPSNR (dB)")
        ax.legend(fontsize=7)
    axes[-1].set_xlabel("train s per scene (2 CPU cores)")
    axes[-1].set_ylabel("mean held-out fgPSNR (dB)")
    axes[-1].set_title("speed against quality (o twin, s vanilla)")
    fig.tight_layout()
    fig.savefig(out, dpi=120)
    plt.close(fig)
    return True


def write_report(work: Path, refine_steps: int, plot_variant: str | None = None, out: Path | None = None) -> str:
    """The report of every run cached under `work` at `out` (default benchmarks/results/rig_scenes.md), its plot beside it;
    the hand-written sections already below its tables are kept. Returns the text written."""
    out = out or RESULTS / "rig_scenes.md"
    runs: dict[str, dict[str, dict]] = {}
    for path in sorted((work / "runs").glob(f"*/*-r{refine_steps}.json")):
        doc = json.loads(path.read_text())
        runs.setdefault(doc["variant"], {})[doc["scene"]] = doc
    if plot_variant:
        plot_against_vanilla(runs, plot_variant, out.with_suffix(".png"))
    lines = [
        "# Reference benchmark: path-traced rig captures (`python -m benchmarks.bench_rig_scenes`)",
        "",
        "`shared/data/rig_scenes`: 8 YCB objects, 9-13 training views at 320x240, metric rig, 0.1 deg / 1 mm "
        "calibration noise not stated by the capture, deformed+decimated CAD among 110 distractors; 12 held-out views "
        f"with exact poses, metrics at the twin's nominal poses and after {refine_steps} test-time refinement steps. "
        "Poses: ADD-S of the training cameras (median over cameras, % of the bounding-sphere diameter), registration -> twin; "
        "Sim(3): ADD-S of the rig-to-object similarity alone (what held-out cameras inherit). "
        "Geometry: symmetric mean closest-point distance to the true surface (exact, from 20k samples of each surface), "
        "% of the diameter; geo change: the median over scenes of the twin's change against its CAD; crossing faces: "
        "faces that cross another (libigl), summed over scenes; watertight: scenes whose welded mesh is closed. Train time on 2 shared "
        "CPU cores (mean and median over the scenes); `load` is the 1-min load average when the run finished; `anchor ms`: "
        "the speed anchor's step read just before each twin trained (median over the scenes; one forward+backward of the tiled "
        "pure-PyTorch rasterizer at 20k splats, 256², `reconstruction.render.anchor`); `x anchor`: the median over the scenes of "
        "each twin's train time over the anchor step read beside it, the figure that carries from one machine to another.",
        "",
        "| variant | scenes | train s | median s | x anchor | load | anchor ms | fgPSNR | IoU | PSNR | SSIM | LPIPS | fgPSNR ref. | IoU ref. | LPIPS ref. | "
        "ADD-S reg % | ADD-S twin % | improved | Sim(3) reg % | Sim(3) twin % | CAD geo % | twin geo % | geo change | "
        "twin geo p95 % | crossing faces CAD / twin | watertight twin / CAD |",
        "|---" * 26 + "|",
    ]
    for variant, by in runs.items():
        ds = list(by.values())
        cad = [d for d in ds if "pose_trained" in d]
        machine = [d["machine_ref_ms"] for d in ds if d.get("machine_ref_ms") is not None]
        ratios = [1000.0 * d["train_wall_s"] / d["machine_ref_ms"] for d in ds if d.get("machine_ref_ms")]
        row = [
            variant,
            str(len(ds)),
            f"{np.mean([d['train_wall_s'] for d in ds]):.0f}",
            f"{np.median([d['train_wall_s'] for d in ds]):.1f}",
            f"{np.median(ratios):.1f}x" if ratios else "-",
            f"{np.mean([d['load'] for d in ds]):.1f}",
            f"{np.median(machine):.0f}" if machine else "-",
        ]
        row += [f"{np.nanmean([_m(d, k) for d in ds]):.3f}" for k in ("fgpsnr", "iou", "psnr", "ssim", "lpips")]
        # Runs without test-time refinement (`--refine-steps 0`) have no refined metrics: '-', not nan.
        refined = [d for d in ds if d.get("mean_refined")]
        row += [f"{np.nanmean([_m(d, k, True) for d in refined]):.3f}" if refined else "-" for k in ("fgpsnr", "iou", "lpips")]
        if cad:
            reg = [d["pose_registration"]["adds_pct_median"] for d in cad]
            tr = [d["pose_trained"]["adds_pct_median"] for d in cad]
            sim = [d.get("sim3_adds_pct", {}) for d in cad]
            row += [
                f"{np.median(reg):.2f}",
                f"{np.median(tr):.2f}",
                f"{sum(t < r for t, r in zip(tr, reg))}/{len(cad)}",
                f"{np.median([x.get('registration', np.nan) for x in sim]):.2f}",
                f"{np.median([x.get('twin', np.nan) for x in sim]):.2f}",
                f"{np.median([d['geometry_cad']['mean_pct'] for d in cad]):.3f}",
                f"{np.median([d['geometry_deformed']['mean_pct'] for d in cad]):.3f}",
                f"{np.median([100 * (d['geometry_deformed']['mean_pct'] / d['geometry_cad']['mean_pct'] - 1) for d in cad]):+.1f} %",
                f"{np.median([d['geometry_deformed']['p95_pct'] for d in cad]):.3f}",
            ]
            known = [d for d in cad if "crossing_faces" in d["geometry_cad"]]
            row += (
                [
                    f"{sum(d['geometry_cad']['crossing_faces'] for d in known)} / {sum(d['geometry_deformed']['crossing_faces'] for d in known)}",
                    f"{sum(d['geometry_deformed']['watertight'] for d in known)} / {sum(d['geometry_cad']['watertight'] for d in known)}",
                ]
                if known
                else ["-", "-"]
            )
        else:
            row += ["-"] * 11
        lines.append("| " + " | ".join(row) + " |")
    cpus = {v: sorted({d["cpu"] for d in by.values() if d.get("cpu")}) for v, by in runs.items()}
    if any(cpus.values()):
        lines += [
            "",
            "CPUs the timed runs trained on (runs before 2026-11-28 did not record theirs): "
            + "; ".join(f"`{v}` {' / '.join(c)}" for v, c in cpus.items() if c)
            + ".",
        ]
    lines += [
        "",
        "Per scene: fgPSNR / IoU at nominal poses; ADD-S % registration -> twin; geometry % CAD -> twin.",
        "",
        "| scene | " + " | ".join(runs) + " |",
        "|---" * (len(runs) + 1) + "|",
    ]
    for scene in SCENES:
        cells = []
        for by in runs.values():
            d = by.get(scene)
            if d is None:
                cells.append("-")
                continue
            cell = f"{_m(d, 'fgpsnr'):.2f} / {_m(d, 'iou'):.3f}"
            if "pose_trained" in d:
                cell += (
                    f"; {d['pose_registration']['adds_pct_median']:.2f} -> {d['pose_trained']['adds_pct_median']:.2f}"
                    f"; {d['geometry_cad']['mean_pct']:.2f} -> {d['geometry_deformed']['mean_pct']:.2f}"
                )
            cells.append(cell)
        lines.append(f"| {scene} | " + " | ".join(cells) + " |")
    text = "\n".join(lines) + "\n"
    return write_results(out, text)


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--scenes", default=",".join(SCENES))
    ap.add_argument("--variant", default="engine", help="name of this engine configuration (cache key)")
    ap.add_argument("--preset", default="cpu")
    ap.add_argument("--views", default="all", choices=["all", "5", "3"])
    ap.add_argument("--pose-mode", default=None, choices=["global", "per_camera"])
    ap.add_argument("--override", action="append", default=[], help="preset field KEY=JSON value")
    ap.add_argument("--vanilla", type=int, nargs="*", default=[], help="also train vanilla 3DGS for these iteration counts")
    ap.add_argument("--no-engine", action="store_true", help="only the vanilla runs")
    ap.add_argument(
        "--vanilla-eps2d",
        type=float,
        default=0.3,
        help="screen-space dilation (px^2) vanilla 3DGS trains and is drawn with (3DGS's 0.3; another value names its runs apart)",
    )
    ap.add_argument(
        "--exact-cameras",
        action="store_true",
        help="oracle: train on the true camera poses instead of the noisy recorded ones (name the variant apart)",
    )
    ap.add_argument("--refine-steps", type=int, default=100)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--work", type=Path, default=Path("/tmp/cadsplat-rig-scenes"))
    ap.add_argument("--library", type=Path, default=None, help="built index of rig_scenes/library (built into --work when absent)")
    ap.add_argument("--report-only", action="store_true")
    ap.add_argument("--plot", default=None, help="engine variant drawn against vanilla in rig_scenes.png (default: --variant)")
    ap.add_argument(
        "--out",
        type=Path,
        default=RESULTS / "rig_scenes.md",
        help="the report (its plot beside it); a scratch sweep names its own, the sections written by hand below the tables are kept",
    )
    ap.add_argument("--rescore", action="store_true", help="score the pose and geometry of cached runs' twins again")
    args = ap.parse_args()
    if not RIG_SCENES.is_dir():
        raise SystemExit(f"{RIG_SCENES} is not here: this benchmark needs the shared data (set CADSPLAT_SHARED_DATA)")
    if not args.report_only:
        lib = args.library or args.work / "library"
        if not (lib / "library.json").exists():
            from reconstruction.library import build_library

            build_library(RIG_SCENES / "library", lib, progress=False)
        if not args.no_engine:
            from reconstruction.warmup import compile_kernels

            # As `make env` does at install: a source edit since would charge its compile to the first scene's wall.
            compile_kernels()
        for name in args.scenes.split(","):
            scene = RIG_SCENES / "scenes" / name
            t0 = time.perf_counter()
            if not args.no_engine:
                doc = run_engine(scene, lib, args.work, args)
                print(
                    f"{name} {doc['variant']}: fgPSNR {_m(doc, 'fgpsnr'):.2f} IoU {_m(doc, 'iou'):.3f} "
                    f"ADD-S {doc['pose_registration']['adds_pct_median']:.2f} -> {doc['pose_trained']['adds_pct_median']:.2f} % "
                    f"geo {doc['geometry_cad']['mean_pct']:.3f} -> {doc['geometry_deformed']['mean_pct']:.3f} % "
                    f"({time.perf_counter() - t0:.0f} s)",
                    flush=True,
                )
            for iters in args.vanilla:
                doc = run_vanilla(scene, iters, args.work, args)
                print(
                    f"{name} {doc['variant']}: fgPSNR {_m(doc, 'fgpsnr'):.2f} IoU {_m(doc, 'iou'):.3f} ({doc['train_wall_s']:.0f} s)",
                    flush=True,
                )
    print(write_report(args.work, args.refine_steps, args.plot or args.variant, args.out))


if __name__ == "__main__":
    main()
