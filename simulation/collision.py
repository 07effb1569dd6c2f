"""Collision geometry sized to need: a fitted primitive or one convex hull when either is within
a volume tolerance of the mesh, else a convex decomposition (CoACD).

Primitives (box, cylinder, capsule, sphere) and the hull all enclose the mesh, so their volume
error (V_geom - V_mesh) / V_mesh equals 1 - IoU with the true solid: a 5 % error is a body that
rests at most a few per cent of its size away from where the real object would. CoACD pieces
approximate from both sides; their error is the summed piece volume against the mesh's.
"""

from __future__ import annotations

import multiprocessing as mp
import time
from dataclasses import dataclass, field

import numpy as np

# Primitives are cheapest and most stable in contact; the hull next; decomposition last.
PRIMITIVES = ("sphere", "box", "cylinder", "capsule")
DECOMPOSE_FACES = 2000  # CoACD's cost grows with the input; its pieces do not need the full mesh


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
    """What the simulator collides with. `kind` is a primitive kind, "hull" or "decomposition";
    `pieces` are convex vertex sets [M_i, 3] (object frame) for mesh kinds; `volume_error` is
    (V_collision - V_mesh) / V_mesh; `seconds` the time to make it; `notes` why it was chosen."""

    kind: str
    volume: float
    volume_error: float
    seconds: float
    primitive: Primitive | None = None
    pieces: tuple[np.ndarray, ...] = ()
    notes: tuple[str, ...] = field(default_factory=tuple)

    @property
    def hull_count(self) -> int:
        return len(self.pieces)


@dataclass(frozen=True)
class DecompositionOptions:
    """CoACD settings: `threshold` concavity (lower = more, tighter pieces), at most `max_convex_hull`
    pieces, and `timeout_s` wall-clock cap per mesh (on timeout the convex hull is used and noted)."""

    threshold: float = 0.08
    max_convex_hull: int = 12
    timeout_s: float = 60.0
    resolution: int = 1000
    mcts_iterations: int = 60
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


def _coacd_worker(vertices: np.ndarray, faces: np.ndarray, opts: DecompositionOptions, queue) -> None:
    import coacd

    coacd.set_log_level("error")
    parts = coacd.run_coacd(
        coacd.Mesh(vertices, faces), threshold=opts.threshold, max_convex_hull=opts.max_convex_hull,
        preprocess_mode="off", resolution=opts.resolution, mcts_iterations=opts.mcts_iterations,
        mcts_nodes=opts.mcts_nodes, mcts_max_depth=opts.mcts_max_depth, seed=opts.seed,
    )
    queue.put([np.asarray(v, np.float64) for v, _ in parts])


def decompose(vertices: np.ndarray, faces: np.ndarray, opts: DecompositionOptions = DecompositionOptions()) -> list[np.ndarray] | None:
    """Convex pieces [M_i, 3] of the mesh by CoACD, run in a child process so `opts.timeout_s` can
    stop it; None when it ran out of time. The input is decimated to DECOMPOSE_FACES first."""
    import fast_simplification

    v = np.asarray(vertices, np.float64)
    f = np.asarray(faces, np.int64)
    if len(f) > DECOMPOSE_FACES:
        v32, f = fast_simplification.simplify(v.astype(np.float32), f, target_reduction=1.0 - DECOMPOSE_FACES / len(f))
        v, f = v32.astype(np.float64), f.astype(np.int64)
    ctx = mp.get_context("spawn" if "fork" not in mp.get_all_start_methods() else "fork")
    queue = ctx.Queue()
    proc = ctx.Process(target=_coacd_worker, args=(v, f, opts, queue), daemon=True)
    proc.start()
    try:
        pieces = queue.get(timeout=opts.timeout_s)
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


def collision_geometry(
    vertices: np.ndarray,
    faces: np.ndarray,
    mesh_volume: float,
    *,
    tolerance: float = 0.05,
    primitives: tuple[str, ...] = PRIMITIVES,
    decomposition: DecompositionOptions | None = DecompositionOptions(),
) -> CollisionGeometry:
    """The cheapest geometry within `tolerance` volume error: the best-fitting primitive, else the
    convex hull, else a CoACD decomposition (`decomposition=None` stops at the hull).

    vertices [V, 3], faces [F, 3] in metres; mesh_volume the solid's volume (m^3).
    """
    t0 = time.perf_counter()
    if not mesh_volume > 0:
        raise ValueError("the mesh volume must be positive to size its collision geometry")
    err = lambda vol: (vol - mesh_volume) / mesh_volume  # noqa: E731
    hull = hull_vertices(vertices)
    hull_vol = convex_volume(hull)
    best = min(primitive_candidates(hull, primitives), key=lambda p: p.volume, default=None)
    if best is not None and err(best.volume) <= tolerance:
        return CollisionGeometry(
            best.kind, best.volume, err(best.volume), time.perf_counter() - t0, primitive=best,
            notes=(f"{best.kind} within {100 * err(best.volume):.1f}% of the mesh volume",),
        )
    if err(hull_vol) <= tolerance or decomposition is None:
        why = "within" if err(hull_vol) <= tolerance else "decomposition disabled;"
        return CollisionGeometry(
            "hull", hull_vol, err(hull_vol), time.perf_counter() - t0, pieces=(hull,),
            notes=(f"convex hull {why} {100 * err(hull_vol):.1f}% of the mesh volume",),
        )
    pieces = decompose(vertices, faces, decomposition)
    if not pieces:
        return CollisionGeometry(
            "hull", hull_vol, err(hull_vol), time.perf_counter() - t0, pieces=(hull,),
            notes=(f"CoACD gave no pieces within {decomposition.timeout_s:.0f} s; convex hull used ({100 * err(hull_vol):.1f}% volume error)",),
        )
    vol = sum(convex_volume(p) for p in pieces)
    if abs(err(vol)) >= abs(err(hull_vol)):
        return CollisionGeometry(
            "hull", hull_vol, err(hull_vol), time.perf_counter() - t0, pieces=(hull,),
            notes=(f"CoACD's {len(pieces)} pieces ({100 * err(vol):.1f}%) were no closer than the convex hull ({100 * err(hull_vol):.1f}%)",),
        )
    return CollisionGeometry(
        "decomposition", vol, err(vol), time.perf_counter() - t0, pieces=tuple(pieces),
        notes=(f"CoACD: {len(pieces)} convex pieces, {100 * err(vol):.1f}% volume error (hull {100 * err(hull_vol):.1f}%)",),
    )


def surface_points(geometry: CollisionGeometry, sections: int = 32) -> np.ndarray:
    """Points [S, 3] on the collision geometry's surface (object frame): the pieces' vertices, or a
    primitive's tessellation; what touches the floor when the body rests."""
    import trimesh

    p = geometry.primitive
    if p is None:
        return np.concatenate(geometry.pieces)
    if p.kind == "box":
        mesh = trimesh.creation.box(extents=2 * np.asarray(p.size))
    elif p.kind == "sphere":
        mesh = trimesh.creation.icosphere(subdivisions=3, radius=p.size[0])
    elif p.kind == "cylinder":
        mesh = trimesh.creation.cylinder(radius=p.size[0], height=2 * p.size[1], sections=sections)
    else:
        mesh = trimesh.creation.capsule(radius=p.size[0], height=2 * p.size[1], count=[sections, sections])
    return trimesh.transform_points(mesh.vertices, p.transform)
