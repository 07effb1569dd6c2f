"""No traceback from any command on a truncated, empty or garbage file of every kind it reads (issue 16, 6),
and the twin-directory safety: a sha256 manifest every reader verifies, `--overwrite` only over a twin,
atomic directory exports."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from calibration.camera import Camera
from calibration.capture import FrameData, write_capture
from deploy.cli import main
from tests.simulation.twins import make_twin, skateboard

DAMAGE = {
    "truncated": lambda data: data[: len(data) // 2],
    "empty": lambda data: b"",
    "garbage": lambda data: bytes(np.random.default_rng(0).integers(0, 256, 300, dtype=np.uint8)),
}


@pytest.fixture(scope="module")
def world(tmp_path_factory):
    """A small twin, a capture with masks (its held-out views), a library folder and a calibration."""
    root = tmp_path_factory.mktemp("world")
    twin = make_twin(root / "twin", "skateboard", *skateboard(), n=500)
    rng = np.random.default_rng(1)
    cam = Camera.from_fov(1.0, 48, 36)
    mask = np.zeros((36, 48), bool)
    mask[10:26, 12:36] = True
    frames = [FrameData(f"v{i}", rng.integers(0, 255, (36, 48, 3), dtype=np.uint8), cam, f"cam{i}", mask=mask) for i in range(2)]
    capture = write_capture(root / "capture", frames).root
    lib = root / "lib"
    lib.mkdir()
    (lib / "library.json").write_text(json.dumps({"format": "cadsplat-library", "models": []}))
    from calibration.calibfile import CalibrationDoc, CalibrationStore

    CalibrationStore(root / "calibration.json").commit(CalibrationDoc({"cam0": cam, "cam1": cam}))
    return {"twin": Path(twin), "capture": capture, "lib": lib, "calibration": root / "calibration.json"}


# command (with {twin} {capture} {lib} {calibration} {out} placeholders) -> the files of each kind it reads
CASES = {
    "render": (
        ["render", "{twin}", "--orbit", "2", "--out", "{out}"],
        ["twin/twin.json", "twin/splats.ply", "twin/splats_canonical.npz", "twin/manifest.json"],
    ),
    "export-ply": (
        ["export", "{twin}", "--format", "ply", "--out", "{out}.ply"],
        ["twin/twin.json", "twin/splats.ply", "twin/manifest.json"],
    ),
    "export-mjcf": (["export", "{twin}", "--format", "mjcf", "--out", "{out}"], ["twin/twin.json", "twin/mesh_cad.glb", "twin/splats.ply"]),
    "evaluate": (
        ["evaluate", "{twin}", "--views", "{capture}", "--out", "{out}.json", "--refine-steps", "0"],
        ["twin/splats.ply", "capture/transforms.json", "capture/images/v0.png", "capture/masks/v1.png"],
    ),
    "reconstruct": (
        ["reconstruct", "{capture}", "--library", "{lib}", "--out", "{out}"],
        ["capture/transforms.json", "capture/images/v1.png", "lib/library.json"],
    ),
    "register": (["register", "{capture}", "--library", "{lib}", "--out", "{out}.json"], ["capture/transforms.json", "lib/library.json"]),
    "calibrate-check": (
        ["calibrate", "check", "{capture}", "--calibration", "{calibration}"],
        ["calibration.json", "capture/transforms.json"],
    ),
}


@pytest.mark.parametrize("damage", list(DAMAGE))
@pytest.mark.parametrize("command", list(CASES))
def test_no_traceback_on_a_damaged_file_of_every_kind(world, tmp_path, capsys, command, damage):
    args, files = CASES[command]
    for rel in files:
        kind, _, name = rel.partition("/")
        local = {}
        for key in ("twin", "capture", "lib"):
            local[key] = tmp_path / f"{key}-{rel.replace('/', '_')}"
            shutil.copytree(world[key], local[key])
        local["calibration"] = tmp_path / f"calibration-{rel.replace('/', '_')}.json"
        shutil.copy(world["calibration"], local["calibration"])
        target = local["calibration"] if rel == "calibration.json" else local[kind] / name
        target.write_bytes(DAMAGE[damage](target.read_bytes()))
        out = tmp_path / f"out-{rel.replace('/', '_')}"
        argv = [a.format(out=out, **local) for a in args]
        rc = main(argv)
        captured = capsys.readouterr()
        err = captured.err.strip()
        assert rc != 0, f"{command} exited 0 on a {damage} {rel}"
        assert "Traceback" not in captured.err + captured.out
        assert err and len(err.splitlines()) == 1, f"{command} on a {damage} {rel}: {err!r}"
        assert not out.exists() and not Path(f"{out}.json").exists() and not Path(f"{out}.ply").exists()
        assert not [p for p in tmp_path.iterdir() if p.name.startswith(".out-")], "a half-written output was left"


def test_a_damaged_twin_is_found_by_its_manifest(world, tmp_path, capsys):
    twin = tmp_path / "twin"
    shutil.copytree(world["twin"], twin)
    doc = json.loads((twin / "manifest.json").read_text())
    assert set(doc["sha256"]) >= {"twin.json", "splats.ply", "splats_canonical.npz"}
    data = bytearray((twin / "splats.ply").read_bytes())
    data[-5] ^= 0xFF  # one flipped bit: still a readable PLY, but not the twin that was written
    (twin / "splats.ply").write_bytes(bytes(data))
    assert main(["export", str(twin), "--format", "ply", "--out", str(tmp_path / "s.ply")]) != 0
    assert "splats.ply: sha256 does not match manifest.json" in capsys.readouterr().err


def test_overwrite_replaces_only_a_twin(world, tmp_path, capsys):
    """Issue 16 (5): `reconstruct --overwrite` onto a directory that is not a twin deleted its files."""
    precious = tmp_path / "thesis"
    precious.mkdir()
    (precious / "chapter1.tex").write_text("years of work")
    rc = main(["reconstruct", str(world["capture"]), "--library", str(world["lib"]), "--out", str(precious), "--overwrite"])
    assert rc != 0 and "is not a twin directory" in capsys.readouterr().err
    assert (precious / "chapter1.tex").read_text() == "years of work"
    from reconstruction.twin import TwinError, load_twin, save_twin

    twin = load_twin(world["twin"])
    with pytest.raises(TwinError, match="is not a twin directory"):
        save_twin(twin, precious, overwrite=True)
    assert (precious / "chapter1.tex").exists()
    copy = tmp_path / "copy"
    shutil.copytree(world["twin"], copy)
    save_twin(twin, copy, overwrite=True)  # a twin is replaced
    assert load_twin(copy).num_splats == twin.num_splats


def test_directory_exports_are_atomic_and_replace_only_their_format(world, tmp_path, capsys, monkeypatch):
    """Issue 16 (6): mjcf/colmap exports on a full disk left partial trees."""
    import errno
    import os

    import calibration.fileio as fio

    out = tmp_path / "colmap"
    real, calls = fio._durable_temp, {"n": 0}

    def full_after_one(path, data):
        calls["n"] += 1
        if calls["n"] == 2:
            raise OSError(errno.ENOSPC, os.strerror(errno.ENOSPC), str(path))
        return real(path, data)

    monkeypatch.setattr(fio, "_durable_temp", full_after_one)
    assert main(["export", str(world["twin"]), "--format", "colmap", "--out", str(out)]) != 0
    assert "No space left on device" in capsys.readouterr().err
    assert not out.exists() and not [p.name for p in tmp_path.iterdir()]  # nothing partial, no temp sibling
    monkeypatch.setattr(fio, "_durable_temp", real)
    assert main(["export", str(world["twin"]), "--format", "colmap", "--out", str(out)]) == 0
    assert main(["export", str(world["twin"]), "--format", "colmap", "--out", str(out)]) != 0  # exists: needs --overwrite
    assert main(["export", str(world["twin"]), "--format", "colmap", "--out", str(out), "--overwrite"]) == 0
    other = tmp_path / "notes"
    other.mkdir()
    (other / "a.txt").write_text("keep")
    assert main(["export", str(world["twin"]), "--format", "colmap", "--out", str(other), "--overwrite"]) != 0
    assert "holds no colmap export" in capsys.readouterr().err and (other / "a.txt").exists()


@pytest.mark.parametrize("command", ["register", "reconstruct", "evaluate", "calibrate-check"])
def test_a_capture_path_leading_outside_is_refused_in_one_sentence(world, tmp_path, capsys, command):
    """Issue 58 (3): a capture whose file_path leaves its folder (here by a symbolic link to a copy of the image) is refused."""
    local = {k: tmp_path / k for k in ("twin", "capture", "lib")}
    for key, path in local.items():
        shutil.copytree(world[key], path)
    outside = tmp_path / "outside.png"
    outside.write_bytes((local["capture"] / "images/v1.png").read_bytes())
    (local["capture"] / "images/v1.png").unlink()
    (local["capture"] / "images/v1.png").symlink_to(outside)
    out = tmp_path / "out"
    argv = [a.format(out=out, calibration=world["calibration"], **local) for a in CASES[command][0]]
    rc = main(argv)
    captured = capsys.readouterr()
    assert rc != 0 and "Traceback" not in captured.err + captured.out
    assert len(captured.err.strip().splitlines()) == 1 and "leads outside" in captured.err


def _frames0(doc: dict) -> dict:
    return doc["frames"][0]


# "<key>-<how>" -> what spoils the capture's transforms.json at that key (issue 58, 14)
MALFORMED = {
    "frames-not-objects": lambda d: d.update(frames=[1, 2]),
    "frames-an-object": lambda d: d.update(frames={"a": 1}),
    "cadsplat-a-list": lambda d: d.update(cadsplat=[]),
    "document-a-list": None,
    "file_path-a-number": lambda d: _frames0(d).update(file_path=7),
    "file_path-missing": lambda d: _frames0(d).pop("file_path"),
    "mask_path-a-list": lambda d: _frames0(d).update(mask_path=["masks/v0.png"]),
    "transform_matrix-missing": lambda d: _frames0(d).pop("transform_matrix"),
    "transform_matrix-strings": lambda d: _frames0(d).update(transform_matrix=[["a"] * 4] * 4),
    "transform_matrix-a-number": lambda d: _frames0(d).update(transform_matrix=3),
    "fl_x-a-string": lambda d: _frames0(d).update(fl_x="fifty"),
    "w-a-list": lambda d: _frames0(d).update(w=[48]),
    "h-negative": lambda d: _frames0(d).update(h=-36),
    "cx-a-bool": lambda d: _frames0(d).update(cx=True),
    "dist-a-string": lambda d: _frames0(d).update(dist="0 0 0 0"),
    "fl_y-shared-an-object": lambda d: d.update(fl_y={"v": 1}),
    "timestamp_ns-a-string": lambda d: _frames0(d).update(timestamp_ns="noon"),
    "camera_id-a-list": lambda d: _frames0(d).update(camera_id=[0]),
    "sha256-a-list": lambda d: d["cadsplat"].update(sha256=["images/v0.png"]),
    "sha256-entry-a-number": lambda d: d["cadsplat"]["sha256"].update({"images/v0.png": 5}),
    "background-a-string": lambda d: d["cadsplat"].update(background="background/"),
    "units-a-list": lambda d: d["cadsplat"].update(units=[]),
    "calibration_uncertainty-text": lambda d: d["cadsplat"].update(calibration_uncertainty={"rotation_deg": "small"}),
}
READERS = {
    "register": CASES["register"][0],
    "reconstruct": CASES["reconstruct"][0],
    "evaluate": CASES["evaluate"][0],
    "calibrate-check": CASES["calibrate-check"][0],
    "render": ["render", "{twin}", "--views", "{capture}", "--out", "{out}"],
}


@pytest.mark.parametrize("command", list(READERS))
@pytest.mark.parametrize("spoil", list(MALFORMED))
def test_wrong_json_types_in_transforms_json_are_one_sentence(world, tmp_path, capsys, command, spoil):
    """Issue 58 (14): every command that reads a capture names the file and the key of a wrong JSON type, in one line."""
    capture = tmp_path / "capture"
    shutil.copytree(world["capture"], capture)
    doc = json.loads((capture / "transforms.json").read_text())
    if MALFORMED[spoil] is None:
        doc = doc["frames"]
    else:
        MALFORMED[spoil](doc)
    (capture / "transforms.json").write_text(json.dumps(doc))
    out = tmp_path / "out"
    argv = [
        a.format(out=out, twin=world["twin"], capture=capture, lib=world["lib"], calibration=world["calibration"]) for a in READERS[command]
    ]
    rc = main(argv)
    captured = capsys.readouterr()
    err = captured.err.strip()
    assert rc != 0 and "Traceback" not in captured.err + captured.out
    assert len(err.splitlines()) == 1 and "transforms.json" in err and spoil.split("-")[0] in err, err
    assert not out.exists() and not Path(f"{out}.json").exists()


@pytest.mark.parametrize("spoil", ["frames-not-objects", "cadsplat-a-list", "file_path-a-number"])
def test_the_installed_entry_point_prints_one_line(world, tmp_path, spoil):
    """The issue's three documents through `python -m deploy.cli register`: exit 2, one line on stderr, no traceback."""
    import os
    import subprocess
    import sys

    capture = tmp_path / "capture"
    shutil.copytree(world["capture"], capture)
    doc = json.loads((capture / "transforms.json").read_text())
    MALFORMED[spoil](doc)
    (capture / "transforms.json").write_text(json.dumps(doc))
    repo = Path(__file__).resolve().parents[2]
    proc = subprocess.run(
        [sys.executable, "-m", "deploy.cli", "register", str(capture), "--library", str(world["lib"]), "--out", str(tmp_path / "r.json")],
        capture_output=True,
        text=True,
        cwd=repo,
        env={**os.environ, "PYTHONPATH": str(repo)},
        timeout=300,
        check=False,
    )
    assert proc.returncode != 0 and "Traceback" not in proc.stderr + proc.stdout
    assert len(proc.stderr.strip().splitlines()) == 1 and "transforms.json" in proc.stderr, proc.stderr


@pytest.mark.parametrize("command", ["register", "reconstruct", "evaluate"])
def test_a_png_bomb_in_a_capture_is_refused_in_one_sentence(world, tmp_path, capsys, monkeypatch, request, command):
    """Issue 58 (9): a capture whose image declares 12000x12000 (its manifest updated to match) is refused before decoding."""
    import cv2

    from calibration.fileio import sha256_file
    from tests.calibration.test_capture import png_bomb

    capture = tmp_path / "capture"
    shutil.copytree(world["capture"], capture)
    png_bomb(capture / "images/v1.png", 12000, 12000)
    doc = json.loads((capture / "transforms.json").read_text())
    doc["cadsplat"]["sha256"]["images/v1.png"] = sha256_file(capture / "images/v1.png")
    (capture / "transforms.json").write_text(json.dumps(doc))
    bomb, real = (capture / "images/v1.png").read_bytes(), cv2.imdecode

    def imdecode(data, flags):
        assert bytes(data) != bomb, "the bomb was decoded"
        return real(data, flags)

    monkeypatch.setattr(cv2, "imdecode", imdecode)
    out = tmp_path / "out"
    lib = request.getfixturevalue("library") if command == "register" else world["lib"]  # register reads the library before the images
    argv = [a.format(out=out, twin=world["twin"], capture=capture, lib=lib, calibration=world["calibration"]) for a in READERS[command]]
    rc = main(argv)
    captured = capsys.readouterr()
    assert rc != 0 and "Traceback" not in captured.err + captured.out
    assert len(captured.err.strip().splitlines()) == 1 and "v1.png: image declares 12000x12000 pixels" in captured.err, captured.err
