"""Twin exports for other tools: an MJCF package (MuJoCo), a USD file (Isaac Sim) and a COLMAP text model.

`cadsplat export TWIN --format mjcf|usd|colmap --out PATH` calls `export_mjcf` / `export_usd` /
`export_colmap`; the simulator reads bodies through `load_body`, which takes a twin directory or a
bare mesh file. MJCF and USD carry the same body: the same repaired mesh, mass properties and
collision shapes.
"""

from __future__ import annotations

import os
from pathlib import Path

import numpy as np

from calibration.fileio import atomic_write_bytes, fsync_dir
from calibration.so3 import matrix_to_quat
from reconstruction.mesh_io import material_names
from reconstruction.twin import MESH_CAD_GLB, TWIN_JSON, load_twin
from simulation.asset import Density, asset_from_twin, choose_density, load_mesh_asset, rig_simulation_table, sh_dc_rgb
from simulation.collision import DEFAULT_TOLERANCE, DecompositionOptions, collision_geometry
from simulation.follow import splats_from_mesh, splats_from_twin
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
) -> tuple[BodySpec, dict]:
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
        splats = splats_from_twin(twin)
    else:
        asset = load_mesh_asset(src, placement.unit, placement.name, density=density)
        splats = splats_from_mesh(asset.vertices, asset.faces, asset.face_rgb, asset.face_part, placement.splats)
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


def colmap_text(cameras, means: np.ndarray, rgb: np.ndarray) -> dict[str, str]:
    """COLMAP text model (cameras.txt, images.txt, points3D.txt) of OpenCV pinhole cameras in the
    object frame and coloured points [N, 3] with rgb [N, 3] in [0, 1].

    COLMAP stores world-to-camera rotations as qw qx qy qz and its pixel (0, 0) centre is at
    (0.5, 0.5), as ours, so intrinsics carry over unchanged. Points have no 2D tracks.
    """
    cam_lines = ["# Camera list with one line of data per camera:", "#   CAMERA_ID, MODEL, WIDTH, HEIGHT, PARAMS[]", f"# Number of cameras: {len(cameras)}"]
    img_lines = ["# Image list with two lines of data per image:", "#   IMAGE_ID, QW, QX, QY, QZ, TX, TY, TZ, CAMERA_ID, NAME", "#   POINTS2D[] as (X, Y, POINT3D_ID)", f"# Number of images: {len(cameras)}"]
    for i, c in enumerate(cameras, start=1):
        cam = c.camera
        k = cam.K
        cam_lines.append(f"{i} PINHOLE {cam.width} {cam.height} {k[0, 0]:.10g} {k[1, 1]:.10g} {k[0, 2]:.10g} {k[1, 2]:.10g}")
        w2c = cam.viewmat
        q = matrix_to_quat(w2c[:3, :3])
        t = w2c[:3, 3]
        img_lines.append(f"{i} {q[0]:.12g} {q[1]:.12g} {q[2]:.12g} {q[3]:.12g} {t[0]:.12g} {t[1]:.12g} {t[2]:.12g} {i} {Path(c.file_path).name}")
        img_lines.append("")
    col = np.clip(np.asarray(rgb) * 255.0 + 0.5, 0, 255).astype(int)
    pts = ["# 3D point list with one line of data per point:", "#   POINT3D_ID, X, Y, Z, R, G, B, ERROR, TRACK[] as (IMAGE_ID, POINT2D_IDX)", f"# Number of points: {len(means)}"]
    pts += [f"{j} {x:.9g} {y:.9g} {z:.9g} {r} {g} {b} 0" for j, ((x, y, z), (r, g, b)) in enumerate(zip(np.asarray(means, np.float64), col), start=1)]
    return {"cameras.txt": "\n".join(cam_lines) + "\n", "images.txt": "\n".join(img_lines) + "\n", "points3D.txt": "\n".join(pts) + "\n"}


def export_colmap(twin_dir: str | os.PathLike, out_dir: str | os.PathLike) -> Path:
    """COLMAP text model of a twin: its training cameras (refined, object frame) and its splat means
    coloured by their DC colour. Returns `out_dir`."""
    twin = load_twin(twin_dir)
    if not twin.cameras:
        raise ValueError(f"{twin_dir}: the twin records no cameras to export")
    out = Path(out_dir)
    out.mkdir(parents=True, exist_ok=True)
    for name, text in colmap_text(twin.cameras, twin.means, sh_dc_rgb(twin.sh[:, 0])).items():
        atomic_write_bytes(out / name, text.encode())
    fsync_dir(out)
    return out

