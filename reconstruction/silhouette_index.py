"""The library's silhouette index: every model seen from a grid of directions, normalised, bit-packed.

Grid: `n_dirs` directions on a Fibonacci sphere (near-uniform, any count). In-plane roll is not
sampled: every silhouette is rotated to its principal axis before the bbox crop (see
`silhouette.normalize_silhouette`), so the roll between a library view and an observed mask comes
out in closed form (angle difference, with the 180-degree flip tried at query time). This keeps
the index small enough to scan thousands of models in well under a second.

Camera: a perspective camera with a 45-degree field of view at the distance where the model's
bounding sphere spans half the image (5.1 radii), the typical framing of a rig camera; a
perspective silhouette at that distance differs from a rig view at 3-8 radii by a few percent
IoU, where an orthographic one would differ more at the near end.

Storage (per model, so adding a model never rebuilds the others): `<key>.npz` with the packed
canvases [D, W] uint64 and per-view geometry [D, 6] float32 (canonical angle, canonical extent,
bbox centre x, y, anisotropy, area; image quantities in normalised units = pixels / focal). The
query-time index concatenates the shards into flat files that are memory-mapped.
"""

from __future__ import annotations

import json
import os
from dataclasses import asdict, dataclass
from pathlib import Path

import numba
import numpy as np
from llvmlite import ir
from numba import types
from numba.extending import intrinsic

from calibration.camera import look_at_c2w
from calibration.fileio import atomic_write_bytes, atomic_write_json
from reconstruction.silhouette import normalize_silhouette, pack, render_silhouette

# Columns of the per-view geometry array.
ANGLE, EXTENT, BX, BY, ANISO, AREA = range(6)


@dataclass(frozen=True)
class GridSpec:
    """How library silhouettes are made; part of every shard's key, so changing it rebuilds."""

    n_dirs: int = 600
    canvas: int = 32
    render_px: int = 192
    fov_deg: float = 45.0
    fill: float = 0.5  # fraction of the image width the bounding sphere spans

    @property
    def words(self) -> int:
        return -(-self.canvas * self.canvas // 64)

    @property
    def focal_px(self) -> float:
        return 0.5 * self.render_px / np.tan(np.radians(0.5 * self.fov_deg))

    def distance(self, radius: float) -> float:
        """Camera distance at which a sphere of `radius` spans `fill` of the field of view."""
        return float(radius / np.sin(np.radians(0.5 * self.fill * self.fov_deg)))

    def to_dict(self) -> dict:
        return asdict(self)


def fibonacci_directions(n: int) -> np.ndarray:
    """`n` near-uniform unit vectors [n, 3] on the sphere (golden-angle spiral)."""
    i = np.arange(n) + 0.5
    z = 1.0 - 2.0 * i / n
    r = np.sqrt(np.clip(1.0 - z * z, 0.0, 1.0))
    phi = np.pi * (3.0 - np.sqrt(5.0)) * i
    return np.stack([r * np.cos(phi), r * np.sin(phi), z], 1)


def view_rotations(directions: np.ndarray) -> np.ndarray:
    """Camera-to-object rotations [D, 3, 3] (OpenCV axes) of cameras placed along `directions` [D, 3], looking at the origin."""
    return np.stack([look_at_c2w(d, np.zeros(3))[:3, :3] for d in directions])


def model_frame(vertices: np.ndarray) -> tuple[np.ndarray, float]:
    """The point library cameras look at (bounding-box centre) [3] and the bounding radius about it."""
    center = 0.5 * (vertices.min(0) + vertices.max(0))
    radius = float(np.linalg.norm(vertices - center, axis=1).max())
    return center, radius


def render_model_views(vertices: np.ndarray, faces: np.ndarray, grid: GridSpec) -> tuple[np.ndarray, np.ndarray]:
    """Packed canonical silhouettes [D, W] uint64 and view geometry [D, 6] float32 of one model (metres, model frame)."""
    center, radius = model_frame(vertices)
    dist = grid.distance(radius)
    f = grid.focal_px
    c = grid.render_px / 2.0
    K = np.array([[f, 0, c], [0, f, c], [0, 0, 1.0]])
    rots = view_rotations(fibonacci_directions(grid.n_dirs))
    canvases = np.zeros((grid.n_dirs, grid.canvas, grid.canvas), dtype=bool)
    geom = np.zeros((grid.n_dirs, 6), dtype=np.float32)
    for i, rot in enumerate(rots):
        c2w = np.eye(4)
        c2w[:3, :3] = rot
        c2w[:3, 3] = center - dist * rot[:, 2]
        viewmat = np.linalg.inv(c2w)
        sil = render_silhouette(vertices, faces, K, viewmat, grid.render_px, grid.render_px)
        if not sil.any():
            continue
        nz = normalize_silhouette(sil, grid.canvas)
        canvases[i] = nz.canvas
        b = nz.bbox_center
        geom[i] = (nz.angle, nz.extent / f, (b[0] - c) / f, (b[1] - c) / f, nz.anisotropy, sil.sum() / f**2)
    return pack(canvases), geom


# --- popcount IoU over packed canvases -------------------------------------------------------


@intrinsic
def _popcount64(typingctx, x):
    sig = types.uint64(types.uint64)

    def codegen(context, builder, signature, args):
        fn = builder.module.declare_intrinsic("llvm.ctpop", [ir.IntType(64)])
        return builder.call(fn, args)

    return sig, codegen


@numba.njit(cache=True)
def _popcount_rows(words: np.ndarray) -> np.ndarray:
    out = np.empty(words.shape[0], dtype=np.int32)
    for i in range(words.shape[0]):
        acc = 0
        for w in range(words.shape[1]):
            acc += _popcount64(words[i, w])
        out[i] = acc
    return out


@numba.njit(cache=True, parallel=True)
def _best_iou(lib: np.ndarray, lib_count: np.ndarray, queries: np.ndarray, q_count: np.ndarray):
    m_rows, n_words = lib.shape
    best = np.zeros(m_rows, dtype=np.float32)
    which = np.zeros(m_rows, dtype=np.int16)
    for m in numba.prange(m_rows):
        cl = lib_count[m]
        for q in range(queries.shape[0]):
            inter = 0
            for w in range(n_words):
                inter += _popcount64(lib[m, w] & queries[q, w])
            union = cl + q_count[q] - inter
            if union > 0:
                v = np.float32(inter) / np.float32(union)
                if v > best[m]:
                    best[m] = v
                    which[m] = q
    return best, which


def popcount_rows(words: np.ndarray) -> np.ndarray:
    """Set bits per row of packed words [M, W] -> [M] int32."""
    return _popcount_rows(np.ascontiguousarray(words, dtype=np.uint64))


def best_iou(lib: np.ndarray, lib_count: np.ndarray, queries: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Packed library rows `lib` [M, W] against packed variants of one observed mask `queries` [Q, W]:
    the best IoU per row [M] float32 and the variant achieving it [M] int16."""
    queries = np.ascontiguousarray(queries, dtype=np.uint64)
    return _best_iou(lib, lib_count, queries, popcount_rows(queries))


def count_window(counts_sorted: np.ndarray, q_counts: np.ndarray, min_iou: float) -> tuple[int, int]:
    """Row range [lo, hi) of a count-sorted library that can reach `min_iou` with any query.

    IoU(A, B) <= min(|A|, |B|) / max(|A|, |B|), so rows outside [min_iou |Q|, |Q| / min_iou] cannot
    pass: an exact prune, not a heuristic.
    """
    t = max(float(min_iou), 1e-6)
    lo = int(np.searchsorted(counts_sorted, np.floor(q_counts.min() * t), side="left"))
    hi = int(np.searchsorted(counts_sorted, np.ceil(q_counts.max() / t), side="right"))
    return lo, hi


# --- on-disk index ---------------------------------------------------------------------------


def shard_key(mesh_sha256: str, unit_scale: float, grid: GridSpec) -> str:
    """Content key of a model's shard: same mesh bytes, unit and grid -> same silhouettes."""
    import hashlib

    blob = json.dumps({"mesh": mesh_sha256, "scale": unit_scale, "grid": grid.to_dict()}, sort_keys=True)
    return hashlib.sha256(blob.encode()).hexdigest()[:24]


def write_shard(path: Path, words: np.ndarray, geom: np.ndarray, center: np.ndarray, radius: float, **extra: np.ndarray) -> str:
    """Write one model's shard (plus `extra` arrays) atomically; returns its sha256."""
    import io

    buf = io.BytesIO()
    np.savez(buf, words=words, geom=geom, center=center, radius=np.array(radius), **extra)
    return atomic_write_bytes(path, buf.getvalue())


def read_shard(path: Path) -> dict:
    with np.load(path) as z:
        return {k: z[k] for k in z.files}


@dataclass(frozen=True)
class Matches:
    """Top library views for one observed mask: rows into the index [k], IoU [k], query variant [k]."""

    rows: np.ndarray
    iou: np.ndarray
    variant: np.ndarray
    best_iou: float


@dataclass
class SilhouetteIndex:
    """All models' silhouettes as flat memory-mapped arrays, rows sorted by set-bit count.

    words [M, W] uint64 (M = models x directions), counts [M] int32 (ascending), geom [M, 6]
    float32, model_row [M] int32 (into `model_ids`), dir_idx [M] int32 (grid direction),
    centers [n_models, 3] and radii [n_models] (the frame each model's views were rendered in).
    """

    grid: GridSpec
    model_ids: list[str]
    words: np.ndarray
    counts: np.ndarray
    geom: np.ndarray
    model_row: np.ndarray
    dir_idx: np.ndarray
    centers: np.ndarray
    radii: np.ndarray

    def __post_init__(self) -> None:
        self.rotations = view_rotations(fibonacci_directions(self.grid.n_dirs))

    def __len__(self) -> int:
        return int(self.words.shape[0])

    def _scan(self, variants: np.ndarray, lo: int, hi: int, model_mask: np.ndarray | None) -> tuple[np.ndarray, np.ndarray]:
        if hi <= lo:
            return np.zeros(0, np.float32), np.zeros(0, np.int16)
        best, which = best_iou(self.words[lo:hi], self.counts[lo:hi], variants)
        if model_mask is not None:
            best = np.where(model_mask[self.model_row[lo:hi]], best, np.float32(0.0))
        return best, which

    def query(self, variants: np.ndarray, *, top_k: int = 50, min_iou: float = 0.7, model_mask: np.ndarray | None = None) -> Matches:
        """Top-`top_k` rows with IoU >= `min_iou` against any of one mask's packed variants [Q, W].

        `model_mask` [n_models] bool restricts the search to some models. `best_iou` is the best
        IoU seen in the count window even when nothing passes (for the error message).
        """
        q_counts = popcount_rows(variants)
        lo, hi = count_window(self.counts, q_counts, min_iou)
        best, which = self._scan(variants, lo, hi, model_mask)
        top_seen = float(best.max()) if len(best) else 0.0
        if top_seen < min_iou:
            # Nothing passes: scan a wider window once so the caller can say how close it came.
            lo, hi = count_window(self.counts, q_counts, min(min_iou, 0.3))
            best, which = self._scan(variants, lo, hi, model_mask)
            top_seen = float(best.max()) if len(best) else 0.0
        ok = np.flatnonzero(best >= min_iou)
        if len(ok) > top_k:
            ok = ok[np.argpartition(-best[ok], top_k - 1)[:top_k]]
        ok = ok[np.argsort(-best[ok], kind="stable")]
        return Matches(ok + lo, best[ok], which[ok], top_seen)


FLAT_FILES = ("words", "counts", "geom", "model_row", "dir_idx")


def consolidate(index_dir: Path, grid: GridSpec, shards: list[tuple[str, Path]]) -> dict:
    """Concatenate per-model shards (id, path) into the count-sorted flat files `open_index` maps; returns their sha256s."""
    parts = [read_shard(p) for _, p in shards]
    d = grid.n_dirs
    words = np.concatenate([p["words"] for p in parts]) if parts else np.zeros((0, grid.words), np.uint64)
    counts = popcount_rows(words) if len(words) else np.zeros(0, np.int32)
    order = np.argsort(counts, kind="stable")
    arrays = {
        "words": words[order],
        "counts": counts[order],
        "geom": (np.concatenate([p["geom"] for p in parts]) if parts else np.zeros((0, 6), np.float32))[order],
        "model_row": np.repeat(np.arange(len(parts), dtype=np.int32), d)[order],
        "dir_idx": np.tile(np.arange(d, dtype=np.int32), len(parts))[order],
        "centers": np.array([p["center"] for p in parts]).reshape(-1, 3),
        "radii": np.array([float(p["radius"]) for p in parts]),
    }
    digests = {}
    for name, arr in arrays.items():
        digests[f"index/{name}.npy"] = _atomic_save_npy(index_dir / f"{name}.npy", arr)
    digests["index/ids.json"] = atomic_write_json(index_dir / "ids.json", {"grid": grid.to_dict(), "model_ids": [m for m, _ in shards]})
    return digests


def _atomic_save_npy(path: Path, arr: np.ndarray) -> str:
    import io

    buf = io.BytesIO()
    np.save(buf, np.ascontiguousarray(arr))
    return atomic_write_bytes(path, buf.getvalue())


def open_index(index_dir: str | os.PathLike) -> SilhouetteIndex:
    """Memory-map a consolidated index directory."""
    index_dir = Path(index_dir)
    meta = json.loads((index_dir / "ids.json").read_text())
    maps = {name: np.load(index_dir / f"{name}.npy", mmap_mode="r") for name in FLAT_FILES}
    return SilhouetteIndex(
        grid=GridSpec(**meta["grid"]),
        model_ids=list(meta["model_ids"]),
        centers=np.load(index_dir / "centers.npy"),
        radii=np.load(index_dir / "radii.npy"),
        **maps,
    )
