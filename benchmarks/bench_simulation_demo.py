"""The paper's physics demo, measured: the screwdriver twin dropped onto the clamp twin (MuJoCo, the
twins' repaired meshes for mass, CoACD pieces chosen by volume error for contact, the Gaussians
following the bodies), and the same drop with the true meshes (rig_scenes gt_mesh.ply, same object
frames, same density, same initial poses, collision at a tighter 5 % tolerance) as the reference.

Reported: collision geometry of each body, the rest pose of each body (position and rotation
differences twin vs true), the contact points at rest (count, per body pair, and the distance from
each twin contact to the nearest true contact), wall times, each beside its ratio to the speed anchor's
step read at the start of the run (`x anchor`; `benchmarks._common.machine_reading`, its ms, CPU and load
stated above the tables). Also the exploded view of the six-solid CAD counter (parts from connected components).

    python -m benchmarks.bench_simulation_demo [--twins ../twins_base] [--duration 1.5]

Writes benchmarks/results/simulation_demo/{drop.md, simulation.gif, frame_first.png,
frame_last.png, contacts.png, exploded.png}.
"""

from __future__ import annotations

import argparse
import tempfile
import time
from dataclasses import replace
from pathlib import Path

import numpy as np

from benchmarks._common import REPO, RESULTS, SHARED, MachineReading, machine_reading
from calibration.camera import Camera, look_at_c2w
from calibration.fileio import atomic_write_png
from calibration.so3 import axis_angle_to_matrix, matrix_to_quat, quat_to_matrix
from simulation.asset import load_mesh_asset
from simulation.collision import DecompositionOptions
from simulation.export import load_body
from simulation.follow import camera_path, render_bodies, render_trajectory, splats_from_mesh
from simulation.mjcf import SimOptions, write_mjcf_package
from simulation.parts import explode
from simulation.run import load_model, simulate
from simulation.scene import CameraSpec, Placement

OUT = RESULTS / "simulation_demo"
CLAMP, SCREWDRIVER = "050_medium_clamp", "043_phillips_screwdriver"
DROP_HEIGHT = 0.06  # m between the clamp's top and the screwdriver's lowest point
SCREW_TURN = matrix_to_quat(
    axis_angle_to_matrix(np.array([0.0, 0.0, np.deg2rad(35.0)])) @ axis_angle_to_matrix(np.array([np.deg2rad(8.0), 0.0, 0.0]))
)


def placements(clamp_src: Path, screw_src: Path, tolerance: float, clamp_mesh: np.ndarray, screw_mesh: np.ndarray) -> list[Placement]:
    """The clamp resting flat at the origin, the screwdriver turned 35 deg, tilted 8 deg, its centre
    above the clamp's centre, DROP_HEIGHT above the clamp's top. Poses come from the true meshes so
    both runs start identically."""
    clamp_centre = 0.5 * (clamp_mesh.min(0) + clamp_mesh.max(0))
    screw_centre = 0.5 * (screw_mesh.min(0) + screw_mesh.max(0))
    clamp_z = -float(clamp_mesh[:, 2].min())
    screw_rot = quat_to_matrix(SCREW_TURN)
    xy = clamp_centre[:2] - (screw_rot @ screw_centre)[:2]
    z = clamp_z + float(clamp_mesh[:, 2].max()) + DROP_HEIGHT - float((screw_mesh @ screw_rot.T)[:, 2].min())
    unit = {"unit": "m"} if clamp_src.is_file() else {}
    return [
        Placement(name="clamp", source=clamp_src, pos=(0.0, 0.0, clamp_z), collision_tolerance=tolerance, **unit),
        Placement(
            name="screwdriver",
            source=screw_src,
            pos=(float(xy[0]), float(xy[1]), z),
            quat=tuple(SCREW_TURN),
            collision_tolerance=tolerance,
            **unit,
        ),
    ]


def run(places: list[Placement], out: Path, duration: float, fps: float, decomposition: DecompositionOptions):
    """(bodies, splats, trajectory, contacts at the end [(body_a, body_b, pos [3])], seconds) of one drop."""
    import mujoco

    t0 = time.perf_counter()
    loaded = [load_body(p, decomposition) for p in places]
    bodies, splats = [b for b, _ in loaded], [s for _, s in loaded]
    prep_s = time.perf_counter() - t0
    model = load_model(write_mjcf_package(out, bodies, SimOptions()))
    t0 = time.perf_counter()
    traj = simulate(model, duration, fps)
    data = mujoco.MjData(model)
    while data.time < duration - 0.5 * model.opt.timestep:
        mujoco.mj_step(model, data)
    names = ["world"] + [b.asset.name for b in bodies]
    contacts = [
        tuple(sorted((names[model.geom_bodyid[c.geom1]], names[model.geom_bodyid[c.geom2]]))) + (np.array(c.pos),)
        for c in data.contact[: data.ncon]
    ]
    return bodies, splats, traj, contacts, prep_s, time.perf_counter() - t0


def angle_deg(qa: np.ndarray, qb: np.ndarray) -> float:
    return float(np.degrees(2 * np.arccos(np.clip(abs(np.dot(qa, qb)), -1.0, 1.0))))


def contact_summary(contacts: list, pair: tuple[str, str]) -> np.ndarray:
    return np.array([c[2] for c in contacts if (c[0], c[1]) == pair]).reshape(-1, 3)


def collision_table(bodies_by_run: dict[str, list], machine: MachineReading) -> list[str]:
    """Markdown rows of each body's collision geometry per run ('twin', 'true'), its seconds beside their x anchor."""
    lines = [
        "| body | run | mass kg | collision | shapes | vol. err | Hausdorff mm | collision s | x anchor |",
        "|---|---|---:|---|---:|---:|---:|---:|---:|",
    ]
    for run_name, bodies in bodies_by_run.items():
        for b in bodies:
            c = b.collision
            lines.append(
                f"| {b.asset.name} | {run_name} | {b.asset.mass.mass:.4f} | {c.kind} | {c.hull_count + len(c.primitives)} "
                f"| {100 * c.volume_error:+.1f}% | {1e3 * c.hausdorff:.2f} | {c.seconds:.0f} | {machine.x_anchor(c.seconds)} |"
            )
    return lines


def wall_time_line(seconds: dict[str, float], frames: int, splats: int, machine: MachineReading) -> str:
    """The demo's wall times (keys prep_twin, prep_true, sim_twin, sim_true, render), each with its x anchor."""
    x = {k: machine.x_anchor(v) for k, v in seconds.items()}
    return (
        f"Wall time (x anchor): twin bodies {seconds['prep_twin']:.0f} s ({x['prep_twin']}; repair, mass, CoACD), true bodies "
        f"{seconds['prep_true']:.0f} s ({x['prep_true']}); simulation {seconds['sim_twin']:.1f} s ({x['sim_twin']}, twin) / "
        f"{seconds['sim_true']:.1f} s ({x['sim_true']}, true); Gaussian renders {seconds['render']:.0f} s ({x['render']}) for "
        f"{frames} frames ({splats} splats)."
    )


def drop_demo(twins: Path, duration: float, fps: float, decomposition: DecompositionOptions, machine: MachineReading) -> str:
    from scipy.spatial import cKDTree

    gt = {n: SHARED / "rig_scenes" / "scenes" / n / "gt_mesh.ply" for n in (CLAMP, SCREWDRIVER)}
    true_v = {n: load_mesh_asset(p, "m").vertices for n, p in gt.items()}
    runs = {
        "twin": placements(twins / CLAMP, twins / SCREWDRIVER, 0.10, true_v[CLAMP], true_v[SCREWDRIVER]),
        "true": placements(gt[CLAMP], gt[SCREWDRIVER], 0.05, true_v[CLAMP], true_v[SCREWDRIVER]),
    }
    with tempfile.TemporaryDirectory() as tmp:
        res = {k: run(v, Path(tmp) / k, duration, fps, decomposition) for k, v in runs.items()}
    bodies_t, splats_t, traj_t, contacts_t, prep_t, sim_t = res["twin"]
    bodies_r, _, traj_r, contacts_r, prep_r, sim_r = res["true"]

    spec = CameraSpec(mode="turntable", eye=(0.22, -0.26, 0.2), target=(0.0, 0.0, 0.02), width=256, height=192, fov_deg=45, turns=0.15)
    t0 = time.perf_counter()
    frames = render_trajectory(splats_t, traj_t.poses(), camera_path(spec, len(traj_t.times)))
    render_s = time.perf_counter() - t0
    import imageio.v3 as iio

    iio.imwrite(OUT / "simulation.gif", frames, extension=".gif", duration=1000.0 / fps, loop=0)
    atomic_write_png(OUT / "frame_first.png", frames[0])
    atomic_write_png(OUT / "frame_last.png", frames[-1])
    plot_contacts(contacts_t, contacts_r, OUT / "contacts.png")

    lines = [
        "# Physics demo: the screwdriver twin dropped onto the clamp twin, against the same drop with the true meshes\n",
        f"Twins from the engine's rig_scenes run; true meshes = rig_scenes gt_mesh.ply (same object frames). ABS density, "
        f"{DROP_HEIGHT * 100:.0f} cm drop, screwdriver turned 35 deg and tilted 8 deg over the clamp's centre, {duration:g} s at 1 ms steps, "
        f"MuJoCo {__import__('mujoco').__version__}. {machine.header()}\n",
        *collision_table({"twin": bodies_t, "true": bodies_r}, machine),
    ]
    lines += [
        "",
        f"Rest pose (last frame; body origin = object-frame origin) and contacts at rest; final kinetic energy "
        f"{traj_t.kinetic[-1]:.1e} J (twin) / {traj_r.kinetic[-1]:.1e} J (true):",
        "",
        "| body | twin pos mm | true pos mm | pos diff mm | rotation diff deg |",
        "|---|---|---|---:|---:|",
    ]
    for i, b in enumerate(bodies_t):
        pt, pr = 1e3 * traj_t.pos[-1, i], 1e3 * traj_r.pos[-1, i]
        lines.append(
            f"| {b.asset.name} | {np.round(pt, 1).tolist()} | {np.round(pr, 1).tolist()} | {np.linalg.norm(pt - pr):.1f} "
            f"| {angle_deg(traj_t.quat[-1, i], traj_r.quat[-1, i]):.1f} |"
        )
    lines += ["", "| contact pair | twin contacts | true contacts | twin to nearest true contact, mean / max mm |", "|---|---:|---:|---|"]
    for pair in sorted({(c[0], c[1]) for c in contacts_t + contacts_r}):
        a, b = contact_summary(contacts_t, pair), contact_summary(contacts_r, pair)
        near = (
            "n/a"
            if not (len(a) and len(b))
            else "{:.1f} / {:.1f}".format(*(1e3 * np.array([(d := cKDTree(b).query(a)[0]).mean(), d.max()])))
        )
        lines.append(f"| {pair[0]} - {pair[1]} | {len(a)} | {len(b)} | {near} |")
    lines += [
        "",
        wall_time_line(
            {"prep_twin": prep_t, "prep_true": prep_r, "sim_twin": sim_t, "sim_true": sim_r, "render": render_s},
            len(frames),
            sum(len(s) for s in splats_t),
            machine,
        ),
        "",
        "![first](frame_first.png) ![last](frame_last.png) ![contacts](contacts.png)",
    ]
    return "\n".join(lines) + "\n"


def plot_contacts(twin: list, true: list, path: Path) -> None:
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    fig, ax = plt.subplots(figsize=(5, 4.5))
    for contacts, label, marker in ((true, "true meshes", "o"), (twin, "twins", "x")):
        pts = np.array([c[2] for c in contacts]).reshape(-1, 3)
        ax.scatter(1e3 * pts[:, 0], 1e3 * pts[:, 1], marker=marker, label=f"{label} ({len(pts)})")
    ax.set_aspect("equal")
    ax.set_xlabel("x mm")
    ax.set_ylabel("y mm")
    ax.set_title("contact points at rest (top view)")
    ax.legend()
    fig.tight_layout()
    fig.savefig(path, dpi=110)


def exploded_counter() -> float:
    t0 = time.perf_counter()
    asset = load_mesh_asset(SHARED / "cad" / "parts" / "counter.unitsmm.STL", name="counter", split_components=True)
    # Colour each part so the explosion reads at a glance.
    palette = np.array([[0.85, 0.2, 0.2], [0.2, 0.6, 0.25], [0.2, 0.35, 0.85], [0.9, 0.7, 0.1], [0.6, 0.3, 0.7], [0.2, 0.7, 0.75]])
    s = splats_from_mesh(asset.vertices, asset.faces, palette[asset.face_part % len(palette)], asset.face_part, 60000)
    g = s.gaussians
    centre = asset.vertices.mean(0)
    cam = Camera.from_fov(np.deg2rad(50), 320, 240, look_at_c2w(centre + np.array([0.25, -0.35, 0.35]), centre))
    assembled, _ = render_bodies([g], [np.eye(4)], cam)
    exploded = replace(g, means=explode(g.means, s.part_label, len(asset.part_names), 0.8))
    exp_rgb, _ = render_bodies([exploded], [np.eye(4)], cam)
    atomic_write_png(OUT / "exploded.png", np.concatenate([assembled, exp_rgb], 1))
    return time.perf_counter() - t0


def main() -> None:
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--twins", type=Path, default=REPO.parent / "twins_base", help="directory of twins named by scene")
    ap.add_argument("--duration", type=float, default=1.5)
    ap.add_argument("--fps", type=float, default=12.0)
    ap.add_argument("--coacd-timeout", type=float, default=1800.0, help="CoACD wall-clock budget per part (s); the product's is 300")
    args = ap.parse_args()
    if not SHARED.exists():
        raise SystemExit(f"needs the shared data folder {SHARED}")
    missing = [n for n in (CLAMP, SCREWDRIVER) if not (args.twins / n / "twin.json").exists()]
    if missing:
        raise SystemExit(f"no twin of {', '.join(missing)} in {args.twins}")
    OUT.mkdir(parents=True, exist_ok=True)
    machine = machine_reading()
    report = drop_demo(args.twins, args.duration, args.fps, DecompositionOptions(timeout_s=args.coacd_timeout), machine)
    (OUT / "drop.md").write_text(report)
    print(report)
    exploded_s = exploded_counter()
    print(f"exploded view of counter: {exploded_s:.1f} s ({machine.x_anchor(exploded_s)} the anchor)")


if __name__ == "__main__":
    main()
