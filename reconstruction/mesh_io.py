"""Mesh files: read into named parts, write the twin's GLB, and the unit a mesh file declares.

`read_mesh_parts` is the one reader (the library, twins, `reconstruct` and `simulate` all use it):
any file trimesh reads -> `MeshParts` in the file's own units, one part per GLB/glTF node or OBJ
object/group, face colours when the file has them. Two explicit options: `weld` merges vertices
at the same position (STL and UV-seamed OBJ files repeat them), `split_components` gives each
connected piece of a single-part file its own part. No caller splits by default, so a one-piece
STL is one part in the library, in a twin and in a simulation alike.

Units: a file's unit comes from its name (`counter.unitsmm.stl`) or a `units.json` beside it; the
table of unit names is `calibration.units`.
"""

from __future__ import annotations

import json
import os
import re
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from calibration.units import UNIT_TO_M

_UNIT_TAG = re.compile(r"\.units(" + "|".join(sorted(UNIT_TO_M, key=len, reverse=True)) + r")$", re.IGNORECASE)

# glTF is +Y up; the object frame is z up (the rig's table). Our GLBs put the parts under this root
# node, a -90 degree turn about x (+z -> +y), so a glTF viewer shows the part standing as on the rig;
# `read_mesh_parts` knows the node and takes the parts back in the object frame.
GLTF_Y_UP_NODE = "cadsplat_object_z_up"
Z_UP_TO_Y_UP = np.array([[1.0, 0.0, 0.0, 0.0], [0.0, 0.0, 1.0, 0.0], [0.0, -1.0, 0.0, 0.0], [0.0, 0.0, 0.0, 1.0]])


class MeshError(ValueError):
    """A mesh file that cannot be read or used as it is: `path` and the `reason`, one plain sentence."""

    def __init__(self, path: str | os.PathLike, reason: str):
        super().__init__(path, reason)
        self.path, self.reason = path, reason

    def __str__(self) -> str:
        return f"{self.path}: {self.reason}"


@dataclass
class MeshParts:
    """A triangle mesh split into named parts: `vertices` [V, 3], `faces` [F, 3], `face_part` [F] int
    into `part_names`, and `face_rgb` [F, 3] in [0, 1] when the file gave colours (else None)."""

    vertices: np.ndarray
    faces: np.ndarray
    face_part: np.ndarray
    part_names: list[str]
    face_rgb: np.ndarray | None = None


def component_labels(faces: np.ndarray, num_vertices: int) -> np.ndarray:
    """Connected-component label [F] of each face (faces sharing a vertex are connected), numbered
    by first appearance so the labelling is deterministic."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components

    faces = np.asarray(faces, np.int64)
    f = len(faces)
    # Bipartite face-vertex graph: components of it are the mesh's connected pieces.
    rows = np.repeat(np.arange(f), 3)
    cols = f + faces.reshape(-1)
    n = f + int(num_vertices)
    graph = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
    _, labels = connected_components(graph, directed=False)
    face_labels = labels[:f]
    _, first, inverse = np.unique(face_labels, return_index=True, return_inverse=True)
    order = np.argsort(np.argsort(first))
    return order[inverse].astype(np.int64)


def weld_vertices(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Vertices at the same position (to trimesh's merge tolerance) merged and unused ones dropped:
    (vertices [V', 3] float64, faces [F, 3]); faces keep their count and order."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    with np.errstate(invalid="ignore"):  # a non-finite vertex is the caller's to report, not a cast warning
        mesh.merge_vertices()
    return np.asarray(mesh.vertices, np.float64), np.asarray(mesh.faces, np.int64)


def _load_scene(path: Path):
    """The file as a trimesh.Scene (unprocessed; OBJ objects and groups as separate geometries)."""
    import trimesh

    kwargs = {"split_objects": True, "split_groups": True} if path.suffix.lower() == ".obj" else {}
    try:
        return trimesh.load(str(path), force="scene", process=False, **kwargs)
    except Exception as e:  # trimesh raises many types on bad files
        raise MeshError(path, f"cannot be read as a mesh ({type(e).__name__}: {e})") from None


def read_mesh_parts(path: str | os.PathLike, *, weld: bool = False, split_components: bool = False) -> MeshParts:
    """A mesh file (a GLB written by `parts_glb_bytes`, a CAD export, a PLY, a textured OBJ) ->
    MeshParts in the file's own units, one part per scene node named after it.

    `weld`: merge vertices at the same position (`weld_vertices`). `split_components`: a file with a single part is
    split into its connected pieces (`component_0`, ...; pieces sharing a vertex are one piece, so
    an unwelded file is welded first). Raises MeshError for a missing, unreadable or empty file.
    """
    import trimesh

    path = Path(path)
    if not path.is_file():
        raise MeshError(path, "no such mesh file")
    scene = _load_scene(path)
    verts, faces, labels, names, colors = [], [], [], [], []
    offset = 0
    to_object = _object_frame(scene)  # a twin's own GLB comes back in its object frame
    for node in scene.graph.nodes_geometry:
        transform, geom_name = scene.graph[node]
        mesh = scene.geometry[geom_name]
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            continue
        verts.append(trimesh.transform_points(mesh.vertices, to_object @ transform))
        faces.append(np.asarray(mesh.faces, np.int64) + offset)
        labels.append(np.full(len(mesh.faces), len(names)))
        names.append(str(node))
        colors.append(_face_colors(mesh))
        offset += len(mesh.vertices)
    if not names:
        raise MeshError(path, "holds no triangles")
    vertices, all_faces = np.concatenate(verts), np.concatenate(faces)
    if weld or (split_components and len(names) == 1):
        vertices, all_faces = weld_vertices(vertices, all_faces)
    face_part = np.concatenate(labels)
    if split_components and len(names) == 1:
        face_part = component_labels(all_faces, len(vertices))
        names = [f"component_{i}" for i in range(int(face_part.max()) + 1)]
    face_rgb = None if any(c is None for c in colors) else np.concatenate(colors)
    return MeshParts(vertices, all_faces, face_part, names, face_rgb)


def _face_colors(mesh) -> np.ndarray | None:
    """Mean vertex colour [F, 3] in [0, 1] from a texture or colour visual; None for an untextured mesh."""
    visual = mesh.visual
    if visual.kind is None:
        return None
    try:
        vc = np.asarray(visual.to_color().vertex_colors if visual.kind == "texture" else visual.vertex_colors)
    except (AttributeError, ValueError, IndexError):
        return None
    if vc.shape[0] != len(mesh.vertices):
        return None
    return vc[np.asarray(mesh.faces)][..., :3].mean(1) / 255.0


def material_names(path: str | os.PathLike) -> list[str]:
    """Names of the materials a mesh file gives its geometry (OBJ's usemtl, glTF materials): where a
    CAD export says what a part is made of (`Steel_AISI_304`). Empty when it names none or cannot be read."""
    import trimesh

    try:
        scene = trimesh.load(str(path), force="scene", process=False)
    except Exception:  # an unreadable file names no material; reading its mesh reports the error
        return []
    names = []
    for node in scene.graph.nodes_geometry:
        material = getattr(getattr(scene.geometry[scene.graph[node][1]], "visual", None), "material", None)
        if getattr(material, "name", None):
            names.append(str(material.name))
    return names


def parts_glb_bytes(parts: MeshParts) -> bytes:
    """GLB with one node per part, named after the part (empty parts are left out), under the
    GLTF_Y_UP_NODE root so the z-up object frame stands upright in +Y-up viewers."""
    import trimesh

    scene = trimesh.Scene(base_frame="world")
    scene.graph.update(frame_from="world", frame_to=GLTF_Y_UP_NODE, matrix=Z_UP_TO_Y_UP)
    for p, name in enumerate(parts.part_names):
        sel = np.flatnonzero(parts.face_part == p)
        if sel.size == 0:
            continue
        sub = trimesh.Trimesh(parts.vertices, parts.faces[sel], process=False)
        sub.remove_unreferenced_vertices()
        scene.add_geometry(sub, node_name=name, geom_name=name, parent_node_name=GLTF_Y_UP_NODE)
    return scene.export(file_type="glb")


def _object_frame(scene) -> np.ndarray:
    """[4, 4] taking a loaded trimesh.Scene's world coordinates to the object frame: the inverse of
    our Y-up root when the file has it (GLBs written by `parts_glb_bytes`), else identity."""
    if GLTF_Y_UP_NODE in scene.graph.nodes:
        return np.linalg.inv(scene.graph.get(GLTF_Y_UP_NODE)[0])
    return np.eye(4)


def unit_of(path: Path, default: str) -> str:
    """Declared unit of a mesh file: a `.units<u>` name tag, then `units.json` beside it (file name ->
    unit), then `default`. A units.json that cannot be read or names an unknown unit is a MeshError."""
    tag = _UNIT_TAG.search(path.stem)
    if tag:
        return tag.group(1).lower()
    table = path.parent / "units.json"
    if table.exists():
        try:
            declared = json.loads(table.read_text())
        except json.JSONDecodeError as e:
            raise MeshError(table, f"invalid JSON ({e.msg} at line {e.lineno})") from None
        unit = declared.get(path.name)
        if unit is not None:
            if unit not in UNIT_TO_M:
                raise MeshError(table, f"unit {unit!r} for {path.name} is not one of {', '.join(UNIT_TO_M)}")
            return unit
    return default
