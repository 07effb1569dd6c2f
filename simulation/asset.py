"""Twin or CAD mesh -> simulation asset: the (deformed) mesh in metres, repaired into a closed,
consistently outward-oriented surface (trimesh, MeshFix, manifold3d) or refused, with the volume it
encloses, mass from a density, inertia about the centre of mass, and a colour per face.

Density, first that applies: the caller's density or material (a CLI flag), a material named in
the CAD file (`steel_part` ...), rig.toml's `[simulation]` table (`material`/`density`), else ABS.

The asset's frame is the object frame: a simulator body placed at pose T puts vertex x at T x,
which is exactly where the twin's Gaussians must go too (see `follow`).
"""

from __future__ import annotations

import os
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from calibration.units import UNIT_TO_M
from reconstruction.mesh_io import MeshParts, read_mesh_parts, unit_of
from reconstruction.splats import SH_C0
from reconstruction.twin import Twin

if TYPE_CHECKING:
    import trimesh

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
class Density:
    """kg/m^3, the material it stands for, and where it came from ("flag", "cad", "rig.toml", "default")."""

    value: float
    material: str
    source: str


@dataclass(frozen=True)
class MassProperties:
    """Solid-body properties at a uniform density (SI units, object frame) of a closed mesh.

    inertia [3, 3] is about the centre of mass with object-frame axes; `principal_moments` [3]
    (ascending) and `principal_axes` [3, 3] (columns) diagonalise it.
    """

    volume: float
    mass: float
    center_of_mass: np.ndarray
    inertia: np.ndarray

    @property
    def principal_moments(self) -> np.ndarray:
        return np.linalg.eigvalsh(self.inertia)

    @property
    def principal_axes(self) -> np.ndarray:
        return np.linalg.eigh(self.inertia)[1]


class RepairError(ValueError):
    """A mesh that cannot be made a closed solid; the message says why in one sentence."""


@dataclass(frozen=True)
class RepairReport:
    """What `repair_mesh` changed on its way to a closed, consistently outward-oriented surface.

    Counts against the input: vertices welded, faces removed (degenerate, duplicate, dangling or
    re-triangulated), faces added (hole fills, re-triangulation, unions), faces whose winding was
    reversed; the defects found (boundary edges = holes, non-manifold edges, inconsistently wound
    edges); connected pieces, pieces dropped (open sheets enclosing no volume, under
    SHEET_AREA_LIMIT of the surface) and whether overlapping pieces were merged by a boolean union;
    the enclosed volume before (signed, m^3; meaningless when the input was open) and after, and
    the tools used ("trimesh", "meshfix", "manifold").
    """

    vertices_welded: int
    faces_removed: int
    faces_added: int
    faces_flipped: int
    boundary_edges: int
    nonmanifold_edges: int
    misoriented_edges: int
    pieces: int
    pieces_dropped: int
    pieces_merged: bool
    volume_before: float
    volume_after: float
    tools: tuple[str, ...]

    @property
    def changed(self) -> bool:
        return bool(
            self.vertices_welded
            or self.faces_removed
            or self.faces_added
            or self.faces_flipped
            or self.pieces_dropped
            or self.pieces_merged
        )

    def summary(self) -> list[str]:
        """One sentence per change, for the manifest and the command's output."""
        out = []
        if self.vertices_welded:
            out.append(f"welded {self.vertices_welded} duplicate vertices")
        if self.boundary_edges:
            out.append(f"closed holes bounded by {self.boundary_edges} open edges")
        if self.nonmanifold_edges:
            out.append(f"resolved {self.nonmanifold_edges} non-manifold edges")
        if self.faces_flipped:
            out.append(f"reversed the winding of {self.faces_flipped} faces so all point outwards")
        if self.pieces_dropped:
            out.append(f"dropped {self.pieces_dropped} open sheet(s) enclosing no volume")
        if self.pieces_merged:
            out.append(f"merged {self.pieces} pieces that overlap or touch into one solid (boolean union)")
        if self.faces_removed or self.faces_added:
            out.append(f"removed {self.faces_removed} and added {self.faces_added} faces")
        return out or ["the mesh was already a closed, consistently oriented surface"]


# An open piece smaller than this fraction of the surface is debris (a scan fin, a stray sheet)
# and is dropped; a larger one means the mesh has no interior to give it mass, and it is refused.
SHEET_AREA_LIMIT = 0.01


def _edge_stats(faces: np.ndarray) -> tuple[int, int, int]:
    """(boundary, non-manifold, misoriented) undirected edge counts of faces [F, 3]: used once,
    more than twice, or twice in the same direction."""
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    undirected = np.sort(directed, 1)
    _, inv, counts = np.unique(undirected, axis=0, return_inverse=True, return_counts=True)
    forward = np.zeros(len(counts), np.int64)
    np.add.at(forward, inv.reshape(-1), (directed[:, 0] < directed[:, 1]).astype(np.int64))
    return int((counts == 1).sum()), int((counts > 2).sum()), int(((counts == 2) & (forward != 1)).sum())


def signed_volume(vertices: np.ndarray, faces: np.ndarray) -> float:
    """Volume enclosed by faces [F, 3] (divergence theorem; negative when wound inwards, meaningless
    when open)."""
    t = np.asarray(vertices, np.float64)[np.asarray(faces, np.int64)]
    return float(np.einsum("ij,ij->i", t[:, 0], np.cross(t[:, 1], t[:, 2])).sum() / 6.0)


def manifold_pieces(faces: np.ndarray) -> np.ndarray:
    """Piece label [F] of each face: faces connected through edges shared by exactly two faces.
    A non-manifold edge (a fin, two solids touching along an edge) separates pieces."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    f = len(faces)
    directed = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    owner = np.tile(np.arange(f), 3)
    _, inv, counts = np.unique(np.sort(directed, 1), axis=0, return_inverse=True, return_counts=True)
    inv = inv.reshape(-1)
    shared = counts[inv] == 2
    order = np.argsort(inv[shared], kind="stable")
    pairs = owner[shared][order].reshape(-1, 2)
    graph = coo_matrix((np.ones(len(pairs)), (pairs[:, 0], pairs[:, 1])), shape=(f, f))
    return connected_components(graph, directed=False)[1]


def _meshfix(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """MeshFix (pymeshfix) on one piece: fills holes, removes non-manifold and self-intersecting
    faces, orients consistently. Returns empty arrays when nothing closed survives."""
    import pymeshfix

    v, f = pymeshfix.clean_from_arrays(
        np.ascontiguousarray(vertices, np.float64), np.ascontiguousarray(faces, np.int32), remove_smallest_components=False
    )
    return np.asarray(v, np.float64).reshape(-1, 3), np.asarray(f, np.int64).reshape(-1, 3)


def _close_piece(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray, set[str]]:
    """One manifold-connected piece made closed and outward: winding fixed by trimesh when only
    the orientation is wrong, else MeshFix. Returns (vertices, faces, tools used)."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    mesh.remove_unreferenced_vertices()
    boundary, nonmanifold, misoriented = _edge_stats(np.asarray(mesh.faces))
    tools: set[str] = set()
    if boundary or nonmanifold:
        v, f = _meshfix(mesh.vertices, mesh.faces)
        tools.add("meshfix")
        if len(f) == 0:
            return v, f, tools
        mesh = trimesh.Trimesh(v, f, process=False)
    elif misoriented:
        trimesh.repair.fix_winding(mesh)
        tools.add("trimesh")
    if signed_volume(mesh.vertices, mesh.faces) < 0:
        mesh.invert()
        tools.add("trimesh")
    return np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64), tools


def _face_keys(vertices: np.ndarray, faces: np.ndarray, scale: float) -> list[tuple]:
    """Orientation-free identity of each face: its corner positions quantised by `scale`, sorted."""
    q = np.round(np.asarray(vertices)[faces] / scale).astype(np.int64)
    return [tuple(sorted(map(tuple, corners))) for corners in q.tolist()]


def repair_mesh(vertices: np.ndarray, faces: np.ndarray, face_data: dict[str, np.ndarray] | None = None):
    """A closed, consistently outward-oriented surface from vertices [V, 3] and faces [F, 3], or
    RepairError with the reason when none can be made.

    Steps: weld duplicate vertices, drop degenerate and duplicate faces (trimesh); split into
    pieces at non-manifold edges; close each open piece with MeshFix (holes, non-manifold and
    self-intersecting faces) or fix its winding (trimesh); drop open debris sheets (under
    SHEET_AREA_LIMIT of the area), refuse larger ones; merge pieces that overlap or touch with a
    boolean union (manifold3d), whose validity check is the final proof the result is closed.
    Per-face arrays in `face_data` ([F, ...]) follow the faces; new faces take the value of their
    nearest original face. Returns (vertices [V', 3], faces [F', 3], face_data', RepairReport).
    """
    import trimesh

    face_data = {k: np.asarray(v) for k, v in (face_data or {}).items()}
    v_in = np.asarray(vertices, np.float64)
    f_in = np.asarray(faces, np.int64)
    mesh, keep, welded = _weld_and_clean(v_in, f_in)
    v0, f0 = np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64)
    boundary, nonmanifold, misoriented = _edge_stats(f0)
    volume_before = signed_volume(v0, f0)
    labels = manifold_pieces(f0)
    solids, dropped, tools = _close_pieces(v0, f0, labels, mesh.area_faces)
    solids, merged = _union_if_touching(solids)
    if merged:
        tools.add("manifold")
    offsets = np.cumsum([0] + [len(v) for v, _ in solids])
    v_out = np.concatenate([v for v, _ in solids])
    f_out = np.concatenate([f + o for (_, f), o in zip(solids, offsets)])
    result = trimesh.Trimesh(v_out, f_out, process=False)
    if not signed_volume(v_out, f_out) > 0:
        raise RepairError("the mesh encloses no volume (flat or degenerate), so it has no mass")
    matched, source, flipped = _match_original_faces(mesh, result)
    kept_ids = source[matched]
    keep_idx = np.flatnonzero(keep)
    face_data = {k: d[keep_idx][source] for k, d in face_data.items()}
    report = RepairReport(
        vertices_welded=welded,
        faces_removed=len(f_in) - len(np.unique(kept_ids)),
        faces_added=int((~matched).sum()),
        faces_flipped=flipped,
        boundary_edges=boundary,
        nonmanifold_edges=nonmanifold,
        misoriented_edges=misoriented,
        pieces=int(labels.max()) + 1,
        pieces_dropped=dropped,
        pieces_merged=bool(merged),
        volume_before=volume_before,
        volume_after=signed_volume(v_out, f_out),
        tools=tuple(sorted(tools)),
    )
    return v_out, f_out, face_data, report


def _weld_and_clean(v_in: np.ndarray, f_in: np.ndarray) -> tuple[trimesh.Trimesh, np.ndarray, int]:
    """The trimesh of vertices [V, 3] and faces [F, 3] welded, without degenerate, duplicate or unused elements.

    Returns (mesh, keep [F] bool: the input faces kept, number of vertices welded away).
    """
    import trimesh

    if len(f_in) == 0 or not np.all(np.isfinite(v_in)):
        raise RepairError("the mesh is empty or has non-finite vertices")
    mesh = trimesh.Trimesh(v_in, f_in, process=False)
    mesh.merge_vertices()
    welded = len(v_in) - len(mesh.vertices)
    keep = mesh.nondegenerate_faces() & mesh.unique_faces()
    mesh.update_faces(keep)
    mesh.remove_unreferenced_vertices()
    if len(mesh.faces) == 0:
        raise RepairError("the mesh has no faces with area, so it encloses no volume")
    return mesh, keep, welded


def _close_pieces(
    v0: np.ndarray, f0: np.ndarray, labels: np.ndarray, areas: np.ndarray
) -> tuple[list[tuple[np.ndarray, np.ndarray]], int, set[str]]:
    """Each piece (faces [F] labelled by `labels`) closed into a solid, small open sheets dropped, large ones refused.

    Returns (solids as (vertices, faces) pairs, number of sheets dropped, tools used).
    """
    total_area = float(areas.sum())
    min_volume = 1e-9 * float(np.ptp(v0, 0).max()) ** 3  # below this a piece is a sheet (back-to-back faces)
    solids, dropped, tools = [], 0, {"trimesh"}
    for label in range(int(labels.max()) + 1):
        sel = labels == label
        v, f, used = _close_piece(v0, f0[sel])
        tools |= used
        if len(f) and _edge_stats(f) == (0, 0, 0) and signed_volume(v, f) > min_volume:
            solids.append((v, f))
            continue
        share = float(areas[sel].sum()) / total_area
        if share >= SHEET_AREA_LIMIT:
            raise RepairError(
                f"the mesh cannot be closed: a piece of {int(sel.sum())} faces ({100 * share:.0f}% of its surface) is an open sheet with no inside"
            )
        dropped += 1
    if not solids:
        raise RepairError("the mesh cannot be closed: it is an open sheet with no inside")
    return solids, dropped, tools


def _union_if_touching(
    solids: list[tuple[np.ndarray, np.ndarray]],
) -> tuple[list[tuple[np.ndarray, np.ndarray]], bool]:
    """The solids, proven closed by manifold3d, merged into one by boolean union when any overlap or touch.

    Returns (solids, whether they were merged).
    """
    import manifold3d

    manifolds = [manifold3d.Manifold(manifold3d.Mesh64(vert_properties=v, tri_verts=f.astype(np.uint64))) for v, f in solids]
    bad = [m.status() for m in manifolds if m.status() != manifold3d.Error.NoError]
    if bad:
        raise RepairError(f"the mesh cannot be closed: after repair a piece is still not a closed surface ({bad[0].name})")
    if len(solids) <= 1:
        return solids, False
    union = manifold3d.Manifold.batch_boolean(manifolds, manifold3d.OpType.Add)
    separate = sum(m.volume() for m in manifolds)
    merged = union.volume() < separate * (1 - 1e-9) or union.num_tri() != sum(m.num_tri() for m in manifolds)
    if not merged:
        return solids, False
    out = union.to_mesh64()
    return [(np.asarray(out.vert_properties, np.float64)[:, :3], np.asarray(out.tri_verts, np.int64))], True


def _match_original_faces(mesh: trimesh.Trimesh, result: trimesh.Trimesh) -> tuple[np.ndarray, np.ndarray, int]:
    """Which of result's faces [F'] survived unchanged from the cleaned mesh's faces [F], and each one's source face.

    Returns (matched [F'] bool, source [F'] index into mesh's faces: the same face, or the nearest
    original for new faces, number of surviving faces whose winding was flipped).
    """
    from scipy.spatial import cKDTree

    v0, f0 = np.asarray(mesh.vertices), np.asarray(mesh.faces, np.int64)
    v_out, f_out = np.asarray(result.vertices), np.asarray(result.faces, np.int64)
    scale = max(float(np.ptp(v0, 0).max()), 1e-12) * 1e-9
    original = dict(zip(_face_keys(v0, f0, scale), range(len(f0))))
    matches = np.array([original.get(k, -1) for k in _face_keys(v_out, f_out, scale)])
    matched = matches >= 0
    n0 = mesh.face_normals[matches[matched]]
    flipped = int(((result.face_normals[matched] * n0).sum(1) < 0).sum())
    _, nearest = cKDTree(mesh.triangles_center).query(result.triangles_center)
    source = np.where(matched, matches, nearest)
    return matched, source, flipped


def mass_properties(vertices: np.ndarray, faces: np.ndarray, density: float) -> MassProperties:
    """Volume, mass, centre of mass and inertia (about the centre of mass) of the solid bounded by
    a closed, outward-oriented mesh (metres, kg/m^3); what `repair_mesh` returns. Anything else is
    refused: an open mesh has no inside, and its hull would overstate the mass."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    if not mesh.is_volume:
        raise RepairError("the mesh is not a closed, consistently oriented surface; repair it first (repair_mesh)")
    if not mesh.volume > 0:
        raise RepairError("the mesh encloses no volume (flat or degenerate), so it has no mass")
    props = mesh.mass_properties
    return MassProperties(
        volume=float(props.volume),
        mass=float(props.volume * density),
        center_of_mass=np.asarray(props.center_mass, np.float64),
        inertia=np.asarray(props.inertia, np.float64) * density,
    )


@dataclass
class SimAsset:
    """One rigid body: vertices [V, 3] metres (object frame), faces [F, 3], face_part [F] into
    part_names, face_rgb [F, 3] in [0, 1], its density, mass properties and repair report."""

    name: str
    vertices: np.ndarray
    faces: np.ndarray
    face_part: np.ndarray
    part_names: list[str]
    face_rgb: np.ndarray
    density: Density
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


def material_in_names(names: list[str]) -> str | None:
    """The first known material named in CAD material/part names (`Steel_AISI_304` -> steel)."""
    import re

    for name in names:
        for word in re.split(r"[^a-z]+", str(name).lower()):
            if word in MATERIAL_DENSITY:
                return word
    return None


def choose_density(
    density: float | None = None, material: str | None = None, *, cad_names: list[str] = (), rig: dict | None = None
) -> Density:
    """The body's density by precedence: flag (`density`, `material`), a material in the CAD's
    `cad_names`, rig.toml's [simulation] table `rig` ({"density": ..., "material": ...}), default."""
    if density is not None or material is not None:
        return Density(*resolve_density(density, material), "flag")
    cad = material_in_names(list(cad_names))
    if cad is not None:
        return Density(*resolve_density(None, cad), "cad")
    if rig and (rig.get("density") is not None or rig.get("material") is not None):
        return Density(*resolve_density(rig.get("density"), rig.get("material")), "rig.toml")
    return Density(*resolve_density(None, None), "default")


SIMULATION_KEYS = ("density", "material", "hull_budget", "up", "cad_up_axis")


def rig_simulation_table(path: str | os.PathLike) -> dict:
    """rig.toml's optional [simulation] table, checked; {} when it has none. Keys: material, density
    (of exported twins); hull_budget (most convex hulls of a collision decomposition); up (the rig
    frame's up, [3]); cad_up_axis (the CAD models' declared up axis, "+y", "z", ...)."""
    import tomllib

    try:
        doc = tomllib.loads(Path(path).read_text())
    except FileNotFoundError:
        raise ValueError(f"{path}: no such rig config file") from None
    except tomllib.TOMLDecodeError as e:
        raise ValueError(f"{path}: not valid TOML ({e})") from None
    from simulation.up import axis_vector, unit

    table = doc.get("simulation", {})
    extra = sorted(set(table) - set(SIMULATION_KEYS))
    if extra:
        raise ValueError(f"{path}: unknown key simulation.{extra[0]} (known: {', '.join(SIMULATION_KEYS)})")
    resolve_density(table.get("density"), table.get("material"))
    budget = table.get("hull_budget")
    if budget is not None and not (isinstance(budget, int) and not isinstance(budget, bool) and 1 <= budget <= 10000):
        raise ValueError(f"{path}: simulation.hull_budget must be an integer from 1 to 10000, got {budget!r}")
    try:
        if table.get("up") is not None:
            unit(table["up"], "simulation.up")
        if table.get("cad_up_axis") is not None:
            axis_vector(table["cad_up_axis"])
    except ValueError as e:
        raise ValueError(f"{path}: {e}") from None
    return table


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


def build_asset(name: str, parts: MeshParts, *, face_rgb: np.ndarray | None = None, density: Density | None = None) -> SimAsset:
    """Repair `parts` (metres, object frame) into a closed solid and compute its mass properties
    (RepairError when it cannot be closed). Faces without a colour are mid grey."""
    density = density or choose_density()
    rgb = np.full((len(parts.faces), 3), 0.5) if face_rgb is None else np.asarray(face_rgb, np.float64)
    try:
        v, f, data, report = repair_mesh(np.asarray(parts.vertices, np.float64), parts.faces, {"part": parts.face_part, "rgb": rgb})
    except RepairError as e:
        raise RepairError(f"{name}: {e}") from None
    return SimAsset(
        name=name,
        vertices=v,
        faces=f,
        face_part=data["part"].astype(np.int64),
        part_names=list(parts.part_names),
        face_rgb=data["rgb"],
        density=density,
        mass=mass_properties(v, f, density.value),
        repair=report,
    )


def asset_from_twin(twin: Twin, name: str | None = None, *, density: Density | None = None) -> SimAsset:
    """The twin's deformed CAD mesh as a rigid body, faces coloured from the nearby splats."""
    parts = twin.load_mesh_deformed()
    centres = parts.vertices[parts.faces].mean(1)
    g = twin.gaussians
    opacity = g.activated()[3].numpy().astype(np.float64)
    rgb = bake_face_colors(centres, g.means, sh_dc_rgb(g.sh[:, 0]), opacity)
    return build_asset(name or twin.model_id, parts, face_rgb=rgb, density=density)


def load_mesh_asset(
    path: str | os.PathLike,
    unit: str | None = None,
    name: str | None = None,
    *,
    density: Density | None = None,
    split_components: bool = False,
) -> SimAsset:
    """A CAD/mesh file as a rigid body. `unit` (m, mm, cm, in) may be omitted only when the file
    name declares it (`part.unitsmm.stl`) or a units.json beside it does; it is never guessed.

    Parts are the file's (GLB nodes, OBJ objects), as in a twin of the same file; `split_components`
    makes each connected piece of a single-part file (an STL of several solids) its own part."""
    path = Path(path)
    unit = unit or unit_of(path, "")
    if unit not in UNIT_TO_M:
        raise ValueError(f"{path.name}: declare its unit (one of {', '.join(UNIT_TO_M)}); mesh files do not say")
    parts = read_mesh_parts(path, weld=True, split_components=split_components)
    metric = MeshParts(parts.vertices * UNIT_TO_M[unit], parts.faces, parts.face_part, parts.part_names)
    return build_asset(name or path.name.split(".")[0], metric, face_rgb=parts.face_rgb, density=density)
