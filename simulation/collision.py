"""Collision geometry sized to need, per CAD part: a fitted primitive or one convex hull when either
is within a volume tolerance of the part, else a convex decomposition (CoACD) whose number of
pieces is chosen by that same tolerance.

Volume error is (V_collision - V_mesh) / V_mesh with V_collision the volume of the union of the
collision shapes (manifold3d booleans, so overlapping pieces are not counted twice). Primitives and
the hull enclose the mesh, so for them it equals 1 - IoU with the true solid. CoACD pieces
approximate from both sides and their error shrinks as the concavity threshold does: each run's
error sets the next threshold until the error is within tolerance. A physics engine pays for every
hull on every step, so a decomposition has a hull budget (`DecompositionOptions.hull_budget`, shared
among the parts by volume): a run over it sends the search back up between the finest threshold
within budget and the coarsest over it, and when no run lands within it CoACD merges its pieces
down to it. The volume error left at the budget is reported. The report also gives the
Hausdorff distance between the collision set's surface and the mesh's (see `hausdorff`).
"""

from __future__ import annotations

import multiprocessing as mp
import os
import signal
import sys
import time
from dataclasses import dataclass, field, replace

import numpy as np

# Primitives are cheapest and most stable in contact; the hull next; decomposition last.
PRIMITIVES = ("sphere", "box", "cylinder", "capsule")
DECOMPOSE_FACES = 4000  # CoACD's cost grows with the input; its pieces do not need a finer mesh
DEFAULT_TOLERANCE = 0.10
DEFAULT_HULL_BUDGET = 32  # Isaac Sim's convex decomposition defaults to a few dozen hulls
PR_SET_PDEATHSIG = 1  # linux/prctl.h
HAUSDORFF_SAMPLES = 5000  # per surface: spacing ~ sqrt(area / samples), 1.4 mm on a 0.1 m part


@dataclass(frozen=True)
class Primitive:
    """An MJCF primitive in the object frame: `kind`, MuJoCo `size` (half-sizes / radius, half-length),
    `transform` [4, 4] object-from-primitive (the primitive's axis is its local z), `volume` m^3."""

    kind: str
    size: tuple[float, ...]
    transform: np.ndarray
    volume: float


@dataclass(frozen=True)
class CollisionGeometry:
    """What the simulator collides with: `primitives` and convex `pieces` (vertex sets [M_i, 3],
    object frame). `kind` is a primitive kind or "hull" or "decomposition" for one part, "parts" when
    each CAD part got its own; `volume` of their union, `volume_error` (V - V_mesh) / V_mesh,
    `hausdorff` (m) between its surface and the mesh's, `seconds` to make it, `notes` why."""

    kind: str
    volume: float
    volume_error: float
    seconds: float
    primitives: tuple[Primitive, ...] = ()
    pieces: tuple[np.ndarray, ...] = ()
    notes: tuple[str, ...] = field(default_factory=tuple)
    hausdorff: float = float("nan")
    hull_budget: int | None = None

    @property
    def primitive(self) -> Primitive | None:
        """The single primitive when the whole body is one."""
        return self.primitives[0] if len(self.primitives) == 1 and not self.pieces else None

    @property
    def hull_count(self) -> int:
        return len(self.pieces)


@dataclass(frozen=True)
class DecompositionOptions:
    """CoACD settings. The first run uses concavity `threshold`; while the volume error exceeds the
    tolerance the next threshold is scaled by tolerance / error (at most `rounds` runs, not below
    `min_threshold`), so the piece count follows the error. `max_convex_hull` caps the pieces of a
    run (-1: no cap); `timeout_s` caps the wall clock of all runs for one part (past it the best so
    far, or the convex hull, is used and noted). The floor is low enough for thin parts such as a
    spatula's blade a few mm thick (benchmarks/results/twin_physics.md). `hull_budget` (None: no budget) is
    the most pieces the whole body may have; runs over it move the threshold back up (see the module
    docstring), which may take up to `rounds` runs."""

    threshold: float = 0.05
    min_threshold: float = 0.005
    rounds: int = 5
    max_convex_hull: int = -1
    hull_budget: int | None = DEFAULT_HULL_BUDGET
    timeout_s: float = 300.0
    resolution: int = 1000
    mcts_iterations: int = 30
    mcts_nodes: int = 10
    mcts_max_depth: int = 2
    seed: int = 0


def fit_box(vertices: np.ndarray) -> Primitive:
    """Minimum-volume oriented bounding box (trimesh's) of vertices [N, 3]."""
    import trimesh

    to_box, extents = trimesh.bounds.oriented_bounds(np.asarray(vertices, np.float64))
    half = np.asarray(extents, np.float64) / 2
    return Primitive("box", tuple(half.tolist()), np.linalg.inv(to_box), float(np.prod(extents)))


def fit_sphere(vertices: np.ndarray) -> Primitive:
    """Enclosing sphere of vertices [N, 3] about the better of the axis-aligned and oriented box
    centres (within a few per cent of the minimum sphere at a fraction of the cost of Welzl's)."""
    pts = np.asarray(vertices, np.float64)
    centres = [0.5 * (pts.min(0) + pts.max(0)), fit_box(pts).transform[:3, 3]]
    radii = [float(np.linalg.norm(pts - c, axis=1).max()) for c in centres]
    i = int(np.argmin(radii))
    t = np.eye(4)
    t[:3, 3] = centres[i]
    return Primitive("sphere", (radii[i],), t, float(4.0 / 3.0 * np.pi * radii[i] ** 3))


def _cylinder_about(points: np.ndarray, axis: np.ndarray) -> Primitive:
    """Smallest enclosing cylinder of points [N, 3] with its axis along `axis` [3]."""
    import trimesh
    from scipy.spatial import ConvexHull

    z = axis / np.linalg.norm(axis)
    x = np.cross(z, [1.0, 0.0, 0.0] if abs(z[0]) < 0.9 else [0.0, 1.0, 0.0])
    x /= np.linalg.norm(x)
    rot = np.stack([x, np.cross(z, x), z], 1)
    local = points @ rot
    xy = local[:, :2]
    centre_xy, r = trimesh.nsphere.minimum_nsphere(xy[ConvexHull(xy).vertices])
    lo, hi = local[:, 2].min(), local[:, 2].max()
    t = np.eye(4)
    t[:3, :3] = rot
    t[:3, 3] = rot @ np.array([centre_xy[0], centre_xy[1], 0.5 * (lo + hi)])
    return Primitive("cylinder", (float(r), float(hi - lo) / 2), t, float(np.pi * r * r * (hi - lo)))


def fit_cylinder(vertices: np.ndarray) -> Primitive:
    """Smallest enclosing cylinder of vertices [N, 3] over candidate axes: the oriented box's, the
    principal axes, and trimesh's direction search (which alone misses tilted axes); axis = local z."""
    import trimesh

    pts = np.asarray(vertices, np.float64)
    axes = list(fit_box(pts).transform[:3, :3].T)
    axes += list(np.linalg.svd(pts - pts.mean(0), full_matrices=False)[2])
    axes.append(np.asarray(trimesh.bounds.minimum_cylinder(pts)["transform"])[:3, 2])
    return min((_cylinder_about(pts, a) for a in axes), key=lambda p: p.volume)


def fit_capsule(vertices: np.ndarray) -> Primitive:
    """Smallest capsule enclosing vertices [N, 3] about the minimum cylinder's axis and radius.

    A point at axial |z| and radial rho is inside the capsule of half-length h when
    |z| <= h or (|z| - h)^2 + rho^2 <= r^2, so h = max(|z| - sqrt(r^2 - rho^2), 0).
    """
    cyl = fit_cylinder(vertices)
    r = cyl.size[0]
    local = (np.asarray(vertices, np.float64) - cyl.transform[:3, 3]) @ cyl.transform[:3, :3]
    rho2 = np.minimum((local[:, :2] ** 2).sum(1), r * r)
    h = float(max((np.abs(local[:, 2]) - np.sqrt(r * r - rho2)).max(), 0.0))
    return Primitive("capsule", (r, h), cyl.transform, float(np.pi * r * r * (2 * h) + 4.0 / 3.0 * np.pi * r**3))


def convex_volume(points: np.ndarray) -> float:
    from scipy.spatial import ConvexHull

    return float(ConvexHull(points).volume)


def hull_vertices(vertices: np.ndarray) -> np.ndarray:
    """Vertices [M, 3] of the convex hull of vertices [N, 3]."""
    from scipy.spatial import ConvexHull

    pts = np.asarray(vertices, np.float64)
    return pts[ConvexHull(pts).vertices]


def _die_with_parent(parent_pid: int) -> None:
    """Linux: have the kernel SIGKILL this child when the thread that started it goes, so a killed service
    leaves no CoACD running on (it did: minutes of CPU, holding the service's stdout open)."""
    if sys.platform.startswith("linux"):
        import ctypes

        ctypes.CDLL(None, use_errno=True).prctl(PR_SET_PDEATHSIG, signal.SIGKILL)
    if os.getppid() != parent_pid:  # the parent died before the request above took effect
        os._exit(1)


def _coacd_worker(vertices: np.ndarray, faces: np.ndarray, opts: DecompositionOptions, threshold: float, queue, parent_pid: int) -> None:
    _die_with_parent(parent_pid)
    import coacd

    coacd.set_log_level("error")
    parts = coacd.run_coacd(
        coacd.Mesh(vertices, faces),
        threshold=threshold,
        max_convex_hull=opts.max_convex_hull,
        preprocess_mode="off",
        resolution=opts.resolution,
        mcts_iterations=opts.mcts_iterations,
        mcts_nodes=opts.mcts_nodes,
        mcts_max_depth=opts.mcts_max_depth,
        seed=opts.seed,
    )
    queue.put([np.asarray(v, np.float64) for v, _ in parts])


def decimated(vertices: np.ndarray, faces: np.ndarray, target: int = DECOMPOSE_FACES) -> tuple[np.ndarray, np.ndarray]:
    """The mesh decimated to about `target` faces (fast-simplification), unchanged when smaller."""
    import fast_simplification

    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    if len(f) <= target:
        return v, f
    v32, f2 = fast_simplification.simplify(v.astype(np.float32), f, target_reduction=1.0 - target / len(f))
    return v32.astype(np.float64), f2.astype(np.int64)


def decompose(
    vertices: np.ndarray,
    faces: np.ndarray,
    opts: DecompositionOptions = DecompositionOptions(),
    threshold: float | None = None,
    timeout_s: float | None = None,
) -> list[np.ndarray] | None:
    """Convex pieces [M_i, 3] of the mesh by one CoACD run at `threshold` (default opts.threshold),
    in a child process so the timeout can stop it; None when it ran out of time."""
    v, f = decimated(vertices, faces)
    # Spawn, never fork: a service that reconstructed in-process holds torch/OpenMP threads, and a forked
    # child deadlocks on a mutex one of them held (seen: the export step hung for its whole time budget).
    ctx = mp.get_context("spawn")
    queue = ctx.Queue()
    proc = ctx.Process(
        target=_coacd_worker, args=(v, f, opts, opts.threshold if threshold is None else threshold, queue, os.getpid()), daemon=True
    )
    proc.start()
    try:
        pieces = queue.get(timeout=opts.timeout_s if timeout_s is None else timeout_s)
    except Exception:  # queue.Empty on timeout; the child is stopped below either way
        pieces = None
    finally:
        if proc.is_alive():
            proc.terminate()
        proc.join(5)
    if pieces is None:
        return None
    return [hull_vertices(p) for p in pieces if len(p) >= 4 and convex_volume(p) > 0]


def primitive_candidates(vertices: np.ndarray, kinds: tuple[str, ...] = PRIMITIVES) -> list[Primitive]:
    fit = {"sphere": fit_sphere, "box": fit_box, "cylinder": fit_cylinder, "capsule": fit_capsule}
    return [fit[k](vertices) for k in kinds]


def primitive_solid(p: Primitive, segments: int = 64):
    """manifold3d solid of a primitive in the object frame (round shapes with `segments` sides)."""
    import manifold3d

    M = manifold3d.Manifold
    if p.kind == "box":
        solid = M.cube(tuple(2.0 * float(x) for x in p.size), center=True)
    elif p.kind == "sphere":
        solid = M.sphere(float(p.size[0]), segments)
    elif p.kind == "cylinder":
        solid = M.cylinder(2.0 * float(p.size[1]), float(p.size[0]), circular_segments=segments, center=True)
    else:
        r, h = float(p.size[0]), float(p.size[1])
        solid = M.batch_hull([M.sphere(r, segments).translate((0.0, 0.0, z)) for z in (-h, h)])
    return solid.transform(np.asarray(p.transform, np.float64)[:3, :4])


def union_mesh(primitives: tuple[Primitive, ...], pieces: tuple[np.ndarray, ...]):
    """The union of the collision shapes as one closed trimesh (manifold3d boolean)."""
    import manifold3d
    import trimesh

    solids = [manifold3d.Manifold.hull_points(np.asarray(p, np.float64)) for p in pieces]
    solids += [primitive_solid(prim) for prim in primitives]
    out = manifold3d.Manifold.batch_boolean(solids, manifold3d.OpType.Add).to_mesh64()
    return trimesh.Trimesh(np.asarray(out.vert_properties)[:, :3], np.asarray(out.tri_verts, np.int64), process=False)


def union_volume(primitives: tuple[Primitive, ...], pieces: tuple[np.ndarray, ...]) -> float:
    """Volume (m^3) of the union of the shapes; a lone primitive's exact closed form."""
    if len(primitives) == 1 and not pieces:
        return primitives[0].volume
    if len(pieces) == 1 and not primitives:
        return convex_volume(pieces[0])
    return float(union_mesh(primitives, pieces).volume)


def shape_meshes(primitives: tuple[Primitive, ...], pieces: tuple[np.ndarray, ...]) -> list:
    """Each collision shape as a closed convex trimesh (object frame)."""
    import trimesh

    out = [trimesh.convex.convex_hull(np.asarray(p, np.float64)) for p in pieces]
    for prim in primitives:
        m = primitive_solid(prim).to_mesh64()
        out.append(trimesh.Trimesh(np.asarray(m.vert_properties)[:, :3], np.asarray(m.tri_verts, np.int64), process=False))
    return out


def boundary_points(shapes: list, samples: int, seed: int = 0) -> np.ndarray:
    """Points [S, 3] on the boundary of the union of convex `shapes`: area-uniform samples on each
    shape less those inside or on another shape (where CoACD pieces meet at a cut, their faces are
    inside the solid, not on its surface)."""
    import trimesh
    from scipy.spatial import ConvexHull

    eps = 1e-4 * max(float(np.ptp(np.concatenate([m.vertices for m in shapes]), 0).max()), 1e-12)  # CoACD cuts leave micrometre gaps
    planes = [ConvexHull(np.asarray(m.vertices)).equations for m in shapes]
    total = sum(m.area for m in shapes)
    kept = []
    for i, m in enumerate(shapes):
        pts = np.concatenate(
            [trimesh.sample.sample_surface(m, max(int(samples * m.area / total), 1), seed=seed + i)[0], np.asarray(m.vertices)]
        )
        covered = np.zeros(len(pts), bool)
        for j, eq in enumerate(planes):
            if j != i:
                covered |= (pts @ eq[:, :3].T + eq[:, 3]).max(1) <= eps
        kept.append(pts[~covered])
    return np.concatenate(kept)


def hausdorff(mesh, shapes: list, samples: int = HAUSDORFF_SAMPLES, seed: int = 0) -> float:
    """Symmetric Hausdorff distance (m) between a mesh's surface and the surface of the union of
    convex `shapes`: exact closest-point distances (trimesh.proximity) from `samples` area-uniform
    points and the vertices of each surface to the other. Sampling can only miss the worst point,
    so this reads low by at most the sample spacing, sqrt(area / samples)."""
    import trimesh

    mesh_pts = np.concatenate([trimesh.sample.sample_surface(mesh, samples, seed=seed)[0], np.asarray(mesh.vertices)])
    to_shapes = float(trimesh.proximity.closest_point(trimesh.util.concatenate(shapes), mesh_pts)[1].max())
    to_mesh = float(trimesh.proximity.closest_point(mesh, boundary_points(shapes, samples, seed))[1].max())
    return max(to_shapes, to_mesh)


def _adaptive_decomposition(
    vertices,
    faces,
    mesh_volume: float,
    tolerance: float,
    opts: DecompositionOptions,
    budget: int | None = None,
) -> tuple[tuple[np.ndarray, ...], float, list[str]]:
    """CoACD pieces chosen by volume error within a hull `budget` (None: none): runs at falling
    thresholds until the error is within `tolerance`; a run over the budget makes the next threshold
    the geometric mean of the finest within budget and the coarsest over it (or twice this one); when
    no run lands within budget, CoACD's own cap merges the finest run's pieces down to it.
    Returns (pieces, error, notes) of the best run within budget; no pieces when none finished in time."""
    t_end = time.perf_counter() + opts.timeout_s
    best: tuple[tuple[np.ndarray, ...], float] = ((), np.inf)
    notes, threshold = [], opts.threshold
    over_at, within_at = 0.0, np.inf  # the coarsest threshold over the budget, the finest within it
    for _ in range(max(opts.rounds, 1)):
        left = t_end - time.perf_counter()
        pieces = decompose(vertices, faces, opts, threshold=threshold, timeout_s=left) if left > 0 else None
        if not pieces:
            notes.append(f"CoACD at threshold {threshold:.3g} did not finish within the {opts.timeout_s:.0f} s budget")
            break
        err = union_volume((), tuple(pieces)) / mesh_volume - 1
        over = budget is not None and len(pieces) > budget
        notes.append(
            f"CoACD threshold {threshold:.3g}: {len(pieces)} pieces{' (over the budget)' if over else ''}, {100 * err:+.1f}% volume"
        )
        if over:
            over_at = max(over_at, threshold)
        else:
            within_at = min(within_at, threshold)
            if abs(err) < abs(best[1]):
                best = (tuple(pieces), err)
            if abs(err) <= tolerance or threshold <= opts.min_threshold:
                break
        if over_at > 0 and np.isfinite(within_at):
            if within_at / over_at < 1.15:  # bracketed tightly: finer steps change a piece or two
                break
            threshold = float(np.sqrt(over_at * within_at))
        elif over:
            threshold = min(1.0, 2.0 * threshold)
        else:
            threshold = max(opts.min_threshold, threshold * float(np.clip(0.8 * tolerance / abs(err), 0.25, 0.8)))
    if budget is not None and not best[0] and over_at > 0 and t_end > time.perf_counter():
        cap = budget if opts.max_convex_hull < 1 else min(budget, opts.max_convex_hull)
        pieces = decompose(vertices, faces, replace(opts, max_convex_hull=cap), threshold=over_at, timeout_s=t_end - time.perf_counter())
        if pieces:
            err = union_volume((), tuple(pieces)) / mesh_volume - 1
            best = (tuple(pieces), err)
            notes.append(f"CoACD threshold {over_at:.3g} merged to the budget: {len(pieces)} pieces, {100 * err:+.1f}% volume")
    return best[0], best[1], notes


def _part_geometry(
    vertices,
    faces,
    volume: float,
    tolerance: float,
    primitives: tuple[str, ...],
    decomposition: DecompositionOptions | None,
    budget: int | None = None,
):
    """(primitives, pieces, error, notes) for one closed part, at most `budget` pieces."""
    err = lambda vol: (vol - volume) / volume  # noqa: E731
    hull = hull_vertices(vertices)
    hull_err = err(convex_volume(hull))
    best = min(primitive_candidates(hull, primitives), key=lambda p: p.volume, default=None)
    if best is not None and err(best.volume) <= tolerance:
        return (best,), (), err(best.volume), [f"{best.kind} within {100 * err(best.volume):.1f}% of the volume"]
    if hull_err <= tolerance or decomposition is None:
        why = "within" if hull_err <= tolerance else "(decomposition disabled)"
        return (), (hull,), hull_err, [f"convex hull {why} {100 * hull_err:.1f}% of the volume"]
    pieces, dec_err, notes = _adaptive_decomposition(vertices, faces, volume, tolerance, decomposition, budget)
    if not pieces or abs(dec_err) >= abs(hull_err):
        why = "no CoACD run finished" if not pieces else f"CoACD's best ({100 * dec_err:+.1f}%) was no closer"
        return (), (hull,), hull_err, notes + [f"{why}; convex hull used ({100 * hull_err:.1f}% volume error)"]
    return (
        (),
        pieces,
        dec_err,
        notes + [f"CoACD: {len(pieces)} convex pieces, {100 * dec_err:+.1f}% volume error (hull {100 * hull_err:+.1f}%)"],
    )


def _closed_parts(vertices: np.ndarray, faces: np.ndarray, face_part: np.ndarray) -> list[tuple[np.ndarray, np.ndarray, float]] | None:
    """Each part as its own closed mesh (vertices, faces, volume), or None when a part is not
    closed on its own (parts that share edges are one solid to the simulator)."""
    import trimesh

    out = []
    for p in np.unique(face_part):
        sub = trimesh.Trimesh(vertices, faces[face_part == p], process=False)
        sub.remove_unreferenced_vertices()
        if not (sub.is_volume and sub.volume > 0):
            return None
        out.append((np.asarray(sub.vertices), np.asarray(sub.faces, np.int64), float(sub.volume)))
    return out


def collision_geometry(
    vertices: np.ndarray,
    faces: np.ndarray,
    mesh_volume: float,
    *,
    face_part: np.ndarray | None = None,
    tolerance: float = DEFAULT_TOLERANCE,
    primitives: tuple[str, ...] = PRIMITIVES,
    decomposition: DecompositionOptions | None = DecompositionOptions(),
    measure_hausdorff: bool = True,
) -> CollisionGeometry:
    """The cheapest geometry within `tolerance` volume error, per CAD part when `face_part` [F]
    labels parts that are closed solids on their own (else for the whole mesh): the best-fitting
    primitive, else the convex hull, else a CoACD decomposition (`decomposition=None` stops at the hull).

    vertices [V, 3], faces [F, 3] in metres (a closed mesh); mesh_volume the solid's volume (m^3).
    """
    import trimesh

    t0 = time.perf_counter()
    if not mesh_volume > 0:
        raise ValueError("the mesh volume must be positive to size its collision geometry")
    v, f = np.asarray(vertices, np.float64), np.asarray(faces, np.int64)
    parts = _closed_parts(v, f, np.asarray(face_part)) if face_part is not None and len(np.unique(face_part)) > 1 else None
    if parts is None:
        parts = [(v, f, float(mesh_volume))]
    budget = None if decomposition is None else decomposition.hull_budget
    shares = hull_shares(budget, [pvol for _, _, pvol in parts])
    prims, pieces, notes = [], [], []
    for (pv, pf, pvol), share in zip(parts, shares):
        pr, pc, _, n = _part_geometry(pv, pf, pvol, tolerance, primitives, decomposition, share)
        prims += pr
        pieces += pc
        notes += n
    prims, pieces = tuple(prims), tuple(pieces)
    volume = union_volume(prims, pieces)
    if len(parts) > 1:
        kind = "parts"
        notes.insert(0, f"{len(parts)} parts, each sized on its own")
    else:
        kind = prims[0].kind if prims else ("hull" if len(pieces) == 1 else "decomposition")
    dist = float("nan")
    if measure_hausdorff:
        dist = hausdorff(trimesh.Trimesh(v, f, process=False), shape_meshes(prims, pieces))
    if budget is not None and len(pieces) + len(prims) > budget:
        notes.append(f"{len(pieces) + len(prims)} shapes for {len(parts)} parts: over the hull budget of {budget}, one per part at least")
    return CollisionGeometry(kind, volume, volume / mesh_volume - 1, time.perf_counter() - t0, prims, pieces, tuple(notes), dist, budget)


def hull_shares(budget: int | None, volumes: list[float]) -> list[int | None]:
    """Each part's share of a hull `budget` (None: no budget): one each, the rest by volume; they sum
    to at most the budget whenever it is at least the number of parts."""
    if budget is None:
        return [None] * len(volumes)
    spare = max(budget - len(volumes), 0)
    total = float(sum(volumes)) or 1.0
    return [1 + int(spare * v / total) for v in volumes]


def surface_points(geometry: CollisionGeometry, sections: int = 32) -> np.ndarray:
    """Points [S, 3] on the collision geometry's surface (object frame): the pieces' vertices and the
    primitives' tessellations; what touches the floor when the body rests."""
    pts = [np.asarray(p) for p in geometry.pieces]
    pts += [np.asarray(primitive_solid(p, sections).to_mesh64().vert_properties)[:, :3] for p in geometry.primitives]
    return np.concatenate(pts)
