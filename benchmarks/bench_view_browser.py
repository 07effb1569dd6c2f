"""Third-party renders of the rig_scenes twins in headless Chromium against the engine's (issue 59's acceptance).

For every twin directory under --twins (one per scene, copied to a scratch folder first: the exports are
written beside the twin's files, which the server serves), `cadsplat export` writes the KHR_gaussian_splatting
GLB and the .spz; then, at each of --cameras (training cameras, indices into twin.json), Chromium draws:
- the page of `cadsplat view` (Spark reading splats.ply, the object frame);
- the .spz export through Spark's own .spz loader, turned back into the object frame;
- the GLB through Babylon.js's glTF loader (tests/khr_page): its colour composited by Babylon itself over an
  opaque white page, its silhouette from a transparent canvas (on one, Babylon's splat material adds the splats'
  alphas: tests/deploy/test_view.py says why), and, for the record, that transparent canvas over white.
Each against `reconstruction.gaussians.render` of the twin's splats over white: PSNR over the union of the two
alpha > 0.5 masks, and the IoU of those masks.

    python -m benchmarks.bench_view_browser --twins DIR [--only SCENE ...] [--cameras 0,4,8] [--out FILE]

Prints the table (benchmarks/results/view_browser.md carries it), and writes it to --out when given.
"""

from __future__ import annotations

import argparse
import os
import shutil
import subprocess
import sys
import tempfile
import threading
from pathlib import Path

import numpy as np

from benchmarks._common import load_line
from deploy.view import VENDOR_DIR, ViewRoots, ViewServer
from reconstruction.gaussians import render
from reconstruction.twin import load_twin
from simulation.gltf_splats import read_glb
from tests.browser import Chromium, chromium_binary, iou, psnr_over

REPO = Path(__file__).resolve().parents[1]
NODE_MODULES = Path(sys.prefix) / "node" / "node_modules"
KHR_PAGE = REPO / "tests" / "khr_page"


def export(twin_dir: Path, fmt: str) -> Path:
    out = twin_dir / f"splats.{fmt}"
    env = {**os.environ, "PYTHONPATH": str(REPO)}
    res = subprocess.run(
        [sys.executable, "-m", "deploy.cli", "export", str(twin_dir), "--format", fmt, "--out", str(out)],
        capture_output=True,
        text=True,
        env=env,
    )
    if res.returncode != 0:
        raise RuntimeError(f"cadsplat export --format {fmt}: {res.stderr.strip()}")
    return out


def served(roots: ViewRoots):
    server = ViewServer(roots)
    thread = threading.Thread(target=server.serve_forever, daemon=True)
    thread.start()
    return server, thread


def measure(browser: Chromium, twin_dir: Path, cameras: list[int]) -> list[dict]:
    """One row per (camera, reader): PSNR dB and IoU against the engine's render."""
    twin = load_twin(twin_dir)
    doc, _ = read_glb(export(twin_dir, "glb").read_bytes())
    export(twin_dir, "spz")
    gltf_from_object = np.asarray(doc["nodes"][0]["extras"]["cadsplat"]["gltf_from_object"], np.float64)
    to_gltf = ",".join(f"{x:.17g}" for x in gltf_from_object.ravel())
    to_object = ",".join(f"{x:.17g}" for x in np.linalg.inv(gltf_from_object).ravel())
    rows = []
    page, page_thread = served(ViewRoots(twin_dir))
    khr, khr_thread = served(ViewRoots(twin_dir, web=KHR_PAGE, vendor=NODE_MODULES))
    try:
        for index in cameras:
            cam = twin.cameras[index].camera
            out, a = render(twin.gaussians, cam.viewmat[None], cam.K[None], cam.width, cam.height)
            want, want_alpha = out[0].numpy(), a[0].numpy()

            def shot(server: ViewServer, query: str) -> np.ndarray:
                return browser.screenshot(server.url(query), cam.width, cam.height)[0] / 255.0

            def row(reader: str, rgb: np.ndarray, alpha: np.ndarray) -> None:
                union = (want_alpha > 0.5) | (alpha > 0.5)
                rows.append(
                    {"camera": index, "reader": reader, "psnr": psnr_over(rgb, want, union), "iou": iou(want_alpha > 0.5, alpha > 0.5)}
                )

            for reader, query in (
                ("splats.ply (the page)", f"camera={index}"),
                ("splats.spz (Spark)", f"camera={index}&splats=splats.spz&frame={to_object}"),
            ):
                s = shot(page, query)
                row(reader, s[..., :3] * s[..., 3:] + 1.0 - s[..., 3:], s[..., 3])
            canvas = shot(khr, f"camera={index}&frame={to_gltf}")
            white = shot(khr, f"camera={index}&frame={to_gltf}&background=white")
            row("splats.glb (Babylon.js, over white)", white[..., :3], canvas[..., 3])
            row(
                "splats.glb (Babylon.js, transparent canvas over white)",
                canvas[..., :3] * canvas[..., 3:] + 1.0 - canvas[..., 3:],
                canvas[..., 3],
            )
    finally:
        for server, thread in ((page, page_thread), (khr, khr_thread)):
            server.shutdown()
            server.server_close()
            thread.join()
    return rows


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("--twins", type=Path, required=True, help="one twin directory per scene name")
    ap.add_argument("--only", nargs="*", default=None)
    ap.add_argument("--cameras", default="0,4,8", help="training camera indices, comma-separated")
    ap.add_argument("--out", type=Path, default=None)
    args = ap.parse_args()
    binary = chromium_binary()
    if binary is None or not (VENDOR_DIR / "@sparkjsdev").is_dir() or not (NODE_MODULES / "babylonjs").is_dir():
        sys.exit("needs chromium, the vendored three.js and Spark, and Babylon.js under .venv/node (`make env`)")
    cameras = [int(c) for c in args.cameras.split(",")]
    scenes = sorted(p.name for p in args.twins.iterdir() if (p / "twin.json").is_file())
    if args.only:
        scenes = [s for s in scenes if s in args.only]
    lines = [
        "| scene | SH | eps2d | camera | reader | PSNR dB | alpha IoU |",
        "|---|---:|---:|---:|---|---:|---:|",
    ]
    browser = Chromium(binary)
    try:
        with tempfile.TemporaryDirectory(prefix="cadsplat-view-bench-") as scratch:
            for scene in scenes:
                twin_dir = Path(scratch) / scene
                shutil.copytree(args.twins / scene, twin_dir)
                twin = load_twin(twin_dir)
                for r in measure(browser, twin_dir, cameras):
                    lines.append(
                        f"| {scene} | {twin.gaussians.sh_degree} | {twin.gaussians.eps2d:g} | {r['camera']} | {r['reader']} | {r['psnr']:.2f} | {r['iou']:.4f} |"
                    )
                    print(lines[-1], flush=True)
                shutil.rmtree(twin_dir)
    finally:
        browser.close()
    text = "\n".join(
        [
            "# Third-party renders of the rig_scenes twins (headless Chromium) against the engine's render",
            "",
            f"`python -m benchmarks.bench_view_browser --twins {args.twins} --cameras {args.cameras}`; {load_line()}.",
            "",
            *lines,
            "",
        ]
    )
    print(text)
    if args.out is not None:
        args.out.write_text(text)


if __name__ == "__main__":
    main()
