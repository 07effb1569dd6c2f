"""The twin's surface: the CAD mesh as the fit moved it, out to where its splats' alpha falls to 1/2,
and still a plausible surface (nothing folds through itself that did not in the CAD).

Pure functions on vertex arrays; the faces, and with them the part labels, are the CAD's throughout.
"""

from __future__ import annotations

import numpy as np

from reconstruction.gaussians import Gaussians
from reconstruction.splats import alpha_half_reach


def silhouette_surface(vertices: np.ndarray, faces: np.ndarray, gaussians: Gaussians) -> np.ndarray:
    """Vertices [V, 3] of a mesh whose splats sit on it, moved out along their normals to where the splats'
    alpha falls to 1/2: the surface the silhouettes and images were fitted to. Splats centred on a
    surface render it larger by that reach, so the fit pulls their centres (and the mesh through them)
    inside the object by as much (rig scenes: 0.4-1.35 mm, 11-39 % of the volume).

    faces [F, 3]; gaussians: the fitted splats (object frame). Every vertex moves by the splats' median
    reach: a neighbourhood's median follows single large splats at thin edges outwards (rig scenes,
    8 nearest splats: the toy airplane 0.72 -> 0.92 % of the diameter from the truth) and makes
    spikes an inspection reads as defects.
    """
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    normals = np.asarray(mesh.vertex_normals, np.float64)
    # Face winding gives the normals' side; a consistently wound mesh with negative volume points inward.
    if mesh.is_winding_consistent and mesh.volume < 0:
        normals = -normals
    return np.asarray(vertices, np.float64) + normals * float(np.median(alpha_half_reach(gaussians)))


def self_intersecting_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[F] bool: the faces that cross another face of the mesh (vertices [V, 3], faces [F, 3]); faces that
    only share a vertex or an edge do not count (libigl, AABB tree and exact predicates)."""
    from igl.predicates import find_self_intersections

    out = np.zeros(len(faces), bool)
    if len(faces) == 0:
        return out
    _, pairs, _ = find_self_intersections(np.ascontiguousarray(vertices, np.float64), np.ascontiguousarray(faces, np.int64))
    out[np.asarray(pairs, np.int64).reshape(-1)] = True
    return out


def untangle(rest: np.ndarray, moved: np.ndarray, faces: np.ndarray, rounds: int = 8) -> tuple[np.ndarray, np.ndarray]:
    """`moved` [V, 3] pulled back towards `rest` [V, 3] (the same faces [F, 3]) around every face that
    crosses another where it did not in `rest`: the vertices of such faces halve their move, round after
    round, and after `rounds` go back to rest until nothing new crosses (rest itself is the end point).
    Returns (vertices [V, 3], kept [V]: the fraction of its move each vertex kept)."""
    rest = np.asarray(rest, np.float64)
    move = np.asarray(moved, np.float64) - rest
    faces = np.asarray(faces, np.int64)
    already = self_intersecting_faces(rest, faces)
    kept = np.ones(len(rest))
    for r in range(rounds + len(rest)):
        out = rest + kept[:, None] * move
        new = self_intersecting_faces(out, faces) & ~already
        if not new.any():
            return out, kept
        at = np.unique(faces[new])
        kept[at] = 0.5 * kept[at] if r < rounds else 0.0
    return rest + kept[:, None] * move, kept
