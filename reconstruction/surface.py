"""The twin's surface: the CAD mesh as the fit moved it, out to where its splats' alpha falls to 1/2,
and still a plausible surface (nothing folds through itself that did not in the CAD).

Pure functions on vertex arrays; the faces, and with them the part labels, are the CAD's throughout.
"""

from __future__ import annotations

from collections.abc import Sequence

import numpy as np

from calibration.camera import Camera
from reconstruction.gaussians import Gaussians
from reconstruction.splats import alpha_half_reach


def offset_along_normals(vertices: np.ndarray, faces: np.ndarray, distance: float) -> np.ndarray:
    """Vertices [V, 3] moved `distance` along their outward vertex normals (faces [F, 3]; negative: inwards)."""
    import trimesh

    mesh = trimesh.Trimesh(vertices, faces, process=False)
    normals = np.asarray(mesh.vertex_normals, np.float64)
    # Face winding gives the normals' side; a consistently wound mesh with negative volume points inward.
    if mesh.is_winding_consistent and mesh.volume < 0:
        normals = -normals
    return np.asarray(vertices, np.float64) + normals * float(distance)


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
    return offset_along_normals(vertices, faces, float(np.median(alpha_half_reach(gaussians))))


def silhouette_pixels(vertices: np.ndarray, faces: np.ndarray, cameras: Sequence[Camera]) -> int:
    """Pixels the mesh (vertices [V, 3], faces [F, 3]) covers, summed over `cameras`."""
    from reconstruction.inspect import rasterize_mesh

    return int(sum(int(np.count_nonzero(rasterize_mesh(vertices, faces, cam)[1] >= 0)) for cam in cameras))


def mask_area_offset(vertices: np.ndarray, faces: np.ndarray, cameras: Sequence[Camera], masks: np.ndarray,
                     bracket: float, steps: int = 10) -> float:
    """The distance along the normals (within +-`bracket`, units of the vertices) at which the mesh's
    silhouettes in `cameras` cover as many pixels as `masks` [V, H, W] bool do: the area grows with the
    distance, so bisection finds it; a mesh that needs more than the bracket gets the bracket's end.

    Splats blend into one another at the rim, so their union reaches past any single splat's own alpha-1/2
    radius; the masks say by how much (rig scenes: the alpha-1/2 surface covers 0.967-1.000 of the mask pixels).
    """
    target = int(np.count_nonzero(masks))
    lo, hi = -float(bracket), float(bracket)
    for _ in range(steps):
        mid = 0.5 * (lo + hi)
        if silhouette_pixels(offset_along_normals(vertices, faces, mid), faces, cameras) < target:
            lo = mid
        else:
            hi = mid
    return 0.5 * (lo + hi)


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
