"""The CAD library: a directory of meshes (metres, model frame), `library.json`, and the silhouette index.

Layout of LIB:
    library.json          models (id, file, unit, sha256, part names, ...), skipped files, grid, sha256s
    meshes/<id>.<ext>      the source mesh files, byte-for-byte (their own units; `unit` converts)
    index/<key>.npz        one shard per model: packed silhouettes, view geometry, scoring mesh
    index/*.npy, ids.json  the consolidated, count-sorted index (memory-mapped at query time)

A model's id is its path under MESH_DIR without the extension. Units: the `--unit` default, or a
`.units<u>` tag in the file name (`counter.unitsmm.stl`), or a `units.json` beside the file mapping
file names to units (`reconstruction.mesh_io.unit_of`). Files are read, welded, by
`reconstruction.mesh_io.read_mesh_parts`. Meshes are never re-centred or re-oriented: the twin
lives in the CAD frame.
"""

from __future__ import annotations

import json
import multiprocessing
import os
from concurrent.futures import ProcessPoolExecutor
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np
import trimesh

from calibration.fileio import atomic_write_bytes, atomic_write_json, sha256_file
from calibration.guard import PathOutside, contained
from calibration.units import UNIT_TO_M
from reconstruction.mesh_io import MeshError, read_mesh_parts, unit_of
from reconstruction.silhouette_index import (
    GridSpec,
    SilhouetteIndex,
    consolidate,
    model_frame,
    open_index,
    read_shard,
    render_model_views,
    shard_key,
    write_shard,
)

MESH_EXTS = (".obj", ".stl", ".ply", ".glb")
CAD_ONLY_EXTS = (".step", ".stp")
LIBRARY_JSON = "library.json"
FORMAT = "cadsplat-library/1"
# Faces kept in the mesh that registration renders thousands of times; at rig resolutions a
# decimation this fine leaves the silhouettes as the full mesh's (benchmarks/results/registration.md).
SCORING_FACES = 3000
# Outside this size range (largest extent, metres) a unit is probably wrong; the build says so.
PLAUSIBLE_EXTENT_M = (0.002, 5.0)


class LibraryError(ValueError):
    """A library directory or mesh folder that cannot be used as it is."""


@dataclass(frozen=True)
class ModelEntry:
    id: str
    mesh_path: Path
    unit: str
    sha256: str
    part_names: tuple[str, ...]
    components: int
    extent_m: tuple[float, float, float]
    shard: Path

    @property
    def scale_to_m(self) -> float:
        return UNIT_TO_M[self.unit]


@dataclass
class Library:
    root: Path
    models: list[ModelEntry]
    grid: GridSpec
    skipped: list[dict] = field(default_factory=list)
    warnings: list[str] = field(default_factory=list)
    _index: SilhouetteIndex | None = None

    @property
    def ids(self) -> list[str]:
        return [m.id for m in self.models]

    def entry(self, model_id: str) -> ModelEntry:
        for m in self.models:
            if m.id == model_id:
                return m
        raise KeyError(f"model {model_id!r} is not in the library at {self.root}")

    @property
    def index(self) -> SilhouetteIndex:
        if self._index is None:
            self._index = open_index(self.root / "index")
        return self._index

    def load_mesh(self, model_id: str) -> trimesh.Trimesh:
        """The full mesh in metres, in the model's own frame."""
        e = self.entry(model_id)
        mesh, _ = load_mesh_file(e.mesh_path)
        mesh.apply_scale(e.scale_to_m)
        return mesh

    def scoring_mesh(self, model_id: str) -> tuple[np.ndarray, np.ndarray]:
        """Decimated mesh (vertices [N, 3] metres, faces [F, 3]) used to score registration hypotheses."""
        shard = read_shard(self.entry(model_id).shard)
        return shard["score_vertices"], shard["score_faces"]


def load_mesh_file(path: Path) -> tuple[trimesh.Trimesh, tuple[str, ...]]:
    """The file's parts as one welded triangle mesh, and their names (sorted; empty for a single part)."""
    parts = read_mesh_parts(path, weld=True)
    names = tuple(sorted(parts.part_names)) if len(parts.part_names) > 1 else ()
    return trimesh.Trimesh(parts.vertices, parts.faces, process=False), names


def check_mesh(mesh: trimesh.Trimesh, path: Path) -> None:
    """Raise MeshError with the reason when `mesh` (read from `path`) cannot be a model."""
    v = np.asarray(mesh.vertices)
    if len(mesh.faces) == 0 or len(v) == 0:
        raise MeshError(path, "is empty (no faces)")
    if not np.all(np.isfinite(v)):
        raise MeshError(path, "has non-finite vertex coordinates")
    extent = float(np.ptp(v, axis=0).max())
    if extent <= 0 or mesh.area <= 1e-12 * max(extent, 1e-300) ** 2:
        raise MeshError(path, "has zero surface area")


def _decimate(vertices: np.ndarray, faces: np.ndarray, target: int) -> tuple[np.ndarray, np.ndarray]:
    if len(faces) <= target:
        return vertices, faces
    import fast_simplification

    v, f = fast_simplification.simplify(vertices.astype(np.float32), faces.astype(np.int32), target_reduction=1.0 - target / len(faces))
    return v.astype(np.float64), f.astype(np.int64)


def _build_model(job: tuple[str, str, float, dict, str]) -> dict:
    """Worker: load, check, render one model's shard. Returns a report dict (never raises for a bad mesh)."""
    model_id, path, scale, grid_d, shard_path = job
    try:
        mesh, parts = load_mesh_file(Path(path))
        check_mesh(mesh, Path(path))
        v = np.asarray(mesh.vertices, np.float64) * scale
        f = np.asarray(mesh.faces, np.int64)
        components = len(trimesh.graph.connected_components(mesh.face_adjacency, nodes=np.arange(len(f)), min_len=1))
        words, geom = render_model_views(v, f, GridSpec(**grid_d))
        center, radius = model_frame(v)
        sv, sf = _decimate(v, f, SCORING_FACES)
        write_shard(Path(shard_path), words, geom, center, radius, score_vertices=sv, score_faces=sf)
        return {"id": model_id, "ok": True, "parts": parts, "components": components, "extent": np.ptp(v, axis=0).tolist()}
    except MeshError as e:
        return {"id": model_id, "ok": False, "reason": e.reason}


def scan_meshes(mesh_dir: Path) -> list[Path]:
    return sorted(p for p in mesh_dir.rglob("*") if p.is_file() and p.suffix.lower() in MESH_EXTS and not p.name.startswith("."))


def model_id_of(path: Path, mesh_dir: Path) -> str:
    return path.relative_to(mesh_dir).with_suffix("").as_posix()


def build_library(
    mesh_dir, out_dir, *, unit: str = "m", workers: int | None = None, progress: bool = True, grid: GridSpec | None = None, log=print
) -> Library:
    """Build (or update) the library at `out_dir` from every mesh under `mesh_dir`.

    Models whose shard already exists (same bytes, unit and grid) are not re-rendered. Bad meshes are
    reported one line each through `log` and skipped. `library.json` is written last, atomically.
    """
    mesh_dir, out_dir = Path(mesh_dir), Path(out_dir)
    files = _mesh_files(mesh_dir, unit)
    grid = grid or GridSpec()
    (out_dir / "index").mkdir(parents=True, exist_ok=True)
    (out_dir / "meshes").mkdir(exist_ok=True)

    plans, jobs, skipped = _plan(mesh_dir, files, out_dir, unit, grid, log)
    reports = _run_jobs(jobs, workers, progress) if jobs else {}
    models, warnings, failed = _model_entries(mesh_dir, out_dir, plans, reports, grid, log)
    skipped += failed
    if not models:
        raise LibraryError(f"{mesh_dir}: none of its {len(files)} mesh files could be used")
    digests = consolidate(out_dir / "index", grid, [(m.id, m.shard) for m in models])
    keep = {m.shard.name for m in models}
    for old in (out_dir / "index").glob("*.npz"):
        if old.name not in keep:
            old.unlink()
    atomic_write_json(out_dir / LIBRARY_JSON, _library_doc(out_dir, grid, models, skipped, warnings, digests))
    # What was just written and hashed is handed on as it is; `load_library` verifies it for every later reader.
    return Library(out_dir, models, grid, skipped, warnings)


def _mesh_files(mesh_dir: Path, unit: str) -> list[Path]:
    """The mesh files under `mesh_dir` (`scan_meshes`); LibraryError for an unknown default `unit`, a missing folder or no meshes."""
    if unit not in UNIT_TO_M:
        raise LibraryError(f"unit {unit!r} is not one of {', '.join(UNIT_TO_M)}")
    if not mesh_dir.is_dir():
        raise LibraryError(f"{mesh_dir}: not a directory of meshes")
    files = scan_meshes(mesh_dir)
    if not files:
        raise LibraryError(f"{mesh_dir}: no mesh files ({', '.join(MESH_EXTS)}) found")
    return files


def _plan(
    mesh_dir: Path, files: list[Path], out_dir: Path, unit: str, grid: GridSpec, log
) -> tuple[list[tuple[str, Path, str, str, Path]], list[tuple[str, str, float, dict, str]], list[dict]]:
    """The plan of each usable mesh file, (model id, path, unit, sha256, shard path), the `_build_model` jobs of
    those whose shard is not built yet, and the files skipped ({file, reason}, each logged): STEP files and files
    of an unknown unit."""
    plans, jobs, skipped = [], [], []
    for path in sorted(p for p in mesh_dir.rglob("*") if p.is_file() and p.suffix.lower() in CAD_ONLY_EXTS):
        reason = "STEP files are not read (no B-rep kernel in this build); export the part as STL, OBJ, PLY or GLB"
        skipped.append({"file": str(path), "reason": reason})
        log(f"skipped {path}: {reason}")
    for path in files:
        mid = model_id_of(path, mesh_dir)
        try:
            u = unit_of(path, unit)
        except MeshError as e:
            skipped.append({"file": str(path), "reason": str(e)})
            log(f"skipped {path}: {e}")
            continue
        digest = sha256_file(path)
        shard = out_dir / "index" / f"{shard_key(digest, UNIT_TO_M[u], grid)}.npz"
        plans.append((mid, path, u, digest, shard))
        if not shard.exists():
            jobs.append((mid, str(path), UNIT_TO_M[u], grid.to_dict(), str(shard)))
    return plans, jobs, skipped


def _model_entries(
    mesh_dir: Path,
    out_dir: Path,
    plans: list[tuple[str, Path, str, str, Path]],
    reports: dict,
    grid: GridSpec,
    log,
) -> tuple[list[ModelEntry], list[str], list[dict]]:
    """The entries of the planned models that built (their mesh copied into `out_dir`/meshes), the size warnings
    and the models that failed ({file, reason}); each warning and failure is logged.

    A model's report comes from this build's `reports`, else from the previous library.json, else (a shard of an
    interrupted build) is re-derived."""
    previous = _previous_entries(out_dir)
    models, warnings, failed = [], [], []
    for mid, path, u, digest, shard in plans:
        rep = reports.get(mid) or previous.get(digest + str(shard))
        if rep is None:
            # A shard from an interrupted build: its metadata is re-derived cheaply.
            rep = _build_model((mid, str(path), UNIT_TO_M[u], grid.to_dict(), str(shard)))
        if not rep["ok"]:
            failed.append({"file": str(path), "reason": rep["reason"]})
            log(f"skipped {path}: {rep['reason']}")
            continue
        dst = out_dir / "meshes" / path.relative_to(mesh_dir)
        dst.parent.mkdir(parents=True, exist_ok=True)
        if not dst.exists() or sha256_file(dst) != digest:
            atomic_write_bytes(dst, path.read_bytes())
        size = max(rep["extent"])
        if not PLAUSIBLE_EXTENT_M[0] <= size <= PLAUSIBLE_EXTENT_M[1]:
            w = f"{mid}: {size:.4g} m across in unit '{u}'; if that is wrong, declare its unit (name.units<u>.ext or units.json)"
            warnings.append(w)
            log(f"warning {w}")
        models.append(ModelEntry(mid, dst, u, digest, tuple(rep["parts"]), int(rep["components"]), tuple(rep["extent"]), shard))
    return models, warnings, failed


def _library_doc(
    out_dir: Path, grid: GridSpec, models: list[ModelEntry], skipped: list[dict], warnings: list[str], digests: dict[str, str]
) -> dict:
    """library.json's document: the grid, the models, what was skipped and why, the warnings, and the sha256 of every
    index file (`digests`, the consolidated index's) and shard."""
    return {
        "format": FORMAT,
        "grid": grid.to_dict(),
        "models": [
            {
                "id": m.id,
                "file": m.mesh_path.relative_to(out_dir).as_posix(),
                "unit": m.unit,
                "sha256": m.sha256,
                "part_names": list(m.part_names),
                "components": m.components,
                "extent_m": list(m.extent_m),
                "shard": m.shard.relative_to(out_dir).as_posix(),
            }
            for m in models
        ],
        "skipped": skipped,
        "warnings": warnings,
        "sha256": {**digests, **{m.shard.relative_to(out_dir).as_posix(): sha256_file(m.shard) for m in models}},
    }


def _previous_entries(out_dir: Path) -> dict:
    """Reports of models already in an existing library.json, keyed by mesh sha256 + shard path."""
    p = out_dir / LIBRARY_JSON
    if not p.exists():
        return {}
    try:
        doc = json.loads(p.read_text())
    except json.JSONDecodeError:
        return {}
    return {
        m["sha256"] + str(out_dir / m["shard"]): {
            "ok": True,
            "parts": m.get("part_names", []),
            "components": m.get("components", 1),
            "extent": m["extent_m"],
        }
        for m in doc.get("models", [])
    }


def _run_jobs(jobs: list, workers: int | None, progress: bool) -> dict:
    workers = max(1, min(workers or os.cpu_count() or 1, len(jobs)))
    reports = {}
    bar = None
    if progress:
        from rich.progress import BarColumn, MofNCompleteColumn, Progress, TextColumn, TimeRemainingColumn

        bar = Progress(TextColumn("silhouettes"), BarColumn(), MofNCompleteColumn(), TimeRemainingColumn(), transient=False)
        bar.start()
        task = bar.add_task("build", total=len(jobs))
    try:
        if workers == 1:
            results = map(_build_model, jobs)
        else:
            pool = ProcessPoolExecutor(workers, mp_context=multiprocessing.get_context("fork"))
            results = pool.map(_build_model, jobs, chunksize=1)
        for rep in results:
            reports[rep["id"]] = rep
            if bar is not None:
                bar.advance(task)
        if workers > 1:
            pool.shutdown()
    finally:
        if bar is not None:
            bar.stop()
    return reports


def load_library(path) -> Library:
    """Open a built library directory (the index is memory-mapped on first use).

    Every mesh and shard it names must lie inside the library, and every mesh must still have the
    sha256 recorded at build time: each is hashed once here, so a replaced mesh is refused before use.
    """
    root = Path(path)
    p = root / LIBRARY_JSON
    if not p.exists():
        raise LibraryError(f"{root}: no library.json here; build one with 'cadsplat library build'")
    try:
        doc = json.loads(p.read_text())
    except json.JSONDecodeError as e:
        raise LibraryError(f"{p}: invalid JSON ({e.msg} at line {e.lineno})") from None
    if not isinstance(doc, dict) or doc.get("format") != FORMAT:
        raise LibraryError(f"{p}: not a {FORMAT} library")
    if not isinstance(doc.get("models"), list) or not isinstance(doc.get("grid"), dict):
        raise LibraryError(f"{p}: models must be a list and grid a table")
    models = [_model_entry(m, i, root, p) for i, m in enumerate(doc["models"])]
    for m in models:
        if not m.shard.exists():
            raise LibraryError(f"{m.shard}: index shard of {m.id} is missing; rebuild the library")
        if not m.mesh_path.is_file():
            raise LibraryError(f"{m.mesh_path}: mesh of {m.id} is missing; rebuild the library")
        if sha256_file(m.mesh_path) != m.sha256:
            raise LibraryError(
                f"{m.mesh_path}: the mesh of model {m.id} is not the one the library was built from (sha256 differs); rebuild the library"
            )
    try:
        grid = GridSpec(**doc["grid"])
    except TypeError as e:
        raise LibraryError(f"{p}: grid is malformed ({e})") from None
    return Library(root, models, grid, doc.get("skipped", []), doc.get("warnings", []))


def _model_entry(m, i: int, root: Path, doc_path: Path) -> ModelEntry:
    """models[i] of library.json as a ModelEntry, its paths kept inside `root`; LibraryError naming the key otherwise."""
    where = f"{doc_path}: models[{i}]"
    if not isinstance(m, dict):
        raise LibraryError(f"{where} must be a table")
    for key in ("id", "file", "unit", "sha256", "shard"):
        if not isinstance(m.get(key), str) or not m[key]:
            raise LibraryError(f"{where}.{key} must be a non-empty string, got {m.get(key)!r}")
    if m["unit"] not in UNIT_TO_M:
        raise LibraryError(f"{where}.unit {m['unit']!r} is not one of {', '.join(UNIT_TO_M)}")
    extent = m.get("extent_m")
    if not (isinstance(extent, list) and len(extent) == 3 and all(isinstance(x, (int, float)) and not isinstance(x, bool) for x in extent)):
        raise LibraryError(f"{where}.extent_m must be a list of 3 numbers, got {extent!r}")
    if (
        not isinstance(m.get("part_names", []), list)
        or isinstance(m.get("components", 1), bool)
        or not isinstance(m.get("components", 1), int)
    ):
        raise LibraryError(f"{where}: part_names must be a list and components an integer")
    try:
        mesh_path = contained(root, m["file"], what=f"{where}.file")
        shard = contained(root, m["shard"], what=f"{where}.shard")
    except PathOutside as e:
        raise LibraryError(str(e)) from None
    return ModelEntry(
        m["id"],
        mesh_path,
        m["unit"],
        m["sha256"],
        tuple(str(n) for n in m.get("part_names", [])),
        int(m.get("components", 1)),
        tuple(float(x) for x in extent),
        shard,
    )
