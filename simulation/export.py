"""Twin exports for other tools: the splats as a PLY, the deformed mesh as a GLB, an MJCF package
(MuJoCo), a USD file (Isaac Sim) and a COLMAP text model.

`FORMATS` is the export table (format -> exporter, help) that `cadsplat export` and the service's
export step both go through `write_export`, which writes atomically. The simulator reads bodies
through `load_body`, which takes a twin directory or a bare mesh file. MJCF and USD carry the same
body: the same repaired mesh, mass properties and collision shapes.
"""

from __future__ import annotations

import os
import shutil
import tempfile
from pathlib import Path
from typing import Callable

import numpy as np

from calibration.fileio import atomic_write_bytes, fsync_dir, publish_dir
from reconstruction.gaussians import Gaussians
from reconstruction.mesh_io import material_names, parts_glb_bytes
from reconstruction.twin import MESH_CAD_GLB, SPLATS_PLY, TWIN_JSON, TwinError, load_twin, splats_to_ply_bytes
from simulation.asset import Density, asset_from_twin, choose_density, load_mesh_asset, rig_simulation_table, sh_dc_rgb
from simulation.collision import DEFAULT_TOLERANCE, DecompositionOptions, collision_geometry
from simulation.follow import splats_from_mesh
from simulation.mjcf import BodySpec, SimOptions, write_mjcf_package
from simulation.scene import Placement, resting_position

IDENTITY_QUAT = np.array([1.0, 0.0, 0.0, 0.0])


def body_density(placement: Placement, rig: dict | None = None) -> Density:
    """The placement's density: its own density/material, else a material the CAD names (the twin's
    mesh_cad.glb or the mesh file), else rig.toml's [simulation] table `rig`, else the default."""
    src = placement.source
    cad = src / MESH_CAD_GLB if src.is_dir() else src
    names = material_names(cad) if cad.exists() else []
    return choose_density(placement.density, placement.material, cad_names=names, rig=rig)


def load_body(
    placement: Placement, decomposition: DecompositionOptions | None = DecompositionOptions(), rig: dict | None = None
) -> tuple[BodySpec, Gaussians]:
    """A scene entry -> (BodySpec placed as the scene says, its splats in the object frame).

    A twin directory gives its deformed mesh and its Gaussians; a mesh file gives the mesh and
    `placement.splats` opaque splats sampled on it. `rig`: rig.toml's [simulation] table.
    """
    src = placement.source
    density = body_density(placement, rig)
    if src.is_dir():
        if not (src / TWIN_JSON).exists():
            raise ValueError(f"{src}: a directory but not a twin (no {TWIN_JSON})")
        twin = load_twin(src)
        asset = asset_from_twin(twin, placement.name, density=density)
        splats = twin.gaussians
    else:
        asset = load_mesh_asset(src, placement.unit, placement.name, density=density)
        splats = splats_from_mesh(asset.vertices, asset.faces, asset.face_rgb, asset.face_part, placement.splats).gaussians
    col = collision_geometry(
        asset.vertices, asset.faces, asset.mass.volume, face_part=asset.face_part, tolerance=placement.collision_tolerance, decomposition=decomposition
    )
    quat = np.asarray(placement.quat, np.float64)
    pos = resting_position(asset.vertices, quat, placement.pos, placement.bottom)
    return BodySpec(asset, col, pos, quat, placement.fixed), splats


def twin_body(
    twin_dir: str | os.PathLike, *, density: float | None = None, material: str | None = None, rig_toml: str | os.PathLike | None = None,
    tolerance: float = DEFAULT_TOLERANCE, decomposition: DecompositionOptions | None = DecompositionOptions(),
) -> BodySpec:
    """One twin as a free body resting on z = 0 (object frame = body frame), density by flag, CAD
    material, rig.toml ([simulation]) or default."""
    twin_dir = Path(twin_dir)
    if not twin_dir.is_dir():
        raise ValueError(f"{twin_dir}: not a twin directory")
    rig = rig_simulation_table(rig_toml) if rig_toml is not None else None
    placement = Placement(name=_body_name(twin_dir), source=twin_dir, bottom=0.0, density=density, material=material, collision_tolerance=tolerance)
    return load_body(placement, decomposition, rig)[0]


def export_mjcf(twin_dir: str | os.PathLike, out_dir: str | os.PathLike, **physics) -> Path:
    """MJCF package of one twin resting on a floor (object frame = body frame, lowest point at z = 0).
    `physics`: density, material, rig_toml, tolerance, decomposition (see `twin_body`).

    Returns the path of `model.xml`.
    """
    return write_mjcf_package(out_dir, [twin_body(twin_dir, **physics)], SimOptions())


def export_usd(twin_dir: str | os.PathLike, out: str | os.PathLike, **physics) -> Path:
    """USD file (UsdGeom + UsdPhysics, for Isaac Sim) of one twin, read back and checked with pxr.
    `out` is a .usd/.usda/.usdc file or a directory (then `<twin>.usda` in it). Returns its path."""
    from simulation.usd import write_usd

    out = Path(out)
    if out.suffix.lower() not in (".usd", ".usda", ".usdc"):
        out = out / f"{_body_name(Path(twin_dir))}.usda"
    return write_usd(out, twin_body(twin_dir, **physics))


def _body_name(path: Path) -> str:
    name = "".join(c if c.isalnum() or c in "_-" else "_" for c in path.resolve().name)
    return name or "twin"


def colmap_reconstruction(cameras, means: np.ndarray, rgb: np.ndarray):
    """pycolmap Reconstruction of OpenCV pinhole cameras in the object frame (image and camera ids
    1..n in order) and coloured points [N, 3] with rgb [N, 3] in [0, 1], without 2D tracks.

    COLMAP's pixel (0, 0) centre is at (0.5, 0.5), as ours, so intrinsics carry over unchanged.
    """
    import pycolmap

    rec = pycolmap.Reconstruction()
    for i, c in enumerate(cameras, start=1):
        cam = c.camera
        k = cam.K
        rec.add_camera_with_trivial_rig(pycolmap.Camera(model="PINHOLE", width=cam.width, height=cam.height, params=[k[0, 0], k[1, 1], k[0, 2], k[1, 2]], camera_id=i))
        image = pycolmap.Image(name=Path(c.file_path).name, camera_id=i, image_id=i)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(cam.viewmat[:3, :4]))
    col = np.clip(np.asarray(rgb) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    for xyz, c in zip(np.asarray(means, np.float64), col):
        rec.add_point3D(xyz, pycolmap.Track(), c)
    return rec


def export_colmap(twin_dir: str | os.PathLike, out_dir: str | os.PathLike) -> Path:
    """COLMAP text model of a twin: its training cameras (refined, object frame) and its splat means
    coloured by their DC colour. Returns `out_dir`."""
    twin = load_twin(twin_dir)
    if not twin.cameras:
        raise ValueError(f"{twin_dir}: the twin records no cameras to export")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        colmap_reconstruction(twin.cameras, twin.gaussians.means, sh_dc_rgb(twin.gaussians.sh[:, 0])).write_text(tmp)
        for f in sorted(Path(tmp).iterdir()):
            atomic_write_bytes(out / f.name, f.read_bytes())  # durable, as every other export file
    fsync_dir(out)
    return out


def _write_atomic(data: bytes, out: Path, name: str) -> Path:
    if out.is_dir():
        out = out / name
    out.parent.mkdir(parents=True, exist_ok=True)
    atomic_write_bytes(out, data)
    return out


def export_ply(twin_dir: str | os.PathLike, out: str | os.PathLike) -> Path:
    """The splats re-encoded as the current PLY layout (SH padded to degree 3, so Inria's loader
    reads it without --sh_degree), also for twins saved before the padding."""
    twin = load_twin(twin_dir)  # validates the twin before anything is written
    data = splats_to_ply_bytes(twin.gaussians)
    return _write_atomic(data, Path(out), SPLATS_PLY)


def export_glb(twin_dir: str | os.PathLike, out: str | os.PathLike) -> Path:
    """The deformed mesh re-encoded +Y up (parts under the object-frame root node), also for twins
    whose GLB was saved z up."""
    twin = load_twin(twin_dir)
    if not twin.mesh_deformed_path.exists():
        raise TwinError(f"{twin.mesh_deformed_path}: the twin has no deformed mesh to export")
    return _write_atomic(parts_glb_bytes(twin.load_mesh_deformed()), Path(out), twin.mesh_deformed_path.name)


# format -> (exporter, help). Each exporter takes (twin_dir, out, **options) and returns the written path.
FORMATS: dict[str, tuple[Callable[..., Path], str]] = {
    "ply": (export_ply, "the splats as an Inria 3DGS PLY (opens in 3DGS viewers)"),
    "glb": (export_glb, "the deformed CAD mesh, one node per part, +Y up"),
    "mjcf": (export_mjcf, "a MuJoCo model package"),
    "usd": (export_usd, "a USD rigid body with mass and collision (Isaac Sim)"),
    "colmap": (export_colmap, "a COLMAP sparse model of the twin's cameras"),
}

# The file every export of a directory format holds: what makes a directory "an export of that format".
DIRECTORY_MARKERS = {"mjcf": "model.xml", "colmap": "cameras.txt"}

# Formats that carry a rigid body take the physics options (density, material, rig_toml); the others take none.
PHYSICS_FORMATS = ("mjcf", "usd")


class ExportError(ValueError):
    """An export refused before anything is written (the output exists). One plain sentence."""


def write_export(fmt: str, twin_dir: Path, out: Path, *, overwrite: bool = False, **options) -> Path:
    """Export the twin at `twin_dir` as `fmt` to `out`, atomically; returns what was written.

    A file is written beside its name and renamed; a directory format is built in a hidden sibling
    directory and renamed into place, so a full disk or a kill leaves the old output or none. An
    existing output is replaced only with `overwrite`, and only when it holds an export of `fmt`.
    `options` go to the format's exporter (the physics options of `PHYSICS_FORMATS`).
    """
    exporter = FORMATS[fmt][0]
    if fmt not in DIRECTORY_MARKERS:
        if out.exists() and not out.is_dir() and not overwrite:
            raise ExportError(f"{out} already exists; pass --overwrite to replace it")
        return exporter(twin_dir, out, **options)
    if out.exists():
        if not overwrite:
            raise ExportError(f"{out} already exists; pass --overwrite to replace it")
        if not (out / DIRECTORY_MARKERS[fmt]).is_file():
            raise ExportError(f"{out} holds no {fmt} export (no {DIRECTORY_MARKERS[fmt]}), so it is not replaced; choose another --out")
    load_twin(twin_dir)  # a damaged twin fails here, before anything is written
    out.parent.mkdir(parents=True, exist_ok=True)
    tmp = Path(tempfile.mkdtemp(prefix=f".{out.name}.", suffix=".incoming", dir=out.parent))
    try:
        exporter(twin_dir, tmp, **options)
        fsync_dir(tmp)
        publish_dir(tmp, out)
    except BaseException:
        shutil.rmtree(tmp, ignore_errors=True)
        raise
    return out
