"""The paper's section-5 demos on shared real meshes: a textured YCB banana dropped onto the YCB foam
brick (MuJoCo, rendered with Gaussians that follow the bodies, via `cadsplat simulate`), and an
exploded view of the six-solid CAD counter (parts from connected components).

    .venv/bin/python benchmarks/simulation_demo.py

Writes benchmarks/results/simulation_demo/{scene.toml, simulation.gif, frame_first.png,
frame_last.png, exploded.png} and prints the wall times.
"""

from __future__ import annotations

import shutil
import sys
import tempfile
import time
from pathlib import Path

import numpy as np

REPO = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(REPO))

from calibration.camera import Camera, look_at_c2w  # noqa: E402
from calibration.fileio import atomic_write_png  # noqa: E402
from deploy.cli import main as cli  # noqa: E402
from simulation.asset import load_mesh_asset  # noqa: E402
from simulation.follow import render_bodies, splats_from_mesh  # noqa: E402
from simulation.parts import explode  # noqa: E402

SHARED = REPO.parent / "shared" / "data"
OUT = REPO / "benchmarks" / "results" / "simulation_demo"

SCENE = """duration = 2.0
fps = 12
[camera]
mode = "turntable"
eye = [0.28, -0.28, 0.2]
target = [0, 0, 0.04]
width = 256
height = 192
fov_deg = 45
turns = 0.15
[[twin]]
name = "brick"
path = "{ycb}/061_foam_brick/textured.obj"
unit = "m"
bottom = 0.0
material = "foam"
splats = 30000
[[twin]]
name = "banana"
path = "{ycb}/011_banana/textured.obj"
unit = "m"
pos = [0.0, 0.0, 0.0]
euler_deg = [10, 0, 40]
bottom = 0.12
splats = 30000
"""


def main() -> None:
    if not SHARED.exists():
        sys.exit(f"needs the shared data folder {SHARED}")
    OUT.mkdir(parents=True, exist_ok=True)
    scene = OUT / "scene.toml"
    scene.write_text(SCENE.format(ycb=SHARED.resolve() / "objects" / "ycb"))
    with tempfile.TemporaryDirectory() as tmp:
        t0 = time.perf_counter()
        code = cli(["simulate", str(scene), "--out", str(Path(tmp) / "run"), "--no-decompose"])
        print(f"cadsplat simulate: exit {code}, {time.perf_counter() - t0:.1f} s")
        run = Path(tmp) / "run"
        shutil.copy(run / "simulation.gif", OUT / "simulation.gif")
        frames = sorted((run / "frames").glob("*.png"))
        shutil.copy(frames[0], OUT / "frame_first.png")
        shutil.copy(frames[-1], OUT / "frame_last.png")
        shutil.copy(run / "poses.json", OUT / "poses.json")

    t0 = time.perf_counter()
    asset = load_mesh_asset(SHARED / "cad" / "parts" / "counter.unitsmm.STL", name="counter")
    s = splats_from_mesh(asset.vertices, asset.faces, np.tile([0.55, 0.6, 0.7], (len(asset.faces), 1)), asset.face_part, 60000)
    # Colour each part so the explosion reads at a glance.
    palette = np.array([[0.85, 0.2, 0.2], [0.2, 0.6, 0.25], [0.2, 0.35, 0.85], [0.9, 0.7, 0.1], [0.6, 0.3, 0.7], [0.2, 0.7, 0.75]])
    s["sh"] = ((palette[s["part_label"] % len(palette)] - 0.5) / 0.28209479177387814).astype(np.float32)[:, None, :]
    centre = asset.vertices.mean(0)
    cam = Camera.from_fov(np.deg2rad(50), 320, 240, look_at_c2w(centre + np.array([0.25, -0.35, 0.35]), centre))
    assembled, _ = render_bodies([s], [np.eye(4)], cam)
    exploded = dict(s, means=explode(s["means"], s["part_label"], len(asset.part_names), 0.8))
    exp_rgb, _ = render_bodies([exploded], [np.eye(4)], cam)
    atomic_write_png(OUT / "exploded.png", np.concatenate([assembled, exp_rgb], 1))
    print(f"exploded view of counter ({len(asset.part_names)} parts, 60k splats): {time.perf_counter() - t0:.1f} s")


if __name__ == "__main__":
    main()
