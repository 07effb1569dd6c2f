"""Collision geometry sized to need: primitives for primitive shapes, the hull for convex ones,
CoACD pieces for concave ones, with the volume error that justified each choice."""

from __future__ import annotations

import os
import signal
import subprocess
import sys
import time
from pathlib import Path

import numpy as np
import pytest
import trimesh

from simulation.collision import (
    DecompositionOptions,
    collision_geometry,
    fit_box,
    fit_capsule,
    fit_cylinder,
    fit_sphere,
    hull_shares,
    surface_points,
)

FAST = DecompositionOptions(max_convex_hull=8, mcts_iterations=20, resolution=500, timeout_s=600)  # a generous cap: the CPU is shared


def rotated(mesh: trimesh.Trimesh, seed: int = 0) -> trimesh.Trimesh:
    t = trimesh.transformations.random_rotation_matrix(np.random.default_rng(seed).random(3))
    t[:3, 3] = [0.1, -0.2, 0.3]
    return mesh.copy().apply_transform(t)


def choose(mesh, **kw):
    return collision_geometry(mesh.vertices, mesh.faces, mesh.volume, **kw)


def test_rotated_box_gets_its_box():
    mesh = rotated(trimesh.creation.box(extents=[0.04, 0.1, 0.2]))
    col = choose(mesh)
    assert col.kind == "box" and abs(col.volume_error) < 1e-6
    assert sorted(col.primitive.size) == pytest.approx([0.02, 0.05, 0.1], rel=1e-6)
    # The primitive's pose puts its surface on the mesh: every mesh vertex is a box corner.
    local = (mesh.vertices - col.primitive.transform[:3, 3]) @ col.primitive.transform[:3, :3]
    assert np.abs(np.abs(local) - np.array(col.primitive.size)).max() < 1e-6


def test_cylinder_capsule_and_sphere_are_recognised():
    cyl = choose(rotated(trimesh.creation.cylinder(radius=0.03, height=0.2, sections=96), 1))
    assert cyl.kind == "cylinder" and cyl.volume_error < 0.01
    assert cyl.primitive.size == pytest.approx((0.03, 0.1), rel=0.01)
    cap = choose(rotated(trimesh.creation.capsule(radius=0.02, height=0.1, count=[48, 48]), 2))
    assert cap.kind == "capsule" and cap.volume_error < 0.02
    assert cap.primitive.size == pytest.approx((0.02, 0.05), rel=0.02)
    sph = choose(trimesh.creation.icosphere(subdivisions=4, radius=0.05))
    assert sph.kind == "sphere" and sph.volume_error < 0.01


def test_primitives_enclose_the_points():
    pts = np.random.default_rng(3).normal(size=(500, 3)) * [0.05, 0.02, 0.01]
    for fit in (fit_box, fit_sphere, fit_cylinder, fit_capsule):
        p = fit(pts)
        local = (pts - p.transform[:3, 3]) @ p.transform[:3, :3]
        r = np.linalg.norm(local[:, :2], axis=1)
        if p.kind == "box":
            inside = np.all(np.abs(local) <= np.array(p.size) + 1e-9, 1)
        elif p.kind == "sphere":
            inside = np.linalg.norm(local, axis=1) <= p.size[0] + 1e-9
        elif p.kind == "cylinder":
            inside = (r <= p.size[0] + 1e-9) & (np.abs(local[:, 2]) <= p.size[1] + 1e-9)
        else:
            dz = np.maximum(np.abs(local[:, 2]) - p.size[1], 0)
            inside = np.hypot(r, dz) <= p.size[0] + 1e-9
        assert inside.all(), p.kind


def test_convex_but_irregular_mesh_gets_one_hull():
    mesh = trimesh.convex.convex_hull(np.random.default_rng(4).normal(size=(200, 3)) * 0.05)
    col = choose(mesh)
    assert col.kind == "hull" and col.hull_count == 1 and abs(col.volume_error) < 1e-9


def test_concave_torus_is_decomposed_and_beats_its_hull():
    mesh = trimesh.creation.torus(major_radius=0.05, minor_radius=0.015, major_sections=32, minor_sections=16)
    hull_error = mesh.convex_hull.volume / mesh.volume - 1
    col = choose(mesh, decomposition=FAST)
    assert col.kind == "decomposition" and 2 <= col.hull_count <= FAST.max_convex_hull
    assert abs(col.volume_error) < 0.25 < hull_error
    # The hole stays open: no piece covers the torus axis.
    pts = surface_points(col)
    assert np.linalg.norm(pts[:, :2], axis=1).min() > 0.02


def test_decomposition_timeout_falls_back_to_the_hull_and_says_so():
    mesh = trimesh.creation.torus(major_radius=0.05, minor_radius=0.015)
    col = choose(mesh, decomposition=DecompositionOptions(timeout_s=0.01))
    assert col.kind == "hull" and "convex hull used" in col.notes[-1] and "did not finish" in col.notes[0]


def test_zero_volume_is_refused():
    mesh = trimesh.creation.box(extents=[1, 1, 1])
    with pytest.raises(ValueError, match="volume must be positive"):
        collision_geometry(mesh.vertices, mesh.faces, 0.0)


def test_piece_count_follows_the_volume_error():
    mesh = trimesh.creation.torus(major_radius=0.05, minor_radius=0.01, major_sections=24, minor_sections=12)
    uncapped = DecompositionOptions(mcts_iterations=20, resolution=500, timeout_s=600)
    loose = choose(mesh, tolerance=0.5, decomposition=uncapped)
    tight = choose(mesh, tolerance=0.1, decomposition=uncapped)
    assert loose.kind == tight.kind == "decomposition"
    assert abs(tight.volume_error) <= 0.1 < mesh.convex_hull.volume / mesh.volume - 1
    assert tight.hull_count >= loose.hull_count
    # The collision surface lies within a few millimetres of the torus surface (tube radius 10 mm).
    assert 0 < tight.hausdorff < 0.005


def test_the_decomposition_keeps_to_its_hull_budget_and_reports_the_error_left():
    mesh = trimesh.creation.torus(major_radius=0.05, minor_radius=0.01, major_sections=24, minor_sections=12)
    budget = DecompositionOptions(hull_budget=5, threshold=0.02, rounds=4, mcts_iterations=20, resolution=500, timeout_s=600)
    col = choose(mesh, tolerance=0.02, decomposition=budget)  # a tolerance only many pieces could meet
    assert col.kind == "decomposition" and 1 < col.hull_count <= 5 == col.hull_budget
    assert any("over the budget" in n or "merged to the budget" in n for n in col.notes)
    assert col.notes[-1].startswith(f"CoACD: {col.hull_count} convex pieces, {100 * col.volume_error:+.1f}% volume error")


def test_hull_shares_split_the_budget_by_volume_one_hull_each_at_least():
    assert hull_shares(None, [1.0, 2.0]) == [None, None]
    shares = hull_shares(32, [1.0, 1.0, 6.0])
    assert shares == [4, 4, 22] and sum(shares) <= 32  # 1 each, then 29 by volume, rounded down
    assert hull_shares(2, [1.0, 1.0, 1.0]) == [1, 1, 1]  # more parts than hulls: one each, said by the caller


def test_each_cad_part_gets_its_own_primitive():
    from tests.simulation.twins import skateboard

    parts, _ = skateboard()
    mesh = trimesh.Trimesh(parts.vertices, parts.faces, process=False)
    col = collision_geometry(parts.vertices, parts.faces, mesh.volume, face_part=parts.face_part)
    assert col.kind == "parts" and col.hull_count == 0
    assert sorted(p.kind for p in col.primitives) == ["box"] + ["cylinder"] * 4
    assert abs(col.volume_error) < 0.02 and col.hausdorff < 0.001


def test_clamp_hangs_on_a_5mm_rod_through_its_opening_which_one_hull_cannot(tmp_path):
    """The bundled clamp CAD variant hung by the opening between its jaws and handles on a fixed
    5 mm rod: with CoACD pieces the opening stays open and the clamp hangs; its single convex hull
    fills the opening, so MuJoCo pushes the rod out and the clamp falls."""
    from calibration.so3 import axis_angle_to_matrix, matrix_to_quat
    from reconstruction.mesh_io import MeshParts
    from simulation.asset import build_asset, choose_density
    from simulation.mjcf import BodySpec, SimOptions, write_mjcf_package
    from simulation.run import load_model, simulate
    from tests.conftest import REPO

    m = trimesh.load(REPO / "sample" / "library_meshes" / "medium_clamp_cad.ply", process=False)
    clamp = build_asset("clamp", MeshParts(m.vertices, m.faces, np.zeros(len(m.faces), int), ["clamp"]))
    rod_mesh = trimesh.creation.capsule(radius=0.0025, height=0.08, count=[16, 16])
    rod_mesh.apply_transform(trimesh.transformations.rotation_matrix(np.pi / 2, [1, 0, 0]))  # along world y
    rod = build_asset(
        "rod",
        MeshParts(rod_mesh.vertices, rod_mesh.faces, np.zeros(len(rod_mesh.faces), int), ["rod"]),
        density=choose_density(material="steel"),
    )
    rod_col = collision_geometry(rod.vertices, rod.faces, rod.mass.volume, decomposition=None)
    assert rod_col.kind == "capsule"
    # The clamp stood on edge, the opening's axis (object z) along the rod; the opening's centre
    # (7.4 mm clear radius, found on this mesh) 3.9 mm below the rod's axis: a 1 mm drop onto it.
    rot = axis_angle_to_matrix(np.array([np.pi / 2, 0.0, 0.0]))
    opening = np.array([0.003, -0.018, 0.5 * (clamp.vertices[:, 2].min() + clamp.vertices[:, 2].max())])
    pos = np.array([0.0, 0.0, -0.0039]) - rot @ opening
    coarse = DecompositionOptions(threshold=0.08, rounds=1, mcts_iterations=20, resolution=500, timeout_s=600)
    heights = {}
    for name, decomposition in [("pieces", coarse), ("hull", None)]:
        col = collision_geometry(
            clamp.vertices,
            clamp.faces,
            clamp.mass.volume,
            tolerance=0.1,
            primitives=(),
            decomposition=decomposition,
            measure_hausdorff=False,
        )
        assert col.kind == ("decomposition" if decomposition else "hull")
        bodies = [BodySpec(rod, rod_col, np.zeros(3), np.array([1.0, 0, 0, 0]), fixed=True), BodySpec(clamp, col, pos, matrix_to_quat(rot))]
        traj = simulate(load_model(write_mjcf_package(tmp_path / name, bodies, SimOptions(floor=False))), 1.5, fps=20)
        heights[name] = traj.pos[:, 1, 2]
    assert heights["pieces"].min() > -0.04  # it swings on the rod, its origin never more than 4 cm below it
    assert heights["hull"][-1] < -1.0  # one hull: pushed off the rod, in free fall


REPO = Path(__file__).resolve().parents[2]


def _children(pid: int) -> set[int]:
    """Child pids of a process (Linux /proc; every thread's list, since threads start children too)."""
    out: set[int] = set()
    for task in Path(f"/proc/{pid}/task").glob("*"):
        out |= {int(c) for c in (task / "children").read_text().split()}
    return out


@pytest.mark.skipif(not Path("/proc/self/task").exists(), reason="needs Linux /proc to see the child process")
def test_a_killed_parent_takes_its_coacd_child_with_it(tmp_path):
    """A SIGKILLed service must not leave CoACD running (it held the service's stdout and the CPU for minutes)."""
    script = (
        "import trimesh; from simulation.collision import decompose, DecompositionOptions\n"
        "m = trimesh.creation.torus(major_radius=0.05, minor_radius=0.015, major_sections=128, minor_sections=64)\n"
        "print('start', flush=True)\n"
        "decompose(m.vertices, m.faces, DecompositionOptions(threshold=0.001, timeout_s=600))\n"
    )
    parent = subprocess.Popen(
        [sys.executable, "-c", script], stdout=subprocess.PIPE, text=True, cwd=REPO, env={**os.environ, "PYTHONPATH": str(REPO)}
    )
    try:
        assert parent.stdout.readline().startswith("start")
        deadline = time.monotonic() + 60
        while not (child := _children(parent.pid)) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert child, "decompose started no child process"
        time.sleep(3)  # past the child's start-up (it exits by itself if its parent dies before handing it the job)
        parent.send_signal(signal.SIGKILL)
        parent.wait(10)
        deadline = time.monotonic() + 10
        while any(Path(f"/proc/{c}").exists() and "zombie" not in _state(c) for c in child) and time.monotonic() < deadline:
            time.sleep(0.1)
        assert not [c for c in child if Path(f"/proc/{c}").exists() and "zombie" not in _state(c)]
    finally:
        parent.kill()
        parent.wait()


def _state(pid: int) -> str:
    try:
        return next(line for line in Path(f"/proc/{pid}/status").read_text().splitlines() if line.startswith("State:")).lower()
    except (OSError, StopIteration):
        return "zombie"
