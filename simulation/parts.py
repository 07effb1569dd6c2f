"""CAD parts: labels from the file (GLB nodes, OBJ objects/groups), else connected components;
every splat inherits its face's part; exploded views translate parts away from the assembly centre.

Part labels are what makes a twin editable: the paper's exploded skateboard moves the wheels'
Gaussians off their axles while the deck stays put (section 5).
"""

from __future__ import annotations

import os
from collections.abc import Iterable, Sequence
from dataclasses import replace
from pathlib import Path

import numpy as np

from reconstruction.gaussians import Gaussians
from reconstruction.twin import MeshParts, Twin, object_frame_from_file

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


def _merged(vertices: np.ndarray, faces: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Weld vertices at identical positions (UV seams split them in OBJ files); faces keep their order."""
    uniq, inverse = np.unique(np.asarray(vertices, np.float64), axis=0, return_inverse=True)
    return uniq, inverse.reshape(-1)[np.asarray(faces, np.int64)]


def read_mesh_parts(path: str | os.PathLike) -> tuple[MeshParts, np.ndarray | None]:
    """A CAD/mesh file -> (MeshParts in the file's own units, face colours [F, 3] in [0, 1] or None).

    Parts: GLB/glTF nodes, OBJ objects or groups; a single-piece file is split into connected
    components (`component_0`, ...). Colours come from the file's texture or colours when it has them.
    """
    import trimesh

    path = Path(path)
    if not path.exists():
        raise FileNotFoundError(f"{path}: no such mesh file")
    kwargs = {"split_objects": True, "split_groups": True} if path.suffix.lower() == ".obj" else {}
    try:
        loaded = trimesh.load(str(path), force="scene", process=False, **kwargs)
    except Exception as e:  # trimesh raises many types on bad files
        raise ValueError(f"{path}: cannot be read as a mesh ({type(e).__name__}: {e})") from None
    verts, faces, labels, names, colors = [], [], [], [], []
    offset = 0
    to_object = object_frame_from_file(loaded)  # a twin's own GLB comes back in its object frame
    for node in loaded.graph.nodes_geometry:
        transform, geom_name = loaded.graph[node]
        mesh = loaded.geometry[geom_name]
        if not isinstance(mesh, trimesh.Trimesh) or len(mesh.faces) == 0:
            continue
        verts.append(trimesh.transform_points(mesh.vertices, to_object @ transform))
        faces.append(np.asarray(mesh.faces, np.int64) + offset)
        labels.append(np.full(len(mesh.faces), len(names)))
        names.append(str(node))
        colors.append(_face_colors(mesh))
        offset += len(mesh.vertices)
    if not names:
        raise ValueError(f"{path}: holds no triangles")
    vertices, all_faces = _merged(np.concatenate(verts), np.concatenate(faces))
    face_part = np.concatenate(labels)
    if len(names) == 1:
        face_part = component_labels(all_faces, len(vertices))
        names = [f"component_{i}" for i in range(int(face_part.max()) + 1)]
    face_rgb = None if any(c is None for c in colors) else np.concatenate(colors)
    return MeshParts(vertices, all_faces, face_part, names), face_rgb


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


def splat_parts(face_index: np.ndarray, face_part: np.ndarray) -> np.ndarray:
    """Part label of each splat [N] from the face it lies on (face_index [N], face_part [F])."""
    return np.asarray(face_part, np.int64)[np.asarray(face_index, np.int64)]


def part_indices(names: Iterable[str | int], part_names: Sequence[str]) -> list[int]:
    """Part names or indices -> indices; an unknown part is a ValueError naming the known ones."""
    out = []
    for p in names:
        if isinstance(p, str) and p in part_names:
            i = list(part_names).index(p)
        elif isinstance(p, (int, np.integer)) or (isinstance(p, str) and p.isdigit()):
            i = int(p)
            if not 0 <= i < len(part_names):
                raise ValueError(f"part index {i} is out of range; the twin has {len(part_names)} parts")
        else:
            raise ValueError(f"no part named {p!r}; the parts are {', '.join(part_names)}")
        out.append(i)
    return out


def part_centroids(means: np.ndarray, part_label: np.ndarray, num_parts: int) -> np.ndarray:
    """Mean splat position of each part [P, 3]; parts without splats get NaN."""
    sums = np.zeros((num_parts, 3))
    np.add.at(sums, part_label, np.asarray(means, np.float64))
    counts = np.bincount(part_label, minlength=num_parts).astype(np.float64)
    with np.errstate(invalid="ignore", divide="ignore"):
        return sums / counts[:, None]


def explode_offsets(centroids: np.ndarray, factor: float, centre: np.ndarray | None = None, moving: np.ndarray | None = None) -> np.ndarray:
    """Per-part translations [P, 3] = factor * (centroid - centre), zero for parts not in `moving` [P] bool.

    `centre` defaults to the mean of the (finite) part centroids, so a part at the centre of the
    assembly (the deck) stays where it is while outer parts (the wheels) slide outwards.
    """
    c = np.asarray(centroids, np.float64)
    finite = np.all(np.isfinite(c), 1)
    centre = c[finite].mean(0) if centre is None else np.asarray(centre, np.float64)
    off = float(factor) * np.where(finite[:, None], c - centre, 0.0)
    if moving is not None:
        off[~np.asarray(moving, bool)] = 0.0
    return off


def explode(means: np.ndarray, part_label: np.ndarray, num_parts: int, factor: float, moving: np.ndarray | None = None) -> np.ndarray:
    """Exploded splat means [N, 3]: each part translated away from the assembly centre by `factor`."""
    off = explode_offsets(part_centroids(means, part_label, num_parts), factor, moving=moving)
    return (np.asarray(means, np.float64) + off[part_label]).astype(np.float32)


def list_parts(twin: Twin) -> list[tuple[int, str, int]]:
    """(index, name, splat count) of each part of `twin`."""
    counts = np.bincount(twin.part_label, minlength=len(twin.part_names))
    return [(i, name, int(counts[i])) for i, name in enumerate(twin.part_names)]


def exploded_splats(twin: Twin, factor: float, hidden: Iterable[str | int] = (), moving: Iterable[str | int] | None = None) -> tuple[Gaussians, np.ndarray]:
    """The twin's Gaussians with its parts exploded by `factor` and the `hidden` parts removed, and the
    part label [M] of each kept one. `moving` limits the explosion to those parts (default: all). Names or indices.
    """
    if not np.isfinite(factor) or factor < 0:
        raise ValueError(f"explode factor must be a finite number >= 0, got {factor}")
    p = len(twin.part_names)
    move_mask = None
    if moving is not None:
        move_mask = np.zeros(p, bool)
        move_mask[part_indices(moving, twin.part_names)] = True
    g = twin.gaussians
    exploded = replace(g, means=explode(g.means, twin.part_label, p, factor, move_mask))
    keep = ~np.isin(twin.part_label, part_indices(hidden, twin.part_names))
    return exploded.subset(keep), twin.part_label[keep]
