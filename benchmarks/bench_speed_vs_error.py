"""Speed against error (issue 6): the method's presets, its ablations and the baselines, one harness.

    python -m benchmarks.bench_speed_vs_error [--quick] [--work DIR] [--scenes N] [--refine-steps N] [--out FILE.md]

Scenes: the synthetic rig (rig.synthetic, MuJoCo) photographs real YCB meshes from ../shared/data
(9-13 train views, 320x240, 0.3 deg / 2 mm calibration noise, 36 held-out orbit views). The CAD
model the method gets is the object decimated to 30 % and smoothly deformed (never the photographed
mesh), alone in its library. Training views: all, and 8 / 5 / 3 chosen by farthest-point sampling
over camera centres (first view drawn from the seed), as the paper's sparsity study.

Methods (one point per method x preset):
- full: the engine with presets `preview`, `cpu`, and `paper` (600k splats; iterations / 30 and
  one scene on a CPU, the full schedule on every scene where CUDA is present);
- ablations (`presets.ABLATIONS`, `cpu` preset): no-mask-warmup (the paper's strongest) on every
  scene; no-deformation, no-pose and no-sh-smoothness on the first two on a CPU (no-dropout is
  not run: the `cpu` preset has dropout off already);
- sphere-init: the `cpu` preset on the paper's sphere instead of the CAD model (first two scenes on a CPU);
- vanilla-3dgs: `baselines.train_vanilla_3dgs`, the original recipe, schedule scaled to its iterations.

Runs go breadth-first (every scene at all views, then 3, 5 and 8 views; then the sphere and the
other ablations on the first scenes), so an interrupted sweep has reported the rows that matter
most.

Every run's twin is scored by `reconstruction.evaluation` (the paper's protocol) on evenly spread
held-out views. Each run's metrics are cached as JSON under the work directory, so an interrupted
sweep resumes where it stopped. Each run reads the speed anchor's step just before it trains
(`benchmarks._common.machine_reading`) and caches it with its train time; the table's `x anchor` is the median over
a row's runs of one over the other. Writes benchmarks/results/speed_vs_error.md (or --out) and
speed_vs_error_time.png / speed_vs_error_views.png beside it.

Ablations and the sphere init are the engine's own switches (`reconstruct(init=..., ablations=...)`,
`cadsplat reconstruct --init sphere --ablate NAME`).
"""

from __future__ import annotations

import argparse
import json
import sys
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks._common import RESULTS, SHARED, cpu_line, decimate, deform, engine_kwargs, load_line, machine_reading, median_x_anchor

YCB = SHARED / "objects" / "ycb"
OBJECTS = (
    "050_medium_clamp",
    "037_scissors",
    "043_phillips_screwdriver",
    "011_banana",
    "072-c_toy_airplane",
    "033_spatula",
    "077_rubiks_cube",
    "061_foam_brick",
)
VIEW_COUNTS = ("all", 8, 5, 3)
# Methods whose twin lives in the CAD model's frame, so that gt.json's object-frame poses apply.
CAD_FRAME_METHODS = ("full", "no-mask-warmup", "no-deformation", "no-pose", "no-sh-smoothness")
SUMMARY = ("psnr", "ssim", "lpips", "mpsnr", "mlpips", "fgpsnr", "iou")


@dataclass(frozen=True)
class Run:
    scene: str
    method: str  # full | an ablation (presets.ABLATIONS) | sphere-init | vanilla-3dgs
    preset: str  # engine preset, or "i<iterations>" for vanilla 3DGS
    views: str  # "all" or a count

    @property
    def key(self) -> str:
        return f"{self.scene}/{self.method}-{self.preset}-v{self.views}"


# ------------------------------------------------------------------------------------ scenes


def make_scene(work: Path, index: int, obj: str) -> Path:
    """Synthetic rig capture of `obj` + its CAD library (one deformed, decimated variant); cached."""
    import trimesh

    from reconstruction.library import build_library
    from rig.synthetic import synth_dataset

    d = work / "scenes" / f"{index:02d}_{obj}"
    if not (d / "gt.json").exists():
        synth_dataset(
            YCB / obj / "textured.obj",
            d,
            views=9 + index % 5,
            heldout=36,
            size=(320, 240),
            seed=200 + index,
            calib_noise_deg=0.3,
            calib_noise_mm=2.0,
            texture_size=512,
        )
    if not (d / "lib" / "library.json").exists():
        (d / "cad").mkdir(exist_ok=True)
        mesh = trimesh.load(YCB / obj / "textured.obj", force="mesh")
        deform(decimate(mesh, 0.3), 0.03, seed=index).export(d / "cad" / f"{obj}_cad.stl")
        build_library(d / "cad", d / "lib", unit="m", workers=1, progress=False, log=lambda _m: None)
    return d


def fps_views(centres: np.ndarray, k: int, seed: int) -> list[int]:
    """Farthest-point sampling of k camera centres [V, 3], the first drawn from `seed` (paper 4.4.1)."""
    rng = np.random.default_rng(seed)
    chosen = [int(rng.integers(len(centres)))]
    dist = np.linalg.norm(centres - centres[chosen[0]], axis=1)
    while len(chosen) < min(k, len(centres)):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(centres - centres[nxt], axis=1))
    return sorted(chosen)


# ------------------------------------------------------------------------------------ symmetries


def scene_symmetries(scene_dir: Path, gt: dict) -> list[np.ndarray]:
    """Near-symmetries [4, 4] of the photographed mesh within the scene's calibration noise; cached in the scene."""
    cache = scene_dir / "near_symmetries.npz"
    if cache.exists():
        return list(np.load(cache)["transforms"])
    import trimesh

    from reconstruction.symmetry import near_symmetries

    mesh = trimesh.load(YCB / scene_dir.name[3:] / "textured.obj", force="mesh", process=False)
    found = near_symmetries(np.asarray(mesh.vertices), np.asarray(mesh.faces), 1e-3 * gt["calib_noise"]["sigma_mm"])
    transforms = np.stack([f.transform for f in found]) if found else np.zeros((0, 4, 4))
    np.savez(cache, transforms=transforms)
    return list(transforms)


# ------------------------------------------------------------------------------------ one run


def run_one(run: Run, scene_dir: Path, work: Path, args) -> dict:
    """Train (engine or baseline) and evaluate one configuration; the metrics JSON is cached."""
    import torch

    from calibration.capture import load_views, read_capture
    from calibration.fileio import atomic_write_json
    from reconstruction.evaluation import run_protocol
    from reconstruction.twin import save_twin

    cache = work / "runs" / f"{run.key}-r{args.refine_steps}-h{args.heldout_views}.json"
    if cache.exists():
        return json.loads(cache.read_text())
    train = read_capture(scene_dir / "train")
    centres = np.stack([f.camera.c2w[:3, 3] for f in train.frames])
    idx = list(range(len(train))) if run.views == "all" else fps_views(centres, int(run.views), seed=args.seed)
    twin_dir = work / "twins" / run.key
    anchor_ms = machine_reading().anchor_ms
    engine: dict = {}  # the baseline is trained here; run_protocol then scores its twin (reuse)
    if run.method == "vanilla-3dgs":
        if not (twin_dir / "twin.json").exists():
            from reconstruction.baselines import VanillaConfig, train_vanilla_3dgs, vanilla_twin

            images, masks, cams = load_views(train, idx)
            cfg = VanillaConfig().scaled(int(run.preset[1:]), init_points=args.vanilla_init_points)
            result = train_vanilla_3dgs(images, masks, cams, cfg, seed=args.seed)
            names = [train.frames[i].camera_id for i in idx]
            save_twin(vanilla_twin(result, cams, names), twin_dir, overwrite=True)
    else:
        engine = {"preset": run.preset, **engine_kwargs(run.method, run.preset, torch.cuda.is_available())}
    gt = json.loads((scene_dir / "gt.json").read_text())
    cad_frame = run.method in CAD_FRAME_METHODS
    result = run_protocol(
        scene_dir / "train",
        scene_dir / "heldout",
        scene_dir / "lib",
        twin_dir,
        views=idx,
        seed=args.seed,
        heldout_views=args.heldout_views,
        refine_steps=args.refine_steps,
        gt=gt if cad_frame else None,
        symmetries=scene_symmetries(scene_dir, gt) if cad_frame else None,
        reuse=True,
        overwrite=True,
        **engine,
    )
    doc = {
        "run": run.__dict__,
        "train_views": idx,
        "heldout_views": result.heldout_views,
        "refine_steps": args.refine_steps,
        "train_wall_s": result.timings_s["reconstruct"],
        "anchor_ms": anchor_ms,
        "num_splats": result.twin.num_splats,
        "mean": result.mean,
        "mean_refined": result.mean_refined,
        "eval_timings_s": result.report["timings_s"],
        "registration": {k: v for k, v in (result.reg_raw or {}).items() if k.endswith("median")},
        "registration_near_symmetric": {k: v for k, v in (result.reg_refined or {}).items() if k.endswith("median")},
    }
    cache.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_json(cache, doc)
    return doc


# ------------------------------------------------------------------------------------ report


def _mean(docs: list[dict], key: str, refined: bool) -> float:
    vals = [(d["mean_refined"] if refined and d["mean_refined"] else d["mean"]).get(key) for d in docs]
    vals = [v for v in vals if v is not None]
    return float(np.mean(vals)) if vals else float("nan")


def _anchor_span(docs: list[dict]) -> str:
    """'readings 1380-1520 ms': the range of the anchor steps the runs read, or a note that none did."""
    anchors = [d["anchor_ms"] for d in docs if d.get("anchor_ms")]
    return f"readings {min(anchors):.0f}-{max(anchors):.0f} ms" if anchors else "no run read one"


def _registration(doc: dict) -> dict:
    """The run's registration medians modulo near-symmetries when recorded, else the raw ones."""
    return doc.get("registration_near_symmetric") or doc["registration"]


def write_report(docs: list[dict], args, wall: float) -> str:
    """The markdown table (written to `args.out`) and the two plots beside it, from the cached runs `docs`."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    refined = args.refine_steps > 0
    groups: dict[tuple[str, str, str], list[dict]] = {}
    for d in docs:
        r = d["run"]
        groups.setdefault((r["method"], r["preset"], str(r["views"])), []).append(d)
    lines = [
        "# Speed against error (python -m benchmarks.bench_speed_vs_error)",
        "",
        f"{'--quick: ' if args.quick else ''}{len({d['run']['scene'] for d in docs})} synthetic rig scenes (YCB meshes, 320x240, "
        f"0.3 deg / 2 mm calibration noise, deformed+decimated CAD), {args.heldout_views} held-out views each, metrics "
        f"{'after ' + str(args.refine_steps) + ' test-time refinement steps' if refined else 'at the nominal poses (no refinement)'}; "
        f"train wall time on this machine's shared CPU ({cpu_line()}; {load_line()} when this table was written; load "
        "from other jobs inflates it); `x anchor`: the median over a row's runs of each train time over the speed anchor's "
        "step read just before that run trained (`reconstruction.render.anchor`: one forward+backward of the tiled "
        f"pure-PyTorch rasterizer, 20k splats at 256²; {_anchor_span(docs)}; '-' for runs cached before the anchor was recorded). "
        + (f"Sweep wall time {wall / 60:.1f} min." if wall else "Rewritten from the cached runs (--report-only).")
        + " Rows appear as their runs finish: a row with fewer scenes is a sweep that was stopped.",
        "",
        "Means over the scenes each row ran on. Δ columns: the row minus `full`/`cpu` at the same views, paired over the "
        "scenes both ran on (the fair comparison when a row covers fewer scenes). 'no ref.': at the twin's poses, before "
        "test-time refinement. rot / ctr: registration error of the training cameras (median over cameras, then median "
        "over scenes), modulo the photographed mesh's near-symmetries (turns moving its surface by less than the 2 mm "
        "calibration noise, `reconstruction.symmetry`) where the run recorded them, marked *; raw otherwise.",
        "",
        "| method | preset | views | scenes | train s | x anchor | splats | PSNR | SSIM | LPIPS | mPSNR | mLPIPS | fgPSNR | IoU | fgPSNR no ref. | IoU no ref. | Δ fgPSNR | Δ IoU | rot deg | ctr % |",
        "|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    order = {"full": 0, "no-mask-warmup": 1, "no-deformation": 2, "no-pose": 3, "no-sh-smoothness": 4, "sphere-init": 5, "vanilla-3dgs": 6}
    vorder = {v: i for i, v in enumerate(map(str, VIEW_COUNTS))}

    def metric(d: dict, key: str, use_refined: bool = refined) -> float:
        m = d["mean_refined"] if use_refined and d.get("mean_refined") else d["mean"]
        return float("nan") if m.get(key) is None else float(m[key])

    def paired(ds: list[dict], views: str, key: str) -> str:
        ref = {d["run"]["scene"]: d for d in groups.get(("full", "cpu", views), [])}
        diffs = [metric(d, key) - metric(ref[d["run"]["scene"]], key) for d in ds if d["run"]["scene"] in ref]
        return f"{np.mean(diffs):+.3f} ({len(diffs)})" if diffs else "-"

    for (method, preset, views), ds in sorted(groups.items(), key=lambda kv: (vorder.get(kv[0][2], 9), order.get(kv[0][0], 9), kv[0][1])):
        reg = [_registration(d) for d in ds if d.get("registration") and method in CAD_FRAME_METHODS]
        star = "*" if reg and all(d.get("registration_near_symmetric") for d in ds) else ""
        rot = f"{np.median([r['rotation_deg_median'] for r in reg]):.2f}{star}" if reg else "-"
        ctr = f"{np.median([r['center_pct_median'] for r in reg]):.2f}{star}" if reg else "-"
        cells = [f"{_mean(ds, k, refined):.3f}" for k in SUMMARY]
        cells += [f"{np.nanmean([metric(d, k, False) for d in ds]):.3f}" for k in ("fgpsnr", "iou")]
        delta = ["-", "-"] if (method, preset) == ("full", "cpu") else [paired(ds, views, k) for k in ("fgpsnr", "iou")]
        lines.append(
            f"| {method} | {preset} | {views} | {len(ds)} | {np.mean([d['train_wall_s'] for d in ds]):.0f} | "
            f"{median_x_anchor([(d['train_wall_s'], d.get('anchor_ms')) for d in ds])} | "
            f"{int(np.mean([d['num_splats'] for d in ds]))} | " + " | ".join(cells + delta) + f" | {rot} | {ctr} |"
        )
    scenes = sorted({d["run"]["scene"] for d in docs})
    cols = [
        k
        for k in sorted(
            {(d["run"]["method"], d["run"]["preset"]) for d in docs if str(d["run"]["views"]) == "all"},
            key=lambda mp: (order.get(mp[0], 9), mp[1]),
        )
    ]
    by = {(d["run"]["scene"], d["run"]["method"], d["run"]["preset"]): d for d in docs if str(d["run"]["views"]) == "all"}
    lines += [
        "",
        "Per scene, all training views: fgPSNR (dB) / IoU after refinement; rot (deg) of the training cameras for the CAD-frame methods.",
        "",
        "| scene | " + " | ".join(f"{m}/{p}" for m, p in cols) + " |",
        "|---|" + "---|" * len(cols),
    ]
    for sc in scenes:
        cells = []
        for m, p in cols:
            d = by.get((sc, m, p))
            if d is None:
                cells.append("-")
                continue
            star = "*" if d.get("registration_near_symmetric") else ""
            rot = f", {_registration(d)['rotation_deg_median']:.1f}°{star}" if d.get("registration") and m in CAD_FRAME_METHODS else ""
            cells.append(f"{metric(d, 'fgpsnr'):.2f} / {metric(d, 'iou'):.3f}{rot}")
        lines.append(f"| {sc} | " + " | ".join(cells) + " |")
    time_png, views_png = args.out.with_name(f"{args.out.stem}_time.png"), args.out.with_name(f"{args.out.stem}_views.png")
    lines += ["", f"![wall time vs quality]({time_png.name})", "", f"![quality vs views]({views_png.name})", ""]

    fig, axes = plt.subplots(1, 3, figsize=(15, 4.2))
    for ax, key, label in zip(axes, ("fgpsnr", "mlpips", "iou"), ("fgPSNR (dB) ↑", "mLPIPS ↓", "IoU ↑")):
        for (method, preset, views), ds in groups.items():
            if views != str(VIEW_COUNTS[0]):
                continue
            x = np.mean([d["train_wall_s"] for d in ds])
            ax.scatter(x, _mean(ds, key, refined), s=40)
            ax.annotate(f"{method}/{preset}", (x, _mean(ds, key, refined)), fontsize=7, xytext=(3, 3), textcoords="offset points")
        ax.set_xscale("log")
        ax.set_xlabel("train wall time (s, log)")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    fig.suptitle("All training views: one point per method x preset (mean over scenes)")
    fig.tight_layout()
    args.out.parent.mkdir(parents=True, exist_ok=True)
    fig.savefig(time_png, dpi=110)
    plt.close(fig)

    fig, axes = plt.subplots(1, 2, figsize=(11, 4.2))
    for ax, key, label in zip(axes, ("fgpsnr", "iou"), ("fgPSNR (dB) ↑", "IoU ↑")):
        series: dict[tuple[str, str], list[tuple[int, float]]] = {}
        for (method, preset, _views), ds in groups.items():
            n = int(np.mean([len(d["train_views"]) for d in ds]))
            series.setdefault((method, preset), []).append((n, _mean(ds, key, refined)))
        for (method, preset), pts in sorted(series.items()):
            pts.sort()
            ax.plot([p[0] for p in pts], [p[1] for p in pts], "o-", label=f"{method}/{preset}")
        ax.set_xlabel("training views")
        ax.set_ylabel(label)
        ax.grid(alpha=0.3)
    axes[0].legend(fontsize=7)
    fig.tight_layout()
    fig.savefig(views_png, dpi=110)
    plt.close(fig)
    text = "\n".join(lines)
    args.out.write_text(text)
    return text


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    ap.add_argument(
        "--quick",
        action="store_true",
        help="2 scenes, all + 3 views, preview presets, short vanilla, 4 held-out views, 20 refinement steps",
    )
    ap.add_argument(
        "--work",
        type=Path,
        default=Path("/tmp/cadsplat-bench-speed-vs-error"),
        help="cache of scenes, twins and per-run metrics (resumable)",
    )
    ap.add_argument("--scenes", type=int, default=None)
    ap.add_argument("--refine-steps", type=int, default=None)
    ap.add_argument("--seed", type=int, default=0)
    ap.add_argument("--report-only", action="store_true", help="rewrite the table and plots from the runs cached in --work")
    ap.add_argument("--out", type=Path, default=RESULTS / "speed_vs_error.md", help="the table; its two plots are written beside it")
    ap.add_argument(
        "--few", type=int, default=None, help="scenes for the sphere and extra-ablation rows (default: 2 on a CPU, all on CUDA)"
    )
    ap.add_argument(
        "--only",
        action="append",
        default=None,
        metavar="METHOD/PRESET/VIEWS",
        help="run only these rows of the plan, e.g. full/cpu/all (repeatable)",
    )
    args = ap.parse_args()
    if not YCB.exists():
        sys.exit(f"needs the shared data folder ({YCB} is absent)")
    import torch

    cuda = torch.cuda.is_available()
    if args.quick:
        n_scenes, args.heldout_views = args.scenes or 2, 4
        args.refine_steps = 20 if args.refine_steps is None else args.refine_steps
        args.vanilla_init_points = 3000
        per_view = [("full", "preview"), ("vanilla-3dgs", "i300")]
        plan = [(v, m, p, n_scenes) for v in ("all", 3) for m, p in per_view]
        plan += [("all", m, "preview", n_scenes) for m in ("no-mask-warmup", "sphere-init")]
    else:
        n_scenes, args.heldout_views = args.scenes or 6, 6
        args.refine_steps = 50 if args.refine_steps is None else args.refine_steps
        args.vanilla_init_points = 10_000 if not cuda else 100_000
        vanilla = "i3000" if cuda else "i1000"
        # On 2 CPU cores a cpu-preset run and its scoring take ~2 min: every scene gets the view-count study
        # and the strongest ablation; the sphere, the other ablations and the CPU `paper` run get fewer.
        few = min(args.few or (n_scenes if cuda else 2), n_scenes)
        plan = [
            ("all", m, p, n_scenes) for m, p in (("full", "cpu"), ("vanilla-3dgs", vanilla), ("no-mask-warmup", "cpu"), ("full", "preview"))
        ]
        plan += [(v, m, p, n_scenes) for v in (3, 5, 8) for m, p in (("full", "cpu"), ("vanilla-3dgs", vanilla))]
        plan += [("all", m, "cpu", few) for m in ("sphere-init", "no-deformation", "no-pose", "no-sh-smoothness")]
        plan += [("all", "full", "paper", n_scenes if cuda else 1)]
    if args.only:
        plan = [row for row in plan if f"{row[1]}/{row[2]}/{row[0]}" in args.only]
        if not plan:
            sys.exit(f"--only {', '.join(args.only)} matches no row of the plan")
    args.work.mkdir(parents=True, exist_ok=True)
    t0 = time.perf_counter()
    if args.report_only:
        docs = [
            json.loads(p.read_text()) for p in sorted((args.work / "runs").glob(f"*/*-r{args.refine_steps}-h{args.heldout_views}.json"))
        ]
        print(write_report(docs, args, 0.0))
        return
    scenes = [make_scene(args.work, i, obj) for i, obj in enumerate(OBJECTS[:n_scenes])]
    docs = []
    for views, method, preset, upto in plan:
        for scene in scenes[:upto]:
            run = Run(scene.name, method, preset, str(views))
            t = time.perf_counter()
            try:
                doc = run_one(run, scene, args.work, args)
            except Exception as e:  # one failed configuration is reported, the sweep goes on
                print(f"{run.key}: FAILED ({e.__class__.__name__}: {e})", flush=True)
                continue
            docs.append(doc)
            m = doc["mean_refined"] or doc["mean"]
            print(
                f"{run.key}: train {doc['train_wall_s']:.0f} s, fgPSNR {m['fgpsnr']}, IoU {m['iou']:.3f} ({time.perf_counter() - t:.0f} s)",
                flush=True,
            )
            write_report(docs, args, time.perf_counter() - t0)
    print(write_report(docs, args, time.perf_counter() - t0))


if __name__ == "__main__":
    main()
