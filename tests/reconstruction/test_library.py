"""CAD library: units, bad meshes reported and skipped, incremental builds, library.json, memory-mapped index."""

from __future__ import annotations

import json

import numpy as np
import pytest
import trimesh

from reconstruction.library import LibraryError, build_library, load_library
from reconstruction.silhouette_index import GridSpec
from tests.conftest import require_shared

GRID = GridSpec(n_dirs=40, canvas=32, render_px=96)


def quiet(lines):
    return lines.append


def test_units_frames_and_library_json(tmp_path):
    src = tmp_path / "meshes"
    (src / "sub").mkdir(parents=True)
    box = trimesh.creation.box([0.1, 0.05, 0.02])
    box.apply_translation([0.3, 0.0, 0.0])  # off-centre: the library must not re-centre it
    box.copy().apply_scale(1000).export(src / "plate.unitsmm.stl")
    box.copy().apply_scale(100).export(src / "sub" / "bar.stl")
    (src / "sub" / "units.json").write_text(json.dumps({"bar.stl": "cm"}))
    box.export(src / "block.obj")
    lines = []
    lib = build_library(src, tmp_path / "lib", unit="m", grid=GRID, workers=1, progress=False, log=quiet(lines))
    assert sorted(lib.ids) == ["block", "plate.unitsmm", "sub/bar"]
    assert {m.id: m.unit for m in lib.models} == {"block": "m", "plate.unitsmm": "mm", "sub/bar": "cm"}
    for mid in lib.ids:
        mesh = lib.load_mesh(mid)
        assert np.allclose(mesh.bounds, box.bounds, atol=1e-6)
        v, f = lib.scoring_mesh(mid)
        assert np.allclose(v.min(0), box.bounds[0], atol=1e-6)
    doc = json.loads((tmp_path / "lib" / "library.json").read_text())
    entry = next(m for m in doc["models"] if m["id"] == "sub/bar")
    assert entry["unit"] == "cm" and len(entry["sha256"]) == 64 and entry["components"] == 1
    assert (tmp_path / "lib" / entry["file"]).read_bytes() == (src / "sub" / "bar.stl").read_bytes()
    idx = lib.index
    assert len(idx) == 3 * GRID.n_dirs and isinstance(idx.words, np.memmap)
    assert np.all(np.diff(idx.counts) >= 0)
    assert lines == []


def test_bad_meshes_are_reported_and_skipped(tmp_path):
    src = tmp_path / "meshes"
    src.mkdir()
    trimesh.creation.box([0.1, 0.1, 0.1]).export(src / "good.stl")
    (src / "empty.stl").write_bytes(b"")
    (src / "garbage.obj").write_text("this is not a mesh\n")
    (src / "flat.obj").write_text("v 0 0 0\nv 1 0 0\nv 2 0 0\nf 1 2 3\n")  # zero area
    (src / "nan.obj").write_text("v 0 0 0\nv nan 0 0\nv 0 1 0\nf 1 2 3\n")
    lines = []
    lib = build_library(src, tmp_path / "lib", grid=GRID, workers=1, progress=False, log=quiet(lines))
    assert lib.ids == ["good"]
    assert len(lines) == 4 and all(line.startswith("skipped ") and "\n" not in line for line in lines)
    assert {s["file"].split("/")[-1] for s in lib.skipped} == {"empty.stl", "garbage.obj", "flat.obj", "nan.obj"}


def test_adding_a_model_does_not_rebuild_the_others(tmp_path):
    src = tmp_path / "meshes"
    src.mkdir()
    trimesh.creation.box([0.1, 0.1, 0.1]).export(src / "a.stl")
    lib = build_library(src, tmp_path / "lib", grid=GRID, workers=1, progress=False, log=lambda s: None)
    shard = lib.entry("a").shard
    stamp = shard.stat().st_mtime_ns
    trimesh.creation.cylinder(0.02, 0.1).export(src / "b.stl")
    lib2 = build_library(src, tmp_path / "lib", grid=GRID, workers=1, progress=False, log=lambda s: None)
    assert lib2.ids == ["a", "b"] and lib2.entry("a").shard.stat().st_mtime_ns == stamp
    assert len(lib2.index) == 2 * GRID.n_dirs
    (src / "a.stl").unlink()
    lib3 = build_library(src, tmp_path / "lib", grid=GRID, workers=1, progress=False, log=lambda s: None)
    assert lib3.ids == ["b"] and not shard.exists()


def test_parallel_build_matches_serial(tmp_path):
    src = tmp_path / "meshes"
    src.mkdir()
    for i in range(3):
        trimesh.creation.box([0.1, 0.05 + 0.02 * i, 0.03]).export(src / f"m{i}.stl")
    a = build_library(src, tmp_path / "a", grid=GRID, workers=1, progress=False, log=lambda s: None)
    b = build_library(src, tmp_path / "b", grid=GRID, workers=2, progress=False, log=lambda s: None)
    assert np.array_equal(np.asarray(a.index.words), np.asarray(b.index.words))


def test_shared_cad_parts_mixed_units(tmp_path):
    parts = require_shared("cad", "parts")
    lines = []
    lib = build_library(parts, tmp_path / "lib", unit="in", grid=GRID, workers=2, progress=False, log=quiet(lines))
    assert lib.entry("counter.unitsmm").unit == "mm"
    assert max(lib.entry("counter.unitsmm").extent_m) == pytest.approx(0.3048, rel=1e-3)
    # Files in millimetres read as inches come out metres-to-a-hundred-metres across: the build says so.
    assert any("large_block" in w for w in lib.warnings)
    assert "featuretype" in lib.ids  # the STL; the STEP twin is reported, not read
    assert any(s["file"].endswith("featuretype.STEP") and "STEP" in s["reason"] for s in lib.skipped)


def test_missing_or_bad_library(tmp_path):
    with pytest.raises(LibraryError, match="no library.json"):
        load_library(tmp_path)
    with pytest.raises(LibraryError, match="no mesh files"):
        build_library(tmp_path, tmp_path / "lib", progress=False)
    with pytest.raises(LibraryError, match="unit 'ft'"):
        build_library(tmp_path, tmp_path / "lib", unit="ft", progress=False)


def _one_box_library(tmp_path):
    src = tmp_path / "meshes"
    src.mkdir()
    trimesh.creation.box([0.1, 0.05, 0.02]).export(src / "plate.stl")
    return build_library(src, tmp_path / "lib", grid=GRID, workers=1, progress=False, log=lambda s: None).root


@pytest.mark.parametrize("how", ["absolute", "dotdot", "symlink", "shard-dotdot"])
def test_library_paths_stay_inside_the_library(tmp_path, how):
    """Issue 58 (3): a library's mesh `file` (and shard) is read only from inside the library."""
    root = _one_box_library(tmp_path)
    doc = json.loads((root / "library.json").read_text())
    outside = tmp_path / "elsewhere.stl"
    outside.write_bytes((root / doc["models"][0]["file"]).read_bytes())  # same bytes: only containment refuses it
    if how == "absolute":
        doc["models"][0]["file"] = str(outside)
    elif how == "dotdot":
        doc["models"][0]["file"] = "../elsewhere.stl"
    elif how == "shard-dotdot":
        (tmp_path / "elsewhere.npz").write_bytes((root / doc["models"][0]["shard"]).read_bytes())
        doc["models"][0]["shard"] = "../elsewhere.npz"
    else:
        (root / doc["models"][0]["file"]).unlink()
        (root / doc["models"][0]["file"]).symlink_to(outside)
    (root / "library.json").write_text(json.dumps(doc))
    with pytest.raises(LibraryError, match=r"models\[0\]\.(file|shard) .*(leads outside|is absolute)") as err:
        load_library(root)
    assert "\n" not in str(err.value)


def test_a_replaced_mesh_is_refused_on_load_naming_its_model(tmp_path, monkeypatch):
    """Issue 58 (3): the mesh must be the one the library was built from (its recorded sha256), checked once per load."""
    from reconstruction import library

    root = _one_box_library(tmp_path)
    hashed = []
    real = library.sha256_file
    monkeypatch.setattr(library, "sha256_file", lambda p: hashed.append(p) or real(p))
    lib = load_library(root)
    lib.load_mesh("plate")
    lib.load_mesh("plate")
    assert len(hashed) == 1  # at load, not at each use
    trimesh.creation.box([0.2, 0.05, 0.02]).export(root / "meshes" / "plate.stl")
    with pytest.raises(LibraryError, match=r"mesh of model plate is not the one the library was built from") as err:
        load_library(root)
    assert "\n" not in str(err.value)


@pytest.mark.parametrize(
    "models", [[1, 2], [{"id": "plate"}], [{"id": "p", "file": 7, "unit": "m", "sha256": "0", "shard": "x", "extent_m": [1, 1, 1]}]]
)
def test_malformed_library_json_is_one_sentence(tmp_path, models):
    root = _one_box_library(tmp_path)
    doc = json.loads((root / "library.json").read_text())
    doc["models"] = models
    (root / "library.json").write_text(json.dumps(doc))
    with pytest.raises(LibraryError, match=r"library\.json: models\[0\]"):
        load_library(root)
