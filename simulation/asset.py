"""Twin or CAD mesh -> simulation asset: the (deformed) mesh in metres, repaired where trimesh can,
with volume, mass from a density and inertia about the centre of mass, and a colour per face.

The asset's frame is the object frame: a simulator body placed at pose T puts vertex x at T x,
which is exactly where the twin's Gaussians must go too (see `follow`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from reconstruction.library import UNIT_TO_M, unit_of
from reconstruction.splats import SH_C0
from reconstruction.twin import MeshParts, Twin
from simulation.parts import read_mesh_parts

# kg/m^3. Default "plastic" is ABS, the commonest material of small factory parts.
MATERIAL_DENSITY: dict[str, float] = {
    "plastic": 1050.0,
    "abs": 1050.0,
    "pla": 1240.0,
    "nylon": 1150.0,
    "rubber": 1100.0,
    "wood": 700.0,
    "foam": 100.0,
    "aluminium": 2700.0,
    "steel": 7850.0,
    "brass": 8500.0,
}
DEFAULT_MATERIAL = "plastic"


@dataclass(frozen=True)
class MassProperties:
    """Solid-body properties at a uniform density (SI units, object frame).

    inertia [3, 3] is about the centre of mass with object-frame axes. `exact` is False when the
    mesh is not a closed volume and its convex hull stood in for it.
    """

    volume: float
    mass: float
    center_of_mass: np.ndarray
    inertia: np.ndarray
    exact: bool


@dataclass(frozen=True)
class RepairReport:
    """What `repair_mesh` changed: vertices welded, faces dropped (degenerate/duplicate), faces added
    filling holes, whether the winding was reversed to point outwards, and the result's closedness."""

    vertices_welded: int
    faces_removed: int
    faces_added: int
    inverted: bool
    watertight: bool


@dataclass
class SimAsset:
    """One rigid body: vertices [V, 3] metres (object frame), faces [F, 3], face_part [F] into
    part_names, face_rgb [F, 3] in [0, 1], density kg/m^3, its mass properties and repair report."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    face_part: np.ndarray
    part_names: list[str]
    face_rgb: np.ndarray
    density: float
    material: str
    mass: MassProperties
    repair: RepairReport

    def trimesh(self):
        import trimesh

        return trimesh.Trimesh(self.vertices, self.faces, process=False)

    @property
    def lowest_z(self) -> float:
        return float(self.vertices[:, 2].min())


def resolve_density(density: float | None, material: str | None) -> tuple[float, str]:
    """Explicit density wins; else the material's; else the default material's."""
    material = (material or DEFAULT_MATERIAL).lower()
    if density is not None:
        if not (np.isfinite(density) and density > 0):
            raise ValueError(f"density must be a positive number of kg/m^3, got {density}")
        return float(density), material
    if material not in MATERIAL_DENSITY:
        raise ValueError(f"unknown material {material!r}; use one of {', '.join(MATERIAL_DENSITY)} or give a density")
    return MATERIAL_DENSITY[material], material


def repair_mesh(vertices: np.ndarray, faces: np.ndarray, face_data: dict[str, np.ndarray] | None = None):
    """Weld duplicate vertices, drop degenerate and duplicate faces, make winding consistent and
    outward, fill small (triangle/quad) holes. Per-face arrays in `face_data` ([F, ...]) follow the
    faces; filled faces take the values of their nearest original face.

    Returns (vertices [V', 3], faces [F', 3], face_data', RepairReport).
    """
    import trimesh
    from scipy.spatial import cKDTree

    face_data = {k: np.asarray(v) for k, v in (face_data or {}).items()}
    mesh = trimesh.Trimesh(np.asarray(vertices, np.float64), np.asarray(faces, np.int64), process=False)
    v0, f0 = len(mesh.vertices), len(mesh.faces)
    mesh.merge_vertices()
    keep = mesh.nondegenerate_faces() & mesh.unique_faces()
    mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()
    face_data = {k: v[keep] for k, v in face_data.items()}
    volume_before = mesh.volume if mesh.is_winding_consistent else 0.0
    trimesh.repair.fix_normals(mesh, multibody=True)
    inverted = bool(volume_before < 0 and mesh.volume > 0)
    n_kept = len(mesh.faces)
    trimesh.repair.fill_holes(mesh)
    added = len(mesh.faces) - n_kept
    if added:
        centres = mesh.triangles_center
        _, nearest = cKDTree(centres[:n_kept]).query(centres[n_kept:])
        face_data = {k: np.concatenate([v, v[nearest]]) for k, v in face_data.items()}
    report = RepairReport(
        vertices_welded=v0 - len(mesh.vertices),
        faces_removed=f0 - int(keep.sum()),
        faces_added=added,
        inverted=inverted,
        watertight=bool(mesh.is_watertight),
    )
    return np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64), face_data, report


def mass_properties(vertices: np.ndarray, faces: np.ndarray, density: float) -> MassProperties:
    """Volume, mass, centre of mass and inertia of the solid bounded by the mesh (metres, kg/m^3).

    An open or inside-out mesh has no meaningful volume; its convex hull stands in (exact=False).
    """
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    exact = bool(mesh.is_volume)
    solid = mesh if exact else mesh.convex_hull
    if not solid.volume > 0:
        raise ValueError("the mesh encloses no volume (flat or degenerate), so it has no mass")
    props = solid.mass_properties
    return MassProperties(
        volume=float(props.volume),
        mass=float(props.volume * density),
        center_of_mass=np.asarray(props.center_mass, np.float64),
        inertia=np.asarray(props.inertia, np.float64) * density,
        exact=exact,
    )


def sh_dc_rgb(sh_dc: np.ndarray) -> np.ndarray:
    """3DGS degree-0 colour [N, 3] in [0, 1] from DC coefficients [N, 3]."""
    return np.clip(0.5 + SH_C0 * np.asarray(sh_dc, np.float64), 0.0, 1.0)


def bake_face_colors(face_centers: np.ndarray, means: np.ndarray, rgb: np.ndarray, opacity: np.ndarray, k: int = 8) -> np.ndarray:
    """Colour [F, 3] of each face from its k nearest splats, weighted by opacity / distance.

    face_centers [F, 3]; means [N, 3]; rgb [N, 3] (the splats' view-independent colour); opacity [N].
    """
    from scipy.spatial import cKDTree

    k = int(min(k, len(means)))
    dist, idx = cKDTree(means).query(face_centers, k=k)
    dist, idx = dist.reshape(len(face_centers), k), idx.reshape(len(face_centers), k)
    scale = np.median(dist[:, 0]) + 1e-12
    w = np.asarray(opacity, np.float64)[idx] / (dist + scale)
    return (w[..., None] * np.asarray(rgb, np.float64)[idx]).sum(1) / np.maximum(w.sum(1, keepdims=True), 1e-12)


def build_asset(
    name: str,
    parts: MeshParts,
    *,
    face_rgb: np.ndarray | None = None,
    density: float | None = None,
    material: str | None = None,
) -> SimAsset:
    """Repair `parts` (metres, object frame) and compute its mass properties. Faces without a
    colour are mid grey."""
    rho, material = resolve_density(density, material)
    v = np.asarray(parts.vertices, np.float64)
    if len(parts.faces) == 0 or not np.all(np.isfinite(v)):
        raise ValueError(f"{name}: the mesh is empty or has non-finite vertices")
    rgb = np.full((len(parts.faces), 3), 0.5) if face_rgb is None else np.asarray(face_rgb, np.float64)
    v, f, data, report = repair_mesh(v, parts.faces, {"part": parts.face_part, "rgb": rgb})
    return SimAsset(
        name=name, vertices=v, faces=f, face_part=data["part"].astype(np.int64), part_names=list(parts.part_names),
        face_rgb=data["rgb"], density=rho, material=material, mass=mass_properties(v, f, rho), repair=report,
    )


def asset_from_twin(twin: Twin, name: str | None = None, *, density: float | None = None, material: str | None = None) -> SimAsset:
    """The twin's deformed CAD mesh as a rigid body, faces coloured from the nearby splats."""
    parts = twin.load_mesh_deformed()
    centres = parts.vertices[parts.faces].mean(1)
    opacity = 1.0 / (1.0 + np.exp(-twin.opacity_logits.astype(np.float64)))
    rgb = bake_face_colors(centres, twin.means, sh_dc_rgb(twin.sh[:, 0]), opacity)
    return build_asset(name or twin.model_id, parts, face_rgb=rgb, density=density, material=material)


def load_mesh_asset(
    path: str | os.PathLike, unit: str | None = None, name: str | None = None, *, density: float | None = None, material: str | None = None
) -> SimAsset:
    """A CAD/mesh file as a rigid body. `unit` (m, mm, cm, in) may be omitted only when the file
    name declares it (`part.unitsmm.stl`) or a units.json beside it does; it is never guessed."""
    path = Path(path)
    unit = unit or unit_of(path, "")
    if unit not in UNIT_TO_M:
        raise ValueError(f"{path.name}: declare its unit (one of {', '.join(UNIT_TO_M)}); mesh files do not say")
    parts, rgb = read_mesh_parts(path)
    parts = MeshParts(parts.vertices * UNIT_TO_M[unit], parts.faces, parts.face_part, parts.part_names)
    return build_asset(name or path.name.split(".")[0], parts, face_rgb=rgb, density=density, material=material)
