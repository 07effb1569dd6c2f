"""Twin exports for other tools: the splats as an Inria PLY, a glTF `KHR_gaussian_splatting` GLB (the
deformed mesh alongside when asked), a Niantic .spz, an MJCF package (MuJoCo), a USD file (Isaac Sim:
splats, mesh and rigid body) and a COLMAP text model.

`FORMATS` is the export table (format -> exporter, help) that `cadsplat export` and the service's
export step both go through `write_export`, which writes atomically and never replaces an output
without `overwrite`. The simulator reads bodies through `load_body`, which takes a twin directory or
a bare mesh file. MJCF and USD carry the same body: the same repaired mesh, mass properties and
collision shapes.

Every export but the PLY and COLMAP (the twin's own object frame, as the engine renders it) stands
the part as it stood on the line: up (`simulation.up`: the twin's record, rig.toml, the CAD's
declared axis, else +z, said as such) becomes glTF's and spz's +Y, USD's upAxis and MuJoCo's +z,
and each says where up came from (GLB: the root node's extras; USD: customLayerData; MJCF: manifest).
"""

from __future__ import annotations

import os
import shutil
import tempfile
from collections.abc import Callable
from dataclasses import replace
from pathlib import Path

import numpy as np

from calibration.fileio import atomic_write_bytes, fsync_dir, publish_dir
from calibration.so3 import matrix_to_quat
from reconstruction.gaussians import Gaussians
from reconstruction.mesh_io import MeshParts, material_names
from reconstruction.twin import MESH_CAD_GLB, SPLATS_PLY, TWIN_JSON, Twin, TwinError, load_twin, splats_to_ply_bytes
from simulation.asset import Density, asset_from_twin, choose_density, load_mesh_asset, rig_simulation_table, sh_dc_rgb
from simulation.collision import DEFAULT_TOLERANCE, DecompositionOptions, collision_geometry
from simulation.follow import splats_from_mesh
from simulation.gltf_splats import glb_bytes, splats_gltf
from simulation.mjcf import BodySpec, SimOptions, write_mjcf_package
from simulation.scene import Placement, resting_position
from simulation.spz import spz_bytes
from simulation.up import Up, resolve_up, standing


def body_density(placement: Placement, rig: dict | None = None) -> Density:
    """The placement's density: its own density/material, else a material the CAD names (the twin's
    mesh_cad.glb or the mesh file), else rig.toml's [simulation] table `rig`, else the default."""
    src = placement.source
    cad = src / MESH_CAD_GLB if src.is_dir() else src
    names = material_names(cad) if cad.exists() else []
    return choose_density(placement.density, placement.material, cad_names=names, rig=rig)


def load_body(
    placement: Placement,
    decomposition: DecompositionOptions | None = DecompositionOptions(),
    rig: dict | None = None,
    twin: Twin | None = None,
) -> tuple[BodySpec, Gaussians]:
    """A scene entry -> (BodySpec placed as the scene says, its splats in the object frame).

    A twin directory gives its deformed mesh and its Gaussians (`twin`, when the caller has read it
    already); a mesh file gives the mesh and `placement.splats` opaque splats sampled on it. `rig`:
    rig.toml's [simulation] table.
    """
    src = placement.source
    density = body_density(placement, rig)
    if src.is_dir():
        if not (src / TWIN_JSON).exists():
            raise ValueError(f"{src}: a directory but not a twin (no {TWIN_JSON})")
        twin = twin or load_twin(src)
        asset = asset_from_twin(twin, placement.name, density=density)
        splats = twin.gaussians
    else:
        asset = load_mesh_asset(src, placement.unit, placement.name, density=density)
        splats = splats_from_mesh(asset.vertices, asset.faces, asset.face_rgb, asset.face_part, placement.splats).gaussians
    col = collision_geometry(
        asset.vertices,
        asset.faces,
        asset.mass.volume,
        face_part=asset.face_part,
        tolerance=placement.collision_tolerance,
        decomposition=decomposition,
    )
    quat = np.asarray(placement.quat, np.float64)
    pos = resting_position(asset.vertices, quat, placement.pos, placement.bottom)
    return BodySpec(asset, col, pos, quat, placement.fixed), splats


def twin_up(twin: Twin, rig: dict | None = None, cad_up_axis: str | None = None) -> Up:
    """The twin's up in its object frame (`simulation.up.resolve_up`): its own record, else rig.toml's
    [simulation] `up` (rig frame) through its registration, else the CAD's declared axis (`cad_up_axis`,
    else rig.toml's `cad_up_axis`), else +z."""
    rig = rig or {}
    return resolve_up(
        twin_up=twin.up_object,
        rig_up=rig.get("up"),
        rotation_rig_to_object=twin.sim3_rig_to_object.rotation,
        cad_up_axis=cad_up_axis or rig.get("cad_up_axis"),
    )


def twin_body(
    twin_dir: str | os.PathLike,
    *,
    density: float | None = None,
    material: str | None = None,
    rig_toml: str | os.PathLike | None = None,
    tolerance: float = DEFAULT_TOLERANCE,
    decomposition: DecompositionOptions | None = DecompositionOptions(),
    hull_budget: int | None = None,
    up: Up | None = None,
    twin: Twin | None = None,
) -> BodySpec:
    """One twin as a free body standing on z = 0 as it stood on the line (`up` turned to +z; object
    frame = body frame), density by flag, CAD material, rig.toml ([simulation]) or default; at most
    `hull_budget` convex hulls (flag, else rig.toml's `hull_budget`, else the decomposition's own).
    `twin`: the twin at `twin_dir` when the caller has read it already."""
    twin_dir = Path(twin_dir)
    if not twin_dir.is_dir():
        raise ValueError(f"{twin_dir}: not a twin directory")
    rig = rig_simulation_table(rig_toml) if rig_toml is not None else None
    budget = hull_budget if hull_budget is not None else (rig or {}).get("hull_budget")
    if decomposition is not None and budget is not None:
        decomposition = replace(decomposition, hull_budget=int(budget))
    quat = (1.0, 0.0, 0.0, 0.0) if up is None else tuple(float(x) for x in matrix_to_quat(standing(up.vector, "+z")))
    placement = Placement(
        name=_body_name(twin_dir),
        source=twin_dir,
        quat=quat,
        bottom=0.0,
        density=density,
        material=material,
        collision_tolerance=tolerance,
    )
    return load_body(placement, decomposition, rig, twin)[0]


def _physics(twin_dir: Path, physics: dict) -> tuple[Twin, dict, dict]:
    """(the twin, rig.toml's [simulation] table, the physics options less the up ones) of an export call; the twin is
    `physics["twin"]` when the caller has it in memory, else read (and verified) from `twin_dir`."""
    twin = physics.get("twin") or load_twin(twin_dir)
    rig = rig_simulation_table(physics["rig_toml"]) if physics.get("rig_toml") is not None else {}
    return twin, rig, {k: v for k, v in physics.items() if k not in ("cad_up_axis", "twin")}


def export_mjcf(twin_dir: str | os.PathLike, out_dir: str | os.PathLike, **physics) -> Path:
    """MJCF package of one twin standing on a floor as it stood on the line (lowest point at z = 0),
    the manifest saying where up came from. `physics`: density, material, rig_toml, tolerance,
    decomposition, hull_budget (see `twin_body`), cad_up_axis (see `twin_up`).

    Returns the path of `model.xml`.
    """
    twin, rig, options = _physics(Path(twin_dir), physics)
    up = twin_up(twin, rig, physics.get("cad_up_axis"))
    return write_mjcf_package(out_dir, [twin_body(twin_dir, up=up, twin=twin, **options)], SimOptions(), extra={"up": up.to_dict()})


def export_usd(twin_dir: str | os.PathLike, out: str | os.PathLike, **physics) -> Path:
    """USD file (UsdVol splats + UsdGeom mesh + UsdPhysics body, for Isaac Sim) of one twin, standing
    as on the line, read back and checked with pxr. `out` is a .usd/.usda/.usdc file or a directory
    (then `<twin>.usda` in it). `physics` as `export_mjcf`. Returns its path."""
    from simulation.usd import write_usd

    out = Path(out)
    if out.suffix.lower() not in USD_SUFFIXES:
        out = out / f"{_body_name(Path(twin_dir))}.usda"
    twin, rig, options = _physics(Path(twin_dir), physics)
    return write_usd(out, twin_body(twin_dir, twin=twin, **options), twin.gaussians, twin_up(twin, rig, physics.get("cad_up_axis")))


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
        rec.add_camera_with_trivial_rig(
            pycolmap.Camera(model="PINHOLE", width=cam.width, height=cam.height, params=[k[0, 0], k[1, 1], k[0, 2], k[1, 2]], camera_id=i)
        )
        image = pycolmap.Image(name=Path(c.file_path).name, camera_id=i, image_id=i)
        rec.add_image_with_trivial_frame(image, pycolmap.Rigid3d(cam.viewmat[:3, :4]))
    col = np.clip(np.asarray(rgb) * 255.0 + 0.5, 0, 255).astype(np.uint8)
    for xyz, c in zip(np.asarray(means, np.float64), col):
        rec.add_point3D(xyz, pycolmap.Track(), c)
    return rec


def export_colmap(twin_dir: str | os.PathLike, out_dir: str | os.PathLike, *, twin: Twin | None = None) -> Path:
    """COLMAP text model of a twin: its training cameras (refined, object frame) and its splat means
    coloured by their DC colour. Returns `out_dir`. `twin`: the twin at `twin_dir` when already in memory."""
    twin = twin or load_twin(twin_dir)
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


def export_ply(twin_dir: str | os.PathLike, out: str | os.PathLike, *, twin: Twin | None = None) -> Path:
    """The splats re-encoded as the current PLY layout (SH padded to degree 3, so Inria's loader
    reads it without --sh_degree), also for twins saved before the padding; object frame."""
    twin = twin or load_twin(twin_dir)  # validates the twin before anything is written
    data = splats_to_ply_bytes(twin.gaussians)
    return _write_atomic(data, Path(out), SPLATS_PLY)


def gltf_frame(twin: Twin, rig_toml: str | os.PathLike | None = None, cad_up_axis: str | None = None) -> tuple[Up, np.ndarray]:
    """(the twin's up, [4, 4] glTF-from-object: the rotation standing up along +Y)."""
    up = twin_up(twin, rig_simulation_table(rig_toml) if rig_toml is not None else None, cad_up_axis)
    t = np.eye(4)
    t[:3, :3] = standing(up.vector, "+y")
    return up, t


def export_glb(
    twin_dir: str | os.PathLike,
    out: str | os.PathLike,
    *,
    mesh: bool = False,
    rig_toml: str | os.PathLike | None = None,
    cad_up_axis: str | None = None,
    twin: Twin | None = None,
) -> Path:
    """The splats as a glTF KHR_gaussian_splatting GLB (`simulation.gltf_splats`), with the deformed mesh
    (one node per part) when `mesh`, +Y up as the part stood on the line."""
    twin = twin or load_twin(twin_dir)
    up, gltf_from_object = gltf_frame(twin, rig_toml, cad_up_axis)
    parts = None
    if mesh:
        if not twin.mesh_deformed_path.exists():
            raise TwinError(f"{twin.mesh_deformed_path}: the twin has no deformed mesh to export")
        p = twin.load_mesh_deformed()
        parts = MeshParts(p.vertices @ gltf_from_object[:3, :3].T, p.faces, p.face_part, p.part_names)
    # eps2d: the screen-space dilation the splats were fitted with, which the extension has no field for and a viewer
    # needs to draw them as trained (benchmarks/results/view_browser.md, Babylon's kernelSize).
    extras = {
        "up": up.to_dict(),
        "gltf_from_object": gltf_from_object.tolist(),
        "model_id": twin.model_id,
        "num_splats": twin.num_splats,
        "eps2d": twin.gaussians.eps2d,
    }
    doc, blob = splats_gltf(twin.gaussians.transformed(gltf_from_object), parts, name=_body_name(Path(twin_dir)), extras=extras)
    return _write_atomic(glb_bytes(doc, blob), Path(out), "splats.glb")


def export_spz(
    twin_dir: str | os.PathLike,
    out: str | os.PathLike,
    *,
    rig_toml: str | os.PathLike | None = None,
    cad_up_axis: str | None = None,
    twin: Twin | None = None,
) -> Path:
    """The splats as a Niantic .spz (`simulation.spz`), in its RUB frame (+Y up) as the part stood on the line."""
    twin = twin or load_twin(twin_dir)
    _, gltf_from_object = gltf_frame(twin, rig_toml, cad_up_axis)
    return _write_atomic(spz_bytes(twin.gaussians.transformed(gltf_from_object)), Path(out), "splats.spz")


# format -> (exporter, help). Each exporter takes (twin_dir, out, **options) and returns the written path.
FORMATS: dict[str, tuple[Callable[..., Path], str]] = {
    "ply": (export_ply, "the splats as an Inria 3DGS PLY, object frame (opens in 3DGS viewers)"),
    "glb": (export_glb, "the splats as a glTF KHR_gaussian_splatting GLB, +Y up (the deformed mesh too with --mesh)"),
    "spz": (export_spz, "the splats as a Niantic .spz, +Y up (Spark, Babylon.js, PlayCanvas)"),
    "mjcf": (export_mjcf, "a MuJoCo model package"),
    "usd": (export_usd, "a USD asset: splats, mesh and a rigid body with mass and collision (Isaac Sim)"),
    "colmap": (export_colmap, "a COLMAP sparse model of the twin's cameras"),
}

# The file every export of a directory format holds: what makes a directory "an export of that format".
DIRECTORY_MARKERS = {"mjcf": "model.xml", "colmap": "cameras.txt"}
# The file a file format writes when --out is a directory.
DEFAULT_FILE_NAMES = {"ply": SPLATS_PLY, "glb": "splats.glb", "spz": "splats.spz"}
USD_SUFFIXES = (".usd", ".usda", ".usdc")

# Formats that carry a rigid body take the physics options (density, material, rig_toml, hull_budget); the others take none.
PHYSICS_FORMATS = ("mjcf", "usd")
# Formats that stand the part up take rig_toml and cad_up_axis.
UP_FORMATS = ("glb", "spz", "mjcf", "usd")


class ExportError(ValueError):
    """An export refused before anything is written (the output exists). One plain sentence."""


def export_file(fmt: str, twin_dir: Path, out: Path) -> Path:
    """The file a file format writes for `--out out`: `out` itself, or its default name inside `out`
    when `out` is a directory (for USD, whenever `out` has no USD suffix)."""
    if fmt == "usd":
        return out if out.suffix.lower() in USD_SUFFIXES else out / f"{_body_name(Path(twin_dir))}.usda"
    return out / DEFAULT_FILE_NAMES[fmt] if out.is_dir() else out


def write_export(fmt: str, twin_dir: Path, out: Path, *, overwrite: bool = False, twin: Twin | None = None, **options) -> Path:
    """Export the twin at `twin_dir` as `fmt` to `out`, atomically; returns what was written.

    A file is written beside its name and renamed; a directory format is built in a hidden sibling
    directory and renamed into place, so a full disk or a kill leaves the old output or none. An
    existing output is replaced only with `overwrite`, and only when it holds an export of `fmt`.
    `options` go to the format's exporter (the physics options of `PHYSICS_FORMATS`); `twin`: the twin at
    `twin_dir` when the caller holds it already (a service job), so it is not read and verified again.
    """
    if twin is not None:
        options["twin"] = twin
    exporter = FORMATS[fmt][0]
    if fmt not in DIRECTORY_MARKERS:
        target = export_file(fmt, twin_dir, out)
        if target.exists() and not overwrite:
            raise ExportError(f"{target} already exists; pass --overwrite to replace it")
        if target.is_dir():
            raise ExportError(f"{target} is a directory, so it is not replaced; choose another --out")
        return exporter(twin_dir, target, **options)
    if out.exists():
        if not overwrite:
            raise ExportError(f"{out} already exists; pass --overwrite to replace it")
        if not (out / DIRECTORY_MARKERS[fmt]).is_file():
            raise ExportError(f"{out} holds no {fmt} export (no {DIRECTORY_MARKERS[fmt]}), so it is not replaced; choose another --out")
    if twin is None:
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
