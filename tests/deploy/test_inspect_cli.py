"""`cadsplat inspect`: the verdict on stdout, the exit code a PLC reads, and the report files."""

import csv
import json
import re

import numpy as np
import pytest
import trimesh

from calibration.camera import look_at_c2w
from calibration.fileio import sha256_file
from calibration.sim3 import Sim3
from deploy.cli import main
from reconstruction.mesh_io import MeshParts
from reconstruction.splats import init_splats
from reconstruction.twin import Twin, TwinCamera, save_twin


def two_parts() -> MeshParts:
    """A ball (radius 40 mm) with a peg beside it: two named parts, metres."""
    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.04)
    peg = trimesh.creation.cylinder(radius=0.01, height=0.06, sections=24).apply_translation([0.07, 0.0, 0.0])
    v = np.concatenate([ball.vertices, peg.vertices])
    f = np.concatenate([ball.faces, peg.faces + len(ball.vertices)])
    part = np.concatenate([np.zeros(len(ball.faces), np.int64), np.ones(len(peg.faces), np.int64)])
    return MeshParts(v, f, part, ["ball", "peg"])


def dented(parts: MeshParts, centre, depth_m: float, radius_m: float) -> MeshParts:
    """`parts` with the ball's vertices near `centre` pushed towards the ball's centre by up to `depth_m`."""
    v = parts.vertices.copy()
    ball = np.unique(parts.faces[parts.face_part == 0])
    d = np.linalg.norm(v[ball] - centre, axis=1)
    push = depth_m * np.clip(1 - d / radius_m, 0, 1)
    v[ball] -= push[:, None] * v[ball] / np.linalg.norm(v[ball], axis=1, keepdims=True)
    return MeshParts(v, parts.faces, parts.face_part, parts.part_names)


def make_twin(root, name, deformed: MeshParts | None, elevations=(-35.0, 35.0)):
    parts = two_parts()
    s = init_splats(parts.vertices, parts.faces, 2000, sh_degree=0, face_part=parts.face_part, seed=0)
    cams = []
    # 640x480 at 0.4 m: a pixel is about 0.6 mm at the ball, fine enough for a 1 mm tolerance beyond the uncertainty.
    k = np.array([[600.0, 0, 320], [0, 600.0, 240], [0, 0, 1]])
    centre = np.array([0.02, 0.0, 0.0])
    for el in np.radians(elevations):
        for az in np.linspace(0, 2 * np.pi, 6, endpoint=False):
            eye = centre + 0.4 * np.array([np.cos(el) * np.cos(az), np.cos(el) * np.sin(az), np.sin(el)])
            cams.append(TwinCamera(f"images/c{len(cams):02d}.png", f"c{len(cams):02d}", k, 640, 480, look_at_c2w(eye, centre)))
    twin = Twin(
        model_id="ball_and_peg",
        sim3_rig_to_object_init=Sim3.identity(),
        sim3_rig_to_object=Sim3.identity(),
        cameras=cams,
        preset="test",
        choices={},
        timings_s={},
        losses={},
        gaussians=s.gaussians,
        means_canonical=s.means,
        face_index=s.face_index,
        barycentrics=s.barycentrics,
        part_label=s.part_label,
        part_names=parts.part_names,
    )
    return save_twin(twin, root / name, mesh_cad=parts, mesh_deformed=deformed)


def test_pass_writes_the_whole_report(tmp_path, capsys):
    twin = make_twin(tmp_path, "good", two_parts())
    out = tmp_path / "report"
    assert main(["inspect", str(twin), "--out", str(out), "--turntable", "2", "--tolerance", "2"]) == 0
    assert re.fullmatch(r"PASS max 0\.0 \+-\d\.\d\d mm \(tolerance 2 mm\)", capsys.readouterr().out.strip())
    doc = json.loads((out / "inspection.json").read_text())
    assert doc["verdict"]["status"] == "PASS" and sorted(p["name"] for p in doc["parts"]) == ["ball", "peg"]
    for name, digest in doc["sha256"].items():
        assert sha256_file(out / name) == digest
    assert {"views/c00.png", "turntable/orbit_000.png", "legend.png", "deviation.ply", "deviation.glb"} <= set(doc["sha256"])
    rows = list(csv.DictReader((out / "parts" / "ball.csv").open()))
    assert len(rows) == 642 and {r["status"] for r in rows} <= {"ok", "unseen"}
    # Every seen vertex carries its uncertainty, in the CSV, the PLY and the JSON; unseen ones none.
    seen = [r for r in rows if r["status"] == "ok"]
    assert seen and all(0 < float(r["uncertainty_mm"]) < 2.0 and float(r["pixel_mm"]) > 0 for r in seen)
    assert all(r["uncertainty_mm"] == "" for r in rows if r["status"] == "unseen")
    from plyfile import PlyData

    ply = PlyData.read(str(out / "deviation.ply"))["vertex"]
    assert np.isfinite(ply["uncertainty_mm"]).sum() >= len(seen)
    assert 0 < doc["surface"]["uncertainty_median_mm"] < 2.0 and doc["verdict"]["uncertainty_mm"] > 0
    assert doc["verdict"]["straddling"] == [] and doc["surface"]["uncertain_pct"] == 0.0
    # The map is read after its best-fit alignment, and says which motion it took out.
    assert doc["surface"]["alignment"]["kind"] == "rigid" and len(doc["surface"]["alignment"]["rotation_deg"]) == 3
    assert "best-fit alignment" in doc["settings"]["deviation"]
    # Inspecting again replaces the report; a directory that is not a report is never replaced.
    assert main(["inspect", str(twin), "--out", str(out), "--turntable", "0", "--tolerance", "2"]) == 0
    assert "turntable/orbit_000.png" not in json.loads((out / "inspection.json").read_text())["sha256"]
    (tmp_path / "precious").mkdir()
    assert main(["inspect", str(twin), "--out", str(tmp_path / "precious")]) == 2
    assert "not an earlier inspection" in capsys.readouterr().err


def test_a_dent_fails_at_its_place_and_passes_a_looser_tolerance(tmp_path, capsys):
    centre = np.array([0.0, -0.04, 0.0])  # on the ball's side, seen by the ring
    twin = make_twin(tmp_path, "dent", dented(two_parts(), centre, 0.004, 0.015))
    assert main(["inspect", str(twin), "--tolerance", "1.5", "--turntable", "0"]) == 1
    line = capsys.readouterr().out.strip()
    # Read after the part's least-squares best fit, which the dent pulls towards itself by its share of the area.
    assert re.match(r"FAIL part 'ball' -3\.[89] \+-\d\.\d\d mm at \(", line) and "% of the surface out of tolerance" in line
    doc = json.loads((twin / "inspection" / "inspection.json").read_text())
    at = np.array(doc["verdict"]["at_mm"])
    assert np.linalg.norm(at - centre * 1000) < 3.0
    assert main(["inspect", str(twin), "--tolerance", "6", "--turntable", "0"]) == 0


def test_a_dent_within_its_uncertainty_of_the_tolerance_is_uncertain_and_named(tmp_path, capsys):
    centre = np.array([0.0, -0.04, 0.0])
    twin = make_twin(tmp_path, "dent", dented(two_parts(), centre, 0.004, 0.015))
    assert main(["inspect", str(twin), "--tolerance", "3.9", "--turntable", "0"]) == 4
    line = capsys.readouterr().out.strip()
    assert line.startswith("UNCERTAIN ") and "lie within their uncertainty of the 3.9 mm tolerance: vertex " in line
    doc = json.loads((twin / "inspection" / "inspection.json").read_text())
    named = doc["verdict"]["straddling"]
    assert doc["verdict"]["reason"] == "near tolerance" and named and named[0]["part"] == "ball"
    assert np.linalg.norm(np.array(named[0]["at_mm"]) - centre * 1000) < 3.0
    assert all(abs(abs(v["deviation_mm"]) - 3.9) <= v["uncertainty_mm"] for v in named)
    rows = list(csv.DictReader((twin / "inspection" / "parts" / "ball.csv").open()))
    assert {int(r["vertex"]) for r in rows if r["status"] == "uncertain"} == {v["vertex"] for v in named}


def test_unseen_surface_makes_the_verdict_uncertain_never_a_pass(tmp_path, capsys):
    # Cameras only above: the underside is unseen, and a dent there must not pass as in tolerance.
    twin = make_twin(tmp_path, "top", dented(two_parts(), np.array([0.0, 0.0, -0.04]), 0.003, 0.012), elevations=(50.0,))
    assert main(["inspect", str(twin), "--turntable", "0", "--max-unseen", "20"]) == 3
    line = capsys.readouterr().out.strip()
    assert line.startswith("UNCERTAIN") and "% of the surface unseen" in line and "% in no camera's view)" in line
    doc = json.loads((twin / "inspection" / "inspection.json").read_text())
    assert doc["verdict"]["unseen_pct"] > 20
    # The underside is the rig's coverage: most of what is unseen is in no camera's view at all.
    assert doc["verdict"]["out_of_view_pct"] == doc["surface"]["out_of_view_pct"] > 0.5 * doc["verdict"]["unseen_pct"]
    rows = list(csv.DictReader((twin / "inspection" / "parts" / "ball.csv").open()))
    deep = [r for r in rows if r["deviation_mm"] and float(r["deviation_mm"]) < -1.0]
    assert deep and all(r["status"] == "unseen" and r["in_view"] == "0" for r in deep)


@pytest.mark.parametrize("args, message", [(["--tolerance", "0"], "--tolerance"), (["--max-unseen", "120"], "--max-unseen")])
def test_bad_arguments_exit_2(tmp_path, capsys, args, message):
    twin = make_twin(tmp_path, "t", two_parts())
    assert main(["inspect", str(twin), *args]) == 2
    assert message in capsys.readouterr().err


def test_a_twin_without_its_meshes_cannot_be_inspected(tmp_path, capsys):
    twin = make_twin(tmp_path, "nomesh", None)
    assert main(["inspect", str(twin)]) == 2
    err = capsys.readouterr().err
    assert "mesh_deformed.glb" in err and "Traceback" not in err
    assert main(["inspect", str(tmp_path / "nothing")]) == 2


def test_the_job_record_and_the_history_carry_the_verdict_per_part_id(tmp_path, capsys):
    from deploy.jobs import JobStore
    from deploy.steps import PipelineConfig, inspect_step, inspection_history

    work = tmp_path / "jobs" / "cap-0001"
    make_twin(work, "twin", dented(two_parts(), np.array([0.0, -0.04, 0.0]), 0.004, 0.015))
    record = inspect_step(work, PipelineConfig("unused-library", inspection_tolerance_mm=1.0))
    assert record["status"] == "FAIL" and record["exit_code"] == 1 and record["part"] == "ball"
    assert record["line"].startswith("FAIL part 'ball' -3.8 +-") and (work / "inspection" / "inspection.json").exists()
    # A second call (a resumed job) reads the report instead of redoing it.
    assert inspect_step(work, PipelineConfig("unused-library", inspection_tolerance_mm=5.0)) == record

    store = JobStore(tmp_path / "jobs.sqlite")
    outputs = [
        ("cap-0001", "ball_and_peg", record),
        ("cap-0002", "ball_and_peg", {**record, "status": "PASS", "line": "PASS max 0.3 mm (tolerance 1 mm)"}),
        ("cap-0003", "bracket", {**record, "status": "UNCERTAIN", "line": "UNCERTAIN 40 % of the surface unseen"}),
    ]
    for i, (capture, model, insp) in enumerate(outputs, 1):
        store.add(capture, tmp_path / capture)
        store.claim_next()
        store.finish_step(i, "register", {"model_id": model, "score": 0.9})
        store.finish_step(i, "reconstruct", {"model_id": model, "twin": "", "fit_iou": 0.9, "inspection": insp})
    store.add("cap-0004", tmp_path / "cap-0004")  # not reconstructed yet: not in the history
    history = inspection_history(store.jobs())
    assert {k: [r["status"] for r in v] for k, v in history.items()} == {"ball_and_peg": ["FAIL", "PASS"], "bracket": ["UNCERTAIN"]}
    assert list(inspection_history(store.jobs(), "bracket")) == ["bracket"]
    assert main(["service", "history", "--work", str(tmp_path), "--part", "ball_and_peg"]) == 0
    out = capsys.readouterr().out
    assert "ball_and_peg: 2 inspected, 1 PASS, 1 FAIL, 0 UNCERTAIN" in out and "cap-0001" in out and "bracket" not in out
    assert main(["service", "status", "--work", str(tmp_path)]) == 0
    assert "UNCERTAIN 40 % of the surface unseen" in capsys.readouterr().out


def test_the_kiosk_shows_the_part_verdict():
    from deploy.kiosk import render_work
    from deploy.kiosk_state import ApplianceState, Verdict

    line = "FAIL part 'ball' -2.0 mm at (0.0, -38.0, 0.0) mm"
    screen = render_work(
        ApplianceState(last_twin=Verdict("cap-0001", "ball_and_peg", 0.9, 0.95, "Good", "Twin is ready to use.", "", line))
    )
    assert f"PART {line}" in screen and max(len(s) for s in screen.splitlines()) <= 78
    assert "PART" not in render_work(ApplianceState(last_twin=Verdict("c", "m", 0.9, 0.95, "Good", "ok")))


def test_rig_toml_turns_inspection_on():
    from rig.config import ConfigError, parse_config

    cams = {"cameras": [{"id": "cam0", "driver": "pattern"}]}
    assert parse_config(cams).inspection is None
    cfg = parse_config({**cams, "inspection": {"tolerance_mm": 0.5}})
    assert (cfg.inspection.tolerance_mm, cfg.inspection.max_unseen_pct) == (0.5, None)
    assert parse_config({**cams, "inspection": {"tolerance_mm": 1, "max_unseen_pct": 30}}).inspection.max_unseen_pct == 30.0
    for bad, message in [
        ({}, "inspection.tolerance_mm is required"),
        ({"tolerance_mm": 0}, "inspection.tolerance_mm must be"),
        ({"tolerance_mm": 1, "max_unseen_pct": 120}, "inspection.max_unseen_pct"),
        ({"tolerance_mm": 1, "tol": 2}, "unknown key"),
    ]:
        with pytest.raises(ConfigError, match=message):
            parse_config({**cams, "inspection": bad})


@pytest.mark.slow
def test_a_synthetic_dent_is_never_passed_and_the_undented_part_never_failed(tmp_path):
    """Issue 18's acceptance, as benchmarks/results/dent_cpu.md measures it, under issue 60's verdict: a 2 mm dent read
    at about -1.6 mm is never passed at a 1.5 mm tolerance (FAIL, or UNCERTAIN naming it when its uncertainty reaches
    the tolerance); the undented part, read at about 1 mm +-0.7, is never failed (PASS, or UNCERTAIN near the tolerance)."""
    from benchmarks.bench_dent import run
    from deploy.inspection_report import DEFAULT_MAX_UNSEEN_PCT

    res = run(
        tmp_path, preset="cpu", depth_mm=2.0, radius_mm=8.0, tolerance_mm=1.5, max_unseen_pct=DEFAULT_MAX_UNSEEN_PCT, log=lambda *_: None
    )
    assert res["nominal"]["exit_code"] in (0, 4), res["nominal"]["line"]
    assert res["dented"]["exit_code"] in (1, 4) and res["dented"]["distance_to_dent_mm"] < 8.0, res["dented"]["line"]


def test_the_benchmark_dent_pushes_in_by_its_depth_and_keeps_the_obj_texture():
    from benchmarks.bench_dent import dent, read_obj_positions, write_obj_positions

    ball = trimesh.creation.icosphere(subdivisions=3, radius=0.04)
    text = (
        "mtllib textured.mtl\n"
        + "".join(f"v {x} {y} {z}\nvt 0.5 0.5\n" for x, y, z in ball.vertices)
        + "vn 0 0 1\n"
        + "".join(f"f {a + 1}/{a + 1}/1 {b + 1}/{b + 1}/1 {c + 1}/{c + 1}/1\n" for a, b, c in ball.faces)
    )
    v, f = read_obj_positions(text)
    np.testing.assert_allclose(v, ball.vertices)
    top = int(np.argmax(v[:, 2]))
    moved = dent(v, f, v[top], 0.002, 0.01)
    r = np.linalg.norm(moved, axis=1)
    assert abs(r[top] - 0.038) < 1e-6 and np.all(r <= 0.04 + 1e-9)
    far = np.linalg.norm(v - v[top], axis=1) >= 0.01
    np.testing.assert_allclose(moved[far], v[far])
    out = write_obj_positions(text, moved)
    assert "vn " not in out and f"f {f[0, 0] + 1}/{f[0, 0] + 1} " in out and "vt 0.5 0.5" in out and "mtllib textured.mtl" in out
    np.testing.assert_allclose(read_obj_positions(out)[0], moved, atol=1e-7)


def test_the_capture_masks_refine_the_map_and_a_capture_without_the_twins_views_is_refused(tmp_path, capsys):
    import cv2

    from reconstruction.inspect import rasterize_mesh

    twin = make_twin(tmp_path, "good", two_parts())
    # The capture the twin was made from: masks of the part as it is, at the cameras' own resolution.
    capture = tmp_path / "capture"
    (capture / "masks").mkdir(parents=True)
    (capture / "images").mkdir()
    frames = []
    from reconstruction.twin import load_twin

    parts = two_parts()
    for cam in load_twin(twin).cameras:
        mask = rasterize_mesh(parts.vertices, parts.faces, cam.camera)[1] >= 0
        name = cam.file_path.split("/")[-1]
        cv2.imwrite(str(capture / "masks" / name), (255 * mask).astype(np.uint8))
        cv2.imwrite(str(capture / "images" / name), np.full((cam.height, cam.width, 3), 128, np.uint8))
        gl = cam.c2w_object_opencv @ np.diag([1.0, -1.0, -1.0, 1.0])
        frames.append(
            {
                "file_path": cam.file_path,
                "mask_path": f"masks/{name}",
                "transform_matrix": gl.tolist(),
                "camera_id": cam.camera_id,
                "fl_x": cam.K[0, 0],
                "fl_y": cam.K[1, 1],
                "cx": cam.K[0, 2],
                "cy": cam.K[1, 2],
                "w": cam.width,
                "h": cam.height,
            }
        )
    (capture / "transforms.json").write_text(json.dumps({"camera_model": "OPENCV", "frames": frames, "cadsplat": {"units": "m"}}))
    out = tmp_path / "report"
    assert main(["inspect", str(twin), "--out", str(out), "--turntable", "0", "--tolerance", "2", "--capture", str(capture)]) == 0
    doc = json.loads((out / "inspection.json").read_text())
    assert doc["settings"]["refined_by_masks"] and doc["verdict"]["max_abs_mm"] < 0.3
    frames.pop()
    (capture / "transforms.json").write_text(json.dumps({"camera_model": "OPENCV", "frames": frames, "cadsplat": {"units": "m"}}))
    assert main(["inspect", str(twin), "--out", str(out), "--turntable", "0", "--capture", str(capture)]) == 2
    assert "holds no view images/c11.png" in capsys.readouterr().err
