"""The twin's surface: the CAD mesh as the fit moved it, out to where its splats' alpha falls to 1/2,
and still a plausible surface (nothing folds through itself that did not in the CAD).

Pure functions on vertex arrays; the faces, and with them the part labels, are the CAD's throughout.
"""

from __future__ import annotations

from collections.abc import Sequence
from typing import TYPE_CHECKING

import numpy as np

from calibration.camera import Camera
from reconstruction.gaussians import Gaussians
from reconstruction.silhouette import closed_winding, render_silhouette
from reconstruction.splats import alpha_half_reach

if TYPE_CHECKING:
    import scipy.sparse


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
    inside the object by as much (measured on the rig scenes: benchmarks/results/twin_physics.md).

    faces [F, 3]; gaussians: the fitted splats (object frame). Every vertex moves by the splats' median
    reach: a neighbourhood's median follows single large splats at thin edges outwards and makes
    spikes an inspection reads as defects (benchmarks/results/twin_physics.md).
    """
    return offset_along_normals(vertices, faces, float(np.median(alpha_half_reach(gaussians))))


def silhouette_overlap(
    vertices: np.ndarray, faces: np.ndarray, cameras: Sequence[Camera], masks: np.ndarray, *, winding: int | None = None
) -> float:
    """Intersection over union, pooled over `cameras`, of the mesh's silhouettes (vertices [V, 3], faces [F, 3])
    and `masks` [C, H, W] bool (0 when both are empty); views of mixed sizes sit top-left on the masks' canvas.
    `winding`: the mesh's `closed_winding` (found here when not given)."""
    if winding is None:
        winding = closed_winding(vertices, faces)
    inter = union = 0
    for cam, mask in zip(cameras, masks, strict=True):
        covered = render_silhouette(vertices, faces, cam.K, cam.viewmat, cam.width, cam.height, winding=winding)
        mask = cam.crop(mask)
        inter += int(np.count_nonzero(covered & mask))
        union += int(np.count_nonzero(covered | mask))
    return inter / max(union, 1)


def mask_overlap_offset(
    vertices: np.ndarray, faces: np.ndarray, cameras: Sequence[Camera], masks: np.ndarray, bracket: float, steps: int = 14
) -> float:
    """The distance along the normals (within +-`bracket`, units of the vertices) at which the mesh's
    silhouettes in `cameras` best overlap `masks` [C, H, W] bool: pooled IoU, golden-section search over one
    peak (0.24 % of the bracket after 14 steps; a mesh that needs more gets the bracket's end). The answer is
    the best distance evaluated, and 0 unless another overlaps strictly better (a flat overlap, such as a mesh
    out of every view, moves nothing).

    Splats blend into one another at the rim, so their union reaches past any single splat's own alpha-1/2
    radius; the masks say by how much. Overlap, not area: where the fit left a part beside its place, a step
    that matched the areas would shrink the whole part by the excess on one side and ignore the deficit on
    the other (measured on the rig scenes' spatula: benchmarks/results/twin_physics.md).
    """
    # A move of a few percent of the size keeps the faces and the side they face: one winding holds for every step.
    winding = closed_winding(vertices, faces)
    best = [0.0, silhouette_overlap(vertices, faces, cameras, masks, winding=winding)]

    def overlap(distance: float) -> float:
        value = silhouette_overlap(offset_along_normals(vertices, faces, distance), faces, cameras, masks, winding=winding)
        if value > best[1]:
            best[:] = [distance, value]
        return value

    ratio = (np.sqrt(5.0) - 1.0) / 2.0
    lo, hi = -float(bracket), float(bracket)
    x1, x2 = hi - ratio * (hi - lo), lo + ratio * (hi - lo)
    f1, f2 = overlap(x1), overlap(x2)
    for _ in range(steps):
        if f1 < f2:
            lo, x1, f1 = x1, x2, f2
            x2 = lo + ratio * (hi - lo)
            f2 = overlap(x2)
        else:
            hi, x2, f2 = x2, x1, f1
            x1 = hi - ratio * (hi - lo)
            f1 = overlap(x1)
    return float(best[0])


def self_intersecting_pairs(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[P, 2] int64, sorted rows without repeats: the pairs of faces (i < j) of the mesh (vertices [V, 3], faces
    [F, 3]) that cross each other; faces that only share a vertex or an edge do not count (libigl, AABB tree and
    exact predicates)."""
    from igl.predicates import find_self_intersections

    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    if len(faces) == 0:
        return np.zeros((0, 2), np.int64)
    _, pairs, _ = find_self_intersections(np.ascontiguousarray(vertices, np.float64), np.ascontiguousarray(faces))
    return np.unique(np.sort(np.asarray(pairs, np.int64).reshape(-1, 2), axis=1), axis=0)


def self_intersecting_faces(vertices: np.ndarray, faces: np.ndarray) -> np.ndarray:
    """[F] bool: the faces that cross another face of the mesh (vertices [V, 3], faces [F, 3])."""
    out = np.zeros(len(faces), bool)
    out[self_intersecting_pairs(vertices, faces).reshape(-1)] = True
    return out


def vertex_neighbour_mean(faces: np.ndarray, n_vertices: int) -> scipy.sparse.csr_matrix:
    """[V, V] sparse row-stochastic matrix: row v averages over the vertices sharing an edge with v (faces [F, 3]);
    a vertex on no edge keeps its own value."""
    import scipy.sparse as sp

    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    edges = np.concatenate([faces[:, [0, 1]], faces[:, [1, 2]], faces[:, [2, 0]]])
    edges = edges[edges[:, 0] != edges[:, 1]]
    rows = np.concatenate([edges[:, 0], edges[:, 1]])
    cols = np.concatenate([edges[:, 1], edges[:, 0]])
    adjacency = sp.coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n_vertices, n_vertices)).tocsr()
    adjacency.data[:] = 1.0
    alone = np.asarray(adjacency.sum(axis=1)).reshape(-1) == 0
    adjacency = (adjacency + sp.diags(alone.astype(np.float64))).tocsr()
    return (sp.diags(1.0 / np.asarray(adjacency.sum(axis=1)).reshape(-1)) @ adjacency).tocsr()


def untangle(
    rest: np.ndarray, moved: np.ndarray, faces: np.ndarray, smooth_rounds: int = 30, pull_rounds: int = 8
) -> tuple[np.ndarray, np.ndarray]:
    """`moved` [V, 3] with every crossing of two faces that did not cross in `rest` [V, 3] (the same faces
    [F, 3]) undone, the moves kept as far as they can be.

    First the move is smoothed where the surface folds: the vertices of both faces of each new crossing and
    their neighbours take their neighbours' mean move, round after round. A fold is a move that changes faster
    across the surface than the part is thick; the neighbours' mean keeps where the part went, where pulling back
    towards the CAD would undo the carry (measured on the rig scenes' spatula: benchmarks/results/twin_physics.md).
    Folds that `smooth_rounds` leave are pulled back: their faces' vertices halve their move towards `rest` for
    `pull_rounds` rounds, then go back to rest, until nothing new crosses (two faces at rest cross only as they
    did in rest, so this ends).
    Returns (vertices [V, 3], untangled [V] bool: the vertices whose move changed).
    """
    rest = np.asarray(rest, np.float64)
    faces = np.asarray(faces, np.int64).reshape(-1, 3)
    given = np.asarray(moved, np.float64) - rest
    move = given.copy()
    n_faces = max(len(faces), 1)
    crossing_in_rest = self_intersecting_pairs(rest, faces) @ np.array([n_faces, 1])

    def newly_crossing(vertices: np.ndarray) -> np.ndarray:
        pairs = self_intersecting_pairs(vertices, faces)
        return np.unique(pairs[~np.isin(pairs @ np.array([n_faces, 1]), crossing_in_rest)])

    neighbour_mean = vertex_neighbour_mean(faces, len(rest))
    for _ in range(smooth_rounds):
        folded = newly_crossing(rest + move)
        if len(folded) == 0:
            return rest + move, np.any(move != given, axis=1)
        at = np.zeros(len(rest), bool)
        at[faces[folded].reshape(-1)] = True
        at |= neighbour_mean @ at.astype(np.float64) > 0
        move[at] = (neighbour_mean @ move)[at]
    kept = np.ones(len(rest))
    pulls = 0
    while len(folded := newly_crossing(rest + kept[:, None] * move)):
        at = np.unique(faces[folded])
        kept[at] = 0.5 * kept[at] if pulls < pull_rounds else 0.0
        pulls += 1
    final = kept[:, None] * move
    return rest + final, np.any(final != given, axis=1)
